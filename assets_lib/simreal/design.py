"""Observation blocks, whitening, nuisance projection and per-run Gram matrices (simreal.md sec. 4.2).

One :class:`Design` holds, for one realisation of the experiment (the real data or a replicate), every row of
the three blocks (``effects.py``) whitened by the twin's stochastic model and with the run's *nuisance*
parameters projected out (Frisch-Waugh): per run and channel the base model's own linear terms (bias, scale
factor and misalignment row, linear g-sensitivity; for accelerometer positions also K2 and cross-coupling).
Refitting only those on a held-out run is then exactly the residualisation done here, so every held-out
prediction of the attribution step is a p x p solve on the per-run Gram matrices (simreal.md sec. 4.2: "with
per-run Gram matrices each (candidate x fold) fit is a p x p solve").

Whitening: block A (plateau means) by the Cholesky factor of diag(sem^2 - 2 ln2 tau^2) + tau^2 G + K^2 min(t_i, t_j)
(segmentation's Allan-based standard errors, the twin's bias instability between plateaus with the library's 1/f
kernel G of ``fit_core.log_kernel``, tau^2 = B^2/pi, and the twin's rate random walk K); block B by the twin's
white, flicker and quantisation level of a 10-sample mean; block C by the alignment's standard error. Remaining
misfit of the whitening (bias instability between plateaus) is calibrated by the sim-vs-sim distribution of
every statistic, never assumed away.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import pandas as pd

from assets_lib.calibration.fit_core import log_kernel
from assets_lib.calibration.segmentation import CHANNELS
from assets_lib.simreal import effects as fx
from assets_lib.simreal import run_level
from assets_lib.simreal.experiment import DECIMATE, ProcessedRun, RunInputs

AX = "xyz"


@dataclass(frozen=True)
class Atom:
    """One candidate (family, channel, shape) and its columns in the design."""

    family: str
    channel: int | None
    shape: float | None
    cols: tuple[int, ...]


def candidate_atoms() -> list[Atom]:
    atoms, k = [], 0
    for fam in fx.FAMILIES.values():
        chans = fam.channels if fam.channels else (None,)
        for ch in chans:
            for sh in fam.shapes:
                atoms.append(Atom(fam.name, ch, sh, tuple(range(k, k + fam.n_coef))))
                k += fam.n_coef
    return atoms


ATOMS = candidate_atoms()
N_COLS = sum(len(a.cols) for a in ATOMS)
#: view-only features on block A (not effects): visit order
VIEW_ONLY = ("visit_order",)


@dataclass(frozen=True, eq=False)
class Design:
    """Whitened, nuisance-projected rows of all blocks plus per-run Gram matrices."""

    run_ids: tuple[str, ...]
    gram: np.ndarray  # (n_runs, 3 blocks, P, P)
    xty: np.ndarray  # (n_runs, 3, P)
    yty: np.ndarray  # (n_runs, 3)
    carries: np.ndarray  # (n_runs, n_atoms) bool: the run carries the atom's signature
    rows: pd.DataFrame  # block, run, channel, step_index, y (whitened residualised)
    extra_t: dict = field(default_factory=dict)  # view-only projection statistics {(view, run, channel): t}
    #: block A per (run index, channel): whitened projected y and columns, the whitening-and-projection operator M
    #: (any further signature on those rows enters as M @ x) and the plateaus' (plan, step) keys, for the
    #: lack-of-fit test of accepted effects (``attribution.lack_of_fit``)
    a_rows: dict = field(default_factory=dict)
    #: block D (``run_level.py``): per power cycle (rows of ``d_cycles``) Gram sums of the whitened, cycle-bias-
    #: projected run-level bias rows; ``run_cycle``: each run's row in ``d_cycles`` (-1: no block-D row)
    gram_d: np.ndarray | None = None  # (n_cycles, P, P)
    xty_d: np.ndarray | None = None  # (n_cycles, P)
    yty_d: np.ndarray | None = None  # (n_cycles,)
    carries_d: np.ndarray | None = None  # (n_cycles, n_atoms)
    d_cycles: tuple = ()
    run_cycle: tuple = ()


def _orth(a: np.ndarray, tol: float = 1e-10) -> np.ndarray:
    if a.size == 0:
        return np.zeros((a.shape[0], 0))
    u, s, _ = np.linalg.svd(a, full_matrices=False)
    keep = s > tol * max(s[0], 1e-300)
    return u[:, keep]


#: names of ``_nuisance``'s columns (block D shares them by name across the runs of a power cycle)
def nuisance_names(kind: str, j: int) -> tuple:
    if j < 3:
        return ("1", "w_x", "w_y", "w_z", "f_x", "f_y", "f_z") if kind == "rate" else ("1", "f_x", "f_y", "f_z")
    if kind == "rate":
        return ("1", "f_x", "f_y", "f_z")
    return ("1", "f_x", "f_y", "f_z", "k2", "c_1", "c_2")


def _nuisance(kind: str, j: int, w: np.ndarray, f: np.ndarray) -> np.ndarray:
    one = np.ones((len(w), 1))
    if j < 3:
        if kind == "rate":
            return np.hstack([one, w, f])
        return np.hstack([one, f])
    if kind == "rate":
        return np.hstack([one, f])
    i = j - 3
    others = [k for k in range(3) if k != i]
    return np.hstack([one, f, f[:, [i]] ** 2, f[:, [i]] * f[:, others]])


def block_a_features(p: pd.DataFrame, inp: RunInputs) -> dict:
    w = p[[f"omega_ref_{a}_radps" for a in AX]].to_numpy(float)
    we = p[[f"omega_earth_{a}_radps" for a in AX]].to_numpy(float)
    f = p[[f"f_ref_{a}_mps2" for a in AX]].to_numpy(float)
    tmid = 0.5 * (p["t_start_s"].to_numpy(float) + p["t_end_s"].to_numpy(float))
    ton0 = float(inp.t_on_s[0] - inp.t_s[0])
    lags = {}
    i0 = np.searchsorted(inp.t_s, p["t_start_s"].to_numpy(float))
    i1 = np.maximum(np.searchsorted(inp.t_s, p["t_end_s"].to_numpy(float), side="right"), i0 + 1)
    for lag in fx.THERMAL_LAGS_S:
        if lag:
            c = np.concatenate([[0.0], np.cumsum(fx.lagged_temperature(inp.t_s, inp.temperature_degc, lag))])
            lags[float(lag)] = (c[i1] - c[i0]) / (i1 - i0)
    # plateau means of the wobble's signature -(e_m x f) (effects.columns, table_wobble on block A)
    wob = np.stack([-np.cross(e, inp.f_b_mps2) for e in (inp.tilt_e1_b, inp.tilt_e2_b)], axis=1)  # (n, 2, 3)
    cw = np.concatenate([np.zeros((1, 2, 3)), np.cumsum(wob, axis=0)])
    wob_mean = (cw[i1] - cw[i0]) / (i1 - i0)[:, None, None]
    return {"n": len(p), "omega": w, "omega_motion": w - we, "force": f, "temp": p["temperature_degc_mean"].to_numpy(float),
                "t_on": tmid + ton0, "t_run": tmid,
                "is_rate": (p["kind"].to_numpy() == "rate") & (np.abs(p["commanded_rate_radps"].to_numpy(float)) > 0),
                "step": p["step_index"].to_numpy(float), "temp_lag": lags, "wobble": wob_mean}


def _project(yw, Xw, Nw):
    Q = _orth(Nw)
    return yw - Q @ (Q.T @ yw), Xw - Q @ (Q.T @ Xw)


#: columns with block-D (run-level) signatures: every family with block-A columns (``run_level.py``)
D_COLS = np.zeros(N_COLS)
for _at in ATOMS:
    if fx.has_block(_at.family, "A"):
        D_COLS[list(_at.cols)] = 1.0


def build_design(runs: tuple[RunInputs, ...], processed: dict, twin, imus: dict, real_windows: dict,
                 rk_per_channel: np.ndarray, bias_offset: dict | None = None) -> Design:
    """Blocks A, B, C, D of one realisation. ``real_windows``: run -> list of (step, sample index array) of the
    real run's rate windows (block B rows are fixed by the recorded experiment). ``bias_offset``: run -> (6,) bias
    the realisation was simulated with (replicates: the real run's fitted bias), subtracted from the run-level
    observations of block D (``run_level.py``)."""
    flicker_b = np.array([p.b for p in twin.noise])
    d_entries = []
    n_runs = len(runs)
    P = N_COLS
    gram = np.zeros((n_runs, 3, P, P))
    xty = np.zeros((n_runs, 3, P))
    yty = np.zeros((n_runs, 3))
    carries = np.zeros((n_runs, len(ATOMS)), bool)
    rows = []
    extra = {}
    a_rows = {}
    rails = twin.rails
    for ri, inp in enumerate(runs):
        pr: ProcessedRun = processed[inp.run_id]
        p = pr.plateaus
        p = p[~p["flagged"] & (p["n_samples"] > 0)].reset_index(drop=True)
        cyc = twin.cycle(inp.power_cycle)
        parts_y, parts_X = {"A": [], "B": [], "C": []}, {"A": [], "B": [], "C": []}
        # ---------------- block A
        if len(p):
            feat = block_a_features(p, inp)
            gp, ap = cyc.predict(feat["omega"], feat["force"])
            pred = np.column_stack([gp, ap])
            for j, ch in enumerate(CHANNELS):
                y = p[f"{ch}_mean"].to_numpy(float) - pred[:, j]
                s = p[f"{ch}_sem"].to_numpy(float)
                ok = np.isfinite(y) & np.isfinite(s) & (s > 0)
                rail = rails[0] if j < 3 else rails[1]
                if rail:
                    ok &= np.abs(p[f"{ch}_mean"].to_numpy(float)) < 0.98 * rail
                    if j < 3:  # a plateau whose other gyro axes clip is not trusted either
                        for c2 in CHANNELS[:3]:
                            ok &= np.abs(p[f"{c2}_mean"].to_numpy(float)) < 0.98 * rail
                if ok.sum() < 3:
                    continue
                idx = np.flatnonzero(ok)
                sub = {k: (v[idx] if isinstance(v, np.ndarray) else v) for k, v in feat.items()}
                sub["temp_lag"] = {k: v[idx] for k, v in feat["temp_lag"].items()}
                sub["n"] = idx.size
                X = np.zeros((idx.size, P))
                for ai, at in enumerate(ATOMS):
                    if not fx.has_block(at.family, "A"):
                        continue
                    if at.channel is not None and at.channel != j:
                        continue
                    c = fx.columns(at.family, "A", sub, j, at.shape)
                    if c is not None:
                        X[:, list(at.cols)] = c
                N = _nuisance(inp.kind, j, sub["omega"], sub["force"])
                t = sub["t_run"] - sub["t_run"].min()
                tlen = (p["t_end_s"].to_numpy(float) - p["t_start_s"].to_numpy(float))[idx]
                # bias instability between plateaus: tau^2 G with the library's 1/f kernel (fit_core.log_kernel),
                # tau^2 = B^2 / pi, the white part of the sems reduced by its Allan floor (as fit_core.flicker_gls)
                tau2 = flicker_b[j] ** 2 / np.pi
                D = np.maximum(s[idx] ** 2 - 2 * np.log(2) * tau2, 0.1 * s[idx] ** 2)
                C = np.diag(D) + tau2 * log_kernel(sub["t_run"], tlen) + rk_per_channel[j] ** 2 * np.minimum.outer(t, t)
                try:
                    L = np.linalg.cholesky(C)
                except np.linalg.LinAlgError:
                    L = np.diag(s[idx])
                Li = np.linalg.inv(L)
                if j in run_level.CHANNELS:
                    off = float(bias_offset[inp.run_id][j]) if bias_offset and inp.run_id in bias_offset else 0.0
                    e = run_level.entry(ri, j, inp.power_cycle, Li, N, nuisance_names(inp.kind, j), y[idx], X, D,
                                        sub["t_on"], tlen, D_COLS, off)
                    if e is not None:
                        d_entries.append(e)
                yr, Xr = _project(Li @ y[idx], Li @ X, Li @ N)
                Q = _orth(Li @ N)
                plan_key = (inp.kind, len(getattr(getattr(inp.manifest, "plan", None), "steps", ()) or ()))
                a_rows[(ri, j)] = {"y": yr, "X": Xr, "M": Li - Q @ (Q.T @ Li),
                                   "keys": [(plan_key, int(st)) for st in p["step_index"].to_numpy()[idx]]}
                # view-only: visit order
                vo = Li @ sub["step"]
                _, vr = _project(vo, vo[:, None], Li @ N)
                nv = float(vr[:, 0] @ vr[:, 0])
                if nv > 1e-20:
                    extra[("residual_vs_visit_order", inp.run_id, fx.CHANNEL_NAMES[j])] = (float(vr[:, 0] @ yr), nv)
                parts_y["A"].append(yr)
                parts_X["A"].append(Xr)
                for k_, (yy, st) in enumerate(zip(yr, p["step_index"].to_numpy()[idx])):
                    rows.append(("A", inp.run_id, fx.CHANNEL_NAMES[j], int(st), float(yy)))
        # ---------------- block B (columns cached: they depend on the recorded inputs only)
        wb = real_windows.get(inp.run_id)
        if wb is not None and wb["idx"].size and inp.run_id in imus:
            ii = wb["idx"]
            y_all = imus[inp.run_id][list(CHANNELS)].to_numpy(float)[ii]
            gp, ap = cyc.predict(inp.omega_b_radps[ii], inp.f_b_mps2[ii])
            res = y_all - np.column_stack([gp, ap])
            grp = wb["grp"]
            cnt = np.bincount(grp)
            fs = 1.0 / float(np.median(np.diff(inp.t_s)))
            for j, ch in enumerate(CHANNELS):
                nz = twin.noise[j]
                sig2 = nz.n**2 * fs / DECIMATE + 3 * nz.q**2 * fs**2 / DECIMATE**2 + 0.5 * (2 * np.log(2) / np.pi) * nz.b**2
                sig2 += inp.lsb_si[j] ** 2 / 12 / DECIMATE
                sig = float(np.sqrt(max(sig2, 1e-30)))
                rb = res[:, j].reshape(-1, DECIMATE).mean(axis=1)
                rb = rb - (np.bincount(grp, rb) / cnt)[grp]
                yb = rb / sig
                parts_y["B"].append(yb)
                parts_X["B"].append(wb["X"][j] / sig)
                rms = np.sqrt(np.bincount(grp, yb**2) / cnt)
                for st, v in zip(wb["steps"], rms):
                    rows.append(("B", inp.run_id, fx.CHANNEL_NAMES[j], int(st), float(v)))
        # ---------------- block C
        if np.isfinite(pr.clock_drift_ppm) and np.isfinite(pr.clock_drift_stderr_ppm) and pr.clock_drift_stderr_ppm > 0:
            X = np.zeros((1, P))
            for at in ATOMS:
                if fx.FAMILIES[at.family].block == "C":
                    X[:, list(at.cols)] = fx.columns(at.family, "C", {"n": 1}, 0, at.shape)
            se = pr.clock_drift_stderr_ppm
            parts_y["C"].append(np.array([pr.clock_drift_ppm / se]))
            parts_X["C"].append(X / se)
            rows.append(("C", inp.run_id, None, None, float(pr.clock_drift_ppm / se)))
        for bi, blk in enumerate("ABC"):
            if parts_y[blk]:
                Y = np.concatenate(parts_y[blk])
                X = np.vstack(parts_X[blk])
                gram[ri, bi] = X.T @ X
                xty[ri, bi] = X.T @ Y
                yty[ri, bi] = float(Y @ Y)
    # a run carries a signature when it holds >= 1 % of the signature's total (whitened) energy: the earth-rate
    # component of a static run "carries" omega x T only numerically (measured: such folds gained exactly 0 and
    # blocked the all-but-one fold rule for a hidden temperature scale factor)
    dg = np.diagonal(gram.sum(axis=1), axis1=1, axis2=2)  # (n_runs, P)
    tot = dg.sum(axis=0)
    share = np.where(tot > 0, dg / np.where(tot > 0, tot, 1.0), 0.0)
    for ai, at in enumerate(ATOMS):
        carries[:, ai] = np.any(share[:, list(at.cols)] >= 0.01, axis=1)
    # ---------------- block D (run level): per power cycle and channel
    cyc_ids = sorted({e.cycle for e in d_entries})
    gd = np.zeros((len(cyc_ids), P, P))
    xd = np.zeros((len(cyc_ids), P))
    sd = np.zeros(len(cyc_ids))
    run_cycle = np.full(n_runs, -1)
    for ci, pc in enumerate(cyc_ids):
        for j in range(6):
            es = [e for e in d_entries if e.cycle == pc and e.channel == j]
            out = run_level.cycle_rows(es, flicker_b[j] ** 2 / np.pi, rk_per_channel[j] ** 2)
            if out is None:
                continue
            yd, Xd = out
            ris = [e.run_index for e in es]
            gd[ci] += Xd.T @ Xd
            xd[ci] += Xd.T @ yd
            sd[ci] += float(yd @ yd)
            run_cycle[ris] = ci
            for v in yd:
                rows.append(("D", None, fx.CHANNEL_NAMES[j], None, float(v)))
    carries_d = np.zeros((len(cyc_ids), len(ATOMS)), bool)
    if len(cyc_ids):
        ddg = np.diagonal(gd, axis1=1, axis2=2)
        tot_d = tot + ddg.sum(axis=0)
        share_d = np.where(tot_d > 0, ddg / np.where(tot_d > 0, tot_d, 1.0), 0.0)
        for ai, at in enumerate(ATOMS):
            carries_d[:, ai] = np.any(share_d[:, list(at.cols)] >= 0.01, axis=1)
    df = pd.DataFrame(rows, columns=["block", "run_id", "channel", "step_index", "y"])
    return Design(tuple(r.run_id for r in runs), gram, xty, yty, carries, df, extra, a_rows, gd, xd, sd, carries_d,
                  tuple(cyc_ids), tuple(int(c) for c in run_cycle))


def real_rate_windows(runs, processed, imus: dict, rails=(None, None)) -> dict:
    """Block B rows: the real run's kept samples of each rate window, cut to 10-sample blocks, with the
    signature columns (decimated, window mean removed); fixed for every replicate (recorded inputs)."""
    out = {}
    P = N_COLS
    b_atoms = [a for a in ATOMS if fx.FAMILIES[a.family].block == "B"]
    for inp in runs:
        if inp.kind != "rate" or inp.table is None:
            continue
        pr = processed[inp.run_id]
        p = pr.plateaus
        g_all = imus[inp.run_id][list(CHANNELS[:3])].to_numpy(float)
        idx_l, grp_l, steps = [], [], []
        for _, row in p.iterrows():
            if row["kind"] != "rate" or row["commanded_rate_radps"] == 0 or row["flagged"]:
                continue
            k = int(row["step_index"])
            idx = np.flatnonzero((pr.window_step == k) & pr.keep)
            if rails[0] and idx.size and np.max(np.abs(g_all[idx])) >= 0.98 * rails[0]:
                continue  # a clipped window carries no table-angle signature
            m = (idx.size // DECIMATE) * DECIMATE
            if m < 2 * DECIMATE:
                continue
            idx_l.append(idx[:m])
            grp_l.append(np.full(m // DECIMATE, len(steps)))
            steps.append(k)
        if not idx_l:
            continue
        ii = np.concatenate(idx_l)
        grp = np.concatenate(grp_l)
        feat = {"n": ii.size, "theta": inp.table_angle_rad[ii], "rate_t": inp.table_rate_radps[ii], "u": inp.table_axis_b[ii],
                    "e1": inp.tilt_e1_b[ii], "e2": inp.tilt_e2_b[ii], "force": inp.f_b_mps2[ii]}
        cnt = np.bincount(grp)
        Xj = {}
        for j in range(6):
            X = np.zeros((ii.size, P))
            for at in b_atoms:
                c = fx.columns(at.family, "B", feat, j, at.shape)
                if c is not None:
                    X[:, list(at.cols)] = c
            Xb = X.reshape(-1, DECIMATE, P).mean(axis=1)
            means = np.stack([np.bincount(grp, Xb[:, c]) / cnt for c in range(P)], axis=1)
            Xj[j] = Xb - means[grp]
        out[inp.run_id] = {"idx": ii, "grp": grp, "steps": steps, "X": Xj}
    return out
