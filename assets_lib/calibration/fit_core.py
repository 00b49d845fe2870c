"""Weighted least squares with identifiability analysis, automatic exclusions and honest covariance.

The engine behind every calibration fit (gyro rate fit, accelerometer multi-position fit, the [SEED001]
plateau-mean fits). Pure numpy/scipy.

Identifiability (which coefficients a schedule observes)
    Each design column is divided by a physical full-scale (max |input| over the design for rate columns,
    g for specific-force columns, g^2 for second-order columns, 1 for the bias column), so a fully excited
    column has entries of order one. Columns are then orthogonalised one by one in a fixed physical
    priority order (bias, scale factor, misalignment, then the optional second-order / g-sensitivity terms;
    a column-pivoted QR whose pivot order is prescribed). A column whose RMS excitation orthogonal to the
    columns accepted before it is below ``rel_tol`` (default 1e-3 of full scale) is *not observable*: its
    value is reported as NaN with ``observable=False`` and the reason (not excited, or only a combination
    with named columns is observable) instead of a noise-dominated number. The default 1e-3 is set by the
    reference inputs: table-axis alignment (~20 arcsec = 1e-4), rate accuracy and the modelled earth-rate
    projection are good to ~1e-4 of full scale, so an excitation below 1e-3 of full scale would let those
    modelling errors bias the coefficient by >10 %.
    If a rejected column lies in the span of accepted *optional* columns, those optional columns are rejected
    too: their estimates would silently absorb the unobservable term (e.g. g-sensitivity on three mutually
    exclusive orientations plus a bias column). Absorption into core columns (e.g. K2 into the bias when no
    position has the sensing axis horizontal) is the textbook behaviour and is stated in the reason.

Exclusions
    Rows may be pre-excluded (segmentation flags, saturation). Then, iteratively, the externally studentized
    residual (leave-one-out, [BELSLEY1980]) of every testable row is compared with the Bonferroni
    critical value t_{1 - alpha / (2 n)}(dof - 1), alpha = 0.01 family-wise; the worst row beyond it is excluded and the fit repeated,
    at most ``max_exclusion_fraction`` of the rows ([COOK1982], sec. 2.2.1: Bonferroni outlier test).
    The scale of the test is the residual scatter, not the plateau standard errors, so a genuine smooth
    nonlinearity (systematic residuals everywhere) does not turn the end plateaus into "outliers".

Correlated noise between plateaus (``times``)
    When the plateau times are known, the final fit is a GLS with Sigma = diag(sem^2 - 2 ln2 tau_s^2) + tau^2 G
    (tau_s^2 the 1/f level the sems contain, :func:`white_variance`),
    G the covariance shape of window means of 1/f (bias-instability) noise relative to the run mean plus the
    Allan floor at the run length, and tau^2 = B^2 / pi estimated by REML (:func:`flicker_gls`). Bias
    instability makes low-frequency contrasts (positions minutes apart) noisier than independent sems promise
    while the plateau-to-plateau scatter does not show it. A tau^2 from the run's Allan analysis is used when
    given and non-zero (:func:`flicker_prior_tau2`); an undetected B falls back to REML. The run mean's own
    wander is invisible in the run's data, so the biases' uncertainty rests on this tau^2.

Covariance (``cov_policy``)
    With plateau standard errors sigma (``*_sem``) the fit is weighted (W = 1/sigma^2): the sems set the
    *relative* weights. The overall variance factor phi of C = phi (A^T W A)^-1 is then estimated by pooling
    the two sources of information about it ("pooled"): the sems' own absolute level, treated as a prior
    estimate phi = 1 worth nu_0 = 4 degrees of freedom, and the residual chi-square with nu = n - p:
    phi = (nu_0 + chi^2) / (nu_0 + nu), intervals Student-t with nu_0 + nu dof (the conjugate scaled-inverse-
    chi^2 update; [GUM] 4.2 / G.4 Type A with effective degrees of freedom). Why not the sems alone: they describe
    the noise *within* a plateau (segmentation's Allan-based sem), not what varies *between* plateaus over a
    run (bias instability and rate random walk across minutes, table and fixture errors, temperature), and an
    underestimate of 15-30 % costs 2-3 points of coverage. Why not the scatter alone: with few dof (a 6-position
    plan has one) it is too noisy, and nu_0 = 4 (~ +/-35 % on sigma) keeps it in check. Why not "the larger of
    the two": it over-covers (~96.5 % at nu = 17) when the sems are right. A chi-square consistency test
    (p < 0.001) adds a warning naming the likely causes ([COX2002]). Without sems, ordinary
    least squares with phi = RSS/nu and Student-t(nu) intervals ("residual").

    "marginal": when the run's 1/f level is integrated out (``flicker_tau2`` with ``flicker_tau2_dof``,
    :func:`flicker_gls`), the GLS covariance is already the posterior covariance over the uncertain noise level:
    the law of total variance carries tau^2's spread, and the plateau residuals entered that posterior through the
    REML likelihood. Scaling it again by phi and widening by Student-t(nu_0 + nu) counts the same uncertainty twice
    (the t is the marginal of a normal over an unknown variance, [GELMAN2013] sec. 3.2; here the variance was
    already marginalised) and uses the residuals twice. So phi = 1 and the normal factor 1.96; the sems' white level
    comes from thousands of samples per plateau (segmentation's Allan fit) and is not the uncertain part. With
    both, the few-dof fits over-covered with z sd ~1 (coverage benchmark, position runs of 556 trials, seed 8821:
    6-position accelerometer k2 0.991 -> 0.976, scale factor 0.985 -> 0.964, misalignment 0.983 -> 0.967; 12-position
    accelerometer bias 0.988 -> 0.964; tumble K0 0.967 -> 0.952, K3 0.975 -> 0.957 over 458 tumble runs). The
    chi-square test still guards the model: at p < 0.001 (scatter the noise model cannot explain) the fit falls back
    to "pooled" (Birge-inflated, Student-t) and warns. Still wide on the 6-position plan (k2 0.976, z sd 0.89;
    gyro g-sensitivity 0.975): there the covariance itself, not the factor, is too wide (z sd 0.76-0.83 for the
    tactical grade's integrated fits).

Undetected 1/f level (B = 0) on a schedule with < 3 residual dof (the 6-position plan)
    tau^2 was taken at its sem bound (F = 2 ln2 tau^2 = median sem^2), which is 30-300x the truth for gyros whose
    floor lies far below their white noise. The caller now passes the sampling law of the Allan estimate
    (:class:`FlickerLaw`, :func:`flicker_law`): B = 0 is the event "F_hat <= 0" of a shifted chi-square
    (F_hat + W ~ (F + W) chi^2_nu / nu, the white octaves' scatter as the offset W, [SATTERTHWAITE1946]), a censored
    observation ([TOBIN1958]); tau^2 is integrated out with that likelihood times the plateaus' REML likelihood, prior
    flat in tau (not in ln tau^2: with a likelihood flat near zero a log-uniform prior leaves the posterior set by the
    grid's lower end, [GELMAN2006] sec. 4), policy 'marginal'. Measured on the 6-position runs of the cached position
    trials of seed 8821 (37 trials, 111 axis fits per grade, :mod:`multiposition` fits, before -> after, coverage /
    z sd; trial-clustered SEs 0.01-0.02 on coverage): gyro bias
    navigation 1.000 / 0.42 -> 1.000 / 0.53, tactical 1.000 / 0.45 -> 1.000 / 0.56, consumer 0.982 / 0.90 -> 0.964 /
    0.96; gyro g-sensitivity 0.988 / 0.985 / 0.952 -> 0.976 / 0.979 / 0.946 (navigation / tactical / consumer);
    accelerometer k2 tactical 1.000 / 0.81 -> 0.982 / 0.84, consumer 0.973 -> 0.964, scale factor tactical 0.973 ->
    0.964, bias tactical 0.982 / 0.86 -> 0.955 / 0.92, consumer 0.928 -> 0.928. Fits with B detected or >= 3 residual
    dof are unchanged (REML for an undetected B, as before).

    What is still wide and why (measured, not fixed): the 6-position gyro bias with B *detected* at navigation and
    tactical grade (z sd 0.43 and 0.42; all plans: navigation 1.000 / 0.48, tactical 0.997 / 0.60 over 230 and 294
    axis fits). The true floor lies at 0.003 (navigation) and 0.04 (tactical) of a plateau's sem^2, far below what
    one run's plateaus resolve; a "detected" B is the positive tail of the non-negative Allan fit, 10x (median of
    tau^2 ratio: navigation 106, tactical 9) the truth. The same censored law for detected B (a normal or shifted
    chi-square density) lowered it only to 1.000 / 0.65 and 0.980 / 0.79 and broke the consumer grade (0.892, z sd
    1.23 where B is well resolved), and REML alone for undetected B with many dof gives navigation 0.968 / 0.84 but
    consumer 0.864 / 1.88. The run's own data cannot tell a floor at 0.003 sem^2 from one at 0.3 sem^2; an interval
    right at every grade needs information from outside the run (the device's long static Allan record as a prior
    on B), which the calibration fits do not receive today.

Device noise prior (:mod:`assets_lib.calibration.noise_prior`)
    The fits can take B from the device's static records instead of the run's plateaus: a two-sided estimate as
    ``flicker_tau2`` with the dof of its interval (:func:`flicker_dof_from_interval`), integrated as above; an upper
    bound as :class:`FlickerBoundLaw` (tau^2 <= bound^2 / pi: the run's own Allan law and the plateaus' REML, flat
    in tau, truncated there), never as B. The stages pass both; measured on the dev cache (benchmarks/README.md,
    "Device noise prior" and "Session 10").
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property

import numpy as np
from scipy import stats

DEFAULT_REL_TOL = 1e-3
#: acceptable reduced chi-square of a fit's standardized residuals (noise model consistency): one band for the
#: calibration stage's gate and check and for a record's status (assets_lib.records.validity)
CHI2_BAND = (0.2, 5.0)
DEFAULT_ALPHA = 0.01  # family-wise level of the Bonferroni outlier test (false exclusion in ~1 % of fits)
DEFAULT_SEM_PRIOR_DOF = 4.0  # degrees of freedom given to the plateau sems' absolute level (~ +/-35 % on sigma)


@dataclass(frozen=True, eq=False)
class Identifiability:
    """[SEED003] eq. 3 pre-check: which columns of x = (A^T A)^-1 A^T b the schedule determines."""

    observable: np.ndarray  # (p,) bool
    excitation: np.ndarray  # (p,) RMS orthogonal excitation in full-scale units
    reason: tuple[str, ...]  # '' when observable
    condition_number: float  # of the scaled design restricted to the observable columns


@dataclass(frozen=True, eq=False)
class LinearFit:
    """Result of :func:`fit_linear`: parameters in the units of the unscaled design."""

    names: tuple[str, ...]
    value: np.ndarray  # (p,), NaN where not observable
    cov: np.ndarray  # (p, p), NaN rows/cols where not observable
    observable: np.ndarray
    unobservable_reason: tuple[str, ...]
    excitation: np.ndarray
    condition_number: float
    used: np.ndarray  # (n,) bool
    exclusion_reason: tuple[str, ...]  # per row, '' when used
    exclusion_kind: tuple[str, ...]  # per row: '', 'pre', 'outlier', 'invalid'
    fitted: np.ndarray  # (n,) model prediction for every row (used or not)
    residual: np.ndarray  # (n,) y - fitted
    sigma: np.ndarray | None  # (n,) plateau standard errors given
    std_residual: np.ndarray  # (n,) externally studentized (used rows) / prediction-standardized (excluded)
    leverage: np.ndarray  # (n,) hat diagonal (NaN for excluded rows)
    n_used: int
    dof: int
    chi2: float  # weighted residual sum of squares (RSS when unweighted)
    chi2_pvalue: float
    scale: float  # variance factor applied to (A^T W A)^-1
    cov_policy: str  # 'pooled' (sems + scatter) | 'marginal' (1/f level integrated) | 'residual' (no sems) | 'none'
    outlier_critical: float  # last Bonferroni critical value used (NaN if no test)
    warnings: tuple[str, ...] = field(default=())
    sem_prior_dof: float = 0.0
    flicker_tau2: float = 0.0  # REML variance of the 1/f (bias instability) component between plateaus
    sem_flicker_tau2: float | None = None  # the 1/f level the sems already contain (fit_linear's argument)

    @property
    def stderr(self) -> np.ndarray:
        return np.sqrt(np.diag(self.cov))

    @property
    def k95(self) -> float:
        """Coverage factor of a 95 % interval: Student-t with the variance factor's degrees of freedom."""
        if self.cov_policy == "pooled":
            return float(stats.t.ppf(0.975, self.dof + self.sem_prior_dof))
        if self.cov_policy == "marginal":
            return float(stats.norm.ppf(0.975))
        if self.cov_policy == "residual" and self.dof > 0:
            return float(stats.t.ppf(0.975, self.dof))
        return float(stats.norm.ppf(0.975))

    def index(self, name: str) -> int:
        return self.names.index(name)

    def get(self, name: str) -> tuple[float, float]:
        i = self.names.index(name)
        return float(self.value[i]), float(np.sqrt(self.cov[i, i]))

    def predict_variance(self, A: np.ndarray) -> np.ndarray:
        """Variance of the fitted mean at design rows ``A`` (observable columns only)."""
        obs = self.observable
        Ao = np.asarray(A, float)[:, obs]
        C = self.cov[np.ix_(obs, obs)]
        return np.einsum("ij,jk,ik->i", Ao, C, Ao)


def identifiability(
    A_scaled: np.ndarray,
    names: tuple[str, ...] | list[str],
    optional: np.ndarray | None = None,
    rel_tol: float = DEFAULT_REL_TOL,
    forced_out: set[int] | None = None,
    nuisance: np.ndarray | None = None,
) -> Identifiability:
    """Priority-ordered Gram-Schmidt (prescribed-pivot QR) of the scaled design; see the module docstring.

    Columns are taken in the given order (the priority order). ``optional`` marks columns that are dropped
    when a rejected column would be absorbed into them.
    """
    A = np.asarray(A_scaled, float)
    n, p = A.shape
    optional = np.zeros(p, bool) if optional is None else np.asarray(optional, bool)
    nuisance = np.zeros(p, bool) if nuisance is None else np.asarray(nuisance, bool)
    names = tuple(names)
    forced_reason: dict[int, str] = {j: "not estimated" for j in (forced_out or ())}
    root_n = np.sqrt(max(n, 1))
    for _ in range(p + 1):
        accepted: list[int] = []
        Q = np.zeros((n, 0))
        exc = np.zeros(p)
        reason = [""] * p
        for j in range(p):
            a = A[:, j]
            r = a - Q @ (Q.T @ a)
            r = r - Q @ (Q.T @ r)
            exc[j] = np.linalg.norm(r) / root_n
            if j in forced_reason or exc[j] < rel_tol or n == 0:
                continue
            accepted.append(j)
            Q = np.column_stack([Q, r / np.linalg.norm(r)])
        new_forced = False
        for j in (j for j in range(p) if j not in accepted):
            if j in forced_reason:
                reason[j] = forced_reason[j]
                continue
            a = A[:, j]
            size = np.linalg.norm(a) / root_n
            if size < rel_tol or not accepted:
                reason[j] = (
                    f"not excited by this schedule (RMS excitation {size:.1e} of full scale < {rel_tol:.0e}); "
                    "not estimated"
                )
                continue
            Aa = A[:, accepted]
            c = np.linalg.lstsq(Aa, a, rcond=None)[0]
            contrib = np.abs(c) * np.linalg.norm(Aa, axis=0) / root_n
            partners = [accepted[k] for k in np.flatnonzero(contrib > rel_tol)]
            pn = ", ".join(names[k] for k in partners) or "none"
            reason[j] = (
                f"not separable from [{pn}] with this schedule (orthogonal excitation {exc[j]:.1e} < {rel_tol:.0e}); "
                f"not estimated, its effect is absorbed into [{pn}]"
            )
            if nuisance[j]:
                continue  # a nuisance column only absorbs what it can; it never forces others out
            if any(optional[k] and not nuisance[k] for k in partners) and j not in forced_reason:
                forced_reason[j] = reason[j]
                new_forced = True
            for k in partners:
                if optional[k] and not nuisance[k] and k not in forced_reason:
                    forced_reason[k] = (
                        f"not estimated: confounded with the unobservable {names[j]} in this schedule "
                        f"(its estimate would absorb {names[j]})"
                    )
                    new_forced = True
        if not new_forced:
            break
    obs = np.zeros(p, bool)
    obs[accepted] = True
    if accepted:
        sv = np.linalg.svd(A[:, accepted], compute_uv=False)
        cond = float(sv[0] / sv[-1]) if sv[-1] > 0 else float("inf")
    else:
        cond = float("nan")
    return Identifiability(observable=obs, excitation=exc, reason=tuple(reason), condition_number=cond)


@dataclass(frozen=True, eq=False)
class WeightedSolution:
    """One weighted least-squares solve over the rows in use (the inner step of :func:`fit_linear`)."""

    ident: Identifiability
    observable: np.ndarray  # (p,) bool, columns solved for
    rows: np.ndarray  # indices of the rows used
    weights: np.ndarray  # 1/sigma of those rows (ones without sems)
    x: np.ndarray  # (k,) solution on the observable columns
    cov_unscaled: np.ndarray  # (k, k) (A^T W A)^-1
    leverage: np.ndarray  # hat diagonal of the used rows
    weighted_residual: np.ndarray  # (y - A x) / sigma on the used rows
    chi2: float  # weighted residual sum of squares
    n_observable: int
    dof: int


def _solve(Aw: np.ndarray, yw: np.ndarray):
    """Least squares via thin QR on column-equilibrated weighted design; returns x, (Aw^T Aw)^-1, hat diag."""
    norms = np.linalg.norm(Aw, axis=0)
    norms[norms == 0] = 1.0
    B = Aw / norms
    Q, R = np.linalg.qr(B, mode="reduced")
    x = np.linalg.solve(R, Q.T @ yw) / norms
    Rinv = np.linalg.solve(R, np.eye(R.shape[0]))
    C = (Rinv @ Rinv.T) / np.outer(norms, norms)
    h = np.sum(Q**2, axis=1)
    return x, C, h


def fit_linear(
    A: np.ndarray,
    y: np.ndarray,
    names: tuple[str, ...] | list[str],
    *,
    sigma: np.ndarray | None = None,
    scales: np.ndarray | None = None,
    optional: np.ndarray | None = None,
    rel_tol: float = DEFAULT_REL_TOL,
    pre_excluded: dict[int, str] | None = None,
    outlier_test: bool = True,
    alpha: float = DEFAULT_ALPHA,
    sem_prior_dof: float = DEFAULT_SEM_PRIOR_DOF,
    max_exclusion_fraction: float = 0.25,
    outlier_note=None,
    screen_columns: np.ndarray | None = None,
    nuisance: np.ndarray | None = None,
    times: tuple[np.ndarray, np.ndarray] | None = None,
    flicker_tau2: float | None = None,
    flicker_tau2_dof: float | FlickerLaw | FlickerBoundLaw | None = None,
    sem_flicker_tau2: float | None = None,
) -> LinearFit:
    """[SEED003] eq. 3, x = (A^T W A)^-1 A^T W b, with identifiability, Bonferroni outlier test and chi^2 check.

    ``A`` (n, p) design in physical units, columns in priority order; ``y`` (n,) observations; ``sigma`` (n,)
    standard errors of the observations (plateau sems) or None; ``scales`` (p,) physical full-scale of each
    column (defaults to the column max-abs); ``pre_excluded`` {row: reason} rows not to use;
    ``outlier_note(row, residual, used_mask) -> str`` may add context to an outlier's reason.
    ``times`` (t_mid_s, t_len_s) of every row: enables the correlated-noise (1/f) GLS of :func:`flicker_gls` for
    the final fit (needs sems and a constant column). ``flicker_tau2`` the run's 1/f level (:func:`flicker_prior_tau2`)
    and ``flicker_tau2_dof`` its degrees of freedom (:func:`flicker_b_dof`): with both, the fit marginalises over
    tau^2 (see :func:`flicker_gls`) instead of taking the estimate as exact; a :class:`FlickerLaw` instead of the
    dof: the Allan estimate's full sampling law (used when B was not detected, module docstring); a
    :class:`FlickerBoundLaw` with ``flicker_tau2`` its ``tau2_max``: only an upper bound on B is known (the device's
    static record, :mod:`assets_lib.calibration.noise_prior`), tau^2 integrated over [0, tau2_max].
    ``sem_flicker_tau2``: the 1/f level tau^2 whose Allan floor 2 ln2 tau^2 the ``sigma`` already contain
    (segmentation's SEM model, :func:`sem_flicker_tau2`; 0 when that model left the floor out): the plateaus'
    white part is then sigma^2 - 2 ln2 sem_flicker_tau2 whatever tau^2 the GLS weighs (:func:`flicker_covariance`);
    None: the sems are taken to contain the floor of the tau^2 weighed.
    ``nuisance`` (p,) bool: columns that absorb what they can (kept while linearly independent, never forcing
    other columns out); a caller reports them only when the whole nuisance group is observable.
    ``screen_columns`` (n, m): extra smooth nuisance regressors used only by the outlier test (e.g. |w|, w^2,
    w^3 on a rate sweep), so that a genuine systematic signature (nonlinearity, asymmetry) is not mistaken for
    isolated outliers; the reported fit uses the base model and its chi-square check / Birge inflation then
    carries the systematic misfit into the uncertainties.
    """
    A = np.asarray(A, float)
    y = np.asarray(y, float)
    n, p = A.shape
    names = tuple(names)
    if scales is None:
        scales = np.max(np.abs(A), axis=0) if n else np.ones(p)
        scales = np.where(scales > 0, scales, 1.0)
    scales = np.asarray(scales, float)
    sig = None if sigma is None else np.asarray(sigma, float)
    reason = [""] * n
    kind = [""] * n
    used = np.ones(n, bool)
    bad = ~np.isfinite(y) | ~np.all(np.isfinite(A), axis=1)
    if sig is not None:
        bad |= ~np.isfinite(sig) | (sig <= 0)
    for i in np.flatnonzero(bad):
        used[i] = False
        reason[i] = "invalid: non-finite mean, reference or standard error"
        kind[i] = "invalid"
    for i, r in (pre_excluded or {}).items():
        if used[i]:
            used[i] = False
            reason[i] = r
            kind[i] = "pre"
    warnings: list[str] = []
    n_out_max = int(np.floor(max_exclusion_fraction * used.sum()))
    n_out = 0
    crit = float("nan")
    As = A / scales
    nuis_base = np.zeros(p, bool) if nuisance is None else np.asarray(nuisance, bool)

    def wfit(Am, Ams, nm, opt):
        nu = np.r_[nuis_base, np.ones(Am.shape[1] - p, bool)]
        ident = identifiability(Ams[used], nm, opt, rel_tol, nuisance=nu)
        obs = ident.observable
        idx = np.flatnonzero(used)
        w = np.ones(len(idx)) if sig is None else 1.0 / sig[idx]
        Aw = Am[np.ix_(idx, np.flatnonzero(obs))] * w[:, None]
        yw = y[idx] * w
        k = int(obs.sum())
        if k == 0:
            x, C0, h = np.zeros(0), np.zeros((0, 0)), np.zeros(len(idx))
        else:
            x, C0, h = _solve(Aw, yw)
        rw = yw - Aw @ x if k else yw.copy()
        return WeightedSolution(ident, obs, idx, w, x, C0, h, rw, float(rw @ rw), k, len(idx) - k)

    opt_base = np.zeros(p, bool) if optional is None else np.asarray(optional, bool)
    if screen_columns is not None and np.asarray(screen_columns).size:
        S = np.asarray(screen_columns, float).reshape(n, -1)
        s_sc = np.max(np.abs(S), axis=0)
        s_sc = np.where(s_sc > 0, s_sc, 1.0)
        A_scr = np.column_stack([A, S])
        As_scr = np.column_stack([As, S / s_sc])
        n_scr = names + tuple(f"screen_{m}" for m in range(S.shape[1]))
        o_scr = np.r_[opt_base, np.ones(S.shape[1], bool)]
    else:
        A_scr, As_scr, n_scr, o_scr = A, As, names, opt_base
    def studentized(sol: WeightedSolution):
        idx, h, rw, chi2, dof = sol.rows, sol.leverage, sol.weighted_residual, sol.chi2, sol.dof
        if dof < 3 or chi2 <= 0:
            return None
        testable = h < 1.0 - 1e-9
        s2_del = (chi2 - rw**2 / np.where(testable, 1 - h, 1.0)) / (dof - 1)
        with np.errstate(divide="ignore", invalid="ignore"):
            t_ext = rw / np.sqrt(np.maximum(s2_del, 1e-300) * (1 - h))
        t_ext[~testable] = 0.0
        crit = float(stats.t.ppf(1 - alpha / (2 * len(idx)), dof - 1))
        return t_ext, crit, dof

    screened = A_scr is not A
    while outlier_test and n_out < n_out_max:
        base = wfit(A, As, names, opt_base)
        tb = studentized(base)
        if tb is None:
            break
        t_ext, crit, dof_t = tb
        score = np.abs(t_ext) / crit
        if screened:
            # an outlier must stand out both from the straight model and from the smooth-systematic screen model
            ts = studentized(wfit(A_scr, As_scr, n_scr, o_scr))
            if ts is not None:
                score = np.minimum(score, np.abs(ts[0]) / ts[1])
        j = int(np.argmax(score))
        if score[j] <= 1.0:
            break
        idx, w, rw = base.rows, base.weights, base.weighted_residual
        row = int(idx[j])
        used[row] = False
        kind[row] = "outlier"
        note = outlier_note(row, float(rw[j] / w[j]), used.copy()) if outlier_note else ""
        reason[row] = (
            f"outlier: externally studentized residual {t_ext[j]:+.1f} beyond the Bonferroni critical value "
            f"{crit:.2f} (alpha {alpha:g}, n {len(idx)}, dof {dof_t - 1})"
            + (" and also beyond it against smooth nonlinearity/asymmetry terms" if screened else "")
            + (f"; {note}" if note else "")
        )
        n_out += 1
    sol = wfit(A, As, names, opt_base)
    ident, obs, idx, w, x, C0, h = sol.ident, sol.observable, sol.rows, sol.weights, sol.x, sol.cov_unscaled, sol.leverage
    chi2, k, dof = sol.chi2, sol.n_observable, sol.dof
    tau2 = 0.0
    marginal = False  # the 1/f level integrated out (flicker_gls with prior_dof): the noise level's uncertainty is in C
    C_common = None  # the run mean's 1/f wander on the constant column (not scaled by the residual chi-square)
    # REML needs a few residual dof; a 1/f level given by the run's Allan analysis applies to any schedule
    # (a 6-position plan has 2 dof: without it the biases lost the 1/f wander, coverage 0.84, z sd 2.0)
    if flicker_tau2 is not None and flicker_tau2 == FLICKER_UNDETECTED:
        # the Allan fit within the plateaus saw no 1/f floor. With >= 3 residual dof the plateaus' contrasts
        # estimate it (REML). With fewer (a 6-position plan) nothing does, and it is not zero: it lies below the
        # plateau variance, sem^2 >= 2 ln2 tau^2 (the floor is part of a window mean's Allan variance), so tau^2
        # is taken at that bound (tactical accelerometer on the 6-position plan, B undetected in 21 % of runs:
        # bias z sd 2.0, coverage 0.79 with tau^2 = 0). The bound for every dof over-covered gyros whose 1/f
        # floor lies far below their white noise (navigation rate-fit bias z sd 0.37). Given the Allan estimate's
        # sampling law (a FlickerLaw as flicker_tau2_dof) the bound is replaced by integrating tau^2 out with the
        # censored likelihood of "not detected" (module docstring).
        if dof >= 3 or sig is None or not len(idx):
            flicker_tau2 = None
        elif isinstance(flicker_tau2_dof, FLICKER_LAWS):
            flicker_tau2 = flicker_tau2_dof.resolution_tau2  # grid anchor; the censored law weighs it
        else:
            flicker_tau2 = float(np.median(sig[idx] ** 2)) / FLICKER_WHITE
    prior = flicker_tau2 is not None and flicker_tau2 > 0
    if times is not None and sig is not None and k and (dof >= 3 or prior):
        t_mid, t_len = (np.asarray(v, float) for v in times)
        X = A[np.ix_(idx, np.flatnonzero(obs))]
        if np.all(np.isfinite(t_mid[idx])) and np.all(np.isfinite(t_len[idx])) and np.any(np.all(X == X[0], axis=0)):
            tau2, gx, gC, gchi2 = flicker_gls(X, y[idx], sig[idx], t_mid[idx], t_len[idx], tau2=flicker_tau2,
                                               prior_dof=flicker_tau2_dof, sem_tau2=sem_flicker_tau2)
            if tau2 > 0:
                x, C0, chi2 = gx, gC, gchi2
                marginal = _integrates_tau2(flicker_tau2, flicker_tau2_dof)
                # Sigma's constant part c 11^T (c = 2 ln2 tau^2, the run mean's wander) moves only the constant
                # column's estimate (1 lies in the design's column space: Rao's structure [RAO1967]), by exactly c; the
                # residuals, contrasts between plateaus, carry no information about it, so the scatter's Birge
                # scaling below applies to the rest only (scaling the whole covariance by chi2/dof < 1 shrank the
                # accelerometer bias intervals: z sd 1.18, coverage 0.92 in the full-chain Monte Carlo)
                c = int(np.flatnonzero(np.all(X == X[0], axis=0) & (X[0] != 0))[0])
                e = np.zeros(X.shape[1])
                e[c] = 1.0 / X[0, c]
                C_common = FLICKER_WHITE * tau2 * np.outer(e, e)
    if outlier_test and n_out >= n_out_max and n_out > 0:
        warnings.append(
            f"outlier exclusion stopped at the limit of {n_out_max} rows ({max_exclusion_fraction:.0%}); "
            "the model may be inadequate for these data"
        )
    # covariance policy (module docstring): sems pooled with the residual chi-square
    pval = float(stats.chi2.sf(chi2, dof)) if (k and dof > 0 and sig is not None) else float("nan")
    if k and sig is not None and marginal and not (np.isfinite(pval) and pval < 1e-3):
        scale, policy = 1.0, "marginal"  # no variance factor, no Student-t on top of the integrated level (docstring)
    elif k and sig is not None:
        scale, policy = (sem_prior_dof + chi2) / (sem_prior_dof + dof), "pooled"
        if np.isfinite(pval) and pval < 1e-3:
            warnings.append(
                f"residual scatter significantly exceeds the plateau standard errors (chi2 {chi2:.3g} for {dof} dof, "
                f"p = {pval:.1e}): unmodelled effects or underestimated sems; uncertainties scaled by the scatter"
            )
    elif k and dof > 0:
        scale, policy = chi2 / dof, "residual"
    elif k:
        scale, policy = float("nan"), "none"
        warnings.append("no degrees of freedom left and no standard errors given: uncertainties unknown")
    else:
        scale, policy = float("nan"), "none"
    value = np.full(p, np.nan)
    cov = np.full((p, p), np.nan)
    oi = np.flatnonzero(obs)
    if k:
        value[oi] = x
        cov[np.ix_(oi, oi)] = C0 * scale if C_common is None else (C0 - C_common) * scale + C_common
    fitted = A[:, oi] @ x if k else np.zeros(n)
    resid = y - fitted
    # standardized residuals
    std_res = np.full(n, np.nan)
    lev = np.full(n, np.nan)
    lev[idx] = h
    if k and dof > 1:
        rw_u = resid[idx] * w
        # leave-one-out variance in the weighting of rw_u and h (after a flicker GLS, chi2 is the whitened one)
        s2_del = (float(rw_u @ rw_u) - rw_u**2 / np.maximum(1 - h, 1e-12)) / (dof - 1)
        with np.errstate(divide="ignore", invalid="ignore"):
            t = rw_u / np.sqrt(np.maximum(s2_del, 1e-300) * np.maximum(1 - h, 1e-12))
        t[h >= 1 - 1e-9] = np.nan
        std_res[idx] = t
    ex = np.flatnonzero(~used & np.all(np.isfinite(A), axis=1) & np.isfinite(y))
    if k and len(ex):
        pv = np.einsum("ij,jk,ik->i", A[np.ix_(ex, oi)], cov[np.ix_(oi, oi)], A[np.ix_(ex, oi)])
        if sig is not None:
            noise = sig[ex] ** 2 * (scale if np.isfinite(scale) else 1.0)
        else:
            noise = np.full(len(ex), scale)
        with np.errstate(invalid="ignore"):
            std_res[ex] = resid[ex] / np.sqrt(pv + noise)
    return LinearFit(
        names=names,
        value=value,
        cov=cov,
        observable=obs,
        unobservable_reason=ident.reason,
        excitation=ident.excitation,
        condition_number=ident.condition_number,
        used=used,
        exclusion_reason=tuple(reason),
        exclusion_kind=tuple(kind),
        fitted=fitted,
        residual=resid,
        sigma=sig,
        std_residual=std_res,
        leverage=lev,
        n_used=int(used.sum()),
        dof=int(dof),
        chi2=chi2,
        chi2_pvalue=pval,
        scale=float(scale),
        cov_policy=policy,
        outlier_critical=crit,
        warnings=tuple(warnings),
        sem_prior_dof=float(sem_prior_dof if policy == "pooled" else 0.0),
        flicker_tau2=float(tau2),
        sem_flicker_tau2=sem_flicker_tau2,
    )


#: the run mean's 1/f wander in units of tau^2 = B^2 / pi: the Allan floor (2 ln2 / pi) B^2 ([IEEE952] C.3)
FLICKER_WHITE = 2.0 * np.log(2.0)
#: ``flicker_tau2`` value meaning "an Allan analysis looked for a 1/f level and did not see it" (see fit_linear)
FLICKER_UNDETECTED = -1.0


def log_kernel(t_mid: np.ndarray, t_len: np.ndarray) -> np.ndarray:
    """Covariance shape of window means of 1/f (flicker, bias-instability) noise, up to a constant.

    1/f noise has the generalized covariance -ln|u - v| (conditionally positive definite on contrasts; the
    constant is absorbed by the bias column). Between windows i != j the mean of -ln|u - v| over both windows is
    taken at the centres (-ln|t_i - t_j|, exact to O((T/dt)^2)); within a window of length T it is -ln T + 3/2.
    A constant ln(span) keeps the matrix positive for the numerical work.
    """
    t = np.asarray(t_mid, float)
    T = np.maximum(np.asarray(t_len, float), 1e-9)
    span = float(np.ptp(t) + T.max()) * np.e
    d = np.abs(t[:, None] - t[None, :])
    dmin = 0.5 * (T[:, None] + T[None, :])
    G = np.log(span / np.maximum(d, dmin))
    np.fill_diagonal(G, np.log(span / T) + 1.5)
    return G


def flicker_b(p, channel: str) -> float | None:
    """The run's pooled 1/f level B of a channel from segmentation (``<channel>_flicker_b``), or None."""
    c = f"{channel}_flicker_b"
    return float(p[c].iloc[0]) if c in p and len(p) else None


def sem_flicker_tau2(p, channel: str) -> float | None:
    """tau^2 = B_s^2 / pi of the 1/f level the plateau sems contain (``<channel>_sem_flicker_b``: segmentation's SEM
    model, 0 where its selection left the floor out; :func:`white_variance`), or None for a table without it."""
    c = f"{channel}_sem_flicker_b"
    if c not in p or not len(p):
        return None
    b = float(p[c].iloc[0])
    return b**2 / np.pi if np.isfinite(b) and b >= 0 else None


def flicker_prior_tau2(b: float | None) -> float | None:
    """tau^2 = B^2 / pi of the correlated-noise GLS from a 1/f level B found by an Allan analysis (segmentation's
    pooled fit of the run), or None (tau^2 by REML from the plateaus) when B is unknown or was not detected.

    An undetected 1/f level is not a zero one: fixing tau^2 = 0 when the Allan fit put B at zero dropped the
    bias-instability wander from the biases' uncertainty (tactical accelerometer bias coverage 0.68, z sd 2.2 in
    the full-chain Monte Carlo; 0.93 with this rule). B = 0 (looked for, not seen within the plateaus) returns
    :data:`FLICKER_UNDETECTED`: :func:`fit_linear` then estimates tau^2 by REML, or with too few residual
    dof for that bounds it by the plateau sems (see there).
    """
    if b is None or not np.isfinite(b) or b < 0:
        return None
    if b == 0:
        return FLICKER_UNDETECTED
    return float(b) ** 2 / np.pi


def white_variance(sig: np.ndarray, tau2: float, sem_tau2: float | None = None) -> np.ndarray:
    """The plateaus' variance without their 1/f part: sem^2 - 2 ln2 tau_s^2 ([IEEE952] C.3 floor; not below
    0.1 sem^2), tau_s^2 = ``sem_tau2``, the 1/f level the sems contain (segmentation's SEM model,
    :func:`sem_flicker_tau2`), or the weighed ``tau2`` when that is not known.

    Why the sems' own level: a plateau's sem is sigma_A(T) of the run's SEM model, whose 1/f term enters only when the
    model selection admits it. Where it left it out (tactical accelerometer: floor ~ white at T = 15 s) the sems are
    white only, and subtracting the device record's floor took most of the white noise away (0.1 sem^2 kept).
    """
    D0 = np.asarray(sig, float) ** 2
    floor = FLICKER_WHITE * (tau2 if sem_tau2 is None else max(float(sem_tau2), 0.0))
    return np.maximum(D0 - floor, 0.1 * D0)


def flicker_covariance(sig: np.ndarray, t_mid: np.ndarray, t_len: np.ndarray, tau2: float,
                       sem_tau2: float | None = None) -> np.ndarray:
    """Sigma = diag(:func:`white_variance`) + tau^2 G of :func:`flicker_gls` (G double-centred plus the Allan floor)."""
    D0 = np.asarray(sig, float) ** 2
    if not tau2 > 0:
        return np.diag(D0)
    G = log_kernel(t_mid, t_len)
    G = G - G.mean(axis=0, keepdims=True) - G.mean(axis=1, keepdims=True) + G.mean() + FLICKER_WHITE
    return np.diag(white_variance(sig, tau2, sem_tau2)) + tau2 * G


def flicker_gls(X: np.ndarray, y: np.ndarray, sig: np.ndarray, t_mid: np.ndarray, t_len: np.ndarray,
                tau2: float | None = None, prior_dof: float | None = None, sem_tau2: float | None = None):
    """GLS with Sigma = diag(sem^2) + tau^2 G (G = :func:`log_kernel`), tau^2 >= 0 by REML ([PATTERSON1971]).

    Bias instability (flicker) makes plateau errors correlated over the run: low-frequency contrasts (up vs down
    positions several minutes apart) do not average down as independent sems promise, and the residual scatter,
    dominated by plateau-to-plateau differences, does not show it. The REML amplitude of the 1/f component
    restores the right variance for such contrasts. Returns (tau2, x, (X^T S^-1 X)^-1, r^T S^-1 r); tau2 = 0
    means plain WLS.

    A given ``tau2`` is an estimate (the run's Allan analysis). With ``prior_dof`` nu, its degrees of freedom
    (tau2_hat ~ tau2 chi^2_nu / nu, :func:`flicker_b_dof`), tau^2 is not taken as exact but integrated out
    ([GELMAN2013] sec. 3.2, the scaled-inverse-chi^2 posterior of a variance): on a log grid the posterior
    combines that chi-square likelihood with the plateaus' own REML likelihood (their contrasts), prior flat in
    ln tau^2; the estimate is the posterior mean of the GLS solutions and its covariance the posterior mean of the
    GLS covariances plus the spread of the solutions (law of total variance). Returned tau2 is the posterior mean.
    Why: the biases' variance is mostly the run mean's 1/f wander 2 ln2 tau^2, and a B read from 6-26 s plateaus
    is uncertain (nu 2-60): taken as exact, an underestimated B gives large z (accelerometer bias z sd 1.16-1.17,
    tactical and consumer, 1.01-1.07 with the true B, in 900 simulated position runs; 1.03-1.07 marginalised).
    A sem-based upper bound on tau^2 is not used: the sems are computed from the same B (circular).
    ``sem_tau2``: the 1/f level the sems contain (:func:`white_variance`).
    """
    from scipy.optimize import minimize_scalar

    D0 = sig**2
    G = log_kernel(t_mid, t_len)
    # deviations from the run mean (double-centred kernel), plus the run mean's own wander at the Allan floor
    # sigma_A^2(T_run) = 2 ln2 tau^2: the bias estimate is uncertain by the bias instability at the run length
    white = FLICKER_WHITE  # Allan floor of 1/f noise: (2 ln2 / pi) B^2 = 2 ln2 tau^2
    G = G - G.mean(axis=0, keepdims=True) - G.mean(axis=1, keepdims=True) + G.mean() + white
    n, p = X.shape
    scale = float(np.median(D0))

    def parts(tau2):
        S = np.diag(white_variance(sig, tau2, sem_tau2)) + tau2 * G
        L = np.linalg.cholesky(S)
        Xw = np.linalg.solve(L, X)
        yw = np.linalg.solve(L, y)
        Q, R = np.linalg.qr(Xw)
        x = np.linalg.solve(R, Q.T @ yw)
        r = yw - Xw @ x
        return L, R, x, r

    def nll(log_ratio):
        tau2 = scale * np.exp(log_ratio)
        try:
            L, R, x, r = parts(tau2)
        except np.linalg.LinAlgError:
            return np.inf
        return 2 * np.sum(np.log(np.diag(L))) + 2 * np.sum(np.log(np.abs(np.diag(R)))) + float(r @ r)

    if _integrates_tau2(tau2, prior_dof):
        return _flicker_marginal(parts, nll, float(tau2), prior_dof, scale, p)
    if tau2 is not None:
        if tau2 <= 0:
            return 0.0, None, None, None
        L, R, x, r = parts(float(tau2))
        Rinv = np.linalg.solve(R, np.eye(p))
        return float(tau2), x, Rinv @ Rinv.T, float(r @ r)
    try:
        base = nll(-30.0)
        res = minimize_scalar(nll, bounds=(-12.0, 6.0), method="bounded", options={"xatol": 1e-3})
        if not res.success or res.fun >= base - 1e-9:
            return 0.0, None, None, None
        tau2 = scale * float(np.exp(res.x))
        L, R, x, r = parts(tau2)
    except np.linalg.LinAlgError:
        return 0.0, None, None, None
    Rinv = np.linalg.solve(R, np.eye(p))
    return tau2, x, Rinv @ Rinv.T, float(r @ r)


def _integrates_tau2(tau2: float | None, prior_dof) -> bool:
    """Whether :func:`flicker_gls` integrates tau^2 out (an Allan estimate with its degrees of freedom or law)."""
    if isinstance(prior_dof, FLICKER_LAWS):
        return bool(tau2 is not None and tau2 > 0)
    return bool(tau2 is not None and tau2 > 0 and prior_dof is not None and np.isfinite(prior_dof) and prior_dof > 0)


#: log grid of tau^2 / tau2_hat for the marginalisation over the 1/f level (:func:`flicker_gls`)
FLICKER_GRID = np.linspace(-7.0, 4.0, 45)


def _flicker_marginal(parts, nll, t0: float, nu, scale: float, p: int):
    """Posterior-mean GLS over tau^2 (see :func:`flicker_gls`): grid in ln tau^2, weights from the Allan estimate's
    likelihood (chi-square with nu dof, a :class:`FlickerLaw`, or a :class:`FlickerBoundLaw`) and the plateaus' REML
    likelihood."""
    law = nu if isinstance(nu, FLICKER_LAWS) else None
    if isinstance(law, FlickerBoundLaw):  # a bound's own grid: midpoints in ln tau^2 below tau2_max
        grid = law.tau2_grid
    elif law is not None:  # from below the detection scale to above the estimate
        lo = law.resolution_tau2 * np.exp(FLICKER_GRID[0])
        hi = max(law.resolution_tau2, law.f_hat / FLICKER_WHITE) * np.exp(FLICKER_GRID[-1])
        grid = np.geomspace(lo, hi, max(len(FLICKER_GRID), int(np.ceil(np.log(hi / lo) / 0.25)) + 1))
    else:
        grid = t0 * np.exp(FLICKER_GRID)
    sols, logw = [], []
    for t2 in grid:
        try:
            L, R, x, r = parts(float(t2))
        except np.linalg.LinAlgError:
            continue
        Rinv = np.linalg.solve(R, np.eye(p))
        # prior flat in ln tau^2 (scaled-inverse-chi^2 law), or flat in tau (the censored law, [GELMAN2006])
        lik = law.loglik(t2) + 0.5 * np.log(t2) if law is not None else -0.5 * nu * (t0 / t2 + np.log(t2))
        lw = -0.5 * nll(np.log(t2 / scale)) + lik
        sols.append((t2, x, Rinv @ Rinv.T))
        logw.append(lw)
    if not sols:
        return 0.0, None, None, None
    w = np.exp(np.asarray(logw) - np.max(logw))
    w /= w.sum()
    xs = np.array([s_[1] for s_ in sols])
    xm = w @ xs
    d = xs - xm
    C = np.einsum("k,kij->ij", w, np.array([s_[2] for s_ in sols])) + (d * w[:, None]).T @ d
    tm = float(w @ np.array([s_[0] for s_ in sols]))
    L, R, x, r = parts(tm)
    return tm, xm, C, float(r @ r)  # chi-square of the GLS at the posterior-mean tau^2


def flicker_b_dof(p, channel: str, max_cluster_fraction: float = 0.5) -> float | None:
    """Degrees of freedom nu of the run's 1/f level F = (2 ln2 / pi) B^2 as segmentation's pooled Allan fit reads
    it ([IEEE952] C.23 fitted to the EDF-weighted mean overlapping Allan variance of the plateaus, [NIST1065]
    EDF), from the plateau table: per plateau k its length T_k, samples n_k and white level N_k^2 = (sem_k^2 - F)
    T_k; the pooled estimate at cluster size m (octaves up to ``max_cluster_fraction`` n_k) has variance
    2 sum_k e_km avar_km^2 / E_m^2 (e_km = (n_k - 2m + 1) / m, E_m = sum_k e_km); the Fisher information of
    (white scale, F) over the octaves (taken as independent) gives var(F_hat), nu = 2 F^2 / var(F_hat).
    None without the columns or an estimated B."""
    got = _floor_inputs(p, channel, detected_only=True)
    if got is None:
        return None
    b, n, T, sem2, f_sem = got
    F = FLICKER_WHITE / np.pi * b**2
    try:
        vF = _flicker_floor_var(n, T, sem2, f_sem, F, max_cluster_fraction)
    except np.linalg.LinAlgError:
        return None
    return float(FLICKER_DOF_EFFICIENCY * 2.0 * F**2 / vF) if vF > 0 else None


def flicker_dof_from_interval(b: float, lo: float, hi: float, level: float = 0.95) -> float:
    """Degrees of freedom nu of B^2 from B and its equal-tailed interval [lo, hi] at ``level``, with B_hat^2 ~
    B^2 chi^2_nu / nu ([GELMAN2013] sec. 3.2, the law :func:`fit_linear` integrates tau^2 over): (hi / lo)^2 =
    chi^2_nu(1 - a/2) / chi^2_nu(a/2), solved for nu (a profile-likelihood interval of an Allan fit, as
    ``imulab allan`` prints, is read as if it were that interval). ValueError for an interval that is only a bound
    (lo <= 0) or does not contain B."""
    from scipy.optimize import brentq

    b, lo, hi = float(b), float(lo), float(hi)
    if not (np.isfinite(lo) and np.isfinite(hi) and lo > 0):
        raise ValueError(f"interval [{lo:g}, {hi:g}] is an upper bound (lower end <= 0): B was not resolved; give "
                         "B = 0 (not detected) or its degrees of freedom")
    if not lo <= b <= hi or hi <= lo:
        raise ValueError(f"interval [{lo:g}, {hi:g}] must contain B = {b:g} and have high > low")
    a = 1.0 - level
    target = 2.0 * np.log(hi / lo)

    def gap(log_nu):
        nu = np.exp(log_nu)
        return float(np.log(stats.chi2.ppf(1 - a / 2, nu)) - np.log(stats.chi2.ppf(a / 2, nu))) - target

    lo_nu, hi_nu = np.log(0.05), np.log(1e8)
    if gap(hi_nu) > 0:
        return 1e8
    if gap(lo_nu) < 0:
        return 0.05
    return float(np.exp(brentq(gap, lo_nu, hi_nu, xtol=1e-10)))


def _floor_inputs(p, channel: str, detected_only: bool):
    """(B, n_samples, length_s, sem^2, F_sem) of a channel's usable plateaus (>= 4 samples, positive length, finite
    sem) from a plateau table, or None without the columns, with fewer than two such plateaus, or with B missing
    (negative or NaN; also zero when ``detected_only``). F_sem = 2 ln2 tau_s^2, the Allan floor the sems contain
    (:func:`sem_flicker_tau2`; that of B for a table without the column): sem^2 - F_sem is a plateau's white part."""
    need = (f"{channel}_sem", f"{channel}_flicker_b", "n_samples", "t_start_s", "t_end_s")
    if any(c not in p for c in need) or not len(p):
        return None
    b = float(p[f"{channel}_flicker_b"].iloc[0])
    if not np.isfinite(b) or b < 0 or (detected_only and b == 0):
        return None
    n = p["n_samples"].to_numpy(float)
    T = (p["t_end_s"] - p["t_start_s"]).to_numpy(float)
    sem2 = p[f"{channel}_sem"].to_numpy(float) ** 2
    ok = (n >= 4) & (T > 0) & np.isfinite(sem2)
    if ok.sum() < 2:
        return None
    ts = sem_flicker_tau2(p, channel)
    f_sem = FLICKER_WHITE * (b**2 / np.pi if ts is None else ts)
    return b, n[ok], T[ok], sem2[ok], f_sem


def _flicker_floor_var(n: np.ndarray, T: np.ndarray, sem2: np.ndarray, f_white: float, F: float,
                       max_cluster_fraction: float) -> float:
    """var(F_hat) of the pooled Allan floor at a true floor F: the inverse Fisher information of (white scale, F)
    over the octaves taken as independent (:func:`flicker_b_dof`), the plateaus' white levels N_k^2 = (sem_k^2 -
    f_white) T_k; raises ``np.linalg.LinAlgError`` when the information is singular."""
    dt = float(np.median(T / np.maximum(n - 1, 1)))
    N2 = np.maximum(sem2 - f_white, 0.0) * T
    caps = np.maximum(1, (max_cluster_fraction * n).astype(int))
    info = np.zeros((2, 2))
    for m in 2 ** np.arange(int(np.log2(caps.max())) + 1):
        sel = caps >= m
        e = np.maximum(1.0, (n[sel] - 2 * m + 1) / m)
        E = e.sum()
        white = N2[sel] / (m * dt)
        var = 2.0 * np.sum(e * (white + F) ** 2) / E**2
        J = np.array([np.sum(e * white) / E, 1.0])
        if not var > 0:  # no white level left and F = 0: the octave says nothing (callers get a non-finite scale)
            return float("nan")
        info += np.outer(J, J) / var
    return float(np.linalg.inv(info)[1, 1])


#: the octave Allan variances of one window are correlated (overlapping clusters share samples), which the
#: independent-octave information of :func:`flicker_b_dof` ignores: the empirical nu = 2 / var(F_hat / F) over 900
#: simulated position runs (5 plans x 3 grades, 60 runs each) was 0.45-0.70 of the independent one where B is well
#: detected (navigation, consumer; median 0.5) and 0.25-0.45 for the tactical accelerometer (B often undetected)
FLICKER_DOF_EFFICIENCY = 0.5


@dataclass(frozen=True)
class FlickerLaw:
    """Sampling law of the run's Allan floor estimate F_hat = (2 ln2 / pi) B_hat^2 (segmentation's pooled fit).

    F_hat is the non-negative least-squares value of an unconstrained estimate of variance v(F) from the Fisher
    information of :func:`flicker_b_dof` evaluated at the candidate F (white levels from the plateau sems), times
    1 / FLICKER_DOF_EFFICIENCY. Its law is a shifted chi-square, F_hat + W ~ (F + W) chi^2_nu / nu
    ([SATTERTHWAITE1946] moment match of sqrt(v) at F = 0 and F = 10 sqrt(v(0))): far above the white scatter W it is
    :func:`flicker_b_dof`'s chi-square, near zero it keeps the white octaves' scatter. Detected (F_hat > 0): its
    density; not detected (F_hat = 0): censored, P(F_hat <= 0) = P(chi^2_nu <= nu W / (F + W)) ([TOBIN1958]).
    :func:`fit_linear` uses it for an undetected B with < 3 residual dof (module docstring).
    """

    f_hat: float
    n: np.ndarray
    T: np.ndarray
    sem2: np.ndarray
    max_cluster_fraction: float = 0.5
    f_sem: float | None = None  # the Allan floor the sems contain (None: f_hat's); sem^2 - f_sem is the white part

    def var(self, F: float) -> float:
        f_white = self.f_hat if self.f_sem is None else self.f_sem
        return _flicker_floor_var(self.n, self.T, self.sem2, f_white, F, self.max_cluster_fraction) / FLICKER_DOF_EFFICIENCY

    @cached_property
    def resolution_tau2(self) -> float:
        """tau^2 whose floor 2 ln2 tau^2 equals the standard error of F_hat at F = 0 (the detection scale)."""
        return float(np.sqrt(self.var(0.0))) / FLICKER_WHITE

    @cached_property
    def shifted_chi2(self) -> tuple[float, float]:
        """(nu, W): F_hat + W ~ (F + W) chi^2_nu / nu matching sqrt(v(F)) at F = 0 and F = 10 sqrt(v(0))
        (Satterthwaite: the white octaves' chi-square scatter as an offset W of the 1/f level)."""
        s0 = np.sqrt(self.var(0.0))
        F1 = 10.0 * s0
        slope = (np.sqrt(self.var(F1)) - s0) / F1
        slope = max(float(slope), 1e-6)
        return 2.0 / slope**2, s0 / slope

    def loglik(self, tau2: float) -> float:
        F = FLICKER_WHITE * tau2
        nu, W = self.shifted_chi2
        if self.f_hat > 0:
            return float(-0.5 * nu * ((self.f_hat + W) / (F + W) + np.log(F + W)))
        return float(stats.chi2.logcdf(nu * W / (F + W), nu))


def flicker_law(p, channel: str, max_cluster_fraction: float = 0.5) -> FlickerLaw | None:
    """The :class:`FlickerLaw` of a channel's B from a plateau table, or None without the columns."""
    got = _floor_inputs(p, channel, detected_only=False)
    if got is None:
        return None
    b, n, T, sem2, f_sem = got
    law = FlickerLaw(FLICKER_WHITE / np.pi * b**2, n, T, sem2, max_cluster_fraction, f_sem)
    try:
        r = law.resolution_tau2
    except np.linalg.LinAlgError:
        return None
    return law if np.isfinite(r) and r > 0 else None


@dataclass(frozen=True)
class FlickerBoundLaw:
    """What an upper bound on B says of tau^2 = B^2 / pi: tau^2 <= tau2_max, nothing more. Posterior
    p(tau | plateaus) ~ L_REML(tau^2) 1[0 <= tau <= tau_max] (prior flat in tau on [0, tau_max], [GELMAN2006] sec. 4).

    The device's long static record (the ``allan_deviation`` stage's IEEE 952 fit, [IEEE952] C.23) reports B as a
    one-sided upper bound (the profile interval's upper end, ``is_upper_bound``) when the record does not resolve the
    floor: a navigation gyro's floor shows at tau ~ 1e4-1e5 s, beyond a practical record. Taking the bound as B
    over-covers (it lies 2-7x above the truth: rate-fit bias z sd 0.45 / 0.66 navigation / tactical on 20-min
    records, benchmarks/README.md session 9); the bound as a hard support with a prior flat in tau (not in
    ln tau^2: with a likelihood flat near zero a log-uniform prior leaves the posterior set by the grid's lower end,
    [GELMAN2006] sec. 4) leaves the plateaus' REML likelihood ([PATTERSON1971]) to weigh the levels below it, and
    with a REML flat there the posterior mean of tau^2 is tau2_max / 3. Hard, not a smooth edge: the bound is the
    record's 95 % upper limit and the REML term already falls above the plateaus' own level, so the support is the
    only information the bound carries; a softened edge (mass above the bound) would add back the over-coverage
    the bound as B showed. Measured (dev cache, benchmarks/README.md "Device noise prior"): right where the bound lies
    ~1.7-2.4x above the true B (navigation gyro, 3 h and 8 h records: bias z sd 0.75-0.87 -> 0.98-1.06; tactical,
    20 min: 0.86-0.89 -> 0.98-0.99); still wide at 6.5x (navigation, 20 min: rate fit 0.80 -> 0.70) and too narrow
    at ~1x (tactical channels still a bound at 3 h: z sd 1.62), since the posterior mean sits near tau2_max / 3.

    ``inner``: the run's own Allan law (:class:`FlickerLaw` of its plateaus), weighed inside the support, so the
    bound truncates what the run says (its censored likelihood) rather than replacing it: posterior
    ~ L_REML L_run 1[tau <= tau_max], flat in tau. Where the bound is near the truth the run's law lifts tau^2
    toward it (the 66 of 600 tactical channels a bound at 3 h: rate-fit bias z sd 1.27, coverage 0.89; session 9's
    bound alone on other trials 1.62 / 0.75); far above the truth it changes little against the bound alone
    (navigation at 3 h, 100 devices: rate-fit bias z sd 0.956 both; benchmarks/README.md "Session 10"). The bound lies
    below the run's own detection scale in 94-100 % of channels even at 20 min.

    Interface of :class:`FlickerLaw` for :func:`fit_linear` / :func:`flicker_gls` / :func:`_flicker_marginal`:
    ``loglik`` (the inner law's inside the support, or 0 without one; -inf above), ``resolution_tau2`` (the bound:
    the grid's anchor), ``f_hat`` (0: no estimate), and ``tau2_grid``, the midpoints of ``FLICKER_BOUND_STEPS``
    cells of width 0.25 in ln tau^2 below tau2_max (a midpoint rule: the density in ln tau^2 is largest at the bound,
    where an end point would over-weigh half a cell); the mass below the grid, tau < tau_max e^-5.5, is 0.4 % of the
    prior's (without an inner law).
    """

    tau2_max: float
    f_hat: float = 0.0
    #: the run's own Allan estimate's law (:func:`flicker_law` of its plateaus), weighed inside the support: the
    #: bound then truncates what the run says instead of replacing it
    inner: FlickerLaw | None = None

    def __post_init__(self):
        if not (np.isfinite(self.tau2_max) and self.tau2_max > 0):
            raise ValueError(f"FlickerBoundLaw needs a positive finite tau2_max, got {self.tau2_max!r}")

    @property
    def resolution_tau2(self) -> float:
        return float(self.tau2_max)

    @property
    def tau2_grid(self) -> np.ndarray:
        return float(self.tau2_max) * np.exp(-FLICKER_BOUND_STEP * (np.arange(FLICKER_BOUND_STEPS) + 0.5))

    def loglik(self, tau2: float) -> float:
        if not 0.0 <= tau2 <= self.tau2_max * (1.0 + 1e-12):
            return -np.inf
        return 0.0 if self.inner is None else self.inner.loglik(tau2)


#: ln tau^2 cell width and number of cells of :class:`FlickerBoundLaw`'s grid (down to tau2_max e^-11)
FLICKER_BOUND_STEP = 0.25
FLICKER_BOUND_STEPS = 44
#: the sampling laws :func:`fit_linear` accepts as ``flicker_tau2_dof`` (duck-typed: loglik, resolution_tau2, f_hat)
FLICKER_LAWS = (FlickerLaw, FlickerBoundLaw)
