"""Stage assets, generated from the stage list (``assets_lib.stages.registry``): one Dagster asset per stage that
- handles a whole partition range in one run (``BackfillPolicy.single_run``: one run per partition costs seconds),
- computes each partition with ``assets_lib.stages.engine.compute_partition`` (the one way; versions derived from
  code and inputs, unchanged work reused, outputs written atomically and never overwritten),
- records each partition's outcome (status, version, a few scalars) on that partition's materialization, and
  returns a ``MaterializeResult`` with the run's counts and errors (and plots when a single partition ran). A
  range run yields one materialization per partition, each carrying the run-level metadata: a table of every
  partition there was copied into every event (quadratic in the batch size).
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


def partition_metadata(o: Outcome) -> dict:
    """What one partition's materialization shows: its outcome, version and the stage's scalars."""
    return {"status": o.describe()[:200], "version": o.version or "", **_scalars(o.summary)}


def outcomes_metadata(spec: StageSpec, outcomes: list[Outcome], store: VersionedStore, table: bool = True) -> dict:
    """The run-level metadata; with ``table``, a table of every partition's outcome (unpartitioned assets: the
    one materialization is the run's)."""
    errors = [f"{o.key}: {o.reason}" for o in outcomes if o.failed]
    metadata: dict = {}
    if table:
        rows = [{"partition": o.key, **partition_metadata(o)} for o in outcomes]
        metadata["partitions"] = dg.MetadataValue.md(pd.DataFrame(rows).to_markdown(index=False) if rows
                                                     else "(no partitions)")
    metadata |= {
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
        o = compute_partition(graph, spec, key, store, archive, run_id=context.run.run_id)
        if o.failed:
            context.log.error(f"{spec.name} failed for {key}: {o.reason}")
        outcomes.append(o)
    digest = hashlib.sha256(json.dumps(sorted((o.key, o.version or "") for o in outcomes)).encode()).hexdigest()[:20]
    partitioned = spec.level != "fleet"
    if partitioned:
        for o in outcomes:
            context.add_asset_metadata(partition_metadata(o), partition_key=o.key)
    return dg.MaterializeResult(metadata=outcomes_metadata(spec, outcomes, store, table=not partitioned),
                                data_version=dg.DataVersion(digest))


def _asset_kwargs(level: str) -> dict:
    if level == "capture":
        return {"partitions_def": captures, "backfill_policy": dg.BackfillPolicy.single_run()}
    if level == "device":
        return {"partitions_def": devices, "backfill_policy": dg.BackfillPolicy.single_run()}
    return {}


def stage_deps(graph: StageGraph, spec: StageSpec) -> list[dg.AssetDep]:
    """The asset's deps: an upstream of the same level maps key to key; a cross-level read (a device or fleet stage
    reading finer partitions) and a sibling (a capture stage reading the captures of its device) map to every
    partition (``AllPartitionMapping``), so in one run the upstream is materialized over the whole range first."""
    return [dg.AssetDep(u) if graph[u].level == spec.level and u not in spec.siblings
            else dg.AssetDep(u, partition_mapping=dg.AllPartitionMapping()) for u in spec.dependencies]


def stage_asset(graph: StageGraph, spec: StageSpec) -> dg.AssetsDefinition:
    deps = stage_deps(graph, spec)

    @dg.asset(name=spec.name, group_name=spec.group, code_version=spec.code_version, deps=deps, kinds=set(spec.kinds),
              description=spec.description, **_asset_kwargs(spec.level))
    def _asset(context: dg.AssetExecutionContext, store: ParquetStore, archive: LabArchive,
               workspace_lock: WorkspaceLock) -> dg.MaterializeResult:  # held for the run: see WorkspaceLock
        return run_stage(context, graph, spec, store.store, archive.archive)

    return _asset


def stage_assets(graph: StageGraph) -> list[dg.AssetsDefinition]:
    return [stage_asset(graph, s) for s in graph]
