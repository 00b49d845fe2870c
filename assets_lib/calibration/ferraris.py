"""Ferraris calibration (six static positions + three rotations), in imucal's convention, with uncertainties.

[FERRARIS1995], as implemented by imucal (Kuederle et al., JOSS 2022):

* static means U_p (axis j up, column j) and U_a (axis j down); bias b_a = diag(U_p + U_a) / 2 (eq. 19-20);
  K_a^2 = diag(U_d U_d^T) / (4 g^2) with U_d = U_p - U_a (eq. 23); R_a = K_a^-1 U_d / (2 g) (eq. 22);
* gyro bias b_g = mean over all six static phases (earth rate ignored); g-sensitivity
  K_ga = (G_p - G_a) / (2 g) from the gyro means of the same phases (eq. 9);
* the rotations: gyro corrected by b_g and K_ga a_cal, summed over each rotation / rate (eq. 13-14) into the
  columns of W; M = W / expected_angle (eq. 15); K_g^2 = diag(M M^T), R_g = K_g^-1 M (eq. 12).

Calibrated values: a = R_a^-1 K_a^-1 (u_a - b_a); w = R_g^-1 K_g^-1 (u_g - K_ga a - b_g) (imucal's sign
convention: a rotation that integrates to +360 deg against an expected -360 deg puts -1 on R_g's diagonal).

Uncertainty: first-order propagation (numerical Jacobian) of the standard errors of the inputs: every static
mean (sample standard deviation / sqrt(n), the samples taken as independent: an underestimate for correlated
noise) and every rotation sum (the static gyro noise integrated over the rotation's samples). Observability:
all 21 + 9 terms are determined by the six positions and three rotations (no term is unobservable); earth rate
and the rotations' start/stop attitude errors are not modelled and appear only as bias in K_g / R_g.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from assets_lib.coefficient import Coefficient

STATIC_SECTIONS = ("x_p", "x_a", "y_p", "y_a", "z_p", "z_a")
ROTATION_SECTIONS = ("x_rot", "y_rot", "z_rot")


@dataclass(frozen=True)
class FerrarisFit:
    """imucal-compatible matrices (input units per output unit) and their standard errors (same shapes)."""

    K_a: np.ndarray
    R_a: np.ndarray
    b_a: np.ndarray
    K_g: np.ndarray
    R_g: np.ndarray
    K_ga: np.ndarray
    b_g: np.ndarray
    stderr: dict
    gravity: float
    expected_angle_deg: float
    acc_unit: str
    gyr_unit: str
    from_acc_unit: str
    from_gyr_unit: str

    def coefficients(self) -> dict[str, Coefficient]:
        """Every matrix element as a Coefficient, named like ``K_a[0][0]`` (units in imucal's convention)."""
        units = {"K_a": f"{self.from_acc_unit} per {self.acc_unit}", "R_a": "1", "b_a": self.from_acc_unit,
                 "K_g": f"{self.from_gyr_unit} per {self.gyr_unit}", "R_g": "1",
                 "K_ga": f"{self.from_gyr_unit} per {self.acc_unit}", "b_g": self.from_gyr_unit}
        out = {}
        for name, unit in units.items():
            v = np.asarray(getattr(self, name))
            s = np.asarray(self.stderr[name])
            for idx in np.ndindex(v.shape):
                key = name + "".join(f"[{i}]" for i in idx)
                out[key] = Coefficient(float(v[idx]), float(s[idx]), unit)
        return out

    def to_imucal_dict(self) -> dict:
        d = {k: np.asarray(getattr(self, k)).tolist() for k in ("K_a", "R_a", "b_a", "K_g", "R_g", "K_ga", "b_g")}
        d.update(acc_unit=self.acc_unit, gyr_unit=self.gyr_unit, from_acc_unit=self.from_acc_unit,
                 from_gyr_unit=self.from_gyr_unit, cal_type="Ferraris")
        return d

    def calibrate_acc(self, acc: np.ndarray) -> np.ndarray:
        return (np.linalg.inv(self.R_a) @ np.linalg.inv(self.K_a) @ (np.asarray(acc, float) - self.b_a).T).T

    def calibrate_gyr(self, gyr: np.ndarray, acc_cal: np.ndarray) -> np.ndarray:
        g = np.asarray(gyr, float) - (self.K_ga @ np.asarray(acc_cal, float).T).T - self.b_g
        return (np.linalg.inv(self.R_g) @ np.linalg.inv(self.K_g) @ g.T).T


def _solve(acc_means: np.ndarray, gyr_means: np.ndarray, gyr_b: np.ndarray, rot_acc_sums: np.ndarray,
           rot_gyr_sums: np.ndarray, rot_n: np.ndarray, rate_hz: float, grav: float, angle: float):
    """Closed form from the sufficient statistics (all linear in the samples): static means (6 x 3, in
    STATIC_SECTIONS order), the gyro bias, and per rotation the sums of raw acc and gyro and the sample count."""
    U_p = acc_means[0::2].T
    U_a = acc_means[1::2].T
    b_a = np.diag((U_p + U_a) / 2.0)
    U_d = U_p - U_a
    K_a = np.diag(np.sqrt(np.diag(U_d @ U_d.T) / (4.0 * grav ** 2)))
    R_a = np.linalg.inv(K_a) @ U_d / (2.0 * grav)
    G_p = gyr_means[0::2].T
    G_a = gyr_means[1::2].T
    K_ga = (G_p - G_a) / (2.0 * grav)
    A = np.linalg.inv(R_a) @ np.linalg.inv(K_a)
    W = np.zeros((3, 3))
    for j in range(3):
        acc_cal_sum = A @ (rot_acc_sums[j] - rot_n[j] * b_a)  # the correction is linear: sum of calibrated acc
        W[:, j] = (rot_gyr_sums[j] - K_ga @ acc_cal_sum - rot_n[j] * gyr_b) / rate_hz
    M = W @ np.linalg.inv(angle * np.eye(3))
    K_g = np.diag(np.sqrt(np.diag(M @ M.T)))
    R_g = np.linalg.inv(K_g) @ M
    return K_a, R_a, b_a, K_g, R_g, K_ga


def ferraris_fit(sections: dict, sample_rate_hz: float, *, gravity: float = 9.81, expected_angle_deg: float = -360.0,
                 from_acc_unit: str = "a.u.", from_gyr_unit: str = "a.u.") -> FerrarisFit:
    """[FERRARIS1995] closed form (module docstring) from ``sections[name] = (acc (n, 3), gyr (n, 3))`` for the
    nine imucal sections; output in m/s^2 (gravity in m/s^2) and deg/s (expected angle in deg)."""
    missing = [s for s in STATIC_SECTIONS + ROTATION_SECTIONS if s not in sections]
    if missing:
        raise ValueError(f"Ferraris calibration needs sections {list(STATIC_SECTIONS + ROTATION_SECTIONS)}; missing {missing}")
    acc = {k: np.asarray(v[0], float) for k, v in sections.items()}
    gyr = {k: np.asarray(v[1], float) for k, v in sections.items()}
    acc_means = np.array([acc[s].mean(axis=0) for s in STATIC_SECTIONS])
    gyr_means = np.array([gyr[s].mean(axis=0) for s in STATIC_SECTIONS])
    gyr_all = np.vstack([gyr[s] for s in STATIC_SECTIONS])
    b_g = gyr_all.mean(axis=0)
    rot_acc = np.array([acc[s].sum(axis=0) for s in ROTATION_SECTIONS])
    rot_gyr = np.array([gyr[s].sum(axis=0) for s in ROTATION_SECTIONS])
    rot_n = np.array([acc[s].shape[0] for s in ROTATION_SECTIONS], float)
    args = (sample_rate_hz, gravity, expected_angle_deg)
    K_a, R_a, b_a, K_g, R_g, K_ga = _solve(acc_means, gyr_means, b_g, rot_acc, rot_gyr, rot_n, *args)

    # --- first-order uncertainty propagation over the inputs (independent standard errors) ---
    acc_se = np.array([acc[s].std(axis=0, ddof=1) / np.sqrt(len(acc[s])) for s in STATIC_SECTIONS])
    gyr_se = np.array([gyr[s].std(axis=0, ddof=1) / np.sqrt(len(gyr[s])) for s in STATIC_SECTIONS])
    gyr_sd = np.sqrt(np.mean([gyr[s].var(axis=0, ddof=1) for s in STATIC_SECTIONS], axis=0))
    acc_sd = np.sqrt(np.mean([acc[s].var(axis=0, ddof=1) for s in STATIC_SECTIONS], axis=0))
    bg_se = gyr_all.std(axis=0, ddof=1) / np.sqrt(len(gyr_all))
    rot_acc_se = np.sqrt(rot_n)[:, None] * acc_sd[None, :]
    rot_gyr_se = np.sqrt(rot_n)[:, None] * gyr_sd[None, :]
    x0 = np.concatenate([acc_means.ravel(), gyr_means.ravel(), b_g, rot_acc.ravel(), rot_gyr.ravel()])
    se = np.concatenate([acc_se.ravel(), gyr_se.ravel(), bg_se, rot_acc_se.ravel(), rot_gyr_se.ravel()])

    def outputs(x):
        am, gm, bg, ra, rg = x[:18].reshape(6, 3), x[18:36].reshape(6, 3), x[36:39], x[39:48].reshape(3, 3), x[48:57].reshape(3, 3)
        o = _solve(am, gm, bg, ra, rg, rot_n, *args)
        return np.concatenate([m.ravel() for m in o] + [bg])

    y0 = outputs(x0)
    jac = np.empty((y0.size, x0.size))
    for i in range(x0.size):
        h = 1e-6 * max(abs(x0[i]), se[i], 1e-12)
        xp = x0.copy(); xp[i] += h
        xm = x0.copy(); xm[i] -= h
        jac[:, i] = (outputs(xp) - outputs(xm)) / (2 * h)
    sd = np.sqrt(np.einsum("ij,j,ij->i", jac, se ** 2, jac))
    shapes = [("K_a", (3, 3)), ("R_a", (3, 3)), ("b_a", (3,)), ("K_g", (3, 3)), ("R_g", (3, 3)), ("K_ga", (3, 3)), ("b_g", (3,))]
    stderr, pos = {}, 0
    for name, shp in shapes:
        size = int(np.prod(shp))
        stderr[name] = sd[pos:pos + size].reshape(shp)
        pos += size
    return FerrarisFit(K_a, R_a, b_a, K_g, R_g, K_ga, b_g, stderr, gravity, expected_angle_deg,
                       "m/s^2", "deg/s", from_acc_unit, from_gyr_unit)
