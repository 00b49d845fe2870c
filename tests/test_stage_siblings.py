"""Sibling reads (``StageSpec.siblings``): a capture stage reading a capture stage's partitions for every capture of
the SAME device (a device-wide prior, e.g. the bias-instability level of the device's static runs). A toy graph,
never registered: a root stage reading a value from the run folder, ``z_noise`` (static runs, a gate rejecting a
negative value) and ``a_fit`` (rate runs) reading ``z_noise`` as siblings. The names put the reader first in
alphabetical order, so a Dagster run that ordered the steps by name instead of by the sibling edge would fail.
Covered: versions, skip rules (missing, not applicable, rejected), the view's accessor, validation, the planning
cache, the reprocessing planner, the asset graph and a real batched Dagster run."""

from __future__ import annotations

import json
import shutil
import tempfile
import warnings
from pathlib import Path

import dagster as dg
import pandas as pd
import pytest
from prod_helpers import SHM, temp_instance, toy_definitions

from assets_lib.stages import graph_cache
from assets_lib.stages import plan as planning
from assets_lib.stages.engine import StageGraph, compute_partition, decide, sibling_keys
from assets_lib.stages.spec import Gate, StageOutput, StageSpec, stage
from assets_lib.store import LandingArchive, VersionedStore
from pipelines import reprocess
from pipelines.assets import stage_deps
from pipelines.launch import materialize_archive, register_landed_runs
from pipelines.partitions import registered_keys
from pipelines.resources import LabArchive

warnings.filterwarnings("ignore")


# ---------------------------------------------------------------------------------------------------------------
# The toy graph and archive
# ---------------------------------------------------------------------------------------------------------------
@stage("toy_raw", level="capture", group="toy", code_version="1")
def toy_raw(key, inputs):
    """Toy root: the value of the run folder's value.json."""
    v = json.loads((inputs.run_dir() / "value.json").read_text())["v"]
    return StageOutput(tables={"value": pd.DataFrame({"v": [float(v)]})})


def _not_negative(out: StageOutput) -> str | None:
    v = float(out.tables["noise"]["b"].iloc[0])
    return f"b = {v} < 0" if v < 0 else None


@stage("z_noise", level="capture", group="toy", code_version="1", upstream=("toy_raw",), applies_to=("static",),
       gates=(Gate("not_negative", _not_negative),))
def z_noise(key, inputs):
    """Toy sibling: a 'noise level' of a static run (its value)."""
    return StageOutput(tables={"noise": pd.DataFrame({"b": [inputs.table("toy_raw", "value")["v"].iloc[0]]})})


@stage("a_fit", level="capture", group="toy", code_version="1", upstream=("toy_raw",), applies_to=("rate",),
       siblings=("z_noise",))
def a_fit(key, inputs):
    """Toy reader: its own value and the noise level of every static run of its device."""
    sib = inputs.sibling_tables("z_noise", "noise")
    assert list(sib) == inputs.sibling_keys("z_noise")
    rows = [{"sibling": k, "b": float(t["b"].iloc[0])} for k, t in sib.items()]
    own = float(inputs.table("toy_raw", "value")["v"].iloc[0])
    return StageOutput(tables={"prior": pd.DataFrame(rows, columns=["sibling", "b"]),
                               "own": pd.DataFrame({"v": [own]})})


GRAPH = StageGraph([toy_raw, z_noise, a_fit])


def land(landing: Path, key: str, kind: str, value: float) -> None:
    """A toy run folder: its manifest (test kind), a value, the _COMPLETE marker."""
    dev, run = key.split("__")
    d = Path(landing) / dev / run
    d.mkdir(parents=True, exist_ok=True)
    (d / "manifest.json").write_text(json.dumps({"test_kind": kind}))
    (d / "value.json").write_text(json.dumps({"v": value}))
    (d / "_COMPLETE").write_text("")


#: A: two rate runs, two static runs, one run of another kind; B: a rate run and a static run the gate rejects;
#: C: a rate run and no static run
RUNS = {"A__r1": ("rate", 1.0), "A__r2": ("rate", 2.0), "A__s1": ("static", 10.0), "A__s2": ("static", 20.0),
        "A__m1": ("multiposition", 30.0), "B__r1": ("rate", 3.0), "B__s1": ("static", -5.0), "C__r1": ("rate", 4.0)}


@pytest.fixture
def workdir():
    d = Path(tempfile.mkdtemp(prefix="imulab-sib-", dir=SHM))
    yield d
    shutil.rmtree(d, ignore_errors=True)


def toy_world(workdir: Path, runs=RUNS):
    landing = workdir / "landing"
    for k, (kind, v) in runs.items():
        land(landing, k, kind, v)
    return VersionedStore(workdir / "store"), LandingArchive(landing)


def compute_all(store, archive, keys, graph=GRAPH) -> dict:
    return {(s.name, k): compute_partition(graph, s, k, store, archive) for s in graph for k in keys}


def fit_inputs(store, key) -> dict:
    return store.read_meta("a_fit", key)["inputs"]


# ---------------------------------------------------------------------------------------------------------------
# Engine
# ---------------------------------------------------------------------------------------------------------------
def test_sibling_versions_and_skip_rules(workdir):
    store, archive = toy_world(workdir)
    out = compute_all(store, archive, sorted(RUNS))
    status = {k: o.status for k, o in out.items()}
    assert status[("z_noise", "A__s1")] == "written" and status[("z_noise", "A__r1")] == "not applicable"
    assert status[("z_noise", "B__s1")] == "failed"  # rejected by its gate
    # every rate run gets its fit: a rejected sibling (B) or none at all (C) neither blocks nor waits
    assert all(status[("a_fit", k)] == "written" for k in ("A__r1", "A__r2", "B__r1", "C__r1"))
    ins = fit_inputs(store, "A__r1")
    assert ins == {"toy_raw/A__r1": store.current_version("toy_raw", "A__r1"),
                   "z_noise/A__s1": store.current_version("z_noise", "A__s1"),
                   "z_noise/A__s2": store.current_version("z_noise", "A__s2")}  # not A__m1 (not applicable), no B
    assert fit_inputs(store, "B__r1") == {"toy_raw/B__r1": store.current_version("toy_raw", "B__r1")}
    assert fit_inputs(store, "C__r1") == {"toy_raw/C__r1": store.current_version("toy_raw", "C__r1")}
    # the accessor gave the compute the device's static runs' tables, and only those
    assert store.read("a_fit", "A__r1", "prior").to_dict("records") == [{"sibling": "A__s1", "b": 10.0},
                                                                        {"sibling": "A__s2", "b": 20.0}]
    assert store.read("a_fit", "A__r2", "prior")["sibling"].tolist() == ["A__s1", "A__s2"]
    assert store.read("a_fit", "B__r1", "prior").empty and store.read("a_fit", "C__r1", "prior").empty
    assert sibling_keys("z_noise", "A__r1", store.partitions) == ["A__s1", "A__s2"]


def test_missing_sibling_is_skipped_then_enters_the_version(workdir):
    store, archive = toy_world(workdir)
    keys = sorted(RUNS)
    for k in keys:  # the sibling stage not computed yet: the reader computes without it
        compute_partition(GRAPH, toy_raw, k, store, archive)
    assert compute_partition(GRAPH, a_fit, "A__r1", store, archive).status == "written"
    first = store.current_version("a_fit", "A__r1")
    assert fit_inputs(store, "A__r1") == {"toy_raw/A__r1": store.current_version("toy_raw", "A__r1")}
    for k in keys:
        compute_partition(GRAPH, z_noise, k, store, archive)
    d = decide(GRAPH, a_fit, "A__r1", store, archive)
    assert d.status == "compute" and d.version != first and "z_noise/A__s1" in d.inputs


def test_sibling_added_changed_or_removed_changes_the_version_of_that_device_only(workdir):
    store, archive = toy_world(workdir)
    keys = sorted(RUNS)
    compute_all(store, archive, keys)
    before = {k: store.current_version("a_fit", k) for k in ("A__r1", "A__r2", "B__r1", "C__r1")}

    def versions(keys):
        compute_all(store, archive, keys)
        return {k: store.current_version("a_fit", k) for k in before}

    land(archive.landing_dir, "A__s3", "static", 30.0)  # added
    keys.append("A__s3")
    added = versions(keys)
    assert added["A__r1"] != before["A__r1"] and added["A__r2"] != before["A__r2"]
    assert added["B__r1"] == before["B__r1"] and added["C__r1"] == before["C__r1"]
    assert store.read("a_fit", "A__r1", "prior")["b"].tolist() == [10.0, 20.0, 30.0]

    land(archive.landing_dir, "A__s1", "static", 11.0)  # changed (re-landed)
    changed = versions(keys)
    assert changed["A__r1"] not in (added["A__r1"], before["A__r1"]) and changed["B__r1"] == before["B__r1"]

    land(archive.landing_dir, "A__s1", "static", -1.0)  # now rejected by its gate: removed from the inputs
    removed = versions(keys)
    assert removed["A__r1"] not in (changed["A__r1"], added["A__r1"])
    assert "z_noise/A__s1" not in fit_inputs(store, "A__r1")
    assert store.read("a_fit", "A__r1", "prior")["sibling"].tolist() == ["A__s2", "A__s3"]

    # removed from the partitions (the planner's view of a run that will not exist): gone from the inputs too
    d = decide(GRAPH, a_fit, "A__r1", store, archive,
               partitions_of=lambda s: [k for k in store.partitions(s) if k != "A__s3"])
    assert "z_noise/A__s3" not in d.inputs and d.version != removed["A__r1"]


def test_a_stage_may_read_its_upstream_as_a_sibling_too(workdir):
    """Own key through ``upstream`` (required), the device's other captures through ``siblings`` (optional)."""
    @stage("toy_pool", level="capture", group="toy", code_version="1", upstream=("toy_raw",), siblings=("toy_raw",))
    def toy_pool(key, inputs):
        """Toy: the device's values."""
        return StageOutput(tables={"v": pd.DataFrame({"k": inputs.sibling_keys("toy_raw")})})

    store, archive = toy_world(workdir)
    graph = StageGraph([toy_raw, toy_pool])
    compute_all(store, archive, sorted(RUNS), graph)
    assert store.read("toy_pool", "B__r1", "v")["k"].tolist() == ["B__r1", "B__s1"]
    assert sorted(store.read_meta("toy_pool", "B__r1")["inputs"]) == ["toy_raw/B__r1", "toy_raw/B__s1"]
    assert [d.asset_key for d in stage_deps(graph, toy_pool)] == [dg.AssetKey("toy_raw")]  # one dep, over every partition
    assert isinstance(stage_deps(graph, toy_pool)[0].partition_mapping, dg.AllPartitionMapping)


# ---------------------------------------------------------------------------------------------------------------
# Validation, graph operations, planning cache
# ---------------------------------------------------------------------------------------------------------------
def _spec(name, level, upstream=(), siblings=()):
    return StageSpec(name, level, "1", tuple(upstream), lambda k, i: None, siblings=tuple(siblings))


def test_only_capture_stages_declare_or_are_siblings():
    with pytest.raises(ValueError, match="only a capture-level stage"):
        StageGraph([toy_raw, z_noise, _spec("dev", "device", ("z_noise",), siblings=("z_noise",))])
    with pytest.raises(ValueError, match="only a capture-level stage"):
        stage("dev", level="device", group="toy", code_version="1", siblings=("z_noise",))
    with pytest.raises(ValueError, match="only capture-level stages can be siblings"):
        StageGraph([toy_raw, z_noise, _spec("dev", "device", ("z_noise",)), _spec("x", "capture", ("toy_raw",),
                                                                                  siblings=("dev",))])
    with pytest.raises(ValueError, match="not listed before it"):  # a sibling is ordered like an upstream
        StageGraph([toy_raw, a_fit, z_noise])
    with pytest.raises(ValueError, match="not listed before it"):  # no cycle through oneself
        StageGraph([toy_raw, _spec("x", "capture", ("toy_raw",), siblings=("x",))])
    assert a_fit.dependencies == ("toy_raw", "z_noise")


def test_siblings_are_dependencies_of_graph_operations(tmp_path):
    assert GRAPH.without(["z_noise"]).names == ["toy_raw"]
    assert [s.name for s in GRAPH.capture_closure(["a_fit"])] == ["toy_raw", "z_noise", "a_fit"]
    fp = "x" * 64
    graph_cache.save(GRAPH, tmp_path / "g.json", fingerprint=fp)
    loaded = graph_cache.load(tmp_path / "g.json", fingerprint=fp)
    assert loaded["a_fit"].siblings == ("z_noise",) and loaded["z_noise"].siblings == ()
    assert loaded["a_fit"].code_version == a_fit.code_version


# ---------------------------------------------------------------------------------------------------------------
# Reprocessing planner and Dagster
# ---------------------------------------------------------------------------------------------------------------
def test_planner_new_capture_changes_the_expected_version_of_its_devices_readers_only(workdir):
    store, archive = toy_world(workdir)
    keys = sorted(RUNS)
    compute_all(store, archive, keys)
    plan = planning.plan_reprocess(GRAPH, store, archive, keys)
    assert plan.empty and plan.sibling_readers == ("a_fit",)
    land(archive.landing_dir, "A__s3", "static", 30.0)
    plan = planning.plan_reprocess(GRAPH, store, archive, [*keys, "A__s3"])
    stale = {(s.stage, s.key) for s in plan.stale}
    assert stale == {("toy_raw", "A__s3"), ("z_noise", "A__s3"), ("a_fit", "A__r1"), ("a_fit", "A__r2")}
    reason = next(s.reason for s in plan.stale if (s.stage, s.key) == ("a_fit", "A__r1"))
    assert "z_noise/A__s3" in reason
    for k in ("B__r1", "C__r1"):
        assert plan.expected[("a_fit", k)] == store.current_version("a_fit", k)
    # the planner predicted what the engine then computes
    compute_all(store, archive, [*keys, "A__s3"])
    assert all(store.current_version(s.stage, s.key) == s.expected for s in plan.stale)
    # a device's captures need not be contiguous in the partition order: one range when a reader is stale
    order = ["A__r1", "A__s1", "B__r1", "B__s1", "A__s3"]
    runs = reprocess.planned_runs(plan, order, ["A", "B"], levels=("capture",))
    assert [(r.first, r.last) for r in runs] == [("A__r1", "A__s3")]


def test_dagster_edge_and_one_batched_run_then_reprocessing(workdir):
    """Definitions load with the sibling edge (every partition); one batched run materializes the sibling over
    the range first; a capture landed later (not contiguous with its device's captures) is reprocessed so the
    readers of its device reach their expected versions, and the plan is empty afterwards."""
    first = {k: v for k, v in RUNS.items() if k != "A__s2"}
    store, archive = toy_world(workdir, first)
    landing = archive.landing_dir
    defs = toy_definitions(landing, workdir / "store", GRAPH)
    node = defs.resolve_asset_graph().get(dg.AssetKey("a_fit"))
    assert dg.AssetKey("z_noise") in node.parent_keys
    dep = next(d for d in stage_deps(GRAPH, a_fit) if d.asset_key == dg.AssetKey("z_noise"))
    assert isinstance(dep.partition_mapping, dg.AllPartitionMapping)
    with temp_instance() as inst:
        register_landed_runs(inst, LabArchive(landing_dir=str(landing)))
        summary = materialize_archive(defs, inst)
        assert summary.success and [j for j, _, _ in summary.runs] == ["calibrate_captures"]  # one run
        ins = fit_inputs(store, "A__r1")  # the reader saw the sibling computed in the same run
        assert set(ins) == {"toy_raw/A__r1", "z_noise/A__s1"}
        assert store.read("a_fit", "A__r2", "prior")["sibling"].tolist() == ["A__s1"]
        assert planning.plan_reprocess(GRAPH, store, archive, *registered_keys(inst)).empty

        land(landing, "A__s2", "static", 20.0)  # registered after B's runs: A's captures are not contiguous
        register_landed_runs(inst, LabArchive(landing_dir=str(landing)))
        cap, dev = registered_keys(inst)
        assert cap.index("A__s2") > cap.index("B__s1")
        plan = planning.plan_reprocess(GRAPH, store, archive, cap, dev)
        assert {("a_fit", "A__r1"), ("a_fit", "A__r2"), ("z_noise", "A__s2")} <= {(s.stage, s.key) for s in plan.stale}
        assert "a_fit" not in {s.stage for s in plan.stale if not s.key.startswith("A__")}
        assert reprocess.run_plan(defs, inst, plan, store).success
        assert all(store.current_version(s.stage, s.key) == s.expected for s in plan.stale)
        assert store.read("a_fit", "A__r1", "prior")["sibling"].tolist() == ["A__s1", "A__s2"]
        assert planning.plan_reprocess(GRAPH, store, archive, cap, dev).empty


def test_recompute_capture_recomputes_the_siblings_a_stage_reads(workdir):
    """``imulab verify``'s recomputation (``recompute_capture`` into an empty store) gives a sibling reader the version
    the pipeline gave it: the device's other captures' sibling stages are computed first (rejected or not applicable
    ones skipped as the engine skips them)."""
    from assets_lib.stages.engine import recompute_capture

    store, archive = toy_world(workdir)
    compute_all(store, archive, sorted(RUNS))
    for key in ("A__r1", "B__r1", "C__r1"):
        fresh = VersionedStore(workdir / f"fresh_{key}")
        got = recompute_capture(GRAPH, key, fresh, archive, ["a_fit"])
        assert got[f"a_fit/{key}"] == store.current_version("a_fit", key)
        assert fresh.read("a_fit", key, "prior").equals(store.read("a_fit", key, "prior"))
    assert {"z_noise/A__s1", "z_noise/A__s2"} <= set(recompute_capture(GRAPH, "A__r2", VersionedStore(workdir / "f2"),
                                                                       archive, ["a_fit"]))
