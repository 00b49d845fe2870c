"""Stage ``calibration_record``: per device, one audited, hash-chained JSON record and one HTML certificate per
captured run (``assets_lib.records``), plus ``records.parquet`` (run_id, start_time_utc, record_sha256,
prev_record_sha256, ...). A blocking check verifies the chain after every materialization.

Records whose certified content is unchanged are reused verbatim from the device's current version (creation
time, Dagster run id and bytes kept), so a rerun changes nothing and a new run appends one link
(assets_lib/records/content.py explains the hashing).
"""


import importlib
import importlib.util

import dagster as dg

from assets_lib.records import (
    PLOT_SOURCES,
    StoreView,
    build_device_records,
    certificate_html,
    chain_problems,
    load_records_dir,
    record_file_bytes,
    records_table,
    software_info,
    utc_now_iso,
)
from pipelines.partitions import capture_key, devices, split_capture_key
from pipelines.resources import ParquetStore
from pipelines.stage import STAGES, StageInputs, StageOutput, stage

for _m in ("ingest", "calibration", "noise"):  # register upstream stages first when imported on its own
    if importlib.util.find_spec(f"pipelines.defs.{_m}") is not None:
        importlib.import_module(f"pipelines.defs.{_m}")

UPSTREAM = tuple(a for a in ("ingested_run", "gyro_rate_fit", "accel_multiposition_fit", "allan_deviation")
                 if a in STAGES)
RESERVED = {"meta", "records"}  # file stems the version folder already uses


@stage("calibration_record", level="device", group="records", code_version="1", upstream=UPSTREAM,
       kinds=("json", "html", "parquet"))
def calibration_record(device: str, inputs: StageInputs) -> StageOutput | None:
    """Audited calibration record (JSON, hash-chained per device) and HTML certificate for every run of a device."""
    keys = inputs.keys_of("ingested_run")
    if not keys:
        return None
    bad = [k for k in keys if split_capture_key(k)[1] in RESERVED]
    if bad:
        raise ValueError(f"run ids {bad} collide with the record folder's own files ({sorted(RESERVED)})")
    view = StoreView(inputs.store, dict(inputs.versions))
    previous = {}
    current = inputs.store.current_version("calibration_record", device)
    if current is not None:
        previous, _ = load_records_dir(inputs.store.version_dir("calibration_record", device, current))
    software = software_info()
    built = build_device_records(view, keys, previous, software, utc_now_iso(), getattr(inputs, "run_id", None))
    files = {}
    for rec, _ in built:
        rid = rec["content"]["run"]["run_id"]
        ck = capture_key(device, rid)
        plots = {name: png for a in PLOT_SOURCES for name, png in view.pngs(a, ck).items()}
        files[f"{rid}.json"] = record_file_bytes(rec)
        files[f"{rid}.html"] = certificate_html(rec, plots).encode("utf-8")
    records = [r for r, _ in built]
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


@dg.asset_check(asset=calibration_record, name="record_chain_intact", blocking=True, partitions_def=devices,
                description="Every record's hash matches its content, every link matches the previous record, and "
                            "every ingested run the version was built from has its record.")
def record_chain_intact(context: dg.AssetCheckExecutionContext, store: ParquetStore) -> dg.AssetCheckResult:
    st = store.store
    keys = context.partition_keys if context.has_partition_key_range or context.has_partition_key \
        else st.partitions("calibration_record")
    problems, checked = [], 0
    for dev in keys:
        version = st.current_version("calibration_record", dev)
        if version is None:
            continue
        vdir = st.version_dir("calibration_record", dev, version)
        recs, listing = load_records_dir(vdir)
        meta = st.read_meta("calibration_record", dev, version)
        expected = []
        for k, v in (meta.get("inputs") or {}).items():
            asset, _, part = k.partition("/")
            if asset == "ingested_run":
                m = st.read_meta("ingested_run", part, v)
                expected.append((m["run_id"], m["start_time_utc"]))
        problems += [f"{dev}: {p}" for p in chain_problems(recs, listing, expected)]
        checked += len(recs)
    return dg.AssetCheckResult(
        passed=not problems,
        severity=dg.AssetCheckSeverity.ERROR,
        metadata={"records_checked": checked, "problems": "\n".join(problems) or "none"},
        description="; ".join(problems)[:2000] or None,
    )


ASSETS = [calibration_record]
CHECKS = [record_chain_intact]
