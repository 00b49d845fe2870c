"""The certified content of a run's record, built from stored stage outputs, and the device's chain of records.

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

import json
import subprocess
from datetime import datetime, timezone
from pathlib import Path

import numpy as np
import pandas as pd

from assets_lib.store.view import StoreView  # the one read view over the store

from assets_lib.records.canonical import RECORD_SCHEMA_VERSION, canonical_json, content_sha256, to_jsonable
from assets_lib.records.validity import RecordStatus, record_status, reduced_chi_square

COEFFICIENT_SOURCES = ("gyro_rate_fit", "accel_multiposition_fit", "tablefree_fit")
NOISE_SOURCES = ("allan_deviation",)
PLOT_SOURCES = (*COEFFICIENT_SOURCES, *NOISE_SOURCES)
COEFFICIENT_FIELDS = ("sensor", "axis", "coefficient", "value", "stderr", "unit", "value_lab", "stderr_lab", "unit_lab",
                      "observable", "n_plateaus", "n_samples", "method")
RECORDS_TABLE_COLUMNS = ["run_id", "start_time_utc", "test_kind", "record_sha256", "prev_record_sha256",
                         "n_coefficients", "status", "status_reasons", "created_utc", "dagster_run_id"]


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
    status = _status(view, key, manifest.device.grade, coefficients)
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
        "status": status.status,
        "status_reasons": list(status.reasons),
    })


def _status(view: StoreView, key: str, grade: str, coefficients: list[dict]) -> RecordStatus:
    """Validity of the record (``assets_lib.records.validity``) from its coefficients, the fits' residuals and the
    Allan stage's model-inside-interval shares."""
    chi2 = {}
    for asset in COEFFICIENT_SOURCES:
        if view.has_table(asset, "residuals", key):
            r = view.table(asset, "residuals", key)
            if "std_residual" in r:
                chi2[asset] = reduced_chi_square(r["std_residual"].to_numpy(dtype=float),
                                                 r["excluded"].to_numpy(dtype=bool) if "excluded" in r else None)
    inside = {}
    for asset in NOISE_SOURCES:
        if view.has(asset, key):
            inside.update(view.meta(asset, key).get("model_inside_ci") or {})
    return record_status(grade, coefficients, chi2, inside)


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
        "status": r["content"].get("status", "unknown"),
        "status_reasons": "; ".join(r["content"].get("status_reasons") or []),
        "created_utc": r["provenance"].get("created_utc"), "dagster_run_id": r["provenance"].get("dagster_run_id"),
    } for r in records]
    return pd.DataFrame(rows, columns=RECORDS_TABLE_COLUMNS)
