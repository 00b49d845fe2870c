"""Apply a calibration: invert the sensor error model (docs/design.md, [SEED000] eq. 1-2) sample by sample.

    accel: f = M_a^-1 (y_a - b_a - K2 f**2 - f * (Kc f))      M = diag(K)(I + E); fixed-point iteration from
                                                              f_0 = M_a^-1 (y_a - b_a), iterated to convergence
                                                              (second-order terms are < 1e-3 of f: a contraction)
    gyro:  w = M_g^-1 (y_g - b_g - G f)                       with f the corrected specific force

This is the record's own convention (the simulator's forward model, ``forward``, is its exact inverse), not
imu_tk's ``T K (y - b)`` nor imucal's ``R^-1 K^-1 (y - b)``: those are the same equations with M factored
differently (see ``assets_lib.records.export``).

``correction_stderr`` propagates the terms' standard errors into the corrected signals (first order, terms
independent: a record carries standard errors, not covariances), used for z-scores and the navigation budget,
and adds the bias drift between the calibration and the data (``assets_lib.apply.drift``: bias instability and
random walk from the calibration's Allan terms over the time span of the data, turn-on repeatability across
power cycles), an independent input of [GUM] eq. 10.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
import pandas as pd

from assets_lib.apply.drift import ApplySpan, BiasDrift, bias_drift
from assets_lib.apply.model import FAMILY_FIELDS, Calibration, Triad

GYRO_COLUMNS = ("gyro_x_radps", "gyro_y_radps", "gyro_z_radps")
ACCEL_COLUMNS = ("accel_x_mps2", "accel_y_mps2", "accel_z_mps2")
#: fixed-point iterations a firmware export prescribes (contraction ~2 K2 |f| < 1e-2 per step for any
#: plausible device: 4 steps leave < 1e-8 of the second-order term); ``correct`` iterates to convergence
ACCEL_ITERATIONS = 4
MAX_ITERATIONS = 60


@dataclass(frozen=True)
class Corrected:
    """Calibrated angular rate [rad/s] and specific force [m/s^2], (n, 3) each, body (sensor-triad) axes."""

    gyro_radps: np.ndarray
    accel_mps2: np.ndarray


def _as3(a, name: str) -> np.ndarray:
    x = np.asarray(a, dtype=float)
    if x.ndim == 1:
        x = x[None, :]
    if x.ndim != 2 or x.shape[1] != 3:
        raise ValueError(f"{name}: expected an (n, 3) array, got shape {np.shape(a)}")
    return x


def forward(cal: Calibration, omega_b_radps, f_b_mps2) -> Corrected:
    """[SEED000] eq. 1-2 (docs/design.md): the outputs the modelled sensor gives for true inputs (no noise)."""
    w, f = _as3(omega_b_radps, "omega_b_radps"), _as3(f_b_mps2, "f_b_mps2")
    g, a = cal.gyro, cal.accel
    yg = w @ g.matrix().T + g.bias + f @ g.g_sensitivity.T
    ya = f @ a.matrix().T + a.bias + a.k2 * f**2 + f * (f @ a.cross_coupling.T)
    return Corrected(yg, ya)


def correct(cal: Calibration, gyro_radps, accel_mps2) -> Corrected:
    """[SEED000] eq. 1-2 inverted: calibrated rate and specific force from the sensor outputs (SI, body axes)."""
    yg, ya = _as3(gyro_radps, "gyro_radps"), _as3(accel_mps2, "accel_mps2")
    if yg.shape != ya.shape:
        raise ValueError(f"gyro {yg.shape} and accel {ya.shape} arrays must have the same shape")
    a, g = cal.accel, cal.gyro
    ma_inv = np.linalg.inv(a.matrix())
    f = (ya - a.bias) @ ma_inv.T
    if np.any(a.k2) or np.any(a.cross_coupling):
        for _ in range(MAX_ITERATIONS):
            nxt = (ya - a.bias - a.k2 * f**2 - f * (f @ a.cross_coupling.T)) @ ma_inv.T
            done = np.all(np.abs(nxt - f) <= 1e-15 * np.maximum(np.abs(nxt), 1.0))
            f = nxt
            if done:
                break
    w = (yg - g.bias - f @ g.g_sensitivity.T) @ np.linalg.inv(g.matrix()).T
    return Corrected(w, f)


def correct_frame(cal: Calibration, imu: pd.DataFrame) -> pd.DataFrame:
    """A canonical IMU frame (``raw_schemas.tables.CANONICAL_IMU_SCHEMA``, SI) with its six channels calibrated;
    other columns (time, temperature, counter) are kept."""
    missing = [c for c in (*GYRO_COLUMNS, *ACCEL_COLUMNS) if c not in imu.columns]
    if missing:
        raise ValueError(f"IMU frame: expected canonical SI columns {list(GYRO_COLUMNS + ACCEL_COLUMNS)}, "
                         f"missing {missing}")
    out = imu.copy()
    c = correct(cal, imu[list(GYRO_COLUMNS)].to_numpy(float), imu[list(ACCEL_COLUMNS)].to_numpy(float))
    out[list(GYRO_COLUMNS)] = c.gyro_radps
    out[list(ACCEL_COLUMNS)] = c.accel_mps2
    return out


def perturbed(cal: Calibration, sensor: str, field: str, idx: tuple, delta: float) -> Calibration:
    """The calibration with one term moved by ``delta`` (for sensitivities)."""
    tri: Triad = getattr(cal, sensor)
    arr = np.array(getattr(tri, field), dtype=float)
    arr[idx] += delta
    return replace(cal, **{sensor: replace(tri, **{field: arr})})


@dataclass(frozen=True)
class Sensitivities:
    """d(corrected)/d(term) x stderr for every term with a standard error: ``gyro`` / ``accel`` (n_terms, n, 3)."""

    terms: tuple[tuple[str, str, str, tuple], ...]
    gyro: np.ndarray
    accel: np.ndarray

    def stderr(self) -> Corrected:
        """Root sum of squares over the terms (independent terms, first order)."""
        return Corrected(np.sqrt((self.gyro**2).sum(axis=0)), np.sqrt((self.accel**2).sum(axis=0)))


def sensitivities(cal: Calibration, gyro_radps, accel_mps2) -> Sensitivities:
    """GUM (JCGM 100:2008) eq. 10 terms c_k u_k: change of the corrected outputs for a one-standard-error change
    of each term (central difference at +/- 1 stderr; the model is linear or nearly so in every term)."""
    keys, sig = cal.stderr_vector()
    base_g, base_a = _as3(gyro_radps, "gyro_radps"), _as3(accel_mps2, "accel_mps2")
    dg = np.zeros((len(keys), *base_g.shape))
    da = np.zeros((len(keys), *base_a.shape))
    for k, ((sensor, field, _fam, idx), s) in enumerate(zip(keys, sig)):
        hi = correct(perturbed(cal, sensor, field, idx, s), base_g, base_a)
        lo = correct(perturbed(cal, sensor, field, idx, -s), base_g, base_a)
        dg[k] = 0.5 * (hi.gyro_radps - lo.gyro_radps)
        da[k] = 0.5 * (hi.accel_mps2 - lo.accel_mps2)
    return Sensitivities(tuple(keys), dg, da)


def drift_of(cal: Calibration) -> BiasDrift:
    """The calibration's bias-drift terms (``assets_lib.apply.drift.bias_drift``) from its noise rows."""
    src = next((r["run_id"] for r in cal.records if r.get("test_kind") == "static"), "")
    return bias_drift(cal.noise, src, cal.turn_on_repeatability)


def drift_stderr(cal: Calibration, gyro_radps, accel_mps2, span: ApplySpan | None = None) -> Corrected:
    """[GUM] eq. 10 term of the bias drift: the corrected outputs' change for a one-sigma drift of each bias axis
    (central difference, as ``sensitivities``), sigma from ``assets_lib.apply.drift`` over ``span``.

    ``span`` None: every row is taken as the mean of a whole run (T = L), the least drift any other run has:
    the Allan floor (2 ln2 / pi) B^2 of [IEEE952] C.3."""
    yg, ya = _as3(gyro_radps, "gyro_radps"), _as3(accel_mps2, "accel_mps2")
    n = len(yg)
    drift = drift_of(cal)
    vg, va = np.zeros_like(yg), np.zeros_like(ya)
    for sensor in ("gyro", "accel"):
        var = drift.variance(sensor, span, n)  # (n, 3)
        for i in range(3):
            sig = np.sqrt(var[:, i])
            if not np.any(sig > 0):
                continue
            d = float(np.max(sig))
            hi = correct(perturbed(cal, sensor, "bias", (i,), d), yg, ya)
            lo = correct(perturbed(cal, sensor, "bias", (i,), -d), yg, ya)
            scale = (sig / d)[:, None]
            vg += (0.5 * (hi.gyro_radps - lo.gyro_radps) * scale) ** 2
            va += (0.5 * (hi.accel_mps2 - lo.accel_mps2) * scale) ** 2
    return Corrected(np.sqrt(vg), np.sqrt(va))


def correction_stderr(cal: Calibration, gyro_radps, accel_mps2, span: ApplySpan | None = None) -> Corrected:
    """Standard uncertainty of the corrected outputs ([GUM] eq. 10, independent inputs): the terms' standard
    errors plus the bias drift between the calibration and the data over ``span`` (``drift_stderr``)."""
    c = sensitivities(cal, gyro_radps, accel_mps2).stderr()
    d = drift_stderr(cal, gyro_radps, accel_mps2, span)
    return Corrected(np.hypot(c.gyro_radps, d.gyro_radps), np.hypot(c.accel_mps2, d.accel_mps2))


__all__ = [
    "ACCEL_COLUMNS",
    "FAMILY_FIELDS",
    "GYRO_COLUMNS",
    "ApplySpan",
    "Corrected",
    "Sensitivities",
    "correct",
    "correct_frame",
    "correction_stderr",
    "drift_of",
    "drift_stderr",
    "forward",
    "perturbed",
    "sensitivities",
]
