"""Ingestion of raw run folders: every contract violation is refused with a precise RawDataError, good runs are
read without touching the raw archive, and CSV/parquet give the same SI frames with exact count conversion.

Bad inputs are made by writing a good simulated run (a 2-step plan at 100 Hz) and corrupting a copy.
"""

from __future__ import annotations

import hashlib
import json
import os
import stat
from pathlib import Path

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from assets_lib.sim.plans import build_plan
from assets_lib.sim.simulator import example_device, simulate_run, write_run
from raw_schemas.errors import RawDataError
from raw_schemas.manifest import IMU_CHANNELS
from raw_schemas.readers import discover_runs, ingest_run
from raw_schemas.tables import CANONICAL_IMU_SCHEMA, CANONICAL_TABLE_SCHEMA
from raw_schemas.units import family_of, si_factor

DEVICE = "TAC-001"
RUN = "r001"
TWO_STEP = {
    "name": "two_step",
    "frame": "ENU",
    "lead_s": 1.0,
    "transition_s": 2.0,
    "steps": [
        {"kind": "static", "axes": {"x": "E", "y": "N", "z": "U"}, "duration_s": 5.0, "settle_s": 1.0},
        {"kind": "rate", "axes": {"x": "E", "y": "N", "z": "U"}, "table_rate_dps": 36.0, "duration_s": 10.0,
         "settle_s": 1.0},
    ],
}
FORMATS = ("csv", "parquet")


def _simulate(run_id: str = RUN, **kw):
    truth = example_device(DEVICE, "tactical", seed=5)
    return simulate_run(truth, build_plan(TWO_STEP), run_id, test_kind="rate", seed=11, **kw)


@pytest.fixture(scope="module")
def sim():
    return _simulate()


def _write(run, tmp_path: Path, fmt: str) -> Path:
    return write_run(run, tmp_path / "landing", fmt, truth_dir=tmp_path / "truth")


@pytest.fixture(params=FORMATS)
def fmt(request):
    return request.param


@pytest.fixture
def run_dir(sim, tmp_path, fmt) -> Path:
    return _write(sim, tmp_path, fmt)


# ------------------------------------------------------------------------------------------------------------
# Corruption helpers
# ------------------------------------------------------------------------------------------------------------
def _csv_lines(path: Path) -> list[str]:
    text = path.read_text()
    assert text.endswith("\n")
    return text[:-1].split("\n")


def _write_csv_lines(path: Path, lines: list[str]) -> None:
    path.write_text("\n".join(lines) + "\n")


def _set_csv_cell(path: Path, row: int, col: str, value: str) -> None:
    """Replace the text of data row ``row`` (1-based, header excluded), column ``col``."""
    lines = _csv_lines(path)
    header = lines[0].split(",")
    fields = lines[row].split(",")
    fields[header.index(col)] = value
    lines[row] = ",".join(fields)
    _write_csv_lines(path, lines)


def _stream(run_dir: Path, stem: str = "imu") -> Path:
    (p,) = [q for q in (run_dir / f"{stem}.csv", run_dir / f"{stem}.parquet") if q.is_file()]
    return p


def _read_raw(path: Path) -> pd.DataFrame:
    return pd.read_csv(path) if path.suffix == ".csv" else pd.read_parquet(path)


def _write_raw(path: Path, df: pd.DataFrame) -> None:
    if path.suffix == ".csv":
        df.to_csv(path, index=False)
    else:
        df.to_parquet(path, index=False)


def _write_parquet_arrays(path: Path, columns: dict) -> None:
    """Write parquet straight from Arrow arrays (pandas would turn NaN into null)."""
    pq.write_table(pa.table(columns), path)


def _edit_manifest(run_dir: Path, fn) -> None:
    p = run_dir / "manifest.json"
    m = json.loads(p.read_text())
    fn(m)
    p.write_text(json.dumps(m, indent=2))


def _ingest_error(run_dir: Path) -> RawDataError:
    with pytest.raises(RawDataError) as ei:
        ingest_run(run_dir)
    return ei.value


def _check(err: RawDataError, file: str, where: str, expected: str, found: str | None = None, found_has: str = ""):
    assert err.file == file
    assert err.where == where
    assert err.expected == expected
    if found is not None:
        assert err.found == found
    assert found_has in (err.found or "")
    assert str(err) == f"{file}" + (f", {where}" if where else "") + f": expected {expected}" + (
        f", found {err.found}" if err.found is not None else ""
    )


def _where(fmt: str, row: int, col: str) -> str:
    return f"row {row} (line {row + 1}), column '{col}'" if fmt == "csv" else f"row {row}, column '{col}'"


# ------------------------------------------------------------------------------------------------------------
# The good run (baseline for every corruption below)
# ------------------------------------------------------------------------------------------------------------
def test_good_run_ingests(run_dir, sim, fmt):
    r = ingest_run(run_dir)
    assert list(r.imu.columns) == CANONICAL_IMU_SCHEMA.names
    assert list(r.table.columns) == CANONICAL_TABLE_SCHEMA.names
    assert len(r.imu) == len(sim.imu_raw)
    assert r.partition_key == f"{DEVICE}__{RUN}"
    assert sorted(r.file_sha256) == sorted(["_COMPLETE", "manifest.json", f"imu.{fmt}", f"table.{fmt}"])


# ------------------------------------------------------------------------------------------------------------
# Columns and values
# ------------------------------------------------------------------------------------------------------------
def test_missing_column(run_dir, fmt):
    p = _stream(run_dir)
    _write_raw(p, _read_raw(p).drop(columns=["gyro_y"]))
    _check(_ingest_error(run_dir), f"imu.{fmt}", "header",
           "columns ['time_s', 'gyro_x', 'gyro_y', 'gyro_z', 'accel_x', 'accel_y', 'accel_z'] "
           "(+ optional ['temperature', 'counter'])", "missing ['gyro_y']")


def test_extra_column(run_dir, fmt):
    p = _stream(run_dir)
    df = _read_raw(p)
    df["pressure"] = 1013.0
    _write_raw(p, df)
    _check(_ingest_error(run_dir), f"imu.{fmt}", "header",
           "only columns ['time_s', 'gyro_x', 'gyro_y', 'gyro_z', 'accel_x', 'accel_y', 'accel_z', 'temperature', "
           "'counter']", "unexpected ['pressure']")


@pytest.mark.parametrize("col", ["gyro_y", "time_s", "counter"])
def test_text_in_numeric_column(run_dir, fmt, col):
    p = _stream(run_dir)
    if fmt == "csv":
        _set_csv_cell(p, 100, col, "abc")
    else:
        df = _read_raw(p)
        df[col] = df[col].astype(str)
        df.loc[99, col] = "abc"
        _write_raw(p, df)
    _check(_ingest_error(run_dir), f"imu.{fmt}", _where(fmt, 100, col), "a number", "'abc'")


@pytest.mark.parametrize(
    "text, value, shown", [("nan", np.nan, "nan"), ("inf", np.inf, "inf"), ("-inf", -np.inf, "-inf")]
)
@pytest.mark.parametrize("col", ["accel_z", "temperature"])
def test_non_finite_value(run_dir, fmt, col, text, value, shown):
    p = _stream(run_dir)
    if fmt == "csv":
        _set_csv_cell(p, 100, col, text)
    else:
        df = _read_raw(p)
        vals = df[col].to_numpy(dtype=float, copy=True)
        vals[99] = value
        _write_parquet_arrays(
            p, {c: (pa.array(vals) if c == col else pa.array(df[c].to_numpy())) for c in df.columns}
        )
    _check(_ingest_error(run_dir), f"imu.{fmt}", _where(fmt, 100, col), "a finite number", f"{shown} (1 such row)")


def test_nan_in_several_rows_counts_them(run_dir, fmt):
    p = _stream(run_dir)
    if fmt == "csv":
        for row in (40, 41, 700):
            _set_csv_cell(p, row, "gyro_x", "NaN")
    else:
        df = _read_raw(p)
        vals = df["gyro_x"].to_numpy(dtype=float, copy=True)
        vals[[39, 40, 699]] = np.nan
        _write_parquet_arrays(
            p, {c: (pa.array(vals) if c == "gyro_x" else pa.array(df[c].to_numpy())) for c in df.columns}
        )
    _check(_ingest_error(run_dir), f"imu.{fmt}", _where(fmt, 40, "gyro_x"), "a finite number", "nan (3 such rows)")


@pytest.mark.parametrize("col", ["gyro_y", "time_s", "counter", "temperature"])
def test_empty_field(run_dir, fmt, col):
    p = _stream(run_dir)
    if fmt == "csv":
        _set_csv_cell(p, 100, col, "")
        found = "an empty field (1 such row)"
    else:  # parquet: a null
        df = _read_raw(p)
        mask = np.zeros(len(df), dtype=bool)
        mask[99] = True
        _write_parquet_arrays(
            p, {c: pa.array(df[c].to_numpy(), mask=mask if c == col else None) for c in df.columns}
        )
        found = "a null value (1 such row)"
    _check(_ingest_error(run_dir), f"imu.{fmt}", _where(fmt, 100, col), "a finite number", found)


def test_counts_not_integer(run_dir, fmt):
    p = _stream(run_dir)
    df = _read_raw(p)
    df["gyro_x"] = df["gyro_x"].astype(float)
    df.loc[99, "gyro_x"] = df.loc[99, "gyro_x"] + 0.5
    _write_raw(p, df)
    _check(_ingest_error(run_dir), f"imu.{fmt}", _where(fmt, 100, "gyro_x"),
           "an integer count (manifest unit 'counts')", repr(float(df.loc[99, "gyro_x"])))


def test_counts_written_as_integral_floats_are_accepted(run_dir, fmt, sim):
    p = _stream(run_dir)
    df = _read_raw(p)
    for ch in IMU_CHANNELS:
        df[ch] = df[ch].astype(float)  # 123.0: still an integer count
    _write_raw(p, df)
    r = ingest_run(run_dir)
    assert len(r.imu) == len(sim.imu_raw)


# ------------------------------------------------------------------------------------------------------------
# Time stamps and counter
# ------------------------------------------------------------------------------------------------------------
def _set_value(run_dir: Path, col: str, row: int, value, stem: str = "imu") -> None:
    p = _stream(run_dir, stem)
    df = _read_raw(p)
    df.loc[row - 1, col] = value
    _write_raw(p, df)


def test_time_not_monotonic(run_dir, fmt):
    _set_value(run_dir, "time_s", 100, 0.5)  # previous row is 0.98
    _check(_ingest_error(run_dir), f"imu.{fmt}", _where(fmt, 100, "time_s"), "time increasing (previous row 0.98)",
           "0.5: time goes backwards")


def test_time_duplicated(run_dir, fmt):
    _set_value(run_dir, "time_s", 100, 0.98)
    _check(_ingest_error(run_dir), f"imu.{fmt}", _where(fmt, 100, "time_s"), "a unique time stamp",
           "0.98, the same as the previous row")


def test_time_gap(run_dir, fmt):
    p = _stream(run_dir)
    df = _read_raw(p)
    _write_raw(p, df.drop(index=range(99, 149)).reset_index(drop=True))  # rows 100..149 dropped
    _check(_ingest_error(run_dir), f"imu.{fmt}", "rows 99-100, column 'time_s'", "samples every 0.01 s",
           "a gap of 0.51 s (1 gaps in all)")


def test_sample_rate_not_as_declared(run_dir, fmt):
    _edit_manifest(run_dir, lambda m: m.update(sample_rate_hz=50.0))
    _check(_ingest_error(run_dir), f"imu.{fmt}", "column 'time_s'",
           "a sample period of 1/50 Hz = 0.02 s (manifest sample_rate_hz)", "a median period of 0.01 s")


def test_counter_jump(run_dir, fmt):
    p = _stream(run_dir)
    df = _read_raw(p)
    df.loc[99:, "counter"] += 7  # 7 samples lost, time stamps intact
    _write_raw(p, df)
    _check(_ingest_error(run_dir), f"imu.{fmt}", _where(fmt, 100, "counter"), "counter 99 (previous + 1)",
           "106: samples dropped or repeated")


# ------------------------------------------------------------------------------------------------------------
# Plan versus data length
# ------------------------------------------------------------------------------------------------------------
def test_data_shorter_than_plan(run_dir, fmt):
    p = _stream(run_dir)
    _write_raw(p, _read_raw(p).iloc[:1500])  # the plan ends at 18 s, data at 14.99 s
    _check(_ingest_error(run_dir), f"imu.{fmt}", _where(fmt, 1500, "time_s"),
           "data covering plan step 1 (z-up +36 deg/s) to 18 s",
           "data ending at 14.99 s (2 steps planned, plan ends at 18 s)")


def test_data_far_longer_than_plan(tmp_path, fmt):
    # a 61 s tail after an 18 s plan: beyond max(60 s, 10 % of the plan) -> wrong manifest/plan?
    run = _simulate(tail_s=61.0)
    d = _write(run, tmp_path, fmt)
    n = len(run.imu_raw)
    _check(_ingest_error(d), f"imu.{fmt}", _where(fmt, n, "time_s"),
           "data ending within 60 s after the plan (18 s)", "data ending at 79 s: is this the right manifest/plan?")


def test_data_within_tail_tolerance_is_accepted(tmp_path, fmt):
    run = _simulate(tail_s=59.0)
    assert len(ingest_run(_write(run, tmp_path, fmt)).imu) == len(run.imu_raw)


def test_data_starting_after_plan_start(run_dir, fmt):
    p = _stream(run_dir)
    df = _read_raw(p).iloc[150:].reset_index(drop=True)  # first sample at 1.5 s, step 0 starts at 1 s
    _write_raw(p, df)
    _check(_ingest_error(run_dir), f"imu.{fmt}", _where(fmt, 1, "time_s"), "data starting by plan step 0 at 1 s",
           "first sample at 1.5 s")


# ------------------------------------------------------------------------------------------------------------
# Truncated files
# ------------------------------------------------------------------------------------------------------------
def test_csv_last_line_cut_mid_row(sim, tmp_path):
    d = _write(sim, tmp_path, "csv")
    p = d / "imu.csv"
    lines = _csv_lines(p)[:1001]
    cut = lines[1000][:9]
    _write_csv_lines(p, lines[:1000] + [cut])  # newline-terminated, but too few fields
    nfields = cut.count(",") + 1
    _check(_ingest_error(d), "imu.csv", "row 1000 (line 1001)", "9 comma-separated fields as in the header",
           f"{nfields}: {cut!r} (line cut mid-row?)")


def test_csv_cut_without_trailing_newline(sim, tmp_path):
    d = _write(sim, tmp_path, "csv")
    p = d / "imu.csv"
    data = p.read_bytes()
    line_starts = [i + 1 for i, b in enumerate(data) if b == 0x0A]
    p.write_bytes(data[: line_starts[1000] + 7])  # 7 bytes into data row 1001
    _check(_ingest_error(d), "imu.csv", "row 1001 (line 1002)",
           "every line terminated by a newline (file truncated during capture?)", "a cut-off last line")


def test_csv_complete_rows_but_no_final_newline(sim, tmp_path):
    d = _write(sim, tmp_path, "csv")
    p = d / "imu.csv"
    p.write_bytes(p.read_bytes()[:-1])
    n = len(sim.imu_raw)
    _check(_ingest_error(d), "imu.csv", f"row {n} (line {n + 1})",
           "every line terminated by a newline (file truncated during capture?)", "a cut-off last line")


@pytest.mark.parametrize("keep", [0.6, 0.999])
def test_parquet_truncated(sim, tmp_path, keep):
    d = _write(sim, tmp_path, "parquet")
    p = d / "imu.parquet"
    data = p.read_bytes()
    p.write_bytes(data[: int(len(data) * keep)])
    _check(_ingest_error(d), "imu.parquet", "file", "a complete, readable parquet file (truncated?)")


def test_empty_csv(sim, tmp_path):
    d = _write(sim, tmp_path, "csv")
    (d / "imu.csv").write_bytes(b"")
    _check(_ingest_error(d), "imu.csv", "file", "a header line and data rows", "an empty file")


# ------------------------------------------------------------------------------------------------------------
# Manifest
# ------------------------------------------------------------------------------------------------------------
def test_missing_manifest(run_dir):
    (run_dir / "manifest.json").unlink()
    _check(_ingest_error(run_dir), "manifest.json", f"in {run_dir}", "a manifest.json file", "none")


def test_invalid_json(run_dir):
    p = run_dir / "manifest.json"
    p.write_text('{\n  "schema_version": "1.0",\n  "run_id": "r001"\n  "test_kind": "rate"\n}\n')  # missing comma
    _check(_ingest_error(run_dir), "manifest.json", "line 4 column 3", "valid JSON", "Expecting ',' delimiter")


def test_manifest_not_an_object(run_dir):
    (run_dir / "manifest.json").write_text("[1, 2]\n")
    _check(_ingest_error(run_dir), "manifest.json", "top level", "a JSON object", "list")


@pytest.mark.parametrize("version, shown", [("2.0", "'2.0'"), (1.0, "1.0"), (None, "None")])
def test_wrong_schema_version(run_dir, version, shown):
    if version is None:
        _edit_manifest(run_dir, lambda m: m.pop("schema_version"))
    else:
        _edit_manifest(run_dir, lambda m: m.update(schema_version=version))
    _check(_ingest_error(run_dir), "manifest.json", "field 'schema_version'", "one of ['1.0']", shown)


@pytest.mark.parametrize(
    "stamp, found",
    [
        ("2026-01-05T09:00:00+01:00", "'2026-01-05T09:00:00+01:00' (offset +01:00)"),
        ("2026-01-05T08:00:00", "'2026-01-05T08:00:00' (no UTC offset)"),
    ],
)
def test_start_time_not_utc(run_dir, stamp, found):
    _edit_manifest(run_dir, lambda m: m.update(start_time_utc=stamp))
    _check(_ingest_error(run_dir), "manifest.json", "field 'start_time_utc'",
           "an ISO 8601 time with UTC offset zero, e.g. 2026-01-05T08:00:00Z", found)


def test_start_time_with_zero_offset_accepted(run_dir):
    _edit_manifest(run_dir, lambda m: m.update(start_time_utc="2026-01-05T08:00:00+00:00"))
    assert ingest_run(run_dir).manifest.start_time_utc.utcoffset().total_seconds() == 0


@pytest.mark.parametrize(
    "channel, spec, where, expected, found",
    [
        ("gyro_y", {"unit": "counts", "lsb": 1e-4, "lsb_unit": "dps"}, "channels.gyro_y.lsb_unit",
         "one of the gyro units ['deg/h', 'deg/s', 'mrad/s', 'rad/s']", "unknown unit 'dps'"),
        ("accel_x", {"unit": "m/s2"}, "channels.accel_x.unit",
         "one of the accel units ['g', 'm/s^2', 'mg', 'ug'] (or unit 'counts' with lsb and lsb_unit)",
         "unknown unit 'm/s2'"),
        ("temperature", {"unit": "degF"}, "channels.temperature.unit", "one of the temperature units ['degC']",
         "unknown unit 'degF'"),
    ],
)
def test_unknown_unit_string(run_dir, channel, spec, where, expected, found):
    _edit_manifest(run_dir, lambda m: m["channels"].update({channel: spec}))
    _check(_ingest_error(run_dir), "manifest.json", f"field '{where}'", expected, found)


def test_counts_without_lsb(run_dir):
    _edit_manifest(run_dir, lambda m: m["channels"]["gyro_z"].pop("lsb"))
    _check(_ingest_error(run_dir), "manifest.json", "field 'channels.gyro_z'",
           "a channel in 'counts' needs 'lsb' and 'lsb_unit'")


def test_unknown_manifest_field(run_dir):
    _edit_manifest(run_dir, lambda m: m["site"].update(altitude_m=400.0))
    _check(_ingest_error(run_dir), "manifest.json", "field 'site.altitude_m'", "only the fields of the manifest schema",
           "unknown field 'altitude_m'")


def test_missing_manifest_field(run_dir):
    _edit_manifest(run_dir, lambda m: m["device"].pop("grade"))
    _check(_ingest_error(run_dir), "manifest.json", "field 'device.grade'", "a value (required field)", "no such field")


def test_bad_enum_value(run_dir):
    _edit_manifest(run_dir, lambda m: m["device"].update(grade="military"))
    _check(_ingest_error(run_dir), "manifest.json", "field 'device.grade'",
           "'consumer', 'industrial', 'tactical' or 'navigation'", "'military'")


@pytest.mark.parametrize("field", ["device", "run"])
def test_manifest_ids_must_match_folders(run_dir, field):
    if field == "device":
        _edit_manifest(run_dir, lambda m: m["device"].update(id="TAC-999"))
        found = f"'TAC-999'/'{RUN}'"
    else:
        _edit_manifest(run_dir, lambda m: m.update(run_id="r999"))
        found = f"'{DEVICE}'/'r999'"
    _check(_ingest_error(run_dir), "manifest.json", "fields 'device.id'/'run_id'",
           f"'{DEVICE}'/'{RUN}' (the folder names)", found)


def test_run_folder_renamed_is_refused(run_dir):
    moved = run_dir.parent / "r002"
    run_dir.rename(moved)
    _check(_ingest_error(moved), "manifest.json", "fields 'device.id'/'run_id'",
           f"'{DEVICE}'/'r002' (the folder names)", f"'{DEVICE}'/'{RUN}'")


# ------------------------------------------------------------------------------------------------------------
# Folder-level rules
# ------------------------------------------------------------------------------------------------------------
def test_both_imu_csv_and_parquet(sim, tmp_path):
    d = _write(sim, tmp_path, "csv")
    sim.imu_raw.to_parquet(d / "imu.parquet", index=False)
    _check(_ingest_error(d), "imu.*", f"in {d}", "one of imu.csv or imu.parquet", "both")


def test_missing_imu_stream(run_dir, fmt):
    (run_dir / f"imu.{fmt}").unlink()
    _check(_ingest_error(run_dir), "imu.csv", f"in {run_dir}", "an IMU stream imu.csv or imu.parquet", "none")


def test_run_without_complete_marker_is_refused_and_skipped(sim, tmp_path, fmt):
    landing = tmp_path / "landing"
    done = write_run(sim, landing, fmt)  # truth goes to <landing>/_truth/<device>/<run>.json
    capturing = write_run(_simulate("r002"), landing, fmt)
    (capturing / "_COMPLETE").unlink()
    assert (landing / "_truth" / DEVICE / f"{RUN}.json").is_file()
    (landing / "_truth" / DEVICE / "r009").mkdir()
    (landing / "_truth" / DEVICE / "r009" / "_COMPLETE").write_text("")  # '_' folders are never devices
    (landing / DEVICE / ".tmp-r003").mkdir()  # nor '.' folders runs
    (landing / DEVICE / ".tmp-r003" / "_COMPLETE").write_text("")
    assert discover_runs(landing) == [done]
    _check(_ingest_error(capturing), "_COMPLETE", f"in {capturing}",
           "the completion marker written last by the capture job", "none (run still being captured?)")
    (capturing / "_COMPLETE").write_text("")
    assert discover_runs(landing) == [done, capturing]


def test_table_step_index_out_of_range(run_dir, fmt):
    for bad in (2, -2):
        _set_value(run_dir, "step_index", 300, bad, stem="table")
        _check(_ingest_error(run_dir), f"table.{fmt}", _where(fmt, 300, "step_index"),
               "-1 or a plan step index 0..1", str(bad))


def test_table_time_not_monotonic(run_dir, fmt):
    p = _stream(run_dir, "table")
    df = _read_raw(p)
    prev = float(df.loc[48, "time_s"])
    df.loc[49, "time_s"] = prev - 0.5
    _write_raw(p, df)
    _check(_ingest_error(run_dir), f"table.{fmt}", _where(fmt, 50, "time_s"),
           f"time increasing (previous row {prev!r})", f"{prev - 0.5!r}: time goes backwards")


# ------------------------------------------------------------------------------------------------------------
# Good runs: read-only, hashes, format independence, exact count conversion
# ------------------------------------------------------------------------------------------------------------
def _snapshot(root: Path) -> dict:
    out = {}
    for p in sorted(root.rglob("*")):
        st = p.stat()
        digest = hashlib.sha256(p.read_bytes()).hexdigest() if p.is_file() else None
        out[str(p.relative_to(root))] = (p.is_file(), st.st_size, st.st_mtime_ns, stat.S_IMODE(st.st_mode), digest)
    return out


def test_ingest_never_modifies_the_raw_folder(run_dir):
    landing = run_dir.parents[1]
    before = _snapshot(landing)
    ingest_run(run_dir)
    assert _snapshot(landing) == before


def test_ingest_from_read_only_folder(run_dir, sim):
    landing = run_dir.parents[1]
    paths = sorted(landing.rglob("*"), reverse=True) + [landing]
    modes = {p: stat.S_IMODE(p.stat().st_mode) for p in paths}
    try:
        for p in paths:
            p.chmod(0o555 if p.is_dir() else 0o444)
        before = _snapshot(landing)
        if os.geteuid() != 0:  # root ignores permission bits, so only check they bite for normal users
            with pytest.raises(PermissionError):
                (run_dir / "probe").write_text("x")
        r = ingest_run(run_dir)
        assert len(r.imu) == len(sim.imu_raw)
        assert _snapshot(landing) == before
    finally:
        for p in reversed(paths):
            p.chmod(modes[p])


def test_file_hashes_equal_hashlib(run_dir):
    r = ingest_run(run_dir)
    files = sorted(p for p in run_dir.iterdir() if p.is_file())
    assert sorted(r.file_sha256) == [p.name for p in files]
    for p in files:
        assert r.file_sha256[p.name] == hashlib.sha256(p.read_bytes()).hexdigest()
    assert r.run_dir == str(run_dir)


def test_csv_and_parquet_give_identical_frames(sim, tmp_path):
    # CSV written with round-trip float formatting, so both files hold the same numbers
    d_csv = _write(sim, tmp_path / "a", "parquet")
    for stem, df in (("imu", sim.imu_raw), ("table", sim.table_raw)):
        (d_csv / f"{stem}.parquet").unlink()
        df.to_csv(d_csv / f"{stem}.csv", index=False)
    d_pq = _write(sim, tmp_path / "b", "parquet")
    a, b = ingest_run(d_csv), ingest_run(d_pq)
    pd.testing.assert_frame_equal(a.imu, b.imu, check_exact=True)
    pd.testing.assert_frame_equal(a.table, b.table, check_exact=True)
    assert a.manifest == b.manifest


def test_simulator_csv_and_parquet_imu_frames_identical(sim, tmp_path):
    a = ingest_run(_write(sim, tmp_path / "a", "csv"))
    b = ingest_run(_write(sim, tmp_path / "b", "parquet"))
    pd.testing.assert_frame_equal(a.imu, b.imu, check_exact=True)


def test_counts_convert_back_exactly(run_dir, sim):
    r = ingest_run(run_dir)
    canon_names = dict(zip(IMU_CHANNELS, CANONICAL_IMU_SCHEMA.names[1:7]))
    for ch in IMU_CHANNELS:
        spec = r.manifest.channels[ch]
        assert spec.unit == "counts"
        lsb_si = spec.lsb * si_factor(family_of(ch), spec.lsb_unit)
        counts = sim.imu_raw[ch].to_numpy()
        back = r.imu[canon_names[ch]].to_numpy() / lsb_si
        assert np.array_equal(np.rint(back).astype(np.int64), counts)
        assert np.all(np.abs(back - counts) <= np.spacing(np.abs(counts).astype(float)))
    assert np.array_equal(r.imu["counter"].to_numpy(dtype=np.int64), sim.imu_raw["counter"].to_numpy())
    np.testing.assert_array_equal(r.imu["time_s"].to_numpy(), sim.imu_raw["time_s"].to_numpy())


def test_table_converted_to_si(run_dir, sim):
    r = ingest_run(run_dir)
    np.testing.assert_allclose(r.table["angle_rad"], np.radians(sim.table_raw["angle_deg"]), rtol=1e-8, atol=1e-12)
    np.testing.assert_allclose(r.table["rate_radps"], np.radians(sim.table_raw["rate_dps"]), rtol=1e-8, atol=1e-12)
    assert np.array_equal(r.table["step_index"].to_numpy(), sim.table_raw["step_index"].to_numpy())

