"""Apply a calibration to a file: read any IMU data the contract readers read, check units and device, write
calibrated canonical parquet whose metadata names the calibration (``imulab apply``).

Accepted inputs (``read_imu_input``):
- a captured run folder ``<landing>/<device>/<run>/`` (manifest + imu.csv|parquet): ingested with
  ``raw_schemas.readers.ingest_run`` (counts and lab units converted to SI by the manifest's channel table);
- a raw stream ``imu.csv|parquet`` (columns ``gyro_x ...``) with its ``manifest.json`` beside it (or given);
- a canonical SI table (columns ``gyro_x_radps ... accel_z_mps2``, e.g. the ``ingested_run`` store's
  ``imu.parquet``); the device is read from a ``manifest.json`` beside it when there is one.

Units: a raw stream without a manifest is refused (its columns carry no unit; counts cannot be told from SI);
canonical columns are checked to hold SI values: the median specific-force magnitude must lie within a factor
of 5 of 1 g (counts or g/mg values fail loudly, naming the column).
"""

from __future__ import annotations

import json
import os
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq

from assets_lib.apply.compensate import (
    ACCEL_COLUMNS,
    GYRO_COLUMNS,
    correct_frame,
    drift_of,
)
from assets_lib.apply.model import Calibration, CalibrationError
from raw_schemas.errors import RawDataError
from raw_schemas.manifest import load_manifest
from raw_schemas.readers import (
    MANIFEST_FILE,
    canonical_imu,
    ingest_run,
    read_stream,
    sha256_file,
)
from raw_schemas.tables import RAW_IMU_REQUIRED
from raw_schemas.units import STANDARD_GRAVITY_MPS2

METADATA_KEY = b"imulab.calibration"
#: canonical accelerometer columns must have a median |f| within this factor of 1 g (SI check)
SI_GRAVITY_FACTOR = 5.0


@dataclass(frozen=True)
class ImuInput:
    """Canonical SI IMU frame read from ``path``, with the device/run it comes from when known."""

    imu: pd.DataFrame
    path: str
    device_id: str | None
    run_id: str | None
    how: str  # 'run folder' | 'raw stream + manifest' | 'canonical SI table'
    sha256: dict[str, str]
    power_cycle_index: int | None = None  # from the manifest, when there is one


def _check_si(imu: pd.DataFrame, name: str) -> None:
    f = imu[list(ACCEL_COLUMNS)].to_numpy(float)
    norm = np.linalg.norm(f, axis=1)
    med = float(np.median(norm)) if norm.size else float("nan")
    if not (STANDARD_GRAVITY_MPS2 / SI_GRAVITY_FACTOR <= med <= STANDARD_GRAVITY_MPS2 * SI_GRAVITY_FACTOR):
        raise RawDataError(name, f"columns {list(ACCEL_COLUMNS)}",
                           "specific force in m/s^2 (median |f| near 9.8 for any IMU log under gravity)",
                           f"a median |f| of {med:.6g}: raw counts or g/mg values in SI-named columns? Ingest the run "
                           "folder (the manifest converts counts), or convert to m/s^2")


def read_imu_input(path: str | Path, manifest: str | Path | None = None) -> ImuInput:
    """Canonical SI frame from a run folder, a raw stream (+ manifest) or a canonical table; see the module doc."""
    p = Path(path)
    if p.is_dir():
        run = ingest_run(p)
        return ImuInput(run.imu, str(p), run.manifest.device.id, run.manifest.run_id, "run folder", run.file_sha256,
                        run.manifest.power_cycle_index)
    if not p.is_file():
        raise RawDataError(str(p), "", "a run folder, an imu.csv|parquet stream or a canonical SI parquet/csv", "no such file")
    raw = read_stream(p)
    cols = set(raw.columns)
    man_path = Path(manifest) if manifest else p.parent / MANIFEST_FILE
    if set(RAW_IMU_REQUIRED) <= cols:
        if not man_path.is_file():
            raise RawDataError(p.name, f"columns {list(RAW_IMU_REQUIRED[1:])}",
                               "a manifest.json beside the stream (or --manifest) giving each channel's unit "
                               "(counts + LSB, deg/s, g ...)", "none: raw columns carry no unit, counts cannot be told "
                               "from SI values")
        man = load_manifest(man_path)
        imu = canonical_imu(man, raw, p.name)
        _check_si(imu, p.name)
        return ImuInput(imu, str(p), man.device.id, man.run_id, "raw stream + manifest",
                        {p.name: sha256_file(p), man_path.name: sha256_file(man_path)}, man.power_cycle_index)
    need = ("time_s", *GYRO_COLUMNS, *ACCEL_COLUMNS)
    if set(need) <= cols:
        imu = raw
        bad = [c for c in need if not pd.api.types.is_numeric_dtype(imu[c])]
        if bad:
            raise RawDataError(p.name, f"column '{bad[0]}'", "numbers", f"dtype {imu[bad[0]].dtype}")
        _check_si(imu, p.name)
        dev = run_id = cycle = None
        hashes = {p.name: sha256_file(p)}
        if man_path.is_file():
            man = load_manifest(man_path)
            dev, run_id, cycle = man.device.id, man.run_id, man.power_cycle_index
            hashes[man_path.name] = sha256_file(man_path)
        return ImuInput(imu, str(p), dev, run_id, "canonical SI table", hashes, cycle)
    raise RawDataError(p.name, "header", f"raw columns {list(RAW_IMU_REQUIRED)} (with a manifest) or canonical SI "
                       f"columns {list(need)}", f"columns {sorted(cols)}")


def check_device(cal: Calibration, data: ImuInput, device: str | None = None, force: bool = False) -> list[str]:
    """Refuse applying a device's calibration to another device's data (unless ``force``); returns warnings."""
    dev = data.device_id or device
    if data.device_id and device and device != data.device_id:
        raise CalibrationError(f"--device {device!r} contradicts the data's manifest (device {data.device_id!r})")
    if dev is None:
        if force:
            return [f"{data.path}: device unknown (no manifest); applied the calibration of {cal.device_id} because of --force"]
        raise CalibrationError(f"{data.path}: cannot tell which device the data comes from (no manifest): pass "
                               f"--device {cal.device_id} to state it, or --force")
    if dev != cal.device_id:
        if force:
            return [f"calibration of device {cal.device_id} applied to data of device {dev} (--force)"]
        raise CalibrationError(f"the calibration is for device {cal.device_id!r}, the data ({data.path}) comes from "
                               f"device {dev!r}: refused (use --force to apply it anyway)")
    return []


def power_cycle_warnings(cal: Calibration, data: ImuInput) -> list[str]:
    """Data from another power cycle than the records whose biases are applied: the biases have changed by the
    device's turn-on repeatability since (``assets_lib.apply.drift``); say by how much, or that it is unknown."""
    used = {t.run_id for t in cal.terms if t.coefficient == "bias"}
    cycles = sorted({r.get("power_cycle_index") for r in cal.records if r["run_id"] in used} - {None})
    if data.power_cycle_index is None or not cycles or data.power_cycle_index in cycles:
        return []
    rep = cal.turn_on_repeatability
    if rep and "gyro" in rep and "accel" in rep:
        size = ("; turn-on bias repeatability (1 sigma) gyro " + ", ".join(f"{v:.3g}" for v in rep["gyro"])
                + " rad/s, accel " + ", ".join(f"{v:.3g}" for v in rep["accel"]) + " m/s^2")
    else:
        size = "; the turn-on bias repeatability is unknown (records of fewer than 3 power cycles)"
    return [(f"the data are from power cycle {data.power_cycle_index}, the biases applied from power cycle(s) "
             f"{cycles}: they differ by the device's turn-on repeatability{size}")]


def calibration_metadata(cal: Calibration, data: ImuInput, warnings: list[str], imulab_version: str = "") -> dict:
    """What the output's parquet metadata says about how it was calibrated."""
    return {
        "calibration_sha256": cal.identity_sha256,
        "kind": "record" if (len(cal.records) == 1 and cal.at_utc is None) else "device_calibration",
        "device_id": cal.device_id,
        "valid_at_utc": cal.at_utc,
        "records": list(cal.records),  # run id, record sha256, test kind, start time, store version
        "record_schema_versions": sorted({str(r.get("record_schema_version")) for r in cal.records}),
        "applied_terms": [f"{t.sensor} {t.axis} {t.coefficient}" for t in cal.terms],
        "missing_groups": list(cal.missing_groups),
        "not_applied": list(cal.not_applied),
        "bias_drift": drift_of(cal).note,
        "model": "docs/design.md sensor error model, inverted (assets_lib.apply.compensate)",
        "input": {"path": data.path, "how": data.how, "device_id": data.device_id, "run_id": data.run_id,
                  "sha256": data.sha256},
        "warnings": warnings,
        "imulab_version": imulab_version,
    }


def write_calibrated(out: str | Path, imu: pd.DataFrame, meta: dict) -> Path:
    """Atomic parquet write (temp file + os.replace) with ``meta`` under the ``imulab.calibration`` key."""
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    table = pa.Table.from_pandas(imu, preserve_index=False)
    table = table.replace_schema_metadata({**(table.schema.metadata or {}),
                                           METADATA_KEY: json.dumps(meta, sort_keys=True).encode()})
    fd, tmp = tempfile.mkstemp(prefix=f".{out.name}.", dir=out.parent)
    os.close(fd)
    try:
        pq.write_table(table, tmp)
        os.replace(tmp, out)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return out


def read_calibration_metadata(path: str | Path) -> dict | None:
    md = pq.read_schema(path).metadata or {}
    return json.loads(md[METADATA_KEY]) if METADATA_KEY in md else None


def apply_file(cal: Calibration, data_path, out, *, manifest=None, device: str | None = None, force: bool = False,
               imulab_version: str = "") -> tuple[Path, dict]:
    """Read ``data_path``, check device and units, apply ``cal``, write ``out``; returns (path, metadata)."""
    data = read_imu_input(data_path, manifest)
    warnings = check_device(cal, data, device, force)
    if cal.missing_groups and set(cal.missing_groups) - {"noise"}:
        warnings.append("not calibrated (nominal model kept): " + ", ".join(g for g in cal.missing_groups if g != "noise"))
    warnings += power_cycle_warnings(cal, data)
    meta = calibration_metadata(cal, data, warnings, imulab_version)
    return write_calibrated(out, correct_frame(cal, data.imu), meta), meta


def write_json_atomic(out: str | Path, obj: dict) -> Path:
    """JSON (indented, sorted keys) written to a temp file and moved into place."""
    return write_text_atomic(out, json.dumps(obj, indent=1, sort_keys=True, allow_nan=False) + "\n")


def write_text_atomic(out: str | Path, text: str) -> Path:
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{out.name}.", dir=out.parent)
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as f:
            f.write(text)
        os.replace(tmp, out)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return out
