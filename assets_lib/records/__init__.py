"""Audited calibration records: one JSON record per device and run, hash-chained per device, with an HTML certificate.

Record (``record_schema_version`` 1.0, JSON Schema in ``raw_schemas/record.schema.json``)::

    {"record_schema_version": "1.0",
     "record_sha256": sha256(canonical_json(content)),
     "content":    {...everything certified: device, run, test conditions, raw file hashes, coefficients with
                    uncertainties and units, noise terms, stage versions, software, prev_record_sha256},
     "provenance": {"created_utc": ..., "dagster_run_id": ...}}

Canonical JSON: ``json.dumps(sort_keys=True, separators=(",", ":"), ensure_ascii=False, allow_nan=False)`` encoded
UTF-8; floats are written by ``float.__repr__`` (the shortest string that reads back to the same double, so
parse -> re-serialize is the identity), NaN/inf become ``null`` (an unobservable coefficient has value null and
``observable`` false), numpy scalars become Python scalars. The file on disk is the same object indented for
reading; the hash is always over the canonical form of ``content``, so whitespace never matters.

Hashing and idempotency (the design decision):
- The creation time and the Dagster run id differ between reruns, so they live in ``provenance``, outside the
  hash. Everything that is certified (numbers, units, conditions, raw hashes, code and software versions, the
  previous record's hash) is inside ``content``.
- When the device's records are rebuilt (a new run lands, or a rerun after a code change elsewhere), each run's
  record is compared with the record of the same run in the device's current stored version: when the content
  is equal apart from ``software`` (i.e. same numbers, conditions, raw hashes, stage versions and previous hash),
  the stored record is reused verbatim: same creation time, run id, software block, hash and bytes. Rebuilding
  an unchanged device therefore changes nothing, and a new run only appends a link to the chain.
- ``software`` (imulab version, git commit, dirty flag) is inside the hash, so nobody can re-label which build
  certified a record; a record is re-certified (new hash) only when its certified content changes. A store
  rebuilt from scratch by a different commit gives records whose ``software`` and hashes differ while every
  number is identical; ``imulab verify`` compares the numbers, not the hashes, against a recomputation.
- Chain: records of a device are ordered by the run's start time (ties by run id); the content of each holds
  ``prev_record_sha256`` = the previous record's ``record_sha256`` (null for the first). Editing a record breaks
  its own hash; re-hashing an edited record breaks the next link; deleting a record breaks the link after it and
  leaves its run listed in ``records.parquet`` and present in the archive.
- ``provenance`` is informational and not tamper-evident (Dagster's event log keeps the run ids independently).
"""

from __future__ import annotations

import base64
import hashlib
import html
import json
import math
import subprocess
from datetime import datetime, timezone
from pathlib import Path

import numpy as np
import pandas as pd

from assets_lib.store.view import StoreView  # noqa: F401 - the one read view (re-exported for readers of records)

RECORD_SCHEMA_VERSION = "1.0"
SCHEMA_PATH = Path(__file__).resolve().parents[2] / "raw_schemas" / "record.schema.json"
COEFFICIENT_SOURCES = ("gyro_rate_fit", "accel_multiposition_fit", "tablefree_fit")
NOISE_SOURCES = ("allan_deviation",)
PLOT_SOURCES = (*COEFFICIENT_SOURCES, *NOISE_SOURCES)
COEFFICIENT_FIELDS = ("sensor", "axis", "coefficient", "value", "stderr", "unit", "value_lab", "stderr_lab", "unit_lab",
                      "observable", "n_plateaus", "n_samples", "method")
#: relative tolerance of a recomputed number (see ``imulab verify``): 1e-9 of max(|recorded|, |recomputed|, stderr)
FLOAT_RTOL = 1e-9
RECORDS_TABLE_COLUMNS = ["run_id", "start_time_utc", "test_kind", "record_sha256", "prev_record_sha256",
                         "n_coefficients", "created_utc", "dagster_run_id"]


# ---------------------------------------------------------------------------------------------------------------
# Canonical JSON and hashes
# ---------------------------------------------------------------------------------------------------------------
def to_jsonable(v):
    """Plain JSON values: numpy scalars -> Python, NaN/inf -> None, tuples -> lists, timestamps -> ISO strings."""
    if isinstance(v, dict):
        return {str(k): to_jsonable(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [to_jsonable(x) for x in v]
    if isinstance(v, np.ndarray):
        return [to_jsonable(x) for x in v.tolist()]
    if isinstance(v, (bool, np.bool_)):
        return bool(v)
    if isinstance(v, (int, np.integer)):
        return int(v)
    if isinstance(v, (float, np.floating)):
        f = float(v)
        return f if math.isfinite(f) else None
    if isinstance(v, (pd.Timestamp, datetime)):
        return v.isoformat()
    if v is None or isinstance(v, str):
        return v
    if v is pd.NA or v is pd.NaT:
        return None
    return str(v)


def canonical_json(obj) -> bytes:
    """Sorted keys, no whitespace, floats by repr, UTF-8: equal objects give equal bytes."""
    return json.dumps(to_jsonable(obj), sort_keys=True, separators=(",", ":"), ensure_ascii=False,
                      allow_nan=False).encode("utf-8")


def sha256_hex(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def content_sha256(content: dict) -> str:
    return sha256_hex(canonical_json(content))


def record_file_bytes(record: dict) -> bytes:
    """The record as stored: indented, sorted, UTF-8 (the hash is over canonical ``content``, not these bytes)."""
    return (json.dumps(to_jsonable(record), sort_keys=True, indent=1, ensure_ascii=False, allow_nan=False)
            + "\n").encode("utf-8")


def load_record(path: str | Path) -> dict:
    return json.loads(Path(path).read_text(encoding="utf-8"))


# ---------------------------------------------------------------------------------------------------------------
# Software identity
# ---------------------------------------------------------------------------------------------------------------
def software_info(source_dir: str | None = None) -> dict:
    """imulab version, ``git rev-parse HEAD`` of the source tree ('unknown' without git) and whether it was dirty
    (tracked files modified; untracked files ignored). Not cached: a long-lived code server sees new commits."""
    from importlib.metadata import PackageNotFoundError, version

    try:
        __version__ = version("imulab")
    except PackageNotFoundError:  # pragma: no cover - running from a source tree that was never installed
        __version__ = "unknown"
    src = Path(source_dir) if source_dir else Path(__file__).resolve().parents[2]
    commit, dirty = "unknown", None
    try:
        out = subprocess.run(["git", "-C", str(src), "rev-parse", "HEAD"], capture_output=True, text=True, timeout=10)
        if out.returncode == 0:
            commit = out.stdout.strip()
            st = subprocess.run(["git", "-C", str(src), "status", "--porcelain", "--untracked-files=no"],
                                capture_output=True, text=True, timeout=30)
            dirty = bool(st.stdout.strip()) if st.returncode == 0 else None
    except (OSError, subprocess.SubprocessError):
        pass
    return {"imulab_version": __version__, "git_commit": commit, "git_dirty": dirty}


def utc_now_iso() -> str:
    return datetime.now(timezone.utc).replace(microsecond=0).isoformat().replace("+00:00", "Z")


# ---------------------------------------------------------------------------------------------------------------
# Building the content of one run's record from stored stage outputs
# ---------------------------------------------------------------------------------------------------------------
def _stage_chain(view: StoreView, key: str) -> dict:
    """asset -> {version, code_version} for every stage the run's outputs were computed from (walked via meta)."""
    out: dict[str, dict] = {}
    todo = [k.split("/", 1)[0] for k in view.versions if k.endswith(f"/{key}")]
    while todo:
        asset = todo.pop()
        if asset in out or not view.has(asset, key):
            continue
        m = view.meta(asset, key)
        out[asset] = {"version": view.versions[f"{asset}/{key}"], "code_version": str(m.get("code_version", ""))}
        for up, v in (m.get("inputs") or {}).items():
            a, _, part = up.partition("/")
            if a != "raw" and part == key:
                view.versions.setdefault(f"{a}/{key}", v)
                todo.append(a)
    return dict(sorted(out.items()))


def _coefficient_rows(view: StoreView, key: str) -> list[dict]:
    rows = []
    for asset in COEFFICIENT_SOURCES:
        if not view.has_table(asset, "coefficients", key):
            continue
        c = view.table(asset, "coefficients", key)
        for r in c.to_dict(orient="records"):
            row = {f: r.get(f) for f in COEFFICIENT_FIELDS}
            row["source"] = asset
            rows.append(to_jsonable(row))
    return sorted(rows, key=lambda r: (r["source"], r["sensor"], r["axis"], r["coefficient"], r["method"] or ""))


def _noise_rows(view: StoreView, key: str) -> list[dict]:
    rows = []
    for asset in NOISE_SOURCES:
        if view.has_table(asset, "noise", key):
            for r in view.table(asset, "noise", key).to_dict(orient="records"):
                rows.append(to_jsonable({**r, "source": asset}))
    return rows


def run_content(view: StoreView, key: str, prev_record_sha256: str | None, software: dict) -> dict:
    """The certified content of the record of capture ``key`` (the ``content`` block; see the module docstring)."""
    from assets_lib.sim.earth import site_gravity_mps2
    from raw_schemas.manifest import Manifest

    ing = view.meta("ingested_run", key)
    manifest = Manifest.model_validate_json((view.version_dir("ingested_run", key) / "manifest.json").read_text())
    temp = view.table("ingested_run", "imu", key, columns=["time_s", "temperature_degc"])
    tc = temp["temperature_degc"].to_numpy(dtype=float)
    tc = tc[np.isfinite(tc)]
    steps = manifest.plan.steps
    site = manifest.site
    coefficients = _coefficient_rows(view, key)
    return to_jsonable({
        "record_schema_version": RECORD_SCHEMA_VERSION,
        "device": {"id": manifest.device.id, "model": manifest.device.model, "grade": manifest.device.grade,
                   "serial": manifest.device.serial},
        "run": {"run_id": manifest.run_id, "test_kind": manifest.test_kind,
                "start_time_utc": ing.get("start_time_utc", manifest.start_time_utc.isoformat()),
                "power_cycle_index": manifest.power_cycle_index, "table_id": manifest.table_id,
                "sample_rate_hz": manifest.sample_rate_hz, "n_samples": int(len(temp)),
                "duration_s": float(temp["time_s"].iloc[-1]) if len(temp) else 0.0},
        "test_conditions": {
            "site": {"name": site.name, "latitude_deg": site.latitude_deg, "longitude_deg": site.longitude_deg,
                     "height_m": site.height_m, "gravity_model": site.gravity_model},
            "latitude_deg": site.latitude_deg,
            "gravity_mps2": site_gravity_mps2(site),
            "temperature_degc": ({"min": float(tc.min()), "max": float(tc.max()), "mean": float(tc.mean())}
                                 if tc.size else None),
            "plan": {"name": manifest.plan.name, "frame": manifest.plan.frame, "n_steps": len(steps),
                     "n_rate_steps": sum(s.kind == "rate" for s in steps),
                     "n_static_steps": sum(s.kind == "static" for s in steps),
                     "duration_s": float(manifest.plan.end_s)},
        },
        "raw_files": dict(sorted((ing.get("file_sha256") or {}).items())),
        "coefficients": coefficients,
        "noise": _noise_rows(view, key),
        "stages": _stage_chain(view, key),
        "software": software,
        "prev_record_sha256": prev_record_sha256,
    })


def make_record(content: dict, created_utc: str, dagster_run_id: str | None) -> dict:
    return {"record_schema_version": RECORD_SCHEMA_VERSION, "record_sha256": content_sha256(content),
            "content": content, "provenance": {"created_utc": created_utc, "dagster_run_id": dagster_run_id}}


def same_certified_content(a: dict, b: dict) -> bool:
    """Equal content apart from the software block (the reuse rule of the module docstring)."""
    strip = lambda c: {k: v for k, v in c.items() if k != "software"}  # noqa: E731
    return canonical_json(strip(a)) == canonical_json(strip(b))


def run_order_key(start_time_utc: str, run_id: str):
    return (pd.Timestamp(start_time_utc).tz_convert("UTC") if start_time_utc else pd.Timestamp.min.tz_localize("UTC"),
            run_id)


def build_device_records(view: StoreView, keys: list[str], previous: dict[str, dict] | None = None,
                         software: dict | None = None, created_utc: str | None = None,
                         dagster_run_id: str | None = None) -> list[tuple[dict, bool]]:
    """Records of a device's captures ``keys`` in chain order, as (record, reused) pairs. ``previous``: the device's
    stored records by run id, reused verbatim when their certified content is unchanged."""
    software = software or software_info()
    created_utc = created_utc or utc_now_iso()
    previous = previous or {}
    metas = {k: view.meta("ingested_run", k) for k in keys}
    ordered = sorted(keys, key=lambda k: run_order_key(metas[k].get("start_time_utc", ""), metas[k].get("run_id", k)))
    out, prev_sha = [], None
    for k in ordered:
        content = run_content(view, k, prev_sha, software)
        old = previous.get(content["run"]["run_id"])
        if old is not None and "content" in old and same_certified_content(old["content"], content) \
                and content_sha256(old["content"]) == old.get("record_sha256"):
            rec, reused = old, True
        else:
            rec, reused = make_record(content, created_utc, dagster_run_id), False
        out.append((rec, reused))
        prev_sha = rec["record_sha256"]
    return out


def records_table(records: list[dict]) -> pd.DataFrame:
    rows = [{
        "run_id": r["content"]["run"]["run_id"], "start_time_utc": r["content"]["run"]["start_time_utc"],
        "test_kind": r["content"]["run"]["test_kind"], "record_sha256": r["record_sha256"],
        "prev_record_sha256": r["content"]["prev_record_sha256"],
        "n_coefficients": sum(c["observable"] for c in r["content"]["coefficients"]),
        "created_utc": r["provenance"].get("created_utc"), "dagster_run_id": r["provenance"].get("dagster_run_id"),
    } for r in records]
    return pd.DataFrame(rows, columns=RECORDS_TABLE_COLUMNS)


# ---------------------------------------------------------------------------------------------------------------
# Reading stored records and checking them
# ---------------------------------------------------------------------------------------------------------------
def load_records_dir(directory: str | Path) -> tuple[dict[str, dict], pd.DataFrame | None]:
    """Records (``<run_id>.json`` carrying ``record_schema_version``) and ``records.parquet`` of a version folder."""
    d = Path(directory)
    recs = {}
    for p in sorted(d.glob("*.json")):
        try:
            r = json.loads(p.read_text(encoding="utf-8"))
        except (json.JSONDecodeError, UnicodeDecodeError):
            recs[p.stem] = {"_unreadable": str(p)}
            continue
        if isinstance(r, dict) and "record_schema_version" in r:
            recs[p.stem] = r
    listing = pd.read_parquet(d / "records.parquet") if (d / "records.parquet").is_file() else None
    return recs, listing


def self_hash_problem(record: dict, name: str = "") -> str | None:
    """A record whose stored hash is not the hash of its content was edited after it was made."""
    if "_unreadable" in record:
        return f"record {name}: not valid JSON ({record['_unreadable']})"
    got = content_sha256(record.get("content", {}))
    if got != record.get("record_sha256"):
        return (f"record of run {name or record['content']['run']['run_id']}: stored record_sha256 "
                f"{str(record.get('record_sha256'))[:16]}... is not the sha256 of its content ({got[:16]}...): "
                "the record was edited")
    return None


def chain_problems(records: dict[str, dict], listing: pd.DataFrame | None = None, expected_runs=None,
                   up_to_run: str | None = None) -> list[str]:
    """Every break of a device's hash chain, named: edited records, missing records, broken links.

    ``records``: run id -> record; ``listing``: records.parquet of the same version (the device's index);
    ``expected_runs``: (run_id, start_time_utc) of the device's runs in the archive; ``up_to_run``: only the chain
    up to and including this run is checked."""
    problems = []
    good = {rid: r for rid, r in records.items() if "_unreadable" not in r}
    problems += [p for rid, r in records.items() if (p := self_hash_problem(r, rid))]
    order = {rid: run_order_key(r["content"]["run"]["start_time_utc"], rid) for rid, r in good.items()}
    listed = {}
    if listing is not None:
        for row in listing.itertuples():
            listed[row.run_id] = (row.record_sha256, row.start_time_utc)
            order.setdefault(row.run_id, run_order_key(row.start_time_utc, row.run_id))
    for rid, start in expected_runs or []:
        order.setdefault(rid, run_order_key(start, rid))
    limit = order.get(up_to_run) if up_to_run else None
    in_scope = lambda rid: limit is None or order[rid] <= limit  # noqa: E731
    for rid, (sha, _) in sorted(listed.items(), key=lambda kv: order[kv[0]]):
        if not in_scope(rid):
            continue
        if rid not in records:
            problems.append(f"record of run {rid} is missing (records.parquet lists it with sha256 {sha[:16]}...): "
                            "deleted from the chain")
        elif rid in good and good[rid].get("record_sha256") != sha:
            problems.append(f"record of run {rid}: sha256 {str(good[rid].get('record_sha256'))[:16]}... differs from "
                            f"records.parquet ({sha[:16]}...)")
    for rid, _ in expected_runs or []:
        if in_scope(rid) and rid not in records and rid not in listed:
            problems.append(f"run {rid} is in the archive but has no record")
    by_hash = {r.get("record_sha256"): rid for rid, r in good.items()}
    by_hash.update({sha: rid for rid, (sha, _) in listed.items() if sha not in by_hash})
    chain = sorted((rid for rid in good if in_scope(rid)), key=lambda rid: order[rid])
    for i, rid in enumerate(chain):
        got = good[rid]["content"].get("prev_record_sha256")
        want = good[chain[i - 1]].get("record_sha256") if i else None
        if got == want:
            continue
        prev_name = chain[i - 1] if i else None
        owner = by_hash.get(got)
        where = (f"which is the record of run {owner}" + (" (missing)" if owner not in good else "")) if owner \
            else "which matches no record"
        problems.append(
            f"chain link broken before run {rid}: its prev_record_sha256 is "
            f"{(got or 'null')[:16]}{'...' if got else ''}, {where}; the previous record present is "
            + (f"run {prev_name} with sha256 {str(want)[:16]}..." if prev_name else "none (it should be the first)"))
    return problems


# ---------------------------------------------------------------------------------------------------------------
# Comparing a recorded content with a recomputed one
# ---------------------------------------------------------------------------------------------------------------
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


# ---------------------------------------------------------------------------------------------------------------
# Certificate
# ---------------------------------------------------------------------------------------------------------------
_CSS = """body{font-family:Helvetica,Arial,sans-serif;margin:2em;color:#222;max-width:70em}
table{border-collapse:collapse;margin:0.6em 0 1.4em 0;font-size:0.88em}
td,th{border:1px solid #bbb;padding:0.25em 0.6em;text-align:left}th{background:#eee}
td.num{text-align:right;font-family:monospace}code{font-size:0.85em;word-break:break-all}
.muted{color:#777}h1{font-size:1.5em}h2{font-size:1.15em;margin-top:1.6em}img{max-width:100%;border:1px solid #ddd}"""


def _e(v) -> str:
    return html.escape("" if v is None else str(v))


def _fmt(v, digits: int = 6) -> str:
    return "n/a" if v is None else f"{v:.{digits}g}"


def _kv_table(pairs) -> str:
    return "<table>" + "".join(f"<tr><th>{_e(k)}</th><td>{v}</td></tr>" for k, v in pairs) + "</table>"


def certificate_html(record: dict, plots: dict[str, bytes] | None = None) -> str:
    """Human-readable certificate of one record: conditions, coefficient table with standard and expanded (k = 2)
    uncertainties in lab units (SI value in full precision alongside), noise terms, raw file hashes, software,
    chain hashes, and the residual / Allan plots embedded as base64 PNG."""
    c = record["content"]
    dev, run, tc = c["device"], c["run"], c["test_conditions"]
    temp = tc.get("temperature_degc") or {}
    parts = [f"<!DOCTYPE html><html lang='en'><head><meta charset='utf-8'><title>Calibration certificate "
             f"{_e(dev['id'])} {_e(run['run_id'])}</title><style>{_CSS}</style></head><body>",
             f"<h1>Calibration certificate: {_e(dev['id'])}, run {_e(run['run_id'])}</h1>",
             _kv_table([
                 ("Device", f"{_e(dev['id'])} ({_e(dev['model'])}, {_e(dev['grade'])} grade"
                            + (f", serial {_e(dev['serial'])}" if dev.get("serial") else "") + ")"),
                 ("Test", f"{_e(run['test_kind'])}, started {_e(run['start_time_utc'])}, power cycle "
                          f"{_e(run['power_cycle_index'])}"),
                 ("Record sha256", f"<code>{_e(record['record_sha256'])}</code>"),
                 ("Previous record sha256", f"<code>{_e(c.get('prev_record_sha256') or 'none (first record)')}</code>"),
                 ("Record schema", _e(record["record_schema_version"])),
             ]),
             "<h2>Test conditions</h2>",
             _kv_table([
                 ("Site", f"{_e(tc['site']['name'])}, latitude {_fmt(tc['latitude_deg'], 8)} deg, height "
                          f"{_fmt(tc['site']['height_m'])} m"),
                 ("Local gravity", f"{_fmt(tc['gravity_mps2'], 9)} m/s^2 ({_e(tc['site']['gravity_model'])})"),
                 ("Temperature", f"{_fmt(temp.get('min'), 4)} to {_fmt(temp.get('max'), 4)} degC (mean "
                                 f"{_fmt(temp.get('mean'), 4)})" if temp else "not recorded"),
                 ("Plan", f"{_e(tc['plan']['name'])}: {tc['plan']['n_steps']} steps ({tc['plan']['n_rate_steps']} "
                          f"rate, {tc['plan']['n_static_steps']} static), {_fmt(tc['plan']['duration_s'])} s, "
                          f"frame {_e(tc['plan']['frame'])}"),
                 ("Samples", f"{run['n_samples']} at {_fmt(run['sample_rate_hz'])} Hz"
                             + (f", table {_e(run['table_id'])}" if run.get("table_id") else "")),
             ])]
    coefs = c["coefficients"]
    parts.append("<h2>Coefficients</h2>")
    if coefs:
        parts.append("<table><tr><th>Source</th><th>Sensor</th><th>Axis</th><th>Coefficient</th><th>Value</th>"
                     "<th>Std. uncertainty</th><th>Expanded U (k=2)</th><th>Unit</th><th>Value (SI)</th>"
                     "<th>Std. unc. (SI)</th><th>SI unit</th><th>Method</th></tr>")
        for r in coefs:
            obs = r["observable"]
            parts.append(
                f"<tr><td>{_e(r['source'])}</td><td>{_e(r['sensor'])}</td><td>{_e(r['axis'])}</td>"
                f"<td>{_e(r['coefficient'])}</td>"
                + (f"<td class=num>{_fmt(r['value_lab'], 7)}</td><td class=num>{_fmt(r['stderr_lab'], 3)}</td>"
                   f"<td class=num>{_fmt(2 * r['stderr_lab'] if r['stderr_lab'] is not None else None, 3)}</td>"
                   if obs else "<td colspan=3 class=muted>not observable with this plan</td>")
                + f"<td>{_e(r['unit_lab'])}</td><td class=num>{_e(repr(r['value']) if r['value'] is not None else 'n/a')}"
                f"</td><td class=num>{_e(repr(r['stderr']) if r['stderr'] is not None else 'n/a')}</td>"
                f"<td>{_e(r['unit'])}</td><td>{_e(r['method'])}</td></tr>")
        parts.append("</table><p class=muted>Standard uncertainty = the fit's standard error (1 sigma); expanded "
                     "uncertainty U = 2 x standard uncertainty (approx. 95 % coverage).</p>")
    else:
        parts.append("<p class=muted>No coefficients are fitted from this test kind.</p>")
    if c.get("noise"):
        cols = [k for k in c["noise"][0] if k not in ("device_id", "run_id")]
        parts.append("<h2>Noise terms</h2><table><tr>" + "".join(f"<th>{_e(k)}</th>" for k in cols) + "</tr>")
        for r in c["noise"]:
            parts.append("<tr>" + "".join(
                f"<td class=num>{_fmt(r.get(k), 6)}</td>" if isinstance(r.get(k), float) else f"<td>{_e(r.get(k))}</td>"
                for k in cols) + "</tr>")
        parts.append("</table>")
    for name, png in (plots or {}).items():
        parts.append(f"<h2>{_e(name)}</h2><img alt='{_e(name)}' src='data:image/png;base64,"
                     f"{base64.b64encode(png).decode()}'>")
    parts.append("<h2>Raw data (sha256)</h2>" + _kv_table([(n, f"<code>{_e(h)}</code>") for n, h in
                                                          c["raw_files"].items()]))
    sw = c["software"]
    parts.append("<h2>Software</h2>" + _kv_table(
        [("imulab", _e(sw.get("imulab_version"))),
         ("git commit", f"<code>{_e(sw.get('git_commit'))}</code>" + (" (working tree modified)" if sw.get("git_dirty")
                                                                      else "")),
         *[(f"stage {a}", f"code version {_e(s['code_version'])}, output version <code>{_e(s['version'])}</code>")
           for a, s in c["stages"].items()]]))
    pv = record.get("provenance", {})
    parts.append(f"<p class=muted>Created {_e(pv.get('created_utc'))} by Dagster run {_e(pv.get('dagster_run_id'))}. "
                 "Verify with <code>imulab verify " + _e(run["run_id"]) + ".json</code>: it recomputes the "
                 "coefficients from the raw archive and checks the hash chain.</p></body></html>\n")
    return "".join(parts)
