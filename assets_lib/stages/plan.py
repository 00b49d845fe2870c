"""Reprocessing plan: which partitions are stale, why, and the version each will have once recomputed.

A partition is stale when the version it *should* have (``engine.decide``: the same rule that computes it) differs
from its ``CURRENT`` version, or when it has never been materialized. Stages are walked in graph order and every
stage's inputs use its upstreams' (and siblings') *expected* versions, so a changed code version or a re-landed raw
file propagates down the graph before anything runs (a new capture of a device changes the expected version of the
stages reading it as a sibling on the device's other captures).

A partition whose stage produced no output at its expected version (the compute returned ``None`` or failed)
would look "never materialized" forever; ``record_no_output`` notes such (stage, partition, version) triples in
``<store>/_reprocess/no_output.json`` after a launch, and they are not requested again until their expected
version changes (new code or new input). Plain Python: the Dagster schedules and ``imulab reprocess`` launch
what it finds (``pipelines.reprocess``).
"""

from __future__ import annotations

import json
import os
import tempfile
from dataclasses import dataclass, field
from pathlib import Path

from assets_lib.stages.engine import StageGraph, StageSpec, decide, stage_keys
from assets_lib.store import VersionedStore, split_capture_key

LEDGER = Path("_reprocess") / "no_output.json"


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
    blocked: int = 0  # an upstream partition failed a quality gate
    #: (stage, key, reason) of partitions whose expected version failed: the compute raised (noted in the store)
    #: or a quality gate rejected the stored output; and of partitions blocked by such an upstream
    failed: list[tuple[str, str, str]] = field(default_factory=list)
    blocked_by: list[tuple[str, str, str]] = field(default_factory=list)
    up_to_date: int = 0
    #: capture stages that read siblings (``StageSpec.siblings``): when one is stale, the captures are launched as
    #: one range so every sibling is recomputed before it is read (``pipelines.reprocess.planned_runs``)
    sibling_readers: tuple[str, ...] = ()

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


def stale_reason(store: VersionedStore, spec: StageSpec, key: str, current: str | None, inputs: dict[str, str]) -> str:
    if current is None:
        return "never materialized"
    try:
        meta = store.read_meta(spec.name, key, current)
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


def plan_reprocess(graph: StageGraph, store: VersionedStore, archive, capture_keys, device_keys=None,
                   use_ledger: bool = True) -> ReprocessPlan:
    """Stale partitions of every stage of ``graph`` for ``capture_keys`` (and their devices)."""
    capture_keys = list(capture_keys)
    if device_keys is None:
        device_keys = sorted({split_capture_key(k)[0] for k in capture_keys})
    device_keys = list(device_keys)
    ledger = read_ledger(store) if use_ledger else {}
    expected: dict[tuple[str, str], str | None] = {}
    planned = {"capture": capture_keys, "device": device_keys}

    def version_of(stage: str, key: str) -> str | None:
        """The version ``stage/key`` will have once the plan ran (its current one when not planned)."""
        if (stage, key) in expected:
            return expected[(stage, key)]
        return store.current_version(stage, key)

    def partitions_of(stage: str) -> list[str]:
        """Partitions that exist now or will once the plan ran."""
        return sorted(set(store.partitions(stage))
                      | {k for k in planned.get(graph[stage].level, []) if expected.get((stage, k))})

    plan = ReprocessPlan(order=graph.names, sibling_readers=tuple(s.name for s in graph if s.siblings))
    for spec in graph:
        for key in stage_keys(spec, capture_keys, device_keys):
            d = decide(graph, spec, key, store, archive, version_of, partitions_of)
            if d.status in ("waiting", "blocked"):
                expected[(spec.name, key)] = None
                plan.waiting += d.status == "waiting"
                if d.status == "blocked":
                    plan.blocked += 1
                    plan.blocked_by.append((spec.name, key, d.reason))
                continue
            if d.status == "not applicable":
                expected[(spec.name, key)] = None
                plan.not_applicable += 1
                continue
            current = store.current_version(spec.name, key)
            failure = store.failure(spec.name, key, d.version) if use_ledger else None
            if current == d.version:
                expected[(spec.name, key)] = d.version
                plan.up_to_date += 1
                why = store.rejection(spec.name, key, d.version)
                if why is not None:
                    plan.failed.append((spec.name, key, why))
            elif failure is not None and not store.exists(spec.name, key, d.version):
                expected[(spec.name, key)] = None  # the compute failed at this version: not retried, reported
                plan.failed.append((spec.name, key, failure))
            elif ledger.get(f"{spec.name}/{key}") == d.version and not store.exists(spec.name, key, d.version):
                expected[(spec.name, key)] = None  # produced no output at this version: do not retry
                plan.no_output.append((spec.name, key, d.version))
            else:
                expected[(spec.name, key)] = d.version
                plan.stale.append(StalePartition(spec.name, spec.level, key, current, d.version,
                                                 stale_reason(store, spec, key, current, d.inputs)))
    plan.expected = {k: v for k, v in expected.items() if v is not None}
    return plan


def record_no_output(store: VersionedStore, plan: ReprocessPlan, attempted: set[tuple[str, str]]) -> int:
    """After a launch: note stale (stage, partition) pairs in ``attempted`` (the stage ran over the partition)
    that still lack their expected version: the stage produced no output there (not applicable, or the compute
    failed for that partition)."""
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
