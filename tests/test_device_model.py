"""Device-model files: the published JSON Schema, the loader's errors, model <-> truth conversion, and the round
trip calibrated device -> ``imulab twin`` -> model file -> ``imulab simulate --device-model`` -> refit."""

from __future__ import annotations

import json
from dataclasses import replace
from datetime import datetime, timedelta, timezone
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from click.testing import CliRunner

from assets_lib.calibration.multiposition import (
    fit_accel_multiposition,
    fit_gyro_static,
)
from assets_lib.calibration.rate_fit import fit_gyro_rate
from assets_lib.calibration.segmentation import segment_run
from assets_lib.noise.allan import allan_deviations
from assets_lib.noise.identification import fit_all, noise_table
from assets_lib.sim.device_model import effects_of, model_from_truth, truth_for_cycle
from assets_lib.sim.effects import EFFECTS, sensor_chain
from assets_lib.sim.simulator import example_device, simulate_run, write_run
from imulab.cli import main
from assets_lib.store import VersionedStore
from raw_schemas.device_model import device_model_json_schema, load_device_model
from raw_schemas.errors import RawDataError
from raw_schemas.readers import discover_runs, ingest_run
from raw_schemas.tables import ACCEL_COLUMNS, GYRO_COLUMNS

ROOT = Path(__file__).resolve().parents[1]
T0 = datetime(2026, 2, 2, 8, 0, tzinfo=timezone.utc)
Z = 5.0


def test_published_schema_is_the_models():
    on_disk = json.loads((ROOT / "raw_schemas" / "device_model.schema.json").read_text())
    assert on_disk == device_model_json_schema()


def test_loader_names_file_field_and_expectation(tmp_path):
    model = model_from_truth({0: example_device("NAV-9", "navigation", 1)})
    doc = json.loads(model.model_dump_json())
    doc["power_cycles"][0]["gyro"]["scale_factor"] = [1.0, 1.0]
    p = tmp_path / "bad.json"
    p.write_text(json.dumps(doc))
    with pytest.raises(RawDataError, match=r"bad.json.*power_cycles.0.gyro.scale_factor.*3 values"):
        load_device_model(p)
    p.write_text("{")
    with pytest.raises(RawDataError, match="valid JSON"):
        load_device_model(p)


def test_model_and_truth_convert_both_ways():
    base = example_device("TAC-4", "tactical", 7)
    # a model holds fitted cycles, not the turn-on spreads that draw new ones
    base = replace(base, bias_repeatability=(0.0, 0.0), scale_repeatability=(0.0, 0.0))
    truths = {c: base.for_power_cycle(c, 7) for c in (0, 1, 3)}
    effs = [EFFECTS["warmup_bias"](tau_s=(300.0,), gyro_radps=((1e-4, 0, 0),)),
            EFFECTS["latency"](gyro_s=2e-3)]
    model = model_from_truth(truths, effs)
    again = type(model).model_validate_json(model.model_dump_json())
    for c, t in truths.items():
        assert truth_for_cycle(again, c) == t
    assert truth_for_cycle(again, 2) == truths[1]  # an unfitted cycle takes the nearest earlier one
    assert effects_of(again) == sensor_chain(effs)


def _calibrate_into_store(landing: Path, store: VersionedStore):
    """What the pipeline stores per run (ingested manifest, fit coefficients, Allan noise table), computed with
    the same science functions, written with the pipeline's versioned store."""
    for d in discover_runs(landing):
        ing = ingest_run(d)
        key = ing.manifest.partition_key
        mjson = (json.dumps(json.loads(ing.manifest.model_dump_json()), indent=1, sort_keys=True) + "\n").encode()
        store.write("ingested_run", key, "v1", {"imu": ing.imu}, files={"manifest.json": mjson})
        kind = ing.manifest.test_kind
        if kind == "static":
            ch = list(GYRO_COLUMNS + ACCEL_COLUMNS)
            res = allan_deviations(ing.imu[ch], ing.manifest.sample_rate_hz, taus="octave", channels=ch, ci_level=0.95)
            store.write("allan_deviation", key, "v1", {"noise": noise_table(fit_all(res))})
            continue
        p = segment_run(ing.manifest, ing.imu, ing.table).plateaus
        if kind == "rate":
            store.write("gyro_rate_fit", key, "v1", {"coefficients": fit_gyro_rate(p).coefficient_table()})
        else:
            coef = pd.concat([fit_accel_multiposition(p).coefficient_table(), fit_gyro_static(p).coefficient_table()],
                             ignore_index=True)
            store.write("accel_multiposition_fit", key, "v1", {"coefficients": coef})


def _coefficients(landing: Path) -> dict:
    out = {}
    for d in discover_runs(landing):
        ing = ingest_run(d)
        if ing.manifest.test_kind == "static":
            continue
        p = segment_run(ing.manifest, ing.imu, ing.table).plateaus
        c = (fit_gyro_rate(p).coefficient_table() if ing.manifest.test_kind == "rate"
             else pd.concat([fit_accel_multiposition(p).coefficient_table(), fit_gyro_static(p).coefficient_table()]))
        out[(ing.manifest.power_cycle_index, ing.manifest.test_kind)] = c
    return out


def _z(value, stderr, truth):
    return abs(value - truth) / stderr


@pytest.mark.slow
def test_twin_round_trip_from_a_calibrated_device(tmp_path):
    truth0 = example_device("TAC-31", "tactical", 11)
    land = tmp_path / "landing"
    truths = {}
    for c in (0, 1):
        tr = truth0.for_power_cycle(c, 11, 7.0 * c)
        truths[c] = tr
        start = T0 + timedelta(days=7 * c)
        runs = [simulate_run(tr, "quick_rate", f"pc{c:02d}-rate", power_cycle_index=c, seed=3, start_time_utc=start,
                             plan_kwargs={"duration_scale": 0.5}),
                simulate_run(tr, "quick_24_position", f"pc{c:02d}-pos24", power_cycle_index=c, seed=3,
                             start_time_utc=start + timedelta(hours=1), plan_kwargs={"duration_scale": 0.5})]
        if c == 0:
            runs.append(simulate_run(tr, "static_long", "pc00-static", power_cycle_index=0, seed=3, table_log=False,
                                     start_time_utc=start + timedelta(hours=2), plan_kwargs={"static_duration_s": 600.0}))
        for r in runs:
            write_run(r, land)
    store = VersionedStore(tmp_path / "store")
    _calibrate_into_store(land, store)

    model_file = tmp_path / "TAC-31.json"
    effects_file = tmp_path / "effects.json"
    effects_file.write_text(json.dumps([{"family": "bias_ramp", "params": {"gyro_radps_per_s": [0, 0, 1e-8]}}]))
    res = CliRunner().invoke(main, ["twin", "TAC-31", "--store", str(tmp_path / "store"), "--out", str(model_file),
                                    "--effects", str(effects_file)])
    assert res.exit_code == 0, res.output
    model = load_device_model(model_file)
    assert [p.index for p in model.power_cycles] == [0, 1]
    assert [e.family for e in model.effects] == ["bias_ramp"]
    # the model holds the calibrated values: within their standard errors of the truth
    for c, tr in truths.items():
        pc = model.cycle(c)
        for i in range(3):
            assert _z(pc.gyro.scale_factor[i], pc.gyro.scale_factor_stderr[i], tr.gyro.scale[i]) < Z
            assert _z(pc.accel.scale_factor[i], pc.accel.scale_factor_stderr[i], tr.accel.scale[i]) < Z
            assert _z(pc.accel.bias_mps2[i], pc.accel.bias_stderr_mps2[i], tr.accel.bias[i]) < Z
            assert _z(pc.gyro.bias_radps[i], pc.gyro.bias_stderr_radps[i], tr.gyro.bias[i]) < Z
            for j in range(3):
                if i != j:
                    assert _z(pc.gyro.misalignment_rad[i][j], pc.gyro.misalignment_stderr_rad[i][j],
                              tr.gyro.misalignment_rad[i][j]) < Z
                    assert _z(pc.gyro.g_sensitivity_radps_per_mps2[i][j],
                              pc.gyro.g_sensitivity_stderr_radps_per_mps2[i][j], tr.g_sensitivity[i][j]) < Z
    gn = model.noise.gyro.x.n
    assert gn == pytest.approx(truth0.gyro.noise[0].n, rel=0.15)  # ARW from the 600 s static record

    # simulate the model's unit and refit it: the fits land on the model within their standard errors
    out = tmp_path / "twin_landing"
    res = CliRunner().invoke(main, ["simulate", "--device-model", str(model_file), "--plan", "quick_rate",
                                    "--plan", "quick_24_position", "--out", str(out), "--seed", "9"])
    assert res.exit_code == 0, res.output
    assert "bias_ramp" in res.output
    coefs = _coefficients(out)
    assert sorted(coefs) == [(0, "multiposition"), (0, "rate"), (1, "multiposition"), (1, "rate")]
    for (c, kind), tab in coefs.items():
        pc = model.cycle(c)
        for _, r in tab[tab.observable.astype(bool)].iterrows():
            i = "xyz".index(r.axis)
            if r.sensor == "gyro" and r.coefficient == "scale_factor":
                want = pc.gyro.scale_factor[i]
            elif r.sensor == "accel" and r.coefficient == "scale_factor":
                want = pc.accel.scale_factor[i]
            elif r.sensor == "accel" and r.coefficient == "bias":
                want = pc.accel.bias_mps2[i]
            elif r.coefficient.startswith("misalignment_"):
                j = "xyz".index(r.coefficient[-1])
                want = (pc.gyro if r.sensor == "gyro" else pc.accel).misalignment_rad[i][j]
            else:
                continue
            assert _z(r.value, r.stderr, want) < Z, (c, kind, r.sensor, r.axis, r.coefficient, r.value, want)
    truth_files = sorted((out / "_truth" / "TAC-31").glob("*.json"))
    doc = json.loads(truth_files[0].read_text())
    assert doc["effect_params"][0]["family"] == "bias_ramp"

    # replay: the model's unit driven by a recorded run's inputs
    rep_out = tmp_path / "replayed"
    rec = land / "TAC-31" / "pc01-rate"
    res = CliRunner().invoke(main, ["simulate", "--device-model", str(model_file), "--replay", str(rec),
                                    "--out", str(rep_out)])
    assert res.exit_code == 0, res.output
    a, b = ingest_run(rec), ingest_run(rep_out / "TAC-31" / "pc01-rate")
    np.testing.assert_array_equal(a.imu["time_s"], b.imu["time_s"])
    pd.testing.assert_frame_equal(a.table, b.table)
    np.testing.assert_array_equal(a.imu["temperature_degc"], b.imu["temperature_degc"])
    assert np.abs(a.imu["gyro_z_radps"] - b.imu["gyro_z_radps"]).mean() < 0.01  # same motion, different noise


def test_simulate_without_model_rejects_model_options(tmp_path):
    res = CliRunner().invoke(main, ["simulate", "--plan", "quick_rate", "--out", str(tmp_path)])
    assert res.exit_code != 0 and "--device-model" in res.output
