"""Stages ``calibration_record`` and ``certificate``.

``calibration_record``: per device, one audited, hash-chained JSON record per captured run (``assets_lib.records``),
plus ``records.parquet`` (run_id, start_time_utc, record_sha256, prev_record_sha256, ...). Records whose certified
content is unchanged are reused verbatim from the device's current version (creation time, orchestrator run id and
bytes kept), so a rerun changes nothing and a new run appends one link (assets_lib/records/__init__.py explains the
hashing).

``certificate``: the human-readable HTML certificate of every record of the device's current record version, with
the residual and Allan plots of its run (drawn from the stored outputs, ``assets_lib.stages.figures``) and the
navigation budget of the device calibration at the record's start (``assets_lib.navigation.budget``). Rendering
cost more CPU than the calibration itself (issue 10 item 8), so it is a stage of its own that ``imulab run``
leaves out unless asked (``imulab certificates``, ``imulab run --certificates``); the Dagster daemon's sensors
materialize it like any other asset. A certificate embeds its record, so ``imulab verify CERT.html`` checks it
against the chain and the raw archive wherever it lies.
"""

from __future__ import annotations

import pandas as pd

from assets_lib.navigation.budget import certificate_calibration
from assets_lib.records import (
    PLOT_SOURCES,
    build_device_records,
    certificate_html,
    load_records_dir,
    record_file_bytes,
    records_table,
    software_info,
    utc_now_iso,
)
from assets_lib.stages.figures import figures
from assets_lib.stages.spec import StageOutput, stage
from assets_lib.store.keys import capture_key, split_capture_key

RESERVED = {"meta", "records", "certificates"}  # file stems the version folders already use
CERTIFICATE_COLUMNS = ["run_id", "record_sha256", "file", "status", "n_plots", "navigation_budget"]


@stage("calibration_record", level="device", group="records", code_version="1",
       upstream=("ingested_run", "gyro_rate_fit", "accel_multiposition_fit", "tablefree_fit", "allan_deviation"),
       kinds=("json", "parquet"))
def calibration_record(device: str, inputs) -> StageOutput | None:
    """Audited calibration record (JSON, hash-chained per device) for every run of a device."""
    keys = inputs.keys_of("ingested_run")
    if not keys:
        return None
    bad = [k for k in keys if split_capture_key(k)[1] in RESERVED]
    if bad:
        raise ValueError(f"run ids {bad} collide with the record folder's own files ({sorted(RESERVED)})")
    view = inputs.copy()
    previous = {}
    current = inputs.store.current_version("calibration_record", device)
    if current is not None:
        previous, _ = load_records_dir(inputs.store.version_dir("calibration_record", device, current))
    software = software_info()
    built = build_device_records(view, keys, previous, software, utc_now_iso(), inputs.run_id)
    records = [r for r, _ in built]
    files = {f"{rec['content']['run']['run_id']}.json": record_file_bytes(rec) for rec in records}
    return StageOutput(
        tables={"records": records_table(records)},
        meta={
            "chain_head_sha256": records[-1]["record_sha256"],
            "n_records": len(records),
            "reused_runs": [r["content"]["run"]["run_id"] for r, reused in built if reused],
            "software": software,
        },
        files=files,
        summary={"n_records": len(records), "n_reused": sum(reused for _, reused in built),
                 "chain_head": records[-1]["record_sha256"][:16]},
    )


@stage("certificate", level="device", group="certificates", code_version="1",
       upstream=("calibration_record", "ingested_run", *PLOT_SOURCES), kinds=("html", "parquet"))
def certificate(device: str, inputs) -> StageOutput | None:
    """HTML calibration certificate of every record of the device: values rounded to their uncertainty, residual and
    Allan plots, navigation budget, the record embedded for ``imulab verify CERT.html``."""
    if not inputs.has("calibration_record", device):
        return None
    by_run, listing = load_records_dir(inputs.version_dir("calibration_record", device))
    records = [by_run[rid] for rid in listing["run_id"]]  # chain order, as the record stage wrote them
    files, rows = {}, []
    for rec in records:
        rid = rec["content"]["run"]["run_id"]
        ck = capture_key(device, rid)
        plots = {f"{a}: {name}": png for a in PLOT_SOURCES for name, png in figures(a, ck, inputs).items()}
        # the navigation budget of the device calibration at the record's start (assets_lib.navigation.budget)
        cal = certificate_calibration(records, rid)
        files[f"{rid}.html"] = certificate_html(rec, plots, cal).encode("utf-8")
        rows.append({"run_id": rid, "record_sha256": rec["record_sha256"], "file": f"{rid}.html",
                     "status": rec["content"].get("status"), "n_plots": len(plots),
                     "navigation_budget": cal is not None})
    return StageOutput(
        tables={"certificates": pd.DataFrame(rows, columns=CERTIFICATE_COLUMNS)},
        meta={"record_version": inputs.versions[f"calibration_record/{device}"], "n_certificates": len(rows)},
        files=files,
        summary={"n_certificates": len(rows)},
    )
