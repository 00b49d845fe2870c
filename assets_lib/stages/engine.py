"""The one way to compute a partition, used by the Dagster assets, by ``imulab verify`` and by the reprocessing planner.

- ``StageGraph``: an ordered, validated list of stages (every upstream and sibling before the stages reading it).
- Versions: a partition's version is ``version_id(stage, code_version, inputs)`` where ``inputs`` are the sha256 of
  the raw run files (root stages) or the versions of the upstream partitions it reads (``input_versions``; which
  partitions a stage reads is ``upstream_keys``, the one rule; a capture stage's siblings, the same stage's
  partitions for every capture of its device, are ``sibling_keys``). Equal code and inputs give an equal version, so
  unchanged work is reused, not recomputed or rewritten (idempotent), and the planner predicts versions before
  anything runs by passing the versions upstreams *will* have.
- ``decide`` says what a (stage, partition) needs: its inputs are missing (waiting), the stage does not apply to
  the run's test kind, or its expected version; ``compute_partition`` then reuses the stored version or calls the
  stage's pure compute function and writes the result atomically, never overwriting a version. One failing
  partition gives an ``Outcome`` with status ``failed`` and its reason; it never stops the others.
"""

from __future__ import annotations

import json
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from pathlib import Path

from assets_lib.stages.spec import LEVELS, StageSpec
from assets_lib.store import (
    FLEET_KEY,
    StoreView,
    VersionedStore,
    split_capture_key,
    version_id,
)
from assets_lib.store.versioned import REJECTED
from raw_schemas.hashcache import hash_folder_files

#: the root stage whose stored metadata names a run's test kind
KIND_SOURCE = "ingested_run"


class StageGraph:
    """Stages in dependency order (upstreams first), looked up by name. Built once from an explicit list."""

    def __init__(self, stages: Iterable[StageSpec]):
        self._specs = tuple(stages)
        self._by_name: dict[str, StageSpec] = {}
        for s in self._specs:
            if s.name in self._by_name:
                raise ValueError(f"stage {s.name!r} listed twice")
            missing = [u for u in s.dependencies if u not in self._by_name]
            if missing:
                raise ValueError(f"stage {s.name!r}: upstream {missing} not listed before it")
            for u in s.upstream:
                if LEVELS.index(self._by_name[u].level) > LEVELS.index(s.level):
                    raise ValueError(f"stage {s.name!r} ({s.level}) reads {u!r} ({self._by_name[u].level}): "
                                     "stages read only their own level or a finer one")
            if s.siblings and s.level != "capture":
                raise ValueError(f"stage {s.name!r} ({s.level}) declares siblings {list(s.siblings)}: only a "
                                 "capture-level stage reads siblings (the partitions of other captures of its device)")
            for u in s.siblings:
                if self._by_name[u].level != "capture":
                    raise ValueError(f"stage {s.name!r} reads {u!r} ({self._by_name[u].level}) as a sibling: only "
                                     "capture-level stages can be siblings (device and fleet stages are upstreams)")
            self._by_name[s.name] = s

    def __iter__(self):
        return iter(self._specs)

    def __len__(self) -> int:
        return len(self._specs)

    def __contains__(self, name) -> bool:
        return name in self._by_name

    def __getitem__(self, name: str) -> StageSpec:
        return self._by_name[name]

    @property
    def names(self) -> list[str]:
        return [s.name for s in self._specs]

    def at_level(self, level: str) -> list[StageSpec]:
        return [s for s in self._specs if s.level == level]

    @property
    def levels(self) -> set[str]:
        return {s.level for s in self._specs}

    def roots(self) -> list[str]:
        """Capture stages computed straight from the raw run folder."""
        return [s.name for s in self._specs if s.level == "capture" and not s.upstream]

    def capture_closure(self, names: Iterable[str]) -> list[StageSpec]:
        """The capture-level stages among ``names`` and everything they need, in order."""
        needed: set[str] = set()
        todo = [n for n in names if n in self]
        while todo:
            n = todo.pop()
            if n not in needed and self[n].level == "capture":
                needed.add(n)
                todo += list(self[n].dependencies)
        return [s for s in self._specs if s.name in needed]

    def with_stages(self, *stages: StageSpec, replace: bool = False) -> StageGraph:
        """A new graph with ``stages`` appended (or, with ``replace``, substituted for the stages of the same name)."""
        if replace:
            new = {s.name: s for s in stages}
            return StageGraph(new.get(s.name, s) for s in self._specs)
        return StageGraph((*self._specs, *stages))

    def subset(self, names: Iterable[str]) -> StageGraph:
        keep = set(names)
        return StageGraph(s for s in self._specs if s.name in keep)

    def without(self, names: Iterable[str]) -> StageGraph:
        """The graph less ``names`` and every stage that reads one of them (transitively); KeyError names unknown
        stages."""
        dropped = set(names)
        unknown = sorted(dropped - set(self._by_name))
        if unknown:
            raise KeyError(f"unknown stage(s) {unknown}; stages: {self.names}")
        for s in self._specs:  # dependency order: upstreams are decided first
            if any(u in dropped for u in s.dependencies):
                dropped.add(s.name)
        return self.subset(n for n in self.names if n not in dropped)


# ---------------------------------------------------------------------------------------------------------------
# Versions
# ---------------------------------------------------------------------------------------------------------------
def raw_versions(run_dir: Path) -> dict[str, str]:
    """sha256 of every file of a raw run folder: the root of every version chain (each file read once per process
    while its state is unchanged: ``raw_schemas.hashcache``)."""
    return {f"raw/{name}": digest for name, digest in hash_folder_files(run_dir).items()}


def upstream_keys(graph: StageGraph, spec: StageSpec, up: str, key: str, partitions_of: Callable[[str], Iterable[str]]
                  ) -> list[str]:
    """Partitions of upstream ``up`` that ``spec`` reads for ``key``: the same key, or all captures of the device
    (device stages reading capture stages), or every partition (fleet stages). ``partitions_of(stage)`` lists the
    partitions that exist (or will exist once a reprocessing plan ran)."""
    level = graph[up].level
    if level == "capture" and spec.level != "capture":
        return sorted(k for k in partitions_of(up) if spec.level == "fleet" or split_capture_key(k)[0] == key)
    if level == "device" and spec.level == "fleet":
        return sorted(partitions_of(up))
    return [key]


def sibling_keys(sib: str, key: str, partitions_of: Callable[[str], Iterable[str]]) -> list[str]:
    """Partitions of sibling stage ``sib`` that a capture stage reads for capture ``key``: every capture of the same
    device that exists (or will, once a reprocessing plan ran), ``key`` itself included."""
    device = split_capture_key(key)[0]
    return sorted(k for k in partitions_of(sib) if split_capture_key(k)[0] == device)


def gather_inputs(graph: StageGraph, spec: StageSpec, key: str, store: VersionedStore, archive,
                  version_of: Callable | None = None, partitions_of: Callable | None = None
                  ) -> tuple[dict[str, str] | None, str | None]:
    """(versions of what ``spec`` computes ``key`` from, or None when an input is missing; the reason the partition
    is blocked, when a capture-level upstream version was rejected by a quality gate).

    Device and fleet stages read the upstream partitions that exist and were not rejected; so do capture stages
    read their siblings (``sibling_keys``): a sibling partition without a version (missing, not applicable, or
    failed) or rejected by a gate is left out, never waited for, and the others enter the inputs as
    ``"<sibling>/<key>"`` like upstreams. ``version_of(stage, key)`` defaults to the stored CURRENT version; the
    reprocessing planner passes expected ones.
    """
    version_of = version_of or store.current_version
    partitions_of = partitions_of or store.partitions
    out: dict[str, str] = {}
    if spec.level == "capture" and not spec.upstream:
        d = archive.run_dir(key)
        if not d.is_dir():
            return None, None
        out = raw_versions(d)
    for up in spec.upstream:
        for k in upstream_keys(graph, spec, up, key, partitions_of):
            v = version_of(up, k)
            if v is None:
                if spec.level == "capture":
                    return None, None
                continue
            why = store.rejection(up, k, v)
            if why is not None:
                if spec.level == "capture":
                    return None, f"{up} rejected ({why})"
                continue
            out[f"{up}/{k}"] = v
    for sib in spec.siblings:  # optional inputs: what exists and passed its gates
        for k in sibling_keys(sib, key, partitions_of):
            v = version_of(sib, k)
            if v is not None and store.rejection(sib, k, v) is None:
                out[f"{sib}/{k}"] = v
    if spec.level != "capture" and not out:
        return None, None
    return out, None


def input_versions(graph: StageGraph, spec: StageSpec, key: str, store: VersionedStore, archive,
                   version_of: Callable | None = None, partitions_of: Callable | None = None) -> dict[str, str] | None:
    """Versions of what ``spec`` computes ``key`` from, or None when an input is missing or rejected."""
    return gather_inputs(graph, spec, key, store, archive, version_of, partitions_of)[0]


def expected_version(spec: StageSpec, inputs: dict[str, str]) -> str:
    return version_id(spec.name, spec.code_version, inputs)


def run_test_kind(store: VersionedStore, archive, key: str, version_of: Callable | None = None) -> str | None:
    """Test kind of a capture: from its ingested manifest when that version is stored, else from the raw manifest."""
    v = (version_of or store.current_version)(KIND_SOURCE, key)
    if v is not None and store.exists(KIND_SOURCE, key, v):
        return store.read_meta(KIND_SOURCE, key, v).get("test_kind")
    try:
        return json.loads((archive.run_dir(key) / "manifest.json").read_text()).get("test_kind")
    except (OSError, ValueError):
        return None


@dataclass(frozen=True)
class Decision:
    """What a (stage, partition) needs: ``waiting`` (an input is missing), ``blocked`` (an upstream partition
    failed a quality gate; ``reason`` says which), ``not applicable``, or ``compute`` at ``version`` from
    ``inputs`` (reused when that version is stored)."""

    status: str
    inputs: dict[str, str] | None = None
    version: str | None = None
    kind: str | None = None
    reason: str = ""


def decide(graph: StageGraph, spec: StageSpec, key: str, store: VersionedStore, archive,
           version_of: Callable | None = None, partitions_of: Callable | None = None) -> Decision:
    inputs, blocked = gather_inputs(graph, spec, key, store, archive, version_of, partitions_of)
    if blocked is not None:
        return Decision("blocked", reason=blocked)
    if inputs is None:
        return Decision("waiting")
    if spec.applies_to is not None and spec.level == "capture":
        kind = run_test_kind(store, archive, key, version_of)
        if kind not in spec.applies_to:
            return Decision("not applicable", inputs, kind=kind)
    return Decision("compute", inputs, expected_version(spec, inputs))


# ---------------------------------------------------------------------------------------------------------------
# Computing partitions
# ---------------------------------------------------------------------------------------------------------------
#: outcome statuses: ``written`` / ``reused`` (the partition has its version), ``waiting`` (an input is missing),
#: ``blocked`` (an upstream partition failed a gate), ``not applicable`` (test kind), ``no output`` (the compute
#: returned None), ``failed`` (the compute raised, or a gate rejected its output: ``version`` is then set)
DONE = ("written", "reused")


@dataclass(frozen=True)
class Outcome:
    stage: str
    key: str
    status: str
    version: str | None = None
    reason: str = ""
    summary: dict = field(default_factory=dict)
    plots: dict = field(default_factory=dict)

    @property
    def done(self) -> bool:
        return self.status in DONE

    @property
    def failed(self) -> bool:
        return self.status == "failed"

    def describe(self) -> str:
        """One line for tables and logs."""
        return {"waiting": "skipped: inputs missing", "failed": f"error: {self.reason}"}.get(
            self.status, f"{self.status} ({self.reason})" if self.reason else self.status)


def compute_partition(graph: StageGraph, spec: StageSpec, key: str, store: VersionedStore, archive,
                      run_id: str | None = None) -> Outcome:
    """Bring ``spec``'s partition ``key`` to its expected version: reuse it when stored, else compute and write it."""
    d = decide(graph, spec, key, store, archive)
    if d.status == "waiting":
        return Outcome(spec.name, key, "waiting", reason="inputs missing")
    if d.status == "blocked":
        return Outcome(spec.name, key, "blocked", reason=d.reason)
    if d.status == "not applicable":
        return Outcome(spec.name, key, "not applicable", reason=f"test kind {d.kind}")
    if store.exists(spec.name, key, d.version):
        store.write(spec.name, key, d.version, {})  # only moves CURRENT back if needed
        why = store.rejection(spec.name, key, d.version)
        return Outcome(spec.name, key, "reused" if why is None else "failed", d.version, reason=why or "")
    try:
        out = spec.compute(key, StoreView(store, d.inputs, key, archive, run_id))
    except Exception as e:  # noqa: BLE001 - one bad partition must not stop the batch; the outcome says why
        reason = f"{type(e).__name__}: {e}"
        store.note_failure(spec.name, key, d.version, reason)
        return Outcome(spec.name, key, "failed", reason=reason)
    if out is None:
        return Outcome(spec.name, key, "no output")
    failures = gate_failures(spec, out)
    files = dict(out.files)
    files.update({f"{n}.png": png for n, png in out.plots.items()})
    meta = {"code_version": spec.code_version, "inputs": d.inputs, **out.meta}
    if failures:
        files[REJECTED] = ("\n".join(failures) + "\n").encode()
        meta["gate_failures"] = failures
    store.write(spec.name, key, d.version, out.tables, meta=meta, files=files)
    return Outcome(spec.name, key, "failed" if failures else "written", d.version, reason="; ".join(failures),
                   summary=dict(out.summary), plots=dict(out.plots))


def gate_failures(spec: StageSpec, out) -> list[str]:
    """``gate <name>: <reason>`` for every gate of ``spec`` the output fails."""
    out_list = []
    for g in spec.gates:
        why = g.check(out)
        if why:
            out_list.append(f"gate {g.name}: {why}")
    return out_list


def stage_keys(spec: StageSpec, capture_keys: Iterable[str], device_keys: Iterable[str]) -> list[str]:
    """The partitions of ``spec`` among the given capture and device partitions."""
    return {"capture": list(capture_keys), "device": list(device_keys)}.get(spec.level, [FLEET_KEY])


def recompute_capture(graph: StageGraph, key: str, store: VersionedStore, archive, stages: Iterable[str]) -> dict[str, str]:
    """Compute the capture-level ``stages`` (and what they need) for ``key`` into ``store`` (``imulab verify``
    recomputes a record's run into a temporary store this way); returns ``{"<stage>/<key>": version}`` of what
    was computed. A stage reading siblings gets them first: the sibling stages (and what they need) for every other
    complete capture of the device in ``archive``, as the pipeline computes them (a sibling that fails or does not
    apply is skipped there as here). A failing stage of ``key`` raises, naming the stage and the reason."""
    versions = {}
    device = split_capture_key(key)[0]
    siblings_done: set[str] = set()
    for spec in graph.capture_closure(stages):
        for sib in spec.siblings:
            if sib in siblings_done:
                continue
            siblings_done.add(sib)
            for other in sorted(archive.complete_runs()):
                if other == key or split_capture_key(other)[0] != device:
                    continue
                for s in graph.capture_closure([sib]):
                    o = compute_partition(graph, s, other, store, archive)
                    if o.done:
                        versions[f"{s.name}/{other}"] = o.version
        o = compute_partition(graph, spec, key, store, archive)
        if o.failed and o.version is None:  # the compute raised (a gate rejection is an outcome, not an error)
            raise RuntimeError(f"stage {spec.name} failed for {key}: {o.reason}")
        if o.done:
            versions[f"{spec.name}/{key}"] = o.version
    return versions
