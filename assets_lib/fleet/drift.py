"""Fleet drift of calibration coefficients: per device and coefficient, the series of run estimates over time.

Model (random effects, one series = one device, sensor, axis, coefficient and fit method, runs ordered by start
time): x_i = mu + beta t_i + e_i, e_i ~ N(0, sigma_i^2) independent, with

    sigma_i^2 = sigma_turnon^2 + se_i^2

where se_i is the run's own standard error (the fit's ``stderr``) and sigma_turnon the device's turn-on to
turn-on scatter, i.e. the noise-corrected bias / scale-factor repeatability ([SEED000] eq. 23, [GJB2426A] B_r,
``assets_lib.calibration.repeatability``: sqrt(max(0, s^2 - rms(se)^2))). A run estimate scatters about the device's mean
by both, independently, so their variances add. This is never smaller than the larger of the repeatability
standard deviation and the run's stderr, the usual rule of thumb for control limits (it is the quadrature form of
that rule: sqrt(s_r^2 + se^2) >= max(s_r, se)); taking the larger of the two alone would understate sigma by up
to a factor sqrt(2) when both are comparable. Without repeatability, sigma_turnon = 0: the limits are then the
measurement uncertainty alone, which over-flags a device whose turn-on scatter exceeds its stderr (the status
column says so: ``sigma_source``).

Per series:
- Trend: weighted least squares line (weights 1/sigma_i^2, sigma_i treated as known), slope per day with its
  standard error and a normal (z) confidence interval; the fitted line with its confidence band at every run;
  chi^2 of the line as a consistency diagnostic (Birge ratio; [COX2002]).
- Control limits (Shewhart individuals chart, [MONTGOMERY2013] sec. 6.4): centre = the weighted mean of the
  series, limits centre +/- 3 sigma_i. A run outside them is marked ``beyond_limits`` (probability 0.27 % per in-control run).
- Drift beyond limits: the fitted trend's excursion over the series, D = beta (t_last - t_first), is flagged when
  it is both significant, |D| / se(D) > z_drift (default 3, two-sided alpha = 0.27 %), and beyond the control
  band, |D| > limit_sigma * sigma (default 3 sigma, sigma = RMS of sigma_i): the coefficient has moved since
  the device's first run by more than the turn-on scatter allows, and the move is not noise. Designed false-alarm
  probability per in-control series: P(|Z| > max(z_drift, limit_sigma sigma / se(D))) <= 0.27 %
  (:func:`drift_false_alarm_probability`).
- Abrupt shift: a two-sided tabular CUSUM ([MONTGOMERY2013] sec. 9.1.2; [NISTHB] sec. 6.3.2.3) on self-starting
  standardized residuals u_i = (x_i - m_{i-1}) / sqrt(sigma_i^2 + v_{i-1}) with m_{i-1}, v_{i-1} the weighted mean
  of the earlier runs and its variance ([HAWKINS1987], self-starting CUSUM): with known sigma_i the u_i are
  independent N(0, 1) when the device is in control, so the chart's false-alarm probability over a short series is computable exactly. Reference value
  k = 0.5 (optimal for a 1 sigma shift) and decision interval h = 5: two-sided in-control ARL 465 runs,
  out-of-control ARL 10.4 / 4.0 / 2.6 runs for a 1 / 2 / 3 sigma shift ([MONTGOMERY2013] Table 9.3). h = 5
  rather than h = 4 (ARL0 168) because a fleet holds hundreds of series and every alarm is a warning to a person.
  The probability of an alarm within n - 1 residuals is computed by the [BROOK1972]
  Markov chain (:func:`cusum_false_alarm_probability`). After an alarm the run where the change happened is
  the maximum-likelihood change point of a single step ([HINKLEY1970]), i.e. the split with
  the smallest weighted residual sum of squares, and the series is called an abrupt *shift* when that step
  model fits better than the straight line by more than ``shift_penalty`` (chi^2 units; default ln n, the BIC
  price of the change point's location), otherwise a *drift*. A series is flagged at most once: 'shift' or
  'drift'.

Where sigma_turnon comes from (``sigma_source``):
- 'repeatability': the repeatability was measured on other runs than the series (a qualification set,
  [MONTGOMERY2013] phase I): sigma is known, the rules above have their designed rates exactly.
- 'repeatability, detrended (in-sample)': the repeatability stage computed it over the very runs being monitored
  (the pipeline's case). Used as is, a drift would inflate it and hide itself: a linear drift D over Q equally
  spaced runs adds D^2 (Q + 1) / (12 (Q - 1)) to s^2, so |D| / s can never exceed sqrt(12 (Q - 1) / (Q + 1))
  < 3.5, and a 3-sigma rule could never fire. So the repeatability is re-estimated about the fitted line
  (the same sample variance with the trend's sum of squares removed, n - 2 degrees of freedom, noise-corrected),
  and the drift significance uses Student's t with n - 2 degrees of freedom at the same alpha (0.27 %) and the
  slope interval t quantiles: the textbook slope test, exact for homoscedastic normal runs. The price is power:
  few runs cannot separate a drift from turn-on scatter (3 runs: 1 degree of freedom, t = 236), which is the
  truth, not a defect. The CUSUM then uses the same sigma as if known (its designed rate is approximate).
- 'stderr only': no repeatability; sigma_turnon = 0 (over-flags devices whose turn-on scatter exceeds stderr).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from functools import lru_cache

import numpy as np
import pandas as pd
from scipy import stats

SERIES_KEYS = ("device_id", "sensor", "axis", "coefficient", "method")
#: coefficients analyzed by default: the ones whose turn-on repeatability the pipeline measures
DEFAULT_COEFFICIENTS = ("bias", "scale_factor")
#: repeatability table coefficient -> coefficient it describes (assets_lib.calibration.repeatability)
REPEATABILITY_OF = {"bias_repeatability": "bias", "scale_factor_repeatability": "scale_factor"}
RELATIVE_REPEATABILITY = {"scale_factor_repeatability"}


@dataclass(frozen=True)
class DriftConfig:
    """Chart parameters (see the module docstring for the sources and the designed rates)."""

    cusum_k: float = 0.5
    cusum_h: float = 5.0
    z_drift: float = 3.0
    limit_sigma: float = 3.0
    confidence: float = 0.95
    min_runs: int = 3
    shift_penalty: float | None = None  # chi^2 units; None: ln(n)
    in_sample_min_runs: int = 4  # an in-sample (detrended) sigma needs n - 2 >= 2 degrees of freedom
    coefficients: tuple[str, ...] | None = DEFAULT_COEFFICIENTS  # None: every coefficient present


# ---------------------------------------------------------------------------------------------------------------
# Core numerics (arrays in, frozen dataclasses out; fast enough for Monte Carlo studies)
# ---------------------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class TrendFit:
    """Weighted straight line x = a + b t with known per-point sigma (t in days from the first run)."""

    intercept: float
    slope_per_day: float
    slope_stderr_per_day: float
    slope_ci_low: float
    slope_ci_high: float
    cov: tuple[tuple[float, float], tuple[float, float]]
    chi2: float
    dof: int
    span_days: float
    excursion: float  # slope * span: the trend's change from the first to the last run
    excursion_stderr: float
    z: float  # excursion / its stderr (= slope / its stderr)
    confidence: float
    sigma_dof: float | None = None  # None: sigma known (z); else degrees of freedom of the estimated sigma (t)

    def line(self, t) -> np.ndarray:
        return self.intercept + self.slope_per_day * np.asarray(t, float)

    def line_stderr(self, t) -> np.ndarray:
        t = np.asarray(t, float)
        (c00, c01), (_, c11) = self.cov
        return np.sqrt(np.maximum(c00 + 2 * t * c01 + t * t * c11, 0.0))

    @property
    def birge_ratio(self) -> float:
        return math.sqrt(self.chi2 / self.dof) if self.dof > 0 else float("nan")


def weighted_trend(t_days, x, sigma, confidence: float = 0.95, sigma_dof: float | None = None) -> TrendFit:
    """Weighted least squares line ([COX2002]): b = S_tx/S_tt with W = 1/sigma^2, var(b) = 1/S_tt;
    z interval for known sigma, Student-t(sigma_dof) interval when sigma was estimated from the residuals."""
    t = np.asarray(t_days, float)
    x = np.asarray(x, float)
    w = 1.0 / np.asarray(sigma, float) ** 2
    sw = w.sum()
    tb = (w * t).sum() / sw
    xb = (w * x).sum() / sw
    stt = (w * (t - tb) ** 2).sum()
    if stt <= 0:
        raise ValueError("a trend needs runs at two different times at least")
    b = (w * (t - tb) * (x - xb)).sum() / stt
    a = xb - b * tb
    vb = 1.0 / stt
    va = 1.0 / sw + tb * tb * vb
    cab = -tb * vb
    r = x - a - b * t
    chi2 = float((w * r * r).sum())
    se = math.sqrt(vb)
    zq = _z_two_sided(confidence) if sigma_dof is None else float(stats.t.ppf(0.5 + confidence / 2, sigma_dof))
    span = float(t.max() - t.min())
    return TrendFit(
        intercept=float(a), slope_per_day=float(b), slope_stderr_per_day=se,
        slope_ci_low=float(b - zq * se), slope_ci_high=float(b + zq * se),
        cov=((float(va), float(cab)), (float(cab), float(vb))), chi2=chi2, dof=len(x) - 2, span_days=span,
        excursion=float(b * span), excursion_stderr=se * span, z=float(b / se), confidence=confidence,
        sigma_dof=sigma_dof,
    )


@lru_cache(maxsize=16)
def _z_two_sided(confidence: float) -> float:
    return float(stats.norm.ppf(0.5 + confidence / 2))


def drift_false_alarm_probability(excursion_stderr: float, sigma: float, z_drift: float = 3.0,
                                  limit_sigma: float = 3.0, sigma_dof: float | None = None) -> float:
    """[MONTGOMERY2013] sec. 6.2.2 (alpha of a 3-sigma rule): P(|Z| > max(z_drift, limit_sigma sigma / se(D))) for
    known sigma; with an estimated sigma the bound alpha = P(|Z| > z_drift) of the t test (the band term is random)."""
    if sigma_dof is not None:
        return math.erfc(z_drift / math.sqrt(2.0))
    c = max(z_drift, limit_sigma * sigma / excursion_stderr)
    return math.erfc(c / math.sqrt(2.0))


def drift_threshold(z_drift: float, sigma_dof: float | None) -> float:
    """Critical |slope / se| of the drift test: z_drift for known sigma, else the Student-t quantile at the same alpha."""
    if sigma_dof is None:
        return z_drift
    return float(stats.t.isf(stats.norm.sf(z_drift), sigma_dof))


def detrended_turn_on_sigma(t_days, x, stderrs) -> tuple[float, int]:
    """Repeatability about the fitted line ([SEED000] eq. 23 with the trend removed), noise-corrected:
    sqrt(max(0, RSS_ols / (n - 2) - mean(se^2))), and its degrees of freedom n - 2."""
    t = np.asarray(t_days, float)
    x = np.asarray(x, float)
    se = np.asarray(stderrs, float)
    n = len(x)
    A = np.column_stack([np.ones(n), t - t.mean()])
    coef, *_ = np.linalg.lstsq(A, x, rcond=None)
    r = x - A @ coef
    s2 = float(r @ r) / (n - 2)
    se2 = float(np.mean(np.where(np.isfinite(se), se, 0.0) ** 2))
    return math.sqrt(max(s2 - se2, 0.0)), n - 2


def self_starting_residuals(x, sigma) -> np.ndarray:
    """[HAWKINS1987], known sigma: u_i = (x_i - m_{i-1}) / sqrt(sigma_i^2 + v_{i-1}); u_0 = NaN."""
    x = np.asarray(x, float)
    s2 = np.asarray(sigma, float) ** 2
    w = 1.0 / s2
    cw = np.cumsum(w)
    cwx = np.cumsum(w * x)
    u = np.full(x.shape, np.nan)
    m = cwx[:-1] / cw[:-1]
    u[1:] = (x[1:] - m) / np.sqrt(s2[1:] + 1.0 / cw[:-1])
    return u


@dataclass(frozen=True)
class CusumResult:
    """Tabular CUSUM statistics C+ and C- per run (NaN where no residual) and the first alarm."""

    c_plus: tuple[float, ...]
    c_minus: tuple[float, ...]
    alarm_index: int | None  # index (into the series) of the first run where C+ or C- > h
    alarm_side: str | None  # 'up' | 'down'
    k: float
    h: float


def tabular_cusum(z, k: float = 0.5, h: float = 5.0) -> CusumResult:
    """[MONTGOMERY2013] eq. 9.2-9.3 (NIST e-Handbook 6.3.2.3): C+_i = max(0, z_i - k + C+_{i-1}), C-_i = max(0, -z_i - k + C-_{i-1})."""
    z = np.asarray(z, float)
    cp = np.full(z.shape, np.nan)
    cm = np.full(z.shape, np.nan)
    p = m = 0.0
    alarm, side = None, None
    for i, zi in enumerate(z):
        if not np.isfinite(zi):
            continue
        p = max(0.0, zi - k + p)
        m = max(0.0, -zi - k + m)
        cp[i], cm[i] = p, m
        if alarm is None and (p > h or m > h):
            alarm, side = i, ("up" if p > h else "down")
    return CusumResult(tuple(cp.tolist()), tuple(cm.tolist()), alarm, side, k, h)


def _brook_evans_matrix(k: float, h: float, m: int, shift: float) -> np.ndarray:
    """Transition matrix among the m in-control states (state j covers ((j - 1/2) w, (j + 1/2) w], w = 2h/(2m - 1);
    state 0 holds C = 0; the top edge is h): R[i, j] = P(next in j | now at the centre of i)."""
    w = 2.0 * h / (2 * m - 1)
    c = np.arange(m) * w
    edges_hi = (np.arange(m) + 0.5) * w
    cdf = stats.norm.cdf(edges_hi[None, :] - c[:, None] + k - shift)
    return np.diff(np.concatenate([np.zeros((m, 1)), cdf], axis=1), axis=1)


def cusum_one_sided_arl(k: float = 0.5, h: float = 5.0, shift: float = 0.0, m: int = 300) -> float:
    """[BROOK1972]: average run length from C = 0, (I - R)^-1 1 ([MONTGOMERY2013] table 9.3)."""
    R = _brook_evans_matrix(k, h, m, shift)
    return float(np.linalg.solve(np.eye(m) - R, np.ones(m))[0])


def cusum_one_sided_alarm_probability(n: int, k: float = 0.5, h: float = 5.0, m: int = 300, shift: float = 0.0) -> float:
    """[BROOK1972] Markov chain: P(one-sided CUSUM from 0 signals within n N(shift,1) steps)."""
    if n <= 0:
        return 0.0
    R = _brook_evans_matrix(k, h, m, shift)
    p = np.zeros(m)
    p[0] = 1.0
    for _ in range(n):
        p = p @ R
    return float(1.0 - p.sum())


@lru_cache(maxsize=256)
def cusum_false_alarm_probability(n_residuals: int, k: float = 0.5, h: float = 5.0) -> float:
    """Two-sided alarm probability within ``n_residuals`` in-control steps: 1 - (1 - p1)^2 (sides treated as
    independent, [MONTGOMERY2013] sec. 9.1.3; they are weakly dependent, the approximation is checked by simulation
    in tests/test_drift.py)."""
    p1 = cusum_one_sided_alarm_probability(n_residuals, k, h)
    return float(1.0 - (1.0 - p1) ** 2)


@dataclass(frozen=True)
class StepFit:
    """Single mean shift between runs index-1 and index (maximum-likelihood change point)."""

    index: int  # first run after the shift
    size: float  # mean after - mean before
    size_stderr: float
    chi2: float


def step_change(x, sigma) -> StepFit:
    """Hinkley 1970 (Biometrika 57:1): the change point maximizing the likelihood of a single step in mean."""
    x = np.asarray(x, float)
    w = 1.0 / np.asarray(sigma, float) ** 2
    n = len(x)
    if n < 2:
        raise ValueError("a step needs two runs at least")
    best = None
    for j in range(1, n):
        w0, w1 = w[:j], w[j:]
        m0 = (w0 * x[:j]).sum() / w0.sum()
        m1 = (w1 * x[j:]).sum() / w1.sum()
        chi2 = float((w0 * (x[:j] - m0) ** 2).sum() + (w1 * (x[j:] - m1) ** 2).sum())
        if best is None or chi2 < best[0]:
            best = (chi2, j, m1 - m0, math.sqrt(1 / w0.sum() + 1 / w1.sum()))
    chi2, j, size, se = best
    return StepFit(int(j), float(size), float(se), chi2)


# ---------------------------------------------------------------------------------------------------------------
# One series
# ---------------------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class SeriesDrift:
    """Drift analysis of one device / coefficient series (values SI, times in days from the device's first run)."""

    key: dict
    unit: str
    run_ids: tuple[str, ...]
    start_times_utc: tuple[str, ...]
    t_days: tuple[float, ...]
    values: tuple[float, ...]
    stderrs: tuple[float, ...]
    sigma_turnon: float
    sigma_source: str  # 'repeatability' | 'repeatability, detrended (in-sample)' | 'given' | 'stderr only'
    sigma_dof: float | None  # None: sigma_turnon treated as known; else its degrees of freedom
    sigmas: tuple[float, ...]  # per-run sigma_i = sqrt(sigma_turnon^2 + se_i^2)
    center: float
    trend: TrendFit | None
    cusum: CusumResult | None
    step: StepFit | None
    beyond_limits: tuple[bool, ...]
    drift_flag: bool
    shift_flag: bool
    status: str  # 'ok' | 'drift' | 'shift' | 'too short: n runs'
    drift_false_alarm_designed: float
    cusum_false_alarm_designed: float

    @property
    def n(self) -> int:
        return len(self.values)

    @property
    def sigma(self) -> float:
        """RMS of the per-run sigmas: the series' control-band unit."""
        return float(np.sqrt(np.mean(np.square(self.sigmas)))) if self.sigmas else float("nan")

    @property
    def flagged(self) -> bool:
        return self.drift_flag or self.shift_flag

    @property
    def shift_run_id(self) -> str | None:
        return self.run_ids[self.step.index] if self.shift_flag and self.step else None

    def z_scores(self) -> np.ndarray:
        """Standardized deviation from the centre line, (x_i - centre) / sigma_i."""
        return (np.asarray(self.values) - self.center) / np.asarray(self.sigmas)


def analyze_series(t_days, values, stderrs, *, sigma_turnon: float | None = None, sigma_source: str = "given",
                   sigma_dof: float | None = None, config: DriftConfig = DriftConfig(), key: dict | None = None,
                   unit: str = "", run_ids=None, start_times_utc=None) -> SeriesDrift:
    """Trend, control limits, drift and shift flags of one series (module docstring: [MONTGOMERY2013] 6.4, 9.1).

    ``sigma_turnon`` known (``sigma_dof`` None) or estimated with ``sigma_dof`` degrees of freedom (t test)."""
    t = np.asarray(t_days, float)
    x = np.asarray(values, float)
    se = np.asarray(stderrs, float)
    n = len(x)
    order = np.argsort(t, kind="stable")
    t, x, se = t[order], x[order], se[order]
    run_ids = tuple(np.asarray(run_ids if run_ids is not None else [str(i) for i in range(n)], object)[order].tolist())
    starts = tuple(np.asarray(start_times_utc if start_times_utc is not None else [""] * n, object)[order].tolist())
    if sigma_turnon is None or not np.isfinite(sigma_turnon):
        sigma_turnon, sigma_source, sigma_dof = 0.0, "stderr only", None
    se_ok = np.where(np.isfinite(se) & (se > 0), se, 0.0)
    sig = np.sqrt(sigma_turnon**2 + se_ok**2)
    if n and not np.all(sig > 0):
        raise ValueError("every run needs a positive stderr or the series a positive turn-on sigma")
    center = float((x / sig**2).sum() / (1 / sig**2).sum()) if n else float("nan")
    beyond = tuple(bool(v) for v in np.abs(x - center) > config.limit_sigma * sig)
    common = dict(key=dict(key or {}), unit=unit, run_ids=run_ids, start_times_utc=starts, t_days=tuple(t.tolist()),
                  values=tuple(x.tolist()), stderrs=tuple(se.tolist()), sigma_turnon=float(sigma_turnon),
                  sigma_source=sigma_source, sigma_dof=sigma_dof, sigmas=tuple(sig.tolist()), center=center,
                  beyond_limits=beyond)
    if n < max(config.min_runs, 2) or np.ptp(t) <= 0:
        return SeriesDrift(**common, trend=None, cusum=None, step=None, drift_flag=False, shift_flag=False,
                           status=f"too short: {n} run{'s' * (n != 1)}", drift_false_alarm_designed=float("nan"),
                           cusum_false_alarm_designed=float("nan"))
    trend = weighted_trend(t, x, sig, config.confidence, sigma_dof)
    rms_sigma = float(np.sqrt(np.mean(sig**2)))
    significant = abs(trend.z) > drift_threshold(config.z_drift, sigma_dof)
    beyond_band = abs(trend.excursion) > config.limit_sigma * rms_sigma
    u = self_starting_residuals(x, sig)
    cus = tabular_cusum(u, config.cusum_k, config.cusum_h)
    step = step_change(x, sig)
    penalty = math.log(n) if config.shift_penalty is None else config.shift_penalty
    shift_flag = cus.alarm_index is not None and step.chi2 + penalty < trend.chi2
    drift_flag = significant and beyond_band and not shift_flag
    status = "shift" if shift_flag else "drift" if drift_flag else "ok"
    return SeriesDrift(
        **common, trend=trend, cusum=cus, step=step, drift_flag=bool(drift_flag), shift_flag=bool(shift_flag),
        status=status,
        drift_false_alarm_designed=drift_false_alarm_probability(trend.excursion_stderr, rms_sigma, config.z_drift,
                                                                 config.limit_sigma, sigma_dof),
        cusum_false_alarm_designed=cusum_false_alarm_probability(n - 1, config.cusum_k, config.cusum_h),
    )


# ---------------------------------------------------------------------------------------------------------------
# The fleet
# ---------------------------------------------------------------------------------------------------------------
def turn_on_sigma_table(repeatability: pd.DataFrame | None) -> pd.DataFrame:
    """Repeatability table (assets_lib.calibration.repeatability) -> turn-on sigma per (device, sensor, axis, coefficient, method).

    Columns out: the series keys, ``sigma_turnon`` (noise-corrected repeatability, relative for scale factors when
    ``relative``), ``relative`` (bool), ``repeatability`` (the plain sample std), ``n_runs``.
    """
    cols = list(SERIES_KEYS) + ["sigma_turnon", "relative", "repeatability", "n_runs", "run_ids"]
    if repeatability is None or repeatability.empty:
        return pd.DataFrame(columns=cols)
    r = repeatability[repeatability["coefficient"].isin(REPEATABILITY_OF)].copy()
    corrected = r["value_noise_corrected"] if "value_noise_corrected" in r else pd.Series(np.nan, index=r.index)
    out = pd.DataFrame({
        "device_id": r["device_id"].astype(str),
        "sensor": r["sensor"],
        "axis": r["axis"],
        "coefficient": r["coefficient"].map(REPEATABILITY_OF),
        "method": r["method"] if "method" in r else "",
        # noise-corrected value when finite, else the plain sample std (conservative: it includes the stderr)
        "sigma_turnon": np.where(np.isfinite(corrected.to_numpy(float)), corrected, r["value"]).astype(float),
        "relative": r["coefficient"].isin(RELATIVE_REPEATABILITY).to_numpy(),
        "repeatability": r["value"].astype(float),
        "n_runs": r["n_runs"] if "n_runs" in r else np.nan,
        "run_ids": r["run_ids"].astype(str) if "run_ids" in r else "",
    })
    return out[cols].reset_index(drop=True)


@dataclass(frozen=True)
class FleetDrift:
    """Every analyzed series, with tables, warnings and plots."""

    series: tuple[SeriesDrift, ...]
    config: DriftConfig = field(default_factory=DriftConfig)

    # ------------------------------------------------------------------ tables
    def series_table(self) -> pd.DataFrame:
        """One row per series: trend (slope per day, stderr, CI), sigma, flags, designed false-alarm rates."""
        rows = []
        for s in self.series:
            tr = s.trend
            nan = float("nan")
            rows.append({
                **{k: s.key.get(k, "") for k in SERIES_KEYS},
                "unit": s.unit, "n_runs": s.n, "first_run_id": s.run_ids[0] if s.n else "",
                "last_run_id": s.run_ids[-1] if s.n else "",
                "span_days": tr.span_days if tr else nan, "center": s.center, "sigma": s.sigma,
                "sigma_turnon": s.sigma_turnon, "sigma_source": s.sigma_source,
                "sigma_dof": np.nan if s.sigma_dof is None else float(s.sigma_dof),
                "slope_per_day": tr.slope_per_day if tr else nan,
                "slope_stderr_per_day": tr.slope_stderr_per_day if tr else nan,
                "slope_ci_low": tr.slope_ci_low if tr else nan, "slope_ci_high": tr.slope_ci_high if tr else nan,
                "confidence": tr.confidence if tr else nan,
                "excursion": tr.excursion if tr else nan, "excursion_stderr": tr.excursion_stderr if tr else nan,
                "excursion_sigma": (tr.excursion / s.sigma) if tr else nan, "trend_z": tr.z if tr else nan,
                "chi2": tr.chi2 if tr else nan, "dof": tr.dof if tr else -1,
                "cusum_max": float(np.nanmax(np.r_[s.cusum.c_plus, s.cusum.c_minus])) if s.cusum and s.n > 1 else nan,
                "cusum_alarm_run_id": s.run_ids[s.cusum.alarm_index] if s.cusum and s.cusum.alarm_index is not None else "",
                "shift_run_id": s.shift_run_id or "",
                "shift_size": s.step.size if s.shift_flag else nan,
                "shift_size_stderr": s.step.size_stderr if s.shift_flag else nan,
                "n_beyond_limits": int(sum(s.beyond_limits)),
                "drift_flag": s.drift_flag, "shift_flag": s.shift_flag, "status": s.status,
                "drift_false_alarm_designed": s.drift_false_alarm_designed,
                "cusum_false_alarm_designed": s.cusum_false_alarm_designed,
            })
        return pd.DataFrame(rows, columns=SERIES_COLUMNS)

    def points_table(self) -> pd.DataFrame:
        """One row per series and run: value, sigma, z, fitted trend with its band, CUSUM, limit and shift marks."""
        rows = []
        for s in self.series:
            z = s.z_scores()
            tr = s.trend
            line = tr.line(s.t_days) if tr else np.full(s.n, np.nan)
            band = tr.line_stderr(s.t_days) * stats.norm.ppf(0.5 + tr.confidence / 2) if tr else np.full(s.n, np.nan)
            for i in range(s.n):
                rows.append({
                    **{k: s.key.get(k, "") for k in SERIES_KEYS},
                    "run_id": s.run_ids[i], "start_time_utc": s.start_times_utc[i], "t_days": s.t_days[i],
                    "value": s.values[i], "stderr": s.stderrs[i], "sigma": s.sigmas[i], "unit": s.unit,
                    "center": s.center, "lcl": s.center - self.config.limit_sigma * s.sigmas[i],
                    "ucl": s.center + self.config.limit_sigma * s.sigmas[i], "z": float(z[i]),
                    "trend": float(line[i]), "trend_ci_low": float(line[i] - band[i]),
                    "trend_ci_high": float(line[i] + band[i]),
                    "cusum_plus": s.cusum.c_plus[i] if s.cusum else np.nan,
                    "cusum_minus": s.cusum.c_minus[i] if s.cusum else np.nan,
                    "beyond_limits": s.beyond_limits[i],
                    "shift_here": bool(s.shift_flag and s.step.index == i),
                    "status": s.status,
                })
        return pd.DataFrame(rows, columns=POINT_COLUMNS)

    def summary_table(self) -> pd.DataFrame:
        """Fleet summary: one row per coefficient family (sensor, coefficient) and one 'all' row."""
        st = self.series_table()
        rows = []
        groups = [(f"{a} {b}", g) for (a, b), g in st.groupby(["sensor", "coefficient"], sort=True)] if len(st) else []
        for name, g in groups + [("all", st)]:
            an = g[g["status"].isin(["ok", "drift", "shift"])]
            rows.append({
                "family": name, "n_devices": int(g["device_id"].nunique()), "n_series": len(g),
                "n_analyzed": len(an), "n_drift": int(g["drift_flag"].sum()), "n_shift": int(g["shift_flag"].sum()),
                "n_points_beyond_limits": int(g["n_beyond_limits"].sum()),
                "devices_flagged": ",".join(sorted(set(g.loc[g["drift_flag"] | g["shift_flag"], "device_id"]))),
                "median_abs_excursion_sigma": float(np.nanmedian(np.abs(an["excursion_sigma"]))) if len(an) else np.nan,
                "expected_false_alarms": float(np.nansum(an["drift_false_alarm_designed"])
                                               + np.nansum(an["cusum_false_alarm_designed"])) if len(an) else 0.0,
            })
        return pd.DataFrame(rows, columns=SUMMARY_COLUMNS)

    def warnings(self) -> list[dict]:
        """One dict per flagged series: kind ('drift' | 'shift'), device, coefficient, run and a sentence."""
        out = []
        for s in self.series:
            k = s.key
            name = f"{k.get('sensor')} {k.get('axis')} {k.get('coefficient')} ({k.get('method')})"
            if s.drift_flag:
                tr = s.trend
                out.append({"kind": "drift", **k, "run_id": s.run_ids[-1],
                            "message": f"{k.get('device_id')}: {name} drifted {tr.excursion:+.4g} {s.unit} "
                                       f"({tr.excursion / s.sigma:+.1f} sigma) from run {s.run_ids[0]} to run "
                                       f"{s.run_ids[-1]}; slope {tr.slope_per_day:+.3g} +/- "
                                       f"{tr.slope_stderr_per_day:.2g} {s.unit}/day"})
            if s.shift_flag:
                out.append({"kind": "shift", **k, "run_id": s.shift_run_id,
                            "message": f"{k.get('device_id')}: {name} shifted {s.step.size:+.4g} +/- "
                                       f"{s.step.size_stderr:.2g} {s.unit} ({s.step.size / s.sigma:+.1f} sigma) at "
                                       f"run {s.shift_run_id} (CUSUM alarm at run {s.run_ids[s.cusum.alarm_index]})"})
        return out

    # ------------------------------------------------------------------ plots
    def families(self) -> list[tuple[str, str]]:
        return sorted({(s.key.get("sensor", ""), s.key.get("coefficient", "")) for s in self.series})

    def plot_family_png(self, sensor: str, coefficient: str) -> bytes:
        """Control chart of one family: standardized deviation (x - centre)/sigma per run, one line per device
        (and method), one panel per axis, +/- limit lines; runs beyond limits circled red, shift runs as red
        triangles, drifting series dashed with their trend."""
        from matplotlib import colormaps

        from assets_lib.plotting import figure, png

        ser = [s for s in self.series if s.key.get("sensor") == sensor and s.key.get("coefficient") == coefficient]
        axes_present = sorted({s.key.get("axis", "") for s in ser}) or [""]
        labels = sorted({(s.key.get("device_id"), s.key.get("method")) for s in ser})
        # room on the right for the legend (outside the axes), as bbox_inches="tight" gave without a second draw
        legend_in = 0.3 + 0.065 * max((len(f"{d} ({m}) [drift+shift]") for d, m in labels), default=0)
        fig, axs = figure(len(axes_present), 1, figsize=(8.5 + legend_in, 2.7 * len(axes_present)), dpi=100,
                          sharex=True, margins_in=(1.1, legend_in, 0.55, 0.4), hspace=0.15)
        tab10 = colormaps["tab10"]
        colors = {lab: tab10(i % 10) for i, lab in enumerate(labels)}
        for ax, a in zip(axs[:, 0], axes_present):
            lim = self.config.limit_sigma
            ax.axhspan(-lim, lim, color="0.93", zorder=0)
            for yv in (-lim, lim):
                ax.axhline(yv, color="0.45", lw=0.9, ls="--")
            ax.axhline(0, color="0.6", lw=0.8)
            for s in [s for s in ser if s.key.get("axis") == a]:
                lab = (s.key.get("device_id"), s.key.get("method"))
                c = colors[lab]
                t = np.asarray(s.t_days)
                z = s.z_scores()
                ax.plot(t, z, "o-" if not s.drift_flag else "o--", color=c, ms=4, lw=1.3,
                        label=f"{lab[0]} ({lab[1]})" + (f" [{s.status}]" if s.flagged else ""))
                if s.trend is not None and s.drift_flag:
                    tt = np.linspace(t.min(), t.max(), 20)
                    sig_t = np.interp(tt, t, np.asarray(s.sigmas))
                    ax.plot(tt, (s.trend.line(tt) - s.center) / sig_t, "-", color=c, lw=2.2, alpha=0.5)
                b = np.asarray(s.beyond_limits)
                if b.any():
                    ax.plot(t[b], z[b], "o", mfc="none", mec="red", ms=11, mew=2)
                if s.shift_flag:
                    i = s.step.index
                    ax.plot([t[i]], [z[i]], "^", color="red", ms=11)
            ax.set_ylabel(f"{sensor} {a} {coefficient}\n(x - mean) / sigma")
            ax.grid(alpha=0.3)
            if ax.get_legend_handles_labels()[0]:
                ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0))
        axs[-1, 0].set_xlabel("days since the device's first run")
        axs[0, 0].set_title(f"Fleet drift: {sensor} {coefficient} (red circle: beyond +/-{self.config.limit_sigma:g} "
                            "sigma; red triangle: abrupt shift; dashed: drift)", fontsize=9)
        return png(fig)

    def plots(self) -> dict[str, bytes]:
        """One PNG per coefficient family, named ``drift_<sensor>_<coefficient>``."""
        return {f"drift_{s}_{c}": self.plot_family_png(s, c) for s, c in self.families()}


SERIES_COLUMNS = [
    *SERIES_KEYS, "unit", "n_runs", "first_run_id", "last_run_id", "span_days", "center", "sigma", "sigma_turnon",
    "sigma_source", "sigma_dof", "slope_per_day", "slope_stderr_per_day", "slope_ci_low", "slope_ci_high", "confidence",
    "excursion", "excursion_stderr", "excursion_sigma", "trend_z", "chi2", "dof", "cusum_max", "cusum_alarm_run_id",
    "shift_run_id", "shift_size", "shift_size_stderr", "n_beyond_limits", "drift_flag", "shift_flag", "status",
    "drift_false_alarm_designed", "cusum_false_alarm_designed",
]
POINT_COLUMNS = [
    *SERIES_KEYS, "run_id", "start_time_utc", "t_days", "value", "stderr", "sigma", "unit", "center", "lcl", "ucl",
    "z", "trend", "trend_ci_low", "trend_ci_high", "cusum_plus", "cusum_minus", "beyond_limits", "shift_here",
    "status",
]
SUMMARY_COLUMNS = [
    "family", "n_devices", "n_series", "n_analyzed", "n_drift", "n_shift", "n_points_beyond_limits",
    "devices_flagged", "median_abs_excursion_sigma", "expected_false_alarms",
]


def fleet_drift(coefficients: pd.DataFrame, run_times: pd.DataFrame, repeatability: pd.DataFrame | None = None,
                config: DriftConfig = DriftConfig()) -> FleetDrift:
    """Every (device, sensor, axis, coefficient, method) series of a COEFFICIENT TABLE, ordered by run start time.

    ``run_times``: columns device_id, run_id, start_time_utc (ISO 8601 UTC). ``repeatability``: the repeatability
    stage's table (assets_lib.calibration.repeatability.REPEATABILITY_COLUMNS) or None.
    """
    c = coefficients
    if "observable" in c:
        c = c[c["observable"].astype(bool)]
    c = c[np.isfinite(c["value"].astype(float))]
    if config.coefficients is not None:
        c = c[c["coefficient"].isin(config.coefficients)]
    if "method" not in c:
        c = c.assign(method="")
    times = run_times[["device_id", "run_id", "start_time_utc"]].drop_duplicates(["device_id", "run_id"])
    c = c.merge(times, on=["device_id", "run_id"], how="inner")
    c = c.assign(_t=pd.to_datetime(c["start_time_utc"], utc=True))
    first = c.groupby("device_id")["_t"].transform("min")
    c = c.assign(_days=(c["_t"] - first).dt.total_seconds() / 86400.0)
    rep = turn_on_sigma_table(repeatability).set_index(list(SERIES_KEYS))
    out = []
    for key, g in c.sort_values(["_t", "run_id"]).groupby(list(SERIES_KEYS), sort=True):
        kd = dict(zip(SERIES_KEYS, key))
        sigma_t, source, dof = None, "stderr only", None
        if key in rep.index:
            r = rep.loc[[key]].iloc[0]
            rep_runs = {s for s in str(r["run_ids"]).split(",") if s}
            if rep_runs & set(g["run_id"].astype(str)):
                # in-sample: the repeatability saw these runs (and any drift in them): re-estimate it about the trend
                source = "repeatability, detrended (in-sample)"
                if len(g) >= config.in_sample_min_runs and g["_days"].nunique() > 1:
                    sigma_t, dof = detrended_turn_on_sigma(g["_days"], g["value"], g["stderr"])
                else:
                    sigma_t, dof = float(r["sigma_turnon"]) * (abs(float(g["value"].mean())) if r["relative"] else 1.0), \
                        max(len(g) - 2, 1)
            else:
                sigma_t = float(r["sigma_turnon"]) * (abs(float(g["value"].mean())) if r["relative"] else 1.0)
                source = "repeatability"
        out.append(analyze_series(
            g["_days"].to_numpy(), g["value"].to_numpy(float), g["stderr"].to_numpy(float), sigma_turnon=sigma_t,
            sigma_source=source, sigma_dof=dof, config=config, key=kd, unit=str(g["unit"].iloc[0]) if "unit" in g else "",
            run_ids=g["run_id"].astype(str).to_numpy(), start_times_utc=g["start_time_utc"].astype(str).to_numpy(),
        ))
    return FleetDrift(tuple(out), config)
