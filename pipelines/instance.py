"""The Dagster instance of a workspace, created once and used by one ``imulab run`` at a time.

- ``open_instance``: the persistent SQLite instance in a Dagster home, created (``dagster.yaml`` and every
  storage's schema) under an exclusive file lock, so two processes starting on a new folder cannot both create
  the schema (two alembic heads break the instance for good).
- ``acquire_run_lock`` / ``run_lock``: an exclusive lock on the Dagster home and the store for a whole
  ``imulab run``: a second run waits for the first (printing who holds the lock) or, past its timeout, refuses
  with a clear message. Locks are ``flock`` locks (``filelock``): the kernel releases them when the holder dies,
  so a killed run never leaves a stale lock.
- ``fail_abandoned_runs``: runs launched in process by imulab whose process is gone (killed) stay STARTED in
  Dagster forever; at the next start, holding the lock, they are marked failed with the reason.
- ``note_archive`` / ``recorded_archive``: the store remembers the archive it was computed from (``ARCHIVE``), so
  ``imulab verify`` finds it from any working directory.
"""

from __future__ import annotations

import contextlib
import json
import os
import socket
import time
from pathlib import Path
from typing import Callable, Iterator

import dagster as dg
from filelock import FileLock, Timeout

RUN_LOCK = ".imulab-run.lock"
RUN_OWNER = ".imulab-run.owner.json"
CREATE_LOCK = ".imulab-instance.lock"
ARCHIVE_FILE = "ARCHIVE"
#: tags on every run imulab launches in process: who ran it (to recognise a killed run later)
PID_TAG, HOST_TAG = "imulab/pid", "imulab/host"
#: default wait for a run lock (s); IMULAB_LOCK_TIMEOUT_S overrides it (0: refuse at once)
DEFAULT_LOCK_TIMEOUT_S = 3600.0
ACTIVE = (dg.DagsterRunStatus.STARTED, dg.DagsterRunStatus.STARTING, dg.DagsterRunStatus.CANCELING)


class RunLockedError(RuntimeError):
    """Another ``imulab run`` holds the workspace and did not finish within the timeout."""


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


def _owner(path: Path) -> str:
    try:
        o = json.loads(path.read_text())
        return f"pid {o['pid']} on {o['host']}, started {o['started_utc']}"
    except (OSError, ValueError, KeyError):
        return "owner unknown"


def acquire_run_lock(dagster_home: Path, store: Path | None = None, timeout_s: float | None = None,
                     echo: Callable[[str], None] = print) -> contextlib.ExitStack:
    """Hold the workspace (the Dagster home, then the store) for one run; returns the held locks (``close()``
    releases them; so does the end of the process). Waits up to ``timeout_s`` (default $IMULAB_LOCK_TIMEOUT_S or
    3600 s; 0 refuses at once) and raises ``RunLockedError`` naming the holder."""
    if timeout_s is None:
        timeout_s = float(os.environ.get("IMULAB_LOCK_TIMEOUT_S", DEFAULT_LOCK_TIMEOUT_S))
    dirs = [Path(dagster_home).resolve()]
    if store is not None and Path(store).resolve() != dirs[0]:
        dirs.append(Path(store).resolve())
    stack = contextlib.ExitStack()
    try:
        deadline = time.monotonic() + timeout_s
        for d in dirs:  # always home before store: two runs can never wait on each other in a cycle
            d.mkdir(parents=True, exist_ok=True)
            lock = FileLock(str(d / RUN_LOCK))
            try:
                lock.acquire(timeout=0)
            except Timeout:
                left = max(0.0, deadline - time.monotonic())
                if left <= 0:
                    raise RunLockedError(f"another imulab run is using {d} ({_owner(d / RUN_OWNER)}); refusing to "
                                         f"start (IMULAB_LOCK_TIMEOUT_S={timeout_s:g})") from None
                echo(f"another imulab run is using {d} ({_owner(d / RUN_OWNER)}); waiting for it to finish "
                     f"(up to {left:.3g} s)")
                try:
                    lock.acquire(timeout=left)
                except Timeout:
                    raise RunLockedError(f"another imulab run is still using {d} ({_owner(d / RUN_OWNER)}) after "
                                         f"{timeout_s:g} s; try again when it has finished") from None
            stack.callback(lock.release)
            tmp = d / f"{RUN_OWNER}.{os.getpid()}"
            tmp.write_text(json.dumps({"pid": os.getpid(), "host": socket.gethostname(),
                                       "started_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())}))
            os.replace(tmp, d / RUN_OWNER)
    except BaseException:
        stack.close()
        raise
    return stack


@contextlib.contextmanager
def run_lock(dagster_home: Path, store: Path | None = None, timeout_s: float | None = None,
             echo: Callable[[str], None] = print) -> Iterator[None]:
    """``acquire_run_lock`` as a context manager."""
    with acquire_run_lock(dagster_home, store, timeout_s, echo):
        yield


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


def note_archive(store: Path, landing: Path) -> None:
    """Remember in the store which archive it is computed from (read by ``imulab verify``)."""
    store = Path(store)
    store.mkdir(parents=True, exist_ok=True)
    tmp = store / f".{ARCHIVE_FILE}.{os.getpid()}"
    tmp.write_text(str(Path(landing).resolve()) + "\n")
    os.replace(tmp, store / ARCHIVE_FILE)


def recorded_archive(store: Path) -> Path | None:
    p = Path(store) / ARCHIVE_FILE
    try:
        return Path(p.read_text().strip()) if p.is_file() else None
    except OSError:
        return None
