"""Bias and scale-factor repeatability over power-cycled runs (seed 000 eq. 23, seed 003 eq. 9)."""

from __future__ import annotations

import numpy as np
import pandas as pd
from scipy import stats

from assets_lib.calibration.rate_fit import fit_gyro_rate
from assets_lib.calibration.repeatability import (
    REPEATABILITY_COLUMNS,
    bias_repeatability,
    repeatability_table,
    scale_factor_repeatability,
)
from synth_plateaus import build_table, random_truth, rate_steps

DEGPH = np.radians(1 / 3600)


def test_chi_square_interval_covers_the_true_spread_at_its_confidence():
    """2000 sets of Q = 7 runs: the 95 % interval on the std covers the true turn-on spread 95 % of the time."""
    rng = np.random.default_rng(0)
    sigma, q, n = 0.3 * DEGPH, 7, 2000
    hits = 0
    for _ in range(n):
        r = bias_repeatability(1.0 * DEGPH + sigma * rng.standard_normal(q))
        hits += r.ci_low <= sigma <= r.ci_high
        assert r.n_runs == q and r.ci_low < r.std < r.ci_high
    assert abs(hits / n - 0.95) < 3.3 * np.sqrt(0.95 * 0.05 / n)


def test_seed000_definition_and_noise_correction():
    vals = np.array([0.11, 0.09, 0.12, 0.10, 0.08, 0.13, 0.10]) * DEGPH
    r = bias_repeatability(vals, np.full(7, 0.01 * DEGPH))
    # eq. 23: sqrt(sum (B_i - mean)^2 / (Q - 1)), written out
    eq23 = np.sqrt(np.sum((vals - vals.sum() / 7) ** 2) / 6)
    assert np.isclose(r.std, eq23)
    assert r.std_noise_corrected < r.std
    assert np.isclose(r.std_noise_corrected**2, r.std**2 - (0.01 * DEGPH) ** 2)
    # a single run has no repeatability
    assert np.isnan(bias_repeatability(vals[:1]).std)


def test_scale_factor_repeatability_is_relative():
    k = 1.0 + np.array([10, -5, 3, 8, -2, 0]) * 1e-6
    r = scale_factor_repeatability(k)
    assert r.relative and np.isclose(r.std, np.std(k, ddof=1) / np.mean(k))
    assert r.ci_low < r.std < r.ci_high


def test_repeatability_table_over_power_cycled_rate_runs():
    """Seven runs of one FOG: per-run bias drawn with a 0.05 deg/h turn-on spread, scale factor with 3 ppm;
    the table reports both per axis with the run count and a chi-square interval that contains the truth."""
    rng = np.random.default_rng(3)
    base = random_truth(rng, "tactical")
    base.Gg[:] = 0.0
    s_b, s_k = 0.05 * DEGPH, 3e-6
    tables = []
    for r in range(7):
        t = random_truth(np.random.default_rng(100 + r), "tactical")
        t.Kg, t.Eg, t.Gg = base.Kg * (1 + s_k * rng.standard_normal(3)), base.Eg, base.Gg
        t.bg = base.bg + s_b * rng.standard_normal(3)
        tab = build_table(t, rate_steps(), rng=rng, gyro_sem=0.002 * DEGPH * 60, run_id=f"R{r}")
        tables.append(fit_gyro_rate(tab, cross_check=False).coefficient_table())
    rep = repeatability_table(pd.concat(tables, ignore_index=True))
    assert list(rep.columns) == REPEATABILITY_COLUMNS
    assert len(rep) == 6 and (rep.n_runs == 7).all()
    br = rep[rep.coefficient == "bias_repeatability"]
    assert (br.unit_lab == "deg/h").all()
    assert ((br.ci_low <= s_b * 1.0) & (s_b <= br.ci_high)).sum() >= 2  # 95 % intervals, 3 axes
    kr = rep[rep.coefficient == "scale_factor_repeatability"]
    assert (kr.unit_lab == "ppm").all()
    assert ((kr.ci_low <= s_k) & (s_k <= kr.ci_high)).sum() >= 2
    assert np.allclose(kr.value_lab, kr.value * 1e6)
    # the interval is the chi-square one
    nu = 6
    r0 = br.iloc[0]
    assert np.isclose(r0.ci_high / r0.value, np.sqrt(nu / stats.chi2.ppf(0.025, nu)))
