"""Physics of the digital twin: what an ideal IMU on the simulated table reads, the error model, the noise,
the table log, power cycles, determinism and the written archive.

Expected values are computed here from first principles (docs/design.md conventions, WGS-84 constants,
closed-form orientations), not from the simulator's own helpers.
"""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest
from scipy.stats import chi2

from assets_lib.sim.earth import normal_gravity_mps2
from assets_lib.sim.noise import AllanParams, allan_noise
from assets_lib.sim.plans import build_plan
from assets_lib.sim.simulator import (
    ArchiveSpec,
    DeviceTruth,
    ErrorModel,
    Saturation,
    SiteSpec,
    TriadTruth,
    example_device,
    simulate_run,
    to_counts,
    write_archive,
    write_run,
)
from raw_schemas.readers import discover_runs, ingest_frames, ingest_run
from raw_schemas.units import si_factor

OMEGA_IE = 7.2921150e-5  # rad/s, docs/design.md
SITE = SiteSpec()
LAT = np.radians(SITE.latitude_deg)
W_IE_ENU = OMEGA_IE * np.array([0.0, np.cos(LAT), np.sin(LAT)])
GYRO = ["gyro_x_radps", "gyro_y_radps", "gyro_z_radps"]
ACCEL = ["accel_x_mps2", "accel_y_mps2", "accel_z_mps2"]
G_LSB_DPS = 1e-7  # fine quantization for the ideal device
A_LSB_G = 1e-8
G_LSB = G_LSB_DPS * np.pi / 180.0  # rad/s per count
A_LSB = A_LSB_G * 9.80665  # m/s^2 per count
IDEAL = (ErrorModel(),)  # no noise, no saturation


def ideal_truth(device_id: str = "IDEAL-1", fs: float = 100.0, **accel_kw) -> DeviceTruth:
    """K = 1, E = 0, b = 0, no noise; optional accel second-order terms via ``accel_kw``."""
    zero3x3 = ((0.0,) * 3,) * 3
    quiet = (AllanParams(),) * 3
    gyro = TriadTruth((1.0,) * 3, zero3x3, (0.0,) * 3, quiet, G_LSB_DPS, "deg/s")
    accel = TriadTruth((1.0,) * 3, zero3x3, (0.0,) * 3, quiet, A_LSB_G, "g", **accel_kw)
    return DeviceTruth(device_id, "ideal", "navigation", gyro, accel, sample_rate_hz=fs)


def canonical(run):
    r = ingest_frames(run.manifest, run.imu_raw, run.table_raw)
    return r.imu["time_s"].to_numpy(), r.imu[GYRO].to_numpy(), r.imu[ACCEL].to_numpy(), r


def window(fs: float, start_s: float, end_s: float) -> slice:
    """Sample indices k with start <= k/fs < end (robust to float noise in the plan times)."""
    return slice(int(np.ceil(start_s * fs - 1e-6)), int(np.ceil(end_s * fs - 1e-6)))


def test_normal_gravity_matches_wgs84_reference():
    """NIMA TR8350.2 eq. 4-1 (Somigliana, closed form with gamma_e, gamma_p) and the normal free-air gradient."""
    a, f = 6378137.0, 1 / 298.257223563
    b = a * (1 - f)
    ge, gp = 9.7803253359, 9.8321849378  # TR8350.2 table 3.4
    for lat in (0.0, 15.0, 34.25, 45.0, 60.0, 90.0, -34.25):
        c2, s2 = np.cos(np.radians(lat)) ** 2, np.sin(np.radians(lat)) ** 2
        ref = (a * ge * c2 + b * gp * s2) / np.sqrt(a**2 * c2 + b**2 * s2)
        assert normal_gravity_mps2(lat, 0.0) == pytest.approx(ref, rel=1e-10)
    # free-air gradient -0.3086 mGal/m = -3.086e-6 s^-2 (varies +-0.1 % with latitude)
    grad = (normal_gravity_mps2(34.25, 400.0) - normal_gravity_mps2(34.25, 0.0)) / 400.0
    assert grad == pytest.approx(-3.086e-6, rel=2e-3)
    assert SITE.gravity_mps2 == normal_gravity_mps2(SITE.latitude_deg, SITE.height_m)


# ------------------------------------------------------------------------------------------------------------
# Static positions: gravity and earth rate
# ------------------------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def static24():
    plan = build_plan("quick_24_position", duration_scale=0.2)
    run = simulate_run(ideal_truth(), plan, "pos24", effects=IDEAL, table_log=False)
    return run, canonical(run)


def _f_direction_24(k: int) -> np.ndarray:
    """Closed form of the 24-position plan (seed 003): 3 mounts x 8 turns of 45 deg about the body axis that
    points horizontally N (x), N (y), N (z); the unit specific-force direction in body axes."""
    th = np.radians(45.0 * (k % 8))
    s, c = np.sin(th), np.cos(th)
    return [np.array([0.0, s, c]), np.array([c, 0.0, s]), np.array([s, c, 0.0])][k // 8]


def test_static_accel_reads_local_gravity_in_all_24_positions(static24):
    run, (t, _, acc, _) = static24
    g = SITE.gravity_mps2
    fs = run.manifest.sample_rate_hz
    steps = run.manifest.plan.steps
    assert len(steps) == 24 and all(s.kind == "static" for s in steps)
    quant = 0.5 * A_LSB * (1 + 1e-9)
    for k, s in enumerate(steps):
        w = window(fs, s.start_s, s.end_s)
        a = acc[w]
        assert len(a) == round(s.duration_s * fs)
        c_b2l = np.asarray(s.orientation_b2l)
        f_b = c_b2l.T @ np.array([0.0, 0.0, g])  # ENU: a static IMU's specific force points up
        np.testing.assert_allclose(a, np.broadcast_to(f_b, a.shape), rtol=0, atol=quant)
        np.testing.assert_allclose(f_b, g * _f_direction_24(k), rtol=0, atol=1e-12)
        norms = np.linalg.norm(a, axis=1)
        assert np.all(np.abs(norms - g) <= np.sqrt(3) * quant)
        u = _f_direction_24(k)
        angle = np.arctan2(np.linalg.norm(np.cross(a, u), axis=1), a @ u)
        assert np.all(angle <= np.sqrt(3) * quant / (g - np.sqrt(3) * quant))


def test_static_gyro_reads_earth_rate_projection(static24):
    run, (t, gyr, _, _) = static24
    fs = run.manifest.sample_rate_hz
    quant = 0.5 * G_LSB * (1 + 1e-9)
    for s in run.manifest.plan.steps:
        w = window(fs, s.start_s, s.end_s)
        expected = np.asarray(s.orientation_b2l).T @ W_IE_ENU
        np.testing.assert_allclose(gyr[w], np.broadcast_to(expected, gyr[w].shape), rtol=0, atol=quant)
        assert np.linalg.norm(gyr[w].mean(axis=0)) == pytest.approx(OMEGA_IE, abs=np.sqrt(3) * quant)


# ------------------------------------------------------------------------------------------------------------
# Rate plateaus
# ------------------------------------------------------------------------------------------------------------
def _one_rate_plan(rate_dps: float, duration_s: float):
    return build_plan(
        {
            "name": "spin",
            "frame": "ENU",
            "lead_s": 2.0,
            "steps": [{"kind": "rate", "axes": {"x": "E", "y": "N", "z": "U"}, "table_rate_dps": rate_dps,
                       "duration_s": duration_s, "settle_s": 0.0}],
        }
    )


@pytest.mark.parametrize("rate_dps", [36.0, -36.0])
def test_rate_plateau_integrates_to_commanded_angle(rate_dps):
    plan = _one_rate_plan(rate_dps, 10.0)
    run = simulate_run(ideal_truth(), plan, "spin", effects=IDEAL, table_log=True)
    t, gyr, _, r = canonical(run)
    fs = run.manifest.sample_rate_hz
    s = plan.steps[0]
    w = window(fs, s.start_s, s.end_s)
    n = len(t[w])
    assert n == 1000
    angle = gyr[w, 2].sum() / fs - OMEGA_IE * np.sin(LAT) * s.duration_s  # minus the earth rate on the up axis
    assert angle == pytest.approx(np.radians(rate_dps * 10.0), abs=n * 0.5 * G_LSB / fs)
    # C_b^l(t) = R(up, r (t - t0)) C_b^l(t0): the horizontal earth rate turns backwards in body axes
    th = np.radians(rate_dps) * (t[w] - s.start_s)
    quant = 0.5 * G_LSB * (1 + 1e-9)
    np.testing.assert_allclose(gyr[w, 0], W_IE_ENU[1] * np.sin(th), rtol=0, atol=quant)
    np.testing.assert_allclose(gyr[w, 1], W_IE_ENU[1] * np.cos(th), rtol=0, atol=quant)
    # the table log turns by the same angle during the step
    tab = r.table
    in_step = tab["step_index"].to_numpy() == 0
    rate_log = tab["rate_radps"].to_numpy()[in_step]
    np.testing.assert_allclose(rate_log, np.radians(rate_dps), rtol=1e-12)


def test_whole_revolution_plateaus_average_horizontal_earth_rate():
    """Seed 000's full-revolution method: over a whole turn about the vertical the horizontal earth rate
    averages out, leaving table rate + Omega sin(lat) on the up axis."""
    fs = 20.0
    plan = build_plan("seed000_rate_full_revolution")
    run = simulate_run(ideal_truth("IDEAL-20", fs), plan, "rev", effects=IDEAL, table_log=False)
    _, gyr, _, _ = canonical(run)
    tol = 0.5 * G_LSB * (1 + 1e-9)  # the mean of quantized samples is within half a count
    omega_h = OMEGA_IE * np.cos(LAT)
    assert len(plan.steps) == 60
    for s in plan.steps:
        assert s.kind == "rate"
        c_b2l = np.asarray(s.orientation_b2l)
        up = int(np.argmax(np.abs(c_b2l[2])))
        assert abs(c_b2l[2, up]) == pytest.approx(1.0, abs=1e-12)
        horiz = [i for i in range(3) if i != up]
        rev_s = 360.0 / abs(s.table_rate_dps)
        assert s.duration_s - s.settle_s == pytest.approx(rev_s, rel=1e-12)
        w = window(fs, s.start_s + s.settle_s, s.end_s)
        assert w.stop - w.start == round(rev_s * fs)
        mean = gyr[w].mean(axis=0)
        assert np.all(np.abs(mean[horiz]) <= tol), (s.index, mean[horiz] / omega_h)
        up_rate = np.sign(c_b2l[2, up]) * mean[up]
        assert up_rate == pytest.approx(np.radians(s.table_rate_dps) + OMEGA_IE * np.sin(LAT), abs=tol)
        # control: three quarters of a turn do not average the horizontal earth rate out
        w34 = slice(w.start, w.start + round(0.75 * rev_s * fs))
        assert np.max(np.abs(gyr[w34].mean(axis=0)[horiz])) > 0.1 * omega_h


# ------------------------------------------------------------------------------------------------------------
# Counts, error model, noise
# ------------------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("family, lsb, unit", [("gyro", 1 / 131.0, "deg/s"), ("gyro", 2e-6, "deg/s"),
                                               ("accel", 1 / 16384.0, "g"), ("accel", 1e-6, "g")])
def test_counts_convert_back_exactly(family, lsb, unit):
    rng = np.random.default_rng(4)
    counts = rng.integers(-(2**31), 2**31, size=20000)
    lsb_si = lsb * si_factor(family, unit)
    frac = rng.uniform(-0.49, 0.49, size=counts.size)
    assert np.array_equal(to_counts((counts + frac) * lsb_si, lsb, unit, family), counts)
    value = counts * lsb_si  # what ingestion produces
    back = value / lsb_si
    assert np.array_equal(np.rint(back).astype(np.int64), counts)
    assert np.all(np.abs(back - counts) <= np.spacing(np.abs(counts).astype(float)))


def test_simulated_counts_are_nearest_counts_of_the_true_signal(static24):
    run, (t, gyr, acc, _) = static24
    for cols, lsb_si in ((GYRO, G_LSB), (ACCEL, A_LSB)):
        raw = run.imu_raw[[c.split("_")[0] + "_" + c.split("_")[1] for c in cols]].to_numpy()
        canon = acc if cols is ACCEL else gyr
        assert np.array_equal(np.rint(canon / lsb_si).astype(np.int64), raw)


def _model_equation(w_b, f_b, tr: DeviceTruth):
    """docs/design.md, written out element by element."""
    kg, eg, bg = np.asarray(tr.gyro.scale), np.asarray(tr.gyro.misalignment_rad), np.asarray(tr.gyro.bias)
    ka, ea, ba = np.asarray(tr.accel.scale), np.asarray(tr.accel.misalignment_rad), np.asarray(tr.accel.bias)
    gs, k2, kc = np.asarray(tr.g_sensitivity), np.asarray(tr.accel.k2), np.asarray(tr.accel.kc)
    yg = np.zeros_like(w_b)
    ya = np.zeros_like(f_b)
    for i in range(3):
        yg[:, i] = kg[i] * (w_b[:, i] + sum(eg[i, j] * w_b[:, j] for j in range(3))) + bg[i]
        yg[:, i] += sum(gs[i, j] * f_b[:, j] for j in range(3))
        ya[:, i] = ka[i] * (f_b[:, i] + sum(ea[i, j] * f_b[:, j] for j in range(3))) + ba[i] + k2[i] * f_b[:, i] ** 2
        ya[:, i] += sum(kc[i, j] * f_b[:, i] * f_b[:, j] for j in range(3) if j != i)
    return yg, ya


def _off(vals):
    m = np.zeros((3, 3))
    m[~np.eye(3, dtype=bool)] = vals
    return tuple(map(tuple, m))


@pytest.mark.parametrize("terms", ["scale_misalignment_bias", "g_sensitivity", "k2", "kc", "all"])
def test_error_model_terms_follow_the_model_equation(terms):
    base = ideal_truth("TERMS-1")
    g = SITE.gravity_mps2
    tr = base
    if terms in ("scale_misalignment_bias", "all"):
        tr = replace(
            tr,
            gyro=replace(tr.gyro, scale=(1 + 300e-6, 1 - 150e-6, 1 + 80e-6), bias=(3e-5, -2e-5, 1e-5),
                         misalignment_rad=_off([2e-4, -1e-4, 3e-4, -2e-4, 1.5e-4, -5e-5])),
            accel=replace(tr.accel, scale=(1 - 200e-6, 1 + 250e-6, 1 + 50e-6), bias=(0.01, -0.02, 0.005),
                          misalignment_rad=_off([-3e-4, 1e-4, 2e-4, 2e-4, -1e-4, 4e-4])),
        )
    if terms in ("g_sensitivity", "all"):
        tr = replace(tr, g_sensitivity=tuple(map(tuple, np.array([[2, -1, 3], [1, -2, 1], [-3, 2, 1]]) * 1e-6)))
    if terms in ("k2", "all"):
        tr = replace(tr, accel=replace(tr.accel, k2=(50e-6 / g, -80e-6 / g, 30e-6 / g)))
    if terms in ("kc", "all"):
        tr = replace(tr, accel=replace(tr.accel, kc=_off(np.array([20, -10, 15, 30, -25, 5]) * 1e-6 / g)))
    plan = build_plan("quick_24_position", duration_scale=0.2)
    run = simulate_run(tr, plan, "terms", effects=IDEAL, table_log=False)
    ideal = simulate_run(base, plan, "terms", effects=IDEAL, table_log=False)
    _, gyr, acc, _ = canonical(run)
    _, gyr0, acc0, _ = canonical(ideal)
    fs = run.manifest.sample_rate_hz
    for s in plan.steps:
        w = window(fs, s.start_s, s.end_s)
        c_b2l = np.asarray(s.orientation_b2l)
        n = w.stop - w.start
        w_b = np.tile(c_b2l.T @ W_IE_ENU, (n, 1))
        f_b = np.tile(c_b2l.T @ np.array([0.0, 0.0, g]), (n, 1))
        yg, ya = _model_equation(w_b, f_b, tr)
        np.testing.assert_allclose(gyr[w], yg, rtol=0, atol=0.5 * G_LSB * (1 + 1e-6))
        np.testing.assert_allclose(acc[w], ya, rtol=0, atol=0.5 * A_LSB * (1 + 1e-6))
    # the terms are visible: far above the quantization
    assert max(np.abs(gyr - gyr0).max() / G_LSB, np.abs(acc - acc0).max() / A_LSB) > 1e3


@pytest.mark.parametrize(
    "params, alpha, taus_samples",
    [
        (AllanParams(q=2e-6), 2, [1, 10, 100]),  # quantization: white PM
        (AllanParams(n=1e-3), 0, [1, 10, 100, 1000]),  # angle random walk: white FM
        (AllanParams(b=1e-3), -1, [10, 100, 1000]),  # bias instability: flicker FM
        (AllanParams(k=1e-3), -2, [10, 100, 1000, 10000]),  # rate random walk: random-walk FM
    ],
    ids=["Q", "N", "B", "K"],
)
def test_noise_allan_variance_matches_model(params, alpha, taus_samples):
    """Overlapping Allan variance of the generated noise inside the 99.9 % chi-square interval of the model
    (NIST SP 1065 sec. 5.2; equivalent degrees of freedom by Greenhall's algorithm)."""
    allantools = pytest.importorskip("allantools")
    fs, n = 100.0, 1 << 17
    y = allan_noise(n, fs, params, np.random.default_rng([952, alpha + 10]))
    taus = np.asarray(taus_samples) / fs
    taus_out, adev, _, _ = allantools.oadev(y, rate=fs, data_type="freq", taus=taus)
    np.testing.assert_allclose(taus_out, taus)
    for m, tau, dev in zip(taus_samples, taus, adev):
        edf = allantools.edf_greenhall(alpha=alpha, d=2, m=m, N=n, overlapping=True, modified=False)
        lo = edf * dev**2 / chi2.ppf(0.9995, edf)
        hi = edf * dev**2 / chi2.ppf(0.0005, edf)
        assert lo <= params.avar(tau) <= hi, (m, dev**2 / params.avar(tau), edf)


def test_rate_ramp_allan_variance_is_exact():
    allantools = pytest.importorskip("allantools")
    p = AllanParams(r=3e-5)
    fs = 100.0
    y = allan_noise(20000, fs, p, np.random.default_rng(0))
    taus = np.array([0.01, 0.1, 1.0, 10.0])
    _, adev, _, _ = allantools.oadev(y, rate=fs, data_type="freq", taus=taus)
    np.testing.assert_allclose(adev**2, p.avar(taus), rtol=1e-6)


# ------------------------------------------------------------------------------------------------------------
# Table log, determinism, power cycles, archive
# ------------------------------------------------------------------------------------------------------------
TWO_RATES = {
    "name": "two_rates",
    "frame": "ENU",
    "lead_s": 1.0,
    "transition_s": 2.0,
    "steps": [
        {"kind": "rate", "axes": {"x": "E", "y": "N", "z": "U"}, "table_rate_dps": 36.0, "duration_s": 10.0},
        {"kind": "rate", "axes": {"x": "E", "y": "N", "z": "U"}, "table_rate_dps": -20.0, "duration_s": 10.0},
    ],
}


@pytest.mark.parametrize("offset", [None, 0.75])
def test_table_log_clock_offset_is_the_reported_one(offset, tmp_path):
    plan = build_plan(TWO_RATES)
    run = simulate_run(ideal_truth(), plan, "clock", effects=IDEAL, table_clock_offset_s=offset, seed=3)
    if offset is not None:
        assert run.table_clock_offset_s == offset
    off = run.table_clock_offset_s
    t, gyr, _, r = canonical(run)
    tab_t = r.table["time_s"].to_numpy()
    tab_rate = r.table["rate_radps"].to_numpy()
    idx = r.table["step_index"].to_numpy()
    dt_tab = float(np.median(np.diff(tab_t)))
    # each step begins in the log within one table sample after (IMU start + offset)
    for k, s in enumerate(plan.steps):
        first = tab_t[np.flatnonzero(idx == k)[0]]
        assert s.start_s + off - 1e-6 <= first < s.start_s + off + dt_tab + 1e-6
    # the table-rate profile matches the IMU's up-axis rate (minus earth rate) only at the reported offset
    imu_rate = gyr[:, 2] - OMEGA_IE * np.sin(LAT)
    cands = np.arange(0.0, 3.0, 1e-3)
    misfit = [np.mean((np.interp(tab_t - c, t, imu_rate) - tab_rate) ** 2) for c in cands]
    assert abs(cands[int(np.argmin(misfit))] - off) <= 2e-3
    # and the offset is what write_run reports in the truth file
    d = write_run(run, tmp_path / "landing", "parquet")
    tfile = tmp_path / "landing" / "_truth" / run.manifest.device.id / f"{run.manifest.run_id}.json"
    assert json.loads(tfile.read_text())["table_clock_offset_s"] == off
    assert d.is_dir()


def _noisy(seed: int, run_id: str = "det", effects=None):
    truth = example_device("TAC-DET", "tactical", seed=7)
    plan = build_plan(TWO_RATES)
    kw = {} if effects is None else {"effects": effects}
    return simulate_run(truth, plan, run_id, seed=seed, **kw)


def test_same_seed_gives_identical_files(tmp_path):
    for fmt in ("csv", "parquet"):
        dirs = [write_run(_noisy(5), tmp_path / f"{fmt}{i}", fmt) for i in (0, 1)]
        roots = [tmp_path / f"{fmt}{i}" for i in (0, 1)]
        files = [sorted(p.relative_to(root) for p in root.rglob("*") if p.is_file()) for root in roots]
        assert files[0] == files[1] and len(files[0]) == 5  # manifest, imu, table, _COMPLETE, truth
        for rel in files[0]:
            assert (roots[0] / rel).read_bytes() == (roots[1] / rel).read_bytes(), rel
        assert dirs[0].name == "det"


def test_different_seed_or_run_gives_independent_noise():
    clean = _noisy(5, effects=(ErrorModel(), Saturation())).imu_raw
    a, b, c = _noisy(5).imu_raw, _noisy(6).imu_raw, _noisy(5, run_id="det2").imu_raw
    for other in (b, c):
        for ch in ("gyro_x", "accel_z"):
            na = (a[ch] - clean[ch]).to_numpy(float)
            nb = (other[ch] - clean[ch]).to_numpy(float)
            assert np.std(na) > 0 and not np.array_equal(na, nb)
            rho = np.corrcoef(na, nb)[0, 1]
            assert abs(rho) < 4.0 / np.sqrt(na.size), (ch, rho)  # independent draws
    assert not a.equals(b)


def test_power_cycle_truths_differ_by_repeatability_spreads():
    base = example_device("TAC-PC", "tactical", seed=2026)
    n_cycles = 400
    cycles = [base.for_power_cycle(c, seed=2026) for c in range(n_cycles)]
    assert base.for_power_cycle(3, seed=2026) == cycles[3]  # deterministic
    assert cycles[1] != cycles[2]
    checks = [
        ("gyro bias", lambda tr: tr.gyro.bias, base.bias_repeatability[0]),
        ("accel bias", lambda tr: tr.accel.bias, base.bias_repeatability[1]),
        ("gyro scale", lambda tr: tr.gyro.scale, base.scale_repeatability[0]),
        ("accel scale", lambda tr: tr.accel.scale, base.scale_repeatability[1]),
    ]
    for name, get, sigma in checks:
        assert sigma > 0
        dev = (np.array([get(tr) for tr in cycles]) - np.asarray(get(base))).ravel()
        n = dev.size
        s2 = np.sum(dev**2)  # known mean 0: s2 / sigma^2 ~ chi2(n)
        assert chi2.ppf(0.0005, n) <= s2 / sigma**2 <= chi2.ppf(0.9995, n), (name, np.sqrt(s2 / n) / sigma)
        assert abs(dev.mean()) <= 3.29 * sigma / np.sqrt(n), name
    for tr in cycles[:5]:  # what a turn-on does not change
        assert tr.gyro.misalignment_rad == base.gyro.misalignment_rad
        assert tr.accel.misalignment_rad == base.accel.misalignment_rad
        assert tr.g_sensitivity == base.g_sensitivity and tr.gyro.noise == base.gyro.noise
        assert tr.accel.k2 == base.accel.k2 and tr.accel.kc == base.accel.kc
    drift = replace(base, gyro_bias_drift_per_day=1e-7)
    later = np.asarray(drift.for_power_cycle(2, 2026, days_since_first=7.0).gyro.bias)
    now = np.asarray(drift.for_power_cycle(2, 2026, days_since_first=0.0).gyro.bias)
    np.testing.assert_allclose(later - now, 7.0 * 1e-7, rtol=1e-9)


def test_written_archive(tmp_path):
    landing = tmp_path / "landing"
    spec = ArchiveSpec(devices=(("NAV-001", "navigation"), ("CON-003", "consumer")), power_cycles=2,
                       static_duration_s=30.0, tumble_duration_scale=0.1)
    paths = write_archive(landing, spec)
    assert sorted(paths) == discover_runs(landing)  # '_truth' is not taken for a device
    assert len(paths) == 2 * (2 * 2 + 2)
    kinds, devices = set(), set()
    allowed = {"manifest.json", "_COMPLETE", "imu.csv", "imu.parquet", "table.csv", "table.parquet"}
    for d in paths:
        assert d.parent.parent == landing
        names = {p.name for p in d.iterdir()}
        assert names <= allowed and {"manifest.json", "_COMPLETE"} <= names  # no truth inside run folders
        r = ingest_run(d)
        kinds.add(r.manifest.test_kind)
        devices.add(r.manifest.device.id)
        assert ("imu.csv" in names) == (r.manifest.device.grade == "consumer")
        cycle = int(d.name[2:4])
        assert r.manifest.power_cycle_index == cycle
        truth_file = landing / "_truth" / d.parent.name / f"{d.name}.json"
        truth = json.loads(truth_file.read_text())["truth"]
        expected = example_device(d.parent.name, r.manifest.device.grade, spec.seed).for_power_cycle(
            cycle, spec.seed, cycle * spec.days_between_cycles)
        np.testing.assert_array_equal(truth["gyro"]["bias"], expected.gyro.bias)
    assert kinds == {"rate", "multiposition", "static", "tumble"}
    assert devices == {"NAV-001", "CON-003"}
    truth_files = sorted((landing / "_truth").rglob("*.json"))
    assert len(truth_files) == len(paths)
    assert not any(p.name.endswith(".json") and p.name != "manifest.json" for d in paths for p in d.iterdir())


# ------------------------------------------------------------------------------------------------------------
# Truth files, effect chains and time since power-on (the digital twin)
# ------------------------------------------------------------------------------------------------------------
def test_truth_file_round_trips_truth_and_effect_chain(tmp_path):
    from assets_lib.sim.effects import EFFECTS, sensor_chain
    from assets_lib.sim.simulator import load_truth

    truth = example_device("TAC-8", "tactical", 4)
    chain = sensor_chain([EFFECTS["bias_step"](at_s=3.0, gyro_radps=(1e-4, 0, 0)), EFFECTS["latency"](gyro_s=1e-3),
                          EFFECTS["noise_model"](gyro_gm_sigma_radps=1e-5)])
    names = [e.name for e in chain]
    assert names.index("latency") < names.index("error_model") < names.index("bias_step") < names.index("allan_noise")
    assert names.index("allan_noise") < names.index("noise_model") < names.index("saturation")
    run = simulate_run(truth, build_plan("quick_rate", duration_scale=0.05), "r", test_kind="rate", effects=chain,
                       seed=8, power_on_s=60.0)
    write_run(run, tmp_path)
    tf = load_truth(tmp_path / "_truth" / "TAC-8" / "r.json")
    assert tf.truth == truth and tf.effects == chain and tf.power_on_s == 60.0 and tf.seed == 8
    assert tf.table_clock_offset_s == run.table_clock_offset_s
    # the default chain writes the truth file as before (no effect parameters, no power-on, no seed)
    plain = simulate_run(truth, build_plan("quick_rate", duration_scale=0.05), "p", test_kind="rate", seed=8)
    write_run(plain, tmp_path)
    doc = json.loads((tmp_path / "_truth" / "TAC-8" / "p.json").read_text())
    assert sorted(doc) == ["effects", "table_clock_offset_s", "truth"]
    doc["effects"].append("plateau_disturbance")
    (tmp_path / "bad.json").write_text(json.dumps(doc))
    with pytest.raises(ValueError, match="cannot be rebuilt"):
        load_truth(tmp_path / "bad.json")


def test_housing_temperature_continues_across_the_runs_of_a_power_cycle():
    truth = ideal_truth()
    plan = build_plan("static_long", static_duration_s=100.0)
    a = simulate_run(truth, plan, "a", test_kind="static", effects=IDEAL, table_log=False)
    b = simulate_run(truth, plan, "b", test_kind="static", effects=IDEAL, table_log=False, power_on_s=900.0)
    ta, tb = a.imu_raw["temperature"].to_numpy(), b.imu_raw["temperature"].to_numpy()
    # 25 + 1.5 (1 - exp(-t/900)): 25.0 at power-on, 25 + 1.5 (1 - 1/e) = 25.948 degC 900 s later (+-0.02 K noise)
    assert abs(ta[:100].mean() - 25.0) < 0.01 and abs(tb[:100].mean() - (25 + 1.5 * (1 - np.exp(-1)))) < 0.01
