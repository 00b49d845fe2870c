"""Real local services for the scale-out tests and benchmarks: PostgreSQL and Redis from Debian's packages,
dagster-celery workers, all on 127.0.0.1, in temp dirs, each started in its own process group and stopped
(with a check that no process of theirs is left).

Install the services with ``.ci/services.sh`` (apt-get); ``missing()`` says what is absent so tests can skip.
"""

from __future__ import annotations

import glob
import os
import pwd
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from prod_helpers import SHM, free_port

REPO = Path(__file__).resolve().parents[1]


def _pg_bindir() -> Path | None:
    for cand in sorted(glob.glob("/usr/lib/postgresql/*/bin"), reverse=True):
        if Path(cand, "postgres").is_file() and Path(cand, "initdb").is_file():
            return Path(cand)
    exe = shutil.which("postgres")
    return Path(exe).resolve().parent if exe and Path(exe).resolve().with_name("initdb").is_file() else None


def missing() -> list[str]:
    """What the distributed test needs and is not installed (empty when everything is there)."""
    out = []
    if shutil.which("redis-server") is None:
        out.append("redis-server (apt-get install redis-server)")
    if _pg_bindir() is None:
        out.append("PostgreSQL server binaries (apt-get install postgresql)")
    elif os.geteuid() == 0:
        try:
            pwd.getpwnam("postgres")
        except KeyError:
            out.append("a 'postgres' system user (created by the postgresql package) to run the server as")
    for mod, pkg in (("dagster_celery", "dagster-celery"), ("dagster_postgres", "dagster-postgres"), ("redis", "redis"),
                     ("psycopg2", "psycopg2-binary")):
        try:
            __import__(mod)
        except ImportError:
            out.append(f"python package {pkg} (pip install -e '.[test]')")
    return out


# ---------------------------------------------------------------------------------------------------------------
# process bookkeeping through /proc (psutil may not be installed)
# ---------------------------------------------------------------------------------------------------------------
def _stat(pid: int) -> tuple[int, int] | None:
    """(ppid, pgrp) of a live, non-zombie process."""
    try:
        text = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return None
    fields = text.rsplit(")", 1)[1].split()
    if fields[0] == "Z":
        return None
    return int(fields[1]), int(fields[2])


def all_pids() -> list[int]:
    return [int(p) for p in os.listdir("/proc") if p.isdigit()]


def descendants(pid: int) -> set[int]:
    children: dict[int, list[int]] = {}
    for p in all_pids():
        st = _stat(p)
        if st:
            children.setdefault(st[0], []).append(p)
    out, todo = set(), [pid]
    while todo:
        for c in children.get(todo.pop(), []):
            if c not in out:
                out.add(c)
                todo.append(c)
    return out


def alive(pids) -> set[int]:
    return {p for p in pids if _stat(p) is not None}


def group_members(pgid: int) -> set[int]:
    return {p for p in all_pids() if (st := _stat(p)) and st[1] == pgid}


class Service:
    """A process started in its own session; ``stop`` signals the group and checks nothing is left."""

    name = "service"

    def __init__(self):
        self.proc: subprocess.Popen | None = None
        self.seen: set[int] = set()

    def _spawn(self, args, log: Path, **kw) -> None:
        self.log = log
        self.proc = subprocess.Popen([str(a) for a in args], stdout=open(log, "ab"), stderr=subprocess.STDOUT,
                                     stdin=subprocess.DEVNULL, start_new_session=True, **kw)
        self.seen = {self.proc.pid}

    def track(self) -> None:
        if self.proc is not None:
            self.seen |= {self.proc.pid} | descendants(self.proc.pid) | group_members(self.proc.pid)

    def stop(self, sig=signal.SIGTERM, timeout: float = 30.0) -> set[int]:
        """Signal the process group, wait, escalate to SIGKILL; returns the pids still alive (should be none)."""
        if self.proc is None:
            return set()
        self.track()
        pgid = self.proc.pid
        try:
            os.killpg(pgid, sig)
        except ProcessLookupError:
            pass
        deadline = time.time() + timeout
        while time.time() < deadline and (alive(self.seen) or self.proc.poll() is None):
            time.sleep(0.1)
        left = alive(self.seen) | group_members(pgid)
        if left:
            for p in left:
                try:
                    os.kill(p, signal.SIGKILL)
                except ProcessLookupError:
                    pass
        try:
            self.proc.wait(5)
        except subprocess.TimeoutExpired:
            pass
        return left

    def tail(self, n: int = 40) -> str:
        try:
            return "\n".join(Path(self.log).read_text(errors="replace").splitlines()[-n:])
        except OSError:
            return ""


class LocalPostgres(Service):
    """A throw-away PostgreSQL cluster on 127.0.0.1:<free port>, user ``imulab`` (trust auth), db ``postgres``."""

    name = "postgres"

    def __init__(self):
        super().__init__()
        # its own dir, traversable by the 'postgres' user (a pytest or mkdtemp dir is 0700)
        self.root = Path(tempfile.mkdtemp(prefix="imulab-pg-", dir=SHM))
        self.port = free_port()
        self.user = "imulab"
        self.db = "postgres"

    def start(self, timeout: float = 60.0) -> "LocalPostgres":
        bindir = _pg_bindir()
        run_as = "postgres" if os.geteuid() == 0 else None
        self.root.mkdir(parents=True, exist_ok=True)
        os.chmod(self.root, 0o755)
        data, sock = self.root / "pgdata", self.root / "sock"
        for d in (data, sock):
            d.mkdir()
            if run_as:
                pw = pwd.getpwnam(run_as)
                os.chown(d, pw.pw_uid, pw.pw_gid)
        log = self.root / "postgres.log"
        log.touch()
        if run_as:
            os.chown(log, pwd.getpwnam(run_as).pw_uid, pwd.getpwnam(run_as).pw_gid)
        init = subprocess.run([str(bindir / "initdb"), "-D", str(data), "-U", self.user, "--auth=trust", "-E", "UTF8",
                               "--no-sync", "--no-instructions"], capture_output=True, text=True, user=run_as,
                              cwd=self.root)
        if init.returncode:
            raise RuntimeError(f"initdb failed:\n{init.stdout[-2000:]}\n{init.stderr[-2000:]}")
        self._spawn([bindir / "postgres", "-D", data, "-c", "listen_addresses=127.0.0.1", "-c", f"port={self.port}",
                     "-c", f"unix_socket_directories={sock}", "-c", "fsync=off", "-c", "synchronous_commit=off",
                     "-c", "full_page_writes=off", "-c", "max_connections=300"], log, user=run_as, cwd=self.root)
        import psycopg2

        deadline = time.time() + timeout
        while True:
            try:
                psycopg2.connect(host="127.0.0.1", port=self.port, user=self.user, dbname=self.db).close()
                return self
            except psycopg2.OperationalError:
                if self.proc.poll() is not None or time.time() > deadline:
                    raise RuntimeError(f"postgres did not start:\n{self.tail()}")
                time.sleep(0.2)

    def stop(self, sig=signal.SIGINT, timeout: float = 30.0) -> set[int]:  # SIGINT: fast shutdown
        left = super().stop(sig, timeout)
        shutil.rmtree(self.root, ignore_errors=True)
        return left

    def dagster_yaml(self) -> str:
        return ("storage:\n  postgres:\n    postgres_db:\n"
                f"      username: {self.user}\n      password: ''\n      hostname: 127.0.0.1\n"
                f"      db_name: {self.db}\n      port: {self.port}\n"
                "      scheme: postgresql+psycopg2\n"  # SQLAlchemy 2.1 defaults postgresql:// to psycopg 3
                "telemetry:\n  enabled: false\n")


class LocalRedis(Service):
    name = "redis"

    def __init__(self, root: Path):
        super().__init__()
        self.root = Path(root)
        self.port = free_port()

    def url(self, db: int) -> str:
        return f"redis://127.0.0.1:{self.port}/{db}"

    def start(self, timeout: float = 30.0) -> "LocalRedis":
        self.root.mkdir(parents=True, exist_ok=True)
        self._spawn(["redis-server", "--port", self.port, "--bind", "127.0.0.1", "--save", "", "--appendonly", "no",
                     "--dir", self.root, "--daemonize", "no", "--protected-mode", "yes"], self.root / "redis.log")
        import redis

        deadline = time.time() + timeout
        while True:
            try:
                if redis.Redis(host="127.0.0.1", port=self.port, socket_timeout=1).ping():
                    return self
            except redis.exceptions.ConnectionError:
                pass
            if self.proc.poll() is not None or time.time() > deadline:
                raise RuntimeError(f"redis did not start:\n{self.tail()}")
            time.sleep(0.1)


def celery_yaml(path: Path, broker: str, backend: str) -> Path:
    """The executor config block the workers read (`dagster-celery worker start -y`)."""
    path.write_text("execution:\n  config:\n"
                    f"    broker: '{broker}'\n    backend: '{backend}'\n"
                    "    config_source:\n      task_acks_late: true\n      worker_prefetch_multiplier: 1\n")
    return path


class CeleryWorker(Service):
    """``dagster-celery worker start -A dagster_celery.app -y celery.yaml -n NAME -- --concurrency=1``."""

    name = "celery worker"

    def __init__(self, name: str, config_yaml: Path, env: dict, log_dir: Path):
        super().__init__()
        self.worker_name = name
        self.config_yaml, self.env, self.log_dir = config_yaml, env, Path(log_dir)

    def start(self) -> "CeleryWorker":
        exe = Path(sys.executable).with_name("dagster-celery")
        cmd = [str(exe) if exe.is_file() else "dagster-celery", "worker", "start", "-A", "dagster_celery.app",
               "-y", str(self.config_yaml), "-n", self.worker_name, "--loglevel", "INFO",
               "--", "--concurrency=1", "--without-gossip", "--without-mingle", "--without-heartbeat"]
        self._spawn(cmd, self.log_dir / f"{self.worker_name}.log", env=self.env, cwd=REPO)
        return self


def wait_for_workers(broker: str, names: list[str], timeout: float = 90.0) -> list[str]:
    """Ping the workers through the broker until every one in ``names`` answers."""
    from celery import Celery

    app = Celery("imulab-ping", broker=broker)
    deadline = time.time() + timeout
    seen: set[str] = set()
    try:
        while time.time() < deadline:
            for reply in app.control.ping(timeout=1.0) or []:
                seen |= {k.split("@", 1)[0] for k in reply}
            if set(names) <= seen:
                return sorted(seen)
            time.sleep(0.5)
    finally:
        app.close()
    raise RuntimeError(f"celery workers {sorted(set(names) - seen)} did not come up (saw {sorted(seen)})")
