"""``imulab allan`` end to end: CSV and parquet, units, streaming, --json and --plot."""

from __future__ import annotations

import json
import math

import numpy as np
import pandas as pd
import pytest
from click.testing import CliRunner

from assets_lib.noise import allan as al
from assets_lib.sim.noise import AllanParams, allan_noise
from imulab.cli import main

D2R = math.pi / 180.0
RATE = 100.0
N = 120_000


@pytest.fixture(scope="module")
def record():
    rng = np.random.default_rng(17)
    gyro = allan_noise(N, RATE, AllanParams(n=0.1 * D2R / 60, b=3 * D2R / 3600), rng)
    accel = 9.80665 + allan_noise(N, RATE, AllanParams(n=1e-3, b=1e-4), rng)
    return pd.DataFrame({"time_s": np.arange(N) / RATE, "gyro_x": gyro, "accel_z": accel})


def _run(args):
    res = CliRunner().invoke(main, ["allan", *map(str, args)], catch_exceptions=False)
    return res


def test_csv_with_units_json_and_plot(tmp_path, record):
    df = record.copy()
    df["gyro_x"] = np.rad2deg(df["gyro_x"])  # the file is in deg/s
    csv = tmp_path / "imu.csv"
    df[["time_s", "gyro_x"]].to_csv(csv, index=False)
    out_json, out_png = tmp_path / "a.json", tmp_path / "a.png"
    res = _run([csv, "--units", "deg/s", "--taus", "dense", "--json", out_json, "--plot", out_png])
    assert res.exit_code == 0, res.output
    assert "gyro_x: OADEV [rad/s]" in res.output and "deg/sqrt(h)" in res.output
    doc = json.loads(out_json.read_text())
    assert doc["rate_hz"] == pytest.approx(RATE)
    ch = doc["channels"]["gyro_x"]
    ref = al.oadev(record["gyro_x"].to_numpy(), RATE, "dense")
    # deg/s -> rad/s conversion applied; CSV text round-trip limits agreement to ~1e-12
    np.testing.assert_allclose(ch["allan"]["adev"], ref.adev, rtol=1e-9)
    np.testing.assert_allclose(ch["allan"]["tau_s"], ref.tau_s)
    noise = {(p["name"], p["method"]): p for p in ch["noise"]}
    n_fit = noise[("N", "fit")]
    assert n_fit["unit_lab"] == "deg/sqrt(h)" and n_fit["ci_lo_lab"] < 0.1 < n_fit["ci_hi_lab"]
    assert n_fit["value_lab"] == pytest.approx(0.1, rel=0.02)
    assert noise[("N", "slope")]["method"] == "slope"
    png = out_png.read_bytes()
    assert png[:8] == b"\x89PNG\r\n\x1a\n" and len(png) > 5000
    import matplotlib.image as mpimg

    img = mpimg.imread(out_png)
    assert img.shape[0] > 200 and img.shape[1] > 200


@pytest.mark.parametrize("stream", [False, True])
def test_parquet_in_memory_and_streamed(tmp_path, record, stream):
    pqf = tmp_path / "imu.parquet"
    record.to_parquet(pqf, row_group_size=50_000)
    out_json = tmp_path / "b.json"
    args = [pqf, "--json", out_json, "--no-fit"]
    if stream:
        args += ["--stream-rows", 1000]
    res = _run(args)
    assert res.exit_code == 0, res.output
    doc = json.loads(out_json.read_text())
    assert doc["streamed"] is stream
    assert set(doc["channels"]) == {"gyro_x", "accel_z"}  # time_s skipped
    assert doc["channels"]["accel_z"]["unit"] == "m/s^2" and doc["channels"]["gyro_x"]["sensor"] == "gyro"
    for c in ("gyro_x", "accel_z"):
        ref = al.oadev(record[c].to_numpy(), RATE, "octave")
        np.testing.assert_array_equal(doc["channels"][c]["allan"]["adev"], ref.adev)


def test_accelerometer_in_g_with_rate_option(tmp_path, record):
    csv = tmp_path / "acc.csv"
    pd.DataFrame({"az": record["accel_z"] / 9.80665}).to_csv(csv, index=False)
    out_json = tmp_path / "c.json"
    res = _run([csv, "--units", "g", "--rate-hz", RATE, "--taus", "12", "--json", out_json])
    assert res.exit_code == 0, res.output
    ch = json.loads(out_json.read_text())["channels"]["az"]
    assert ch["sensor"] == "accel" and len(ch["allan"]["tau_s"]) == 12
    ref = al.oadev(record["accel_z"].to_numpy(), RATE, 12)
    np.testing.assert_allclose(ch["allan"]["adev"], ref.adev, rtol=1e-9)
    noise = {(p["name"], p["method"]): p for p in ch["noise"]}
    assert noise[("N", "fit")]["unit_lab"] == "m/s/sqrt(h)"
    assert noise[("N", "fit")]["value"] == pytest.approx(1e-3, rel=0.03)


def test_errors_are_reported(tmp_path, record):
    csv = tmp_path / "x.csv"
    record[["gyro_x"]].to_csv(csv, index=False)
    res = CliRunner().invoke(main, ["allan", str(csv)])
    assert res.exit_code != 0 and "--rate-hz" in res.output
    res = CliRunner().invoke(main, ["allan", str(csv), "--rate-hz", "100", "--units", "furlong/s"])
    assert res.exit_code != 0 and "unknown unit" in res.output
    res = CliRunner().invoke(main, ["allan", str(csv), "--rate-hz", "100", "--columns", "nope"])
    assert res.exit_code != 0 and "no column" in res.output
    bad = record[["gyro_x"]].copy()
    bad.iloc[10, 0] = np.nan
    bad.to_csv(csv, index=False)
    res = CliRunner().invoke(main, ["allan", str(csv), "--rate-hz", "100"])
    assert res.exit_code != 0 and "non-finite" in res.output


@pytest.fixture(scope="module")
def contract_run(tmp_path_factory):
    """A short static run written as a lab's capture job writes it: integer counts plus a manifest with the LSB."""
    from assets_lib.sim.simulator import example_device, simulate_run, write_run

    truth = example_device("TAC-050", "tactical", 5)
    run = simulate_run(truth, "static_long", "pc00-static", seed=5, table_log=False,
                       plan_kwargs={"static_duration_s": 300.0})
    return write_run(run, tmp_path_factory.mktemp("landing"))


def test_contract_run_read_in_manifest_units(contract_run, tmp_path):
    """Issue 10 item 7: the IMU stream of a contract run is read as counts x LSB in the manifest's unit (-> SI) at
    the manifest's rate, the same numbers ingestion gives, not counts taken for rad/s."""
    from raw_schemas.readers import ingest_run

    imu = contract_run / "imu.parquet"
    assert pd.api.types.is_integer_dtype(pd.read_parquet(imu)["gyro_x"])  # raw counts
    out_json = tmp_path / "a.json"
    res = _run([imu, "--taus", "octave", "--json", out_json])
    assert res.exit_code == 0, res.output
    assert "contract run TAC-050/pc00-static" in res.output and "gyro_x counts x" in res.output
    doc = json.loads(out_json.read_text())
    assert set(doc["channels"]) == {"gyro_x", "gyro_y", "gyro_z", "accel_x", "accel_y", "accel_z"}
    si = ingest_run(contract_run).imu
    for raw, canon in (("gyro_x", "gyro_x_radps"), ("accel_z", "accel_z_mps2")):
        ch = doc["channels"][raw]
        ref = al.oadev(si[canon].to_numpy(), doc["rate_hz"], "octave")
        np.testing.assert_allclose(ch["allan"]["adev"], ref.adev, rtol=1e-9)
    assert doc["channels"]["gyro_x"]["unit"] == "rad/s" and doc["channels"]["accel_z"]["unit"] == "m/s^2"
    n = {(p["name"], p["method"]): p for p in doc["channels"]["gyro_x"]["noise"]}[("N", "fit")]
    assert n["unit_lab"] == "deg/sqrt(h)" and 1e-3 < n["value_lab"] < 10  # a tactical ARW, not 5.7e4
    res = _run([imu, "--units", "deg/s"])
    assert res.exit_code != 0 and "units come from the manifest" in res.output


def test_counts_without_a_manifest_are_refused(contract_run, tmp_path):
    lone = tmp_path / "imu.parquet"
    lone.write_bytes((contract_run / "imu.parquet").read_bytes())
    res = _run([lone])
    assert res.exit_code != 0
    assert "hold integers, i.e. raw counts" in res.output and "no manifest.json" in res.output
