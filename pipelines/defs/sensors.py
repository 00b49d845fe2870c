"""Sensors: the landing sensor (capture jobs are upstream) and the follow-up sensors that chain the levels.

Landing sensor. A run is picked up once its capture job has written ``_COMPLETE`` (written last); it is new when
its ``captures`` partition is not registered yet. The sensor registers new runs as partitions and requests one
batched run (``BackfillPolicy.single_run``) over every partition not yet requested. What was requested is tracked
in the cursor as a position in the registered-partition list (dynamic partitions keep insertion order, and the
sensor appends), never as a wall-clock time or an mtime, so
- a run that completes while a tick scans is simply seen by the next tick,
- a run copied with preserved old timestamps (``cp -p``, ``rsync -a``) is picked up like any other,
- if a tick registered partitions but died before its run was launched (the daemon then keeps the old cursor),
  the next tick requests those partitions again,
- a re-tick never launches the same work twice: the ``run_key`` is a hash of the requested partition keys, and
  the daemon drops a request whose run key it has already launched.
Without a usable cursor (a new sensor, a deleted partition) the registered partitions that the root stage has
never materialized are requested, so nothing is missed either.

Follow-up sensors. When a ``calibrate_captures`` run succeeds, ``captures_to_devices`` requests
``calibrate_devices`` over the devices of that run's partitions; when a ``calibrate_devices`` run succeeds,
``devices_to_fleet`` requests ``fleet_summary``. They follow ``RUN_SUCCESS`` events in the event log (the
mechanism of ``@run_status_sensor``; the cursor is the event's storage id, so a run that started early and
finished late is not skipped) and their run keys derive from the triggering run id. ``sensors(graph)`` builds
them for the jobs the stage graph has.
"""

import hashlib
import json

import dagster as dg

from assets_lib.stages.engine import StageGraph
from assets_lib.store import split_capture_key
from pipelines.jobs import (
    CAPTURES_JOB,
    DEVICES_JOB,
    FLEET_JOB,
    PARTITION_TAG,
    RANGE_END,
    RANGE_START,
    contiguous_blocks,
    range_tags,
)
from pipelines.partitions import captures, devices, new_partition_requests
from pipelines.resources import LabArchive

TRIGGER_TAG = "imulab/triggered_by_run"
#: the root stage whose materializations tell which registered captures were ever computed
ROOT_STAGES = ("ingested_run",)


def landing_digest(keys) -> str:
    return hashlib.sha256("\n".join(sorted(keys)).encode()).hexdigest()[:16]


def _parse_cursor(cursor: str | None) -> dict:
    if not cursor:
        return {}
    try:
        value = json.loads(cursor)
    except ValueError:
        return {}
    return value if isinstance(value, dict) else {}


def unrequested_partitions(instance: dg.DagsterInstance, registered: list[str], cursor: dict) -> list[str]:
    """Registered capture partitions no landing run request has covered yet."""
    n, last = cursor.get("requested"), cursor.get("last")
    if isinstance(n, int) and 0 <= n <= len(registered) and (n == 0 or registered[n - 1] == last):
        return registered[n:]
    done = None
    for name in ROOT_STAGES:
        got = set(instance.get_materialized_partitions(dg.AssetKey(name)))
        done = got if done is None else done & got
    return [k for k in registered if k not in done]


@dg.sensor(job_name=CAPTURES_JOB, minimum_interval_seconds=30, default_status=dg.DefaultSensorStatus.RUNNING)
def landing_sensor(context: dg.SensorEvaluationContext, archive: LabArchive):
    """Register completed runs (``_COMPLETE`` present) as partitions and request one batched run for them."""
    complete = archive.complete_runs()
    cursor = _parse_cursor(context.cursor)
    registered = list(context.instance.get_dynamic_partitions(captures.name))
    new, requests = new_partition_requests(context.instance, complete)
    pending = unrequested_partitions(context.instance, registered, cursor) + new
    order = registered + new  # the partition order once the add requests are applied
    next_cursor = json.dumps({"requested": len(order), "last": order[-1] if order else None,
                              "complete_runs": len(complete), "digest": landing_digest(complete)})
    if not pending:
        return dg.SensorResult(skip_reason=f"no new completed runs ({len(complete)} known)", cursor=next_cursor)
    pending_set = set(pending)
    run_requests = []
    for first, last in contiguous_blocks(order, pending_set):
        block = order[order.index(first): order.index(last) + 1]
        run_requests.append(dg.RunRequest(run_key=f"landing-{landing_digest(block)}", tags=range_tags(first, last)))
    return dg.SensorResult(dynamic_partitions_requests=requests, run_requests=run_requests, cursor=next_cursor)


# ---------------------------------------------------------------------------------------------------------------
# Follow-up sensors: captures -> devices -> fleet
# ---------------------------------------------------------------------------------------------------------------
def run_partition_keys(instance: dg.DagsterInstance, run: dg.DagsterRun, partitions_name: str) -> list[str]:
    """Partition keys a run covered, from its range (or single-partition) tags."""
    tags = run.tags
    if PARTITION_TAG in tags:
        return [tags[PARTITION_TAG]]
    if RANGE_START in tags and RANGE_END in tags:
        ordered = list(instance.get_dynamic_partitions(partitions_name))
        try:
            i, j = ordered.index(tags[RANGE_START]), ordered.index(tags[RANGE_END])
        except ValueError:
            return []
        return ordered[i: j + 1]
    return []


def _successes(instance: dg.DagsterInstance, job_names: list[str], after: int | None, limit: int = 100):
    """RUN_SUCCESS event records of ``job_names`` after storage id ``after`` (ascending)."""
    flt = dg.RunStatusChangeRecordsFilter(event_type=dg.DagsterEventType.RUN_SUCCESS, job_names=job_names,
                                          after_storage_id=after)
    return list(instance.fetch_run_status_changes(flt, limit=limit, ascending=True).records)


def _latest_success_id(instance: dg.DagsterInstance) -> int:
    flt = dg.RunStatusChangeRecordsFilter(event_type=dg.DagsterEventType.RUN_SUCCESS)
    recs = instance.fetch_run_status_changes(flt, limit=1, ascending=False).records
    return recs[0].storage_id if recs else 0


def follow_up_requests(instance: dg.DagsterInstance, run: dg.DagsterRun, request_job: str) -> list[dg.RunRequest]:
    """What to launch after ``run`` succeeded: device ranges covering its captures, or the fleet job."""
    trigger = {TRIGGER_TAG: run.run_id}
    if request_job == FLEET_JOB:
        return [dg.RunRequest(run_key=f"{FLEET_JOB}-after-{run.run_id}", job_name=FLEET_JOB, tags=trigger)]
    keys = run_partition_keys(instance, run, captures.name)
    wanted = {split_capture_key(k)[0] for k in keys}
    ordered = list(instance.get_dynamic_partitions(devices.name))
    return [dg.RunRequest(run_key=f"{DEVICES_JOB}-after-{run.run_id}-{first}..{last}", job_name=DEVICES_JOB,
                          tags={**range_tags(first, last), **trigger})
            for first, last in contiguous_blocks(ordered, wanted)]


def build_follow_up_sensor(name: str, monitored: list[str], request_job: str, description: str):
    @dg.sensor(name=name, job_name=request_job, minimum_interval_seconds=30, description=description,
               default_status=dg.DefaultSensorStatus.RUNNING)
    def _sensor(context: dg.SensorEvaluationContext):
        cursor = _parse_cursor(context.cursor)
        after = cursor.get("after")
        if not isinstance(after, int):  # first tick: start from now, like @run_status_sensor
            latest = _latest_success_id(context.instance)
            return dg.SensorResult(skip_reason="initialised at the latest successful run",
                                   cursor=json.dumps({"after": latest}))
        records = _successes(context.instance, monitored, after)
        requests = []
        for rec in records:
            run = context.instance.get_run_by_id(rec.run_id)
            if run is not None and run.job_name in monitored:  # not every storage filters by job name
                requests += follow_up_requests(context.instance, run, request_job)
        last = records[-1].storage_id if records else after
        if not requests:
            return dg.SensorResult(skip_reason=f"no new successful {'/'.join(monitored)} run", cursor=json.dumps({"after": last}))
        return dg.SensorResult(run_requests=requests, cursor=json.dumps({"after": last}))

    return _sensor


def sensors(graph: StageGraph) -> list:
    """The landing sensor and the follow-up sensors for the jobs ``graph`` has (a job exists when stages of its
    level exist)."""
    levels = graph.levels
    out = [landing_sensor]
    if "capture" in levels and "device" in levels:
        out.append(build_follow_up_sensor(
            "captures_to_devices", [CAPTURES_JOB], DEVICES_JOB,
            "When a calibrate_captures run succeeds, run calibrate_devices over the devices of its partitions."))
    if "fleet" in levels:
        upstream = [j for j, lvl in ((CAPTURES_JOB, "capture"), (DEVICES_JOB, "device")) if lvl in levels]
        monitored = [DEVICES_JOB] if DEVICES_JOB in upstream else upstream
        if monitored:
            out.append(build_follow_up_sensor(
                "devices_to_fleet", monitored, FLEET_JOB,
                f"When a {'/'.join(monitored)} run succeeds, refresh the fleet summary."))
    return out
