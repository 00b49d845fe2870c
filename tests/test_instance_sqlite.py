"""The SQLite tuning of an instance opened by ``pipelines.instance.open_instance`` (``tune_sqlite``): Dagster's own
per-event connections use ``synchronous=NORMAL`` and an idle reader per database keeps the WAL from being
checkpointed at every close; databases outside the instance's home are left as SQLite makes them; every event is
still stored and readable. Real Dagster runs on a real SQLite instance."""

from pathlib import Path

import dagster as dg
from sqlalchemy import create_engine
from sqlalchemy.pool import NullPool

from pipelines import instance as inst_mod
from pipelines.instance import open_instance, release_sqlite


@dg.op
def _one() -> int:
    return 1


@dg.job
def _tiny():
    _one()


def test_instance_databases_are_tuned_and_keep_every_event(tmp_path):
    home = tmp_path / "home"
    with open_instance(home) as instance:
        res = _tiny.execute_in_process(instance=instance)
        assert res.success
        storage = instance.event_log_storage
        with storage.index_connection() as conn:
            assert conn.exec_driver_sql("PRAGMA synchronous").scalar() == 1  # NORMAL
            assert conn.exec_driver_sql("PRAGMA journal_mode").scalar().lower() == "wal"
        with storage.run_connection(res.run_id) as conn:
            assert conn.exec_driver_sql("PRAGMA synchronous").scalar() == 1
        kept = [p for p in inst_mod._KEEP_OPEN if p.startswith(str(home.resolve()))]
        assert any(p.endswith("index.db") for p in kept)
        # the event log keeps one engine (one open connection) per database, the run's among them, instead of
        # building an engine per event; open, the database keeps its WAL instead of a checkpoint at each close
        assert isinstance(storage, inst_mod.PooledSqliteEventLogStorage)
        assert res.run_id in storage._engines and "index" in storage._engines
        assert Path(storage.path_for_shard(res.run_id) + "-wal").exists()
        events = instance.all_logs(res.run_id)
        assert {"STEP_SUCCESS", dg.DagsterEventType.RUN_SUCCESS.value} <= {e.dagster_event.event_type_value for e in events if e.is_dagster_event}
    assert not storage._engines  # closed with the instance
    assert release_sqlite(home) == len(kept)
    assert not [p for p in inst_mod._KEEP_OPEN if p.startswith(str(home.resolve()))]
    # reopened from disk (another process would see the same): every event is there
    with open_instance(home) as again:
        assert len(again.all_logs(res.run_id)) == len(events)
    release_sqlite(home)


def test_databases_outside_the_instance_home_are_untouched(tmp_path):
    open_instance(tmp_path / "home").dispose()
    release_sqlite(tmp_path / "home")
    other = tmp_path / "elsewhere.db"
    engine = create_engine(f"sqlite:///{other}", poolclass=NullPool)
    with engine.connect() as conn:
        assert conn.exec_driver_sql("PRAGMA synchronous").scalar() == 2  # SQLite's default, FULL
    engine.dispose()
    assert str(other) not in inst_mod._KEEP_OPEN
