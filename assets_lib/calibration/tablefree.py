"""Table-free accelerometer calibration from hand-placed static poses ([TEDALDI2014]).

Model (imu_tk's, [TEDALDI2014] eq. 8-10): a = T K (u - b) with u the raw reading, b the
bias (input units), K = diag(k) the scale (output per input unit) and T unit-upper-triangular,
T = [[1, t01, t02], [0, 1, t12], [0, 0, 1]] (the accelerometer frame defines the body frame, so three of the six
misalignment angles are fixed). At every static pose the specific force has the magnitude of local gravity, so
the 9 parameters minimise sum_i (|T K (m_i - b)| - g)^2 over the pose means m_i (residuals in m/s^2, the
quantity the acceptance check evaluates; imu_tk minimises the squared-norm difference g^2 - |a|^2, whose optimum
differs at second order). Start: a linear axis-aligned ellipsoid fit, so no nominal bias or scale is needed.

Uncertainty: the Gauss-Newton covariance s^2 (J^T W J)^-1 at the optimum, s^2 = RSS_W / (n_poses - 9) (the scatter
of the pose magnitudes, including model discrepancy, sets the scale). W = diag(N_i / mean N) when the samples
averaged per pose are given (a pose mean of N_i white-noise samples has variance sigma^2 / N_i), else W = I.
Because s^2 is estimated from only n_poses - 9 residual degrees of freedom (21 for 30 poses), the 95 % interval
is value -/+ t_{0.975, n_poses - 9} SE (Student-t, [GUM] G.3; 2.08 for 21 dof), stored in ``ci_low``/``ci_high``
and as ``k95``; the normal 1.96 would cover only ~93.6 % at 21 dof. Observability: a parameter is reported
unobservable when the Jacobian has a singular value below ``rcond`` x the largest along its direction (e.g.
every pose with one axis horizontal); at least 9 poses with distinct attitudes are needed, 12+ recommended.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import stats
from scipy.optimize import least_squares

from assets_lib.coefficient import Coefficient

PARAM_NAMES = ("t01", "t02", "t12", "k_x", "k_y", "k_z", "b_x", "b_y", "b_z")


@dataclass(frozen=True)
class AccelPoseFit:
    """Tedaldi accelerometer fit: T (3x3 unit-upper), k (3), b (3), coefficients, residuals per pose."""

    T: np.ndarray
    scale: np.ndarray
    bias: np.ndarray
    coefficients: dict
    residual_mps2: np.ndarray      # |a_i| - g per pose mean
    rms_mps2: float
    gravity_mps2: float
    n_poses: int
    covariance: np.ndarray
    unobservable: tuple
    dof: int = 0                   # residual degrees of freedom n_poses - 9 of the variance factor s^2
    k95: float = float(stats.norm.ppf(0.975))  # Student-t coverage factor of the 95 % intervals

    def apply(self, raw: np.ndarray) -> np.ndarray:
        """Calibrated specific force T K (u - b) for raw rows u."""
        return ((self.T * self.scale[None, :]) @ (np.asarray(raw, float) - self.bias).T).T


def _unpack(p):
    T = np.array([[1.0, p[0], p[1]], [0.0, 1.0, p[2]], [0.0, 0.0, 1.0]])
    return T, p[3:6], p[6:9]


def apply_accel_params(p, raw):
    T, k, b = _unpack(p)
    return ((T * k[None, :]) @ (np.asarray(raw, float) - b).T).T


def ellipsoid_start(means: np.ndarray, g: float) -> np.ndarray:
    """Axis-aligned ellipsoid through the pose means (linear LS: sum_j p_j m_j^2 + q_j m_j = 1)."""
    c = means.mean(axis=0)
    s = means.std(axis=0) + 1e-300
    z = (means - c) / s
    A = np.hstack([z * z, z])
    sol, *_ = np.linalg.lstsq(A, np.ones(len(z)), rcond=None)
    p, q = sol[:3], sol[3:]
    if np.any(p <= 0):
        return np.r_[0.0, 0.0, 0.0, g / (s * 1.0), c]
    bz = -q / (2 * p)
    r = 1.0 + np.sum(q * q / (4 * p))
    k = np.sqrt(p / r) * g / s
    return np.r_[0.0, 0.0, 0.0, k, c + bz * s]


def observability(jac: np.ndarray, names, typical: np.ndarray, rcond: float = 1e-3) -> tuple:
    """Names of parameters along near-null directions of the Jacobian with columns scaled by each parameter's
    ``typical`` range (1 for a misalignment in rad, |k| for a scale, a full-scale input for a bias), so that a
    singular value compares how much a plausible change of a term moves the residuals: a direction moving them
    less than ``rcond`` x the best-determined one is reported unobservable (its standard error would exceed the
    range)."""
    js = jac * np.asarray(typical, float)[None, :]
    _, sv, vt = np.linalg.svd(js, full_matrices=True)
    sv = np.r_[sv, np.zeros(vt.shape[0] - sv.size)]
    bad = set()
    for s_i, v in zip(sv, vt):
        if s_i < rcond * sv.max():
            bad.update(names[i] for i in np.flatnonzero(np.abs(v) > 0.3))
    return tuple(sorted(bad))


def fit_accel_poses(pose_means: np.ndarray, gravity_mps2: float, *, input_unit: str = "m/s^2",
                    start: np.ndarray | None = None, n_samples: np.ndarray | None = None) -> AccelPoseFit:
    """[TEDALDI2014] eq. 10 (module docstring): 9-parameter accelerometer fit from static pose means.
    ``n_samples``: samples averaged into each pose mean (weights of the least squares), None for equal weights."""
    m = np.asarray(pose_means, float)
    n = m.shape[0]
    g = float(gravity_mps2)
    p0 = ellipsoid_start(m, g) if start is None else np.asarray(start, float)
    if n_samples is None:
        sw = np.ones(n)
    else:
        w = np.asarray(n_samples, float)
        if w.shape != (n,) or np.any(~np.isfinite(w)) or np.any(w <= 0):
            raise ValueError(f"n_samples: expected {n} positive counts (one per pose mean), got {w!r}")
        sw = np.sqrt(w / w.mean())

    def resid(p):
        return np.linalg.norm(apply_accel_params(p, m), axis=1) - g

    sol = least_squares(lambda p: sw * resid(p), p0, x_scale="jac", xtol=1e-15, ftol=1e-15, gtol=1e-15,
                        max_nfev=2000)
    p = sol.x
    r = resid(p)
    rw = sw * r
    dof = n - p.size
    typical = np.r_[np.ones(3), np.abs(p[3:6]), g / np.abs(p[3:6])]
    unobs = observability(sol.jac, PARAM_NAMES, typical) if n >= p.size else PARAM_NAMES
    s2 = float(rw @ rw / dof) if dof > 0 else np.nan
    k95 = float(stats.t.ppf(0.975, dof)) if dof > 0 else np.nan
    try:
        cov = s2 * np.linalg.pinv(sol.jac.T @ sol.jac)
    except np.linalg.LinAlgError:
        cov = np.full((p.size, p.size), np.nan)
    se = np.sqrt(np.clip(np.diag(cov), 0, None))
    units = ("1", "1", "1") + (f"m/s^2 per {input_unit}",) * 3 + (input_unit,) * 3
    coefs = {}
    for i, name in enumerate(PARAM_NAMES):
        coefs[name] = (Coefficient.unobservable(units[i]) if name in unobs or dof <= 0
                       else Coefficient.with_coverage(float(p[i]), float(se[i]), units[i], True, k95))
    T, k, b = _unpack(p)
    return AccelPoseFit(T, k, b, coefs, r, float(np.sqrt(np.mean(r * r))), g, n, cov, unobs, max(dof, 0), k95)


def static_norm_rms(T: np.ndarray, scale: np.ndarray, bias: np.ndarray, pose_means: np.ndarray, gravity_mps2: float) -> float:
    """RMS of |T K (m_i - b)| - g over pose means: the common yardstick for any parameter set (e.g. imu_tk's)."""
    a = ((np.asarray(T) * np.asarray(scale)[None, :]) @ (np.asarray(pose_means) - np.asarray(bias)).T).T
    r = np.linalg.norm(a, axis=1) - gravity_mps2
    return float(np.sqrt(np.mean(r * r)))


def pose_means(t_s: np.ndarray, x: np.ndarray, starts, ends, n_samples: int | None = None) -> np.ndarray:
    """Mean of each static interval ``[start, end)`` (the first ``n_samples`` samples if given: imu_tk uses 100)."""
    x = np.asarray(x, float)
    out = []
    for a, b in zip(starts, ends):
        b2 = b if n_samples is None else min(b, a + n_samples)
        out.append(x[a:b2].mean(axis=0))
    return np.array(out)
