"""`imulab fit rate|tumble` end to end on seed 001's published plateau means (reconstructed, see seed001_data)."""

from __future__ import annotations

import json

import numpy as np
from click.testing import CliRunner

from imulab.cli import main
from seed001_data import GYRO_PUBLISHED, TUMBLE_PUBLISHED, gyro_table, tumble_table


def _csv(path, header, a, b):
    path.write_text(header + "\n" + "".join(f"{float(x)!r},{float(y)!r}\n" for x, y in zip(a, b)))
    return path


def test_fit_rate_cli_json_reports_exclusions(tmp_path):
    rates, means = gyro_table()
    f = _csv(tmp_path / "rate.csv", "rate_dps,mean_V", rates, means)
    out = tmp_path / "rate.json"
    r = CliRunner().invoke(main, ["fit", "rate", "--means", str(f), "--rate-unit", "deg/s", "--output-unit", "V",
                                  "--json", str(out), "--plot", str(tmp_path / "r.png")])
    assert r.exit_code == 0, r.output
    assert "scale_factor" in r.output and "excluded points (2)" in r.output
    assert "saturated" in r.output and "rail" in r.output
    d = json.loads(out.read_text())
    assert d["kind"] == "rate" and d["n_points"] == 27 and d["n_used"] == 25
    ex = {e["input"]: e for e in d["excluded"]}
    assert ex[90.0]["kind"] == "saturation" and ex[80.0]["kind"] == "saturation"
    coef = {c["name"]: c for c in d["coefficients"]}
    assert coef["scale_factor"]["unit"] == "V/(deg/s)" and coef["scale_factor"]["stderr"] > 0
    assert coef["nonlinearity"]["unit"] == "ppm" and coef["asymmetry"]["unit"] == "ppm"
    assert len(d["residuals"]) == 27 and sum(x["excluded"] for x in d["residuals"]) == 2
    assert (tmp_path / "r.png").read_bytes()[:4] == b"\x89PNG"


def test_fit_rate_cli_flat_top_reproduces_seed001(tmp_path):
    rates, means = gyro_table()
    f = _csv(tmp_path / "rate.csv", "w,U", rates, means)
    out = tmp_path / "r.json"
    r = CliRunner().invoke(main, ["fit", "rate", "--means", str(f), "--exclusion", "flat-top", "--json", str(out)])
    assert r.exit_code == 0, r.output
    coef = {c["name"]: c for c in json.loads(out.read_text())["coefficients"]}
    assert round(coef["zero_output"]["value"], 4) == GYRO_PUBLISHED[0]
    assert round(coef["scale_factor"]["value"], 4) == GYRO_PUBLISHED[1]


def test_fit_rate_cli_units_are_converted(tmp_path):
    rates, means = gyro_table()
    f1 = _csv(tmp_path / "a.csv", "rate,out", rates, means)
    f2 = _csv(tmp_path / "b.csv", "rate,out", np.radians(rates), means)
    res = []
    for f, unit in ((f1, "deg/s"), (f2, "rad/s")):
        out = tmp_path / f"{unit.replace('/', '_')}.json"
        r = CliRunner().invoke(main, ["fit", "rate", "--means", str(f), "--rate-unit", unit, "--json", str(out)])
        assert r.exit_code == 0, r.output
        res.append({c["name"]: c["value"] for c in json.loads(out.read_text())["coefficients"]})
    assert np.isclose(res[1]["scale_factor"], res[0]["scale_factor"] * 180 / np.pi)
    assert np.isclose(res[1]["zero_output"], res[0]["zero_output"])
    assert np.isclose(res[1]["nonlinearity"], res[0]["nonlinearity"])


def test_fit_tumble_cli_json(tmp_path):
    theta, u = tumble_table()
    f = tmp_path / "tumble.csv"
    f.write_text("# seed 001 tumble, model angle\nposition,angle_deg,mean_V\n"
                 + "".join(f"{k + 1},{float(a)!r},{float(b)!r}\n" for k, (a, b) in enumerate(zip(theta, u))))
    out = tmp_path / "t.json"
    r = CliRunner().invoke(main, ["fit", "tumble", "--means", str(f), "--angle-column", "angle_deg",
                                  "--output-column", "mean_V", "--json", str(out)])
    assert r.exit_code == 0, r.output
    assert "excluded points: none" in r.output
    d = json.loads(out.read_text())
    coef = {c["name"]: c for c in d["coefficients"]}
    est = [coef[k]["value"] for k in ("K0", "K1", "K2", "K3")]
    assert [round(abs(est[0]), 3), round(est[1], 4), round(est[3], 4)] == [round(TUMBLE_PUBLISHED[0], 3),
                                                                           TUMBLE_PUBLISHED[1], TUMBLE_PUBLISHED[3]]
    assert coef["K1"]["unit"] == "V/g" and coef["K2"]["unit"] == "V/g^2"
    assert coef["bias"]["unit"] == "mg" and np.isclose(coef["bias"]["value"], est[0] / est[1] * 1e3)


def test_fit_cli_errors_are_clear(tmp_path):
    f = _csv(tmp_path / "x.csv", "a,b", [1, 2, 3], [1, 2, 3])
    r = CliRunner().invoke(main, ["fit", "rate", "--means", str(f), "--rate-column", "nope"])
    assert r.exit_code != 0 and "no column 'nope'" in r.output
    r = CliRunner().invoke(main, ["fit", "tumble", "--means", str(f), "--angle-unit", "grad"])
    assert r.exit_code != 0
    r = CliRunner().invoke(main, ["fit", "--help"])
    assert r.exit_code == 0 and "rate" in r.output and "tumble" in r.output
