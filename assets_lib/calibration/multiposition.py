"""General least-squares multi-position fits from a PLATEAU TABLE, for any position schedule.

Accelerometer ([SEED000] eq. 2, 21-22; [SEED003] eq. 10): per axis i, over the static plateaus,

    y_i = b_i + a_ii f_i + a_ij f_j + a_ik f_k + K2_i f_i^2 + Kc_ij f_i f_j + Kc_ik f_i f_k

with f = ``f_ref_{x,y,z}_mps2``, K_i = a_ii and E_ij = a_ij / a_ii (design.md model). The design matrix is
built from each plateau's reference specific force, so one function serves [SEED003]'s 24-position plan,
[SEED000]'s 8-position-per-axis plan, [SEED001]'s 12-position tumble (K0..K3 = b, K, K2, Kc), a 6-position
plan, or any other schedule. What the schedule cannot observe (e.g. Kc in a 6-position plan, K2 without a
horizontal position) is reported ``observable=False`` with a NaN value and the reason, by the prescribed-pivot
QR of :mod:`assets_lib.calibration.fit_core`.

Gyro biases from the static plateaus ([SEED000] eq. 17-20): z_i = y_i - [K_i (e_i + E_i)] . omega_ref, the
earth-rate projection removed with the rate fit's scale factor and misalignment (or nominal 1 and 0), then
z_i = b_i [+ G_i . f] by WLS; the rate fit's covariance is propagated into the biases; g-sensitivity G is
fitted when the schedule observes it (``g_sensitivity='auto'``).

With plateau times in the table, both fits model the bias-instability (1/f) noise shared between plateaus by
REML/GLS (``correlated_noise=True``, :func:`assets_lib.calibration.fit_core.flicker_gls`); ``drift_order`` adds an optional
polynomial bias drift over the run as nuisance columns.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
import pandas as pd

from assets_lib.calibration.fit_core import (
    DEFAULT_ALPHA,
    DEFAULT_REL_TOL,
    LinearFit,
    fit_linear,
    flicker_b,
    flicker_b_dof,
    flicker_law,
    flicker_prior_tau2,
    sem_flicker_tau2,
)
from assets_lib.calibration.fit_report import (
    coefficient_frame,
    coefficient_row,
    plot_multiposition_residuals_png,
    residual_frame,
)
from assets_lib.calibration.noise_prior import (
    DeviceNoisePrior,
    prior_flicker,
    with_source,
)
from assets_lib.calibration.rate_fit import GyroRateFit, select_rows
from assets_lib.calibration.triad import AXES, off_diagonal_matrix
from assets_lib.coefficient import Coefficient, ratio_with_stderr

METHOD_ACCEL = "wls_multiposition"
METHOD_GYRO = "wls_static_bias_earth_rate_removed"
DRIFT_ORDER = 0  # no drift columns by default: the 1/f GLS carries the slow bias wander
CORRELATED = True


def _times(p: pd.DataFrame):
    if "t_start_s" not in p or "t_end_s" not in p:
        return None
    a, b = p["t_start_s"].to_numpy(float), p["t_end_s"].to_numpy(float)
    return 0.5 * (a + b), b - a


def drift_columns(p: pd.DataFrame, order: int) -> tuple[list[np.ndarray], list[str], list[float]]:
    """Bias drift over the run as polynomial nuisance columns in plateau mid-time (a bias ramp; the slow
    part of bias instability). Centred and scaled to the run half-span so full excitation is order one."""
    if order <= 0 or "t_start_s" not in p or "t_end_s" not in p:
        return [], [], []
    t = 0.5 * (p["t_start_s"].to_numpy(float) + p["t_end_s"].to_numpy(float))
    half = max(0.5 * float(np.ptp(t)), 1e-9)
    u = (t - 0.5 * (t.max() + t.min())) / half
    cols = [u ** (k + 1) - (np.mean(u ** (k + 1)) if k % 2 else 0.0) for k in range(order)]
    names = ["bias_drift"] + [f"bias_drift_order{k + 1}" for k in range(1, order)]
    return cols, names, [half ** (k + 1) for k in range(order)]


def _n_samples(p: pd.DataFrame, used: np.ndarray) -> int:
    return int(p.loc[used, "n_samples"].sum()) if "n_samples" in p else 0


def _vs(fit: LinearFit, name: str, unit: str) -> Coefficient:
    """The fitted column ``name`` as a :class:`Coefficient` with the fit's 95 % coverage factor."""
    k = fit.names.index(name)
    return Coefficient.with_coverage(float(fit.value[k]), float(np.sqrt(fit.cov[k, k])), unit, bool(fit.observable[k]),
                                     fit.k95)


@dataclass(frozen=True, eq=False)
class AccelAxisFit:
    axis: str
    fit: LinearFit
    design: np.ndarray
    scale_factor: Coefficient  # unit "1"
    bias_mps2: Coefficient
    misalignment_rad: dict  # {'y': Coefficient} for E[i, j], rad
    k2: Coefficient  # 1/(m/s^2)
    cross_coupling: dict  # {'y': Coefficient} Kc[i, j] 1/(m/s^2)
    n_plateaus: int
    n_samples: int
    b_source: str = ""  # where the 1/f level B came from when not the run's plateaus (the device's static record)


@dataclass(frozen=True, eq=False)
class AccelMultipositionFit:
    device_id: str
    run_id: str
    axes: tuple[AccelAxisFit, ...]
    plateaus: pd.DataFrame

    def axis(self, a: str) -> AccelAxisFit:
        return self.axes[AXES.index(a)]

    @property
    def scale_factor(self) -> np.ndarray:
        return np.array([a.scale_factor.value for a in self.axes])

    @property
    def bias_mps2(self) -> np.ndarray:
        return np.array([a.bias_mps2.value for a in self.axes])

    @property
    def misalignment_rad(self) -> np.ndarray:
        return off_diagonal_matrix(self.axes, "misalignment_rad", AXES)

    @property
    def k2(self) -> np.ndarray:
        return np.array([a.k2.value for a in self.axes])

    @property
    def cross_coupling(self) -> np.ndarray:
        return off_diagonal_matrix(self.axes, "cross_coupling", AXES)

    def coefficient_table(self) -> pd.DataFrame:
        rows = []
        for ax in self.axes:
            f = ax.fit
            common = dict(device_id=self.device_id, run_id=self.run_id, sensor="accel", axis=ax.axis,
                          n_plateaus=ax.n_plateaus, n_samples=ax.n_samples, method=METHOD_ACCEL, dof=f.dof,
                          cov_policy=f.cov_policy)
            items = [("scale_factor", ax.scale_factor, "scale_factor"), ("bias", ax.bias_mps2, "bias")]
            items += [(f"misalignment_{ax.axis}{a}", v, f"misalignment_{ax.axis}{a}") for a, v in ax.misalignment_rad.items()]
            items += [("k2", ax.k2, "k2")]
            items += [(f"cross_coupling_{ax.axis}{a}", v, f"cross_coupling_{ax.axis}{a}") for a, v in ax.cross_coupling.items()]
            for name, c, col in items:
                note = f.unobservable_reason[f.names.index(col)] if col in f.names else "not in the fitted model"
                if not c.observable and not note and name.startswith("misalignment_"):
                    note = "needs the scale factor of this axis, which the schedule does not observe"
                if name == "bias":
                    note = with_source(note, ax.b_source)
                rows.append(coefficient_row(coefficient=name, estimate=c, note=note, **common))
        return coefficient_frame(rows)

    def residual_table(self) -> pd.DataFrame:
        p = self.plateaus
        parts = []
        for i, ax in enumerate(self.axes):
            parts.append(residual_frame(ax.fit, p, sensor="accel", axis=ax.axis, input_name=f"f_ref_{ax.axis}_mps2",
                                        input_value=p[f"f_ref_{ax.axis}_mps2"].to_numpy(float), input_unit="m/s^2",
                                        observed=p[f"accel_{ax.axis}_mps2_mean"].to_numpy(float), unit="m/s^2"))
        return pd.concat(parts, ignore_index=True)

    def plot_png(self) -> bytes:
        return plot_multiposition_residuals_png(self.residual_table(),
                                                title=f"Accelerometer multi-position residuals {self.device_id} {self.run_id}")


def fit_accel_multiposition(
    plateaus: pd.DataFrame,
    *,
    second_order: bool = True,
    cross_coupling: bool = True,
    kinds: tuple[str, ...] = ("static",),
    outlier_test: bool = True,
    alpha: float = DEFAULT_ALPHA,
    rel_tol: float = DEFAULT_REL_TOL,
    use_flagged: bool = False,
    drift_order: int = DRIFT_ORDER,
    correlated_noise: bool = CORRELATED,
    flicker_b_mps2: np.ndarray | None = None,
    noise_prior: DeviceNoisePrior | None = None,
) -> AccelMultipositionFit:
    """[SEED000] eq. 21-22 / [SEED003] eq. 10: X = (A^T W A)^-1 A^T W Z per accelerometer axis, any schedule.

    Only static plateaus by default (rate plateaus carry centripetal terms the reference does not model).
    K2 and Kc are optional columns: fitted where the schedule separates them, otherwise unobservable.
    ``noise_prior``: the device's 1/f level from its static records
    (:class:`~assets_lib.calibration.noise_prior.DeviceNoisePrior`); for an accelerometer channel it has, it replaces
    the run's B (two-sided: B with its interval's dof; a bound: B <= bound integrated) and the bias coefficient's note
    names the record. Not together with ``flicker_b_mps2`` (ValueError).
    """
    if noise_prior is not None and flicker_b_mps2 is not None:
        raise ValueError("give the 1/f level either as flicker_b_mps2 or as noise_prior, not both")
    p, pre = select_rows(plateaus, kinds, use_flagged)
    if p.empty:
        raise ValueError(f"no plateaus of kind {kinds}")
    b_cols = [f"accel_{a}_mps2_flicker_b" for a in AXES]
    use_b_dof = flicker_b_mps2 is None  # the run's own B (from the table): its degrees of freedom are known
    if flicker_b_mps2 is None and all(c in p for c in b_cols):
        # the run's pooled Allan model from segmentation sets the 1/f level between plateaus
        flicker_b_mps2 = p[b_cols].iloc[0].to_numpy(float)
    dev = str(p["device_id"].iloc[0]) if "device_id" in p else ""
    run = str(p["run_id"].iloc[0]) if "run_id" in p else ""
    F = p[[f"f_ref_{a}_mps2" for a in AXES]].to_numpy(float)
    g_fs = float(np.nanmax(np.linalg.norm(F, axis=1)))
    sig_ok = all(f"accel_{a}_mps2_sem" in p for a in AXES)
    axes = []
    for i, a in enumerate(AXES):
        others = [j for j in range(3) if j != i]
        cols = [np.ones(len(p)), F[:, i]] + [F[:, j] for j in others]
        names = ["bias", "scale_factor"] + [f"misalignment_{a}{AXES[j]}" for j in others]
        scales = [1.0, g_fs, g_fs, g_fs]
        optional = [False] * 4
        if second_order:
            cols.append(F[:, i] ** 2)
            names.append("k2")
            scales.append(g_fs**2)
            optional.append(True)
        if cross_coupling:
            for j in others:
                cols.append(F[:, i] * F[:, j])
                names.append(f"cross_coupling_{a}{AXES[j]}")
                scales.append(g_fs**2 / 2)
                optional.append(True)
        nuisance = [False] * len(cols)
        dc, dn, _ = drift_columns(p, drift_order)
        for c_, n_ in zip(dc, dn):
            cols.append(c_)
            names.append(n_)
            scales.append(1.0)
            optional.append(True)
            nuisance.append(True)
        A = np.column_stack(cols)
        y = p[f"accel_{a}_mps2_mean"].to_numpy(float)
        sig = p[f"accel_{a}_mps2_sem"].to_numpy(float) if sig_ok else None
        ch = f"accel_{a}_mps2"
        dp = prior_flicker(noise_prior, ch, p)
        if dp is None:  # the run's own B (or the given flicker_b_mps2), as before
            dp = (None if flicker_b_mps2 is None else flicker_prior_tau2(float(np.asarray(flicker_b_mps2)[i])),
                  _b_law(p, ch) if use_b_dof else None, "")
        f_tau2, f_dof, b_source = dp
        fit = fit_linear(A, y, names, sigma=sig, scales=np.array(scales), optional=np.array(optional), rel_tol=rel_tol,
                         pre_excluded=pre, outlier_test=outlier_test, alpha=alpha, nuisance=np.array(nuisance),
                         times=_times(p) if correlated_noise else None, flicker_tau2=f_tau2, flicker_tau2_dof=f_dof,
                         sem_flicker_tau2=sem_flicker_tau2(p, ch))
        ks = names.index("scale_factor")
        mis = {}
        for j in others:
            k = names.index(f"misalignment_{a}{AXES[j]}")
            if fit.observable[k] and fit.observable[ks]:
                v, s = ratio_with_stderr(fit.value[k], fit.value[ks], fit.cov[k, k], fit.cov[ks, ks], fit.cov[k, ks])
                mis[AXES[j]] = Coefficient.with_coverage(v, s, "rad", True, fit.k95)
            else:
                mis[AXES[j]] = Coefficient.with_coverage(np.nan, np.nan, "rad", False, fit.k95)
        per_g2 = "1/(m/s^2)"
        k2 = _vs(fit, "k2", per_g2) if second_order else Coefficient.with_coverage(np.nan, np.nan, per_g2, False, fit.k95)
        kc = {AXES[j]: (_vs(fit, f"cross_coupling_{a}{AXES[j]}", per_g2) if cross_coupling
                        else Coefficient.with_coverage(np.nan, np.nan, per_g2, False, fit.k95)) for j in others}
        axes.append(AccelAxisFit(a, fit, A, _vs(fit, "scale_factor", "1"), _vs(fit, "bias", "m/s^2"), mis, k2, kc,
                                 fit.n_used, _n_samples(p, fit.used), b_source))
    return AccelMultipositionFit(dev, run, tuple(axes), p)


@dataclass(frozen=True, eq=False)
class GyroStaticAxisFit:
    axis: str
    fit: LinearFit
    bias_radps: Coefficient
    g_sensitivity: dict  # {'x': Coefficient} rad/s per m/s^2
    earth_removed_with: str
    n_plateaus: int
    n_samples: int
    b_source: str = ""  # where the 1/f level B came from when not the run's plateaus (the device's static record)


@dataclass(frozen=True, eq=False)
class GyroStaticFit:
    device_id: str
    run_id: str
    axes: tuple[GyroStaticAxisFit, ...]
    plateaus: pd.DataFrame

    @property
    def bias_radps(self) -> np.ndarray:
        return np.array([a.bias_radps.value for a in self.axes])

    def coefficient_table(self) -> pd.DataFrame:
        rows = []
        for ax in self.axes:
            f = ax.fit
            common = dict(device_id=self.device_id, run_id=self.run_id, sensor="gyro", axis=ax.axis,
                          n_plateaus=ax.n_plateaus, n_samples=ax.n_samples, method=METHOD_GYRO, dof=f.dof,
                          cov_policy=f.cov_policy)
            rows.append(coefficient_row(coefficient="bias", estimate=ax.bias_radps,
                                        note=with_source(f"earth rate removed with {ax.earth_removed_with}",
                                                         ax.b_source), **common))
            for a, c in ax.g_sensitivity.items():
                k = f.names.index(f"g_sensitivity_{a}")
                rows.append(coefficient_row(coefficient=f"g_sensitivity_{a}", estimate=c,
                                            note=f.unobservable_reason[k], **common))
        return coefficient_frame(rows)

    def residual_table(self) -> pd.DataFrame:
        p = self.plateaus
        parts = []
        for ax in self.axes:
            parts.append(residual_frame(ax.fit, p, sensor="gyro", axis=ax.axis, input_name=f"omega_ref_{ax.axis}_radps",
                                        input_value=p[f"omega_ref_{ax.axis}_radps"].to_numpy(float), input_unit="rad/s",
                                        observed=ax.fit.fitted + ax.fit.residual, unit="rad/s"))
        return pd.concat(parts, ignore_index=True)


def fit_gyro_static(
    plateaus: pd.DataFrame,
    *,
    rate_fit: GyroRateFit | None = None,
    scale_factor: np.ndarray | None = None,
    misalignment_rad: np.ndarray | None = None,
    g_sensitivity: bool | str = "auto",
    outlier_test: bool = True,
    alpha: float = DEFAULT_ALPHA,
    rel_tol: float = DEFAULT_REL_TOL,
    use_flagged: bool = False,
    correlated_noise: bool = True,
    noise_prior: DeviceNoisePrior | None = None,
) -> GyroStaticFit:
    """[SEED000] eq. 17-20: gyro biases from static positions with the earth-rate projection removed.

    The reference ``omega_ref_*`` (= ``omega_earth_*`` for static plateaus) is mapped through the rate fit's
    [K_i (e_i + E_i)] rows (their covariance propagated), or through the given ``scale_factor`` /
    ``misalignment_rad`` (no uncertainty), or nominal (K = 1, E = 0: the canonical outputs' nominal scale).
    ``noise_prior``: the device's 1/f level from its static records
    (:class:`~assets_lib.calibration.noise_prior.DeviceNoisePrior`) replaces the run's B for the gyro channels it has
    (two-sided: B with its interval's dof; a bound: B <= bound integrated); the bias note names the record.
    """
    p, pre = select_rows(plateaus, ("static",), use_flagged)
    if p.empty:
        raise ValueError("no static plateaus")
    dev = str(p["device_id"].iloc[0]) if "device_id" in p else ""
    run = str(p["run_id"].iloc[0]) if "run_id" in p else ""
    W = p[[f"omega_ref_{a}_radps" for a in AXES]].to_numpy(float)
    F = p[[f"f_ref_{a}_mps2" for a in AXES]].to_numpy(float)
    g_fs = float(np.nanmax(np.linalg.norm(F, axis=1)))
    sig_ok = all(f"gyro_{a}_radps_sem" in p for a in AXES)
    out = []
    for i, a in enumerate(AXES):
        if rate_fit is not None:
            m, Cm = rate_fit.axis(a).linear_row()
            src = f"the rate fit of run {rate_fit.run_id} (covariance propagated)"
        else:
            K = np.ones(3) if scale_factor is None else np.asarray(scale_factor, float)
            E = np.zeros((3, 3)) if misalignment_rad is None else np.asarray(misalignment_rad, float)
            m = K[i] * (np.eye(3)[i] + E[i])
            Cm = np.zeros((3, 3))
            src = "the given scale factor and misalignment" if scale_factor is not None else "nominal K = 1, E = 0"
        z = p[f"gyro_{a}_radps_mean"].to_numpy(float) - W @ m
        sig = p[f"gyro_{a}_radps_sem"].to_numpy(float) if sig_ok else None
        cols, names, scales, optional = [np.ones(len(p))], ["bias"], [1.0], [False]
        use_g = g_sensitivity is True or (g_sensitivity == "auto" and np.all(np.isfinite(F)))
        if use_g:
            for j in range(3):
                cols.append(F[:, j])
                names.append(f"g_sensitivity_{AXES[j]}")
                scales.append(g_fs)
                optional.append(True)
        A = np.column_stack(cols)
        ch = f"gyro_{a}_radps"
        dp = prior_flicker(noise_prior, ch, p)
        f_tau2, f_dof, b_source = dp or (flicker_prior_tau2(flicker_b(p, ch)), _b_law(p, ch), "")
        fit = fit_linear(A, z, names, sigma=sig, scales=np.array(scales), optional=np.array(optional), rel_tol=rel_tol,
                         pre_excluded=pre, outlier_test=outlier_test, alpha=alpha,
                         times=_times(p) if correlated_noise else None, flicker_tau2=f_tau2, flicker_tau2_dof=f_dof,
                         sem_flicker_tau2=sem_flicker_tau2(p, ch))
        if np.any(Cm):
            # x = P z with z = y - W m: Cov += P W Cm W^T P^T (rate-fit uncertainty of the earth-rate projection)
            obs = np.flatnonzero(fit.observable)
            u = np.flatnonzero(fit.used)
            w = 1.0 / sig[u] if sig is not None else np.ones(len(u))
            Aw = A[np.ix_(u, obs)] * w[:, None]
            P = np.linalg.pinv(Aw) * w[None, :]
            PW = P @ W[u]
            cov = fit.cov.copy()
            cov[np.ix_(obs, obs)] += PW @ Cm @ PW.T
            fit = replace(fit, cov=cov)
        gs = {AXES[j]: _vs(fit, f"g_sensitivity_{AXES[j]}", "rad/s/(m/s^2)") for j in range(3)} if use_g else {}
        out.append(GyroStaticAxisFit(a, fit, _vs(fit, "bias", "rad/s"), gs, src, fit.n_used, _n_samples(p, fit.used),
                                     b_source))
    return GyroStaticFit(dev, run, tuple(out), p)


def _b_law(p, channel: str):
    """What the fits know of the run's 1/f level beyond B itself: its degrees of freedom when B was detected
    (:func:`flicker_b_dof`), the censored sampling law of the Allan estimate when it was not (:func:`flicker_law`)."""
    b = flicker_b(p, channel)
    if b is not None and b == 0:
        return flicker_law(p, channel)
    return flicker_b_dof(p, channel)
