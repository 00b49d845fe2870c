"""Jobs: one per partition level (every capture stage over a range of captures, every device stage over a range
of devices, the fleet stage), and the range tags with which a single run covers a block of partitions
(``BackfillPolicy.single_run``: one run per partition costs seconds; docs/dagster.md 4)."""

from __future__ import annotations

import dagster as dg

from assets_lib.stages.engine import StageGraph

RANGE_START = "dagster/asset_partition_range_start"
RANGE_END = "dagster/asset_partition_range_end"
PARTITION_TAG = "dagster/partition"

CAPTURES_JOB = "calibrate_captures"
DEVICES_JOB = "calibrate_devices"
FLEET_JOB = "fleet_summary"
JOB_LEVEL = {CAPTURES_JOB: "capture", DEVICES_JOB: "device", FLEET_JOB: "fleet"}
LEVEL_JOB = {level: job for job, level in JOB_LEVEL.items()}
_DESCRIPTIONS = {
    CAPTURES_JOB: "Every per-run stage for a batch of captured runs (one run per partition range).",
    DEVICES_JOB: "Per-device stages (repeatability, records) over a range of devices.",
    FLEET_JOB: "Fleet-wide coefficient drift.",
}


def range_tags(first: str, last: str) -> dict[str, str]:
    return {RANGE_START: first, RANGE_END: last}


def contiguous_blocks(ordered, wanted) -> list[tuple[str, str]]:
    """(first, last) of each maximal run of ``wanted`` keys in ``ordered`` (a partition range is contiguous)."""
    wanted = set(wanted)
    blocks, start, prev = [], None, None
    for k in ordered:
        if k in wanted:
            start = k if start is None else start
            prev = k
        elif start is not None:
            blocks.append((start, prev))
            start = None
    if start is not None:
        blocks.append((start, prev))
    return blocks


def stage_jobs(graph: StageGraph) -> list:
    """One asset job per level that has stages."""
    out = []
    for job, level in JOB_LEVEL.items():
        names = [s.name for s in graph.at_level(level)]
        if names:
            out.append(dg.define_asset_job(job, selection=dg.AssetSelection.assets(*names), description=_DESCRIPTIONS[job]))
    return out
