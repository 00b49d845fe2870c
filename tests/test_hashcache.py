"""The raw-file hash cache (raw_schemas.hashcache) reuses a digest only while the file is untouched: a rewrite of
the same size with the old timestamps put back, a replacement by another file, a file still being written (racy)
are all hashed again, and the engine's raw versions read each file once per state."""

import hashlib
import os
import time

import pytest

from raw_schemas import hashcache
from raw_schemas.hashcache import (
    RACY_S,
    cache_stats,
    cached_sha256,
    clear_cache,
    hash_folder_files,
)


def _sha(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


@pytest.fixture(autouse=True)
def _fresh_cache():
    clear_cache()
    yield
    clear_cache()


def test_untouched_file_is_read_once(tmp_path, monkeypatch):
    monkeypatch.setattr(hashcache, "RACY_S", -1.0)  # the file was just written: accept it for this test
    f = tmp_path / "imu.csv"
    f.write_bytes(b"a" * 5000)
    assert cached_sha256(f) == _sha(b"a" * 5000)
    assert cached_sha256(f) == _sha(b"a" * 5000)
    assert cache_stats()["hits"] == 1 and cache_stats()["misses"] == 1


def test_same_size_rewrite_with_old_mtime_restored_is_hashed_again(tmp_path, monkeypatch):
    monkeypatch.setattr(hashcache, "RACY_S", -1.0)  # remember even fresh files: only the state decides here
    f = tmp_path / "imu.csv"
    f.write_bytes(b"a" * 5000)
    st = f.stat()
    assert cached_sha256(f) == _sha(b"a" * 5000)
    assert cached_sha256(f) == _sha(b"a" * 5000) and cache_stats()["hits"] == 1
    time.sleep(0.01)
    f.write_bytes(b"b" * 5000)  # same size
    os.utime(f, ns=(st.st_atime_ns, st.st_mtime_ns))  # old mtime put back: ctime still tells
    assert f.stat().st_mtime_ns == st.st_mtime_ns and f.stat().st_size == st.st_size
    assert cached_sha256(f) == _sha(b"b" * 5000)


def test_replaced_file_is_hashed_again(tmp_path, monkeypatch):
    monkeypatch.setattr(hashcache, "RACY_S", -1.0)
    f = tmp_path / "imu.csv"
    f.write_bytes(b"a" * 100)
    assert cached_sha256(f) == _sha(b"a" * 100)
    tmp = tmp_path / "new"
    tmp.write_bytes(b"c" * 100)
    os.replace(tmp, f)  # another inode at the same path
    assert cached_sha256(f) == _sha(b"c" * 100)


def test_recently_written_file_is_not_remembered(tmp_path):
    f = tmp_path / "imu.csv"
    f.write_bytes(b"a" * 100)
    assert RACY_S > 0
    cached_sha256(f)
    assert cache_stats()["files"] == 0
    cached_sha256(f)
    assert cache_stats()["hits"] == 0 and cache_stats()["misses"] == 2


def test_folder_hashes_match_plain_sha256_and_engine_versions(tmp_path, monkeypatch):
    from assets_lib.stages.engine import raw_versions
    from raw_schemas.readers import sha256_file

    monkeypatch.setattr(hashcache, "RACY_S", -1.0)
    for name, data in (("manifest.json", b"{}"), ("imu.csv", b"t,x\n0,1\n"), ("_COMPLETE", b"")):
        (tmp_path / name).write_bytes(data)
    (tmp_path / "sub").mkdir()
    expected = {p.name: sha256_file(p) for p in sorted(tmp_path.iterdir()) if p.is_file()}
    assert hash_folder_files(tmp_path) == expected
    assert raw_versions(tmp_path) == {f"raw/{k}": v for k, v in expected.items()}
    assert cache_stats()["hits"] == 3  # the engine reused what the first pass read
