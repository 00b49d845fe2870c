"""The run manifest (``manifest.json``): pydantic model, JSON Schema export, and a loader with clear errors.

Schema version 1.0. ``python -m raw_schemas.manifest`` prints the JSON Schema that ``manifest.schema.json``
holds, so a lab can validate a capture job's output without imulab installed.
"""

from __future__ import annotations

import json
from datetime import datetime
from pathlib import Path
from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from raw_schemas.errors import RawDataError
from raw_schemas.units import COUNT_UNIT, UNITS_BY_FAMILY, family_of

SCHEMA_VERSION = "1.0"
SUPPORTED_SCHEMA_VERSIONS = ("1.0",)

IMU_CHANNELS = ("gyro_x", "gyro_y", "gyro_z", "accel_x", "accel_y", "accel_z")
OPTIONAL_CHANNELS = ("temperature",)


class ContractError(ValueError):
    """A validator's finding with a precise place: ``where`` (dotted path from the manifest root), ``expected``,
    ``found``.

    Pydantic wraps it in its ``ValidationError``; :func:`load_manifest` unwraps it into a :class:`RawDataError`.
    """

    def __init__(self, where: str, expected: str, found: str | None = None):
        self.where, self.expected, self.found = where, expected, found
        super().__init__(f"{where}: expected {expected}" + (f", found {found}" if found is not None else ""))


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class Device(_Strict):
    """The unit under test."""

    id: str = Field(pattern=r"^[A-Za-z0-9][A-Za-z0-9_.-]*$", description="Device id; used in partition keys.")
    model: str
    grade: Literal["consumer", "industrial", "tactical", "navigation"]
    serial: str | None = None


class Site(_Strict):
    """Where the table stands. Local gravity is given, or computed from the WGS-84 normal gravity formula."""

    name: str = ""
    latitude_deg: float = Field(ge=-90.0, le=90.0)
    longitude_deg: float | None = Field(default=None, ge=-180.0, le=180.0)
    height_m: float = 0.0
    gravity_mps2: float | None = Field(default=None, gt=9.7, lt=9.9)
    gravity_model: Literal["given", "wgs84_normal"] = "wgs84_normal"

    @model_validator(mode="after")
    def _gravity_given(self):
        if self.gravity_model == "given" and self.gravity_mps2 is None:
            raise ValueError("gravity_model 'given' needs gravity_mps2")
        return self


class ChannelSpec(_Strict):
    """Unit of one IMU stream column; for raw counts, the value of one count (``lsb``) in ``lsb_unit``."""

    unit: str
    lsb: float | None = Field(default=None, gt=0.0)
    lsb_unit: str | None = None

    @model_validator(mode="after")
    def _counts_need_lsb(self):
        if self.unit == COUNT_UNIT and (self.lsb is None or self.lsb_unit is None):
            raise ValueError("a channel in 'counts' needs 'lsb' and 'lsb_unit'")
        return self

    @property
    def physical_unit(self) -> str:
        return self.lsb_unit if self.unit == COUNT_UNIT else self.unit

    def physical_per_raw(self) -> float:
        """Raw value -> value in ``physical_unit`` (the lsb for counts, 1 otherwise)."""
        return float(self.lsb) if self.unit == COUNT_UNIT else 1.0


class PlanStep(_Strict):
    """One step of the test plan. Times are on the IMU clock, seconds from the first sample.

    ``orientation_b2l`` is the direction-cosine matrix C_b^l (rows) that takes IMU-body vectors to the local
    level frame named by the plan (``ENU`` or ``NED``) at the start of the step. During a ``rate`` step the
    table turns about ``TestPlan.table_axis_level`` at ``table_rate_dps`` (right-handed), so
    C_b^l(t) = R(axis, rate * (t - start_s)) C_b^l(start_s). Samples inside the first ``settle_s`` seconds are
    not used for the plateau.
    """

    index: int = Field(ge=0)
    kind: Literal["rate", "static", "pose", "rotation", "free"]
    start_s: float = Field(ge=0.0)
    duration_s: float = Field(gt=0.0)
    settle_s: float = Field(default=0.0, ge=0.0)
    table_rate_dps: float = 0.0
    orientation_b2l: tuple[tuple[float, float, float], tuple[float, float, float], tuple[float, float, float]] | None = None
    label: str = ""
    #: table-free steps (test kind "tablefree"): the body axis that points up in a hand-placed "pose", if known
    up_axis_body: Literal["+x", "-x", "+y", "-y", "+z", "-z"] | None = None
    #: table-free "rotation" step: body axis turned about and the nominal angle turned (right-handed, deg)
    rotation_axis_body: Literal["x", "y", "z"] | None = None
    rotation_angle_deg: float | None = None

    @field_validator("orientation_b2l")
    @classmethod
    def _orthonormal(cls, v):
        if v is None:
            return v
        m = np.asarray(v, dtype=float)
        err = np.abs(m @ m.T - np.eye(3)).max()
        if err > 1e-6 or np.linalg.det(m) < 0:
            raise ValueError(f"orientation_b2l must be a proper rotation matrix (|C C^T - I| = {err:.2e})")
        return v

    @property
    def end_s(self) -> float:
        return self.start_s + self.duration_s

    @model_validator(mode="after")
    def _settle_inside(self):
        if self.settle_s >= self.duration_s:
            raise ValueError("settle_s must be shorter than duration_s")
        if self.kind in ("static", "pose", "rotation", "free") and self.table_rate_dps != 0.0:
            raise ValueError(f"a {self.kind} step has table_rate_dps 0")
        if self.kind in ("rate", "static") and self.orientation_b2l is None:
            raise ValueError(f"a {self.kind} step needs orientation_b2l")
        if self.kind != "pose" and self.up_axis_body is not None:
            raise ValueError("up_axis_body belongs to a pose step")
        if self.kind != "rotation" and (self.rotation_axis_body is not None or self.rotation_angle_deg is not None):
            raise ValueError("rotation_axis_body / rotation_angle_deg belong to a rotation step")
        return self


class TestPlan(_Strict):
    """Ordered steps of one run, in a named local level frame."""

    __test__ = False  # not a pytest class

    name: str
    frame: Literal["ENU", "NED"] = "ENU"
    table_axis_level: tuple[float, float, float] = (0.0, 0.0, 1.0)
    steps: tuple[PlanStep, ...] = Field(min_length=1)

    @model_validator(mode="after")
    def _ordered(self):
        for i, s in enumerate(self.steps):
            if s.index != i:
                raise ValueError(f"steps[{i}].index is {s.index}, expected {i}")
            if i and s.start_s < self.steps[i - 1].end_s:
                raise ValueError(f"steps[{i}] starts before steps[{i - 1}] ends")
        n = np.linalg.norm(self.table_axis_level)
        if abs(n - 1.0) > 1e-9:
            raise ValueError("table_axis_level must be a unit vector")
        return self

    @property
    def end_s(self) -> float:
        return self.steps[-1].end_s


class Manifest(_Strict):
    """``manifest.json`` of one captured run (schema version 1.0)."""

    schema_version: Literal["1.0"]
    device: Device
    run_id: str = Field(pattern=r"^[A-Za-z0-9][A-Za-z0-9_.-]*$")
    test_kind: Literal["rate", "multiposition", "static", "tumble", "tablefree"]
    start_time_utc: datetime
    site: Site
    sample_rate_hz: float = Field(gt=0.0)
    channels: dict[str, ChannelSpec]
    plan: TestPlan
    power_cycle_index: int = Field(default=0, ge=0)
    table_id: str | None = None
    notes: str = ""

    @field_validator("start_time_utc")
    @classmethod
    def _aware(cls, v: datetime):
        if v.tzinfo is None or v.utcoffset().total_seconds() != 0:
            offset = "no UTC offset" if v.tzinfo is None else f"offset {v.tzname()}"
            raise ContractError("start_time_utc", "an ISO 8601 time with UTC offset zero, e.g. 2026-01-05T08:00:00Z",
                                f"{v.isoformat()!r} ({offset})")
        return v

    @field_validator("channels")
    @classmethod
    def _channels(cls, v: dict[str, ChannelSpec]):
        missing = [c for c in IMU_CHANNELS if c not in v]
        if missing:
            raise ContractError("channels", f"an entry for each of {list(IMU_CHANNELS)}", f"no entry for {missing}")
        for name, spec in v.items():
            if name not in IMU_CHANNELS + OPTIONAL_CHANNELS:
                raise ContractError(f"channels.{name}", f"a channel of {list(IMU_CHANNELS + OPTIONAL_CHANNELS)}",
                                    f"unknown channel {name!r}")
            fam = family_of(name)
            unit = spec.physical_unit
            if unit not in UNITS_BY_FAMILY[fam]:
                key = "lsb_unit" if spec.unit == COUNT_UNIT else "unit"
                raise ContractError(
                    f"channels.{name}.{key}",
                    f"one of the {fam} units {sorted(UNITS_BY_FAMILY[fam])}"
                    + (" (or unit 'counts' with lsb and lsb_unit)" if key == "unit" and fam != "temperature" else ""),
                    f"unknown unit {unit!r}",
                )
        return v

    @model_validator(mode="after")
    def _tablefree_steps(self):
        table_free = {"pose", "rotation", "free"}
        for s in self.plan.steps:
            if (s.kind in table_free) != (self.test_kind == "tablefree"):
                raise ContractError(f"plan.steps.{s.index}.kind",
                                    "steps of kind pose/rotation/free exactly when test_kind is 'tablefree'",
                                    f"kind {s.kind!r} in a {self.test_kind!r} run")
        return self

    @property
    def partition_key(self) -> str:
        return f"{self.device.id}__{self.run_id}"


def manifest_json_schema() -> dict:
    """JSON Schema (draft 2020-12) of the manifest, generated from the model."""
    return Manifest.model_json_schema()


def load_manifest(path: str | Path) -> Manifest:
    """Read and validate ``manifest.json``; every problem raised as :class:`RawDataError` naming the field."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise RawDataError(path.name, f"in {path.parent}", "a manifest.json file", "none") from None
    try:
        raw = json.loads(text)
    except json.JSONDecodeError as e:
        raise RawDataError(path.name, f"line {e.lineno} column {e.colno}", "valid JSON", e.msg) from None
    if not isinstance(raw, dict):
        raise RawDataError(path.name, "top level", "a JSON object", type(raw).__name__)
    version = raw.get("schema_version")
    if version not in SUPPORTED_SCHEMA_VERSIONS:
        raise RawDataError(path.name, "field 'schema_version'", f"one of {list(SUPPORTED_SCHEMA_VERSIONS)}", repr(version))
    try:
        return Manifest.model_validate(raw)
    except ValidationError as e:
        raise _contract_error(path.name, e.errors()[0]) from None


def _contract_error(file: str, err: dict) -> RawDataError:
    """One pydantic error -> RawDataError(file, "field '<dotted.path>'", expected, found)."""
    loc = ".".join(str(p) for p in err["loc"])
    cause = (err.get("ctx") or {}).get("error")
    if isinstance(cause, ContractError):
        return RawDataError(file, f"field '{cause.where}'", cause.expected, cause.found)
    value = err.get("input")
    found = None if isinstance(value, (dict, list)) else repr(value)
    msg = err["msg"].removeprefix("Value error, ")
    if err["type"] == "missing":
        expected, found = "a value (required field)", "no such field"
    elif err["type"] == "extra_forbidden":
        expected, found = "only the fields of the manifest schema", f"unknown field {err['loc'][-1]!r}"
    elif msg.startswith("Input should be "):
        expected = msg.removeprefix("Input should be ")
    else:
        expected = msg
    return RawDataError(file, f"field '{loc or 'top level'}'", expected, found)


if __name__ == "__main__":  # pragma: no cover
    print(json.dumps(manifest_json_schema(), indent=2))
