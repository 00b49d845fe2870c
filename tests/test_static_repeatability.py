"""Turn-on bias repeatability over power-cycled static runs (seed 000), end to end through imulab import."""

from __future__ import annotations

import json

import numpy as np
import pandas as pd
import pytest
from click.testing import CliRunner
from scipy import stats

from assets_lib.calibration.repeatability import static_repeatability, static_run_terms
from assets_lib.sim.noise import AllanParams, allan_noise
from imulab.cli import main

SIGMA_TURN_ON = 1e-3  # rad/s


def _runs(n_runs=8, minutes=10, fs=100.0, seed=0):
    rng = np.random.default_rng(seed)
    biases = SIGMA_TURN_ON * rng.standard_normal(n_runs)
    n = int(minutes * 60 * fs)
    out = []
    for i in range(n_runs):
        g = biases[i] + allan_noise(n, fs, AllanParams(n=1e-3, b=2e-5), rng)
        out.append((i, g))
    return biases, out


def test_static_repeatability_recovers_turn_on_spread():
    biases, runs = _runs()
    frames = [static_run_terms(f"r{i}", i, {"gyro_x": g}, 100.0, {"gyro_x": "rad/s"}) for i, g in runs]
    table = static_repeatability(pd.concat(frames)).set_index("quantity")
    row = table.loc["bias_repeatability"]
    assert row["n_runs"] == 8
    means = np.array([g.mean() for _, g in runs])
    # the estimate is the spread of the run means, and it differs from the true turn-on spread by no more than the
    # spread of the per-run errors (Minkowski: |sd(a) - sd(b)| <= sd(a - b)), which is a few % here
    assert row["value"] == pytest.approx(np.std(means, ddof=1), rel=1e-9)
    assert abs(row["value"] - np.std(biases, ddof=1)) <= np.std(means - biases, ddof=1) < 0.1 * SIGMA_TURN_ON
    assert row["ci_low"] <= SIGMA_TURN_ON <= row["ci_high"]
    # N is the same device noise in every run: its run-to-run spread is only estimation noise (a few %)
    assert table.loc["N_repeatability", "value"] < 0.05
    # and the per-run standard errors explain that spread (chi-square consistency at 99 %)
    per = pd.concat(frames)
    chi2 = float(np.sum(((per["N"] - per["N"].mean()) / per["N_stderr"]) ** 2))
    assert chi2 < stats.chi2.ppf(0.999, len(per) - 1)


def test_cli_repeatability_on_imported_runs(tmp_path):
    biases, runs = _runs(n_runs=5, minutes=5, seed=3)
    prof = {"time": {"rate_hz": 100.0},
            "channels": {**{f"gyro_{a}": {"column": f"g{a}", "unit": "rad/s"} for a in "xyz"},
                         **{f"accel_{a}": {"column": f"a{a}", "unit": "m/s^2"} for a in "xyz"}}}
    (tmp_path / "p.json").write_text(json.dumps(prof))
    rng = np.random.default_rng(9)
    for i, g in runs:
        n = g.size
        df = pd.DataFrame({"gx": g, "gy": 1e-3 * rng.standard_normal(n), "gz": 1e-3 * rng.standard_normal(n),
                           "ax": 0.01 * rng.standard_normal(n), "ay": 0.01 * rng.standard_normal(n),
                           "az": 9.81 + 0.01 * rng.standard_normal(n)})
        src = tmp_path / f"run{i}.csv"
        df.to_csv(src, index=False)
        r = CliRunner().invoke(main, ["import", "profile", str(src), "--landing", str(tmp_path / "land"),
                                      "--device-id", "D1", "--run-id", f"pc{i}", "--power-cycle-index", str(i),
                                      "-o", f"profile={tmp_path / 'p.json'}"])
        assert r.exit_code == 0, r.output
    out = tmp_path / "rep.csv"
    r = CliRunner().invoke(main, ["repeatability", str(tmp_path / "land"), "--csv", str(out)])
    assert r.exit_code == 0, r.output
    t = pd.read_csv(out).set_index(["channel", "quantity"])
    assert t.loc[("gyro_x_radps", "bias_repeatability"), "value"] == pytest.approx(np.std(biases, ddof=1), rel=0.05)
    assert t.loc[("gyro_y_radps", "bias_repeatability"), "value"] < 2e-4


def test_cli_repeatability_needs_two_runs(tmp_path):
    r = CliRunner().invoke(main, ["repeatability", str(tmp_path)])
    assert r.exit_code != 0 and "at least two" in r.output


@pytest.mark.slow
def test_pipeline_repeatability_stage_on_static_runs(tmp_path, monkeypatch):
    """imulab import (x4 power cycles) && imulab run: the repeatability stage writes static_repeatability."""
    monkeypatch.delenv("DAGSTER_HOME", raising=False)
    biases, runs = _runs(n_runs=4, minutes=3, seed=7)
    prof = {"time": {"rate_hz": 100.0},
            "channels": {**{f"gyro_{a}": {"column": f"g{a}", "unit": "rad/s"} for a in "xyz"},
                         **{f"accel_{a}": {"column": f"a{a}", "unit": "m/s^2"} for a in "xyz"}}}
    (tmp_path / "p.json").write_text(json.dumps(prof))
    rng = np.random.default_rng(2)
    for i, g in runs:
        n = g.size
        pd.DataFrame({"gx": g, "gy": 1e-3 * rng.standard_normal(n), "gz": 1e-3 * rng.standard_normal(n),
                      "ax": 0.01 * rng.standard_normal(n), "ay": 0.01 * rng.standard_normal(n),
                      "az": 9.81 + 0.01 * rng.standard_normal(n)}).to_csv(tmp_path / f"run{i}.csv", index=False)
        r = CliRunner().invoke(main, ["import", "profile", str(tmp_path / f"run{i}.csv"), "--landing", str(tmp_path / "land"),
                                      "--device-id", "D1", "--run-id", f"pc{i}", "--power-cycle-index", str(i),
                                      "--start-time-utc", f"2026-01-0{i + 1}T08:00:00Z", "-o", f"profile={tmp_path / 'p.json'}"])
        assert r.exit_code == 0, r.output
    r = CliRunner().invoke(main, ["run", "--archive", str(tmp_path / "land"), "--data-dir", str(tmp_path / "data")])
    assert r.exit_code == 0, r.output
    files = list((tmp_path / "data" / "store" / "repeatability" / "D1").glob("*/static_repeatability.parquet"))
    assert len(files) == 1
    t = pd.read_parquet(files[0]).set_index(["channel", "quantity"])
    assert t.loc[("gyro_x_radps", "bias_repeatability"), "n_runs"] == 4
    assert t.loc[("gyro_x_radps", "bias_repeatability"), "value"] == pytest.approx(np.std(biases, ddof=1), rel=0.1)


def _model_curve(tau, q2, n2, fl, k2, r2):
    return 3 * q2 / tau**2 + n2 / tau + fl + k2 * tau / 3 + r2 * tau**2 / 2


def test_pooled_curve_fit_selects_the_flicker_floor_and_predicts_the_avar_at_the_record_length():
    """fit_pooled_curves on noise-free model curves of three records: a resolved floor is selected and exact, an
    unresolved one is dropped unless kept (keep_flicker), and the unconstrained fit reproduces the curve too."""
    from assets_lib.noise.pooled import fit_pooled_curves

    tau = 0.01 * 2.0 ** np.arange(14)  # octave taus up to ~82 s
    edf = 2e4 / (tau / 0.01)
    theta = (0.0, 1e-8, 4e-10, 0.0, 0.0)  # white + a resolved flicker floor
    fit = fit_pooled_curves([tau] * 3, [_model_curve(tau, *theta)] * 3, [edf] * 3)
    assert fit.selected == (True, False, False) and fit.n_records == 3
    assert fit.theta[1] == pytest.approx(theta[1], rel=1e-6) and fit.theta[2] == pytest.approx(theta[2], rel=1e-6)
    avar, dof = fit.avar_dof(np.array([200.0]))
    assert avar[0] == pytest.approx(_model_curve(200.0, *theta), rel=1e-6)
    assert 1.0 < dof[0] < np.inf
    weak = (0.0, 1e-8, 4e-11, 0.0, 0.0)  # a floor 1/3 of the white AVAR at the longest tau: not selected
    curves = ([tau] * 3, [_model_curve(tau, *weak)] * 3, [edf] * 3)
    assert not fit_pooled_curves(*curves).selected[0] and fit_pooled_curves(*curves).theta[2] == 0.0
    for kw in ({"keep_flicker": True}, {"keep_flicker": True, "nonnegative": False}):
        assert fit_pooled_curves(*curves, **kw).theta[2] == pytest.approx(weak[2], rel=1e-6)
    # a rate ramp is its own column, not a random walk, and the bias standard error leaves it out
    ramp = (0.0, 1e-8, 4e-10, 0.0, 1e-12)
    fr = fit_pooled_curves([tau] * 3, [_model_curve(tau, *ramp)] * 3, [100 * edf] * 3)  # e.g. a longer record
    assert fr.selected == (True, False, True) and fr.theta[3] == 0.0
    assert fr.avar_dof(np.array([200.0]), terms=(0, 1, 2, 3))[0][0] == pytest.approx(1e-8 / 200 + 4e-10, rel=1e-4)


def test_pooled_bias_stderrs_replace_the_per_run_model_and_give_mean_se2_the_shared_dof():
    from assets_lib.calibration.repeatability import (
        STATIC_RUN_COLUMNS,
        pooled_bias_stderrs,
        repeatability,
    )

    theta = (0.0, 1e-8, 4e-10, 0.0, 0.0)
    tau = 0.01 * 2.0 ** np.arange(14)
    edf = 2e4 / (tau / 0.01)
    runs, allan = [], {}
    for i in range(4):
        runs.append(dict(run_id=f"pc{i}", power_cycle_index=i, channel="gyro_x_radps", duration_s=200.0,
                         bias=1e-4 * i, bias_stderr=1e-7, bias_stderr_dof=50.0, N=np.nan, N_stderr=np.nan, B=np.nan,
                         B_stderr=np.nan, unit="rad/s", noise_warnings=""))
        allan[f"pc{i}"] = pd.DataFrame({"channel": "gyro_x_radps", "tau_s": tau,
                                        "adev": np.sqrt(_model_curve(tau, *theta)), "edf": edf})
    out = pooled_bias_stderrs(pd.DataFrame(runs, columns=STATIC_RUN_COLUMNS), allan)
    assert (out["bias_stderr_model"] == "pooled").all()
    assert np.allclose(out["bias_stderr"], np.sqrt(_model_curve(200.0, *theta)), rtol=1e-6)
    d = float(out["bias_stderr_mean_dof"].iloc[0])
    assert np.isfinite(d) and d > 0
    # one shared fit: mean(se^2) carries the fit's dof, not Satterthwaite's sum over 4 independent runs
    v, se = out["bias"].to_numpy(), out["bias_stderr"].to_numpy()
    shared = repeatability(v, se, stderr_mean_dof=d)
    assert shared.noise_corrected_ci_low == pytest.approx(repeatability(v, se, stderr_dofs=[d / 4] * 4)
                                                          .noise_corrected_ci_low, rel=1e-9)
    assert shared.noise_corrected_ci_high != pytest.approx(repeatability(v, se, stderr_dofs=[d] * 4)
                                                           .noise_corrected_ci_high, rel=1e-6)
    # a run without an Allan table keeps its own standard error
    part = pooled_bias_stderrs(pd.DataFrame(runs, columns=STATIC_RUN_COLUMNS), {k: allan[k] for k in ("pc0", "pc1")})
    assert list(part["bias_stderr_model"]) == ["pooled", "pooled", "per_run", "per_run"]
    assert part["bias_stderr"].iloc[3] == 1e-7
