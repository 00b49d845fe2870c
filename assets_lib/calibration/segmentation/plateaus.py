"""The PLATEAU TABLE of one run: windows from the table log or the data, whole turns, outliers, means, SEMs.

Every window is trimmed by the step's ``settle_s`` plus a guard, and a rate plateau is cut to a whole number of
table revolutions where it is long enough ([SEED000] full-revolution method: the horizontal earth rate, table
ripple, wobble and tilt sinusoids average out). Outliers are rejected with :mod:`assets_lib.calibration.outliers`
([SEED001]). Reference inputs are averaged over exactly the kept samples (``kinematics.body_inputs``); standard
errors per :mod:`.window_stats`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pandas as pd

from assets_lib.calibration.outliers import estimate_resolution, reject_outliers_window
from assets_lib.calibration.segmentation.clock import (
    ClockAlignment,
    align_clocks,
    table_steps,
)
from assets_lib.calibration.segmentation.config import SegmentationConfig
from assets_lib.calibration.segmentation.detection import (
    QuietDetection,
    detect_quiet_intervals,
    match_plan,
)
from assets_lib.calibration.segmentation.window_stats import plateau_sem
from assets_lib.noise.pooled import TWO_PI, flicker_b_of_avar
from assets_lib.sim.earth import site_gravity_mps2
from assets_lib.sim.kinematics import body_inputs, kinematics_cache
from raw_schemas.tables import ACCEL_COLUMNS, GYRO_COLUMNS

CHANNELS = GYRO_COLUMNS + ACCEL_COLUMNS


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


def whole_revolution_window(a_s: float, b_s: float, angle_of_t) -> tuple[float, float, float]:
    """[SEED000] full-revolution method: the centred sub-window of [a, b] turning the table a whole number of turns.

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
    cols += [f"{ch}_sem_flicker_b" for ch in CHANNELS]  # the B in the sems: the SEM model's term (0: left out)
    return cols


def segment_run(manifest, imu: pd.DataFrame, table: pd.DataFrame | None = None,
                config: SegmentationConfig = SegmentationConfig(),
                clock_alignment: ClockAlignment | None = None) -> SegmentationResult:
    """Plateau table of one run (docs/design.md PLATEAU TABLE); [SEED003] alignment, [SEED000] whole turns, [SEED001] outliers.

    ``n_samples`` counts the samples kept for the means; ``n_rejected`` the outliers removed from the window;
    ``rejected_fraction`` = n_rejected / (n_samples + n_rejected). SEMs per the module docstring.

    ``clock_alignment``: a table-to-IMU alignment computed before (``align_clocks`` of the recorded run), used
    instead of aligning this run's clocks again. A replicate of a recorded run shares its IMU time stamps and its
    table log, so the offset is the recording's; with it the plateau windows, and every input that depends only on
    them, are the same in every replicate. The replicate's clock drift is then the recorded one (not re-estimated
    from its noise). Ignored without a table log.

    The plan's kinematics are memoised for the call (``kinematics_cache``, bit-identical): the clock alignment's
    trajectory over the IMU time grid then serves the windows' reference inputs by indexing.
    """
    with kinematics_cache():
        return _segment_run(manifest, imu, table, config, clock_alignment)


def _segment_run(manifest, imu: pd.DataFrame, table: pd.DataFrame | None, config: SegmentationConfig,
                 clock_alignment: ClockAlignment | None) -> SegmentationResult:
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
    res = [estimate_resolution(y[:, j]) for j in range(6)]  # quantization step per channel, computed once

    if table is not None and len(table):
        method = "table_log"
        alignment = clock_alignment if clock_alignment is not None else align_clocks(plan, imu, table, cfg, res)
        if alignment.method == "none":
            warnings.append("clock alignment failed: offset 0 assumed")
            for k in reasons:
                reasons[k].append("table/IMU clock alignment failed (offset 0 assumed)")
        elif alignment.correlation_peak < cfg.min_correlation:
            warnings.append(f"clock alignment weak (method {alignment.method}, peak {alignment.correlation_peak:.2f})")
        off = alignment.offset_s if np.isfinite(alignment.offset_s) else 0.0
        tsteps = table_steps(table)
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
        detection = detect_quiet_intervals(t, gyro, accel, cfg.detector, res)
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
    for ch, fit in noise_fits.items():  # [IEEE952] C.3: flicker plateau (2 ln2 / pi) B^2 -> B, shared by the run
        # the B estimate also when the SEM model selection left it out (too weak within plateaus): the fits'
        # correlated-noise GLS needs the run mean's 1/f wander (accel bias z sd 1.3-1.7 with B read as 0)
        df[f"{ch}_flicker_b"] = flicker_b_of_avar(fit.flicker_avar_best)
        # the B the sems contain (the selected term only): the fits' white part is sem^2 minus its floor
        df[f"{ch}_sem_flicker_b"] = flicker_b_of_avar(fit.flicker_avar)
    return SegmentationResult(df, method, alignment, detection, shifts, tuple(unmatched), window_step, keep,
                              noise_fits, tuple(warnings))
