"""Named differences between a recorded content and a recomputed one, each number compared at its own precision.

A recomputed estimate agrees with the recorded one when they differ by at most ``PRECISION_FRACTION`` of the
quantity's precision: its standard error for a coefficient, the half-width of its confidence interval for a
noise term (the whole width for an upper bound). That is ten times finer than the last digit a certificate
prints (two significant digits of the uncertainty) and orders of magnitude above what a different BLAS, summation
order or optional kernel (numba vs numpy Allan kernels: up to 2.5e-8 relative) changes, so a genuine record
verifies in any supported environment while any change a reader could see is reported. Quantities without a
precision (conditions, counts) are compared to ``FLOAT_RTOL`` relative.
"""

from __future__ import annotations

import math

#: relative tolerance of numbers that carry no precision of their own (test conditions, durations)
FLOAT_RTOL = 1e-9
#: a recomputed estimate may differ from the recorded one by this fraction of its standard error / half-interval
PRECISION_FRACTION = 1e-3

COEFFICIENT_NUMBERS = (("value", "stderr"), ("stderr", "stderr"), ("value_lab", "stderr_lab"),
                       ("stderr_lab", "stderr_lab"))
NOISE_NUMBERS = ("value", "ci_lo", "ci_hi")
#: content fields a record schema version added: a record of an earlier version is compared without them
ADDED_IN = {"1.1": ("status", "status_reasons")}


def _num(x) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool)


def _close(a, b, precision: float | None = None, rtol: float = FLOAT_RTOL,
           fraction: float = PRECISION_FRACTION) -> bool:
    """Equal non-numbers; numbers within ``fraction`` x ``precision`` (when given and > 0) or ``rtol`` relative."""
    if a is None or b is None:
        return a is None and b is None
    if not _num(a) or not _num(b):
        return a == b
    tol = rtol * max(abs(a), abs(b))
    if precision is not None and _num(precision) and math.isfinite(precision) and precision > 0:
        tol = max(tol, fraction * precision)
    return abs(a - b) <= tol


def _diff(path: str, a, b, out: list[str], rtol: float = FLOAT_RTOL) -> None:
    if isinstance(a, dict) and isinstance(b, dict):
        for k in sorted(set(a) | set(b)):
            if k not in a:
                out.append(f"{path}.{k}: not in the record, recomputed {b[k]!r}")
            elif k not in b:
                out.append(f"{path}.{k}: recorded {a[k]!r}, absent from the recomputation")
            else:
                _diff(f"{path}.{k}", a[k], b[k], out, rtol)
    elif isinstance(a, list) and isinstance(b, list):
        if len(a) != len(b):
            out.append(f"{path}: {len(a)} entries recorded, {len(b)} recomputed")
        for i, (x, y) in enumerate(zip(a, b)):
            _diff(f"{path}[{i}]", x, y, out, rtol)
    elif not _close(a, b, rtol=rtol):
        out.append(f"{path}: recorded {a!r}, recomputed {b!r}")


def coefficient_id(c: dict) -> str:
    return f"{c['source']}/{c['sensor']}_{c['axis']}/{c['coefficient']}"


def noise_id(r: dict) -> str:
    return f"{r.get('source', '')}/{r.get('channel')}/{r.get('parameter')}/{r.get('method')}"


def noise_half_width(r: dict, lab: bool) -> float | None:
    """Precision of a noise term: half its interval (the bound itself for an upper bound)."""
    sfx = "_lab" if lab else ""
    lo, hi = r.get(f"ci_lo{sfx}"), r.get(f"ci_hi{sfx}")
    if not _num(hi):
        return None
    if r.get("is_upper_bound") or not _num(lo):
        return abs(hi)
    return (hi - lo) / 2.0


def _coefficient_differences(ca: dict, cb: dict, rtol: float, fraction: float) -> list[str]:
    out = []
    for cid in sorted(set(ca) | set(cb)):
        if cid not in cb:
            out.append(f"coefficient {cid}: in the record, not recomputed")
            continue
        if cid not in ca:
            out.append(f"coefficient {cid}: recomputed but not in the record")
            continue
        a, b = ca[cid], cb[cid]
        bad = [f for f, p in COEFFICIENT_NUMBERS if not _close(a.get(f), b.get(f), a.get(p), rtol, fraction)]
        if {"value", "stderr"} & set(bad):  # the lab values follow from the SI ones: name the SI difference only
            bad = [f for f in bad if not f.endswith("_lab")]
        if bad:
            out.append(f"coefficient {cid}: " + "; ".join(
                f"{f} recorded {a.get(f)!r}, recomputed {b.get(f)!r} {a.get('unit_lab' if f.endswith('_lab') else 'unit')}"
                for f in bad))
        for f in ("unit", "unit_lab", "observable", "n_plateaus", "n_samples", "method"):
            if a.get(f) != b.get(f):
                out.append(f"coefficient {cid} {f}: recorded {a.get(f)!r}, recomputed {b.get(f)!r}")
    return out


def _noise_differences(na: dict, nb: dict, rtol: float, fraction: float) -> list[str]:
    out = []
    for nid in sorted(set(na) | set(nb)):
        if nid not in nb or nid not in na:
            out.append(f"noise term {nid}: " + ("in the record, not recomputed" if nid not in nb
                                                 else "recomputed but not in the record"))
            continue
        a, b = na[nid], nb[nid]
        bad = []
        for lab in (False, True):
            prec = noise_half_width(a, lab)
            sfx = "_lab" if lab else ""
            bad += [f + sfx for f in NOISE_NUMBERS if not _close(a.get(f + sfx), b.get(f + sfx), prec, rtol, fraction)]
        if any(not f.endswith("_lab") for f in bad):
            bad = [f for f in bad if not f.endswith("_lab")]
        if bad:
            out.append(f"noise term {nid}: " + "; ".join(
                f"{f} recorded {a.get(f)!r}, recomputed {b.get(f)!r} {a.get('unit_lab' if f.endswith('_lab') else 'unit')}"
                for f in bad))
        rest = sorted(k for k in set(a) | set(b) if k not in {f + s for f in NOISE_NUMBERS for s in ("", "_lab")})
        for k in rest:
            if not _close(a.get(k), b.get(k), rtol=rtol):
                out.append(f"noise term {nid} {k}: recorded {a.get(k)!r}, recomputed {b.get(k)!r}")
    return out


def content_differences(recorded: dict, recomputed: dict, rtol: float = FLOAT_RTOL,
                        fraction: float = PRECISION_FRACTION) -> list[str]:
    """Named differences: raw files, coefficients (value / stderr / lab values within ``fraction`` of the standard
    error), noise terms (within ``fraction`` of the interval half-width), units, and every other field (``rtol``).
    ``software`` and ``prev_record_sha256`` are not compared here (the chain check covers the latter)."""
    out = []
    ra, rb = recorded.get("raw_files", {}), recomputed.get("raw_files", {})
    for name in sorted(set(ra) | set(rb)):
        if ra.get(name) != rb.get(name):
            out.append(f"raw file {name}: recorded sha256 {ra.get(name) or 'none'}, archive has {rb.get(name) or 'none'}")
    out += _coefficient_differences({coefficient_id(c): c for c in recorded.get("coefficients", [])},
                                    {coefficient_id(c): c for c in recomputed.get("coefficients", [])}, rtol, fraction)
    out += _noise_differences({noise_id(r): r for r in recorded.get("noise") or []},
                              {noise_id(r): r for r in recomputed.get("noise") or []}, rtol, fraction)
    skip = ["raw_files", "coefficients", "noise", "software", "prev_record_sha256"]
    version = recorded.get("record_schema_version")
    if version != recomputed.get("record_schema_version"):  # an older record: compare what it certifies
        skip.append("record_schema_version")
        skip += [f for v, fields in ADDED_IN.items() if str(version) < v for f in fields]
    _diff("content", {k: v for k, v in recorded.items() if k not in skip},
          {k: v for k, v in recomputed.items() if k not in skip}, out, rtol)
    return out
