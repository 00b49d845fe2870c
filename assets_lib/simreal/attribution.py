"""Which effect: greedy forward selection on held-out log predictive density, with ambiguity sets.

simreal.md sec. 4.2: every candidate is scored by adding it to the current model; score = leave-one-run-out
held-out gain, summed over the runs that carry its signature, of the whitened SSE with only nuisance parameters
refitted on the held-out run (``design.py`` has projected them out). ``delta_lpd`` is reported on the deviance
scale (twice the held-out log predictive gain), so the gate "likelihood ratio 1000:1" reads
``delta_lpd > 2 ln 1000 = 13.8``. Accept the best candidate if it passes that gate, the sim-vs-sim calibrated
gate (the same score on replicates of the base twin, ``threshold``), and is positive in all but one fold (at
least two folds). Shape parameters (warm-up tau) are chosen on the training runs of each fold.

Ambiguity (simreal.md sec. 4.2 step 4 and 4.4): with every acceptance, candidates that pass the gates and tie
(within 2 ln 10 overall, or the accepted one ahead in fewer than K - 1 of the common folds), or whose columns
reproduce the accepted signature with alias R^2 >= 0.95 after projecting out the already accepted effects.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from assets_lib.simreal.design import ATOMS, Design

GATE = 2.0 * np.log(1000.0)
TIE = 2.0 * np.log(10.0)
ALIAS_R2 = 0.95
MAX_EFFECTS = 4


def groups() -> list[tuple[str, int | None, list[int]]]:
    """Candidates: (family, channel) with their atom indices (one per shape value)."""
    out: dict = {}
    for ai, at in enumerate(ATOMS):
        out.setdefault((at.family, at.channel), []).append(ai)
    return [(f, c, v) for (f, c), v in out.items()]


GROUPS = groups()


def _solve(G: np.ndarray, b: np.ndarray) -> np.ndarray:
    if b.size == 0:
        return np.zeros(0)
    reg = 1e-12 * max(np.trace(G) / max(len(b), 1), 1e-300)
    try:
        return np.linalg.solve(G + reg * np.eye(len(b)), b)
    except np.linalg.LinAlgError:
        return np.linalg.lstsq(G, b, rcond=None)[0]


@dataclass
class Totals:
    """Per-run Gram sums over blocks."""

    G: np.ndarray  # (n_runs, P, P)
    b: np.ndarray  # (n_runs, P)
    s: np.ndarray  # (n_runs,)
    carries: np.ndarray

    @classmethod
    def of(cls, d: Design, blocks=(0, 1, 2)) -> Totals:
        bl = list(blocks)
        return cls(d.gram[:, bl].sum(1), d.xty[:, bl].sum(1), d.yty[:, bl].sum(1), d.carries)

    def heldout_sse(self, cols: list[int], k: int) -> float:
        Gt = self.G.sum(0) - self.G[k]
        bt = self.b.sum(0) - self.b[k]
        if not cols:
            return float(self.s[k])
        g = _solve(Gt[np.ix_(cols, cols)], bt[cols])
        Gk = self.G[k][np.ix_(cols, cols)]
        return float(self.s[k] - 2 * g @ self.b[k][cols] + g @ Gk @ g)

    def train_sse(self, cols: list[int], k: int | None) -> float:
        Gt = self.G.sum(0) - (self.G[k] if k is not None else 0)
        bt = self.b.sum(0) - (self.b[k] if k is not None else 0)
        st = self.s.sum() - (self.s[k] if k is not None else 0)
        if not cols:
            return float(st)
        g = _solve(Gt[np.ix_(cols, cols)], bt[cols])
        return float(st - g @ bt[cols])

    def coef(self, cols: list[int]) -> np.ndarray:
        return _solve(self.G.sum(0)[np.ix_(cols, cols)], self.b.sum(0)[cols])


@dataclass
class Score:
    group: int
    delta_lpd: float
    fold_gains: list
    folds: list  # run indices
    shape: float | None
    atom: int

    @property
    def n_pos(self) -> int:
        return int(np.sum(np.asarray(self.fold_gains) > 0))

    def fold_ok(self) -> bool:
        k = len(self.folds)
        return k >= 2 and self.n_pos >= k - 1


def cols_of(atoms: list[int]) -> list[int]:
    return [c for a in atoms for c in ATOMS[a].cols]


def score_group(t: Totals, gi: int, base_atoms: list[int]) -> Score | None:
    _fam, _ch, atoms = GROUPS[gi]
    carry = np.flatnonzero(t.carries[:, atoms].any(axis=1))
    if carry.size == 0:
        return None
    base = cols_of(base_atoms)
    gains = []
    for k in carry:
        best = None
        for a in atoms:  # shape chosen on the training runs
            sse = t.train_sse(base + list(ATOMS[a].cols), k)
            if best is None or sse < best[0]:
                best = (sse, a)
        a = best[1]
        gains.append(t.heldout_sse(base, k) - t.heldout_sse(base + list(ATOMS[a].cols), k))
    full = min(atoms, key=lambda a: t.train_sse(base + list(ATOMS[a].cols), None))
    return Score(gi, float(np.sum(gains)), [float(g) for g in gains], [int(k) for k in carry], ATOMS[full].shape, full)


def _separable(best: Score, other: Score) -> bool:
    """simreal.md sec. 4.2 step 4: the best candidate is separable from another only if it is ahead in at least
    K - 1 of the K folds both are scored on (with fewer than two common folds: by the overall margin alone)."""
    common = [k for k in best.folds if k in other.folds]
    if len(common) < 2:
        return True
    gb = dict(zip(best.folds, best.fold_gains))
    go = dict(zip(other.folds, other.fold_gains))
    ahead = sum(gb[k] > go[k] for k in common)
    return ahead >= len(common) - 1


def alias_r2(t: Totals, base_atoms: list[int], chosen: int, other_atoms: list[int]) -> float:
    """Fraction of the chosen atom's fitted signature (base projected out) reproduced by another candidate."""
    G = t.G.sum(0)
    A, B = cols_of(base_atoms), list(ATOMS[chosen].cols)
    C = cols_of(other_atoms)
    C = [c for c in C if c not in B]
    if not C:
        return 1.0
    g = _solve(G[np.ix_(A + B, A + B)], t.b.sum(0)[A + B])[len(A):]

    def resid(X, Y):
        if not A:
            return G[np.ix_(X, Y)]
        GA = G[np.ix_(A, A)]
        return G[np.ix_(X, Y)] - G[np.ix_(X, A)] @ _solve_mat(GA, G[np.ix_(A, Y)])

    MBB = resid(B, B)
    ss = float(g @ MBB @ g)
    if ss <= 0:
        return 0.0
    MCC = resid(C, C)
    v = resid(C, B) @ g
    try:
        expl = float(v @ np.linalg.lstsq(MCC, v, rcond=None)[0])
    except np.linalg.LinAlgError:
        return 0.0
    return float(np.clip(expl / ss, 0.0, 1.0))


def _solve_mat(G, B):
    return np.linalg.lstsq(G, B, rcond=None)[0]


@dataclass
class Selection:
    accepted: list  # Score in acceptance order
    ambiguity: list  # list of lists of group indices
    first_step: list  # Score of every candidate at step 1 (for reports and the null calibration)
    coef: dict = field(default_factory=dict)  # atom -> coefficients (all-data fit of the final model)
    jackknife: dict = field(default_factory=dict)  # atom -> leave-one-run-out coefficients (runs carrying the model)


def first_step_scores(t: Totals) -> dict:
    out = {}
    for gi in range(len(GROUPS)):
        s = score_group(t, gi, [])
        if s is not None:
            out[gi] = s.delta_lpd
    return out


def select(d: Design, thresholds: dict | None = None) -> Selection:
    """Greedy forward selection (module docstring). ``thresholds``: group -> calibrated gate (>= GATE)."""
    t = Totals.of(d)
    thr = thresholds or {}
    accepted: list[Score] = []
    amb: list[list[int]] = []
    first: list = []
    base_atoms: list[int] = []
    used_groups: set = set()
    for step in range(MAX_EFFECTS):
        scores = []
        for gi in range(len(GROUPS)):
            if gi in used_groups:
                continue
            s = score_group(t, gi, base_atoms)
            if s is not None:
                scores.append(s)
        if step == 0:
            first = scores
        ok = [s for s in scores if s.delta_lpd > max(GATE, thr.get(s.group, GATE)) and s.fold_ok()]
        if not ok:
            break
        best = max(ok, key=lambda s: s.delta_lpd)
        tie = [s.group for s in ok if s.group != best.group and (s.delta_lpd >= best.delta_lpd - TIE
                                                                  or not _separable(best, s))]
        alias = []
        for s in scores:
            if s.group == best.group or s.group in tie:
                continue
            if alias_r2(t, base_atoms, best.atom, [s.atom]) >= ALIAS_R2:
                alias.append(s.group)
        accepted.append(best)
        amb.append([best.group] + tie + alias)
        base_atoms.append(best.atom)
        used_groups.add(best.group)
    coef, jack = {}, {}
    if base_atoms:
        cols = cols_of(base_atoms)
        g = t.coef(cols)
        carry = np.flatnonzero(t.carries[:, base_atoms].any(axis=1))
        gj = [_solve((t.G.sum(0) - t.G[k])[np.ix_(cols, cols)], (t.b.sum(0) - t.b[k])[cols]) for k in carry] \
            if carry.size >= 3 else []
        k = 0
        for a in base_atoms:
            n = len(ATOMS[a].cols)
            coef[a] = g[k:k + n]
            jack[a] = [x[k:k + n] for x in gj]
            k += n
    return Selection(accepted, amb, first, coef, jack)


def heldout_error(d: Design, atoms: list[int], blocks=(0, 1, 2)) -> float:
    """E: summed leave-one-run-out whitened SSE of the model with ``atoms`` (simreal.md sec. 5.1)."""
    t = Totals.of(d, blocks)
    cols = cols_of(atoms)
    return float(sum(t.heldout_sse(cols, k) for k in range(t.G.shape[0])))


def refit(d: Design, atoms: list[int]) -> dict:
    """All-data coefficients of ``atoms`` on another realisation (for parametric-bootstrap intervals)."""
    t = Totals.of(d)
    g = t.coef(cols_of(atoms))
    out, k = {}, 0
    for a in atoms:
        n = len(ATOMS[a].cols)
        out[a] = g[k:k + n]
        k += n
    return out
