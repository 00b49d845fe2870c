"""Replicate speed-ups change no value: kinematics and flicker-shape caches, the reused clock alignment, the pool.

Each replicate of a short rate run (simulate -> ingest -> segment -> rate fit) is computed without any cache and
again inside ``kinematics_cache`` + ``flicker_shape_cache`` (twice, so the second pass runs on plain cache hits),
and in a process pool: raw frames, plateau tables and coefficient tables must be equal bit for bit.
"""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from assets_lib.calibration.rate_fit import fit_gyro_rate
from assets_lib.calibration.segmentation import align_clocks, segment_run
from assets_lib.sim.kinematics import CACHE_STATS, kinematics_cache, trajectory
from assets_lib.sim.noise import flicker_shape_cache
from assets_lib.sim.plans import build_plan
from assets_lib.sim.simulator import example_device, simulate_run
from assets_lib.simreal.replicates import parallel_map
from raw_schemas.readers import ingest_frames

PLAN = build_plan("quick_rate", duration_scale=0.4)
TRUTH = example_device("CACHE-1", "tactical", 3)  # flicker noise on every channel
_STATE: dict = {}


def _replicate(seed: int, alignment=None):
    run = simulate_run(TRUTH, PLAN, "r", test_kind="rate", seed=seed, table_clock_offset_s=0.61)
    ing = ingest_frames(run.manifest, run.imu_raw, run.table_raw)
    seg = segment_run(ing.manifest, ing.imu, ing.table, clock_alignment=alignment)
    return run.imu_raw, run.table_raw, seg.plateaus, fit_gyro_rate(seg.plateaus).coefficient_table()


def _same(a, b):
    for x, y in zip(a, b):
        pd.testing.assert_frame_equal(x, y, check_exact=True)


@pytest.fixture(scope="module")
def recorded_alignment():
    run = simulate_run(TRUTH, PLAN, "r", test_kind="rate", seed=0, table_clock_offset_s=0.61)
    ing = ingest_frames(run.manifest, run.imu_raw, run.table_raw)
    return align_clocks(ing.manifest.plan, ing.imu, ing.table)


@pytest.mark.parametrize("reuse", [False, True])
def test_caches_are_bit_identical(recorded_alignment, reuse):
    al = recorded_alignment if reuse else None
    plain = [_replicate(s, al) for s in (11, 12)]
    before = dict(CACHE_STATS)
    with kinematics_cache(), flicker_shape_cache() as shapes:
        cached = [_replicate(s, al) for s in (11, 12)]
        assert shapes  # the flicker amplitudes were memoised
    for a, b in zip(plain, cached):
        _same(a, b)
    assert CACHE_STATS["hits"] > before["hits"]
    assert not plain[0][2]["gyro_z_radps_mean"].equals(plain[1][2]["gyro_z_radps_mean"])  # replicates differ


def test_cache_keeps_callers_times_writeable():
    t = np.arange(0.0, 20.0, 0.02)
    with kinematics_cache():
        trajectory(PLAN, np.arange(0.0, 30.0, 0.01))
        tr1 = trajectory(PLAN, t)  # served from the finer grid
        tr = trajectory(PLAN, t)  # asked again (the table log of every replicate): kept under its own key
        tr3 = trajectory(PLAN, t)
    assert tr3 is tr and t.flags.writeable and not tr.c_b2l.flags.writeable
    np.testing.assert_array_equal(tr1.c_b2l, tr.c_b2l)
    ref = trajectory(PLAN, t)
    np.testing.assert_array_equal(tr.c_b2l, ref.c_b2l)
    np.testing.assert_array_equal(tr.table_angle_rad, ref.table_angle_rad)
    t[0] = -1.0  # the caller may still write into its own array


def _pool_worker(seed):
    return _replicate(seed, _STATE.get("al"))


def test_parallel_map_matches_serial(recorded_alignment):
    _STATE["al"] = recorded_alignment
    try:
        serial = [_pool_worker(s) for s in (21, 22)]
        with kinematics_cache(), flicker_shape_cache():
            pooled = parallel_map(_pool_worker, [21, 22], workers=2)
    finally:
        _STATE.clear()
    for a, b in zip(serial, pooled):
        _same(a, b)


def test_flicker_noise_arithmetic_unchanged():
    """The spectrum is built without complex temporaries; the values are those of the plain expression, bit for bit
    (the stored archive depends on them), with and without the shape cache."""
    from scipy import fft as sp_fft

    from assets_lib.sim.noise import FLICKER_SPAN_FACTOR, flicker_noise

    for n, b in ((1001, 1e-5), (24001, 3e-3)):
        m = sp_fft.next_fast_len(int(np.ceil(FLICKER_SPAN_FACTOR * n)), real=True)
        f = np.fft.rfftfreq(m, d=1.0 / 100.0)
        one = np.zeros_like(f)
        one[1:] = b**2 / (np.pi * f[1:])
        amp = np.sqrt(one * 100.0 * m / 4.0)
        rng = np.random.default_rng(n)
        spec = amp * (rng.standard_normal(f.size) + 1j * rng.standard_normal(f.size))
        if m % 2 == 0:
            spec[-1] = spec[-1].real * np.sqrt(2.0)
        ref = np.fft.irfft(spec, n=m)[:n]
        np.testing.assert_array_equal(flicker_noise(n, 100.0, b, np.random.default_rng(n)), ref)
        with flicker_shape_cache():
            for _ in range(2):
                np.testing.assert_array_equal(flicker_noise(n, 100.0, b, np.random.default_rng(n)), ref)
