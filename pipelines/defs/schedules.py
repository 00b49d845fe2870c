"""Scheduled reprocessing: a weekly pass that recomputes only stale partitions (changed code or raw input).

One schedule per job level, all on the same cron and STOPPED by default (turn them on in the UI or with
``dagster schedule start``). Each tick plans with ``pipelines.reprocess`` (the same rule as ``imulab
reprocess``) and emits one range-tagged run per contiguous block of stale partitions, selecting only the stale
stages. Levels chain: while captures are stale, the device and fleet schedules leave the devices of those
captures and the fleet to the follow-up sensors (``captures_to_devices``, ``devices_to_fleet``), which run once
the new capture versions exist; devices stale for their own reasons (a device stage's code version) are
requested directly. Schedules are built when ``pipelines.definitions`` collects ``SCHEDULES``, for the jobs
that exist.
"""


import dagster as dg

from pipelines import reprocess
from pipelines.defs.sensors import CAPTURES_JOB, DEVICES_JOB, FLEET_JOB, JOB_LEVEL
from pipelines.partitions import split_capture_key
from pipelines.resources import LabArchive, ParquetStore
from pipelines.stage import STAGES

CRON = "0 3 * * 0"  # Sundays 03:00, in the instance's time zone unless execution_timezone is set
SCHEDULE_NAMES = {CAPTURES_JOB: "reprocess_captures_weekly", DEVICES_JOB: "reprocess_devices_weekly",
                  FLEET_JOB: "reprocess_fleet_weekly"}


def reprocess_requests(instance: dg.DagsterInstance, store: ParquetStore, archive: LabArchive, job_name: str,
                       levels_present: set[str]) -> tuple[list[dg.RunRequest], str]:
    """Run requests of ``job_name`` for a reprocessing tick, and a one-line description of what is stale."""
    st = store.store
    plan = reprocess.plan_for_instance(instance, st, archive)
    cap, dev = reprocess.registered_keys(instance)
    level = JOB_LEVEL[job_name]
    stale_caps = plan.stale_keys("capture")
    if level == "capture":
        runs = reprocess.planned_runs(plan, cap, dev, levels=("capture",))
    elif level == "device":
        chained = {split_capture_key(k)[0] for k in stale_caps} if "capture" in levels_present else set()
        runs = reprocess.planned_runs(plan, cap, dev, levels=("device",), exclude_devices=chained)
    else:
        below = stale_caps or plan.stale_keys("device")
        runs = [] if below else reprocess.planned_runs(plan, cap, dev, levels=("fleet",))
    requests = [dg.RunRequest(run_key=r.run_key(plan), tags=r.tags, asset_selection=r.asset_selection)
                for r in runs if r.stages]
    what = ", ".join(f"{n}: {len(v)}" for n, v in plan.by_stage().items()) or "nothing stale"
    return requests, what


def build_reprocess_schedule(job_name: str, levels_present: set[str]):
    @dg.schedule(name=SCHEDULE_NAMES[job_name], cron_schedule=CRON, job_name=job_name,
                 default_status=dg.DefaultScheduleStatus.STOPPED,
                 description=f"Weekly: recompute stale partitions of the {JOB_LEVEL[job_name]}-level stages "
                             "(changed code version or raw input), one batched run per contiguous block.")
    def _schedule(context: dg.ScheduleEvaluationContext, store: ParquetStore, archive: LabArchive):
        requests, what = reprocess_requests(context.instance, store, archive, job_name, levels_present)
        if not requests:
            return dg.SkipReason(f"nothing to reprocess for {job_name} ({what})")
        return requests

    return _schedule


def reprocess_schedules() -> list:
    levels = {s.level for s in STAGES.values()}
    return [build_reprocess_schedule(job, levels) for job, level in JOB_LEVEL.items() if level in levels]


def __getattr__(name: str):
    # Evaluated when pipelines.definitions collects the module, after every stage module is imported.
    if name == "SCHEDULES":
        return reprocess_schedules()
    raise AttributeError(name)
