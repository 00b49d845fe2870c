"""Unit strings a manifest may declare, and their factors to the canonical SI units.

Canonical units: gyro rad/s, accelerometer m/s^2, time s, temperature degC.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

#: Standard gravity used only to convert values declared in g or mg (ISO 80000-3); local gravity is separate.
STANDARD_GRAVITY_MPS2 = 9.80665

GYRO_UNITS_TO_RADPS: dict[str, float] = {
    "rad/s": 1.0,
    "deg/s": math.pi / 180.0,
    "deg/h": math.pi / 180.0 / 3600.0,
    "mrad/s": 1e-3,
}
ACCEL_UNITS_TO_MPS2: dict[str, float] = {
    "m/s^2": 1.0,
    "g": STANDARD_GRAVITY_MPS2,
    "mg": 1e-3 * STANDARD_GRAVITY_MPS2,
    "ug": 1e-6 * STANDARD_GRAVITY_MPS2,
}
TEMPERATURE_UNITS = {"degC"}
COUNT_UNIT = "counts"

#: Per channel family, the unit strings accepted and the SI factor of each.
UNITS_BY_FAMILY: dict[str, dict[str, float]] = {
    "gyro": GYRO_UNITS_TO_RADPS,
    "accel": ACCEL_UNITS_TO_MPS2,
    "temperature": {"degC": 1.0},
}


def family_of(channel: str) -> str:
    """Channel family from a raw column name (``gyro_x`` -> ``gyro``)."""
    if channel.startswith("gyro_"):
        return "gyro"
    if channel.startswith("accel_"):
        return "accel"
    if channel == "temperature":
        return "temperature"
    raise KeyError(channel)


def si_factor(family: str, unit: str) -> float:
    """Factor that converts a value in ``unit`` to the canonical SI unit of ``family``; KeyError if unknown."""
    return UNITS_BY_FAMILY[family][unit]


# --------------------------------------------------------------------------------------------------------------
# lab units: the one place that knows deg, deg/h, mg, ug, ppm, arcsec (every factor below is the exact float
# expression the project has always used, so tables are bit-identical whichever module converts)
# --------------------------------------------------------------------------------------------------------------
#: degree / rad, degree per hour / (rad/s), arcsec / rad
RAD_TO_DEG = 180.0 / math.pi
RAD_TO_ARCSEC = 180.0 / math.pi * 3600.0
RADPS_TO_DEGPS = 180.0 / math.pi
RADPS_TO_DEGPH = 180.0 / math.pi * 3600.0
#: the inverse direction (lab -> SI), as used to state simulator truths and grade envelopes
DEG_TO_RAD = math.pi / 180.0
DEGPH_TO_RADPS = DEG_TO_RAD / 3600.0
MG_TO_MPS2 = 1e-3 * STANDARD_GRAVITY_MPS2
UG_TO_MPS2 = 1e-6 * STANDARD_GRAVITY_MPS2
ANGLE_UNITS_TO_RAD: dict[str, float] = {"deg": DEG_TO_RAD, "rad": 1.0}


@dataclass(frozen=True)
class LabUnit:
    """SI unit of a quantity and its lab unit: ``lab = factor * si + offset`` (offset: K - 1 in ppm)."""

    si: str
    lab: str
    factor: float
    offset: float = 0.0

    def to_lab(self, value_si: float) -> float:
        return self.factor * value_si + self.offset if self.offset else value_si * self.factor


_G0 = STANDARD_GRAVITY_MPS2
#: Noise terms of the IEEE 952 model (IEEE952 Annex C) per sensor family: Q, N, B, K, R, Markov, sinusoid.
_NOISE_LAB: dict[str, dict[str, LabUnit]] = {
    "gyro": {
        "Q": LabUnit("rad", "arcsec", RAD_TO_DEG * 3600.0),
        "N": LabUnit("rad/s/sqrt(Hz)", "deg/sqrt(h)", RAD_TO_DEG * 60.0),
        "B": LabUnit("rad/s", "deg/h", RAD_TO_DEG * 3600.0),
        "K": LabUnit("rad/s/sqrt(s)", "deg/h/sqrt(h)", RAD_TO_DEG * 3600.0 * 60.0),
        "R": LabUnit("rad/s^2", "deg/h/h", RAD_TO_DEG * 3600.0**2),
        "markov_q": LabUnit("rad/s/sqrt(s)", "deg/h/sqrt(h)", RAD_TO_DEG * 3600.0 * 60.0),
        "markov_tc": LabUnit("s", "s", 1.0),
        "sin_amplitude": LabUnit("rad/s", "deg/h", RAD_TO_DEG * 3600.0),
        "sin_freq": LabUnit("Hz", "Hz", 1.0),
    },
    "accel": {
        "Q": LabUnit("m/s", "m/s", 1.0),
        "N": LabUnit("m/s^2/sqrt(Hz)", "m/s/sqrt(h)", 60.0),
        "B": LabUnit("m/s^2", "ug", 1.0 / (1e-6 * _G0)),
        "K": LabUnit("m/s^2/sqrt(s)", "m/s/h/sqrt(h)", 3600.0 * 60.0),
        "R": LabUnit("m/s^3", "m/s/h^2", 3600.0**2),
        "markov_q": LabUnit("m/s^2/sqrt(s)", "m/s/h/sqrt(h)", 3600.0 * 60.0),
        "markov_tc": LabUnit("s", "s", 1.0),
        "sin_amplitude": LabUnit("m/s^2", "ug", 1.0 / (1e-6 * _G0)),
        "sin_freq": LabUnit("Hz", "Hz", 1.0),
    },
}
#: channels of unknown family: SI labels of the gyro table, no unit for the five IEEE terms
_NOISE_LAB["si"] = {k: LabUnit(v.si, v.si, 1.0) for k, v in _NOISE_LAB["gyro"].items()}
_NOISE_LAB["si"].update({k: LabUnit("", "", 1.0) for k in ("Q", "N", "B", "K", "R")})
NOISE_TERMS = tuple(_NOISE_LAB["gyro"])


def lab_unit(sensor: str, quantity: str) -> LabUnit:
    """The one lab-unit table: SI unit and lab conversion of a calibration coefficient or noise term.

    ``sensor``: 'gyro' | 'accel' ('si' for noise terms of a channel of unknown family). ``quantity``: a
    COEFFICIENT TABLE name (bias, scale_factor*, sf_*, misalignment_*, g_sensitivity_*, k2, cross_coupling_*,
    *_repeatability) or an IEEE 952 noise term (Q, N, B, K, R, markov_q, markov_tc, sin_amplitude, sin_freq).
    KeyError for anything else.
    """
    c = quantity
    if c in NOISE_TERMS:
        return _NOISE_LAB[sensor][c]
    if c in ("bias", "bias_repeatability"):
        return LabUnit("rad/s", "deg/h", RADPS_TO_DEGPH) if sensor == "gyro" else LabUnit("m/s^2", "mg", 1e3 / _G0)
    if c in ("scale_factor", "scale_factor_pos", "scale_factor_neg"):
        return LabUnit("1", "ppm", 1e6, -1e6)
    if c in ("sf_nonlinearity", "sf_asymmetry", "sf_nonlinearity_floor", "scale_factor_repeatability"):
        return LabUnit("1", "ppm", 1e6)
    if c.startswith("misalignment_"):
        return LabUnit("rad", "arcsec", RAD_TO_ARCSEC)
    if c.startswith("g_sensitivity_"):
        return LabUnit("rad/s/(m/s^2)", "deg/h/g", RADPS_TO_DEGPH * _G0)
    if c == "k2" or c.startswith("cross_coupling_"):
        return LabUnit("1/(m/s^2)", "ug/g^2", _G0 * 1e6)
    raise KeyError(f"no unit known for coefficient {quantity!r}")
