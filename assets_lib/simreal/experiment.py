"""The experiment as recorded: a device's completed runs, their recorded inputs u(t), and one processing chain.

simreal.md sec. 2 ("compare with the calibrated simulator"): real runs and every replicate go through the *same*
code, :func:`process_run` (``segmentation.segment_run`` then the library fits that match the run's kind), so the
fitted degrees of freedom and the coloured noise are accounted for identically. Recorded inputs are computed once
per run (:class:`RunInputs`: timestamps, plan kinematics in body axes, the logged temperature, time since power-on,
table angle and axis) and reused by every replicate.

Power-on time: the start of the first run of each ``power_cycle_index`` (issue 12), so ``t_on_s`` of a sample is
its run's start minus that time plus the sample's time in the run.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd
from scipy.signal import welch

from assets_lib.calibration.multiposition import (
    fit_accel_multiposition,
    fit_gyro_static,
)
from assets_lib.calibration.rate_fit import fit_gyro_rate
from assets_lib.calibration.segmentation import CHANNELS, overlapping_avar, segment_run
from assets_lib.sim.earth import site_gravity_mps2
from assets_lib.sim.kinematics import body_inputs
from raw_schemas.readers import discover_runs, ingest_run

#: canonical channel names as the report spells them
CHANNEL_NAMES = ("gyro_x", "gyro_y", "gyro_z", "accel_x", "accel_y", "accel_z")
DECIMATE = 10  # block length of the sample-level (table-angle) residuals: 10 Hz at 100 Hz


@dataclass(frozen=True, eq=False)
class RunInputs:
    """Recorded inputs of one run, identical for the real run and every replicate (simreal.md sec. 1: u(t))."""

    run_id: str
    kind: str
    power_cycle: int
    manifest: object
    t_s: np.ndarray  # IMU time stamps
    t_on_s: np.ndarray  # time since power-on
    temperature_degc: np.ndarray
    omega_b_radps: np.ndarray  # (n,3) plan kinematics incl. earth rate (the twin's true input)
    f_b_mps2: np.ndarray  # (n,3)
    table_rate_radps: np.ndarray  # (n,) table rate from the plan
    table_angle_rad: np.ndarray  # (n,) table angle from the plan
    table_axis_b: np.ndarray  # (n,3) table axis in body axes
    tilt_e1_b: np.ndarray  # (n,3) level-frame unit vectors perpendicular to the table axis, in body axes
    tilt_e2_b: np.ndarray
    step_index: np.ndarray  # (n,) plan step or -1
    table: pd.DataFrame | None
    lsb_si: np.ndarray  # (6,) output resolution per channel (0 when unknown)
    gravity_mps2: float


@dataclass(frozen=True, eq=False)
class ProcessedRun:
    """What the processing chain gives for one run (real or replicate)."""

    run_id: str
    plateaus: pd.DataFrame
    fit_residuals: pd.DataFrame  # step_index, channel, residual, std_residual, used
    clock_drift_ppm: float
    clock_drift_stderr_ppm: float
    window_step: np.ndarray  # per sample
    keep: np.ndarray
    allan: dict = field(default_factory=dict)  # channel -> (tau_s, adev, approximate EDF) for static runs
    spectrum_peak: dict = field(default_factory=dict)  # channel -> (log10 peak-to-median PSD ratio, frequency Hz)
    noise_fits: dict = field(default_factory=dict)  # segmentation's pooled Allan model per channel


@dataclass(frozen=True, eq=False)
class DeviceExperiment:
    """A device's completed runs with their recorded inputs and the real data processed."""

    device_id: str
    grade: str
    runs: tuple[RunInputs, ...]
    imu: dict  # run_id -> canonical imu DataFrame (real)
    processed: dict  # run_id -> ProcessedRun (real)


def _lsb_si(manifest) -> np.ndarray:
    from raw_schemas.units import si_factor

    out = np.zeros(6)
    for j, ch in enumerate(CHANNEL_NAMES):
        spec = manifest.channels.get(ch) if isinstance(manifest.channels, dict) else None
        if spec is None:
            continue
        lsb = getattr(spec, "lsb", None) if not isinstance(spec, dict) else spec.get("lsb")
        unit = getattr(spec, "lsb_unit", None) if not isinstance(spec, dict) else spec.get("lsb_unit")
        if lsb and unit:
            try:
                out[j] = float(lsb) * si_factor("gyro" if j < 3 else "accel", unit)
            except Exception:  # noqa: BLE001 - an unknown unit only disables quantization of the twin
                out[j] = 0.0
    return out


def run_inputs(manifest, imu: pd.DataFrame, table: pd.DataFrame | None, power_on_utc) -> RunInputs:
    """Recorded inputs of a run; plan time = IMU time (the simulated archives; segmentation confirms it)."""
    plan = manifest.plan
    missing = [k for k, st in enumerate(plan.steps) if getattr(st, "orientation_b2l", None) is None]
    if missing:
        raise ValueError(f"run {manifest.device.id}/{manifest.run_id} ({manifest.test_kind}): plan steps {missing} have "
                         "no orientation (hand-placed / free poses), so the twin cannot be driven by the recorded "
                         "inputs; the sim-to-real diagnosis needs plans with known orientations (table runs)")
    t = imu["time_s"].to_numpy(float)
    g = site_gravity_mps2(manifest.site)
    bi = body_inputs(plan, t, manifest.site.latitude_deg, g)
    tr = bi.trajectory
    ct = np.swapaxes(tr.c_b2l, 1, 2)
    a = np.asarray(plan.table_axis_level, float)
    e1 = np.cross(a, [0.0, 0.0, 1.0]) if abs(a[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
    e1 = e1 - a * (a @ e1)
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(a, e1)
    temp = imu["temperature_degc"].to_numpy(float, na_value=np.nan) if "temperature_degc" in imu else np.full(t.size, np.nan)
    if not np.isfinite(temp).any():
        temp = np.full(t.size, 25.0)
    else:
        temp = pd.Series(temp).interpolate(limit_direction="both").to_numpy()
    dt_on = (manifest.start_time_utc - power_on_utc).total_seconds()
    return RunInputs(
        run_id=manifest.run_id, kind=manifest.test_kind, power_cycle=int(manifest.power_cycle_index), manifest=manifest,
        t_s=t, t_on_s=t + dt_on, temperature_degc=temp, omega_b_radps=bi.omega_b_radps, f_b_mps2=bi.f_b_mps2,
        table_rate_radps=tr.table_rate_radps, table_angle_rad=tr.table_angle_rad, table_axis_b=ct @ a,
        tilt_e1_b=ct @ e1, tilt_e2_b=ct @ e2, step_index=tr.step_index, table=table, lsb_si=_lsb_si(manifest),
        gravity_mps2=g,
    )


def _fit_residual_rows(fit_axes, sensor: str, run_id: str) -> list[dict]:
    rows = []
    for ax in fit_axes:
        f = ax.fit
        for k in range(len(f.residual)):
            rows.append({"run_id": run_id, "row": k, "channel": f"{sensor}_{ax.axis}", "residual": float(f.residual[k]),
                             "std_residual": float(f.std_residual[k]), "used": bool(f.used[k])})
    return rows


def process_run(inp: RunInputs, imu: pd.DataFrame, allan_taus: bool = True) -> ProcessedRun:
    """The library's chain on one run: ``segment_run`` then the fits of its kind (same code for real and sim)."""
    seg = segment_run(inp.manifest, imu, inp.table)
    p = seg.plateaus
    rows: list[dict] = []
    kind = inp.kind
    try:
        if kind == "rate":
            rf = fit_gyro_rate(p, cross_check=False)
            rows += _fit_residual_rows(rf.axes, "gyro", inp.run_id)
            for r in rows:
                r["step_index"] = int(rf.plateaus["step_index"].iloc[r["row"]])
        elif kind in ("multiposition", "tumble") and (p["kind"] == "static").sum() >= 4:
            af = fit_accel_multiposition(p)
            gf = fit_gyro_static(p)
            r1 = _fit_residual_rows(af.axes, "accel", inp.run_id)
            for r in r1:
                r["step_index"] = int(af.plateaus["step_index"].iloc[r["row"]])
            r2 = _fit_residual_rows(gf.axes, "gyro", inp.run_id)
            for r in r2:
                r["step_index"] = int(gf.plateaus["step_index"].iloc[r["row"]])
            rows += r1 + r2
    except ValueError:
        rows = []
    fr = pd.DataFrame(rows, columns=["run_id", "row", "channel", "residual", "std_residual", "used", "step_index"])
    al = seg.alignment
    drift = float(al.clock_drift_ppm) if al is not None else np.nan
    drift_se = float(al.clock_drift_stderr_ppm) if al is not None else np.nan
    allan, peaks = {}, {}
    if kind == "static" and allan_taus:
        y = imu[list(CHANNELS)].to_numpy(float)
        ref = np.column_stack([inp.omega_b_radps, inp.f_b_mps2])
        sel = seg.keep
        if sel.sum() > 2000:
            fs = 1.0 / float(np.median(np.diff(inp.t_s)))
            n = int(sel.sum())
            m = np.unique(np.round(2.0 ** np.arange(0, np.log2(n / 8.0))).astype(int))
            for j, ch in enumerate(CHANNEL_NAMES):
                r = (y[sel, j] - ref[sel, j])
                av, terms = overlapping_avar(r, m)  # (avar per cluster size, number of terms)
                allan[ch] = (np.asarray(m, float) / fs, np.sqrt(np.asarray(av, float)),
                             np.asarray(terms, float) / np.asarray(m, float))  # EDF ~ terms / m (white noise)
                fq, psd = welch(r - r.mean(), fs=fs, nperseg=1024)
                band = fq > 0.5
                if band.sum() > 8:
                    k = int(np.argmax(psd[band]))
                    peaks[ch] = (float(np.log10(psd[band][k] / np.median(psd[band]))), float(fq[band][k]))
    return ProcessedRun(inp.run_id, p, fr, drift, drift_se, seg.window_step, seg.keep, allan, peaks, seg.noise_fits)


def load_device(landing: str | Path, device_id: str) -> DeviceExperiment:
    """Every completed run of ``device_id`` under ``landing``, ingested through the contract readers and processed."""
    dirs = [d for d in discover_runs(landing) if Path(d).parent.name == device_id]
    if not dirs:
        raise FileNotFoundError(f"{landing}: no completed run of device {device_id!r} (expected "
                                f"<landing>/{device_id}/<run>/ with a _COMPLETE marker)")
    ing = [ingest_run(d) for d in dirs]
    return experiment_from_frames([(r.manifest, r.imu, r.table) for r in ing])


def experiment_from_frames(frames) -> DeviceExperiment:
    """A device experiment from (manifest, canonical imu, canonical table | None) of each run (one device)."""
    ing = sorted(frames, key=lambda r: (r[0].start_time_utc, r[0].run_id))
    if len({m.device.id for m, _, _ in ing}) != 1:
        raise ValueError("experiment_from_frames: runs of more than one device")
    first = {}
    for m, _, _ in ing:
        first.setdefault(int(m.power_cycle_index), m.start_time_utc)
    runs, imus, proc = [], {}, {}
    for m, imu, table in ing:
        inp = run_inputs(m, imu, table, first[int(m.power_cycle_index)])
        runs.append(inp)
        imus[inp.run_id] = imu
        proc[inp.run_id] = process_run(inp, imu)
    m0 = ing[0][0]
    return DeviceExperiment(m0.device.id, m0.device.grade or "", tuple(runs), imus, proc)


def list_devices(landing: str | Path) -> list[str]:
    """Device ids with at least one completed run."""
    return sorted({Path(d).parent.name for d in discover_runs(landing)})
