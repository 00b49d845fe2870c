"""The workspace of ``imulab run`` without Dagster (importing Dagster costs about a second; an unchanged archive
answers without it).

- ``acquire_run_lock`` / ``run_lock``: an exclusive lock on the Dagster home and the store for a whole
  ``imulab run`` or ``imulab reprocess`` (and every run the Dagster daemon launches, through the ``workspace_lock``
  resource): a second one waits for the first (printing who holds the lock) or, past its timeout, refuses with a
  clear message. Locks are ``flock`` locks (``filelock``): the kernel releases them when the holder dies, so a
  killed run never leaves a stale lock.
- ``RunState``: what the last ``imulab run`` left in the Dagster home (``.imulab-state.json``): whether it finished
  (a killed run leaves ``clean: false``) and the capture partitions registered on the instance. When it finished
  and every completed run of the archive is registered, the next run may plan without opening the instance.
- ``note_archive`` / ``recorded_archive``: the store remembers the archive it was computed from (``ARCHIVE``), so
  ``imulab verify`` finds it from any working directory.
"""

from __future__ import annotations

import contextlib
import json
import os
import socket
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

from filelock import FileLock, Timeout

RUN_LOCK = ".imulab-run.lock"
RUN_OWNER = ".imulab-run.owner.json"
STATE_FILE = ".imulab-state.json"
ARCHIVE_FILE = "ARCHIVE"
#: default wait for a run lock (s); IMULAB_LOCK_TIMEOUT_S overrides it (0: refuse at once)
DEFAULT_LOCK_TIMEOUT_S = 3600.0


class RunLockedError(RuntimeError):
    """Another ``imulab run`` holds the workspace and did not finish within the timeout."""


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


@dataclass
class RunState:
    """What the last ``imulab run`` on a Dagster home left: ``clean`` (it finished), the store it wrote and the
    capture partitions registered on the instance when it finished."""

    clean: bool = False
    store: str = ""
    captures: list[str] = field(default_factory=list)

    @staticmethod
    def read(dagster_home: Path) -> RunState:
        try:
            d = json.loads((Path(dagster_home) / STATE_FILE).read_text())
            return RunState(bool(d.get("clean")), str(d.get("store", "")), list(d.get("captures", [])))
        except (OSError, ValueError, TypeError, AttributeError):
            return RunState()

    def write(self, dagster_home: Path) -> None:
        home = Path(dagster_home)
        home.mkdir(parents=True, exist_ok=True)
        tmp = home / f".{STATE_FILE}.{os.getpid()}"
        tmp.write_text(json.dumps({"clean": self.clean, "store": self.store, "captures": sorted(self.captures)}))
        os.replace(tmp, home / STATE_FILE)

    def covers(self, store: Path, capture_keys) -> bool:
        """The last run finished on ``store`` and registered every one of ``capture_keys``."""
        return self.clean and self.store == str(Path(store).resolve()) and set(capture_keys) <= set(self.captures)


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
