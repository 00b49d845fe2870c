"""Resources: the lab archive (landing folder of raw runs, read-only) and the versioned parquet store, as thin
Dagster wrappers of ``assets_lib.store.LandingArchive`` and ``assets_lib.store.VersionedStore``; and the
workspace lock every stage asset holds for the length of a run (``WorkspaceLock``)."""

from __future__ import annotations

import contextlib
import os
from pathlib import Path

import dagster as dg

from assets_lib.store import LandingArchive, VersionedStore


class LabArchive(dg.ConfigurableResource):
    """The landing folder where capture jobs drop ``<device>/<run>/`` folders. imulab only reads it."""

    landing_dir: str

    @property
    def archive(self) -> LandingArchive:
        return LandingArchive(Path(self.landing_dir))

    def complete_runs(self) -> dict[str, Path]:
        """Partition key -> folder of every run whose ``_COMPLETE`` marker exists."""
        return self.archive.complete_runs()

    def run_dir(self, partition_key: str) -> Path:
        return self.archive.run_dir(partition_key)


class ParquetStore(dg.ConfigurableResource):
    """Versioned parquet outputs under ``root`` (see ``assets_lib.store.versioned``)."""

    root: str

    @property
    def store(self) -> VersionedStore:
        return VersionedStore(Path(self.root))


class WorkspaceLock(dg.ConfigurableResource):
    """The run lock of ``imulab run`` (``pipelines.workspace``) over the store and the instance's home, held for
    the length of a run that imulab did not execute itself: runs the daemon launches for the landing sensor or a
    reprocessing schedule, or a launch from the UI, wait for an ``imulab run`` / ``imulab reprocess`` on the same
    workspace (and it waits for them). Runs imulab executes in its own process carry its pid (``imulab/pid``) and
    hold the lock already. ``enabled=False`` (the Celery location: steps on other machines, where a local
    ``flock`` means nothing) turns it off."""

    store_dir: str
    enabled: bool = True

    @contextlib.contextmanager
    def yield_for_execution(self, context: dg.InitResourceContext):
        from pipelines.instance import PID_TAG
        from pipelines.workspace import acquire_run_lock

        run = context.run
        if not self.enabled or (run is not None and run.tags.get(PID_TAG) == str(os.getpid())):
            yield self
            return
        home = getattr(context.instance, "root_directory", None) if context.instance is not None else None
        dirs = [Path(home), Path(self.store_dir)] if home else [Path(self.store_dir), None]
        held = acquire_run_lock(dirs[0], dirs[1], echo=context.log.info if context.log else print)
        try:
            yield self
        finally:
            held.close()
