"""`dagster dev -w workspace.yaml` smoke test: the UI serves the code location, and SIGTERM stops every process.

Started through a tiny launcher that resets SIGINT to SIG_DFL before exec: a background process inherits
SIGINT=SIG_IGN, and dagster dev then ignores SIGTERM too (docs/dagster.md 6.4).
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
import urllib.request
from pathlib import Path

import pytest

from local_services import REPO, alive, descendants, group_members
from prod_helpers import SHM, free_port

pytestmark = pytest.mark.slow

LAUNCHER = ("import os, signal, sys; signal.signal(signal.SIGINT, signal.SIG_DFL); "
            "os.execvp(sys.argv[1], sys.argv[1:])")
QUERY = """{ assetNodes { assetKey { path } groupName }
  repositoriesOrError { ... on RepositoryConnection { nodes { name
    sensors { name sensorState { status } } schedules { name scheduleState { status } } jobs { name } } } } }"""


def _get(url: str, data: bytes | None = None, timeout: float = 5.0):
    req = urllib.request.Request(url, data=data, headers={"Content-Type": "application/json"} if data else {})
    with urllib.request.urlopen(req, timeout=timeout) as r:
        return r.status, r.read()


def test_dagster_dev_serves_the_code_location_and_stops_cleanly():

    from pipelines.definitions import build_definitions

    root = Path(tempfile.mkdtemp(prefix="imulab-dev-", dir=SHM))
    home = root / "dagster_home"
    home.mkdir()
    (home / "dagster.yaml").write_text("telemetry:\n  enabled: false\n")
    port = free_port()
    env = {**os.environ, "DAGSTER_HOME": str(home), "IMULAB_LANDING": str(root / "landing"),
           "IMULAB_STORE": str(root / "store"), "PYTHONWARNINGS": "ignore"}
    (root / "landing").mkdir()
    log = open(root / "dev.log", "wb")
    proc = subprocess.Popen([sys.executable, "-c", LAUNCHER, "dagster", "dev", "-w", "workspace.yaml",
                             "-h", "127.0.0.1", "-p", str(port)], cwd=REPO, env=env, stdout=log,
                            stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL, start_new_session=True)
    seen = {proc.pid}
    try:
        deadline = time.time() + 150
        while True:
            try:
                if _get(f"http://127.0.0.1:{port}/server_info")[0] == 200:
                    break
            except OSError:
                pass
            assert proc.poll() is None, (root / "dev.log").read_text()[-3000:]
            assert time.time() < deadline, "dagster dev did not answer /server_info"
            time.sleep(0.5)
        # the code server may still be loading: retry until the asset graph is there
        expected = build_definitions(str(root / "landing"), str(root / "store"))
        want = {(n.key.to_user_string(), n.group_name) for n in expected.resolve_asset_graph().asset_nodes}
        while True:
            status, body = _get(f"http://127.0.0.1:{port}/graphql", json.dumps({"query": QUERY}).encode(), 30)
            data = json.loads(body).get("data") or {}
            nodes = data.get("assetNodes") or []
            if nodes or time.time() > deadline:
                break
            time.sleep(1)
        got = {("/".join(n["assetKey"]["path"]), n["groupName"]) for n in nodes}
        assert got == want
        groups = {g for _, g in got}
        assert "ingest" in groups and len(groups) >= 1
        (repo,) = data["repositoriesOrError"]["nodes"]
        sensors = {s["name"]: s["sensorState"]["status"] for s in repo["sensors"]}
        schedules = {s["name"]: s["scheduleState"]["status"] for s in repo["schedules"]}
        assert sensors.get("landing_sensor") == "RUNNING"
        assert set(sensors) == {s.name for s in expected.sensors}
        assert set(schedules) == {s.name for s in expected.schedules}
        assert all(v == "STOPPED" for v in schedules.values())
        assert {"calibrate_captures"} <= {j["name"] for j in repo["jobs"]}
        seen |= descendants(proc.pid)
        assert len(seen) >= 4, f"expected dev, webserver, daemon and code server processes, saw {seen}"
    finally:
        seen |= descendants(proc.pid)
        t0 = time.time()
        proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(60)
        except subprocess.TimeoutExpired:
            pass
        while alive(seen) and time.time() - t0 < 60:
            time.sleep(0.2)
        left = alive(seen) | group_members(proc.pid)
        for p in left:
            os.kill(p, signal.SIGKILL)
        log.close()
        shutil.rmtree(root, ignore_errors=True)
    assert proc.returncode is not None, "dagster dev ignored SIGTERM"
    assert not left, f"processes left after SIGTERM: {left}"
    print(f"\ndagster dev: {len(seen)} processes, all gone {time.time() - t0:.1f} s after SIGTERM")
