"""Export a calibration (one record or an assembled device calibration) to the files other tools read.

Formats (``EXPORTERS``, one function each with the same signature ``(cal) -> str``):

``kalibr``   Kalibr ``imu.yaml`` (input of ``kalibr_calibrate_imu_camera``): continuous-time white-noise density and
             bias random walk, one scalar per triad, plus ``update_rate``. Kalibr wants
             ``*_noise_density`` in [rad/s/sqrt(Hz)] / [m/s^2/sqrt(Hz)] = the Allan angle/velocity random walk
             coefficient N of IEEE 952 (sigma_Allan(tau) = N / sqrt(tau)), and ``*_random_walk`` in
             [rad/s^2/sqrt(Hz)] / [m/s^3/sqrt(Hz)] = the Allan rate random walk coefficient K
             (sigma_Allan(tau) = K sqrt(tau / 3)); both are already in those units in the record (SI), so no
             factor is applied. Kalibr discretizes them itself: sigma_d = N sqrt(update_rate) per sample and
             sigma_bd = K / sqrt(update_rate) per sample step (stated in the file as comments and tested). The
             scalar is the largest of the three axes (conservative). When the Allan fit found no K (only an upper
             bound), the 95 % upper bound is written and the file says so.
``openvins`` OpenVINS ``kalibr_imu_chain.yaml`` (%YAML:1.0): the same noise block plus the intrinsics of its
             measurement model  w_m = T_w R_IMUtoGYRO w_I + T_g a_I + b_g,  a_m = T_a R_IMUtoACC a_I + b_a
             (OpenVINS loads D_w = T_w^-1, D_a = T_a^-1). ``model: kalibr``: T_w, T_a lower triangular,
             R_IMUtoACC = I, so the file's IMU frame I is the ACCELEROMETER frame: M_a = T_a R_BtoI (RQ
             factorization of our M_a = diag(K_a)(I + E_a)), T_w R_IMUtoGYRO = M_g R_BtoI^T, T_g = G R_BtoI^T;
             ``model: rpng``: upper triangular, R_IMUtoGYRO = I, I = the GYRO frame. R_BtoI (our body/reference
             frame to the file's IMU frame, a rotation of the order of the misalignments) is written as a comment
             and in ``R_BODYtoIMU``-named comment lines: data in our body frame must be rotated by it. Biases are
             not part of the file (OpenVINS estimates them online); they are listed as comments. K2 and
             cross-coupling are not representable and are listed (with their size at 1 g) as comments.
``imucal``   imucal's calibration JSON (``TurntableCalibrationInfo``, format 2.0.0), loadable with
             ``imucal.management.load_calibration_info``: acc = R_a^-1 K_a^-1 (a - b_a),
             gyr = R_g^-1 K_g^-1 (w - b_g - K_ga acc), i.e. K_a = diag(K_a), R_a = I + E_a, K_ga = G exactly (our
             model factored the same way); units m/s^2 and rad/s from SI inputs. K2 and cross-coupling are not
             part of imucal's model (named in ``comment`` with the record hashes).
``firmware_json``, ``c_header``  The compensation matrices for firmware, SI, body axes:
             f0 = ACC_MAT (y_a - ACC_BIAS); repeat ACC_ITERATIONS times:
             f = ACC_MAT (y_a - ACC_BIAS - ACC_K2 .* f.^2 - f .* (ACC_KC f));
             w = GYR_MAT (y_g - GYR_BIAS - GYR_GSENS f), with ACC_MAT = M_a^-1, GYR_MAT = M_g^-1.

Frames and signs: body axes are the axes the record's reference inputs are expressed in (the test plan's body
frame, right-handed); rates positive counter-clockwise about each axis (right-hand rule); specific force
positive along +axis when the axis points up at rest (+g). Every file names the calibration's sha256.
"""

from __future__ import annotations

import json
import math

import numpy as np

from assets_lib.apply.compensate import ACCEL_ITERATIONS
from assets_lib.apply.model import Calibration, CalibrationError

AXES = ("x", "y", "z")


# ---------------------------------------------------------------------------------------------------------------
# Noise terms
# ---------------------------------------------------------------------------------------------------------------
def noise_term(cal: Calibration, sensor: str, parameter: str) -> tuple[float, str, str]:
    """(largest value over the axes [SI], how it was obtained, per-axis detail) of Allan ``parameter`` ('N' or 'K')."""
    if not cal.noise:
        raise CalibrationError(f"calibration {cal.identity_sha256[:16]}... of {cal.device_id} holds no noise terms (a "
                               "static run's record does): export a device calibration (imulab records DEVICE --out "
                               "cal.json) or the static run's record")
    vals, how = [], []
    for ax in AXES:
        ch = f"{sensor}_{ax}_{'radps' if sensor == 'gyro' else 'mps2'}"
        rows = [r for r in cal.noise if r.get("channel") == ch and r.get("parameter") == parameter]
        rows.sort(key=lambda r: r.get("method") != "fit")
        if not rows:
            raise CalibrationError(f"no Allan {parameter} term for channel {ch} in the calibration's noise terms")
        r = rows[0]
        if r.get("value") is not None and not r.get("is_upper_bound"):
            vals.append(float(r["value"]))
            how.append(f"{ax}: {r['value']:.6g} ({r.get('method')})")
        elif r.get("ci_hi") is not None:
            vals.append(float(r["ci_hi"]))
            how.append(f"{ax}: < {r['ci_hi']:.6g} (upper bound, {r.get('ci_level', 0.95):g} level)")
        else:
            raise CalibrationError(f"Allan {parameter} of {ch}: neither a value nor an upper bound")
    k = int(np.argmax(vals))
    return vals[k], ("upper bound" if "<" in how[k] else "identified"), "; ".join(how)


def _rate(cal: Calibration) -> float:
    if not cal.sample_rate_hz:
        raise CalibrationError("the calibration names no sample rate (update_rate)")
    return float(cal.sample_rate_hz)


def _noise_block(cal: Calibration, indent: str = "") -> list[str]:
    rate = _rate(cal)
    out = []
    for sensor, yk, un, urw in (("accel", "accelerometer", "m/s^2/sqrt(Hz)", "m/s^3/sqrt(Hz)"),
                                ("gyro", "gyroscope", "rad/s/sqrt(Hz)", "rad/s^2/sqrt(Hz)")):
        n, nhow, ndet = noise_term(cal, sensor, "N")
        k, khow, kdet = noise_term(cal, sensor, "K")
        out += [f"{indent}# {sensor} Allan N per axis [{un}]: {ndet}",
                f"{indent}# {sensor} Allan K per axis [{urw}]: {kdet}",
                f"{indent}# discrete per sample at {rate:g} Hz: white sigma = N*sqrt(rate) = {n * math.sqrt(rate):.6g}, "
                f"bias step sigma = K/sqrt(rate) = {k / math.sqrt(rate):.6g}",
                f"{indent}{yk}_noise_density: {n!r}  # [{un}] Allan N (largest axis, {nhow})",
                f"{indent}{yk}_random_walk: {k!r}  # [{urw}] Allan K (largest axis, {khow})"]
    return out


def _header(cal: Calibration, what: str, c: str = "#") -> list[str]:
    recs = ", ".join(f"{r['run_id']} {r['record_sha256'][:16]}" for r in cal.records)
    return [f"{c} {what} exported by imulab from the calibration of device {cal.device_id}",
            f"{c} calibration sha256 {cal.identity_sha256}" + (f", valid at {cal.at_utc}" if cal.at_utc else ""),
            f"{c} records: {recs}"]


def export_kalibr(cal: Calibration) -> str:
    """Kalibr imu.yaml (noise densities and random walks from the Allan identification; see the module doc)."""
    lines = _header(cal, "Kalibr imu.yaml") + _noise_block(cal) + [
        "rostopic: /imu0", f"update_rate: {_rate(cal)!r}  # [Hz]"]
    return "\n".join(lines) + "\n"


# ---------------------------------------------------------------------------------------------------------------
# OpenVINS intrinsics
# ---------------------------------------------------------------------------------------------------------------
def rq_lower(m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """M = L R with L lower triangular (positive diagonal) and R a proper rotation (QR of M^T)."""
    q, u = np.linalg.qr(m.T)  # M^T = Q U -> M = U^T Q^T
    s = np.diag(np.sign(np.diag(u)))
    q, u = q @ s, s @ u
    lo, r = u.T, q.T
    if np.linalg.det(r) < 0:  # cannot happen for a near-identity M; kept for safety
        raise CalibrationError("misalignment matrix has a reflection: cannot factor into triangular x rotation")
    return lo, r


def rq_upper(m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """M = U R with U upper triangular (positive diagonal) and R a proper rotation."""
    p = np.eye(3)[::-1]  # reversal permutation turns lower into upper triangular
    lo, r = rq_lower(p @ m @ p)
    return p @ lo @ p, p @ r @ p


def openvins_intrinsics(cal: Calibration, model: str = "kalibr") -> dict[str, np.ndarray]:
    """Tw, R_IMUtoGYRO, Ta, R_IMUtoACC, Tg and R_BODYtoIMU of OpenVINS' ``model`` ('kalibr' or 'rpng')."""
    ma, mg, g = cal.accel.matrix(), cal.gyro.matrix(), cal.gyro.g_sensitivity
    if model == "kalibr":
        ta, r_b2i = rq_lower(ma)  # IMU frame = accelerometer frame
        tw, r_i2g = rq_lower(mg @ r_b2i.T)
        r_i2a = np.eye(3)
    elif model == "rpng":
        tw, r_b2i = rq_upper(mg)  # IMU frame = gyro frame
        ta, r_i2a = rq_upper(ma @ r_b2i.T)
        r_i2g = np.eye(3)
    else:
        raise CalibrationError(f"OpenVINS model must be 'kalibr' or 'rpng', not {model!r}")
    return {"Tw": tw, "R_IMUtoGYRO": r_i2g, "Ta": ta, "R_IMUtoACC": r_i2a, "Tg": g @ r_b2i.T, "R_BODYtoIMU": r_b2i}


def _yaml_matrix(name: str, m: np.ndarray, indent: str = "  ") -> list[str]:
    return [f"{indent}{name}:"] + [f"{indent}  - [ {', '.join(repr(float(v)) for v in row)} ]" for row in m]


def export_openvins(cal: Calibration, model: str = "kalibr") -> str:
    """OpenVINS kalibr_imu_chain.yaml with noise and intrinsics in ``model``'s convention (see the module doc)."""
    mats = openvins_intrinsics(cal, model)
    a = cal.accel
    lines = ["%YAML:1.0"] + _header(cal, f"OpenVINS kalibr_imu_chain.yaml (model {model})") + [
        "# OpenVINS model: w_m = Tw R_IMUtoGYRO w_I + Tg a_I + b_g ; a_m = Ta R_IMUtoACC a_I + b_a (loads Dw = Tw^-1, "
        "Da = Ta^-1)",
        f"# IMU frame I = {'accelerometer' if model == 'kalibr' else 'gyroscope'} frame; our body (reference) frame B "
        "maps to it by R_BODYtoIMU (x_I = R_BODYtoIMU x_B):",
        *[f"#   R_BODYtoIMU row {i}: [{', '.join(f'{v:.15g}' for v in row)}]" for i, row in enumerate(mats["R_BODYtoIMU"])],
        f"# biases (estimated online by OpenVINS; from the record, SI): b_g = {cal.gyro.bias.tolist()} rad/s, "
        f"b_a = {a.bias.tolist()} m/s^2",
        "# not representable in OpenVINS (ignored): accel K2 at 1 g [m/s^2] = "
        f"{(a.k2 * 9.80665**2).tolist()}, largest cross-coupling at 1 g x 1 g [m/s^2] = "
        f"{float(np.abs(a.cross_coupling).max() * 9.80665**2):.3g}",
        *[f"# OpenVINS state Dw = Tw^-1 row {i}: [{', '.join(f'{v:.15g}' for v in row)}]"
          for i, row in enumerate(np.linalg.inv(mats["Tw"]))],
        *[f"# OpenVINS state Da = Ta^-1 row {i}: [{', '.join(f'{v:.15g}' for v in row)}]"
          for i, row in enumerate(np.linalg.inv(mats["Ta"]))],
        "imu0:",
        "  T_i_b:", *[f"    - [ {', '.join(repr(float(v)) for v in row)} ]" for row in np.eye(4)],
        *_noise_block(cal, "  "),
        "  rostopic: /imu0", "  time_offset: 0.0", f"  update_rate: {_rate(cal)!r}", f'  model: "{model}"']
    for k in ("Tw", "R_IMUtoGYRO", "Ta", "R_IMUtoACC", "Tg"):
        lines += _yaml_matrix(k, mats[k])
    return "\n".join(lines) + "\n"


def export_openvins_rpng(cal: Calibration) -> str:
    return export_openvins(cal, "rpng")


# ---------------------------------------------------------------------------------------------------------------
# imucal
# ---------------------------------------------------------------------------------------------------------------
def imucal_dict(cal: Calibration) -> dict:
    """imucal ``TurntableCalibrationInfo`` fields (format 2.0.0)."""
    a, g = cal.accel, cal.gyro
    ignored = []
    if np.any(a.k2) or np.any(a.cross_coupling):
        ignored.append(f"accel K2 {a.k2.tolist()} and cross-coupling (max {np.abs(a.cross_coupling).max():.3g}) "
                       "1/(m/s^2) are not part of imucal's model and are not applied by it")
    comment = (f"imulab calibration {cal.identity_sha256} of device {cal.device_id}"
               + (f" valid at {cal.at_utc}" if cal.at_utc else "") + "; records "
               + ", ".join(f"{r['run_id']}={r['record_sha256']}" for r in cal.records)
               + "; body axes of the record's reference frame; " + "; ".join(ignored))
    u_in_a, u_in_g, u_a, u_g = cal.units
    return {"acc_unit": u_a, "gyr_unit": u_g, "from_acc_unit": u_in_a, "from_gyr_unit": u_in_g,
            "comment": comment, "K_a": np.diag(a.scale).tolist(), "R_a": (np.eye(3) + a.misalignment_rad).tolist(),
            "b_a": a.bias.tolist(), "K_g": np.diag(g.scale).tolist(), "R_g": (np.eye(3) + g.misalignment_rad).tolist(),
            "K_ga": g.g_sensitivity.tolist(), "b_g": g.bias.tolist(), "cal_type": "Turntable",
            "_format_version": "2.0.0"}


def export_imucal(cal: Calibration) -> str:
    return json.dumps(imucal_dict(cal), indent=4, allow_nan=False) + "\n"


def calibration_from_imucal(doc: dict, device_id: str = "imucal") -> Calibration:
    """An imucal Ferraris/Turntable calibration JSON as a Calibration (the inverse of ``imucal_dict``): imucal's
    M = K R is refactored as diag(K')(I + E) with K' = diag(M), E = diag(K')^-1 M - I (zero diagonal), the same
    matrix; b and K_ga (= G) carry over. Units are imucal's (``from_*_unit`` -> ``*_unit``)."""
    from assets_lib.apply.model import Triad

    def triad(k, r, b, g=None):
        m = np.asarray(k, float) @ np.asarray(r, float)
        kd = np.diag(m).copy()
        e = m / kd[:, None] - np.eye(3)
        np.fill_diagonal(e, 0.0)
        t = Triad(kd, e, np.asarray(b, float), np.zeros(3), np.zeros((3, 3)), np.zeros(3))
        return t if g is None else Triad(**{**t.__dict__, "g_sensitivity": np.asarray(g, float)})

    units = (doc.get("from_acc_unit") or "?", doc.get("from_gyr_unit") or "?", doc.get("acc_unit") or "?",
             doc.get("gyr_unit") or "?")
    return Calibration(device_id, triad(doc["K_g"], doc["R_g"], doc["b_g"], doc["K_ga"]),
                       triad(doc["K_a"], doc["R_a"], doc["b_a"]), (), (), (), (), (
                           {"run_id": f"imucal {doc.get('cal_type')}", "record_sha256": "0" * 64, "test_kind": "imucal",
                            "start_time_utc": None, "store_version": None},), None, None, None, None, units)


# ---------------------------------------------------------------------------------------------------------------
# Firmware
# ---------------------------------------------------------------------------------------------------------------
def firmware_dict(cal: Calibration) -> dict:
    a, g = cal.accel, cal.gyro
    return {
        "device_id": cal.device_id, "calibration_sha256": cal.identity_sha256, "valid_at_utc": cal.at_utc,
        "records": [{k: r[k] for k in ("run_id", "record_sha256")} for r in cal.records],
        "units": {"gyro": "rad/s", "accel": "m/s^2", "ACC_K2": "1/(m/s^2)", "ACC_KC": "1/(m/s^2)",
                  "GYR_GSENS": "rad/s/(m/s^2)"},
        "procedure": ["f = ACC_MAT (y_a - ACC_BIAS)",
                      "repeat ACC_ITERATIONS times: f = ACC_MAT (y_a - ACC_BIAS - ACC_K2 .* f.^2 - f .* (ACC_KC f))",
                      "w = GYR_MAT (y_g - GYR_BIAS - GYR_GSENS f)"],
        "frames": "body axes of the record's reference frame, right-handed; rates right-hand positive; +g on an "
                  "axis pointing up at rest",
        "ACC_ITERATIONS": ACCEL_ITERATIONS,
        "ACC_BIAS": a.bias.tolist(), "ACC_MAT": np.linalg.inv(a.matrix()).tolist(), "ACC_K2": a.k2.tolist(),
        "ACC_KC": a.cross_coupling.tolist(),
        "GYR_BIAS": g.bias.tolist(), "GYR_MAT": np.linalg.inv(g.matrix()).tolist(),
        "GYR_GSENS": g.g_sensitivity.tolist(),
    }


def export_firmware_json(cal: Calibration) -> str:
    return json.dumps(firmware_dict(cal), indent=1, allow_nan=False) + "\n"


def _c_array(name: str, v) -> str:
    a = np.asarray(v, dtype=float)
    if a.ndim == 1:
        return f"static const double {name}[3] = {{{', '.join(f'{x:.17g}' for x in a)}}};"
    rows = ",\n    ".join("{" + ", ".join(f"{x:.17g}" for x in row) + "}" for row in a)
    return f"static const double {name}[3][3] = {{\n    {rows}}};"


def export_c_header(cal: Calibration) -> str:
    """C header of the compensation matrices (same content and procedure as ``firmware_json``)."""
    d = firmware_dict(cal)
    guard = "IMULAB_CAL_" + "".join(ch if ch.isalnum() else "_" for ch in cal.device_id.upper()) + "_H"
    lines = [f"/* {ln[2:]} */" for ln in _header(cal, "Compensation matrices (C header)")] + [
        "/* Procedure (SI units, body axes of the record's reference frame, right-handed):",
        *[f" *   {p}" for p in d["procedure"]], " */",
        f"#ifndef {guard}", f"#define {guard}",
        f'#define IMULAB_CAL_DEVICE_ID "{cal.device_id}"',
        f'#define IMULAB_CAL_SHA256 "{cal.identity_sha256}"',
        f"#define IMULAB_ACC_ITERATIONS {ACCEL_ITERATIONS}",
        _c_array("IMULAB_ACC_BIAS", d["ACC_BIAS"]) + "  /* m/s^2 */",
        _c_array("IMULAB_ACC_MAT", d["ACC_MAT"]),
        _c_array("IMULAB_ACC_K2", d["ACC_K2"]) + "  /* 1/(m/s^2) */",
        _c_array("IMULAB_ACC_KC", d["ACC_KC"]) + "  /* 1/(m/s^2) */",
        _c_array("IMULAB_GYR_BIAS", d["GYR_BIAS"]) + "  /* rad/s */",
        _c_array("IMULAB_GYR_MAT", d["GYR_MAT"]),
        _c_array("IMULAB_GYR_GSENS", d["GYR_GSENS"]) + "  /* rad/s per m/s^2 */",
        f"#endif /* {guard} */"]
    return "\n".join(lines) + "\n"


#: format name -> (exporter, default file name)
EXPORTERS = {
    "kalibr": (export_kalibr, "imu.yaml"),
    "openvins": (export_openvins, "kalibr_imu_chain.yaml"),
    "openvins-rpng": (export_openvins_rpng, "kalibr_imu_chain.yaml"),
    "imucal": (export_imucal, "imucal_calibration.json"),
    "firmware-json": (export_firmware_json, "imu_compensation.json"),
    "c-header": (export_c_header, "imu_compensation.h"),
}


def export(cal: Calibration, fmt: str) -> str:
    if fmt not in EXPORTERS:
        raise CalibrationError(f"unknown export format {fmt!r}; known: {', '.join(EXPORTERS)}")
    return EXPORTERS[fmt][0](cal)
