"""The simulator's base sensor chain: the deterministic error model of docs/design.md, the Allan noise of each
axis and output saturation, plus a wild-plateau disturbance used by tests. ``DEFAULT_EFFECTS`` is what
``simulate_run`` applies when no chain is given; the families in this package add to it (``sensor_chain``)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from assets_lib.sim.noise import allan_noise


@dataclass(frozen=True)
class ErrorModel:
    """Deterministic model of docs/design.md ([SEED000] eq. 1-2): scale, misalignment, bias, g-sensitivity, K2, Kc."""

    name: str = "error_model"

    def apply(self, ctx, gyro, accel):
        tr = ctx.truth
        w, f = ctx.inputs.omega_b_radps, ctx.inputs.f_b_mps2
        g = w @ tr.gyro.matrix().T + np.asarray(tr.gyro.bias) + f @ np.asarray(tr.g_sensitivity).T
        if ctx.accel_inputs is not None:
            f = ctx.accel_inputs.f_b_mps2
        kc = np.asarray(tr.accel.kc)
        a = f @ tr.accel.matrix().T + np.asarray(tr.accel.bias) + np.asarray(tr.accel.k2) * f**2
        a = a + f * (f @ kc.T)
        return gyro + g, accel + a


@dataclass(frozen=True)
class AllanNoise:
    """Allan noise of each axis (IEEE 952 Annex C), from the truth's per-axis ``AllanParams``."""

    name: str = "allan_noise"

    def apply(self, ctx, gyro, accel):
        n = ctx.t_s.size
        gyro = gyro.copy()
        accel = accel.copy()
        for i in range(3):
            gyro[:, i] += allan_noise(n, ctx.rate_hz, ctx.truth.gyro.noise[i], ctx.rng)
            accel[:, i] += allan_noise(n, ctx.rate_hz, ctx.truth.accel.noise[i], ctx.rng)
        return gyro, accel


@dataclass(frozen=True)
class Saturation:
    """Output clipped at the triads' full scale (effects.md: flat tops beyond full scale)."""

    name: str = "saturation"

    def apply(self, ctx, gyro, accel):
        fs_g, fs_a = ctx.truth.gyro.full_scale, ctx.truth.accel.full_scale
        if fs_g:
            gyro = np.clip(gyro, -fs_g, fs_g)
        if fs_a:
            accel = np.clip(accel, -fs_a, fs_a)
        return gyro, accel


@dataclass(frozen=True)
class PlateauDisturbance:
    """A wild plateau: a constant offset on one channel during one plan step (a fixture knock, a glitch)."""

    step_index: int
    sensor: str  # 'gyro' | 'accel'
    axis: int
    offset: float  # SI
    name: str = "plateau_disturbance"

    def apply(self, ctx, gyro, accel):
        m = ctx.step_index == self.step_index
        out = (gyro if self.sensor == "gyro" else accel).copy()
        out[m, self.axis] += self.offset
        return (out, accel) if self.sensor == "gyro" else (gyro, out)


DEFAULT_EFFECTS: tuple = (ErrorModel(), AllanNoise(), Saturation())
