"""Polynomial-residual outlier rejection (seed 001, robust MAD threshold) on data with known truth."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.stats import binom, norm

from assets_lib.calibration.outliers import (
    MAD_TO_SIGMA,
    OutlierConfig,
    estimate_resolution,
    reject_outliers,
    reject_outliers_window,
)

FS = 100.0


def _t(n: int) -> np.ndarray:
    return np.arange(n) / FS


def test_planted_outliers_recovered_on_drifting_plateau():
    """Spikes of 6-20 sigma planted on a plateau with a slow warm-up drift are all found; clean samples stay."""
    rng = np.random.default_rng(1)
    n = 3000
    t = _t(n)
    drift = 8.0 * (1 - np.exp(-t / 12.0))  # 8 sigma of warm-up over the window: the polynomial must absorb it
    y = drift[:, None] + rng.standard_normal((n, 6))
    idx = rng.choice(n, 40, replace=False)
    ch = rng.integers(0, 6, 40)
    y[idx, ch] += rng.choice([-1.0, 1.0], 40) * rng.uniform(6.0, 20.0, 40)
    w = reject_outliers_window(t, y)
    rejected = set(np.flatnonzero(~w.keep))
    assert set(idx) <= rejected
    assert len(rejected - set(idx)) <= 3  # false rejections among 2960 clean samples (expected ~1.1)
    assert w.converged and w.iterations >= 2
    assert not w.flagged
    np.testing.assert_allclose(w.sigma_per_channel, 1.0, rtol=0.1)


def test_polynomial_keeps_the_threshold_tight_under_drift():
    """Without the polynomial (degree 0) a drift inflates the robust sigma and 8-sigma spikes go unnoticed."""
    rng = np.random.default_rng(2)
    n = 4000
    t = _t(n)
    y = 10.0 * (t / t[-1]) ** 2 + rng.standard_normal(n)
    idx = rng.choice(n, 20, replace=False)
    y[idx] += 8.0 * rng.choice([-1.0, 1.0], 20)
    w7 = reject_outliers_window(t, y, OutlierConfig(degree=7))
    w0 = reject_outliers_window(t, y, OutlierConfig(degree=0))
    assert set(idx) <= set(np.flatnonzero(~w7.keep)) and w7.n_rejected <= 22
    assert w0.sigma_per_channel[0] > 2.5  # the drift counted as noise
    assert len(set(idx) & set(np.flatnonzero(~w0.keep))) < 10


@pytest.mark.parametrize("n_channels", [1, 6])
def test_false_rejection_rate_on_clean_gaussian_within_bound(n_channels):
    """k = 4: per channel P(|z|>4) = 6.3e-5; a sample is lost if any channel rejects it (union bound n_ch x)."""
    rng = np.random.default_rng(10 + n_channels)
    n, trials = 2000, 150
    rej = tot = 0
    for _ in range(trials):
        w = reject_outliers_window(_t(n), rng.standard_normal((n, n_channels)))
        rej += w.n_rejected
        tot += w.n_samples
    p_theory = n_channels * 2 * norm.sf(4.0)
    # the ~1e-3 budget of the design, and no more than a binomial 99.9 % quantile above 1.5x theory (MAD scatter)
    assert rej / tot <= 1e-3
    assert rej <= binom.ppf(0.999, tot, 1.5 * p_theory)
    assert rej >= binom.ppf(0.001, tot, 0.5 * p_theory)


def test_plateau_losing_too_much_is_flagged_with_reason():
    rng = np.random.default_rng(3)
    n = 2000
    y = rng.standard_normal((n, 3))
    y[500:700, 1] += 30.0  # a 2-s knock on one axis: 10 % of the plateau
    w = reject_outliers_window(_t(n), y, OutlierConfig(max_rejected_fraction=0.05))
    assert w.flagged
    assert "rejected" in w.flag_reason and "> 5%" in w.flag_reason
    assert w.rejected_fraction == pytest.approx(0.1, abs=0.005)
    assert w.rejected_per_channel[1] >= 200 and w.rejected_per_channel[0] <= 2


def test_quantized_channel_does_not_lose_its_one_count_samples():
    """Noise of 0.3 counts: MAD = 0; the sigma floor at one count keeps the +-1 count samples (~10 % of them)."""
    rng = np.random.default_rng(4)
    y = np.rint(0.3 * rng.standard_normal((5000, 3)))
    assert estimate_resolution(y[:, 0]) == 1.0
    assert np.median(np.abs(y[:, 0])) == 0.0  # the MAD collapses
    w = reject_outliers_window(_t(5000), y)
    assert w.n_rejected == 0
    w_nofloor = reject_outliers_window(_t(5000), y, resolution=[None, None, None])
    assert w_nofloor.rejected_fraction > 0.05 and w_nofloor.flagged


def test_estimate_resolution_on_continuous_and_scaled_counts():
    rng = np.random.default_rng(5)
    assert estimate_resolution(rng.standard_normal(1000)) is None
    lsb = np.radians(1 / 131.0)
    counts = np.rint(40 * rng.standard_normal(5000))
    assert estimate_resolution(counts * lsb) == pytest.approx(lsb, rel=1e-9)


def test_hashed_levels_are_numpys_sorted_unique_values():
    from assets_lib.calibration.outliers import _sorted_unique

    rng = np.random.default_rng(6)
    for v in (np.rint(3 * rng.standard_normal(4000)) * 0.01, rng.standard_normal(300),
              np.where(rng.random(500) < 0.5, 0.0, -0.0) + np.rint(rng.standard_normal(500)) * 2e-3):
        u = _sorted_unique(v)
        assert np.array_equal(u, np.unique(v)) and np.all(np.diff(u) > 0)


def test_channels_judged_together_as_one_at_a_time():
    """The first pass is shared by the channels (one design, medians along an axis): each channel's mask and
    robust sigma are those of the channel alone, bit for bit, and a sample is kept when every channel keeps it."""
    rng = np.random.default_rng(7)
    n = 3000
    y = rng.standard_normal((n, 4)) * [1.0, 2e-3, 5.0, 1.0] + np.linspace(0, 1, n)[:, None]
    y[rng.choice(n, 40, replace=False), 0] += 30.0
    y[:, 3] = np.rint(y[:, 3])
    res = [None, None, None, 1.0]
    w = reject_outliers_window(_t(n), y, resolution=res)
    alone = [reject_outliers_window(_t(n), y[:, j], resolution=res[j]) for j in range(4)]
    assert w.sigma_per_channel.tobytes() == np.concatenate([a.sigma_per_channel for a in alone]).tobytes()
    assert np.array_equal(w.keep, np.logical_and.reduce([a.keep for a in alone]))
    assert w.rejected_per_channel.tolist() == [a.n_rejected for a in alone] and w.rejected_per_channel[0] >= 40


def test_reject_outliers_over_plateaus_summary_and_mask():
    rng = np.random.default_rng(6)
    n = 6000
    t = _t(n)
    y = rng.standard_normal((n, 2))
    pid = np.full(n, -1)
    pid[100:2100] = 0
    pid[2500:4500] = 1
    pid[5000:5050] = 2
    y[1000, 0] = 50.0
    y[3000, 1] = -50.0
    res = reject_outliers(t, y, pid)
    assert not res.keep[pid == -1].any()
    assert not res.keep[1000] and not res.keep[3000]
    s = res.summary.set_index("plateau")
    assert list(s.index) == [0, 1, 2]
    assert s.loc[0, "n_rejected"] >= 1 and s.loc[1, "n_rejected"] >= 1
    assert s.loc[0, "n_samples"] == 2000
    assert s.loc[2, "degree_used"] == 0  # 50 samples: one coefficient per >= 50 samples
    assert res.summary["rejected_fraction"].max() < 0.005


def test_mad_constant():
    assert MAD_TO_SIGMA == pytest.approx(1 / norm.ppf(0.75), rel=1e-12)
