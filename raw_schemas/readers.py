"""Read and validate one captured run folder, and convert it to the canonical SI tables.

``ingest_run(run_dir)`` opens files read-only (the raw archive is never modified), hashes every file
(sha256), validates the manifest and the streams against the contract, and returns canonical DataFrames.
Every violation raises :class:`RawDataError` naming the file, the row/column or field, and what was expected.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.csv as pacsv
import pyarrow.parquet as pq

from raw_schemas.errors import RawDataError
from raw_schemas.hashcache import hash_folder_files, sha256_file  # noqa: F401 - sha256_file re-exported
from raw_schemas.manifest import IMU_CHANNELS, Manifest, load_manifest
from raw_schemas.tables import (
    CANONICAL_IMU_SCHEMA,
    CANONICAL_TABLE_SCHEMA,
    RAW_COLUMN_KIND,
    RAW_IMU_OPTIONAL,
    RAW_IMU_REQUIRED,
    RAW_TABLE_OPTIONAL,
    RAW_TABLE_REQUIRED,
)
from raw_schemas.units import COUNT_UNIT, family_of, si_factor

COMPLETE_MARKER = "_COMPLETE"
MANIFEST_FILE = "manifest.json"
#: a step between samples larger than this many nominal periods is a gap
GAP_FACTOR = 1.5
#: data may run past the plan's last step by at most max(this, 10 % of the plan)
PLAN_TAIL_TOLERANCE_S = 60.0


@dataclass(frozen=True)
class IngestedRun:
    """A validated run: manifest, canonical IMU and table frames, and the sha256 of every raw file."""

    manifest: Manifest
    imu: pd.DataFrame
    table: pd.DataFrame | None
    file_sha256: dict[str, str] = field(default_factory=dict)
    run_dir: str = ""

    @property
    def partition_key(self) -> str:
        return self.manifest.partition_key


def is_complete(run_dir: Path) -> bool:
    """A run is complete once its capture job has written the ``_COMPLETE`` marker (written last)."""
    return (Path(run_dir) / COMPLETE_MARKER).is_file()


def find_stream(run_dir: Path, stem: str, required: bool) -> Path | None:
    """``<stem>.csv`` or ``<stem>.parquet`` (exactly one)."""
    found = [p for p in (run_dir / f"{stem}.csv", run_dir / f"{stem}.parquet") if p.is_file()]
    if len(found) > 1:
        raise RawDataError(f"{stem}.*", f"in {run_dir}", f"one of {stem}.csv or {stem}.parquet", "both")
    if not found:
        if required:
            raise RawDataError(f"{stem}.csv", f"in {run_dir}", f"an IMU stream {stem}.csv or {stem}.parquet", "none")
        return None
    return found[0]


# ------------------------------------------------------------------------------------------------------------
# Reading a stream into a pandas frame (types checked column by column, row numbers 1-based data rows)
# ------------------------------------------------------------------------------------------------------------
def read_stream(path: Path) -> pd.DataFrame:
    """Read a CSV or parquet stream; structural problems (truncation, bad encoding) raise RawDataError."""
    name = path.name
    if path.suffix == ".parquet":
        try:
            table = pq.read_table(path)
        except (pa.ArrowInvalid, OSError) as e:
            raise RawDataError(name, "file", "a complete, readable parquet file (truncated?)", str(e).splitlines()[0]) from None
        return _to_pandas(table)
    data = path.read_bytes()
    if not data.strip():
        raise RawDataError(name, "file", "a header line and data rows", "an empty file")
    if not data.endswith(b"\n"):
        last_row = data.count(b"\n")  # header is line 1, so the unterminated line is data row `last_row`
        raise RawDataError(name, f"row {last_row} (line {last_row + 1})",
                           "every line terminated by a newline (file truncated during capture?)", "a cut-off last line")
    try:
        table = pacsv.read_csv(
            pa.py_buffer(data),
            parse_options=pacsv.ParseOptions(newlines_in_values=False),
            # only an empty field is null; 'nan' / 'inf' parse as floats and are reported as such
            convert_options=pacsv.ConvertOptions(null_values=[""], strings_can_be_null=False),
        )
    except pa.ArrowInvalid as e:
        msg = str(e)
        bad = _csv_bad_line(data)
        if bad is None:
            raise RawDataError(name, "file", "a CSV file with a header line and comma-separated data rows",
                               msg) from None
        row, nfields, ncol, line = bad
        raise RawDataError(name, f"row {row} (line {row + 1})", f"{ncol} comma-separated fields as in the header",
                           f"{nfields}: {line!r} (line cut mid-row?)") from None
    return _to_pandas(table)


def _to_pandas(table: pa.Table) -> pd.DataFrame:
    """Arrow -> pandas, keeping a null (empty CSV field, parquet null) distinguishable from NaN: it becomes None."""
    df = table.to_pandas()
    for col in table.column_names:
        if table.column(col).null_count:
            df[col] = pd.Series(table.column(col).to_pylist(), dtype=object, index=df.index)
    return df


def _csv_bad_line(data: bytes) -> tuple[int, int, int, str] | None:
    """(data row, fields found, fields expected, line text) of the first line whose field count differs."""
    lines = data.split(b"\n")
    ncol = lines[0].count(b",") + 1
    for i, line in enumerate(lines[1:], start=1):
        if line and line.count(b",") + 1 != ncol:
            return i, line.count(b",") + 1, ncol, line.decode("utf-8", "replace")
    return None


def _fmt(v) -> str:
    """A raw value as it appears in messages: ``0.5``, ``nan``, ``'abc'`` (no numpy type names)."""
    if isinstance(v, np.generic):
        v = v.item()
    return repr(v)


def _check_columns(df: pd.DataFrame, name: str, required, optional) -> None:
    cols = list(df.columns)
    missing = [c for c in required if c not in cols]
    if missing:
        raise RawDataError(name, "header", f"columns {list(required)} (+ optional {list(optional)})", f"missing {missing}")
    extra = [c for c in cols if c not in required and c not in optional]
    if extra:
        raise RawDataError(name, "header", f"only columns {list(required) + list(optional)}", f"unexpected {extra}")
    dup = [c for c in set(cols) if cols.count(c) > 1]
    if dup:
        raise RawDataError(name, "header", "each column once", f"duplicated {dup}")


def _numeric_column(df: pd.DataFrame, col: str, name: str, kind: str) -> np.ndarray:
    s = df[col]
    if kind == "str":
        return s.to_numpy()
    if not (pd.api.types.is_numeric_dtype(s) and not pd.api.types.is_bool_dtype(s)):
        conv = pd.to_numeric(s, errors="coerce")
        bad = np.flatnonzero(conv.isna().to_numpy() & s.notna().to_numpy())
        if bad.size:
            i = int(bad[0])
            raise RawDataError(name, _row(name, i, col), "a number", _fmt(s.iloc[i]))
        s = conv
    vals = s.to_numpy(dtype=float, na_value=np.nan)
    bad = np.flatnonzero(~np.isfinite(vals))
    if bad.size:
        i = int(bad[0])
        v = df[col].iloc[i]
        if v is None or v is pd.NA:
            found = "an empty field" if name.endswith(".csv") else "a null value"
        else:
            found = _fmt(v)
        raise RawDataError(name, _row(name, i, col), "a finite number", f"{found} ({bad.size} such row{'s' if bad.size > 1 else ''})")
    if kind == "int":
        frac = np.flatnonzero(vals != np.round(vals))
        if frac.size:
            i = int(frac[0])
            raise RawDataError(name, _row(name, i, col), "an integer", _fmt(df[col].iloc[i]))
    return vals


def _row(name: str, i: int, col: str) -> str:
    line = f" (line {i + 2})" if name.endswith(".csv") else ""
    return f"row {i + 1}{line}, column '{col}'"


def _check_time(t: np.ndarray, name: str, rate_hz: float | None) -> None:
    if t.size < 2:
        raise RawDataError(name, "rows", "at least 2 samples", f"{t.size}")
    d = np.diff(t)
    dup = np.flatnonzero(d == 0)
    back = np.flatnonzero(d < 0)
    if back.size and (not dup.size or back[0] < dup[0]):
        i = int(back[0]) + 1
        raise RawDataError(name, _row(name, i, "time_s"), f"time increasing (previous row {_fmt(t[i - 1])})",
                           f"{_fmt(t[i])}: time goes backwards")
    if dup.size:
        i = int(dup[0]) + 1
        raise RawDataError(name, _row(name, i, "time_s"), "a unique time stamp", f"{_fmt(t[i])}, the same as the previous row")
    if rate_hz:
        period = 1.0 / rate_hz
        med = float(np.median(d))
        if abs(med - period) > 0.01 * period:
            raise RawDataError(name, "column 'time_s'", f"a sample period of 1/{rate_hz:g} Hz = {period:.6g} s (manifest sample_rate_hz)",
                               f"a median period of {med:.6g} s")
        gaps = np.flatnonzero(d > GAP_FACTOR * period)
        if gaps.size:
            i = int(gaps[0])
            raise RawDataError(name, f"rows {i + 1}-{i + 2}, column 'time_s'",
                               f"samples every {period:.6g} s", f"a gap of {d[i]:.6g} s ({gaps.size} gaps in all)")


# ------------------------------------------------------------------------------------------------------------
# Validation and conversion
# ------------------------------------------------------------------------------------------------------------
def canonical_imu(manifest: Manifest, raw: pd.DataFrame, name: str = "imu") -> pd.DataFrame:
    """Validate a raw IMU frame against the contract and convert it to ``CANONICAL_IMU_SCHEMA`` (SI)."""
    _check_columns(raw, name, RAW_IMU_REQUIRED, RAW_IMU_OPTIONAL)
    cols = {c: _numeric_column(raw, c, name, RAW_COLUMN_KIND[c]) for c in raw.columns}
    t = cols["time_s"]
    _check_time(t, name, manifest.sample_rate_hz)
    if "counter" in cols:
        jumps = np.flatnonzero(np.diff(cols["counter"]) != 1)
        if jumps.size:
            i = int(jumps[0]) + 1
            raise RawDataError(name, _row(name, i, "counter"), f"counter {int(cols['counter'][i - 1]) + 1} (previous + 1)",
                               f"{int(cols['counter'][i])}: samples dropped or repeated")
    if "temperature" in cols and "temperature" not in manifest.channels:
        raise RawDataError(name, "column 'temperature'", "a 'temperature' entry in manifest channels", "none")
    out = {"time_s": t}
    for ch in IMU_CHANNELS:
        spec = manifest.channels[ch]
        vals = cols[ch]
        if spec.unit == COUNT_UNIT:
            frac = np.flatnonzero(vals != np.round(vals))
            if frac.size:
                i = int(frac[0])
                raise RawDataError(name, _row(name, i, ch), "an integer count (manifest unit 'counts')", _fmt(raw[ch].iloc[i]))
        factor = spec.physical_per_raw() * si_factor(family_of(ch), spec.physical_unit)
        out[CANONICAL_IMU_SCHEMA.names[1 + IMU_CHANNELS.index(ch)]] = vals * factor
    out["temperature_degc"] = cols["temperature"] if "temperature" in cols else np.full(t.size, np.nan)
    out["counter"] = pd.array(cols["counter"].astype(np.int64) if "counter" in cols else [None] * t.size, dtype="Int64")
    _check_plan_length(manifest, t, name)
    return pd.DataFrame(out)[CANONICAL_IMU_SCHEMA.names]


def _check_plan_length(manifest: Manifest, t: np.ndarray, name: str) -> None:
    plan = manifest.plan
    period = 1.0 / manifest.sample_rate_hz
    last = _row(name, t.size - 1, "time_s")
    for s in plan.steps:
        if s.end_s > t[-1] + period:
            raise RawDataError(name, last, f"data covering plan step {s.index} ({s.label or s.kind}) to {s.end_s:.6g} s",
                               f"data ending at {t[-1]:.6g} s ({len(plan.steps)} steps planned, plan ends at {plan.end_s:.6g} s)")
    if t[0] > plan.steps[0].start_s:
        raise RawDataError(name, _row(name, 0, "time_s"), f"data starting by plan step 0 at {plan.steps[0].start_s:.6g} s", f"first sample at {t[0]:.6g} s")
    tail = max(PLAN_TAIL_TOLERANCE_S, 0.1 * plan.end_s)
    if t[-1] > plan.end_s + tail:
        raise RawDataError(name, last, f"data ending within {tail:.6g} s after the plan ({plan.end_s:.6g} s)",
                           f"data ending at {t[-1]:.6g} s: is this the right manifest/plan?")


def canonical_table(manifest: Manifest, raw: pd.DataFrame, name: str = "table") -> pd.DataFrame:
    """Validate a raw turntable log and convert it to ``CANONICAL_TABLE_SCHEMA``."""
    _check_columns(raw, name, RAW_TABLE_REQUIRED, RAW_TABLE_OPTIONAL)
    cols = {c: _numeric_column(raw, c, name, RAW_COLUMN_KIND[c]) for c in raw.columns}
    _check_time(cols["time_s"], name, None)
    idx = cols["step_index"]
    bad = np.flatnonzero((idx < -1) | (idx >= len(manifest.plan.steps)))
    if bad.size:
        i = int(bad[0])
        raise RawDataError(name, _row(name, i, "step_index"), f"-1 or a plan step index 0..{len(manifest.plan.steps) - 1}", _fmt(raw["step_index"].iloc[i]))
    return pd.DataFrame(
        {
            "time_s": cols["time_s"],
            "angle_rad": np.radians(cols["angle_deg"]),
            "rate_radps": np.radians(cols["rate_dps"]),
            "step_index": idx.astype(np.int64),
        }
    )[CANONICAL_TABLE_SCHEMA.names]


def ingest_frames(manifest: Manifest, imu_raw: pd.DataFrame, table_raw: pd.DataFrame | None = None) -> IngestedRun:
    """In-memory ingestion (same validation as files), e.g. for a simulated run."""
    imu = canonical_imu(manifest, imu_raw, "imu")
    table = canonical_table(manifest, table_raw, "table") if table_raw is not None else None
    return IngestedRun(manifest, imu, table)


def ingest_run(run_dir: str | Path) -> IngestedRun:
    """Validate one completed run folder and return its canonical tables and file hashes (read-only)."""
    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        raise RawDataError(str(run_dir), "", "a run folder <landing>/<device_id>/<run_id>/", "no such folder")
    if not is_complete(run_dir):
        raise RawDataError(COMPLETE_MARKER, f"in {run_dir}", "the completion marker written last by the capture job",
                           "none (run still being captured?)")
    hashes = hash_folder_files(run_dir)  # remembered per file state (raw_schemas.hashcache)
    manifest = load_manifest(run_dir / MANIFEST_FILE)
    if manifest.device.id != run_dir.parent.name or manifest.run_id != run_dir.name:
        raise RawDataError(MANIFEST_FILE, "fields 'device.id'/'run_id'",
                           f"{run_dir.parent.name!r}/{run_dir.name!r} (the folder names)",
                           f"{manifest.device.id!r}/{manifest.run_id!r}")
    imu_path = find_stream(run_dir, "imu", required=True)
    imu = canonical_imu(manifest, read_stream(imu_path), imu_path.name)
    table_path = find_stream(run_dir, "table", required=False)
    table = canonical_table(manifest, read_stream(table_path), table_path.name) if table_path else None
    return IngestedRun(manifest, imu, table, hashes, str(run_dir))


def discover_runs(landing: str | Path) -> list[Path]:
    """Completed run folders ``<landing>/<device>/<run>/`` (folders whose name starts with '_' or '.' skipped)."""
    landing = Path(landing)
    out = []
    for dev in sorted(p for p in landing.iterdir() if p.is_dir() and p.name[0] not in "_."):
        out += [r for r in sorted(p for p in dev.iterdir() if p.is_dir() and p.name[0] not in "_.") if is_complete(r)]
    return out
