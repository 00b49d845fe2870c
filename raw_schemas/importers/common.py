"""What every importer returns, and the one writer that turns it into a contract run folder."""

from __future__ import annotations

import json
import os
import shutil
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq

from raw_schemas.errors import RawDataError
from raw_schemas.manifest import SCHEMA_VERSION, Manifest, _contract_error
from raw_schemas.readers import COMPLETE_MARKER, MANIFEST_FILE, ingest_frames

from pydantic import ValidationError


@dataclass(frozen=True)
class ImportedSession:
    """A session read from a foreign format: the raw IMU frame in contract columns (``time_s``, ``gyro_*``,
    ``accel_*`` [, ``temperature``]), the channel specs, the nominal rate, the test kind and its plan steps."""

    imu: pd.DataFrame
    channels: dict
    sample_rate_hz: float
    test_kind: str
    steps: list
    plan_name: str
    notes: str = ""
    start_time_utc: str | None = None  # when the source carries absolute time (ROS stamps)
    sources: dict = field(default_factory=dict)  # file name -> description


@dataclass(frozen=True)
class RunMeta:
    """What the source files do not say: device, run id, site; the command line supplies it."""

    device_id: str
    run_id: str
    device_model: str = "unknown"
    grade: str = "consumer"
    serial: str | None = None
    latitude_deg: float = 0.0
    height_m: float = 0.0
    gravity_mps2: float | None = None
    start_time_utc: str | None = None
    power_cycle_index: int = 0


def median_rate_hz(t_s: np.ndarray, file: str) -> float:
    """Nominal sample rate from time stamps: 1 / median interval (rounded to 1e-6 relative)."""
    d = np.diff(np.asarray(t_s, float))
    if d.size == 0 or not np.all(np.isfinite(d)):
        raise RawDataError(file, "time column", "at least two finite time stamps", f"{t_s.size} samples")
    med = float(np.median(d))
    if med <= 0:
        raise RawDataError(file, "time column", "increasing time stamps", f"a median interval of {med:g} s")
    return float(f"{1.0 / med:.7g}")


def whole_session_steps(t_s: np.ndarray, rate_hz: float, label: str = "hand-moved session") -> list:
    """A single ``free`` step covering the record: the poses are found by segmentation."""
    t0, t1 = float(t_s[0]), float(t_s[-1])
    return [{"index": 0, "kind": "free", "start_s": t0, "duration_s": max(t1 - t0, 1.0 / rate_hz), "label": label}]


def build_manifest(session: ImportedSession, meta: RunMeta) -> Manifest:
    start = meta.start_time_utc or session.start_time_utc or "1970-01-01T00:00:00Z"
    site = {"name": "", "latitude_deg": meta.latitude_deg, "height_m": meta.height_m}
    if meta.gravity_mps2 is not None:
        site.update(gravity_mps2=meta.gravity_mps2, gravity_model="given")
    raw = {
        "schema_version": SCHEMA_VERSION,
        "device": {"id": meta.device_id, "model": meta.device_model, "grade": meta.grade, "serial": meta.serial},
        "run_id": meta.run_id,
        "test_kind": session.test_kind,
        "start_time_utc": start,
        "site": site,
        "sample_rate_hz": session.sample_rate_hz,
        "channels": session.channels,
        "plan": {"name": session.plan_name, "steps": session.steps},
        "power_cycle_index": meta.power_cycle_index,
        "notes": session.notes,
    }
    try:
        return Manifest.model_validate(raw)
    except ValidationError as e:
        raise _contract_error(MANIFEST_FILE + " (generated)", e.errors()[0]) from None


def write_run(session: ImportedSession, landing: Path, meta: RunMeta) -> Path:
    """Validate (as ``ingest_run`` would) and write ``<landing>/<device>/<run>/`` atomically: the files go to a
    hidden staging folder that is renamed into place after ``_COMPLETE`` is written. An existing run folder is
    never overwritten (the landing area is append-only)."""
    manifest = build_manifest(session, meta)
    ingest_frames(manifest, session.imu)  # same stream checks as ingestion; raises RawDataError naming row/column
    dev = Path(landing) / meta.device_id
    final = dev / meta.run_id
    if final.exists():
        raise RawDataError(str(final), "", "a new run folder (the landing area is append-only)", "it exists already")
    dev.mkdir(parents=True, exist_ok=True)
    stage = dev / f".tmp-{meta.run_id}-{os.getpid()}"
    if stage.exists():
        shutil.rmtree(stage)
    stage.mkdir()
    try:
        table = pa.Table.from_pandas(session.imu.reset_index(drop=True), preserve_index=False)
        pq.write_table(table, stage / "imu.parquet", compression="zstd")
        text = json.dumps(json.loads(manifest.model_dump_json(exclude_none=True)), indent=2) + "\n"
        (stage / MANIFEST_FILE).write_text(text, encoding="utf-8")
        (stage / "import.json").write_text(json.dumps({"sources": session.sources}, indent=1, sort_keys=True) + "\n",
                                           encoding="utf-8")
        (stage / COMPLETE_MARKER).write_text("")
        os.replace(stage, final)
    except BaseException:
        shutil.rmtree(stage, ignore_errors=True)
        raise
    return final


def sha256_sources(paths) -> dict:
    from raw_schemas.readers import sha256_file

    out = {}
    for p in paths:
        p = Path(p)
        if p.is_dir():
            for q in sorted(p.rglob("*")):
                if q.is_file():
                    out[str(q.relative_to(p.parent))] = sha256_file(q)
        else:
            out[p.name] = sha256_file(p)
    return out


def option_float(options: dict, key: str, file: str, default: float | None = None, required_for: str = "") -> float | None:
    v = options.get(key)
    if v is None:
        if default is None and required_for:
            raise RawDataError(file, f"option {key!r}", f"-o {key}=<number> ({required_for})", "none given")
        return default
    try:
        return float(v)
    except ValueError:
        raise RawDataError(file, f"option {key!r}", "a number", repr(v)) from None
