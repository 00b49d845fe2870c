"""Clock families: latency and timebase_error (clock stage: they decide when each triad senses its input)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from assets_lib.sim.effects.base import Effect, register


@register
@dataclass(frozen=True)
class Latency(Effect):
    """Effects.md latency, [GROVES2013] (sensor and processing delay): the sample stamped t on the IMU clock
    holds the input of true time t - delay, per triad: y(t) = h(t - dt) ~ h - dt dh/dt.

    The kinematics are evaluated at the delayed times (no interpolation of outputs, so the noise stays white).
    ``gyro_s``, ``accel_s`` [s]; a delay common to both triads is indistinguishable from a table clock offset.
    """

    family = "latency"
    stage = "clock"
    gyro_s: float = 0.0
    accel_s: float = 0.0

    def true_time_s(self, t_s: np.ndarray, triad: str) -> np.ndarray:
        d = self.gyro_s if triad == "gyro" else self.accel_s
        return t_s - d if d else t_s

    def input_gain(self, triad: str) -> float:
        return 1.0


@register
@dataclass(frozen=True)
class TimebaseError(Effect):
    """Effects.md clock-rate mismatch: t_imu = (1 + eps) t_table (eps = ``clock_rate_error``, dimensionless).

    The IMU stamps its samples on its own clock, so true time runs 1/(1 + eps) as fast as the stamps (the table
    log, on the true clock, drifts against them by eps x run length). With ``integrating_outputs`` (delta-angle /
    delta-velocity outputs divided by the nominal sample period, the usual FOG / tactical IMU case) every output
    also scales by 1/(1 + eps) (the sample period is 1/(1 + eps) of nominal): a common scale-factor error of
    -eps on gyros and accelerometers alike ([TITTERTON2004], incremental outputs).
    """

    family = "timebase_error"
    stage = "clock"
    clock_rate_error: float = 0.0
    integrating_outputs: bool = True

    def true_time_s(self, t_s: np.ndarray, triad: str) -> np.ndarray:
        return t_s / (1.0 + self.clock_rate_error) if self.clock_rate_error else t_s

    def input_gain(self, triad: str) -> float:
        return 1.0 / (1.0 + self.clock_rate_error) if self.integrating_outputs else 1.0
