"""Table-free gyro calibration: integrate the gyro between static poses and match the attitude change that the
calibrated accelerometer sees ([TEDALDI2014] Sec. III-C / eq. 14-17).

Model (imu_tk's): w = T K (u - b), T unit-diagonal with six free off-diagonal terms, K = diag(k), b the bias
(input units; by default the mean of the initial static interval, imu_tk's choice, and held fixed). Between
pose i and pose i+1 the calibrated rate is integrated (midpoint rotation vectors on the actual time stamps,
composed exactly as quaternions) into R_i (body at i+1 -> body at i); the gravity direction measured at pose i
carried to pose i+1, R_i^T u_i, must equal the direction measured there, u_{i+1}. The 9 (or 12 with
``fit_bias``) parameters minimise the sum of squared direction differences.

A rotation about the gravity direction of a pose pair leaves no trace in this residual; the terms are
separated only by pose pairs whose rotation axes differ. Uncertainty: Gauss-Newton covariance
s^2 (J^T J)^-1 with s^2 = RSS / (2 n_pairs - n_params) (two independent components per unit-vector
residual); the 95 % interval is value -/+ t_{0.975, dof} SE (Student-t, [GUM] G.3: s^2 is estimated from the
residuals), stored in ``ci_low``/``ci_high`` and as ``k95``. The standard error of a fixed bias is propagated
when ``bias_cov`` is given; the errors of the accelerometer-derived directions are not (small against the
integrated gyro noise in the simulated sessions; the cross-axis terms cover ~93-95 % instead of 95 %). Earth rate (up to 7.3e-5 rad/s, ~0.004 deg over a 1 s move) is not modelled, as in imu_tk.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import stats
from scipy.optimize import least_squares

from assets_lib.calibration.tablefree import observability
from assets_lib.coefficient import Coefficient

PARAM_NAMES = ("t01", "t02", "t10", "t12", "t20", "t21", "k_x", "k_y", "k_z")
BIAS_NAMES = ("b_x", "b_y", "b_z")


@dataclass(frozen=True)
class GyroIntegrationFit:
    T: np.ndarray
    scale: np.ndarray
    bias: np.ndarray
    coefficients: dict
    residual: np.ndarray            # (n_pairs, 3) direction differences
    rms_rad: float                  # RMS angle of the direction mismatch
    n_pairs: int
    covariance: np.ndarray
    unobservable: tuple
    bias_fitted: bool
    dof: int = 0                    # residual degrees of freedom 2 n_pairs - n_params of s^2
    k95: float = float(stats.norm.ppf(0.975))  # Student-t coverage factor of the 95 % intervals

    def apply(self, raw: np.ndarray) -> np.ndarray:
        return ((self.T * self.scale[None, :]) @ (np.asarray(raw, float) - self.bias).T).T


def _T(p):
    return np.array([[1.0, p[0], p[1]], [p[2], 1.0, p[3]], [p[4], p[5], 1.0]])


def _quat_mul(a, b):
    w1, x1, y1, z1 = np.moveaxis(a, -1, 0)
    w2, x2, y2, z2 = np.moveaxis(b, -1, 0)
    return np.stack([w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2,
                     w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
                     w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2,
                     w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2], axis=-1)


def _rotvec_to_quat(v):
    ang = np.linalg.norm(v, axis=-1, keepdims=True)
    half = 0.5 * ang
    s = np.where(ang > 1e-12, np.sin(half) / np.where(ang > 1e-12, ang, 1.0), 0.5 - ang * ang / 48.0)
    return np.concatenate([np.cos(half), v * s], axis=-1)


def _quat_to_dcm(q):
    w, x, y, z = np.moveaxis(q, -1, 0)
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
        np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
        np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1)], -2)


class _Segments:
    """Index layout of the motion segments, padded to a power of two for an ordered pairwise quaternion product."""

    def __init__(self, t_s, ends, starts_next):
        self.idx = []
        lens = []
        for e, s in zip(ends, starts_next):
            i0, i1 = max(int(e) - 1, 0), int(s)  # last static sample of pose i .. first static sample of pose i+1
            self.idx.append(np.arange(i0, i1))
            lens.append(i1 - i0)
        L = 1 << int(np.ceil(np.log2(max(max(lens), 1))))
        self.L = L
        self.gather = np.zeros((len(lens), L), dtype=np.int64)
        self.valid = np.zeros((len(lens), L), dtype=bool)
        for j, ix in enumerate(self.idx):
            self.gather[j, : ix.size] = ix
            self.valid[j, : ix.size] = True
        t = np.asarray(t_s, float)
        self.dt = np.where(self.valid, t[np.minimum(self.gather + 1, t.size - 1)] - t[self.gather], 0.0)

    def rotations(self, w):
        """w: (n, 3) calibrated rate. Returns (n_pairs, 3, 3) R_i (body i+1 -> body i)."""
        wm = 0.5 * (w[self.gather] + w[np.minimum(self.gather + 1, w.shape[0] - 1)])
        q = _rotvec_to_quat(wm * self.dt[..., None])
        q[~self.valid] = (1.0, 0.0, 0.0, 0.0)
        while q.shape[1] > 1:
            q = _quat_mul(q[:, 0::2], q[:, 1::2])
        return _quat_to_dcm(q[:, 0])


def fit_gyro_integration(t_s: np.ndarray, gyro_raw: np.ndarray, starts, ends, gravity_dirs: np.ndarray, bias: np.ndarray,
                         *, scale_start: np.ndarray, fit_bias: bool = False, input_unit: str = "counts",
                         bias_cov: np.ndarray | None = None) -> GyroIntegrationFit:
    """[TEDALDI2014] eq. 14-17 (module docstring). ``gravity_dirs``: unit specific-force directions of the
    poses from the calibrated accelerometer; ``bias``: initial (or fixed) gyro bias; ``scale_start``: initial
    diagonal scale (rad/s per input unit); ``bias_cov``: 3x3 covariance of a fixed ``bias``, propagated into
    the covariance of T and K to first order ([GUM] 5.2: dp = -(J^T J)^-1 J^T J_b db)."""
    u = np.asarray(gyro_raw, float)
    starts = np.asarray(starts)
    ends = np.asarray(ends)
    g = np.asarray(gravity_dirs, float)
    g = g / np.linalg.norm(g, axis=1, keepdims=True)
    seg = _Segments(t_s, ends[:-1], starts[1:])
    names = PARAM_NAMES + (BIAS_NAMES if fit_bias else ())
    p0 = np.r_[np.zeros(6), np.asarray(scale_start, float), np.asarray(bias, float) if fit_bias else []]
    b_fixed = np.asarray(bias, float)

    def model(p):
        b = p[9:12] if fit_bias else b_fixed
        return (_T(p) * p[6:9][None, :]) @ (u - b).T

    def resid(p):
        w = model(p).T
        R = seg.rotations(w)
        pred = np.einsum("kji,kj->ki", R, g[:-1])  # R^T u_i
        return (pred - g[1:]).ravel()

    sol = least_squares(resid, p0, x_scale="jac", xtol=1e-12, ftol=1e-12, gtol=1e-12, max_nfev=500)
    p = sol.x
    r = resid(p).reshape(-1, 3)
    n_pairs = r.shape[0]
    dof = 2 * n_pairs - p.size
    s2 = float(np.sum(r * r) / dof) if dof > 0 else np.nan
    k95 = float(stats.t.ppf(0.975, dof)) if dof > 0 else np.nan
    jtj_inv = np.linalg.pinv(sol.jac.T @ sol.jac)
    cov = s2 * jtj_inv
    if bias_cov is not None and not fit_bias:
        bc = np.asarray(bias_cov, float)
        if bc.shape != (3, 3) or not np.all(np.isfinite(bc)):
            raise ValueError(f"bias_cov: expected a finite 3x3 covariance of the fixed bias, got shape {bc.shape}")
        h = 1e-6 * max(float(np.max(np.abs(u))), 1.0) * 1e-3

        def resid_b(b):
            w = ((_T(p) * p[6:9][None, :]) @ (u - b).T).T
            return (np.einsum("kji,kj->ki", seg.rotations(w), g[:-1]) - g[1:]).ravel()

        jb = np.column_stack([(resid_b(b_fixed + h * e) - resid_b(b_fixed - h * e)) / (2 * h) for e in np.eye(3)])
        a_b = -jtj_inv @ sol.jac.T @ jb
        cov = cov + a_b @ bc @ a_b.T
    se = np.sqrt(np.clip(np.diag(cov), 0, None))
    typical = np.r_[np.ones(6), np.abs(p[6:9]), (1.0 / np.abs(p[6:9])) if fit_bias else []]  # bias: 1 rad/s
    unobs = observability(sol.jac, names, typical)
    units = ("1",) * 6 + (f"rad/s per {input_unit}",) * 3 + (input_unit,) * 3
    coefs = {n: (Coefficient.unobservable(units[i]) if n in unobs or dof <= 0 else Coefficient.with_coverage(float(p[i]), float(se[i]), units[i], True, k95))
             for i, n in enumerate(names)}
    b = p[9:12] if fit_bias else b_fixed
    ang = 2 * np.arcsin(np.clip(np.linalg.norm(r, axis=1) / 2, 0, 1))
    return GyroIntegrationFit(_T(p), p[6:9].copy(), np.asarray(b, float), coefs, r, float(np.sqrt(np.mean(ang ** 2))),
                              n_pairs, cov, unobs, fit_bias, max(dof, 0), k95)
