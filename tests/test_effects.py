"""Every effect family of the digital twin: inject it into a simulated run, write the raw files, read them back
with the ingestion code, and recover the injected magnitude within the estimator's stated standard error.

Estimators: the project's segmentation (plateau means with correlated-noise SEMs, clock alignment) and rate /
multi-position fits where they estimate the quantity; otherwise a least-squares fit written here from the
family's model equation, its standard error from the residual scatter (white noise) or, for the noise model,
from a parametric bootstrap. Injected magnitudes are 10-100x the standard error, so a missing or wrong-signed
effect fails. Small plans and short records: the whole file runs in well under a minute.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.optimize import curve_fit

from assets_lib.calibration.multiposition import fit_accel_multiposition
from assets_lib.calibration.rate_fit import fit_gyro_rate
from assets_lib.calibration.segmentation import overlapping_avar, segment_run
from assets_lib.sim.effects import EFFECTS, effect_from_dict, sensor_chain
from assets_lib.sim.effects.base import lagged
from assets_lib.sim.effects.stochastic import gauss_markov_avar
from assets_lib.sim.kinematics import body_inputs
from assets_lib.sim.noise import AllanParams
from assets_lib.sim.plans import build_plan
from assets_lib.sim.simulator import (
    DeviceTruth,
    SiteSpec,
    TriadTruth,
    simulate_run,
    write_run,
)
from raw_schemas.readers import ingest_run

FS = 100.0
SITE = SiteSpec()
G = SITE.gravity_mps2
Z = 4.0  # |estimate - truth| / stderr must stay below this
GYRO = ["gyro_x_radps", "gyro_y_radps", "gyro_z_radps"]
ACCEL = ["accel_x_mps2", "accel_y_mps2", "accel_z_mps2"]
ZUP = {"x": "E", "y": "N", "z": "U"}
RATES_DPS = (400, -400, 250, -250, 100, -100, 50, -50, 20, -20, 0)


def device(gyro_n=2e-4, accel_n=2e-4, device_id="TWIN-1") -> DeviceTruth:
    """K = 1, E = 0, b = 0, white noise only (gyro [rad/s/sqrt(Hz)], accel [m/s^2/sqrt(Hz)]), fine counts."""
    zero = ((0.0,) * 3,) * 3
    gyro = TriadTruth((1.0,) * 3, zero, (0.0,) * 3, (AllanParams(n=gyro_n),) * 3, 1e-6, "deg/s")
    accel = TriadTruth((1.0,) * 3, zero, (0.0,) * 3, (AllanParams(n=accel_n),) * 3, 1e-7, "g")
    return DeviceTruth(device_id, "twin test unit", "tactical", gyro, accel, sample_rate_hz=FS)


def rate_plan(rates=RATES_DPS, duration_s=10.0):
    steps = [{"kind": "rate", "axes": ZUP, "table_rate_dps": r, "duration_s": duration_s, "settle_s": 1.0} for r in rates]
    return build_plan({"name": "twin_rate", "frame": "ENU", "transition_s": 3.0, "lead_s": 2.0, "steps": steps})


def static_plan(duration_s: float):
    return build_plan({"name": "twin_static", "frame": "ENU", "lead_s": 0.0,
                       "steps": [{"kind": "static", "axes": ZUP, "duration_s": duration_s, "settle_s": 0.0}]})


POS24 = build_plan("quick_24_position", duration_scale=0.5)


def run_raw(tmp_path, plan, extra, *, kind, run_id="r1", dev=None, seed=1, **kw):
    """Simulate with the extra effect families, write the raw files, ingest them back."""
    dev = dev or device()
    run = simulate_run(dev, plan, run_id, test_kind=kind, effects=sensor_chain(extra), seed=seed,
                       table_log=kind != "static", **kw)
    d = write_run(run, tmp_path / "landing")
    return run, ingest_run(d)


def lstsq(a: np.ndarray, y: np.ndarray, sigma: np.ndarray | None = None):
    """(coefficients, standard errors): weighted least squares with known sigmas, else OLS scaled by residuals."""
    if sigma is not None:
        aw, yw = a / sigma[:, None], y / sigma
        coef, *_ = np.linalg.lstsq(aw, yw, rcond=None)
        cov = np.linalg.inv(aw.T @ aw)
        return coef, np.sqrt(np.diag(cov))
    coef, *_ = np.linalg.lstsq(a, y, rcond=None)
    r = y - a @ coef
    s2 = r @ r / (y.size - a.shape[1])
    return coef, np.sqrt(np.diag(s2 * np.linalg.inv(a.T @ a)))


def fitted(fit, sensor: str, axis: str, name: str) -> tuple[float, float]:
    """(value, stderr) of one coefficient from a fit's tidy coefficient table (docs/design.md contract)."""
    c = fit.coefficient_table()
    r = c[(c.sensor == sensor) & (c.axis == axis) & (c.coefficient == name)]
    assert len(r) == 1 and bool(r.observable.iloc[0]), f"{sensor} {axis} {name} not observable"
    return float(r.value.iloc[0]), float(r.stderr.iloc[0])


def assert_recovered(est, se, truth, what):
    est, se, truth = map(np.atleast_1d, (est, se, truth))
    assert np.all(se > 0) and np.all(np.abs(truth) > 5 * se), f"{what}: injected {truth} not well above stderr {se}"
    z = (est - truth) / se
    assert np.all(np.abs(z) < Z), f"{what}: estimate {est} vs truth {truth}, stderr {se}, z {z}"


def block_means(t, y, seconds=1.0):
    m = int(round(seconds * FS))
    k = t.size // m
    return t[: k * m].reshape(k, m).mean(axis=1), y[: k * m].reshape(k, m, *y.shape[1:]).mean(axis=1)


def plateau_rows(seg):
    p = seg.plateaus
    return p[~p["flagged"].astype(bool) & (p["n_samples"] > 0)]


def window_samples(seg, ing, min_rate_dps=0.0):
    """Kept samples of every plateau turning at least ``min_rate_dps``: (step index per sample, mask)."""
    plan = ing.manifest.plan
    ws = seg.window_step
    fast = np.array([abs(s.table_rate_dps) >= min_rate_dps and s.table_rate_dps != 0 for s in plan.steps])
    m = (ws >= 0) & seg.keep
    m[m] = fast[ws[m]]
    return ws, m


def table_angle_at_imu(seg, ing):
    """Nominal table angle (table log) at the IMU samples, through the segmentation's clock alignment."""
    tab = ing.table
    ang = np.unwrap(tab["angle_rad"].to_numpy())
    return np.interp(ing.imu["time_s"].to_numpy() + seg.alignment.offset_s, tab["time_s"].to_numpy(), ang)


def demean_per_step(y, ws, m):
    out = np.zeros_like(y)
    for k in np.unique(ws[m]):
        s = m & (ws == k)
        out[s] = y[s] - y[s].mean(axis=0)
    return out


# ------------------------------------------------------------------------------------------------------------
def test_registry_round_trips_every_family():
    assert len(EFFECTS) == 15
    for name, cls in EFFECTS.items():
        e = cls()
        assert e.family == name and effect_from_dict(e.to_dict()) == e
    with pytest.raises(ValueError, match="unknown effect family"):
        effect_from_dict({"family": "magnetism", "params": {}})
    with pytest.raises(ValueError, match="unknown parameter"):
        effect_from_dict({"family": "latency", "params": {"delay": 1.0}})


def test_temperature_bias_quadratic_and_lag(tmp_path):
    k1, k2, lag = 1e-4, 5e-6, 30.0
    ka = 2e-4
    eff = EFFECTS["temperature_bias"](gyro_radps_per_k=(k1, 0, 0), gyro_radps_per_k2=(k2, 0, 0),
                                      accel_mps2_per_k=(0, ka, 0), lag_s=lag)
    chamber = lambda t: 25.0 + 8.0 * np.sin(2 * np.pi * t / 300.0) + 2.0  # noqa: E731
    _, ing = run_raw(tmp_path, static_plan(600.0), [eff], kind="static", temperature_degc=chamber)
    t = ing.imu["time_s"].to_numpy()
    temp = ing.imu["temperature_degc"].to_numpy()  # the logged (noisy, rounded) thermometer

    def model(tt, b, a1, a2, tau):
        d = lagged(temp, t, tau) - 25.0
        return block_means(t, b + a1 * d + a2 * d**2)[1]

    tb, yb = block_means(t, ing.imu["gyro_x_radps"].to_numpy())
    p, cov = curve_fit(model, tb, yb, p0=[0.0, 5e-5, 0.0, 10.0])
    se = np.sqrt(np.diag(cov))
    assert_recovered(p[1:], se[1:], [k1, k2, lag], "gyro temperature bias k1, k2, lag")
    ya = block_means(t, ing.imu["accel_y_mps2"].to_numpy())[1]
    pa, cova = curve_fit(lambda tt, b, a1, tau: model(tt, b, a1, 0.0, tau), tb, ya, p0=[0.0, 5e-5, 10.0])
    assert_recovered(pa[1:], np.sqrt(np.diag(cova))[1:], [ka, lag], "accel temperature bias, lag")


def test_temperature_scale_factor(tmp_path):
    s1 = 1e-4  # 0.01 %/K, a MEMS gyro's scale-factor temperature coefficient
    eff = EFFECTS["temperature_scale_factor"](gyro_per_k=(0, 0, s1))
    chamber = lambda t: 25.0 + 8.0 * np.sin(2 * np.pi * t / 97.0)  # noqa: E731
    _, ing = run_raw(tmp_path, rate_plan(), [eff], kind="rate", temperature_degc=chamber)
    p = plateau_rows(segment_run(ing.manifest, ing.imu, ing.table))
    w = p["omega_ref_z_radps"].to_numpy()
    r = p["gyro_z_radps_mean"].to_numpy() - w
    a = np.column_stack([np.ones_like(w), w, w * (p["temperature_degc_mean"].to_numpy() - 25.0)])
    coef, se = lstsq(a, r, p["gyro_z_radps_sem"].to_numpy())
    assert_recovered(coef[2], se[2], s1, "gyro scale-factor temperature coefficient")


def test_warmup_bias_from_power_on(tmp_path):
    amp, tau, amp_a = 5e-4, 120.0, 2e-3
    eff = EFFECTS["warmup_bias"](tau_s=(tau,), gyro_radps=((amp, 0, 0),), accel_mps2=((0, 0, amp_a),))
    _, ing = run_raw(tmp_path, static_plan(600.0), [eff], kind="static")
    t = ing.imu["time_s"].to_numpy()
    tb, yb = block_means(t, ing.imu[["gyro_x_radps", "accel_z_mps2"]].to_numpy())
    f = lambda tt, b, a, ta: b + a * np.exp(-tt / ta)  # noqa: E731
    for j, truth in ((0, amp), (1, amp_a)):
        p, cov = curve_fit(f, tb, yb[:, j], p0=[yb[-1, j], yb[0, j] - yb[-1, j], 60.0])
        assert_recovered(p[1:], np.sqrt(np.diag(cov))[1:], [truth, tau], f"warm-up amplitude and tau ({j})")


def test_warmup_continues_across_runs_of_a_power_cycle(tmp_path):
    """The second run of a cycle, started 300 s after power-on, sees the transient where the first left it."""
    amp, tau = 5e-4, 200.0
    eff = EFFECTS["warmup_bias"](tau_s=(tau,), gyro_radps=((amp, 0, 0),))
    _, ing = run_raw(tmp_path, static_plan(200.0), [eff], kind="static", run_id="late", power_on_s=300.0)
    tb, yb = block_means(ing.imu["time_s"].to_numpy(), ing.imu["gyro_x_radps"].to_numpy() - 0.0)
    _, ing0 = run_raw(tmp_path, static_plan(200.0), [], kind="static", run_id="late")  # same noise, no effect
    _, y0 = block_means(ing0.imu["time_s"].to_numpy(), ing0.imu["gyro_x_radps"].to_numpy())
    coef, se = lstsq(np.exp(-(tb + 300.0) / tau)[:, None], yb - y0)
    assert abs(coef[0] - amp) < 1e-3 * amp  # noise cancels exactly: only counts rounding remains


def test_bias_ramp_is_continuous_across_a_power_cycle(tmp_path):
    rate = 1e-6  # rad/s per s
    eff = EFFECTS["bias_ramp"](gyro_radps_per_s=(0, 0, rate))
    rows, cols = [], []
    for i, (rid, t_on) in enumerate((("a", 0.0), ("b", 500.0))):
        _, ing = run_raw(tmp_path, static_plan(300.0), [eff], kind="static", run_id=rid, power_on_s=t_on)
        tb, yb = block_means(ing.imu["time_s"].to_numpy(), ing.imu["gyro_z_radps"].to_numpy())
        rows.append(np.column_stack([np.full(tb.size, i == 0), np.full(tb.size, i == 1), tb + t_on]).astype(float))
        cols.append(yb)
    coef, se = lstsq(np.vstack(rows), np.concatenate(cols))
    assert_recovered(coef[2], se[2], rate, "bias ramp over the power cycle")
    # one intercept for both runs: the ramp did not restart at the second run
    assert abs(coef[1] - coef[0]) < Z * np.hypot(se[0], se[1])


def test_bias_step_with_settling(tmp_path):
    step, at, settle = 2e-3, 120.0, 15.0
    eff = EFFECTS["bias_step"](at_s=at, gyro_radps=(0, step, 0), accel_mps2=(0, 0, -3e-3), settle_tau_s=settle)
    _, ing = run_raw(tmp_path, static_plan(300.0), [eff], kind="static")
    t = ing.imu["time_s"].to_numpy()
    tb, yb = block_means(t, ing.imu[["gyro_y_radps", "accel_z_mps2"]].to_numpy(), 0.5)
    f = lambda tt, b, d, ta: b + d * np.where(tt >= at, 1 - np.exp(-np.clip(tt - at, 0, None) / ta), 0.0)  # noqa: E731
    for j, truth in ((0, step), (1, -3e-3)):
        p, cov = curve_fit(f, tb, yb[:, j], p0=[0.0, yb[-1, j] - yb[0, j], 5.0])
        assert_recovered(p[1:], np.sqrt(np.diag(cov))[1:], [truth, settle], f"bias step and settling ({j})")


def test_g_sensitivity_linear_and_g_squared(tmp_path):
    g1 = ((2e-4, 0.0, 1e-4), (0.0, -1.5e-4, 0.0), (5e-5, 0.0, 3e-4))
    g2 = np.zeros((3, 6))
    g2[0, 3] = 2e-5  # x gyro: f_x f_y
    g2[2, 0] = -1.5e-5  # z gyro: f_x^2
    eff = EFFECTS["g_sensitivity"](linear_radps_per_mps2=g1, quadratic_radps_per_mps2sq=g2)
    _, ing = run_raw(tmp_path, POS24, [eff], kind="multiposition")
    p = plateau_rows(segment_run(ing.manifest, ing.imu, ing.table))
    f = p[["f_ref_x_mps2", "f_ref_y_mps2", "f_ref_z_mps2"]].to_numpy()
    # f_x^2 + f_y^2 + f_z^2 = g^2 on every position: the zz product is the bias, xx and yy are read against zz
    a = np.column_stack([np.ones(len(p)), f, f[:, 0] ** 2, f[:, 1] ** 2, f[:, 0] * f[:, 1], f[:, 0] * f[:, 2],
                         f[:, 1] * f[:, 2]])
    for i, ax in enumerate("xyz"):
        r = p[f"gyro_{ax}_radps_mean"].to_numpy() - p[f"omega_ref_{ax}_radps"].to_numpy()
        coef, se = lstsq(a, r, p[f"gyro_{ax}_radps_sem"].to_numpy())
        nz = np.abs(np.asarray(g1[i])) > 0
        assert_recovered(coef[1:4][nz], se[1:4][nz], np.asarray(g1[i])[nz], f"g-sensitivity row {ax}")
        assert np.all(np.abs(coef[1:4][~nz]) < Z * se[1:4][~nz])
        quad_truth = np.array([g2[i, 0] - g2[i, 2], g2[i, 1] - g2[i, 2], g2[i, 3], g2[i, 4], g2[i, 5]])
        nq = np.abs(quad_truth) > 0
        if nq.any():
            assert_recovered(coef[4:][nq], se[4:][nq], quad_truth[nq], f"g^2 sensitivity row {ax}")
        assert np.all(np.abs(coef[4:][~nq]) < Z * se[4:][~nq])


def test_scale_factor_nonlinearity_polynomial(tmp_path):
    fs = np.radians(500.0)
    c2, c3 = 1e-3, -1.5e-3
    eff = EFFECTS["scale_factor_nonlinearity"](sensor="gyro", full_scale=fs, quadratic=(0, 0, c2), cubic=(0, 0, c3))
    assert eff.max_deviation_fs()[2] == pytest.approx(abs(c2) + abs(c3), rel=1e-6)  # at -FS both terms add
    _, ing = run_raw(tmp_path, rate_plan(), [eff], kind="rate")
    p = plateau_rows(segment_run(ing.manifest, ing.imu, ing.table))
    w = p["omega_ref_z_radps"].to_numpy()
    a = np.column_stack([np.ones_like(w), w, w**2, w**3])
    coef, se = lstsq(a, p["gyro_z_radps_mean"].to_numpy() - w, p["gyro_z_radps_sem"].to_numpy())
    assert_recovered(coef[2:] * [fs, fs**2], se[2:] * [fs, fs**2], [c2, c3], "polynomial nonlinearity c2, c3")


def test_scale_factor_nonlinearity_compressive(tmp_path):
    fs, dev = np.radians(450.0), 2e-3
    eff = EFFECTS["scale_factor_nonlinearity"](sensor="gyro", full_scale=fs, form="compressive", max_deviation=(0, 0, dev))
    assert eff.max_deviation_fs()[2] == pytest.approx(dev, rel=1e-6)
    _, ing = run_raw(tmp_path, rate_plan(), [eff], kind="rate")
    p = plateau_rows(segment_run(ing.manifest, ing.imu, ing.table))
    w = p["omega_ref_z_radps"].to_numpy()
    r = p["gyro_z_radps_mean"].to_numpy() - w
    f = lambda x, b, u: b + u * fs * np.tanh(x / (u * fs)) - x  # noqa: E731  (u = x_c / FS)
    par, cov = curve_fit(f, w, r, p0=[0.0, 5.0], sigma=p["gyro_z_radps_sem"].to_numpy(), absolute_sigma=True)
    u, su = par[1], np.sqrt(cov[1, 1])
    d = lambda u: 1 - u * np.tanh(1 / u)  # noqa: E731
    est = d(u)
    se = abs((d(u + 1e-6) - d(u - 1e-6)) / 2e-6) * su
    assert_recovered(est, se, dev, "compressive max deviation at full scale")


def test_scale_factor_asymmetry_gyro_and_accel(tmp_path):
    eg, ea = 2e-3, 8e-4  # gyro: the hinge fit now carries the 1/f noise between plateaus (stderr 2e-4)
    eff = EFFECTS["scale_factor_asymmetry"](gyro=(0, 0, eg), accel=(ea, 0, 0))
    _, ing = run_raw(tmp_path, rate_plan(), [eff], kind="rate")
    fit = fit_gyro_rate(segment_run(ing.manifest, ing.imu, ing.table).plateaus)
    assert_recovered(*fitted(fit, "gyro", "z", "sf_asymmetry"), eg, "gyro asymmetry (rate fit, K+ vs K-)")
    _, ing = run_raw(tmp_path, POS24, [eff], kind="multiposition", run_id="p1")
    p = plateau_rows(segment_run(ing.manifest, ing.imu, ing.table))
    f = p[["f_ref_x_mps2", "f_ref_y_mps2", "f_ref_z_mps2"]].to_numpy()
    a = np.column_stack([np.ones(len(p)), f[:, 0], np.abs(f[:, 0]), f[:, 0] ** 2])
    coef, se = lstsq(a, p["accel_x_mps2_mean"].to_numpy() - f[:, 0], p["accel_x_mps2_sem"].to_numpy())
    assert_recovered(2 * coef[2], 2 * se[2], ea, "accel asymmetry (|f| term, with f^2 free)")


def _rate_residual_slope(t, y, u, tt=None):
    """LS delay from y - u(t) = -delay du/dt (u the true input on the table clock, du/dt by differences)."""
    du = np.gradient(u, t, axis=0).ravel()
    r = (y - u).ravel()
    m = np.abs(du) > 1e-3
    coef, se = lstsq(-du[m, None], r[m])
    return coef[0], se[0]


def test_latency_per_triad(tmp_path):
    dg, da = 5e-3, 2e-3
    eff = EFFECTS["latency"](gyro_s=dg, accel_s=da)
    run, ing = run_raw(tmp_path, rate_plan(), [eff], kind="rate")
    t = ing.imu["time_s"].to_numpy()
    bi = body_inputs(ing.manifest.plan, t, SITE.latitude_deg, G)
    est, se = _rate_residual_slope(t, ing.imu[GYRO].to_numpy(), bi.omega_b_radps)
    assert_recovered(est, se, dg, "gyro latency")
    _, ing = run_raw(tmp_path, POS24, [eff], kind="multiposition", run_id="p1")
    t = ing.imu["time_s"].to_numpy()
    bi = body_inputs(ing.manifest.plan, t, SITE.latitude_deg, G)
    est, se = _rate_residual_slope(t, ing.imu[ACCEL].to_numpy(), bi.f_b_mps2)
    assert_recovered(est, se, da, "accel latency")


def test_timebase_error_is_a_common_scale_factor_and_a_clock_drift(tmp_path):
    eps = 2e-4
    eff = EFFECTS["timebase_error"](clock_rate_error=eps)
    _, ing = run_raw(tmp_path, rate_plan(), [eff], kind="rate")
    seg = segment_run(ing.manifest, ing.imu, ing.table)
    v, se = fitted(fit_gyro_rate(seg.plateaus), "gyro", "z", "scale_factor")
    assert_recovered(v - 1, se, 1 / (1 + eps) - 1, "gyro scale factor")
    # t_table = t_imu / (1 + eps) + offset: the offset drifts by -eps / (1 + eps) per IMU second (segmentation's
    # drift statistic, a delay-and-drift fit over the whole record)
    al = seg.alignment
    assert_recovered(al.clock_drift_ppm, al.clock_drift_stderr_ppm, -1e6 * eps / (1 + eps), "clock drift [ppm]")
    _, ing = run_raw(tmp_path, POS24, [eff], kind="multiposition", run_id="p1")
    acc = fit_accel_multiposition(segment_run(ing.manifest, ing.imu, ing.table).plateaus)
    for a in "xyz":
        v, se = fitted(acc, "accel", a, "scale_factor")
        assert_recovered(v - 1, se, 1 / (1 + eps) - 1, f"accel {a} scale factor")


def test_lever_arm_centripetal(tmp_path):
    r = np.array([0.04, -0.03, 0.01])
    eff = EFFECTS["lever_arm"](position_m=tuple(r))
    _, ing = run_raw(tmp_path, rate_plan(), [eff], kind="rate")
    p = plateau_rows(segment_run(ing.manifest, ing.imu, ing.table))
    w = (p[[f"omega_ref_{a}_radps" for a in "xyz"]].to_numpy() - p[[f"omega_earth_{a}_radps" for a in "xyz"]].to_numpy())
    rows, ys, ss = [], [], []
    for k in range(len(p)):
        wx = np.array([[0, -w[k, 2], w[k, 1]], [w[k, 2], 0, -w[k, 0]], [-w[k, 1], w[k, 0], 0]])
        rows.append(wx @ wx)  # w x (w x r) = [w]x^2 r
        ys.append([p.iloc[k][f"accel_{a}_mps2_mean"] - p.iloc[k][f"f_ref_{a}_mps2"] for a in "xyz"])
        ss.append([p.iloc[k][f"accel_{a}_mps2_sem"] for a in "xyz"])
    a, y, s = np.vstack(rows), np.concatenate(ys), np.concatenate(ss)
    a = np.column_stack([a[:, :2], np.tile(np.eye(3), (len(p), 1))])  # z-axis turns: r_z has no centripetal term
    coef, se = lstsq(a, y, s)
    assert_recovered(coef[:2], se[:2], r[:2], "lever arm r_x, r_y")


def test_table_rate_error_mean_and_ripple(tmp_path):
    eps, a1, p1, a2, p2 = 3e-4, 2e-4, 0.3, 1e-4, -1.0
    eff = EFFECTS["table_rate_error"](mean_error=eps, ripple_1_per_rev=a1, ripple_1_phase_rad=p1, ripple_2_per_rev=a2,
                                      ripple_2_phase_rad=p2)
    _, ing = run_raw(tmp_path, rate_plan(), [eff], kind="rate")
    seg = segment_run(ing.manifest, ing.imu, ing.table)
    v, se = fitted(fit_gyro_rate(seg.plateaus), "gyro", "z", "scale_factor")
    assert_recovered(v - 1, se, eps, "mean table-rate error (as scale factor)")
    ws, m = window_samples(seg, ing, 50.0)
    th = table_angle_at_imu(seg, ing)[m]
    w = np.radians(np.array([s.table_rate_dps for s in ing.manifest.plan.steps]))[ws[m]]
    y = demean_per_step(ing.imu["gyro_z_radps"].to_numpy(), ws, m)[m]
    a = np.column_stack([w * np.sin(th), w * np.cos(th), w * np.sin(2 * th), w * np.cos(2 * th)])
    coef, se = lstsq(a, y)
    truth = [a1 * np.cos(p1), a1 * np.sin(p1), a2 * np.cos(p2), a2 * np.sin(p2)]
    assert_recovered(coef, se, truth, "table-rate ripple 1/rev and 2/rev")


def test_table_wobble_once_per_revolution_in_horizontal_accels(tmp_path):
    beta = 2e-4
    eff = EFFECTS["table_wobble"](tilt_rad=beta, azimuth_rad=0.7)
    _, ing = run_raw(tmp_path, rate_plan(), [eff], kind="rate")
    seg = segment_run(ing.manifest, ing.imu, ing.table)
    ws, m = window_samples(seg, ing, 50.0)  # plateaus of at least one whole turn
    th = table_angle_at_imu(seg, ing)[m]
    for ax in ("accel_x_mps2", "accel_y_mps2"):
        y = demean_per_step(ing.imu[ax].to_numpy(), ws, m)[m]
        coef, se = lstsq(np.column_stack([np.sin(th), np.cos(th)]), y)
        amp = np.hypot(*coef)
        assert_recovered(amp, max(se), G * np.sin(beta), f"1/rev wobble amplitude in {ax}")


def _rate_from_orientation(m, h):
    """Level-frame angular rate implied by the orientation samples (central differences): [w x] = dC/dt C^T."""
    c = m.c_b2l
    dc = (c[2:] - c[:-2]) / (2 * h)
    om = dc @ np.swapaxes(c[1:-1], 1, 2)
    return 0.5 * np.stack([om[:, 2, 1] - om[:, 1, 2], om[:, 0, 2] - om[:, 2, 0], om[:, 1, 0] - om[:, 0, 1]], axis=1)


def test_table_wobble_rates_are_those_of_its_orientation():
    """Rigid-body consistency of both wobble forms: the level-frame rate handed to the gyro is d/dt(C) C^T of the
    orientation handed to the accelerometer, through rate plateaus and ramps. For the platter wobble the coning term
    theta_dot (a - P a) is needed: without it (the orientation tilted, the rate only rotated) the check fails."""
    from assets_lib.sim.simulator import true_inputs

    plan = rate_plan(rates=(400, -250, 100), duration_s=4.0)
    h = 1e-4
    t = np.arange(0.0, plan.end_s, h)
    _, m0 = true_inputs(plan, t, SITE.latitude_deg, G, [])
    e0 = np.linalg.norm(_rate_from_orientation(m0, h) - m0.omega_motion_level_radps[1:-1], axis=1)
    smooth = e0 < 1e-5  # the nominal motion's own finite-difference error, O(h^2 w^3); ramp corners excluded
    assert smooth.mean() > 0.95
    for kw in ({"tilt_rad": 3e-3, "azimuth_rad": 0.4}, {"wobble_rad": 3e-3, "wobble_azimuth_rad": -1.1},
               {"tilt_rad": 2e-3, "wobble_rad": 3e-3, "wobble_azimuth_rad": 2.0}):
        _, m = true_inputs(plan, t, SITE.latitude_deg, G, [EFFECTS["table_wobble"](**kw)])
        err = np.linalg.norm(_rate_from_orientation(m, h) - m.omega_motion_level_radps[1:-1], axis=1)
        assert np.all(err[smooth] < e0[smooth] + 1e-7), (kw, np.max(err[smooth] - e0[smooth]))
    _, m = true_inputs(plan, t, SITE.latitude_deg, G, [EFFECTS["table_wobble"](wobble_rad=3e-3)])
    a = np.asarray(plan.table_axis_level, float)
    pa = (m.c_b2l @ np.swapaxes(m0.c_b2l, 1, 2)) @ a  # P a, P = C' C^T the tilt turning with the table
    rigid_only = m.omega_motion_level_radps - m.table_rate_radps[:, None] * (a - pa)  # P w_l
    assert np.abs(_rate_from_orientation(m, h) - rigid_only[1:-1])[smooth].max() > 1e-2  # coning: 7 rad/s x 3e-3


def test_table_wobble_platter_tilt_gives_rate_proportional_cross_axis_gyro(tmp_path):
    """A platter tilted by beta against the spin axis: the gyro's cross-axis plateau means move by omega beta (slope
    against the table rate = the tilt of the body-frame spin axis), the accelerometers by a constant g beta."""
    beta, az = 5e-4, 0.9
    eff = EFFECTS["table_wobble"](wobble_rad=beta, wobble_azimuth_rad=az)
    _, ing = run_raw(tmp_path, rate_plan(), [eff], kind="rate")
    p = plateau_rows(segment_run(ing.manifest, ing.imu, ing.table))
    a = np.asarray(ing.manifest.plan.table_axis_level, float)
    spin_b = eff._tip(a, beta, az).T @ a  # body spin axis at a ZUP mount (C_b^l = I at table angle 0)
    w = p["commanded_rate_radps"].to_numpy()
    for j, ax in enumerate("xy"):
        y = (p[f"gyro_{ax}_radps_mean"] - p[f"omega_ref_{ax}_radps"]).to_numpy()
        coef, se = lstsq(np.column_stack([w, np.ones_like(w)]), y, p[f"gyro_{ax}_radps_sem"].to_numpy())
        assert_recovered(coef[0], se[0], spin_b[j], f"gyro {ax} cross-axis slope (omega beta)")
        acc = (p[f"accel_{ax}_mps2_mean"] - p[f"f_ref_{ax}_mps2"]).to_numpy()
        assert_recovered(acc.mean(), acc.std(ddof=1) / np.sqrt(acc.size) + p[f"accel_{ax}_mps2_sem"].mean(),
                         G * spin_b[j], f"accel {ax} constant g beta")


def test_vibration_line(tmp_path):
    f0, ag, aa, ph = 7.3, 1e-3, 0.02, 0.4
    eff = EFFECTS["vibration"](frequency_hz=f0, gyro_radps=(ag, 0, 0), accel_mps2=(0, 0, aa), phase_rad=ph)
    _, ing = run_raw(tmp_path, static_plan(60.0), [eff], kind="static")
    t = ing.imu["time_s"].to_numpy()
    for col, truth in (("gyro_x_radps", ag), ("accel_z_mps2", aa)):
        y = ing.imu[col].to_numpy()
        spec = np.abs(np.fft.rfft(y - y.mean()))
        freqs = np.fft.rfftfreq(y.size, 1 / FS)
        assert abs(freqs[np.argmax(spec)] - f0) <= freqs[1]
        coef, se = lstsq(np.column_stack([np.ones_like(t), np.sin(2 * np.pi * f0 * t), np.cos(2 * np.pi * f0 * t)]), y)
        assert_recovered(coef[1:], se[1:], [truth * np.cos(ph), truth * np.sin(ph)], f"vibration {col}")


def _noise_fit(t, y):
    m = np.unique(np.round(np.logspace(0, np.log10(y.size // 8), 30)).astype(int))
    av, _ = overlapping_avar(y, m)
    taus = m / FS
    f = lambda tau, n, s, tc: np.log(n**2 / tau + gauss_markov_avar(tau, s, tc))  # noqa: E731
    p, _ = curve_fit(f, taus, np.log(av), p0=[1e-4, 1e-3, 1.0], bounds=([0, 0, 0.01], [1, 1, 100]))
    return p


def test_noise_model_white_plus_gauss_markov(tmp_path):
    """Allan-variance fit of N, sigma_GM, tau_GM; standard errors by a parametric bootstrap of the same pipeline."""
    n, sig, tc = 1e-4, 2e-3, 3.0
    quiet = device(gyro_n=0.0, accel_n=0.0)
    eff = EFFECTS["noise_model"](gyro_n_radps_per_rthz=n, gyro_gm_sigma_radps=sig, gyro_gm_tau_s=tc)
    _, ing = run_raw(tmp_path, static_plan(300.0), [eff], kind="static", dev=quiet)
    t = ing.imu["time_s"].to_numpy()
    est = _noise_fit(t, ing.imu["gyro_x_radps"].to_numpy())
    boot = []
    for b in range(8):
        e = EFFECTS["noise_model"](gyro_n_radps_per_rthz=est[0], gyro_gm_sigma_radps=est[1], gyro_gm_tau_s=est[2])
        run = simulate_run(quiet, static_plan(300.0), f"boot{b}", test_kind="static", effects=sensor_chain([e]),
                           seed=100 + b, table_log=False)
        y = run.imu_raw["gyro_x"].to_numpy() * np.radians(quiet.gyro.lsb)
        boot.append(_noise_fit(t, y))
    se = np.std(boot, axis=0, ddof=1)
    assert_recovered(est, se, [n, sig, tc], "noise model N, sigma_GM, tau_GM")
