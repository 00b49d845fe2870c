"""Calibrate one table-free run (test kind ``tablefree``): choose the procedure from the plan, find the poses,
fit, and return one coefficient table with uncertainties and observability.

* Plan with six ``pose`` steps carrying ``up_axis_body`` (+x ... -z) and three ``rotation`` steps about x, y, z:
  the Ferraris closed form (:mod:`assets_lib.calibration.ferraris`) on the annotated sections.
* Otherwise (``free`` steps, optionally a leading ``pose`` = the initial static interval): static poses are
  detected (:mod:`assets_lib.calibration.poses`; level from the initial interval when declared), the
  accelerometer is fitted to the pose magnitudes ([TEDALDI2014], :mod:`assets_lib.calibration.tablefree`)
  and the gyro by integration between poses (:mod:`assets_lib.calibration.gyro_integration`) with its bias the
  mean of the initial static interval (or of all poses when none is declared; earth rate then enters the bias).

Inputs are the canonical (SI) IMU frame; coefficients are in SI per canonical unit (for channels declared in
counts, canonical = counts x lsb, so scale factors are relative to the nominal lsb).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import pandas as pd

from assets_lib.calibration.ferraris import ROTATION_SECTIONS, STATIC_SECTIONS, ferraris_fit
from assets_lib.calibration.gyro_integration import fit_gyro_integration
from assets_lib.calibration.poses import StaticPoses, detect_static_poses
from assets_lib.calibration.tablefree import fit_accel_poses, pose_means
from assets_lib.coefficient import Coefficient
from raw_schemas.tables import ACCEL_COLUMNS, GYRO_COLUMNS

#: imu_tk's defaults: 1 s (101-sample) window, 100 samples averaged per pose, threshold factor swept 2..10
WINDOW_S = 1.01
POSE_SAMPLES = 100
K_SWEEP = (2.0, 3.0, 4.0, 5.0, 6.0, 7.0, 8.0, 9.0, 10.0)
MIN_POSES = 12


@dataclass(frozen=True)
class TableFreeResult:
    method: str                              # "ferraris" or "tedaldi"
    coefficients: dict                       # name -> Coefficient
    poses: StaticPoses | None
    accel_fit: object
    gyro_fit: object
    diagnostics: dict = field(default_factory=dict)
    warnings: tuple = ()

    def table(self) -> pd.DataFrame:
        rows = [{"term": k, "value": c.value, "stderr": c.stderr, "unit": c.unit, "observable": c.observable}
                for k, c in self.coefficients.items()]
        return pd.DataFrame(rows, columns=["term", "value", "stderr", "unit", "observable"])


def _ferraris_sections(plan) -> dict | None:
    sec = {}
    for s in plan.steps:
        if s.kind == "pose" and s.up_axis_body:
            sec[f"{s.up_axis_body[1]}_{'p' if s.up_axis_body[0] == '+' else 'a'}"] = s
        elif s.kind == "rotation" and s.rotation_axis_body:
            sec[f"{s.rotation_axis_body}_rot"] = s
    return sec if all(k in sec for k in STATIC_SECTIONS + ROTATION_SECTIONS) else None


def _slice(t, s) -> slice:
    return slice(int(np.searchsorted(t, s.start_s)), int(np.searchsorted(t, s.end_s - 1e-9)))


def _mean_stderr(x: np.ndarray, rate_hz: float) -> np.ndarray:
    """Standard error of a window mean per column: sqrt(sigma_A^2(T)) of the fitted IEEE 952 model at the window
    length T ([IEEE952] C.1; under bias instability sigma / sqrt(n) is too small)."""
    from assets_lib.noise.allan import allan_deviation
    from assets_lib.noise.identification import fit_noise

    out = []
    for j in range(x.shape[1]):
        r = allan_deviation(x[:, j], rate_hz, "octave")
        try:
            out.append(float(np.sqrt(fit_noise(r, sensor="si").model_avar(np.array([x.shape[0] / rate_hz]))[0])))
        except ValueError:  # too short for a noise fit
            out.append(float(np.std(x[:, j], ddof=1) / np.sqrt(x.shape[0])))
    return np.array(out)


def calibrate_tablefree(manifest, imu: pd.DataFrame, gravity_mps2: float) -> TableFreeResult:
    t = imu["time_s"].to_numpy(float)
    acc = imu[list(ACCEL_COLUMNS)].to_numpy(float)
    gyr = imu[list(GYRO_COLUMNS)].to_numpy(float)
    plan = manifest.plan
    sec = _ferraris_sections(plan)
    if sec is not None:
        angle = {s.rotation_angle_deg for k, s in sec.items() if k.endswith("_rot")}
        if len(angle) != 1 or None in angle:
            raise ValueError("Ferraris rotations need one common rotation_angle_deg")
        sl = {k: _slice(t, s) for k, s in sec.items()}
        fit = ferraris_fit({k: (acc[v], np.degrees(gyr[v])) for k, v in sl.items()}, manifest.sample_rate_hz,
                           gravity=gravity_mps2, expected_angle_deg=angle.pop(),
                           from_acc_unit="m/s^2 (nominal)", from_gyr_unit="deg/s (nominal)")
        norms = np.linalg.norm(fit.calibrate_acc(np.array([acc[sl[k]].mean(0) for k in STATIC_SECTIONS])), axis=1)
        return TableFreeResult("ferraris", fit.coefficients(), None, fit, fit,
                               {"static_norm_rms_mps2": float(np.sqrt(np.mean((norms - gravity_mps2) ** 2)))})
    ref_steps = [s for s in plan.steps if s.kind == "pose"]
    ref = _slice(t, ref_steps[0]) if ref_steps else None
    best = None
    for k in K_SWEEP:  # imu_tk: the threshold factor with the smallest accelerometer residual wins
        poses = detect_static_poses(t, acc, window_s=WINDOW_S, k=k, reference=ref)
        if poses.count < MIN_POSES:
            continue
        m = pose_means(t, acc, poses.starts, poses.ends, POSE_SAMPLES)
        n_avg = np.minimum(np.asarray(poses.ends) - np.asarray(poses.starts), POSE_SAMPLES)
        af = fit_accel_poses(m, gravity_mps2, input_unit="m/s^2 (nominal)", n_samples=n_avg)
        if best is None or af.rms_mps2 < best[2].rms_mps2:
            best = (k, poses, af, m)
    if best is None:
        raise ValueError(f"fewer than {MIN_POSES} static poses found for every threshold factor {K_SWEEP}: "
                         "not enough poses for a table-free calibration")
    k, poses, af, m = best
    bias = gyr[ref].mean(axis=0) if ref is not None else pose_means(t, gyr, poses.starts, poses.ends).mean(axis=0)
    warnings = () if ref is not None else ("no initial static interval declared: gyro bias = mean over all poses "
                                           "(earth rate projected on the mean attitude enters it)",)
    n_ref = (ref.stop - ref.start) if ref is not None else 0
    bias_se = _mean_stderr(gyr[ref], manifest.sample_rate_hz) if ref is not None and n_ref >= 64 else np.full(3, np.nan)
    gf = fit_gyro_integration(t, gyr, poses.starts, poses.ends, af.apply(m), bias, scale_start=np.ones(3),
                              input_unit="rad/s (nominal)",
                              bias_cov=np.diag(bias_se ** 2) if np.all(np.isfinite(bias_se)) else None)
    coefs = {f"accel_{n}": c for n, c in af.coefficients.items()}
    coefs.update({f"gyro_{n}": c for n, c in gf.coefficients.items()})
    for i, ax in enumerate("xyz"):
        coefs[f"gyro_b_{ax}"] = Coefficient(float(bias[i]), float(bias_se[i]), "rad/s (nominal)")
    diag = {"threshold_factor": k, "n_poses": poses.count, "accel_norm_rms_mps2": af.rms_mps2,
            "gyro_direction_rms_rad": gf.rms_rad, "unobservable": list(af.unobservable) + list(gf.unobservable)}
    return TableFreeResult("tedaldi", coefs, poses, af, gf, diag, warnings)


AXES = "xyz"
_T_NAMES = {(0, 1): "t01", (0, 2): "t02", (1, 0): "t10", (1, 2): "t12", (2, 0): "t20", (2, 1): "t21"}


def coefficient_table(result: TableFreeResult, device_id: str, run_id: str, n_samples: int) -> pd.DataFrame:
    """COEFFICIENT TABLE rows (``fit_report.COEFFICIENT_COLUMNS``) of a table-free calibration: per sensor and
    axis ``scale_factor`` (relative to the nominal lsb), ``bias`` (SI), ``misalignment_<i><j>`` (rad, small
    angle), and for Ferraris ``g_sensitivity_<j>`` of the gyro."""
    from assets_lib.calibration.fit_report import coefficient_frame
    from assets_lib.calibration.fit_report import coefficient_row as _row
    from raw_schemas.units import lab_unit

    def coefficient_row(*, sensor, coefficient, value, stderr, observable, ci=None, **kw):
        # ci: the fit's own 95 % interval (Tedaldi fits: Student-t at the residual dof), kept in ci95_low/high
        lo, hi = ci.interval() if ci is not None and ci.observable else (np.nan, np.nan)
        est = Coefficient(float(value), float(stderr), lab_unit(sensor, coefficient).si, bool(observable), lo, hi)
        return _row(sensor=sensor, coefficient=coefficient, estimate=est, **kw)

    def _dof(sensor):
        f = result.accel_fit if sensor == "accel" else result.gyro_fit
        return getattr(f, "dof", np.nan)

    rows = []
    n_p = result.poses.count if result.poses is not None else 6
    common = dict(device_id=device_id, run_id=run_id, n_plateaus=n_p, n_samples=n_samples)
    if result.method == "tedaldi":
        c = result.coefficients
        for sensor in ("accel", "gyro"):
            for i, a in enumerate(AXES):
                k = c[f"{sensor}_k_{a}"]
                rows.append(coefficient_row(sensor=sensor, axis=a, coefficient="scale_factor", value=k.value,
                                            stderr=k.stderr, observable=k.observable, method="tedaldi", ci=k,
                                            dof=_dof(sensor), **common))
                b = c[f"{sensor}_b_{a}"]
                rows.append(coefficient_row(sensor=sensor, axis=a, coefficient="bias", value=b.value, stderr=b.stderr,
                                            observable=b.observable and np.isfinite(b.stderr), method="tedaldi",
                                            ci=b if sensor == "accel" else None,
                                            dof=_dof(sensor) if sensor == "accel" else np.nan,
                                            note="initial static interval mean" if sensor == "gyro" else "", **common))
                for j, aj in enumerate(AXES):
                    name = _T_NAMES.get((i, j))
                    key = f"{sensor}_{name}" if name else None
                    if key in c:
                        m = c[key]
                        rows.append(coefficient_row(sensor=sensor, axis=a, coefficient=f"misalignment_{a}{aj}",
                                                    value=m.value, stderr=m.stderr, observable=m.observable,
                                                    method="tedaldi", ci=m, dof=_dof(sensor), **common))
    else:
        f = result.accel_fit
        d2r = np.pi / 180.0
        note = "imucal convention: R_g diagonal sign carries the rotation sense against expected_angle"
        for sensor, K, R, b, sK, sR, sb, fac in (
                ("accel", f.K_a, f.R_a, f.b_a, f.stderr["K_a"], f.stderr["R_a"], f.stderr["b_a"], 1.0),
                ("gyro", f.K_g, f.R_g, f.b_g, f.stderr["K_g"], f.stderr["R_g"], f.stderr["b_g"], d2r)):
            for i, a in enumerate(AXES):
                rows.append(coefficient_row(sensor=sensor, axis=a, coefficient="scale_factor", value=K[i, i],
                                            stderr=sK[i, i], observable=True, method="ferraris", **common))
                rows.append(coefficient_row(sensor=sensor, axis=a, coefficient="bias", value=b[i] * fac,
                                            stderr=sb[i] * fac, observable=True, method="ferraris", **common))
                sgn = np.sign(R[i, i])
                for j, aj in enumerate(AXES):
                    if j != i:
                        rows.append(coefficient_row(sensor=sensor, axis=a, coefficient=f"misalignment_{a}{aj}",
                                                    value=sgn * R[i, j], stderr=sR[i, j], observable=True,
                                                    method="ferraris", note=note if sensor == "gyro" else "", **common))
        # design.md's error model adds G f at the output, like the bias (y = K(I+E) w + b + G f; assets_lib.apply
        # inverts it so), and imucal's u_g = K_g R_g w + K_ga a + b_g adds K_ga a there too: G = K_ga (deg/s -> rad/s
        # per m/s^2), not K_ga / K_g (an input-referred value, off by the scale factor)
        for i, a in enumerate(AXES):
            for j, aj in enumerate(AXES):
                rows.append(coefficient_row(sensor="gyro", axis=a, coefficient=f"g_sensitivity_{aj}",
                                            value=f.K_ga[i, j] * d2r, stderr=f.stderr["K_ga"][i, j] * d2r,
                                            observable=True, method="ferraris", **common))
    return coefficient_frame(rows)


def plot_tablefree_png(imu: pd.DataFrame, result: TableFreeResult, title: str = "", max_points: int = 20000) -> bytes:
    """Calibrated specific force with the static poses shaded (Tedaldi) or the raw accel (Ferraris), as PNG."""
    from assets_lib.plotting import figure, png

    t = imu["time_s"].to_numpy(float)
    acc = imu[list(ACCEL_COLUMNS)].to_numpy(float)
    step = max(1, t.size // max_points)
    fig, ax = figure(1, 1, figsize=(9, 3.6), dpi=90, squeeze=True, margins_in=(0.8, 0.15, 0.55, 0.35))
    if result.method == "tedaldi":
        ax.plot(t[::step], result.accel_fit.apply(acc[::step]), lw=0.5)
        for a, b in zip(result.poses.starts, result.poses.ends):
            ax.axvspan(t[a], t[b - 1], color="g", alpha=0.15, lw=0)
        sub = (f"{result.poses.count} static poses, |f|-g RMS {1e3 * result.accel_fit.rms_mps2:.2f} mm/s^2, "
               f"gyro direction RMS {1e3 * result.gyro_fit.rms_rad:.2f} mrad")
    else:
        ax.plot(t[::step], result.accel_fit.calibrate_acc(acc[::step]), lw=0.5)
        sub = f"Ferraris, static |f|-g RMS {1e3 * result.diagnostics['static_norm_rms_mps2']:.2f} mm/s^2"
    ax.set_xlabel("t [s]")
    ax.set_ylabel("calibrated specific force [m/s^2]")
    ax.set_title(f"{title}  {sub}".strip(), fontsize=9)
    return png(fig)
