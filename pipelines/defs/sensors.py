"""Capture jobs are upstream: the landing sensor registers every completed run as a ``captures`` partition and
asks for one batched run over the new ones.

Idempotency comes from the data, not the clock: a run is new when its partition is not registered yet, and the
run request's ``run_key`` is a hash of the new partition keys, so a re-tick never launches the same work twice.
A run that lands while a tick scans is simply seen by the next tick. The cursor records a digest of the
completed runs seen (for the UI and for cheap "nothing changed" ticks), never a wall-clock time.
"""


import hashlib
import json

import dagster as dg

from pipelines.partitions import captures, devices, split_capture_key
from pipelines.resources import LabArchive

RANGE_START = "dagster/asset_partition_range_start"
RANGE_END = "dagster/asset_partition_range_end"


def range_tags(first: str, last: str) -> dict[str, str]:
    return {RANGE_START: first, RANGE_END: last}


def landing_digest(keys) -> str:
    return hashlib.sha256("\n".join(sorted(keys)).encode()).hexdigest()[:16]


@dg.sensor(job_name="calibrate_captures", minimum_interval_seconds=30, default_status=dg.DefaultSensorStatus.RUNNING)
def landing_sensor(context: dg.SensorEvaluationContext, archive: LabArchive):
    """Register completed runs (``_COMPLETE`` present) as partitions and request one batched run for them."""
    complete = archive.complete_runs()
    digest = landing_digest(complete)
    known = set(context.instance.get_dynamic_partitions(captures.name))
    new = sorted(k for k in complete if k not in known)
    cursor = json.dumps({"complete_runs": len(complete), "digest": digest})
    if not new:
        return dg.SensorResult(skip_reason=f"no new completed runs ({len(complete)} known)", cursor=cursor)
    known_devices = set(context.instance.get_dynamic_partitions(devices.name))
    new_devices = sorted({split_capture_key(k)[0] for k in new} - known_devices)
    requests = [captures.build_add_request(new)]
    if new_devices:
        requests.append(devices.build_add_request(new_devices))
    return dg.SensorResult(
        dynamic_partitions_requests=requests,
        run_requests=[dg.RunRequest(run_key=f"landing-{landing_digest(new)}", tags=range_tags(new[0], new[-1]))],
        cursor=cursor,
    )

SENSORS = [landing_sensor]
