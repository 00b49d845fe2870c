"""Whitespace/CSV numeric text tables with row-precise errors (shared by the text importers)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from raw_schemas.errors import RawDataError


def read_numeric_columns(path: Path, ncols: int, comment: str = "#") -> np.ndarray:
    """Rows of exactly ``ncols`` whitespace-separated finite numbers; RawDataError names line and expectation."""
    if not path.is_file():
        raise RawDataError(str(path), "", "an existing file", "no such file")
    rows = []
    with open(path, "r", encoding="utf-8", errors="replace") as f:
        for lineno, line in enumerate(f, start=1):
            s = line.split(comment, 1)[0].strip()
            if not s:
                continue
            parts = s.replace(",", " ").split()
            if len(parts) != ncols:
                raise RawDataError(path.name, f"line {lineno}", f"{ncols} numbers per line", f"{len(parts)}: {s[:80]!r}")
            try:
                vals = [float(x) for x in parts]
            except ValueError:
                raise RawDataError(path.name, f"line {lineno}", "numbers", repr(s[:80])) from None
            if not all(np.isfinite(vals)):
                raise RawDataError(path.name, f"line {lineno}", "finite numbers", repr(s[:80]))
            rows.append(vals)
    if len(rows) < 2:
        raise RawDataError(path.name, "file", "at least two data lines", f"{len(rows)}")
    return np.asarray(rows, dtype=float)
