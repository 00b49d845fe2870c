"""Stage ``ingested_run``: validate each captured run against the raw-log contract, store canonical SI parquet."""

from __future__ import annotations

import json

from assets_lib.stages.spec import StageOutput, stage
from raw_schemas.readers import ingest_run


@stage("ingested_run", level="capture", group="ingest", code_version="2")
def ingested_run(key: str, inputs) -> StageOutput:
    """Raw run folder -> canonical IMU (and turntable) parquet, manifest and sha256 of every raw file."""
    run = ingest_run(inputs.run_dir())
    m = run.manifest
    tables = {"imu": run.imu}
    if run.table is not None:
        tables["table"] = run.table
    meta = {
        "device_id": m.device.id,
        "run_id": m.run_id,
        "test_kind": m.test_kind,
        "grade": m.device.grade,
        "start_time_utc": m.start_time_utc.isoformat(),
        "power_cycle_index": m.power_cycle_index,
        "file_sha256": run.file_sha256,
        "n_samples": len(run.imu),
        "has_table_log": run.table is not None,
        "sample_rate_hz": m.sample_rate_hz,
    }
    return StageOutput(
        tables=tables,
        meta=meta,
        files={"manifest.json": (json.dumps(json.loads(m.model_dump_json()), indent=1, sort_keys=True) + "\n").encode()},
        summary={"test_kind": m.test_kind, "n_samples": len(run.imu), "duration_s": float(run.imu.time_s.iloc[-1])},
    )
