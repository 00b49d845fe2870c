"""Allan-family deviations: agreement with allantools, NIST SP 1065 NBS14, Stable32 tables; precision; streaming."""

from __future__ import annotations

import gzip
import hashlib
from pathlib import Path

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from assets_lib.noise import allan as al
from assets_lib.noise import intervals as allan_ci

allantools = pytest.importorskip("allantools")

BACKENDS = ["numpy"] + (["numba"] if al.HAVE_NUMBA else [])
KIND_FUNCS = {
    "adev": "adev",
    "oadev": "oadev",
    "mdev": "mdev",
    "tdev": "tdev",
    "hdev": "hdev",
    "ohdev": "ohdev",
}


def _series(n, seed=1, offset=0.5):
    """White rate noise + rate random walk + offset (the benchmark series of benchmarks/bench_allan.py)."""
    rng = np.random.default_rng(seed)
    return offset + 0.1 * rng.standard_normal(n) + np.cumsum(1e-4 * np.sqrt(0.01) * rng.standard_normal(n))


# ---------------------------------------------------------------------------------------------------------------
# agreement with allantools on the same data and taus
# ---------------------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("backend", BACKENDS)
def test_oadev_matches_allantools_dense(backend):
    y = _series(300_000)
    m = al.averaging_factors(len(y), "dense")
    r = al.oadev(y, 100.0, m / 100.0, backend=backend, alpha=0)
    ref_tau, ref_dev, _, ref_n = allantools.oadev(y, rate=100.0, data_type="freq", taus=m / 100.0)
    assert np.array_equal(np.round(ref_tau * 100).astype(int), r.m)
    np.testing.assert_array_equal(r.n_terms, ref_n)
    np.testing.assert_allclose(r.adev, ref_dev, rtol=1e-12, atol=0)


@pytest.mark.parametrize("kind", list(KIND_FUNCS))
def test_every_kind_matches_allantools(kind):
    y = _series(50_000, seed=4)
    r = al.allan_deviation(y, 10.0, "octave", kind=kind, alpha=0)
    f = getattr(allantools, KIND_FUNCS[kind])
    ref_tau, ref_dev, _, ref_n = f(y, rate=10.0, data_type="freq", taus=r.tau_s)
    k = len(ref_tau)
    assert k >= len(r.m) - 2 and k > 10
    np.testing.assert_allclose(r.tau_s[:k], ref_tau)
    np.testing.assert_array_equal(r.n_terms[:k], ref_n)
    np.testing.assert_allclose(r.adev[:k], ref_dev, rtol=1e-12, atol=0)


def test_angle_input_equals_rate_input():
    """Phase-like input: the angle record theta[k] = sum y[:k+1] tau0 is the rate record y[1:]."""
    y = _series(100_000, seed=7)
    theta = np.cumsum(y) / 50.0 + 3.0
    ra = al.oadev(theta, 50.0, "dense", data_type="angle", alpha=0)
    rr = al.oadev(y[1:], 50.0, ra.tau_s, alpha=0)
    np.testing.assert_array_equal(ra.m, rr.m)
    np.testing.assert_allclose(ra.adev, rr.adev, rtol=1e-9)


# ---------------------------------------------------------------------------------------------------------------
# NIST SP 1065 NBS14 (pp. 107-108)
# ---------------------------------------------------------------------------------------------------------------
NBS14_10 = {  # tau = 1, 2
    "adev": (91.22945, 115.8082),
    "oadev": (91.22945, 85.95287),
    "mdev": (91.22945, 74.78849),
    "hdev": (70.80608, 116.7980),
    "tdev": (52.67135, 86.35831),
    "ohdev": (70.80607, 85.61487),
}
NBS14_1000 = {  # tau = 1, 10, 100
    "adev": (2.922319e-01, 9.965736e-02, 3.897804e-02),
    "oadev": (2.922319e-01, 9.159953e-02, 3.241343e-02),
    "mdev": (2.922319e-01, 6.172376e-02, 2.170921e-02),
    "hdev": (2.943883e-01, 1.052754e-01, 3.910860e-02),
    "tdev": (1.687202e-01, 3.563623e-01, 1.253382e00),
    "ohdev": (2.943883e-01, 9.581083e-02, 3.237638e-02),
}


def nbs14_1000() -> np.ndarray:
    n = [1234567890]
    for _ in range(999):
        n.append((16807 * n[-1]) % 2147483647)
    assert n[1:4] == [395529916, 1209410747, 633705974]
    return np.array(n, dtype=float) / 2147483647.0


@pytest.mark.parametrize("kind", list(NBS14_10))
def test_nbs14_10_point(kind):
    y = np.array([892, 809, 823, 798, 671, 644, 883, 903, 677], dtype=float)
    r = al.allan_deviation(y, 1.0, [1.0, 2.0], kind=kind, alpha=0)
    np.testing.assert_allclose(r.adev, NBS14_10[kind], rtol=1e-6)
    x = np.array([0.0, 103.11111, 123.22222, 157.33333, 166.44444, 48.55555, -96.33333, -2.22222, 111.88889, 0.0])
    rp = al.allan_deviation(x, 1.0, [1.0, 2.0], kind=kind, data_type="angle", alpha=0)
    np.testing.assert_allclose(rp.adev, NBS14_10[kind], rtol=1e-6)


@pytest.mark.parametrize("kind", list(NBS14_1000))
@pytest.mark.parametrize("backend", BACKENDS)
def test_nbs14_1000_point(kind, backend):
    y = nbs14_1000()
    r = al.allan_deviation(y, 1.0, [1.0, 10.0, 100.0], kind=kind, alpha=0, backend=backend)
    np.testing.assert_allclose(r.adev, NBS14_1000[kind], rtol=1e-6)


# ---------------------------------------------------------------------------------------------------------------
# Stable32 tables (../shared/data/allantools_testdata), checksums verified first
# ---------------------------------------------------------------------------------------------------------------
def _verified(shared_data: Path, rel: str) -> Path:
    root = shared_data / "allantools_testdata"
    src = (root / "SOURCE.txt").read_text()
    sums = {}
    for line in src.splitlines():
        parts = line.split()
        if len(parts) == 2 and len(parts[0]) == 64 and parts[1].startswith("./"):
            sums[parts[1][2:]] = parts[0]
    assert rel in sums, f"{rel} not listed in SOURCE.txt"
    p = root / rel
    assert hashlib.sha256(p.read_bytes()).hexdigest() == sums[rel], f"checksum mismatch for {rel}"
    return p


def _load_series(path: Path) -> np.ndarray:
    opener = gzip.open if path.suffix == ".gz" else open
    with opener(path, "rt") as fh:
        vals = [float(line.split()[0]) for line in fh if line.strip() and not line.lstrip().startswith("#")]
    return np.array(vals)


def _load_table(path: Path) -> pd.DataFrame:
    rows = []
    for line in path.read_text().splitlines():
        s = line.strip()
        if not s or s.startswith("#"):
            continue
        parts = s.split()
        if len(parts) >= 7:
            rows.append([float(v) for v in parts[:7]])
    return pd.DataFrame(rows, columns=["af", "tau", "n", "alpha", "min", "sigma", "max"])


STABLE32_CASES = [
    # (series, data_type, tau0, table, kind, rtol)
    ("phasedat/PHASE.DAT", "angle", 1.0, "phasedat/phase_dat_adev_octave.txt", "adev", 1e-4),
    ("phasedat/PHASE.DAT", "angle", 1.0, "phasedat/phase_dat_oadev_octave.txt", "oadev", 1e-4),
    ("phasedat/PHASE.DAT", "angle", 1.0, "phasedat/phase_dat_mdev_octave.txt", "mdev", 1e-4),
    ("phasedat/PHASE.DAT", "angle", 1.0, "phasedat/phase_dat_hdev_octave.txt", "hdev", 1e-4),
    ("phasedat/PHASE.DAT", "angle", 1.0, "phasedat/phase_dat_ohdev_octave.txt", "ohdev", 1e-4),
    ("phasedat/PHASE.DAT", "angle", 1.0, "phasedat/phase_dat_tdev_octave.txt", "tdev", 1e-4),
    ("phasedat/PHASE.DAT", "angle", 1.0, "phasedat/phase_dat_oadev.txt", "oadev", 1e-4),
    ("gps/gps_1pps_phase_data.txt.gz", "angle", 1.0, "gps/stable32_OADEV_octave.txt", "oadev", 1e-4),
    ("gps/gps_1pps_phase_data.txt.gz", "angle", 1.0, "gps/stable32_ADEV_decade.txt", "adev", 1e-4),
    ("gps/gps_1pps_phase_data.txt.gz", "angle", 1.0, "gps/stable32_MDEV_octave.txt", "mdev", 1e-4),
    ("gps/gps_1pps_phase_data.txt.gz", "angle", 1.0, "gps/stable32_HDEV_octave.txt", "hdev", 1e-4),
    ("gps/gps_1pps_phase_data.txt.gz", "angle", 1.0, "gps/stable32_OHDEV_octave.txt", "ohdev", 1e-4),
    ("gps/gps_1pps_phase_data.txt.gz", "angle", 1.0, "gps/stable32_TDEV_octave.txt", "tdev", 1e-4),
    ("Cs5071A/5071A_phase.txt.gz", "angle", 1.0, "Cs5071A/oadev_decade.txt", "oadev", 1e-4),
    ("Cs5071A/5071A_phase.txt.gz", "angle", 1.0, "Cs5071A/adev_decade.txt", "adev", 1e-4),
    ("Cs5071A/5071A_phase.txt.gz", "angle", 1.0, "Cs5071A/mdev_decade.txt", "mdev", 1e-4),
    ("Cs5071A/5071A_phase.txt.gz", "angle", 1.0, "Cs5071A/hdev_decade.txt", "hdev", 1e-4),
    ("Cs5071A/5071A_phase.txt.gz", "angle", 1.0, "Cs5071A/ohdev_decade.txt", "ohdev", 1e-4),
    ("Keysight53230A_ti_noise_floor/tic_phase.txt", "angle", 1.0, "Keysight53230A_ti_noise_floor/tic_oadev.txt", "oadev", 1e-4),
    ("Keysight53230A_ti_noise_floor/tic_phase.txt", "angle", 1.0, "Keysight53230A_ti_noise_floor/tic_mdev.txt", "mdev", 1e-4),
    ("Keysight53230A_ti_noise_floor/tic_phase.txt", "angle", 1.0, "Keysight53230A_ti_noise_floor/tic_ohdev.txt", "ohdev", 1e-4),
    ("ocxo/ocxo_frequency.txt", "ocxo", 1.0, "ocxo/oadev_octave.txt", "oadev", 2e-3),
    ("pink_frequency/pink_frequency.txt", "rate", 42.0, "pink_frequency/adev.txt", "adev", 1e-4),
    ("pink_frequency/pink_frequency.txt", "rate", 42.0, "pink_frequency/oadev.txt", "oadev", 1e-4),
    ("pink_frequency/pink_frequency.txt", "rate", 42.0, "pink_frequency/mdev.txt", "mdev", 1e-4),
    ("pink_frequency/pink_frequency.txt", "rate", 42.0, "pink_frequency/hdev.txt", "hdev", 1e-4),
]

_SERIES_CACHE: dict[str, np.ndarray] = {}


def _series_for(shared_data, rel, data_type):
    if rel not in _SERIES_CACHE:
        x = _load_series(_verified(shared_data, rel))
        if data_type == "ocxo":
            x = (x - 1e7) / 1e7  # absolute frequency in Hz -> fractional frequency
        _SERIES_CACHE[rel] = x
    return _SERIES_CACHE[rel]


@pytest.mark.shared_data
@pytest.mark.parametrize("series,data_type,tau0,table,kind,rtol", STABLE32_CASES, ids=[c[3] for c in STABLE32_CASES])
def test_stable32_tables(shared_data, series, data_type, tau0, table, kind, rtol):
    x = _series_for(shared_data, series, data_type)
    t = _load_table(_verified(shared_data, table))
    dt = "rate" if data_type in ("rate", "ocxo") else "angle"
    r = al.allan_deviation(x, 1.0 / tau0, t["af"].to_numpy() * tau0, kind=kind, data_type=dt, alpha=0)
    assert len(r.m) == len(t), "every tabulated averaging factor is computed"
    np.testing.assert_array_equal(r.m, t["af"].astype(int))
    np.testing.assert_array_equal(r.n_terms, t["n"].astype(int))
    np.testing.assert_allclose(r.adev, t["sigma"], rtol=rtol)


CI_CASES = [
    ("phasedat/PHASE.DAT", "phasedat/phase_dat_adev_octave.txt", "adev"),
    ("phasedat/PHASE.DAT", "phasedat/phase_dat_oadev_octave.txt", "oadev"),
    ("phasedat/PHASE.DAT", "phasedat/phase_dat_mdev_octave.txt", "mdev"),
    ("phasedat/PHASE.DAT", "phasedat/phase_dat_hdev_octave.txt", "hdev"),
    ("phasedat/PHASE.DAT", "phasedat/phase_dat_ohdev_octave.txt", "ohdev"),
    ("phasedat/PHASE.DAT", "phasedat/phase_dat_tdev_octave.txt", "tdev"),
    ("gps/gps_1pps_phase_data.txt.gz", "gps/stable32_OADEV_octave.txt", "oadev"),
    ("gps/gps_1pps_phase_data.txt.gz", "gps/stable32_MDEV_octave.txt", "mdev"),
    ("gps/gps_1pps_phase_data.txt.gz", "gps/stable32_OHDEV_octave.txt", "ohdev"),
    ("gps/gps_1pps_phase_data.txt.gz", "gps/stable32_ADEV_decade.txt", "adev"),
]


@pytest.mark.shared_data
@pytest.mark.parametrize("series,table,kind", CI_CASES, ids=[c[1] for c in CI_CASES])
def test_intervals_match_stable32_min_max(shared_data, series, table, kind):
    """Greenhall EDF + chi-square at Stable32's alpha reproduce MinSigma / MaxSigma (68.3 %)."""
    x = _series_for(shared_data, series, "angle")
    t = _load_table(_verified(shared_data, table))
    t = t[(t["min"] > 0) & (t["max"] > 0)]
    assert len(t) >= 5
    r = al.allan_deviation(x, 1.0, t["af"].to_numpy(), kind=kind, data_type="angle", alpha=t["alpha"].to_numpy())
    # Stable32 prints 5 digits; allantools' own suite reaches 1e-3 on these bounds
    np.testing.assert_allclose(r.ci_lo, t["min"], rtol=1e-3)
    np.testing.assert_allclose(r.ci_hi, t["max"], rtol=1e-3)


# ---------------------------------------------------------------------------------------------------------------
# EDF against allantools' Greenhall implementation
# ---------------------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("kind", ["adev", "oadev", "mdev", "hdev", "ohdev"])
def test_edf_matches_allantools_greenhall(kind):
    d, overlapping, modified = allan_ci.KIND_EDF_ARGS[kind]
    n_phase = 10_001
    checked = 0
    for alpha in range(2 - 2 * d + 1 if d == 2 else -4, 3):
        if alpha + 2 * d <= 1:
            continue
        for m in (1, 2, 3, 8, 30, 100, 333, 1000, 3000):
            try:
                ref = allantools.edf_greenhall(alpha, d, m, n_phase, overlapping=overlapping, modified=modified)
            except (NotImplementedError, AssertionError):
                continue
            ours = allan_ci.edf_greenhall(alpha, d, m, n_phase, overlapping, modified)
            np.testing.assert_allclose(ours, ref, rtol=1e-12)
            checked += 1
    assert checked > 20


def test_chi2_interval_contains_estimate_and_narrows():
    dev = np.ones(3)
    lo, hi = allan_ci.chi2_interval(dev, np.array([5.0, 50.0, 5000.0]), 0.95)
    assert np.all(lo < 1) and np.all(hi > 1)
    assert np.all(np.diff(hi - lo) < 0)


@pytest.mark.slow
def test_interval_coverage_white_noise():
    """Per-tau 68.3 % intervals cover the true ADEV of white rate noise about 68 % of the time."""
    rng = np.random.default_rng(42)
    sigma, n, trials = 0.3, 2000, 300
    m = np.array([1, 4, 16, 64, 256])
    hits = np.zeros(len(m))
    for _ in range(trials):
        r = al.oadev(sigma * rng.standard_normal(n), 1.0, m.astype(float), alpha=0)
        true = sigma / np.sqrt(m)
        hits += (r.ci_lo <= true) & (true <= r.ci_hi)
    cov = hits / trials
    # binomial sd at p = 0.683, 300 trials: 0.027; 4 sd either side
    assert np.all(np.abs(cov - allan_ci.ONE_SIGMA_CI) < 0.11), cov


# ---------------------------------------------------------------------------------------------------------------
# noise identification
# ---------------------------------------------------------------------------------------------------------------
def test_acf_noise_id_pure_noises():
    rng = np.random.default_rng(3)
    n = 200_000
    white = rng.standard_normal(n)
    rw = np.cumsum(rng.standard_normal(n))
    f = np.fft.rfftfreq(n)
    spec = (rng.standard_normal(len(f)) + 1j * rng.standard_normal(len(f))) / np.sqrt(np.maximum(f, f[1]))
    spec[0] = 0
    flicker = np.fft.irfft(spec, n)
    for y, want in ((white, 0), (flicker, -1), (rw, -2)):
        r = al.oadev(y, 1.0, "octave")
        a = r.alpha[r.m <= 400]  # at least 500 averages per tau
        # a statistical identifier (Riley & Greenhall 2004): mostly exact, never off by more than one
        assert np.mean(a == want) >= 0.85, (want, a)
        assert np.all(np.abs(a - want) <= 1), (want, a)


# ---------------------------------------------------------------------------------------------------------------
# precision: float32 input, gravity offset (float64 accumulation, [NIST1065] eq. 4)
# ---------------------------------------------------------------------------------------------------------------
def test_float32_gravity_axis_matches_float64():
    n = 10_000_000
    rng = np.random.default_rng(9)
    acc32 = (9.8 + 2e-3 * rng.standard_normal(n, dtype=np.float32)
             + np.cumsum(1e-6 * rng.standard_normal(n, dtype=np.float32), dtype=np.float32)).astype(np.float32)
    r32 = al.oadev(acc32, 100.0, "octave", alpha=0)
    r64 = al.oadev(acc32.astype(np.float64), 100.0, "octave", alpha=0)
    assert np.max(np.abs(r32.adev / r64.adev - 1.0)) <= 1e-9
    # the hazard this guards against: a float32 cumulative sum without mean removal is wrong by > 1 %
    x_naive = np.concatenate([[0.0], np.cumsum(acc32)]).astype(np.float64)
    naive = np.sqrt(np.mean((x_naive[2:] - 2 * x_naive[1:-1] + x_naive[:-2]) ** 2) / 2.0)
    assert abs(naive / r64.adev[0] - 1.0) > 1e-2


def test_float64_no_mean_bias_with_large_offset():
    y = _series(400_000, seed=5, offset=0.0)
    r0 = al.oadev(y, 100.0, "octave", alpha=0)
    r1 = al.oadev(y + 9.80665, 100.0, "octave", alpha=0)
    np.testing.assert_allclose(r1.adev, r0.adev, rtol=1e-10)


# ---------------------------------------------------------------------------------------------------------------
# streaming == in memory; several channels
# ---------------------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("data_type", ["rate", "angle"])
def test_streaming_parquet_identical_to_in_memory(tmp_path, monkeypatch, backend, data_type):
    monkeypatch.setattr(al.streaming, "SMALL_SPAN", 1 << 18)  # force the cursor route for the larger taus
    n = 1_200_000  # two streaming blocks
    y = _series(n, seed=11)
    if data_type == "angle":
        y = np.cumsum(y) / 100.0
    t = pa.table({"time_s": np.arange(n) / 100.0, "gyro_x": y, "gyro_y": y.astype(np.float32)})
    path = tmp_path / "imu.parquet"
    pq.write_table(t, path, row_group_size=150_000)
    out = al.allan_parquet(path, 100.0, ["gyro_x", "gyro_y"], 40, data_type=data_type, backend=backend)
    mem = al.oadev(y, 100.0, 40, data_type=data_type, backend=backend)
    mem32 = al.oadev(y.astype(np.float32), 100.0, 40, data_type=data_type, backend=backend)
    assert np.any(2 * mem.m > al.streaming.SMALL_SPAN) and np.any(2 * mem.m <= al.streaming.SMALL_SPAN)
    np.testing.assert_array_equal(out["gyro_x"].adev, mem.adev)
    np.testing.assert_array_equal(out["gyro_x"].edf, mem.edf)
    np.testing.assert_array_equal(out["gyro_y"].adev, mem32.adev)


def test_stream_engine_on_array_identical(monkeypatch):
    monkeypatch.setattr(al.streaming, "SMALL_SPAN", 1 << 12)
    y = _series(1_300_000, seed=2)
    a = al.allan_stream_array(y, 10.0, "octave")
    b = al.oadev(y, 10.0, "octave")
    np.testing.assert_array_equal(a.adev, b.adev)
    np.testing.assert_array_equal(a.alpha, b.alpha)


@pytest.mark.skipif(not al.HAVE_NUMBA, reason="numba not installed: one backend only")
@pytest.mark.parametrize("n", [1, 7, 8, 9, 127, 128, 129, 1000, 4099, al.KERNEL_BLOCK])
def test_kernel_block_sums_are_numpy_pairwise_bit_for_bit(n):
    """The numba block sum reproduces np.add.reduce of the squared second differences term by term."""
    rng = np.random.default_rng(n)
    x = np.cumsum(rng.standard_normal(n + 4)) * 1e-3
    x0, x1, x2 = x[:n], x[2 : n + 2], x[4 : n + 4]
    d = (x2 - x1) - (x1 - x0)
    ref = float(np.add.reduce(d * d))
    assert al.kernels._NumbaKernel().block(x0, x1, x2) == ref
    assert al.kernels._NumpyKernel().block(x0, x1, x2) == ref
    y = rng.standard_normal(3 * al.SUM_BLOCK + n)
    t = 0.0
    for a in range(0, len(y), al.SUM_BLOCK):
        t += float(np.add.reduce(y[a : a + al.SUM_BLOCK]))
    assert al.kernels.block_sum(y) == t


@pytest.mark.skipif(not al.HAVE_NUMBA, reason="numba not installed: one backend only")
def test_backends_give_identical_stored_tables():
    """Issue 10 item 4: what the pipeline stores (Allan table and IEEE 952 noise table, intervals included) does
    not depend on whether the optional numba kernel is installed: both kernels give the same bits."""
    from assets_lib.noise import identification as ni

    rng = np.random.default_rng(10)
    n = 360_000  # one hour at 100 Hz, white + flicker-like + random walk on six channels
    data = {f"{s}_{a}": 1e-3 * rng.standard_normal(n) + np.cumsum(2e-6 * rng.standard_normal(n)) + 0.01 * k
            for k, (s, a) in enumerate((s, a) for s in ("gyro", "accel") for a in "xyz")}
    tables = {}
    for backend in ("numpy", "numba"):
        res = al.allan_deviations(pd.DataFrame(data), 100.0, "octave", ci_level=0.95, backend=backend)
        allan = pd.concat([r.to_frame() for r in res.values()], ignore_index=True)
        tables[backend] = (allan, ni.noise_table(ni.fit_all(res)))
    pd.testing.assert_frame_equal(tables["numpy"][0], tables["numba"][0], check_exact=True)
    pd.testing.assert_frame_equal(tables["numpy"][1], tables["numba"][1], check_exact=True)
    y = _series(500_000, seed=8)  # dense grid: the chain partition (m >= M_CHAIN) too, and the streaming route
    a = al.oadev(y, 100.0, "dense", backend="numpy")
    b = al.oadev(y, 100.0, "dense", backend="numba")
    c = al.allan_stream_array(y, 100.0, "dense", backend="numba")
    assert np.any(a.m >= al.M_CHAIN)
    for f in ("adev", "ci_lo", "ci_hi", "edf", "alpha"):
        np.testing.assert_array_equal(getattr(a, f), getattr(b, f))
        np.testing.assert_array_equal(getattr(a, f), getattr(c, f))


def test_six_channels_equal_single_calls():
    rng = np.random.default_rng(4)
    data = rng.standard_normal((100_000, 6)) + np.array([0.1, -0.2, 0.3, 0.0, 0.0, 9.81])
    names = [f"{s}_{a}" for s in ("gyro", "accel") for a in "xyz"]
    res = al.allan_deviations(data, 100.0, "octave", channels=names)
    assert list(res) == names
    for k, nm in enumerate(names):
        single = al.oadev(np.ascontiguousarray(data[:, k]), 100.0, "octave")
        np.testing.assert_array_equal(res[nm].adev, single.adev)
    tab = al.allan_table(res, 100.0)
    assert set(tab["channel"]) == set(names)
    assert {"channel", "tau_s", "adev", "ci_lo", "ci_hi", "edf", "n_terms"} <= set(tab.columns)
    assert np.all(tab["ci_lo"] < tab["adev"]) and np.all(tab["adev"] < tab["ci_hi"])


# ---------------------------------------------------------------------------------------------------------------
# tau grids and input checks
# ---------------------------------------------------------------------------------------------------------------
def test_tau_grids():
    n = 1_000_000
    octave = al.averaging_factors(n, "octave")
    assert octave[0] == 1 and np.all(octave[1:] == 2 * octave[:-1]) and n + 1 - 2 * octave[-1] >= 2
    decade = al.averaging_factors(n, "decade")
    assert list(decade[:6]) == [1, 2, 4, 10, 20, 40]
    dense = al.averaging_factors(n, "dense")
    assert len(dense) == 100 and len(np.unique(dense)) == 100 and dense.max() <= (n - 1) // 2
    assert len(al.averaging_factors(n, 37)) == 37
    with pytest.raises(ValueError):
        al.averaging_factors(n, "weekly")


def test_rejects_gaps_and_bad_input():
    y = _series(1000)
    y[500] = np.nan
    with pytest.raises(ValueError, match="non-finite"):
        al.oadev(y, 1.0)
    with pytest.raises(ValueError):
        al.oadev(np.ones((10, 2)), 1.0)
    with pytest.raises(ValueError):
        al.allan_deviation(_series(100), 1.0, kind="totdev")
