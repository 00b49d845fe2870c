"""Fleet drift science (assets_lib.fleet.drift) on synthetic series with known truth.

Monte Carlo sizes are the reduced versions (a few thousand trials); every rate is compared with its designed or
analytical value through a binomial tolerance of 4 standard deviations, so a wrong formula fails while chance
almost never does (two-sided 6e-5 per comparison).
"""

from __future__ import annotations

import math

import numpy as np
import pandas as pd
import pytest
from scipy import stats

from assets_lib.fleet.drift import (
    analyze_series,
    cusum_false_alarm_probability,
    cusum_one_sided_arl,
    detrended_turn_on_sigma,
    fleet_drift,
    self_starting_residuals,
    tabular_cusum,
    weighted_trend,
)
from assets_lib.calibration.repeatability import repeatability_table

N_RUNS = 10
T_DAYS = np.arange(N_RUNS) * 7.0  # weekly calibrations
SE = np.array([0.5, 0.7, 0.6, 0.5, 0.8, 0.6, 0.5, 0.7, 0.6, 0.55])  # per-run stderr, heterogeneous
SIGMA_TURNON = 0.8
SIG = np.sqrt(SIGMA_TURNON**2 + SE**2)


def _within(measured: float, p: float, n: int, k: float = 4.0) -> bool:
    return abs(measured - p) <= k * math.sqrt(p * (1 - p) / n) + 0.5 / n


def _series(rng, mean_shape):
    return 3.0 + mean_shape + SIG * rng.standard_normal(N_RUNS)


def _analyze(x):
    return analyze_series(T_DAYS, x, SE, sigma_turnon=SIGMA_TURNON)


# ----------------------------------------------------------------------------------------------------- primitives
def test_weighted_trend_matches_polyfit():
    rng = np.random.default_rng(0)
    x = 1.0 + 0.03 * T_DAYS + SIG * rng.standard_normal(N_RUNS)
    tr = weighted_trend(T_DAYS, x, SIG)
    coef, cov = np.polyfit(T_DAYS, x, 1, w=1 / SIG, cov="unscaled")
    assert tr.slope_per_day == pytest.approx(coef[0], rel=1e-12)
    assert tr.intercept == pytest.approx(coef[1], rel=1e-12)
    assert tr.slope_stderr_per_day == pytest.approx(math.sqrt(cov[0, 0]), rel=1e-10)
    assert tr.excursion == pytest.approx(coef[0] * 63.0, rel=1e-12)
    assert tr.slope_ci_low < tr.slope_per_day < tr.slope_ci_high


def test_cusum_arl_matches_montgomery_table_9_3():
    # Montgomery (2013) Table 9.3, two-sided tabular CUSUM, k = 1/2: ARL0 = 168 (h = 4), 465 (h = 5);
    # a 1-sigma shift: 8.38 (h = 4), 10.4 (h = 5). Two-sided ARL0 = one-sided / 2 (symmetric sides).
    assert cusum_one_sided_arl(0.5, 4.0) / 2 == pytest.approx(168, rel=0.01)
    assert cusum_one_sided_arl(0.5, 5.0) / 2 == pytest.approx(465, rel=0.01)
    assert cusum_one_sided_arl(0.5, 4.0, shift=1.0) == pytest.approx(8.38, rel=0.01)
    assert cusum_one_sided_arl(0.5, 5.0, shift=1.0) == pytest.approx(10.4, rel=0.01)


def test_self_starting_residuals_are_iid_standard_normal():
    rng = np.random.default_rng(1)
    u = np.array([self_starting_residuals(_series(rng, 0.0), SIG)[1:] for _ in range(4000)])
    assert np.abs(u.mean(axis=0)).max() < 4 / math.sqrt(4000)
    assert np.abs(u.var(axis=0) - 1).max() < 4 * math.sqrt(2 / 4000)
    c = np.corrcoef(u.T)[np.triu_indices(N_RUNS - 1, 1)]
    assert np.abs(c).max() < 4.5 / math.sqrt(4000)


def test_cusum_false_alarm_probability_matches_simulation():
    """Brook-Evans + independent sides vs a direct simulation of the two-sided chart on N(0, 1) residuals."""
    rng = np.random.default_rng(2)
    n_trials, k, h, steps = 200_000, 0.5, 5.0, N_RUNS - 1
    z = rng.standard_normal((n_trials, steps))
    cp = np.zeros(n_trials)
    cm = np.zeros(n_trials)
    alarm = np.zeros(n_trials, bool)
    for i in range(steps):
        cp = np.maximum(0, z[:, i] - k + cp)
        cm = np.maximum(0, -z[:, i] - k + cm)
        alarm |= (cp > h) | (cm > h)
    p = cusum_false_alarm_probability(steps, k, h)
    assert 0.003 < p < 0.02
    assert _within(alarm.mean(), p, n_trials)
    # the loop implementation agrees with the vectorized one
    for row in range(200):
        res = tabular_cusum(np.r_[np.nan, z[row]], k, h)
        assert (res.alarm_index is not None) == alarm[row]


# ------------------------------------------------------------------------------------------- series behaviour
def test_stable_devices_false_alarm_rate_near_design():
    rng = np.random.default_rng(3)
    n = 3000
    raw_drift = cusum = any_flag = 0
    designed_drift = designed_cusum = None
    for _ in range(n):
        s = _analyze(_series(rng, 0.0))
        raw_drift += abs(s.trend.z) > 3.0 and abs(s.trend.excursion) > 3.0 * s.sigma
        cusum += s.cusum.alarm_index is not None
        any_flag += s.flagged
        designed_drift, designed_cusum = s.drift_false_alarm_designed, s.cusum_false_alarm_designed
    assert designed_drift <= 0.0027 + 1e-12
    assert _within(raw_drift / n, designed_drift, n)
    assert _within(cusum / n, designed_cusum, n)
    # a flag needs the drift rule, or a CUSUM alarm and the step model: never more than the two designed rates
    assert any_flag / n <= designed_drift + designed_cusum + 4 * math.sqrt((designed_drift + designed_cusum) / n)


def test_drifting_device_is_flagged_with_designed_power():
    """A drift of 5 sigma over the series: the drift rule's power is P(Z + D/se(D) > c), c = max(3, 3 sigma/se(D))."""
    rng = np.random.default_rng(4)
    ramp = np.linspace(0, 1, N_RUNS)
    probe = _analyze(_series(rng, 0.0))
    d = 5.0 * probe.sigma
    c = max(3.0, 3.0 * probe.sigma / probe.trend.excursion_stderr)
    power = stats.norm.sf(c - d / probe.trend.excursion_stderr)
    n = 1000
    raw = flagged = as_drift = 0
    for _ in range(n):
        s = _analyze(_series(rng, d * ramp))
        raw += s.trend.excursion > 3.0 * s.sigma and s.trend.z > 3.0
        flagged += s.flagged
        as_drift += s.drift_flag
    assert power > 0.9
    assert _within(raw / n, power, n)
    assert flagged / n >= 0.95
    assert as_drift / n >= 0.75  # the rest is called an abrupt shift (still a warning)


def test_abrupt_shift_detected_at_the_right_run():
    rng = np.random.default_rng(5)
    step = 6.0 * SIG * (np.arange(N_RUNS) >= 6)
    n, right = 400, 0
    for _ in range(n):
        s = _analyze(_series(rng, step))
        right += s.shift_flag and s.shift_run_id == "6" and not s.drift_flag
    assert right / n >= 0.95
    s = _analyze(_series(np.random.default_rng(50), step))
    assert s.status == "shift" and s.step.index == 6
    assert s.step.size == pytest.approx(6.0 * s.sigma, abs=4 * s.step.size_stderr)


def test_slope_confidence_interval_covers_truth_at_nominal_rate():
    rng = np.random.default_rng(6)
    slope = 0.05
    n, covered = 3000, 0
    for _ in range(n):
        s = _analyze(_series(rng, slope * T_DAYS))
        covered += s.trend.slope_ci_low <= slope <= s.trend.slope_ci_high
    assert _within(covered / n, 0.95, n)


def test_in_sample_sigma_uses_student_t_and_keeps_drift_detectable():
    """Repeatability from the monitored runs themselves (the pipeline's case): sigma re-estimated about the trend,
    n - 2 dof, t test at the same alpha. A stable device stays below alpha, the slope CI keeps its coverage, and
    a drift of 8 sigma is found (used as is, the in-sample repeatability would cap |D| / s below 3.2 at n = 10)."""
    rng = np.random.default_rng(8)
    n, null_flags, covered, caught = 1500, 0, 0, 0
    slope = 8.0 * SIG.mean() / T_DAYS[-1]
    for _ in range(n):
        for shape in (0.0, slope * T_DAYS):
            x = _series(rng, shape)
            s_t, dof = detrended_turn_on_sigma(T_DAYS, x, SE)
            s = analyze_series(T_DAYS, x, SE, sigma_turnon=s_t, sigma_dof=dof)
            assert s.trend.sigma_dof == N_RUNS - 2
            if np.isscalar(shape):
                null_flags += s.drift_flag
                covered += s.trend.slope_ci_low <= 0.0 <= s.trend.slope_ci_high
            else:
                caught += s.flagged
    alpha = 2 * stats.norm.sf(3.0)
    assert null_flags / n <= alpha + 4 * math.sqrt(alpha / n)
    assert _within(covered / n, 0.95, n)
    assert caught / n >= 0.95


def test_short_series_is_reported_not_flagged():
    s = analyze_series([0, 7], [1.0, 50.0], [0.1, 0.1], sigma_turnon=0.1)
    assert s.status.startswith("too short") and not s.flagged and s.trend is None


# ------------------------------------------------------------------------------------------------------ fleet
def _fleet_frames(seed=7):
    """Three devices x (gyro, accel) x (bias, scale_factor) x 3 axes, 8 weekly runs; DRIFT drifts in gyro x bias,
    SHIFT shifts in accel y scale factor at run r05, STABLE is stable. Repeatability from a separate qualification
    set (phase I) of 6 runs per device."""
    rng = np.random.default_rng(seed)
    t0 = pd.Timestamp("2026-01-05T08:00:00Z")
    units = {("gyro", "bias"): "rad/s", ("accel", "bias"): "m/s^2", ("gyro", "scale_factor"): "1",
             ("accel", "scale_factor"): "1"}
    base = {("gyro", "bias"): 1e-5, ("accel", "bias"): 5e-3, ("gyro", "scale_factor"): 1.0002,
            ("accel", "scale_factor"): 0.9998}
    turnon = {("gyro", "bias"): 2e-7, ("accel", "bias"): 1e-4, ("gyro", "scale_factor"): 30e-6,
              ("accel", "scale_factor"): 20e-6}
    rows, qual, times = [], [], []
    for dev in ("DRIFT-1", "SHIFT-2", "STABLE-3"):
        for r in range(8):
            times.append({"device_id": dev, "run_id": f"r{r:02d}",
                          "start_time_utc": (t0 + pd.Timedelta(days=7 * r, hours=r % 3)).isoformat()})
        for (sensor, coef), b in base.items():
            for axis in "xyz":
                sd = turnon[(sensor, coef)]
                se = 0.5 * sd
                method = "rate_fit" if sensor == "gyro" else "multiposition"
                for r in range(8):
                    v = b + math.hypot(sd, se) * rng.standard_normal()
                    if dev == "DRIFT-1" and (sensor, coef, axis) == ("gyro", "bias", "x"):
                        v += 8 * math.hypot(sd, se) * r / 7
                    if dev == "SHIFT-2" and (sensor, coef, axis) == ("accel", "scale_factor", "y") and r >= 5:
                        v += 8 * math.hypot(sd, se)
                    rows.append(dict(device_id=dev, run_id=f"r{r:02d}", sensor=sensor, axis=axis, coefficient=coef,
                                     value=v, stderr=se, unit=units[(sensor, coef)], observable=True, method=method))
                for q in range(6):
                    qual.append(dict(device_id=dev, run_id=f"q{q}", sensor=sensor, axis=axis, coefficient=coef,
                                     value=b + math.hypot(sd, se) * rng.standard_normal(), stderr=se, observable=True,
                                     method=method))
    return pd.DataFrame(rows), pd.DataFrame(times), repeatability_table(pd.DataFrame(qual))


def test_fleet_drift_tables_warnings_and_plots():
    coefs, times, rep = _fleet_frames()
    fd = fleet_drift(coefs, times, rep)
    st = fd.series_table()
    assert len(st) == 3 * 4 * 3 and (st["sigma_source"] == "repeatability").all()
    flagged = st[st["drift_flag"] | st["shift_flag"]]
    got = {(r.device_id, r.sensor, r.axis, r.coefficient, r.status) for r in flagged.itertuples()}
    assert ("DRIFT-1", "gyro", "x", "bias", "drift") in got
    assert ("SHIFT-2", "accel", "y", "scale_factor", "shift") in got
    assert len(got) <= 3  # 34 stable series: at most one chance alarm (expected 34 x ~0.9 % = 0.3)
    shift = st[(st.device_id == "SHIFT-2") & (st.sensor == "accel") & (st.axis == "y") & (st.coefficient == "scale_factor")]
    assert shift["shift_run_id"].item() == "r05"
    # scale-factor repeatability is relative: sigma_turnon is it times |mean K|
    row_rep = rep[(rep.device_id == "SHIFT-2") & (rep.sensor == "accel") & (rep.axis == "y")
                  & (rep.coefficient == "scale_factor_repeatability")].iloc[0]
    assert shift["sigma_turnon"].item() == pytest.approx(row_rep["value_noise_corrected"] * 0.9998, rel=1e-3)
    drift = st[(st.device_id == "DRIFT-1") & (st.sensor == "gyro") & (st.axis == "x") & (st.coefficient == "bias")]
    assert drift["slope_ci_low"].item() > 0 and drift["excursion_sigma"].item() > 3
    warnings = fd.warnings()
    assert any(w["kind"] == "drift" and w["device_id"] == "DRIFT-1" and w["run_id"] == "r07" for w in warnings)
    assert any(w["kind"] == "shift" and w["device_id"] == "SHIFT-2" and w["run_id"] == "r05" and "r05" in w["message"]
               for w in warnings)
    pts = fd.points_table()
    assert len(pts) == 36 * 8 and pts["shift_here"].sum() >= 1
    assert (pts["lcl"] < pts["center"]).all() and (pts["center"] < pts["ucl"]).all()
    summ = fd.summary_table()
    assert set(summ["family"]) == {"gyro bias", "gyro scale_factor", "accel bias", "accel scale_factor", "all"}
    assert summ.set_index("family").loc["all", "n_series"] == 36
    assert "DRIFT-1" in summ.set_index("family").loc["gyro bias", "devices_flagged"]
    plots = fd.plots()
    assert sorted(plots) == ["drift_accel_bias", "drift_accel_scale_factor", "drift_gyro_bias", "drift_gyro_scale_factor"]
    for png in plots.values():
        assert png[:8] == b"\x89PNG\r\n\x1a\n" and len(png) > 5000


def test_fleet_drift_without_repeatability_uses_stderr_only():
    coefs, times, _ = _fleet_frames()
    fd = fleet_drift(coefs[coefs.device_id == "STABLE-3"], times, None)
    st = fd.series_table()
    assert (st["sigma_source"] == "stderr only").all() and (st["sigma_turnon"] == 0).all()
    se = coefs[coefs.device_id == "STABLE-3"].groupby(["sensor", "axis", "coefficient"])["stderr"].first()
    got = st.set_index(["sensor", "axis", "coefficient"])["sigma"]
    assert np.allclose(got.sort_index().to_numpy(), se.sort_index().to_numpy(), rtol=1e-12)
    # limits from the stderr alone are narrower than the stable device's true scatter: chance flags are expected
    assert (st["status"] != "too short: 8 runs").all()
