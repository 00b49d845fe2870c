"""The Dagster instance of a workspace, created once and used by one ``imulab run`` at a time.

- ``open_instance``: the persistent SQLite instance in a Dagster home, created (``dagster.yaml`` and every
  storage's schema) under an exclusive file lock, so two processes starting on a new folder cannot both create
  the schema (two alembic heads break the instance for good).
- ``acquire_run_lock`` / ``run_lock``, ``note_archive`` / ``recorded_archive``: in ``pipelines.workspace`` (no
  Dagster import there), re-exported here.
- ``fail_abandoned_runs``: runs launched in process by imulab whose process is gone (killed) stay STARTED in
  Dagster forever; at the next start, holding the lock, they are marked failed with the reason.
- ``tune_sqlite``: Dagster's SQLite storages open and close one connection per event (``NullPool``), so every event
  paid a commit fsync and, closing the database's last connection, a WAL checkpoint with more fsyncs (about 25 ms
  of I/O per event on a busy disk, most of a fresh run's Dagster cost). For the databases of an instance opened
  here, connections use ``synchronous=NORMAL`` (WAL mode: no fsync per commit, still safe against corruption; a
  power loss can lose the last events, never the parquet store, which is fsynced) and one idle reader per
  database stays open while the process runs, so closing an event's connection no longer checkpoints (SQLite's
  automatic checkpoint every 1000 pages still runs). Nothing else about the storage changes.
- ``PooledSqliteEventLogStorage``: Dagster's SQLite event log storage also builds a new SQLAlchemy engine for every
  connection (two per asset event: the run's database and the index); on a fresh run that was most of the CPU an
  event costs (each partition's materialization and planned events). The instance opened here keeps one engine,
  with one open connection, per database (the index and the last few runs), under the storage's own lock; the
  databases, their schema and every statement are Dagster's, so ``dagster dev`` and other processes read the
  same files as before.
"""

from __future__ import annotations

import atexit
import os
import socket
import sqlite3
import threading
from collections import OrderedDict
from contextlib import contextmanager
from pathlib import Path

import dagster as dg
from dagster._core.instance import InstanceType
from dagster._core.instance.factory import create_instance_from_ref
from dagster._core.instance.ref import InstanceRef
from dagster._core.storage.event_log.sqlite.sqlite_event_log import SqliteEventLogStorage
from dagster._core.storage.sqlite import SQLITE_BUSY_TIMEOUT_SECONDS
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


#: instance homes whose SQLite databases are tuned (``tune_sqlite``), and the idle reader kept open per database
_TUNED_HOMES: set[str] = set()
_KEEP_OPEN: OrderedDict[str, sqlite3.Connection] = OrderedDict()
#: at most this many idle readers at once (a test session opens many instances): the oldest is closed first
MAX_KEEP_OPEN = 16
_KEEP_LOCK = threading.Lock()
_LISTENING = False


def _tune_connection(dbapi_conn, _record) -> None:
    """SQLAlchemy ``connect`` hook: ``synchronous=NORMAL`` and an idle reader for databases of tuned homes."""
    if not isinstance(dbapi_conn, sqlite3.Connection) or not _TUNED_HOMES:
        return
    try:
        row = dbapi_conn.execute("PRAGMA database_list").fetchone()
        path = row[2] if row else ""
        if not path or not any(path.startswith(h) for h in _TUNED_HOMES):
            return
        dbapi_conn.execute("PRAGMA synchronous=NORMAL")
        # the reader must open the file once it is in WAL mode (Dagster switches a new database after its schema)
        if path in _KEEP_OPEN or dbapi_conn.execute("PRAGMA journal_mode").fetchone()[0].lower() != "wal":
            return
        keep = sqlite3.connect(path, check_same_thread=False, timeout=60)
        keep.execute("SELECT count(*) FROM sqlite_master").fetchall()  # attach to the WAL index; no transaction kept
    except sqlite3.Error:  # tuning is an optimisation only: never fail Dagster's own connection over it
        return
    with _KEEP_LOCK:
        if path in _KEEP_OPEN:
            keep.close()
            return
        _KEEP_OPEN[path] = keep
        while len(_KEEP_OPEN) > MAX_KEEP_OPEN:
            _KEEP_OPEN.popitem(last=False)[1].close()


def release_sqlite(home: str | os.PathLike | None = None) -> int:
    """Close the idle readers (of ``home``'s databases, or all); returns how many were closed."""
    prefix = None if home is None else str(Path(home).resolve())
    with _KEEP_LOCK:
        paths = [p for p in _KEEP_OPEN if prefix is None or p.startswith(prefix)]
        for p in paths:
            _KEEP_OPEN.pop(p).close()
    return len(paths)


def tune_sqlite(home: str | os.PathLike) -> None:
    """Tune the SQLite databases under ``home`` for this process (see the module docstring)."""
    global _LISTENING
    from sqlalchemy import event
    from sqlalchemy.engine import Engine

    _TUNED_HOMES.add(str(Path(home).resolve()) + os.sep)
    if not _LISTENING:
        event.listen(Engine, "connect", _tune_connection)
        atexit.register(release_sqlite)
        _LISTENING = True


class PooledSqliteEventLogStorage(SqliteEventLogStorage):
    """Dagster's SQLite event log storage with one engine (one open connection) per database instead of one per
    connection (module docstring). At most ``MAX_ENGINES`` databases are held open (least recently used closed
    first); ``dispose`` and ``wipe`` close them all."""

    MAX_ENGINES = 4

    def __init__(self, base_dir: str, inst_data=None):
        self._engines: OrderedDict = OrderedDict()
        super().__init__(base_dir, inst_data)

    @contextmanager
    def _connect(self, shard: str):
        from sqlalchemy import create_engine
        from sqlalchemy.pool import StaticPool

        with self._db_lock:  # one user of a connection at a time (the event log watcher runs in a thread)
            engine = self._engines.get(shard)
            if engine is None:
                engine = create_engine(self.conn_string_for_shard(shard), poolclass=StaticPool,
                                       connect_args={"timeout": SQLITE_BUSY_TIMEOUT_SECONDS, "check_same_thread": False})
                if shard not in self._initialized_dbs:
                    self._initdb(engine)
                    self._initialized_dbs.add(shard)
                self._engines[shard] = engine
                while len(self._engines) > self.MAX_ENGINES:
                    self._engines.popitem(last=False)[1].dispose()
            else:
                self._engines.move_to_end(shard)
            with engine.connect() as conn:
                with conn.begin():
                    yield conn

    def _close_engines(self) -> None:
        with self._db_lock:
            while self._engines:
                self._engines.popitem()[1].dispose()

    def wipe(self) -> None:
        self._close_engines()
        super().wipe()

    def dispose(self) -> None:
        self._close_engines()
        super().dispose()


def _instance_with_pooled_events(home: Path) -> dg.DagsterInstance:
    """The instance ``DagsterInstance.from_config(home)`` builds, its SQLite event log storage (the default; any
    other configured storage is kept as is) replaced by a ``PooledSqliteEventLogStorage`` on the same folder."""
    ref = InstanceRef.from_dir(str(home))
    unified = ref.storage
    events = unified.event_log_storage if unified else ref.event_storage
    if type(events) is not SqliteEventLogStorage or ref.custom_instance_class is not None:
        return create_instance_from_ref(ref)
    pooled = PooledSqliteEventLogStorage(events._base_dir, inst_data=events.inst_data)  # noqa: SLF001
    return dg.DagsterInstance(
        instance_type=InstanceType.PERSISTENT,
        local_artifact_storage=ref.local_artifact_storage,
        run_storage=unified.run_storage if unified else ref.run_storage,
        event_storage=pooled,
        schedule_storage=unified.schedule_storage if unified else ref.schedule_storage,
        compute_log_manager=None, scheduler=ref.scheduler, run_coordinator=None, run_launcher=None,
        settings=ref.settings, secrets_loader=ref.secrets_loader, defs_state_storage=ref.defs_state_storage,
        ref=ref)


def open_instance(dagster_home: str | os.PathLike | None = None) -> dg.DagsterInstance:
    """A persistent instance in ``dagster_home`` (or $DAGSTER_HOME), so ``dagster dev`` shows the same runs; its
    configuration and storage schemas are created once, under a file lock."""
    home = dagster_home or os.environ.get("DAGSTER_HOME")
    if home is None:
        raise ValueError("no Dagster home given and DAGSTER_HOME is not set")
    home = Path(home).resolve()
    home.mkdir(parents=True, exist_ok=True)
    tune_sqlite(home)
    with FileLock(str(home / CREATE_LOCK)):
        cfg = home / "dagster.yaml"
        if not cfg.exists():
            tmp = home / f".dagster.yaml.{os.getpid()}"
            tmp.write_text("telemetry:\n  enabled: false\n")
            os.replace(tmp, cfg)
        instance = _instance_with_pooled_events(home)
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
