"""sha256 of raw files, remembered per process by the file's identity and state, so a run that plans, ingests and
plans again reads each raw file once instead of four times.

A remembered digest is used only while the file's state is exactly the one it was hashed at: device, inode, size,
modification time and status-change time (``st_ctime_ns``, which every write, rename onto the path or ``utime``
moves and no user can set back). A file replaced (new inode), rewritten (size, mtime or ctime) or touched is hashed
again. Two more guards against the "racy" case git documents (a rewrite within the clock tick of the stored
timestamps leaves them equal): a file modified less than ``RACY_S`` seconds before it was hashed is not remembered,
and neither is one whose state changed while it was being read.
"""

from __future__ import annotations

import hashlib
import os
import threading
import time
from pathlib import Path

#: files modified this recently (seconds) when hashed are not remembered (timestamps may not show a rewrite yet)
RACY_S = 2.0

_LOCK = threading.Lock()
_CACHE: dict[str, tuple[tuple[int, ...], str]] = {}
_STATS = {"hits": 0, "misses": 0}


def sha256_file(path: str | os.PathLike, chunk: int = 1 << 20) -> str:
    """Content hash of a file, streamed (no cache)."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while b := f.read(chunk):
            h.update(b)
    return h.hexdigest()


def _state(st: os.stat_result) -> tuple[int, ...]:
    return (st.st_dev, st.st_ino, st.st_size, st.st_mtime_ns, st.st_ctime_ns)


def cached_sha256(path: str | os.PathLike) -> str:
    """``sha256_file(path)``, reusing the digest computed earlier in this process while the file's state is unchanged."""
    p = os.path.abspath(path)
    before = os.stat(p)
    state = _state(before)
    with _LOCK:
        hit = _CACHE.get(p)
        if hit is not None and hit[0] == state:
            _STATS["hits"] += 1
            return hit[1]
        _STATS["misses"] += 1
    digest = sha256_file(p)
    after = os.stat(p)
    newest_ns = max(after.st_mtime_ns, after.st_ctime_ns)
    if _state(after) == state and time.time_ns() - newest_ns > RACY_S * 1e9:
        with _LOCK:
            _CACHE[p] = (state, digest)
    return digest


def cache_stats() -> dict[str, int]:
    """Hits and misses so far, and how many files are remembered."""
    with _LOCK:
        return {**_STATS, "files": len(_CACHE)}


def clear_cache() -> None:
    with _LOCK:
        _CACHE.clear()
        _STATS.update(hits=0, misses=0)


def hash_folder_files(folder: str | os.PathLike) -> dict[str, str]:
    """File name -> sha256 of every file directly in ``folder``, sorted by name (cached per file state)."""
    return {p.name: cached_sha256(p) for p in sorted(Path(folder).iterdir()) if p.is_file()}
