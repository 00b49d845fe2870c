"""Phase construction: float64 "phase" x of a rate or angle record, blockwise, the same bits from any source.

Layer 1 of :mod:`assets_lib.noise.allan` ([NIST1065] eq. 4; [SEED002] eq. 1): rate -> cumulative sum of the
mean-removed rate; angle -> the angle minus the line through its end points; accumulated in float64 whatever
the input dtype (a float32 running sum loses the small tau; [NIST1065] eq. 4).
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Iterator
from dataclasses import dataclass

import numpy as np

from assets_lib.noise.allan import kernels as _k

#: block of the cumulative-sum pass and of the streaming reader
PHASE_BLOCK = 1 << 20


@dataclass(frozen=True)
class PhaseSpec:
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


def check_finite(block: np.ndarray, where: int) -> None:
    if not np.isfinite(block).all():
        bad = where + int(np.flatnonzero(~np.isfinite(block))[0])
        raise ValueError(
            f"non-finite sample at index {bad}: Allan deviations need a gap-free record (split or fill the gap)"
        )


def phase_spec_from_blocks(blocks: Iterable[np.ndarray], data_type: str, sink=None) -> PhaseSpec:
    """Pass 0: the mean (rate) or the end points (angle), summed blockwise in float64 in a fixed block order.

    ``sink``: optional binary file receiving the float64 samples (the streaming route's raw spill).
    """
    total = 0.0
    n = 0
    first = last = None
    scratch = np.empty(PHASE_BLOCK)
    for raw in blocks:
        b = _as_f64_block(raw, scratch)
        bs = _k.block_sum(b)
        if not math.isfinite(bs):  # NaN / inf propagate into the sum: locate them only then
            check_finite(b, n)
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
        return PhaseSpec("rate", n, mean=total / n)
    if data_type == "angle":
        return PhaseSpec("angle", n, theta0=first, slope=(last - first) / (n - 1))
    raise ValueError(f"data_type must be 'rate' or 'angle', got {data_type!r}")


class PhaseWriter:
    """Turns consecutive raw blocks into consecutive phase values (bit-identical for any source)."""

    def __init__(self, spec: PhaseSpec):
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
            self.x_last = _k.cumsum_rate(b, s.mean, self.x_last, out)
        else:
            b = _as_f64_block(raw, self.scratch)
            np.subtract(b, s.theta0, out=out, dtype=np.float64)
            k = np.arange(self.next_index, self.next_index + L, dtype=np.float64)
            k *= s.slope
            np.subtract(out, k, out=out)
        self.next_index += L


def array_blocks(y: np.ndarray, start: int = 0, size: int = PHASE_BLOCK) -> Iterator[np.ndarray]:
    for a in range(start, len(y), size):
        yield y[a : a + size]


def build_phase(y: np.ndarray, data_type: str = "rate", out: np.ndarray | None = None) -> tuple[np.ndarray, PhaseSpec]:
    """[SEED002] eq. 1 / [NIST1065] eq. 4: float64 phase of a record (mean-removed cumulative sum for rate)."""
    y = np.asarray(y)
    if y.ndim != 1:
        raise ValueError("build_phase takes one channel (1-D)")
    spec = phase_spec_from_blocks(array_blocks(y), data_type)
    x = out[: spec.n_phase] if out is not None and len(out) >= spec.n_phase else np.empty(spec.n_phase)
    w = PhaseWriter(spec)
    head = w.first_values()
    x[: len(head)] = head
    pos = len(head)
    for raw in array_blocks(y):
        w.write(raw, x[pos : pos + len(raw)])
        pos += len(raw)
    return x, spec
