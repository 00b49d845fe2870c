"""Noise-term and noise-corrected repeatability intervals: the MLS interval's coverage, and a small run of
benchmarks/coverage_noise.py (the allan_deviation stage's computation on simulated static runs)."""

from __future__ import annotations

import importlib.util
import math
from pathlib import Path

import numpy as np
import pytest
from scipy import stats

from assets_lib.calibration.repeatability import bias_repeatability, mls_difference_interval

ROOT = Path(__file__).resolve().parents[1]


def _bench():
    spec = importlib.util.spec_from_file_location("coverage_noise", ROOT / "benchmarks" / "coverage_noise.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_mls_interval_with_known_noise_is_the_shifted_chi_square_interval():
    s1, nu1, s2 = 4.0, 5, 1.5
    lo, hi = mls_difference_interval(s1, nu1, s2, math.inf)
    assert lo == pytest.approx(nu1 * s1 / stats.chi2.ppf(0.975, nu1) - s2, rel=1e-12)
    assert hi == pytest.approx(nu1 * s1 / stats.chi2.ppf(0.025, nu1) - s2, rel=1e-12)
    # an uncertain noise variance (nu2 = 20) lowers the lower limit; the upper one is set by s1's chi-square
    lo2, hi2 = mls_difference_interval(s1, nu1, s2, 20)
    assert lo2 < lo and hi2 == pytest.approx(hi, rel=0.01)
    assert mls_difference_interval(s1, nu1, s2, 1e9) == pytest.approx((lo, hi), rel=1e-4)


@pytest.mark.parametrize("sigma_over_se", [0.5, 1.0, 3.0])
def test_noise_corrected_repeatability_interval_covers_the_turn_on_spread(sigma_over_se):
    """3000 devices, 6 runs each, per-run standard errors known (two run lengths: heterogeneous): the 95 % MLS
    interval on the noise-corrected spread covers the true turn-on spread 95 % of the time (not the plain std's
    interval, which is about the turn-on spread plus the noise)."""
    rng = np.random.default_rng(11)
    se = np.array([1.0, 1.0, 1.0, 2.0, 2.0, 2.0])
    sigma = sigma_over_se * 1.5
    n, hits, plain = 3000, 0, 0
    for _ in range(n):
        v = sigma * rng.standard_normal(6) + se * rng.standard_normal(6)
        r = bias_repeatability(v, se)
        hits += r.noise_corrected_ci_low <= sigma <= r.noise_corrected_ci_high
        plain += r.ci_low <= sigma <= r.ci_high
        assert r.noise_corrected_ci_low <= r.std_noise_corrected <= r.noise_corrected_ci_high
    cov = hits / n
    assert 0.93 <= cov <= 0.97, cov
    assert plain / n < cov  # the uncorrected interval is centred on sqrt(sigma^2 + se^2)


def test_interval_z_is_the_interval_pivot_on_its_construction_scale():
    """z of a profile-likelihood interval: |z| < 1.96 exactly when the interval covers, each side scaled by its
    own half-width on the variance (or ln) scale; a symmetric interval in theta gives the plain Wald z."""
    bench = _bench()
    z95 = bench.Z95
    rng = np.random.default_rng(3)
    for _ in range(200):
        est = rng.uniform(1.0, 2.0)
        lo, hi = est * rng.uniform(0.2, 0.95), est * rng.uniform(1.05, 3.0)
        t = rng.uniform(0.1, 4.0)
        for scale in ("variance", "log"):
            z = bench.interval_z(est, t, lo, hi, scale)
            assert (abs(z) < z95) == (lo < t < hi)
            assert np.sign(z) == np.sign(est - t)
    # theta = 4 +- 1.96 (sd 1): a truth at theta = 3 is one sd low
    lo, hi = math.sqrt(4 - z95), math.sqrt(4 + z95)
    assert bench.interval_z(2.0, math.sqrt(3.0), lo, hi, "variance") == pytest.approx(1.0)
    assert bench.interval_z(2.0, math.sqrt(5.0), lo, hi, "variance") == pytest.approx(-1.0)


@pytest.mark.slow
def test_small_noise_coverage_run_scores_every_printed_interval(tmp_path):
    """Nine trials (every grade x noise plan) through the stage's computation: every scored row is well formed,
    bounds are one-sided, and the white-noise terms (always two-sided) sit near their truths (|z| < 5)."""
    bench = _bench()
    df = bench.run(seed=77, trials=9, workers=1, duration_s=240.0, cycles=3)
    assert set(df["grade"]) == set(bench.GRADES) and set(df["plan"]) == set(bench.PLANS)
    fams = set(df["family"])
    assert {"gyro:N", "accel:N", "gyro:bias_repeatability_noise_corrected",
            "accel:bias_repeatability_noise_corrected"} <= fams
    assert any(f.endswith(":markov_fit") for f in fams) and any(f.endswith(":bound") for f in fams)
    two = df[df["kind"] == "two_sided"]
    assert (two["lo"] <= two["hi"]).all()
    b = df[df["kind"] == "upper_bound"]
    assert (b["lo"] == 0).all() and (b["covered"] == (b["truth"] <= b["hi"])).all()
    n = two[two["family"].isin(["gyro:N", "accel:N"])]
    assert len(n) >= 40 and np.isfinite(n["z"]).all() and (n["z"].abs() < 5).all()
    assert n["covered"].mean() >= 0.8
    tabs = bench.summarize(df)
    text = bench.markdown(tabs, {"seed": 77, "trials": 9, "duration_s": 240.0, "cycles": 3, "seconds": 0,
                                 "command": "test"})
    assert "| gyro:N |" in text
    # zero truths (accelerometer Q on the device plan): counted, with the share printed two-sided there
    allr = tabs["term_all_reports"].set_index("family")
    assert allr.loc["accel:Q", "n_truth_zero"] > 0 and 0.0 <= allr.loc["accel:Q", "two_sided_at_zero"] <= 1.0
    assert "two-sided at truth = 0" in text
