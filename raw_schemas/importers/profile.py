"""Generic CSV / parquet logs described by an import profile (JSON; schema ``raw_schemas/import_profile.schema.json``).

A profile says which source column feeds each contract channel, with its unit (or ``counts`` + ``lsb`` +
``lsb_unit``) and an optional sign (``-1`` to flip an axis: the per-channel axis map), where time comes from (a
column in s/ms/us/ns, or a constant rate), and how the text is laid out. Example::

    {
      "time": {"column": "timestamp", "unit": "ms"},
      "delimiter": ",",
      "channels": {
        "gyro_x": {"column": "gy", "unit": "deg/s"},
        "gyro_y": {"column": "gx", "unit": "deg/s", "sign": -1},
        "gyro_z": {"column": "gz", "unit": "deg/s"},
        "accel_x": {"column": "ay", "unit": "counts", "lsb": 0.000488, "lsb_unit": "g"},
        "accel_y": {"column": "ax", "unit": "counts", "lsb": 0.000488, "lsb_unit": "g", "sign": -1},
        "accel_z": {"column": "az", "unit": "counts", "lsb": 0.000488, "lsb_unit": "g"}
      },
      "test_kind": "static"
    }

``python -m raw_schemas.importers.profile`` prints the JSON Schema.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Literal

import numpy as np
import pandas as pd
from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from raw_schemas.errors import RawDataError
from raw_schemas.importers.common import ImportedSession, median_rate_hz, sha256_sources, whole_session_steps
from raw_schemas.manifest import IMU_CHANNELS, _contract_error

TIME_UNITS_TO_S = {"s": 1.0, "ms": 1e-3, "us": 1e-6, "ns": 1e-9}

#: the ``-o KEY=VALUE`` options this importer reads (key -> one-line description); any other key is refused
OPTIONS = {
    "profile": "import profile JSON (schema raw_schemas/import_profile.schema.json; required)",
}


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class TimeSpec(_Strict):
    """Time from a ``column`` (in ``unit``; shifted so the first sample is at 0 when ``zero_at_first``), or from
    a constant ``rate_hz`` (sample k at k / rate_hz)."""

    column: str | None = None
    unit: Literal["s", "ms", "us", "ns"] = "s"
    zero_at_first: bool = True
    rate_hz: float | None = Field(default=None, gt=0.0)

    @model_validator(mode="after")
    def _one(self):
        if (self.column is None) == (self.rate_hz is None):
            raise ValueError("time needs exactly one of 'column' or 'rate_hz'")
        return self


class ColumnSpec(_Strict):
    """One contract channel: source ``column``, its ``unit`` (or counts + lsb + lsb_unit), ``sign`` (+1/-1)."""

    column: str
    unit: str
    lsb: float | None = Field(default=None, gt=0.0)
    lsb_unit: str | None = None
    sign: Literal[1, -1] = 1


class ImportProfile(_Strict):
    """How to read one family of CSV / parquet logs into the raw-log contract."""

    time: TimeSpec
    channels: dict[str, ColumnSpec]
    delimiter: str = ","
    comment: str | None = None
    header: bool = True
    column_names: list[str] | None = None
    skip_rows: int = Field(default=0, ge=0)
    test_kind: Literal["static", "tablefree"] = "static"
    sample_rate_hz: float | None = Field(default=None, gt=0.0)

    @model_validator(mode="after")
    def _channels(self):
        missing = [c for c in IMU_CHANNELS if c not in self.channels]
        unknown = [c for c in self.channels if c not in IMU_CHANNELS + ("temperature",)]
        if missing or unknown:
            raise ValueError(f"channels must map each of {list(IMU_CHANNELS)} (+ optional temperature); "
                             f"missing {missing}, unknown {unknown}")
        if not self.header and not self.column_names:
            raise ValueError("a file without a header line needs 'column_names'")
        return self


def profile_json_schema() -> dict:
    return ImportProfile.model_json_schema()


def load_profile(path: Path) -> ImportProfile:
    try:
        raw = json.loads(Path(path).read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise RawDataError(str(path), "", "an import profile JSON file", "no such file") from None
    except json.JSONDecodeError as e:
        raise RawDataError(Path(path).name, f"line {e.lineno} column {e.colno}", "valid JSON", e.msg) from None
    try:
        return ImportProfile.model_validate(raw)
    except ValidationError as e:
        raise _contract_error(Path(path).name, e.errors()[0]) from None


def _read_table(path: Path, prof: ImportProfile) -> pd.DataFrame:
    if not path.is_file():
        raise RawDataError(str(path), "", "an existing CSV or parquet file", "no such file")
    if path.suffix == ".parquet":
        return pd.read_parquet(path)
    try:
        return pd.read_csv(path, sep=prof.delimiter, comment=prof.comment, skiprows=prof.skip_rows,
                           header=0 if prof.header else None, names=prof.column_names, skipinitialspace=True,
                           keep_default_na=False, na_values=[""])
    except (pd.errors.ParserError, UnicodeDecodeError) as e:
        raise RawDataError(path.name, "file", "a delimited text table as the profile describes", str(e).splitlines()[0]) from None


def _column(df: pd.DataFrame, col: str, name: str, line_offset: int) -> np.ndarray:
    if col not in df.columns:
        raise RawDataError(name, "header", f"a column {col!r} (named in the profile)", f"columns {list(df.columns)}")
    v = pd.to_numeric(df[col], errors="coerce").to_numpy(float)
    bad = np.flatnonzero(~np.isfinite(v))
    if bad.size:
        i = int(bad[0])
        v0 = df[col].iloc[i]
        v0 = v0.item() if isinstance(v0, np.generic) else v0
        raise RawDataError(name, f"row {i + 1} (line {i + 1 + line_offset}), column {col!r}", "a finite number",
                           f"{v0!r} ({bad.size} such row{'s' if bad.size > 1 else ''})")
    return v


def read(sources: list[Path], options: dict) -> ImportedSession:
    if len(sources) != 1:
        raise RawDataError("(sources)", "command line", "one CSV or parquet file", f"{len(sources)} files")
    if "profile" not in options:
        raise RawDataError("(options)", "option 'profile'", "-o profile=PROFILE.json", "none given")
    prof_path = Path(options["profile"])
    prof = load_profile(prof_path)
    path = sources[0]
    df = _read_table(path, prof)
    off = prof.skip_rows + (1 if prof.header else 0)
    if prof.time.column is not None:
        t = _column(df, prof.time.column, path.name, off) * TIME_UNITS_TO_S[prof.time.unit]
        if prof.time.zero_at_first:
            t = t - t[0]
    else:
        t = np.arange(len(df)) / prof.time.rate_hz
    rate = prof.sample_rate_hz or prof.time.rate_hz or median_rate_hz(t, path.name)
    out = {"time_s": t}
    channels = {}
    for ch, spec in prof.channels.items():
        out[ch] = spec.sign * _column(df, spec.column, path.name, off)
        channels[ch] = spec.model_dump(exclude={"column", "sign"}, exclude_none=True)
    imu = pd.DataFrame(out)
    return ImportedSession(
        imu=imu, channels=channels, sample_rate_hz=float(rate), test_kind=prof.test_kind,
        steps=(whole_session_steps(t, rate) if prof.test_kind == "tablefree" else
               [{"index": 0, "kind": "static", "start_s": float(t[0]), "duration_s": float(t[-1] - t[0]) or 1.0 / rate,
                 "orientation_b2l": [[1, 0, 0], [0, 1, 0], [0, 0, 1]], "label": "static record (orientation unknown)"}]),
        plan_name=f"imported with profile {prof_path.name}",
        notes=f"imported from {path.name} with profile {prof_path.name}",
        sources=sha256_sources([path, prof_path]),
    )


if __name__ == "__main__":  # pragma: no cover
    print(json.dumps(profile_json_schema(), indent=2))
