"""Plateaus without a table log: quiet intervals in the IMU data and their match to the plan steps.

Quiet intervals are detected in the IMU data alone ([TEDALDI2014] variance detector on the gyro- and
accelerometer-norm, threshold a multiple of the record's own noise floor, edges refined sample by sample) and
matched to the plan steps by a common time shift, using both timing and content (expected angular rate and
specific-force direction); steps without a matching interval are reported.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pandas as pd
from scipy.ndimage import uniform_filter1d

from assets_lib.calibration.outliers import MAD_TO_SIGMA, estimate_resolution
from assets_lib.calibration.segmentation.config import (
    DetectorConfig,
    SegmentationConfig,
)
from assets_lib.sim.kinematics import body_inputs


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
    t_s: np.ndarray, gyro: np.ndarray, accel: np.ndarray | None = None, config: DetectorConfig = DetectorConfig(),
    resolution: list | None = None,
) -> QuietDetection:
    """imu_tk static detector ([TEDALDI2014] sec. IV-A): moving variance vs k x noise floor, min duration.

    Statistic: moving variance (centred, ``window_s``) of |gyro| and |accel| (norms are unchanged by the rotation
    of a constant-magnitude vector, so constant-rate plateaus are quiet too). Threshold: ``k_threshold`` x the
    ``floor_quantile`` quantile of each statistic. Edges are then refined sample by sample: a quiet run ends where a
    sample leaves the run's median by more than ``edge_k_sigma`` robust sigmas on any axis (within one window of
    the coarse edge). Runs separated by less than ``merge_gap_s`` with the same median are merged.

    ``resolution``: the quantization steps of the gyro then accelerometer channels (``estimate_resolution`` of each
    column), when the caller has them already (``segment_run``); used only with ``center`` "none", where they are
    the steps of the very values the detector reads.
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
    # quantization step per channel (gyro, then accelerometer), each computed once
    known = list(resolution) if resolution is not None and cfg.center == "none" else None
    res_g = known[:3] if known is not None else [estimate_resolution(g[:, j]) for j in range(3)]
    res_a = (known[3:6] if known is not None else [estimate_resolution(a[:, j]) for j in range(3)]) if a is not None \
        else []

    def stat_and_threshold(v, res):
        s = _moving_variance(np.linalg.norm(v, axis=1), w)
        pos = s[s > 0]
        floor = np.quantile(pos, cfg.floor_quantile) if pos.size else 0.0
        q = max([r for r in res if r] or [0.0])
        floor = max(floor, q * q / 12.0, np.finfo(float).tiny)
        return s, cfg.k_threshold * floor

    sg, thr_g = stat_and_threshold(g, res_g)
    quiet = sg < thr_g
    if a is not None:
        sa, thr_a = stat_and_threshold(a, res_a)
        quiet &= sa < thr_a
    else:
        sa, thr_a = np.zeros(n), np.inf
    starts, ends = _runs(quiet)

    both = g if a is None else np.column_stack([g, a])
    res_all = np.array([r or 0.0 for r in res_g + res_a])
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
# Plan matching
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
