"""Stage assets, generated from the stage list (``assets_lib.stages.registry``): one Dagster asset per stage that
- handles a whole partition range in one run (``BackfillPolicy.single_run``: one run per partition costs seconds),
- computes each partition with ``assets_lib.stages.engine.compute_partition`` (the one way; versions derived from
  code and inputs, unchanged work reused, outputs written atomically and never overwritten),
- returns a ``MaterializeResult`` with a table of per-partition outcomes (and plots when a single partition ran).
A partition that fails is logged with its reason and does not stop the others.
"""


import base64
import hashlib
import json
from pathlib import Path

import dagster as dg
import pandas as pd

from assets_lib.stages.engine import Outcome, StageGraph, StageSpec, compute_partition
from assets_lib.store import FLEET_KEY, VersionedStore
from pipelines.partitions import captures, devices
from pipelines.resources import LabArchive, ParquetStore, WorkspaceLock


def _png_md(title: str, png: bytes) -> str:
    return f"**{title}**\n\n![{title}](data:image/png;base64,{base64.b64encode(png).decode()})"


def _scalars(d: dict) -> dict:
    return {k: v for k, v in d.items() if isinstance(v, (int, float, str, bool))}


def outcomes_metadata(spec: StageSpec, outcomes: list[Outcome], store: VersionedStore) -> dict:
    rows = [{"partition": o.key, "status": o.describe()[:200], "version": o.version or "", **_scalars(o.summary)}
            for o in outcomes]
    errors = [f"{o.key}: {o.reason}" for o in outcomes if o.failed]
    md = pd.DataFrame(rows).to_markdown(index=False) if rows else "(no partitions)"
    metadata: dict = {
        "partitions": dg.MetadataValue.md(md),
        "written": sum(o.status == "written" for o in outcomes),
        "reused": sum(o.status == "reused" for o in outcomes),
        "errors": len(errors),
        "store": dg.MetadataValue.path(str(Path(store.root) / spec.name)),
    }
    if len(outcomes) == 1:
        for name, png in outcomes[0].plots.items():
            metadata[f"plot_{name}"] = dg.MetadataValue.md(_png_md(name, png))
    if errors:
        metadata["error_messages"] = dg.MetadataValue.md("\n".join(f"- {e}" for e in errors))
    return metadata


def run_stage(context, graph: StageGraph, spec: StageSpec, store: VersionedStore, archive) -> dg.MaterializeResult:
    keys = [FLEET_KEY] if spec.level == "fleet" else list(context.partition_keys)
    outcomes = []
    for key in keys:
        o = compute_partition(graph, spec, key, store, archive, run_id=context.run_id)
        if o.failed:
            context.log.error(f"{spec.name} failed for {key}: {o.reason}")
        outcomes.append(o)
    digest = hashlib.sha256(json.dumps(sorted((o.key, o.version or "") for o in outcomes)).encode()).hexdigest()[:20]
    return dg.MaterializeResult(metadata=outcomes_metadata(spec, outcomes, store), data_version=dg.DataVersion(digest))


def _asset_kwargs(level: str) -> dict:
    if level == "capture":
        return {"partitions_def": captures, "backfill_policy": dg.BackfillPolicy.single_run()}
    if level == "device":
        return {"partitions_def": devices, "backfill_policy": dg.BackfillPolicy.single_run()}
    return {}


def stage_asset(graph: StageGraph, spec: StageSpec) -> dg.AssetsDefinition:
    deps = [dg.AssetDep(u) if graph[u].level == spec.level else dg.AssetDep(u, partition_mapping=dg.AllPartitionMapping())
            for u in spec.upstream]

    @dg.asset(name=spec.name, group_name=spec.group, code_version=spec.code_version, deps=deps, kinds=set(spec.kinds),
              description=spec.description, **_asset_kwargs(spec.level))
    def _asset(context: dg.AssetExecutionContext, store: ParquetStore, archive: LabArchive,
               workspace_lock: WorkspaceLock) -> dg.MaterializeResult:  # held for the run: see WorkspaceLock
        return run_stage(context, graph, spec, store.store, archive.archive)

    return _asset


def stage_assets(graph: StageGraph) -> list[dg.AssetsDefinition]:
    return [stage_asset(graph, s) for s in graph]
