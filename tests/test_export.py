"""Exports round-trip: imucal loads ours with its own loader and calibrates like ``correct``; Kalibr/OpenVINS noise
values follow the tools' continuous-time convention (checked with the Allan deviation of data discretized the way
Kalibr does); OpenVINS intrinsics reproduce our model in both of its conventions; the firmware JSON / C header
procedure reproduces ``correct``."""

from __future__ import annotations

import json
import math
import re
from dataclasses import replace
from datetime import timedelta

import numpy as np
import pytest
import yaml
from click.testing import CliRunner

from assets_lib.apply import assemble, correct, forward
from assets_lib.apply.model import CalibrationError
from assets_lib.noise.allan import oadev
from assets_lib.records.export import export, openvins_intrinsics
from assets_lib.sim.simulator import example_device
from imulab.cli import main
from tests.record_factory import (
    T0,
    fitted_record,
    make_record,
    noise_rows,
)

N_G, K_G, N_A, K_A_UB = 2.5e-4, 3e-6, 5e-4, 4e-5


@pytest.fixture(scope="module")
def cal():
    truth = example_device("TAC-E01", "tactical", 9).for_power_cycle(0, 9)
    rate, _, _ = fitted_record(truth, "quick_rate", "a-rate", 1, T0)
    pos, run, _ = fitted_record(truth, "quick_24_position", "a-pos24", 1, T0 + timedelta(hours=1))
    static = make_record(run, None, noise_rows(N_G, K_G, N_A, K_A_UB))
    static["content"]["run"].update(run_id="a-static", test_kind="static",
                                    start_time_utc=(T0 + timedelta(hours=2)).isoformat())
    static = make_record_like(static)
    return assemble([rate, pos, static], T0 + timedelta(days=1))


def make_record_like(rec):
    """Re-hash an edited test record (its content changed after make_record)."""
    import hashlib

    rec["record_sha256"] = hashlib.sha256(json.dumps(rec["content"], sort_keys=True, separators=(",", ":"),
                                                     allow_nan=False).encode()).hexdigest()
    return rec


def _io(cal, n=400, seed=1):
    rng = np.random.default_rng(seed)
    w, f = 2 * rng.standard_normal((n, 3)), 9.8 * rng.standard_normal((n, 3))
    y = forward(cal, w, f)
    return w, f, y


def linear_only(cal):
    """The calibration without the accelerometer's second-order terms (what imucal and OpenVINS can hold)."""
    return replace(cal, accel=replace(cal.accel, k2=np.zeros(3), cross_coupling=np.zeros((3, 3))))


def test_imucal_loads_our_export_and_calibrates_like_apply(cal, tmp_path):
    from imucal import TurntableCalibrationInfo
    from imucal.management import load_calibration_info

    p = tmp_path / "imucal.json"
    p.write_text(export(cal, "imucal"))
    info = load_calibration_info(p)
    assert isinstance(info, TurntableCalibrationInfo)
    assert cal.identity_sha256 in info.comment
    _, f, y = _io(cal)
    acc, gyr = info.calibrate(y.accel_mps2, y.gyro_radps, acc_unit="m/s^2", gyr_unit="rad/s")
    lin = correct(linear_only(cal), y.gyro_radps, y.accel_mps2)
    np.testing.assert_allclose(acc, lin.accel_mps2, rtol=0, atol=1e-12)
    np.testing.assert_allclose(gyr, lin.gyro_radps, rtol=0, atol=1e-13)
    # the full calibration differs from imucal's only by the second-order terms imucal cannot hold (named in comment)
    full = correct(cal, y.gyro_radps, y.accel_mps2)
    a = cal.accel
    second = (a.k2 * f**2 + f * (f @ a.cross_coupling.T)) @ np.linalg.inv(a.matrix()).T
    np.testing.assert_allclose(acc - full.accel_mps2, second, rtol=0, atol=2e-3 * np.abs(second).max())
    assert np.abs(second).max() > 1e-4
    assert "K2" in info.comment
    # imucal refuses data in other units, as its contract says
    with pytest.raises(ValueError):
        info.calibrate(y.accel_mps2, y.gyro_radps, acc_unit="g", gyr_unit="rad/s")


def test_kalibr_noise_values_and_their_discretization(cal):
    doc = yaml.safe_load(export(cal, "kalibr"))
    assert doc["update_rate"] == 100.0
    # largest axis: N * 1.02 (noise_rows scales axes by 1, 1.01, 1.02); K identified * 1.2; accel K: upper bound * 1.2
    assert doc["gyroscope_noise_density"] == pytest.approx(N_G * 1.02, rel=1e-12)
    assert doc["gyroscope_random_walk"] == pytest.approx(K_G * 1.2, rel=1e-12)
    assert doc["accelerometer_noise_density"] == pytest.approx(N_A * 1.02, rel=1e-12)
    assert doc["accelerometer_random_walk"] == pytest.approx(K_A_UB * 1.2, rel=1e-12)
    assert "upper bound" in export(cal, "kalibr")
    # Kalibr's discretization (sigma_d = density * sqrt(rate), bias step = random_walk / sqrt(rate)) applied to
    # generated data: the Allan deviation gives back the exported densities (IEEE 952 Annex C: N at tau = 1 s,
    # K from sigma(tau) = K sqrt(tau / 3))
    rate = doc["update_rate"]
    nd, rw = doc["gyroscope_noise_density"], doc["gyroscope_random_walk"]
    rng = np.random.default_rng(4)
    white = nd * math.sqrt(rate) * rng.standard_normal(400_000)
    r = oadev(white, rate, taus=[1.0])
    assert r.adev[0] == pytest.approx(nd, rel=0.02)
    walk = np.cumsum(rw / math.sqrt(rate) * rng.standard_normal(400_000))
    r = oadev(walk, rate, taus=[100.0])
    assert r.adev[0] / math.sqrt(100.0 / 3) == pytest.approx(rw, rel=0.15)
    # a calibration without noise terms cannot be exported to Kalibr
    with pytest.raises(CalibrationError, match="no noise terms"):
        export(replace(cal, noise=()), "kalibr")


@pytest.mark.parametrize("model", ["kalibr", "rpng"])
def test_openvins_intrinsics_reproduce_the_model(cal, model):
    text = export(cal, "openvins" if model == "kalibr" else "openvins-rpng")
    assert text.startswith("%YAML:1.0\n")
    doc = yaml.safe_load(text.split("\n", 1)[1])["imu0"]
    assert doc["model"] == model
    m = {k: np.array(doc[k], dtype=float) for k in ("Tw", "R_IMUtoGYRO", "Ta", "R_IMUtoACC", "Tg")}
    tri = np.tril if model == "kalibr" else np.triu
    np.testing.assert_array_equal(m["Tw"], tri(m["Tw"]))
    np.testing.assert_array_equal(m["Ta"], tri(m["Ta"]))
    np.testing.assert_array_equal(m["R_IMUtoACC" if model == "kalibr" else "R_IMUtoGYRO"], np.eye(3))
    for k in ("R_IMUtoGYRO", "R_IMUtoACC"):
        np.testing.assert_allclose(m[k] @ m[k].T, np.eye(3), atol=1e-14)
        assert np.linalg.det(m[k]) == pytest.approx(1.0)
    dw = [float(v) for v in re.findall(r"Dw = Tw\^-1 row \d: \[([^\]]*)\]", text) for v in v.split(",")]
    np.testing.assert_allclose(np.reshape(dw, (3, 3)) @ m["Tw"], np.eye(3), atol=1e-13)
    np.testing.assert_array_equal(np.reshape(dw, (3, 3)), tri(np.reshape(dw, (3, 3))))  # Dw keeps the structure
    r_b2i = openvins_intrinsics(cal, model)["R_BODYtoIMU"]
    rows = [float(v) for v in re.findall(r"R_BODYtoIMU row \d: \[([^\]]*)\]", text) for v in v.split(",")]
    np.testing.assert_allclose(np.reshape(rows, (3, 3)), r_b2i, rtol=0, atol=1e-14)
    # OpenVINS' measurement model with these matrices, fed the true inputs in its IMU frame, gives our model's outputs
    lin = linear_only(cal)
    w, f, y = _io(lin)
    w_i, f_i = w @ r_b2i.T, f @ r_b2i.T
    wm = w_i @ (m["Tw"] @ m["R_IMUtoGYRO"]).T + f_i @ m["Tg"].T + cal.gyro.bias
    am = f_i @ (m["Ta"] @ m["R_IMUtoACC"]).T + cal.accel.bias
    np.testing.assert_allclose(wm, y.gyro_radps, rtol=0, atol=1e-13)
    np.testing.assert_allclose(am, y.accel_mps2, rtol=0, atol=1e-12)


def _c_arrays(text):
    out = {}
    for name, body in re.findall(r"static const double (\w+)\[3\](?:\[3\])? = \{(.*?)\};", text, flags=re.DOTALL):
        out[name.replace("IMULAB_", "")] = np.array([float(v) for v in re.findall(r"[-+0-9.eE]+", body)]).reshape(
            (3, 3) if body.count("{") else (3,))
    out["ACC_ITERATIONS"] = int(re.search(r"#define IMULAB_ACC_ITERATIONS (\d+)", text).group(1))
    return out


def _firmware(d, yg, ya):
    """The documented firmware procedure, step by step."""
    f = (ya - d["ACC_BIAS"]) @ np.asarray(d["ACC_MAT"]).T
    for _ in range(d["ACC_ITERATIONS"]):
        f = (ya - d["ACC_BIAS"] - d["ACC_K2"] * f**2 - f * (f @ np.asarray(d["ACC_KC"]).T)) @ np.asarray(d["ACC_MAT"]).T
    w = (yg - d["GYR_BIAS"] - f @ np.asarray(d["GYR_GSENS"]).T) @ np.asarray(d["GYR_MAT"]).T
    return w, f


def test_firmware_json_and_c_header_reproduce_apply(cal):
    _, _, y = _io(cal)
    want = correct(cal, y.gyro_radps, y.accel_mps2)
    js = json.loads(export(cal, "firmware-json"))
    hdr = export(cal, "c-header")
    assert cal.identity_sha256 in hdr and js["calibration_sha256"] == cal.identity_sha256
    for d in ({k: (np.asarray(v) if isinstance(v, list) else v) for k, v in js.items()}, _c_arrays(hdr)):
        w, f = _firmware(d, y.gyro_radps, y.accel_mps2)
        np.testing.assert_allclose(f, want.accel_mps2, rtol=0, atol=1e-11)
        np.testing.assert_allclose(w, want.gyro_radps, rtol=0, atol=1e-12)
    # the header is valid C: it compiles when a compiler is available
    import shutil
    import subprocess
    import tempfile
    from pathlib import Path

    cc = shutil.which("cc") or shutil.which("gcc")
    if cc:
        with tempfile.TemporaryDirectory() as t:
            (Path(t) / "cal.h").write_text(hdr)
            (Path(t) / "main.c").write_text('#include "cal.h"\nint main(void){return IMULAB_ACC_MAT[0][0] > 0 ? 0 : 1;}\n')
            r = subprocess.run([cc, "-Wall", "-Werror", "-Wno-unused-const-variable", "-o", str(Path(t) / "a"),
                                str(Path(t) / "main.c")], capture_output=True, text=True)
            assert r.returncode == 0, r.stderr
            assert subprocess.run([str(Path(t) / "a")]).returncode == 0


def test_imulab_export_command(cal, tmp_path):
    p = tmp_path / "cal.json"
    p.write_text(json.dumps(cal.to_json()))
    runner = CliRunner()
    for fmt in ("kalibr", "openvins", "openvins-rpng", "imucal", "firmware-json", "c-header"):
        out = tmp_path / f"out.{fmt}"
        r = runner.invoke(main, ["export", str(p), "--format", fmt, "--out", str(out)])
        assert r.exit_code == 0, (fmt, r.output)
        assert cal.identity_sha256 in out.read_text()
    r = runner.invoke(main, ["export", str(p), "--format", "vins"])
    assert r.exit_code == 2


def test_imucal_example_session_through_our_apply_and_export(shared_data, tmp_path):
    """Real data: imucal's reference calibration of its annotated example session (raw counts, shared/data
    imucal_example), taken into our model, applied by ``correct``, and exported back: imucal's own calibrate()
    with its file, with our export, and our apply give the same numbers."""
    import pandas as pd
    from imucal.management import load_calibration_info

    from assets_lib.records.export import calibration_from_imucal

    d = shared_data / "imucal_example"
    ref = load_calibration_info(d / "example_cal.json")
    ours = calibration_from_imucal(json.loads((d / "example_cal.json").read_text()), "imucal-example")
    df = pd.read_csv(d / "annotated_session.csv")
    acc = df[["acc_x", "acc_y", "acc_z"]].to_numpy(float)
    gyr = df[["gyr_x", "gyr_y", "gyr_z"]].to_numpy(float)
    a_ref, g_ref = ref.calibrate(acc, gyr, acc_unit="a.u.", gyr_unit="a.u.")
    c = correct(ours, gyr, acc)
    np.testing.assert_allclose(c.accel_mps2, a_ref, rtol=1e-10, atol=1e-10)
    np.testing.assert_allclose(c.gyro_radps, g_ref, rtol=1e-10, atol=1e-9)  # deg/s here (imucal's output unit)
    p = tmp_path / "ours.json"
    p.write_text(export(ours, "imucal"))
    back = load_calibration_info(p)
    a2, g2 = back.calibrate(acc, gyr, acc_unit="a.u.", gyr_unit="a.u.")
    np.testing.assert_allclose(a2, a_ref, rtol=1e-10, atol=1e-10)
    np.testing.assert_allclose(g2, g_ref, rtol=1e-10, atol=1e-9)
    # sanity: the calibrated static sections read 1 g along the named axis (9.81 in imucal's convention)
    xp = df["part"] == "x_p"
    assert np.median(c.accel_mps2[xp.to_numpy(), 0]) == pytest.approx(9.81, abs=0.02)


def test_imulab_ferraris_record_of_imucal_session_calibrates_alike_in_imucal_and_imulab(shared_data, tmp_path):
    """Real data, imulab's own record: imucal's example session (raw counts, shared/data imucal_example) imported
    (``imulab import imucal``: counts -> SI by the declared lsb), fitted by imulab's Ferraris path
    (``calibrate_tablefree`` -> ``coefficient_table``, the ``tablefree_fit`` stage), made into a record, exported
    to imucal's JSON and loaded by imucal's own loader: imucal's calibrate() and ``imulab apply`` give the same
    numbers on the whole session. And both agree with imucal's own reference calibration of the session (its
    example_cal.json) to within what separates the two fits' models."""
    from types import SimpleNamespace

    import pandas as pd
    from imucal.management import load_calibration_info

    from assets_lib.apply import calibration_from_record, correct_frame
    from assets_lib.calibration.tablefree_session import (
        calibrate_tablefree,
        coefficient_table,
    )
    from raw_schemas.importers import RunMeta, import_run
    from raw_schemas.readers import ingest_run
    from raw_schemas.tables import ACCEL_COLUMNS, GYRO_COLUMNS

    d = shared_data / "imucal_example"
    landing = import_run("imucal", [d / "annotated_session.csv"], tmp_path / "land", RunMeta("bmi160", "ferraris1"),
                         {"sample_rate_hz": "204.8", "accel_lsb": str(1 / 2048), "gyro_lsb": str(1 / 16.4)})
    run = ingest_run(landing)
    res = calibrate_tablefree(run.manifest, run.imu, 9.81)
    assert res.method == "ferraris"
    coef = coefficient_table(res, "bmi160", "ferraris1", len(run.imu))
    rec = make_record(SimpleNamespace(manifest=run.manifest, imu_raw=run.imu), None)
    rec["content"]["coefficients"] = [
        {**{k: (None if isinstance(v, float) and not math.isfinite(v) else (v.item() if hasattr(v, "item") else v))
            for k, v in r.items() if k in ("sensor", "axis", "coefficient", "value", "stderr", "unit", "value_lab",
                                           "stderr_lab", "unit_lab", "observable", "n_plateaus", "n_samples",
                                           "method")}, "source": "tablefree_fit"}
        for r in coef.to_dict(orient="records")]
    rec = make_record_like(rec)
    cal = calibration_from_record(rec)
    assert cal.missing_groups == ("noise",) and len(cal.terms) == 2 * (3 + 3 + 6) + 9

    # imulab apply (the Python API behind the command) on the ingested session
    ours = correct_frame(cal, run.imu)
    # imucal, with our export loaded by its own loader, on the same SI data
    p = tmp_path / "imucal.json"
    p.write_text(export(cal, "imucal"))
    theirs = load_calibration_info(p)
    acc, gyr = run.imu[list(ACCEL_COLUMNS)].to_numpy(float), run.imu[list(GYRO_COLUMNS)].to_numpy(float)
    a_imucal, g_imucal = theirs.calibrate(acc, gyr, acc_unit="m/s^2", gyr_unit="rad/s")
    np.testing.assert_allclose(a_imucal, ours[list(ACCEL_COLUMNS)].to_numpy(), rtol=1e-10, atol=1e-10)
    np.testing.assert_allclose(g_imucal, ours[list(GYRO_COLUMNS)].to_numpy(), rtol=1e-10, atol=1e-12)
    # the numbers are a calibration, not the identity: the raw session differs from them
    assert np.abs(a_imucal - acc).max() > 0.05

    # imucal's own reference calibration of the session (counts -> m/s^2, deg/s): the same accelerations to the
    # size of what the record's model leaves out (imucal's R rows are unit vectors, our E is R - I: second order
    # in the misalignments), the same rates up to the rotation-sense convention imucal keeps in R_g's sign
    # (on the session's counts in the ingested row order: the declared lsb undone)
    ref = load_calibration_info(d / "example_cal.json")
    counts_a, counts_g = acc / (9.80665 / 2048), np.degrees(gyr) * 16.4
    assert np.abs(counts_a - np.round(counts_a)).max() < 1e-6 and len(counts_a) == len(pd.read_csv(d / "annotated_session.csv"))
    a_ref, g_ref = ref.calibrate(counts_a, counts_g, acc_unit="a.u.", gyr_unit="a.u.")
    a_ours = ours[list(ACCEL_COLUMNS)].to_numpy()
    g_ours_dps = np.degrees(ours[list(GYRO_COLUMNS)].to_numpy())
    misal = max(np.abs(np.asarray(ref.R_a) - np.diag(np.diag(ref.R_a))).max(), 1e-6)
    assert np.abs(a_ours - a_ref).max() < 10 * misal**2 * 9.81 + 1e-6, (np.abs(a_ours - a_ref).max(), misal)
    sign = np.sign(np.diag(ref.R_g))
    scale = np.abs(g_ref).max()
    assert np.abs(g_ours_dps * sign - g_ref).max() < 1e-3 * scale, np.abs(g_ours_dps * sign - g_ref).max() / scale
