"""Streaming OADEV from parquet: memory independent of N, bit-identical to the in-memory result.

Layer 3b of :mod:`assets_lib.noise.allan`: the record is read in blocks, the phase kept in a sliding window
for 2m <= ``SMALL_SPAN`` and spilled to a temporary file for larger taus (read back in the chain order of
:mod:`.kernels`). Same block partitions as the in-memory route, hence the same bits.
"""

from __future__ import annotations

import tempfile
from collections.abc import Iterator, Mapping, Sequence

import numpy as np

from assets_lib.noise.allan import kernels as _k
from assets_lib.noise.allan.estimators import ID_POINTS, AllanResult, finish_result, resolve_m
from assets_lib.noise.allan.phase import PHASE_BLOCK, PhaseSpec, PhaseWriter, array_blocks, phase_spec_from_blocks
from assets_lib.noise.intervals import ONE_SIGMA_CI

#: streaming: taus with 2m <= SMALL_SPAN are served by the sliding window, larger ones from the phase spill file
SMALL_SPAN = 1 << 23


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
        return array_blocks(self.y, start_block * PHASE_BLOCK)


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
    B = _k.KERNEL_BLOCK

    def read(i, L, out):
        fh.seek(8 * i)
        fh.readinto(memoryview(out[:L]).cast("B"))

    if m < _k.M_CHAIN:  # the canonical partition [kB, (k+1)B), as in the in-memory window route
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
    return _k.ordered_sum(P, m, n)


def _streaming_oadev(source: _BlockSource, spec: PhaseSpec, m: np.ndarray, kernel, need_id: bool,
                     spill_dir=None):
    """One pass over the record: sliding phase window for 2m <= SMALL_SPAN, phase spilled to a temporary file
    for the larger taus (read back in chain order). Same block partitions as the in-memory route."""
    n_phase = spec.n_phase
    m = np.asarray(m, dtype=np.int64)
    n_terms = (n_phase - 2 * m).astype(np.int64)
    acc = np.zeros(len(m))
    small = 2 * m <= SMALL_SPAN
    ms, nt = m[small].copy(), n_terms[small].copy()
    flags = ms >= _k.M_CHAIN
    next_a = np.zeros(len(ms), dtype=np.int64)
    a_small = np.zeros(len(ms))
    span = int(2 * ms.max()) if len(ms) else 0
    cap = span + _k.KERNEL_BLOCK + PHASE_BLOCK + 8
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
        writer = PhaseWriter(spec)
        head = writer.first_values()
        win[: len(head)] = head
        filled = len(head)
        if spill is not None and filled:
            spill.write(win[:filled].tobytes())
        if need_id:
            collect(0, filled)
        with _k.single_thread_blas():
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
                bufs = [_k.aligned_empty(_k.KERNEL_BLOCK) for _ in range(3)]
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
    """[SEED002] eq. 4 streamed: OADEV of parquet columns read in batches, memory independent of N.

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
    kern = _k.get_kernel(backend)
    for col in cols:
        with tempfile.TemporaryFile(dir=spill_dir) as raw_spill:
            # pass 0 decodes the column once: sums for the mean, float64 samples to a spill file (page cache)
            spec = phase_spec_from_blocks(_ParquetSource(path, col).blocks(0), data_type, sink=raw_spill)
            raw_spill.flush()
            m = resolve_m(taus, spec.n_samples, rate_hz, "oadev", data_type)
            acc, n_terms, dec = _streaming_oadev(_FileSource(raw_spill, spec.n_samples), spec, m, kern,
                                                 alpha is None, spill_dir)
        dev_units = np.sqrt(acc / (2.0 * n_terms)) / m if len(m) else np.zeros(0)
        unit = units.get(col, "") if isinstance(units, Mapping) else (units or "")
        res = finish_result("oadev", data_type, rate_hz, spec, m, dev_units, n_terms, alpha, dec, ci_level, col, unit, kern.name)
        f = scale.get(col, 1.0) if isinstance(scale, Mapping) else float(scale)
        if f != 1.0:
            res = scaled_result(res, f)
        out[col] = res
    return out


def scaled_result(res: AllanResult, f: float) -> AllanResult:
    from dataclasses import replace

    return replace(res, adev=res.adev * abs(f), ci_lo=res.ci_lo * abs(f), ci_hi=res.ci_hi * abs(f))


def allan_stream_array(y: np.ndarray, rate_hz: float, taus="octave", **kw) -> AllanResult:
    """The streaming route applied to an in-memory array (for tests and benchmarks of the streaming engine)."""
    data_type = kw.pop("data_type", "rate")
    alpha = kw.pop("alpha", None)
    ci_level = kw.pop("ci_level", ONE_SIGMA_CI)
    kern = _k.get_kernel(kw.pop("backend", "auto"))
    src = _ArraySource(np.asarray(y))
    spec = phase_spec_from_blocks(src.blocks(0), data_type)
    m = resolve_m(taus, spec.n_samples, rate_hz, "oadev", data_type)
    acc, n_terms, dec = _streaming_oadev(src, spec, m, kern, alpha is None)
    dev_units = np.sqrt(acc / (2.0 * n_terms)) / m
    return finish_result("oadev", data_type, rate_hz, spec, m, dev_units, n_terms, alpha, dec, ci_level, "", "", kern.name)
