"""Run-level block D: each run's fitted bias as an observation, the power cycle's bias as nuisance.

Block A (``design.py``) projects each run's bias out of its plateau means (the twin refits it per run, as the real
fit does), so an effect that moves the bias *between* the runs of one power cycle (a bias ramp: 2e-8 rad/s^2 x
1,500 s between the rate and the position run = 3e-5 rad/s, against a tactical bias instability of ~4e-6 rad/s)
leaves only its slope within each run there. Block D keeps the discarded part (docs/simreal.md, "Run-level
block"):

- observations of run r, channel j: what block A's Frisch-Waugh projection discards, i.e. the run's fitted
  nuisance combinations z_r = W_r' y with W_r = L^-1' Q_r, Q_r an orthonormal basis of L^-1 N (N the run's
  nuisance columns: bias, linear g-sensitivity or accelerometer row, the rate run's scale/misalignment row; L the
  Cholesky factor of block A's plateau covariance). In a position run these are the bias and the linear terms; in
  a rate run whose table axis is along +x, +y, +z the bias is not separable from the linear g-sensitivity (three
  orientations, four columns), so its observations are the three orientation levels b + G f_k. The same W_r
  applied to a signature column x gives its run-level signature W_r' x (one linear operator, as in every block);
- covariance of the z_r of one power cycle: W_r' C_cyc W_s, C_cyc the covariance of *all* the cycle's plateau
  means as one record: white part per plateau (block A's D), the twin's bias instability tau^2 G with the
  library's 1/f kernel (``fit_core.log_kernel``, tau^2 = B^2 / pi) over the plateaus' mid-times since power-on,
  and the twin's rate random walk K^2 min(t_i, t_j) since power-on [IEEE952 annex C; fit_core.flicker_gls].
  Its diagonal blocks are each run's own white, 1/f and random-walk terms; the off-diagonal blocks carry the 1/f
  and random-walk covariance between the runs' plateaus. The constant of the 1/f kernel lies in the bias
  direction and is removed with the cycle's bias;
- nuisance: the power cycle's base model, i.e. the same nuisance terms shared by name by every run of the cycle
  (one bias, one linear g-sensitivity / accelerometer row, ...: the base twin's terms are per power cycle),
  projected out after whitening (Frisch-Waugh). What remains is the between-run inconsistency of the run fits:
  a bias that moves between the runs (bias ramp, warm-up, temperature), and the run-level projection of any
  block-A signature (an |omega| asymmetry raises a rate run's levels against the position run's bias), which is
  why every family with block-A columns has block-D columns too (``design.D_COLS``).

Rows are grouped per power cycle; the selection holds a cycle's block-D rows out together
(``attribution.Totals``: folds per power cycle for the families with block-D columns, ``effects.has_block``).

Replicates of the twin simulate each run with the real run's fitted bias (so that every other statistic sees the
real offsets); their run-level observations are taken relative to that injected bias (``bias_offset``), i.e.
under the null hypothesis of one bias per power cycle plus the twin's noise, which is what the sim-vs-sim gate of
a block-D candidate must be calibrated on.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from assets_lib.calibration.fit_core import log_kernel

#: output channels with block-D rows: the gyros. On the quick tier's null devices the accelerometers' run-level
#: rows were over-dispersed against the twin's noise (sum of squares 20.2 and 23.8 for 9 rows, chi^2(9), on
#: WH-000 accel_y and WH-001 accel_z; the gyros' 3-7): the twin's accelerometer bias instability does not describe
#: their between-run scatter, and the replicates (simulated from that twin) cannot calibrate what it lacks
#: (docs/simreal.md, "Run-level block (session 6)")
CHANNELS = (0, 1, 2)


@dataclass(frozen=True)
class RunEntry:
    """One run's block-A rows of one channel, reduced to what block D needs."""

    run_index: int
    channel: int
    cycle: int
    W: np.ndarray  # (n_plateaus, k): z = W' y over the run's kept plateaus (unwhitened rows)
    z: np.ndarray  # (k,)
    Z: np.ndarray  # (k, P) run-level signatures of every column
    M: np.ndarray  # (k, n_names) the run's nuisance columns seen through W, by name
    names: tuple
    white_var: np.ndarray  # per-plateau white variance (block A's D)
    t_on_s: np.ndarray  # plateau mid-times since power-on
    len_s: np.ndarray  # plateau lengths


def entry(run_index: int, channel: int, cycle: int, Li: np.ndarray, N: np.ndarray, names: tuple, y: np.ndarray,
          X: np.ndarray, white_var: np.ndarray, t_on_s: np.ndarray, len_s: np.ndarray, d_cols: np.ndarray,
          bias_offset: float = 0.0, tol: float = 1e-10) -> RunEntry | None:
    """The run's block-D entry (module docstring); ``d_cols`` masks the columns with block-D signatures;
    ``bias_offset`` (the bias a replicate was simulated with) is subtracted from the rows first."""
    Nw = Li @ N
    u, s, _ = np.linalg.svd(Nw, full_matrices=False)
    Q = u[:, s > tol * max(s[0], 1e-300)]
    if Q.shape[1] == 0:
        return None
    W = Li.T @ Q
    return RunEntry(run_index, channel, cycle, W, W.T @ (y - bias_offset), (W.T @ X) * d_cols, W.T @ N, tuple(names),
                    np.asarray(white_var, float), np.asarray(t_on_s, float), np.asarray(len_s, float))


def _orth(a: np.ndarray, tol: float = 1e-10) -> np.ndarray:
    if a.size == 0:
        return np.zeros((a.shape[0], 0))
    u, s, _ = np.linalg.svd(a, full_matrices=False)
    return u[:, s > tol * max(s[0], 1e-300)]


def cycle_rows(entries: list[RunEntry], tau2: float, k2: float):
    """Whitened block-D rows of one (cycle, channel) with the cycle's shared nuisance projected out: (y, X), or
    None with fewer than two runs or nothing left."""
    if len(entries) < 2:
        return None
    t = np.concatenate([e.t_on_s for e in entries])
    T = np.concatenate([e.len_s for e in entries])
    C = np.diag(np.concatenate([e.white_var for e in entries])) + tau2 * log_kernel(t, T) + k2 * np.minimum.outer(t, t)
    names = sorted({nm for e in entries for nm in e.names})
    K = sum(e.z.size for e in entries)
    Wf = np.zeros((t.size, K))
    M = np.zeros((K, len(names)))
    r = c = 0
    for e in entries:
        n, k = e.W.shape
        Wf[r:r + n, c:c + k] = e.W
        for i, nm in enumerate(e.names):
            M[c:c + k, names.index(nm)] = e.M[:, i]
        r, c = r + n, c + k
    V = Wf.T @ C @ Wf
    try:
        L = np.linalg.cholesky(V)
    except np.linalg.LinAlgError:
        L = np.diag(np.sqrt(np.maximum(np.diag(V), 1e-300)))
    Li = np.linalg.inv(L)
    y = Li @ np.concatenate([e.z for e in entries])
    X = Li @ np.vstack([e.Z for e in entries])
    Q = _orth(Li @ M)
    # orthonormal basis of the complement of the cycle's nuisance: K - rank rows
    u = np.linalg.svd(np.eye(K) - Q @ Q.T)[0]
    B = u[:, : K - Q.shape[1]]
    if B.shape[1] == 0:
        return None
    return B.T @ y, B.T @ X
