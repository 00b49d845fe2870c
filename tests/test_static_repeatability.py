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
