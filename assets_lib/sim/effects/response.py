"""Sensor-response families: g_sensitivity, scale_factor_nonlinearity, scale_factor_asymmetry (sensor stage)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import brentq

from assets_lib.sim.effects.base import Effect, register, vec3

Z3 = (0.0, 0.0, 0.0)
Z33 = ((0.0,) * 3,) * 3
#: order of the six g-squared products f_j f_k in ``quadratic_radps_per_mps2sq``
G2_PAIRS = ((0, 0), (1, 1), (2, 2), (0, 1), (0, 2), (1, 2))


def _sensed(ctx, sensor: str) -> np.ndarray:
    """The input the triad senses through its scale/misalignment matrix: diag(K)(I+E) x (docs/design.md)."""
    if sensor == "gyro":
        return ctx.inputs.omega_b_radps @ ctx.truth.gyro.matrix().T
    acc = ctx.accel_inputs if getattr(ctx, "accel_inputs", None) is not None else ctx.inputs
    return acc.f_b_mps2 @ ctx.truth.accel.matrix().T


def _add(sensor, gyro, accel, d):
    return (gyro + d, accel) if sensor == "gyro" else (gyro, accel + d)


@register
@dataclass(frozen=True)
class GSensitivity(Effect):
    """[IEEE952] model equation, g-sensitive and g^2 (anisoelastic) drift terms, [TITTERTON2004]:
    w_i += sum_j G[i][j] f_j + sum_(j<=k) G2[i][jk] f_j f_k, f = specific force at the gyro (gravity, centripetal,
    tangential, vibration).

    ``linear_radps_per_mps2`` (3x3, row = gyro axis); ``quadratic_radps_per_mps2sq`` (3x6, columns in the order
    xx, yy, zz, xy, xz, yz). Adds to the truth's own ``g_sensitivity``.
    """

    family = "g_sensitivity"
    stage = "sensor"
    linear_radps_per_mps2: tuple = Z33
    quadratic_radps_per_mps2sq: tuple = ((0.0,) * 6,) * 3

    def apply(self, ctx, gyro, accel):
        f = ctx.inputs.f_b_mps2
        g1 = np.asarray(self.linear_radps_per_mps2, dtype=float).reshape(3, 3)
        g2 = np.asarray(self.quadratic_radps_per_mps2sq, dtype=float).reshape(3, 6)
        prods = np.column_stack([f[:, j] * f[:, k] for j, k in G2_PAIRS])
        return gyro + f @ g1.T + prods @ g2.T, accel


@register
@dataclass(frozen=True)
class ScaleFactorNonlinearity(Effect):
    """[IEEE952] / [IEEE1293] scale-factor nonlinearity (max deviation from the straight line over full scale,
    relative to full scale). With x the sensed input and FS = ``full_scale`` (SI):

    - ``form='polynomial'``: y = x + FS (c2 (x/FS)^2 + c3 (x/FS)^3), c2 = ``quadratic``, c3 = ``cubic``
      (dimensionless, per axis); an even part (w^2) and an S shape (w^3);
    - ``form='compressive'``: y = x_c tanh(x / x_c), with x_c set per axis so that the output at full scale
      falls short by ``max_deviation`` FS (gain compression towards the rails).

    ``max_deviation_fs()`` returns the resulting max |y - x| / FS over [-FS, FS] per axis.
    """

    family = "scale_factor_nonlinearity"
    stage = "sensor"
    sensor: str = "gyro"
    full_scale: float = np.radians(400.0)
    form: str = "polynomial"
    quadratic: tuple = Z3
    cubic: tuple = Z3
    max_deviation: tuple = Z3

    def _check(self):
        if self.sensor not in ("gyro", "accel"):
            raise ValueError(f"scale_factor_nonlinearity.sensor must be 'gyro' or 'accel', not {self.sensor!r}")
        if self.form not in ("polynomial", "compressive"):
            raise ValueError(f"scale_factor_nonlinearity.form must be 'polynomial' or 'compressive', not {self.form!r}")
        if not self.full_scale > 0:
            raise ValueError("scale_factor_nonlinearity.full_scale must be > 0 (SI)")

    def compression_scale(self) -> np.ndarray:
        """x_c per axis solving FS - x_c tanh(FS/x_c) = max_deviation FS (inf for no compression)."""
        out = np.full(3, np.inf)
        for i, d in enumerate(vec3(self.max_deviation, "max_deviation")):
            if d <= 0:
                continue
            if d >= 1:
                raise ValueError("scale_factor_nonlinearity.max_deviation must be < 1")
            fn = lambda u, d=d: 1.0 - u * np.tanh(1.0 / u) - d  # noqa: E731  (u = x_c / FS)
            out[i] = self.full_scale * brentq(fn, 1e-3, 1e6)
        return out

    def deviation(self, x: np.ndarray) -> np.ndarray:
        """y - x for sensed inputs x (n, 3)."""
        self._check()
        fs = self.full_scale
        if self.form == "polynomial":
            u = x / fs
            return fs * (vec3(self.quadratic, "quadratic") * u**2 + vec3(self.cubic, "cubic") * u**3)
        xc = self.compression_scale()
        d = np.zeros_like(x)
        for i in range(3):
            if np.isfinite(xc[i]):
                d[:, i] = xc[i] * np.tanh(x[:, i] / xc[i]) - x[:, i]
        return d

    def max_deviation_fs(self) -> np.ndarray:
        x = np.linspace(-self.full_scale, self.full_scale, 2001)[:, None] * np.ones(3)
        return np.abs(self.deviation(x)).max(axis=0) / self.full_scale

    def apply(self, ctx, gyro, accel):
        return _add(self.sensor, gyro, accel, self.deviation(_sensed(ctx, self.sensor)))


@register
@dataclass(frozen=True)
class ScaleFactorAsymmetry(Effect):
    """[IEEE952] scale-factor asymmetry (definitions), effects.md: K = K_bar (1 + eps/2 sgn x), so y += (eps/2) |x| with x
    the sensed input; eps = (K+ - K-)/K_bar, dimensionless per axis (gyro and accelerometer)."""

    family = "scale_factor_asymmetry"
    stage = "sensor"
    gyro: tuple = Z3
    accel: tuple = Z3

    def apply(self, ctx, gyro, accel):
        g = 0.5 * vec3(self.gyro, "gyro") * np.abs(_sensed(ctx, "gyro"))
        a = 0.5 * vec3(self.accel, "accel") * np.abs(_sensed(ctx, "accel"))
        return gyro + g, accel + a
