"""The one read view over the store: given versions of upstream partitions, their tables, metadata and files.

A stage's compute function receives a ``StoreView`` bound to the partition it computes (``key``) and to the exact
upstream versions its own version was derived from (a device stage lists its device's captures with ``keys_of``, a
capture stage its siblings, the same device's captures of a sibling stage, with ``sibling_keys``); the records module reads a run's outputs through the same
view. Nothing here writes.
"""

from __future__ import annotations

import json
from pathlib import Path

import pandas as pd

from assets_lib.store.keys import split_capture_key
from assets_lib.store.versioned import META, VersionedStore, read_table


class StoreView:
    """Read access to given versions (``{"<asset>/<key>": version}``) of a ``VersionedStore``."""

    def __init__(self, store: VersionedStore, versions: dict[str, str], key: str | None = None,
                 archive=None, run_id: str | None = None):
        self.store = store
        self.versions = versions
        self.key = key  # the partition being computed (default key of every read)
        self.archive = archive  # the LandingArchive (root stages read the raw folder)
        self.run_id = run_id  # the orchestrator's run computing this partition (provenance only)

    def _key(self, key: str | None) -> str:
        k = key or self.key
        if k is None:
            raise ValueError("no partition key given and the view is not bound to one")
        return k

    def has(self, asset: str, key: str | None = None) -> bool:
        return f"{asset}/{self._key(key)}" in self.versions

    def version_dir(self, asset: str, key: str | None = None) -> Path:
        k = self._key(key)
        return self.store.version_dir(asset, k, self.versions.get(f"{asset}/{k}"))

    def table(self, asset: str, name: str, key: str | None = None, columns=None) -> pd.DataFrame:
        return read_table(self.version_dir(asset, key) / f"{name}.parquet", columns=columns)

    def has_table(self, asset: str, name: str, key: str | None = None) -> bool:
        return self.has(asset, key) and (self.version_dir(asset, key) / f"{name}.parquet").is_file()

    def meta(self, asset: str, key: str | None = None) -> dict:
        return json.loads((self.version_dir(asset, key) / META).read_text())

    def file(self, asset: str, name: str, key: str | None = None) -> bytes:
        """An extra file stored with an upstream version (e.g. ``manifest.json`` of ``ingested_run``)."""
        return (self.version_dir(asset, key) / name).read_bytes()

    def pngs(self, asset: str, key: str | None = None) -> dict[str, bytes]:
        if not self.has(asset, key):
            return {}
        return {f"{asset}: {p.stem}": p.read_bytes() for p in sorted(self.version_dir(asset, key).glob("*.png"))}

    def keys_of(self, asset: str) -> list[str]:
        """Partitions of ``asset`` this view holds (device and fleet stages read many)."""
        return sorted(k.split("/", 1)[1] for k in self.versions if k.startswith(f"{asset}/"))

    def sibling_keys(self, asset: str) -> list[str]:
        """Captures of the bound partition's device whose ``asset`` partition this view holds: a capture stage's
        siblings (``StageSpec.siblings``) that exist and passed their gates, the bound key included when it does."""
        device = split_capture_key(self._key(None))[0]
        return [k for k in self.keys_of(asset) if split_capture_key(k)[0] == device]

    def sibling_tables(self, asset: str, name: str, columns=None) -> dict[str, pd.DataFrame]:
        """``{capture key: table}`` of the sibling partitions of ``asset`` that stored a table ``name``."""
        return {k: self.table(asset, name, key=k, columns=columns) for k in self.sibling_keys(asset)
                if self.has_table(asset, name, key=k)}

    def run_dir(self) -> Path:
        """The raw run folder of the bound capture partition."""
        return self.archive.run_dir(self._key(None))

    def copy(self) -> StoreView:
        """A view over a copy of the version map (callers that add versions, e.g. walking a chain, use it)."""
        return StoreView(self.store, dict(self.versions), self.key, self.archive, self.run_id)
