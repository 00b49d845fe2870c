"""Table-to-IMU clock alignment from a turntable log ([SEED003]: time-align table and IMU data first).

The logged table rate is cross-correlated with the gyro projected on the table axis (body-frame table axis
C_b^l(t)^T a), the peak refined to a fraction of a sample by a parabola, then by a least-squares delay fit;
plateaus are then cut where the table log says step k ran.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pandas as pd
from scipy import signal

from assets_lib.calibration.outliers import MAD_TO_SIGMA
from assets_lib.calibration.segmentation.config import SegmentationConfig
from assets_lib.calibration.segmentation.detection import detect_quiet_intervals
from assets_lib.sim.kinematics import trajectory
from raw_schemas.tables import ACCEL_COLUMNS, GYRO_COLUMNS


@dataclass(frozen=True)
class ClockAlignment:
    """Table-to-IMU clock alignment: t_table = t_imu + offset_s.

    Method ``xcorr_table_rate_parabolic+ls``: normalised cross-correlation peak, parabolic sub-sample refinement,
    then a least-squares (Gauss-Newton) delay fit. ``offset_stderr_s`` is the Cramer-Rao bound of a delay in white
    noise, sigma_e / sqrt(sum (alpha dr/dt)^2) with sigma_e the robust residual scatter: a lower bound that leaves
    out table-log interpolation and time-stamp rounding (sub-microsecond here). ``clock_drift_ppm`` compares the
    offsets of the two record halves, each at its information centroid (where the table rate changes; see
    ``_delay_crlb_centroid``), then fits the drift over the whole record (``_refine_delay_drift``); a clock-rate
    error is otherwise indistinguishable from a scale factor.
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


def _uniform(t: np.ndarray, y: np.ndarray, dt: float) -> tuple[float, np.ndarray]:
    n = int(np.floor((t[-1] - t[0]) / dt)) + 1
    grid = t[0] + dt * np.arange(n)
    return float(t[0]), np.interp(grid, t, y)


def _table_axis_body(plan, t_s: np.ndarray, chunk: int = 200_000) -> np.ndarray:
    """Body-frame table axis u_b(t) = C_b^l(t)^T a along the plan's kinematics ([SEED000] eq. 3-5)."""
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


def _refine_delay_drift(t_imu, g_proj, t_tab, r_tab, offset, drift, iterations: int = 8) -> tuple[float, float]:
    """Clock drift by Gauss-Newton on g(t) = alpha r(t + tau_m + d (t - t_m)) + beta over the whole record, from the
    halves' estimate d; -> (d, its Cramer-Rao standard error), d dimensionless (offset change per IMU second).

    A delay held constant over a half misfits the ramps far from the half's centroid by alpha dr/dt d (t - t_c),
    tens of noise sigmas at 200 ppm, and the robust inlier test then drops them: the halves alone read the drift
    5-20 % high or low. Fitting the drift itself keeps every ramp (inliers re-selected each step, as in
    ``_refine_delay``; only the samples where the table rate changes, the others carry no delay information);
    standard error from the 2 x 2 information matrix ([KAY1993] eq. 3.18, vector form).
    """
    x = t_imu - 0.5 * (t_imu[0] + t_imu[-1])
    tau = offset
    # only samples where the table rate changes inform the delay (J = alpha dr/dt (1, t - t_m)): fit on those,
    # widened by 3 samples on each side so that the ramps stay inside as the delay moves
    rr = np.interp(t_imu + tau + drift * x, t_tab, r_tab, left=np.nan, right=np.nan)
    act = np.isfinite(rr)
    act[act] = np.gradient(rr[act], t_imu[act]) != 0
    act = np.convolve(act, np.ones(7), mode="same") > 0
    if act.sum() < 10:
        return np.nan, np.nan
    # gain and bias (alpha, beta) from the whole record, mostly its plateaus, as in the constant-delay fit
    m = _delay_inliers(t_imu, g_proj, rr)
    if m.sum() < 10:
        return np.nan, np.nan
    coef, *_ = np.linalg.lstsq(np.column_stack([rr[m], np.ones(m.sum())]), g_proj[m], rcond=None)
    h = float(np.median(np.diff(t_imu)))
    t_imu, g_proj, x = t_imu[act], g_proj[act], x[act]
    se = np.nan
    for _ in range(iterations):
        tt = t_imu + tau + drift * x
        rr = np.interp(tt, t_tab, r_tab, left=np.nan, right=np.nan)
        # dr/dt by central differences one IMU sample apart (np.gradient of the full record; the subset has gaps)
        rdot = (np.interp(tt + h, t_tab, r_tab) - np.interp(tt - h, t_tab, r_tab)) / (2 * h)
        e = g_proj - coef[0] * rr - coef[1]
        ok = np.isfinite(e)
        med = np.median(e[ok])
        sig_all = MAD_TO_SIGMA * np.median(np.abs(e[ok] - med))
        m = ok & (np.abs(e - med) <= 5 * sig_all) if sig_all > 0 else ok
        if m.sum() < 10:
            return np.nan, np.nan
        e = e[m]
        deriv = coef[0] * rdot[m]
        jac = np.column_stack([deriv, deriv * x[m]])
        info = jac.T @ jac
        if not np.linalg.det(info) > 0:
            return np.nan, np.nan
        step = np.linalg.solve(info, jac.T @ e)
        tau += float(step[0])
        drift += float(step[1])
        sig = MAD_TO_SIGMA * np.median(np.abs(e - np.median(e)))
        se = float(sig * np.sqrt(np.linalg.inv(info)[1, 1]))
        if abs(step[1]) < 1e-3 * se:  # converged far inside its own uncertainty
            break
    return float(drift), se


def _delay_inliers(t_imu, g_proj, rr) -> np.ndarray:
    m = np.isfinite(rr)
    if m.sum() < 10:
        return m
    a_mat = np.column_stack([rr[m], np.ones(m.sum())])
    coef, *_ = np.linalg.lstsq(a_mat, g_proj[m], rcond=None)
    e = g_proj[m] - a_mat @ coef
    med = np.median(e)
    sig = MAD_TO_SIGMA * np.median(np.abs(e - med))
    out = m.copy()
    out[m] = np.abs(e - med) <= 5 * sig if sig > 0 else True
    return out


def _delay_crlb(t_imu, g_proj, t_tab, r_tab, offset, dt) -> float:
    """Cramer-Rao bound of a delay in white noise (Kay, Fundamentals of Statistical Signal Processing I, eq. 3.18)."""
    return _delay_crlb_centroid(t_imu, g_proj, t_tab, r_tab, offset)[0]


def _delay_crlb_centroid(t_imu, g_proj, t_tab, r_tab, offset) -> tuple[float, float]:
    """(Cramer-Rao bound of the delay, the time the delay estimate refers to).

    The least-squares delay weighs sample i by its Fisher information w_i = (alpha dr/dt)^2 ([KAY1993] eq. 3.18),
    so when the delay drifts, tau(t) = tau_c + d (t - t_c), the estimate is (to first order) the drifting delay at
    the information centroid t_c = sum w_i t_i / sum w_i: on a rate plan the table's ramps, not the record's middle.
    """
    rr = np.interp(t_imu + offset, t_tab, r_tab, left=np.nan, right=np.nan)
    m = _delay_inliers(t_imu, g_proj, rr)
    if m.sum() < 10:
        return np.nan, np.nan
    a_mat = np.column_stack([rr[m], np.ones(m.sum())])
    coef, *_ = np.linalg.lstsq(a_mat, g_proj[m], rcond=None)
    e = g_proj[m] - a_mat @ coef
    sig = MAD_TO_SIGMA * np.median(np.abs(e - np.median(e)))
    deriv = np.gradient(rr[m], t_imu[m])
    w = (coef[0] * deriv) ** 2
    energy = np.sum(w)
    if not energy > 0:
        return np.nan, np.nan
    return float(sig / np.sqrt(energy)), float(np.sum(w * t_imu[m]) / energy)


def table_steps(table: pd.DataFrame) -> dict[int, tuple[float, float]]:
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
    """The table rate clipped where the gyro saturates ([SEED003]: align the table rate with the gyro's output).

    A gyro whose measuring range is below the plan's rates reads flat at its rail on the fast plateaus; against the
    unclipped table rate the correlation peak then shifts (on [SEED003]'s repetitive sequence a consumer gyro at
    +-250 deg/s on the +-400 deg/s plan aligned 2989 s off; on the quick rate plan 0.1-1.2 ms off instead of
    0.05-0.1 ms). When the projected gyro spans less than ``shortfall`` of the table's range on a side, the
    reference is clipped at the gyro's extreme on that side, so both signals saturate alike; otherwise it is
    returned unchanged.
    """
    lo, hi = float(np.min(g_proj)), float(np.max(g_proj))
    r_lo, r_hi = float(np.min(r_tab)), float(np.max(r_tab))
    clip_hi = hi if r_hi > 0 and hi < shortfall * r_hi else None
    clip_lo = lo if r_lo < 0 and lo > shortfall * r_lo else None
    if clip_hi is None and clip_lo is None:
        return r_tab
    return np.clip(r_tab, clip_lo, clip_hi)


def align_clocks(plan, imu: pd.DataFrame, table: pd.DataFrame, config: SegmentationConfig = SegmentationConfig(),
                 resolution: list | None = None) -> ClockAlignment:
    """[SEED003] time alignment: offset (t_table = t_imu + offset) maximising corr(table rate, gyro . u_b), parabolic peak.

    Falls back to matching step centres (table ``step_index`` runs vs detected quiet intervals) when the table
    rate carries no signal (e.g. a position plan whose table log shows no rotation) or correlates poorly.
    ``resolution``: the channels' quantization steps when known (``detect_quiet_intervals``).
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
                se_h, t_c = _delay_crlb_centroid(ti, gi, t_tab[tsel], r_tab[tsel], o)
                if not np.isfinite(t_c):
                    break
                halves.append((o, se_h, t_c))  # each half's offset refers to its information centroid
            if len(halves) == 2:
                (o1, s1, c1), (o2, s2, c2) = halves
                d0 = (o2 - o1) / (c2 - c1)
                drift, drift_se = d0 * 1e6, np.hypot(s1, s2) / (c2 - c1) * 1e6  # kept if the joint fit fails
                d, d_se = _refine_delay_drift(t_imu, gp, t_tab, r_tab, off, d0)
                if np.isfinite(d) and np.isfinite(d_se):
                    drift, drift_se = d * 1e6, d_se * 1e6
            return ClockAlignment(off, se, "xcorr_table_rate_parabolic+ls", peak, drift, drift_se, int(t_imu.size))
    # fallback: step centres
    det = detect_quiet_intervals(t_imu, gyro, imu[list(ACCEL_COLUMNS)].to_numpy(dtype=float), cfg.detector,
                                 resolution)
    steps = table_steps(table)
    if det.intervals.empty or not steps:
        return ClockAlignment(0.0, np.nan, "none", np.nan, n_samples=int(t_imu.size))
    qs = det.intervals["t_start_s"].to_numpy()
    qe = det.intervals["t_end_s"].to_numpy()
    qc = 0.5 * (qs + qe)
    tc = np.array([0.5 * (a + b) for a, b in steps.values()])
    cands = (tc[:, None] - qc[None, :]).ravel()
    if halfwidth is not None:
        cands = cands[np.abs(cands - cfg.clock_offset_prior_s) <= halfwidth]
    cands = np.unique(np.round(cands, 3))
    # score of a candidate offset: the longest overlap of each table step with a quiet interval, summed in step order
    scores = np.zeros(cands.size)
    for a, b in steps.values():
        overlap = np.minimum(qe, b - cands[:, None]) - np.maximum(qs, a - cands[:, None])
        scores += np.clip(overlap, 0, None).max(axis=1)
    best, best_score = 0.0, -1.0
    for c, score in zip(cands, scores):
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
