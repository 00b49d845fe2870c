"""Table and environment families: table_rate_error, table_wobble (table stage), lever_arm, vibration (input
stage). The written table log stays the nominal (commanded) one: the IMU senses the true motion."""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from assets_lib.sim.effects.base import Effect, TableMotion, register, vec3
from assets_lib.sim.kinematics import rotation_about

Z3 = (0.0, 0.0, 0.0)


@register
@dataclass(frozen=True)
class TableRateError(Effect):
    """Effects.md turntable rate error / ripple: w_true = w_cmd (1 + eps + sum_k a_k sin(k theta + phi_k)), k = 1, 2.

    eps = ``mean_error``; a_1, a_2 = ``ripple_1_per_rev``, ``ripple_2_per_rev`` (dimensionless, relative to the
    rate), phases [rad]. The angle follows exactly: d_theta = eps theta + sum_k (a_k / k)(cos phi_k - cos(k theta +
    phi_k)) (first order in a_k), applied as a rotation about the table axis. The table log keeps w_cmd and the
    nominal angle, so eps is a scale-factor error for the gyro fit and the ripple averages out over whole turns.
    """

    family = "table_rate_error"
    stage = "table"
    mean_error: float = 0.0
    ripple_1_per_rev: float = 0.0
    ripple_1_phase_rad: float = 0.0
    ripple_2_per_rev: float = 0.0
    ripple_2_phase_rad: float = 0.0

    def _terms(self):
        return ((1, self.ripple_1_per_rev, self.ripple_1_phase_rad), (2, self.ripple_2_per_rev, self.ripple_2_phase_rad))

    def perturb(self, m: TableMotion) -> TableMotion:
        th, w = m.table_angle_rad, m.table_rate_radps
        dth = self.mean_error * th
        rel = np.full(th.shape, self.mean_error)
        for k, a, ph in self._terms():
            if a:
                dth = dth + (a / k) * (np.cos(ph) - np.cos(k * th + ph))
                rel = rel + a * np.sin(k * th + ph)
        rot = rotation_about(m.axis_level, dth)
        c = rot @ m.c_b2l
        wl = np.einsum("nij,nj->ni", rot, m.omega_motion_level_radps) + (w * rel)[:, None] * m.axis_level
        return replace(m, c_b2l=c, omega_motion_level_radps=wl, table_angle_rad=th + dth, table_rate_radps=w * (1 + rel))


@register
@dataclass(frozen=True)
class TableWobble(Effect):
    """Effects.md table wobble / axis tilt, two rigid-body forms (tilts in rad, small):

    * ``tilt_rad`` towards ``azimuth_rad`` (about the nominal axis from level-frame x): the bearing axis itself is
      tilted, fixed in space. The true orientation is R(k, beta) C_b^l and the table spins about the tilted axis
      R a, so the body rate is unchanged (a rigid rotation about a body-fixed axis); the tilt turns with the table as
      seen from the IMU: horizontal accelerometers read a once-per-revolution g beta sin(theta + phi), and the
      earth-rate projection changes by the same rotation. No gyro term.
    * ``wobble_rad`` towards ``wobble_azimuth_rad`` (platter frame, at table angle 0): the platter (the IMU mount)
      is tilted against the spin axis, so its normal cones about the axis once per turn. In the level frame the
      tilt P(theta) = R(a, theta) W R(a, theta)^T turns with the table; the orientation is P C_b^l and, since P
      changes with theta, the level-frame rate gains the coning term ([TITTERTON2004] angular rate of a
      time-varying rotation, d/dt (P C) (P C)^T): w_l' = P w_l + theta_dot (a - P a). In body axes the spin
      axis is tilted by beta: the gyro reads a constant cross-axis omega beta (proportional to the table rate,
      like a misalignment of this mount) and the accelerometers a constant g beta; no once-per-revolution term.
    """

    family = "table_wobble"
    stage = "table"
    tilt_rad: float = 0.0
    azimuth_rad: float = 0.0
    wobble_rad: float = 0.0
    wobble_azimuth_rad: float = 0.0

    @staticmethod
    def _tip(axis_level: np.ndarray, beta: float, azimuth: float) -> np.ndarray:
        a = np.asarray(axis_level, dtype=float)
        e1 = np.cross(a, [0.0, 1.0, 0.0]) if abs(a[0]) < 0.9 else np.cross(a, [0.0, 0.0, 1.0])
        e1 = np.cross(e1, a)
        e1 /= np.linalg.norm(e1)
        e2 = np.cross(a, e1)
        d = np.cos(azimuth) * e1 + np.sin(azimuth) * e2  # tilt direction
        return rotation_about(np.cross(a, d), beta)  # tips the axis a towards d by beta

    def tilt_rotation(self, axis_level: np.ndarray) -> np.ndarray:
        return self._tip(axis_level, self.tilt_rad, self.azimuth_rad)

    def perturb(self, m: TableMotion) -> TableMotion:
        c, wl = m.c_b2l, m.omega_motion_level_radps
        if self.wobble_rad:
            a = np.asarray(m.axis_level, dtype=float)
            rt = rotation_about(a, m.table_angle_rad)  # (n, 3, 3)
            p = rt @ self._tip(a, self.wobble_rad, self.wobble_azimuth_rad) @ np.swapaxes(rt, 1, 2)
            c = p @ c
            wl = np.einsum("nij,nj->ni", p, wl) + m.table_rate_radps[:, None] * (a - p @ a)
        if self.tilt_rad:
            r = self.tilt_rotation(m.axis_level)
            c, wl = r @ c, wl @ r.T
        return replace(m, c_b2l=c, omega_motion_level_radps=wl)


@register
@dataclass(frozen=True)
class LeverArm(Effect):
    """[TITTERTON2004] lever-arm (size) effect: the accelerometer at body position r (from a point on the
    rotation axis) senses f = f_0 + dw/dt x r + w x (w x r), w = table motion rate in body axes.

    ``position_m`` (x, y, z) [m]; on a plateau the centripetal term is -w^2 r_perp (radial), during ramps the
    tangential term dw/dt x r appears. Only the accelerometer triad's input changes.
    """

    family = "lever_arm"
    stage = "input"
    position_m: tuple = Z3

    def add_inputs(self, triad: str, inputs, motion: TableMotion):
        if triad != "accel":
            return inputs
        r = vec3(self.position_m, "position_m")
        w = motion.omega_motion_body_radps()
        wd = motion.omega_dot_body_radps2()
        extra = np.cross(wd, r) + np.cross(w, np.cross(w, r))
        return replace(inputs, f_b_mps2=inputs.f_b_mps2 + extra)


@register
@dataclass(frozen=True)
class Vibration(Effect):
    """Effects.md vibration (table motor, environment), [IEEE1293] vibration environment: a sinusoid of frequency
    ``frequency_hz`` in the sensed inputs, w += A_w sin(2 pi f t + phi), f += A_a sin(2 pi f t + phi).

    ``gyro_radps`` [rad/s] and ``accel_mps2`` [m/s^2] amplitudes per body axis; the vibration passes through the
    sensor model, so a g^2 sensitivity rectifies it. Keep f below Nyquist for a resolved line (above it aliases,
    as in a real unfiltered IMU).
    """

    family = "vibration"
    stage = "input"
    frequency_hz: float = 0.0
    gyro_radps: tuple = Z3
    accel_mps2: tuple = Z3
    phase_rad: float = 0.0

    def add_inputs(self, triad: str, inputs, motion: TableMotion):
        s = np.sin(2 * np.pi * self.frequency_hz * motion.t_s + self.phase_rad)[:, None]
        if triad == "gyro":
            return replace(inputs, omega_b_radps=inputs.omega_b_radps + s * vec3(self.gyro_radps, "gyro_radps"))
        return replace(inputs, f_b_mps2=inputs.f_b_mps2 + s * vec3(self.accel_mps2, "accel_mps2"))
