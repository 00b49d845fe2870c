"""Applying a calibration: exact inverse of the sensor model, z-scores of a record applied to another run of the
same device, the device calibration assembled from records at a date, and ``imulab apply`` on files."""

from __future__ import annotations

import json
from datetime import timedelta

import numpy as np
import pandas as pd
import pytest
from click.testing import CliRunner

from assets_lib.apply import (
    assemble,
    calibration_from_record,
    correct,
    correct_frame,
    correction_stderr,
    forward,
)
from assets_lib.apply.files import read_calibration_metadata
from assets_lib.apply.model import (
    Calibration,
    CalibrationError,
    Triad,
    calibration_from_json,
)
from assets_lib.sim.simulator import example_device, simulate_run, write_run
from imulab.cli import main
from raw_schemas.readers import ingest_run
from tests.record_factory import T0, fitted_record, plateaus_of, write_store_records

G = [f"gyro_{a}_radps" for a in "xyz"]
A = [f"accel_{a}_mps2" for a in "xyz"]
OMEGA = [f"omega_ref_{a}_radps" for a in "xyz"]
FORCE = [f"f_ref_{a}_mps2" for a in "xyz"]


@pytest.fixture(scope="module")
def device():
    """One tactical device, one power cycle: rate and 24-position runs fitted (run A), as records."""
    truth = example_device("TAC-Z01", "tactical", 5).for_power_cycle(0, 5)
    rate, _, _ = fitted_record(truth, "quick_rate", "a-rate", 1, T0)
    pos, _, _ = fitted_record(truth, "quick_24_position", "a-pos24", 1, T0 + timedelta(hours=1))
    return {"truth": truth, "records": [rate, pos], "cal": assemble([rate, pos], T0 + timedelta(days=1))}


def test_correct_inverts_the_model_with_every_term():
    rng = np.random.default_rng(3)
    tri = lambda: Triad(1 + 1e-3 * rng.standard_normal(3), 1e-3 * (rng.standard_normal((3, 3)) * (1 - np.eye(3))),
                        1e-2 * rng.standard_normal(3), np.zeros(3), np.zeros((3, 3)), np.zeros(3))
    g, a = tri(), tri()
    g = Triad(**{**g.__dict__, "g_sensitivity": 1e-4 * rng.standard_normal((3, 3))})
    a = Triad(**{**a.__dict__, "k2": 1e-4 * rng.standard_normal(3), "cross_coupling": 1e-4 * rng.standard_normal((3, 3)) * (1 - np.eye(3))})
    cal = Calibration("X", g, a, (), (), (), (), (), None, None, None)
    w, f = rng.standard_normal((500, 3)), 15 * rng.standard_normal((500, 3))
    y = forward(cal, w, f)
    c = correct(cal, y.gyro_radps, y.accel_mps2)
    assert np.abs(c.accel_mps2 - f).max() < 1e-12 * 15 * 10
    assert np.abs(c.gyro_radps - w).max() < 1e-13 * 10
    # and the inverse is not the identity: the raw outputs differ from the truth by far more
    assert np.abs(y.accel_mps2 - f).max() > 1e-2


def _z(cal, p, sensor):
    p = p[~p["flagged"].astype(bool)]
    yg, ya = p[[c + "_mean" for c in G]].to_numpy(), p[[c + "_mean" for c in A]].to_numpy()
    c, s = correct(cal, yg, ya), correction_stderr(cal, yg, ya)
    if sensor == "gyro":
        ref, sem, got, unc = p[OMEGA].to_numpy(), p[[c_ + "_sem" for c_ in G]].to_numpy(), c.gyro_radps, s.gyro_radps
    else:
        ref, sem, got, unc = p[FORCE].to_numpy(), p[[c_ + "_sem" for c_ in A]].to_numpy(), c.accel_mps2, s.accel_mps2
    return ((got - ref) / np.sqrt(sem**2 + unc**2)).ravel()


def test_record_applied_to_other_runs_of_the_device_gives_unit_z_scores(device):
    """Runs B (same device and power cycle, other noise): rate plateaus for the gyro, 24 positions for the accel
    (static: the accel model is nonlinear, so only static plateau means invert exactly), 3 seeds."""
    cal = device["cal"]
    nominal = Calibration(cal.device_id, Triad.nominal(), Triad.nominal(), (), (), (), (), (), None, None, None)
    zs = {"gyro": [], "accel": []}
    z_nominal = []
    for seed in (11, 12, 13):
        for plan, sensor in (("quick_rate", "gyro"), ("quick_24_position", "accel")):
            p = plateaus_of(simulate_run(device["truth"], plan, f"b-{seed}", seed=seed))
            zs[sensor].append(_z(cal, p, sensor))
            z_nominal.append(_z(nominal, p, sensor))
    for sensor, parts in zs.items():
        z = np.concatenate(parts)
        assert len(z) > 200
        assert 0.8 < z.std() < 1.25, (sensor, z.std())
        assert abs(z.mean()) < 0.35, (sensor, z.mean())
    # the same check without the calibration fails by orders of magnitude
    assert np.concatenate(z_nominal).std() > 30


def test_assemble_takes_each_group_from_the_newest_record_holding_it(device):
    truth = device["truth"]
    rate2, _, _ = fitted_record(truth, "quick_rate", "c-rate", 2, T0 + timedelta(days=7))
    recs = device["records"] + [rate2]
    before = assemble(recs, T0 + timedelta(days=3))
    after = assemble(recs, T0 + timedelta(days=8))
    src = lambda cal: {t.group: t.run_id for t in cal.terms}
    assert src(before) == {"gyro_scale_misalignment": "a-rate", "gyro_bias_g": "a-pos24", "accel": "a-pos24"}
    assert src(after) == {"gyro_scale_misalignment": "c-rate", "gyro_bias_g": "a-pos24", "accel": "a-pos24"}
    assert after.missing_groups == ("noise",)
    assert {r["run_id"] for r in after.records} == {"c-rate", "a-pos24"}
    with pytest.raises(CalibrationError, match="no record started at or before"):
        assemble(recs, T0 - timedelta(days=1))
    # a single rate record: gyro bias from the rate fit (b + G f_bar), accel nominal and named missing
    one = calibration_from_record(rate2)
    assert one.missing_groups == ("accel", "noise")
    assert one.identity_sha256 == rate2["record_sha256"]
    # device calibration file round trip, and an edited file is refused
    doc = json.loads(json.dumps(after.to_json()))
    back = calibration_from_json(doc)
    assert back.identity_sha256 == after.identity_sha256
    np.testing.assert_array_equal(back.gyro.matrix(), after.gyro.matrix())
    doc["terms"][0]["value"] += 1e-3
    with pytest.raises(CalibrationError, match="edited"):
        calibration_from_json(doc)


def test_record_units_are_checked(device):
    rec = json.loads(json.dumps(device["records"][0]))
    row = next(c for c in rec["content"]["coefficients"] if c["coefficient"] == "bias")
    row["unit"] = "deg/h"
    with pytest.raises(CalibrationError, match=r"expected SI unit 'rad/s', found 'deg/h'"):
        calibration_from_record(rec)


def test_imulab_apply_on_files(device, tmp_path):
    truth = device["truth"]
    landing = tmp_path / "landing"
    run_dir = write_run(simulate_run(truth, "quick_24_position", "d-pos24", seed=21, plan_kwargs={"duration_scale": 0.2}),
                        landing)
    other = write_run(simulate_run(example_device("NAV-Z02", "navigation", 5), "quick_24_position", "d-pos24", seed=21,
                                   plan_kwargs={"duration_scale": 0.2}), landing)
    vdir = write_store_records(tmp_path / "store", device["records"])
    rec = vdir / "a-pos24.json"
    runner = CliRunner()
    out = tmp_path / "cal.parquet"
    r = runner.invoke(main, ["apply", str(rec), str(run_dir), "--out", str(out)])
    assert r.exit_code == 0, r.output
    meta = read_calibration_metadata(out)
    assert meta["calibration_sha256"] == device["records"][1]["record_sha256"]
    assert meta["records"][0]["store_version"] == "v0001" and meta["records"][0]["run_id"] == "a-pos24"
    assert meta["records"][0]["record_schema_version"] == "1.0" and meta["record_schema_versions"] == ["1.0"]
    assert meta["input"]["sha256"]["imu.parquet"] and meta["missing_groups"] == ["gyro_scale_misalignment", "noise"]
    got = pd.read_parquet(out)
    want = correct_frame(calibration_from_record(device["records"][1]), ingest_run(run_dir).imu)
    np.testing.assert_array_equal(got[G + A].to_numpy(), want[G + A].to_numpy())
    # calibrated static accel norms sit closer to local gravity than the raw ones
    raw = ingest_run(run_dir).imu
    g0 = 9.7966
    assert np.median(np.abs(np.linalg.norm(got[A], axis=1) - g0)) < 0.5 * np.median(np.abs(np.linalg.norm(raw[A], axis=1) - g0))

    # another device: refused, then forced
    r = runner.invoke(main, ["apply", str(rec), str(other), "--out", str(tmp_path / "x.parquet")])
    assert r.exit_code == 1 and "for device 'TAC-Z01'" in r.output and "'NAV-Z02'" in r.output
    assert not (tmp_path / "x.parquet").exists()
    r = runner.invoke(main, ["apply", str(rec), str(other), "--out", str(tmp_path / "x.parquet"), "--force"])
    assert r.exit_code == 0 and "NAV-Z02" in read_calibration_metadata(tmp_path / "x.parquet")["warnings"][0]

    # a raw stream without its manifest: counts cannot be told from SI
    lone = tmp_path / "lone"
    lone.mkdir()
    (lone / "imu.parquet").write_bytes((run_dir / "imu.parquet").read_bytes())
    r = runner.invoke(main, ["apply", str(rec), str(lone / "imu.parquet"), "--out", str(tmp_path / "y.parquet")])
    assert r.exit_code == 1 and "imu.parquet" in r.output and "manifest.json" in r.output
    # ... with the manifest given it works
    r = runner.invoke(main, ["apply", str(rec), str(lone / "imu.parquet"), "--manifest", str(run_dir / "manifest.json"),
                             "--out", str(tmp_path / "y.parquet")])
    assert r.exit_code == 0, r.output
    # a canonical SI table holding counts: caught by the gravity check, column named
    bad = ingest_run(run_dir).imu.copy()
    bad[A] = pd.read_parquet(run_dir / "imu.parquet")[["accel_x", "accel_y", "accel_z"]].to_numpy(float)
    bad.to_parquet(lone / "canon.parquet")
    r = runner.invoke(main, ["apply", str(rec), str(lone / "canon.parquet"), "--device", "TAC-Z01", "--out",
                             str(tmp_path / "z.parquet")])
    assert r.exit_code == 1 and "accel_x_mps2" in r.output and "raw counts" in r.output
    # a good canonical table without a manifest needs the device stated
    ingest_run(run_dir).imu.to_parquet(lone / "si.parquet")
    r = runner.invoke(main, ["apply", str(rec), str(lone / "si.parquet"), "--out", str(tmp_path / "z.parquet")])
    assert r.exit_code == 1 and "--device TAC-Z01" in r.output
    r = runner.invoke(main, ["apply", str(rec), str(lone / "si.parquet"), "--device", "TAC-Z01", "--out",
                             str(tmp_path / "z.parquet")])
    assert r.exit_code == 0, r.output
