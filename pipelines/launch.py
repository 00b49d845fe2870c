"""Launch batched runs from Python (the CLI and tests): register landed runs, then one run per level.

Order: every per-run stage over all capture partitions in one run, then every per-device stage over all device
partitions in one run, then the fleet stage. Reused versions cost only a lookup, so running over everything is
cheap; ``pipelines.reprocess`` narrows the ranges to stale partitions.
"""

from dataclasses import dataclass, field

import dagster as dg

from assets_lib.stages.plan import plan_reprocess, record_no_output
from assets_lib.store import FLEET_KEY
from pipelines.jobs import (
    CAPTURES_JOB,
    DEVICES_JOB,
    FLEET_JOB,
    JOB_LEVEL,
    RANGE_END,
    RANGE_START,
    contiguous_blocks,
    range_tags,
)
from pipelines.instance import open_instance, process_tags  # noqa: F401 - open_instance re-exported
from pipelines.partitions import (
    captures,
    devices,
    new_partition_requests,
    registered_keys,
)
from pipelines.resources import LabArchive

QUIET = {"loggers": {"console": {"config": {"log_level": "WARNING"}}}}


def register_landed_runs(instance: dg.DagsterInstance, archive: LabArchive) -> list[str]:
    """Register every completed run of the archive not registered yet (as the landing sensor does, without
    requesting runs); returns the new capture keys."""
    new, requests = new_partition_requests(instance, archive.complete_runs())
    for req in requests:
        instance.add_dynamic_partitions(req.partitions_def_name, list(req.partition_keys))
    return new


@dataclass
class LaunchSummary:
    runs: list[tuple[str, str, bool]] = field(default_factory=list)  # (job, run id, success)
    succeeded_steps: set[str] = field(default_factory=set)  # step keys (= stage names) that succeeded in some run
    attempted: set[tuple[str, str]] = field(default_factory=set)  # (stage, partition) whose step succeeded
    warnings: list[str] = field(default_factory=list)  # failed non-blocking checks: "<asset> <check>: <what>"

    @property
    def success(self) -> bool:
        return all(ok for _, _, ok in self.runs)


def run_job(defs: dg.Definitions, instance: dg.DagsterInstance, job_name: str, tags: dict | None = None,
            asset_selection=None, quiet: bool = True, summary: LaunchSummary | None = None) -> LaunchSummary:
    """One in-process run of ``job_name`` (optionally a subset of its assets) on ``instance``."""
    summary = summary if summary is not None else LaunchSummary()
    res = defs.resolve_job_def(job_name).execute_in_process(
        instance=instance, run_config=QUIET if quiet else None, tags={**(tags or {}), **process_tags()},
        asset_selection=asset_selection,
        raise_on_error=False)
    summary.runs.append((job_name, res.run_id, res.success))
    steps = {e.step_key for e in res.all_events if e.is_step_success and e.step_key}
    summary.succeeded_steps |= steps
    summary.warnings += failed_checks(res)
    keys = _covered_keys(instance, job_name, tags or {})
    summary.attempted |= {(step, k) for step in steps for k in keys}
    return summary


def failed_checks(res) -> list[str]:
    """One line per failed asset-check evaluation of a run: asset, check and the failures it lists."""
    out = []
    for e in res.all_events:
        if e.event_type_value != "ASSET_CHECK_EVALUATION":
            continue
        ev = e.event_specific_data
        if ev.passed:
            continue
        md = ev.metadata or {}
        what = md.get("failures") or md.get("problems") or md.get("flagged")
        what = getattr(what, "value", what) or ev.description or ""
        out.append(f"{ev.asset_key.to_user_string()} {ev.check_name}: {str(what).replace(chr(10), '; ')}"[:300])
    return out


def _covered_keys(instance: dg.DagsterInstance, job_name: str, tags: dict) -> list[str]:
    """Partition keys a run of ``job_name`` with ``tags`` covers (the fleet key for unpartitioned jobs)."""
    if RANGE_START not in tags:
        return [FLEET_KEY]
    name = captures.name if JOB_LEVEL.get(job_name) == "capture" else devices.name
    ordered = list(instance.get_dynamic_partitions(name))
    try:
        return ordered[ordered.index(tags[RANGE_START]): ordered.index(tags[RANGE_END]) + 1]
    except ValueError:
        return []


def execute(defs: dg.Definitions, instance: dg.DagsterInstance, job_name: str, partitions_name: str | None,
            keys: set[str] | None = None, quiet: bool = True, summary: LaunchSummary | None = None) -> LaunchSummary:
    """Run ``job_name`` over ``keys`` (all registered partitions when None), one run per contiguous block."""
    summary = summary if summary is not None else LaunchSummary()
    if partitions_name is None:
        return run_job(defs, instance, job_name, quiet=quiet, summary=summary)
    ordered = list(instance.get_dynamic_partitions(partitions_name))
    wanted = set(ordered) if keys is None else set(keys) & set(ordered)
    for first, last in contiguous_blocks(ordered, wanted):
        run_job(defs, instance, job_name, tags=range_tags(first, last), quiet=quiet, summary=summary)
    return summary


def materialize_archive(defs: dg.Definitions, instance: dg.DagsterInstance, capture_keys: set[str] | None = None,
                        device_keys: set[str] | None = None, quiet: bool = True,
                        record_outcomes: bool = True) -> LaunchSummary:
    """The main job: per-run stages, then per-device stages, then the fleet stage.

    With ``record_outcomes``, partitions whose stage ran but produced no output are noted for reprocessing
    (``assets_lib.stages.plan.record_no_output``), so an unchanged archive has nothing stale afterwards."""
    job_names = {j.name for j in defs.resolve_all_job_defs()}
    summary = LaunchSummary()
    if CAPTURES_JOB in job_names:
        execute(defs, instance, CAPTURES_JOB, captures.name, capture_keys, quiet, summary)
    if DEVICES_JOB in job_names:
        execute(defs, instance, DEVICES_JOB, devices.name, device_keys, quiet, summary)
    if FLEET_JOB in job_names:
        execute(defs, instance, FLEET_JOB, None, None, quiet, summary)
    if record_outcomes and capture_keys is None and device_keys is None:
        store = defs.resources["store"].store
        archive = defs.resources["archive"].archive
        plan = plan_reprocess(defs.resources["stages"], store, archive, *registered_keys(instance), use_ledger=False)
        record_no_output(store, plan, summary.attempted)
    return summary
