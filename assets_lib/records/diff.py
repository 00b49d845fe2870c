"""Named differences between a recorded content and a recomputed one."""

from __future__ import annotations

#: relative tolerance of a recomputed number (see ``imulab verify``): 1e-9 of max(|recorded|, |recomputed|, stderr)
FLOAT_RTOL = 1e-9


def _close(a, b, scale: float = 0.0, rtol: float = FLOAT_RTOL) -> bool:
    if a is None or b is None:
        return a is None and b is None
    if isinstance(a, bool) or isinstance(b, bool) or not isinstance(a, (int, float)) or not isinstance(b, (int, float)):
        return a == b
    return abs(a - b) <= rtol * max(abs(a), abs(b), abs(scale or 0.0))


def _diff(path: str, a, b, out: list[str]) -> None:
    if isinstance(a, dict) and isinstance(b, dict):
        for k in sorted(set(a) | set(b)):
            if k not in a:
                out.append(f"{path}.{k}: not in the record, recomputed {b[k]!r}")
            elif k not in b:
                out.append(f"{path}.{k}: recorded {a[k]!r}, absent from the recomputation")
            else:
                _diff(f"{path}.{k}", a[k], b[k], out)
    elif isinstance(a, list) and isinstance(b, list):
        if len(a) != len(b):
            out.append(f"{path}: {len(a)} entries recorded, {len(b)} recomputed")
        for i, (x, y) in enumerate(zip(a, b)):
            _diff(f"{path}[{i}]", x, y, out)
    elif not _close(a, b):
        out.append(f"{path}: recorded {a!r}, recomputed {b!r}")


def coefficient_id(c: dict) -> str:
    return f"{c['source']}/{c['sensor']}_{c['axis']}/{c['coefficient']}"


def content_differences(recorded: dict, recomputed: dict, rtol: float = FLOAT_RTOL) -> list[str]:
    """Named differences: raw files, coefficients (value / stderr / units, tolerance ``rtol`` of
    max(|value|, stderr)), noise terms and every other field. ``software`` and ``prev_record_sha256`` are not
    compared here (the chain check covers the latter)."""
    out = []
    ra, rb = recorded.get("raw_files", {}), recomputed.get("raw_files", {})
    for name in sorted(set(ra) | set(rb)):
        if ra.get(name) != rb.get(name):
            out.append(f"raw file {name}: recorded sha256 {ra.get(name) or 'none'}, archive has {rb.get(name) or 'none'}")
    ca = {coefficient_id(c): c for c in recorded.get("coefficients", [])}
    cb = {coefficient_id(c): c for c in recomputed.get("coefficients", [])}
    for cid in sorted(set(ca) | set(cb)):
        if cid not in cb:
            out.append(f"coefficient {cid}: in the record, not recomputed")
            continue
        if cid not in ca:
            out.append(f"coefficient {cid}: recomputed but not in the record")
            continue
        a, b = ca[cid], cb[cid]
        bad = [f for f in ("value", "stderr", "value_lab", "stderr_lab")
               if not _close(a.get(f), b.get(f), (a.get("stderr_lab") if f.endswith("_lab") else a.get("stderr")) or 0.0,
                             rtol)]
        if {"value", "stderr"} & set(bad):  # the lab values follow from the SI ones: name the SI difference only
            bad = [f for f in bad if not f.endswith("_lab")]
        if bad:
            out.append(f"coefficient {cid}: " + "; ".join(
                f"{f} recorded {a.get(f)!r}, recomputed {b.get(f)!r} {a.get('unit_lab' if f.endswith('_lab') else 'unit')}"
                for f in bad))
        for f in ("unit", "unit_lab", "observable", "n_plateaus", "n_samples", "method"):
            if a.get(f) != b.get(f):
                out.append(f"coefficient {cid} {f}: recorded {a.get(f)!r}, recomputed {b.get(f)!r}")
    rest_a = {k: v for k, v in recorded.items() if k not in ("raw_files", "coefficients", "software",
                                                             "prev_record_sha256")}
    rest_b = {k: v for k, v in recomputed.items() if k not in ("raw_files", "coefficients", "software",
                                                               "prev_record_sha256")}
    _diff("content", rest_a, rest_b, out)
    return out
