"""Launch batched runs from Python (the CLI and tests): register landed runs, then one run per level.

Order: every per-run stage over all capture partitions in one run, then every per-device stage over all device
partitions in one run, then the fleet stage. Reused versions cost only a lookup, so running over everything is
cheap; ``reprocess`` narrows the ranges to stale partitions.
"""

import os
from dataclasses import dataclass, field
from pathlib import Path

import dagster as dg

from pipelines.defs.sensors import landing_sensor, range_tags
from pipelines.partitions import captures, devices
from pipelines.resources import LabArchive

QUIET = {"loggers": {"console": {"config": {"log_level": "WARNING"}}}}


def open_instance(dagster_home: str | os.PathLike | None = None) -> dg.DagsterInstance:
    """A persistent instance in ``dagster_home`` (or $DAGSTER_HOME), so ``dagster dev`` shows the same runs."""
    home = dagster_home or os.environ.get("DAGSTER_HOME")
    if home is None:
        raise ValueError("no Dagster home given and DAGSTER_HOME is not set")
    home = Path(home).resolve()
    home.mkdir(parents=True, exist_ok=True)
    cfg = home / "dagster.yaml"
    if not cfg.exists():
        cfg.write_text("telemetry:\n  enabled: false\n")
    return dg.DagsterInstance.from_config(str(home))


def register_landed_runs(instance: dg.DagsterInstance, archive: LabArchive) -> list[str]:
    """Evaluate the landing sensor once and apply its partition requests; returns the new capture keys."""
    result = landing_sensor(dg.build_sensor_context(instance=instance, resources={"archive": archive}))
    new: list[str] = []
    for req in getattr(result, "dynamic_partitions_requests", None) or []:
        instance.add_dynamic_partitions(req.partitions_def_name, list(req.partition_keys))
        if req.partitions_def_name == captures.name:
            new += list(req.partition_keys)
    return new


@dataclass
class LaunchSummary:
    runs: list[tuple[str, str, bool]] = field(default_factory=list)  # (job, run id, success)

    @property
    def success(self) -> bool:
        return all(ok for _, _, ok in self.runs)


def _contiguous_blocks(ordered: list[str], wanted: set[str]) -> list[tuple[str, str]]:
    blocks, start, prev = [], None, None
    for k in ordered:
        if k in wanted:
            start = start or k
            prev = k
        elif start:
            blocks.append((start, prev))
            start = None
    if start:
        blocks.append((start, prev))
    return blocks


def execute(defs: dg.Definitions, instance: dg.DagsterInstance, job_name: str, partitions_name: str | None,
            keys: set[str] | None = None, quiet: bool = True, summary: LaunchSummary | None = None) -> LaunchSummary:
    """Run ``job_name`` over ``keys`` (all registered partitions when None), one run per contiguous block."""
    summary = summary or LaunchSummary()
    job = defs.resolve_job_def(job_name)
    cfg = QUIET if quiet else None
    if partitions_name is None:
        res = job.execute_in_process(instance=instance, run_config=cfg, raise_on_error=False)
        summary.runs.append((job_name, res.run_id, res.success))
        return summary
    ordered = list(instance.get_dynamic_partitions(partitions_name))
    wanted = set(ordered) if keys is None else set(keys) & set(ordered)
    for first, last in _contiguous_blocks(ordered, wanted):
        res = job.execute_in_process(instance=instance, run_config=cfg, tags=range_tags(first, last), raise_on_error=False)
        summary.runs.append((job_name, res.run_id, res.success))
    return summary


def materialize_archive(defs: dg.Definitions, instance: dg.DagsterInstance, capture_keys: set[str] | None = None,
                        device_keys: set[str] | None = None, quiet: bool = True) -> LaunchSummary:
    """The main job: per-run stages, then per-device stages, then the fleet stage."""
    summary = execute(defs, instance, "calibrate_captures", captures.name, capture_keys, quiet)
    job_names = {j.name for j in defs.resolve_all_job_defs()}
    if "calibrate_devices" in job_names:
        execute(defs, instance, "calibrate_devices", devices.name, device_keys, quiet, summary)
    if "fleet_summary" in job_names:
        execute(defs, instance, "fleet_summary", None, None, quiet, summary)
    return summary
