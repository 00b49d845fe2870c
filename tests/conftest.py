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
# test modules are run in a second process, on the other core, while the rest of the suite goes on, and the
# module's tests wait for them and make their assertions on what they left. Such a module lists its jobs in
# ``BACKGROUND_JOBS``: names of module functions taking a work dir (the code its tests ran in process before); a
# test gets a job's finished work dir with ``background_job(name)``. The jobs of the modules of the selected tests
# that use the fixture run one at a time, in collection order (so at most two cores are busy; the job's numerical
# libraries on one thread), not niced (on a loaded machine a niced job starves and the suite waits for it).
# Nothing is shared: a job writes only under its own work dir (tmpfs when there is one), removed at session end.
# ------------------------------------------------------------------------------------------------------------------
_ONE_THREAD = {k: "1" for k in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS")}
#: runs ``<function>(Path(<work dir>))`` of a test module loaded from its file
_RUNNER = ("import sys, importlib.util as u; from pathlib import Path; "
           "s = u.spec_from_file_location('imulab_background_job', sys.argv[1]); m = u.module_from_spec(s); "
           "s.loader.exec_module(m); getattr(m, sys.argv[2])(Path(sys.argv[3]))")


class BackgroundJob:
    def __init__(self, module_file: Path, name: str):
        self.module_file, self.name = Path(module_file), name
        self.label = f"{self.module_file.name}::{name}"
        self.proc: subprocess.Popen | None = None
        self.done = threading.Event()
        self.cancelled = self.queued = False
        self.lock = threading.Lock()
        self.elapsed_s = self.waited_s = self.cpu_s = None
        shm = Path("/dev/shm")
        self.workdir = Path(tempfile.mkdtemp(prefix=f"imulab-bg-{name}-",
                                             dir=shm if shm.is_dir() and os.access(shm, os.W_OK) else None))
        self.log = self.workdir / "job.log"
        (self.workdir / "work").mkdir()

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
                    self.proc = subprocess.Popen([sys.executable, "-c", _RUNNER, str(self.module_file), self.name,
                                                  str(self.workdir / "work")], cwd=REPO, env=env, stdout=log,
                                                 stderr=subprocess.STDOUT,
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
        self.waited_s = (self.waited_s or 0.0) + time.monotonic() - t0
        rc = None if self.proc is None else self.proc.returncode
        if rc != 0:
            log = self.log.read_text() if self.log.is_file() else "(not started)"
            pytest.fail(f"background job {self.label} exited {rc}:\n{log[-5000:]}")
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


_JOBS: dict[tuple[str, str], BackgroundJob] = {}


def _module_jobs(module) -> list[BackgroundJob]:
    """The module's jobs, created (not started) on first use."""
    names = getattr(module, "BACKGROUND_JOBS", ())
    assert names, f"{module.__name__} uses background_job but lists no BACKGROUND_JOBS"
    out = []
    for name in names:
        key = (module.__file__, name)
        if key not in _JOBS:
            _JOBS[key] = BackgroundJob(Path(module.__file__), name)
            out.append(_JOBS[key])
    return out


def _run_queue(jobs: list[BackgroundJob]) -> None:
    for job in jobs:
        job.run()


def pytest_collection_finish(session):
    queue = []
    for item in session.items:  # the selected tests: a module's jobs are queued if one of them will wait for them
        mod = getattr(item, "module", None)
        if mod is not None and "background_job" in getattr(item, "fixturenames", ()):
            queue += _module_jobs(mod)
    if queue and not session.config.option.collectonly:
        for job in queue:
            job.queued = True
        threading.Thread(target=_run_queue, args=(queue,), name="imulab-background-jobs", daemon=True).start()


def pytest_terminal_summary(terminalreporter):
    for job in _JOBS.values():
        if job.elapsed_s is not None:
            cpu = "" if job.cpu_s is None else f" ({job.cpu_s:.1f} s CPU)"
            waited = "" if job.waited_s is None else f", its tests waited {job.waited_s:.1f} s for it"
            terminalreporter.write_line(f"background job {job.label}: {job.elapsed_s:.1f} s{cpu}{waited}")


def pytest_sessionfinish(session):
    for job in _JOBS.values():
        job.close()


@pytest.fixture(scope="module")
def background_job(request):
    """``background_job(name)``: the finished work dir of this module's job ``name`` (run now if not queued)."""
    module = request.module

    def get(name: str) -> Path:
        assert name in getattr(module, "BACKGROUND_JOBS", ()), f"{name} is not in {module.__name__}.BACKGROUND_JOBS"
        key = (module.__file__, name)
        if key not in _JOBS:
            _module_jobs(module)
        job = _JOBS[key]
        if not job.queued:
            job.queued = True
            job.run()  # nothing queued it: run it now
        return job.wait()

    return get
