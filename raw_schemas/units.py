"""Unit strings a manifest may declare, and their factors to the canonical SI units.

Canonical units: gyro rad/s, accelerometer m/s^2, time s, temperature degC.
"""

from __future__ import annotations

import math

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
