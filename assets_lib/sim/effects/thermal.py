"""Thermal and time-since-power-on bias families: temperature_bias, temperature_scale_factor, warmup_bias,
bias_ramp, bias_step (sensor stage; outputs in SI)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from assets_lib.sim.effects.base import Effect, lagged, register, vec3

Z3 = (0.0, 0.0, 0.0)


def _sensor_temperature(ctx, lag_s: float) -> np.ndarray:
    return lagged(ctx.temperature_degc, ctx.t_s, lag_s)


@register
@dataclass(frozen=True)
class TemperatureBias(Effect):
    """[IEEE952] model equation, temperature-sensitive drift term, [TITTERTON2004]: b(T) = k1 dT + k2 dT^2, dT = T_s - T0.

    T_s is the sensing element's temperature: the thermometer temperature through a first-order lag
    ``lag_s`` (dT_s/dt = (T - T_s)/lag_s; 0 = no lag), which makes the bias show hysteresis between heating
    and cooling when plotted against the logged temperature (effects.md: die-vs-thermometer lag).
    Gyro [rad/s/K, rad/s/K^2], accelerometer [m/s^2/K, m/s^2/K^2], per body axis.
    """

    family = "temperature_bias"
    stage = "sensor"
    gyro_radps_per_k: tuple = Z3
    gyro_radps_per_k2: tuple = Z3
    accel_mps2_per_k: tuple = Z3
    accel_mps2_per_k2: tuple = Z3
    reference_degc: float = 25.0
    lag_s: float = 0.0

    def apply(self, ctx, gyro, accel):
        dt = (_sensor_temperature(ctx, self.lag_s) - self.reference_degc)[:, None]
        g = dt * vec3(self.gyro_radps_per_k, "gyro_radps_per_k") + dt**2 * vec3(self.gyro_radps_per_k2, "gyro_radps_per_k2")
        a = dt * vec3(self.accel_mps2_per_k, "accel_mps2_per_k") + dt**2 * vec3(self.accel_mps2_per_k2, "accel_mps2_per_k2")
        return gyro + g, accel + a


@register
@dataclass(frozen=True)
class TemperatureScaleFactor(Effect):
    """[IEEE952] model equation, scale-factor temperature sensitivity, effects.md: SF(T) = SF0 (1 + s1 dT), dT = T_s - T0.

    Added as s1 dT times the sensed input through the truth's scale/misalignment matrix; s1 [1/K] per axis;
    T_s lagged like :class:`TemperatureBias`.
    """

    family = "temperature_scale_factor"
    stage = "sensor"
    gyro_per_k: tuple = Z3
    accel_per_k: tuple = Z3
    reference_degc: float = 25.0
    lag_s: float = 0.0

    def apply(self, ctx, gyro, accel):
        dt = (_sensor_temperature(ctx, self.lag_s) - self.reference_degc)[:, None]
        acc_in = ctx.accel_inputs if getattr(ctx, "accel_inputs", None) is not None else ctx.inputs
        sg = ctx.inputs.omega_b_radps @ ctx.truth.gyro.matrix().T
        sa = acc_in.f_b_mps2 @ ctx.truth.accel.matrix().T
        return gyro + dt * vec3(self.gyro_per_k, "gyro_per_k") * sg, accel + dt * vec3(self.accel_per_k, "accel_per_k") * sa


@register
@dataclass(frozen=True)
class WarmupBias(Effect):
    """[IEEE952] warm-up (turn-on transient) test, effects.md: b(t) = sum_j A_j exp(-t_on / tau_j), t_on from power-on.

    ``tau_s`` lists the time constants; ``gyro_radps`` / ``accel_mps2`` give one (x, y, z) amplitude per time
    constant (the bias at power-on minus its settled value). Continuous across the runs of a power cycle because
    t_on counts from power-on, not from the run start.
    """

    family = "warmup_bias"
    stage = "sensor"
    tau_s: tuple = (600.0,)
    gyro_radps: tuple = (Z3,)
    accel_mps2: tuple = (Z3,)

    def _sum(self, t_on, amps, name):
        amps = np.asarray(amps, dtype=float).reshape(-1, 3)
        if amps.shape[0] != len(self.tau_s):
            raise ValueError(f"warmup_bias.{name}: one (x, y, z) amplitude per time constant ({len(self.tau_s)})")
        out = np.zeros((t_on.size, 3))
        for a, tau in zip(amps, self.tau_s):
            out += np.exp(-t_on / float(tau))[:, None] * a
        return out

    def apply(self, ctx, gyro, accel):
        t_on = np.asarray(ctx.time_since_power_on_s, dtype=float)
        return gyro + self._sum(t_on, self.gyro_radps, "gyro_radps"), accel + self._sum(t_on, self.accel_mps2, "accel_mps2")


@register
@dataclass(frozen=True)
class BiasRamp(Effect):
    """[IEEE952] Annex C rate-ramp term (deterministic part): b(t) = R t_on, t_on from power-on, so the ramp is
    continuous across the runs of a power cycle. Gyro [rad/s per s], accelerometer [m/s^2 per s]."""

    family = "bias_ramp"
    stage = "sensor"
    gyro_radps_per_s: tuple = Z3
    accel_mps2_per_s: tuple = Z3

    def apply(self, ctx, gyro, accel):
        t_on = np.asarray(ctx.time_since_power_on_s, dtype=float)[:, None]
        return (gyro + t_on * vec3(self.gyro_radps_per_s, "gyro_radps_per_s"),
                accel + t_on * vec3(self.accel_mps2_per_s, "accel_mps2_per_s"))


@register
@dataclass(frozen=True)
class BiasStep(Effect):
    """Bias step (a mode hop, a fixture knock, [IEEE952] bias shift): b(t) = D (1 - exp(-(t - t_s)/tau))
    for t >= t_s, else 0; ``settle_tau_s`` = 0 is an instantaneous step.

    ``at_s`` is on the run's IMU clock (``clock='run'``) or counted from power-on (``clock='power_on'``).
    Gyro [rad/s], accelerometer [m/s^2] per axis.
    """

    family = "bias_step"
    stage = "sensor"
    at_s: float = 0.0
    gyro_radps: tuple = Z3
    accel_mps2: tuple = Z3
    settle_tau_s: float = 0.0
    clock: str = "run"

    def shape(self, ctx) -> np.ndarray:
        if self.clock not in ("run", "power_on"):
            raise ValueError(f"bias_step.clock must be 'run' or 'power_on', not {self.clock!r}")
        t = np.asarray(ctx.t_s if self.clock == "run" else ctx.time_since_power_on_s, dtype=float) - self.at_s
        on = t >= 0
        if self.settle_tau_s > 0:
            return np.where(on, -np.expm1(-np.clip(t, 0, None) / self.settle_tau_s), 0.0)
        return on.astype(float)

    def apply(self, ctx, gyro, accel):
        s = self.shape(ctx)[:, None]
        return gyro + s * vec3(self.gyro_radps, "gyro_radps"), accel + s * vec3(self.accel_mps2, "accel_mps2")
