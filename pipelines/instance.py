"""The Dagster instance of a workspace, created once and used by one ``imulab run`` at a time.

- ``open_instance``: the persistent SQLite instance in a Dagster home, created (``dagster.yaml`` and every
  storage's schema) under an exclusive file lock, so two processes starting on a new folder cannot both create
  the schema (two alembic heads break the instance for good).
- ``acquire_run_lock`` / ``run_lock``, ``note_archive`` / ``recorded_archive``: in ``pipelines.workspace`` (no
  Dagster import there), re-exported here.
- ``fail_abandoned_runs``: runs launched in process by imulab whose process is gone (killed) stay STARTED in
  Dagster forever; at the next start, holding the lock, they are marked failed with the reason.
"""

from __future__ import annotations

import os
import socket
from pathlib import Path

import dagster as dg
from filelock import FileLock

# the run lock lives in a module without Dagster (an unchanged archive answers without importing it); re-exported
from pipelines.workspace import (  # noqa: F401
    DEFAULT_LOCK_TIMEOUT_S,
    RUN_LOCK,
    RUN_OWNER,
    RunLockedError,
    acquire_run_lock,
    note_archive,
    recorded_archive,
    run_lock,
)

CREATE_LOCK = ".imulab-instance.lock"
#: tags on every run imulab launches in process: who ran it (to recognise a killed run later)
PID_TAG, HOST_TAG = "imulab/pid", "imulab/host"
ACTIVE = (dg.DagsterRunStatus.STARTED, dg.DagsterRunStatus.STARTING, dg.DagsterRunStatus.CANCELING)


def process_tags() -> dict[str, str]:
    return {PID_TAG: str(os.getpid()), HOST_TAG: socket.gethostname()}


def open_instance(dagster_home: str | os.PathLike | None = None) -> dg.DagsterInstance:
    """A persistent instance in ``dagster_home`` (or $DAGSTER_HOME), so ``dagster dev`` shows the same runs; its
    configuration and storage schemas are created once, under a file lock."""
    home = dagster_home or os.environ.get("DAGSTER_HOME")
    if home is None:
        raise ValueError("no Dagster home given and DAGSTER_HOME is not set")
    home = Path(home).resolve()
    home.mkdir(parents=True, exist_ok=True)
    with FileLock(str(home / CREATE_LOCK)):
        cfg = home / "dagster.yaml"
        if not cfg.exists():
            tmp = home / f".dagster.yaml.{os.getpid()}"
            tmp.write_text("telemetry:\n  enabled: false\n")
            os.replace(tmp, cfg)
        instance = dg.DagsterInstance.from_config(str(home))
        # touch every storage while holding the lock: schemas are created (and stamped) by exactly one process
        instance.get_runs(limit=1)
        instance.get_dynamic_partitions("captures")
        instance.all_instigator_state()
    return instance


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def fail_abandoned_runs(instance: dg.DagsterInstance) -> list[str]:
    """Mark failed every run launched in process by imulab on this host that is still STARTED although its
    process is gone (killed). Call it holding ``run_lock``. Returns the run ids marked."""
    host = socket.gethostname()
    marked = []
    for run in instance.get_runs(filters=dg.RunsFilter(statuses=list(ACTIVE))):
        if run.remote_job_origin is not None:  # launched by a daemon / webserver: Dagster's run monitoring owns it
            continue
        pid_tag, run_host = run.tags.get(PID_TAG), run.tags.get(HOST_TAG)
        pid = int(pid_tag) if pid_tag and pid_tag.isdigit() else None
        if run_host not in (None, host) or (pid is not None and (pid == os.getpid() or _alive(pid))):
            continue
        instance.report_run_failed(run, f"abandoned: the process that ran it (pid {pid or 'unknown'}) is gone "
                                        "(killed or crashed); marked failed by the next imulab run")
        marked.append(run.run_id)
    return marked
