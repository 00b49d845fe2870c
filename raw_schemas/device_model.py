"""Device-model file (``device_model.json``): the fitted model of one unit, the input of the digital twin.

Schema version 1.0. ``python -m raw_schemas.device_model`` prints the JSON Schema that
``device_model.schema.json`` holds. Everything is SI (units in the field names); the sensor error model is the
one of docs/design.md:

    gyro:  y_g = diag(K_g)(I + E_g) w + b_g + G f + n_g
    accel: y_a = diag(K_a)(I + E_a) f + b_a + K2 f^2 + sum_(j!=i) Kc[i, j] f_i f_j + n_a

- ``power_cycles``: the fitted base model per power cycle (turn-on biases and scale factors differ between
  cycles); each value may carry a standard error (``*_stderr``, same shape, null when unknown) and the runs it
  came from (``sources``).
- ``noise``: per axis IEEE 952 Annex C terms (q, n, b, k, r) plus a first-order Gauss-Markov term
  (``gm_sigma``, ``gm_tau_s``), SI: gyro q [rad], n [rad/s/sqrt(Hz)], b [rad/s], k [rad/s/sqrt(s)], r [rad/s^2],
  gm_sigma [rad/s]; accelerometer the same with m for rad.
- ``outputs``: how the unit writes its counts (LSB and its unit) and its full scale (saturation), SI.
- ``effects``: unmodelled-effect families with their parameters, ``{"family": name, "params": {...}}``, as in
  ``assets_lib.sim.effects`` (family names and parameters are checked there, not here: this module imports
  nothing from the science packages).
"""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator

from raw_schemas.errors import RawDataError
from raw_schemas.manifest import Device

DEVICE_MODEL_SCHEMA_VERSION = "1.0"

Vec3 = list[float]
Mat3 = list[list[float]]
Vec3Se = list[float | None]  # standard errors: null where the term was not fitted
Mat3Se = list[list[float | None]]


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


def _shape(v, rows: int, cols: int | None, name: str):
    if v is None:
        return v
    if len(v) != rows or (cols is not None and any(len(r) != cols for r in v)):
        raise ValueError(f"{name}: expected {rows} values" + (f" of {cols}" if cols else ""))
    return v


class AxisNoise(_Strict):
    """IEEE 952 Annex C terms of one axis plus a Gauss-Markov term (SI, see the module docstring)."""

    q: float = Field(0.0, ge=0.0)
    n: float = Field(0.0, ge=0.0)
    b: float = Field(0.0, ge=0.0)
    k: float = Field(0.0, ge=0.0)
    r: float = Field(0.0, ge=0.0)
    gm_sigma: float = Field(0.0, ge=0.0)
    gm_tau_s: float = Field(1.0, gt=0.0)


class TriadNoise(_Strict):
    x: AxisNoise = AxisNoise()
    y: AxisNoise = AxisNoise()
    z: AxisNoise = AxisNoise()


class NoiseModel(_Strict):
    gyro: TriadNoise = TriadNoise()
    accel: TriadNoise = TriadNoise()


class GyroModel(_Strict):
    scale_factor: Vec3
    misalignment_rad: Mat3 = Field(description="E[i][j]: axis i's sensitivity to body axis j; zero diagonal")
    bias_radps: Vec3
    g_sensitivity_radps_per_mps2: Mat3 = [[0.0] * 3] * 3
    scale_factor_stderr: Vec3Se | None = None
    misalignment_stderr_rad: Mat3Se | None = None
    bias_stderr_radps: Vec3Se | None = None
    g_sensitivity_stderr_radps_per_mps2: Mat3Se | None = None

    @field_validator("scale_factor", "bias_radps", "scale_factor_stderr", "bias_stderr_radps")
    @classmethod
    def _v3(cls, v, info):
        return _shape(v, 3, None, info.field_name)

    @field_validator("misalignment_rad", "g_sensitivity_radps_per_mps2", "misalignment_stderr_rad",
                     "g_sensitivity_stderr_radps_per_mps2")
    @classmethod
    def _m3(cls, v, info):
        return _shape(v, 3, 3, info.field_name)


class AccelModel(_Strict):
    scale_factor: Vec3
    misalignment_rad: Mat3
    bias_mps2: Vec3
    k2_per_mps2: Vec3 = [0.0] * 3
    cross_coupling_per_mps2: Mat3 = Field([[0.0] * 3] * 3, description="Kc[i][j] f_i f_j; zero diagonal")
    scale_factor_stderr: Vec3Se | None = None
    misalignment_stderr_rad: Mat3Se | None = None
    bias_stderr_mps2: Vec3Se | None = None
    k2_stderr_per_mps2: Vec3Se | None = None
    cross_coupling_stderr_per_mps2: Mat3Se | None = None

    @field_validator("scale_factor", "bias_mps2", "k2_per_mps2", "scale_factor_stderr", "bias_stderr_mps2",
                     "k2_stderr_per_mps2")
    @classmethod
    def _v3(cls, v, info):
        return _shape(v, 3, None, info.field_name)

    @field_validator("misalignment_rad", "cross_coupling_per_mps2", "misalignment_stderr_rad",
                     "cross_coupling_stderr_per_mps2")
    @classmethod
    def _m3(cls, v, info):
        return _shape(v, 3, 3, info.field_name)


class PowerCycleModel(_Strict):
    """The fitted base model of one power cycle (turn-on)."""

    index: int = Field(ge=0)
    gyro: GyroModel
    accel: AccelModel
    sources: list[str] = Field(default_factory=list, description="run ids the coefficients were fitted from")


class Outputs(_Strict):
    gyro_lsb: float = Field(gt=0.0)
    gyro_lsb_unit: str = "deg/s"
    accel_lsb: float = Field(gt=0.0)
    accel_lsb_unit: str = "g"
    gyro_full_scale_radps: float | None = Field(default=None, gt=0.0)
    accel_full_scale_mps2: float | None = Field(default=None, gt=0.0)


class EffectSpec(_Strict):
    family: str
    params: dict[str, Any] = Field(default_factory=dict)


class DeviceModel(_Strict):
    """``device_model.json`` (schema version 1.0)."""

    schema_version: Literal["1.0"] = DEVICE_MODEL_SCHEMA_VERSION
    device: Device
    sample_rate_hz: float = Field(gt=0.0)
    temperature_degc: float = 25.0
    outputs: Outputs
    noise: NoiseModel = NoiseModel()
    power_cycles: list[PowerCycleModel] = Field(min_length=1)
    effects: list[EffectSpec] = Field(default_factory=list)
    provenance: dict[str, Any] = Field(default_factory=dict, description="where the model came from (free form)")

    @field_validator("power_cycles")
    @classmethod
    def _unique(cls, v):
        idx = [p.index for p in v]
        if len(set(idx)) != len(idx):
            raise ValueError(f"power cycle indices must be unique, got {idx}")
        return v

    def cycle(self, index: int) -> PowerCycleModel:
        """The model of power cycle ``index`` (the nearest earlier one, else the first, when it was not fitted)."""
        by = {p.index: p for p in self.power_cycles}
        if index in by:
            return by[index]
        earlier = [i for i in by if i < index]
        return by[max(earlier)] if earlier else by[min(by)]


def device_model_json_schema() -> dict:
    """JSON Schema (draft 2020-12) of the device-model file, generated from the model."""
    return DeviceModel.model_json_schema()


def load_device_model(path: str | Path) -> DeviceModel:
    """Read and validate a device-model file; a clear error names the file, the field and what was expected."""
    path = Path(path)
    try:
        data = json.loads(path.read_text())
    except FileNotFoundError:
        raise RawDataError(str(path), "file", "a device-model JSON file", "no such file") from None
    except json.JSONDecodeError as e:
        raise RawDataError(path.name, f"line {e.lineno} column {e.colno}", "valid JSON", e.msg) from None
    try:
        return DeviceModel.model_validate(data)
    except ValidationError as e:
        err = e.errors()[0]
        where = ".".join(str(x) for x in err["loc"]) or "file"
        raise RawDataError(path.name, where, err["msg"], repr(err.get("input"))[:120]) from None


def write_device_model(model: DeviceModel, path: str | Path) -> Path:
    """Write atomically (temporary sibling, then rename)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_text(model.model_dump_json(indent=1) + "\n")
    tmp.replace(path)
    return path


if __name__ == "__main__":  # pragma: no cover
    json.dump(device_model_json_schema(), sys.stdout, indent=2)
    sys.stdout.write("\n")
