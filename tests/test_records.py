"""Audited calibration records: the real pipeline (Dagster, in process) on a small simulated archive, then
``imulab verify`` on good and tampered records, archives and chains."""

from __future__ import annotations

import json
import re
import shutil
import tempfile
import warnings
from datetime import datetime, timedelta, timezone
from pathlib import Path

import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq
import pytest
from click.testing import CliRunner

from assets_lib.sim.simulator import example_device, simulate_run, write_run
from assets_lib.records import (
    SCHEMA_PATH,
    StoreView,
    build_device_records,
    canonical_json,
    chain_problems,
    content_sha256,
    load_record,
    load_records_dir,
    record_file_bytes,
)
from assets_lib.store import VersionedStore

DEVICE = "TAC-007"
RUNS = ("pc00-rate", "pc01-rate", "pc02-rate")


@pytest.fixture(scope="module")
def lab():
    """3 power-cycled rate runs of one tactical device, weekly, through the real pipeline (per-run and per-device
    jobs, as ``imulab run`` launches them), on tmpfs when there is one (fsync is slow on this disk)."""
    warnings.filterwarnings("ignore")
    shm = Path("/dev/shm")
    root = Path(tempfile.mkdtemp(prefix="imulab-records-", dir=shm if shm.is_dir() else None))
    landing, store = root / "landing", root / "store"
    base = example_device(DEVICE, "tactical", 11)
    t0 = datetime(2026, 2, 2, 8, tzinfo=timezone.utc)
    for c, run_id in enumerate(RUNS):
        truth = base.for_power_cycle(c, 11, 7.0 * c)
        write_run(simulate_run(truth, "quick_rate", run_id, power_cycle_index=c, start_time_utc=t0 + timedelta(days=7 * c),
                               seed=11, plan_kwargs={"duration_scale": 0.3}), landing)
    from pipelines.definitions import build_definitions
    from pipelines.launch import execute, open_instance, register_landed_runs
    from pipelines.resources import LabArchive

    defs = build_definitions(str(landing), str(store))
    with open_instance(root / "dagster_home") as inst:
        register_landed_runs(inst, LabArchive(landing_dir=str(landing)))
        summary = execute(defs, inst, "calibrate_captures", "captures")
        execute(defs, inst, "calibrate_devices", "devices", summary=summary)
    dev_runs = [r for r in summary.runs if r[0] == "calibrate_devices"]
    assert dev_runs and all(ok for _, _, ok in dev_runs), summary.runs
    st = VersionedStore(store)
    vdir = st.version_dir("calibration_record", DEVICE)
    yield {"root": root, "landing": landing, "store": store, "st": st, "vdir": vdir, "defs": defs,
           "dagster_run_ids": [rid for _, rid, _ in dev_runs]}
    shutil.rmtree(root, ignore_errors=True)


def _verify(*args):
    from imulab.cli import main

    return CliRunner().invoke(main, ["verify", *map(str, args)], catch_exceptions=False)


# ------------------------------------------------------------------------------------------------ the records
def test_records_stored_and_chained(lab):
    st, vdir = lab["st"], lab["vdir"]
    table = st.read("calibration_record", DEVICE, "records")
    assert list(table["run_id"]) == list(RUNS)  # ordered by start time
    assert pd.isna(table["prev_record_sha256"].iloc[0])
    assert list(table["prev_record_sha256"].iloc[1:]) == list(table["record_sha256"].iloc[:-1])
    for row in table.itertuples():
        rec = load_record(vdir / f"{row.run_id}.json")
        assert rec["record_schema_version"] == "1.0"
        assert rec["record_sha256"] == row.record_sha256 == content_sha256(rec["content"])
        assert rec["provenance"]["dagster_run_id"] in lab["dagster_run_ids"]
        c = rec["content"]
        assert set(c["raw_files"]) == {"imu.parquet", "table.parquet", "manifest.json", "_COMPLETE"}
        ing = st.read_meta("ingested_run", f"{DEVICE}__{row.run_id}")
        assert c["raw_files"] == ing["file_sha256"]
        assert c["test_conditions"]["plan"]["name"] and c["test_conditions"]["plan"]["n_steps"] > 10
        assert 9.79 < c["test_conditions"]["gravity_mps2"] < 9.80
        t = c["test_conditions"]["temperature_degc"]
        assert t["min"] < t["mean"] < t["max"]
        coef = st.read("gyro_rate_fit", f"{DEVICE}__{row.run_id}", "coefficients")
        rec_bias = {(r["axis"]): r["value"] for r in c["coefficients"] if r["coefficient"] == "bias"}
        assert rec_bias == dict(zip(coef.loc[coef.coefficient == "bias", "axis"],
                                    coef.loc[coef.coefficient == "bias", "value"]))
        assert {"ingested_run", "plateaus", "gyro_rate_fit"} <= set(c["stages"])
        assert len(c["software"]["git_commit"]) in (7, 40, 64) or c["software"]["git_commit"] == "unknown"
    assert chain_problems(*load_records_dir(vdir)) == []


def test_canonical_json_is_stable():
    obj = {"b": [1.0, 0.1, -0.0, 1e-300, 2.5e17], "a": {"z": None, "y": "é"}, "n": float("nan")}
    text = canonical_json(obj)
    assert text == '{"a":{"y":"é","z":null},"b":[1.0,0.1,-0.0,1e-300,2.5e+17],"n":null}'.encode()
    assert canonical_json(json.loads(text)) == text  # parse -> serialize is the identity


def test_record_json_validates_against_schema(lab):
    jsonschema = pytest.importorskip("jsonschema")
    schema = json.loads(SCHEMA_PATH.read_text())
    jsonschema.Draft202012Validator.check_schema(schema)
    v = jsonschema.Draft202012Validator(schema)
    rec = load_record(lab["vdir"] / f"{RUNS[1]}.json")
    assert list(v.iter_errors(rec)) == []
    broken = json.loads(json.dumps(rec))
    broken["content"]["coefficients"][0]["stderr"] = -1.0
    del broken["content"]["raw_files"]
    assert len(list(v.iter_errors(broken))) >= 2


def test_certificate_html_has_coefficients_and_plots(lab):
    html = (lab["vdir"] / f"{RUNS[1]}.html").read_text(encoding="utf-8")
    rec = load_record(lab["vdir"] / f"{RUNS[1]}.json")
    assert rec["record_sha256"] in html and rec["content"]["prev_record_sha256"] in html
    shown = [c for c in rec["content"]["coefficients"] if c["observable"]]
    assert len(shown) >= 12
    for c in shown:
        assert repr(c["value"]) in html and f"{c['value_lab']:.7g}" in html
    assert re.search(r"<img [^>]*src='data:image/png;base64,iVBORw0KGgo", html)  # an embedded PNG (residuals)
    assert "gyro_rate_fit" in html and "deg/h" in html and "ppm" in html


def test_rebuild_reuses_unchanged_records_byte_for_byte(lab):
    """Idempotency: rebuilding a device's records later, by another run, reuses every unchanged record (same
    hash, creation time and bytes); only a changed record (and the links after it) is re-certified."""
    st, vdir = lab["st"], lab["vdir"]
    previous, _ = load_records_dir(vdir)
    meta = st.read_meta("calibration_record", DEVICE)
    view = StoreView(st, dict(meta["inputs"]))
    keys = [k.split("/", 1)[1] for k in meta["inputs"] if k.startswith("ingested_run/")]
    again = build_device_records(view, keys, previous, created_utc="2099-01-01T00:00:00Z", dagster_run_id="other")
    assert all(reused for _, reused in again)
    for rec, _ in again:
        assert record_file_bytes(rec) == (vdir / f"{rec['content']['run']['run_id']}.json").read_bytes()
    fresh = build_device_records(view, keys, {}, software={"imulab_version": "9", "git_commit": "unknown",
                                                           "git_dirty": None},
                                 created_utc="2099-01-01T00:00:00Z", dagster_run_id="other")
    assert not any(reused for _, reused in fresh)
    assert fresh[0][0]["record_sha256"] != again[0][0]["record_sha256"]  # software is certified, hence hashed
    assert fresh[1][0]["content"]["prev_record_sha256"] == fresh[0][0]["record_sha256"]
    strip = lambda r: {k: v for k, v in r["content"].items() if k not in ("software", "prev_record_sha256")}  # noqa: E731
    assert [strip(r) for r, _ in fresh] == [strip(r) for r, _ in again]
    # and the pipeline itself: a second materialization writes nothing new
    versions_before = st.versions("calibration_record", DEVICE)
    from pipelines.launch import execute, open_instance

    with open_instance(lab["root"] / "dagster_home") as inst:
        s = execute(lab["defs"], inst, "calibrate_devices", "devices")
    assert s.success and st.versions("calibration_record", DEVICE) == versions_before


# ------------------------------------------------------------------------------------------------- verification
def test_good_record_verifies(lab):
    res = _verify(lab["vdir"] / f"{RUNS[1]}.json", "--archive", lab["landing"], "--store", lab["store"])
    assert res.exit_code == 0, res.output
    assert "VERIFIED" in res.output and "earlier record pc00-rate verifies" in res.output
    assert "FAIL" not in res.output


def test_tampered_coefficient_fails_naming_it(lab, tmp_path):
    rec = load_record(lab["vdir"] / f"{RUNS[2]}.json")
    row = next(c for c in rec["content"]["coefficients"] if c["coefficient"] == "bias" and c["axis"] == "y")
    recorded = row["value"]
    row["value"] = recorded * 1.001
    # a careful forger also re-hashes the record: the recomputation and the stored chain still catch it
    rec["record_sha256"] = content_sha256(rec["content"])
    forged = tmp_path / f"{RUNS[2]}.json"
    forged.write_bytes(record_file_bytes(rec))
    res = _verify(forged, "--archive", lab["landing"], "--store", lab["store"], "--shallow")
    assert res.exit_code == 1, res.output
    assert f"coefficient gyro_rate_fit/gyro_y/bias: value recorded {recorded * 1.001!r}, recomputed {recorded!r}" \
        in res.output
    assert "the stored chain's record of run pc02-rate has sha256" in res.output
    # edited without re-hashing: the record's own hash names the edit as well
    rec["record_sha256"] = load_record(lab["vdir"] / f"{RUNS[2]}.json")["record_sha256"]
    forged.write_bytes(record_file_bytes(rec))
    res = _verify(forged, "--archive", lab["landing"], "--store", lab["store"], "--shallow")
    assert res.exit_code == 1 and "the record was edited" in res.output
    assert "gyro_rate_fit/gyro_y/bias" in res.output


def test_tampered_raw_file_fails_naming_it(lab, tmp_path):
    archive = tmp_path / "landing"
    shutil.copytree(lab["landing"], archive)
    imu = archive / DEVICE / RUNS[1] / "imu.parquet"
    df = pd.read_parquet(imu)
    df.loc[len(df) // 2, "gyro_x"] += 1  # one sample, one count
    pq.write_table(pa.Table.from_pandas(df, preserve_index=False), imu)
    res = _verify(lab["vdir"] / f"{RUNS[1]}.json", "--archive", archive, "--store", lab["store"], "--shallow")
    assert res.exit_code == 1, res.output
    assert re.search(r"FAIL raw file imu\.parquet: recorded sha256 [0-9a-f]{64}, archive file has [0-9a-f]{64}",
                     res.output)
    assert "raw file table.parquet" not in res.output  # only the changed file is named
    # an earlier run's file changed: verifying a later record names it through the chain
    res = _verify(lab["vdir"] / f"{RUNS[2]}.json", "--archive", archive, "--store", lab["store"], "--shallow")
    assert res.exit_code == 1 and "earlier record pc01-rate: raw file imu.parquet" in res.output


def test_deleted_record_in_the_middle_is_detected(lab, tmp_path):
    copy = tmp_path / "records"
    shutil.copytree(lab["vdir"], copy)
    (copy / f"{RUNS[1]}.json").unlink()
    recs, listing = load_records_dir(copy)
    problems = chain_problems(recs, listing)
    assert any("record of run pc01-rate is missing" in p for p in problems)
    assert any("chain link broken before run pc02-rate" in p and "run pc01-rate (missing)" in p for p in problems)
    res = _verify(copy / f"{RUNS[2]}.json", "--archive", lab["landing"], "--store", lab["store"], "--shallow")
    assert res.exit_code == 1, res.output
    assert "record of run pc01-rate is missing" in res.output and "chain link broken before run pc02-rate" in res.output
    # the first record has no predecessor: it still verifies on its own
    res = _verify(copy / f"{RUNS[0]}.json", "--archive", lab["landing"], "--store", lab["store"], "--shallow")
    assert res.exit_code == 0, res.output


def test_chain_check_blocks_on_a_deleted_record(lab, tmp_path):
    """The Dagster check (blocking) on a store whose current version lost a record: the device run fails and
    the check names the run."""
    import dagster as dg

    from pipelines.definitions import build_definitions

    store = tmp_path / "store"
    shutil.copytree(lab["store"], store)
    vdir = VersionedStore(store).version_dir("calibration_record", DEVICE)
    (vdir / f"{RUNS[1]}.json").unlink()
    defs = build_definitions(str(lab["landing"]), str(store))
    job = defs.resolve_job_def("calibrate_devices")
    with dg.instance_for_test() as inst:
        inst.add_dynamic_partitions("devices", [DEVICE])
        res = job.execute_in_process(instance=inst, partition_key=DEVICE, raise_on_error=False)
        assert not res.success  # blocking with ERROR severity: the device run fails (``imulab run`` exits 1)
        evals = [e.event_specific_data for e in res.all_events if e.event_type_value == "ASSET_CHECK_EVALUATION"]
    chain = [e for e in evals if e.check_name == "record_chain_intact"]
    assert chain and not chain[0].passed
    assert "pc01-rate" in chain[0].metadata["problems"].value
