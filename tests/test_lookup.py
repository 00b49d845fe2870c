"""Looking a calibration up by date: the record valid at a date, the device calibration assembled there, and the
staleness and fleet-drift warnings (drift tables computed by the real fleet-drift code, stored like the pipeline)."""

from __future__ import annotations

import json
from dataclasses import replace
from datetime import timedelta
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from click.testing import CliRunner

from assets_lib.apply.model import CalibrationError, load_calibration
from assets_lib.fleet.drift import fleet_drift
from assets_lib.records.lookup import drift_flags, lookup
from assets_lib.sim.simulator import example_device
from imulab.cli import main
from tests.record_factory import T0, coefficients_of, fitted_record, write_store_records

DEV = "TAC-L01"


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    """A rate run and four weekly 24-position runs; the accelerometer x bias jumps by 5 mg at the fourth."""
    root = tmp_path_factory.mktemp("lookup") / "store"
    base = example_device(DEV, "tactical", 3)
    records, coefs, times = [], [], []
    for c in range(4):
        truth = base.for_power_cycle(c, 3, 7 * c)
        if c == 3:
            truth = replace(truth, accel=replace(truth.accel, bias=tuple(np.array(truth.accel.bias) + [0.049, 0, 0])))
        start = T0 + timedelta(days=7 * c)
        plans = [("quick_rate", "rate")] if c == 0 else []
        for plan, tag in plans + [("quick_24_position", "pos24")]:
            rid = f"pc{c:02d}-{tag}"
            st = start + timedelta(hours=0 if tag == "rate" else 1)
            rec, run, p = fitted_record(truth, plan, rid, 1, st, power_cycle_index=c)
            records.append(rec)
            coefs.append(coefficients_of(p, run.manifest.test_kind).assign(
                device_id=DEV, run_id=rid, source="gyro_rate_fit" if tag == "rate" else "accel_multiposition_fit"))
            times.append({"device_id": DEV, "run_id": rid, "start_time_utc": st.isoformat()})
    write_store_records(root, records)
    fd = fleet_drift(pd.concat(coefs, ignore_index=True), pd.DataFrame(times))
    d = root / "fleet_drift" / "fleet" / "v0001"
    d.mkdir(parents=True)
    fd.series_table().to_parquet(d / "drift.parquet")
    fd.points_table().to_parquet(d / "drift_points.parquet")
    (d.parent / "CURRENT").write_text("v0001")
    return root


def test_valid_record_and_groups_at_a_date(store):
    r = lookup(store, DEV, T0 + timedelta(days=8), max_age_days=365)
    assert r.valid_run_id == "pc01-pos24"
    assert list(r.table["run_id"]) == ["pc00-rate", "pc00-pos24", "pc01-pos24", "pc02-pos24", "pc03-pos24"]
    src = {t.group: t.run_id for t in r.calibration.terms}
    assert src == {"gyro_scale_misalignment": "pc00-rate", "gyro_bias_g": "pc01-pos24", "accel": "pc01-pos24"}
    assert any("holds noise" in w for w in r.warnings)
    assert not any("days old" in w for w in r.warnings)
    with pytest.raises(CalibrationError, match="no calibration records of device 'NOPE'"):
        lookup(store, "NOPE")


def test_staleness_warning(store):
    r = lookup(store, DEV, T0 + timedelta(days=60), max_age_days=30)
    old = [w for w in r.warnings if "days old" in w]
    # pc03-pos24 (accel, gyro bias; 39 days) and pc00-rate (gyro scale; 60 days) are both past 30 days
    assert len(old) == 2 and any("pc00-rate" in w and "60.0 days" in w for w in old)
    assert not [w for w in lookup(store, DEV, T0 + timedelta(days=60), max_age_days=90).warnings if "days old" in w]


def test_drift_warnings_only_for_events_after_the_calibration_used(store):
    ev = drift_flags(store, DEV)
    assert len(ev) and (ev["kind"] != "").all()
    at = T0 + timedelta(days=15)  # valid: pc02-pos24 (accel, gyro bias) and pc00-rate (gyro scale)
    r = lookup(store, DEV, at, max_age_days=365)
    since = T0  # pc00-rate is the oldest record whose terms are used
    want = ev[(ev["start_time_utc"] >= since) & (ev["start_time_utc"] <= at)]
    got = [w for w in r.warnings if w.startswith("fleet drift flagged")]
    assert len(got) == len(want)
    # the jump of run pc03 is flagged for accel x bias, and only a lookup after that run warns about it
    assert ((ev["run_id"] == "pc03-pos24") & (ev["axis"] == "x") & (ev["coefficient"] == "bias")).any()
    assert not any("pc03-pos24" in w for w in got)
    later = lookup(store, DEV, T0 + timedelta(days=22), max_age_days=365)
    assert any("accel x bias" in w and "pc03-pos24" in w for w in later.warnings)


def test_records_command(store, tmp_path):
    runner = CliRunner()
    out = tmp_path / "cal.json"
    r = runner.invoke(main, ["records", DEV, "--store", str(store), "--at", (T0 + timedelta(days=8)).isoformat(),
                             "--max-age", "365", "--out", str(out)])
    assert r.exit_code == 0, r.output
    valid_lines = [ln for ln in r.output.splitlines() if "<- valid" in ln]
    assert len(valid_lines) == 1 and valid_lines[0].split()[0] == "pc01-pos24"
    cal = load_calibration(out)
    assert cal.device_id == DEV and cal.at_utc.startswith((T0 + timedelta(days=8)).date().isoformat())
    assert json.loads(out.read_text())["calibration_sha256"] == cal.identity_sha256
    r = runner.invoke(main, ["records", DEV, "--store", str(store), "--at", (T0 + timedelta(days=60)).isoformat(),
                             "--strict"])
    assert r.exit_code == 1 and "days old" in r.output


BACKGROUND_JOBS = ("real_pipeline_store",)  # run in a second process from the start of the session (tests/conftest.py)


def real_pipeline_store(work: Path) -> None:
    """Rate, 24-position and static runs of one device (short plans) in ``work / "landing"``, through the Dagster
    pipeline (per-run and per-device jobs, as ``imulab run`` launches them) into ``work / "store"``."""
    import warnings

    from assets_lib.sim.simulator import simulate_run, write_run
    from pipelines.definitions import build_definitions
    from pipelines.launch import execute, open_instance, register_landed_runs
    from pipelines.resources import LabArchive

    warnings.filterwarnings("ignore")
    landing, store = work / "landing", work / "store"
    truth = example_device("TAC-P01", "tactical", 8)
    for plan, rid, h, kw in (("quick_rate", "pc00-rate", 0, {"plan_kwargs": {"duration_scale": 0.3}}),
                             ("quick_24_position", "pc00-pos24", 1, {"plan_kwargs": {"duration_scale": 0.3}}),
                             ("static_long", "pc00-static", 2, {"table_log": False,
                                                                "plan_kwargs": {"static_duration_s": 600.0}})):
        write_run(simulate_run(truth, plan, rid, start_time_utc=T0 + timedelta(hours=h), seed=8, **kw), landing)
    defs = build_definitions(str(landing), str(store))
    with open_instance(work / "dagster_home") as inst:
        register_landed_runs(inst, LabArchive(landing_dir=str(landing)))
        summary = execute(defs, inst, "calibrate_captures", "captures")
        execute(defs, inst, "calibrate_devices", "devices", summary=summary)


@pytest.mark.slow
def test_real_pipeline_records_are_used_end_to_end(background_job, tmp_path):
    """The records the Dagster pipeline writes (rate, 24-position and static runs of one device, short plans; this
    module's background job ``real_pipeline_store``): looked up, applied to a run folder, exported to Kalibr and
    imucal."""
    import yaml

    from assets_lib.apply.files import read_calibration_metadata

    work = background_job("real_pipeline_store")
    landing, store = work / "landing", work / "store"
    r = lookup(store, "TAC-P01", T0 + timedelta(days=1), max_age_days=30)
    assert {t.group: t.run_id for t in r.calibration.terms} == {
        "gyro_scale_misalignment": "pc00-rate", "gyro_bias_g": "pc00-pos24", "accel": "pc00-pos24"}
    assert r.calibration.missing_groups == () and r.calibration.noise
    runner = CliRunner()
    cal_json = tmp_path / "cal.json"
    res = runner.invoke(main, ["records", "TAC-P01", "--store", str(store), "--at", (T0 + timedelta(days=1)).isoformat(),
                               "--out", str(cal_json)])
    assert res.exit_code == 0, res.output
    res = runner.invoke(main, ["apply", str(cal_json), str(landing / "TAC-P01" / "pc00-pos24"), "--out",
                               str(tmp_path / "cal.parquet")])
    assert res.exit_code == 0, res.output
    meta = read_calibration_metadata(tmp_path / "cal.parquet")
    assert meta["calibration_sha256"] == json.loads(cal_json.read_text())["calibration_sha256"]
    res = runner.invoke(main, ["export", str(cal_json), "--format", "kalibr", "--out", str(tmp_path / "imu.yaml")])
    assert res.exit_code == 0, res.output
    doc = yaml.safe_load((tmp_path / "imu.yaml").read_text())
    # the tactical device's white noise (simulator truth: 0.15 deg/sqrt(h) gyro, 0.03/60 m/s^2/sqrt(Hz) accel)
    assert doc["gyroscope_noise_density"] == pytest.approx(np.radians(0.15) / 60, rel=0.1)
    assert doc["accelerometer_noise_density"] == pytest.approx(0.03 / 60, rel=0.1)
    res = runner.invoke(main, ["export", str(cal_json), "--format", "imucal", "--out", str(tmp_path / "imucal.json")])
    assert res.exit_code == 0, res.output
    from imucal.management import load_calibration_info

    assert load_calibration_info(tmp_path / "imucal.json").K_a.shape == (3, 3)
