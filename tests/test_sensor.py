"""The capture (landing) sensor and the follow-up sensors, on real instances and real runs.

Sensors are evaluated by calling the decorated function with ``build_sensor_context`` (docs/dagster.md 6.2), and
the dynamic partition requests are applied to the instance as the daemon would.
"""

from __future__ import annotations

import json
import os
import shutil
import tempfile
import time
import warnings
from pathlib import Path

import dagster as dg
import pytest
from prod_helpers import (
    DEVICES,
    QUIET,
    SHM,
    apply_partition_requests,
    small_run,
    temp_instance,
    toy_definitions,
    toy_stages,
    write_small_archive,
)

from assets_lib.sim.simulator import write_run
from pipelines.defs.sensors import TRIGGER_TAG, landing_sensor
from pipelines.jobs import RANGE_END, RANGE_START
from pipelines.partitions import captures, devices
from pipelines.resources import LabArchive

warnings.filterwarnings("ignore")


@pytest.fixture
def workdir():
    d = Path(tempfile.mkdtemp(prefix="imulab-sensor-", dir=SHM))
    yield d
    shutil.rmtree(d, ignore_errors=True)


def tick(instance, archive: LabArchive, cursor=None, apply=True):
    # used as a context manager so its resources (and the instance context they enter) close in order
    with dg.build_sensor_context(instance=instance, cursor=cursor, resources={"archive": archive}) as context:
        result = landing_sensor(context)
    if apply:
        apply_partition_requests(instance, result)
    return result


def requested(result) -> list[tuple[str, str]]:
    return [(r.tags[RANGE_START], r.tags[RANGE_END]) for r in (result.run_requests or [])]


def keys_in(instance, first, last) -> list[str]:
    order = list(instance.get_dynamic_partitions(captures.name))
    return order[order.index(first): order.index(last) + 1]


def land(landing: Path, device: str, grade: str, run_id: str, seed: int = 11, complete: bool = True) -> str:
    d = write_run(small_run(device, grade, run_id, seed=seed), landing)
    if not complete:
        (d / "_COMPLETE").unlink()
    return f"{device}__{run_id}"


def test_only_completed_runs_and_never_twice(workdir):
    landing = workdir / "landing"
    keys = write_small_archive(landing)
    partial = land(landing, "TST-C", "consumer", "pc00-pos24", complete=False)  # capture job still writing
    archive = LabArchive(landing_dir=str(landing))
    with temp_instance() as inst:
        r1 = tick(inst, archive)
        assert requested(r1) == [(keys[0], keys[-1])]
        assert keys_in(inst, keys[0], keys[-1]) == keys
        assert partial not in inst.get_dynamic_partitions(captures.name)
        assert sorted(inst.get_dynamic_partitions(devices.name)) == ["TST-A", "TST-B"]

        r2 = tick(inst, archive, r1.cursor)  # re-tick: nothing new
        assert not r2.run_requests and r2.skip_reason

        (landing / "TST-C" / "pc00-pos24" / "_COMPLETE").write_text("")  # the capture job finishes
        r3 = tick(inst, archive, r2.cursor, apply=False)
        assert requested(r3) == [(partial, partial)]
        again = tick(inst, archive, r2.cursor, apply=False)  # the daemon re-evaluates the same tick
        assert [r.run_key for r in again.run_requests] == [r.run_key for r in r3.run_requests]
        apply_partition_requests(inst, r3)
        assert "TST-C" in inst.get_dynamic_partitions(devices.name)
        assert not tick(inst, archive, r3.cursor).run_requests
        # every run was requested exactly once over the whole sequence
        covered = [k for f, l in requested(r1) + requested(r3) for k in keys_in(inst, f, l)]
        assert sorted(covered) == sorted(keys + [partial])


class RacingArchive(LabArchive):
    """A landing folder where a capture job finishes a run right after the sensor scanned it."""

    def complete_runs(self):
        seen = super().complete_runs()
        late = Path(self.landing_dir) / "TST-C" / "pc09-pos24"
        if not late.exists():
            land(Path(self.landing_dir), "TST-C", "consumer", "pc09-pos24")
        return seen


def test_runs_landing_during_a_tick_or_with_old_mtimes_are_picked_up(workdir):
    landing = workdir / "landing"
    keys = write_small_archive(landing)
    racing = RacingArchive(landing_dir=str(landing))
    with temp_instance() as inst:
        r1 = tick(inst, racing)
        assert keys_in(inst, *requested(r1)[0]) == keys  # the late run was not seen by this scan ...
        r2 = tick(inst, racing, r1.cursor)
        assert requested(r2) == [("TST-C__pc09-pos24", "TST-C__pc09-pos24")]  # ... and is by the next one

        # a run copied from elsewhere with its old timestamps preserved (cp -p, rsync -a)
        src = workdir / "elsewhere"
        run_dir = write_run(small_run("TST-B", "navigation", "pc07-pos24", seed=3), src)
        old = time.time() - 400 * 86400
        for p in [*run_dir.iterdir(), run_dir, run_dir.parent]:
            os.utime(p, (old, old))
        shutil.copytree(run_dir, landing / "TST-B" / "pc07-pos24", copy_function=shutil.copy2)
        assert (landing / "TST-B" / "pc07-pos24" / "_COMPLETE").stat().st_mtime < time.time() - 300 * 86400
        r3 = tick(inst, racing, r2.cursor)
        assert requested(r3) == [("TST-B__pc07-pos24", "TST-B__pc07-pos24")]
        assert not tick(inst, racing, r3.cursor).run_requests


def test_restart_with_stored_cursor_and_lost_ticks(workdir):
    landing = workdir / "landing"
    keys = write_small_archive(landing)
    archive = LabArchive(landing_dir=str(landing))
    home = Path(tempfile.mkdtemp(prefix="imulab-home-", dir=SHM))
    (home / "dagster.yaml").write_text("telemetry:\n  enabled: false\n")
    try:
        with dg.DagsterInstance.from_config(str(home)) as inst:
            r1 = tick(inst, archive)
            stored = r1.cursor
        # daemon restarts; two runs land meanwhile
        new = sorted([land(landing, "TST-C", "consumer", "pc00-pos24"), land(landing, "TST-A", "tactical", "pc05-pos24")])
        with dg.DagsterInstance.from_config(str(home)) as inst:
            r2 = tick(inst, archive, stored)
            assert [keys_in(inst, f, l) for f, l in requested(r2)] == [new]
            assert list(inst.get_dynamic_partitions(captures.name)) == keys + new  # nothing duplicated

            # a tick that registered partitions but died before launching its run: the daemon keeps the old
            # cursor, and the next tick asks for those partitions again (same run key: launched at most once)
            lost = land(landing, "TST-C", "consumer", "pc06-pos24")
            r3 = tick(inst, archive, r2.cursor)  # partitions applied, cursor r3.cursor lost
            r4 = tick(inst, archive, r2.cursor)
            assert requested(r4) == [(lost, lost)] == requested(r3)
            assert [r.run_key for r in r4.run_requests] == [r.run_key for r in r3.run_requests]

            # a new sensor without cursor: registered partitions the ingest stage never materialized are requested
            r5 = tick(inst, archive, None)
            assert sorted(k for f, l in requested(r5) for k in keys_in(inst, f, l)) == sorted(keys + new + [lost])
    finally:
        shutil.rmtree(home, ignore_errors=True)


def test_run_request_materializes_exactly_the_new_partitions(workdir):
    landing, store = workdir / "landing", workdir / "store"
    first = write_small_archive(landing, devices=DEVICES[:1])
    archive = LabArchive(landing_dir=str(landing))
    with toy_stages() as toys, temp_instance() as inst:
        defs = toy_definitions(landing, store, toys)
        job = defs.resolve_job_def("calibrate_captures")
        r1 = tick(inst, archive)
        (req,) = r1.run_requests
        assert job.execute_in_process(instance=inst, tags=req.tags, run_config=QUIET).success
        second = sorted(land(landing, "TST-B", "navigation", f"pc0{i}-pos24", seed=i) for i in range(3))
        r2 = tick(inst, archive, r1.cursor)
        (req2,) = r2.run_requests
        assert keys_in(inst, req2.tags[RANGE_START], req2.tags[RANGE_END]) == second
        res = job.execute_in_process(instance=inst, tags=req2.tags, run_config=QUIET)
        assert res.success
        mats = {e.partition for e in res.get_asset_materialization_events() if e.asset_key == dg.AssetKey("ingested_run")}
        assert mats == set(second)
        assert set(inst.get_materialized_partitions(dg.AssetKey("ingested_run"))) == set(first + second)
        assert sorted(p.name for p in (store / "ingested_run").iterdir()) == sorted(first + second)
        # without a cursor (e.g. `imulab run`), partitions already materialized are not requested again
        assert not tick(inst, archive, None).run_requests


def test_follow_up_sensors_chain_captures_devices_fleet(workdir):
    landing, store = workdir / "landing", workdir / "store"
    keys = write_small_archive(landing, devices=DEVICES[:3], runs_per_device=1)
    archive = LabArchive(landing_dir=str(landing))
    with toy_stages() as toys, temp_instance() as inst:
        defs = toy_definitions(landing, store, toys)
        to_devices = defs.resolve_sensor_def("captures_to_devices")
        to_fleet = defs.resolve_sensor_def("devices_to_fleet")
        c_dev = to_devices(dg.build_sensor_context(instance=inst)).cursor  # first tick starts from "now"
        c_fleet = to_fleet(dg.build_sensor_context(instance=inst)).cursor

        tick(inst, archive)
        order = list(inst.get_dynamic_partitions(captures.name))
        assert order == keys
        # a run over the first two captures only (devices TST-A, TST-B)
        cap = defs.resolve_job_def("calibrate_captures").execute_in_process(
            instance=inst, tags={RANGE_START: keys[0], RANGE_END: keys[1]}, run_config=QUIET)
        assert cap.success
        r = to_devices(dg.build_sensor_context(instance=inst, cursor=c_dev))
        (req,) = r.run_requests
        assert req.job_name == "calibrate_devices"
        assert (req.tags[RANGE_START], req.tags[RANGE_END]) == ("TST-A", "TST-B")
        assert cap.run_id in req.run_key and req.tags[TRIGGER_TAG] == cap.run_id
        assert not to_devices(dg.build_sensor_context(instance=inst, cursor=r.cursor)).run_requests
        assert not to_fleet(dg.build_sensor_context(instance=inst, cursor=c_fleet)).run_requests

        dev = defs.resolve_job_def("calibrate_devices").execute_in_process(instance=inst, tags=req.tags, run_config=QUIET)
        assert dev.success
        assert sorted(p.name for p in (store / "toy_device").iterdir()) == ["TST-A", "TST-B"]
        rf = to_fleet(dg.build_sensor_context(instance=inst, cursor=c_fleet))
        (freq,) = rf.run_requests
        assert freq.job_name == "fleet_summary" and dev.run_id in freq.run_key
        assert defs.resolve_job_def("fleet_summary").execute_in_process(instance=inst, tags=freq.tags, run_config=QUIET).success
        fleet = __import__("pandas").read_parquet(next((store / "toy_fleet" / "fleet").glob("*/fleet.parquet")))
        assert sorted(fleet["device"]) == ["TST-A", "TST-B"]
        assert not to_fleet(dg.build_sensor_context(instance=inst, cursor=rf.cursor)).run_requests
        assert json.loads(r.cursor)["after"] > json.loads(c_dev)["after"]
