"""Resources: the lab archive (landing folder of raw runs, read-only) and the versioned parquet store."""

from __future__ import annotations

from pathlib import Path

import dagster as dg

from pipelines.partitions import capture_key, split_capture_key
from pipelines.storage import VersionedStore
from raw_schemas.readers import discover_runs


class LabArchive(dg.ConfigurableResource):
    """The landing folder where capture jobs drop ``<device>/<run>/`` folders. imulab only reads it."""

    landing_dir: str

    def complete_runs(self) -> dict[str, Path]:
        """Partition key -> folder of every run whose ``_COMPLETE`` marker exists."""
        root = Path(self.landing_dir)
        if not root.is_dir():
            return {}
        return {capture_key(p.parent.name, p.name): p for p in discover_runs(root)}

    def run_dir(self, partition_key: str) -> Path:
        device_id, run_id = split_capture_key(partition_key)
        return Path(self.landing_dir) / device_id / run_id


class ParquetStore(dg.ConfigurableResource):
    """Versioned parquet outputs under ``root`` (see ``pipelines.storage``)."""

    root: str

    @property
    def store(self) -> VersionedStore:
        return VersionedStore(Path(self.root))
