"""The table-free experiment: twin, recorded inputs and replicates of a hand-moved session (test kind ``tablefree``).

simreal.md sec. 2 ("compare with the calibrated simulator") for sessions without a table: the sensor model is the
table-free fit of the session itself (``tablefree_session.calibrate_tablefree``: Tedaldi accelerometer
a = T K (u - b) and gyro w = T_g K_g (u - b_g) by integration between poses [TEDALDI2014]; or Ferraris' closed
form a = R_a^-1 K_a^-1 (u - b_a), w = R_g^-1 K_g^-1 (u - K_ga a - b_g) [FERRARIS1995]), written uniformly as

    f = M_a (u_a - b_a),   w = M_g (u_g - G f - b_g)      (G = 0 for Tedaldi).

The recorded inputs u(t) are estimated from the data (nothing else is known about a hand-moved session):

* static poses (detected by the same detector as the fit, or the plan's annotated sections): specific force
  g * the pose's calibrated gravity direction, rate 0 (earth rate is not modelled, as in imu_tk and imucal);
* motion between poses: the calibrated rate and specific force low-passed at ``LOWPASS_HZ`` (hand motion; the
  low-pass keeps the real white noise from entering the truth), plus a constant body-rate correction per motion
  interval, solved so that integrating the truth (midpoint rotation vectors on the recorded time stamps, the
  fit's own integrator) carries the gravity direction of pose i exactly onto that of pose i+1: the twin is
  self-consistent, so whatever the real gyro-integration residual holds beyond noise is a gap;
* time stamps and the temperature log as recorded.

A replicate: raw = M_a^-1 f + b_a, M_g^-1 w + G f + b_g, plus Allan noise (IEEE 952 terms fitted on the longest
static interval, [IEEE952] C.1), quantized at the manifest's lsb, then pushed through ``calibrate_tablefree``
(the same code as the real session), and reduced to its residual rows (``TFRealisation``):

* ``A`` static-pose accelerometer residuals |f_i| - g (pose means as the fit uses them);
* ``S`` calibrated gyro means of each pose per channel (they should read 0: bias from the initial interval);
* ``P`` gyro-integration residuals R_i^T u_i - u_{i+1} per rotation between poses (3 components);
* the longest static interval's residual (Allan bands, spectrum).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import pandas as pd

from assets_lib.calibration.ferraris import STATIC_SECTIONS
from assets_lib.calibration.gyro_integration import _T, _Segments
from assets_lib.calibration.tablefree import apply_accel_params
from assets_lib.calibration.tablefree_session import (
    POSE_SAMPLES,
    _ferraris_sections,
    _slice,
    calibrate_tablefree,
)
from assets_lib.sim.earth import site_gravity_mps2
from assets_lib.sim.noise import AllanParams, allan_noise
from assets_lib.simreal.experiment import _lsb_si
from raw_schemas.tables import ACCEL_COLUMNS, GYRO_COLUMNS

LOWPASS_HZ = 10.0
CHANNELS6 = tuple(GYRO_COLUMNS) + tuple(ACCEL_COLUMNS)


@dataclass(frozen=True, eq=False)
class TFModel:
    """f = M_a (u_a - b_a); w = M_g (u_g - G f - b_g) (module docstring), SI per canonical unit."""

    m_a: np.ndarray
    b_a: np.ndarray
    m_g: np.ndarray
    g_sens: np.ndarray
    b_g: np.ndarray

    @staticmethod
    def of(res) -> TFModel:
        if res.method == "tedaldi":
            a, g = res.accel_fit, res.gyro_fit
            return TFModel(a.T * a.scale[None, :], a.bias.copy(), g.T * g.scale[None, :], np.zeros((3, 3)),
                           g.bias.copy())
        f = res.accel_fit
        d2r = np.pi / 180.0
        return TFModel(np.linalg.inv(f.K_a @ f.R_a), np.asarray(f.b_a, float), np.linalg.inv(f.K_g @ f.R_g),
                       np.asarray(f.K_ga, float) * d2r, np.asarray(f.b_g, float) * d2r)

    def calibrate(self, gyro_raw: np.ndarray, accel_raw: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        f = (self.m_a @ (accel_raw - self.b_a).T).T
        w = (self.m_g @ (gyro_raw - f @ self.g_sens.T - self.b_g).T).T
        return w, f

    def raw(self, w: np.ndarray, f: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        ua = np.linalg.solve(self.m_a, f.T).T + self.b_a
        ug = np.linalg.solve(self.m_g, w.T).T + f @ self.g_sens.T + self.b_g
        return ug, ua

    def to_json(self) -> dict:
        return {"accel_matrix": self.m_a.tolist(), "accel_bias_si": self.b_a.tolist(), "gyro_matrix": self.m_g.tolist(),
                "gyro_g_sensitivity_radps_per_mps2": self.g_sens.tolist(), "gyro_bias_si": self.b_g.tolist()}


@dataclass(frozen=True, eq=False)
class TFInputs:
    """Recorded inputs of one table-free run (identical for the real run and every replicate)."""

    run_id: str
    manifest: object
    gravity_mps2: float
    t_s: np.ndarray
    temperature_degc: np.ndarray  # NaN when not logged
    t_on_s: np.ndarray
    omega_true: np.ndarray  # (n,3) twin truth in the calibrated frame
    f_true: np.ndarray
    lsb_si: np.ndarray
    noise: tuple  # 6 AllanParams (raw canonical units)
    static_ref: slice  # the longest static interval (Allan bands, spectrum)


@dataclass(frozen=True, eq=False)
class TFRealisation:
    """Residual rows of one realisation (real or replicate) of a table-free run."""

    run_id: str
    method: str
    model: TFModel
    signals: dict  # w, f (calibrated, (n,3)), T (n,), t (n,), t_on (n,)
    pose_starts: np.ndarray
    pose_ends: np.ndarray
    pose_t: np.ndarray  # pose centre times
    a_y: np.ndarray  # (n_p,) |f_i| - g
    a_u: np.ndarray  # (n_p,3) gravity directions
    a_ranges: tuple  # (start, stop) sample ranges of the pose means of A
    a_nuis: np.ndarray | None  # (n_p, 9) Jacobian of A w.r.t. the accelerometer fit (Tedaldi), None for Ferraris
    s_y: np.ndarray  # (n_p,3) calibrated gyro pose means
    p_y: np.ndarray  # (n_pairs,3) integration residuals (empty for Ferraris)
    p_nuis: np.ndarray | None  # (3 n_pairs, 9) Jacobian w.r.t. T_g, K_g
    pair_fun: object  # w (n,3) -> (n_pairs,3) integration residuals (None for Ferraris)
    static_resid: np.ndarray  # (m,6) raw residual of the longest static interval
    fs_hz: float
    diagnostics: dict = field(default_factory=dict)


def _static_ranges(res, manifest, t) -> tuple[np.ndarray, np.ndarray]:
    if res.method == "tedaldi":
        return np.asarray(res.poses.starts), np.asarray(res.poses.ends)
    sec = _ferraris_sections(manifest.plan)
    sl = [_slice(t, sec[k]) for k in STATIC_SECTIONS]
    o = np.argsort([s.start for s in sl])
    return np.array([sl[i].start for i in o]), np.array([sl[i].stop for i in o])


def _reference(manifest, t, starts, ends) -> slice:
    steps = [s for s in manifest.plan.steps if s.kind == "pose"]
    if steps and not _ferraris_sections(manifest.plan):
        return _slice(t, steps[0])
    k = int(np.argmax(np.asarray(ends) - np.asarray(starts)))
    return slice(int(starts[k]), int(ends[k]))


def pair_residual_fun(t_s, starts, ends, dirs):
    """w (n,3) -> (n_pairs,3) R_i^T u_i - u_{i+1}, with the gyro fit's integrator ([TEDALDI2014] eq. 14-17)."""
    seg = _Segments(t_s, np.asarray(ends)[:-1], np.asarray(starts)[1:])
    u = dirs / np.linalg.norm(dirs, axis=1, keepdims=True)

    def fun(w):
        R = seg.rotations(np.asarray(w, float))
        return np.einsum("kji,kj->ki", R, u[:-1]) - u[1:]

    return fun


def realise(manifest, imu: pd.DataFrame, gravity_mps2: float, static_ref: slice | None = None) -> TFRealisation:
    """Calibrate one realisation with the library code and reduce it to residual rows (module docstring)."""
    res = calibrate_tablefree(manifest, imu, gravity_mps2)
    t = imu["time_s"].to_numpy(float)
    ug = imu[list(GYRO_COLUMNS)].to_numpy(float)
    ua = imu[list(ACCEL_COLUMNS)].to_numpy(float)
    model = TFModel.of(res)
    w, f = model.calibrate(ug, ua)
    starts, ends = _static_ranges(res, manifest, t)
    T = imu["temperature_degc"].to_numpy(float, na_value=np.nan) if "temperature_degc" in imu else np.full(t.size, np.nan)
    sig = {"w": w, "f": f, "T": T, "t": t, "t_on": t - t[0]}
    if res.method == "tedaldi":
        rng_ = tuple((int(a), int(min(b, a + POSE_SAMPLES))) for a, b in zip(starts, ends))
        m = np.array([ua[a:b].mean(0) for a, b in rng_])
        af = res.accel_fit
        p0 = np.r_[af.T[0, 1], af.T[0, 2], af.T[1, 2], af.scale, af.bias]
        a_y = np.asarray(af.residual_mps2, float)

        def a_res(p):
            return np.linalg.norm(apply_accel_params(p, m), axis=1) - gravity_mps2

        a_nuis = _num_jac(a_res, p0, np.r_[np.full(3, 1e-6), np.abs(p0[3:6]) * 1e-6, np.maximum(np.abs(p0[6:9]), 1.0) * 1e-7])
        dirs = af.apply(m)
        gf = res.gyro_fit
        pf = pair_residual_fun(t, starts, ends, dirs)
        pg = np.r_[gf.T[0, 1], gf.T[0, 2], gf.T[1, 0], gf.T[1, 2], gf.T[2, 0], gf.T[2, 1], gf.scale]

        def p_res(p):
            return pf(((_T(p) * p[6:9][None, :]) @ (ug - gf.bias).T).T).ravel()

        p_nuis = _num_jac(p_res, pg, np.r_[np.full(6, 1e-6), np.abs(pg[6:9]) * 1e-6])
        p_y = np.asarray(gf.residual, float)
    else:
        rng_ = tuple((int(a), int(b)) for a, b in zip(starts, ends))
        mf = np.array([f[a:b].mean(0) for a, b in rng_])
        a_y = np.linalg.norm(mf, axis=1) - gravity_mps2
        dirs = mf
        a_nuis = p_nuis = pf = None
        p_y = np.zeros((0, 3))
    s_y = np.array([w[a:b].mean(0) for a, b in zip(starts, ends)])
    ref = static_ref if static_ref is not None else _reference(manifest, t, starts, ends)
    raw = np.column_stack([ug, ua])[ref]
    fs = 1.0 / float(np.median(np.diff(t)))
    return TFRealisation(manifest.run_id, res.method, model, sig, starts, ends, 0.5 * (t[starts] + t[np.maximum(ends - 1, 0)]),
                         a_y, dirs / np.linalg.norm(dirs, axis=1, keepdims=True), rng_, a_nuis, s_y, p_y, p_nuis, pf,
                         raw - raw.mean(0), fs, dict(res.diagnostics))


def _num_jac(fun, p0, h):
    cols = []
    for i in range(p0.size):
        e = np.zeros(p0.size)
        e[i] = h[i]
        cols.append((fun(p0 + e) - fun(p0 - e)) / (2 * h[i]))
    return np.column_stack(cols)


# ---------------------------------------------------------------------------------------------------------------
# recorded inputs and the twin's truth
# ---------------------------------------------------------------------------------------------------------------
def _lowpass(x: np.ndarray, fs: float) -> np.ndarray:
    from scipy.signal import butter, sosfiltfilt

    fc = min(LOWPASS_HZ, 0.25 * fs)
    sos = butter(4, fc / (0.5 * fs), output="sos")
    return sosfiltfilt(sos, x, axis=0)


def consistent_rates(t, w, starts, ends, dirs, iters: int = 4) -> tuple[np.ndarray, np.ndarray]:
    """Add a constant body rate per motion interval so that integrating ``w`` maps pose i's gravity direction onto
    pose i+1's (least-norm correction: the rotation about gravity is left as recorded). Returns (w, corrections)."""
    n_pairs = len(starts) - 1
    if n_pairs < 1:
        return w, np.zeros((0, 3))
    seg_id = np.full(t.size, -1)
    for k in range(n_pairs):
        seg_id[int(ends[k]):int(starts[k + 1])] = k
    inside = seg_id >= 0
    fun = pair_residual_fun(t, starts, ends, dirs)
    C = np.zeros((n_pairs, 3))

    def wc(C_):
        w2 = w.copy()
        w2[inside] += C_[seg_id[inside]]
        return w2

    h = 1e-5
    for _ in range(iters):
        r0 = fun(wc(C))
        J = np.stack([(fun(wc(C + h * np.eye(3)[a][None, :])) - r0) / h for a in range(3)], axis=2)  # (k,3,3)
        jtj = np.einsum("kia,kib->kab", J, J)
        lam = 1e-8 * np.trace(jtj, axis1=1, axis2=2)[:, None, None] * np.eye(3) + 1e-300 * np.eye(3)
        dc = -np.linalg.solve(jtj + lam, np.einsum("kia,ki->ka", J, r0)[..., None])[..., 0]
        C = C + dc
    return wc(C), C


def _noise_params(raw_ref: np.ndarray, fs: float, lsb: np.ndarray) -> tuple:
    """IEEE 952 terms per channel of the longest static interval ([IEEE952] C.1), the quantization the twin applies
    explicitly removed from the white term; white noise only when the interval is too short for a fit."""
    from assets_lib.noise.allan.estimators import allan_deviation
    from assets_lib.noise.identification import fit_noise

    out = []
    for j in range(6):
        x = raw_ref[:, j] - raw_ref[:, j].mean()
        q2 = lsb[j] ** 2 / (12.0 * fs) if lsb[j] > 0 else 0.0
        n2, b, k = max(float(np.var(x, ddof=1)) / fs - q2, 0.0), 0.0, 0.0
        if x.size / fs >= 20.0:
            try:
                nf = fit_noise(allan_deviation(x, fs, "octave"), sensor="si")
                th = dict(zip(nf.terms, nf.theta))
                # theta holds the squares; the twin quantizes explicitly (lsb^2/12 white), so Q is not replayed
                n2 = max(float(th.get("N", n2)) - q2, 0.0)
                b = float(np.sqrt(max(th.get("B", 0.0), 0.0)))
                k = float(np.sqrt(max(th.get("K", 0.0), 0.0)))
            except (ValueError, np.linalg.LinAlgError):
                pass
        out.append(AllanParams(n=float(np.sqrt(n2)), b=b, k=k))
    return tuple(out)


def recorded_inputs(manifest, imu: pd.DataFrame, real: TFRealisation) -> TFInputs:
    """The twin's truth and recorded inputs of a run from its real realisation (module docstring)."""
    t = real.signals["t"]
    fs = real.fs_hz
    g = site_gravity_mps2(manifest.site)
    w_lp = _lowpass(real.signals["w"], fs)
    f_lp = _lowpass(real.signals["f"], fs)
    starts, ends = real.pose_starts, real.pose_ends
    static = np.zeros(t.size, bool)
    for (a, b), u in zip(zip(starts, ends), real.a_u):
        static[a:b] = True
        f_lp[a:b] = g * u
        w_lp[a:b] = 0.0
    if real.method == "tedaldi":
        w_true, _ = consistent_rates(t, w_lp, starts, ends, real.a_u)
    else:
        w_true = w_lp
    ref = _reference(manifest, t, starts, ends)
    lsb = _lsb_si(manifest)
    ug = imu[list(GYRO_COLUMNS)].to_numpy(float)
    ua = imu[list(ACCEL_COLUMNS)].to_numpy(float)
    raw_ref = np.column_stack([ug, ua])[ref]
    if raw_ref.shape[0] / fs < 20.0:  # Ferraris sections: pool the within-section scatter of every static section
        raw_ref = np.vstack([np.column_stack([ug, ua])[a:b] - np.column_stack([ug, ua])[a:b].mean(0)
                             for a, b in zip(starts, ends)])
    T = real.signals["T"]
    return TFInputs(manifest.run_id, manifest, g, t, T, real.signals["t_on"], w_true, f_lp, lsb,
                    _noise_params(raw_ref, fs, lsb), ref)


@dataclass(frozen=True, eq=False)
class TFTwin:
    """The table-free twin of a device: per run its fitted model and recorded inputs, plus accepted effects."""

    device_id: str
    models: dict  # run_id -> TFModel
    inputs: dict  # run_id -> TFInputs
    effects: tuple = ()  # (family, channel name, coefficients, shape, signature function)

    def with_effects(self, effects) -> TFTwin:
        return TFTwin(self.device_id, self.models, self.inputs, tuple(effects))

    def to_json(self) -> dict:
        return {"format": "imulab.simreal.tablefree_model/1", "device_id": self.device_id,
                "runs": {r: {**m.to_json(), "noise_allan_si": {c: {"n": p.n, "b": p.b, "k": p.k}
                                                              for c, p in zip(CHANNELS6, self.inputs[r].noise)}}
                         for r, m in self.models.items()},
                "effects": [{"family": f, "channel": c, "coefficients": list(map(float, np.atleast_1d(v))), "shape": s}
                            for f, c, v, s, _ in self.effects],
                "truth": "recorded inputs estimated from the data: poses from the calibrated accelerometer, rotations "
                         "from the gyro-integrated attitude (docs/simreal.md, table-free sessions)"}


def simulate_tablefree(twin: TFTwin, run_id: str, rng: np.random.Generator) -> pd.DataFrame:
    """A replicate of a recorded table-free run (canonical frame)."""
    inp = twin.inputs[run_id]
    w, f = inp.omega_true.copy(), inp.f_true.copy()
    sig = {"w": inp.omega_true, "f": inp.f_true, "T": inp.temperature_degc, "t": inp.t_s, "t_on": inp.t_on_s}
    for _fam, ch, coef, shape, fn in twin.effects:
        j = ("gyro_x", "gyro_y", "gyro_z", "accel_x", "accel_y", "accel_z").index(ch)
        d = fn(sig, j % 3, shape) @ np.atleast_1d(coef)
        (w if j < 3 else f)[:, j % 3] += d
    ug, ua = twin.models[run_id].raw(w, f)
    y = np.column_stack([ug, ua])
    n = y.shape[0]
    fs = 1.0 / float(np.median(np.diff(inp.t_s)))
    for j in range(6):
        y[:, j] += allan_noise(n, fs, inp.noise[j], rng)
        if inp.lsb_si[j] > 0:
            y[:, j] = np.rint(y[:, j] / inp.lsb_si[j]) * inp.lsb_si[j]
    df = pd.DataFrame({"time_s": inp.t_s})
    for j, c in enumerate(CHANNELS6):
        df[c] = y[:, j]
    df["temperature_degc"] = inp.temperature_degc
    df["counter"] = np.arange(n, dtype=np.int64)
    return df
