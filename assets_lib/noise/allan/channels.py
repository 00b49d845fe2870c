"""Several channels in one call: (N, C) arrays, mappings or DataFrames, one float64 phase buffer reused.

Layer 4 of :mod:`assets_lib.noise.allan`; every channel is computed exactly as
:func:`assets_lib.noise.allan.estimators.allan_deviation` would (bit-identical).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence

import numpy as np
import pandas as pd

from assets_lib.noise.allan import kernels as _k
from assets_lib.noise.allan.estimators import (
    ID_POINTS,
    AllanResult,
    allan_deviation,
    deviation_from_phase,
    finish_result,
    resolve_m,
)
from assets_lib.noise.allan.phase import PHASE_BLOCK, PhaseSpec, PhaseWriter, check_finite
from assets_lib.noise.intervals import ONE_SIGMA_CI


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
    """[SEED002] eq. 4 per channel: several channels in one call, reusing one float64 phase buffer.

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
    step = _k.SUM_BLOCK  # one pass over the rows: transpose and the canonical block sums together
    for a in range(0, n, step):
        blk = arr[a : a + step]
        for c in range(C):
            seg = xs[c][lead + a : lead + a + len(blk)]
            np.copyto(seg, blk[:, c], casting="same_kind")
            bs = _k.block_sum(seg)
            if not math.isfinite(bs):
                check_finite(seg, a)
                raise ValueError(f"samples {a}..{a + len(seg)} overflow a float64 sum")
            totals[c] += bs
    kern = _k.get_kernel(backend)
    m = resolve_m(taus, n, rate_hz, kind, data_type)
    out = {}
    for c, name in enumerate(names):
        x = xs[c]
        if data_type == "rate":
            spec = PhaseSpec("rate", n, mean=totals[c] / n)
        else:
            spec = PhaseSpec("angle", n, theta0=float(x[0]), slope=(float(x[-1]) - float(x[0])) / (n - 1))
        w = PhaseWriter(spec)
        if lead:
            x[0] = 0.0
        for a in range(0, n, PHASE_BLOCK):
            seg = x[lead + a : lead + min(a + PHASE_BLOCK, n)]
            w.write(seg, seg)
        dev_units, n_terms = deviation_from_phase(x, m, kind, kern) if len(m) else (np.zeros(0), np.zeros(0))
        dec = {int(mj): np.array(x[:: int(mj)][: ID_POINTS + 1]) for mj in m} if alpha is None else None
        unit = units.get(name, "") if isinstance(units, Mapping) else (units or "")
        out[name] = finish_result(kind, data_type, rate_hz, spec, m, dev_units, n_terms, alpha, dec, ci_level, name, unit,
                            kern.name)
        xs[c] = None  # release this channel's phase
        del x
    return out


def allan_table(data, rate_hz: float, channels: Sequence[str] | None = None, taus="octave", **kw) -> pd.DataFrame:
    """[SEED002] eq. 4: tidy table (channel, tau_s, adev, ci_lo, ci_hi, edf, n_terms, m, alpha) of several channels."""
    if isinstance(data, Mapping) and data and isinstance(next(iter(data.values())), AllanResult):
        res = data
    else:
        res = allan_deviations(data, rate_hz, taus, channels=channels, **kw)
    frames = [r.to_frame() for r in res.values()]
    cols = ["channel", "tau_s", "adev", "ci_lo", "ci_hi", "edf", "n_terms", "m", "alpha", "kind"]
    if not frames:
        return pd.DataFrame(columns=cols)
    return pd.concat(frames, ignore_index=True)[cols]
