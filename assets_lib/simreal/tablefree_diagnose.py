"""Sim-to-real diagnosis of table-free (hand-moved) sessions: where / which effect / how far it shrinks.

The table-free experiment of ``tablefree_twin``: the twin is the session's own table-free fit, the replicates are
driven by the recorded inputs estimated from the data and pushed through ``calibrate_tablefree``. Then, as in
``diagnose.py`` (simreal.md sec. 1):

**Rows** (residuals the fit leaves, each realisation its own): ``A`` static-pose |f| - g, ``S`` calibrated gyro
pose means per channel, ``P`` gyro-integration residuals per rotation (3 components). Each row block and channel
is whitened by the RMS of the same rows over the base replicates (the sim-vs-sim noise of that row type,
fitted degrees of freedom included), and the fit's own parameters are projected out (the Jacobian of the
Tedaldi accelerometer and gyro fits; a constant per gyro channel on ``S``, whose bias is a nuisance).

**Where**: views calibrated against the replicates (``views.calibrate``, BH q over all views): per-pose
``static_norm_residual`` and ``static_gyro_residual``, per-rotation ``rotation_residual`` (angle), the
signature projections ``residual_vs_*`` of every candidate below (whitened, nuisance-projected), the fit scatter
``fit_chi2_*`` (stochastic), ``allan_band_tau*`` of the longest static interval (stochastic) and its
``residual_spectrum_peak``; BH q over the views [BENJAMINI1995].

**Which**: candidate signatures, each linear in its coefficients, acting on the calibrated signals (a gyro
candidate adds d_w_j(t), an accelerometer one d_f_j(t)); on ``A`` rows the first-order change u_i . d_f, on
``S`` rows the pose mean of d_w_j, on ``P`` rows the numerical derivative of the integration residual:

============================ ================================================ ==================================
family                       signature on channel j                           needs
============================ ================================================ ==================================
g_sensitivity (gyro)         f_x, f_y, f_z (linear G: not in the Tedaldi      poses (S) and rotations (P)
                             base model; confounded with the earth rate's
                             vertical part Omega sin(lat) f / g)
bias_ramp                    t                                                poses
warmup_bias                  exp(-t_on / tau), tau profiled (30, 120, 300 s)  poses; power-on = first sample
temperature_bias             T - mean T                                       a temperature log varying > 0.5 K
temperature_scale_factor     x_j (T - mean T), x = w (gyro) or f (accel)      same
scale_factor_nonlinearity    gyro w_j^2, w_j^3 (P); accel f_j^2 (A)           rotations / poses
scale_factor_asymmetry       gyro |w_j| (P)                                   rotations
============================ ================================================ ==================================

Greedy forward selection on blocked cross-validation [ROBERTS2017]: ``K_FOLDS`` contiguous blocks of poses in time (a table-free
session is a single run, so leave-one-run-out is impossible; a block holds its poses, their gyro means and the
rotations that leave them). Accept when the held-out gain exceeds the larger of 2 ln 1000 and the sim-vs-sim
level mean + 5 sd of the first-step score over the base replicates, positive in >= K-1 folds. Ambiguity: ties
within 2 ln 10 and alias R^2 >= 0.95, and g_sensitivity <-> earth rate unless the magnitude's interval lies
above Omega / g (the most the earth rate's vertical part, Omega sin(lat) f / g, can mimic; heading unknown). Shrink as in
``diagnose.py`` (held-out whitened error over the replicate floor). Magnitude intervals: 95 % from the
whitened least-squares covariance (Monte Carlo through the magnitude). The views are re-run with replicates of
the augmented twin (the effect injected into the recorded inputs).

**Not testable** (reported with the reason): lever_arm, table_rate_error, table_wobble (no table),
timebase_error (no independent clock: a sample-rate error is a common gyro scale factor, absorbed by K_g),
latency (no external reference), bias_step (one run), vibration (spectral view only), noise_model (stochastic
views: verdict ``noise_model``); temperature families without a varying temperature log; every attributed
family of a Ferraris session (six poses and three rotations leave no held-out fold: the closed form is exactly
determined for the gyro and has 6 residual equations for 12 accelerometer terms).
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from assets_lib.simreal.tablefree_twin import (
    TFTwin,
    realise,
    recorded_inputs,
    simulate_tablefree,
)
from assets_lib.simreal.views import ViewTable, calibrate

GATE = 2 * np.log(1000.0)
TIE = 2 * np.log(10.0)
NULL_SD = 5.0
K_FOLDS = 5
ALIAS_R2 = 0.95
WARMUP_TAUS_S = (30.0, 120.0, 300.0)
SCHEMA_VERSION = "1.0"
EARTH_RATE_RADPS = 7.292115e-5
REPORT_CHANNELS = ("gyro_x", "gyro_y", "gyro_z", "accel_x", "accel_y", "accel_z")

NOT_TESTABLE_TABLEFREE = {
    "lever_arm": "no turntable: no centripetal acceleration of a known rate and axis",
    "table_rate_error": "no turntable",
    "table_wobble": "no turntable",
    "timebase_error": "no independent clock: a sample-rate error is a common gyro scale factor, absorbed by the "
                      "integration fit's K_g (effects.md sec. 2, scale factor <-> clock rate)",
    "latency": "no external reference signal to delay against",
    "bias_step": "a single run: a step cannot be validated on another run; it shows in the static gyro views",
    "vibration": "localised by the residual-spectrum view only (no deterministic candidate)",
    "noise_model": "stochastic: routed to the noise-model verdict by the Allan-band views",
}


# ---------------------------------------------------------------------------------------------------------------
# candidate signatures: fn(signals, axis, shape) -> (n, n_coef) on the calibrated signals
# ---------------------------------------------------------------------------------------------------------------
def _tc(s):
    T = s["T"]
    return (T - np.nanmean(T))[:, None]


SIGNATURES = {
    ("g_sensitivity", "gyro"): (lambda s, j, sh: s["f"], 3, "f"),
    ("bias_ramp", "gyro"): (lambda s, j, sh: s["t"][:, None], 1, "time"),
    ("bias_ramp", "accel"): (lambda s, j, sh: s["t"][:, None], 1, "time"),
    ("warmup_bias", "gyro"): (lambda s, j, sh: np.exp(-s["t_on"] / sh)[:, None], 1, "time_since_power_on_exp"),
    ("warmup_bias", "accel"): (lambda s, j, sh: np.exp(-s["t_on"] / sh)[:, None], 1, "time_since_power_on_exp"),
    ("temperature_bias", "gyro"): (lambda s, j, sh: _tc(s), 1, "temperature"),
    ("temperature_bias", "accel"): (lambda s, j, sh: _tc(s), 1, "temperature"),
    ("temperature_scale_factor", "gyro"): (lambda s, j, sh: s["w"][:, j:j + 1] * _tc(s), 1, "rate_x_temperature"),
    ("temperature_scale_factor", "accel"): (lambda s, j, sh: s["f"][:, j:j + 1] * _tc(s), 1, "force_x_temperature"),
    ("scale_factor_nonlinearity", "gyro"): (lambda s, j, sh: np.column_stack([s["w"][:, j] ** 2, s["w"][:, j] ** 3]), 2,
                                            "rate_squared"),
    ("scale_factor_nonlinearity", "accel"): (lambda s, j, sh: s["f"][:, j:j + 1] ** 2, 1, "force_squared"),
    ("scale_factor_asymmetry", "gyro"): (lambda s, j, sh: np.abs(s["w"][:, j:j + 1]), 1, "abs_rate"),
}
UNITS = {"g_sensitivity": ("rad/s per m/s^2", None), "bias_ramp": ("rad/s^2", "m/s^3"),
         "warmup_bias": ("rad/s", "m/s^2"), "temperature_bias": ("rad/s/K", "m/s^2/K"),
         "temperature_scale_factor": ("1/K", "1/K"), "scale_factor_nonlinearity": ("1", "1"),
         "scale_factor_asymmetry": ("1", None)}


@dataclass(frozen=True)
class Candidate:
    family: str
    channel: int  # 0..5
    shape: float | None

    @property
    def sensor(self) -> str:
        return "gyro" if self.channel < 3 else "accel"

    @property
    def fn(self):
        return SIGNATURES[(self.family, self.sensor)][0]

    @property
    def n_coef(self) -> int:
        return SIGNATURES[(self.family, self.sensor)][1]

    @property
    def view(self) -> str:
        return "residual_vs_" + SIGNATURES[(self.family, self.sensor)][2]

    @property
    def group(self) -> tuple:
        return (self.family, self.channel)


def testable(reals: list) -> tuple[list[Candidate], dict]:
    """Candidates the session can test, and the families it cannot (with the reason)."""
    nt = dict(NOT_TESTABLE_TABLEFREE)
    if any(r.method != "tedaldi" for r in reals):
        for fam in UNITS:
            nt[fam] = ("Ferraris session (six poses, three rotations): the closed form is exactly determined for the "
                       "gyro and leaves no held-out fold for the accelerometer; the views still localise a gap")
        return [], nt
    temp_ok = all(np.isfinite(r.signals["T"]).all() and np.ptp(r.signals["T"][r.pose_starts]) > 0.5 for r in reals)
    out = []
    for (fam, sensor) in SIGNATURES:
        if fam.startswith("temperature") and not temp_ok:
            nt[fam] = "no temperature log varying by more than 0.5 K over the poses"
            continue
        for j in range(3):
            ch = j if sensor == "gyro" else 3 + j
            for sh in (WARMUP_TAUS_S if fam == "warmup_bias" else (None,)):
                out.append(Candidate(fam, ch, sh))
    return out, nt


# ---------------------------------------------------------------------------------------------------------------
# design of one realisation: whitened, nuisance-projected rows and candidate columns
# ---------------------------------------------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class TFDesign:
    y: np.ndarray  # (m,) whitened projected residual
    X: dict  # Candidate -> (m, n_coef)
    fold: np.ndarray  # (m,)
    block: np.ndarray  # 'A' | 'S' | 'P'
    channel: np.ndarray  # row channel (0..5) or -1


def _rows_meta(r):
    n_p = len(r.a_y)
    kf = np.minimum((np.arange(n_p) * K_FOLDS) // max(n_p, 1), K_FOLDS - 1)
    blocks, chans, folds = ["A"] * n_p, [-1] * n_p, list(kf)
    for j in range(3):
        blocks += ["S"] * n_p
        chans += [j] * n_p
        folds += list(kf)
    n_pairs = r.p_y.shape[0]
    for k in range(n_pairs):
        blocks += ["P"] * 3
        chans += [0, 1, 2]
        folds += [kf[k]] * 3
    return np.array(blocks), np.array(chans), np.array(folds)


def _raw_y(r):
    return np.r_[r.a_y, r.s_y[:, 0], r.s_y[:, 1], r.s_y[:, 2], r.p_y.ravel()]


def noise_scales(reps: list) -> dict:
    """RMS of each row block and channel over the base replicates (sim-vs-sim)."""
    acc: dict = {}
    for r in reps:
        b, c, _ = _rows_meta(r)
        y = _raw_y(r)
        if b.size and r.s_y.size:
            y[b == "S"] = (r.s_y - r.s_y.mean(0)).T.ravel()
        for key in set(zip(b, c)):
            m = (b == key[0]) & (c == key[1])
            acc.setdefault(key, []).append(y[m])
    return {k: float(np.sqrt(np.mean(np.concatenate(v) ** 2))) for k, v in acc.items()}


def _cand_rows(r, cand: Candidate) -> np.ndarray:
    """Signature of ``cand`` on the rows of realisation ``r`` (before whitening), (m, n_coef)."""
    sig = r.signals
    X = cand.fn(sig, cand.channel % 3, cand.shape)
    n_p = len(r.a_y)
    n_pairs = r.p_y.shape[0]
    out = np.zeros((n_p * 4 + 3 * n_pairs, cand.n_coef))
    if cand.sensor == "accel":
        j = cand.channel - 3
        for i, (a, b) in enumerate(r.a_ranges):
            out[i] = r.a_u[i, j] * X[a:b].mean(0)
        return out
    j = cand.channel
    for i, (a, b) in enumerate(zip(r.pose_starts, r.pose_ends)):
        out[n_p * (1 + j) + i] = X[a:b].mean(0)
    if n_pairs and r.pair_fun is not None:
        w = sig["w"]
        for c in range(cand.n_coef):
            x = X[:, c]
            scale = np.sqrt(np.mean(x * x))
            if scale == 0:
                continue
            h = 1e-4 / scale
            wp, wm = w.copy(), w.copy()
            wp[:, j] += h * x
            wm[:, j] -= h * x
            out[n_p * 4:, c] = ((r.pair_fun(wp) - r.pair_fun(wm)) / (2 * h)).ravel()
    return out


def build_design(r, cands: list, scales: dict) -> TFDesign:
    b, c, folds = _rows_meta(r)
    wt = np.array([1.0 / scales.get((bi, ci), np.inf) if scales.get((bi, ci), 0) > 0 else 0.0 for bi, ci in zip(b, c)])
    y = _raw_y(r) * wt
    n_p = len(r.a_y)
    cols = []
    if r.a_nuis is not None:
        N = np.zeros((b.size, r.a_nuis.shape[1]))
        N[:n_p] = r.a_nuis
        cols.append(N)
    for j in range(3):
        N = np.zeros((b.size, 1))
        N[(b == "S") & (c == j)] = 1.0
        cols.append(N)
    if r.p_nuis is not None and r.p_y.size:
        N = np.zeros((b.size, r.p_nuis.shape[1]))
        N[n_p * 4:] = r.p_nuis
        cols.append(N)
    N = np.hstack(cols) * wt[:, None]
    keep = np.linalg.norm(N, axis=0) > 0
    Q, R_ = np.linalg.qr(N[:, keep])
    Q = Q[:, np.abs(np.diag(R_)) > 1e-10 * np.abs(np.diag(R_)).max()]

    def proj(v):
        return v - Q @ (Q.T @ v)

    X = {cd: proj(_cand_rows(r, cd) * wt[:, None]) for cd in cands}
    return TFDesign(proj(y), X, folds, b, c)


# ---------------------------------------------------------------------------------------------------------------
# selection (blocked CV, greedy forward)
# ---------------------------------------------------------------------------------------------------------------
def _cv(y, X, folds):
    """Held-out gain per fold (SSE reduction) of adding columns X to a model of residual y."""
    gains, E = [], 0.0
    for k in np.unique(folds):
        tr, te = folds != k, folds == k
        Xt = X[tr]
        if not np.any(np.abs(X[te]) > 0) or np.linalg.matrix_rank(Xt) < X.shape[1]:
            continue
        beta = np.linalg.lstsq(Xt, y[tr], rcond=None)[0]
        r = y[te] - X[te] @ beta
        gains.append(float(y[te] @ y[te] - r @ r))
        E += float(r @ r)
    return np.array(gains), E


@dataclass(frozen=True)
class Step:
    cand: Candidate
    delta_lpd: float
    n_pos: int
    folds: int


def first_step_scores(d: TFDesign) -> dict:
    best: dict = {}
    for cd, X in d.X.items():
        g, _ = _cv(d.y, X, d.fold)
        s = float(g.sum()) if g.size else -np.inf
        best[cd.group] = max(best.get(cd.group, -np.inf), s)
    return best


def _orth(X, A):
    if A is None or A.shape[1] == 0:
        return X
    Q, _ = np.linalg.qr(A)
    return X - Q @ (Q.T @ X)


def select(d: TFDesign, gates: dict):
    accepted, amb, first = [], [], []
    y = d.y.copy()
    A = None
    while True:
        steps = []
        for cd, X in d.X.items():
            if any(s.cand.group == cd.group for s in accepted):
                continue
            Xo = _orth(X, A)
            if np.linalg.norm(Xo) < 1e-12:
                continue
            g, _ = _cv(y, Xo, d.fold)
            if g.size < 2:
                continue
            steps.append(Step(cd, float(g.sum()), int((g > 0).sum()), int(g.size)))
        if not steps:
            break
        # best shape per group
        byg = {}
        for s in steps:
            if s.cand.group not in byg or s.delta_lpd > byg[s.cand.group].delta_lpd:
                byg[s.cand.group] = s
        ranked = sorted(byg.values(), key=lambda s: -s.delta_lpd)
        if not accepted:
            first = ranked
        top = ranked[0]
        gate = max(GATE, gates.get(top.cand.group, GATE))
        if not (top.delta_lpd > gate and top.n_pos >= top.folds - 1):
            break
        Xo = _orth(d.X[top.cand], A)
        beta = np.linalg.lstsq(Xo, y, rcond=None)[0]
        fit = Xo @ beta
        grp = [top.cand]
        for s in ranked[1:]:
            Xs = _orth(d.X[s.cand], A)
            tie = top.delta_lpd - s.delta_lpd < TIE
            alias = 1.0 - float(np.sum((fit - Xs @ np.linalg.lstsq(Xs, fit, rcond=None)[0]) ** 2)) / max(float(fit @ fit), 1e-300)
            if tie or alias >= ALIAS_R2:
                grp.append(s.cand)
        accepted.append(top)
        amb.append(grp)
        A = d.X[top.cand] if A is None else np.hstack([A, d.X[top.cand]])
        y = d.y - A @ np.linalg.lstsq(A, d.y, rcond=None)[0]
    return accepted, amb, first


def coefficients(d: TFDesign, accepted: list):
    """Joint least-squares coefficients and covariance (whitened rows: unit variance) of the accepted candidates."""
    if not accepted:
        return [], []
    A = np.hstack([d.X[s.cand] for s in accepted])
    beta, *_ = np.linalg.lstsq(A, d.y, rcond=None)
    cov = np.linalg.pinv(A.T @ A)
    out, covs, i = [], [], 0
    for s in accepted:
        n = s.cand.n_coef
        out.append(beta[i:i + n])
        covs.append(cov[i:i + n, i:i + n])
        i += n
    return out, covs


def heldout_error(d: TFDesign, cands: list) -> float:
    if not cands:
        return float(d.y @ d.y)
    X = np.hstack([d.X[c] for c in cands])
    _, E = _cv(d.y, X, d.fold)
    return E


def magnitude(cand: Candidate, coef: np.ndarray, reals) -> float:
    c = np.atleast_1d(coef)
    if cand.family == "g_sensitivity":
        return float(np.linalg.norm(c))
    if cand.family == "scale_factor_nonlinearity":
        if cand.sensor == "accel":
            return float(c[0] * 9.80665)  # K2 f^2 / f at 1 g: relative deviation at 1 g
        wmax = max(float(np.max(np.abs(r.signals["w"][:, cand.channel]))) for r in reals)
        ws = np.linspace(-wmax, wmax, 201)
        v = c[0] * ws**2 + c[1] * ws**3
        k = int(np.argmax(np.abs(v)))
        return float(v[k] / wmax)
    if cand.family == "scale_factor_asymmetry":
        return float(2.0 * c[0])
    return float(c[0])


# ---------------------------------------------------------------------------------------------------------------
# views
# ---------------------------------------------------------------------------------------------------------------
def _match(real_t: np.ndarray, rep_t: np.ndarray, tol_s: float = 2.0) -> np.ndarray:
    if rep_t.size == 0:
        return np.full(real_t.size, -1)
    k = np.abs(real_t[:, None] - rep_t[None, :]).argmin(1)
    return np.where(np.abs(rep_t[k] - real_t) <= tol_s, k, -1)


def compute_views(r, d: TFDesign, real_pose_t: np.ndarray) -> dict:
    from scipy.signal import welch

    from assets_lib.noise.pooled import overlapping_avar

    out = {}
    run = r.run_id
    mi = _match(real_pose_t, r.pose_t)
    for i, k in enumerate(mi):
        if k < 0:
            continue
        out[("static_norm_residual", run, None, i)] = float(r.a_y[k])
        for j in range(3):
            out[("static_gyro_residual", run, REPORT_CHANNELS[j], i)] = float(r.s_y[k, j] - r.s_y[:, j].mean())
        if k < r.p_y.shape[0] and i < len(real_pose_t) - 1 and mi[i + 1] == k + 1:
            out[("rotation_residual", run, None, i)] = float(np.linalg.norm(r.p_y[k]))
    for cd, X in d.X.items():
        if cd.family == "warmup_bias" and cd.shape != 120.0:
            continue
        for c in range(X.shape[1]):
            gg = float(X[:, c] @ X[:, c])
            if gg > 1e-20:
                suffix = "" if X.shape[1] == 1 else (f"_{'xyz'[c]}" if cd.family == "g_sensitivity" else f"_{c + 2}")
                out[(cd.view + suffix, run, REPORT_CHANNELS[cd.channel], None)] = float(X[:, c] @ d.y / np.sqrt(gg))
    out[("fit_chi2_static_norm", run, None, None)] = float(np.log(np.mean(r.a_y**2) + 1e-30))
    for j in range(3):
        out[("fit_chi2_static_gyro", run, REPORT_CHANNELS[j], None)] = float(np.log(np.var(r.s_y[:, j]) + 1e-30))
    if r.p_y.size:
        out[("fit_chi2_rotation", run, None, None)] = float(np.log(np.mean(r.p_y**2) + 1e-30))
    x = r.static_resid
    if x.shape[0] >= 64:
        n = x.shape[0]
        m = np.unique(np.round(2.0 ** np.arange(0, np.log2(n / 8.0))).astype(int))
        for j, ch in enumerate(REPORT_CHANNELS):
            av, _ = overlapping_avar(x[:, j], m)  # (avar, n_terms) per cluster size
            for t_, a in zip(m / r.fs_hz, np.sqrt(np.asarray(av, float))):
                if a > 0:
                    out[(f"allan_band_tau{t_:.3g}s", run, ch, None)] = float(np.log10(a))
            fq, psd = welch(x[:, j] - x[:, j].mean(), fs=r.fs_hz, nperseg=min(1024, n))
            band = fq > 0.5
            if band.sum() > 8 and np.median(psd[band]) > 0:
                out[("residual_spectrum_peak", run, ch, None)] = float(np.log10(psd[band].max() / np.median(psd[band])))
    return out


# ---------------------------------------------------------------------------------------------------------------
# the diagnosis
# ---------------------------------------------------------------------------------------------------------------
def is_tablefree_device(frames) -> bool:
    return bool(frames) and all(m.test_kind == "tablefree" for m, _, _ in frames)


def load_tablefree_frames(landing, device_id: str):
    """(manifest, imu, table) of every completed run of ``device_id`` when all of them are table-free, else None
    (only the manifests are read to decide)."""
    import json
    from pathlib import Path

    from raw_schemas.readers import discover_runs, ingest_run

    dirs = [Path(d) for d in discover_runs(landing) if Path(d).parent.name == device_id]
    if not dirs or any(json.loads((d / "manifest.json").read_text()).get("test_kind") != "tablefree" for d in dirs):
        return None
    return [(r.manifest, r.imu, r.table) for r in (ingest_run(d) for d in dirs)]


def _replicate(twin: TFTwin, frames, seed: int, r: int, refs: dict):
    import hashlib

    out = []
    for m, _imu, _t in frames:
        key = int.from_bytes(hashlib.sha256(m.run_id.encode()).digest()[:4], "little")
        df = simulate_tablefree(twin, m.run_id, np.random.default_rng([seed, r, key]))
        try:
            out.append(realise(m, df, twin.inputs[m.run_id].gravity_mps2, refs[m.run_id]))
        except ValueError:  # the replicate's pose detection failed: the replicate is dropped (counted)
            return None
    return out


_STATE: dict = {}


def _worker(args):
    r, seed = args
    st = _STATE["tf"]
    return _replicate(st["twin"], st["frames"], seed, r, st["refs"])


def run_replicates(twin, frames, n, seed, workers, say, label="base"):
    import multiprocessing as mp
    from concurrent.futures import ProcessPoolExecutor

    refs = {m.run_id: twin.inputs[m.run_id].static_ref for m, _, _ in frames}
    _STATE["tf"] = {"twin": twin, "frames": frames, "refs": refs}
    out = []
    try:
        if (workers or 1) <= 1 or n <= 1:
            for r in range(n):
                out.append(_worker((r, seed)))
                if (r + 1) % 5 == 0 or r + 1 == n:
                    say(f"  {label} replicate {r + 1}/{n}")
        else:
            with ProcessPoolExecutor(max_workers=workers, mp_context=mp.get_context("fork")) as ex:
                for i, rep in enumerate(ex.map(_worker, [(r, seed) for r in range(n)])):
                    out.append(rep)
                    if (i + 1) % 5 == 0 or i + 1 == n:
                        say(f"  {label} replicate {i + 1}/{n}")
    finally:
        _STATE.pop("tf", None)
    return [o for o in out if o is not None], sum(o is None for o in out)


def _views_all(reals, designs, real_pose_t):
    v = {}
    for r, d in zip(reals, designs):
        v.update(compute_views(r, d, real_pose_t[r.run_id]))
    return v


def _pooled(designs: list) -> TFDesign:
    """One design over several runs (rows stacked; folds kept per pose block)."""
    if len(designs) == 1:
        return designs[0]
    keys = designs[0].X.keys()
    return TFDesign(np.concatenate([d.y for d in designs]), {k: np.vstack([d.X[k] for d in designs]) for k in keys},
                    np.concatenate([d.fold for d in designs]), np.concatenate([d.block for d in designs]),
                    np.concatenate([d.channel for d in designs]))


def diagnose_tablefree(frames, device_id: str, replicates: int = 20, seed: int = 0, workers: int | None = None,
                       aug_replicates: int | None = None, progress=None):
    """Diagnosis of a device whose runs are all table-free (the fields of ``diagnose.Diagnosis``)."""
    from assets_lib.sim.earth import site_gravity_mps2
    from assets_lib.simreal.replicates import default_workers

    say = progress or (lambda msg: None)
    workers = default_workers() if workers is None else workers
    tm = {}
    t0 = time.time()
    frames = sorted(frames, key=lambda f: (f[0].start_time_utc, f[0].run_id))
    reals, models, inputs = [], {}, {}
    for m, imu, _ in frames:
        r = realise(m, imu, site_gravity_mps2(m.site))
        reals.append(r)
        models[m.run_id] = r.model
        inputs[m.run_id] = recorded_inputs(m, imu, r)
    twin = TFTwin(device_id, models, inputs)
    real_pose_t = {r.run_id: r.pose_t for r in reals}
    cands, not_testable = testable(reals)
    tm["load_fit_twin"] = time.time() - t0
    say(f"{device_id}: {len(frames)} table-free run(s) fitted ({tm['load_fit_twin']:.1f} s); {replicates} base replicates ...")
    t1 = time.time()
    reps, dropped = run_replicates(twin, frames, replicates, seed, workers, say)
    tm["replicates_base"] = time.time() - t1
    if len(reps) < 3:
        raise ValueError(f"{device_id}: only {len(reps)} of {replicates} replicates could be calibrated (the pose "
                         "detector failed on the others): too few to calibrate the views")
    scales = {}
    for i in range(len(reals)):
        scales[i] = noise_scales([rp[i] for rp in reps])
    real_d = [build_design(r, cands, scales[i]) for i, r in enumerate(reals)]
    rep_d = [[build_design(r, cands, scales[i]) for i, r in enumerate(rp)] for rp in reps]
    real_views = _views_all(reals, real_d, real_pose_t)
    vt = calibrate(real_views, [_views_all(rp, dd, real_pose_t) for rp, dd in zip(reps, rep_d)],
                   min_reps=min(5, len(reps)))
    D = _pooled(real_d)
    D_reps = [_pooled(dd) for dd in rep_d]
    gates = {}
    if cands:
        null = {}
        for dr in D_reps:
            for g_, v in first_step_scores(dr).items():
                null.setdefault(g_, []).append(v)
        gates = {g_: max(GATE, float(np.mean(v) + NULL_SD * np.std(v, ddof=1))) if len(v) > 2 else GATE
                 for g_, v in null.items()}
        accepted, amb, first = select(D, gates)
    else:
        accepted, amb, first = [], [], []
    coefs, covs = coefficients(D, accepted)
    # whitened coefficients -> SI: the rows were whitened and so were the columns: beta is already in SI per column
    eff_out, effects = [], []
    rng = np.random.default_rng(seed + 1)
    for s, b, cv in zip(accepted, coefs, covs):
        mag = magnitude(s.cand, b, reals)
        draws = rng.multivariate_normal(b, cv, size=400, method="svd") if np.all(np.isfinite(cv)) else None
        mags = np.array([magnitude(s.cand, x, reals) for x in draws]) if draws is not None else np.array([])
        lo, hi = (float(np.percentile(mags, 2.5)), float(np.percentile(mags, 97.5))) if mags.size else (np.nan, np.nan)
        unit = UNITS[s.cand.family][0 if s.cand.sensor == "gyro" else 1] or ""
        eff_out.append({"family": s.cand.family, "channel": REPORT_CHANNELS[s.cand.channel], "magnitude": mag,
                        "ci_lo": lo, "ci_hi": hi, "unit": unit, "delta_lpd": s.delta_lpd, "folds_positive": s.n_pos,
                        "folds": s.folds, "shape": {"tau_s": s.cand.shape} if s.cand.shape else None,
                        "coefficients": [float(x) for x in b]})
        effects.append((s.cand.family, REPORT_CHANNELS[s.cand.channel], b, s.cand.shape, s.cand.fn))
    ambiguity = []
    for grp, e in zip(amb, eff_out):
        fams = []
        for c in grp:
            if c.family not in fams:
                fams.append(c.family)
        # without a temperature log, a warm-up or a ramp cannot be told from a temperature bias (effects.md sec. 2)
        if {"warmup_bias", "bias_ramp"} & set(fams) and "temperature_bias" in not_testable:
            fams.append("temperature_bias")
        # the earth rate's vertical part, Omega sin(lat) f / g, is linear in f like a g-sensitivity (heading unknown,
        # effects.md sec. 2): ambiguous unless the interval excludes every G the earth rate can mimic (<= Omega / g)
        if "g_sensitivity" in fams and not (np.isfinite(e["ci_lo"]) and e["ci_lo"] > EARTH_RATE_RADPS / 9.78):
            fams.append("earth_rate")
        ambiguity.append(fams)
    accepted_c = [s.cand for s in accepted]
    E_base = heldout_error(D, [])
    E_model = heldout_error(D, accepted_c)
    floor = np.array([heldout_error(dr, []) for dr in D_reps])
    fm, fsd = float(floor.mean()), float(floor.std(ddof=1))
    init_sd = (E_base - fm) / fsd if fsd > 0 else float("nan")
    rem_sd = (E_model - fm) / fsd if fsd > 0 else float("nan")
    denom = E_base - fm
    if accepted and denom > 0:
        ratio = (E_base - E_model) / denom
        lo_d, hi_d = E_base - (fm - 1.96 * fsd), E_base - (fm + 1.96 * fsd)
        cands_ = [(E_base - E_model) / x for x in (lo_d, hi_d) if x > 0]
        ratio_ci = [float(min(cands_)), float(max(cands_)) if hi_d > 0 else None] if cands_ else [None, None]
    else:
        ratio, ratio_ci = 0.0, [0.0, 0.0]
    aug = twin.with_effects(effects)
    vt_after = None
    if effects:
        t3 = time.time()
        n_aug = aug_replicates if aug_replicates is not None else max(5, replicates // 2)
        say(f"{device_id}: {len(effects)} effect(s) accepted; {n_aug} augmented-twin replicates ...")
        areps, _ = run_replicates(aug, frames, n_aug, seed + 7919, workers, say, "augmented")
        if len(areps) >= 3:
            ad = [[build_design(r, cands, scales[i]) for i, r in enumerate(rp)] for rp in areps]
            vt_after = calibrate(real_views, [_views_all(rp, dd, real_pose_t) for rp, dd in zip(areps, ad)],
                                 min_reps=min(5, len(areps)))
        tm["replicates_augmented"] = time.time() - t3
    sig_det, sig_sto = vt.significant(False), vt.significant(True)
    if effects:
        verdict = "explained" if (vt_after is not None and vt_after.significant(False).empty) else "partly_explained"
    elif not sig_det.empty:
        verdict = "unexplained"
    elif not sig_sto.empty:
        verdict = "noise_model"
    else:
        verdict = "no_gap"
    top = vt.table.iloc[0] if len(vt.table) else None
    where_t = vt.table[vt.table["significant"]] if not vt.significant().empty else vt.table.head(10)
    where = [{"view": w.view, "run_id": w.run_id, "channel": w.channel,
              "step_index": None if w.step_index is None or (isinstance(w.step_index, float) and np.isnan(w.step_index))
              else int(w.step_index), "z": float(w.z), "q_value": float(w.q)} for w in where_t.head(50).itertuples(index=False)]
    tested = sorted({c.family for c in cands})
    report = {
        "schema_version": SCHEMA_VERSION, "device_id": device_id, "runs": [m.run_id for m, _, _ in frames],
        "verdict": verdict,
        "gap": {"detected": verdict != "no_gap", "z": float(abs(top["z"])) if top is not None else 0.0,
                "p_value": float(vt.table["q"].min()) if len(vt.table) else 1.0},
        "where": where, "effects": eff_out, "ambiguity": ambiguity,
        "shrink": {"ratio": float(ratio), "ratio_ci": ratio_ci, "remaining_floor_sd": float(rem_sd),
                   "initial_floor_sd": float(init_sd)},
        "experiment": "tablefree",
        "testable": tested,
        "not_testable": not_testable,
        "replicates": {"base": replicates, "calibrated": len(reps), "dropped": dropped,
                       "augmented": 0 if vt_after is None else n_aug, "seed": seed},
        "views_after": ([{"view": w.view, "run_id": w.run_id, "channel": w.channel, "z": float(w.z), "q_value": float(w.q)}
                         for w in vt_after.significant(False).head(20).itertuples(index=False)]
                        if vt_after is not None else None),
        "selection_first_step": [{"family": s.cand.family, "channel": REPORT_CHANNELS[s.cand.channel],
                                  "delta_lpd": s.delta_lpd, "gate": gates.get(s.cand.group, GATE),
                                  "folds_positive": s.n_pos, "folds": s.folds} for s in first[:15]],
        "fit": {r.run_id: {"method": r.method, "n_poses": len(r.a_y), "n_rotations": int(r.p_y.shape[0]),
                           **{k: v for k, v in r.diagnostics.items() if isinstance(v, (int, float))}} for r in reals},
        "timings_s": tm,
    }
    tm["total"] = time.time() - t0
    plots = {"views": vt, "views_after": vt_after, "E": (E_base, E_model, floor), "effects": eff_out,
             "tablefree": {"reals": reals, "reps": reps, "scales": scales, "vt": vt}}
    diag = TFDiagnosis(report, twin, aug, vt, vt_after, tm, plots)
    import base64

    plots["extra_png"] = {f"table-free views of run {k}": base64.b64encode(v).decode() for k, v in figures(diag).items()}
    return diag


@dataclass
class TFDiagnosis:
    """Same fields as ``diagnose.Diagnosis`` (the report writers take either)."""

    report: dict
    twin: TFTwin
    augmented: TFTwin
    views: ViewTable
    views_after: ViewTable | None
    timings_s: dict
    plots: dict

    def twin_file(self) -> dict:
        """``<device>.twin.json``: the augmented table-free twin (format ``imulab.simreal.tablefree_model/1``: per run
        the fitted model, its noise and the accepted effects; the recorded inputs stay with the session)."""
        return self.augmented.to_json()


def figures(diag) -> dict:
    """Table-free plots (PNG bytes): static-pose residuals, gyro pose means against specific force, rotation
    residuals, Allan bands of the static interval; real against the replicates' 95 % band."""
    import io

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    st = diag.plots["tablefree"]
    out = {}
    for i, real in enumerate(st["reals"]):
        reps = [rp[i] for rp in st["reps"]]
        fig, axs = plt.subplots(2, 2, figsize=(11, 7))
        ax = axs[0, 0]
        band = []
        for rp in reps:
            mi = _match(real.pose_t, rp.pose_t)
            band.append(np.where(mi >= 0, rp.a_y[np.maximum(mi, 0)], np.nan))
        band = np.array(band) * 1e3
        k = np.arange(len(real.a_y))
        ax.fill_between(k, np.nanpercentile(band, 2.5, 0), np.nanpercentile(band, 97.5, 0), color="0.8",
                        label="twin replicates 95 %")
        ax.plot(k, real.a_y * 1e3, "o-", color="C3", ms=3, label="real")
        ax.set_xlabel("static pose (time order)")
        ax.set_ylabel("|f| - g [mm/s^2]")
        ax.set_title("static-pose accelerometer residual", fontsize=9)
        ax.legend(fontsize=7)
        ax = axs[0, 1]
        f = np.array([real.signals["f"][a:b].mean(0) for a, b in zip(real.pose_starts, real.pose_ends)])
        k = np.arange(len(real.a_y))
        for j in range(3):
            off = (j - 1) * 0.3  # deg/s between channels
            ax.plot(k, (real.s_y[:, j] - real.s_y[:, j].mean()) * 180 / np.pi + off, "o-", ms=3, lw=0.6,
                    color=f"C{j}", label=f"gyro {'xyz'[j]} (offset {off:+.1f})")
            sd = np.nanmean([np.std(rp.s_y[:, j]) for rp in reps]) * 180 / np.pi
            ax.axhspan(off - 1.96 * sd, off + 1.96 * sd, color=f"C{j}", alpha=0.12)
            for e in diag.report["effects"]:
                if e["family"] == "g_sensitivity" and e["channel"] == REPORT_CHANNELS[j]:
                    pr = f @ np.asarray(e["coefficients"])
                    ax.plot(k, (pr - pr.mean()) * 180 / np.pi + off, "x", color="k", ms=4)
        ax.set_xlabel("static pose (time order)")
        ax.set_ylabel("gyro pose mean - mean [deg/s]")
        ax.set_title("static gyro residual (bands: twin 95 %; x: fitted g-sensitivity G f)", fontsize=9)
        ax.legend(fontsize=7)
        ax = axs[1, 0]
        if real.p_y.size:
            ang = np.degrees(np.linalg.norm(real.p_y, axis=1))
            rb = np.array([np.degrees(np.linalg.norm(rp.p_y, axis=1)).mean() for rp in reps])
            rq = np.concatenate([np.degrees(np.linalg.norm(rp.p_y, axis=1)) for rp in reps])
            peak = [np.degrees(np.max(np.linalg.norm(real.signals["w"][e:s], axis=1))) if s > e else 0.0
                    for e, s in zip(real.pose_ends[:-1], real.pose_starts[1:])]
            ax.plot(peak, ang, "o", ms=3, color="C3", label="real, per rotation")
            ax.axhline(np.percentile(rq, 95), color="0.4", ls="--", label="twin replicates 95th percentile")
            ax.axhline(rb.mean(), color="0.6", ls=":", label="twin mean")
            ax.set_xlabel("peak rate of the rotation [deg/s]")
            ax.set_ylabel("integration residual [deg]")
            ax.legend(fontsize=7)
        else:
            ax.text(0.5, 0.5, "no integration residual: the Ferraris closed form\nis exactly determined by its three rotations",
                    ha="center", va="center", transform=ax.transAxes, fontsize=8)
            ax.set_axis_off()
        ax.set_title("gyro integration residual per rotation", fontsize=9)
        ax = axs[1, 1]
        vt = diag.views.table
        al = vt[vt["view"].str.startswith("allan_band") & (vt["run_id"] == real.run_id)]
        for j, ch in enumerate(REPORT_CHANNELS):
            s = al[al["channel"] == ch]
            if s.empty:
                continue
            tau = s["view"].str.extract(r"tau([0-9.e+-]+)s")[0].astype(float).to_numpy()
            o = np.argsort(tau)
            ax.plot(tau[o], 10 ** s["real"].to_numpy()[o], "-", color=f"C{j}", label=f"{ch} real")
            lo = 10 ** (s["rep_mean"] - 1.96 * s["rep_sd"]).to_numpy()[o]
            hi = 10 ** (s["rep_mean"] + 1.96 * s["rep_sd"]).to_numpy()[o]
            ax.fill_between(tau[o], lo, hi, color=f"C{j}", alpha=0.15)
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("tau [s]")
        ax.set_ylabel("Allan deviation (SI)")
        ax.set_title("longest static interval: real (lines) vs twin 95 % (bands)", fontsize=9)
        ax.legend(fontsize=6, ncol=2)
        fig.suptitle(f"{diag.report['device_id']} / {real.run_id}: verdict {diag.report['verdict']}", fontsize=10)
        fig.tight_layout()
        buf = io.BytesIO()
        fig.savefig(buf, format="png", dpi=90)
        plt.close(fig)
        out[real.run_id] = buf.getvalue()
    return out
