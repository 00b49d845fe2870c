"""The imulab code location with the dagster-celery executor: every step of a run goes to a Celery worker.

Use it where runs are launched (``dagster job execute -m pipelines.celery_defs ...``, or as the code location of a
deployment whose workers listen on the same broker). Configuration comes from the environment, so the run
coordinator and every worker build the same definitions:

- ``IMULAB_CELERY_BROKER`` (default ``redis://127.0.0.1:6379/0``) and ``IMULAB_CELERY_BACKEND`` (default: the
  broker URL with database 1): the Celery broker and result backend;
- ``IMULAB_LANDING`` / ``IMULAB_STORE``: the archive and the store, which must be the same paths (a shared volume
  or object storage mounted the same way) on the coordinator and on every worker;
- ``DAGSTER_HOME``: an instance on PostgreSQL shared by all (SQLite cannot be shared between machines).

Steps exchange nothing through IO managers: every stage writes its own versioned parquet through
``ParquetStore`` and returns a ``MaterializeResult``, so the default filesystem IO manager (required by the
executor, "artifacts persisted") only ever stores nothing. Workers: ``dagster-celery worker start -A
dagster_celery.app -y celery.yaml`` (see docs/deployment.md).
"""

from __future__ import annotations

import os

from dagster_celery import celery_executor

from pipelines.location import build_definitions, default_paths
from pipelines.resources import WorkspaceLock


def celery_config() -> dict:
    broker = os.environ.get("IMULAB_CELERY_BROKER", "redis://127.0.0.1:6379/0")
    backend = os.environ.get("IMULAB_CELERY_BACKEND") or broker.rsplit("/", 1)[0] + "/1"
    return {
        "broker": broker,
        "backend": backend,
        # a worker holds at most the task it runs (late ack + prefetch 1): work spreads over idle workers
        "config_source": {"task_acks_late": True, "worker_prefetch_multiplier": 1},
    }


# steps run on other machines: a local flock would not exclude anything there (pipelines.resources.WorkspaceLock)
defs = build_definitions(executor=celery_executor.configured(celery_config()),
                         extra_resources={"workspace_lock": WorkspaceLock(store_dir=default_paths()[1], enabled=False)})
