"""Replicates of the twin driven by the recorded inputs, pushed through the same chain, in parallel processes.

Each replicate r of a device: every run simulated by ``twin.simulate_run_imu`` with the seed (seed, r, run),
processed by ``experiment.process_run`` (segmentation and library fits), the replicate's **own twin** fitted from it
by ``twin.fit_twin`` (the estimator the real data went through), then turned into a ``Design`` against that own twin
and its views. A parametric-bootstrap check compares T(y, theta_hat(y)) on the real data with
T(y_r, theta_hat(y_r)) on each replicate ([EFRON1993] ch. 6: the bootstrap repeats every
data-dependent step); computing the replicate's statistic against the real data's theta_hat instead leaves out the
twin's estimation error (the real residuals are taken against parameters fitted to them, a replicate's were not).
Replicates run in worker processes (``concurrent.futures``, fork start: the recorded inputs are shared
copy-on-write, never pickled); results depend only on (seed, r), so they are identical for any worker count.
The plan kinematics and flicker spectral shapes are cached across replicates (bit-identical to computing them).
"""

from __future__ import annotations

import multiprocessing as mp
import os
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass

import numpy as np

from assets_lib.sim.kinematics import kinematics_cache
from assets_lib.sim.noise import flicker_shape_cache
from assets_lib.simreal.design import Design, build_design
from assets_lib.simreal.experiment import DeviceExperiment, process_run
from assets_lib.simreal.twin import TwinModel, fit_twin, simulate_run_imu
from assets_lib.simreal.views import compute_views

_STATE: dict = {}


@dataclass(frozen=True, eq=False)
class Replicate:
    index: int
    design: Design
    views: dict


def _stable(text: str) -> int:
    import hashlib

    return int.from_bytes(hashlib.sha256(text.encode()).digest()[:4], "little")


def one_replicate(r: int, seed: int, twin: TwinModel, runs, windows, rk) -> Replicate:
    imus, proc = {}, {}
    for inp in runs:
        rng = np.random.default_rng([seed, r, _stable(inp.run_id)])
        imu = simulate_run_imu(twin, inp, rng)
        imus[inp.run_id] = imu
        proc[inp.run_id] = process_run(inp, imu)
    own = refit_like_real(twin, runs, imus, proc)
    # run-level block D under the null of one bias per power cycle: relative to the bias each run was simulated with
    d = build_design(runs, proc, own, imus, windows, np.array([p.k for p in own.noise]), bias_offset=twin.bias)
    return Replicate(r, d, compute_views(d, proc, own.noise))


def refit_like_real(twin: TwinModel, runs, imus: dict, proc: dict) -> TwinModel:
    """The replicate's own base twin: ``fit_twin`` on the replicate's processed runs (the real data's estimator
    path), keeping ``twin``'s device id."""
    return fit_twin(DeviceExperiment(twin.device_id, "", tuple(runs), imus, proc))


def _worker(args):
    r, seed, key = args
    st = _STATE[key]
    return one_replicate(r, seed, st["twin"], st["runs"], st["windows"], st["rk"])


def default_workers() -> int:
    return max(1, min(2, os.cpu_count() or 1))


def parallel_map(fn, items, workers: int | None = None, progress=None) -> list:
    """``[fn(x) for x in items]`` in worker processes (fork start: what the parent holds, e.g. recorded inputs and a
    warm ``kinematics_cache``, is shared copy-on-write, never pickled; ``fn`` and the results are pickled). Results
    come back in order and do not depend on the worker count. ``progress(done, n)`` after each."""
    items = list(items)
    n = len(items)
    workers = default_workers() if workers is None else workers
    out = []
    if workers <= 1 or n <= 1:
        for x in items:
            out.append(fn(x))
            if progress:
                progress(len(out), n)
        return out
    with ProcessPoolExecutor(max_workers=min(workers, n), mp_context=mp.get_context("fork")) as ex:
        for res in ex.map(fn, items):
            out.append(res)
            if progress:
                progress(len(out), n)
    return out


def run_replicates(twin: TwinModel, runs, windows, rk, n: int, seed: int, workers: int | None = None,
                   progress=None, key: str = "base") -> list[Replicate]:
    """``n`` replicates (indices 0..n-1) of ``twin``; ``progress(done, n)`` after each."""
    _STATE[key] = {"twin": twin, "runs": runs, "windows": windows, "rk": rk}
    try:  # plan kinematics and flicker spectral shapes are the same in every replicate (bit-identical caches)
        with kinematics_cache(), flicker_shape_cache():
            return parallel_map(_worker, [(r, seed, key) for r in range(n)], workers, progress)
    finally:
        _STATE.pop(key, None)
