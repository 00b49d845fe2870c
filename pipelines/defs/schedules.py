"""Scheduled reprocessing: a weekly pass that recomputes only stale partitions (changed code or raw input).

One schedule per job level, all on the same cron and STOPPED by default (turn them on in the UI or with
``dagster schedule start``). Each tick plans with ``pipelines.reprocess`` (the same rule as ``imulab
reprocess``) and emits one range-tagged run per contiguous block of stale partitions, selecting only the stale
stages. Levels chain: while captures are stale, the device and fleet schedules leave the devices of those
captures and the fleet to the follow-up sensors (``captures_to_devices``, ``devices_to_fleet``), which run once
the new capture versions exist; devices stale for their own reasons (a device stage's code version) are
requested directly. ``schedules(graph)`` builds one per job the stage graph has.
"""

import dagster as dg

from assets_lib.stages.engine import StageGraph
from assets_lib.store import split_capture_key
from pipelines import reprocess
from pipelines.jobs import CAPTURES_JOB, DEVICES_JOB, FLEET_JOB, JOB_LEVEL
from pipelines.partitions import registered_keys
from pipelines.resources import LabArchive, ParquetStore

CRON = "0 3 * * 0"  # Sundays 03:00, in the instance's time zone unless execution_timezone is set
SCHEDULE_NAMES = {CAPTURES_JOB: "reprocess_captures_weekly", DEVICES_JOB: "reprocess_devices_weekly",
                  FLEET_JOB: "reprocess_fleet_weekly"}


def reprocess_requests(instance: dg.DagsterInstance, graph: StageGraph, store: ParquetStore, archive: LabArchive,
                       job_name: str) -> tuple[list[dg.RunRequest], str]:
    """Run requests of ``job_name`` for a reprocessing tick, and a one-line description of what is stale."""
    plan = reprocess.plan_for_instance(instance, graph, store.store, archive.archive)
    cap, dev = registered_keys(instance)
    level = JOB_LEVEL[job_name]
    stale_caps = plan.stale_keys("capture")
    if level == "capture":
        runs = reprocess.planned_runs(plan, cap, dev, levels=("capture",))
    elif level == "device":
        chained = {split_capture_key(k)[0] for k in stale_caps} if "capture" in graph.levels else set()
        runs = reprocess.planned_runs(plan, cap, dev, levels=("device",), exclude_devices=chained)
    else:
        below = stale_caps or plan.stale_keys("device")
        runs = [] if below else reprocess.planned_runs(plan, cap, dev, levels=("fleet",))
    requests = [dg.RunRequest(run_key=r.run_key(plan), tags=r.tags, asset_selection=r.asset_selection)
                for r in runs if r.stages]
    what = ", ".join(f"{n}: {len(v)}" for n, v in plan.by_stage().items()) or "nothing stale"
    return requests, what


def build_reprocess_schedule(graph: StageGraph, job_name: str):
    @dg.schedule(name=SCHEDULE_NAMES[job_name], cron_schedule=CRON, job_name=job_name,
                 default_status=dg.DefaultScheduleStatus.STOPPED,
                 description=f"Weekly: recompute stale partitions of the {JOB_LEVEL[job_name]}-level stages "
                             "(changed code version or raw input), one batched run per contiguous block.")
    def _schedule(context: dg.ScheduleEvaluationContext, store: ParquetStore, archive: LabArchive):
        requests, what = reprocess_requests(context.instance, graph, store, archive, job_name)
        if not requests:
            return dg.SkipReason(f"nothing to reprocess for {job_name} ({what})")
        return requests

    return _schedule


def schedules(graph: StageGraph) -> list:
    """One weekly reprocessing schedule per job the stage graph has."""
    return [build_reprocess_schedule(graph, job) for job, level in JOB_LEVEL.items() if level in graph.levels]
