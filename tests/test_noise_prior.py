"""The device's noise prior (assets_lib.calibration.noise_prior): B from the device's static records replaces the run's
B in the calibration fits; an upper bound enters as FlickerBoundLaw (tau^2 integrated below it), not as B."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from assets_lib.calibration.fit_core import (
    FLICKER_WHITE,
    FlickerBoundLaw,
    fit_linear,
    flicker_covariance,
    flicker_dof_from_interval,
    flicker_gls,
)
from assets_lib.calibration.multiposition import (
    fit_accel_multiposition,
    fit_gyro_static,
)
from assets_lib.calibration.noise_prior import ChannelNoisePrior, DeviceNoisePrior
from assets_lib.calibration.rate_fit import fit_gyro_rate


def _noise_rows(rows):
    """A NOISE TABLE of the allan_deviation stage with only the columns the prior reads (+ distractor rows)."""
    out = []
    for ch, v, lo, hi, ub in rows:
        out.append(dict(channel=ch, parameter="B", value=v, ci_lo=lo, ci_hi=hi, method="fit", is_upper_bound=ub,
                        ci_level=0.95))
        out.append(dict(channel=ch, parameter="N", value=1e-3, ci_lo=0.9e-3, ci_hi=1.1e-3, method="fit",
                        is_upper_bound=False, ci_level=0.95))
        out.append(dict(channel=ch, parameter="B", value=v * 0.01 if np.isfinite(v) else 1e-12, ci_lo=1e-13,
                        ci_hi=1e-12, method="slope", is_upper_bound=False, ci_level=0.95))
    return pd.DataFrame(out)


def test_prior_picks_the_narrowest_two_sided_record_else_the_smallest_bound():
    gx, gy, gz, ax = "gyro_x_radps", "gyro_y_radps", "gyro_z_radps", "accel_x_mps2"
    short = _noise_rows([(gx, 1.0e-5, 0.5e-5, 2.0e-5, False), (gy, np.nan, 0.0, 3e-5, True),
                         (gz, np.nan, 0.0, 9e-6, True), (ax, 2e-5, 0.0, 4e-5, False)])
    long_ = _noise_rows([(gx, 1.1e-5, 0.9e-5, 1.3e-5, False), (gy, np.nan, 0.0, 2e-5, True),
                         (gz, 8e-6, 6e-6, 1.1e-5, False), (ax, np.nan, 0.0, 5e-5, True)])
    mid = _noise_rows([(gx, 1.2e-5, 1.0e-5, 1.6e-5, False), (gy, np.nan, 0.0, 2.5e-5, True)])
    pr = DeviceNoisePrior.from_noise_tables([short, long_, mid], ["S20m", "S8h", "S3h"], [1200.0, 28800.0, 10800.0],
                                            device_id="D")
    x, y, z, a = pr.get(gx), pr.get(gy), pr.get(gz), pr.get(ax)
    # narrowest relative interval: 1.3/0.9 = 1.44 (8 h) beats 1.6/1.0 = 1.6 (3 h) and 4 (20 min)
    assert (x.run_id, x.b, x.is_upper_bound, x.duration_s) == ("S8h", 1.1e-5, False, 28800.0)
    # only bounds: the smallest
    assert (y.run_id, y.ci_hi, y.is_upper_bound) == ("S8h", 2e-5, True) and np.isnan(y.b)
    # a two-sided estimate beats any bound, even a tighter-looking one
    assert (z.run_id, z.b, z.is_upper_bound) == ("S8h", 8e-6, False)
    # a lower end at 0 is a bound (ci_hi), not an estimate: the smaller of 4e-5 and 5e-5
    assert (a.run_id, a.ci_hi, a.is_upper_bound) == ("S20m", 4e-5, True)
    assert "gyro_q_radps" not in pr and gx in pr and len(pr.channels) == 4
    t2, nu = pr.flicker(gx)
    assert t2 == pytest.approx(1.1e-5**2 / np.pi) and nu == pytest.approx(flicker_dof_from_interval(1.1e-5, 0.9e-5, 1.3e-5))
    t2, law = pr.flicker(gy)
    assert isinstance(law, FlickerBoundLaw) and t2 == pytest.approx(2e-5**2 / np.pi) and law.tau2_max == t2
    assert "S8h" in pr.source(gx) and "upper bound" in pr.source(gy) and pr.source("gyro_q_radps") == ""
    with pytest.raises(KeyError):
        pr.flicker("gyro_q_radps")
    with pytest.raises(ValueError):
        DeviceNoisePrior.from_noise_tables([short], ["a", "b"], [1.0])


def _design():
    g = 9.8
    f = np.array([g, -g, 0, 0, 0, 0, g, -g, g, -g])
    X = np.column_stack([np.ones(10), f, f**2])
    return X, 30.0 + 60.0 * np.arange(10), np.full(10, 20.0)


def test_bound_law_keeps_tau2_below_the_bound_and_the_interval_between_the_two_ends():
    """tau^2 flat in tau below the bound, weighed by the plateaus' REML: the posterior mean stays below the bound
    even where the plateaus' own level lies far above it, and the bias interval lies between the WLS one (tau^2 = 0)
    and the one with tau^2 at the bound."""
    X, t_mid, t_len = _design()
    sem = np.full(10, 2e-4)
    tau2_true = 0.4 * sem[0] ** 2 / FLICKER_WHITE  # a 1/f-heavy run: REML alone reads a level well above the bound
    tmax = tau2_true / 20.0
    L = np.linalg.cholesky(flicker_covariance(sem, t_mid, t_len, tau2_true))
    y = X @ np.array([0.05, 1.001, 1e-4]) + L @ np.random.default_rng(2).standard_normal(10)
    reml = flicker_gls(X, y, sem, t_mid, t_len)[0]
    assert reml > 3 * tmax  # without the bound the level is far above it
    law = FlickerBoundLaw(tmax)
    assert law.loglik(0.5 * tmax) == 0.0 and law.loglik(1.01 * tmax) == -np.inf and law.f_hat == 0.0
    assert np.all(law.tau2_grid < tmax) and law.resolution_tau2 == tmax
    tm, _, C, _ = flicker_gls(X, y, sem, t_mid, t_len, tau2=tmax, prior_dof=law)
    assert 0 < tm < tmax
    W = np.diag(1.0 / sem**2)
    var0 = np.linalg.inv(X.T @ W @ X)[0, 0]
    var_max = flicker_gls(X, y, sem, t_mid, t_len, tau2=tmax)[2][0, 0]
    assert var0 < C[0, 0] < var_max
    fit = fit_linear(X, y, ("bias", "scale_factor", "k2"), sigma=sem, outlier_test=False, times=(t_mid, t_len),
                     flicker_tau2=tmax, flicker_tau2_dof=law)
    assert fit.cov_policy == "marginal" and 0 < fit.flicker_tau2 < tmax
    assert var0 < fit.cov[0, 0] < var_max
    with pytest.raises(ValueError):
        FlickerBoundLaw(0.0)


def _segmented(dev, plan, run_id, seed):
    from assets_lib.calibration.segmentation import segment_run
    from assets_lib.sim.simulator import simulate_run
    from raw_schemas.readers import ingest_frames

    sim = simulate_run(dev, plan, run_id, seed=seed)
    ing = ingest_frames(sim.manifest, sim.imu_raw, sim.table_raw)
    return segment_run(ing.manifest, ing.imu, ing.table).plateaus


@pytest.fixture(scope="module")
def nav_runs():
    """A navigation IMU's quick_rate run (the run's gyro B detected on x and y at 7-10x the truth) and its
    quick_24_position run, segmented."""
    from assets_lib.sim.simulator import example_device

    dev = example_device("NAV-T", "navigation", seed=3)
    return dev, _segmented(dev, "quick_rate", "r1", 14), _segmented(dev, "quick_24_position", "p1", 15)


def _tables(p0, p1, prior="absent"):
    kw = {} if prior == "absent" else {"noise_prior": prior}
    return (fit_gyro_rate(p0, **kw).coefficient_table(), fit_gyro_static(p1, **kw).coefficient_table(),
            fit_accel_multiposition(p1, **kw).coefficient_table())


def test_no_prior_or_a_prior_without_the_channel_changes_nothing(nav_runs):
    dev, p, p1 = nav_runs
    base = _tables(p, p1)
    none = _tables(p, p1, None)
    other = DeviceNoisePrior((ChannelNoisePrior("gyro_w_radps", 1e-8, 0.9e-8, 1.1e-8, False, "S", 1.0),))
    empty = _tables(p, p1, other)
    for a, b, c in zip(base, none, empty):
        pd.testing.assert_frame_equal(a, b, check_exact=True)
        pd.testing.assert_frame_equal(a, c, check_exact=True)
    # a prior with the channel does change the fit (so the comparison above can fail), and says so in the note
    b = dev.gyro.noise[0].b
    gx = DeviceNoisePrior((ChannelNoisePrior("gyro_x_radps", b, 0.8 * b, 1.25 * b, False, "S8h", 28800.0),))
    t = fit_gyro_rate(p, noise_prior=gx).coefficient_table()
    with pytest.raises(AssertionError):
        pd.testing.assert_frame_equal(base[0], t)
    sel = (t.coefficient == "bias")
    assert "static record S8h" in t[sel & (t.axis == "x")].note.iloc[0]
    assert "static record" not in t[sel & (t.axis == "y")].note.iloc[0]
    acc = DeviceNoisePrior((ChannelNoisePrior("accel_x_mps2", np.nan, 0.0, 1e-4, True, "S20m", 1200.0),
                            ChannelNoisePrior("gyro_z_radps", np.nan, 0.0, 1e-7, True, "S20m", 1200.0)))
    ta = fit_accel_multiposition(p1, noise_prior=acc).coefficient_table()
    tg = fit_gyro_static(p1, noise_prior=acc).coefficient_table()
    assert "upper bound" in ta[(ta.coefficient == "bias") & (ta.axis == "x")].note.iloc[0]
    assert "S20m" not in ta[(ta.coefficient == "bias") & (ta.axis == "y")].note.iloc[0]
    assert "upper bound" in tg[(tg.coefficient == "bias") & (tg.axis == "z")].note.iloc[0]
    with pytest.raises(ValueError):
        fit_accel_multiposition(p1, flicker_b_mps2=np.ones(3), noise_prior=other)


def test_two_sided_device_prior_narrows_a_navigation_rate_bias_interval(nav_runs):
    """The run's plateaus read a navigation gyro's B at 7-10x the truth (detected on x and y): the bias carries a run
    mean wander 50-100x too large. A two-sided B from a long static record (here the device's B with an 8-h-like
    interval) puts tau^2 at the device's level and the interval shrinks."""
    dev, p, _ = nav_runs
    b = np.array([dev.gyro.noise[i].b for i in range(3)])
    ratio = np.array([p[f"gyro_{a}_radps_flicker_b"].iloc[0] for a in "xyz"]) / b
    assert ratio[0] > 3 and ratio[1] > 3  # the case this test is about: B detected far above the truth
    nt = _noise_rows([(f"gyro_{a}_radps", b[i], 0.8 * b[i], 1.25 * b[i], False) for i, a in enumerate("xyz")])
    pr = DeviceNoisePrior.from_noise_tables([nt], ["S8h"], [28800.0])
    f0, f1 = fit_gyro_rate(p), fit_gyro_rate(p, noise_prior=pr)
    for i in (0, 1):
        s0, s1 = f0.axes[i].bias_radps.stderr, f1.axes[i].bias_radps.stderr
        assert s1 < 0.7 * s0
        assert f1.axes[i].fit.cov_policy == "marginal"
        assert f1.axes[i].fit.flicker_tau2 == pytest.approx(b[i] ** 2 / np.pi, rel=0.3)
    assert all("static record S8h" in ax.b_source for ax in f1.axes)


def test_a_bound_truncates_the_runs_own_law(nav_runs):
    """Where the device's record only bounds B (a navigation gyro: 2.4x the truth at 3 h), the fit keeps what its run
    says (the censored Allan law of its plateaus) and cuts it at the bound: the law is the run's inside the support,
    -inf above; the run's B read at 7-10x the truth gives way to a level below the bound, and the bias interval
    narrows against the run's own."""
    from assets_lib.calibration.fit_core import FlickerLaw, flicker_law
    from assets_lib.calibration.noise_prior import prior_flicker

    dev, p, _ = nav_runs
    b = np.array([dev.gyro.noise[i].b for i in range(3)])
    nt = _noise_rows([(f"gyro_{a}_radps", np.nan, 0.0, 2.4 * b[i], True) for i, a in enumerate("xyz")])
    pr = DeviceNoisePrior.from_noise_tables([nt], ["S3h"], [10800.0])
    t2, law, source = prior_flicker(pr, "gyro_x_radps", p)
    run = flicker_law(p, "gyro_x_radps")
    assert isinstance(law, FlickerBoundLaw) and isinstance(law.inner, FlickerLaw) and run is not None
    assert t2 == pytest.approx((2.4 * b[0]) ** 2 / np.pi) and "upper bound" in source
    for f in (0.01, 0.3, 0.99):
        assert law.loglik(f * t2) == pytest.approx(run.loglik(f * t2))
    assert law.loglik(1.01 * t2) == -np.inf
    assert prior_flicker(pr, "gyro_x_radps")[1].inner is None  # without the plateaus: the bound alone
    f0, f1 = fit_gyro_rate(p), fit_gyro_rate(p, noise_prior=pr)
    for i in (0, 1):
        assert 0 < f1.axes[i].fit.flicker_tau2 < (2.4 * b[i]) ** 2 / np.pi
        assert f1.axes[i].bias_radps.stderr < 0.8 * f0.axes[i].bias_radps.stderr
        assert "upper bound" in f1.axes[i].b_source
