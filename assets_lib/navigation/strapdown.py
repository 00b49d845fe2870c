"""Free-inertial strapdown navigation in the local-level ENU frame ([SEED002] "捷联惯导算法": attitude, velocity and
position updates; [SEED004] step (2)a: velocity equation with earth rate, transport rate and gravity; position
from the position-matrix rates L' = v_N / (R_M + h), lambda' = v_E / ((R_N + h) cos L)).

Vectorized over a batch of cases (the same true motion with different sensor errors), so an error budget is one
integration. Per step dt, with body increments from the rate and specific force at the step's midpoint:

    C_{k+1} = Exp(-omega_in^n dt) C_k Exp(omega_b dt)              (omega_in^n = omega_ie^n + omega_en^n)
    v_{k+1} = v_k + dt (C_{k+1/2} f_b + g^n - (2 omega_ie^n + omega_en^n) x v_k),
              C_{k+1/2} = Exp(-omega_in^n dt/2) C_k Exp(omega_b dt/2)
    L, lambda from v_N, v_E as above (trapezoidal); height held at the site's (the vertical channel of a free inertial system
    diverges and is always aided: [SEED004] "高度通道发散, 要使用外界高度信息对高度通道进行阻尼").

Earth: WGS-84 radii of curvature, earth rate ``EARTH_RATE_RADPS`` and normal gravity (``assets_lib.sim.earth``),
so a sensor with no error at rest stays at rest. Position and attitude errors of a case are taken against the
error-free case integrated alongside (numerical errors of the scheme cancel).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from assets_lib.sim.earth import EARTH_RATE_RADPS, normal_gravity_mps2

WGS84_A_M = 6378137.0
WGS84_E2 = 0.00669437999013


def radii_m(lat_rad) -> tuple[np.ndarray, np.ndarray]:
    """Meridian R_M and prime-vertical R_N radii of curvature of WGS-84 [m]."""
    s2 = np.sin(lat_rad) ** 2
    rn = WGS84_A_M / np.sqrt(1 - WGS84_E2 * s2)
    return rn * (1 - WGS84_E2) / (1 - WGS84_E2 * s2), rn


def skew(v: np.ndarray) -> np.ndarray:
    """(..., 3) -> (..., 3, 3) cross-product matrices."""
    z = np.zeros(v.shape[:-1])
    return np.stack([np.stack([z, -v[..., 2], v[..., 1]], -1), np.stack([v[..., 2], z, -v[..., 0]], -1),
                     np.stack([-v[..., 1], v[..., 0], z], -1)], -2)


def exp_so3(phi: np.ndarray) -> np.ndarray:
    """Rodrigues: rotation matrices of rotation vectors (..., 3)."""
    th = np.linalg.norm(phi, axis=-1)[..., None, None]
    small = th < 1e-8
    ths = np.where(small, 1.0, th)
    a = np.where(small, 1 - th**2 / 6, np.sin(ths) / ths)
    b = np.where(small, 0.5 - th**2 / 24, (1 - np.cos(ths)) / ths**2)
    k = skew(phi)
    return np.eye(3) + a * k + b * (k @ k)


def _exp_small(phi: np.ndarray) -> np.ndarray:
    """Exp of rotation vectors below 1e-3 rad (navigation-frame rates x dt): I + K + K^2/2, error < |phi|^3 / 6."""
    kx = np.zeros((phi.shape[0], 3, 3))
    kx[:, 0, 1], kx[:, 0, 2], kx[:, 1, 2] = -phi[:, 2], phi[:, 1], -phi[:, 0]
    kx[:, 1, 0], kx[:, 2, 0], kx[:, 2, 1] = phi[:, 2], -phi[:, 1], phi[:, 0]
    return np.eye(3) + kx + 0.5 * (kx @ kx)


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    out = np.empty_like(a)
    out[:, 0] = a[:, 1] * b[:, 2] - a[:, 2] * b[:, 1]
    out[:, 1] = a[:, 2] * b[:, 0] - a[:, 0] * b[:, 2]
    out[:, 2] = a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]
    return out


def attitude_error_rad(c_est: np.ndarray, c_true: np.ndarray) -> np.ndarray:
    """Rotation vector phi (nav frame, ENU: [east tilt, north tilt, heading]) with C_est = Exp(-phi) C_true, i.e.
    C_est = (I - phi x) C_true for small angles; exact (log map) for any size."""
    from scipy.spatial.transform import Rotation

    e = np.asarray(c_true) @ np.swapaxes(np.asarray(c_est), -1, -2)  # Exp(phi)
    shape = e.shape[:-2]
    return Rotation.from_matrix(e.reshape(-1, 3, 3)).as_rotvec().reshape(*shape, 3)


@dataclass(frozen=True)
class NavSolution:
    """States at the requested output times: ``position_en_m`` (cases, times, 2) east/north displacement from the
    start, ``velocity_enu_mps`` (cases, times, 3), ``c_b2n`` (cases, times, 3, 3)."""

    t_s: np.ndarray
    position_en_m: np.ndarray
    velocity_enu_mps: np.ndarray
    c_b2n: np.ndarray


def strapdown(dt_s, omega_b_radps: np.ndarray, f_b_mps2: np.ndarray, c_b2n0: np.ndarray, latitude_deg: float,
              height_m: float = 0.0, out_steps=None, n_steps: int | None = None) -> NavSolution:
    """Integrate a batch of cases. ``omega_b_radps``, ``f_b_mps2``: (cases, steps, 3) or (steps, 3) midpoint inputs of
    each step (broadcast over cases); ``c_b2n0`` (3, 3) initial attitude (ENU), at rest at ``latitude_deg``.
    ``dt_s``: a step length [s] or one per step; ``out_steps``: step counts at which to report (default every
    step); ``n_steps``: number of steps when the inputs are constant (given as one step)."""
    w = np.asarray(omega_b_radps, float)
    f = np.asarray(f_b_mps2, float)
    if w.ndim == 2:
        w = w[None]
    if f.ndim == 2:
        f = f[None]
    k = max(w.shape[0], f.shape[0])
    n = max(w.shape[1], f.shape[1], n_steps or 0, np.size(dt_s) if np.ndim(dt_s) else 0)
    dts = np.broadcast_to(np.asarray(dt_s, float), (n,))
    out_steps = np.arange(n + 1) if out_steps is None else np.asarray(out_steps, int)
    want = set(out_steps.tolist())
    lat0 = np.radians(latitude_deg)
    lat = np.full(k, lat0)
    lon = np.zeros(k)
    v = np.zeros((k, 3))
    c = np.broadcast_to(np.asarray(c_b2n0, float), (k, 3, 3)).copy()
    rm0, rn0 = radii_m(lat0)
    g_site = normal_gravity_mps2(latitude_deg, height_m)
    pos, vel, att = [], [], []

    def record():
        pos.append(np.stack([lon * (rn0 + height_m) * np.cos(lat0), (lat - lat0) * (rm0 + height_m)], -1))
        vel.append(v.copy())
        att.append(c.copy())

    if 0 in want:
        record()
    chunk = 512
    for start in range(0, n, chunk):
        stop = min(n, start + chunk)
        idx = np.arange(start, stop)
        # body-side factors of every step of the chunk at once: Exp(w dt) and the half-step-rotated force
        wc = np.broadcast_to(w[:, idx] if w.shape[1] > 1 else w[:, :1], (k, len(idx), 3))
        fc = np.broadcast_to(f[:, idx] if f.shape[1] > 1 else f[:, :1], (k, len(idx), 3))
        dtc = dts[idx][None, :, None]
        rot_b_all = exp_so3(wc * dtc)
        f_half_all = np.einsum("knij,knj->kni", exp_so3(0.5 * wc * dtc), fc)
        for j, i in enumerate(idx):
            dt_s = dts[i]
            rm, rn = radii_m(lat)
            w_ie = np.zeros((k, 3))
            w_ie[:, 1], w_ie[:, 2] = EARTH_RATE_RADPS * np.cos(lat), EARTH_RATE_RADPS * np.sin(lat)
            w_en = np.empty((k, 3))
            w_en[:, 0] = -v[:, 1] / (rm + height_m)
            w_en[:, 1] = v[:, 0] / (rn + height_m)
            w_en[:, 2] = v[:, 0] * np.tan(lat) / (rn + height_m)
            rot_n_half = _exp_small(-0.5 * (w_ie + w_en) * dt_s)
            f_n = (rot_n_half @ (c @ f_half_all[:, j, :, None]))[..., 0]
            acc = f_n - _cross(2 * w_ie + w_en, v)
            acc[:, 2] -= g_site  # normal gravity of the site (its change over a few km of drift is < 1e-6 g)
            v_old = v
            v = v + dt_s * acc
            v[:, 2] = 0.0  # height aided
            lat = lat + dt_s * 0.5 * (v_old[:, 1] + v[:, 1]) / (rm + height_m)
            lon = lon + dt_s * 0.5 * (v_old[:, 0] + v[:, 0]) / ((rn + height_m) * np.cos(lat))
            c = rot_n_half @ rot_n_half @ c @ rot_b_all[:, j]
            if i + 1 in want:
                record()
    t = np.concatenate([[0.0], np.cumsum(dts)])[out_steps]
    return NavSolution(t, np.stack(pos, 1), np.stack(vel, 1), np.stack(att, 1))
