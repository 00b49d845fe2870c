"""Plateau segmentation: SEM under correlated noise, clock alignment, whole revolutions, plan matching without a
table log, end-to-end against the simulator's truth, and the static/rotation detector on real sessions."""

from __future__ import annotations

import dataclasses
import hashlib
import json
import re
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from assets_lib.sim.earth import site_gravity_mps2
from assets_lib.sim.noise import AllanParams, allan_noise
from assets_lib.calibration.outliers import reject_outliers_window
from assets_lib.calibration.segmentation import (
    CHANNELS,
    DetectorConfig,
    PooledAllanFit,
    SegmentationConfig,
    align_clocks,
    detect_quiet_intervals,
    mean_difference_variance,
    plateau_columns,
    plateau_sem,
    plot_segmentation_png,
    segment_run,
    whole_revolution_window,
)
from assets_lib.sim.simulator import UG, example_device, simulate_run
from raw_schemas.readers import ingest_frames

FS = 100.0


# ------------------------------------------------------------------------------------------------------------
# Truth model (docs/design.md) and shared simulated runs
# ------------------------------------------------------------------------------------------------------------
def truth_prediction(plateaus: pd.DataFrame, truth) -> np.ndarray:
    """y_g = diag(K)(I+E) omega + b + G f;  y_a = diag(K)(I+E) f + b + K2 f^2 + sum_j Kc[i,j] f_i f_j."""
    w = plateaus[[f"omega_ref_{a}_radps" for a in "xyz"]].to_numpy()
    f = plateaus[[f"f_ref_{a}_mps2" for a in "xyz"]].to_numpy()
    g = w @ truth.gyro.matrix().T + np.asarray(truth.gyro.bias) + f @ np.asarray(truth.g_sensitivity).T
    a = f @ truth.accel.matrix().T + np.asarray(truth.accel.bias) + np.asarray(truth.accel.k2) * f**2
    a = a + f * (f @ np.asarray(truth.accel.kc).T)
    return np.column_stack([g, a])


def means_and_sems(p: pd.DataFrame) -> tuple[np.ndarray, np.ndarray]:
    return p[[f"{c}_mean" for c in CHANNELS]].to_numpy(), p[[f"{c}_sem" for c in CHANNELS]].to_numpy()


TABLE_OFFSET_S = 1.2345


@pytest.fixture(scope="module")
def white_device():
    """Tactical device whose noise at plateau length is white-dominated (accel bias instability 2 ug, not 20)."""
    base = example_device("SEG-W", "tactical", 7)
    return dataclasses.replace(base, accel=dataclasses.replace(base.accel, noise=(AllanParams(n=0.03 / 60, b=2 * UG),) * 3))


@pytest.fixture(scope="module")
def base_device():
    return example_device("SEG-B", "tactical", 7)


def _ingested(truth, plan, seed, **kw):
    run = simulate_run(truth, plan, f"{plan}-{seed}", seed=seed, **kw)
    return run, ingest_frames(run.manifest, run.imu_raw, run.table_raw)


@pytest.fixture(scope="module")
def rate_run(white_device):
    return _ingested(white_device, "quick_rate", 4, table_clock_offset_s=TABLE_OFFSET_S)


@pytest.fixture(scope="module")
def position_run(white_device):
    return _ingested(white_device, "quick_24_position", 4)


@pytest.fixture(scope="module")
def rate_segments(rate_run):
    _, ing = rate_run
    return segment_run(ing.manifest, ing.imu, ing.table), segment_run(ing.manifest, ing.imu, None)


@pytest.fixture(scope="module")
def position_segments(position_run):
    _, ing = position_run
    return segment_run(ing.manifest, ing.imu, ing.table), segment_run(ing.manifest, ing.imu, None)


# ------------------------------------------------------------------------------------------------------------
# SEM under correlated noise
# ------------------------------------------------------------------------------------------------------------
def test_mean_difference_variance_reproduces_allan_definition():
    """Two adjacent T-means differ with variance 2 sigma_A^2(T) (IEEE 952 C.1): flicker 2 (2 ln2/pi) B^2, RW 2 K^2 T/3."""
    t = 20.0
    fl = PooledAllanFit(np.zeros(1), np.zeros(1), 1.7e-8, 0.0)
    rw = PooledAllanFit(np.zeros(1), np.zeros(1), 0.0, 3.0e-9)
    assert mean_difference_variance(fl, 0, t, t / 2, t, 1.5 * t, FS) == pytest.approx(2 * 1.7e-8, rel=1e-3)
    assert mean_difference_variance(rw, 0, t, t / 2, t, 1.5 * t, FS) == pytest.approx(2 * 3.0e-9 * t / 3, rel=1e-3)
    wn = PooledAllanFit(np.zeros(1), np.array([4e-6]), 0.0, 0.0)
    assert mean_difference_variance(wn, 0, t, 50.0, 100.0, 50.0, FS) == pytest.approx(4e-6 * (1 / t - 1 / 100.0))


def _sem_z(params: AllanParams, n_win: int, t_s: float, trials: int, seed: int):
    """Back-to-back windows with known, different true levels; z of consecutive differences (SEM and naive)."""
    rng = np.random.default_rng(seed)
    n = int(t_s * FS)
    z, zn, ratio = [], [], []
    for _ in range(trials):
        levels = rng.uniform(-1.0, 1.0, n_win)  # known truth of each plateau
        x = allan_noise(n_win * n, FS, params, rng) + np.repeat(levels, n)
        segs = [x[k * n : (k + 1) * n] - levels[k] for k in range(n_win)]  # residual about the known level
        sr = plateau_sem(segs, 1 / FS)
        means = np.array([x[k * n : (k + 1) * n].mean() for k in range(n_win)])
        d = np.diff(means - levels)
        z += list(d / np.hypot(sr.sem[1:], sr.sem[:-1]))
        zn += list(d / np.hypot(sr.naive_sem[1:], sr.naive_sem[:-1]))
        ratio += list(sr.sem**2 / params.avar(t_s))
    return np.std(z), np.std(zn), np.median(ratio)


def test_sem_calibrated_on_flicker_plus_random_walk():
    """White + bias instability + rate random walk, 24 windows of 30 s: naive sigma/sqrt(n) is ~1.9x too small."""
    p = AllanParams(n=1e-3, b=3.9e-4, k=4e-5)  # at T = 30 s: white 29 %, flicker 45 %, RW 26 % of AVAR(T)
    z_std, naive_std, ratio = _sem_z(p, 24, 30.0, trials=50, seed=3)
    assert 0.85 <= z_std <= 1.2
    assert naive_std > 1.6
    assert 0.6 <= ratio <= 1.4  # median SEM^2 / true sigma_A^2(T)


def test_window_allan_variance_agrees_with_the_noise_package():
    """The short-window estimator of the pooled SEM model (noise.pooled.overlapping_avar, cumulative-sum form) is
    the same quantity as noise.allan.oadev; they differ only in summation order."""
    from assets_lib.noise import allan as al
    from assets_lib.noise.pooled import overlapping_avar

    x = np.random.default_rng(3).standard_normal(6000) * 1e-3 + np.cumsum(1e-6 * np.ones(6000))
    m = np.array([1, 2, 4, 16, 64, 256, 1024, 2999])
    avar, n_terms = overlapping_avar(x, m)
    ref = al.oadev(x, 1.0, m.astype(float), alpha=0)
    np.testing.assert_array_equal(ref.m, m)
    np.testing.assert_array_equal(n_terms, ref.n_terms)
    np.testing.assert_allclose(avar, ref.adev**2, rtol=1e-12, atol=0)


def test_sem_on_white_noise_is_sigma_over_sqrt_n():
    """No over-correction: on white noise the model selection keeps (almost always) the white terms only."""
    z_std, naive_std, ratio = _sem_z(AllanParams(n=1e-3), 24, 30.0, trials=30, seed=4)
    assert 0.9 <= z_std <= 1.1 and 0.9 <= naive_std <= 1.1
    assert ratio == pytest.approx(1.0, abs=0.05)


# ------------------------------------------------------------------------------------------------------------
# Clock alignment and whole revolutions (table log)
# ------------------------------------------------------------------------------------------------------------
def test_clock_offset_recovered(rate_run):
    run, ing = rate_run
    al = align_clocks(ing.manifest.plan, ing.imu, ing.table)
    assert run.table_clock_offset_s == TABLE_OFFSET_S
    err = al.offset_s - TABLE_OFFSET_S
    assert al.method.startswith("xcorr")
    assert al.correlation_peak > 0.99
    assert abs(err) < 0.01 / FS  # a hundredth of an IMU sample
    assert abs(err) < 4 * al.offset_stderr_s  # stderr: Cramer-Rao bound from the residual noise
    assert abs(al.clock_drift_ppm) < 4 * al.clock_drift_stderr_ppm + 1e-3  # no clock-rate error simulated


@pytest.mark.slow
def test_clock_drift_unbiased_with_honest_stderr(white_device):
    """A clock-rate error eps reads as -eps / (1 + eps) (t_imu = (1 + eps) t_table): over seeds at +-200 ppm the
    mean error is within 3 standard errors of the mean and the z-scores scatter like N(0, 1). The half-record
    offsets alone (constant delay per half, ramps far from the centroid dropped as outliers) read ~5 % high, the
    halves at their middles ~20 % low (-158 ppm for -200)."""
    from assets_lib.sim.effects import EFFECTS, sensor_chain

    errs, zs = [], []
    for seed, eps in enumerate((2e-4, -2e-4) * 4):
        chain = sensor_chain([EFFECTS["timebase_error"](clock_rate_error=eps)])
        _, ing = _ingested(white_device, "quick_rate", 100 + seed, table_clock_offset_s=TABLE_OFFSET_S, effects=chain)
        al = align_clocks(ing.manifest.plan, ing.imu, ing.table)
        truth = -1e6 * eps / (1 + eps)
        errs.append(al.clock_drift_ppm - truth)
        zs.append(errs[-1] / al.clock_drift_stderr_ppm)
        assert abs(truth) > 50 * al.clock_drift_stderr_ppm  # a precise statistic, so a 5 % bias would fail
    errs, zs = np.array(errs), np.array(zs)
    assert abs(errs.mean()) < 3 * errs.std(ddof=1) / np.sqrt(errs.size)
    assert np.all(np.abs(zs) < 4) and 0.5 < zs.std(ddof=1) < 1.6


def test_segment_run_reuses_a_given_alignment(white_device, rate_run):
    """``clock_alignment=``: the run's own alignment gives the same table as aligning again; a replicate (same
    plan, time stamps and table log, other noise) with the recorded alignment keeps the recorded plateau windows."""
    _, ing = rate_run
    al = align_clocks(ing.manifest.plan, ing.imu, ing.table)
    own = segment_run(ing.manifest, ing.imu, ing.table)
    given = segment_run(ing.manifest, ing.imu, ing.table, clock_alignment=al)
    pd.testing.assert_frame_equal(own.plateaus, given.plateaus, check_exact=True)
    assert given.alignment is al
    _, rep = _ingested(white_device, "quick_rate", 4 + 1000, table_clock_offset_s=TABLE_OFFSET_S)
    rep = dataclasses.replace(rep, manifest=ing.manifest)  # the replicate of the recorded run
    r = segment_run(rep.manifest, rep.imu, rep.table, clock_alignment=al)
    assert r.alignment is al
    np.testing.assert_array_equal(r.window_step, own.window_step)
    for c in ["t_start_s", "t_end_s", "revolutions", "commanded_rate_radps"]:
        np.testing.assert_array_equal(r.plateaus[c].to_numpy(), own.plateaus[c].to_numpy())
    assert not np.array_equal(r.plateaus["gyro_z_radps_mean"], own.plateaus["gyro_z_radps_mean"])  # other noise


def test_clock_offset_found_far_from_prior(white_device):
    """A large offset (table clock 250 s ahead) is still found: the search spans every lag with >= 50 % overlap."""
    run, ing = _ingested(white_device, "quick_rate", 5, table_clock_offset_s=250.0)
    al = align_clocks(ing.manifest.plan, ing.imu, ing.table)
    assert abs(al.offset_s - 250.0) < 0.01 / FS


def test_static_plan_aligns_on_step_centres(position_run):
    """A position plan's table log shows no rotation rate: the offset comes from step boundaries vs quiet intervals."""
    run, ing = position_run
    assert np.all(ing.table["rate_radps"] == 0.0)
    al = align_clocks(ing.manifest.plan, ing.imu, ing.table)
    assert al.method == "step_centres"
    assert abs(al.offset_s - run.table_clock_offset_s) <= 1.0 / FS
    assert al.offset_stderr_s > 0


def test_whole_revolutions_chosen(rate_segments, rate_run):
    _, ing = rate_run
    p = rate_segments[0].plateaus.set_index("step_index")
    dt = 1 / FS
    n_whole = 0
    for s in ing.manifest.plan.steps:
        row = p.loc[s.index]
        period = 360.0 / abs(s.table_rate_dps) if s.table_rate_dps else np.inf
        usable = s.duration_s - s.settle_s - 2 * SegmentationConfig().guard_s
        length = row["t_end_s"] - row["t_start_s"] + dt
        if usable >= period:
            n_whole += 1
            assert row["revolutions"] == np.floor(usable / period) >= 1
            assert abs(length - row["revolutions"] * period) <= dt
        else:
            assert row["revolutions"] < 1
            assert row["revolutions"] == pytest.approx(length / period, abs=dt / period)
    assert n_whole >= 12


def test_whole_revolution_window_is_centred():
    rate = np.radians(30.0)
    a, b, q = whole_revolution_window(10.0, 45.0, lambda t: -rate * t)
    assert q == 2.0
    assert b - a == pytest.approx(24.0, abs=1e-6)
    assert 0.5 * (a + b) == pytest.approx(27.5, abs=1e-6)
    assert whole_revolution_window(0.0, 5.0, lambda t: rate * t)[2] == pytest.approx(150 / 360)


# ------------------------------------------------------------------------------------------------------------
# End to end against the truth model
# ------------------------------------------------------------------------------------------------------------
def _check_against_truth(seg, truth, n_steps):
    p = seg.plateaus
    assert list(p.columns) == plateau_columns()
    assert len(p) == n_steps and not p["flagged"].any(), p.loc[p["flagged"], "flag_reason"].tolist()
    m, s = means_and_sems(p)
    z = (m - truth_prediction(p, truth)) / s
    assert np.isfinite(z).all()
    assert 0.8 <= np.std(z) <= 1.25
    assert np.abs(z).max() < 4.5
    return z


def test_rate_run_matches_truth_with_and_without_table(rate_segments, white_device, rate_run):
    _, ing = rate_run
    n = len(ing.manifest.plan.steps)
    z_tab = _check_against_truth(rate_segments[0], white_device, n)
    z_imu = _check_against_truth(rate_segments[1], white_device, n)
    assert rate_segments[0].method == "table_log" and rate_segments[1].method == "imu_only"
    # both ways cut (nearly) the same windows: the plateau means agree far inside their SEMs
    assert np.abs(z_tab - z_imu).max() < 0.5
    p = rate_segments[0].plateaus
    cmd = np.radians([s.table_rate_dps for s in ing.manifest.plan.steps])
    np.testing.assert_allclose(p["commanded_rate_radps"], cmd)
    # reference = table rate along the body table axis + earth rate
    w_ref = p[[f"omega_ref_{a}_radps" for a in "xyz"]].to_numpy()
    w_e = p[[f"omega_earth_{a}_radps" for a in "xyz"]].to_numpy()
    np.testing.assert_allclose(np.linalg.norm(w_ref - w_e, axis=1), np.abs(cmd), rtol=1e-9)
    assert np.all(np.linalg.norm(w_e, axis=1) < 7.3e-5)


def test_position_run_matches_truth_with_and_without_table(position_segments, white_device, position_run):
    _, ing = position_run
    n = len(ing.manifest.plan.steps)
    _check_against_truth(position_segments[0], white_device, n)
    _check_against_truth(position_segments[1], white_device, n)
    p = position_segments[1].plateaus
    f = p[[f"f_ref_{a}_mps2" for a in "xyz"]].to_numpy()
    np.testing.assert_allclose(np.linalg.norm(f, axis=1), site_gravity_mps2(ing.manifest.site), rtol=1e-12)
    assert (p["revolutions"] == 0).all() and (p["commanded_rate_radps"] == 0).all()


def test_plateau_differences_calibrated_under_bias_instability(base_device):
    """Default tactical noise (accel bias instability 20 ug): consecutive plateau differences vs truth have z std ~1.

    The SEM is the Allan deviation at the window length, i.e. the scatter of a plateau mean about its neighbours;
    against a fixed bias, plateau means of a flicker-dominated channel scatter more (log growth with run length).
    """
    z = []
    for plan in ("quick_rate", "quick_24_position"):
        _, ing = _ingested(base_device, plan, 9)
        p = segment_run(ing.manifest, ing.imu, ing.table).plateaus.sort_values("t_start_s")
        m, s = means_and_sems(p)
        d = np.diff(m - truth_prediction(p, base_device), axis=0)
        z.append((d / np.hypot(s[1:], s[:-1])).ravel())
    assert 0.8 <= np.std(np.concatenate(z)) <= 1.25


# ------------------------------------------------------------------------------------------------------------
# Without a table log: plan matching
# ------------------------------------------------------------------------------------------------------------
def test_imu_only_windows_match_table_windows(position_segments):
    tab, imu = (s.plateaus for s in position_segments)
    assert position_segments[1].unmatched_steps == ()
    assert np.abs(tab["t_start_s"] - imu["t_start_s"]).max() <= 0.2
    assert np.abs(tab["t_end_s"] - imu["t_end_s"]).max() <= 0.2


def test_imu_only_recovers_plan_shift(position_run, white_device):
    """The test started 3 s before the IMU's time zero (plan times 3 s late): found from the data alone."""
    _, ing = position_run
    imu = ing.imu[ing.imu["time_s"] >= 3.0].copy()
    imu["time_s"] -= 3.0
    seg = segment_run(ing.manifest, imu.reset_index(drop=True), None)
    assert seg.unmatched_steps == ()
    np.testing.assert_allclose(seg.plan_shift_s, -3.0, atol=1.0 / FS)
    _check_against_truth(seg, white_device, len(ing.manifest.plan.steps))


def test_unmatched_step_reported(position_run):
    """A step disturbed by a 0.7 Hz oscillation has no quiet interval: reported and flagged, the others unaffected."""
    _, ing = position_run
    imu = ing.imu.copy()
    s = ing.manifest.plan.steps[5]
    m = (imu["time_s"] >= s.start_s) & (imu["time_s"] < s.end_s)
    imu.loc[m, "gyro_z_radps"] += 0.5 * np.sin(2 * np.pi * 0.7 * imu.loc[m, "time_s"])
    seg = segment_run(ing.manifest, imu, None)
    assert seg.unmatched_steps == (5,)
    p = seg.plateaus.set_index("step_index")
    assert p.loc[5, "flagged"] and "unmatched" in p.loc[5, "flag_reason"]
    assert p.loc[5, "n_samples"] == 0 and np.isnan(p.loc[5, "gyro_z_radps_mean"])
    assert not p.drop(index=5)["flagged"].any()


def test_glitches_rejected_and_means_unchanged(rate_run, rate_segments):
    _, ing = rate_run
    clean = rate_segments[0]
    imu = ing.imu.copy()
    rng = np.random.default_rng(8)
    inside = np.flatnonzero(clean.keep)
    hit = rng.choice(inside, 60, replace=False)
    col = rng.choice(list(CHANNELS), 60)
    p = clean.plateaus
    for i, c in zip(hit, col):  # 12 per-sample sigmas (sem x sqrt(n) on these white-dominated channels)
        imu.loc[i, c] += 12 * (p[f"{c}_sem"] * np.sqrt(p["n_samples"])).median() * rng.choice([-1, 1])
    seg = segment_run(ing.manifest, imu, ing.table)
    assert not seg.keep[hit].any()
    m0, s0 = means_and_sems(clean.plateaus)
    m1, _ = means_and_sems(seg.plateaus)
    assert np.abs((m1 - m0) / s0).max() < 0.5
    assert (seg.plateaus["n_rejected"] >= clean.plateaus["n_rejected"]).all()


def test_segmentation_png(rate_run, rate_segments):
    _, ing = rate_run
    png = plot_segmentation_png(ing.imu, rate_segments[0], title="quick_rate")
    assert png[:8] == b"\x89PNG\r\n\x1a\n" and len(png) > 10_000


# ------------------------------------------------------------------------------------------------------------
# Real sessions (shared reference data)
# ------------------------------------------------------------------------------------------------------------
def _verify_sha256(folder: Path, names: list[str]) -> None:
    text = (folder / "SOURCE.txt").read_text()
    sums = dict((name, h) for h, name in re.findall(r"^([0-9a-f]{64})\s+\./(\S+)\s*$", text, flags=re.M))
    for name in names:
        assert hashlib.sha256((folder / name).read_bytes()).hexdigest() == sums[name], f"{name}: checksum differs"


def test_ferraris_session_sections(shared_data):
    """imucal example session (102.4 Hz, deg/s and m/s^2) against its hand-drawn section list."""
    folder = shared_data / "imucal_example"
    _verify_sha256(folder, ["example_ferraris_session.csv", "example_ferraris_session_list.json"])
    d = pd.read_csv(folder / "example_ferraris_session.csv")
    sections = json.loads((folder / "example_ferraris_session_list.json").read_text())
    fs = 102.4
    t = d["n_samples"].to_numpy() / fs
    gyro = np.radians(d[["gyr_x", "gyr_y", "gyr_z"]].to_numpy())
    det = detect_quiet_intervals(t, gyro, d[["acc_x", "acc_y", "acc_z"]].to_numpy())
    iv, mo = det.intervals, det.motions
    for name in ("x_p", "x_a", "y_p", "y_a", "z_p", "z_a"):
        s0, s1 = sections[name]["start"], sections[name]["end"]
        ov = np.clip(np.minimum(iv["end_index"], s1) - np.maximum(iv["start_index"], s0), 0, None)
        assert ov.max() >= 0.95 * (s1 - s0), f"{name}: static section not inside one detected static interval"
        j = int(np.argmax(ov))
        assert iv.loc[j, "kind"] == "static"
    rotations = []
    for name, axis in (("x_rot", "x"), ("y_rot", "y"), ("z_rot", "z")):
        s0, s1 = sections[name]["start"], sections[name]["end"]
        ov = np.clip(np.minimum(mo["end_index"], s1) - np.maximum(mo["start_index"], s0), 0, None)
        j = int(np.argmax(ov))
        rotations.append(j)
        assert abs(mo.loc[j, "start_index"] - s0) / fs <= 0.3, name
        assert abs(mo.loc[j, "end_index"] - s1) / fs <= 0.3, name
        ang = np.degrees(mo.loc[j, ["angle_x", "angle_y", "angle_z"]].to_numpy(dtype=float))
        assert abs(abs(ang["xyz".index(axis)]) - 360.0) < 20.0  # one full turn about that axis
        assert np.abs(np.delete(ang, "xyz".index(axis))).max() < 10.0
    # every other motion is a re-orientation of at most ~190 deg
    others = mo.drop(index=rotations)
    assert np.degrees(others["angle_norm"]).max() < 200.0


def _read_xsens(folder: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    acc = np.loadtxt(folder / "xsens_acc.mat")  # plain ASCII despite the extension: t, x, y, z
    gyr = np.loadtxt(folder / "xsens_gyro.mat")
    np.testing.assert_array_equal(acc[:, 0], gyr[:, 0])
    return acc[:, 0], gyr[:, 1:], acc[:, 1:]


def test_xsens_static_intervals_and_gyro_bias(shared_data):
    folder = shared_data / "imu_tk_xsens"
    _verify_sha256(folder, ["xsens_acc.mat", "xsens_gyro.mat", "REFERENCE.txt"])
    t, gyr, acc = _read_xsens(folder)
    assert t.size == 51175
    det = detect_quiet_intervals(t, gyr, acc, DetectorConfig(center="median"))  # raw counts: remove ~32768 offsets
    iv = det.intervals
    first = iv.iloc[0]
    assert first["t_start_s"] <= t[0] + 1.0 and 50.0 <= first["t_end_s"] <= 56.0  # the initial ~50 s static interval
    poses = iv.iloc[1:]
    assert 34 <= len(poses) <= 42  # "about 38 static poses"
    assert poses["duration_s"].min() >= 1.0
    # published gyro bias = mean of the rows with t <= 50 s, all inside the detected initial interval
    init = t <= 50.0
    assert np.all(det.quiet[init])
    np.testing.assert_allclose(gyr[init].mean(axis=0), [32777.15046, 32459.81653, 32511.84894], atol=5e-6)
    # the robust plateau mean of that interval agrees with it within its SEM, rejecting next to nothing
    w = reject_outliers_window(t[init], gyr[init])
    assert w.rejected_fraction < 2e-3
    dt = float(np.median(np.diff(t)))
    sem = np.array([plateau_sem([gyr[init, i]], dt).sem[0] for i in range(3)])
    assert np.all(np.abs(gyr[init][w.keep].mean(axis=0) - gyr[init].mean(axis=0)) < sem)
