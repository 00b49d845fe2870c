"""Stationary (analytic, coarse) alignment and its error closed forms.

[SEED004] step (2)(1)c: with gravity and earth rate known in the navigation frame and measured in the body frame,
C_b^n = [g^n, w_ie^n, g^n x w_ie^n]^T^-1 [g^b, w_ie^b, g^b x w_ie^b]^T (here with the specific force f = -g,
ENU: f^n = [0, 0, g], w_ie^n = Omega [0, cos L, sin L]), orthonormalized with gravity first (TRIAD).

Closed forms (small errors, level body axes ENU, first order; Titterton & Weston, Strapdown Inertial Navigation
Technology, 2nd ed., sec. 10.3): with the sensor errors resolved in the navigation frame,
    east tilt   phi_E = -b_N / g          north tilt phi_N = b_E / g
    heading     phi_U = -eps_E / (Omega cos L) + (b_E / g) tan L
(phi: C_est = (I - phi x) C_true). The heading error of gyrocompassing is the gyro's east error over the
horizontal earth rate; the level errors are the accelerometers' horizontal errors over g.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from assets_lib.sim.earth import EARTH_RATE_RADPS


def _triad(v1: np.ndarray, v2: np.ndarray) -> np.ndarray:
    """Orthonormal rows (t1, t2, t3): t1 along v1, t2 along v1 x v2, t3 = t1 x t2 (v1 is kept exactly)."""
    t1 = v1 / np.linalg.norm(v1, axis=-1, keepdims=True)
    t2 = np.cross(v1, v2)
    t2 = t2 / np.linalg.norm(t2, axis=-1, keepdims=True)
    return np.stack([t1, t2, np.cross(t1, t2)], -2)


def analytic_alignment(f_b_mps2, omega_b_radps, latitude_deg: float, gravity_mps2: float) -> np.ndarray:
    """[SEED004] analytic alignment: C_b^n (ENU) from mean specific force and angular rate in body axes (..., 3).

    The seed's vector triple (g, w_ie, g x w_ie) in both frames, orthonormalized with gravity first (TRIAD):
    levelling uses the accelerometers only, the heading the gyros' horizontal projection."""
    lat = np.radians(latitude_deg)
    fn = np.array([0.0, 0.0, gravity_mps2])
    wn = EARTH_RATE_RADPS * np.array([0.0, np.cos(lat), np.sin(lat)])
    tn = _triad(fn, wn)
    tb = _triad(np.asarray(f_b_mps2, float), np.asarray(omega_b_radps, float))
    return np.swapaxes(tn, -1, -2) @ tb  # v_n = C v_b:  tn^T tb maps body triad vectors onto nav ones


@dataclass(frozen=True)
class AlignmentError:
    """Level (east and north tilt) and heading errors [rad] of a stationary alignment."""

    east_tilt_rad: np.ndarray
    north_tilt_rad: np.ndarray
    heading_rad: np.ndarray


def alignment_error_closed_form(df_n_mps2, domega_n_radps, latitude_deg: float, gravity_mps2: float) -> AlignmentError:
    """Titterton & Weston sec. 10.3 (module doc): errors from sensor errors resolved in ENU (..., 3)."""
    df = np.asarray(df_n_mps2, float)
    dw = np.asarray(domega_n_radps, float)
    lat = np.radians(latitude_deg)
    return AlignmentError(-df[..., 1] / gravity_mps2, df[..., 0] / gravity_mps2,
                          -dw[..., 0] / (EARTH_RATE_RADPS * np.cos(lat)) + df[..., 0] / gravity_mps2 * np.tan(lat))


def alignment_error_numerical(c_b2n_true, df_b_mps2, domega_b_radps, latitude_deg: float,
                              gravity_mps2: float) -> AlignmentError:
    """Errors of ``analytic_alignment`` run on the true inputs plus body-frame sensor errors (..., 3)."""
    c = np.asarray(c_b2n_true, float)
    lat = np.radians(latitude_deg)
    f_b = c.T @ np.array([0.0, 0.0, gravity_mps2])
    w_b = c.T @ (EARTH_RATE_RADPS * np.array([0.0, np.cos(lat), np.sin(lat)]))
    est = analytic_alignment(f_b + np.asarray(df_b_mps2, float), w_b + np.asarray(domega_b_radps, float),
                             latitude_deg, gravity_mps2)
    # level errors from where the estimate puts the true vertical, heading from where it puts north (so a large
    # heading error does not leak into the tilts as it does in a rotation vector): e = C_true C_est^T ~ I + phi x
    e = c @ np.swapaxes(est, -1, -2)
    return AlignmentError(-np.arcsin(np.clip(e[..., 1, 2], -1, 1)), np.arcsin(np.clip(e[..., 0, 2], -1, 1)),
                          np.arctan2(e[..., 1, 0], e[..., 0, 0]))
