"""Overlapping-Allan kernels: sums of squared second differences over fixed blocks, numpy or numba.

Layer 2 of :mod:`assets_lib.noise.allan`. The overlapping estimator ([NIST1065] eq. 11) is computed exactly
(every offset i) with blockwise second differences: no N-sized temporary per tau. Both kernels visit one fixed
block partition, a function of (m, n) only, so the in-memory and streaming routes give the same bits.
``KERNEL_BLOCK``, ``SUM_BLOCK`` and ``M_CHAIN`` define that partition.
"""

from __future__ import annotations

import contextlib
import ctypes
import glob
import os

import numpy as np

try:  # optional accelerator: the same estimator (see the kernel classes)
    import numba as _numba

    HAVE_NUMBA = True
except Exception:  # pragma: no cover - exercised when numba is absent
    _numba = None
    HAVE_NUMBA = False

#: i-block of the second-difference kernel (the fixed partition shared by every route)
KERNEL_BLOCK = 1 << 14
#: the mean is the sequential sum of pairwise sums over contiguous float64 blocks of SUM_BLOCK samples
SUM_BLOCK = 1 << 15
#: taus with m >= M_CHAIN use the chain-ordered block partition (one memory stream per tau)
M_CHAIN = 1 << 16


def block_sum(b: np.ndarray) -> float:
    """Sequential sum of the sums of SUM_BLOCK pieces of a contiguous float64 block (the canonical order).

    Each piece is summed in numpy's pairwise order (``np.add.reduce`` of a contiguous float64 array); the numba
    loop reproduces that order operation for operation, so the mean has the same bits with either kernel.
    """
    if HAVE_NUMBA:
        return float(_nb_block_sum(b, SUM_BLOCK))
    t = 0.0
    for a in range(0, len(b), SUM_BLOCK):
        t += float(np.add.reduce(b[a : a + SUM_BLOCK]))
    return t




def cumsum_rate(b: np.ndarray, mean: float, x_last: float, out: np.ndarray) -> float:
    """``out = x_last + cumsum(b - mean)`` (one block of the rate phase); returns the last value.

    The numba loop performs the same IEEE operations in the same order as the numpy branch: identical bits.
    """
    if HAVE_NUMBA:
        return float(_nb_phase_rate(b, mean, x_last, out))
    np.subtract(b, mean, out=out, dtype=np.float64)
    out[0] += x_last
    np.cumsum(out, out=out)
    return float(out[-1])


def aligned_empty(n: int) -> np.ndarray:
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
def single_thread_blas():
    """Pin OpenBLAS to one thread while thousands of small dot products run (a multithreaded BLAS only adds overhead to dot products of this size)."""
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
    """numpy blockwise kernel: second differences into a preallocated, 64-byte aligned buffer, squared in place,
    then summed by ``np.add.reduce`` (numpy's pairwise order; not a BLAS dot, whose order depends on the CPU)."""

    name = "numpy"

    def __init__(self):
        self.S = aligned_empty(2 * KERNEL_BLOCK)
        self.D = aligned_empty(KERNEL_BLOCK)
        self.T = aligned_empty(KERNEL_BLOCK)

    def _block(self, x0, x1, x2) -> float:
        L = len(x0)
        D, T = self.D[:L], self.T[:L]
        np.subtract(x2, x1, out=D)
        np.subtract(x1, x0, out=T)
        np.subtract(D, T, out=D)
        np.multiply(D, D, out=D)
        return float(np.add.reduce(D))

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
                    np.multiply(D[:L], D[:L], out=D[:L])
                    s += float(np.add.reduce(D[:L]))
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
        return ordered_sum(P, m, n)

    def block(self, x0, x1, x2) -> float:
        return self._block(x0, x1, x2)


def ordered_sum(P: np.ndarray, m: int, n: int) -> float:
    """Sum of chain-block partials in increasing-i order (the order the streaming route accumulates)."""
    B = KERNEL_BLOCK
    s = 0.0
    for jj in range(P.shape[0]):
        for rb in range(P.shape[1]):
            if jj * m + rb * B < n:
                s += float(P[jj, rb])
    return s


if HAVE_NUMBA:
    # No fastmath anywhere: every sum below is numpy's pairwise summation (numpy/_core/src/umath/loops_utils.h.src,
    # pairwise_sum: < 8 terms sequentially; <= 128 terms in eight interleaved accumulators combined as
    # ((r0 + r1) + (r2 + r3)) + ((r4 + r5) + (r6 + r7)) plus the remainder; else split at n/2 rounded down to a
    # multiple of 8), term by term, so numba and numpy return identical bits (tests/test_allan.py checks it).
    # Squares are written to a block buffer first (a vectorised loop), as the numpy kernel does.

    @_numba.njit(boundscheck=False, cache=True)
    def _nb_leaf_sum(b, lo, n):  # pragma: no cover - compiled
        """One leaf of numpy's pairwise sum (n <= 128 terms)."""
        if n < 8:
            res = 0.0
            for i in range(lo, lo + n):
                res += b[i]
            return res
        r0, r1, r2, r3 = b[lo], b[lo + 1], b[lo + 2], b[lo + 3]
        r4, r5, r6, r7 = b[lo + 4], b[lo + 5], b[lo + 6], b[lo + 7]
        i = lo + 8
        top = lo + n - (n % 8)
        while i < top:
            r0 += b[i]
            r1 += b[i + 1]
            r2 += b[i + 2]
            r3 += b[i + 3]
            r4 += b[i + 4]
            r5 += b[i + 5]
            r6 += b[i + 6]
            r7 += b[i + 7]
            i += 8
        res = ((r0 + r1) + (r2 + r3)) + ((r4 + r5) + (r6 + r7))
        while i < lo + n:
            res += b[i]
            i += 1
        return res

    @_numba.njit(boundscheck=False, cache=True)
    def _nb_pairwise_sum(b, lo, n):  # pragma: no cover - compiled
        """``np.add.reduce(b[lo:lo + n])``: numpy's pairwise tree without recursion (post-order, explicit stack;
        leaves of <= 128 terms, each node split at n/2 rounded down to a multiple of 8, combined left + right)."""
        s_lo = np.empty(64, np.int64)
        s_n = np.empty(64, np.int64)
        s_join = np.empty(64, np.bool_)
        vals = np.empty(64)
        s_lo[0], s_n[0], s_join[0] = lo, n, False
        top = 1
        vtop = 0
        while top > 0:
            top -= 1
            a, m, join = s_lo[top], s_n[top], s_join[top]
            if join:
                vals[vtop - 2] = vals[vtop - 2] + vals[vtop - 1]
                vtop -= 1
            elif m <= 128:
                vals[vtop] = _nb_leaf_sum(b, a, m)
                vtop += 1
            else:
                m2 = m // 2
                m2 -= m2 % 8
                s_lo[top], s_n[top], s_join[top] = a, m, True
                s_lo[top + 1], s_n[top + 1], s_join[top + 1] = a + m2, m - m2, False
                s_lo[top + 2], s_n[top + 2], s_join[top + 2] = a, m2, False
                top += 3
        return 0.0 + vals[0]  # np.add.reduce starts from the identity 0.0

    @_numba.njit(boundscheck=False, cache=True)
    def _nb_ssq(x0, x1, x2, buf):  # pragma: no cover - compiled
        """sum of ((x2 - x1) - (x1 - x0))^2 in numpy's order: squares into ``buf``, then the pairwise sum."""
        n = x0.shape[0]
        for i in range(n):
            d = (x2[i] - x1[i]) - (x1[i] - x0[i])
            buf[i] = d * d
        return _nb_pairwise_sum(buf, 0, n)

    @_numba.njit(boundscheck=False, cache=True)
    def _nb_window(x, base, ms, n_terms, chain, next_a, acc, avail_end, B, buf):  # pragma: no cover - compiled
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
                s += _nb_ssq(x[lo:hi], x[lo + m : hi + m], x[lo + 2 * m : hi + 2 * m], buf)
                a = b
            acc[j] = s
            next_a[j] = a

    @_numba.njit(boundscheck=False, cache=True)
    def _nb_chain(x, m, n, B, buf):  # pragma: no cover - compiled
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
                P[jj, rb] = _nb_ssq(x[i0:i1], x[i0 + m : i1 + m], x[i0 + 2 * m : i1 + 2 * m], buf)
        s = 0.0
        for jj in range(J):
            for rb in range(R):
                if jj * m + rb * B < n:
                    s += P[jj, rb]
        return s

    @_numba.njit(boundscheck=False, cache=True)
    def _nb_block_sum(b, piece):  # pragma: no cover - compiled
        t = 0.0
        for a in range(0, b.shape[0], piece):
            t += _nb_pairwise_sum(b, a, min(piece, b.shape[0] - a))
        return t

    @_numba.njit(boundscheck=False, cache=True)
    def _nb_phase_rate(b, mean, x_last, out):  # pragma: no cover - compiled
        acc = x_last
        for k in range(b.shape[0]):
            acc = acc + (b[k] - mean)
            out[k] = acc
        return acc


class _NumbaKernel:
    """Compiled kernel (numba): the same block partition and the same summation order as the numpy kernel,
    term by term, hence the same bits; faster (no Python loop per block, no temporaries but one buffer)."""

    name = "numba"

    def __init__(self):
        self.buf = aligned_empty(KERNEL_BLOCK)

    def window(self, x, base, ms, n_terms, chain, next_a, acc, avail_end):
        _nb_window(x, np.int64(base), ms, n_terms, chain, next_a, acc, np.int64(avail_end), np.int64(KERNEL_BLOCK),
                   self.buf)

    def chain(self, x, m, n):
        return float(_nb_chain(x, np.int64(m), np.int64(n), np.int64(KERNEL_BLOCK), self.buf))

    def block(self, x0, x1, x2) -> float:
        return float(_nb_ssq(x0, x1, x2, self.buf))


def get_kernel(backend: str):
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
# overlapping Allan sums of a phase array in memory
# --------------------------------------------------------------------------------------------------------------
def oadev_sums_inmemory(x: np.ndarray, m: np.ndarray, kernel) -> np.ndarray:
    """[NIST1065] eq. 11 ([SEED002] eq. 4): sum_i (x[i+2m] - 2x[i+m] + x[i])^2 for each m, exactly.

    Small m: block-outer, tau-inner over cache-sized windows. m >= M_CHAIN: blocks visited in chains
    i, i+m, i+2m, ... so that two of the three phase windows are still in cache (one memory stream per tau).
    Both partitions are fixed functions of (m, n): the streaming route reproduces them bit for bit.
    """
    n_phase = len(x)
    m = np.asarray(m, dtype=np.int64)
    n_terms = (n_phase - 2 * m).astype(np.int64)
    acc = np.zeros(len(m))
    chain = m >= M_CHAIN
    with single_thread_blas():
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
