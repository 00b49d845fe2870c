"""Single-axis fits on tables of plateau means (labs without raw logs): [SEED001]'s rate and tumble fits.

Rate ([SEED001] eq. 1-3, [SEED003] eq. 3-8): U_j = U0 + K w_j + v_j over commanded rates w_j, by least squares;
nonlinearity (max deviation over the full-scale output, ppm) and asymmetry (K+ vs K-, ppm), each with an
uncertainty; saturated and wild plateaus excluded automatically and reported.

Tumble ([SEED001] eq. 4-7): U = K0 + K1 sin(theta) + K2 sin^2(theta) + K3 sin(theta) cos(theta), the input
a_i = sin(theta) g and the cross input a_o = cos(theta) g; optionally the [IEEE1293] misalignment term
delta_o cos(theta). Coefficients in the lab's output unit (V, counts, ...) per g and per g^2.

Both use the same engine (:func:`assets_lib.calibration.fit_core.fit_linear`) as the plateau-table fits: identifiability,
Bonferroni-tested exclusions with reasons, and the covariance policy described there. Inputs are converted to
SI (rad/s, rad) inside; coefficients are reported in the lab's units at the edge.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import pandas as pd

from assets_lib.calibration.fit_core import (
    DEFAULT_ALPHA,
    DEFAULT_REL_TOL,
    FlickerBoundLaw,
    LinearFit,
    fit_linear,
    flicker_prior_tau2,
)
from assets_lib.calibration.rate_fit import compression_note, sweep_asymmetry, sweep_nonlinearity, sweep_screen_columns
from assets_lib.calibration.saturation import detect_saturation
from assets_lib.coefficient import Coefficient, ratio_with_stderr
from raw_schemas.units import ANGLE_UNITS_TO_RAD, GYRO_UNITS_TO_RADPS

EXCLUSION_MODES = ("auto", "saturation", "flat-top", "none")


@dataclass(frozen=True)
class MeansCoefficient:
    """A named coefficient of a plateau-means fit, in the lab's units, with its note."""

    name: str
    estimate: Coefficient
    note: str = ""

    value = property(lambda self: self.estimate.value)
    stderr = property(lambda self: self.estimate.stderr)
    unit = property(lambda self: self.estimate.unit)
    observable = property(lambda self: self.estimate.observable)
    ci95_low = property(lambda self: self.estimate.interval()[0])
    ci95_high = property(lambda self: self.estimate.interval()[1])

    def as_dict(self) -> dict:
        return {"name": self.name, "value": self.value, "stderr": self.stderr, "unit": self.unit,
                "ci95_low": self.ci95_low, "ci95_high": self.ci95_high, "observable": self.observable,
                "note": self.note}


@dataclass(frozen=True)
class ExcludedPoint:
    row: int
    input: float
    output: float
    kind: str  # 'saturation' | 'outlier' | 'invalid'
    reason: str


@dataclass(frozen=True, eq=False)
class MeansFit:
    """Result of a plateau-means fit, in the lab's units."""

    kind: str  # 'rate' | 'tumble'
    input_unit: str
    output_unit: str
    coefficients: tuple[MeansCoefficient, ...]
    excluded: tuple[ExcludedPoint, ...]
    residuals: pd.DataFrame
    n_points: int
    n_used: int
    dof: int
    residual_rms: float
    cov_policy: str
    fit: LinearFit
    warnings: tuple[str, ...] = field(default=())

    def coefficient(self, name: str) -> MeansCoefficient:
        for c in self.coefficients:
            if c.name == name:
                return c
        raise KeyError(name)

    def to_dict(self) -> dict:
        def clean(v):
            if isinstance(v, (float, np.floating)):
                return None if not np.isfinite(v) else float(v)
            if isinstance(v, (np.integer,)):
                return int(v)
            if isinstance(v, (np.bool_,)):
                return bool(v)
            return v

        res = self.residuals.copy()
        return {
            "kind": self.kind,
            "input_unit": self.input_unit,
            "output_unit": self.output_unit,
            "n_points": self.n_points,
            "n_used": self.n_used,
            "dof": self.dof,
            "residual_rms": clean(self.residual_rms),
            "cov_policy": self.cov_policy,
            "coefficients": [{k: clean(v) for k, v in c.as_dict().items()} for c in self.coefficients],
            "excluded": [{k: clean(v) for k, v in e.__dict__.items()} for e in self.excluded],
            "residuals": [{k: clean(v) for k, v in r.items()} for r in res.to_dict(orient="records")],
            "warnings": list(self.warnings),
        }


def _coef(fit: LinearFit, name: str, value: float, stderr: float, unit: str, observable: bool = True, note: str = ""):
    est = Coefficient.with_coverage(value, stderr, unit, bool(observable and np.isfinite(value)), fit.k95)
    return MeansCoefficient(name, est, note)


def _exclusions(fit: LinearFit, x_lab, y, sat: dict[int, str]) -> tuple[ExcludedPoint, ...]:
    out = []
    for r in np.flatnonzero(~fit.used):
        kind = "saturation" if r in sat else (fit.exclusion_kind[r] if fit.exclusion_kind[r] != "pre" else "user")
        out.append(ExcludedPoint(int(r), float(x_lab[r]), float(y[r]), kind, fit.exclusion_reason[r]))
    return tuple(out)


def _residuals(fit: LinearFit, x_lab, y, input_name: str) -> pd.DataFrame:
    return pd.DataFrame(
        {
            "row": np.arange(len(y)),
            input_name: np.asarray(x_lab, float),
            "output": y,
            "fitted": fit.fitted,
            "residual": fit.residual,
            "std_residual": fit.std_residual,
            "excluded": ~fit.used,
            "reason": list(fit.exclusion_reason),
        }
    )


def _check_mode(exclusion: str):
    if exclusion not in EXCLUSION_MODES:
        raise ValueError(f"exclusion must be one of {EXCLUSION_MODES}, not {exclusion!r}")


def _plateau_times(times, n: int):
    """(t_mid_s, t_len_s) for fit_linear from (t_start_s, t_end_s) of n plateaus, or None."""
    if times is None:
        return None
    a, b = (np.asarray(v, float) for v in times)
    if a.shape != (n,) or b.shape != (n,):
        raise ValueError(f"times: expected (t_start_s, t_end_s) arrays of {n} plateaus, got shapes {a.shape}, {b.shape}")
    if np.any(b < a):
        raise ValueError(f"times: plateau {int(np.flatnonzero(b < a)[0])} ends (t_end_s) before it starts (t_start_s)")
    return 0.5 * (a + b), b - a


def _flicker_inputs(flicker_b, flicker_b_dof, flicker_b_max):
    """(flicker_tau2, flicker_tau2_dof) for :func:`fit_linear` from B (with its dof) or from a bound on it only
    (tau^2 <= bound^2 / pi, :class:`FlickerBoundLaw`); ValueError for both, or a bound that is not positive."""
    if flicker_b_max is None:
        return flicker_prior_tau2(flicker_b), flicker_b_dof
    if flicker_b is not None or flicker_b_dof is not None:
        raise ValueError("give the 1/f level B (with its dof) or only a bound on it (flicker_b_max), not both")
    if not (np.isfinite(flicker_b_max) and flicker_b_max > 0):
        raise ValueError(f"flicker_b_max must be a positive bound on B, not {flicker_b_max}")
    t2 = flicker_prior_tau2(float(flicker_b_max))
    return t2, FlickerBoundLaw(t2)


def _sem_tau2(sem_flicker_b):
    """tau_s^2 = B_s^2 / pi of the 1/f level the sems contain, or None (not given); ValueError unless B_s >= 0."""
    if sem_flicker_b is None:
        return None
    if not (np.isfinite(sem_flicker_b) and sem_flicker_b >= 0):
        raise ValueError(f"sem_flicker_b must be >= 0 (0: the sems are white only), not {sem_flicker_b}")
    return float(sem_flicker_b) ** 2 / np.pi


def fit_rate_means(
    rate,
    output,
    sem=None,
    *,
    rate_unit: str = "deg/s",
    output_unit: str = "",
    exclusion: str = "auto",
    alpha: float = DEFAULT_ALPHA,
    rel_tol: float = DEFAULT_REL_TOL,
    times=None,
    flicker_b: float | None = None,
    flicker_b_dof: float | None = None,
    flicker_b_max: float | None = None,
    sem_flicker_b: float | None = None,
) -> MeansFit:
    """[SEED001] eq. 1-3: U = U0 + K w by least squares over plateau means, with automatic exclusions.

    ``rate`` commanded rates in ``rate_unit`` (deg/s, rad/s, deg/h, mrad/s); ``output`` plateau means in any
    unit; ``sem`` optional standard errors of the means. ``exclusion``: 'auto' (saturation: flat tops and
    plateaus at the rail, then the Bonferroni outlier test), 'saturation' (flat tops and rail, no outlier test),
    'flat-top' (only plateaus whose output stopped following the input), 'none'. Coefficients: ``zero_output`` U0 [output unit],
    ``scale_factor`` K [output unit per rate unit], ``bias_equivalent`` U0/K [rate unit], ``nonlinearity`` and
    ``asymmetry`` [ppm], ``scale_factor_pos/neg``.

    ``times`` (t_start_s, t_end_s) of every plateau and ``flicker_b`` (the run's 1/f level B, output unit) enable
    the correlated-noise GLS of :func:`~assets_lib.calibration.fit_core.fit_linear` (as the rate fit has it):
    without them the plateaus are independent, which bias instability breaks (the 1/f noise shared between
    plateaus minutes apart; means-fit K+, K-, asymmetry z sd 1.1-1.5 in the coverage benchmark). ``flicker_b_dof``:
    the degrees of freedom of that B (:func:`~assets_lib.calibration.fit_core.flicker_b_dof` from a plateau table):
    the fit then integrates over the 1/f level instead of taking B as exact. ``flicker_b_max`` (instead of
    ``flicker_b``): only an upper bound on B, as an Allan analysis of a record too short to resolve the floor gives
    it (``imulab allan``'s interval [0, bound]): integrated over below the bound
    (:class:`~assets_lib.calibration.fit_core.FlickerBoundLaw`). ``sem_flicker_b``: the 1/f level B the ``sem``
    already contain (imulab's plateau table: ``<channel>_sem_flicker_b``; 0 for sems that are white only, as
    std/sqrt(n) of a plateau's samples): a plateau's white part is then sem^2 less that level's Allan floor whatever
    1/f level the GLS weighs (:func:`~assets_lib.calibration.fit_core.white_variance`); without it the sems are read
    as containing the floor of the level weighed (tactical means-fit nonlinearity coverage 0.90-0.93 with sems that
    did not).
    """
    _check_mode(exclusion)
    if rate_unit not in GYRO_UNITS_TO_RADPS:
        raise ValueError(f"unknown rate unit {rate_unit!r}; one of {sorted(GYRO_UNITS_TO_RADPS)}")
    fac = GYRO_UNITS_TO_RADPS[rate_unit]
    x_lab = np.asarray(rate, float)
    w = x_lab * fac
    y = np.asarray(output, float)
    sig = None if sem is None else np.asarray(sem, float)
    ou = output_unit or "output"
    sat: dict[int, str] = {}
    if exclusion != "none":
        sat = detect_saturation(w, y, sig, x_unit=rate_unit, x_factor=1 / fac, rail=exclusion != "flat-top")
    A = np.column_stack([np.ones(len(w)), w])
    names = ("zero_output", "scale_factor")
    scales = np.array([1.0, max(np.nanmax(np.abs(w)), 1e-300)])
    sweep = np.ones(len(w), bool)
    note = compression_note(w, sweep, sat, sign_gain=np.sign(np.nanmedian(np.diff(y[np.argsort(w)])) or 1.0))
    tm = _plateau_times(times, len(w))
    prior_tau2, prior_dof = _flicker_inputs(flicker_b, flicker_b_dof, flicker_b_max)
    sem_tau2 = _sem_tau2(sem_flicker_b)
    fit = fit_linear(A, y, names, sigma=sig, scales=scales, rel_tol=rel_tol, pre_excluded=sat,
                     outlier_test=exclusion == "auto", alpha=alpha, outlier_note=note,
                     screen_columns=sweep_screen_columns(w, np.isfinite(w)), times=tm,
                     flicker_tau2=prior_tau2, flicker_tau2_dof=prior_dof, sem_flicker_tau2=sem_tau2)
    U0, sU0 = fit.get("zero_output")
    K, sK = fit.get("scale_factor")
    k = fit.names.index("scale_factor")
    coefs = [
        _coef(fit, "zero_output", U0, sU0, ou),
        _coef(fit, "scale_factor", K * fac, sK * fac, f"{ou}/({rate_unit})"),
    ]
    if fit.observable.all():
        be, sbe = ratio_with_stderr(U0, K, fit.cov[0, 0], fit.cov[k, k], fit.cov[0, k])
        coefs.append(_coef(fit, "bias_equivalent", be / fac, sbe / fac, rate_unit,
                           note="zero output expressed as input rate, U0/K"))
    nz = np.abs(w) > 0
    nl, nls, floor, at, fs, nsw = sweep_nonlinearity(fit, A, w, nz, K, tm, flicker_tau2=prior_tau2,
                                                     flicker_tau2_dof=prior_dof)
    ok = bool(np.isfinite(nl))  # the interval is clipped at zero: nonlinearity is a magnitude
    est = Coefficient(nl * 1e6, nls * 1e6, "ppm", ok, max(nl - 1.96 * nls, 0.0) * 1e6, (nl + 1.96 * nls) * 1e6)
    coefs.append(MeansCoefficient("nonlinearity", est,
                             f"max |residual| over full-scale output |K| max|w| = {fs:.6g} {ou}, worst at "
                             f"{at / fac:+.6g} {rate_unit}; noise floor (95 %) {floor * 1e6:.3g} ppm"))
    pre_asym = {int(r): fit.exclusion_reason[r] for r in np.flatnonzero(~fit.used)}
    # the hinge fit takes its 1/f level from the run (Allan B) or, without one, by its own REML, never the straight
    # line's: a REML under the straight line reads an asymmetry's |w| misfit as 1/f noise (tau^2 up to 1e4x the
    # truth), which widened K+, K- and the asymmetry (z sd 0.55-0.65 with asymmetry injected, coverage 0.99)
    kp, sp, kn, sn, asym, sasym, fa = sweep_asymmetry(A, names, y, sig, w, 1, pre_asym, scales, np.zeros(2, bool), rel_tol,
                                                      times=tm, flicker_tau2=prior_tau2, flicker_tau2_dof=prior_dof,
                                                      sem_flicker_tau2=sem_tau2)
    kk = fa.k95 if fa is not None else 1.96
    if fa is not None and np.isfinite(asym) and fa.observable[1]:
        # K = mean(K+, K-) from the hinge fit, as the rate fit reports it: on a symmetric sweep the straight line's
        # slope is the same number, but its uncertainty read the asymmetry's |w| misfit as noise (as 1/f level by
        # REML, or by the chi-square scaling): K z sd 0.48 (navigation, tactical) and 1.56 (consumer, coverage
        # 0.81) with asymmetry injected in the coverage benchmark, 1.0-1.1 without
        Kh, sKh = fa.get("scale_factor")
        coefs[1] = MeansCoefficient("scale_factor", Coefficient.with_coverage(Kh * fac, sKh * fac,
                                                                             f"{ou}/({rate_unit})", True, kk),
                                    "hinge fit U = U0 + K w + (dK/2)|w|: K = mean(K+, K-)")
    for name, v, s, u in (("scale_factor_pos", kp * fac, sp * fac, f"{ou}/({rate_unit})"),
                          ("scale_factor_neg", kn * fac, sn * fac, f"{ou}/({rate_unit})"),
                          ("asymmetry", asym * 1e6, sasym * 1e6, "ppm")):
        coefs.append(MeansCoefficient(name, Coefficient.with_coverage(v, s, u, bool(np.isfinite(v)), kk),
                                      "hinge fit U = U0 + K w + (dK/2)|w|; asymmetry = (K+ - K-)/mean(K+, K-)"))
    rms = float(np.sqrt(np.mean(fit.residual[fit.used] ** 2))) if fit.n_used else float("nan")
    res = _residuals(fit, x_lab, y, f"rate_{rate_unit}")
    return MeansFit("rate", rate_unit, ou, tuple(coefs), _exclusions(fit, x_lab, y, sat), res, len(y), fit.n_used,
                    fit.dof, rms, fit.cov_policy, fit, fit.warnings)


def fit_tumble_means(
    angle,
    output,
    sem=None,
    *,
    angle_unit: str = "deg",
    output_unit: str = "",
    misalignment_term: bool = False,
    exclusion: str = "auto",
    alpha: float = DEFAULT_ALPHA,
    rel_tol: float = DEFAULT_REL_TOL,
    times=None,
    flicker_b: float | None = None,
    flicker_b_dof: float | None = None,
    flicker_b_max: float | None = None,
    sem_flicker_b: float | None = None,
) -> MeansFit:
    """[SEED001] eq. 5-7: U = K0 + K1 sin + K2 sin^2 + K3 sin cos over tumble positions (a_i = sin theta [g]).

    K0 [output unit], K1 [output unit/g], K2 and K3 [output unit/g^2]; derived: bias K0/K1 [mg], K2/K1 and
    K3/K1 [ug/g^2]; with ``misalignment_term`` also delta_o (cos theta term / K1) [rad]. Coefficients the
    positions cannot separate are reported unobservable (e.g. K2 without a horizontal position).
    ``exclusion``: 'auto' (Bonferroni outlier test) or 'none' ('saturation' and 'flat-top' act like 'none').
    ``times`` / ``flicker_b`` / ``flicker_b_dof`` / ``flicker_b_max``: plateau (t_start_s, t_end_s), the run's 1/f
    level and its degrees of freedom, or only a bound on it, and ``sem_flicker_b``, the level the sems contain, as in
    :func:`fit_rate_means`.
    """
    _check_mode(exclusion)
    if angle_unit not in ANGLE_UNITS_TO_RAD:
        raise ValueError(f"unknown angle unit {angle_unit!r}; one of {sorted(ANGLE_UNITS_TO_RAD)}")
    x_lab = np.asarray(angle, float)
    th = x_lab * ANGLE_UNITS_TO_RAD[angle_unit]
    y = np.asarray(output, float)
    sig = None if sem is None else np.asarray(sem, float)
    ou = output_unit or "output"
    s, c = np.sin(th), np.cos(th)
    cols = [np.ones(len(th)), s]
    names = ["K0", "K1"]
    optional = [False, False]
    if misalignment_term:
        cols.append(c)
        names.append("delta_o_term")
        optional.append(False)
    cols += [s**2, s * c]
    names += ["K2", "K3"]
    optional += [True, True]
    A = np.column_stack(cols)
    scales = np.array([1.0, 1.0] + ([1.0] if misalignment_term else []) + [1.0, 0.5])
    prior_tau2, prior_dof = _flicker_inputs(flicker_b, flicker_b_dof, flicker_b_max)
    fit = fit_linear(A, y, names, sigma=sig, scales=scales, optional=np.array(optional), rel_tol=rel_tol,
                     outlier_test=exclusion == "auto", alpha=alpha, times=_plateau_times(times, len(th)),
                     flicker_tau2=prior_tau2, flicker_tau2_dof=prior_dof, sem_flicker_tau2=_sem_tau2(sem_flicker_b))
    coefs = []
    units = {"K0": ou, "K1": f"{ou}/g", "K2": f"{ou}/g^2", "K3": f"{ou}/g^2", "delta_o_term": f"{ou}/g"}
    for j, nm in enumerate(names):
        v, se = fit.get(nm)
        coefs.append(_coef(fit, nm, v, se, units[nm], bool(fit.observable[j]), fit.unobservable_reason[j]))
    k1 = names.index("K1")
    C = fit.cov
    for nm, out_name, fac, unit in (("K0", "bias", 1e3, "mg"), ("K2", "K2_per_K1", 1e6, "ug/g^2"),
                                    ("K3", "K3_per_K1", 1e6, "ug/g^2"), ("delta_o_term", "misalignment", 1.0, "rad")):
        if nm not in names:
            continue
        j = names.index(nm)
        if fit.observable[j] and fit.observable[k1]:
            v, se = ratio_with_stderr(fit.value[j], fit.value[k1], C[j, j], C[k1, k1], C[j, k1])
            coefs.append(_coef(fit, out_name, v * fac, se * fac, unit, note=f"{nm}/K1"))
        else:
            coefs.append(MeansCoefficient(out_name, Coefficient.unobservable(unit), f"{nm} or K1 not observable"))
    rms = float(np.sqrt(np.mean(fit.residual[fit.used] ** 2))) if fit.n_used else float("nan")
    res = _residuals(fit, x_lab, y, f"angle_{angle_unit}")
    return MeansFit("tumble", angle_unit, ou, tuple(coefs), _exclusions(fit, x_lab, y, {}), res, len(y), fit.n_used,
                    fit.dof, rms, fit.cov_policy, fit, fit.warnings)
