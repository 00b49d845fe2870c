"""Allan-family estimators of one channel: result type, tau grids, OADEV/ADEV/MDEV/TDEV/HDEV/OHDEV, intervals.

Layer 3 of :mod:`assets_lib.noise.allan`. Definitions ([SEED002] eq. 3 and 4; [NIST1065] eqs. 7, 10, 14, 16,
17 and 18): overlapping Allan variance sigma^2(m) = sum_i (x[i+2m] - 2 x[i+m] + x[i])^2 / (2 n m^2 c^2),
i = 0..n-1, on the phase x of :mod:`.phase`; the non-overlapping (stride m), modified, time, Hadamard and
overlapping Hadamard variants alongside. Per tau: EDF ([GREENHALL2003]) at the power-law exponent identified
by the lag-1 ACF ([RILEY2004]) and a chi-square interval ([NIST1065] sec. 5.3).

Units: SI in, SI out. ``tau_s`` in seconds; deviations in the rate unit of the input (rad/s, m/s^2), also
for angle input (rad in, rad/s out).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np
import pandas as pd

from assets_lib.noise.allan import kernels as _k
from assets_lib.noise.allan.phase import PhaseSpec, build_phase
from assets_lib.noise.intervals import ONE_SIGMA_CI, acf_noise_id, chi2_interval, edf_for_kind

KINDS = ("adev", "oadev", "mdev", "tdev", "hdev", "ohdev")
DATA_TYPES = ("rate", "angle")
#: averaged points used for lag-1 ACF noise identification per tau
ID_POINTS = 4096
#: fewest averaged points for which the lag-1 ACF identification is trusted ([RILEY2004])
ID_MIN_POINTS = 32



# --------------------------------------------------------------------------------------------------------------
# result
# --------------------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class AllanResult:
    """One channel's deviation curve with per-tau EDF and chi-square interval ([NIST1065] sec. 5.3)."""

    kind: str  #: 'oadev' | 'adev' | 'mdev' | 'tdev' | 'hdev' | 'ohdev'
    data_type: str  #: 'rate' (frequency-like) | 'angle' (phase-like)
    rate_hz: float
    n_samples: int  #: input samples
    m: np.ndarray  #: averaging factors (tau = m / rate_hz)
    tau_s: np.ndarray
    adev: np.ndarray  #: the deviation of type ``kind`` (rate units; TDEV: angle units / rate)
    n_terms: np.ndarray  #: number of squared differences summed
    edf: np.ndarray  #: equivalent degrees of freedom ([GREENHALL2003])
    ci_lo: np.ndarray
    ci_hi: np.ndarray
    alpha: np.ndarray  #: power-law exponent used for the EDF (lag-1 ACF identification or given)
    ci_level: float
    channel: str = ""
    unit: str = ""
    backend: str = ""

    @property
    def avar(self) -> np.ndarray:
        return self.adev**2

    def to_frame(self) -> pd.DataFrame:
        return pd.DataFrame(
            {
                "channel": self.channel,
                "kind": self.kind,
                "m": self.m,
                "tau_s": self.tau_s,
                "adev": self.adev,
                "ci_lo": self.ci_lo,
                "ci_hi": self.ci_hi,
                "edf": self.edf,
                "n_terms": self.n_terms,
                "alpha": self.alpha,
            }
        )


# --------------------------------------------------------------------------------------------------------------
# tau grids
# --------------------------------------------------------------------------------------------------------------
def n_terms_for(kind: str, n_phase: int, m: np.ndarray) -> np.ndarray:
    """[NIST1065] eqs. 7, 10, 14, 16, 17: number of terms of each estimator for ``n_phase`` phase points."""
    m = np.asarray(m, dtype=np.int64)
    if kind == "oadev":
        return n_phase - 2 * m
    if kind == "adev":
        return (n_phase - 1) // m - 1
    if kind in ("mdev", "tdev"):
        return n_phase - 3 * m + 1
    if kind == "ohdev":
        return n_phase - 3 * m
    if kind == "hdev":
        return (n_phase - 1) // m - 2
    raise ValueError(f"unknown kind {kind!r}; expected one of {KINDS}")


def averaging_factors(
    n_samples: int,
    grid: str | int = "octave",
    *,
    kind: str = "oadev",
    data_type: str = "rate",
    m_max: int | None = None,
) -> np.ndarray:
    """Averaging factors m (tau = m tau0) for a record of ``n_samples``: octave, decade, dense, all or int.

    - ``'octave'``: 1, 2, 4, 8, ...  ([NIST1065] sec. 4; allantools 'octave')
    - ``'decade'``: 1, 2, 4, 10, 20, 40, ...  (Stable32 decade)
    - ``'dense'``: 100 unique log-spaced integers (the MATLAB example's grid); an int k gives k of them
    - ``'all'``: every m
    The default upper limit keeps at least two terms in the estimator (``m_max`` overrides).
    """
    n_phase = n_samples + 1 if data_type == "rate" else n_samples
    cap = _largest_m(kind, n_phase, min_terms=2)
    if m_max is not None:
        cap = min(cap, int(m_max))
    if cap < 1:
        return np.zeros(0, dtype=np.int64)
    if isinstance(grid, (int, np.integer)) and not isinstance(grid, bool):
        return log_spaced_factors(cap, int(grid))
    if grid == "octave":
        return 2 ** np.arange(0, int(math.floor(math.log2(cap))) + 1, dtype=np.int64)
    if grid == "decade":
        out = [mult * 10**k for k in range(0, 20) for mult in (1, 2, 4)]
        return np.array([m for m in out if m <= cap], dtype=np.int64)
    if grid == "dense":
        return log_spaced_factors(cap, 100)
    if grid == "all":
        return np.arange(1, cap + 1, dtype=np.int64)
    raise ValueError(f"unknown tau grid {grid!r}: octave, decade, dense, all or an integer count")


def log_spaced_factors(m_max: int, count: int) -> np.ndarray:
    """``count`` unique integers log-spaced from 1 to ``m_max`` (fewer only if m_max < count)."""
    m_max = int(m_max)
    if m_max <= count:
        return np.arange(1, m_max + 1, dtype=np.int64)
    k = count
    while True:
        m = np.unique(np.round(np.logspace(0.0, math.log10(m_max), k)).astype(np.int64))
        if len(m) >= count:
            return m
        k += 1


def _largest_m(kind: str, n_phase: int, min_terms: int) -> int:
    if kind == "oadev":
        return (n_phase - min_terms) // 2
    if kind == "adev":
        return (n_phase - 1) // (min_terms + 1)
    if kind in ("mdev", "tdev"):
        return (n_phase + 1 - min_terms) // 3
    if kind == "ohdev":
        return (n_phase - min_terms) // 3
    if kind == "hdev":
        return (n_phase - 1) // (min_terms + 2)
    raise ValueError(kind)


def resolve_m(taus, n_samples: int, rate_hz: float, kind: str, data_type: str) -> np.ndarray:
    if isinstance(taus, str) or isinstance(taus, (int, np.integer)):
        return averaging_factors(n_samples, taus, kind=kind, data_type=data_type)
    tau = np.asarray(taus, dtype=float)
    m = np.unique(np.round(tau * rate_hz).astype(np.int64))
    n_phase = n_samples + 1 if data_type == "rate" else n_samples
    m = m[(m >= 1) & (m <= _largest_m(kind, n_phase, 1))]
    return m


# --------------------------------------------------------------------------------------------------------------
# other estimators (numpy, blockwise; they are cheap next to OADEV)
# --------------------------------------------------------------------------------------------------------------
_HDIFF = (1.0, -3.0, 3.0, -1.0)


def _sumsq_diff(x: np.ndarray, m: int, stride: int, order: int) -> tuple[float, int]:
    """[NIST1065] eqs. 7 and 16/17: sum of squared 2nd (Allan) or 3rd (Hadamard) differences of x at lag m."""
    n_phase = len(x)
    n = (n_phase - 1 - order * m) // stride + 1 if n_phase - 1 - order * m >= 0 else 0
    if n <= 0:
        return 0.0, 0
    views = [x[k * m : k * m + (n - 1) * stride + 1 : stride] for k in range(order + 1)]
    B = _k.KERNEL_BLOCK
    D = np.empty(B)
    T = np.empty(B)
    s = 0.0
    for a in range(0, n, B):
        b = min(a + B, n)
        L = b - a
        if order == 2:
            np.subtract(views[2][a:b], views[1][a:b], out=D[:L])
            np.subtract(views[1][a:b], views[0][a:b], out=T[:L])
            np.subtract(D[:L], T[:L], out=D[:L])
        else:  # x3 - 3 x2 + 3 x1 - x0 = (x3 - x0) - 3 (x2 - x1)
            np.subtract(views[2][a:b], views[1][a:b], out=T[:L])
            T[:L] *= 3.0
            np.subtract(views[3][a:b], views[0][a:b], out=D[:L])
            np.subtract(D[:L], T[:L], out=D[:L])
        s += float(np.dot(D[:L], D[:L]))
    return s, n


def _mod_sums(x: np.ndarray, m: int) -> tuple[float, int]:
    """[NIST1065] eq. 14: sum_j (sum_{i=j}^{j+m-1} x[i+2m] - 2x[i+m] + x[i])^2 over j = 0..N-3m."""
    n_phase = len(x)
    n = n_phase - 3 * m + 1
    if n <= 0:
        return 0.0, 0
    B = max(_k.KERNEL_BLOCK, 4 * m)
    s = 0.0
    cs = np.empty(B + m)
    d = np.empty(B + m - 1)
    for a in range(0, n, B):
        b = min(a + B, n)
        L = b - a
        # second differences for i in [a, b + m - 1)
        nd = L + m - 1
        np.subtract(x[a + 2 * m : a + 2 * m + nd], x[a + m : a + m + nd], out=d[:nd])
        d[:nd] -= x[a + m : a + m + nd]
        d[:nd] += x[a : a + nd]
        cs[0] = 0.0
        np.cumsum(d[:nd], out=cs[1 : nd + 1])
        inner = cs[m : m + L] - cs[:L]
        s += float(np.dot(inner, inner))
    return s, n


def deviation_from_phase(x: np.ndarray, m: np.ndarray, kind: str, kernel) -> tuple[np.ndarray, np.ndarray]:
    """Deviation (in phase-sample units: divide by c = 1 for rate, tau0 for angle) and number of terms."""
    m = np.asarray(m, dtype=np.int64)
    n_phase = len(x)
    if kind == "oadev":
        sums = _k.oadev_sums_inmemory(x, m, kernel)
        n = n_phase - 2 * m
        return np.sqrt(sums / (2.0 * n)) / m, n
    dev = np.empty(len(m))
    n_out = np.empty(len(m), dtype=np.int64)
    with _k.single_thread_blas():
        for j, mj in enumerate(m):
            mj = int(mj)
            if kind == "adev":
                s, n = _sumsq_diff(x, mj, mj, 2)
                dev[j] = math.sqrt(s / (2.0 * n)) / mj
            elif kind in ("hdev", "ohdev"):
                s, n = _sumsq_diff(x, mj, mj if kind == "hdev" else 1, 3)
                dev[j] = math.sqrt(s / (6.0 * n)) / mj
            elif kind in ("mdev", "tdev"):
                s, n = _mod_sums(x, mj)
                mvar = s / (2.0 * mj**4 * n)
                dev[j] = math.sqrt(mvar) if kind == "mdev" else mj * math.sqrt(mvar / 3.0)
            else:
                raise ValueError(f"unknown kind {kind!r}")
            n_out[j] = n
    return dev, n_out


# --------------------------------------------------------------------------------------------------------------
# noise identification and intervals
# --------------------------------------------------------------------------------------------------------------
def _alpha_from_decimated(dec: Mapping[int, np.ndarray], m: np.ndarray, data_type: str, kind: str) -> np.ndarray:
    """[RILEY2004]: alpha per tau from the phase sampled every m (first ID_POINTS+1 points)."""
    dmax = 3 if kind in ("hdev", "ohdev") else 2
    out = np.zeros(len(m))
    last = 0.0
    for j, mj in enumerate(m):
        xs = dec[int(mj)]
        if len(xs) - 1 >= ID_MIN_POINTS:
            if data_type == "rate":
                z = np.diff(xs) / float(mj)
                a_int, _ = acf_noise_id(z, "freq", dmax=dmax)
            else:
                a_int, _ = acf_noise_id(xs, "phase", dmax=dmax)
            last = float(a_int)
        out[j] = last
    return out


def finish_result(
    kind: str,
    data_type: str,
    rate_hz: float,
    spec: PhaseSpec,
    m: np.ndarray,
    dev_units: np.ndarray,
    n_terms: np.ndarray,
    alpha,
    dec: Mapping[int, np.ndarray] | None,
    ci_level: float,
    channel: str,
    unit: str,
    backend: str,
) -> AllanResult:
    c = 1.0 if data_type == "rate" else 1.0 / rate_hz
    dev = dev_units / c
    if kind == "tdev":
        dev = dev / rate_hz  # TDEV = tau MDEV / sqrt(3): tau = m / rate_hz (angle units)
    if alpha is None:
        alpha_arr = _alpha_from_decimated(dec, m, data_type, kind) if len(m) else np.zeros(0)
    else:
        alpha_arr = np.broadcast_to(np.asarray(alpha, dtype=float), m.shape).astype(float)
    edf = edf_for_kind(kind, alpha_arr, m, spec.n_phase) if len(m) else np.zeros(0)
    lo, hi = chi2_interval(dev, edf, ci_level)
    return AllanResult(
        kind=kind,
        data_type=data_type,
        rate_hz=float(rate_hz),
        n_samples=spec.n_samples,
        m=m,
        tau_s=m / float(rate_hz),
        adev=dev,
        n_terms=np.asarray(n_terms, dtype=np.int64),
        edf=edf,
        ci_lo=lo,
        ci_hi=hi,
        alpha=alpha_arr,
        ci_level=float(ci_level),
        channel=channel,
        unit=unit,
        backend=backend,
    )


# --------------------------------------------------------------------------------------------------------------
# public single-channel API
# --------------------------------------------------------------------------------------------------------------
def allan_deviation(
    data,
    rate_hz: float,
    taus="octave",
    *,
    kind: str = "oadev",
    data_type: str = "rate",
    ci_level: float = ONE_SIGMA_CI,
    alpha=None,
    backend: str = "auto",
    channel: str = "",
    unit: str = "",
    _phase_buffer: np.ndarray | None = None,
) -> AllanResult:
    """[SEED002] eq. 3/4, [NIST1065] eqs. 7-18: Allan-family deviation of one channel, with EDF and interval.

    ``data``: 1-D rate samples (``data_type='rate'``, e.g. rad/s) or angle samples (``'angle'``, e.g. rad), any
    float dtype (accumulated in float64). ``taus``: 'octave' | 'decade' | 'dense' | 'all' | int count | array of
    tau in seconds (rounded to multiples of 1/rate_hz). ``alpha``: power-law exponent(s) for the EDF; None
    identifies it per tau by lag-1 ACF. ``ci_level``: two-sided level of the chi-square interval.
    """
    if kind not in KINDS:
        raise ValueError(f"unknown kind {kind!r}; expected one of {KINDS}")
    if data_type not in DATA_TYPES:
        raise ValueError(f"data_type must be one of {DATA_TYPES}")
    if not rate_hz > 0:
        raise ValueError("rate_hz must be positive")
    y = np.asarray(data)
    if y.ndim != 1:
        raise ValueError("allan_deviation takes one channel; use allan_deviations for several")
    kern = _k.get_kernel(backend)
    m = resolve_m(taus, len(y), rate_hz, kind, data_type)
    x, spec = build_phase(y, data_type, out=_phase_buffer)
    dev_units, n_terms = deviation_from_phase(x, m, kind, kern) if len(m) else (np.zeros(0), np.zeros(0))
    dec = {int(mj): np.array(x[:: int(mj)][: ID_POINTS + 1]) for mj in m} if alpha is None else None
    return finish_result(kind, data_type, rate_hz, spec, m, dev_units, n_terms, alpha, dec, ci_level, channel, unit, kern.name)


def oadev(data, rate_hz: float, taus="octave", **kw) -> AllanResult:
    """[NIST1065] eq. 10 ([SEED002] eq. 4): overlapping Allan deviation."""
    return allan_deviation(data, rate_hz, taus, kind="oadev", **kw)


def adev(data, rate_hz: float, taus="octave", **kw) -> AllanResult:
    """[NIST1065] eq. 7 ([SEED002] eq. 3): non-overlapping Allan deviation."""
    return allan_deviation(data, rate_hz, taus, kind="adev", **kw)


def mdev(data, rate_hz: float, taus="octave", **kw) -> AllanResult:
    """[NIST1065] eq. 14: modified Allan deviation."""
    return allan_deviation(data, rate_hz, taus, kind="mdev", **kw)


def hdev(data, rate_hz: float, taus="octave", **kw) -> AllanResult:
    """[NIST1065] eq. 16: (non-overlapping) Hadamard deviation."""
    return allan_deviation(data, rate_hz, taus, kind="hdev", **kw)


def ohdev(data, rate_hz: float, taus="octave", **kw) -> AllanResult:
    """[NIST1065] eq. 17: overlapping Hadamard deviation."""
    return allan_deviation(data, rate_hz, taus, kind="ohdev", **kw)


def tdev(data, rate_hz: float, taus="octave", **kw) -> AllanResult:
    """[NIST1065] eq. 15: time deviation, tau * MDEV / sqrt(3)."""
    return allan_deviation(data, rate_hz, taus, kind="tdev", **kw)
