"""Registry, serialisation and shared helpers of the effect families (see the package docstring)."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import ClassVar

import numpy as np
from scipy.signal import lfilter

#: family name -> effect class (pvlib iam.py style registry)
EFFECTS: dict[str, type] = {}
STAGES = ("clock", "table", "input", "sensor", "noise")
AXES = ("x", "y", "z")


def register(cls):
    """Class decorator: add a family to ``EFFECTS`` under ``cls.family``."""
    if cls.stage not in STAGES:
        raise ValueError(f"{cls.__name__}: stage must be one of {STAGES}, not {cls.stage!r}")
    if cls.family in EFFECTS:
        raise ValueError(f"effect family {cls.family!r} registered twice")
    EFFECTS[cls.family] = cls
    return cls


def _tuples(v):
    if isinstance(v, np.ndarray):
        v = v.tolist()
    if isinstance(v, (list, tuple)):
        return tuple(_tuples(x) for x in v)
    return v


def _plain(v):
    if isinstance(v, (list, tuple)):
        return [_plain(x) for x in v]
    if isinstance(v, (np.floating, np.integer)):
        return v.item()
    return v


@dataclass(frozen=True)
class Effect:
    """Base of every family: ``family`` (registry name), ``stage``; parameters are the dataclass fields."""

    family: ClassVar[str] = ""
    stage: ClassVar[str] = ""

    def __post_init__(self):  # arrays and lists become (nested) tuples: hashable, comparable, JSON-ready
        for f in dataclasses.fields(self):
            v = getattr(self, f.name)
            if isinstance(v, (list, tuple, np.ndarray)):
                object.__setattr__(self, f.name, _tuples(v))
            elif isinstance(v, (np.floating, np.integer)):
                object.__setattr__(self, f.name, v.item())

    @property
    def name(self) -> str:  # the simulator's SensorEffect protocol and manifest notes use ``name``
        return self.family

    def to_dict(self) -> dict:
        return {"family": self.family,
                "params": {f.name: _plain(getattr(self, f.name)) for f in dataclasses.fields(self)}}

    @classmethod
    def from_params(cls, params: dict):
        names = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(params) - names)
        if unknown:
            raise ValueError(f"effect {cls.family!r}: unknown parameter(s) {unknown}; expected some of {sorted(names)}")
        return cls(**{k: _tuples(v) for k, v in params.items()})

    # a pre-sensor effect passes the outputs through unchanged when a caller runs it in the sensor chain
    def apply(self, ctx, gyro, accel):
        return gyro, accel


def effect_from_dict(d: dict) -> Effect:
    """Inverse of ``Effect.to_dict``; a clear error for an unknown family or parameter."""
    fam = d.get("family")
    if fam not in EFFECTS:
        raise ValueError(f"unknown effect family {fam!r}; known: {sorted(EFFECTS)}")
    return EFFECTS[fam].from_params(d.get("params", {}))


def effects_from_list(items) -> tuple[Effect, ...]:
    return tuple(effect_from_dict(d) for d in items)


def split_stages(effects) -> dict[str, list]:
    """Registered effects grouped by stage; objects without a registered stage (the base chain) under 'chain'."""
    out: dict[str, list] = {s: [] for s in STAGES}
    out["chain"] = []
    for e in effects:
        st = getattr(type(e), "stage", None)
        (out[st] if st in STAGES else out["chain"]).append(e)
    return out


def sensor_chain(extra=(), base=None) -> tuple:
    """The simulator's effect chain with ``extra`` families added where they belong: clock/table/input effects
    (run before the kinematics, listed first), sensor effects after the error model, noise effects after the
    Allan noise, saturation last."""
    from assets_lib.sim.effects.core import DEFAULT_EFFECTS, AllanNoise, ErrorModel

    base = tuple(DEFAULT_EFFECTS if base is None else base)
    st = split_stages(extra)
    out = list(st["clock"] + st["table"] + st["input"])
    placed_s = placed_n = False
    for e in base:
        out.append(e)
        if isinstance(e, ErrorModel):
            out += st["sensor"]
            placed_s = True
        if isinstance(e, AllanNoise):
            out += st["noise"]
            placed_n = True
    if not placed_s:
        out += st["sensor"]
    if not placed_n:
        out += st["noise"]
    return tuple(out)


@dataclass(frozen=True)
class TableMotion:
    """True table motion at the times one triad senses: C_b^l (n,3,3), level-frame motion rate (n,3) [rad/s],
    table angle [rad] and rate [rad/s] about the table axis, step index, unit table axis (level frame)."""

    t_s: np.ndarray
    c_b2l: np.ndarray
    omega_motion_level_radps: np.ndarray
    table_angle_rad: np.ndarray
    table_rate_radps: np.ndarray
    step_index: np.ndarray
    axis_level: np.ndarray

    def omega_motion_body_radps(self) -> np.ndarray:
        return np.einsum("nji,nj->ni", self.c_b2l, self.omega_motion_level_radps)

    def omega_dot_body_radps2(self) -> np.ndarray:
        """d(omega_b)/dt = C^T d(omega_l)/dt (the omega x omega term vanishes), by central differences."""
        if self.t_s.size < 2:
            return np.zeros_like(self.omega_motion_level_radps)
        wdot_l = np.gradient(self.omega_motion_level_radps, self.t_s, axis=0)
        return np.einsum("nji,nj->ni", self.c_b2l, wdot_l)


def lagged(x: np.ndarray, t_s: np.ndarray, tau_s: float) -> np.ndarray:
    """First-order lag dy/dt = (x - y)/tau, exact for a piecewise-constant input on the median step, y(0) = x(0)."""
    x = np.asarray(x, dtype=float)
    if tau_s <= 0 or x.size < 2:
        return x
    dt = float(np.median(np.diff(t_s)))
    a = np.exp(-dt / tau_s)
    y, _ = lfilter([1 - a], [1, -a], x, zi=[a * x[0]])
    return y


def vec3(v, name: str) -> np.ndarray:
    a = np.asarray(v, dtype=float)
    if a.shape != (3,):
        raise ValueError(f"{name}: expected 3 values (x, y, z), got shape {a.shape}")
    return a
