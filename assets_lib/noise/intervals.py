"""Equivalent degrees of freedom and chi-square confidence intervals of Allan-family deviations.

[GREENHALL2003] (the EDF algorithm [NIST1065] sec. 5.3 and [STABLE32] use); chi-square interval [NIST1065]
eq. 42. Noise-type identification by the lag-1 autocorrelation: [RILEY2004].

Power-law exponent ``alpha`` is that of the fractional-frequency (rate) PSD S_y(f) ~ f^alpha:
+2 white phase (quantization, Q), +1 flicker phase, 0 white rate (angle random walk, N),
-1 flicker rate (bias instability, B), -2 random-walk rate (rate random walk, K), -3, -4.
"""

from __future__ import annotations

import functools
import math

import numpy as np
from scipy import stats
from scipy.special import binom

#: Stable32's default: a "1-sigma" interval.
ONE_SIGMA_CI = 0.682689492137

#: [GREENHALL2003], table 1 (modified variances): (a0, a1) by alpha (+2..-4) and d (1..3).
_TABLE1 = {
    2: [(2.0 / 3.0, 1.0 / 3.0), (7.0 / 9.0, 1.0 / 2.0), (22.0 / 25.0, 2.0 / 3.0)],
    1: [(0.840, 0.345), (0.997, 0.616), (1.141, 0.843)],
    0: [(1.079, 0.368), (1.033, 0.607), (1.184, 0.848)],
    -1: [None, (1.048, 0.534), (1.180, 0.816)],
    -2: [None, (1.302, 0.535), (1.175, 0.777)],
    -3: [None, None, (1.194, 0.703)],
    -4: [None, None, (1.489, 0.702)],
}
#: [GREENHALL2003], table 2 (unmodified variances, large r): (a0, a1).
_TABLE2 = {
    2: [(3.0 / 2.0, 1.0 / 2.0), (35.0 / 18.0, 1.0), (231.0 / 100.0, 3.0 / 2.0)],
    1: [(78.6, 25.2), (790.0, 410.0), (9950.0, 6520.0)],
    0: [(2.0 / 3.0, 1.0 / 6.0), (2.0 / 3.0, 1.0 / 3.0), (7.0 / 9.0, 1.0 / 2.0)],
    -1: [None, (0.852, 0.375), (0.997, 0.617)],
    -2: [None, (1.079, 0.368), (1.033, 0.607)],
    -3: [None, None, (1.053, 0.553)],
    -4: [None, None, (1.302, 0.535)],
}
#: [GREENHALL2003], table 3 (unmodified variances, alpha = +1): (b0, b1) by d.
_TABLE3 = [(6.0, 4.0), (15.23, 12.0), (47.8, 40.0)]

_J_MAX = 100
#: binomial weights of the d-th difference, eq. 9
_DIFF_WEIGHTS = {1: (2.0, -1.0), 2: (6.0, -4.0, 1.0), 3: (20.0, -15.0, 6.0, -1.0)}


def _sw(t: np.ndarray, alpha: int) -> np.ndarray:
    """[GREENHALL2003] eq. 7: the generalized autocovariance sw(t) of the power-law phase noise."""
    t = np.asarray(t, dtype=float)
    a = np.abs(t)
    if alpha == 2:
        return -a
    if alpha == 0:
        return a**3
    if alpha == -2:
        return a**5
    if alpha == -4:
        return a**7
    power = {1: 2, -1: 4, -3: 6}[alpha]
    with np.errstate(divide="ignore", invalid="ignore"):
        out = t**power * np.log(a)
    return np.where(a == 0.0, 0.0, out)


def _sx(t: np.ndarray, F: float, alpha: int) -> np.ndarray:
    """[GREENHALL2003] eq. 8: sx(t) for the filter factor F (F = inf is the limit)."""
    if math.isinf(F):
        return _sw(t, alpha + 2)
    return F**2 * (2.0 * _sw(t, alpha) - _sw(t - 1.0 / F, alpha) - _sw(t + 1.0 / F, alpha))


def _sz(t: np.ndarray, F: float, alpha: int, d: int) -> np.ndarray:
    """[GREENHALL2003] eq. 9: sz(t), the d-th difference of sx."""
    w = _DIFF_WEIGHTS[d]
    out = w[0] * _sx(t, F, alpha)
    for k in range(1, d + 1):
        out = out + w[k] * (_sx(t - k, F, alpha) + _sx(t + k, F, alpha))
    return out


def _basic_sum(J: float, M: float, S: float, F: float, alpha: int, d: int) -> float:
    """[GREENHALL2003] eq. 10: the basic sum BS(J, M, S, F, alpha, d)."""
    J = int(J)
    j = np.arange(1, J, dtype=float)
    first = _sz(np.array(0.0), F, alpha, d) ** 2
    second = (1.0 - J / M) * _sz(np.array(J / S), F, alpha, d) ** 2
    third = np.sum(2.0 * (1.0 - j / M) * _sz(j / S, F, alpha, d) ** 2) if J > 1 else 0.0
    return float(first + second + third)


@functools.lru_cache(maxsize=1 << 16)
def edf_greenhall(alpha: int, d: int, m: int, n_phase: int, overlapping: bool, modified: bool) -> float:
    """[GREENHALL2003] section 4 ([NIST1065] sec. 5.3): EDF of a d-th difference variance estimate.

    ``d`` = 2 (Allan, modified Allan) or 3 (Hadamard); ``m`` averaging factor; ``n_phase`` number of phase
    points; ``overlapping`` stride 1 (else m); ``modified`` MVAR / TVAR. Requires alpha + 2 d > 1.
    """
    alpha = int(alpha)
    if alpha + 2 * d <= 1:
        raise ValueError(f"alpha={alpha} is not admissible for d={d} (alpha + 2d must exceed 1)")
    m = int(m)
    F = 1.0 if modified else float(m)
    S = float(m) if overlapping else 1.0
    L = m / F + m * d
    M = 1.0 + math.floor(S * (n_phase - L) / m)
    if M < 1:
        return float("nan")
    J = min(M, (d + 1) * S)
    r = M / S
    if modified:  # case 1, all alpha
        if J <= _J_MAX:
            return 1.0 / (_basic_sum(J, M, S, 1.0, alpha, d) / (_sz(np.array(0.0), 1.0, alpha, d) ** 2 * M))
        if r > d + 1:
            a0, a1 = _TABLE1[alpha][d - 1]
            return 1.0 / ((1.0 / r) * (a0 - a1 / r))
        mp = _J_MAX / r
        return 1.0 / (_basic_sum(_J_MAX, _J_MAX, mp, 1.0, alpha, d) / (_sz(np.array(0.0), F, alpha, d) ** 2 * _J_MAX))
    if alpha <= 0:  # case 2
        if J <= _J_MAX:
            mp = float(m) if m * (d + 1) <= _J_MAX else math.inf
            return 1.0 / (_basic_sum(J, M, S, mp, alpha, d) / (_sz(np.array(0.0), mp, alpha, d) ** 2 * M))
        if r > d + 1:
            a0, a1 = _TABLE2[alpha][d - 1]
            return 1.0 / ((1.0 / r) * (a0 - a1 / r))
        mp = _J_MAX / r
        return 1.0 / (
            _basic_sum(_J_MAX, _J_MAX, mp, math.inf, alpha, d) / (_sz(np.array(0.0), math.inf, alpha, d) ** 2 * _J_MAX)
        )
    if alpha == 1:  # case 3
        if J <= _J_MAX:
            return 1.0 / (_basic_sum(J, M, S, float(m), 1, d) / (_sz(np.array(0.0), float(m), 1, d) ** 2 * M))
        b0, b1 = _TABLE3[d - 1]
        if r > d + 1:
            a0, a1 = _TABLE2[1][d - 1]
            return 1.0 / ((1.0 / ((b0 + b1 * math.log(m)) ** 2 * r)) * (a0 - a1 / r))
        mp = _J_MAX / r
        return 1.0 / (_basic_sum(_J_MAX, _J_MAX, mp, mp, 1, d) / ((b0 + b1 * math.log(m)) ** 2 * _J_MAX))
    # case 4: alpha = +2, unmodified
    if math.ceil(r) <= d:
        # few terms: the exact basic-sum form (eq. 10) with F = m
        return 1.0 / (_basic_sum(J, M, S, float(m), 2, d) / (_sz(np.array(0.0), float(m), 2, d) ** 2 * M))
    a0 = binom(4 * d, 2 * d) / binom(2 * d, d) ** 2
    a1 = d / 2.0
    return 1.0 / ((1.0 / M) * (a0 - a1 / r))


#: (d, overlapping, modified) of each deviation kind ([GREENHALL2003] table 0 / SP 1065 sec. 5.3)
KIND_EDF_ARGS = {
    "adev": (2, False, False),
    "oadev": (2, True, False),
    "mdev": (2, True, True),
    "tdev": (2, True, True),
    "hdev": (3, False, False),
    "ohdev": (3, True, False),
}


def edf_for_kind(kind: str, alpha: np.ndarray, m: np.ndarray, n_phase: int) -> np.ndarray:
    """[GREENHALL2003]: EDF per tau for ``kind`` with the noise exponent ``alpha`` per tau."""
    d, overlapping, modified = KIND_EDF_ARGS[kind]
    alpha = np.broadcast_to(np.asarray(alpha), np.shape(m))
    lo = 2 - 2 * d  # smallest admissible alpha: alpha + 2d > 1
    out = np.empty(len(m))
    for j, (a, mj) in enumerate(zip(alpha, m)):
        a_int = int(np.clip(np.round(a), lo, 2))
        out[j] = edf_greenhall(a_int, d, int(mj), int(n_phase), overlapping, modified)
    return out


def chi2_interval(dev: np.ndarray, edf: np.ndarray, ci_level: float = ONE_SIGMA_CI) -> tuple[np.ndarray, np.ndarray]:
    """[NIST1065] eq. 42: chi-square interval of a deviation, sigma * sqrt(edf / chi2_{p}(edf))."""
    dev = np.asarray(dev, dtype=float)
    edf = np.asarray(edf, dtype=float)
    p_lo = 0.5 * (1.0 - ci_level)
    with np.errstate(invalid="ignore", divide="ignore"):
        lo = dev * np.sqrt(edf / stats.chi2.ppf(1.0 - p_lo, edf))
        hi = dev * np.sqrt(edf / stats.chi2.ppf(p_lo, edf))
    return lo, hi


def lag1_acf(z: np.ndarray) -> float:
    """[RILEY2004] eq. 2: lag-1 autocorrelation of a series (mean removed, vectorised)."""
    z = np.asarray(z, dtype=float)
    z = z - z.mean()
    den = float(np.dot(z, z))
    if den == 0.0:
        return 0.0
    return float(np.dot(z[:-1], z[1:]) / den)


def _detrend(z: np.ndarray, deg: int) -> np.ndarray:
    t = np.linspace(-1.0, 1.0, len(z))
    coef = np.polynomial.polynomial.polyfit(t, z, deg)
    return z - np.polynomial.polynomial.polyval(t, coef)


def acf_noise_id(z: np.ndarray, data_type: str, dmax: int = 2) -> tuple[int, float]:
    """[RILEY2004] sec. 3: power-law exponent alpha by lag-1 ACF with differencing.

    ``z``: the series at the averaging factor of interest: decimated phase (``data_type='phase'``) or
    averaged frequency/rate (``'freq'``). Returns (alpha rounded to an integer, alpha as float).
    """
    z = np.asarray(z, dtype=float)
    z = _detrend(z, 2 if data_type == "phase" else 1)
    d = 0
    while True:
        r1 = lag1_acf(z)
        delta = r1 / (1.0 + r1)
        if delta < 0.25 or d >= dmax or len(z) < 8:
            p = -2.0 * (delta + d)
            alpha = p + (2.0 if data_type == "phase" else 0.0)
            alpha_int = int(-np.round(2.0 * delta) - 2 * d) + (2 if data_type == "phase" else 0)
            return alpha_int, float(alpha)
        z = np.diff(z)
        d += 1
