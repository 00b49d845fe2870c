"""Plausible coefficient magnitudes per device grade, for quality gates (a coefficient outside is suspect).

Generous envelopes around typical datasheet values ([IEEE952], [IEEE1431] and [IEEE1293] specification formats): a fit that
lands outside means a mis-declared unit, a wrong plan or a broken sensor, not a normal device.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from raw_schemas.units import DEGPH_TO_RADPS as DEGPH, MG_TO_MPS2 as MG


@dataclass(frozen=True)
class GradeEnvelope:
    gyro_bias_radps: float
    gyro_scale_error: float  # |K - 1|
    gyro_misalignment_rad: float
    accel_bias_mps2: float
    accel_scale_error: float
    accel_misalignment_rad: float


GRADE_ENVELOPES: dict[str, GradeEnvelope] = {
    "navigation": GradeEnvelope(1.0 * DEGPH, 500e-6, 2e-3, 1.0 * MG, 1000e-6, 2e-3),
    "tactical": GradeEnvelope(100.0 * DEGPH, 5e-3, 10e-3, 20.0 * MG, 5e-3, 10e-3),
    "industrial": GradeEnvelope(1800.0 * DEGPH, 2e-2, 30e-3, 80.0 * MG, 2e-2, 30e-3),
    "consumer": GradeEnvelope(18000.0 * DEGPH, 5e-2, 60e-3, 150.0 * MG, 5e-2, 60e-3),
}


def implausible(grade: str, sensor: str, coefficient: str, value_si: float) -> str | None:
    """Why ``value_si`` of ``coefficient`` is implausible for the grade, or None (unknown coefficients pass)."""
    env = GRADE_ENVELOPES[grade]
    limit = None
    if coefficient == "bias":
        limit = env.gyro_bias_radps if sensor == "gyro" else env.accel_bias_mps2
        mag = abs(value_si)
    elif coefficient == "scale_factor":
        limit = env.gyro_scale_error if sensor == "gyro" else env.accel_scale_error
        mag = abs(value_si - 1.0)
    elif coefficient.startswith("misalignment"):
        limit = env.gyro_misalignment_rad if sensor == "gyro" else env.accel_misalignment_rad
        mag = abs(value_si)
    if limit is None or not np.isfinite(value_si) or mag <= limit:
        return None
    return f"{sensor} {coefficient} {value_si:.6g} exceeds the {grade} envelope {limit:.3g}"
