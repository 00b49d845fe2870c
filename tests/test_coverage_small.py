"""A small version of the coverage benchmark (benchmarks/mc_calibration_coverage.py, issue 15).

Three simulated devices through simulate -> ingest -> segment -> the stages' fits: every interval-bearing family
is scored, z-scores are of unit order, and the trial-clustered standard errors are right on cases with a known
answer. The coverage targets themselves need >= 2,000 trials (the benchmark), not a unit test.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "benchmarks"))

import mc_calibration_coverage as mc

FAMILIES = {
    "accel:accel:bias", "accel:accel:scale_factor", "accel:accel:misalignment", "accel:accel:k2",
    "accel:accel:cross_coupling", "gyro:rate:bias", "gyro:rate:scale_factor", "gyro:rate:misalignment",
    "gyro:rate:scale_factor_pos", "gyro:rate:scale_factor_neg", "gyro:rate:sf_asymmetry",
    "gyro:rate:sf_nonlinearity_below_floor", "gyro:static:bias", "gyro:static:g_sensitivity",
    "gyro:difference:scale_factor", "gyro:difference:misalignment", "gyro:means:scale_factor",
    "gyro:means:scale_factor_pos", "gyro:means:scale_factor_neg", "gyro:means:asymmetry",
    "gyro:means:nonlinearity_below_floor", "accel:tablefree:bias", "accel:tablefree:scale_factor",
    "accel:tablefree:misalignment", "gyro:tablefree:scale_factor", "gyro:tablefree:misalignment",
}


def test_clustered_standard_errors_known_cases():
    # 40 trials of 5 estimates each; within a trial all covered or none: the clustered SE is the SE of 40 trials
    cov = np.repeat(np.r_[np.ones(30), np.zeros(10)].astype(bool), 5)
    d = pd.DataFrame({"trial": np.repeat(np.arange(40), 5), "covered": cov, "z": np.repeat(np.linspace(-1, 1, 40), 5)})
    r = mc.clustered(d)
    assert r["coverage"] == pytest.approx(0.75)
    assert r["coverage_se"] == pytest.approx(np.sqrt(0.75 * 0.25 / 39), rel=1e-9)
    z_t = np.linspace(-1, 1, 40)
    assert r["mean_z_se"] == pytest.approx(np.std(z_t, ddof=1) / np.sqrt(40), rel=1e-9)
    # independent estimates, one per trial: the usual binomial SE (times sqrt(T / (T - 1)))
    rng = np.random.default_rng(3)
    z = rng.standard_normal(4000)
    d = pd.DataFrame({"trial": np.arange(4000), "covered": np.abs(z) < 1.96, "z": z})
    r = mc.clustered(d)
    assert r["coverage_se"] == pytest.approx(np.sqrt(r["coverage"] * (1 - r["coverage"]) / 4000), rel=1e-3)
    assert r["sd_z"] == pytest.approx(np.std(z, ddof=1), rel=1e-9)
    assert r["sd_z_se"] == pytest.approx(1 / np.sqrt(2 * 4000), rel=0.1)


def test_simulated_flicker_wanders_by_the_allan_floor():
    """The fits' bias uncertainty counts the run mean's 1/f wander at the Allan floor (2 ln2 / pi) B^2; the
    simulator must produce it (a zero-mean FFT block as long as the run made it zero: biases over-covered)."""
    from assets_lib.sim.noise import flicker_noise

    rng = np.random.default_rng(15)
    floor = 2 * np.log(2) / np.pi
    for n in (2048, 3001):
        x = np.array([flicker_noise(n, 100.0, 1.0, rng) for _ in range(800)])
        assert 0.8 < np.var(x.mean(axis=1)) / floor < 1.25
        h = n // 2
        assert 0.85 < np.var(x[:, :h].mean(axis=1) - x[:, h:2 * h].mean(axis=1)) / (2 * floor) < 1.15


@pytest.mark.slow
def test_small_benchmark_scores_every_family(tmp_path):
    out = tmp_path / "cov"
    rc = mc.main(["--seed", "915", "--trials", "3", "--plans", "quick", "--out", str(out), "--records",
                  "--noise-every", "0"])  # the noise hook's own test is below
    assert rc in (0, 1)  # 1: targets not met, expected with three trials
    doc = json.loads(out.with_suffix(".json").read_text())
    fams = {r["family"] for r in doc["family"]}
    assert FAMILIES <= fams, FAMILIES - fams
    assert {r["grade"] for r in doc["grade"]} == set(mc.GRADES) | {"ungraded"}  # ungraded: table-free sessions
    recs = pd.read_csv(out.with_suffix(".records.csv"))
    z = recs["z"].dropna().to_numpy()
    assert len(z) > 150
    # intervals of the right order: pooled z of unit scale, no estimate absurdly far from its truth
    assert abs(z.mean()) < 0.4
    assert 0.6 < z.std(ddof=1) < 1.6
    assert np.max(np.abs(z)) < 8
    assert 0.8 < recs["covered"].mean() <= 1.0
    text = out.with_suffix(".md").read_text()
    assert "--seed 915 --trials 3" in text
    # the seeds and the other schedules: a 6-position run and the seed 003 rate sequence (dwell scaled)
    r = pd.DataFrame(mc.trial((915, 3, False, 0)))
    assert set(r["rate_plan"]) == {"seed003_rate_sequence"} and set(r["pos_plan"]) == {"six_position", mc.TUMBLE_PLAN}
    # every trial scores the tumble fit, here on a tumble run of its own (its rows and its gate under that plan)
    tu = r[r["fit"] == "tumble"]
    assert len(tu) and set(tu["pos_plan"]) == {mc.TUMBLE_PLAN} and set(tu["axis"]) == {"x", "z"}
    assert set(r.loc[r["coefficient"] == "tumble_run_passed", "pos_plan"]) == {mc.TUMBLE_PLAN}
    rest = r[(r["fit"] != "tumble") & (r["coefficient"] != "tumble_run_passed")]
    assert set(rest["pos_plan"]) == {"six_position"}
    assert {"accel:accel:bias", "accel:accel:scale_factor", "gyro:rate:sf_asymmetry"} <= set(mc.family(r))
    # injected scale-factor nonlinearity (trial 12: plan-cycle 2): scored away from zero against the noise-free
    # statistic; the rate run's other rows (their truth absorbs the curve) are not scored in that trial
    r = pd.DataFrame(mc.trial((915, 12, True, 0)))
    nl = r[mc.family(r) == "gyro:means:nonlinearity"]
    assert len(nl) == 3 and r["nonlinearity_injected"].all()
    assert (nl["truth"] > 0).all() and (nl["z"].abs() < 6).all()
    assert not (r["fit"].isin(["rate", "difference"]) | (mc.family(r) == "gyro:means:scale_factor")).any()


@pytest.mark.slow
def test_noise_hook_rows_join_the_trial(monkeypatch):
    """The noise scoring hook of benchmarks/coverage_noise.py, ``score_noise(noise_trial(seed, k, grade=...))``,
    runs on the trials ``noise_every`` selects, and its rows (family, channel, estimate, truth, z, covered) become
    this benchmark's rows with the trial's labels. The interface is the module's own (stand-in: the real module
    lives with the noise work and needs its stages)."""
    import types

    calls = []

    def noise_trial(seed, k, grade=None):
        calls.append((seed, k, grade))
        return {"seed": seed, "trial": k, "grade": grade}

    def score_noise(o):
        return [{"family": "gyro:N", "channel": "gyro_x_radps", "estimate": 1.1, "truth": 1.0, "z": 0.5,
                 "covered": True, "plan": "device", "run": "long", "trial": o["trial"]},
                {"family": "accel:K:bound", "channel": "accel_y_mps2", "estimate": np.nan, "truth": 2.0,
                 "z": np.nan, "covered": True, "plan": "device", "run": "long", "trial": o["trial"]}]

    monkeypatch.setitem(sys.modules, "coverage_noise", types.SimpleNamespace(noise_trial=noise_trial,
                                                                             score_noise=score_noise))
    r = pd.DataFrame(mc.trial((916, 0, True, 2)))
    assert calls == [(916, 0, mc.GRADES[0])]
    rows = r[r["fit"] == "noise"]
    assert set(mc.family(rows)) == {"gyro:noise:N", "accel:noise:K_bound"}
    assert (rows["grade"] == mc.GRADES[0]).all() and (rows["trial"] == 0).all()
    assert mc.noise_rows({"trial": 1, "grade": "tactical"}, 916, 1)[0]["z"] == 0.5
    tabs = mc.summarize(r)
    assert "gyro:noise:N" in set(tabs["family"]["family"])


@pytest.mark.slow
def test_a_static_record_reaches_the_stage_fits_and_the_means_rows():
    """--static-s: the trial's navigation device gets a 20-min static record; its gyro B is only an upper bound there,
    which the `imulab fit` rows pass as a lab would (`--flicker-b-ci 0 BOUND` = flicker_b_max) and the stage fits take
    as a bound truncating the run's own B; its accelerometer B is two-sided."""
    from assets_lib.sim.simulator import example_device

    prior = mc.static_prior(example_device("MC917-00000", "navigation", seed=917), 917, 0, 1200.0)
    g, a = prior.get("gyro_x_radps"), prior.get("accel_x_mps2")
    assert g.is_upper_bound and not a.is_upper_bound
    assert set(mc.flicker_options(None, "gyro_x_radps", prior)) == {"flicker_b_max"}
    assert set(mc.flicker_options(None, "accel_x_mps2", prior)) == {"flicker_b", "flicker_b_dof"}
    r = pd.DataFrame(mc.trial((917, 0, True, 0, {"navigation": 1200.0})))
    r = r[r["grade"] != "ungraded"]  # the table-free session's device is not graded
    assert len(r) and (r["grade"] == "navigation").all()
    fams = set(mc.family(r))
    assert {"gyro:rate:bias", "gyro:static:bias", "gyro:means:asymmetry"} <= fams
    z = r["z"].dropna()
    assert len(z) > 50 and np.max(np.abs(z)) < 8
