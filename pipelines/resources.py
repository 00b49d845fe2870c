"""Resources: the lab archive (landing folder of raw runs, read-only) and the versioned parquet store, as thin
Dagster wrappers of ``assets_lib.store.LandingArchive`` and ``assets_lib.store.VersionedStore``."""

from __future__ import annotations

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
