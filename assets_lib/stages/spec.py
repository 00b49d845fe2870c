"""What a stage is: a named pure function ``compute(key, view) -> StageOutput | None`` at one partition level, with
its upstream stages (and, for a capture stage, its sibling stages: read for every capture of the same device), a
declared code version and the test kinds it applies to. ``@stage(...)`` turns a function
into a ``StageSpec``; nothing is registered anywhere (the ordered list is ``assets_lib.stages.registry``)."""

from __future__ import annotations

import functools
from collections.abc import Callable
from dataclasses import dataclass, field

import pandas as pd

from assets_lib.stages.sources import source_digest

#: separates the declared code version from the digest of the sources the stage runs
SOURCE_TAG = "+src."
LEVELS = ("capture", "device", "fleet")


@dataclass
class StageOutput:
    """What a stage computed for one partition."""

    tables: dict[str, pd.DataFrame]
    meta: dict = field(default_factory=dict)  # JSON-able facts stored with the version (units, counts, flags)
    files: dict[str, bytes] = field(default_factory=dict)  # extra files stored with the version (PNG, JSON, HTML)
    summary: dict = field(default_factory=dict)  # a few scalars shown as metadata in the UI
    plots: dict[str, bytes] = field(default_factory=dict)  # PNGs shown inline in the UI (also stored as files)


@dataclass(frozen=True)
class Gate:
    """A quality gate of a stage: ``check(output)`` returns None when the partition passes, else a one-line reason
    naming the figure that failed. A partition that fails a gate keeps its output (stored, for diagnosis) but is
    marked rejected: its status is failed and no downstream stage computes from it. Other partitions go on."""

    name: str
    check: Callable[[StageOutput], str | None]
    description: str = ""


@dataclass(frozen=True)
class StageSpec:
    name: str
    level: str  # 'capture' | 'device' | 'fleet'
    declared_version: str
    upstream: tuple[str, ...]
    compute: Callable
    group: str = "default"
    applies_to: tuple[str, ...] | None = None  # test kinds a capture stage applies to (None: all)
    kinds: tuple[str, ...] = ("parquet",)
    description: str = ""
    gates: tuple[Gate, ...] = ()
    #: capture-level stages whose partitions for every capture of the SAME device (this key included, when it
    #: exists) a capture-level stage reads, e.g. a device-wide noise prior from the device's static runs. Optional
    #: inputs: a missing, not-applicable or gate-rejected sibling partition is skipped, never waited for; the ones
    #: read enter the version (``engine.gather_inputs``), so adding, changing or removing one makes it stale.
    siblings: tuple[str, ...] = ()

    @property
    def dependencies(self) -> tuple[str, ...]:
        """Every stage this one reads: its upstreams, then its siblings (ordering, cycles, dropping stages)."""
        return tuple(dict.fromkeys((*self.upstream, *self.siblings)))

    @functools.cached_property
    def code_version(self) -> str:
        """The declared version plus a digest of the sources the compute function runs (its module and the project
        modules it imports), so a science change that forgot to bump the declared version still makes outputs stale."""
        return f"{self.declared_version}{SOURCE_TAG}{source_digest(self.compute.__module__)}"


def stage(name: str, *, level: str, group: str, code_version: str, upstream=(), applies_to=None,
          kinds=("parquet",), description: str = "", gates=(), siblings=()):
    """Decorator: the function becomes the ``compute`` of a ``StageSpec`` (returned in its place).

    ``upstream``: stages read at the same key (same level) or over the finer partitions of this one (a device
    stage reads every capture of its device, a fleet stage every partition). ``siblings`` (capture stages only):
    capture stages read for every capture of the same device, optional inputs (``StageSpec.siblings``; the compute
    lists them with ``inputs.sibling_keys(stage)``)."""
    if level not in LEVELS:
        raise ValueError(f"stage {name!r}: level {level!r} is not one of {LEVELS}")
    if siblings and level != "capture":
        raise ValueError(f"stage {name!r} ({level}) declares siblings {list(siblings)}: only a capture-level stage "
                         "reads siblings (the partitions of other captures of its device)")

    def deco(compute) -> StageSpec:
        doc = description or (compute.__doc__ or "").strip().splitlines()[0]
        return StageSpec(name, level, str(code_version), tuple(upstream), compute, group,
                         tuple(applies_to) if applies_to else None, tuple(kinds), doc, tuple(gates),
                         tuple(siblings))

    return deco
