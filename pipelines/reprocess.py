"""Reprocessing with Dagster: the plan (``assets_lib.stages.plan``) over the partitions registered on an instance,
turned into batched runs: stale partitions are grouped into contiguous blocks of the partition order, one
range-tagged run per block and level (single-run backfill policy), never one run per partition. The
``imulab reprocess`` command and the reprocessing schedules both use it.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass

import dagster as dg

from assets_lib.stages.engine import StageGraph
from assets_lib.stages.plan import ReprocessPlan, plan_reprocess, record_no_output
from assets_lib.store import VersionedStore
from pipelines.jobs import FLEET_JOB, LEVEL_JOB, contiguous_blocks, range_tags
from pipelines.launch import LaunchSummary, run_job
from pipelines.partitions import registered_keys

REPROCESS_TAG = "imulab/reprocess"


def plan_for_instance(instance: dg.DagsterInstance, graph: StageGraph, store: VersionedStore, archive,
                      use_ledger: bool = True) -> ReprocessPlan:
    """The reprocessing plan over every partition registered on ``instance`` (``archive``: a ``LandingArchive``)."""
    cap, dev = registered_keys(instance)
    return plan_reprocess(graph, store, archive, cap, dev, use_ledger)


@dataclass(frozen=True)
class PlannedRun:
    job: str
    level: str
    first: str | None
    last: str | None
    stages: tuple[str, ...]

    @property
    def tags(self) -> dict[str, str]:
        base = {REPROCESS_TAG: "1"}
        return {**base, **range_tags(self.first, self.last)} if self.first is not None else base

    @property
    def asset_selection(self) -> list[dg.AssetKey]:
        return [dg.AssetKey(s) for s in self.stages]

    def run_key(self, plan: ReprocessPlan) -> str:
        keys = sorted((s, k, v) for (s, k), v in plan.expected.items() if s in self.stages)
        digest = hashlib.sha256(json.dumps([self.job, self.first, self.last, keys]).encode()).hexdigest()[:16]
        return f"reprocess-{self.level}-{digest}"


def planned_runs(plan: ReprocessPlan, capture_order: list[str], device_order: list[str],
                 levels=("capture", "device", "fleet"), exclude_devices=()) -> list[PlannedRun]:
    """One run per contiguous block of stale partitions and level, selecting only the stale stages.

    When a stage reading siblings is stale, the stale captures are launched as ONE range (first to last stale
    capture; partitions between them are reused, not recomputed): a device's captures need not be contiguous in
    the partition order, and a sibling recomputed in a later run than its reader would leave the reader at a
    version other than the expected one (and the no-output ledger would then keep it from being retried)."""
    runs: list[PlannedRun] = []
    exclude_devices = set(exclude_devices)
    orders = {"capture": capture_order, "device": device_order}
    for level in levels:
        if level == "fleet":
            stages = plan.stale_stages("fleet")
            if stages:
                runs.append(PlannedRun(FLEET_JOB, level, None, None, tuple(stages)))
            continue
        wanted = set(plan.stale_keys(level)) - (exclude_devices if level == "device" else set())
        ordered = orders[level]
        if level == "capture" and set(plan.sibling_readers) & set(plan.stale_stages(level)):
            at = [i for i, k in enumerate(ordered) if k in wanted]
            wanted = set(ordered[at[0]: at[-1] + 1]) if at else wanted
        for first, last in contiguous_blocks(ordered, wanted):
            block = ordered[ordered.index(first): ordered.index(last) + 1]
            runs.append(PlannedRun(LEVEL_JOB[level], level, first, last, tuple(plan.stale_stages(level, block))))
    return runs


def run_plan(defs: dg.Definitions, instance: dg.DagsterInstance, plan: ReprocessPlan, store: VersionedStore,
             quiet: bool = True) -> LaunchSummary:
    """Execute the planned runs level by level (captures, then devices, then fleet) in this process, then note
    partitions that produced no output. Returns the ``LaunchSummary``."""
    cap, dev = registered_keys(instance)
    summary = LaunchSummary()
    jobs = {j.name for j in defs.resolve_all_job_defs()}
    for run in planned_runs(plan, cap, dev):
        if run.job in jobs and run.stages:
            run_job(defs, instance, run.job, tags=run.tags, asset_selection=run.asset_selection, quiet=quiet,
                    summary=summary)
    record_no_output(store, plan, summary.attempted)
    return summary
