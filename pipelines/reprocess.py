"""Reprocessing: which partitions are stale, why, and the batched runs that bring them up to date.

A partition is stale when the version it *should* have differs from its ``CURRENT`` version, or when it has
never been materialized. The expected version is the one ``pipelines.stage.run_stage`` would compute:
``version_id(stage, code_version, inputs)`` where the inputs are the raw file hashes (root stages) or the
upstream partitions' versions. Stages are walked in dependency order and every stage's inputs use its
upstreams' *expected* versions, so a changed code version or a re-landed raw file propagates down the graph
before anything runs. Stale partitions are then grouped into contiguous blocks of the partition order, one
range-tagged run per block and level (single-run backfill policy), never one run per partition.

A partition whose stage produced no output at its expected version (the compute returned ``None`` or failed)
would look "never materialized" forever; ``record_no_output`` notes such (stage, partition, version) triples in
``<store>/_reprocess/no_output.json`` after a launch, and they are not requested again until their expected
version changes (new code or new input). This module is plain Python on top of Dagster's instance: the
``imulab reprocess`` command and the reprocessing schedules both use it.
"""

from __future__ import annotations

import hashlib
import json
import os
import tempfile
from dataclasses import dataclass, field
from pathlib import Path

import dagster as dg

from pipelines.defs.sensors import CAPTURES_JOB, DEVICES_JOB, FLEET_JOB, contiguous_blocks, range_tags
from pipelines.partitions import captures, devices, split_capture_key
from pipelines.resources import LabArchive
from pipelines.stage import FLEET_KEY, STAGES, StageSpec, expected_version, input_versions
from pipelines.storage import VersionedStore

LEDGER = Path("_reprocess") / "no_output.json"
LEVEL_JOB = {"capture": CAPTURES_JOB, "device": DEVICES_JOB, "fleet": FLEET_JOB}
REPROCESS_TAG = "imulab/reprocess"


@dataclass(frozen=True)
class StalePartition:
    stage: str
    level: str
    key: str
    current: str | None
    expected: str
    reason: str


@dataclass
class ReprocessPlan:
    """Stale partitions per stage (dependency order) and the expected version of every partition."""

    order: list[str]
    stale: list[StalePartition] = field(default_factory=list)
    expected: dict[tuple[str, str], str] = field(default_factory=dict)
    no_output: list[tuple[str, str, str]] = field(default_factory=list)  # (stage, key, version) skipped per ledger
    not_applicable: int = 0
    waiting: int = 0
    up_to_date: int = 0

    @property
    def empty(self) -> bool:
        return not self.stale

    def stale_keys(self, level: str) -> list[str]:
        return sorted({s.key for s in self.stale if s.level == level})

    def stale_stages(self, level: str, keys=None) -> list[str]:
        keys = None if keys is None else set(keys)
        names = {s.stage for s in self.stale if s.level == level and (keys is None or s.key in keys)}
        return [n for n in self.order if n in names]

    def by_stage(self) -> dict[str, list[StalePartition]]:
        out: dict[str, list[StalePartition]] = {}
        for s in self.stale:
            out.setdefault(s.stage, []).append(s)
        return {n: out[n] for n in self.order if n in out}


def stage_order() -> list[StageSpec]:
    """Every registered stage, upstreams first (registration order among independent stages)."""
    done: dict[str, StageSpec] = {}

    def visit(name: str, path: tuple[str, ...] = ()):
        if name in done:
            return
        if name in path:
            raise ValueError(f"stage cycle: {' -> '.join(path + (name,))}")
        spec = STAGES[name]
        for up in spec.upstream:
            visit(up, path + (name,))
        done[name] = spec

    for name in list(STAGES):
        visit(name)
    return list(done.values())


def read_ledger(store: VersionedStore) -> dict[str, str]:
    p = Path(store.root) / LEDGER
    try:
        return json.loads(p.read_text())
    except (OSError, ValueError):
        return {}


def _write_ledger(store: VersionedStore, ledger: dict[str, str]) -> None:
    p = Path(store.root) / LEDGER
    text = json.dumps(dict(sorted(ledger.items())), indent=1) + "\n"
    if p.is_file() and p.read_text() == text:
        return
    p.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=".no_output.", dir=p.parent)
    with os.fdopen(fd, "w") as f:
        f.write(text)
    os.replace(tmp, p)


def _raw_test_kind(archive: LabArchive, key: str) -> str | None:
    try:
        return json.loads((archive.run_dir(key) / "manifest.json").read_text()).get("test_kind")
    except (OSError, ValueError):
        return None


class _Planner:
    def __init__(self, store: VersionedStore, archive: LabArchive, capture_keys, device_keys, ledger):
        self.store, self.archive, self.ledger = store, archive, ledger
        self.capture_keys = list(capture_keys)
        self.device_keys = list(device_keys)
        self.expected: dict[tuple[str, str], str | None] = {}

    def version_of(self, stage: str, key: str) -> str | None:
        """The version ``stage/key`` will have once the plan ran (its current one when not planned)."""
        if (stage, key) in self.expected:
            return self.expected[(stage, key)]
        return self.store.current_version(stage, key)

    def upstream_keys(self, spec: StageSpec, up: str, key: str) -> list[str]:
        level = STAGES[up].level
        if level == "capture" and spec.level != "capture":
            keys = set(self.store.partitions(up)) | {k for k in self.capture_keys if self.expected.get((up, k))}
            return sorted(k for k in keys if spec.level == "fleet" or split_capture_key(k)[0] == key)
        if level == "device" and spec.level == "fleet":
            return sorted(set(self.store.partitions(up)) | {k for k in self.device_keys if self.expected.get((up, k))})
        return [key]

    def inputs(self, spec: StageSpec, key: str) -> dict[str, str] | None:
        """``pipelines.stage.input_versions`` on expected upstream versions."""
        return input_versions(spec, key, self.store, self.archive, self.version_of, self.upstream_keys)

    def test_kind(self, key: str, inputs: dict[str, str]) -> str | None:
        v = inputs.get(f"ingested_run/{key}")
        if v is not None and self.store.exists("ingested_run", key, v):
            return self.store.read_meta("ingested_run", key, v).get("test_kind")
        return _raw_test_kind(self.archive, key)

    def reason(self, spec: StageSpec, key: str, current: str | None, inputs: dict[str, str]) -> str:
        if current is None:
            return "never materialized"
        try:
            meta = self.store.read_meta(spec.name, key, current)
        except (OSError, ValueError):
            return "current version unreadable"
        parts = []
        if str(meta.get("code_version")) != str(spec.code_version):
            parts.append(f"code version {meta.get('code_version')} -> {spec.code_version}")
        old = meta.get("inputs") or {}
        changed = sorted(k for k in set(old) | set(inputs) if old.get(k) != inputs.get(k))
        raw = [k.split("/", 1)[1] for k in changed if k.startswith("raw/")]
        ups = [k for k in changed if not k.startswith("raw/")]
        if raw:
            parts.append("raw input changed: " + ", ".join(raw))
        if ups:
            shown = ", ".join(ups[:3]) + (f" (+{len(ups) - 3} more)" if len(ups) > 3 else "")
            parts.append("upstream changed: " + shown)
        return "; ".join(parts) or "version differs"

    def plan(self) -> ReprocessPlan:
        order = stage_order()
        plan = ReprocessPlan(order=[s.name for s in order])
        for spec in order:
            keys = {"capture": self.capture_keys, "device": self.device_keys}.get(spec.level, [FLEET_KEY])
            for key in keys:
                inputs = self.inputs(spec, key)
                if inputs is None:
                    self.expected[(spec.name, key)] = None
                    plan.waiting += 1
                    continue
                if spec.applies_to is not None and spec.level == "capture" and self.test_kind(key, inputs) not in spec.applies_to:
                    self.expected[(spec.name, key)] = None
                    plan.not_applicable += 1
                    continue
                version = expected_version(spec, inputs)
                current = self.store.current_version(spec.name, key)
                if current == version:
                    self.expected[(spec.name, key)] = version
                    plan.up_to_date += 1
                elif self.ledger.get(f"{spec.name}/{key}") == version and not self.store.exists(spec.name, key, version):
                    self.expected[(spec.name, key)] = None  # produced no output at this version: do not retry
                    plan.no_output.append((spec.name, key, version))
                else:
                    self.expected[(spec.name, key)] = version
                    plan.stale.append(StalePartition(spec.name, spec.level, key, current, version,
                                                     self.reason(spec, key, current, inputs)))
        plan.expected = {k: v for k, v in self.expected.items() if v is not None}
        return plan


def registered_keys(instance: dg.DagsterInstance) -> tuple[list[str], list[str]]:
    """Capture and device partition keys in partition order."""
    cap = list(instance.get_dynamic_partitions(captures.name))
    dev = list(instance.get_dynamic_partitions(devices.name))
    extra = sorted({split_capture_key(k)[0] for k in cap} - set(dev))
    return cap, dev + extra


def plan_reprocess(store: VersionedStore, archive: LabArchive, capture_keys, device_keys=None,
                   use_ledger: bool = True) -> ReprocessPlan:
    """Stale partitions of every registered stage for ``capture_keys`` (and their devices)."""
    if device_keys is None:
        device_keys = sorted({split_capture_key(k)[0] for k in capture_keys})
    ledger = read_ledger(store) if use_ledger else {}
    return _Planner(store, archive, capture_keys, device_keys, ledger).plan()


def plan_for_instance(instance: dg.DagsterInstance, store: VersionedStore, archive: LabArchive,
                      use_ledger: bool = True) -> ReprocessPlan:
    cap, dev = registered_keys(instance)
    return plan_reprocess(store, archive, cap, dev, use_ledger)


@dataclass(frozen=True)
class PlannedRun:
    job: str
    level: str
    first: str | None
    last: str | None
    stages: tuple[str, ...]

    @property
    def tags(self) -> dict[str, str]:
        base = {REPROCESS_TAG: "1"}
        return {**base, **range_tags(self.first, self.last)} if self.first is not None else base

    @property
    def asset_selection(self) -> list[dg.AssetKey]:
        return [dg.AssetKey(s) for s in self.stages]

    def run_key(self, plan: ReprocessPlan) -> str:
        keys = sorted((s, k, v) for (s, k), v in plan.expected.items() if s in self.stages)
        digest = hashlib.sha256(json.dumps([self.job, self.first, self.last, keys]).encode()).hexdigest()[:16]
        return f"reprocess-{self.level}-{digest}"


def planned_runs(plan: ReprocessPlan, capture_order: list[str], device_order: list[str],
                 levels=("capture", "device", "fleet"), exclude_devices=()) -> list[PlannedRun]:
    """One run per contiguous block of stale partitions and level, selecting only the stale stages."""
    runs: list[PlannedRun] = []
    exclude_devices = set(exclude_devices)
    orders = {"capture": capture_order, "device": device_order}
    for level in levels:
        if level == "fleet":
            stages = plan.stale_stages("fleet")
            if stages:
                runs.append(PlannedRun(FLEET_JOB, level, None, None, tuple(stages)))
            continue
        wanted = set(plan.stale_keys(level)) - (exclude_devices if level == "device" else set())
        ordered = orders[level]
        for first, last in contiguous_blocks(ordered, wanted):
            block = ordered[ordered.index(first): ordered.index(last) + 1]
            runs.append(PlannedRun(LEVEL_JOB[level], level, first, last, tuple(plan.stale_stages(level, block))))
    return runs


def record_no_output(store: VersionedStore, plan: ReprocessPlan, attempted: set[tuple[str, str]]) -> int:
    """After a launch: note stale (stage, partition) pairs in ``attempted`` (a run covering the partition ran the
    stage's step successfully) that still lack their expected version: the stage produced no output there (not
    applicable, or the compute failed for that partition)."""
    ledger = read_ledger(store)
    added = 0
    for s in plan.stale:
        if s.expected == store.current_version(s.stage, s.key):
            ledger.pop(f"{s.stage}/{s.key}", None)
        elif (s.stage, s.key) in attempted and not store.exists(s.stage, s.key, s.expected):
            ledger[f"{s.stage}/{s.key}"] = s.expected
            added += 1
    if added or (Path(store.root) / LEDGER).is_file():
        _write_ledger(store, ledger)
    return added


def outcome(store: VersionedStore, plan: ReprocessPlan) -> list[tuple[StalePartition, str]]:
    """(stale partition, 'rewritten' | 'no output') once the plan ran."""
    return [(s, "rewritten" if store.current_version(s.stage, s.key) == s.expected else "no output") for s in plan.stale]


def run_plan(defs: dg.Definitions, instance: dg.DagsterInstance, plan: ReprocessPlan, store: VersionedStore,
             quiet: bool = True):
    """Execute the planned runs level by level (captures, then devices, then fleet) in this process, then note
    partitions that produced no output. Returns the ``LaunchSummary``."""
    from pipelines.launch import LaunchSummary, run_job

    cap, dev = registered_keys(instance)
    summary = LaunchSummary()
    jobs = {j.name for j in defs.resolve_all_job_defs()}
    for run in planned_runs(plan, cap, dev):
        if run.job in jobs and run.stages:
            run_job(defs, instance, run.job, tags=run.tags, asset_selection=run.asset_selection, quiet=quiet,
                    summary=summary)
    record_no_output(store, plan, summary.attempted)
    return summary
