"""[IEEE952] noise terms from an Allan variance curve: generalised least squares with intervals, and slope reads.

[IEEE952] Annex C (C.23): sigma^2(tau) = 3Q^2/tau^2 + N^2/tau + (2 ln2/pi) B^2 + K^2 tau/3 + R^2 tau^2/2,
optionally + first-order Markov (C.25) and sinusoid (C.27) terms ([SEED002] sec. 2.2 (1)-(7)).

Estimator: the model is linear in theta = (Q^2, N^2, B^2, K^2, R^2[, ...]). The AVAR
points are heteroscedastic and strongly correlated across tau, so they are fitted by non-negative generalised
least squares with their covariance V evaluated at the current model (iterated):
- variances V_jj = 2 sigma^4_model(tau_j) / edf_j, edf from [GREENHALL2003] at the model's local
  power-law exponent (interpolated between integer alphas), or the sampled-data large-n variance below when
  that is larger (m = 1: white rate samples give EDF 2n/3, Greenhall's filter F = m 0.78 n);
- correlations from the large-n Gaussian approximation
  Cov(s2_j, s2_k) ~ min(n_j, n_k) / (n_j n_k tau0) * integral_0^{fs/2} S(f)^2 |H_j(f)|^2 |H_k(f)|^2 df,
  |H_m(f)|^2 = 4 sin^4(pi f m tau0)/(m sin(pi f tau0))^2 (sampled rate data), S the model's two-sided rate PSD
  (the generalisation of [VACCARO2012] to the [IEEE952] mixture).
Terms the data do not support are eliminated backwards (a term whose two-sided Wald interval reaches zero is
dropped, the least significant first, and the rest refitted: a boundary term biases its collinear neighbours).
Whether the record identifies a term at all is decided on the profile likelihood of the AVAR points with their
full covariance V ([NIST1065] sec. 5, [VENZON1988]): the set of theta_k whose profile GLS chi2, every other term
free and non-negative, lies within chi2_1(level) of the minimum. When that set reaches zero (collinear long-tau
terms, B, K and R on a short record, can trade places) the term is reported as a one-sided upper bound (the
profile set's upper end), not as a number, whatever the elimination kept; the report switches between the two
on the same likelihood ([FELDMAN1998]). A term the record identifies gets a Satterthwaite chi-square interval
(theta is a variance) from the active-set Wald covariance (X_A' V^-1 X_A)^-1 ([LAWSON1974]: terms at zero are
constraints; lowering its lower end to the profile's, which extends toward the neighbours put at zero, over-covered
N and B, z sd 0.7-0.8 in benchmarks/coverage_noise.py), except the long-tau terms B, K and R: they trade places
with each other, so the active set (a dropped K or R held at zero) charges their share of the long-tau AVAR to the
kept term with no uncertainty (B two-sided coverage 0.89-0.91); their two-sided interval is the profile set itself,
and their printed value its centre (the fit with every term free), not the eliminated fit's.
The quantization term's PSD in V is the sampled one, (4 Q^2 / tau0) sin^2(pi f tau0) ([IEEE952] C.2), not its
small-f form, which overstated the variance of Q-dominated short-tau points 1.3-1.9x. The Markov correlation time
comes from a profile GLS chi2 on a fine grid; its profile set is printed as markov_tc's interval and markov_q's
interval is the joint profile-likelihood set of (q_c, T_c) projected on q_c (every other term and T_c free); whether
the record holds a Markov term at all is tested with the supremum of the likelihood-ratio gain over the T_c grid
([DAVIES1987]: T_c exists only under the alternative), else q_c and T_c are bounds. T_c is a nuisance parameter of
the long-tau terms too (a long-T_c hump trades places with B and K): in a Markov fit their profile sets are the
union over the T_c set of each T_c's profile interval, cut at the global minimum. benchmarks/coverage_noise.py measures the coverage of
every printed interval.
The classic slope reads (N at tau = 1 s on the -1/2 line, K at tau = 3 s on the +1/2 line, B = flat minimum /
0.664, Q at tau = sqrt(3) s, R at tau = sqrt(2) s) are given beside the fit (method 'slope'); they are biased
when terms overlap ([GUERRIER2016]) and benchmarks/mc_noise_id.py measures by how much.

Real curves (docs/realdata.md). A real sensor's curve departs from the ideal mixture (anti-alias and decimation
filters, flicker that is not exactly 1/f, temperature): the short-tau points carry millions of degrees of
freedom, so with purely statistical weights they dominate the fit and a model that misses them by a few percent
is pulled far off everywhere else (chi2/dof ~ 2000 on a real phone record). Three safeguards:

* **Model discrepancy in the weights.** When the GLS chi2 exceeds its 99.9 % chi-square quantile, a relative
  discrepancy variance delta^2 sigma^4_model(tau) is added to every point's variance (a fractional model error
  common to all taus, the additive model-discrepancy term of Kennedy & O'Hagan 2001), with delta solved so that
  chi2 / dof = 1; the term intervals widen accordingly. ``delta`` is reported (``NoiseFit.discrepancy``).
* **Tau range.** ``tau_min_s`` / ``tau_max_s`` restrict the fit (default: every tau with at least
  ``min_terms`` terms and m <= N/4). The range used is reported (``NoiseFit.tau_range_s``).
* **Check against the curve.** The fitted model is compared with the curve's chi-square intervals at a
  family-wise ``check_ci`` (99 % over all fitted taus, Bonferroni) over the fit range; every contiguous tau range where it leaves them is named in
  ``NoiseFit.warnings`` (with the model/curve ratio), so the CLI, record and certificate can say so loudly.

Slope reads use only points with at least ``min_edf`` degrees of freedom (the last points of a curve have 1-3,
a +-50 % interval, and a slope through them can be anything).
"""

from __future__ import annotations

import functools
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
import pandas as pd
from scipy import optimize, stats

from assets_lib.coefficient import Coefficient
from assets_lib.noise.allan import AllanResult
from assets_lib.noise.intervals import edf_greenhall
from raw_schemas.units import lab_unit

LN2_PI = 2.0 * math.log(2.0) / math.pi  # (2 ln2 / pi): B plateau factor, sqrt = 0.664
TERMS = ("Q", "N", "B", "K", "R")
#: local log-log slope of sigma^2 for each term (alpha = -slope - 1 for the EDF)
#: terms collinear at the long-tau end of a record, intervals from the profile likelihood (fit_noise)
_LONG_TAU_TERMS = ("B", "K", "R")
_TERM_ALPHA = {"Q": 2.0, "N": 0.0, "B": -1.0, "K": -2.0, "R": -2.0, "M": 0.0, "S": 0.0}

def sensor_of(channel: str = "", unit: str = "") -> str:
    """'gyro' | 'accel' | 'si' from a channel name (gyro_*, accel_*) or an SI unit string."""
    c = channel.lower()
    if c.startswith("gyro") or "radps" in c:
        return "gyro"
    if c.startswith("acc") or "mps2" in c:
        return "accel"
    if unit == "rad/s":
        return "gyro"
    if unit in ("m/s^2", "m/s2"):
        return "accel"
    return "si"


# --------------------------------------------------------------------------------------------------------------
# model basis
# --------------------------------------------------------------------------------------------------------------
def basis(tau_s: np.ndarray, terms: Sequence[str] = TERMS) -> np.ndarray:
    """[IEEE952] eq. C.23: columns g_k(tau) with sigma^2 = sum_k theta_k g_k, theta = (Q^2, N^2, ...)."""
    tau = np.asarray(tau_s, dtype=float)
    cols = {
        "Q": 3.0 / tau**2,
        "N": 1.0 / tau,
        "B": np.full_like(tau, LN2_PI),
        "K": tau / 3.0,
        "R": tau**2 / 2.0,
    }
    return np.column_stack([cols[t] for t in terms])


def markov_avar_unit(tau_s: np.ndarray, tc_s: float) -> np.ndarray:
    """[IEEE952] eq. C.25 ([SEED002] (6)): AVAR of a first-order Markov rate with (q_c T_c)^2 = 1."""
    tau = np.asarray(tau_s, dtype=float)
    r = tau / tc_s
    return (1.0 / tau) * (1.0 - (1.0 / (2.0 * r)) * (3.0 - 4.0 * np.exp(-r) + np.exp(-2.0 * r)))


def sinusoid_avar_unit(tau_s: np.ndarray, f0_hz: float) -> np.ndarray:
    """[IEEE952] eq. C.27 ([SEED002] (7)): AVAR of a sinusoidal rate of unit amplitude at f0."""
    x = math.pi * f0_hz * np.asarray(tau_s, dtype=float)
    return (np.sin(x) ** 2 / x) ** 2


# --------------------------------------------------------------------------------------------------------------
# covariance of AVAR estimates at a model
# --------------------------------------------------------------------------------------------------------------
def _psd_two_sided(f: np.ndarray, theta: Mapping[str, float], tau0: float, tc_s: float | None) -> np.ndarray:
    """[IEEE952] Annex C (C.2-C.6): two-sided rate PSD of the model terms (random terms only)."""
    w = 2.0 * np.pi * f
    S = np.zeros_like(f)
    # quantization: white angle noise of the samples, differenced: (4 Q^2 / tau0) sin^2(pi f tau0) ([IEEE952] C.2
    # before its small-f form tau0 Q^2 w^2, which overstates the PSD near Nyquist by up to pi^2 / 4 and so the
    # variance of the short-tau AVAR points where Q dominates: Q intervals 1.25x too wide, z sd 0.8)
    S += theta.get("Q", 0.0) * 4.0 * np.sin(np.pi * f * tau0) ** 2 / tau0
    S += theta.get("N", 0.0)
    S += theta.get("B", 0.0) / (2.0 * np.pi * f)
    S += theta.get("K", 0.0) / w**2
    if tc_s is not None and theta.get("M", 0.0) > 0:
        # (q_c T_c)^2 = theta_M; Lorentzian with the same low-frequency level as an ARW of N^2 = theta_M
        S += theta["M"] / (1.0 + (w * tc_s) ** 2)
    return S


def avar_correlation(
    tau_s: np.ndarray, n_terms: np.ndarray, theta: Mapping[str, float], rate_hz: float, tc_s: float | None = None
) -> np.ndarray:
    """Large-n Gaussian correlation of overlapping AVAR estimates at a model ([VACCARO2012], generalised)."""
    cov = avar_covariance_large_n(tau_s, n_terms, theta, rate_hz, tc_s)
    d = np.sqrt(np.diag(cov))
    R = cov / np.outer(d, d)
    np.fill_diagonal(R, 1.0)
    return R


@functools.lru_cache(maxsize=64)
def _avar_transfer(tau_bytes: bytes, rate_hz: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The model-free part of :func:`avar_covariance_large_n` at the taus (``tau_bytes``, float64) and rate: the log
    frequency grid, its weights, |H_m(f)|^2 per tau and the diagonal's factor; a fit evaluates the covariance at
    hundreds of models on the same taus, so these are computed once (read-only arrays)."""
    tau = np.frombuffer(tau_bytes, dtype=float)
    tau0 = 1.0 / rate_hz
    m = np.maximum(np.rint(tau / tau0), 1.0)
    f_lo = 1e-3 / tau.max()
    f_hi = 0.5 * rate_hz
    c = 8.0  # above f tau = c the sin^4 factor is replaced by its mean 3/8
    n_grid = int(np.ceil(np.log10(f_hi / f_lo) * 200)) + 2
    f = np.geomspace(f_lo, f_hi, n_grid)
    lnf = np.log(f)
    df = np.gradient(lnf) * f  # trapezoid-like weights on the log grid
    u = np.pi * np.outer(f, tau)  # (grid, taus)
    fast = np.outer(f, tau) > c
    s4 = np.where(fast, 3.0 / 8.0, np.sin(u) ** 4)
    G = 4.0 * s4 / (np.outer(np.sin(np.pi * f * tau0), m)) ** 2
    # diagonal: the mean of sin^8 is 35/128, not (3/8)^2
    G_diag = G * np.where(fast, 35.0 / 18.0, 1.0)
    for arr in (f, df, G, G_diag):
        arr.flags.writeable = False
    return f, df, G, G_diag


def avar_covariance_large_n(
    tau_s: np.ndarray, n_terms: np.ndarray, theta: Mapping[str, float], rate_hz: float, tc_s: float | None = None
) -> np.ndarray:
    """Large-n Gaussian covariance of overlapping AVAR estimates of sampled rate data at a model.

    With d^j_i the second differences at tau_j = m_j tau0 (A_j = mean(d^j^2) / 2), for a Gaussian model
    Cov(A_j, A_k) ~ min(n_j, n_k) / (n_j n_k tau0) * int_0^{fs/2} S(f)^2 |H_j(f)|^2 |H_k(f)|^2 df
    (Isserlis and Parseval; [VACCARO2012] generalised to the [IEEE952] mixture), S the two-sided rate PSD and
    |H_m(f)|^2 = 4 sin^4(pi f m tau0) / (m sin(pi f tau0))^2 the transfer of m-sample averages differenced at lag
    m: the transfer of sampled data, exact at m = 1 where the continuous 4 sin^4(pi f tau) / (pi f tau)^2 (and
    [GREENHALL2003]'s filter F = m) overstate the white-noise degrees of freedom by 17 %.
    """
    tau = np.asarray(tau_s, dtype=float)
    tau0 = 1.0 / rate_hz
    f, df, G, G_diag = _avar_transfer(tau.tobytes(), float(rate_hz))
    S = _psd_two_sided(f, theta, tau0, tc_s)
    Wv = (S**2 * df)[:, None]
    I = (G * Wv).T @ G
    diag = np.einsum("gj,gj->j", G * Wv, G_diag)
    I[np.diag_indices_from(I)] = diag
    n = np.asarray(n_terms, dtype=float)
    nmin = np.minimum.outer(n, n)
    return nmin / np.outer(n, n) * I / tau0


def _edf_mix(tau: np.ndarray, parts: np.ndarray, alphas: np.ndarray, m: np.ndarray, n_phase: int) -> np.ndarray:
    """Greenhall EDF at the mixture's local power-law exponent (interpolated between integer alphas)."""
    tot = parts.sum(axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        share = np.where(tot[:, None] > 0, parts / tot[:, None], 0.0)
    a_eff = np.clip((share * alphas[None, :]).sum(axis=1), -2.0, 2.0)
    out = np.empty(len(tau))
    for j in range(len(tau)):
        lo = math.floor(a_eff[j])
        hi = min(lo + 1, 2)
        w = a_eff[j] - lo
        e_lo = edf_greenhall(int(lo), 2, int(m[j]), n_phase, True, False)
        e_hi = edf_greenhall(int(hi), 2, int(m[j]), n_phase, True, False) if w > 0 else e_lo
        out[j] = (1.0 - w) * e_lo + w * e_hi
    return out


# --------------------------------------------------------------------------------------------------------------
# results
# --------------------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class NoiseParameter:
    """One noise term: its SI :class:`Coefficient` (interval at ``ci_level``), method and upper-bound flag.

    ``estimate.value`` is NaN when the term is only bounded (``is_upper_bound``; ``ci_hi`` is the bound);
    ``estimate.stderr`` is the delta-method standard error of a fitted term (NaN for slope reads and bounds).
    Lab units come from the one lab-unit table, ``raw_schemas.units.lab_unit``.
    """

    name: str
    estimate: Coefficient
    sensor: str  #: 'gyro' | 'accel' | 'si' (selects the lab units)
    method: str  #: 'fit' | 'slope'
    is_upper_bound: bool

    value = property(lambda self: self.estimate.value)
    ci_lo = property(lambda self: self.estimate.ci_low)
    ci_hi = property(lambda self: self.estimate.ci_high)
    unit = property(lambda self: self.estimate.unit)
    ci_level = property(lambda self: self.estimate.ci_level)

    @property
    def lab(self) -> Coefficient:
        return self.estimate.to_lab(lab_unit(self.sensor, self.name))

    value_lab = property(lambda self: self.lab.value)
    ci_lo_lab = property(lambda self: self.lab.ci_low)
    ci_hi_lab = property(lambda self: self.lab.ci_high)
    unit_lab = property(lambda self: self.lab.unit)

    def as_dict(self) -> dict:
        """Flat record (the NOISE TABLE columns but the channel, plus the standard error)."""
        lab = self.lab
        return {"name": self.name, "value": self.value, "stderr": self.estimate.stderr, "ci_lo": self.ci_lo,
                "ci_hi": self.ci_hi, "unit": self.unit, "value_lab": lab.value, "ci_lo_lab": lab.ci_low,
                "ci_hi_lab": lab.ci_high, "unit_lab": lab.unit, "method": self.method,
                "is_upper_bound": self.is_upper_bound, "ci_level": self.ci_level}


@dataclass(frozen=True)
class NoiseFit:
    """[IEEE952] fit of one channel: parameters, theta (variances) and their covariance, the model curve."""

    channel: str
    sensor: str
    parameters: tuple  #: NoiseParameter, method 'fit'
    slope_parameters: tuple  #: NoiseParameter, method 'slope'
    terms: tuple  #: names of theta entries ('Q', 'N', 'B', 'K', 'R'[, 'M'][, 'S'])
    theta: np.ndarray  #: (Q^2, N^2, B^2, K^2, R^2, ...) SI
    theta_cov: np.ndarray
    tau_s: np.ndarray  #: taus used by the fit
    avar: np.ndarray  #: measured AVAR at those taus
    chi2: float  #: generalised residual sum of squares
    dof: int
    markov_tc_s: float | None = None
    sin_f0_hz: float | None = None
    iterations: int = 0
    tau_range_s: tuple = (math.nan, math.nan)  #: (min, max) tau used by the fit
    discrepancy: float = 0.0  #: relative model discrepancy delta added to the weights (0: none needed)
    outside_tau_ranges: tuple = ()  #: ((tau_lo, tau_hi, min ratio, max ratio), ...) model/curve outside check_ci
    warnings: tuple = ()

    @property
    def matches_curve(self) -> bool:
        return not self.outside_tau_ranges

    def term_avar(self, tau_s: np.ndarray) -> dict[str, np.ndarray]:
        """[IEEE952] eq. C.23: each term's contribution to sigma^2(tau)."""
        tau = np.asarray(tau_s, dtype=float)
        out = {}
        for k, t in enumerate(self.terms):
            if t in TERMS:
                out[t] = self.theta[k] * basis(tau, (t,))[:, 0]
            elif t == "M":
                out[t] = self.theta[k] * markov_avar_unit(tau, self.markov_tc_s)
            elif t == "S":
                out[t] = self.theta[k] * sinusoid_avar_unit(tau, self.sin_f0_hz)
        return out

    def model_avar(self, tau_s: np.ndarray) -> np.ndarray:
        parts = self.term_avar(tau_s)
        return np.sum(list(parts.values()), axis=0) if parts else np.zeros(np.shape(tau_s))

    def design(self, tau_s: np.ndarray) -> np.ndarray:
        """Columns g_k(tau) of the fitted terms ([IEEE952] C.23, C.25, C.27): sigma^2(tau) = design @ theta."""
        tau = np.asarray(tau_s, dtype=float)
        cols = []
        for t in self.terms:
            if t in TERMS:
                cols.append(basis(tau, (t,))[:, 0])
            elif t == "M":
                cols.append(markov_avar_unit(tau, self.markov_tc_s))
            else:
                cols.append(sinusoid_avar_unit(tau, self.sin_f0_hz))
        return np.column_stack(cols)

    def model_avar_dof(self, tau_s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The model AVAR at ``tau_s`` and its degrees of freedom 2 sigma^4 / (g' C g) (Satterthwaite, C the
        Wald covariance of theta; inf when C gives it no variance)."""
        g = self.design(tau_s)
        a = g @ self.theta
        var = np.einsum("ij,jk,ik->i", g, self.theta_cov, g)
        with np.errstate(divide="ignore", invalid="ignore"):
            dof = np.where(var > 0, 2.0 * a**2 / var, np.inf)
        return a, dof

    def parameter(self, name: str, method: str = "fit") -> NoiseParameter:
        for p in self.parameters if method == "fit" else self.slope_parameters:
            if p.name == name:
                return p
        raise KeyError(name)


def _param(name, value, lo, hi, sensor, method, upper, ci_level, stderr=math.nan) -> NoiseParameter:
    est = Coefficient(float(value), float(stderr), lab_unit(sensor, name).si, not upper, float(lo), float(hi),
                      float(ci_level))
    return NoiseParameter(name=name, estimate=est, sensor=sensor, method=method, is_upper_bound=bool(upper))


# --------------------------------------------------------------------------------------------------------------
# the fit
# --------------------------------------------------------------------------------------------------------------
def _nn_gls(X: np.ndarray, a: np.ndarray, V: np.ndarray) -> tuple[np.ndarray, float]:
    """min (a - X t)' V^-1 (a - X t) subject to t >= 0 ([LAWSON1974] NNLS on the whitened system)."""
    L = np.linalg.cholesky(V)
    Xw = np.linalg.solve(L, X)
    aw = np.linalg.solve(L, a)
    scale = np.linalg.norm(Xw, axis=0)
    scale[scale == 0] = 1.0
    t, rnorm = optimize.nnls(Xw / scale, aw, maxiter=50 * X.shape[1])
    return t / scale, float(rnorm**2)


def _regularise(V: np.ndarray) -> np.ndarray:
    d = np.sqrt(np.diag(V))
    R = V / np.outer(d, d)
    R = 0.999 * R + 0.001 * np.eye(len(d))  # keeps the near-singular dense-grid correlation invertible
    return R * np.outer(d, d)


def _select(res: AllanResult, max_m_fraction: float, min_terms: int, tau_min_s: float | None = None,
            tau_max_s: float | None = None) -> np.ndarray:
    ok = (res.n_terms >= min_terms) & (res.m <= max_m_fraction * res.n_samples) & np.isfinite(res.adev)
    ok &= res.adev > 0
    if tau_min_s is not None:
        ok &= res.tau_s >= tau_min_s * (1 - 1e-9)
    if tau_max_s is not None:
        ok &= res.tau_s <= tau_max_s * (1 + 1e-9)
    return ok


def _discrepancy(Xd: np.ndarray, a: np.ndarray, V: np.ndarray, model: np.ndarray, p_level: float = 0.999
                 ) -> tuple[float, np.ndarray]:
    """Relative discrepancy delta with GLS chi2(delta) / dof = 1 when the statistical chi2 is implausibly large
    (above its ``p_level`` quantile); returns (delta, V + delta^2 diag(model^2))."""
    dof = max(len(a) - Xd.shape[1], 1)
    _, chi2_0 = _nn_gls(Xd, a, V)
    if chi2_0 <= stats.chi2.ppf(p_level, dof):
        return 0.0, V
    m2 = np.diag(np.maximum(model, 1e-300) ** 2)

    def excess(log_d):
        return _nn_gls(Xd, a, V + math.exp(2 * log_d) * m2)[1] / dof - 1.0

    lo, hi = math.log(1e-6), math.log(10.0)
    if excess(hi) > 0:
        d = 10.0
    elif excess(lo) < 0:
        d = 1e-6
    else:
        d = math.exp(optimize.brentq(excess, lo, hi, xtol=1e-3))
    return d, V + d * d * m2


def _outside_ranges(res: AllanResult, sel: np.ndarray, model_avar, check_ci: float) -> tuple:
    """Contiguous tau ranges (within the selection) where the model deviation leaves the curve's chi-square
    interval at ``check_ci``: ((tau_lo, tau_hi, min model/curve, max model/curve), ...)."""
    from assets_lib.noise.intervals import chi2_interval

    tau, dev, edf = res.tau_s[sel], res.adev[sel], res.edf[sel]
    # family-wise over the fitted taus (Bonferroni): a dense grid of 100 taus would otherwise see a point outside
    # its own 99 % interval by chance in most records
    lo, hi = chi2_interval(dev, edf, 1.0 - (1.0 - check_ci) / max(len(tau), 1))
    mdev = np.sqrt(np.maximum(model_avar(tau), 0.0))
    out = (mdev < lo) | (mdev > hi)
    ranges = []
    j = 0
    while j < len(tau):
        if out[j]:
            k = j
            while k + 1 < len(tau) and out[k + 1]:
                k += 1
            ratio = mdev[j:k + 1] / dev[j:k + 1]
            ranges.append((float(tau[j]), float(tau[k]), float(ratio.min()), float(ratio.max())))
            j = k + 1
        else:
            j += 1
    return tuple(ranges)


def fit_noise(
    res: AllanResult,
    terms: Sequence[str] = TERMS,
    *,
    markov: bool = False,
    sinusoid: bool = False,
    ci_level: float = 0.95,
    sensor: str | None = None,
    max_m_fraction: float = 0.25,
    min_terms: int = 4,
    iterations: int = 4,
    tau_min_s: float | str | None = "auto",
    tau_max_s: float | None = None,
    model_discrepancy: bool = True,
    check_ci: float = 0.99,
    min_edf: float = 10.0,
) -> NoiseFit:
    """[IEEE952] Annex C fit by iterated non-negative GLS; intervals on every term; model-discrepancy
    weights, tau range and the check against the curve's intervals as in the module doc.

    ``tau_min_s="auto"`` (default): the smallest tau of the curve from which the fitted model stays inside the
    curve's ``check_ci`` intervals up to ``tau_max_s`` (tried in order over the curve's taus up to
    tau_max / 30, keeping at least len(terms) + 3 points); when the short-tau end had to be cut, the start is
    moved one octave further (twice that tau) if the model still matches there; the excluded short-tau range
    is named in ``warnings``. When no start works, the whole range is fitted and the mismatch is warned about. ``None``:
    every usable tau."""
    if res.kind != "oadev":
        raise ValueError("fit_noise expects an overlapping Allan deviation (kind='oadev')")
    kw = dict(terms=terms, markov=markov, sinusoid=sinusoid, ci_level=ci_level, sensor=sensor,
              max_m_fraction=max_m_fraction, min_terms=min_terms, iterations=iterations, tau_max_s=tau_max_s,
              model_discrepancy=model_discrepancy, check_ci=check_ci, min_edf=min_edf)
    if isinstance(tau_min_s, str):
        if tau_min_s != "auto":
            raise ValueError(f"tau_min_s must be a number, None or 'auto', not {tau_min_s!r}")
        sel0 = _select(res, max_m_fraction, min_terms, None, tau_max_s)
        taus = res.tau_s[sel0]
        need = len(terms) + (1 if markov else 0) + (1 if sinusoid else 0) + 3
        cands = [t for i, t in enumerate(taus) if len(taus) - i >= need and t <= taus.max() / 30.0] or [taus.min()]
        first = None
        t_short = taus[min(2, len(taus) - 1)]
        for i0, t0 in enumerate(cands):
            f = fit_noise(res, tau_min_s=float(t0), **kw)
            first = first or f
            if i0 == 0 and not f.matches_curve and all(r[0] > t_short * (1 + 1e-9) for r in f.outside_tau_ranges):
                # the departure is not at the short-tau end: cutting short taus cannot remove it, and it would
                # throw away the points that separate Q from N (a chance excursion of a mid-tau point, 1 % of
                # ideal curves at the family-wise check, then left Q and N collinear: z up to 12 in
                # benchmarks/coverage_noise.py); the whole range is kept and the departure is warned about
                return f
            if f.matches_curve and i0 > 0:
                # one octave of margin: at the edge of a departure a model absorbs the residual misfit by
                # trading terms (a filtered white noise looks like a negative Q term there), so start later
                t_guard = 2.0 * t0
                if len(taus[taus >= t_guard * (1 - 1e-9)]) >= need:
                    g = fit_noise(res, tau_min_s=float(t_guard), **kw)
                    if g.matches_curve:
                        f, t0 = g, taus[taus >= t_guard * (1 - 1e-9)].min()
            if f.matches_curve:
                if t0 > taus.min():
                    note = (f"{res.channel or 'channel'}: fit starts at tau {t0:.4g} s; for tau {taus.min():.4g}-"
                            f"{taus[taus < t0].max():.4g} s the curve departs from the IEEE 952 model (filter response "
                            f"or coloured short-tau noise): terms read there would be wrong")
                    f = _replace(f, warnings=(note,) + f.warnings)
                return f
        return _replace(first, warnings=first.warnings + (f"{res.channel or 'channel'}: no tau range start makes the "
                                                          "model match the curve; whole range fitted",))
    sensor = sensor or sensor_of(res.channel, res.unit)
    sel = _select(res, max_m_fraction, min_terms, tau_min_s, tau_max_s)
    if sel.sum() < len(terms) + 1:
        raise ValueError(f"only {int(sel.sum())} usable taus in the tau range "
                         f"[{tau_min_s or res.tau_s.min():g}, {tau_max_s or res.tau_s.max():g}] s for {len(terms)} terms")
    tau = res.tau_s[sel]
    a = res.avar[sel]
    m = res.m[sel]
    n = res.n_terms[sel].astype(float)
    n_phase = res.n_samples + 1 if res.data_type == "rate" else res.n_samples
    term_list = list(terms)
    X = basis(tau, term_list)
    tc = f0 = None
    if markov:
        term_list.append("M")
    if sinusoid:
        term_list.append("S")

    def design(tc_, f0_):
        cols = [X]
        if markov:
            cols.append(markov_avar_unit(tau, tc_)[:, None])
        if sinusoid:
            cols.append(sinusoid_avar_unit(tau, f0_)[:, None])
        return np.hstack(cols)

    alphas = np.array([_TERM_ALPHA[t] for t in term_list])

    def covariance(theta_vec, Xd):
        parts = Xd * theta_vec[None, :]
        model = parts.sum(axis=1)
        model = np.where(model > 0, model, a)
        edf = _edf_mix(tau, np.clip(parts, 0, None), alphas, m, n_phase)
        th = {t: float(v) for t, v in zip(term_list, theta_vec)}
        C = avar_covariance_large_n(tau, n, th, res.rate_hz, tc)
        dl = np.sqrt(np.diag(C))
        R = C / np.outer(dl, dl)
        np.fill_diagonal(R, 1.0)
        # variance: [GREENHALL2003] (finite-length effects at long taus) unless the sampled-data large-n variance
        # is larger (m = 1: white rate samples have EDF 2n/3, Greenhall's filter F = m gives 0.78 n)
        d = np.maximum(np.sqrt(2.0 * model**2 / edf), dl)
        return _regularise(R * np.outer(d, d))

    # start: diagonal weights from the measured points ([NIST1065] EDF of the identified noise)
    V = np.diag(2.0 * a**2 / np.where(np.isfinite(res.edf[sel]) & (res.edf[sel] > 0), res.edf[sel], 1.0))
    grid_tc = np.geomspace(tau.min() * 2, tau.max() / 2, 24) if markov else [None]
    grid_f0 = np.geomspace(1.0 / tau.max(), 0.5 / tau.min(), 32) if sinusoid else [None]
    theta = None
    it = 0
    for it in range(1, iterations + 1):
        best = None
        for tc_ in grid_tc:
            for f0_ in grid_f0:
                Xd = design(tc_, f0_)
                t_, rss = _nn_gls(Xd, a, V)
                if best is None or rss < best[0]:
                    best = (rss, t_, tc_, f0_, Xd)
        rss, theta_new, tc, f0, Xd = best
        if markov or sinusoid:
            grid_tc = [tc] if markov else grid_tc
            grid_f0 = [f0] if sinusoid else grid_f0
        converged = theta is not None and np.allclose(theta_new, theta, rtol=1e-4, atol=0)
        theta = theta_new
        V = covariance(theta, Xd)
        if converged:
            break
    Xd = design(tc, f0)
    delta = 0.0
    if model_discrepancy:
        for _ in range(3):  # discrepancy at the current model, refit, statistical covariance at the new model
            theta, _ = _nn_gls(Xd, a, V)
            Vstat = covariance(theta, Xd)
            delta, V = _discrepancy(Xd, a, Vstat, np.maximum(Xd @ theta, 1e-300))
            if delta == 0.0:
                break
    z2 = stats.norm.ppf(0.5 + ci_level / 2.0)
    profile = None
    if markov:
        # T_c by profile GLS chi2 on a fine grid (the coarse grid above only seeded the weights); the Markov
        # intervals below carry T_c's uncertainty: the profile set chi2(T_c) <= min + chi2_1(ci_level)
        fine = np.geomspace(tau.min() * 2, tau.max() / 2, 97)
        chis = np.array([_nn_gls(design(t_, f0), a, V)[1] for t_ in fine])
        j = int(np.argmin(chis))
        lf = np.log(fine)
        tc = float(fine[j])
        if 0 < j < len(fine) - 1:  # parabola through the grid minimum and its neighbours (ln T_c)
            c0, c1, c2 = chis[j - 1], chis[j], chis[j + 1]
            den = c0 - 2.0 * c1 + c2
            if den > 0:
                tc = float(math.exp(lf[j] + 0.5 * (c0 - c2) / den * (lf[j + 1] - lf[j])))
        Xd = design(tc, f0)
        # the GLS chi2 differences are scaled by the dispersion chi2_min / dof when it exceeds 1 (quasi-likelihood
        # profile: weights that understate the scatter would make the T_c set too narrow)
        disp = max(1.0, float(chis.min()) / max(len(a) - Xd.shape[1] - 1, 1))
        cut = chis.min() + disp * stats.chi2.ppf(ci_level, 1)
        inside = np.flatnonzero(chis <= cut)
        # the set's edges where the chi2 crosses the cut between grid points (linear in ln T_c), not the last grid
        # point inside (a set one grid step too narrow at each end)
        edges = []
        for i, o in ((inside.min(), inside.min() - 1), (inside.max(), inside.max() + 1)):
            if 0 <= o < len(fine) and chis[o] > chis[i]:
                w = (cut - chis[i]) / (chis[o] - chis[i])
                edges.append(float(math.exp(lf[i] + w * (lf[o] - lf[i]))))
        profile = np.unique(np.concatenate([fine[inside], edges, [tc]]))
    cov_at = None
    if not sinusoid:
        def cov_at(th_vec):
            Vn = covariance(np.maximum(th_vec, 0.0), Xd)
            return Vn + delta * delta * np.diag(np.maximum(Xd @ th_vec, 1e-300) ** 2) if delta > 0 else Vn
    k_m = term_list.index("M") if markov else -1
    # is a Markov term in the record at all? T_c is searched, so the supremum test ([DAVIES1987]), not chi2_1
    m_identified = markov and _markov_davies_p(_nn_gls(np.delete(Xd, k_m, axis=1), a, V)[1], chis, disp) < 1 - ci_level
    # other terms: the fit with the Markov term at the profile's T_c even when it is not identified (the fit without
    # it charged the Markov term's AVAR to B: B z mean +1.1 / +1.8, gyro B coverage 0.46, in
    # benchmarks/coverage_noise.py)
    theta, rss, cov, sd_all, bound_theta, (lo_prof, hi_prof, centre) = _significant_terms(Xd, a, V, z2, cov_at)
    if markov and profile is not None:
        lo_prof, hi_prof, bound_theta = _markov_nuisance(Xd, a, V, z2, lo_prof, hi_prof, bound_theta, fine, chis,
                                                         design, f0, term_list)
    short_fit = short_sd = None
    if markov:
        # Q and N in a Markov fit: the fit with the long-tau terms free, not the eliminated one (see below)
        free = [j for j in range(len(term_list)) if term_list[j] != "Q" or theta[j] > 0]
        short_fit = np.zeros(len(term_list))
        short_fit[free] = _nn_gls(Xd[:, free], a, V)[0]
        Lc = np.linalg.cholesky(V)
        Xc = np.linalg.solve(Lc, Xd)
        short_sd = _active_set_covariance(Xc.T @ Xc, short_fit)[1]
    params, slope_params = [], []
    for k, t in enumerate(term_list):
        th, sd = float(theta[k]), float(sd_all[k])
        name = {"M": "markov_q", "S": "sin_amplitude"}.get(t, t)
        if t == "M" and profile is not None:
            # printed at its joint profile set's centre, the fit with every term free at T_c (as B, K and R): the
            # eliminated fit holds a dropped B or K at zero and charges its share of the AVAR to theta_M (q_c read
            # above the set's centre in 71 % of the identified channels, mean z +0.25 / +0.46 in
            # benchmarks/coverage_noise.py)
            th_m = float(centre[k]) if centre[k] > 0 else th
            params.append(_markov_joint_profile(fine, design, f0, a, V, disp * stats.chi2.ppf(ci_level, 1), k,
                                                sensor, ci_level, th_m, sd, tc, bound_theta.get(k), m_identified))
            continue
        if k in bound_theta:
            ub_val = _theta_to_param(t, bound_theta[k], tc)
            params.append(_param(name, math.nan, 0.0, ub_val, sensor, "fit", True, ci_level))
        elif t in _LONG_TAU_TERMS:
            # B, K, R trade places at the long-tau end: the active-set Wald interval holds the terms the elimination
            # dropped at zero, so their share of the long-tau AVAR is charged to the kept term with no uncertainty
            # (B two-sided coverage 0.89-0.91 where K or R was dropped, benchmarks/coverage_noise.py). The interval
            # is the profile-likelihood set with every other term free and non-negative ([VENZON1988]), the same
            # set that decided the term is identified. The printed estimate is that set's centre, the fit with every
            # term free (the eliminated fit's value charged the dropped neighbours' share to the kept term: accel
            # B z mean +0.41 where K and R were injected, benchmarks/coverage_noise.py); theta (the model curve)
            # stays the eliminated fit's
            if centre[k] > 0:
                th = float(centre[k])
            lo, hi = min(float(lo_prof[k]), th), max(float(hi_prof[k]), th)
            se = _theta_to_param(t, th, tc) * ((hi - lo) / (2.0 * z2)) / (2.0 * th)
        else:
            if short_fit is not None and short_fit[k] > 0:
                # a Markov fit's elimination drops B where the Markov hump covers the long taus, and then charges
                # B's flat share of the short-tau AVAR to N with no uncertainty (accel N z sd 1.17, consumer 1.29,
                # benchmarks/coverage_noise.py): N and Q are read from the fit with B, K, R and the Markov term free
                # and non-negative (Q held at zero where the elimination dropped it: a free Q pulls N down, as in
                # _significant_terms) and their Wald deviations from its active set
                th, sd = float(short_fit[k]), float(short_sd[k])
            nu = 2.0 * th**2 / sd**2  # Satterthwaite: theta_hat ~ theta chi2_nu / nu
            lo = nu * th / stats.chi2.ppf(0.5 + ci_level / 2.0, nu)
            hi = nu * th / stats.chi2.ppf(0.5 - ci_level / 2.0, nu)
            # delta method: d sqrt(theta) = d theta / (2 sqrt(theta)) (Markov: also / T_c)
            se = _theta_to_param(t, th, tc) * sd / (2.0 * th)
        if k not in bound_theta:
            params.append(_param(name, _theta_to_param(t, th, tc), _theta_to_param(t, lo, tc),
                                 _theta_to_param(t, hi, tc), sensor, "fit", False, ci_level, se))
    if markov:
        # profile-likelihood set of T_c (an interval when the Markov term is supported, else the grid searched)
        tlo, thi = (float(profile.min()), float(profile.max())) if profile is not None else (tc, tc)
        if next(p_ for p_ in params if p_.name == "markov_q").is_upper_bound:
            # the record does not identify the Markov term: its T_c is not estimated either (the profile's minimum,
            # often at the grid's end, was a meaningless point: z down to -3.6 in benchmarks/coverage_noise.py); it
            # is bounded only by the longest T_c searched (half the longest tau fitted)
            params.append(_param("markov_tc", math.nan, 0.0, float(fine.max()), sensor, "fit", True, ci_level))
        else:
            params.append(_param("markov_tc", tc, tlo, thi, sensor, "fit", False, ci_level))
    if sinusoid:
        params.append(_param("sin_freq", f0, f0, f0, sensor, "fit", False, ci_level))
    slope_params = slope_reads(res, sensor=sensor, ci_level=ci_level, min_edf=min_edf, tau_min_s=tau_min_s,
                               tau_max_s=tau_max_s)
    proto = NoiseFit(res.channel, sensor, (), (), tuple(term_list), theta, cov, tau, a, rss, 1, tc, f0)
    outside = _outside_ranges(res, sel, proto.model_avar, check_ci)
    warns = []
    for lo_t, hi_t, rmin, rmax in outside:
        warns.append(f"{res.channel or 'channel'}: the noise model leaves the curve's {100 * check_ci:g} % (family-wise) intervals "
                     f"for tau {lo_t:.4g}-{hi_t:.4g} s (model/curve {rmin:.3g}-{rmax:.3g})")
    if delta > 0:
        warns.append(f"{res.channel or 'channel'}: the curve departs from the IEEE 952 model by ~{100 * delta:.3g} % "
                     f"(relative discrepancy added to the fit weights; intervals widened)")
    return NoiseFit(
        channel=res.channel,
        sensor=sensor,
        parameters=tuple(params),
        slope_parameters=tuple(slope_params),
        terms=tuple(term_list),
        theta=theta,
        theta_cov=cov,
        tau_s=tau,
        avar=a,
        chi2=rss,
        dof=int(len(a) - np.count_nonzero(theta)),
        markov_tc_s=tc,
        sin_f0_hz=f0,
        iterations=it,
        tau_range_s=(float(tau.min()), float(tau.max())),
        discrepancy=float(delta),
        outside_tau_ranges=outside,
        warnings=tuple(warns),
    )


def _markov_joint_profile(fine, design, f0, a, V, crit, k, sensor, ci_level, th, sd, tc, bound, identified=True):
    """markov_q = q_c = sqrt(theta_M) / T_c by the joint profile likelihood of (q_c, T_c) ([VENZON1988]): the set
    {q : min over T_c (the fine grid) and every other term >= 0 of the GLS chi2 with theta_M = (q T_c)^2
    <= chi2_min + crit}. At fixed T_c the GLS chi2 is convex in theta_M, so its set there is an interval; the
    q set is the union of those intervals over T_c, each cut at the global minimum + crit (not at its own:
    the union of per-T_c 95 % intervals over T_c's 95 % set, a projection, over-covered, gyro markov_q 0.98 with
    z sd 0.74 in benchmarks/coverage_noise.py). When theta_M = 0 lies in the set (the fit without the Markov term
    is within crit of the minimum; it does not depend on T_c), or the T_c search's supremum test
    (:func:`_markov_davies_p`, decided by the caller: ``identified``) does not reject "no Markov term", the record
    does not identify the term: an upper bound, at least the significance test's ``bound``."""
    L = np.linalg.cholesky(V)
    aw = np.linalg.solve(L, a)
    Xws = [np.linalg.solve(L, design(t_, f0)) for t_ in fine]
    p = Xws[0].shape[1]
    others = [j for j in range(p) if j != k]
    Xo = Xws[0][:, others]  # the other columns do not depend on T_c
    so = np.linalg.norm(Xo, axis=0)
    so[so == 0] = 1.0
    Xo = Xo / so

    def chi(th_m, xk):
        r = aw - xk * th_m
        return float(optimize.nnls(Xo, r, maxiter=50 * p)[1] ** 2) if Xo.shape[1] else float(r @ r)

    fits = []
    for Xw in Xws:
        sc = np.linalg.norm(Xw, axis=0)
        sc[sc == 0] = 1.0
        t_all, rn = optimize.nnls(Xw / sc, aw, maxiter=50 * p)
        fits.append((float(t_all[k] / sc[k]), float(rn**2), 1.0 / sc[k]))
    chi_min = min(f_[1] for f_ in fits)
    chi0 = chi(0.0, Xws[0][:, k])
    cut = chi_min + crit
    los, his = [], []
    for t_, Xw, (thk, c_k, step) in zip(fine, Xws, fits):
        if c_k > cut:
            continue
        xk = Xw[:, k]
        lo = 0.0
        if thk > 0 and chi(0.0, xk) > cut:
            lo = optimize.brentq(lambda v, xk=xk: chi(v, xk) - cut, 0.0, thk, xtol=1e-12 * max(thk, step), rtol=1e-6)
        up = thk + step
        for _ in range(80):
            if chi(up, xk) > cut:
                break
            step *= 2.0
            up = thk + step
        hi = optimize.brentq(lambda v, xk=xk: chi(v, xk) - cut, thk, up, xtol=1e-12 * up, rtol=1e-6)
        los.append(_theta_to_param("M", lo, t_))
        his.append(_theta_to_param("M", hi, t_))
    if chi0 <= cut or not his or not identified:
        ub = max(his + ([_theta_to_param("M", bound, tc)] if bound is not None else []) or [0.0])
        return _param("markov_q", math.nan, 0.0, ub, sensor, "fit", True, ci_level)
    if th <= 0:  # the elimination at the interpolated T_c dropped the term the joint profile identifies
        j = int(np.argmin([f_[1] for f_ in fits]))
        th, tc = fits[j][0], float(fine[j])
    val = _theta_to_param("M", th, tc)
    lo, hi = min(min(los), val), max(max(his), val)
    return _param("markov_q", val, lo, hi, sensor, "fit", False, ci_level, val * sd / (2.0 * th) if th > 0 else math.nan)


def _markov_nuisance(Xd, a, V, z2, lo_p, hi_p, bounds, fine, chis, design, f0, term_list):
    """The long-tau terms' (B, K, R) profile sets in a Markov fit with T_c free, not held at its profile point
    (T_c is a nuisance parameter of their likelihood too; the Markov hump trades places with B and K when T_c is
    long): {theta_k : min over T_c and every other term >= 0 of the GLS chi2 <= chi2_min + z2^2} ([VENZON1988]),
    the union over the T_c grid (every 4th point of the fine grid inside the T_c set, the set's ends) of each
    T_c's profile interval cut at the global minimum. A term whose set reaches zero at some T_c is a bound (its
    set's upper end). Held at the profile's T_c, gyro B covered 0.83 (z sd 1.34): where the Markov term was not
    identified its hump was charged to B (benchmarks/coverage_noise.py)."""
    long_k = [k for k in range(Xd.shape[1]) if term_list[k] in _LONG_TAU_TERMS]
    if not long_k:
        return lo_p, hi_p, bounds
    cut = float(np.min(chis)) + z2 * z2
    lo_p, hi_p, bounds = lo_p.copy(), hi_p.copy(), dict(bounds)
    inside = np.flatnonzero(chis <= cut)
    pick = np.unique(np.concatenate([inside[::4], inside[[0, -1]]]))
    for i in pick:
        lo_t, hi_t, _ = _profile_limits(design(fine[i], f0), a, V, cut - float(chis[i]), only=long_k)
        for k in long_k:
            lo_p[k] = min(lo_p[k], lo_t[k])
            hi_p[k] = max(hi_p[k], hi_t[k])
    for k in long_k:
        if k in bounds or lo_p[k] <= 0:
            bounds[k] = max(bounds.get(k, 0.0), float(hi_p[k]))
    return lo_p, hi_p, bounds


def _markov_davies_p(chi0: float, chis: np.ndarray, disp: float = 1.0) -> float:
    """p-value of "a Markov term is present" when its T_c is searched ([DAVIES1987] upper bound): T_c exists
    only under the alternative, so the largest likelihood-ratio gain over the T_c grid, u^2 = (chi0 - min chis) /
    disp, is the supremum of a chi-square process, not one chi2_1 variable:
    P(sup Z^2 > u^2) <= P(chi2_1 > u^2) + V exp(-u^2 / 2) / sqrt(2 pi) (twice the one-sided bound Phi(-u) +
    V exp(-u^2 / 2) / sqrt(8 pi)), V the total variation over the grid of the root
    process Z(T_c) = sqrt(max(chi0 - chi2(T_c), 0) / disp). With T_c known (V = 0) it is the chi2_1 test the joint
    profile set applies; V = 0.5-8 raises the 5 % critical value of the gain from 3.84 to 4.7-8.5. The chi2_1 cut
    alone took chance gains for a Markov term in 3.5 % of the benchmark's channels, at T_c 0.02-3 s against a
    truth of 16-57 s: at short T_c the term is white noise minus a quantization term, 1/tau - 3 T_c / (2 tau^2)
    ([IEEE952] C.25 for tau >> T_c), and fits the short-tau scatter (benchmarks/coverage_noise.py)."""
    u2 = max(chi0 - float(np.min(chis)), 0.0) / disp
    z = np.sqrt(np.maximum(chi0 - np.asarray(chis, dtype=float), 0.0) / disp)
    v = float(np.sum(np.abs(np.diff(z))))
    return float(min(1.0, stats.chi2.sf(u2, 1) + v / math.sqrt(2.0 * math.pi) * math.exp(-u2 / 2.0)))


def _significant_terms(Xd: np.ndarray, a: np.ndarray, V: np.ndarray, z2: float, cov_at=None):
    """Non-negative GLS with backward elimination of the terms the data do not support.

    A term whose two-sided Wald interval reaches zero (theta - z2 sd <= 0) is dropped, the least significant
    first, and the rest refitted, until every remaining term is significant. Keeping unsupported terms at the
    boundary biases the others: a quantization term fitted to white noise is positive half the time and, being
    collinear with N at short taus, pulls N down by half its standard error (benchmarks/coverage_noise.py).
    A dropped term, or a kept one whose profile interval (:func:`_profile_limits`, every other term free) reaches
    zero, is reported as an upper bound: the profile interval's upper end ([FELDMAN1998]: one likelihood decides
    between the two reports); with ``cov_at`` (theta -> V) the bound is tested at its own covariance
    (:func:`_bound_at_null`). Returns theta (dropped terms 0), the GLS chi2, the active-set covariance,
    one standard deviation per term, {index: upper bound on theta} of the terms reported as bounds and the
    profile interval's (lower ends, upper ends).
    """
    p = Xd.shape[1]
    L = np.linalg.cholesky(V)
    Xw = np.linalg.solve(L, Xd)
    info = Xw.T @ Xw
    keep = list(range(p))
    while True:
        th_k, rss = _nn_gls(Xd[:, keep], a, V)
        theta = np.zeros(p)
        theta[keep] = th_k
        cov, sd = _active_set_covariance(info, theta, keep)
        weak = [k for k in keep if theta[k] <= 0 or theta[k] - z2 * sd[k] <= 0]
        if not weak or len(keep) == 1:
            break
        keep.remove(min(weak, key=lambda k: theta[k] / sd[k] if sd[k] > 0 else 0.0))
    lo_p, hi_p, _ = _profile_limits(Xd, a, V, z2 * z2)
    centre, _ = _nn_gls(Xd, a, V)  # the profile sets' common minimum: every term free and non-negative
    bounds = {}
    for k in range(p):
        if k in keep and theta[k] > 0 and lo_p[k] > 0:
            continue
        bounds[k] = float(hi_p[k]) if cov_at is None else max(float(hi_p[k]),
                                                              _bound_at_null(Xd, a, V, k, z2 * z2, cov_at))
    return theta, rss, cov, sd, bounds, (lo_p, hi_p, centre)


def _profile_limits(Xd: np.ndarray, a: np.ndarray, V: np.ndarray, crit: float, only=None):
    """Profile-likelihood limits of each theta_k on the GLS chi2 with every other term free and non-negative.

    With V fixed at the fitted model the Gaussian likelihood of the AVAR points gives the profile
    chi2_p(theta_k) = min_{theta_j >= 0, j != k} (a - X theta)' V^-1 (a - X theta) ([NIST1065] sec. 5 / [IEEE952]
    Annex C: the AVAR estimates are correlated across tau, V their full covariance); the set
    chi2_p(theta_k) <= min chi2 + crit (crit = chi2_1(level)) is the profile interval ([VENZON1988]). Collinear
    long-tau terms (B, K, R on a short record) can trade places inside it: when theta_k = 0 lies in the set the
    record does not identify the term, lo = 0 and only the upper limit is meaningful (a bound). Returns (lo, hi,
    theta at each upper limit (row k: the profile's theta with theta_k = hi_k)); ``only``: the terms to profile.
    """
    p = Xd.shape[1]
    L = np.linalg.cholesky(V)
    Xw = np.linalg.solve(L, Xd)
    aw = np.linalg.solve(L, a)
    scale = np.linalg.norm(Xw, axis=0)
    scale[scale == 0] = 1.0
    Xs = Xw / scale
    t_full, r_full = optimize.nnls(Xs, aw, maxiter=50 * p)
    chi_min = float(r_full**2)
    lo = np.zeros(p)
    hi = np.zeros(p)
    at_hi = np.zeros((p, p))
    for k in range(p) if only is None else only:
        others = [j for j in range(p) if j != k]
        Xo = Xs[:, others]

        def excess(th, k=k, Xo=Xo):
            r = aw - Xw[:, k] * th
            if Xo.shape[1]:
                _, rn = optimize.nnls(Xo, r, maxiter=50 * p)
            else:
                rn = float(np.linalg.norm(r))
            return float(rn**2) - chi_min - crit

        th0 = float(t_full[k] / scale[k])
        step = 1.0 / scale[k]  # the term's standard deviation when it is alone
        if th0 > 0 and excess(0.0) > 0:
            lo[k] = optimize.brentq(excess, 0.0, th0, xtol=1e-12 * max(th0, step), rtol=1e-6)
        up = th0 + step
        for _ in range(80):
            if excess(up) > 0:
                break
            step *= 2.0
            up = th0 + step
        lo_b = th0 if excess(th0) <= 0 else 0.0
        hi[k] = optimize.brentq(excess, lo_b, up, xtol=1e-12 * up, rtol=1e-6) if excess(up) > 0 else up
        at_hi[k, k] = hi[k]
        if others:
            t_o, _ = optimize.nnls(Xo, aw - Xw[:, k] * hi[k], maxiter=50 * p)
            at_hi[k, others] = t_o / scale[others]
    return lo, hi, at_hi


def _bound_at_null(Xd: np.ndarray, a: np.ndarray, V: np.ndarray, k: int, crit: float, cov_at, iterations: int = 3
                   ) -> float:
    """Upper bound on theta_k tested with the AVAR covariance of the null it tests ([IEEE952] Annex C points have
    variance ~ 2 sigma^4 / EDF: at a larger theta_k they scatter more). With V fixed at a fit that came out low the
    profile's upper end is too tight (accelerometer B bounds held 0.83 of the time, benchmarks/coverage_noise.py);
    here V is re-evaluated at the profile's theta at the bound and the bound recomputed, a few times (the score-test
    form of the profile interval)."""
    _, hi, at_hi = _profile_limits(Xd, a, V, crit, only=[k])
    for _ in range(iterations):
        V0 = cov_at(at_hi[k])
        _, hi2, at_hi = _profile_limits(Xd, a, V0, crit, only=[k])
        done = abs(hi2[k] - hi[k]) <= 1e-3 * abs(hi[k])
        hi = hi2
        if done:
            break
    return float(hi[k])


def _active_set_covariance(info: np.ndarray, theta: np.ndarray, allowed=None) -> tuple[np.ndarray, np.ndarray]:
    """Wald covariance of the non-negative GLS fit on its active set ([LAWSON1974]: the terms at zero are
    constraints, not parameters): (X_A' V^-1 X_A)^-1 for the terms with theta > 0, zero rows for the others.
    Also one standard deviation per term: the active set's for an active term; for a term at zero (among
    ``allowed``), its standard deviation when it is added alone to the active set. The full
    inverse would charge every estimate with the collinearity of terms the data put at zero (e.g. Q against N at
    short taus), widening the intervals of white-noise N by ~1.5x (benchmarks/coverage_noise.py)."""
    p = len(theta)
    act = np.flatnonzero(theta > 0)
    cov = np.zeros((p, p))
    sd = np.zeros(p)
    if act.size:
        cov[np.ix_(act, act)] = np.linalg.pinv(info[np.ix_(act, act)])
        sd[act] = np.sqrt(np.maximum(np.diag(cov)[act], 0.0))
    for k in np.flatnonzero(theta <= 0):
        if allowed is not None and k not in allowed:
            continue
        idx = np.append(act, k)
        c = np.linalg.pinv(info[np.ix_(idx, idx)])
        sd[k] = math.sqrt(max(c[-1, -1], 0.0))
    return cov, sd


def _replace(fit: NoiseFit, **changes) -> NoiseFit:
    import dataclasses

    return dataclasses.replace(fit, **changes)


def _theta_to_param(t: str, th: float, tc: float | None) -> float:
    """theta -> coefficient: sqrt for the IEEE terms; Markov q_c = sqrt(theta) / T_c (theta = (q_c T_c)^2)."""
    if t == "M":
        return math.sqrt(max(th, 0.0)) / tc
    return math.sqrt(max(th, 0.0))


# --------------------------------------------------------------------------------------------------------------
# classic slope reads
# --------------------------------------------------------------------------------------------------------------
def slope_reads(res: AllanResult, *, sensor: str | None = None, ci_level: float = 0.95, tol: float = 0.25,
                min_edf: float = 10.0, tau_min_s: float | None = None, tau_max_s: float | None = None) -> list:
    """[IEEE952] C.3 / [SEED002] sec. 2.2 / [ELSHEIMY2008]: single-line reads of Q, N, B, K, R on the log-log ADEV curve.

    N: the -1/2 line through the point whose local slope is closest to -1/2, read at tau = 1 s; K: the +1/2
    line read at tau = 3 s; Q: -1 line at tau = sqrt(3) s; R: +1 line at tau = sqrt(2) s; B: the curve minimum
    / sqrt(2 ln2 / pi). The interval carries the chi-square interval of the deviation at the read point
    (at ``ci_level``, from the point's EDF). A read is omitted when no part of the curve has a slope within
    ``tol`` of the line's. Points with fewer than ``min_edf`` degrees of freedom, or outside the tau range, are
    not read.
    """
    sensor = sensor or sensor_of(res.channel, res.unit)
    ok = (res.n_terms >= 4) & (res.adev > 0) & np.isfinite(res.adev)
    ok &= np.isfinite(res.edf) & (res.edf >= min_edf)
    if tau_min_s is not None:
        ok &= res.tau_s >= tau_min_s * (1 - 1e-9)
    if tau_max_s is not None:
        ok &= res.tau_s <= tau_max_s * (1 + 1e-9)
    tau, dev, edf = res.tau_s[ok], res.adev[ok], res.edf[ok]
    out = []
    if len(tau) < 3:
        return out
    from assets_lib.noise.intervals import chi2_interval

    lo_all, hi_all = chi2_interval(dev, edf, ci_level)
    slope = np.gradient(np.log(dev), np.log(tau))
    for name, target, tau_read in (
        ("Q", -1.0, math.sqrt(3.0)),
        ("N", -0.5, 1.0),
        ("K", 0.5, 3.0),
        ("R", 1.0, math.sqrt(2.0)),
    ):
        j = int(np.argmin(np.abs(slope - target)))
        if abs(slope[j] - target) > tol:
            continue
        f = (tau_read / tau[j]) ** target
        val = dev[j] * f
        if name == "Q":
            val, lo, hi = val * tau_read / math.sqrt(3.0), lo_all[j] * f, hi_all[j] * f
        else:
            lo, hi = lo_all[j] * f, hi_all[j] * f
        out.append(_param(name, val, lo, hi, sensor, "slope", False, ci_level))
    j = int(np.argmin(dev))
    c = math.sqrt(LN2_PI)
    out.append(_param("B", dev[j] / c, lo_all[j] / c, hi_all[j] / c, sensor, "slope", False, ci_level))
    order = {n: i for i, n in enumerate(TERMS)}
    out.sort(key=lambda p: order.get(p.name, 99))
    return out


# --------------------------------------------------------------------------------------------------------------
# tables and plots
# --------------------------------------------------------------------------------------------------------------
NOISE_COLUMNS = [
    "channel",
    "parameter",
    "value",
    "ci_lo",
    "ci_hi",
    "unit",
    "value_lab",
    "ci_lo_lab",
    "ci_hi_lab",
    "unit_lab",
    "method",
    "is_upper_bound",
    "ci_level",
    "tau_min_s",
    "tau_max_s",
    "fit_warning",
]


def fit_all(results: Mapping[str, AllanResult], **kw) -> dict[str, NoiseFit]:
    """:func:`fit_noise` for each channel of ``allan_deviations``."""
    return {name: fit_noise(r, **kw) for name, r in results.items()}


def noise_table(fits, **kw) -> pd.DataFrame:
    """Tidy table (channel, parameter, value, ci_lo, ci_hi, unit, *_lab, method, is_upper_bound, the fit's tau range
    and its warnings, joined by " | ", on every row of the channel) of fits.

    ``fits``: mapping channel -> NoiseFit, or mapping channel -> AllanResult (fitted here with ``kw``).
    """
    if isinstance(fits, NoiseFit):
        fits = {fits.channel: fits}
    fits = {k: (fit_noise(v, **kw) if isinstance(v, AllanResult) else v) for k, v in fits.items()}
    rows = []
    for ch, fit in fits.items():
        for p in list(fit.parameters) + list(fit.slope_parameters):
            rows.append(
                {
                    "channel": ch,
                    "parameter": p.name,
                    "value": p.value,
                    "ci_lo": p.ci_lo,
                    "ci_hi": p.ci_hi,
                    "unit": p.unit,
                    "value_lab": p.value_lab,
                    "ci_lo_lab": p.ci_lo_lab,
                    "ci_hi_lab": p.ci_hi_lab,
                    "unit_lab": p.unit_lab,
                    "method": p.method,
                    "is_upper_bound": p.is_upper_bound,
                    "ci_level": p.ci_level,
                    "tau_min_s": fit.tau_range_s[0],
                    "tau_max_s": fit.tau_range_s[1],
                    "fit_warning": " | ".join(fit.warnings),
                }
            )
    return pd.DataFrame(rows, columns=NOISE_COLUMNS)


_TERM_STYLE = {"Q": "-1", "N": "-1/2", "B": "0", "K": "+1/2", "R": "+1", "M": "Markov", "S": "sine"}


def plot_allan(results, fits: Mapping[str, NoiseFit] | None = None, path=None, title: str = "") -> bytes:
    """Log-log Allan deviation per channel with chi-square bars, the fitted model and each term's line (PNG)."""
    from assets_lib.plotting import figure, log_axes, png

    if isinstance(results, AllanResult):
        results = {results.channel or "ch": results}
    names = list(results)
    ncol = min(3, len(names)) or 1
    nrow = int(math.ceil(len(names) / ncol)) or 1
    fig, axes = figure(nrow, ncol, figsize=(5.2 * ncol, 4.2 * nrow), dpi=110, margins_in=(0.8, 0.15, 0.55, 0.6))
    for ax, name in zip(axes.ravel(), names):
        r = results[name]
        ok = np.isfinite(r.adev) & (r.adev > 0)
        yerr = np.vstack([r.adev - r.ci_lo, r.ci_hi - r.adev])[:, ok]
        yerr = np.where(np.isfinite(yerr), yerr, 0.0)
        ax.errorbar(r.tau_s[ok], r.adev[ok], yerr=yerr, fmt="o", ms=2.5, lw=0.8, color="k", label=r.kind.upper())
        fit = fits.get(name) if fits else None
        if fit is not None:
            tt = np.geomspace(r.tau_s[ok].min(), r.tau_s[ok].max(), 200)
            ax.loglog(tt, np.sqrt(fit.model_avar(tt)), "r-", lw=1.5, label="fit")
            bound = {p.name: p.is_upper_bound for p in fit.parameters}
            for t, v in fit.term_avar(tt).items():
                if np.any(v > 0):
                    ub = bound.get({"M": "markov_q", "S": "sin_amplitude"}.get(t, t), False)
                    ax.loglog(tt, np.sqrt(np.clip(v, 1e-300, None)), ":" if ub else "--", lw=0.9,
                              label=f"{t} ({_TERM_STYLE[t]})" + (" upper bound" if ub else ""))
            ymin = r.adev[ok].min() / 5
            ax.set_ylim(bottom=ymin)
        log_axes(ax)
        ax.set_xlabel("tau [s]")
        ax.set_ylabel(f"{r.kind.upper()} [{r.unit or 'SI'}]")
        ax.set_title(name)
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize=7, loc="lower left")
    for ax in axes.ravel()[len(names) :]:
        ax.set_visible(False)
    if title:
        fig.suptitle(title)
    data = png(fig)
    if path is not None:
        with open(path, "wb") as fh:
            fh.write(data)
    return data
