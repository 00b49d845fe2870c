"""Reprocessing: stale partitions per stage from the registry, batched runs over contiguous blocks, the weekly
schedules, and ``imulab reprocess``. Real Dagster runs on a small simulated archive with toy stages at every level.
"""

from __future__ import annotations

import shutil
import tempfile
import warnings
from pathlib import Path

import dagster as dg
import pandas as pd
import pytest
from prod_helpers import (
    SHM,
    TOY_STAGES,
    temp_instance,
    toy_definitions,
    toy_stages,
    tree_digest,
    write_realistic_archive,
    write_small_archive,
)

from assets_lib.stages import plan as planning
from assets_lib.stages.spec import SOURCE_TAG, StageOutput, stage
from assets_lib.store import LandingArchive, VersionedStore, split_capture_key
from pipelines import reprocess
from pipelines.jobs import RANGE_END, RANGE_START
from pipelines.launch import materialize_archive, register_landed_runs
from pipelines.resources import LabArchive, ParquetStore

warnings.filterwarnings("ignore")
TOY_CHAIN = {"toy_capture_a", "toy_capture_b", "toy_device", "toy_fleet"}


@pytest.fixture(scope="module")
def pristine_archive():
    """The lab's archive: written once, never modified by imulab (tests modify copies)."""
    d = Path(tempfile.mkdtemp(prefix="imulab-archive-", dir=SHM))
    keys = write_small_archive(d / "landing")
    yield d / "landing", keys
    shutil.rmtree(d, ignore_errors=True)


@pytest.fixture
def workdir():
    d = Path(tempfile.mkdtemp(prefix="imulab-reproc-", dir=SHM))
    yield d
    shutil.rmtree(d, ignore_errors=True)


def setup(instance, defs, landing):
    register_landed_runs(instance, LabArchive(landing_dir=str(landing)))
    summary = materialize_archive(defs, instance)
    assert summary.success and summary.runs
    return summary


def plan_of(instance, landing, store, graph) -> planning.ReprocessPlan:
    return reprocess.plan_for_instance(instance, graph, VersionedStore(store), LandingArchive(Path(landing)))


def stale_set(plan) -> set[tuple[str, str]]:
    return {(s.stage, s.key) for s in plan.stale if s.stage in set(TOY_STAGES) | {"ingested_run"}}


def schedule_requests(defs, name, instance, landing, store):
    with dg.build_schedule_context(instance=instance, resources={
            "store": ParquetStore(root=str(store)), "archive": LabArchive(landing_dir=str(landing))}) as ctx:
        out = defs.resolve_schedule_def(name)(ctx)
    return [] if isinstance(out, dg.SkipReason) else list(out)


def copy_landing(src: Path, dst: Path) -> Path:
    shutil.copytree(src, dst, copy_function=shutil.copy2)
    return dst


def bump_raw(landing: Path, key: str) -> None:
    """A lab re-lands a run: one sample of its IMU file changes."""
    dev, run = split_capture_key(key)
    p = landing / dev / run / "imu.parquet"
    df = pd.read_parquet(p)
    df.loc[len(df) // 2, "gyro_x"] += 3
    df.to_parquet(p, index=False)


def test_nothing_changed_nothing_runs(pristine_archive, workdir):
    src, keys = pristine_archive
    landing, store = copy_landing(src, workdir / "landing"), workdir / "store"
    with toy_stages() as toys, temp_instance() as inst:
        defs = toy_definitions(landing, store, toys)
        setup(inst, defs, landing)
        before, runs_before = tree_digest(store), inst.get_runs_count()
        plan = plan_of(inst, landing, store, toys)
        assert plan.empty and plan.up_to_date >= len(keys) * 4 + 3
        for name in ("reprocess_captures_weekly", "reprocess_devices_weekly", "reprocess_fleet_weekly"):
            assert schedule_requests(defs, name, inst, landing, store) == []
        summary = reprocess.run_plan(defs, inst, plan, VersionedStore(store))
        assert summary.runs == [] and inst.get_runs_count() == runs_before
        assert tree_digest(store) == before  # not a byte written


def test_code_version_change_recomputes_that_stage_and_downstream_only(pristine_archive, workdir):
    src, keys = pristine_archive
    landing, store = copy_landing(src, workdir / "landing"), workdir / "store"
    devices = sorted({split_capture_key(k)[0] for k in keys})
    vstore = VersionedStore(store)
    with toy_stages("1") as toys, temp_instance() as inst:
        setup(inst, toy_definitions(landing, store, toys), landing)
        old = {(s, k): vstore.current_version(s, k) for s in ("toy_capture_a", "ingested_run", "toy_side") for k in keys}
        with toy_stages("2") as toys2:  # a new release of toy_capture_a's code
            defs2 = toy_definitions(landing, store, toys2)
            plan = plan_of(inst, landing, store, toys2)
            expected = ({(s, k) for s in ("toy_capture_a", "toy_capture_b") for k in keys}
                        | {("toy_device", d) for d in devices} | {("toy_fleet", "fleet")})
            assert stale_set(plan) == expected
            assert {s.stage for s in plan.stale} - TOY_CHAIN == set()  # nothing else in the code location
            reasons = {(s.stage, s.key): s.reason for s in plan.stale}
            reason = reasons[("toy_capture_a", keys[0])]  # declared version plus the source digest
            assert reason.startswith(f"code version 1{SOURCE_TAG}") and f" -> 2{SOURCE_TAG}" in reason, reason
            assert reasons[("toy_capture_b", keys[0])].startswith("upstream changed: toy_capture_a/")

            # the weekly schedules: one batched capture run (all captures are contiguous) with only the stale
            # stages; devices and fleet are left to the follow-up sensors until the captures are rewritten
            (req,) = schedule_requests(defs2, "reprocess_captures_weekly", inst, landing, store)
            assert (req.tags[RANGE_START], req.tags[RANGE_END]) == (keys[0], keys[-1])
            assert set(req.asset_selection) == {dg.AssetKey("toy_capture_a"), dg.AssetKey("toy_capture_b")}
            assert schedule_requests(defs2, "reprocess_devices_weekly", inst, landing, store) == []
            assert schedule_requests(defs2, "reprocess_fleet_weekly", inst, landing, store) == []

            summary = reprocess.run_plan(defs2, inst, plan, vstore)
            assert summary.success and [j for j, _, _ in summary.runs] == ["calibrate_captures", "calibrate_devices", "fleet_summary"]
            assert plan_of(inst, landing, store, toys2).empty
            for k in keys:
                assert vstore.current_version("toy_capture_a", k) == plan.expected[("toy_capture_a", k)] != old[("toy_capture_a", k)]
                assert len(vstore.versions("toy_capture_a", k)) == 2 and len(vstore.versions("toy_capture_b", k)) == 2
                for s in ("ingested_run", "toy_side"):
                    assert vstore.versions(s, k) == [old[(s, k)]]
                # audit: the old version is still there and readable
                assert vstore.read_meta("toy_capture_a", k, old[("toy_capture_a", k)])["code_version"].split(SOURCE_TAG)[0] == "1"
                assert not vstore.read("toy_capture_a", k, "means", old[("toy_capture_a", k)]).empty
            assert all(o == "rewritten" for _, o in planning.outcome(vstore, plan))


def test_relanded_raw_file_recomputes_only_that_partition(pristine_archive, workdir):
    src, keys = pristine_archive
    landing, store = copy_landing(src, workdir / "landing"), workdir / "store"
    vstore = VersionedStore(store)
    src_digest = tree_digest(src)
    with toy_stages() as toys, temp_instance() as inst:
        defs = toy_definitions(landing, store, toys)
        setup(inst, defs, landing)
        before = {(s, k): vstore.current_version(s, k) for s in ("ingested_run", "toy_capture_a", "toy_side") for k in keys}
        changed = [keys[0], keys[2]]  # not adjacent: two blocks
        for k in changed:
            bump_raw(landing, k)
        plan = plan_of(inst, landing, store, toys)
        expected = ({(s, k) for s in ("ingested_run", "toy_capture_a", "toy_capture_b", "toy_side") for k in changed}
                    | {("toy_device", split_capture_key(k)[0]) for k in changed} | {("toy_fleet", "fleet")})
        assert stale_set(plan) == expected
        assert {s.reason for s in plan.stale if s.stage == "ingested_run"} == {"raw input changed: imu.parquet"}

        reqs = schedule_requests(defs, "reprocess_captures_weekly", inst, landing, store)
        assert sorted((r.tags[RANGE_START], r.tags[RANGE_END]) for r in reqs) == [(k, k) for k in changed]
        job = defs.resolve_job_def("calibrate_captures")
        for r in reqs:
            assert job.execute_in_process(instance=inst, tags=r.tags, asset_selection=r.asset_selection).success
        # captures rewritten: now the device schedule asks for both devices in one run, then the fleet schedule
        (dreq,) = schedule_requests(defs, "reprocess_devices_weekly", inst, landing, store)
        assert (dreq.tags[RANGE_START], dreq.tags[RANGE_END]) == ("TST-A", "TST-B")
        assert defs.resolve_job_def("calibrate_devices").execute_in_process(instance=inst, tags=dreq.tags).success
        (freq,) = schedule_requests(defs, "reprocess_fleet_weekly", inst, landing, store)
        assert defs.resolve_job_def("fleet_summary").execute_in_process(instance=inst, tags=freq.tags).success
        assert plan_of(inst, landing, store, toys).empty

        for (s, k), v in before.items():
            if k in changed:
                assert vstore.versions(s, k) == sorted([v, vstore.current_version(s, k)]) and vstore.current_version(s, k) != v
                assert vstore.read_meta(s, k, v)["partition"] == k  # the old version stays readable
            else:
                assert vstore.versions(s, k) == [v]
        old_imu = vstore.read("ingested_run", changed[0], "imu", before[("ingested_run", changed[0])])
        new_imu = vstore.read("ingested_run", changed[0], "imu")
        assert (old_imu["gyro_x_radps"] != new_imu["gyro_x_radps"]).sum() == 1
    assert tree_digest(src) == src_digest  # the lab's archive itself was never touched


def test_no_output_partitions_are_not_requested_again(pristine_archive, workdir):
    """A stage that produces nothing for a partition (compute returns None) is not retried until its inputs or
    code change, so an unchanged archive has nothing stale after `imulab run`."""
    src, keys = pristine_archive
    landing, store = copy_landing(src, workdir / "landing"), workdir / "store"
    with toy_stages() as toys, temp_instance() as inst:
        @stage("toy_picky", level="capture", group="toy", code_version="1", upstream=("ingested_run",))
        def toy_picky(key, inputs):
            """Toy: output only for the TST-A runs."""
            return StageOutput(tables={"x": pd.DataFrame({"a": [1]})}) if key.startswith("TST-A") else None

        graph = toys.with_stages(toy_picky)
        defs = toy_definitions(landing, store, graph)
        setup(inst, defs, landing)
        plan = plan_of(inst, landing, store, graph)
        assert plan.empty and sorted(k for s, k, _ in plan.no_output) == [k for k in keys if k.startswith("TST-B")]
        bump_raw(landing, keys[-1])  # new input for a TST-B run: tried again
        plan = plan_of(inst, landing, store, graph)
        assert ("toy_picky", keys[-1]) in {(s.stage, s.key) for s in plan.stale}
        assert reprocess.run_plan(defs, inst, plan, VersionedStore(store)).success
        assert plan_of(inst, landing, store, graph).empty


def test_cli_reprocess(workdir):
    """`imulab reprocess` on the real code location (every science stage) and a short but realistic archive."""
    from click.testing import CliRunner

    from imulab.commands.reprocess import command

    landing = workdir / "landing"
    keys = write_realistic_archive(landing)
    args = ["--archive", str(landing), "--data-dir", str(workdir)]
    runner = CliRunner()
    first = runner.invoke(command, args)
    assert first.exit_code == 0, first.output
    assert f"registered {len(keys)} newly landed runs" in first.output and "never materialized" in first.output
    assert "rewritten ingested_run/" in first.output
    assert "nothing to reprocess" in runner.invoke(command, args).output
    bump_raw(landing, keys[1])
    dry = runner.invoke(command, [*args, "--dry-run"])
    assert dry.exit_code == 0 and f"{keys[1]}: raw input changed: imu.parquet" in dry.output
    assert f"calibrate_captures [{keys[1]}..{keys[1]}]" in dry.output and "dry run: nothing executed" in dry.output
    out = runner.invoke(command, args)
    assert out.exit_code == 0, out.output
    assert f"rewritten ingested_run/{keys[1]}" in out.output and "rewrote" in out.output
    assert "nothing to reprocess" in runner.invoke(command, args).output
