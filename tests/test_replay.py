"""Replay of recorded inputs: a simulated run replayed with its own truth, effects and seed gives the same raw
files byte for byte; a replay follows the recorded temperature log and power-on time."""

from __future__ import annotations

import hashlib
from datetime import datetime, timedelta, timezone

import numpy as np
import pytest

from assets_lib.sim.effects import EFFECTS, sensor_chain
from assets_lib.sim.plans import build_plan
from assets_lib.sim.replay import infer_power_on_s, load_replay, replay_run, replicates
from assets_lib.sim.simulator import example_device, simulate_run, write_run

T0 = datetime(2026, 3, 2, 9, 0, tzinfo=timezone.utc)


def _digests(d):
    return {p.name: hashlib.sha256(p.read_bytes()).hexdigest() for p in sorted(d.iterdir()) if p.is_file()}


@pytest.mark.parametrize("fmt", ["parquet", "csv"])
@pytest.mark.parametrize("extra", [(), ("latency", "g_sensitivity", "warmup_bias", "table_rate_error", "noise_model")])
def test_replaying_a_simulated_run_reproduces_its_raw_files(tmp_path, fmt, extra):
    params = {"latency": {"gyro_s": 4e-3}, "g_sensitivity": {"linear_radps_per_mps2": ((1e-4, 0, 0),) * 3},
              "warmup_bias": {"tau_s": (300.0,), "gyro_radps": ((2e-4, 0, 0),)},
              "table_rate_error": {"mean_error": 1e-4, "ripple_1_per_rev": 1e-4},
              "noise_model": {"gyro_gm_sigma_radps": 1e-4, "gyro_gm_tau_s": 5.0}}
    chain = sensor_chain([EFFECTS[k].from_params(params[k]) for k in extra])
    truth = example_device("TAC-7", "tactical", 3)
    plan = build_plan("quick_rate", duration_scale=0.15)
    run = simulate_run(truth, plan, "pc00-rate", test_kind="rate", effects=chain, seed=17, power_on_s=420.0,
                       start_time_utc=T0)
    orig = write_run(run, tmp_path / "a", fmt)
    rep = replay_run(orig)
    again = write_run(rep, tmp_path / "b", fmt)
    assert _digests(orig) == _digests(again)
    assert rep.power_on_s == 420.0


def test_replay_uses_the_recorded_temperature_and_inferred_power_on(tmp_path):
    truth = example_device("CON-5", "consumer", 1)
    land = tmp_path / "land"
    plan = build_plan("quick_24_position", duration_scale=0.2)
    chamber = lambda t: 20.7 + 6.4 * (t / (t.max() + 1.0))  # noqa: E731  (a recorded 20.7-27.1 degC ramp)
    first = simulate_run(truth, plan, "pc01-a", test_kind="multiposition", power_cycle_index=1, start_time_utc=T0,
                         temperature_degc=chamber)
    second = simulate_run(truth, plan, "pc01-b", test_kind="multiposition", power_cycle_index=1,
                          start_time_utc=T0 + timedelta(seconds=1800), temperature_degc=chamber)
    other = simulate_run(truth, plan, "pc02-a", test_kind="multiposition", power_cycle_index=2,
                         start_time_utc=T0 + timedelta(seconds=900))
    for r in (first, second, other):
        write_run(r, land)
    d = land / "CON-5" / "pc01-b"
    assert infer_power_on_s(d) == 1800.0
    assert infer_power_on_s(land / "CON-5" / "pc01-a") == 0.0
    assert infer_power_on_s(land / "CON-5" / "pc02-a") == 0.0
    rep_in = load_replay(d)
    assert rep_in.power_on_s == 1800.0
    # a temperature effect follows the recorded log (20.7 .. 27.1 degC), not the default housing profile
    k = 1e-3
    eff = EFFECTS["temperature_bias"](gyro_radps_per_k=(k, 0, 0))
    base = replay_run(d, truth, sensor_chain([]), seed=5)
    warm = replay_run(d, truth, sensor_chain([eff]), seed=5)
    temp = rep_in.temperature
    assert temp.min() < 21.0 and temp.max() > 26.5
    lsb = np.radians(truth.gyro.lsb)
    diff = (warm.imu_raw["gyro_x"].to_numpy() - base.imu_raw["gyro_x"].to_numpy()) * lsb
    np.testing.assert_allclose(diff, k * (temp - 25.0), atol=lsb)
    # a warm-up effect counts from the inferred power-on, 1800 s before this run
    wu = EFFECTS["warmup_bias"](tau_s=(600.0,), gyro_radps=((0.01, 0, 0),))
    rep = replay_run(d, truth, sensor_chain([wu]), seed=5)
    diff = (rep.imu_raw["gyro_x"].to_numpy() - base.imu_raw["gyro_x"].to_numpy()) * lsb
    t = rep_in.time_s
    np.testing.assert_allclose(diff, 0.01 * np.exp(-(t + 1800.0) / 600.0), atol=lsb)


def test_replicates_of_a_recorded_run_differ_only_by_noise(tmp_path):
    truth = example_device("NAV-3", "navigation", 2)
    run = simulate_run(truth, build_plan("quick_rate", duration_scale=0.1), "r", test_kind="rate", seed=1)
    d = write_run(run, tmp_path)
    rep = load_replay(d)
    reps = list(replicates(rep, truth, sensor_chain([]), [1, 2, 3]))
    assert reps[0].imu_raw.equals(replay_run(d, truth, sensor_chain([]), 1).imu_raw)  # cached == uncached
    assert reps[0].imu_raw.equals(run.imu_raw)
    for r in reps[1:]:
        assert r.imu_raw["time_s"].equals(run.imu_raw["time_s"]) and r.table_raw.equals(run.table_raw)
        assert not r.imu_raw["gyro_z"].equals(run.imu_raw["gyro_z"])
        lsb = np.radians(truth.gyro.lsb)
        assert np.std((r.imu_raw["gyro_z"] - run.imu_raw["gyro_z"]) * lsb) < 1e-4  # noise only (rad/s)
