"""One way to build every stage asset: batched partitions, content-derived versions, versioned parquet.

A stage is a pure function ``compute(key, inputs) -> StageOutput | None`` (the science lives in ``assets_lib``);
``capture_stage`` / ``device_stage`` / ``fleet_stage`` turn it into a Dagster asset that
- handles a whole partition range in one run (``BackfillPolicy.single_run``: one run per partition costs seconds),
- derives each partition's version from its code version and its inputs' versions (raw file hashes at the root),
  so unchanged work is reused, not recomputed or rewritten (idempotent; ``imulab reprocess`` uses the same rule),
- writes through ``ParquetStore`` atomically, never overwriting a version,
- returns a ``MaterializeResult`` with per-partition metadata (and plots when a single partition is run).
The registry ``STAGES`` is what staleness checks and reprocessing walk.
"""


import base64
import functools
import hashlib
import json
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import dagster as dg
import pandas as pd

from pipelines.partitions import captures, devices, split_capture_key
from pipelines.resources import LabArchive, ParquetStore
from pipelines.storage import VersionedStore, version_id
from raw_schemas.readers import sha256_file

FLEET_KEY = "fleet"


@dataclass
class StageOutput:
    """What a stage computed for one partition."""

    tables: dict[str, pd.DataFrame]
    meta: dict = field(default_factory=dict)  # JSON-able facts stored with the version (units, counts, flags)
    files: dict[str, bytes] = field(default_factory=dict)  # extra files stored with the version (PNG, JSON, HTML)
    summary: dict = field(default_factory=dict)  # a few scalars shown as metadata in the UI
    plots: dict[str, bytes] = field(default_factory=dict)  # PNGs shown inline in the UI (also stored as files)


@dataclass(frozen=True)
class StageSpec:
    name: str
    level: str  # 'capture' | 'device' | 'fleet'
    code_version: str
    upstream: tuple[str, ...]
    compute: Callable
    applies_to: tuple[str, ...] | None = None  # test kinds a capture stage applies to (None: all)


STAGES: dict[str, StageSpec] = {}


class StageInputs:
    """Read access for a stage's compute function: upstream tables and metadata, the raw folder."""

    def __init__(self, store: VersionedStore, archive: LabArchive | None, key: str, versions: dict[str, str],
                 run_id: str | None = None):
        self.store = store
        self.archive = archive
        self.key = key
        self.versions = versions
        self.run_id = run_id  # the Dagster run computing this partition (None outside Dagster); provenance only

    def table(self, asset: str, name: str, key: str | None = None) -> pd.DataFrame:
        k = key or self.key
        return self.store.read(asset, k, name, self.versions.get(f"{asset}/{k}"))

    def meta(self, asset: str, key: str | None = None) -> dict:
        k = key or self.key
        return self.store.read_meta(asset, k, self.versions.get(f"{asset}/{k}"))

    def file(self, asset: str, name: str, key: str | None = None) -> bytes:
        """An extra file stored with an upstream version (e.g. ``manifest.json`` of ``ingested_run``)."""
        k = key or self.key
        return (self.store.version_dir(asset, k, self.versions.get(f"{asset}/{k}")) / name).read_bytes()

    def has_table(self, asset: str, name: str, key: str | None = None) -> bool:
        k = key or self.key
        return (self.store.version_dir(asset, k, self.versions.get(f"{asset}/{k}")) / f"{name}.parquet").is_file()

    def run_dir(self) -> Path:
        return self.archive.run_dir(self.key)

    def keys_of(self, asset: str) -> list[str]:
        """Partitions of ``asset`` this computation reads (device and fleet stages read many)."""
        return sorted(k.split("/", 1)[1] for k in self.versions if k.startswith(f"{asset}/"))


# ---------------------------------------------------------------------------------------------------------------
# Versions (shared by the assets and by the staleness check)
# ---------------------------------------------------------------------------------------------------------------
def raw_versions(run_dir: Path) -> dict[str, str]:
    """sha256 of every file of a raw run folder: the root of every version chain."""
    return {f"raw/{p.name}": sha256_file(p) for p in sorted(Path(run_dir).iterdir()) if p.is_file()}


def default_upstream_keys(spec: StageSpec, up: str, key: str, store: VersionedStore) -> list[str]:
    """Partitions of upstream ``up`` that ``spec`` reads for ``key``: the same key, or all of the device's
    captures (device stages), or everything (fleet stages)."""
    level = STAGES[up].level
    if level == "capture" and spec.level != "capture":
        return [k for k in store.partitions(up) if spec.level == "fleet" or split_capture_key(k)[0] == key]
    if level == "device" and spec.level == "fleet":
        return store.partitions(up)
    return [key]


def input_versions(spec: StageSpec, key: str, store: VersionedStore, archive: LabArchive | None,
                   version_of: Callable | None = None, upstream_keys: Callable | None = None):
    """Versions of what ``spec`` computes ``key`` from, or None when an input is missing.

    ``version_of(stage, key)`` defaults to the stored CURRENT version; reprocessing plans pass expected ones.
    """
    version_of = version_of or store.current_version
    upstream_keys = upstream_keys or (lambda s, up, k: default_upstream_keys(s, up, k, store))
    if spec.level == "capture" and not spec.upstream:
        d = archive.run_dir(key)
        return raw_versions(d) if d.is_dir() else None
    out: dict[str, str] = {}
    for up in spec.upstream:
        for k in upstream_keys(spec, up, key):
            v = version_of(up, k)
            if v is None:
                if spec.level == "capture":
                    return None
                continue
            out[f"{up}/{k}"] = v
    if spec.level != "capture" and not out:
        return None
    return out


def expected_version(spec: StageSpec, inputs: dict[str, str]) -> str:
    return version_id(spec.name, spec.code_version, inputs)


# ---------------------------------------------------------------------------------------------------------------
# Running a stage over the partitions of a run
# ---------------------------------------------------------------------------------------------------------------
def _png_md(title: str, png: bytes) -> str:
    return f"**{title}**\n\n![{title}](data:image/png;base64,{base64.b64encode(png).decode()})"


def run_stage(context, spec: StageSpec, store: VersionedStore, archive: LabArchive | None) -> dg.MaterializeResult:
    keys = [FLEET_KEY] if spec.level == "fleet" else list(context.partition_keys)
    rows, errors, plots = [], [], {}
    single = len(keys) == 1
    for key in keys:
        inputs = input_versions(spec, key, store, archive)
        if inputs is None:
            rows.append({"partition": key, "status": "skipped: inputs missing", "version": ""})
            continue
        if spec.applies_to is not None and spec.level == "capture":
            kind = _test_kind(store, key, inputs)
            if kind not in spec.applies_to:
                rows.append({"partition": key, "status": f"not applicable ({kind})", "version": ""})
                continue
        version = expected_version(spec, inputs)
        if store.exists(spec.name, key, version):
            store.write(spec.name, key, version, {})  # only moves CURRENT back if needed
            rows.append({"partition": key, "status": "reused", "version": version})
            continue
        try:
            out = spec.compute(key, StageInputs(store, archive, key, inputs, run_id=context.run_id))
        except Exception as e:  # noqa: BLE001 - one bad partition must not stop the batch; reported below
            errors.append(f"{key}: {type(e).__name__}: {e}")
            context.log.error(f"{spec.name} failed for {key}: {e}")
            rows.append({"partition": key, "status": f"error: {e}"[:200], "version": ""})
            continue
        if out is None:
            rows.append({"partition": key, "status": "not applicable", "version": ""})
            continue
        files = dict(out.files)
        files.update({f"{n}.png": png for n, png in out.plots.items()})
        store.write(spec.name, key, version, out.tables,
                    meta={"code_version": spec.code_version, "inputs": inputs, **out.meta}, files=files)
        rows.append({"partition": key, "status": "written", "version": version, **_scalars(out.summary)})
        if single:
            plots = out.plots
    md = pd.DataFrame(rows).to_markdown(index=False) if rows else "(no partitions)"
    metadata: dict = {
        "partitions": dg.MetadataValue.md(md),
        "written": sum(r["status"] == "written" for r in rows),
        "reused": sum(r["status"] == "reused" for r in rows),
        "errors": len(errors),
        "store": dg.MetadataValue.path(str(Path(store.root) / spec.name)),
    }
    for name, png in plots.items():
        metadata[f"plot_{name}"] = dg.MetadataValue.md(_png_md(name, png))
    if errors:
        metadata["error_messages"] = dg.MetadataValue.md("\n".join(f"- {e}" for e in errors))
    digest = hashlib.sha256(json.dumps(sorted((r["partition"], r["version"]) for r in rows)).encode()).hexdigest()[:20]
    return dg.MaterializeResult(metadata=metadata, data_version=dg.DataVersion(digest))


def _scalars(d: dict) -> dict:
    return {k: v for k, v in d.items() if isinstance(v, (int, float, str, bool))}


def _test_kind(store: VersionedStore, key: str, inputs: dict[str, str]) -> str | None:
    """Test kind of a capture, from its ingested manifest."""
    v = inputs.get(f"ingested_run/{key}") or store.current_version("ingested_run", key)
    return store.read_meta("ingested_run", key, v).get("test_kind") if v else None


# ---------------------------------------------------------------------------------------------------------------
# Decorators
# ---------------------------------------------------------------------------------------------------------------
def _asset_kwargs(level: str) -> dict:
    if level == "capture":
        return {"partitions_def": captures, "backfill_policy": dg.BackfillPolicy.single_run()}
    if level == "device":
        return {"partitions_def": devices, "backfill_policy": dg.BackfillPolicy.single_run()}
    return {}


def _dep(up: str, level: str) -> dg.AssetDep:
    if STAGES[up].level == level:
        return dg.AssetDep(up)
    return dg.AssetDep(up, partition_mapping=dg.AllPartitionMapping())


SOURCE_TAG = "+src."


@functools.lru_cache(maxsize=None)
def _source_digest(module_file: str) -> str:
    """sha256 of the science and contract sources (``assets_lib``, ``raw_schemas``) and the stage's module."""
    root = Path(__file__).resolve().parents[1]
    files = sorted(root.glob("assets_lib/**/*.py")) + sorted(root.glob("raw_schemas/*.py")) + [Path(module_file)]
    h = hashlib.sha256()
    for f in files:
        if f.is_file():
            h.update(f.name.encode())
            h.update(f.read_bytes())
    return h.hexdigest()[:10]


def full_code_version(declared: str, compute) -> str:
    """The declared code version plus a digest of the code it runs, so a science change that forgot to bump the
    declared version still makes every output stale (``imulab reprocess`` and records see it)."""
    module = sys.modules.get(compute.__module__)
    module_file = getattr(module, "__file__", None) or ""
    return f"{declared}{SOURCE_TAG}{_source_digest(module_file)}"


def stage(name: str, *, level: str, group: str, code_version: str, upstream=(), description: str = "",
          applies_to=None, kinds=("parquet",)):
    """Register ``compute`` as a stage and return its Dagster asset."""

    def deco(compute):
        full = full_code_version(code_version, compute)
        spec = StageSpec(name, level, full, tuple(upstream), compute,
                         tuple(applies_to) if applies_to else None)
        STAGES[name] = spec

        @dg.asset(
            name=name,
            group_name=group,
            code_version=full,
            deps=[_dep(u, level) for u in upstream],
            kinds=set(kinds),
            description=description or (compute.__doc__ or "").strip().splitlines()[0],
            **_asset_kwargs(level),
        )
        def _asset(context: dg.AssetExecutionContext, store: ParquetStore, archive: LabArchive) -> dg.MaterializeResult:
            return run_stage(context, spec, store.store, archive)

        return _asset

    return deco
