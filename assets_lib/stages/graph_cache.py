"""The stage graph without importing the stages: what the reprocessing planner needs of every stage (name, level,
upstream, siblings, test kinds, code version), saved once the real graph was imported and reused while no project
source changed, so a run on an unchanged archive plans without importing the science (scipy, numba) or computing
source digests.

The cache is keyed by ``sources_fingerprint``: a sha256 over the path and bytes of every ``.py`` file of the
project packages (``assets_lib``, ``raw_schemas``), a superset of what any stage's code version reads
(``assets_lib.stages.sources``), so an edit anywhere invalidates it. Specs loaded from it have no compute function:
they plan, they never compute (``compute_partition`` on one raises).
"""

from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path

from assets_lib.stages.engine import StageGraph
from assets_lib.stages.sources import PROJECT_PACKAGES, ROOT
from assets_lib.stages.spec import StageSpec

FORMAT = 2  # 2: siblings


def sources_fingerprint(root: Path = ROOT) -> str:
    """sha256 over the relative path and bytes of every project source file, in sorted order."""
    h = hashlib.sha256()
    for pkg in PROJECT_PACKAGES:
        for f in sorted(Path(root, pkg).rglob("*.py")):
            h.update(str(f.relative_to(root)).encode() + b"\0")
            h.update(f.read_bytes())
    return h.hexdigest()


def _not_loaded(key, inputs):
    raise RuntimeError("this stage graph was loaded from the planning cache (assets_lib.stages.graph_cache): it plans, "
                       "it does not compute; import assets_lib.stages.registry to compute")


def save(graph: StageGraph, path: Path, fingerprint: str | None = None) -> None:
    """Write the planning view of ``graph`` to ``path`` (atomically)."""
    data = {"format": FORMAT, "fingerprint": fingerprint or sources_fingerprint(), "stages": [
        {"name": s.name, "level": s.level, "declared_version": s.declared_version, "upstream": list(s.upstream),
         "siblings": list(s.siblings),
         "group": s.group, "applies_to": None if s.applies_to is None else list(s.applies_to), "kinds": list(s.kinds),
         "description": s.description, "code_version": s.code_version} for s in graph]}
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}")
    tmp.write_text(json.dumps(data, indent=1))
    os.replace(tmp, path)


def load(path: Path, fingerprint: str | None = None) -> StageGraph | None:
    """The planning view saved at ``path`` when it was saved from the current sources, else None."""
    try:
        data = json.loads(Path(path).read_text())
    except (OSError, ValueError):
        return None
    if data.get("format") != FORMAT or data.get("fingerprint") != (fingerprint or sources_fingerprint()):
        return None
    specs = []
    for d in data["stages"]:
        s = StageSpec(d["name"], d["level"], d["declared_version"], tuple(d["upstream"]), _not_loaded, d["group"],
                      None if d["applies_to"] is None else tuple(d["applies_to"]), tuple(d["kinds"]), d["description"],
                      siblings=tuple(d.get("siblings", ())))
        s.__dict__["code_version"] = d["code_version"]  # the cached_property's slot: no source digest recomputed
        specs.append(s)
    return StageGraph(specs)


def prime(graph: StageGraph, path: Path, fingerprint: str | None = None) -> int:
    """Give the stages of the real ``graph`` their code versions from the cache at ``path`` when it was saved from
    the current sources (the same sources give the same digests), so they are not parsed again; returns how many
    stages were primed."""
    cached = load(path, fingerprint)
    if cached is None:
        return 0
    n = 0
    for s in graph:
        if s.name in cached and "code_version" not in s.__dict__ \
                and cached[s.name].declared_version == s.declared_version:
            s.__dict__["code_version"] = cached[s.name].code_version
            n += 1
    return n
