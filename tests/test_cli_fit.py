"""`imulab fit rate|tumble` end to end on seed 001's published plateau means (reconstructed, see seed001_data)."""

from __future__ import annotations

import json

import numpy as np
import pytest
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


def _rate_table_with_times(tmp_path, seed=5):
    """A rate sweep tabulated as a lab would: commanded rate, plateau mean and sem, start/end times [s]; the output
    carries a random-walk wander between plateaus (correlated noise the independent-plateau fit does not see)."""
    rng = np.random.default_rng(seed)
    rates = np.array([-100, -50, -20, -10, -5, 5, 10, 20, 50, 100, 0], float)
    t0 = np.arange(rates.size) * 60.0
    t1 = t0 + 40.0
    wander = np.cumsum(rng.normal(0, 2e-4, rates.size))
    sem = np.full(rates.size, 1e-4)
    means = 0.2 + 0.05 * rates + wander + rng.normal(0, 1e-4, rates.size)
    path = tmp_path / "rate_t.csv"
    path.write_text("rate_dps,mean_V,sem_V,t0_s,t1_s\n" + "".join(
        ",".join(repr(float(v)) for v in row) + "\n" for row in zip(rates, means, sem, t0, t1)))
    return path, rates, means, sem, (t0, t1)


def test_fit_rate_cli_times_and_flicker_level_are_the_scored_fit(tmp_path):
    """With plateau times and the run's 1/f level (what the coverage benchmark scores as `imulab fit rate`), the
    command prints exactly fit_rate_means' correlated-noise fit; without times it warns that the intervals leave
    out the noise shared between plateaus."""
    from assets_lib.calibration.fit_core import flicker_dof_from_interval
    from assets_lib.calibration.means_fit import fit_rate_means

    f, rates, means, sem, times = _rate_table_with_times(tmp_path)
    common = ["fit", "rate", "--means", str(f), "--rate-column", "rate_dps", "--output-column", "mean_V",
              "--sem-column", "sem_V"]
    out = tmp_path / "t.json"
    r = CliRunner().invoke(main, common + ["--start-column", "t0_s", "--end-column", "t1_s", "--flicker-b", "3e-4",
                                          "--flicker-b-dof", "12", "--json", str(out)])
    assert r.exit_code == 0, r.output
    assert "taken as independent" not in r.output
    d = json.loads(out.read_text())
    assert d["correlated_noise"] is True and d["flicker_b_dof"] == 12
    ref = fit_rate_means(rates, means, sem, output_unit="V", times=times, flicker_b=3e-4, flicker_b_dof=12.0)
    got = {c["name"]: (c["value"], c["stderr"]) for c in d["coefficients"]}
    for c in ref.coefficients:
        if c.observable and np.isfinite(c.value):
            assert np.isclose(got[c.name][0], c.value, rtol=1e-12), c.name
            assert np.isclose(got[c.name][1], c.stderr, rtol=1e-12), c.name
    # independent plateaus: a warning, and the zero output's interval lacks the wander
    out2 = tmp_path / "i.json"
    r2 = CliRunner().invoke(main, common + ["--json", str(out2)])
    assert r2.exit_code == 0, r2.output
    assert "warning: no plateau times" in r2.output and "too narrow" in r2.output
    ind = {c["name"]: c["stderr"] for c in json.loads(out2.read_text())["coefficients"]}
    assert got["zero_output"][1] > 1.5 * ind["zero_output"]
    # B's interval as imulab allan prints it gives the degrees of freedom
    out3 = tmp_path / "ci.json"
    r3 = CliRunner().invoke(main, common + ["--start-column", "t0_s", "--end-column", "t1_s", "--flicker-b", "3e-4",
                                           "--flicker-b-ci", "2e-4", "5e-4", "--json", str(out3)])
    assert r3.exit_code == 0, r3.output
    assert np.isclose(json.loads(out3.read_text())["flicker_b_dof"], flicker_dof_from_interval(3e-4, 2e-4, 5e-4))


def test_fit_cli_sem_flicker_level_is_the_scored_fit(tmp_path):
    """`--sem-flicker-b` (the 1/f level the sems contain: the plateau table's <channel>_sem_flicker_b, 0 for white
    sems) prints exactly fit_rate_means / fit_tumble_means with that level, records it in the JSON, and changes the
    intervals against the default reading (the sems taken to contain the weighed level's floor)."""
    from assets_lib.calibration.means_fit import fit_rate_means, fit_tumble_means

    f, rates, means, sem, times = _rate_table_with_times(tmp_path)
    common = ["fit", "rate", "--means", str(f), "--rate-column", "rate_dps", "--output-column", "mean_V",
              "--sem-column", "sem_V", "--start-column", "t0_s", "--end-column", "t1_s", "--flicker-b", "1e-4",
              "--flicker-b-dof", "50"]
    out, out0 = tmp_path / "s.json", tmp_path / "d.json"
    r = CliRunner().invoke(main, common + ["--sem-flicker-b", "0", "--json", str(out)])
    r0 = CliRunner().invoke(main, common + ["--json", str(out0)])
    assert r.exit_code == 0 and r0.exit_code == 0, r.output + r0.output
    d, d0 = json.loads(out.read_text()), json.loads(out0.read_text())
    assert d["sem_flicker_b"] == 0 and d0["sem_flicker_b"] is None
    ref = fit_rate_means(rates, means, sem, output_unit="V", times=times, flicker_b=1e-4, flicker_b_dof=50.0,
                         sem_flicker_b=0.0)
    got = {c["name"]: c["stderr"] for c in d["coefficients"]}
    dflt = {c["name"]: c["stderr"] for c in d0["coefficients"]}
    assert np.isclose(got["scale_factor"], ref.coefficient("scale_factor").stderr, rtol=1e-12)
    assert np.isclose(got["nonlinearity"], ref.coefficient("nonlinearity").stderr, rtol=1e-12)
    assert not np.isclose(got["zero_output"], dflt["zero_output"], rtol=1e-3)
    # the tumble fit takes it the same way
    th = np.arange(0.0, 360.0, 30.0)
    s_, c_ = np.sin(np.radians(th)), np.cos(np.radians(th))
    y = 0.01 + 1.001 * s_ + 1e-4 * s_**2 + 2e-4 * c_ + np.random.default_rng(4).normal(0, 5e-5, th.size)
    t0 = np.arange(th.size) * 60.0
    tf = tmp_path / "tumble.csv"
    tf.write_text("angle_deg,mean_V,sem_V,t0_s,t1_s\n" + "".join(
        f"{float(a)!r},{float(v)!r},5e-05,{float(t)!r},{float(t) + 30.0!r}\n" for a, v, t in zip(th, y, t0)))
    out_t = tmp_path / "t.json"
    rt = CliRunner().invoke(main, ["fit", "tumble", "--means", str(tf), "--sem-column", "sem_V", "--start-column",
                                   "t0_s", "--end-column", "t1_s", "--misalignment-term", "--flicker-b", "4e-5",
                                   "--sem-flicker-b", "0", "--json", str(out_t)])
    assert rt.exit_code == 0, rt.output
    reft = fit_tumble_means(th, y, np.full(th.size, 5e-5), output_unit="V", misalignment_term=True,
                            times=(t0, t0 + 30.0), flicker_b=4e-5, sem_flicker_b=0.0)
    gt = {c["name"]: c["stderr"] for c in json.loads(out_t.read_text())["coefficients"]}
    assert np.isclose(gt["K1"], reft.coefficient("K1").stderr, rtol=1e-12)


def test_fit_rate_cli_takes_an_upper_bound_on_b(tmp_path):
    """A record that only bounds B (imulab allan prints [0, bound]): `--flicker-b-ci 0 BOUND` alone integrates the 1/f
    level below the bound (fit_rate_means(flicker_b_max=...)), which is narrower than taking the bound as B."""
    from assets_lib.calibration.means_fit import fit_rate_means

    f, rates, means, sem, times = _rate_table_with_times(tmp_path)
    out = tmp_path / "b.json"
    r = CliRunner().invoke(main, ["fit", "rate", "--means", str(f), "--rate-column", "rate_dps", "--output-column",
                                  "mean_V", "--sem-column", "sem_V", "--start-column", "t0_s", "--end-column", "t1_s",
                                  "--flicker-b-ci", "0", "6e-4", "--json", str(out)])
    assert r.exit_code == 0, r.output
    d = json.loads(out.read_text())
    assert d["flicker_b_max"] == 6e-4 and d["flicker_b"] is None
    ref = fit_rate_means(rates, means, sem, output_unit="V", times=times, flicker_b_max=6e-4)
    exact = fit_rate_means(rates, means, sem, output_unit="V", times=times, flicker_b=6e-4)
    got = {c["name"]: c["stderr"] for c in d["coefficients"]}
    assert np.isclose(got["zero_output"], ref.coefficient("zero_output").stderr, rtol=1e-12)
    assert got["zero_output"] < 0.9 * exact.coefficient("zero_output").stderr
    with pytest.raises(ValueError, match="not both"):
        fit_rate_means(rates, means, sem, times=times, flicker_b=1e-4, flicker_b_max=6e-4)


def test_fit_cli_noise_options_fail_clearly(tmp_path):
    f = _rate_table_with_times(tmp_path)[0]
    base = ["fit", "rate", "--means", str(f), "--rate-column", "rate_dps", "--output-column", "mean_V"]
    cases = [
        (["--sem-column", "sem_V", "--start-column", "t0_s"], "go together"),
        (["--start-column", "t0_s", "--end-column", "t1_s"], "--sem-column"),
        (["--sem-column", "sem_V", "--start-column", "t0_s", "--end-column", "nope"], "no column 'nope'"),
        (["--sem-column", "sem_V", "--flicker-b", "1e-4"], "need the plateau times"),
        (["--sem-column", "sem_V", "--start-column", "t0_s", "--end-column", "t1_s", "--flicker-b", "1e-4",
          "--flicker-b-ci", "0", "2e-4"], "upper bound"),
        (["--sem-column", "sem_V", "--start-column", "t0_s", "--end-column", "t1_s", "--flicker-b-ci", "0", "-1"],
         "positive number"),
        (["--sem-column", "sem_V", "--flicker-b-ci", "0", "2e-4"], "need the plateau times"),
        (["--sem-column", "sem_V", "--sem-flicker-b", "0"], "needs the plateau times"),
        (["--sem-column", "sem_V", "--start-column", "t0_s", "--end-column", "t1_s", "--sem-flicker-b", "-1e-4"],
         "--sem-flicker-b must be >= 0"),
    ]
    for extra, msg in cases:
        r = CliRunner().invoke(main, base + extra)
        assert r.exit_code != 0 and msg in r.output, (extra, r.output)


def test_flicker_dof_from_interval_inverts_the_chi_square_interval():
    from scipy import stats

    from assets_lib.calibration.fit_core import flicker_dof_from_interval

    for nu in (1.5, 4.0, 30.0, 800.0):
        lo, hi = (np.sqrt(nu / stats.chi2.ppf(q, nu)) for q in (0.975, 0.025))
        assert np.isclose(flicker_dof_from_interval(1.0, lo, hi), nu, rtol=1e-6)


def test_fit_cli_names_a_cell_that_is_not_a_number(tmp_path):
    f = tmp_path / "bad.csv"
    f.write_text("rate,out\n-10,-0.3\n0,0.2\n10,oops\n20,1.2\n")
    r = CliRunner().invoke(main, ["fit", "rate", "--means", str(f), "--rate-column", "rate", "--output-column", "out"])
    assert r.exit_code != 0
    assert "data row 3, column 'out'" in r.output and "'oops' is not a number" in r.output
