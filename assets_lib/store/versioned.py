"""Versioned, atomic, never-overwritten parquet storage for every asset partition.

Layout: ``<root>/<asset>/<partition>/<version>/<table>.parquet`` (+ ``meta.json``), and a ``CURRENT`` file per
asset partition naming the version readers use. A version id is a content hash of the asset's code version and
the versions of everything it was computed from, so re-running with the same raw data and code maps to the same
version: nothing new is written (idempotent), and bytes are identical. A version directory is written in a
temporary sibling and published with one ``os.rename``; ``CURRENT`` is replaced with ``os.replace``: a crash
never leaves a half-written file where a reader looks. Earlier versions stay on disk for audit.
"""

from __future__ import annotations

import hashlib
import io
import json
import os
import shutil
import tempfile
from collections import OrderedDict
from dataclasses import dataclass
from pathlib import Path

import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq

CURRENT = "CURRENT"
META = "meta.json"
#: file of a version whose output a quality gate rejected (its text is the reason); downstream stages skip it
REJECTED = "REJECTED.txt"


def version_id(asset: str, code_version: str, inputs: dict[str, str] | None = None, params: dict | None = None) -> str:
    """Deterministic version of an asset partition: sha256 over code version, input versions and parameters."""
    payload = json.dumps(
        {"asset": asset, "code_version": code_version, "inputs": inputs or {}, "params": params or {}},
        sort_keys=True,
        default=str,
    )
    return hashlib.sha256(payload.encode()).hexdigest()[:20]


def _fsync_dir(path: Path) -> None:
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:  # pragma: no cover - platforms without directory fds
        return
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def write_parquet_deterministic(df: pd.DataFrame, path: Path) -> None:
    """Parquet without pandas index or time-dependent metadata, so equal frames give equal bytes."""
    table = pa.Table.from_pandas(df, preserve_index=False)
    pq.write_table(table, path, compression="zstd", write_statistics=True)


#: small tables are read many times in one process (a run's coefficients by its asset checks, the device's
#: repeatability and record, the fleet drift): each is parsed once per process and served as a copy
READ_CACHE_MAX_FILE_BYTES = 256 * 1024
READ_CACHE_MAX_ENTRIES = 512
_read_cache: OrderedDict[tuple, pd.DataFrame] = OrderedDict()


def read_table(path: Path, columns=None) -> pd.DataFrame:
    """``pd.read_parquet(path, columns=columns)``; files up to ``READ_CACHE_MAX_FILE_BYTES`` are parsed once per
    process: cached by their bytes' digest (and the columns), so a file rewritten in place is never served stale.
    Each call returns its own copy, so callers may modify it."""
    if os.stat(path).st_size > READ_CACHE_MAX_FILE_BYTES:
        return pd.read_parquet(path, columns=columns)
    data = Path(path).read_bytes()
    key = (hashlib.blake2b(data, digest_size=20).digest(), None if columns is None else tuple(columns))
    df = _read_cache.get(key)
    if df is None:
        df = _read_cache[key] = pd.read_parquet(io.BytesIO(data), columns=columns)
        while len(_read_cache) > READ_CACHE_MAX_ENTRIES:
            _read_cache.popitem(last=False)
    else:
        _read_cache.move_to_end(key)
    return df.copy()


@dataclass(frozen=True)
class VersionedStore:
    """The store every stage reads and writes (the Dagster ``ParquetStore`` resource wraps it; the CLI uses it)."""

    root: Path

    def partition_dir(self, asset: str, partition: str) -> Path:
        return Path(self.root) / asset / partition

    def current_version(self, asset: str, partition: str) -> str | None:
        p = self.partition_dir(asset, partition) / CURRENT
        return p.read_text().strip() if p.is_file() else None

    def version_dir(self, asset: str, partition: str, version: str | None = None) -> Path:
        version = version or self.current_version(asset, partition)
        if version is None:
            raise FileNotFoundError(f"asset {asset!r} partition {partition!r} has not been materialized under {self.root}")
        return self.partition_dir(asset, partition) / version

    def exists(self, asset: str, partition: str, version: str) -> bool:
        return (self.partition_dir(asset, partition) / version / META).is_file()

    def write(
        self,
        asset: str,
        partition: str,
        version: str,
        tables: dict[str, pd.DataFrame],
        meta: dict | None = None,
        files: dict[str, bytes] | None = None,
    ) -> tuple[Path, bool]:
        """Publish ``tables`` (and extra ``files``) as ``version``; returns (dir, written). Existing versions are
        never rewritten: the call then only moves ``CURRENT`` to it."""
        pdir = self.partition_dir(asset, partition)
        final = pdir / version
        written = False
        if not (final / META).is_file():
            pdir.mkdir(parents=True, exist_ok=True)
            tmp = Path(tempfile.mkdtemp(prefix=f".{version}.", dir=pdir))
            try:
                for name, df in tables.items():
                    write_parquet_deterministic(df, tmp / f"{name}.parquet")
                for name, data in (files or {}).items():
                    (tmp / name).write_bytes(data)
                (tmp / META).write_text(json.dumps({"asset": asset, "partition": partition, "version": version,
                                                     "tables": sorted(tables), **(meta or {})},
                                                    sort_keys=True, indent=1, default=str) + "\n")
                for f in tmp.iterdir():
                    with open(f, "rb") as fh:
                        os.fsync(fh.fileno())
                try:
                    os.rename(tmp, final)
                    written = True
                except OSError:
                    if not (final / META).is_file():  # a concurrent writer published the same version
                        raise
            finally:
                if tmp.exists():
                    shutil.rmtree(tmp, ignore_errors=True)
            _fsync_dir(pdir)
        self._set_current(pdir, version)
        return final, written

    def _set_current(self, pdir: Path, version: str) -> None:
        cur = pdir / CURRENT
        if cur.is_file() and cur.read_text().strip() == version:
            return
        fd, tmp = tempfile.mkstemp(prefix=".CURRENT.", dir=pdir)
        with os.fdopen(fd, "w") as f:
            f.write(version + "\n")
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, cur)

    def rejection(self, asset: str, partition: str, version: str | None = None) -> str | None:
        """Why a quality gate rejected this version (None when it was not rejected, or does not exist)."""
        version = version or self.current_version(asset, partition)
        if version is None:
            return None
        p = self.partition_dir(asset, partition) / version / REJECTED
        return p.read_text().strip() if p.is_file() else None

    def note_failure(self, asset: str, partition: str, version: str, reason: str) -> None:
        """Remember that computing ``version`` failed and why (``FAILED-<version>.txt`` beside the versions; written
        atomically, never read as a version): the run summary reports it, and reprocessing does not retry the same
        version until its code or inputs change."""
        pdir = self.partition_dir(asset, partition)
        pdir.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=".FAILED.", dir=pdir)
        with os.fdopen(fd, "w") as f:
            f.write(reason.rstrip() + "\n")
        os.replace(tmp, pdir / f"FAILED-{version}.txt")

    def failure(self, asset: str, partition: str, version: str) -> str | None:
        """The reason noted by ``note_failure`` for ``version`` (None when none was noted)."""
        p = self.partition_dir(asset, partition) / f"FAILED-{version}.txt"
        return p.read_text().strip() if p.is_file() else None

    def read(self, asset: str, partition: str, table: str, version: str | None = None) -> pd.DataFrame:
        return read_table(self.version_dir(asset, partition, version) / f"{table}.parquet")

    def read_meta(self, asset: str, partition: str, version: str | None = None) -> dict:
        return json.loads((self.version_dir(asset, partition, version) / META).read_text())

    def partitions(self, asset: str) -> list[str]:
        d = Path(self.root) / asset
        return sorted(p.name for p in d.iterdir() if (p / CURRENT).is_file()) if d.is_dir() else []

    def versions(self, asset: str, partition: str) -> list[str]:
        d = self.partition_dir(asset, partition)
        return sorted(p.name for p in d.iterdir() if (p / META).is_file()) if d.is_dir() else []
