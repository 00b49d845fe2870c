"""Table-free calibration against published references (imucal's example_cal.json, imu_tk's Xsens demo output)
and against simulated hand-placed sessions with known truth."""

from __future__ import annotations

import json

import numpy as np
import pytest

from assets_lib.calibration.ferraris import ferraris_fit
from assets_lib.calibration.gyro_integration import fit_gyro_integration
from assets_lib.calibration.outliers import estimate_resolution, reject_outliers_window
from assets_lib.calibration.poses import detect_static_poses
from assets_lib.calibration.tablefree import fit_accel_poses, pose_means, static_norm_rms
from assets_lib.calibration.tablefree_session import calibrate_tablefree
from assets_lib.sim.hand_poses import simulate_hand_session
from raw_schemas.importers import ImportedDataWarning, RunMeta, import_run
from raw_schemas.readers import ingest_run

# imu_tk demo output on the Xsens files (REFERENCE.txt)
IMUTK_ACC_T = np.array([[1, -0.0033593, -0.00890639], [0, 1, -0.0213341], [0, 0, 1]])
IMUTK_ACC_K = np.array([0.00241278, 0.00242712, 0.00241168])
IMUTK_ACC_B = np.array([33124.2, 33275.2, 32364.4])
IMUTK_GYRO_T = np.array([[1, 0.00593634, 0.00111101], [0.00808812, 1, -0.0535569], [0.0253067, -0.0025513, 1]])
IMUTK_GYRO_K = np.array([0.000209295, 0.000209899, 0.000209483])
GYRO_BIAS_COUNTS = np.array([32777.150460, 32459.816527, 32511.848940])
G_IMUTK = 9.81744
ACC_LSB, GYRO_LSB = 0.0024, 1 / 6258  # nominal values declared at import; results are converted back to counts


@pytest.fixture(scope="module")
def xsens_run(shared_data, tmp_path_factory):
    d = shared_data / "imu_tk_xsens"
    land = tmp_path_factory.mktemp("land")
    # the counts are read without their mid-scale zero on purpose (results compare with imu_tk's biases in
    # counts), which the import flags (docs/realdata.md sec. 1)
    with pytest.warns(ImportedDataWarning) as caught:
        out = import_run("imu_tk", [d / "xsens_acc.mat", d / "xsens_gyro.mat"], land, RunMeta("xsens", "demo"),
                         {"accel_lsb": str(ACC_LSB), "gyro_lsb": str(GYRO_LSB), "initial_static_s": "50"})
    assert sorted(str(w.message).split(":")[0] for w in caught) == ["xsens_acc.mat", "xsens_gyro.mat"]
    run = ingest_run(out)
    return run, calibrate_tablefree(run.manifest, run.imu, G_IMUTK)


def test_xsens_static_poses_found(xsens_run):
    _, res = xsens_run
    assert res.method == "tedaldi"
    assert 38 <= res.poses.count <= 42  # the initial interval + about 38 hand-placed poses (imu_tk needs >= 12)


def test_xsens_gyro_bias_is_initial_interval_mean(xsens_run):
    _, res = xsens_run
    b_counts = np.array([res.coefficients[f"gyro_b_{a}"].value for a in "xyz"]) / GYRO_LSB
    np.testing.assert_allclose(b_counts, GYRO_BIAS_COUNTS, rtol=0, atol=1e-5)


def test_xsens_accel_fit_no_worse_than_imu_tk_on_same_windows(xsens_run):
    run, res = xsens_run
    acc_counts = run.imu[["accel_x_mps2", "accel_y_mps2", "accel_z_mps2"]].to_numpy() / ACC_LSB
    t = run.imu.time_s.to_numpy()
    m = pose_means(t, acc_counts, res.poses.starts, res.poses.ends, 100)
    ours = static_norm_rms(res.accel_fit.T, res.accel_fit.scale * ACC_LSB, res.accel_fit.bias / ACC_LSB, m, G_IMUTK)
    theirs = static_norm_rms(IMUTK_ACC_T, IMUTK_ACC_K, IMUTK_ACC_B, m, G_IMUTK)
    assert ours <= theirs
    assert ours < 0.003  # ~0.0016 m/s^2: the misalignment model (a scale-only model leaves ~0.04)
    # and the parameters agree with imu_tk's within the data file's stated tolerances
    np.testing.assert_allclose(res.accel_fit.scale * ACC_LSB, IMUTK_ACC_K, rtol=5e-4)
    np.testing.assert_allclose(res.accel_fit.T, IMUTK_ACC_T, atol=2e-3)
    np.testing.assert_allclose(res.accel_fit.bias / ACC_LSB, IMUTK_ACC_B, atol=3.0)


def test_xsens_gyro_scale_and_misalignment_agree_with_imu_tk_within_uncertainty(xsens_run):
    _, res = xsens_run
    c = res.coefficients
    for i, a in enumerate("xyz"):
        k = c[f"gyro_k_{a}"]
        z = (k.value * GYRO_LSB - IMUTK_GYRO_K[i]) / (k.stderr * GYRO_LSB)
        assert abs(z) < 3.0, (a, z)
    for name, (i, j) in {"t01": (0, 1), "t02": (0, 2), "t10": (1, 0), "t12": (1, 2), "t20": (2, 0), "t21": (2, 1)}.items():
        co = c[f"gyro_{name}"]
        assert abs(co.value - IMUTK_GYRO_T[i, j]) < 3.0 * co.stderr, (name, co.value, IMUTK_GYRO_T[i, j], co.stderr)
    assert res.diagnostics["unobservable"] == []


def test_scale_only_model_is_clearly_worse_on_xsens(xsens_run):
    run, res = xsens_run
    t = run.imu.time_s.to_numpy()
    acc = run.imu[["accel_x_mps2", "accel_y_mps2", "accel_z_mps2"]].to_numpy()
    m = pose_means(t, acc, res.poses.starts, res.poses.ends, 100)
    rms_scale_only = static_norm_rms(np.eye(3), res.accel_fit.scale, res.accel_fit.bias, m, G_IMUTK)
    assert rms_scale_only > 5 * res.accel_fit.rms_mps2


def test_ferraris_reproduces_imucal_example_cal(shared_data):
    import pandas as pd

    df = pd.read_csv(shared_data / "imucal_example" / "annotated_session.csv")
    sec = {p: (g[["acc_x", "acc_y", "acc_z"]].to_numpy(), g[["gyr_x", "gyr_y", "gyr_z"]].to_numpy()) for p, g in df.groupby("part")}
    fit = ferraris_fit(sec, 204.8, gravity=9.81, expected_angle_deg=-360.0)
    ref = json.loads((shared_data / "imucal_example" / "example_cal.json").read_text())
    for k in ("K_a", "R_a", "b_a", "K_g", "R_g", "K_ga", "b_g"):
        ours, theirs = np.asarray(getattr(fit, k)), np.asarray(ref[k])
        np.testing.assert_allclose(ours, theirs, rtol=1e-6, atol=1e-6 * np.abs(theirs).max(), err_msg=k)
        assert np.all(np.isfinite(fit.stderr[k])) and np.all(fit.stderr[k] >= 0)
    # the rotations integrate to ~+360 deg against the expected -360: R_g's diagonal carries the sign
    assert np.all(np.diag(fit.R_g) < -0.99)


def test_ferraris_through_import_and_session(shared_data, tmp_path):
    """imulab import imucal ... then the table-free session picks Ferraris; converting the imported canonical
    values back to counts gives imucal's numbers again."""
    src = shared_data / "imucal_example" / "annotated_session.csv"
    out = import_run("imucal", [src], tmp_path, RunMeta("bmi160", "s1"),
                     {"sample_rate_hz": "204.8", "accel_lsb": str(1 / 2048), "gyro_lsb": str(1 / 16.4)})
    run = ingest_run(out)
    res = calibrate_tablefree(run.manifest, run.imu, 9.81)
    assert res.method == "ferraris"
    ref = json.loads((shared_data / "imucal_example" / "example_cal.json").read_text())
    acc_lsb_si = 9.80665 / 2048  # canonical m/s^2 per count
    gyr_lsb_deg = 1 / 16.4
    # K_a (canonical per m/s^2) = K_a(counts per m/s^2) * lsb; b_a (canonical) = b_a(counts) * lsb
    np.testing.assert_allclose(np.diag(res.accel_fit.K_a), np.diag(ref["K_a"]) * acc_lsb_si, rtol=1e-9)
    np.testing.assert_allclose(res.accel_fit.b_a, np.asarray(ref["b_a"]) * acc_lsb_si, rtol=1e-9)
    np.testing.assert_allclose(np.diag(res.gyro_fit.K_g), np.diag(ref["K_g"]) * gyr_lsb_deg, rtol=1e-9)
    np.testing.assert_allclose(res.gyro_fit.R_g, ref["R_g"], rtol=1e-9, atol=1e-12)
    assert res.diagnostics["static_norm_rms_mps2"] < 0.05


def _truth_vec(tr):
    a = {"t01": tr["accel_T"][0, 1], "t02": tr["accel_T"][0, 2], "t12": tr["accel_T"][1, 2],
         "k_x": tr["accel_k"][0], "k_y": tr["accel_k"][1], "k_z": tr["accel_k"][2],
         "b_x": tr["accel_b"][0], "b_y": tr["accel_b"][1], "b_z": tr["accel_b"][2]}
    T = tr["gyro_T"]
    g = {"t01": T[0, 1], "t02": T[0, 2], "t10": T[1, 0], "t12": T[1, 2], "t20": T[2, 0], "t21": T[2, 1],
         "k_x": tr["gyro_k"][0], "k_y": tr["gyro_k"][1], "k_z": tr["gyro_k"][2]}
    return a, g


def test_simulated_hand_session_recovers_truth_within_uncertainty():
    zs = []
    for seed in range(4):
        s = simulate_hand_session(np.random.default_rng(seed))
        ref = slice(0, int(s.initial_static_s * 100))
        p = detect_static_poses(s.t_s, s.accel, k=6, reference=ref)
        assert p.count == 30
        m = pose_means(s.t_s, s.accel, p.starts, p.ends)
        af = fit_accel_poses(m, 9.81)
        gf = fit_gyro_integration(s.t_s, s.gyro, p.starts, p.ends, af.apply(m), s.gyro[ref].mean(0), scale_start=np.ones(3))
        ta, tg = _truth_vec(s.truth)
        zs += [(c.value - ta[n]) / c.stderr for n, c in af.coefficients.items()]
        zs += [(c.value - tg[n]) / c.stderr for n, c in gf.coefficients.items()]
    zs = np.asarray(zs)
    assert np.all(np.isfinite(zs))
    assert np.max(np.abs(zs)) < 4.5
    assert 0.5 < np.std(zs) < 1.6  # standard errors of the right size (not 10x too wide or too narrow)


def test_tablefree_intervals_use_student_t_at_residual_dof():
    """s^2 is estimated from n_poses - 9 (accel) and 2 n_pairs - 9 (gyro) residual dof, so the printed 95 %
    interval is value -/+ t_{0.975, dof} SE ([GUM] G.3), wider than 1.96 SE (coverage ~93.6 % at 21 dof)."""
    from scipy import stats

    s = simulate_hand_session(np.random.default_rng(11))
    ref = slice(0, int(s.initial_static_s * 100))
    p = detect_static_poses(s.t_s, s.accel, k=6, reference=ref)
    m = pose_means(s.t_s, s.accel, p.starts, p.ends)
    af = fit_accel_poses(m, 9.81, n_samples=np.asarray(p.ends) - np.asarray(p.starts))
    gf = fit_gyro_integration(s.t_s, s.gyro, p.starts, p.ends, af.apply(m), s.gyro[ref].mean(0), scale_start=np.ones(3))
    assert af.dof == p.count - 9 and gf.dof == 2 * (p.count - 1) - 9
    for fit in (af, gf):
        k = stats.t.ppf(0.975, fit.dof)
        assert k > 2.0 and fit.k95 == pytest.approx(k)
        for c in fit.coefficients.values():
            lo, hi = c.interval()
            assert (lo, hi) == pytest.approx((c.value - k * c.stderr, c.value + k * c.stderr), rel=1e-12)
    # the fixed bias's uncertainty widens the gyro standard errors (first-order propagation), never narrows them
    gb = fit_gyro_integration(s.t_s, s.gyro, p.starts, p.ends, af.apply(m), s.gyro[ref].mean(0), scale_start=np.ones(3),
                              bias_cov=np.eye(3) * 1e-8)
    se0 = np.array([c.stderr for c in gf.coefficients.values()])
    se1 = np.array([c.stderr for c in gb.coefficients.values()])
    assert np.all(se1 >= se0) and np.any(se1 > 1.01 * se0)
    with pytest.raises(ValueError, match="n_samples"):
        fit_accel_poses(m, 9.81, n_samples=np.ones(len(m) - 1))


def test_single_axis_pose_set_reports_unobservable_terms():
    """Gravity always in the body x-y plane (poses rotated about body z only): the z scale and bias cannot be
    told apart from the pose magnitudes; they are reported unobservable, not fitted to noise."""
    rng = np.random.default_rng(0)
    ang = rng.uniform(0, 2 * np.pi, 20)
    f = 9.81 * np.c_[np.cos(ang), np.sin(ang), np.zeros_like(ang)]  # gravity always in the body x-y plane
    fit = fit_accel_poses(f + 1e-4 * rng.standard_normal(f.shape), 9.81)
    assert "k_z" in fit.unobservable and not fit.coefficients["k_z"].observable
    assert "k_x" not in fit.unobservable and fit.coefficients["k_x"].observable


def test_outliers_do_not_collapse_on_interpolated_quantized_samples():
    """A 0.3-count noise sampled at 27 Hz and linearly interpolated to 100 Hz: the MAD collapses, the repeated
    source levels give the 1-count floor, nothing is rejected (was 33 %)."""
    rng = np.random.default_rng(1)
    n, r = 4000, 3.7
    ns = int(n / r) + 2
    ts = np.arange(ns) * 0.01 * r
    slow = np.rint(0.3 * rng.standard_normal((ns, 3)))
    t = np.arange(n) * 0.01
    y = np.stack([np.interp(t, ts, slow[:, j]) for j in range(3)], 1)
    assert estimate_resolution(y[:, 0]) == pytest.approx(1.0, rel=0.1)
    w = reject_outliers_window(t, y)
    assert w.converged and w.rejected_fraction < 1e-3
    y[2000, 1] = 8.0  # a real spike is still caught
    assert not reject_outliers_window(t, y).keep[2000]


def test_ferraris_second_session_end_to_end_matches_imucal_output(shared_data, tmp_path):
    """example_ferraris_session.csv (102.4 Hz, deg/s and m/s^2) imported with its section list, calibrated from
    its own sections; the first 50 calibrated rows equal imucal's ferraris_example.csv."""
    import pandas as pd

    d = shared_data / "imucal_example"
    out = import_run("imucal", [d / "example_ferraris_session.csv"], tmp_path, RunMeta("bmi160", "s2"),
                     {"sample_rate_hz": "102.4", "sections": str(d / "example_ferraris_session_list.json")})
    run = ingest_run(out)
    assert len(run.imu) == 10376  # every row kept; only the nine sections are steps
    res = calibrate_tablefree(run.manifest, run.imu, 9.81)
    assert res.method == "ferraris"
    imu = run.imu.iloc[:50]
    acc = imu[["accel_x_mps2", "accel_y_mps2", "accel_z_mps2"]].to_numpy()
    gyr = np.degrees(imu[["gyro_x_radps", "gyro_y_radps", "gyro_z_radps"]].to_numpy())
    acc_cal = res.accel_fit.calibrate_acc(acc)
    gyr_cal = res.accel_fit.calibrate_gyr(gyr, acc_cal)
    ref = pd.read_csv(d / "ferraris_example.csv")
    np.testing.assert_allclose(acc_cal, ref[["acc_x", "acc_y", "acc_z"]].to_numpy(), rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(gyr_cal, ref[["gyr_x", "gyr_y", "gyr_z"]].to_numpy(), rtol=1e-9, atol=1e-9)


def test_coefficient_table_rows(xsens_run):
    from assets_lib.calibration.fit_report import COEFFICIENT_COLUMNS
    from assets_lib.calibration.tablefree_session import coefficient_table

    run, res = xsens_run
    t = coefficient_table(res, "xsens", "demo", len(run.imu))
    assert list(t.columns[: len(COEFFICIENT_COLUMNS)]) == COEFFICIENT_COLUMNS
    # accel: 3 scales, 3 biases, 3 misalignments (upper triangle); gyro: 3 + 3 + 6
    assert len(t) == 9 + 12 and t["observable"].all()
    # printed interval = the fit's Student-t interval, wider than the normal one
    ta = t[(t.method == "tedaldi") & (t.coefficient != "bias") | (t.sensor == "accel")]
    half = (ta["ci95_high"] - ta["ci95_low"]) / 2
    np.testing.assert_allclose(half / ta["stderr"], np.where(ta.sensor == "accel", res.accel_fit.k95, res.gyro_fit.k95),
                               rtol=1e-9)
    assert (ta["dof"] > 0).all() and res.accel_fit.k95 > 1.96
    k = t[(t.sensor == "gyro") & (t.coefficient == "scale_factor")].set_index("axis")["value"]
    np.testing.assert_allclose(k.to_numpy() * GYRO_LSB, IMUTK_GYRO_K, rtol=2e-3)


def test_stage_check_names_the_failing_figure():
    from assets_lib.stages.tablefree import fit_problem

    ok = {"gravity_mps2": 9.81, "diagnostics": {"accel_norm_rms_mps2": 0.0014, "unobservable": []}}
    assert fit_problem(ok) is None
    bad = {"gravity_mps2": 9.81, "diagnostics": {"accel_norm_rms_mps2": 0.05, "unobservable": []}}
    assert "static |f| - g RMS 0.05" in fit_problem(bad)
    unobs = {"gravity_mps2": 9.81, "diagnostics": {"static_norm_rms_mps2": 0.001, "unobservable": ["k_z"]}}
    assert "k_z" in fit_problem(unobs)


def test_ferraris_g_sensitivity_row_is_k_ga_at_the_output():
    """The Ferraris gyro g-sensitivity row is imucal's K_ga in rad/s per m/s^2 (design.md: y = K(I+E) w + b + G f,
    G added at the output like the bias; imucal: u_g = K_g R_g w + K_ga a + b_g), so the table's G and bias undo
    imucal's model for a gyro whose scale factor is far from 1 (the row was K_ga / K_g: off by the scale factor)."""
    from assets_lib.calibration.ferraris import FerrarisFit
    from assets_lib.calibration.tablefree_session import TableFreeResult, coefficient_table

    rng = np.random.default_rng(15)
    K_g = np.diag([1.3, 0.8, 1.1])
    R_g = np.eye(3) + 0.01 * rng.standard_normal((3, 3)) * (1 - np.eye(3))
    K_ga = 0.05 * rng.standard_normal((3, 3))  # deg/s per m/s^2
    b_g = rng.standard_normal(3)  # deg/s
    z = np.zeros((3, 3))
    se = {k: np.full(s_, 1e-3) for k, s_ in (("K_a", (3, 3)), ("R_a", (3, 3)), ("b_a", (3,)), ("K_g", (3, 3)),
                                              ("R_g", (3, 3)), ("K_ga", (3, 3)), ("b_g", (3,)))}
    fit = FerrarisFit(np.eye(3), np.eye(3), np.zeros(3), K_g, R_g, K_ga, b_g, se, 9.81, -360.0, "m/s^2", "deg/s",
                      "m/s^2", "deg/s")
    t = coefficient_table(TableFreeResult("ferraris", fit.coefficients(), None, fit, fit), "d", "r", 100)
    g = t[(t.sensor == "gyro")].set_index(["axis", "coefficient"])["value"]
    G = np.array([[g[(a, f"g_sensitivity_{b}")] for b in "xyz"] for a in "xyz"])  # rad/s per m/s^2
    b = np.array([g[(a, "bias")] for a in "xyz"])  # rad/s
    w_dps, acc = 100 * rng.standard_normal((50, 3)), 9.81 * rng.standard_normal((50, 3))
    u = w_dps @ (K_g @ R_g).T + acc @ K_ga.T + b_g  # imucal's forward model, deg/s
    # the output-level terms of the table leave K_g R_g w, which imucal's own calibrate inverts to w
    left = np.radians(u) - b - acc @ G.T
    np.testing.assert_allclose(left, np.radians(w_dps @ (K_g @ R_g).T), rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(fit.calibrate_gyr(u, acc), w_dps, rtol=1e-10, atol=1e-10)
    assert not np.allclose(G, np.radians(K_ga / np.diag(K_g)[:, None]))  # the old row was not this
