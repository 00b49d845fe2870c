"""Gyro rate fit from a PLATEAU TABLE: scale factor, bias, misalignment, nonlinearity, asymmetry.

Model (docs/design.md, [SEED000] eq. 1): y_i = K_i (omega_i + sum_j E_ij omega_j) + b_i [+ G_i . f] + n, per
gyro axis i, with ``omega`` the reference input ``omega_ref_{x,y,z}_radps`` (table rate plus the modelled earth
rate). It is linear in a_ii = K_i, a_ij = K_i E_ij and b_i, and is fitted per axis by weighted least squares
over the plateaus ([SEED003] eq. 3, x = (A^T A)^-1 A^T b, weights 1/sem^2); E_ij = a_ij / a_ii by the delta
method. Misalignment is observable only when the plateaus excite the other axes (rate tests about all three
body axes, [SEED000] eq. 13); otherwise it is reported unobservable. See :mod:`assets_lib.calibration.fit_core` for the
identifiability rule, the exclusion tests and the covariance policy.

Scale-factor asymmetry ([IEEE952]: K+ vs K-) is part of the model: a hinge column (dK/2)|omega_i| next to
K_i omega_i, so K_i is the mean of K+ and K-, b_i the output at zero rate, and an asymmetric sensor's |omega|
signature no longer goes to the bias and the residual scatter (the coverage benchmark: consumer K z sd 1.9 with
asymmetry injected and a straight-line model). The column is optional: a schedule that cannot separate it from
the bias reports the asymmetry unobservable and fits the straight line.

Also: scale-factor nonlinearity ([SEED003]: max deviation from the fitted straight line over the full-scale
output; the same fit without the hinge), K+, K- and asymmetry with uncertainties, automatic exclusion of
saturated and wild plateaus with reasons, and [SEED000]'s +/- full-revolution difference method (eq. 9-13) as a
cross-check.

g-sensitivity enters as centred nuisance columns: the bias shifts between the rate tests' orientations (G f)
are absorbed even when G is not separable from the bias, and the bias is then reported at the schedule's mean
specific force (b + G f_bar, stated in the coefficient's note). With plateau times, the bias-instability
noise shared between plateaus is modelled by REML/GLS (``correlated_noise``). The run's Allan level B enters
with its degrees of freedom (``flicker_b_dof``), integrated over as the static gyro fit does, not as exact.

Known limit (issue 15, navigation grade): the rate-fit bias over-covers (z sd ~0.76-0.82). The flicker level
of a navigation gyro lies 12-24x below the plateau sems: segmentation's pooled Allan fit puts B at 0 in about
half the runs and at 2-14x the truth in the others (40 simulated quick_rate runs), and REML then reads the
plateaus' contrasts as a level 18x the truth, which the bias carries as the run mean's wander 2 ln2 tau^2.
Tried on the same 40 runs per grade (bias z sd navigation / tactical / consumer; now 0.78 / 1.07 / 1.06):
the level fixed at the truth 0.96 / - / 1.03 (reference); the Allan estimate with a normal likelihood
(censored at 0 when undetected) and a flat prior, posterior mean 0.42 / 0.62 / 1.05; the joint maximum of
that likelihood and REML 1.00 / 1.22 / 1.15; a log-uniform prior 0.74-0.84 / - / 1.17-1.21. The plateaus of
these plans do not identify a level so far below their white noise; no tried choice holds for every grade.

Known limit (issue 15, consumer grade): the rate-fit bias is too narrow (z sd 1.2, coverage 0.92 on 300 cached
runs, seed 9151). The excess sits entirely in the axes whose run-level Allan fit did not identify B: undetected
(9 of 300 axis fits) or with ``flicker_b_dof`` < 1 (37): z sd 1.6-2.0, coverage 0.74-0.80; on the other 254
z sd 1.00 (quick_rate) / 1.07 (seed003_rate_sequence), coverage 0.95 / 0.94. The consumer white-noise / 1/f
Allan crossover lies near 7 s, about the plateau length of these plans (6-16 s), so the plateaus' Allan curve
often cannot separate the floor from the white slope; the fit then rests on the plateaus' REML with a flat prior
in ln tau^2, which leans to small levels. The sem bound (sem^2 >= 2 ln2 tau^2, used for the undetected case
with < 3 dof) would suit consumer (bound ~1.4x the true tau^2) but over-covers navigation, whose B is weak
too (bias z sd 0.37 with the bound in every run, see fit_core); a rule keyed on the grade is not a model. A prior
uniform in the level's standard deviation instead of flat in ln tau^2 in the marginalisation ([GELMAN2006]: the
log-uniform prior on a variance component puts its mass near 0) moved the bias z sd only 1.18 -> 1.12 consumer,
0.82 -> 0.80 navigation, 1.05 -> 1.02 tactical on the same 300 runs (not adopted: it is fit_core's, shared by
every fit). Open.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pandas as pd

from assets_lib.calibration.fit_core import (
    DEFAULT_ALPHA,
    DEFAULT_REL_TOL,
    LinearFit,
    fit_linear,
    flicker_b,
    flicker_b_dof,
    flicker_covariance,
    flicker_gls,
    flicker_prior_tau2,
    sem_flicker_tau2,
)
from assets_lib.calibration.fit_report import (
    coefficient_frame,
    coefficient_row,
    plot_rate_residuals_png,
    residual_frame,
)
from assets_lib.calibration.noise_prior import (
    DeviceNoisePrior,
    prior_flicker,
    with_source,
)
from assets_lib.calibration.saturation import detect_saturation
from assets_lib.calibration.triad import AXES, off_diagonal_matrix
from assets_lib.coefficient import Z95, Coefficient, ratio_with_stderr
from assets_lib.sim.earth import EARTH_RATE_RADPS
from raw_schemas.units import RADPS_TO_DEGPS

METHOD = "wls_rate_fit"
METHOD_DIFF = "seed000_full_revolution_difference"
_NC_RNG_SEED = 952  # fixed seed: the nonlinearity noise floor is a deterministic function of the design


def _omega(p: pd.DataFrame) -> np.ndarray:
    return p[[f"omega_ref_{a}_radps" for a in AXES]].to_numpy(float)


def _force(p: pd.DataFrame) -> np.ndarray:
    cols = [f"f_ref_{a}_mps2" for a in AXES]
    if all(c in p for c in cols):
        return p[cols].to_numpy(float)
    return np.full((len(p), 3), np.nan)


def _sem(p: pd.DataFrame, col: str) -> np.ndarray | None:
    return p[col].to_numpy(float) if col in p else None


def _n_samples(p: pd.DataFrame, mask: np.ndarray) -> int:
    return int(p.loc[mask, "n_samples"].sum()) if "n_samples" in p else 0


def select_rows(plateaus: pd.DataFrame, kinds=("rate", "static"), use_flagged: bool = False):
    """Rows of the given kinds, and {row: reason} for rows the segmentation flagged (excluded unless asked)."""
    p = plateaus[plateaus["kind"].isin(kinds)].reset_index(drop=True)
    pre: dict[int, str] = {}
    if not use_flagged and "flagged" in p:
        fl = p["flagged"].fillna(False).to_numpy(bool)
        why = p["flag_reason"].fillna("").astype(str).to_numpy() if "flag_reason" in p else np.full(len(p), "")
        for i in np.flatnonzero(fl):
            pre[int(i)] = f"flagged by segmentation: {why[i] or 'no reason given'}"
    return p, pre


def on_axis_rows(omega: np.ndarray, i: int, kind: np.ndarray | None = None) -> np.ndarray:
    """Plateaus of axis i's rate sweep: rotation mostly about body axis i, or no table rotation at all."""
    norm = np.linalg.norm(omega, axis=1)
    about_i = np.abs(omega[:, i]) >= 0.9 * norm
    still = norm <= 3.0 * EARTH_RATE_RADPS
    return (about_i & ~still) | still


def compression_note(x: np.ndarray, sweep: np.ndarray, saturated: dict[int, str], sign_gain: float = 1.0):
    """Outlier-reason context: an excluded plateau at the end of the sweep whose output falls short of the line."""

    def note(row: int, resid: float, used: np.ndarray) -> str:
        if not sweep[row] or x[row] == 0:
            return ""
        same = sweep & used & (np.sign(x) == np.sign(x[row]))
        at_end = not np.any(np.abs(x[same]) > abs(x[row]))
        compressive = resid * np.sign(sign_gain * x[row]) < 0
        if not (at_end and compressive):
            return ""
        sat_beyond = [k for k in saturated if np.sign(x[k]) == np.sign(x[row]) and abs(x[k]) > abs(x[row])]
        return "at the end of the input range and compressive (output short of the line)" + (
            ": next to saturated plateau(s), likely onset of saturation" if sat_beyond else ": possible saturation onset"
        )

    return note


def sweep_screen_columns(x: np.ndarray, rows: np.ndarray, min_magnitudes: int = 5) -> np.ndarray | None:
    """Nuisance regressors |w|, w^2, w^3 on the sweep rows, for the outlier screen only (the signatures of
    asymmetry and nonlinearity); None when the sweep has fewer than ``min_magnitudes`` distinct |rates|."""
    mags = np.unique(np.round(np.abs(x[rows]), 12))
    if np.sum(mags > 0) < min_magnitudes:
        return None
    xr = np.where(rows, x, 0.0)
    return np.column_stack([np.abs(xr), xr**2, xr**3])


@dataclass(frozen=True, eq=False)
class SweepStats:
    """[SEED003] eq. 4-8: nonlinearity and asymmetry of one axis' rate sweep (ratios; ppm at the report edge)."""

    nonlinearity: Coefficient  # max |residual| / full-scale output (unit "1"); unobservable below two plateaus
    nonlinearity_floor: float  # 95 % quantile of the statistic under pure noise (detection limit)
    nonlinearity_at_input: float  # input of the worst plateau
    full_scale_output: float
    n_sweep: int
    k_pos: Coefficient  # scale factor on positive inputs (hinge fit)
    k_neg: Coefficient
    asymmetry: Coefficient  # (K+ - K-) / mean(K+, K-)
    asymmetry_fit: LinearFit | None


def sweep_nonlinearity(fit: LinearFit, A: np.ndarray, x: np.ndarray, sweep: np.ndarray, gain: float, times=None,
                       flicker_tau2: float | None = None, flicker_tau2_dof: float | None = None):
    """[SEED003] eq. 4-6: K_n = max_j |F_j - (K w_j + F0)| / F_m over the sweep, F_m = |K| max|w| (full scale).

    Standard error: the standard deviation of the worst residual; noise floor: the 95 % quantile of the same
    statistic when the only deviation is the measurement noise (Monte Carlo, fixed seed). Both under the fit's
    own noise model, through the residual projection of its (generalized) least squares: plateau sems plus the
    1/f component shared between plateaus (``times``; tau^2 by REML with |w|, w^2, w^3 in the model,
    :func:`fit_core.flicker_covariance`),
    or, without that model, the sems times the fit's variance factor (the between-plateau scatter). With white
    sems alone the 95 % floor was exceeded by 13 % of linear sensors in the full-chain Monte Carlo.

    ``flicker_tau2``/``flicker_tau2_dof``: the run's Allan 1/f level and its degrees of freedom, as the fit had
    them. The level is then not the plateaus' REML alone but integrated over with that prior
    (:func:`fit_core.flicker_gls`, posterior mean, [GELMAN2013] sec. 3.2): a REML over 9-23 plateaus with five
    columns often puts tau^2 near 0 and the worst residual's sd then lacks the 1/f wander between plateaus
    (consumer means-fit nonlinearity with injected nonlinearity, 60 runs: z sd 1.37 / 1.20 on quick_rate /
    seed003_rate_sequence with the REML level, 0.98 / 1.10 with the true level). Without them: REML as before.
    """
    m = sweep & fit.used
    idx = np.flatnonzero(m)
    nan = (np.nan, np.nan, np.nan, np.nan, np.nan, 0)
    if len(idx) < 2 or not np.isfinite(gain):
        return nan
    fs = abs(gain) * np.max(np.abs(x[idx]))
    if fs <= 0:
        return nan
    r = fit.residual[idx]
    j = int(np.argmax(np.abs(r)))
    used = np.flatnonzero(fit.used)
    sig = fit.sigma[used] if fit.sigma is not None else np.ones(len(used))
    correlated = times is not None and fit.flicker_tau2 > 0
    tau2 = 0.0
    if correlated:
        # the 1/f level with the smooth signatures (|w|, w^2, w^3) in the model: a genuine nonlinearity must not
        # pass for correlated noise and so raise its own detection floor
        t_mid, t_len = (np.asarray(v, float)[used] for v in times)
        X = A[np.ix_(used, np.flatnonzero(fit.observable))]
        scr = sweep_screen_columns(x, sweep)
        Xa = X if scr is None else np.column_stack([X, scr[used]])
        if np.linalg.matrix_rank(Xa) == Xa.shape[1] and len(used) > Xa.shape[1] + 2:
            given = flicker_tau2 is not None and flicker_tau2 > 0  # not FLICKER_UNDETECTED: then REML as before
            tau2 = flicker_gls(Xa, (fit.fitted + fit.residual)[used], sig, t_mid, t_len,
                               tau2=flicker_tau2 if given else None, prior_dof=flicker_tau2_dof if given else None,
                               sem_tau2=fit.sem_flicker_tau2)[0]
        else:
            tau2 = fit.flicker_tau2
    # between-plateau noise: the 1/f model when the fit has one, else the scatter's variance factor
    var_unit = 1.0 if correlated else (fit.scale if fit.cov_policy in ("residual", "pooled") else 1.0)
    if not np.isfinite(var_unit):
        return (float(np.abs(r[j]) / fs), np.nan, np.nan, float(x[idx[j]]), fs, len(idx))
    S = flicker_covariance(sig, t_mid, t_len, tau2, fit.sem_flicker_tau2) if tau2 > 0 else np.diag(sig**2)
    L = np.linalg.cholesky(S)
    Q, _ = np.linalg.qr(np.linalg.solve(L, A[np.ix_(used, np.flatnonzero(fit.observable))]))
    # residual of the GLS fit: r = L (I - Q Q^T) L^-1 e, e ~ N(0, var_unit S)
    Lr = L - (L @ Q) @ Q.T
    pos = np.searchsorted(used, idx)
    sd = np.sqrt(var_unit * np.sum(Lr[pos] ** 2, axis=1))
    rng = np.random.default_rng(_NC_RNG_SEED)
    e = (Lr[pos] @ rng.standard_normal((len(used), 2000))) * np.sqrt(var_unit)
    floor = float(np.quantile(np.max(np.abs(e), axis=0), 0.95) / fs)
    return (float(abs(r[j]) / fs), float(sd[j] / fs), floor, float(x[idx[j]]), float(fs), len(idx))


def sweep_asymmetry(A, names, y, sigma, x_main, main_col: int, pre: dict[int, str], scales, optional, rel_tol,
                    nuisance=None, times=None, flicker_tau2=None, flicker_tau2_dof=None, sem_flicker_tau2=None):
    """Asymmetry by a hinge term: y = ... + Kbar w + (dK/2)|w| (shared bias); K+- = Kbar +- dK/2.

    One fit with a common bias rather than two separate line fits: the bias is anchored by both signs and the
    zero-rate plateaus ([IEEE952]: asymmetry = difference of the positive- and negative-input scale factors
    relative to their mean). Note: an even nonlinearity (w^2) aliases into |w|. With plateau ``times`` the fit
    has the main fit's correlated-noise model (``flicker_tau2``): without it K+, K- and the asymmetry lost the 1/f
    noise shared between plateaus (consumer asymmetry coverage 0.88, z sd 1.48 in the full-chain Monte Carlo);
    ``flicker_tau2_dof``: that level's degrees of freedom or sampling law, integrated over as the main fit does
    (taken as exact, a B read at 2-20x the truth with < 1 dof widened the navigation means-fit asymmetry: z sd 0.91);
    ``sem_flicker_tau2``: the 1/f level the sems contain (:func:`~assets_lib.calibration.fit_core.fit_linear`).
    """
    Ah = np.column_stack([A[:, : main_col + 1], np.abs(x_main), A[:, main_col + 1 :]])
    nh = tuple(names[: main_col + 1]) + ("sf_asymmetry_term",) + tuple(names[main_col + 1 :])
    sc = np.r_[scales[: main_col + 1], scales[main_col], scales[main_col + 1 :]]
    op = np.r_[optional[: main_col + 1], False, optional[main_col + 1 :]]
    nu = None if nuisance is None else np.r_[nuisance[: main_col + 1], False, nuisance[main_col + 1 :]]
    f = fit_linear(Ah, y, nh, sigma=sigma, scales=sc, optional=op, rel_tol=rel_tol, pre_excluded=pre, outlier_test=False,
                   nuisance=nu, times=times, flicker_tau2=flicker_tau2, flicker_tau2_dof=flicker_tau2_dof,
                   sem_flicker_tau2=sem_flicker_tau2)
    return hinge_coefficients(f, main_col, main_col + 1)


def hinge_coefficients(f: LinearFit, k: int, d: int):
    """K+, sK+, K-, sK-, asymmetry, s_asymmetry of a fit with the mean scale factor in column ``k`` and the hinge
    term dK/2 (of |w|) in column ``d`` ([IEEE952]: K+- = Kbar +- dK/2, asymmetry = dK / Kbar); NaN when either
    is unobservable. Returns the fit as the 7th element."""
    if not (f.observable[k] and f.observable[d]):
        return (np.nan,) * 6 + (f,)
    a, hd = f.value[k], f.value[d]
    C = f.cov
    kp, kn = a + hd, a - hd
    sp = np.sqrt(C[k, k] + C[d, d] + 2 * C[k, d])
    sn = np.sqrt(C[k, k] + C[d, d] - 2 * C[k, d])
    asym = 2 * hd / a
    g = np.array([-2 * hd / a**2, 2 / a])
    Cs = C[np.ix_([k, d], [k, d])]
    sa = float(np.sqrt(g @ Cs @ g))
    return float(kp), float(sp), float(kn), float(sn), float(asym), sa, f


@dataclass(frozen=True, eq=False)
class GyroAxisRateFit:
    """One gyro axis: the linear fit and the derived coefficients (SI, ratios)."""

    axis: str
    fit: LinearFit
    design: np.ndarray
    scale_factor: Coefficient  # unit "1"
    bias_radps: Coefficient
    misalignment_rad: dict  # {'y': Coefficient} for E[i, j], rad
    g_sensitivity: dict  # {'x': Coefficient} rad/s per m/s^2
    sweep: SweepStats
    saturated: dict  # {row: reason}
    n_plateaus: int
    n_samples: int
    bias_reference_force_mps2: np.ndarray | None = None  # set when G is not separable: bias = b + G f_bar
    b_source: str = ""  # where the 1/f level B came from when not the run's plateaus (the device's static record)

    def linear_row(self) -> tuple[np.ndarray, np.ndarray]:
        """[a_ix, a_iy, a_iz] = K_i (e_i + E_i) and its covariance; unobservable entries at nominal with 0 var."""
        i = AXES.index(self.axis)
        names = self.fit.names
        v = np.zeros(3)
        v[i] = 1.0
        C = np.zeros((3, 3))
        cols = []
        for j, a in enumerate(AXES):
            nm = "scale_factor" if j == i else f"misalignment_{self.axis}{a}"
            k = names.index(nm)
            cols.append(k if self.fit.observable[k] else None)
            if self.fit.observable[k]:
                v[j] = self.fit.value[k]
        for j, kj in enumerate(cols):
            for m, km in enumerate(cols):
                if kj is not None and km is not None:
                    C[j, m] = self.fit.cov[kj, km]
        return v, C


@dataclass(frozen=True, eq=False)
class DifferenceCheck:
    """[SEED000] eq. 9-13: M = diag(K)(I + E) from +/- plateau pairs at equal |rate| (bias and vertical earth
    rate cancel in the difference; horizontal earth rate averages out over whole revolutions)."""

    fits: tuple  # per output axis LinearFit of dy_i = sum_j M_ij dw_j
    pairs: pd.DataFrame
    scale_factor: np.ndarray
    scale_factor_stderr: np.ndarray
    misalignment: np.ndarray  # E (3, 3), NaN where not observable
    misalignment_stderr: np.ndarray


@dataclass(frozen=True, eq=False)
class GyroRateFit:
    """Gyro rate-fit result for one device and run (three axes), with tidy table and plot helpers."""

    device_id: str
    run_id: str
    axes: tuple[GyroAxisRateFit, ...]
    plateaus: pd.DataFrame
    difference: DifferenceCheck | None

    def axis(self, a: str) -> GyroAxisRateFit:
        return self.axes[AXES.index(a)]

    @property
    def scale_factor(self) -> np.ndarray:
        return np.array([ax.scale_factor.value for ax in self.axes])

    @property
    def bias_radps(self) -> np.ndarray:
        return np.array([ax.bias_radps.value for ax in self.axes])

    @property
    def misalignment_rad(self) -> np.ndarray:
        return off_diagonal_matrix(self.axes, "misalignment_rad", AXES)

    def coefficient_table(self) -> pd.DataFrame:
        rows = []
        for ax in self.axes:
            f = ax.fit
            common = dict(device_id=self.device_id, run_id=self.run_id, sensor="gyro", axis=ax.axis,
                          n_plateaus=ax.n_plateaus, n_samples=ax.n_samples, method=METHOD, dof=f.dof,
                          cov_policy=f.cov_policy)
            k = f.names.index("scale_factor")
            rows.append(coefficient_row(coefficient="scale_factor", estimate=ax.scale_factor,
                                        note=f.unobservable_reason[k], **common))
            k = f.names.index("bias")
            bnote = f.unobservable_reason[k]
            if ax.bias_reference_force_mps2 is not None:
                fb = ", ".join(f"{v:.3f}" for v in ax.bias_reference_force_mps2)
                bnote = (f"bias at the schedule's mean specific force f_bar = [{fb}] m/s^2: b + G f_bar (g-sensitivity "
                         "not separable from the bias in this schedule; see the static multi-position fit)")
            rows.append(coefficient_row(coefficient="bias", estimate=ax.bias_radps, note=with_source(bnote, ax.b_source),
                                        **common))
            for a, c in ax.misalignment_rad.items():
                k = f.names.index(f"misalignment_{ax.axis}{a}")
                note = f.unobservable_reason[k] or ("" if c.observable else "needs the scale factor of this axis, "
                                                                            "which the schedule does not observe")
                rows.append(coefficient_row(coefficient=f"misalignment_{ax.axis}{a}", estimate=c, note=note, **common))
            for a, c in ax.g_sensitivity.items():
                k = f.names.index(f"g_sensitivity_{a}")
                rows.append(coefficient_row(coefficient=f"g_sensitivity_{a}", estimate=c,
                                            note=f.unobservable_reason[k], **common))
            sw = ax.sweep
            ok = sw.nonlinearity.observable
            rows.append(coefficient_row(
                coefficient="sf_nonlinearity", estimate=sw.nonlinearity,
                note=(f"max |residual| / full-scale output {sw.full_scale_output:.6g} rad/s over {sw.n_sweep} plateaus, "
                      f"worst at {sw.nonlinearity_at_input * RADPS_TO_DEGPS:+.6g} deg/s; noise floor (95 %) "
                      f"{sw.nonlinearity_floor * 1e6:.3g} ppm") if ok else "fewer than two sweep plateaus",
                **common))
            ok = sw.asymmetry.observable
            for name, c in (("scale_factor_pos", sw.k_pos), ("scale_factor_neg", sw.k_neg),
                            ("sf_asymmetry", sw.asymmetry)):
                rows.append(coefficient_row(coefficient=name, estimate=c,
                                            note="" if ok else "needs plateaus of both signs on this axis", **common))
        return coefficient_frame(rows)

    def residual_table(self) -> pd.DataFrame:
        om = _omega(self.plateaus)
        parts = []
        for i, ax in enumerate(self.axes):
            col = f"gyro_{ax.axis}_radps_mean"
            parts.append(residual_frame(ax.fit, self.plateaus, sensor="gyro", axis=ax.axis,
                                        input_name=f"omega_ref_{ax.axis}_radps", input_value=om[:, i],
                                        input_unit="rad/s", observed=self.plateaus[col].to_numpy(float), unit="rad/s"))
        return pd.concat(parts, ignore_index=True)

    def exclusions(self) -> pd.DataFrame:
        r = self.residual_table()
        return r[r["excluded"]][["device_id", "run_id", "step_index", "sensor", "axis", "input_value", "reason"]]

    def cross_check_table(self) -> pd.DataFrame:
        """Main fit vs [SEED000] difference method; z uses sqrt(se_diff^2 - se_fit^2) (the difference estimator
        is a less efficient linear estimator on a subset of the same data, [HAUSMAN1978])."""
        if self.difference is None:
            return pd.DataFrame()
        d = self.difference
        rows = []
        for i, ax in enumerate(self.axes):
            sf = ax.scale_factor
            items = [("scale_factor", sf.value, sf.stderr, d.scale_factor[i], d.scale_factor_stderr[i])]
            for j, a in enumerate(AXES):
                if j != i:
                    c = ax.misalignment_rad[a]
                    items.append((f"misalignment_{ax.axis}{a}", c.value, c.stderr, d.misalignment[i, j],
                                  d.misalignment_stderr[i, j]))
            for name, vf, sf, vd, sd in items:
                dv = sd**2 - sf**2
                rows.append(dict(axis=ax.axis, coefficient=name, value_fit=vf, stderr_fit=sf, value_difference=vd,
                                 stderr_difference=sd, delta=vd - vf,
                                 z=(vd - vf) / np.sqrt(dv) if dv > 0.01 * sd**2 else np.nan))
        return pd.DataFrame(rows)

    def plot_png(self) -> bytes:
        return plot_rate_residuals_png(self.residual_table(), title=f"Gyro rate fit residuals {self.device_id} {self.run_id}")


def _times(p: pd.DataFrame):
    """(mid-time, length) of every plateau for the correlated-noise GLS, or None without plateau times."""
    if "t_start_s" not in p or "t_end_s" not in p:
        return None
    a, b = p["t_start_s"].to_numpy(float), p["t_end_s"].to_numpy(float)
    return 0.5 * (a + b), b - a


def _fit_axis(p, pre, i, *, sigma_ok, g_sens, outlier_test, saturation_test, alpha, rel_tol,
              correlated_noise=True, noise_prior=None) -> GyroAxisRateFit:
    a = AXES[i]
    om = _omega(p)
    fr = _force(p)
    y = p[f"gyro_{a}_radps_mean"].to_numpy(float)
    sig = _sem(p, f"gyro_{a}_radps_sem") if sigma_ok else None
    others = [j for j in range(3) if j != i]
    cols = [np.ones(len(p)), om[:, i]] + [om[:, j] for j in others]
    names = ["bias", "scale_factor"] + [f"misalignment_{a}{AXES[j]}" for j in others]
    w_fs = float(np.nanmax(np.abs(om))) if len(p) else 1.0
    scales = [1.0, w_fs, w_fs, w_fs]
    optional = [False, False, False, False]
    use_g = g_sens is True or (g_sens == "auto" and np.all(np.isfinite(fr)))
    sweep = on_axis_rows(om, i)
    pre_i = dict(pre)
    sat: dict[int, str] = {}
    if saturation_test:
        rows = np.flatnonzero(sweep & ~np.isin(np.arange(len(p)), list(pre)))
        ss = sig[rows] * np.sqrt(p["n_samples"].to_numpy(float)[rows]) if (sig is not None and "n_samples" in p) else None
        s = detect_saturation(om[rows, i], y[rows], None if sig is None else sig[rows], x_unit="deg/s",
                              x_factor=RADPS_TO_DEGPS, sample_sigma=ss)
        sat = {int(rows[k]): v for k, v in s.items()}
        pre_i.update(sat)
    # [IEEE952] scale-factor asymmetry in the main model: y = ... + Kbar w + (dK/2)|w|. Without it an asymmetric
    # sensor's |w| signature went to the residuals and the bias (rate-fit K z sd 1.9, consumer, coverage benchmark)
    cols.append(np.abs(om[:, i]))
    names.append("sf_asymmetry_term")
    scales.append(w_fs)
    optional.append(True)
    nuisance = [False] * 5
    f_bar = None
    if use_g:
        # g-sensitivity as centred nuisance columns: they absorb the bias shifts between orientations (G f) even
        # when G itself is not separable from the bias; the intercept is then the bias at the mean force f_bar
        keep = ~np.isin(np.arange(len(p)), list(pre_i))
        f_bar = fr[keep].mean(axis=0) if keep.any() else np.zeros(3)
        g_fs = float(np.nanmax(np.linalg.norm(fr, axis=1))) or 1.0
        for j in range(3):
            cols.append(fr[:, j] - f_bar[j])
            names.append(f"g_sensitivity_{AXES[j]}")
            scales.append(g_fs)
            optional.append(True)
            nuisance.append(True)
    A = np.column_stack(cols)
    scales = np.asarray(scales)
    optional = np.asarray(optional)
    nuisance = np.asarray(nuisance)
    note = compression_note(om[:, i], sweep, sat)
    tm = _times(p) if correlated_noise else None
    rate_rows = sweep & (p["kind"].to_numpy() == "rate") & (np.linalg.norm(om, axis=1) > 3.0 * EARTH_RATE_RADPS)
    ch = f"gyro_{a}_radps"
    # the device's static-record B when given (noise_prior), else the run's own (segmentation's pooled Allan fit)
    dp = prior_flicker(noise_prior, ch, p)
    f_tau2, f_dof, b_source = dp or (flicker_prior_tau2(flicker_b(p, ch)), flicker_b_dof(p, ch), "")
    fit = fit_linear(A, y, names, sigma=sig, scales=scales, optional=optional, rel_tol=rel_tol, pre_excluded=pre_i,
                     outlier_test=outlier_test, alpha=alpha, outlier_note=note,
                     screen_columns=sweep_screen_columns(om[:, i], rate_rows), nuisance=nuisance,
                     times=tm, flicker_tau2=f_tau2, flicker_tau2_dof=f_dof, sem_flicker_tau2=sem_flicker_tau2(p, ch))
    ks = names.index("scale_factor")
    K, sK = fit.get("scale_factor")
    b, sb = fit.get("bias")
    mis = {}
    for j in others:
        nm = f"misalignment_{a}{AXES[j]}"
        k = names.index(nm)
        if fit.observable[k] and fit.observable[ks]:
            v, s = ratio_with_stderr(fit.value[k], fit.value[ks], fit.cov[k, k], fit.cov[ks, ks], fit.cov[k, ks])
            mis[AXES[j]] = Coefficient.with_coverage(v, s, "rad", True, fit.k95)
        else:
            mis[AXES[j]] = Coefficient.with_coverage(np.nan, np.nan, "rad", False, fit.k95)
    gs = {}
    bias_force = None
    if use_g:
        kg = [names.index(f"g_sensitivity_{AXES[j]}") for j in range(3)]
        full = bool(np.all(fit.observable[kg]))
        for j, k in enumerate(kg):
            gs[AXES[j]] = Coefficient.with_coverage(float(fit.value[k]), float(np.sqrt(fit.cov[k, k])), "rad/s/(m/s^2)",
                                                    full, fit.k95)
        kb = names.index("bias")
        if full:
            # b = b_bar - G f_bar
            gvec = np.zeros(len(names))
            gvec[kb] = 1.0
            gvec[kg] = -f_bar
            C = np.nan_to_num(fit.cov)
            b = float(fit.value[kb] - fit.value[kg] @ f_bar)
            sb = float(np.sqrt(gvec @ C @ gvec))
        else:
            bias_force = f_bar
    # nonlinearity ([SEED003] eq. 4-6) is the deviation from the straight line: the same fit without the hinge
    kh = names.index("sf_asymmetry_term")
    line = np.arange(len(names)) != kh
    pre_line = {int(r): fit.exclusion_reason[r] for r in np.flatnonzero(~fit.used)}
    fit_line = fit_linear(A[:, line], y, [n for n in names if n != "sf_asymmetry_term"], sigma=sig, scales=scales[line],
                          optional=optional[line], rel_tol=rel_tol, pre_excluded=pre_line, outlier_test=False,
                          nuisance=nuisance[line], times=tm, flicker_tau2=fit.flicker_tau2 or None,
                          sem_flicker_tau2=fit.sem_flicker_tau2)
    K_line = fit_line.get("scale_factor")[0]
    # the floor's 1/f level from the fit's own input (the device record's B with its law) and the plateaus' REML, as the
    # means fit has it: the REML alone (0 or several times the truth) put the tactical floor's residual sd at 0.965 of
    # the simulated truth's, 0.991 with the input (90 quick_rate axes, 3 h records)
    nl, nls, floor, at, fs, nsw = sweep_nonlinearity(fit_line, A[:, line], om[:, i], rate_rows, K_line, tm,
                                                      flicker_tau2=f_tau2, flicker_tau2_dof=f_dof)
    kp, sp, kn, sn, asym, sasym, fa = hinge_coefficients(fit, ks, names.index("sf_asymmetry_term"))
    if not np.isfinite(asym):
        fa = None
    ok_nl, ok_asym = bool(np.isfinite(nl)), bool(np.isfinite(asym))
    st = SweepStats(Coefficient.with_coverage(nl, nls, "1", ok_nl, Z95), floor, at, fs, nsw,
                    Coefficient.with_coverage(kp, sp, "1", ok_asym, fit.k95),
                    Coefficient.with_coverage(kn, sn, "1", ok_asym, fit.k95),
                    Coefficient.with_coverage(asym, sasym, "1", ok_asym, fit.k95), fa)
    kb = names.index("bias")
    return GyroAxisRateFit(
        axis=a, fit=fit, design=A, scale_factor=Coefficient.with_coverage(K, sK, "1", bool(fit.observable[ks]), fit.k95),
        bias_radps=Coefficient.with_coverage(b, sb, "rad/s", bool(fit.observable[kb]), fit.k95),
        misalignment_rad=mis, g_sensitivity=gs, sweep=st, saturated=sat, n_plateaus=fit.n_used,
        n_samples=_n_samples(p, fit.used), bias_reference_force_mps2=bias_force, b_source=b_source,
    )


def difference_method(p: pd.DataFrame, excluded: list[np.ndarray] | None = None, *, rel_tol=DEFAULT_REL_TOL,
                      sigma_ok: bool = True) -> DifferenceCheck | None:
    """[SEED000] eq. 9-13 from plateau means: pair +w and -w plateaus about the same axis at the same |rate|.

    For each pair, dy = y(+) - y(-) = M (w(+) - w(-)) (bias, g-sensitivity and the vertical earth rate cancel);
    per output axis i a no-intercept least squares dy_i = sum_j M_ij dw_j over the pairs gives K_i = M_ii and
    E_ij = M_ij / M_ii (eq. 12-13). ``excluded[i]`` marks plateaus excluded for output axis i in the main fit.
    """
    om = _omega(p)
    kind = p["kind"].to_numpy()
    norm = np.linalg.norm(om, axis=1)
    rate = (kind == "rate") & (norm > 3.0 * EARTH_RATE_RADPS)
    dom = np.argmax(np.abs(om), axis=1)
    cmd = np.abs(p["commanded_rate_radps"].to_numpy(float)) if "commanded_rate_radps" in p else norm
    pairs = []
    for j in range(3):
        rows = np.flatnonzero(rate & (dom == j))
        mags = cmd[rows]
        used_mag = set()
        for r in rows:
            m = mags[list(rows).index(r)]
            key = round(float(m), 9)
            if key in used_mag:
                continue
            same = rows[np.isclose(mags, m, rtol=1e-6, atol=1e-12)]
            pos = same[om[same, j] > 0]
            neg = same[om[same, j] < 0]
            used_mag.add(key)
            if len(pos) and len(neg):
                pairs.append((j, m, pos, neg))
    if not pairs:
        return None
    Y = np.array([[p[f"gyro_{a}_radps_mean"].to_numpy(float)] for a in AXES])[:, 0, :]
    S = np.array([p[f"gyro_{a}_radps_sem"].to_numpy(float) if f"gyro_{a}_radps_sem" in p else np.full(len(p), np.nan)
                  for a in AXES])
    dW = np.array([om[pos].mean(0) - om[neg].mean(0) for _, _, pos, neg in pairs])
    fits = []
    rec = []
    for i in range(3):
        dy = np.array([Y[i, pos].mean() - Y[i, neg].mean() for _, _, pos, neg in pairs])
        ds = np.array([np.sqrt(np.mean(S[i, pos] ** 2) / len(pos) + np.mean(S[i, neg] ** 2) / len(neg))
                       for _, _, pos, neg in pairs])
        pre = {}
        if excluded is not None:
            for k, (_, _, pos, neg) in enumerate(pairs):
                if excluded[i][pos].any() or excluded[i][neg].any():
                    pre[k] = "a plateau of the pair is excluded in the main fit"
        use_sig = sigma_ok and np.all(np.isfinite(ds) & (ds > 0))
        w_fs = float(np.max(np.abs(dW))) or 1.0
        f = fit_linear(dW, dy, [f"M_{AXES[i]}{a}" for a in AXES], sigma=ds if use_sig else None,
                       scales=np.full(3, w_fs), rel_tol=rel_tol, pre_excluded=pre, outlier_test=False)
        fits.append(f)
        for k, (j, m, pos, neg) in enumerate(pairs):
            rec.append(dict(output_axis=AXES[i], rate_axis=AXES[j], rate_radps=m, n_pos=len(pos), n_neg=len(neg),
                            dy=dy[k], dy_sigma=ds[k], used=bool(f.used[k])))
    K = np.full(3, np.nan)
    sK = np.full(3, np.nan)
    E = np.full((3, 3), np.nan)
    sE = np.full((3, 3), np.nan)
    for i, f in enumerate(fits):
        if f.observable[i]:
            K[i], sK[i] = f.value[i], np.sqrt(f.cov[i, i])
            for j in range(3):
                if j != i and f.observable[j]:
                    E[i, j], sE[i, j] = ratio_with_stderr(f.value[j], f.value[i], f.cov[j, j], f.cov[i, i], f.cov[j, i])
        for j in range(3):
            if j == i:
                E[i, j], sE[i, j] = 0.0, 0.0
    return DifferenceCheck(tuple(fits), pd.DataFrame(rec), K, sK, E, sE)


def fit_gyro_rate(
    plateaus: pd.DataFrame,
    *,
    include_static: bool = True,
    g_sensitivity: bool | str = "auto",
    outlier_test: bool = True,
    saturation_test: bool = True,
    alpha: float = DEFAULT_ALPHA,
    rel_tol: float = DEFAULT_REL_TOL,
    use_flagged: bool = False,
    cross_check: bool = True,
    correlated_noise: bool = True,
    noise_prior: DeviceNoisePrior | None = None,
) -> GyroRateFit:
    """[SEED003] eq. 3 / [SEED000] eq. 6-13: per-axis WLS gyro rate fit over a plateau table (see module doc).

    ``plateaus``: PLATEAU TABLE rows (kind 'rate', plus 'static' when ``include_static``) of one device and
    run. Flagged rows are excluded (reason kept) unless ``use_flagged``. ``g_sensitivity='auto'`` adds
    g-sensitivity columns, kept only where the schedule separates them from the bias. ``noise_prior``: the device's
    1/f level from its static records (:class:`~assets_lib.calibration.noise_prior.DeviceNoisePrior`); for a gyro
    channel it has, it replaces the run's B (two-sided: B with its interval's dof; a bound: B <= bound integrated),
    and the bias coefficient's note names the record. None: the run's own B, as before.
    """
    kinds = ("rate", "static") if include_static else ("rate",)
    p, pre = select_rows(plateaus, kinds, use_flagged)
    if not (p["kind"] == "rate").any():
        raise ValueError("fit_gyro_rate needs plateaus of kind 'rate'")
    dev = str(p["device_id"].iloc[0]) if "device_id" in p else ""
    run = str(p["run_id"].iloc[0]) if "run_id" in p else ""
    sigma_ok = all(f"gyro_{a}_radps_sem" in p for a in AXES)
    axes = tuple(
        _fit_axis(p, pre, i, sigma_ok=sigma_ok, g_sens=g_sensitivity, outlier_test=outlier_test,
                  saturation_test=saturation_test, alpha=alpha, rel_tol=rel_tol, correlated_noise=correlated_noise,
                  noise_prior=noise_prior)
        for i in range(3)
    )
    diff = difference_method(p, [~ax.fit.used for ax in axes], rel_tol=rel_tol, sigma_ok=sigma_ok) if cross_check else None
    return GyroRateFit(dev, run, axes, p, diff)
