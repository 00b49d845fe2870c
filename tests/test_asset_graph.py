"""Approval test of the resolved asset graph: keys, groups, deps, partitions, code versions, checks, jobs,
sensors and schedules, against ``tests/snapshots/asset_graph.json``, so every graph change shows up in review.

Regenerate after an intended change with ``IMULAB_UPDATE_SNAPSHOTS=1 python -m pytest tests/test_asset_graph.py``
and commit the snapshot. Also runs ``dagster definitions validate -w workspace.yaml``.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import dagster as dg
import pytest

from assets_lib.stages.spec import SOURCE_TAG

SNAPSHOT = Path(__file__).with_name("snapshots") / "asset_graph.json"
REPO = Path(__file__).resolve().parents[1]


def _partitions(pd) -> str | None:
    if pd is None:
        return None
    name = getattr(pd, "name", None)
    return f"{type(pd).__name__}({name})" if name else type(pd).__name__


def graph_snapshot(defs: dg.Definitions) -> dict:
    graph = defs.resolve_asset_graph()
    assets = {}
    for node in sorted(graph.asset_nodes, key=lambda n: n.key.to_user_string()):
        bp = node.backfill_policy
        assets[node.key.to_user_string()] = {
            "group": node.group_name,
            "deps": sorted(k.to_user_string() for k in node.parent_keys),
            "partitions": _partitions(node.partitions_def),
            "code_version": (node.code_version or "").split(SOURCE_TAG)[0],  # declared part
            "backfill_policy": None if bp is None else bp.policy_type.value,
            "kinds": sorted(node.kinds),
            "checks": sorted(k.name for k in node.check_keys),
        }
    checks = {}
    for key in sorted(graph.asset_check_keys, key=lambda k: (k.asset_key.to_user_string(), k.name)):
        spec = graph.get_check_spec(key)
        checks[f"{key.asset_key.to_user_string()}:{key.name}"] = {
            "blocking": bool(spec.blocking),
            "partitions": _partitions(getattr(spec, "partitions_def", None)),
        }
    jobs = {}
    for job in sorted(defs.resolve_all_job_defs(), key=lambda j: j.name):
        if job.name.startswith("__"):
            continue
        jobs[job.name] = {
            "assets": sorted(k.to_user_string() for k in job.asset_layer.executable_asset_keys),
            "executor": job.executor_def.name,
        }
    sensors = {s.name: {"targets": sorted(t.job_name for t in s.targets), "default_status": s.default_status.value}
               for s in sorted(defs.sensors or [], key=lambda s: s.name)}
    schedules = {s.name: {"job": s.job_name, "cron": s.cron_schedule, "default_status": s.default_status.value}
                 for s in sorted(defs.schedules or [], key=lambda s: s.name)}
    return {"assets": assets, "checks": checks, "jobs": jobs, "sensors": sensors, "schedules": schedules}


def test_asset_graph_matches_snapshot():
    from pipelines.definitions import build_definitions

    snap = graph_snapshot(build_definitions("/nonexistent/landing", "/nonexistent/store"))
    text = json.dumps(snap, indent=1, sort_keys=True) + "\n"
    if os.environ.get("IMULAB_UPDATE_SNAPSHOTS") == "1":
        SNAPSHOT.parent.mkdir(exist_ok=True)
        SNAPSHOT.write_text(text)
        pytest.skip(f"snapshot written to {SNAPSHOT}")
    assert SNAPSHOT.is_file(), f"no snapshot yet: run IMULAB_UPDATE_SNAPSHOTS=1 python -m pytest {__file__}"
    want = json.loads(SNAPSHOT.read_text())
    # compare section by section for a readable diff
    for section in ("assets", "checks", "jobs", "sensors", "schedules"):
        added = sorted(set(snap[section]) - set(want.get(section, {})))
        removed = sorted(set(want.get(section, {})) - set(snap[section]))
        assert not added and not removed, (
            f"{section}: added {added}, removed {removed}; if intended, regenerate with IMULAB_UPDATE_SNAPSHOTS=1")
        for name, value in snap[section].items():
            assert value == want[section][name], (
                f"{section} {name!r} changed: {want[section][name]} -> {value}; "
                "if intended, regenerate with IMULAB_UPDATE_SNAPSHOTS=1")


def test_snapshot_sees_a_code_version_change():
    """The snapshot is sensitive: a new code version of one stage changes exactly that asset's entry."""
    from prod_helpers import toy_definitions, toy_stages

    with toy_stages("1") as toys:
        one = graph_snapshot(toy_definitions("/x", "/y", toys))["assets"]
    with toy_stages("2") as toys:
        two = graph_snapshot(toy_definitions("/x", "/y", toys))["assets"]
    assert {k for k in one if one[k] != two[k]} == {"toy_capture_a"}
    assert (one["toy_capture_a"]["code_version"], two["toy_capture_a"]["code_version"]) == ("1", "2")


def test_dagster_definitions_validate():
    env = {**os.environ, "IMULAB_LANDING": "/nonexistent/landing", "IMULAB_STORE": "/nonexistent/store",
           "PYTHONWARNINGS": "ignore"}
    exe = Path(sys.executable).with_name("dagster")
    res = subprocess.run([str(exe) if exe.is_file() else "dagster", "definitions", "validate", "-w", "workspace.yaml"],
                         cwd=REPO, env=env, capture_output=True, text=True, timeout=180)
    assert res.returncode == 0, res.stdout[-3000:] + res.stderr[-3000:]
    assert "Validation successful" in res.stdout + res.stderr
