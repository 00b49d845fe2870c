"""Shared fixtures: the reference data sets in ../shared/data (skipped with a reason when absent), and the
background jobs of the costliest test modules (below)."""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = Path(os.environ.get("IMULAB_SHARED_DATA", REPO.parent / "shared" / "data"))


@pytest.fixture(scope="session")
def shared_data() -> Path:
    if not SHARED_DATA.is_dir():
        pytest.skip(f"reference data not found at {SHARED_DATA} (set IMULAB_SHARED_DATA or place ../shared/data)")
    return SHARED_DATA


# ------------------------------------------------------------------------------------------------------------------
# Background jobs. The suite runs in one process, on one core; the costliest self-contained pipeline runs of a few
# test modules are run in a second process, on the other core, while the rest of the suite goes on, and the module's
# tests wait for them and make their assertions on what they left. A module opts in with ``BACKGROUND_JOB = True``
# and runs as ``python <module file> <work dir>`` (the same code its test ran in process before). The jobs of the
# collected modules run one at a time, in collection order (so at most two cores are busy, the job's numerical
# libraries on one thread); not niced: on a loaded machine a niced job starves and the suite waits for it. Nothing
# is shared: a job writes only under its own work dir (tmpfs when there is one), removed at the end of the session.
# ------------------------------------------------------------------------------------------------------------------
_ONE_THREAD = {k: "1" for k in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS")}


class BackgroundJob:
    def __init__(self, module_file: Path):
        self.module_file = Path(module_file)
        self.proc: subprocess.Popen | None = None
        self.done = threading.Event()
        self.cancelled = False
        self.lock = threading.Lock()
        self.elapsed_s = self.waited_s = self.cpu_s = None
        shm = Path("/dev/shm")
        self.workdir = Path(tempfile.mkdtemp(prefix=f"imulab-bg-{self.module_file.stem}-",
                                             dir=shm if shm.is_dir() and os.access(shm, os.W_OK) else None))
        self.log = self.workdir / "job.log"

    def run(self) -> None:
        """Start the job and wait for it (the queue's thread, or the test itself when no queue started it)."""
        try:
            path = os.pathsep.join([str(REPO), str(REPO / "tests"), *filter(None, [os.environ.get("PYTHONPATH")])])
            env = {**os.environ, **_ONE_THREAD, "PYTHONPATH": path, "PYTHONWARNINGS": "ignore"}
            env.pop("DAGSTER_HOME", None)
            with self.lock:
                if self.cancelled:
                    return
                self.started = time.monotonic()
                with open(self.log, "wb") as log:
                    self.proc = subprocess.Popen([sys.executable, str(self.module_file), str(self.workdir / "work")],
                                                 cwd=REPO, env=env, stdout=log, stderr=subprocess.STDOUT,
                                                 start_new_session=True)  # its own process group, killed as one
            if hasattr(os, "wait4"):  # the job's CPU time, its own and its children's
                try:
                    _, status, usage = os.wait4(self.proc.pid, 0)
                except ChildProcessError:  # reaped elsewhere
                    self.proc.wait()
                else:
                    self.proc.returncode = os.waitstatus_to_exitcode(status)
                    self.cpu_s = usage.ru_utime + usage.ru_stime
            else:
                self.proc.wait()
            self.elapsed_s = time.monotonic() - self.started
        finally:
            self.done.set()

    def wait(self) -> Path:
        """The job's work dir once it has finished; fails the test with the job's log if the job itself failed."""
        t0 = time.monotonic()
        self.done.wait()
        self.waited_s = time.monotonic() - t0
        rc = None if self.proc is None else self.proc.returncode
        if rc != 0:
            log = self.log.read_text() if self.log.is_file() else "(not started)"
            pytest.fail(f"background job {self.module_file.name} exited {rc}:\n{log[-5000:]}")
        return self.workdir / "work"

    def close(self) -> None:
        with self.lock:
            self.cancelled = True
        if self.proc is not None:
            if self.proc.returncode is None:
                try:
                    os.killpg(self.proc.pid, signal.SIGKILL)  # the job and the processes it started
                except (ProcessLookupError, PermissionError, AttributeError):
                    self.proc.kill()
            self.done.wait(timeout=60)  # the waiting thread reaps it
        shutil.rmtree(self.workdir, ignore_errors=True)


_JOBS: dict[str, BackgroundJob] = {}


def _run_queue(jobs: list[BackgroundJob]) -> None:
    for job in jobs:
        job.run()


def pytest_collection_finish(session):
    queue = []
    for item in session.items:
        mod = getattr(item, "module", None)
        if mod is not None and getattr(mod, "BACKGROUND_JOB", False) and mod.__file__ not in _JOBS:
            _JOBS[mod.__file__] = job = BackgroundJob(Path(mod.__file__))
            queue.append(job)
    if queue and not session.config.option.collectonly:
        threading.Thread(target=_run_queue, args=(queue,), name="imulab-background-jobs", daemon=True).start()


def pytest_terminal_summary(terminalreporter):
    for job in _JOBS.values():
        if job.elapsed_s is not None:
            cpu = "" if job.cpu_s is None else f" ({job.cpu_s:.1f} s CPU)"
            waited = "" if job.waited_s is None else f", its tests waited {job.waited_s:.1f} s for it"
            terminalreporter.write_line(f"background job {job.module_file.name}: {job.elapsed_s:.1f} s{cpu}{waited}")


def pytest_sessionfinish(session):
    for job in _JOBS.values():
        job.close()



@pytest.fixture(scope="module")
def background_job(request) -> Path:
    """The finished work dir of this module's background job (run now if the session did not queue it)."""
    f = request.module.__file__
    if f not in _JOBS:
        _JOBS[f] = BackgroundJob(Path(f))
        _JOBS[f].run()
    return _JOBS[f].wait()
