"""Standard errors of plateau means under correlated noise: sigma_A(T) of the run's pooled [IEEE952] model.

The SEM reported for a window of length T is the square root of the Allan variance at tau = T,
sigma_A^2(T) = 1/2 E[(ybar_{k+1} - ybar_k)^2] ([IEEE952] C.1): the scatter of a T-long mean about its
neighbours. For white noise it equals sigma^2 / n exactly; for bias instability and rate random walk it stays
finite where sigma / sqrt(n) goes to zero (for a random walk it is also the variance of the window mean about
the process value at the window start, K^2 T / 3). sigma_A^2(T) cannot be computed from one window of length T,
so it is read from a noise model ([IEEE952] Annex C terms) fitted to the EDF-weighted mean overlapping Allan
variance of all plateaus of the run (tau up to T/2; :mod:`assets_lib.noise.pooled`): quantization and white
noise always, bias instability and rate random walk only when they improve the fit by more than
``MODEL_PENALTY`` (calibrated so that white noise gains a spurious term in <= 5 % of runs); each plateau keeps
its own white level (a plateau may be noisier, e.g. table vibration). The fit uses the residual y - reference,
so the deterministic once-per-revolution earth-rate sinusoid of a rotating axis is not taken for noise.
Measured on simulated white + flicker + random-walk noise, z-scores of plateau-mean differences have a standard
deviation of 0.95-1.15 (naive sigma/sqrt(n): 1.8-1.9); when the random walk only emerges at tau ~ T the SEM is
up to ~20 % low. Against a bias held fixed over a whole run, plateau means of a flicker-dominated channel
scatter more than sigma_A(T) (the flicker variance grows with log(run length / T));
:func:`assets_lib.noise.pooled.mean_difference_variance` gives that covariance from the same model.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from assets_lib.noise.pooled import PooledAllanFit, fit_pooled_allan


@dataclass(frozen=True)
class SemResult:
    """Standard errors of the means of several windows of one channel, and the naive sigma/sqrt(n) for contrast."""

    sem: np.ndarray
    naive_sem: np.ndarray
    window_s: np.ndarray
    fit: PooledAllanFit


def plateau_sem(segments: list[np.ndarray], dt_s: float, max_cluster_fraction: float = 0.5) -> SemResult:
    """[IEEE952] C.1: SEM_k^2 = sigma_A^2(T_k) of the pooled Annex C model, T_k = n_k dt (module docstring).

    ``segments``: the residual samples (y - reference) of each window of one channel, in run order.
    """
    fit = fit_pooled_allan(segments, dt_s, max_cluster_fraction)
    n = np.array([len(s) for s in segments], dtype=float)
    tk = n * dt_s
    sem = np.array([np.sqrt(fit.avar(k, tk[k])) if n[k] >= 4 else np.nan for k in range(len(segments))])
    naive = np.array([np.std(s, ddof=1) / np.sqrt(len(s)) if len(s) > 1 else np.nan for s in segments])
    return SemResult(sem, naive, tk, fit)
