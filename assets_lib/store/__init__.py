"""The versioned, never-overwritten parquet store, its partition keys, the read view, and the raw lab archive."""

from assets_lib.store.archive import LandingArchive
from assets_lib.store.keys import FLEET_KEY, SEP, capture_key, split_capture_key
from assets_lib.store.versioned import (
           VersionedStore,
           version_id,
           write_parquet_deterministic,
)
from assets_lib.store.view import StoreView

__all__ = ["FLEET_KEY", "SEP", "LandingArchive", "StoreView", "VersionedStore", "capture_key", "split_capture_key",
           "version_id", "write_parquet_deterministic"]
