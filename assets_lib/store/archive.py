"""The lab archive: the landing folder where capture jobs drop ``<device>/<run>/`` folders. imulab only reads it."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from assets_lib.store.keys import capture_key, split_capture_key
from raw_schemas.readers import discover_runs


@dataclass(frozen=True)
class LandingArchive:
    landing_dir: Path

    def complete_runs(self) -> dict[str, Path]:
        """Partition key -> folder of every run whose ``_COMPLETE`` marker exists."""
        root = Path(self.landing_dir)
        if not root.is_dir():
            return {}
        return {capture_key(p.parent.name, p.name): p for p in discover_runs(root)}

    def incomplete_runs(self) -> list[str]:
        """Partition keys of run folders without ``_COMPLETE`` (a capture job still writing, or one that died)."""
        root = Path(self.landing_dir)
        if not root.is_dir():
            return []
        done = set(self.complete_runs())
        return sorted(capture_key(d.name, r.name) for d in root.iterdir() if d.is_dir() and not d.name.startswith(("_", "."))
                      for r in d.iterdir() if r.is_dir() and not r.name.startswith(("_", "."))
                      and capture_key(d.name, r.name) not in done)

    def run_dir(self, partition_key: str) -> Path:
        device_id, run_id = split_capture_key(partition_key)
        return Path(self.landing_dir) / device_id / run_id
