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
    warnings: tuple = ()  # plausibility warnings on the imported values (each names the file and the figure)


class ImportedDataWarning(UserWarning):
    """An imported session whose values look mis-scaled (e.g. a static |f| far from 1 g): written, but suspect."""


#: median |f| of a record outside this band [g] is not gravity: the counts carry an offset or the lsb/unit is wrong
STATIC_F_BAND_G = (0.5, 2.0)
#: median |w| above this [rad/s] (57 deg/s) is no still or hand-held sensor: the gyro counts carry an offset
STILL_GYRO_MAX_RADPS = 1.0


def channel_si(values: np.ndarray, spec: dict, family: str) -> np.ndarray:
    """Values of one family as stored in the run (counts or a unit) -> canonical SI, as ingestion converts them."""
    from raw_schemas.units import COUNT_UNIT, si_factor

    if spec.get("unit") == COUNT_UNIT:
        return np.asarray(values, float) * float(spec["lsb"]) * si_factor(family, spec["lsb_unit"])
    return np.asarray(values, float) * si_factor(family, spec["unit"])


def gravity_check(accel_si: np.ndarray, file: str, hint: str) -> str | None:
    """A warning when the record's median |f| (m/s^2, rows x 3) is far from 1 g, else None.

    A calibration session (static poses, a hand-moved or multi-position test, a static run) is still most of
    the time, so the median of |f| over all samples is close to 1 g whatever the attitude; a median outside
    :data:`STATIC_F_BAND_G` means the values are not in the declared scale: integer counts read without their
    zero offset (unsigned ADC counts around mid-scale) or a wrong lsb / unit. ``hint`` says which option to give.
    """
    from raw_schemas.units import STANDARD_GRAVITY_MPS2

    mag = np.linalg.norm(np.asarray(accel_si, float), axis=1)
    if mag.size == 0:
        return None
    med = float(np.median(mag))
    lo, hi = STATIC_F_BAND_G
    if lo * STANDARD_GRAVITY_MPS2 <= med <= hi * STANDARD_GRAVITY_MPS2:
        return None
    return (f"{file}: the median specific force |f| of the record is {med:.4g} m/s^2 ({med / STANDARD_GRAVITY_MPS2:.3g} g), "
            f"outside {lo:g}-{hi:g} g for a session that is mostly still: {hint}")


def still_gyro_check(gyro_si: np.ndarray, file: str, hint: str, where: str = "the record") -> str | None:
    """A warning when the median |w| (rad/s, rows x 3) exceeds :data:`STILL_GYRO_MAX_RADPS`, else None."""
    mag = np.linalg.norm(np.asarray(gyro_si, float), axis=1)
    if mag.size == 0:
        return None
    med = float(np.median(mag))
    if med <= STILL_GYRO_MAX_RADPS:
        return None
    return (f"{file}: the median angular rate |w| of {where} is {med:.4g} rad/s ({np.degrees(med):.4g} deg/s), above "
            f"{STILL_GYRO_MAX_RADPS:g} rad/s for a sensor that is mostly still: {hint}")


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
