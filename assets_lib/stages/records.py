"""Stage ``calibration_record``: per device, one audited, hash-chained JSON record and one HTML certificate per
captured run (``assets_lib.records``), plus ``records.parquet`` (run_id, start_time_utc, record_sha256,
prev_record_sha256, ...).

Records whose certified content is unchanged are reused verbatim from the device's current version (creation
time, orchestrator run id and bytes kept), so a rerun changes nothing and a new run appends one link
(assets_lib/records/__init__.py explains the hashing).
"""

from __future__ import annotations

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
from assets_lib.stages.spec import StageOutput, stage
from assets_lib.store.keys import capture_key, split_capture_key

RESERVED = {"meta", "records"}  # file stems the version folder already uses


@stage("calibration_record", level="device", group="records", code_version="1",
       upstream=("ingested_run", "gyro_rate_fit", "accel_multiposition_fit", "tablefree_fit", "allan_deviation"),
       kinds=("json", "html", "parquet"))
def calibration_record(device: str, inputs) -> StageOutput | None:
    """Audited calibration record (JSON, hash-chained per device) and HTML certificate for every run of a device."""
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
    files = {}
    records = [r for r, _ in built]
    for rec, _ in built:
        rid = rec["content"]["run"]["run_id"]
        ck = capture_key(device, rid)
        plots = {name: png for a in PLOT_SOURCES for name, png in view.pngs(a, ck).items()}
        files[f"{rid}.json"] = record_file_bytes(rec)
        # the navigation budget of the device calibration at the record's start (assets_lib.navigation.budget)
        files[f"{rid}.html"] = certificate_html(rec, plots, certificate_calibration(records, rid)).encode("utf-8")
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


