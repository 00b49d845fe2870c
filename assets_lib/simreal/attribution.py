"""Which effect: greedy forward selection on held-out log predictive density, with ambiguity sets.

simreal.md sec. 4.2: every candidate is scored by adding it to the current model; score = leave-one-run-out
held-out gain, summed over the runs that carry its signature, of the whitened SSE with only nuisance parameters
refitted on the held-out run (``design.py`` has projected them out). ``delta_lpd`` is reported on the deviance
scale (twice the held-out log predictive gain), so the gate "likelihood ratio 1000:1" reads
``delta_lpd > 2 ln 1000 = 13.8``. Accept the best candidate if it passes that gate, the sim-vs-sim calibrated
gate (mean + 5 sd of the same score, at the same step, on replicates of the base twin: ``step_gates``), the
family-wise predictive p of the step (``null_p_step`` <= ``ALPHA_STEP``), and is positive in all but one fold (at
least two folds). Held-out solves drop columns absent from a fold's training runs (``Totals.trained_cols``). Shape parameters (warm-up tau) are chosen on the training runs of each fold.

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
#: family-wise level of a selection step: the best null candidate of the step reaches an accepted score with at
#: most this probability (``null_p_step``; every step, the first included)
ALPHA_STEP = 0.05


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


#: a column is absent from a fold's training set when its training Gram diagonal is below this fraction of its
#: diagonal over all runs (e.g. g^2 columns in a device with one position run: held out, the training rate run
#: carries 1e-30 of their energy, and the solve returned 1e+30-scale coefficients that overflowed the matmul)
ABSENT_REL = 1e-9


@dataclass
class Totals:
    """Gram sums over blocks per held-out unit: one row per run (blocks A, B, C), then one row per power cycle
    (block D, ``run_level.py``)."""

    G: np.ndarray  # (n_rows, P, P)
    b: np.ndarray  # (n_rows, P)
    s: np.ndarray  # (n_rows,)
    carries: np.ndarray
    #: fold of each row for the families with block-D columns: the row of its power cycle's block D (a run's rows
    #: and its cycle's run-level rows form one fold), else the row itself
    fold: np.ndarray | None = None
    #: (held-out row, column) pairs dropped because the column is absent from that fold's training rows
    absent: set = field(default_factory=set)

    @classmethod
    def of(cls, d: Design, blocks=(0, 1, 2, 3)) -> Totals:
        bl = [b for b in blocks if b < 3]
        G, b, s, c = d.gram[:, bl].sum(1), d.xty[:, bl].sum(1), d.yty[:, bl].sum(1), d.carries
        n = G.shape[0]
        fold = np.arange(n)
        if 3 in blocks and d.gram_d is not None and len(d.gram_d):
            G = np.concatenate([G, d.gram_d])
            b = np.concatenate([b, d.xty_d])
            s = np.concatenate([s, d.yty_d])
            c = np.vstack([c, d.carries_d])
            fold = np.array([n + rc if rc >= 0 else i for i, rc in enumerate(d.run_cycle)]
                            + [n + k for k in range(len(d.gram_d))])
        return cls(G, b, s, c, fold)

    def fold_units(self, atoms: list[int]) -> list[list[int]]:
        """Held-out units of a model (jackknife): rows carrying ``atoms``, grouped by power cycle when one of them
        has block-D columns."""
        carry = np.flatnonzero(self.carries[:, atoms].any(axis=1))
        if self.fold is None or not any(_has_d(a) for a in atoms):
            return [[int(k)] for k in carry]
        out: dict = {}
        for k in carry:
            out.setdefault(int(self.fold[k]), []).append(int(k))
        return list(out.values())

    def trained_cols(self, cols: list[int], k: int | None) -> list[int]:
        """``cols`` without those absent from the training runs of fold ``k`` (recorded in ``absent``): their
        coefficients are not estimable there, so the fold predicts with the base terms alone (its gain is 0)."""
        if k is None or not cols:
            return list(cols)
        dt = np.einsum("ii->i", self.G.sum(0) - self.G[k])[cols]
        da = np.einsum("ii->i", self.G.sum(0))[cols]
        keep = [c for c, x, y in zip(cols, dt, da) if x > ABSENT_REL * y and x > 0]
        if len(keep) < len(cols):
            self.absent.update((int(k), int(c)) for c in cols if c not in keep)
        return keep

    def heldout_sse(self, cols: list[int], k: int) -> float:
        Gt = self.G.sum(0) - self.G[k]
        bt = self.b.sum(0) - self.b[k]
        cols = self.trained_cols(cols, k)
        if not cols:
            return float(self.s[k])
        g = _solve(Gt[np.ix_(cols, cols)], bt[cols])
        Gk = self.G[k][np.ix_(cols, cols)]
        return float(self.s[k] - 2 * g @ self.b[k][cols] + g @ Gk @ g)

    def train_sse(self, cols: list[int], k: int | None) -> float:
        Gt = self.G.sum(0) - (self.G[k] if k is not None else 0)
        bt = self.b.sum(0) - (self.b[k] if k is not None else 0)
        st = self.s.sum() - (self.s[k] if k is not None else 0)
        cols = self.trained_cols(cols, k)
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
    #: held-out gains per power cycle (fold ids of ``Totals.fold``), for comparing a candidate scored on run folds
    #: with one scored on power-cycle folds (``_separable``)
    cycle_gains: dict | None = None
    #: held-out rows whose training rows lack some of the chosen atom's columns (gain 0 there)
    absent_folds: list = field(default_factory=list)
    #: the gate this score was tested against (None: not tested yet)
    gate: float | None = None
    #: Bonferroni-adjusted predictive p of the score under the replicates at its step (``null_p_step``)
    p_step: float | None = None

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
    gains, absent = [], []
    for k in carry:
        best = None
        for a in atoms:  # shape chosen on the training runs
            sse = t.train_sse(base + list(ATOMS[a].cols), k)
            if best is None or sse < best[0]:
                best = (sse, a)
        a = best[1]
        if len(t.trained_cols(list(ATOMS[a].cols), int(k))) < len(ATOMS[a].cols):
            absent.append(int(k))
        gains.append(t.heldout_sse(base, k) - t.heldout_sse(base + list(ATOMS[a].cols), k))
    full = min(atoms, key=lambda a: t.train_sse(base + list(ATOMS[a].cols), None))
    folds = [int(k) for k in carry]
    agg: dict = {}  # a power cycle's held-out gains (its runs' blocks A-C, its run-level rows) summed
    for k, g in zip(carry, gains):
        f = int(t.fold[k]) if t.fold is not None else int(k)
        agg[f] = agg.get(f, 0.0) + float(g)
    if t.fold is not None and _has_d(atoms[0]):  # folds per power cycle
        folds, gains = list(agg), list(agg.values())
    return Score(gi, float(np.sum(gains)), [float(g) for g in gains], folds, ATOMS[full].shape, full, agg,
                 absent_folds=absent)


def _has_d(atom: int) -> bool:
    from assets_lib.simreal import effects as fx

    return fx.has_block(ATOMS[atom].family, "D")


def _separable(best: Score, other: Score) -> bool:
    """simreal.md sec. 4.2 step 4: the best candidate is separable from another only if it is ahead in at least
    K - 1 of the K folds both are scored on (with fewer than two common folds: by the overall margin alone)."""
    gb = dict(zip(best.folds, best.fold_gains))
    go = dict(zip(other.folds, other.fold_gains))
    if (_has_d(best.atom) != _has_d(other.atom)) and best.cycle_gains and other.cycle_gains:
        gb, go = best.cycle_gains, other.cycle_gains  # one on power-cycle folds: compare both per power cycle
    common = [k for k in gb if k in go]
    if len(common) < 2:
        return True
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
    cov: dict = field(default_factory=dict)  # atom -> whitened least-squares covariance of its coefficients


def first_step_scores(t: Totals) -> dict:
    out = {}
    for gi in range(len(GROUPS)):
        s = score_group(t, gi, [])
        if s is not None:
            out[gi] = s.delta_lpd
    return out


def step_gates(null_totals: list, base_atoms: list[int], null_sd: float) -> dict:
    """group -> sim-vs-sim gate of a selection step: the larger of 2 ln 1000 and mean + ``null_sd`` sd of the
    candidate's score *at this step* (the accepted ``base_atoms`` in the model, as on the real data) over the
    base-twin replicates (simreal.md sec. 5.2). At the first step (``base_atoms`` empty) this is the first-step
    calibration; a later step is calibrated the same way, conditional on what has been accepted."""
    return gates_from_null(step_null(null_totals, base_atoms), null_sd)


def gates_from_null(null: dict, null_sd: float) -> dict:
    """group -> max(2 ln 1000, mean + ``null_sd`` sd) from :func:`step_null`'s (mean, sd, n); 2 ln 1000 alone with
    fewer than three replicates."""
    return {gi: max(GATE, m + null_sd * sd) if n > 2 else GATE for gi, (m, sd, n) in null.items()}


def step_null(null_totals: list, base_atoms: list[int]) -> dict:
    """group -> (mean, sd, n) of the candidate's score at this step over the replicates (``step_gates``)."""
    vals: dict = {}
    for tr in null_totals:
        for gi in range(len(GROUPS)):
            s = score_group(tr, gi, base_atoms)
            if s is not None:
                vals.setdefault(gi, []).append(s.delta_lpd)
    return {gi: (float(np.mean(v)), float(np.std(v, ddof=1)) if len(v) > 1 else float("nan"), len(v))
            for gi, v in vals.items()}


def null_p_step(score: float, null: tuple, m: int) -> float | None:
    """Predictive p of ``score`` under the replicates' (mean, sd, n) of its candidate at this step (Student t with
    n - 1 dof, scale sd sqrt(1 + 1/n): the sd is itself estimated from n replicates), times the ``m`` candidates
    scored at the step (Bonferroni): how often the step's best null candidate would reach it. A candidate is
    accepted only when this is <= ``ALPHA_STEP`` as well as above the mean + 5 sd gate: with R = 5 replicates the
    sd is estimated with 4 dof and ~37 candidates are scored per step, so mean + 5 sd alone lets a candidate through
    about once in 8 steps (WH-012: accel_x temperature scale factor 14.3 against the replicates' -4.2 +- 3.1, gate
    13.8; p_step 0.095)."""
    from scipy.stats import t as student_t

    mean, sd, n = null
    if n < 3 or not np.isfinite(sd) or sd <= 0:
        return None
    z = (score - mean) / (sd * np.sqrt(1.0 + 1.0 / n))
    return float(min(1.0, m * student_t.sf(z, n - 1)))


def select(d: Design, thresholds: dict | None = None, null_designs: list | None = None,
           null_sd: float = 5.0) -> Selection:
    """Greedy forward selection (module docstring). ``thresholds``: group -> calibrated gate (>= GATE) of the first
    step. With ``null_designs`` (designs of base-twin replicates), every later step's gates are recalibrated on
    them conditional on the atoms accepted so far (:func:`step_gates`); without, ``thresholds`` serve every step.
    The gate each accepted score passed is kept in ``Score.gate``."""
    t = Totals.of(d)
    thr = thresholds or {}
    null_t = [Totals.of(nd) for nd in null_designs] if null_designs else []
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
        nul = step_null(null_t, base_atoms) if null_t else {}
        if null_t and (step > 0 or not thresholds):
            thr = gates_from_null(nul, null_sd)
        for s in scores:
            s.gate = max(GATE, thr.get(s.group, GATE))
            s.p_step = null_p_step(s.delta_lpd, nul[s.group], len(scores)) if s.group in nul else None
        ok = [s for s in scores if s.delta_lpd > s.gate and s.fold_ok()
              and (s.p_step is None or s.p_step <= ALPHA_STEP)]
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
    coef, jack, cov = {}, {}, {}
    if base_atoms:
        cols = cols_of(base_atoms)
        g = t.coef(cols)
        # whitened GLS covariance (X' C^-1 X)^-1 of the final model (pseudo-inverse: g^2 columns are only
        # identified up to a common part that the bias absorbs; magnitudes are identifiable contrasts)
        V = np.linalg.pinv(t.G.sum(0)[np.ix_(cols, cols)], rcond=1e-12)
        units = t.fold_units(base_atoms)  # runs, or power cycles for block-D families
        gj = [_solve((t.G.sum(0) - t.G[u].sum(0))[np.ix_(cols, cols)], (t.b.sum(0) - t.b[u].sum(0))[cols])
              for u in units] if len(units) >= 3 else []
        k = 0
        for a in base_atoms:
            n = len(ATOMS[a].cols)
            coef[a] = g[k:k + n]
            jack[a] = [x[k:k + n] for x in gj]
            cov[a] = V[k:k + n, k:k + n]
            k += n
    return Selection(accepted, amb, first, coef, jack, cov)


def magnitude_interval(mag_of, coef: np.ndarray, cov: np.ndarray | None, boots: np.ndarray, jack: np.ndarray,
                       level: float = 0.95) -> tuple[float, float, float]:
    """(estimate, lo, hi) of a magnitude ``mag_of(coef)`` from three uncertainty sources, combined in quadrature
    with a Welch-Satterthwaite t quantile [SATTERTHWAITE1946]:

    - the whitened least-squares standard error (delta method on ``cov``; infinite dof): the noise the twin's
      whitening implies, a floor for the parametric bootstrap when it has few replicates;
    - the parametric bootstrap over augmented-twin replicates (sd with R - 1 dof): the noise as the full chain
      (segmentation, fits, whitening misfit) propagates it; the larger of the two is used;
    - the run-blocked jackknife [KUNSCH1989] (K - 1 dof): between-run scatter from model-form and twin-parameter
      errors that a fixed twin does not carry. With K = 3 runs its 2 dof need t = 4.3, not 1.96.

    The bootstrap bias (mean of the refits minus the estimate) corrects the estimate only when it is significant
    (|bias| > 2 sd / sqrt(R)); its own standard error sd / sqrt(R) is then added to the variance.
    """
    from scipy.stats import t as student_t

    c = np.atleast_1d(np.asarray(coef, float))
    mag = float(mag_of(c))
    parts = []  # (variance, dof)
    if cov is not None and np.all(np.isfinite(cov)) and cov.size:
        grad = np.zeros(c.size)
        for i in range(c.size):
            h = 1e-6 * max(abs(c[i]), np.sqrt(max(cov[i, i], 0.0)), 1e-300)
            e = np.zeros(c.size)
            e[i] = h
            grad[i] = (mag_of(c + e) - mag_of(c - e)) / (2 * h)
        v_ls = float(grad @ cov @ grad)
    else:
        v_ls = 0.0
    shift = 0.0
    boots = np.asarray(boots, float)
    if boots.size >= 3:
        sd_b = float(np.std(boots, ddof=1))
        bias = float(np.mean(boots) - mag)
        se_bias = sd_b / np.sqrt(boots.size)
        if abs(bias) > 2 * se_bias:
            shift = -bias
            parts.append((se_bias**2, boots.size - 1))
        if sd_b**2 > v_ls:
            parts.append((sd_b**2, boots.size - 1))
        else:
            parts.append((v_ls, np.inf))
    elif v_ls > 0:
        parts.append((v_ls, np.inf))
    jack = np.asarray(jack, float)
    if jack.size >= 3:
        v_jk = (jack.size - 1) / jack.size * float(np.sum((jack - jack.mean()) ** 2))
        parts.append((v_jk, jack.size - 1))
    var = sum(v for v, _ in parts)
    if not parts or var <= 0:
        return mag, float("nan"), float("nan")
    den = sum(v**2 / d for v, d in parts if np.isfinite(d) and v > 0)
    dof = var**2 / den if den > 0 else np.inf
    q = float(student_t.ppf(0.5 + level / 2, dof)) if np.isfinite(dof) else 1.959964
    sd = float(np.sqrt(var))
    est = mag + shift
    return mag, est - q * sd, est + q * sd


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


@dataclass(frozen=True)
class LackOfFit:
    """Held-out gain of a per-step saturated model over the accepted model on an accepted effect's own rows."""

    delta_lpd: float
    fold_gains: tuple
    n_steps: int

    def significant(self, gate: float) -> bool:
        k = len(self.fold_gains)
        n_pos = sum(g > 0 for g in self.fold_gains)
        return self.delta_lpd > max(GATE, gate) and k >= 2 and n_pos >= k - 1


def _pinv_solve(G: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.linalg.pinv(G, rcond=1e-10, hermitian=True) @ b


def lack_of_fit(d: Design, atoms: list[int], atom: int) -> LackOfFit | None:
    """Does the accepted model explain the repeatable gap on the rows ``atom`` acts on? (issue 12: what the
    library cannot explain is reported, never forced onto the nearest candidate.)

    Classical lack-of-fit test against pure replication [DRAPER1998, sec. 2.1], in the held-out form of the
    selection: the plans repeat in every power cycle, so a plateau's (plan, step) fixes its inputs (rate,
    orientation, time since power-on). On block A rows of the atom's channel(s) in the runs that carry it, the
    alternative adds one free level per (channel, plan, step), whitened and nuisance-projected like every
    signature (``Design.a_rows``: M @ indicator), to the accepted atoms ``atoms``. Gain = leave-one-run-out
    held-out whitened SSE of the accepted model minus that of the saturated one, summed over the runs: it is
    large when a repeatable residual remains that the accepted family's form does not follow (an omega abs(omega)
    fitted by omega^2 + omega^3 leaves such a residual at every rate), and negative under a correct form (the
    free levels cost variance). Families outside block A (table-angle, clock drift) are not tested (None).
    """
    at_ = ATOMS[atom]
    from assets_lib.simreal import effects as fx

    if not fx.has_block(at_.family, "A") or not d.a_rows:
        return None
    chans = [at_.channel] if at_.channel is not None else \
        [j for j in range(6) if any(k[1] == j for k in d.a_rows)
         and fx.columns(at_.family, "A", {"n": 1, "omega": np.zeros((1, 3)), "omega_motion": np.zeros((1, 3)),
                                         "force": np.zeros((1, 3)), "temp": np.zeros(1), "t_on": np.zeros(1),
                                         "is_rate": np.zeros(1, bool), "wobble": np.zeros((1, 2, 3))}, j) is not None]
    runs = np.flatnonzero(d.carries[:, atom])
    cols = cols_of(atoms)
    keys = sorted({(j, k) for (ri, j), r in d.a_rows.items() if j in chans and ri in runs for k in r["keys"]})
    if not keys or runs.size < 2:
        return None
    kix = {k: i for i, k in enumerate(keys)}
    p0, ns = len(cols), len(keys)
    G = np.zeros((runs.size, p0 + ns, p0 + ns))
    b = np.zeros((runs.size, p0 + ns))
    s = np.zeros(runs.size)
    for n, ri in enumerate(runs):
        for j in chans:
            r = d.a_rows.get((int(ri), j))
            if r is None:
                continue
            S = np.zeros((len(r["keys"]), ns))
            S[np.arange(len(r["keys"])), [kix[(j, k)] for k in r["keys"]]] = 1.0
            Z = np.hstack([r["X"][:, cols], r["M"] @ S])
            G[n] += Z.T @ Z
            b[n] += Z.T @ r["y"]
            s[n] += float(r["y"] @ r["y"])
    gains = []
    for n in range(runs.size):
        Gt, bt = G.sum(0) - G[n], b.sum(0) - b[n]
        sse = []
        for sub in (list(range(p0)), list(range(p0 + ns))):
            g = _pinv_solve(Gt[np.ix_(sub, sub)], bt[sub]) if sub else np.zeros(0)
            Gk = G[n][np.ix_(sub, sub)]
            sse.append(float(s[n] - 2 * g @ b[n][sub] + g @ Gk @ g))
        gains.append(sse[0] - sse[1])
    return LackOfFit(float(np.sum(gains)), tuple(float(g) for g in gains), ns)


def lack_of_fit_report(real: Design, null_designs: list, atoms: list[int], null_sd: float) -> dict:
    """atom -> {"delta_lpd", "gate", "folds_positive", "folds", "significant"} of :func:`lack_of_fit`, the gate
    calibrated like the selection's: the larger of 2 ln 1000 and mean + ``null_sd`` sd of the same statistic on
    base-twin replicates (the accepted atoms refitted there), simreal.md sec. 5.2."""
    out = {}
    for a in atoms:
        lf = lack_of_fit(real, atoms, a)
        if lf is None:
            continue
        null = [x.delta_lpd for x in (lack_of_fit(dd, atoms, a) for dd in null_designs) if x is not None]
        gate = max(GATE, float(np.mean(null) + null_sd * np.std(null, ddof=1))) if len(null) > 2 else GATE
        out[a] = {"delta_lpd": lf.delta_lpd, "gate": gate, "folds_positive": int(sum(g > 0 for g in lf.fold_gains)),
                  "folds": len(lf.fold_gains), "significant": bool(lf.significant(gate))}
    return out
