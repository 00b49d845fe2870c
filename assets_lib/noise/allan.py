"""Allan-family deviations of rate (frequency-like) or angle (phase-like) records: exact, fast, bounded memory.

Definitions (seed 002 eq. 3 and 4; NIST SP 1065 eqs. 7, 10, 14, 16, 17 and 18):
- the record is turned into one float64 "phase" array x (rate: the cumulative sum of the mean-removed rate;
  angle: the angle minus the line through its end points), whatever the input dtype (allan.md section 4);
- overlapping Allan variance  sigma^2(m) = sum_i (x[i+2m] - 2 x[i+m] + x[i])^2 / (2 n m^2 c^2), i = 0..n-1;
- non-overlapping (stride m), modified, time, Hadamard and overlapping Hadamard variants alongside.

The overlapping estimator is computed exactly (every offset i) with blockwise second differences: no N-sized
temporary per tau, one phase array as the only N-sized allocation (in memory), or none at all when streaming
a parquet file (:func:`allan_parquet`). The streaming and in-memory routes share one block partition and one
kernel, so they return bit-identical deviations. Kernels: a compiled loop when numba is importable (an optional
accelerator, about 4x the numpy kernel), else numpy with preallocated buffers; results agree to ~1e-14.

Units: SI in, SI out. ``tau_s`` in seconds; deviations in the rate unit of the input (rad/s, m/s^2), also
for angle input (rad in, rad/s out).
"""

from __future__ import annotations

import contextlib
import ctypes
import glob
import math
import os
from collections.abc import Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass

import numpy as np
import pandas as pd

from assets_lib.noise.intervals import ONE_SIGMA_CI, acf_noise_id, chi2_interval, edf_for_kind

try:  # optional accelerator: results are the same estimator; see module docstring
    import numba as _numba

    HAVE_NUMBA = True
except Exception:  # pragma: no cover - exercised when numba is absent
    _numba = None
    HAVE_NUMBA = False

KINDS = ("adev", "oadev", "mdev", "tdev", "hdev", "ohdev")
DATA_TYPES = ("rate", "angle")

#: i-block of the second-difference kernel (the fixed partition shared by every route)
KERNEL_BLOCK = 1 << 14
#: block of the cumulative-sum pass and of the streaming reader
PHASE_BLOCK = 1 << 20
#: the mean is the sequential sum of pairwise sums over contiguous float64 blocks of SUM_BLOCK samples
SUM_BLOCK = 1 << 15
#: taus with m >= M_CHAIN use the chain-ordered block partition (one memory stream per tau)
M_CHAIN = 1 << 16
#: streaming: taus with 2m <= SMALL_SPAN are served by the sliding window, larger ones from the phase spill file
SMALL_SPAN = 1 << 23
#: averaged points used for lag-1 ACF noise identification per tau
ID_POINTS = 4096
#: fewest averaged points for which the lag-1 ACF identification is trusted (Riley & Greenhall 2004)
ID_MIN_POINTS = 32


# --------------------------------------------------------------------------------------------------------------
# results
# --------------------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class AllanResult:
    """One channel's deviation curve with per-tau EDF and chi-square interval (NIST SP 1065 sec. 5.3)."""

    kind: str  #: 'oadev' | 'adev' | 'mdev' | 'tdev' | 'hdev' | 'ohdev'
    data_type: str  #: 'rate' (frequency-like) | 'angle' (phase-like)
    rate_hz: float
    n_samples: int  #: input samples
    m: np.ndarray  #: averaging factors (tau = m / rate_hz)
    tau_s: np.ndarray
    adev: np.ndarray  #: the deviation of type ``kind`` (rate units; TDEV: angle units / rate)
    n_terms: np.ndarray  #: number of squared differences summed
    edf: np.ndarray  #: equivalent degrees of freedom (Greenhall & Riley 2003)
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
    """NIST SP 1065 eqs. 7, 10, 14, 16, 17: number of terms of each estimator for ``n_phase`` phase points."""
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

    - ``'octave'``: 1, 2, 4, 8, ...  (NIST SP 1065 sec. 4; allantools 'octave')
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


def _resolve_m(taus, n_samples: int, rate_hz: float, kind: str, data_type: str) -> np.ndarray:
    if isinstance(taus, str) or isinstance(taus, (int, np.integer)):
        return averaging_factors(n_samples, taus, kind=kind, data_type=data_type)
    tau = np.asarray(taus, dtype=float)
    m = np.unique(np.round(tau * rate_hz).astype(np.int64))
    n_phase = n_samples + 1 if data_type == "rate" else n_samples
    m = m[(m >= 1) & (m <= _largest_m(kind, n_phase, 1))]
    return m


# --------------------------------------------------------------------------------------------------------------
# phase construction (float64 accumulation whatever the input dtype; allan.md section 4)
# --------------------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class _PhaseSpec:
    """How raw samples become the float64 phase: rate -> cumsum(y - mean); angle -> theta - end-point line."""

    data_type: str
    n_samples: int
    mean: float = 0.0  # rate
    theta0: float = 0.0  # angle
    slope: float = 0.0  # angle, per sample

    @property
    def n_phase(self) -> int:
        return self.n_samples + 1 if self.data_type == "rate" else self.n_samples


def _as_f64_block(block: np.ndarray, scratch: np.ndarray) -> np.ndarray:
    """Contiguous float64 copy (or view) of ``block``: the same values and layout for every source."""
    if block.dtype == np.float64 and block.flags.c_contiguous:
        return block
    out = scratch[: len(block)]
    np.copyto(out, block, casting="same_kind")
    return out


def _check_finite(block: np.ndarray, where: int) -> None:
    if not np.isfinite(block).all():
        bad = where + int(np.flatnonzero(~np.isfinite(block))[0])
        raise ValueError(
            f"non-finite sample at index {bad}: Allan deviations need a gap-free record (split or fill the gap)"
        )


def _block_sum(b: np.ndarray) -> float:
    """Sequential sum of the sums of SUM_BLOCK pieces of a contiguous float64 block (the canonical order).

    Each piece is summed by numba's vectorised loop when numba is present, else by numpy's pairwise sum; every
    route of one installation uses the same function, so the mean is bit-identical across routes.
    """
    if HAVE_NUMBA:
        return float(_nb_block_sum(b, SUM_BLOCK))
    t = 0.0
    for a in range(0, len(b), SUM_BLOCK):
        t += float(np.add.reduce(b[a : a + SUM_BLOCK]))
    return t


def _phase_spec_from_blocks(blocks: Iterable[np.ndarray], data_type: str, sink=None) -> _PhaseSpec:
    """Pass 0: the mean (rate) or the end points (angle), summed blockwise in float64 in a fixed block order.

    ``sink``: optional binary file receiving the float64 samples (the streaming route's raw spill).
    """
    total = 0.0
    n = 0
    first = last = None
    scratch = np.empty(PHASE_BLOCK)
    for raw in blocks:
        b = _as_f64_block(raw, scratch)
        bs = _block_sum(b)
        if not math.isfinite(bs):  # NaN / inf propagate into the sum: locate them only then
            _check_finite(b, n)
            raise ValueError(f"samples {n}..{n + len(b)} overflow a float64 sum")
        if first is None and len(b):
            first = float(b[0])
        if len(b):
            last = float(b[-1])
        total += bs
        n += len(b)
        if sink is not None:
            sink.write(b.tobytes())
    if n < 3:
        raise ValueError(f"need at least 3 samples, got {n}")
    if data_type == "rate":
        return _PhaseSpec("rate", n, mean=total / n)
    if data_type == "angle":
        return _PhaseSpec("angle", n, theta0=first, slope=(last - first) / (n - 1))
    raise ValueError(f"data_type must be 'rate' or 'angle', got {data_type!r}")


class _PhaseWriter:
    """Turns consecutive raw blocks into consecutive phase values (bit-identical for any source)."""

    def __init__(self, spec: _PhaseSpec):
        self.spec = spec
        self.next_index = 0  # raw sample index of the next block
        self.x_last = 0.0  # rate: phase value before the next block
        self.scratch = np.empty(PHASE_BLOCK)

    def first_values(self) -> np.ndarray:
        """Phase values that precede any raw block (rate: x[0] = 0)."""
        return np.zeros(1) if self.spec.data_type == "rate" else np.zeros(0)

    def write(self, raw: np.ndarray, out: np.ndarray) -> None:
        """Write the phase of ``raw`` into ``out`` (len(raw) values)."""
        L = len(raw)
        s = self.spec
        if s.data_type == "rate":
            b = _as_f64_block(raw, self.scratch)
            if HAVE_NUMBA:  # the same IEEE operations in the same order as the numpy branch: identical bits
                self.x_last = float(_nb_phase_rate(b, s.mean, self.x_last, out))
            else:
                np.subtract(b, s.mean, out=out, dtype=np.float64)
                out[0] += self.x_last
                np.cumsum(out, out=out)
                self.x_last = float(out[-1])
        else:
            b = _as_f64_block(raw, self.scratch)
            np.subtract(b, s.theta0, out=out, dtype=np.float64)
            k = np.arange(self.next_index, self.next_index + L, dtype=np.float64)
            k *= s.slope
            np.subtract(out, k, out=out)
        self.next_index += L


def _array_blocks(y: np.ndarray, start: int = 0, size: int = PHASE_BLOCK) -> Iterator[np.ndarray]:
    for a in range(start, len(y), size):
        yield y[a : a + size]


def build_phase(y: np.ndarray, data_type: str = "rate", out: np.ndarray | None = None) -> tuple[np.ndarray, _PhaseSpec]:
    """Seed 002 eq. 1 / NIST SP 1065 eq. 4: float64 phase of a record (mean-removed cumulative sum for rate)."""
    y = np.asarray(y)
    if y.ndim != 1:
        raise ValueError("build_phase takes one channel (1-D)")
    spec = _phase_spec_from_blocks(_array_blocks(y), data_type)
    x = out[: spec.n_phase] if out is not None and len(out) >= spec.n_phase else np.empty(spec.n_phase)
    w = _PhaseWriter(spec)
    head = w.first_values()
    x[: len(head)] = head
    pos = len(head)
    for raw in _array_blocks(y):
        w.write(raw, x[pos : pos + len(raw)])
        pos += len(raw)
    return x, spec


# --------------------------------------------------------------------------------------------------------------
# kernels: sum over one i-block of squared second differences
# --------------------------------------------------------------------------------------------------------------
def _aligned_empty(n: int) -> np.ndarray:
    raw = np.empty(n + 16)
    off = (-raw.ctypes.data % 64) // 8
    return raw[off : off + n]


_OPENBLAS = None


def _openblas_handle():
    global _OPENBLAS
    if _OPENBLAS is None:
        _OPENBLAS = False
        libdir = os.path.join(os.path.dirname(np.__file__), os.pardir, "numpy.libs")
        for path in glob.glob(os.path.join(libdir, "*openblas*")):
            try:
                lib = ctypes.CDLL(path)
                for get, set_ in (
                    ("scipy_openblas_get_num_threads64_", "scipy_openblas_set_num_threads64_"),
                    ("openblas_get_num_threads64_", "openblas_set_num_threads64_"),
                    ("openblas_get_num_threads", "openblas_set_num_threads"),
                ):
                    if hasattr(lib, get) and hasattr(lib, set_):
                        _OPENBLAS = (getattr(lib, get), getattr(lib, set_))
                        break
            except OSError:
                continue
            if _OPENBLAS:
                break
    return _OPENBLAS or None


@contextlib.contextmanager
def _single_thread_blas():
    """Pin OpenBLAS to one thread while thousands of small dot products run (allan.md section 3.2)."""
    h = _openblas_handle()
    if h is None:
        yield
        return
    get, set_ = h
    try:
        before = int(get())
    except Exception:  # pragma: no cover
        yield
        return
    set_(ctypes.c_int(1))
    try:
        yield
    finally:
        set_(ctypes.c_int(before))


class _NumpyKernel:
    """numpy blockwise kernel: second differences into a preallocated, 64-byte aligned buffer, then a dot."""

    name = "numpy"

    def __init__(self):
        self.S = _aligned_empty(2 * KERNEL_BLOCK)
        self.D = _aligned_empty(KERNEL_BLOCK)
        self.T = _aligned_empty(KERNEL_BLOCK)

    def _block(self, x0, x1, x2) -> float:
        L = len(x0)
        D, T = self.D[:L], self.T[:L]
        np.subtract(x2, x1, out=D)
        np.subtract(x1, x0, out=T)
        np.subtract(D, T, out=D)
        return float(np.dot(D, D))

    def window(self, x, base, ms, n_terms, chain, next_a, acc, avail_end):
        """Every complete i-block of each tau whose phase window lies in x[base, avail_end), in increasing i."""
        B = KERNEL_BLOCK
        D, S = self.D, self.S
        for j in range(len(ms)):
            m = int(ms[j])
            nt = int(n_terms[j])
            a = int(next_a[j])
            ch = bool(chain[j])
            s = float(acc[j])
            while a < nt:
                b = min(a + B, nt)
                if ch:
                    b = min(b, (a // m + 1) * m)
                if b + 2 * m > avail_end:
                    break
                L = b - a
                lo = a - base
                if m <= B:  # S = x[i+m] - x[i] once, D = S[i+m] - S[i]: the same floating-point values
                    np.subtract(x[lo + m : lo + L + 2 * m], x[lo : lo + L + m], out=S[: L + m])
                    np.subtract(S[m : m + L], S[:L], out=D[:L])
                    s += float(np.dot(D[:L], D[:L]))
                else:
                    s += self._block(x[lo : lo + L], x[lo + m : lo + L + m], x[lo + 2 * m : lo + L + 2 * m])
                a = b
            acc[j] = s
            next_a[j] = a

    def chain(self, x, m, n):
        """Chain-ordered blocks (i, i+m, i+2m reuse two of three phase windows); partials summed in i order."""
        B = KERNEL_BLOCK
        R = -(-m // B)
        J = -(-n // m)
        P = np.zeros((J, R))
        for rb in range(R):
            r = rb * B
            for jj in range(J):
                i0 = jj * m + r
                if i0 >= n:
                    break
                i1 = min(jj * m + min(r + B, m), n)
                P[jj, rb] = self._block(x[i0:i1], x[i0 + m : i1 + m], x[i0 + 2 * m : i1 + 2 * m])
        return _ordered_sum(P, m, n)

    def block(self, x0, x1, x2) -> float:
        return self._block(x0, x1, x2)


def _ordered_sum(P: np.ndarray, m: int, n: int) -> float:
    """Sum of chain-block partials in increasing-i order (the order the streaming route accumulates)."""
    B = KERNEL_BLOCK
    s = 0.0
    for jj in range(P.shape[0]):
        for rb in range(P.shape[1]):
            if jj * m + rb * B < n:
                s += float(P[jj, rb])
    return s


if HAVE_NUMBA:
    _FM = {"reassoc", "contract"}  # reassociation only for the reduction; no finite-math assumptions

    @_numba.njit(fastmath=_FM, boundscheck=False, cache=True)
    def _nb_ssq(x0, x1, x2):  # pragma: no cover - compiled
        s = 0.0
        for i in range(x0.shape[0]):
            d = (x2[i] - x1[i]) - (x1[i] - x0[i])
            s += d * d
        return s

    @_numba.njit(boundscheck=False, cache=True)
    def _nb_window(x, base, ms, n_terms, chain, next_a, acc, avail_end, B):  # pragma: no cover - compiled
        for j in range(ms.shape[0]):
            m = ms[j]
            nt = n_terms[j]
            a = next_a[j]
            s = acc[j]
            while a < nt:
                b = min(a + B, nt)
                if chain[j]:
                    b = min(b, (a // m + 1) * m)
                if b + 2 * m > avail_end:
                    break
                lo = a - base
                hi = b - base
                s += _nb_ssq(x[lo:hi], x[lo + m : hi + m], x[lo + 2 * m : hi + 2 * m])
                a = b
            acc[j] = s
            next_a[j] = a

    @_numba.njit(boundscheck=False, cache=True)
    def _nb_chain(x, m, n, B):  # pragma: no cover - compiled
        R = (m + B - 1) // B
        J = (n + m - 1) // m
        P = np.zeros((J, R))
        for rb in range(R):
            r = rb * B
            for jj in range(J):
                i0 = jj * m + r
                if i0 >= n:
                    break
                i1 = min(jj * m + min(r + B, m), n)
                P[jj, rb] = _nb_ssq(x[i0:i1], x[i0 + m : i1 + m], x[i0 + 2 * m : i1 + 2 * m])
        s = 0.0
        for jj in range(J):
            for rb in range(R):
                if jj * m + rb * B < n:
                    s += P[jj, rb]
        return s

    @_numba.njit(boundscheck=False, cache=True)
    def _nb_block(x0, x1, x2):  # pragma: no cover - compiled
        return _nb_ssq(x0, x1, x2)

    @_numba.njit(fastmath=_FM, boundscheck=False, cache=True)
    def _nb_piece_sum(b):  # pragma: no cover - compiled
        s = 0.0
        for k in range(b.shape[0]):
            s += b[k]
        return s

    @_numba.njit(boundscheck=False, cache=True)
    def _nb_block_sum(b, piece):  # pragma: no cover - compiled
        t = 0.0
        for a in range(0, b.shape[0], piece):
            t += _nb_piece_sum(b[a : min(a + piece, b.shape[0])])
        return t

    @_numba.njit(boundscheck=False, cache=True)
    def _nb_phase_rate(b, mean, x_last, out):  # pragma: no cover - compiled
        acc = x_last
        for k in range(b.shape[0]):
            acc = acc + (b[k] - mean)
            out[k] = acc
        return acc


class _NumbaKernel:
    """Compiled fused kernel (numba): the same block partition and accumulation order as the numpy kernel."""

    name = "numba"

    def window(self, x, base, ms, n_terms, chain, next_a, acc, avail_end):
        _nb_window(x, np.int64(base), ms, n_terms, chain, next_a, acc, np.int64(avail_end), np.int64(KERNEL_BLOCK))

    def chain(self, x, m, n):
        return float(_nb_chain(x, np.int64(m), np.int64(n), np.int64(KERNEL_BLOCK)))

    def block(self, x0, x1, x2) -> float:
        return float(_nb_block(x0, x1, x2))


def _kernel(backend: str):
    if backend == "auto":
        backend = "numba" if HAVE_NUMBA else "numpy"
    if backend == "numba":
        if not HAVE_NUMBA:
            raise ValueError("backend='numba' requested but numba is not installed")
        return _NumbaKernel()
    if backend == "numpy":
        return _NumpyKernel()
    raise ValueError(f"backend must be 'auto', 'numba' or 'numpy', got {backend!r}")


# --------------------------------------------------------------------------------------------------------------
# overlapping Allan sums: in memory
# --------------------------------------------------------------------------------------------------------------
def _oadev_sums_inmemory(x: np.ndarray, m: np.ndarray, kernel) -> np.ndarray:
    """NIST SP 1065 eq. 11 (seed 002 eq. 4): sum_i (x[i+2m] - 2x[i+m] + x[i])^2 for each m, exactly.

    Small m: block-outer, tau-inner over cache-sized windows. m >= M_CHAIN: blocks visited in chains
    i, i+m, i+2m, ... so that two of the three phase windows are still in cache (one memory stream per tau).
    Both partitions are fixed functions of (m, n): the streaming route reproduces them bit for bit.
    """
    n_phase = len(x)
    m = np.asarray(m, dtype=np.int64)
    n_terms = (n_phase - 2 * m).astype(np.int64)
    acc = np.zeros(len(m))
    chain = m >= M_CHAIN
    with _single_thread_blas():
        if (~chain).any():
            ms, nt = m[~chain].copy(), n_terms[~chain].copy()
            next_a = np.zeros(len(ms), dtype=np.int64)
            a_small = np.zeros(len(ms))
            flags = np.zeros(len(ms), dtype=np.bool_)
            step = 1 << 18
            for end in range(step, n_phase + step, step):
                kernel.window(x, 0, ms, nt, flags, next_a, a_small, min(end, n_phase))
            acc[~chain] = a_small
        for j in np.flatnonzero(chain):
            acc[j] = kernel.chain(x, int(m[j]), int(n_terms[j]))
    return acc


# --------------------------------------------------------------------------------------------------------------
# other estimators (numpy, blockwise; they are cheap next to OADEV)
# --------------------------------------------------------------------------------------------------------------
_HDIFF = (1.0, -3.0, 3.0, -1.0)


def _sumsq_diff(x: np.ndarray, m: int, stride: int, order: int) -> tuple[float, int]:
    """NIST SP 1065 eqs. 7 and 16/17: sum of squared 2nd (Allan) or 3rd (Hadamard) differences of x at lag m."""
    n_phase = len(x)
    n = (n_phase - 1 - order * m) // stride + 1 if n_phase - 1 - order * m >= 0 else 0
    if n <= 0:
        return 0.0, 0
    views = [x[k * m : k * m + (n - 1) * stride + 1 : stride] for k in range(order + 1)]
    B = KERNEL_BLOCK
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
    """NIST SP 1065 eq. 14: sum_j (sum_{i=j}^{j+m-1} x[i+2m] - 2x[i+m] + x[i])^2 over j = 0..N-3m."""
    n_phase = len(x)
    n = n_phase - 3 * m + 1
    if n <= 0:
        return 0.0, 0
    B = max(KERNEL_BLOCK, 4 * m)
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


def _deviation_from_phase(x: np.ndarray, m: np.ndarray, kind: str, kernel) -> tuple[np.ndarray, np.ndarray]:
    """Deviation (in phase-sample units: divide by c = 1 for rate, tau0 for angle) and number of terms."""
    m = np.asarray(m, dtype=np.int64)
    n_phase = len(x)
    if kind == "oadev":
        sums = _oadev_sums_inmemory(x, m, kernel)
        n = n_phase - 2 * m
        return np.sqrt(sums / (2.0 * n)) / m, n
    dev = np.empty(len(m))
    n_out = np.empty(len(m), dtype=np.int64)
    with _single_thread_blas():
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
    """Riley & Greenhall 2004: alpha per tau from the phase sampled every m (first ID_POINTS+1 points)."""
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


def _finish(
    kind: str,
    data_type: str,
    rate_hz: float,
    spec: _PhaseSpec,
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
# public in-memory API
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
    """Seed 002 eq. 3/4, NIST SP 1065 eqs. 7-18: Allan-family deviation of one channel, with EDF and interval.

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
    kern = _kernel(backend)
    m = _resolve_m(taus, len(y), rate_hz, kind, data_type)
    x, spec = build_phase(y, data_type, out=_phase_buffer)
    dev_units, n_terms = _deviation_from_phase(x, m, kind, kern) if len(m) else (np.zeros(0), np.zeros(0))
    dec = {int(mj): np.array(x[:: int(mj)][: ID_POINTS + 1]) for mj in m} if alpha is None else None
    return _finish(kind, data_type, rate_hz, spec, m, dev_units, n_terms, alpha, dec, ci_level, channel, unit, kern.name)


def oadev(data, rate_hz: float, taus="octave", **kw) -> AllanResult:
    """NIST SP 1065 eq. 10 (seed 002 eq. 4): overlapping Allan deviation."""
    return allan_deviation(data, rate_hz, taus, kind="oadev", **kw)


def adev(data, rate_hz: float, taus="octave", **kw) -> AllanResult:
    """NIST SP 1065 eq. 7 (seed 002 eq. 3): non-overlapping Allan deviation."""
    return allan_deviation(data, rate_hz, taus, kind="adev", **kw)


def mdev(data, rate_hz: float, taus="octave", **kw) -> AllanResult:
    """NIST SP 1065 eq. 14: modified Allan deviation."""
    return allan_deviation(data, rate_hz, taus, kind="mdev", **kw)


def hdev(data, rate_hz: float, taus="octave", **kw) -> AllanResult:
    """NIST SP 1065 eq. 16: (non-overlapping) Hadamard deviation."""
    return allan_deviation(data, rate_hz, taus, kind="hdev", **kw)


def ohdev(data, rate_hz: float, taus="octave", **kw) -> AllanResult:
    """NIST SP 1065 eq. 17: overlapping Hadamard deviation."""
    return allan_deviation(data, rate_hz, taus, kind="ohdev", **kw)


def tdev(data, rate_hz: float, taus="octave", **kw) -> AllanResult:
    """NIST SP 1065 eq. 15: time deviation, tau * MDEV / sqrt(3)."""
    return allan_deviation(data, rate_hz, taus, kind="tdev", **kw)


def _channels_of(data, channels: Sequence[str] | None) -> list[tuple[str, np.ndarray]]:
    if isinstance(data, pd.DataFrame):
        cols = list(channels) if channels is not None else [c for c in data.columns if c != "time_s"]
        return [(str(c), data[c].to_numpy()) for c in cols]
    if isinstance(data, Mapping):
        cols = list(channels) if channels is not None else list(data.keys())
        return [(str(c), np.asarray(data[c])) for c in cols]
    arr = np.asarray(data)
    if arr.ndim == 1:
        return [(channels[0] if channels else "ch0", arr)]
    names = list(channels) if channels is not None else [f"ch{k}" for k in range(arr.shape[1])]
    if len(names) != arr.shape[1]:
        raise ValueError("one channel name per column")
    return [(names[k], arr[:, k]) for k in range(arr.shape[1])]


def allan_deviations(
    data, rate_hz: float, taus="octave", *, channels: Sequence[str] | None = None, units=None, **kw
) -> dict[str, AllanResult]:
    """Seed 002 eq. 4 per channel: several channels in one call, reusing one float64 phase buffer.

    ``data``: (N, C) array, mapping of name -> array, or DataFrame (a ``time_s`` column is skipped).
    ``units``: one unit string for all channels or a mapping channel -> unit (labels only; data are SI).
    """
    arr = np.asarray(data) if isinstance(data, np.ndarray) else None
    if arr is not None and arr.ndim == 2 and arr.shape[1] > 1 and not arr.flags.f_contiguous:
        return _deviations_rowmajor(arr, rate_hz, taus, channels=channels, units=units, **kw)
    chans = _channels_of(data, channels)
    n = len(chans[0][1]) if chans else 0
    buf = np.empty(n + 1) if n else None
    out = {}
    for name, y in chans:
        unit = units.get(name, "") if isinstance(units, Mapping) else (units or "")
        out[name] = allan_deviation(y, rate_hz, taus, channel=name, unit=unit, _phase_buffer=buf, **kw)
    return out


def _deviations_rowmajor(arr, rate_hz, taus, *, channels=None, units=None, kind="oadev", data_type="rate",
                         ci_level=ONE_SIGMA_CI, alpha=None, backend="auto") -> dict[str, AllanResult]:
    """Row-major (N, C) input: one transposing pass into C float64 phase buffers (1.0x the input), then each
    channel exactly as :func:`allan_deviation` would compute it (bit-identical)."""
    n, C = arr.shape
    names = list(channels) if channels is not None else [f"ch{k}" for k in range(C)]
    if len(names) != C:
        raise ValueError("one channel name per column")
    if n < 3:
        raise ValueError(f"need at least 3 samples, got {n}")
    lead = 1 if data_type == "rate" else 0
    xs = [np.empty(n + lead) for _ in range(C)]
    totals = [0.0] * C
    step = SUM_BLOCK  # one pass over the rows: transpose and the canonical block sums together
    for a in range(0, n, step):
        blk = arr[a : a + step]
        for c in range(C):
            seg = xs[c][lead + a : lead + a + len(blk)]
            np.copyto(seg, blk[:, c], casting="same_kind")
            bs = _block_sum(seg)
            if not math.isfinite(bs):
                _check_finite(seg, a)
                raise ValueError(f"samples {a}..{a + len(seg)} overflow a float64 sum")
            totals[c] += bs
    kern = _kernel(backend)
    m = _resolve_m(taus, n, rate_hz, kind, data_type)
    out = {}
    for c, name in enumerate(names):
        x = xs[c]
        if data_type == "rate":
            spec = _PhaseSpec("rate", n, mean=totals[c] / n)
        else:
            spec = _PhaseSpec("angle", n, theta0=float(x[0]), slope=(float(x[-1]) - float(x[0])) / (n - 1))
        w = _PhaseWriter(spec)
        if lead:
            x[0] = 0.0
        for a in range(0, n, PHASE_BLOCK):
            seg = x[lead + a : lead + min(a + PHASE_BLOCK, n)]
            w.write(seg, seg)
        dev_units, n_terms = _deviation_from_phase(x, m, kind, kern) if len(m) else (np.zeros(0), np.zeros(0))
        dec = {int(mj): np.array(x[:: int(mj)][: ID_POINTS + 1]) for mj in m} if alpha is None else None
        unit = units.get(name, "") if isinstance(units, Mapping) else (units or "")
        out[name] = _finish(kind, data_type, rate_hz, spec, m, dev_units, n_terms, alpha, dec, ci_level, name, unit,
                            kern.name)
        xs[c] = None  # release this channel's phase
        del x
    return out


def allan_table(data, rate_hz: float, channels: Sequence[str] | None = None, taus="octave", **kw) -> pd.DataFrame:
    """Seed 002 eq. 4: tidy table (channel, tau_s, adev, ci_lo, ci_hi, edf, n_terms, m, alpha) of several channels."""
    if isinstance(data, Mapping) and data and isinstance(next(iter(data.values())), AllanResult):
        res = data
    else:
        res = allan_deviations(data, rate_hz, taus, channels=channels, **kw)
    frames = [r.to_frame() for r in res.values()]
    cols = ["channel", "tau_s", "adev", "ci_lo", "ci_hi", "edf", "n_terms", "m", "alpha", "kind"]
    if not frames:
        return pd.DataFrame(columns=cols)
    return pd.concat(frames, ignore_index=True)[cols]


# --------------------------------------------------------------------------------------------------------------
# streaming (parquet) OADEV: memory independent of N, bit-identical to the in-memory result
# --------------------------------------------------------------------------------------------------------------
class _BlockSource:
    """Raw samples of one channel delivered as consecutive blocks of PHASE_BLOCK starting at any block index."""

    def __init__(self, n_samples: int):
        self.n_samples = n_samples

    def blocks(self, start_block: int = 0) -> Iterator[np.ndarray]:  # pragma: no cover - interface
        raise NotImplementedError


class _ArraySource(_BlockSource):
    def __init__(self, y: np.ndarray):
        super().__init__(len(y))
        self.y = y

    def blocks(self, start_block: int = 0):
        return _array_blocks(self.y, start_block * PHASE_BLOCK)


class _ParquetSource(_BlockSource):
    """One column of a parquet file read row group by row group (pyarrow), re-cut into fixed blocks.

    Memory is bounded by one row group of the column (pyarrow's iter_batches buffers whole files here).
    """

    def __init__(self, path, column: str):
        import pyarrow.parquet as pq

        self.pf = pq.ParquetFile(path)
        self.column = column
        md = self.pf.metadata
        self.rg_rows = [md.row_group(i).num_rows for i in range(md.num_row_groups)]
        self.rg_start = np.concatenate([[0], np.cumsum(self.rg_rows)]).astype(np.int64)
        super().__init__(int(md.num_rows))

    def blocks(self, start_block: int = 0):
        start = start_block * PHASE_BLOCK
        if start >= self.n_samples:
            return
        rg = int(np.searchsorted(self.rg_start, start, side="right") - 1)
        skip = start - int(self.rg_start[rg])
        buf = np.empty(PHASE_BLOCK)
        fill = 0
        for i in range(rg, len(self.rg_rows)):
            col = self.pf.read_row_group(i, columns=[self.column], use_threads=False).column(0)
            if col.null_count:
                raise ValueError(f"column {self.column!r} has nulls: Allan deviations need a gap-free record")
            for chunk in col.chunks:
                arr = chunk.to_numpy(zero_copy_only=False)
                if skip:
                    if skip >= len(arr):
                        skip -= len(arr)
                        continue
                    arr = arr[skip:]
                    skip = 0
                while len(arr):
                    take = min(PHASE_BLOCK - fill, len(arr))
                    buf[fill : fill + take] = arr[:take]
                    fill += take
                    arr = arr[take:]
                    if fill == PHASE_BLOCK:
                        yield buf.copy()
                        fill = 0
            del col
        if fill:
            yield buf[:fill].copy()


class _FileSource(_BlockSource):
    """float64 samples from a binary file (the raw spill), in blocks of PHASE_BLOCK."""

    def __init__(self, fh, n_samples: int):
        super().__init__(n_samples)
        self.fh = fh

    def blocks(self, start_block: int = 0):
        self.fh.seek(8 * start_block * PHASE_BLOCK)
        left = self.n_samples - start_block * PHASE_BLOCK
        while left > 0:
            b = np.fromfile(self.fh, dtype=np.float64, count=min(PHASE_BLOCK, left))
            if len(b) == 0:
                raise IOError("spill file shorter than the record")
            left -= len(b)
            yield b


def _spill_chain_sum(fh, m: int, n: int, kernel, bufs) -> float:
    """Chain-ordered blocks of a large tau read from the phase spill file (page cache, not resident memory)."""
    B = KERNEL_BLOCK

    def read(i, L, out):
        fh.seek(8 * i)
        fh.readinto(memoryview(out[:L]).cast("B"))

    if m < M_CHAIN:  # the canonical partition [kB, (k+1)B), as in the in-memory window route
        s = 0.0
        for a in range(0, n, B):
            L = min(B, n - a)
            for k in range(3):
                read(a + k * m, L, bufs[k])
            s += kernel.block(bufs[0][:L], bufs[1][:L], bufs[2][:L])
        return s
    R = -(-m // B)
    J = -(-n // m)
    P = np.zeros((J, R))

    for rb in range(R):
        r = rb * B
        prev = None  # (i0, L, slot of x[i0+m], slot of x[i0+2m])
        for jj in range(J):
            i0 = jj * m + r
            if i0 >= n:
                break
            i1 = min(jj * m + min(r + B, m), n)
            L = i1 - i0
            if prev is not None and prev[1] == L:
                s0, s1 = prev[2], prev[3]
                s2 = 3 - s0 - s1
            else:
                s0, s1, s2 = 0, 1, 2
                read(i0, L, bufs[s0])
                read(i0 + m, L, bufs[s1])
            read(i0 + 2 * m, L, bufs[s2])
            P[jj, rb] = kernel.block(bufs[s0][:L], bufs[s1][:L], bufs[s2][:L])
            prev = (i0, L, s1, s2)
    return _ordered_sum(P, m, n)


def _streaming_oadev(source: _BlockSource, spec: _PhaseSpec, m: np.ndarray, kernel, need_id: bool,
                     spill_dir=None):
    """One pass over the record: sliding phase window for 2m <= SMALL_SPAN, phase spilled to a temporary file
    for the larger taus (read back in chain order). Same block partitions as the in-memory route."""
    import tempfile

    n_phase = spec.n_phase
    m = np.asarray(m, dtype=np.int64)
    n_terms = (n_phase - 2 * m).astype(np.int64)
    acc = np.zeros(len(m))
    small = 2 * m <= SMALL_SPAN
    ms, nt = m[small].copy(), n_terms[small].copy()
    flags = ms >= M_CHAIN
    next_a = np.zeros(len(ms), dtype=np.int64)
    a_small = np.zeros(len(ms))
    span = int(2 * ms.max()) if len(ms) else 0
    cap = span + KERNEL_BLOCK + PHASE_BLOCK + 8
    win = np.empty(cap)
    base = 0  # phase index of win[0]
    dec = {int(mj): [] for mj in m} if need_id else {}
    dec_next = {int(mj): 0 for mj in m}
    spill = tempfile.TemporaryFile(dir=spill_dir) if (~small).any() else None

    def collect(lo, hi):
        for mj in dec:
            k = dec_next[mj]
            while k <= ID_POINTS and k * mj < hi:
                if k * mj >= lo:
                    dec[mj].append(float(win[k * mj - base]))
                k += 1
            dec_next[mj] = k

    try:
        writer = _PhaseWriter(spec)
        head = writer.first_values()
        win[: len(head)] = head
        filled = len(head)
        if spill is not None and filled:
            spill.write(win[:filled].tobytes())
        if need_id:
            collect(0, filled)
        with _single_thread_blas():
            for raw in source.blocks(0):
                if filled + len(raw) > cap:
                    keep_from = int(next_a.min()) if len(ms) else base + filled
                    for mj in dec:
                        if dec_next[mj] <= ID_POINTS:
                            keep_from = min(keep_from, dec_next[mj] * mj)
                    keep_from = max(base, min(keep_from, base + filled))
                    shift = keep_from - base
                    if filled - shift + len(raw) > cap:
                        raise RuntimeError("streaming window too small")  # pragma: no cover - by construction
                    win[: filled - shift] = win[shift:filled]
                    base, filled = keep_from, filled - shift
                lo = base + filled
                seg = win[filled : filled + len(raw)]
                writer.write(raw, seg)
                if spill is not None:
                    spill.write(seg.tobytes())
                filled += len(raw)
                if need_id:
                    collect(lo, base + filled)
                if len(ms):
                    kernel.window(win, base, ms, nt, flags, next_a, a_small, base + filled)
            acc[small] = a_small
            if spill is not None:
                spill.flush()
                bufs = [_aligned_empty(KERNEL_BLOCK) for _ in range(3)]
                for j in np.flatnonzero(~small):
                    acc[j] = _spill_chain_sum(spill, int(m[j]), int(n_terms[j]), kernel, bufs)
    finally:
        if spill is not None:
            spill.close()
    dec_arr = {mj: np.array(v) for mj, v in dec.items()} if need_id else None
    return acc, n_terms, dec_arr


def allan_parquet(
    path,
    rate_hz: float,
    columns: Sequence[str] | None = None,
    taus="octave",
    *,
    data_type: str = "rate",
    scale: float | Mapping[str, float] = 1.0,
    ci_level: float = ONE_SIGMA_CI,
    alpha=None,
    backend: str = "auto",
    units=None,
    spill_dir=None,
) -> dict[str, AllanResult]:
    """Seed 002 eq. 4 streamed: OADEV of parquet columns read in batches, memory independent of N.

    Reads each column twice (mean, then phase with a sliding window for 2m <= SMALL_SPAN); the phase of taus
    beyond the window is spilled to a temporary file in ``spill_dir`` (8 bytes per sample on disk, read back
    through the page cache, not resident memory). Bit-identical to :func:`allan_deviation` on the same values.
    ``scale``: factor(s) to SI applied after the deviation (the estimator is linear in the data).
    """
    import pyarrow.parquet as pq

    pf = pq.ParquetFile(path)
    names = [f.name for f in pf.schema_arrow]
    cols = list(columns) if columns is not None else [c for c in names if c != "time_s"]
    out = {}
    kern = _kernel(backend)
    import tempfile

    for col in cols:
        with tempfile.TemporaryFile(dir=spill_dir) as raw_spill:
            # pass 0 decodes the column once: sums for the mean, float64 samples to a spill file (page cache)
            spec = _phase_spec_from_blocks(_ParquetSource(path, col).blocks(0), data_type, sink=raw_spill)
            raw_spill.flush()
            m = _resolve_m(taus, spec.n_samples, rate_hz, "oadev", data_type)
            acc, n_terms, dec = _streaming_oadev(_FileSource(raw_spill, spec.n_samples), spec, m, kern,
                                                 alpha is None, spill_dir)
        dev_units = np.sqrt(acc / (2.0 * n_terms)) / m if len(m) else np.zeros(0)
        unit = units.get(col, "") if isinstance(units, Mapping) else (units or "")
        res = _finish("oadev", data_type, rate_hz, spec, m, dev_units, n_terms, alpha, dec, ci_level, col, unit, kern.name)
        f = scale.get(col, 1.0) if isinstance(scale, Mapping) else float(scale)
        if f != 1.0:
            res = _scaled(res, f)
        out[col] = res
    return out


def _scaled(res: AllanResult, f: float) -> AllanResult:
    from dataclasses import replace

    return replace(res, adev=res.adev * abs(f), ci_lo=res.ci_lo * abs(f), ci_hi=res.ci_hi * abs(f))


def allan_stream_array(y: np.ndarray, rate_hz: float, taus="octave", **kw) -> AllanResult:
    """The streaming route applied to an in-memory array (for tests and benchmarks of the streaming engine)."""
    data_type = kw.pop("data_type", "rate")
    alpha = kw.pop("alpha", None)
    ci_level = kw.pop("ci_level", ONE_SIGMA_CI)
    kern = _kernel(kw.pop("backend", "auto"))
    src = _ArraySource(np.asarray(y))
    spec = _phase_spec_from_blocks(src.blocks(0), data_type)
    m = _resolve_m(taus, spec.n_samples, rate_hz, "oadev", data_type)
    acc, n_terms, dec = _streaming_oadev(src, spec, m, kern, alpha is None)
    dev_units = np.sqrt(acc / (2.0 * n_terms)) / m
    return _finish("oadev", data_type, rate_hz, spec, m, dev_units, n_terms, alpha, dec, ci_level, "", "", kern.name)
