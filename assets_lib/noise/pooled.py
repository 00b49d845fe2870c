"""The [IEEE952] noise model pooled over many short windows of one channel (the plateaus of a run).

[IEEE952] Annex C terms fitted to the EDF-weighted mean overlapping Allan variance ([NIST1065] eq. 11) of all
windows, each window keeping its own white level; the model gives the Allan variance at any window length
(the standard error of a plateau mean, :mod:`assets_lib.calibration.segmentation.window_stats`) and the
variance of the difference of two window means. :func:`overlapping_avar` is the compact cumulative-sum form
of the estimator for windows of a few thousand samples; it agrees with :func:`assets_lib.noise.allan.oadev`
to ~1e-15 relative (tests/test_segmentation.py) but keeps its own summation order, which the stored plateau
standard errors are computed in.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np
from scipy.optimize import nnls

TWO_PI = 2.0 * np.pi
#: chi^2 gain a correlated-noise term (B or K) must bring to enter the SEM model: <= 5 % false selection on
#: white noise (calibrated by simulation on 24-39 windows of 12-60 s at 100 Hz)
MODEL_PENALTY = 6.0


@dataclass(frozen=True)
class PooledAllanFit:
    """[IEEE952] Annex C model fitted to all plateaus of one channel: per-plateau Q_k^2, N_k^2; shared B-term, K^2."""

    q2: np.ndarray
    n2: np.ndarray
    flicker_avar: float  # (2 ln 2 / pi) B^2
    k2: float
    #: (2 ln 2 / pi) B^2 of the same fit with the B term kept (no MODEL_PENALTY): the best estimate of a 1/f level
    #: the selection did not admit into the SEM model (an undetected B is not a zero one: the run mean still wanders)
    flicker_avar_estimate: float = 0.0

    @property
    def flicker_avar_best(self) -> float:
        """(2 ln 2 / pi) B^2 ([IEEE952] C.3) to carry on: the selected term, else the kept-B estimate, never < 0."""
        return max(self.flicker_avar, self.flicker_avar_estimate, 0.0)

    def avar(self, k: int, tau_s: float | np.ndarray) -> np.ndarray:
        """[IEEE952] eq. C.23 for plateau k: 3Q^2/tau^2 + N^2/tau + (2 ln2/pi) B^2 + K^2 tau / 3."""
        tau = np.asarray(tau_s, dtype=float)
        return 3 * self.q2[k] / tau**2 + self.n2[k] / tau + self.flicker_avar + self.k2 * tau / 3


def flicker_b_of_avar(avar: float) -> float:
    """[IEEE952] C.3: the bias-instability coefficient B of an Allan floor (2 ln2 / pi) B^2 (0 for a floor <= 0)."""
    return float(np.sqrt(max(float(avar), 0.0) * np.pi / (2 * np.log(2))))


def overlapping_avar(x: np.ndarray, m_list) -> tuple[np.ndarray, np.ndarray]:
    """[NIST1065] eq. 11 (overlapping Allan variance) of rate samples ``x`` at cluster sizes ``m_list``.

    Returns (avar, n_terms) per m; avar in units of x^2.
    """
    x = np.asarray(x, dtype=float)
    c = np.concatenate(([0.0], np.cumsum(x - x.mean())))
    out, terms = [], []
    for m in m_list:
        ybar = (c[m:] - c[:-m]) / m
        d = ybar[m:] - ybar[:-m]
        out.append(0.5 * np.mean(d * d) if d.size else np.nan)
        terms.append(d.size)
    return np.asarray(out), np.asarray(terms)


def fit_pooled_allan(segments: list[np.ndarray], dt_s: float, max_cluster_fraction: float = 0.5) -> PooledAllanFit:
    """[IEEE952] Annex C fitted to the EDF-weighted mean Allan variance of all windows of one channel.

    Each window contributes its overlapping Allan variance at octave cluster sizes and at the median window's
    ``max_cluster_fraction * n`` (the longest tau inside a window); the EDF-weighted average over windows is
    fitted with white (N), quantization (Q) and, when they lower chi^2 by more than ``MODEL_PENALTY`` each, bias
    instability (B) and rate random walk (K), by non-negative least squares in relative error (weights
    sqrt(EDF), EDF ~ (n - 2m + 1) / m, re-weighted by the model). Each window's Q^2, N^2 are the pooled values
    scaled by the median ratio of its own short-tau (m <= 16) Allan variance to the model (a noisier plateau keeps
    its own white level); B and K are shared.
    """
    p = len(segments)
    ns = np.array([len(s) for s in segments])
    valid = np.flatnonzero(ns >= 4)
    if valid.size == 0:
        return PooledAllanFit(np.zeros(p), np.zeros(p), 0.0, 0.0)
    caps = np.maximum(1, (max_cluster_fraction * ns[valid]).astype(int))
    grid = np.unique(np.concatenate([2 ** np.arange(int(np.log2(caps.max())) + 1), [int(np.median(caps))]]))
    av = np.full((p, grid.size), np.nan)
    edf = np.zeros((p, grid.size))
    for k, cap in zip(valid, caps):
        sel = grid <= cap
        a, _ = overlapping_avar(segments[k], grid[sel])
        av[k, sel] = a
        edf[k, sel] = np.maximum(1.0, (ns[k] - 2 * grid[sel] + 1) / grid[sel])
    edf = np.where(np.isfinite(av) & (av > 0), edf, 0.0)
    e_sum = edf.sum(axis=0)
    ok = e_sum > 0
    pooled = np.nansum(np.where(edf > 0, av, 0.0) * edf, axis=0)[ok] / e_sum[ok]
    tau = grid[ok] * dt_s
    a_mat = _design(tau)
    w = np.sqrt(e_sum[ok])
    best, fits = _select_terms(a_mat, pooled, w)
    q2, n2, fl, k2 = best
    fl_est = float(fits[(0, 1, 2, 3) if k2 > 0 else (0, 1, 2)][2])  # B kept, K as selected
    model = a_mat @ best
    short = grid[ok] <= 16
    scale = np.ones(p)
    for k in valid:
        r = av[k, ok][short] / model[short]
        r = r[np.isfinite(r)]
        if r.size:
            scale[k] = float(np.median(r))
    return PooledAllanFit(scale * q2, scale * n2, float(fl), float(k2), fl_est)


def _design(tau: np.ndarray) -> np.ndarray:
    """[IEEE952] eq. C.23 columns for theta = (Q^2, N^2, (2 ln 2 / pi) B^2, K^2)."""
    tau = np.asarray(tau, dtype=float)
    return np.column_stack([3.0 / tau**2, 1.0 / tau, np.ones_like(tau), tau / 3.0])


def _select_terms(a_mat: np.ndarray, y: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, dict]:
    """Q and N (columns 0, 1) always, each further column of ``a_mat`` (B, K, and R when present) when it lowers
    chi^2 by more than ``MODEL_PENALTY``; every subset is fitted, smaller subsets first (the first minimum wins):
    (selected theta, {columns: theta} of every subset)."""
    optional = range(2, a_mat.shape[1])
    best = None
    fits = {}
    for n_extra in range(len(optional) + 1):
        for extra in itertools.combinations(optional, n_extra):
            cols = (0, 1) + extra
            coef, chi2 = _irls_nnls(a_mat[:, cols], y, w)
            score = chi2 + MODEL_PENALTY * len(extra)
            full = np.zeros(a_mat.shape[1])
            full[list(cols)] = coef
            fits[cols] = full
            if best is None or score < best[0]:
                best = (score, full)
    return best[1], fits


@dataclass(frozen=True)
class PooledCurveFit:
    """[IEEE952] Annex C model of several records of one channel with the same noise (the static records of one
    device), fitted once to their EDF-weighted mean Allan variance; theta = (Q^2, N^2, (2 ln 2 / pi) B^2, K^2,
    R^2) (eq. C.23 with the rate ramp R^2 tau^2 / 2); ``theta_cov`` its Wald covariance (relative AVAR error
    variance 2 / EDF per tau, octave taus taken as independent) over the terms off the zero boundary."""

    theta: np.ndarray
    theta_cov: np.ndarray
    selected: tuple[bool, bool, bool]  # (B, K, R) admitted by the MODEL_PENALTY selection
    n_records: int

    def _gradient(self, tau_s, terms) -> np.ndarray:
        g = _design5(np.atleast_1d(np.asarray(tau_s, dtype=float)))
        g[:, [j for j in range(5) if j not in terms]] = 0.0
        return g

    def avar_dof(self, tau_s, terms=(0, 1, 2, 3, 4)) -> tuple[np.ndarray, np.ndarray]:
        """[IEEE952] eq. C.23 at ``tau_s`` from the ``terms`` (indices into theta) and its degrees of freedom
        2 sigma^4 / (g' C g) (Satterthwaite; inf when the covariance gives it no variance)."""
        g = self._gradient(tau_s, terms)
        a = g @ self.theta
        var = np.einsum("ij,jk,ik->i", g, self.theta_cov, g)
        with np.errstate(divide="ignore", invalid="ignore"):
            dof = np.where(var > 0, 2.0 * a**2 / var, np.inf)
        return a, dof

    def mean_avar_dof(self, tau_s, terms=(0, 1, 2, 3, 4)) -> float:
        """Degrees of freedom of the mean over ``tau_s`` of the model AVAR (one fit's estimates, fully dependent:
        2 mean^2 / (gbar' C gbar), not a Satterthwaite sum over the taus; inf without variance)."""
        g = self._gradient(tau_s, terms).mean(axis=0)
        var = float(g @ self.theta_cov @ g)
        return 2.0 * float(g @ self.theta) ** 2 / var if var > 0 else np.inf


def _design5(tau: np.ndarray) -> np.ndarray:
    """:func:`_design` plus the rate-ramp column tau^2 / 2 ([IEEE952] eq. C.23)."""
    tau = np.asarray(tau, dtype=float)
    return np.column_stack([_design(tau), tau**2 / 2.0])


def fit_pooled_curves(tau_s, avar, edf, nonnegative: bool = True, keep_flicker: bool = False) -> PooledCurveFit:
    """[IEEE952] Annex C fitted to the EDF-weighted mean of the Allan variances of records of one channel.

    ``tau_s``, ``avar``, ``edf``: one array per record (the ``allan`` table of each run: tau, adev^2, edf); the
    curves are averaged per tau weighted by EDF (taus missing from a record weigh zero). Q and N always, B, K and
    R each when it lowers chi^2 by more than ``MODEL_PENALTY`` (relative-error NNLS as :func:`fit_pooled_allan`,
    with the rate-ramp column). ``keep_flicker``: B stays in the model even when not selected; ``nonnegative``:
    the returned theta is the NNLS fit, else the unconstrained weighted least-squares fit of the same terms
    (unbiased where a term is at the resolution limit, but noisy). Covariance: Wald, Var(avar_hat / avar) =
    2 / EDF at each tau ([NIST1065] sec. 5.3). Issue 15 measured the three choices
    (assets_lib.calibration.repeatability module doc); the defaults are the one kept."""
    rows = [(np.asarray(t, float), np.asarray(a, float), np.asarray(e, float)) for t, a, e in zip(tau_s, avar, edf)]
    grid = np.unique(np.concatenate([t[np.isfinite(t) & (t > 0)] for t, _, _ in rows]))
    num = np.zeros(grid.size)
    den = np.zeros(grid.size)
    for t, a, e in rows:
        ok = np.isfinite(t) & np.isfinite(a) & (a > 0) & np.isfinite(e) & (e > 0)
        i = np.searchsorted(grid, t[ok])
        np.add.at(num, i, e[ok] * a[ok])
        np.add.at(den, i, e[ok])
    use = den > 0
    if use.sum() < 6:
        raise ValueError(f"fit_pooled_curves: {int(use.sum())} usable taus over {len(rows)} records; expected >= 6")
    tau, y, e_sum = grid[use], num[use] / den[use], den[use]
    a_mat = _design5(tau)
    w = np.sqrt(e_sum)
    sel = _select_terms(a_mat, y, w)[0]
    cols = [0, 1] + [j for j in (2, 3, 4) if sel[j] > 0 or (j == 2 and keep_flicker)]
    if nonnegative:  # B kept, every term >= 0 (NNLS); the covariance over the terms off the boundary
        coef, _ = _irls_nnls(a_mat[:, cols], y, w)
        theta = np.zeros(5)
        theta[cols] = coef
        model = np.maximum(a_mat @ theta, 1e-300)
        cols = [j for j in cols if theta[j] > 0]
    else:
        model = np.maximum(a_mat @ sel, 1e-300)
    aw = a_mat[:, cols] * (w / model)[:, None] / np.sqrt(2.0)  # whitened: unit-variance relative residuals
    info_inv = np.linalg.pinv(aw.T @ aw)
    if not nonnegative:
        theta = np.zeros(5)
        theta[cols] = info_inv @ (aw.T @ (y * w / model / np.sqrt(2.0)))
    cov = np.zeros((5, 5))
    cov[np.ix_(cols, cols)] = info_inv
    return PooledCurveFit(theta, cov, (bool(sel[2] > 0), bool(sel[3] > 0), bool(sel[4] > 0)), len(rows))


def _irls_nnls(a_mat: np.ndarray, y: np.ndarray, w: np.ndarray, passes: int = 3) -> tuple[np.ndarray, float]:
    """Non-negative least squares in relative error, weights sqrt(EDF)/model re-evaluated from the fit."""
    model = y.copy()
    for _ in range(passes):
        aw = a_mat * (w / model)[:, None]
        scale = np.linalg.norm(aw, axis=0)
        scale[scale == 0] = 1.0
        coef, _ = nnls(aw / scale, y * w / model, maxiter=50 * a_mat.shape[1])
        coef = coef / scale
        model = np.maximum(a_mat @ coef, 1e-300)
    chi2 = 0.5 * float(np.sum((w * (y - model) / model) ** 2))  # var(avar_hat / avar) ~ 2 / EDF
    return coef, chi2


def _diff_transfer2(f: np.ndarray, t_a: float, c_a: float, t_r: float, c_r: float) -> np.ndarray:
    """|H_A(f) - H_R(f)|^2 of the difference of two window means (H_W = sinc(pi f T_W) exp(-2 pi i f c_W))."""
    sa = np.sinc(f * t_a)
    sr = np.sinc(f * t_r)
    return sa * sa + sr * sr - 2 * sa * sr * np.cos(TWO_PI * f * (c_a - c_r))


def mean_difference_variance(fit: PooledAllanFit, k: int, t_a: float, c_a: float, t_r: float, c_r: float,
                             rate_hz: float, n_grid: int = 4000) -> float:
    """Var(ybar_A - ybar_R) of two window means (lengths t_a, t_r, centres c_a, c_r) under the model of window k.

    [IEEE952] Annex C two-sided rate PSDs (as ``assets_lib.sim.noise``): white N^2, flicker B^2/(2 pi f),
    random walk K^2/(2 pi f)^2; Var = int S(f) |H_A - H_R|^2 df. White part in closed form N^2 (1/T_A - 1/T_R)
    (A inside R), quantization as its Allan value 3 Q^2 / T_A^2. For a fit that wants the covariance of plateau
    means (e.g. each plateau against the run mean, or two distant plateaus) rather than the local SEM.
    """
    var = 3 * fit.q2[k] / t_a**2 + fit.n2[k] * max(1.0 / t_a - (1.0 / t_r if t_r > 0 else 0.0), 0.0)
    b2 = fit.flicker_avar * np.pi / (2 * np.log(2))
    if b2 > 0 or fit.k2 > 0:
        f = np.geomspace(1e-4 / max(t_r, t_a), 0.5 * rate_hz, n_grid)
        h2 = _diff_transfer2(f, t_a, c_a, t_r, c_r)
        u = np.log(f)
        if b2 > 0:
            var += b2 / np.pi * np.trapezoid(h2, u)
        if fit.k2 > 0:
            var += fit.k2 / (2 * np.pi**2) * np.trapezoid(h2 / f, u)
    return float(var)
