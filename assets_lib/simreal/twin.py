"""The base twin: the device model fitted from the device's own runs, and replicates driven by recorded inputs.

Sensor model of docs/design.md ([SEED000] eq. 1-2): gyro y = M_g omega + b + G f, accel y = M_a f + b + K2 f^2 +
f (Kc f); noise from the IEEE 952 Annex C terms. Every coefficient comes from the library fits of the device's
own runs (``fit_gyro_rate`` rows for M_g, ``fit_gyro_static`` for G, ``fit_accel_multiposition`` for M_a, K2,
Kc), per power cycle, the bias per run (weighted mean of the run's plateau residuals), the noise of each channel
from segmentation's pooled Allan models of the runs (median of Q, N, K; B from the mean of their flicker
variance estimates), and
the output rails where the real data pile up at a full-scale value. A replicate of a run (``simulate_run_imu``)
uses the run's recorded time stamps, temperature log and table motion; the twin's effects (``effects.py``) are
added before saturation and quantization, like the simulator's effect chain.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field

import numpy as np
import pandas as pd

from assets_lib.calibration.segmentation import CHANNELS
from assets_lib.noise.pooled import flicker_b_of_avar
from assets_lib.sim.noise import AllanParams, allan_noise
from assets_lib.simreal.experiment import CHANNEL_NAMES, DeviceExperiment, RunInputs

AX = "xyz"


@dataclass(frozen=True, eq=False)
class CycleModel:
    """Deterministic model of one power cycle (SI)."""

    gyro_m: np.ndarray  # (3,3) diag(K)(I+E)
    gyro_g: np.ndarray  # (3,3) rad/s per m/s^2
    accel_m: np.ndarray
    accel_k2: np.ndarray  # (3,)
    accel_kc: np.ndarray  # (3,3)

    def predict(self, omega: np.ndarray, f: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        g = omega @ self.gyro_m.T + f @ self.gyro_g.T
        a = f @ self.accel_m.T + self.accel_k2 * f**2 + f * (f @ self.accel_kc.T)
        return g, a


@dataclass(frozen=True, eq=False)
class TwinModel:
    """Base twin of a device: per-cycle models, per-run biases, per-channel noise, rails, resolution."""

    device_id: str
    cycles: dict  # power cycle -> CycleModel
    bias: dict  # run_id -> (6,) SI
    noise: tuple  # 6 AllanParams
    rails: tuple  # (gyro rail or None, accel rail or None), SI
    effects: tuple = field(default=())  # accepted effects: tuple[(family, channel, coefficients), ...]
    gm: tuple = field(default=())  # per channel (sigma, tau_s) of a Gauss-Markov term (noise re-estimation), or ()

    def cycle(self, pc: int) -> CycleModel:
        if pc in self.cycles:
            return self.cycles[pc]
        k = min(self.cycles, key=lambda c: abs(c - pc))
        return self.cycles[k]

    def with_effects(self, effects) -> TwinModel:
        return TwinModel(self.device_id, self.cycles, self.bias, self.noise, self.rails, tuple(effects), self.gm)

    def with_noise(self, noise: tuple, gm: tuple) -> TwinModel:
        return TwinModel(self.device_id, self.cycles, self.bias, tuple(noise), self.rails, self.effects, tuple(gm))

    def to_json(self) -> dict:
        """Documented device-model format (docs/simreal.md sec. "twin file"): SI, one entry per power cycle."""
        return {
            "format": "imulab.simreal.device_model/1",
            "device_id": self.device_id,
            "power_cycles": {
                str(pc): {"gyro_matrix": m.gyro_m.tolist(), "gyro_g_sensitivity_radps_per_mps2": m.gyro_g.tolist(),
                          "accel_matrix": m.accel_m.tolist(), "accel_k2_per_mps2": m.accel_k2.tolist(),
                          "accel_cross_coupling_per_mps2": m.accel_kc.tolist()}
                for pc, m in sorted(self.cycles.items())
            },
            "bias_by_run_si": {r: list(map(float, b)) for r, b in self.bias.items()},
            "noise_allan_si": {ch: {"q": p.q, "n": p.n, "b": p.b, "k": p.k, "r": p.r}
                               for ch, p in zip(CHANNEL_NAMES, self.noise)},
            "rails_si": {"gyro": self.rails[0], "accel": self.rails[1]},
            "effects": [{"family": f, "channel": c, "coefficients": list(map(float, np.atleast_1d(v))),
                         "shape": s} for f, c, v, s in self.effects],
        }

    def to_device_model(self, runs) -> dict:
        """The twin as a device-model file (``raw_schemas/device_model.schema.json``, replayed by ``imulab simulate
        --device-model FILE --replay RUN``): per power cycle K, E from diag(K)(I + E), linear G, accelerometer
        matrix, K2 and cross-coupling; the cycle's bias = mean of its runs' fitted biases (each run's own bias in
        ``provenance.bias_by_run_si``); Allan terms per axis; LSB and rails from the manifests; accepted effects as
        the simulator's effect families (``assets_lib.sim.effects``), coefficients converted by
        :func:`effect_spec` (the library regressor coefficients stay in ``provenance.effects``)."""
        from raw_schemas.device_model import DeviceModel

        man = runs[0].manifest
        cycles = []
        for pc, m in sorted(self.cycles.items()):
            rb = [self.bias[r.run_id] for r in runs if r.power_cycle == pc and r.run_id in self.bias]
            b = np.mean(rb, axis=0) if rb else np.zeros(6)
            cycles.append({"index": int(pc), "gyro": _triad_dict(m.gyro_m, b[:3], "radps", g=m.gyro_g),
                           "accel": _triad_dict(m.accel_m, b[3:], "mps2", k2=m.accel_k2, kc=m.accel_kc),
                           "sources": [r.run_id for r in runs if r.power_cycle == pc]})
        ch = man.channels

        def lsb(name, fam):
            spec = ch.get(name)
            if spec is not None and spec.lsb and spec.lsb_unit:
                return float(spec.lsb), spec.lsb_unit
            return 1e-12, "rad/s" if fam == "gyro" else "m/s^2"

        (gl, gu), (al, au) = lsb("gyro_x", "gyro"), lsb("accel_x", "accel")
        gm = self.gm or ((0.0, 1.0),) * 6
        noise = {tri: {ax: {"q": p.q, "n": p.n, "b": p.b, "k": p.k, "r": p.r, "gm_sigma": float(g[0]),
                            "gm_tau_s": float(g[1])}
                       for ax, p, g in zip(AX, self.noise[3 * i:3 * i + 3], gm[3 * i:3 * i + 3])}
                 for i, tri in enumerate(("gyro", "accel"))}
        omega_max = max([float(np.max(np.abs(r.table_rate_radps))) for r in runs if r.kind == "rate"] or [1.0])
        axis = next((np.asarray(r.manifest.plan.table_axis_level, float) for r in runs if r.kind == "rate"),
                    np.array([0.0, 0.0, 1.0]))
        effects = [effect_spec(f, c, v, s_, omega_max, axis) for f, c, v, s_ in self.effects]
        d = {
            "schema_version": "1.0",
            "device": {"id": man.device.id, "model": man.device.model, "grade": man.device.grade},
            "sample_rate_hz": float(man.sample_rate_hz),
            "outputs": {"gyro_lsb": gl, "gyro_lsb_unit": gu, "accel_lsb": al, "accel_lsb_unit": au,
                        "gyro_full_scale_radps": self.rails[0], "accel_full_scale_mps2": self.rails[1]},
            "noise": noise,
            "power_cycles": cycles,
            "effects": [e for e in effects if e is not None],
            "provenance": {"source": "imulab diagnose (assets_lib.simreal): base twin fitted from the device's runs "
                                     "plus the accepted effects",
                           "bias_by_run_si": {r: list(map(float, b)) for r, b in self.bias.items()},
                           "effects": [{"family": f, "channel": c, "coefficients": list(map(float, np.atleast_1d(v))),
                                        "shape": s_} for f, c, v, s_ in self.effects]},
        }
        return DeviceModel.model_validate(d).model_dump(mode="json")


def _triad_dict(m: np.ndarray, b: np.ndarray, unit: str, g=None, k2=None, kc=None) -> dict:
    k = np.diag(m).copy()
    k[k == 0] = 1.0
    e = m / k[:, None] - np.eye(3)
    np.fill_diagonal(e, 0.0)
    out = {"scale_factor": k.tolist(), "misalignment_rad": e.tolist(), f"bias_{unit}": [float(x) for x in b]}
    if g is not None:
        out["g_sensitivity_radps_per_mps2"] = np.asarray(g, float).tolist()
    if k2 is not None:
        out["k2_per_mps2"] = np.asarray(k2, float).tolist()
        kc = np.asarray(kc, float).copy()
        np.fill_diagonal(kc, 0.0)
        out["cross_coupling_per_mps2"] = kc.tolist()
    return out


def _level_basis(axis: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The two level-frame unit vectors perpendicular to the table axis used by ``experiment.run_inputs``."""
    a = np.asarray(axis, float)
    e1 = np.cross(a, [0.0, 0.0, 1.0]) if abs(a[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
    e1 = e1 - a * (a @ e1)
    e1 /= np.linalg.norm(e1)
    return e1, np.cross(a, e1)


def effect_spec(family: str, channel, coef, shape, omega_max: float, axis) -> dict | None:
    """An accepted library effect as the simulator's effect family (``{"family", "params"}``, SI): the library
    regressors of ``effects.py`` are the simulator's forms to first order (docs/simreal.md, twin file)."""
    c = [float(x) for x in np.atleast_1d(coef)]
    j = None if channel is None else CHANNEL_NAMES.index(channel)
    gyro = j is not None and j < 3

    def vec(v):
        out = [0.0, 0.0, 0.0]
        out[j % 3] = v
        return out

    z3 = [0.0, 0.0, 0.0]
    if family == "temperature_bias":
        p = {"gyro_radps_per_k" if gyro else "accel_mps2_per_k": vec(c[0]), "lag_s": float(shape or 0.0)}
    elif family == "temperature_scale_factor":
        p = {"gyro_per_k" if gyro else "accel_per_k": vec(c[0]), "lag_s": float(shape or 0.0)}
    elif family == "warmup_bias":
        p = {"tau_s": [float(shape)], "gyro_radps": [vec(c[0]) if gyro else z3], "accel_mps2": [z3 if gyro else vec(c[0])]}
    elif family == "bias_ramp":
        p = {"gyro_radps_per_s" if gyro else "accel_mps2_per_s": vec(c[0])}
    elif family == "g_sensitivity":
        q = [[0.0] * 6 for _ in range(3)]
        q[j][:3] = c[:3]
        p = {"quadratic_radps_per_mps2sq": q}
    elif family == "scale_factor_nonlinearity":
        fs = float(omega_max)
        p = {"sensor": "gyro", "full_scale": fs, "form": "polynomial", "quadratic": vec(c[0] * fs), "cubic": vec(c[1] * fs**2)}
    elif family == "scale_factor_asymmetry":
        p = {"gyro": vec(2.0 * c[0])}
    elif family == "lever_arm":
        p = {"position_m": c[:3]}
    elif family == "table_rate_error":
        p = {"ripple_1_per_rev": float(np.hypot(c[0], c[1])), "ripple_1_phase_rad": float(np.arctan2(c[1], c[0])),
             "ripple_2_per_rev": float(np.hypot(c[2], c[3])), "ripple_2_phase_rad": float(np.arctan2(c[3], c[2]))}
    elif family == "table_wobble":
        e1, e2 = _level_basis(axis)
        eps = c[0] * e1 + c[1] * e2  # small rotation of the true orientation, level frame
        a = np.asarray(axis, float)
        s1 = np.cross(np.cross(a, [0.0, 1.0, 0.0]) if abs(a[0]) < 0.9 else np.cross(a, [0.0, 0.0, 1.0]), a)
        s1 /= np.linalg.norm(s1)
        s2 = np.cross(a, s1)  # the simulator's tilt basis (TableWobble.tilt_rotation): eps = beta (a x d)
        p = {"tilt_rad": float(np.linalg.norm(eps)), "azimuth_rad": float(np.arctan2(-eps @ s1, eps @ s2))}
    elif family == "timebase_error":
        p = {"clock_rate_error": c[0], "integrating_outputs": False}
    else:
        return None
    return {"family": family, "params": p}


def _cycle_model(exp: DeviceExperiment, pc: int) -> CycleModel | None:
    from assets_lib.calibration.multiposition import (
        fit_accel_multiposition,
        fit_gyro_static,
    )
    from assets_lib.calibration.rate_fit import fit_gyro_rate

    runs = [r for r in exp.runs if r.power_cycle == pc]
    gm, gg, am, k2, kc = np.eye(3), np.zeros((3, 3)), np.eye(3), np.zeros(3), np.zeros((3, 3))
    found = False
    for r in runs:
        p = exp.processed[r.run_id].plateaus
        try:
            if r.kind == "rate" and (p["kind"] == "rate").any():
                rf = fit_gyro_rate(p, cross_check=False)
                for i, ax in enumerate(rf.axes):
                    v, _ = ax.linear_row()
                    gm[i] = v
                found = True
            elif r.kind in ("multiposition", "tumble") and (p["kind"] == "static").sum() >= 6 and r.kind == "multiposition":
                af = fit_accel_multiposition(p)
                for i, ax in enumerate(af.axes):
                    f = ax.fit
                    val = dict(zip(f.names, np.where(f.observable, f.value, 0.0)))
                    am[i, i] = val.get("scale_factor", 1.0) or 1.0
                    for j, a in enumerate(AX):
                        if j != i:
                            am[i, j] = val.get(f"misalignment_{AX[i]}{a}", 0.0)
                            kc[i, j] = val.get(f"cross_coupling_{AX[i]}{a}", 0.0)
                    k2[i] = val.get("k2", 0.0)
                gf = fit_gyro_static(p)
                for i, ax in enumerate(gf.axes):
                    for j, a in enumerate(AX):
                        c = ax.g_sensitivity.get(a)
                        if c is None:
                            continue
                        v, ob = (c.value, c.observable) if hasattr(c, "value") else (c[0], c[2])
                        gg[i, j] = v if ob and np.isfinite(v) else 0.0
                found = True
        except ValueError:
            continue
    return CycleModel(gm, gg, am, k2, kc) if found else None


def _rails(exp: DeviceExperiment) -> tuple:
    out = []
    for sl in (slice(0, 3), slice(3, 6)):
        rail = None
        for imu in exp.imu.values():
            y = np.abs(imu[list(CHANNELS)[sl]].to_numpy(float))
            top = float(np.nanmax(y))
            if top > 0 and np.mean(y >= top * (1 - 1e-9)) > 1e-3:  # pile-up at one value: a rail
                rail = top if rail is None else max(rail, top)
        out.append(rail)
    return tuple(out)


def _noise(exp: DeviceExperiment) -> tuple:
    # median over every run's pooled plateau model: short plateaus bound the taus, so a slow deterministic drift
    # of the long static record (temperature, warm-up) does not leak into the twin's noise (measured: with the
    # static record alone a hidden temperature bias inflated K and hid itself from the plateau views)
    # B: the mean over runs of each run's flicker variance estimate (segmentation's ``{ch}_flicker_b``: the B term
    # also when the SEM model selection left it out), not the median of the selected B: a short run often reads B
    # as exactly 0, and the median of such runs was 0 where the truth is not (measured on the default archive's
    # TAC-002: gyro B 0 against a true 3.9e-6 rad/s, accel_z 0 against 1.96e-4 m/s^2; replicates without bias
    # instability left the real plateau residuals and the long-tau Allan bands over-dispersed, which at R = 100
    # made the null device significant)
    src = list(exp.runs)
    out = []
    for j, ch in enumerate(CHANNELS):
        vals, fl = [], []
        for r in src:
            fit = exp.processed[r.run_id].noise_fits.get(ch)
            if fit is None:
                continue
            fl.append(fit.flicker_avar_best)
            vals.append((float(np.sqrt(np.median(fit.q2))), float(np.sqrt(np.median(fit.n2))),
                         float(np.sqrt(max(fit.k2, 0.0)))))
        v = np.median(np.array(vals), axis=0) if vals else np.zeros(3)
        b = flicker_b_of_avar(np.mean(fl)) if fl else 0.0
        out.append(AllanParams(q=v[0], n=v[1], b=b, k=v[2]))
    return tuple(out)


def fit_twin(exp: DeviceExperiment) -> TwinModel:
    """Base twin from the device's own fits (module docstring)."""
    cycles = {}
    for pc in sorted({r.power_cycle for r in exp.runs}):
        m = _cycle_model(exp, pc)
        if m is not None:
            cycles[pc] = m
    if not cycles:
        cycles[0] = CycleModel(np.eye(3), np.zeros((3, 3)), np.eye(3), np.zeros(3), np.zeros((3, 3)))
    twin = TwinModel(exp.device_id, cycles, {}, _noise(exp), _rails(exp))
    bias = {}
    for r in exp.runs:
        p = exp.processed[r.run_id].plateaus
        p = p[~p["flagged"] & (p["n_samples"] > 0)]
        w = p[[f"omega_ref_{a}_radps" for a in AX]].to_numpy(float)
        f = p[[f"f_ref_{a}_mps2" for a in AX]].to_numpy(float)
        y = p[[f"{c}_mean" for c in CHANNELS]].to_numpy(float)
        s = p[[f"{c}_sem" for c in CHANNELS]].to_numpy(float)
        g, a = twin.cycle(r.power_cycle).predict(w, f)
        res = y - np.column_stack([g, a])
        ok = np.ones(len(p), bool)
        if twin.rails[0]:
            ok &= np.all(np.abs(y[:, :3]) < 0.98 * twin.rails[0], axis=1)
        b = np.zeros(6)
        for j in range(6):
            m = ok & np.isfinite(res[:, j]) & np.isfinite(s[:, j]) & (s[:, j] > 0)
            if m.any():
                wt = 1.0 / s[m, j] ** 2
                b[j] = float(np.sum(wt * res[m, j]) / np.sum(wt))
        bias[r.run_id] = b
    return TwinModel(exp.device_id, twin.cycles, bias, twin.noise, twin.rails)


GM_TAUS_S = (2.0, 5.0, 10.0, 20.0, 50.0, 100.0, 200.0)


def refit_noise(twin: TwinModel, exp: DeviceExperiment) -> tuple[TwinModel, dict]:
    """Noise-model re-estimation (simreal.md sec. 4.2: a gap seen only in stochastic views goes to the noise model):
    per channel with a long static record, the IEEE 952 terms (N, B, K; Q kept) plus one first-order
    Gauss-Markov term ([ELSHEIMY2008], correlation time profiled over ``GM_TAUS_S``) fitted to the static
    residual's Allan variance by non-negative least squares in relative error, weights sqrt(EDF) with
    EDF ~ T/tau. Returns the re-estimated twin and, per channel, the fitted terms."""
    from scipy.optimize import nnls

    from assets_lib.sim.effects.stochastic import gauss_markov_avar

    curves = {}
    for r in exp.runs:
        for ch, (tau, adev, _edf) in exp.processed[r.run_id].allan.items():
            if ch not in curves or tau.size > curves[ch][0].size:
                curves[ch] = (np.asarray(tau, float), np.asarray(adev, float))
    noise, gm, fitted = list(twin.noise), list(twin.gm or ((0.0, 1.0),) * 6), {}
    for j, ch in enumerate(CHANNEL_NAMES):
        if ch not in curves:
            continue
        tau, adev = curves[ch]
        ok = np.isfinite(adev) & (adev > 0) & (tau > 0)
        tau, av = tau[ok], adev[ok] ** 2
        if tau.size < 5:
            continue
        q = noise[j].q
        w = np.sqrt(tau.max() * 8.0 / tau) / av
        base = np.column_stack([1.0 / tau, np.full(tau.size, 2 * np.log(2) / np.pi), tau / 3.0])
        best = None
        for tc in (None,) + GM_TAUS_S:
            X = base if tc is None else np.column_stack([base, gauss_markov_avar(tau, 1.0, tc)])
            target = av - 3 * q**2 / tau**2
            th, res = nnls(X * w[:, None], target * w)
            if best is None or res < best[0] - 1e-9:
                best = (res, tc, th)
        _, tc, th = best
        noise[j] = AllanParams(q=q, n=float(np.sqrt(th[0])), b=float(np.sqrt(th[1])), k=float(np.sqrt(th[2])))
        gm[j] = (float(np.sqrt(th[3])), float(tc)) if tc is not None else (0.0, 1.0)
        fitted[ch] = {"n": noise[j].n, "b": noise[j].b, "k": noise[j].k, "gm_sigma": gm[j][0], "gm_tau_s": gm[j][1]}
    return twin.with_noise(tuple(noise), tuple(gm)), fitted


def simulate_run_imu(twin: TwinModel, inp: RunInputs, rng: np.random.Generator, noise_scale=None) -> pd.DataFrame:
    """A replicate of a recorded run: the twin (plus its effects) on the run's recorded inputs, canonical frame."""
    from assets_lib.simreal.effects import inject

    m = twin.cycle(inp.power_cycle)
    g, a = m.predict(inp.omega_b_radps, inp.f_b_mps2)
    b = twin.bias.get(inp.run_id, np.zeros(6))
    g = g + b[:3]
    a = a + b[3:]
    n = inp.t_s.size
    fs = 1.0 / float(np.median(np.diff(inp.t_s)))
    noise = twin.noise
    for i in range(3):
        g[:, i] += allan_noise(n, fs, noise[i], rng)
        a[:, i] += allan_noise(n, fs, noise[3 + i], rng)
    if twin.gm:
        from assets_lib.sim.effects.stochastic import gauss_markov

        for j, (sig, tc) in enumerate(twin.gm):
            if sig > 0:
                (g if j < 3 else a)[:, j % 3] += gauss_markov(n, fs, sig, tc, rng)
    for fam, ch, coef, shape in twin.effects:
        g, a = inject(fam, ch, coef, shape, inp, g, a, rng)
    if twin.rails[0]:
        g = np.clip(g, -twin.rails[0], twin.rails[0])
    if twin.rails[1]:
        a = np.clip(a, -twin.rails[1], twin.rails[1])
    y = np.column_stack([g, a])
    lsb = inp.lsb_si
    for j in range(6):
        if lsb[j] > 0:
            y[:, j] = np.rint(y[:, j] / lsb[j]) * lsb[j]
    eps = sum(float(np.atleast_1d(c)[0]) for f_, _, c, _ in twin.effects if f_ == "timebase_error")
    df = pd.DataFrame({"time_s": inp.t_s * (1.0 + eps)})
    for j, c in enumerate(CHANNELS):
        df[c] = y[:, j]
    df["temperature_degc"] = inp.temperature_degc
    df["counter"] = np.arange(n, dtype=np.int64)
    return df


def twin_json(twin: TwinModel) -> str:
    return json.dumps(twin.to_json(), indent=1, default=float)
