"""Canonical JSON of a record and its sha256.

Record (``record_schema_version`` 1.1, JSON Schema in ``raw_schemas/record.schema.json``)::

    {"record_schema_version": "1.1",
     "record_sha256": sha256(canonical_json(content)),
     "content":    {...everything certified: device, run, test conditions, raw file hashes, coefficients with
                    uncertainties and units, noise terms, stage versions, software, prev_record_sha256},
     "provenance": {"created_utc": ..., "dagster_run_id": ...}}

Canonical JSON: ``json.dumps(sort_keys=True, separators=(",", ":"), ensure_ascii=False, allow_nan=False)`` encoded
UTF-8; floats are written by ``float.__repr__`` (the shortest string that reads back to the same double, so
parse -> re-serialize is the identity), NaN/inf become ``null`` (an unobservable coefficient has value null and
``observable`` false), numpy scalars become Python scalars. The file on disk is the same object indented for
reading; the hash is always over the canonical form of ``content``, so whitespace never matters.
"""

from __future__ import annotations

import hashlib
import json
import math
from datetime import datetime
from pathlib import Path

import numpy as np
import pandas as pd

#: 1.1 adds ``content.status`` ("valid" | "invalid") and ``content.status_reasons``
RECORD_SCHEMA_VERSION = "1.1"
SCHEMA_PATH = Path(__file__).resolve().parents[2] / "raw_schemas" / "record.schema.json"


def to_jsonable(v):
    """Plain JSON values: numpy scalars -> Python, NaN/inf -> None, tuples -> lists, timestamps -> ISO strings."""
    if isinstance(v, dict):
        return {str(k): to_jsonable(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [to_jsonable(x) for x in v]
    if isinstance(v, np.ndarray):
        return [to_jsonable(x) for x in v.tolist()]
    if isinstance(v, (bool, np.bool_)):
        return bool(v)
    if isinstance(v, (int, np.integer)):
        return int(v)
    if isinstance(v, (float, np.floating)):
        f = float(v)
        return f if math.isfinite(f) else None
    if isinstance(v, (pd.Timestamp, datetime)):
        return v.isoformat()
    if v is None or isinstance(v, str):
        return v
    if v is pd.NA or v is pd.NaT:
        return None
    return str(v)


def canonical_json(obj) -> bytes:
    """Sorted keys, no whitespace, floats by repr, UTF-8: equal objects give equal bytes."""
    return json.dumps(to_jsonable(obj), sort_keys=True, separators=(",", ":"), ensure_ascii=False,
                      allow_nan=False).encode("utf-8")


def sha256_hex(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def content_sha256(content: dict) -> str:
    return sha256_hex(canonical_json(content))


def record_file_bytes(record: dict) -> bytes:
    """The record as stored: indented, sorted, UTF-8 (the hash is over canonical ``content``, not these bytes)."""
    return (json.dumps(to_jsonable(record), sort_keys=True, indent=1, ensure_ascii=False, allow_nan=False)
            + "\n").encode("utf-8")


def load_record(path: str | Path) -> dict:
    return json.loads(Path(path).read_text(encoding="utf-8"))
