"""Plateau segmentation of a run: clock alignment, plateau cutting, outlier rejection, means with honest SEMs.

Two ways to find the plateaus of a plan (``raw_schemas.TestPlan``; plan times are on the IMU clock):

* **with a turntable log** (canonical ``time_s`` on the table clock, ``angle_rad``, ``rate_radps``,
  ``step_index``): the table clock is aligned to the IMU clock by cross-correlating the logged table rate with
  the gyro projected on the table axis (body-frame table axis ``C_b^l(t)^T a``), peak refined to a fraction of a
  sample by a parabola (seed 003: "time-align table and IMU data, then cut each 2-minute plateau"); plateaus are
  then cut where the table log says step k ran.
* **without a table log**: quiet intervals are detected in the IMU data alone (imu_tk's variance detector on the
  gyro- and accelerometer-norm, threshold a multiple of the record's own noise floor, edges refined sample by
  sample) and matched to the plan steps by a common time shift, using both timing and content (expected angular
  rate and specific-force direction); steps without a matching interval are reported.

Every window is trimmed by the step's ``settle_s`` plus a guard, and a rate plateau is cut to a whole number of
table revolutions where it is long enough (seed 000's full-revolution method: the horizontal earth rate, table
ripple, wobble and tilt sinusoids average out). Outliers are rejected with ``assets_lib.calibration.outliers`` (seed 001).
Reference inputs are averaged over exactly the kept samples (``kinematics.body_inputs``).

Standard error of a plateau mean (correlated noise). The SEM reported for a window of length T is the square
root of the Allan variance at tau = T, sigma_A^2(T) = 1/2 E[(ybar_{k+1} - ybar_k)^2] (IEEE Std 952-1997 C.1):
the scatter of a T-long mean about its neighbours. For white noise it equals sigma^2 / n exactly; for bias
instability and rate random walk it stays finite where sigma / sqrt(n) goes to zero (for a random walk it is
also the variance of the window mean about the process value at the window start, K^2 T / 3). sigma_A^2(T)
cannot be computed from one window of length T, so it is read from a noise model (IEEE 952 Annex C terms)
fitted to the EDF-weighted mean overlapping Allan variance of all plateaus of the run (tau up to T/2):
quantization and white noise always, bias instability and rate random walk only when they improve the fit by
more than ``MODEL_PENALTY`` (calibrated so that white noise gains a spurious term in <= 5 % of runs); each
plateau keeps its own white level (a plateau may be noisier, e.g. table vibration). The fit uses the residual
y - reference, so the deterministic once-per-revolution earth-rate sinusoid of a rotating axis is not taken for
noise. Measured on simulated white + flicker + random-walk noise, z-scores of plateau-mean differences have a
standard deviation of 0.95-1.15 (naive sigma/sqrt(n): 1.8-1.9); when the random walk only emerges at tau ~ T the
SEM is up to ~20 % low. Against a bias held fixed over a whole run, plateau means of a flicker-dominated channel
scatter more than sigma_A(T) (the flicker variance grows with log(run length / T)); :func:`mean_difference_variance`
gives that covariance from the same model for a fit that wants it.
"""

from __future__ import annotations

import io
from dataclasses import dataclass, field

import numpy as np
import pandas as pd
from scipy import signal
from scipy.ndimage import uniform_filter1d
from scipy.optimize import nnls

from assets_lib.sim.earth import site_gravity_mps2
from assets_lib.sim.kinematics import body_inputs, trajectory
from assets_lib.calibration.outliers import MAD_TO_SIGMA, OutlierConfig, estimate_resolution, reject_outliers_window
from raw_schemas.tables import ACCEL_COLUMNS, GYRO_COLUMNS

CHANNELS = GYRO_COLUMNS + ACCEL_COLUMNS
TWO_PI = 2.0 * np.pi
#: chi^2 gain a correlated-noise term (B or K) must bring to enter the SEM model: <= 5 % false selection on
#: white noise (calibrated by simulation on 24-39 windows of 12-60 s at 100 Hz)
MODEL_PENALTY = 6.0


# ------------------------------------------------------------------------------------------------------------
# Configuration and results
# ------------------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class DetectorConfig:
    """Quiet-interval (static / constant-rate) detector without a table log (imu_tk-style variance detector).

    ``window_s`` 1.0: imu_tk's 101-sample window at 100 Hz. ``k_threshold`` 6: imu_tk's best multiplier on its
    own Xsens set, here applied to the ``floor_quantile`` (10 %) quantile of the moving variance; for white noise
    a 1-s moving variance exceeds 6 x its 10 % quantile with negligible probability, while ramps and rotations
    exceed it by orders of magnitude. ``center`` "median" subtracts per-axis medians before taking norms (raw
    counts with large offsets); "none" keeps the norms rotation-invariant (canonical SI data).
    """

    window_s: float = 1.0
    k_threshold: float = 6.0
    floor_quantile: float = 0.1
    min_quiet_s: float = 1.0
    refine_edges: bool = True
    edge_k_sigma: float = 5.0
    merge_gap_s: float = 0.5
    use_accel: bool = True
    center: str = "none"
    static_max_rate_radps: float = np.radians(1.0)


@dataclass(frozen=True)
class SegmentationConfig:
    """Settings of :func:`segment_run`.

    Windows: ``settle_s`` of the step plus ``guard_s`` at the start, ``guard_s`` at the end (ramp edges), then
    whole table turns (``whole_revolutions``). Table log: the offset search covers every lag with at least
    ``min_overlap_fraction`` overlap, or ``clock_offset_prior_s +- max_clock_offset_s`` when that is given; a
    peak below ``min_correlation`` falls back to step centres; a table step lasting more than
    ``step_duration_tolerance_s`` (+ 2 log periods) longer or shorter than planned is flagged; the measured table
    rate (angle over the window) replaces the commanded one in ``omega_ref`` when ``use_measured_table_rate``.
    No table log: a common plan shift within ``max_plan_shift_s``; a step matches a quiet interval covering at
    least ``min_match_fraction`` of it, with the mean gyro within ``gyro_rate_abs_tol_radps`` +
    ``gyro_rate_rel_tol`` |omega| of the plan's and the mean specific force within ``accel_direction_tol_deg`` of
    its direction (wide enough for consumer-grade biases and scale errors, narrow enough to tell 45-degree
    positions apart). Windows shorter than ``min_window_s`` are flagged.
    """

    guard_s: float = 0.5
    whole_revolutions: bool = True
    use_measured_table_rate: bool = True
    max_clock_offset_s: float | None = None
    clock_offset_prior_s: float = 0.0
    min_overlap_fraction: float = 0.5
    min_correlation: float = 0.5
    step_duration_tolerance_s: float = 1.0
    max_plan_shift_s: float = 120.0
    min_match_fraction: float = 0.5
    accel_direction_tol_deg: float = 15.0
    gyro_rate_abs_tol_radps: float = np.radians(5.0)
    gyro_rate_rel_tol: float = 0.1
    min_window_s: float = 1.0
    sem_max_cluster_fraction: float = 0.5
    outliers: OutlierConfig = field(default_factory=OutlierConfig)
    detector: DetectorConfig = field(default_factory=DetectorConfig)


@dataclass(frozen=True)
class ClockAlignment:
    """Table-to-IMU clock alignment: t_table = t_imu + offset_s.

    Method ``xcorr_table_rate_parabolic+ls``: normalised cross-correlation peak, parabolic sub-sample refinement,
    then a least-squares (Gauss-Newton) delay fit. ``offset_stderr_s`` is the Cramer-Rao bound of a delay in white
    noise, sigma_e / sqrt(sum (alpha dr/dt)^2) with sigma_e the robust residual scatter: a lower bound that leaves
    out table-log interpolation and time-stamp rounding (sub-microsecond here). ``clock_drift_ppm`` compares the
    offsets of the two record halves (a clock-rate error is otherwise indistinguishable from a scale factor).
    Method ``step_centres`` (table log without rotation rate): median of table-step minus quiet-interval centres;
    ``correlation_peak`` then holds the fraction of steps agreeing within two IMU samples.
    """

    offset_s: float
    offset_stderr_s: float
    method: str
    correlation_peak: float
    clock_drift_ppm: float = np.nan
    clock_drift_stderr_ppm: float = np.nan
    n_samples: int = 0


@dataclass(frozen=True)
class QuietDetection:
    """Quiet intervals (start inclusive, end exclusive sample indices) and the motion between them."""

    intervals: pd.DataFrame
    motions: pd.DataFrame
    quiet: np.ndarray
    gyro_statistic: np.ndarray
    accel_statistic: np.ndarray
    gyro_threshold: float
    accel_threshold: float
    window_samples: int


@dataclass(frozen=True)
class PooledAllanFit:
    """IEEE 952 Annex C model fitted to all plateaus of one channel: per-plateau Q_k^2, N_k^2; shared B-term, K^2."""

    q2: np.ndarray
    n2: np.ndarray
    flicker_avar: float  # (2 ln 2 / pi) B^2
    k2: float

    def avar(self, k: int, tau_s: float | np.ndarray) -> np.ndarray:
        """IEEE Std 952-1997 eq. C.23 for plateau k: 3Q^2/tau^2 + N^2/tau + (2 ln2/pi) B^2 + K^2 tau / 3."""
        tau = np.asarray(tau_s, dtype=float)
        return 3 * self.q2[k] / tau**2 + self.n2[k] / tau + self.flicker_avar + self.k2 * tau / 3


@dataclass(frozen=True)
class SemResult:
    """Standard errors of the means of several windows of one channel, and the naive sigma/sqrt(n) for contrast."""

    sem: np.ndarray
    naive_sem: np.ndarray
    window_s: np.ndarray
    fit: PooledAllanFit


@dataclass(frozen=True)
class SegmentationResult:
    """The PLATEAU TABLE of docs/design.md plus how it was cut.

    ``window_step``: per IMU sample, the plan step whose window contains it (-1 outside); ``keep``: samples used
    in the means. ``plan_shift_s``: per step, IMU-clock start of the step minus the plan's ``start_s``.
    """

    plateaus: pd.DataFrame
    method: str
    alignment: ClockAlignment | None
    detection: QuietDetection | None
    plan_shift_s: np.ndarray
    unmatched_steps: tuple[int, ...]
    window_step: np.ndarray
    keep: np.ndarray
    noise_fits: dict
    warnings: tuple[str, ...] = ()


# ------------------------------------------------------------------------------------------------------------
# Standard error of the mean under correlated noise
# ------------------------------------------------------------------------------------------------------------
def overlapping_avar(x: np.ndarray, m_list) -> tuple[np.ndarray, np.ndarray]:
    """NIST SP 1065 eq. 11 (overlapping Allan variance) of rate samples ``x`` at cluster sizes ``m_list``.

    Returns (avar, n_terms) per m; avar in units of x^2.
    """
    x = np.asarray(x, dtype=float)
    c = np.concatenate(([0.0], np.cumsum(x - x.mean())))
    out, terms = [], []
    for m in m_list:
        ybar = (c[m:] - c[:-m]) / m
        d = ybar[m:] - ybar[:-m]
        out.append(0.5 * np.mean(d * d) if d.size else np.nan)
        terms.append(d.size)
    return np.asarray(out), np.asarray(terms)


def fit_pooled_allan(segments: list[np.ndarray], dt_s: float, max_cluster_fraction: float = 0.5) -> PooledAllanFit:
    """IEEE Std 952-1997 Annex C fitted to the EDF-weighted mean Allan variance of all windows of one channel.

    Each window contributes its overlapping Allan variance at octave cluster sizes and at the median window's
    ``max_cluster_fraction * n`` (the longest tau inside a window); the EDF-weighted average over windows is
    fitted with white (N), quantization (Q) and, when they lower chi^2 by more than ``MODEL_PENALTY`` each, bias
    instability (B) and rate random walk (K), by non-negative least squares in relative error (weights
    sqrt(EDF), EDF ~ (n - 2m + 1) / m, re-weighted by the model). Each window's Q^2, N^2 are the pooled values
    scaled by the median ratio of its own short-tau (m <= 16) Allan variance to the model (a noisier plateau keeps
    its own white level); B and K are shared.
    """
    p = len(segments)
    ns = np.array([len(s) for s in segments])
    valid = np.flatnonzero(ns >= 4)
    if valid.size == 0:
        return PooledAllanFit(np.zeros(p), np.zeros(p), 0.0, 0.0)
    caps = np.maximum(1, (max_cluster_fraction * ns[valid]).astype(int))
    grid = np.unique(np.concatenate([2 ** np.arange(int(np.log2(caps.max())) + 1), [int(np.median(caps))]]))
    av = np.full((p, grid.size), np.nan)
    edf = np.zeros((p, grid.size))
    for k, cap in zip(valid, caps):
        sel = grid <= cap
        a, _ = overlapping_avar(segments[k], grid[sel])
        av[k, sel] = a
        edf[k, sel] = np.maximum(1.0, (ns[k] - 2 * grid[sel] + 1) / grid[sel])
    edf = np.where(np.isfinite(av) & (av > 0), edf, 0.0)
    e_sum = edf.sum(axis=0)
    ok = e_sum > 0
    pooled = np.nansum(np.where(edf > 0, av, 0.0) * edf, axis=0)[ok] / e_sum[ok]
    tau = grid[ok] * dt_s
    a_mat = np.column_stack([3.0 / tau**2, 1.0 / tau, np.ones_like(tau), tau / 3.0])
    w = np.sqrt(e_sum[ok])
    best = None
    for cols in ((0, 1), (0, 1, 2), (0, 1, 3), (0, 1, 2, 3)):
        coef, chi2 = _irls_nnls(a_mat[:, cols], pooled, w)
        score = chi2 + MODEL_PENALTY * (len(cols) - 2)
        if best is None or score < best[0]:
            full = np.zeros(4)
            full[list(cols)] = coef
            best = (score, full)
    q2, n2, fl, k2 = best[1]
    model = a_mat @ best[1]
    short = grid[ok] <= 16
    scale = np.ones(p)
    for k in valid:
        r = av[k, ok][short] / model[short]
        r = r[np.isfinite(r)]
        if r.size:
            scale[k] = float(np.median(r))
    return PooledAllanFit(scale * q2, scale * n2, float(fl), float(k2))


def _irls_nnls(a_mat: np.ndarray, y: np.ndarray, w: np.ndarray, passes: int = 3) -> tuple[np.ndarray, float]:
    """Non-negative least squares in relative error, weights sqrt(EDF)/model re-evaluated from the fit."""
    model = y.copy()
    for _ in range(passes):
        aw = a_mat * (w / model)[:, None]
        scale = np.linalg.norm(aw, axis=0)
        scale[scale == 0] = 1.0
        coef, _ = nnls(aw / scale, y * w / model, maxiter=50 * a_mat.shape[1])
        coef = coef / scale
        model = np.maximum(a_mat @ coef, 1e-300)
    chi2 = 0.5 * float(np.sum((w * (y - model) / model) ** 2))  # var(avar_hat / avar) ~ 2 / EDF
    return coef, chi2


def _diff_transfer2(f: np.ndarray, t_a: float, c_a: float, t_r: float, c_r: float) -> np.ndarray:
    """|H_A(f) - H_R(f)|^2 of the difference of two window means (H_W = sinc(pi f T_W) exp(-2 pi i f c_W))."""
    sa = np.sinc(f * t_a)
    sr = np.sinc(f * t_r)
    return sa * sa + sr * sr - 2 * sa * sr * np.cos(TWO_PI * f * (c_a - c_r))


def mean_difference_variance(fit: PooledAllanFit, k: int, t_a: float, c_a: float, t_r: float, c_r: float,
                             rate_hz: float, n_grid: int = 4000) -> float:
    """Var(ybar_A - ybar_R) of two window means (lengths t_a, t_r, centres c_a, c_r) under the model of window k.

    IEEE Std 952-1997 Annex C two-sided rate PSDs (as ``assets_lib.sim.noise``): white N^2, flicker B^2/(2 pi f),
    random walk K^2/(2 pi f)^2; Var = int S(f) |H_A - H_R|^2 df. White part in closed form N^2 (1/T_A - 1/T_R)
    (A inside R), quantization as its Allan value 3 Q^2 / T_A^2. For a fit that wants the covariance of plateau
    means (e.g. each plateau against the run mean, or two distant plateaus) rather than the local SEM.
    """
    var = 3 * fit.q2[k] / t_a**2 + fit.n2[k] * max(1.0 / t_a - (1.0 / t_r if t_r > 0 else 0.0), 0.0)
    b2 = fit.flicker_avar * np.pi / (2 * np.log(2))
    if b2 > 0 or fit.k2 > 0:
        f = np.geomspace(1e-4 / max(t_r, t_a), 0.5 * rate_hz, n_grid)
        h2 = _diff_transfer2(f, t_a, c_a, t_r, c_r)
        u = np.log(f)
        if b2 > 0:
            var += b2 / np.pi * np.trapezoid(h2, u)
        if fit.k2 > 0:
            var += fit.k2 / (2 * np.pi**2) * np.trapezoid(h2 / f, u)
    return float(var)


def plateau_sem(segments: list[np.ndarray], dt_s: float, max_cluster_fraction: float = 0.5) -> SemResult:
    """IEEE Std 952-1997 C.1: SEM_k^2 = sigma_A^2(T_k) of the pooled Annex C model, T_k = n_k dt (module docstring).

    ``segments``: the residual samples (y - reference) of each window of one channel, in run order.
    """
    fit = fit_pooled_allan(segments, dt_s, max_cluster_fraction)
    n = np.array([len(s) for s in segments], dtype=float)
    tk = n * dt_s
    sem = np.array([np.sqrt(fit.avar(k, tk[k])) if n[k] >= 4 else np.nan for k in range(len(segments))])
    naive = np.array([np.std(s, ddof=1) / np.sqrt(len(s)) if len(s) > 1 else np.nan for s in segments])
    return SemResult(sem, naive, tk, fit)


# ------------------------------------------------------------------------------------------------------------
# Quiet-interval detection (no table log)
# ------------------------------------------------------------------------------------------------------------
def _moving_variance(x: np.ndarray, w: int) -> np.ndarray:
    x = x - np.median(x)
    m = uniform_filter1d(x, w, mode="nearest")
    m2 = uniform_filter1d(x * x, w, mode="nearest")
    return np.maximum(m2 - m * m, 0.0)


def _runs(mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    d = np.diff(np.concatenate(([0], mask.astype(np.int8), [0])))
    return np.flatnonzero(d == 1), np.flatnonzero(d == -1)


def _robust_center_scale(x: np.ndarray, res: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    c = np.median(x, axis=0)
    s = MAD_TO_SIGMA * np.median(np.abs(x - c), axis=0)
    return c, np.maximum(np.maximum(s, res), 1e-300)


def detect_quiet_intervals(
    t_s: np.ndarray, gyro: np.ndarray, accel: np.ndarray | None = None, config: DetectorConfig = DetectorConfig()
) -> QuietDetection:
    """imu_tk static detector (Tedaldi et al. ICRA 2014 sec. IV-A): moving variance vs k x noise floor, min duration.

    Statistic: moving variance (centred, ``window_s``) of |gyro| and |accel| (norms are unchanged by the rotation
    of a constant-magnitude vector, so constant-rate plateaus are quiet too). Threshold: ``k_threshold`` x the
    ``floor_quantile`` quantile of each statistic. Edges are then refined sample by sample: a quiet run ends where a
    sample leaves the run's median by more than ``edge_k_sigma`` robust sigmas on any axis (within one window of
    the coarse edge). Runs separated by less than ``merge_gap_s`` with the same median are merged.
    """
    cfg = config
    t = np.asarray(t_s, dtype=float)
    g = np.asarray(gyro, dtype=float)
    a = None if accel is None or not cfg.use_accel else np.asarray(accel, dtype=float)
    n = t.size
    dt = float(np.median(np.diff(t)))
    w = max(3, int(round(cfg.window_s / dt)) | 1)
    if cfg.center == "median":
        g = g - np.median(g, axis=0)
        a = None if a is None else a - np.median(a, axis=0)
    elif cfg.center != "none":
        raise ValueError(f"center must be 'none' or 'median', not {cfg.center!r}")

    def stat_and_threshold(v):
        s = _moving_variance(np.linalg.norm(v, axis=1), w)
        pos = s[s > 0]
        floor = np.quantile(pos, cfg.floor_quantile) if pos.size else 0.0
        res = [estimate_resolution(v[:, j]) for j in range(3)]
        q = max([r for r in res if r] or [0.0])
        floor = max(floor, q * q / 12.0, np.finfo(float).tiny)
        return s, cfg.k_threshold * floor

    sg, thr_g = stat_and_threshold(g)
    quiet = sg < thr_g
    if a is not None:
        sa, thr_a = stat_and_threshold(a)
        quiet &= sa < thr_a
    else:
        sa, thr_a = np.zeros(n), np.inf
    starts, ends = _runs(quiet)

    both = g if a is None else np.column_stack([g, a])
    res_all = np.array([estimate_resolution(both[:, j]) or 0.0 for j in range(both.shape[1])])
    if cfg.refine_edges and starts.size:
        new_s, new_e = [], []
        for s0, e0 in zip(starts, ends):
            if e0 - s0 < 3:
                continue
            c, sc = _robust_center_scale(both[s0:e0], res_all)
            lo = max(0, s0 - w)
            hi = min(n, s0 + w, e0)
            bad = np.flatnonzero((np.abs(both[lo:hi] - c) > cfg.edge_k_sigma * sc).any(axis=1))
            s1 = lo + bad[-1] + 1 if bad.size else lo
            lo2 = max(s1, e0 - w)
            hi2 = min(n, e0 + w)
            bad = np.flatnonzero((np.abs(both[lo2:hi2] - c) > cfg.edge_k_sigma * sc).any(axis=1))
            e1 = lo2 + bad[0] if bad.size else hi2
            if e1 > s1:
                new_s.append(s1)
                new_e.append(e1)
        # refined runs may now touch or overlap: resolve in order
        starts, ends = [], []
        for s1, e1 in zip(new_s, new_e):
            if ends and s1 < ends[-1]:
                s1 = ends[-1]
            if e1 > s1:
                starts.append(s1)
                ends.append(e1)
        starts, ends = np.asarray(starts, int), np.asarray(ends, int)
    # merge runs split by a short disturbance when both sides agree
    if starts.size > 1:
        ms, me = [int(starts[0])], [int(ends[0])]
        for s1, e1 in zip(starts[1:], ends[1:]):
            gap = t[s1] - t[me[-1] - 1] - dt
            if gap <= cfg.merge_gap_s:
                c1, sc1 = _robust_center_scale(both[ms[-1] : me[-1]], res_all)
                c2, sc2 = _robust_center_scale(both[s1:e1], res_all)
                if np.all(np.abs(c1 - c2) <= cfg.edge_k_sigma * np.maximum(sc1, sc2)):
                    me[-1] = int(e1)
                    continue
            ms.append(int(s1))
            me.append(int(e1))
        starts, ends = np.asarray(ms), np.asarray(me)
    if starts.size:
        dur = t[ends - 1] - t[starts] + dt
        ok = dur >= cfg.min_quiet_s
        starts, ends = starts[ok], ends[ok]
    quiet_final = np.zeros(n, bool)
    rows = []
    for s1, e1 in zip(starts, ends):
        quiet_final[s1:e1] = True
        gm = g[s1:e1].mean(axis=0)
        row = {
            "start_index": int(s1), "end_index": int(e1), "t_start_s": float(t[s1]), "t_end_s": float(t[e1 - 1]),
            "duration_s": float(t[e1 - 1] - t[s1] + dt), "n_samples": int(e1 - s1),
            "gyro_x_mean": gm[0], "gyro_y_mean": gm[1], "gyro_z_mean": gm[2], "gyro_norm_mean": float(np.linalg.norm(gm)),
        }
        if a is not None:
            am = a[s1:e1].mean(axis=0)
            row.update({"accel_x_mean": am[0], "accel_y_mean": am[1], "accel_z_mean": am[2]})
        row["kind"] = "static" if row["gyro_norm_mean"] <= cfg.static_max_rate_radps else "rate"
        rows.append(row)
    intervals = pd.DataFrame(rows)
    mrows = []
    for i in range(len(starts) - 1):
        s1, e1 = int(ends[i]), int(starts[i + 1])
        bias = 0.5 * (g[starts[i] : ends[i]].mean(axis=0) + g[starts[i + 1] : ends[i + 1]].mean(axis=0))
        ang = ((g[s1:e1] - bias) * np.gradient(t)[s1:e1, None]).sum(axis=0)
        mrows.append({
            "start_index": s1, "end_index": e1, "t_start_s": float(t[s1]), "t_end_s": float(t[e1 - 1]),
            "duration_s": float(t[e1 - 1] - t[s1] + dt),
            "angle_x": ang[0], "angle_y": ang[1], "angle_z": ang[2], "angle_norm": float(np.linalg.norm(ang)),
        })
    motions = pd.DataFrame(mrows)
    return QuietDetection(intervals, motions, quiet_final, sg, sa, float(thr_g), float(thr_a), w)


# ------------------------------------------------------------------------------------------------------------
# Clock alignment (table log)
# ------------------------------------------------------------------------------------------------------------
def _uniform(t: np.ndarray, y: np.ndarray, dt: float) -> tuple[float, np.ndarray]:
    n = int(np.floor((t[-1] - t[0]) / dt)) + 1
    grid = t[0] + dt * np.arange(n)
    return float(t[0]), np.interp(grid, t, y)


def _table_axis_body(plan, t_s: np.ndarray, chunk: int = 200_000) -> np.ndarray:
    """Body-frame table axis u_b(t) = C_b^l(t)^T a along the plan's kinematics (seed 000 eq. 3-5)."""
    axis = np.asarray(plan.table_axis_level, dtype=float)
    out = np.empty((t_s.size, 3))
    for i in range(0, t_s.size, chunk):
        tr = trajectory(plan, t_s[i : i + chunk])
        out[i : i + chunk] = np.einsum("nji,j->ni", tr.c_b2l, axis)
    return out


def _xcorr_offset(
    t_imu: np.ndarray, g_proj: np.ndarray, t_tab: np.ndarray, r_tab: np.ndarray, dt: float, cfg: SegmentationConfig,
    prior: float | None = None, halfwidth: float | None = None,
) -> tuple[float, float, float]:
    """Normalised cross-correlation of table rate vs projected gyro; parabolic sub-sample peak. -> (offset, rho, lag)."""
    t0, g = _uniform(t_imu, g_proj, dt)
    tau0, r = _uniform(t_tab, r_tab, dt)
    g = g - g.mean()
    r = r - r.mean()
    z = signal.correlate(r, g, mode="full", method="fft")
    lags = signal.correlation_lags(r.size, g.size, mode="full")
    ng, nr = g.size, r.size
    cg = np.concatenate(([0.0], np.cumsum(g * g)))
    cr = np.concatenate(([0.0], np.cumsum(r * r)))
    n_lo = np.maximum(0, -lags)
    n_hi = np.minimum(ng, nr - lags)
    overlap = n_hi - n_lo
    ok = overlap >= cfg.min_overlap_fraction * min(ng, nr)
    eg = np.where(ok, cg[np.clip(n_hi, 0, ng)] - cg[np.clip(n_lo, 0, ng)], np.nan)
    er = np.where(ok, cr[np.clip(n_hi + lags, 0, nr)] - cr[np.clip(n_lo + lags, 0, nr)], np.nan)
    with np.errstate(invalid="ignore", divide="ignore"):
        rho = z / np.sqrt(eg * er)
    offsets = tau0 - t0 + lags * dt
    if prior is not None and halfwidth is not None:
        ok &= np.abs(offsets - prior) <= halfwidth
    rho = np.where(ok & np.isfinite(rho), rho, -np.inf)
    i = int(np.argmax(rho))
    peak = float(rho[i])
    frac = 0.0
    if 0 < i < rho.size - 1 and np.isfinite(rho[i - 1]) and np.isfinite(rho[i + 1]):
        den = rho[i - 1] - 2 * rho[i] + rho[i + 1]
        if den < 0:
            frac = float(np.clip(0.5 * (rho[i - 1] - rho[i + 1]) / den, -0.5, 0.5))
    return float(offsets[i] + frac * dt), peak, float(lags[i] + frac)


def _refine_delay(t_imu, g_proj, t_tab, r_tab, offset, iterations: int = 4) -> float:
    """Least-squares delay: Gauss-Newton on g(t) = alpha r(t + offset) + beta from the correlation estimate.

    Samples whose residual exceeds 5 robust sigmas (motion the table log does not show, e.g. a re-mount rotation
    about another axis) are left out of each step.
    """
    for _ in range(iterations):
        rr = np.interp(t_imu + offset, t_tab, r_tab, left=np.nan, right=np.nan)
        m = _delay_inliers(t_imu, g_proj, rr)
        if m.sum() < 10:
            break
        a_mat = np.column_stack([rr[m], np.ones(m.sum())])
        coef, *_ = np.linalg.lstsq(a_mat, g_proj[m], rcond=None)
        e = g_proj[m] - a_mat @ coef
        deriv = coef[0] * np.gradient(rr[m], t_imu[m])
        den = np.sum(deriv * deriv)
        if den <= 0:
            break
        step = float(np.sum(e * deriv) / den)
        offset += step
        if abs(step) < 1e-12:
            break
    return offset


def _delay_inliers(t_imu, g_proj, rr) -> np.ndarray:
    m = np.isfinite(rr)
    if m.sum() < 10:
        return m
    a_mat = np.column_stack([rr[m], np.ones(m.sum())])
    coef, *_ = np.linalg.lstsq(a_mat, g_proj[m], rcond=None)
    e = g_proj[m] - a_mat @ coef
    sig = MAD_TO_SIGMA * np.median(np.abs(e - np.median(e)))
    out = m.copy()
    out[m] = np.abs(e - np.median(e)) <= 5 * sig if sig > 0 else True
    return out


def _delay_crlb(t_imu, g_proj, t_tab, r_tab, offset, dt) -> float:
    """Cramer-Rao bound of a delay in white noise (Kay, Fundamentals of Statistical Signal Processing I, eq. 3.18)."""
    rr = np.interp(t_imu + offset, t_tab, r_tab, left=np.nan, right=np.nan)
    m = _delay_inliers(t_imu, g_proj, rr)
    if m.sum() < 10:
        return np.nan
    a_mat = np.column_stack([rr[m], np.ones(m.sum())])
    coef, *_ = np.linalg.lstsq(a_mat, g_proj[m], rcond=None)
    e = g_proj[m] - a_mat @ coef
    sig = MAD_TO_SIGMA * np.median(np.abs(e - np.median(e)))
    deriv = np.gradient(rr[m], t_imu[m])
    energy = np.sum((coef[0] * deriv) ** 2)
    return float(sig / np.sqrt(energy)) if energy > 0 else np.nan


def _table_steps(table: pd.DataFrame) -> dict[int, tuple[float, float]]:
    """[start, end) of each step on the table clock; a log sample holds until the next one (sample-and-hold)."""
    idx = table["step_index"].to_numpy()
    tt = table["time_s"].to_numpy(dtype=float)
    dtab = float(np.median(np.diff(tt))) if tt.size > 1 else 0.0
    out = {}
    for k in np.unique(idx[idx >= 0]):
        sel = np.flatnonzero(idx == k)
        i0, i1 = sel[0], sel[-1]
        out[int(k)] = (float(tt[i0]), float(tt[i1 + 1] if i1 + 1 < tt.size else tt[i1] + dtab))
    return out


def _clip_to_rails(r_tab: np.ndarray, g_proj: np.ndarray, shortfall: float = 0.9) -> np.ndarray:
    """The table rate clipped where the gyro saturates (effects.md: flat tops beyond full scale).

    A sensor whose measuring range is below the plan's rates reads flat at its rail on the fast plateaus; the
    clipped gyro then correlates better with a shifted copy of a repetitive rate sequence than with the true one
    (seen on seed 003's sequence: a consumer gyro at +-250 deg/s on a +-400 deg/s plan aligned 2989 s off). When
    the projected gyro spans less than ``shortfall`` of the table's range on a side, the reference is clipped at
    the gyro's extreme on that side, so both signals saturate alike; otherwise it is returned unchanged.
    """
    lo, hi = float(np.min(g_proj)), float(np.max(g_proj))
    r_lo, r_hi = float(np.min(r_tab)), float(np.max(r_tab))
    clip_hi = hi if r_hi > 0 and hi < shortfall * r_hi else None
    clip_lo = lo if r_lo < 0 and lo > shortfall * r_lo else None
    if clip_hi is None and clip_lo is None:
        return r_tab
    return np.clip(r_tab, clip_lo, clip_hi)


def align_clocks(plan, imu: pd.DataFrame, table: pd.DataFrame, config: SegmentationConfig = SegmentationConfig()
                 ) -> ClockAlignment:
    """Seed 003 time alignment: offset (t_table = t_imu + offset) maximising corr(table rate, gyro . u_b), parabolic peak.

    Falls back to matching step centres (table ``step_index`` runs vs detected quiet intervals) when the table
    rate carries no signal (e.g. a position plan whose table log shows no rotation) or correlates poorly.
    """
    cfg = config
    t_imu = imu["time_s"].to_numpy(dtype=float)
    gyro = imu[list(GYRO_COLUMNS)].to_numpy(dtype=float)
    t_tab = table["time_s"].to_numpy(dtype=float)
    r_tab = table["rate_radps"].to_numpy(dtype=float)
    dt = float(np.median(np.diff(t_imu)))
    halfwidth = cfg.max_clock_offset_s
    prior = cfg.clock_offset_prior_s if halfwidth is not None else None
    if np.std(r_tab) > 0:
        u = _table_axis_body(plan, t_imu)
        gp = np.einsum("ni,ni->n", gyro, u)
        r_tab = _clip_to_rails(r_tab, gp)
        off, peak, _ = _xcorr_offset(t_imu, gp, t_tab, r_tab, dt, cfg, prior, halfwidth)
        if peak >= cfg.min_correlation:
            off = _refine_delay(t_imu, gp, t_tab, r_tab, off)
            se = _delay_crlb(t_imu, gp, t_tab, r_tab, off, dt)
            drift, drift_se = np.nan, np.nan
            mid_imu = 0.5 * (t_imu[0] + t_imu[-1])
            halves = []
            for sel in (t_imu < mid_imu, t_imu >= mid_imu):
                ti, gi = t_imu[sel], gp[sel]
                tsel = (t_tab >= ti[0] + off - 5 * dt) & (t_tab <= ti[-1] + off + 5 * dt)
                if tsel.sum() < 10 or ti.size < 10 or np.std(r_tab[tsel]) == 0:
                    break
                o, p, _ = _xcorr_offset(ti, gi, t_tab[tsel], r_tab[tsel], dt, cfg, off, max(10 * dt, 1.0))
                if p < cfg.min_correlation:
                    break
                o = _refine_delay(ti, gi, t_tab[tsel], r_tab[tsel], o)
                halves.append((o, _delay_crlb(ti, gi, t_tab[tsel], r_tab[tsel], o, dt), 0.5 * (ti[0] + ti[-1])))
            if len(halves) == 2:
                (o1, s1, c1), (o2, s2, c2) = halves
                drift = (o2 - o1) / (c2 - c1) * 1e6
                drift_se = np.hypot(s1, s2) / (c2 - c1) * 1e6
            return ClockAlignment(off, se, "xcorr_table_rate_parabolic+ls", peak, drift, drift_se, int(t_imu.size))
    # fallback: step centres
    det = detect_quiet_intervals(t_imu, gyro, imu[list(ACCEL_COLUMNS)].to_numpy(dtype=float), cfg.detector)
    steps = _table_steps(table)
    if det.intervals.empty or not steps:
        return ClockAlignment(0.0, np.nan, "none", np.nan, n_samples=int(t_imu.size))
    qs = det.intervals["t_start_s"].to_numpy()
    qe = det.intervals["t_end_s"].to_numpy()
    qc = 0.5 * (qs + qe)
    tc = np.array([0.5 * (a + b) for a, b in steps.values()])
    cands = (tc[:, None] - qc[None, :]).ravel()
    if halfwidth is not None:
        cands = cands[np.abs(cands - cfg.clock_offset_prior_s) <= halfwidth]
    best, best_score = 0.0, -1.0
    for c in np.unique(np.round(cands, 3)):
        score = 0.0
        for a, b in steps.values():
            score += np.clip(np.minimum(qe, b - c) - np.maximum(qs, a - c), 0, None).max()
        if score > best_score + 1e-9 or (abs(score - best_score) <= 1e-9 and abs(c) < abs(best)):
            best, best_score = float(c), score
    diffs = []
    for (a, b), c_t in zip(steps.values(), tc):
        ov = np.clip(np.minimum(qe, b - best) - np.maximum(qs, a - best), 0, None)
        j = int(np.argmax(ov))
        if ov[j] > 0:
            diffs.append(c_t - qc[j])
    diffs = np.asarray(diffs)
    off = float(np.median(diffs))
    se = float(1.2533 * MAD_TO_SIGMA * np.median(np.abs(diffs - off)) / np.sqrt(diffs.size)) if diffs.size > 1 else np.nan
    se = float(np.hypot(np.nan_to_num(se), dt / np.sqrt(12.0)))  # edges are located to one IMU sample at best
    frac = float(np.mean(np.abs(diffs - off) < 2 * dt)) if diffs.size else np.nan
    return ClockAlignment(off, se, "step_centres", frac, n_samples=int(t_imu.size))


# ------------------------------------------------------------------------------------------------------------
# Plan matching without a table log
# ------------------------------------------------------------------------------------------------------------
def _expected_inputs(plan, lat: float, g: float, n_pts: int = 16) -> tuple[np.ndarray, np.ndarray]:
    tt = np.concatenate([np.linspace(s.start_s + s.settle_s, s.end_s, n_pts, endpoint=False) for s in plan.steps])
    bi = body_inputs(plan, tt, lat, g)
    n = len(plan.steps)
    return bi.omega_b_radps.reshape(n, n_pts, 3).mean(axis=1), bi.f_b_mps2.reshape(n, n_pts, 3).mean(axis=1)


def match_plan(plan, t_s: np.ndarray, gyro: np.ndarray, accel: np.ndarray, detection: QuietDetection,
               latitude_deg: float, gravity_mps2: float, config: SegmentationConfig = SegmentationConfig()):
    """Common plan-to-data time shift maximising sum_k overlap(step k shifted, quiet) x content match; per-step intervals.

    Content match: |mean gyro - expected omega| <= abs_tol + rel_tol |omega| and angle(mean accel, expected f) <=
    ``accel_direction_tol_deg``. Returns (shift_s, {step: (start_index, end_index)} of the matched quiet runs).
    """
    cfg = config
    t = np.asarray(t_s, float)
    steps = plan.steps
    w_exp, f_exp = _expected_inputs(plan, latitude_deg, gravity_mps2)
    q = detection.quiet.astype(float)
    cq = np.concatenate(([0.0], np.cumsum(q)))
    cg = np.vstack([np.zeros(3), np.cumsum(gyro * q[:, None], axis=0)])
    ca = np.vstack([np.zeros(3), np.cumsum(accel * q[:, None], axis=0)])
    cos_tol = np.cos(np.radians(cfg.accel_direction_tol_deg))
    iv = detection.intervals
    if iv.empty:
        return 0.0, {}
    qs, qe = iv["t_start_s"].to_numpy(), iv["t_end_s"].to_numpy()
    a_s = np.array([s.start_s + s.settle_s for s in steps])
    b_s = np.array([s.end_s for s in steps])

    def step_scores(shift):
        i0 = np.searchsorted(t, a_s + shift)
        i1 = np.searchsorted(t, b_s + shift)
        nq = cq[i1] - cq[i0]
        frac = nq / np.maximum(i1 - i0, 1)
        with np.errstate(invalid="ignore", divide="ignore"):
            gm = (cg[i1] - cg[i0]) / nq[:, None]
            am = (ca[i1] - ca[i0]) / nq[:, None]
            g_tol = cfg.gyro_rate_abs_tol_radps + cfg.gyro_rate_rel_tol * np.linalg.norm(w_exp, axis=1)
            g_ok = np.linalg.norm(gm - w_exp, axis=1) <= g_tol
            cosang = np.einsum("ij,ij->i", am, f_exp) / (np.linalg.norm(am, axis=1) * np.linalg.norm(f_exp, axis=1))
        a_ok = cosang >= cos_tol
        ok = (nq > 0) & g_ok & a_ok & (frac >= cfg.min_match_fraction)
        return np.where(ok, frac, 0.0), ok

    c_q = 0.5 * (qs + qe)
    c_p = 0.5 * (np.array([s.start_s for s in steps]) + b_s)
    cands = np.concatenate([(c_q[:, None] - c_p[None, :]).ravel(), (qs[:, None] - a_s[None, :]).ravel(), [0.0]])
    cands = np.unique(np.round(cands[np.abs(cands) <= cfg.max_plan_shift_s], 3))
    best, best_score = 0.0, -1.0
    for c in cands:
        sc = step_scores(c)[0].sum()
        if sc > best_score + 1e-9 or (abs(sc - best_score) <= 1e-9 and abs(c) < abs(best)):
            best, best_score = float(c), sc
    # refine: median centre difference of the matched steps whose quiet run lies inside the step + gaps
    _, ok = step_scores(best)
    diffs = []
    for k in np.flatnonzero(ok):
        ov = np.clip(np.minimum(qe, b_s[k] + best) - np.maximum(qs, a_s[k] + best), 0, None)
        j = int(np.argmax(ov))
        diffs.append(c_q[j] - c_p[k])
    if diffs:
        ref = float(np.median(diffs))
        if step_scores(ref)[0].sum() >= best_score - 1e-9:
            best = ref
    _, ok = step_scores(best)
    runs = {}
    si, ei = iv["start_index"].to_numpy(), iv["end_index"].to_numpy()
    for k in np.flatnonzero(ok):
        ov = np.clip(np.minimum(qe, b_s[k] + best) - np.maximum(qs, a_s[k] + best), 0, None)
        j = int(np.argmax(ov))
        if ov[j] > 0:
            runs[int(k)] = (int(si[j]), int(ei[j]))
    return best, runs


# ------------------------------------------------------------------------------------------------------------
# Whole revolutions
# ------------------------------------------------------------------------------------------------------------
def whole_revolution_window(a_s: float, b_s: float, angle_of_t) -> tuple[float, float, float]:
    """Seed 000 full-revolution method: the centred sub-window of [a, b] turning the table a whole number of turns.

    ``angle_of_t`` maps IMU-clock times to the (unwrapped, monotone within the step) table angle. Returns
    (start, end, revolutions); when less than one turn fits, the window is unchanged and revolutions fractional.
    """
    grid = np.linspace(a_s, b_s, 2001)
    th = angle_of_t(grid)
    sgn = 1.0 if th[-1] >= th[0] else -1.0
    th = sgn * (th - th[0])
    total = th[-1]
    q = np.floor(total / TWO_PI + 1e-9)
    if q < 1 or not np.all(np.diff(th) >= 0):
        return a_s, b_s, total / TWO_PI
    excess = total - q * TWO_PI
    a2 = float(np.interp(0.5 * excess, th, grid))
    b2 = float(np.interp(total - 0.5 * excess, th, grid))
    return a2, b2, float(q)


# ------------------------------------------------------------------------------------------------------------
# The run
# ------------------------------------------------------------------------------------------------------------
def plateau_columns() -> list[str]:
    """Column order of the PLATEAU TABLE (docs/design.md)."""
    cols = ["device_id", "run_id", "step_index", "kind", "t_start_s", "t_end_s", "n_samples", "n_rejected",
            "rejected_fraction", "commanded_rate_radps", "revolutions"]
    for ch in CHANNELS:
        cols += [f"{ch}_mean", f"{ch}_sem"]
    cols += ["temperature_degc_mean"]
    cols += [f"omega_ref_{a}_radps" for a in "xyz"] + [f"omega_earth_{a}_radps" for a in "xyz"]
    cols += [f"f_ref_{a}_mps2" for a in "xyz"] + ["flagged", "flag_reason"]
    cols += [f"{ch}_flicker_b" for ch in CHANNELS]  # run's pooled bias instability B (channel units)
    return cols


def segment_run(manifest, imu: pd.DataFrame, table: pd.DataFrame | None = None,
                config: SegmentationConfig = SegmentationConfig()) -> SegmentationResult:
    """Plateau table of one run (docs/design.md PLATEAU TABLE); seed 003 alignment, seed 000 whole turns, seed 001 outliers.

    ``n_samples`` counts the samples kept for the means; ``n_rejected`` the outliers removed from the window;
    ``rejected_fraction`` = n_rejected / (n_samples + n_rejected). SEMs per the module docstring.
    """
    cfg = config
    plan = manifest.plan
    lat = manifest.site.latitude_deg
    grav = site_gravity_mps2(manifest.site)
    t = imu["time_s"].to_numpy(dtype=float)
    y = imu[list(CHANNELS)].to_numpy(dtype=float)
    gyro, accel = y[:, :3], y[:, 3:]
    temp = np.full(t.size, np.nan)
    if "temperature_degc" in imu:
        temp = imu["temperature_degc"].to_numpy(dtype=float, na_value=np.nan)
    dt = float(np.median(np.diff(t)))
    n_steps = len(plan.steps)
    warnings: list[str] = []
    reasons: dict[int, list[str]] = {k: [] for k in range(n_steps)}
    windows: dict[int, tuple[float, float]] = {}
    shifts = np.full(n_steps, np.nan)
    alignment = None
    detection = None
    unmatched: list[int] = []
    angle_of_t = {}

    if table is not None and len(table):
        method = "table_log"
        alignment = align_clocks(plan, imu, table, cfg)
        if alignment.method == "none":
            warnings.append("clock alignment failed: offset 0 assumed")
            for k in reasons:
                reasons[k].append("table/IMU clock alignment failed (offset 0 assumed)")
        elif alignment.correlation_peak < cfg.min_correlation:
            warnings.append(f"clock alignment weak (method {alignment.method}, peak {alignment.correlation_peak:.2f})")
        off = alignment.offset_s if np.isfinite(alignment.offset_s) else 0.0
        tsteps = _table_steps(table)
        tt = table["time_s"].to_numpy(dtype=float)
        ang = np.unwrap(table["angle_rad"].to_numpy(dtype=float))
        dtab = float(np.median(np.diff(tt)))
        for k, s in enumerate(plan.steps):
            if k not in tsteps:
                continue
            a, b = tsteps[k]
            # the table log locates a step start only to within one log period: keep the plan's timing then
            shifts[k] = a - off - s.start_s if abs(a - off - s.start_s) > dtab else 0.0
            dur = b - a
            tol = cfg.step_duration_tolerance_s + 2 * dtab
            if abs(dur - s.duration_s) > tol:
                reasons[k].append(f"table log step lasts {dur:.3f} s, plan {s.duration_s:.3f} s")
            windows[k] = (a - off + s.settle_s + cfg.guard_s, b - off - cfg.guard_s)
            angle_of_t[k] = lambda x, o=off: np.interp(x + o, tt, ang)
        med_shift = float(np.nanmedian(shifts)) if np.isfinite(shifts).any() else 0.0
        for k, s in enumerate(plan.steps):
            if k not in windows:
                reasons[k].append("step missing from the table log; cut from the plan")
                shifts[k] = med_shift
                windows[k] = (s.start_s + med_shift + s.settle_s + cfg.guard_s, s.end_s + med_shift - cfg.guard_s)
    else:
        method = "imu_only"
        detection = detect_quiet_intervals(t, gyro, accel, cfg.detector)
        shift, runs = match_plan(plan, t, gyro, accel, detection, lat, grav, cfg)
        shifts[:] = shift if abs(shift) > dt else 0.0  # data agree with the plan's timing within a sample
        for k, s in enumerate(plan.steps):
            if k not in runs:
                unmatched.append(k)
                reasons[k].append("unmatched: no quiet interval matches this step (timing and expected inputs)")
                continue
            i0, i1 = runs[k]
            a = max(s.start_s + shift + s.settle_s, t[i0]) + cfg.guard_s
            b = min(s.end_s + shift, t[i1 - 1] + dt) - cfg.guard_s
            windows[k] = (a, b)
        if unmatched:
            warnings.append(f"{len(unmatched)} plan steps unmatched: {unmatched}")

    # whole revolutions, sample selection, outliers, reference inputs
    window_step = np.full(t.size, -1, dtype=np.int64)
    keep = np.zeros(t.size, bool)
    res = [estimate_resolution(y[:, j]) for j in range(6)]
    per_step = {}
    for k, s in enumerate(plan.steps):
        if k not in windows:
            continue
        a, b = windows[k]
        rate = np.radians(s.table_rate_dps)
        revs = 0.0
        r_meas = np.nan
        if s.kind == "rate" and rate != 0.0 and b > a:
            aot = angle_of_t.get(k) or (lambda x, r=rate: r * x)
            if cfg.whole_revolutions:
                a, b, revs = whole_revolution_window(a, b, aot)
            else:
                revs = abs(aot(np.array([b]))[0] - aot(np.array([a]))[0]) / TWO_PI
            if k in angle_of_t:
                r_meas = float((aot(np.array([b]))[0] - aot(np.array([a]))[0]) / (b - a))
        i0, i1 = np.searchsorted(t, a), np.searchsorted(t, b)
        if i1 - i0 < 2 or (b - a) < cfg.min_window_s:
            reasons[k].append(f"window too short after settle/guard trimming ({max(b - a, 0):.2f} s)")
            continue
        idx = np.arange(i0, i1)
        window_step[idx] = k
        t_plan = np.clip(t[idx] - shifts[k], s.start_s, np.nextafter(s.end_s, -np.inf))
        per_step[k] = dict(idx=idx, t_plan=t_plan, revs=revs, r_meas=r_meas, a=a, b=b)
    # reference inputs of every window in one kinematics evaluation, then the outliers per window
    if per_step:
        ks_all = sorted(per_step)
        bi = body_inputs(plan, np.concatenate([per_step[k]["t_plan"] for k in ks_all]), lat, grav)
        u_all = np.einsum("nji,j->ni", bi.trajectory.c_b2l, np.asarray(plan.table_axis_level, float))
        pos = 0
        for k in ks_all:
            d = per_step[k]
            sl = slice(pos, pos + d["idx"].size)
            pos += d["idx"].size
            d.update(w=bi.omega_b_radps[sl], we=bi.omega_earth_b_radps[sl], f=bi.f_b_mps2[sl], u=u_all[sl])
            d["ref"] = np.column_stack([d["w"], d["f"]])
            wo = reject_outliers_window(t[d["idx"]], y[d["idx"]] - d["ref"], cfg.outliers, res)
            keep[d["idx"]] = wo.keep
            if wo.flagged:
                reasons[k].append(wo.flag_reason)
            d["wo"] = wo

    # pooled noise model per channel and the SEMs
    ks = sorted(per_step)
    noise_fits = {}
    sems = {k: np.full(6, np.nan) for k in ks}
    for j, ch in enumerate(CHANNELS):
        segs = [(y[per_step[k]["idx"], j] - per_step[k]["ref"][:, j])[per_step[k]["wo"].keep] for k in ks]
        if not segs:
            continue
        sr = plateau_sem(segs, dt, cfg.sem_max_cluster_fraction)
        noise_fits[ch] = sr.fit
        for i, k in enumerate(ks):
            sems[k][j] = sr.sem[i]

    rows = []
    for k, s in enumerate(plan.steps):
        row = {c: np.nan for c in plateau_columns()}
        row.update(device_id=manifest.device.id, run_id=manifest.run_id, step_index=k, kind=s.kind,
                   commanded_rate_radps=float(np.radians(s.table_rate_dps)), n_samples=0, n_rejected=0)
        if k in per_step:
            d = per_step[k]
            kp = d["wo"].keep
            idx = d["idx"][kp]
            w_e = d["we"][kp].mean(axis=0)
            if s.kind == "rate" and cfg.use_measured_table_rate and np.isfinite(d["r_meas"]):
                w_ref = w_e + d["r_meas"] * d["u"][kp].mean(axis=0)
            else:
                w_ref = d["w"][kp].mean(axis=0)
            f_ref = d["f"][kp].mean(axis=0)
            row.update(
                t_start_s=float(t[d["idx"][0]]), t_end_s=float(t[d["idx"][-1]]), n_samples=int(kp.sum()),
                n_rejected=int(d["wo"].n_rejected), rejected_fraction=float(d["wo"].rejected_fraction),
                revolutions=float(d["revs"]),
            )
            means = y[idx].mean(axis=0)
            for j, ch in enumerate(CHANNELS):
                row[f"{ch}_mean"] = float(means[j])
                row[f"{ch}_sem"] = float(sems[k][j])
            tk = temp[idx]
            row["temperature_degc_mean"] = float(np.nanmean(tk)) if np.isfinite(tk).any() else np.nan
            for i, ax in enumerate("xyz"):
                row[f"omega_ref_{ax}_radps"] = float(w_ref[i])
                row[f"omega_earth_{ax}_radps"] = float(w_e[i])
                row[f"f_ref_{ax}_mps2"] = float(f_ref[i])
        row["flagged"] = bool(reasons[k])
        row["flag_reason"] = "; ".join(reasons[k])
        rows.append(row)
    df = pd.DataFrame(rows, columns=plateau_columns())
    df["step_index"] = df["step_index"].astype(np.int64)
    df["n_samples"] = df["n_samples"].astype(np.int64)
    df["n_rejected"] = df["n_rejected"].astype(np.int64)
    df["flagged"] = df["flagged"].astype(bool)
    for ch, fit in noise_fits.items():  # IEEE 952 C.3: flicker plateau (2 ln2 / pi) B^2 -> B, shared by the run
        df[f"{ch}_flicker_b"] = float(np.sqrt(max(fit.flicker_avar, 0.0) * np.pi / (2 * np.log(2))))
    return SegmentationResult(df, method, alignment, detection, shifts, tuple(unmatched), window_step, keep,
                              noise_fits, tuple(warnings))


# ------------------------------------------------------------------------------------------------------------
# Figure for asset metadata
# ------------------------------------------------------------------------------------------------------------
def plot_segmentation_png(imu: pd.DataFrame, result: SegmentationResult, title: str = "", max_points: int = 20000,
                          dpi: int = 90) -> bytes:
    """PNG of the run's gyro [deg/s] and accel [m/s^2] traces with the plateau windows shaded (red: flagged)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    t = imu["time_s"].to_numpy(dtype=float)
    step = max(1, t.size // max_points)
    fig = Figure(figsize=(11, 5.5), dpi=dpi)
    FigureCanvasAgg(fig)
    ax_g, ax_a = fig.subplots(2, 1, sharex=True)
    panels = ((ax_g, GYRO_COLUMNS, 180 / np.pi, "gyro [deg/s]"), (ax_a, ACCEL_COLUMNS, 1.0, "accel [m/s^2]"))
    for ax, cols, scale, label in panels:
        for c, color in zip(cols, ("tab:red", "tab:green", "tab:blue")):
            ax.plot(t[::step], imu[c].to_numpy(dtype=float)[::step] * scale, lw=0.6, color=color, label=c.split("_")[1])
        ax.set_ylabel(label)
        ax.legend(loc="upper right", fontsize=7, ncol=3)
        for _, r in result.plateaus.iterrows():
            if np.isfinite(r["t_start_s"]):
                ax.axvspan(r["t_start_s"], r["t_end_s"], color="tab:red" if r["flagged"] else "tab:olive", alpha=0.18, lw=0)
    for _, r in result.plateaus.iterrows():
        if np.isfinite(r["t_start_s"]):
            ax_g.text(0.5 * (r["t_start_s"] + r["t_end_s"]), 1.0, str(r["step_index"]), transform=ax_g.get_xaxis_transform(),
                      ha="center", va="bottom", fontsize=6)
    ax_a.set_xlabel("IMU time [s]")
    fig.suptitle(title or f"segmentation ({result.method}); shaded: plateau windows, red = flagged", fontsize=9)
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png")
    return buf.getvalue()
