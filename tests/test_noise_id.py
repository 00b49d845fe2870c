"""IEEE 952 noise-term fit: exact recovery on model curves, units, upper bounds, slope reads, Monte Carlo."""

from __future__ import annotations

import math

import numpy as np
import pytest

from assets_lib.noise import allan as al
from assets_lib.noise import identification as ni
from assets_lib.noise.intervals import edf_greenhall
from assets_lib.sim.noise import AllanParams, allan_noise

D2R = math.pi / 180.0


def _model_result(params: AllanParams, rate_hz=100.0, n=1_080_000, extra=None, channel="gyro_x") -> al.AllanResult:
    """An AllanResult whose AVAR is exactly the IEEE 952 model (noise-free), with EDF of a real record."""
    m = al.averaging_factors(n, "dense")
    tau = m / rate_hz
    avar = params.avar(tau) + (extra(tau) if extra else 0.0)
    dev = np.sqrt(avar)
    n_terms = n + 1 - 2 * m
    edf = np.array([edf_greenhall(0, 2, int(mj), n + 1, True, False) for mj in m])
    return al.AllanResult(
        kind="oadev", data_type="rate", rate_hz=rate_hz, n_samples=n, m=m, tau_s=tau, adev=dev,
        n_terms=n_terms, edf=edf, ci_lo=dev * 0.9, ci_hi=dev * 1.1, alpha=np.zeros(len(m)),
        ci_level=0.683, channel=channel, unit="rad/s",
    )


def test_basis_is_ieee_c23():
    p = AllanParams(q=1e-6, n=2e-5, b=1e-5, k=1e-6, r=1e-8)
    tau = np.geomspace(0.01, 1e4, 50)
    theta = np.array([p.q**2, p.n**2, p.b**2, p.k**2, p.r**2])
    np.testing.assert_allclose(ni.basis(tau) @ theta, p.avar(tau), rtol=1e-14)


def test_exact_recovery_on_model_curve():
    p = AllanParams(q=3e-7, n=0.07 * D2R / 60, b=2 * D2R / 3600, k=14 * D2R / 3600 / 60, r=0.0)
    res = _model_result(p)
    fit = ni.fit_noise(res, max_m_fraction=0.5)
    for name, true in (("N", p.n), ("B", p.b), ("K", p.k)):
        q = fit.parameter(name)
        assert not q.is_upper_bound
        assert q.value == pytest.approx(true, rel=1e-6)
        assert q.ci_lo < true < q.ci_hi
    # lab units: N deg/sqrt(h), B deg/h, K deg/h/sqrt(h)
    assert fit.parameter("N").value_lab == pytest.approx(0.07, rel=1e-6)
    assert fit.parameter("N").unit_lab == "deg/sqrt(h)"
    assert fit.parameter("B").value_lab == pytest.approx(2.0, rel=1e-6)
    assert fit.parameter("K").value_lab == pytest.approx(14.0, rel=1e-6)
    assert fit.parameter("K").unit_lab == "deg/h/sqrt(h)"
    np.testing.assert_allclose(fit.model_avar(res.tau_s), res.avar, rtol=1e-6)


def test_term_below_the_curves_resolution_is_dropped_and_bounded():
    """R = 2e-9 rad/s^2 is far inside R's interval on this curve: the fit drops it (it would bias the others),
    bounds it with the truth below the bound, and the other terms stay inside their intervals."""
    p = AllanParams(q=3e-7, n=0.07 * D2R / 60, b=2 * D2R / 3600, k=14 * D2R / 3600 / 60, r=2e-9)
    fit = ni.fit_noise(_model_result(p), max_m_fraction=0.5)
    r = fit.parameter("R")
    assert r.is_upper_bound and p.r < r.ci_hi
    assert fit.theta[fit.terms.index("R")] == 0.0
    for name, true in (("Q", p.q), ("N", p.n), ("B", p.b), ("K", p.k)):
        q = fit.parameter(name)
        assert not q.is_upper_bound and q.ci_lo < true < q.ci_hi


def test_absent_terms_are_upper_bounds():
    p = AllanParams(n=2e-5, k=1e-6)
    fit = ni.fit_noise(_model_result(p))
    for name in ("Q", "B", "R"):
        q = fit.parameter(name)
        assert q.is_upper_bound and math.isnan(q.value) and q.ci_hi > 0 and q.ci_lo == 0
    assert not fit.parameter("N").is_upper_bound and not fit.parameter("K").is_upper_bound


def test_accelerometer_units():
    vrw = 0.05 / 60.0  # 0.05 m/s/sqrt(h) in m/s^2/sqrt(Hz)
    b = 50e-6 * 9.80665  # 50 ug
    fit = ni.fit_noise(_model_result(AllanParams(n=vrw, b=b), channel="accel_z"))
    assert fit.sensor == "accel"
    assert fit.parameter("N").unit_lab == "m/s/sqrt(h)" and fit.parameter("N").value_lab == pytest.approx(0.05, rel=1e-6)
    assert fit.parameter("B").unit_lab == "ug" and fit.parameter("B").value_lab == pytest.approx(50.0, rel=1e-6)


def test_slope_reads_on_single_term_curves():
    for name, p in (("N", AllanParams(n=3e-5)), ("K", AllanParams(k=2e-6)), ("Q", AllanParams(q=1e-6)),
                    ("R", AllanParams(r=1e-7))):
        reads = {q.name: q for q in ni.slope_reads(_model_result(p))}
        assert reads[name].value == pytest.approx(getattr(p, name.lower()), rel=1e-9), name
        assert reads[name].method == "slope"
    reads = {q.name: q for q in ni.slope_reads(_model_result(AllanParams(b=1e-5)))}
    assert reads["B"].value == pytest.approx(1e-5, rel=1e-12)


def test_markov_term_recovered_on_model_curve():
    qc, tc = 2e-6, 30.0
    extra = lambda tau: (qc * tc) ** 2 * ni.markov_avar_unit(tau, tc)  # noqa: E731
    res = _model_result(AllanParams(n=1e-5), extra=extra)
    fit = ni.fit_noise(res, terms=("N",), markov=True)
    assert fit.parameter("markov_tc").value == pytest.approx(tc, rel=0.25)  # T_c is profiled on a grid
    assert fit.parameter("markov_q").value == pytest.approx(qc, rel=0.3)
    plain = ni.fit_noise(res, terms=("N",))
    assert fit.chi2 < plain.chi2


def test_profile_limits_are_wald_for_separated_terms_and_reach_zero_for_collinear_ones():
    """[VENZON1988] profile interval on the GLS chi2: for terms the design separates (both well inside their
    intervals) it is the Wald interval theta +- z sd; for two terms with the same tau shape (what B, K and R become
    over the last octaves of a short record) neither is identified, so each profile set reaches zero (a bound)."""
    tau = np.geomspace(0.01, 100.0, 20)
    X = ni.basis(tau, ("N", "K"))
    theta = np.array([1e-6, 3e-8])
    a = X @ theta
    V = np.diag((0.05 * a) ** 2)
    lo, hi, _ = ni._profile_limits(X, a, V, 1.959964**2)
    sd = np.sqrt(np.diag(np.linalg.inv(X.T @ np.linalg.solve(V, X))))
    assert np.all(theta - 1.96 * sd > 0)
    np.testing.assert_allclose(lo, theta - 1.959964 * sd, rtol=1e-4)
    np.testing.assert_allclose(hi, theta + 1.959964 * sd, rtol=1e-4)
    Xc = np.column_stack([X[:, 1], 2.0 * X[:, 1], X[:, 0]])  # K twice: no record can split it
    lo_c, hi_c, _ = ni._profile_limits(Xc, a, V, 1.959964**2)
    assert lo_c[0] == 0.0 and lo_c[1] == 0.0 and lo_c[2] > 0
    assert hi_c[0] == pytest.approx(theta[1] + 1.959964 * sd[1], rel=1e-3)  # all of K's power in column 0


def test_unidentified_markov_term_prints_q_and_tc_as_bounds():
    """White noise only: the Markov term is not in the record, so markov_q and its T_c are printed as bounds (no
    point value), never as a T_c at the edge of the searched grid with an interval."""
    rng = np.random.default_rng(5)
    y = 1e-3 * rng.standard_normal(60_000)
    fit = ni.fit_noise(al.oadev(y, 100.0, channel="gyro_x"), markov=True)
    q, tc = fit.parameter("markov_q"), fit.parameter("markov_tc")
    assert q.is_upper_bound and tc.is_upper_bound
    assert math.isnan(tc.value) and tc.ci_lo == 0.0 and tc.ci_hi == pytest.approx(fit.tau_s.max() / 2, rel=1e-9)


def test_tables_and_plot():
    res = _model_result(AllanParams(n=2e-5, b=1e-5, k=1e-6))
    fits = {"gyro_x": ni.fit_noise(res)}
    tab = ni.noise_table(fits)
    assert list(tab.columns) == ni.NOISE_COLUMNS
    assert set(tab["method"]) == {"fit", "slope"}
    assert tab.loc[(tab.parameter == "N") & (tab.method == "fit"), "value"].item() == pytest.approx(2e-5, rel=1e-6)
    png = ni.plot_allan({"gyro_x": res}, fits)
    assert png[:8] == b"\x89PNG\r\n\x1a\n" and len(png) > 5000


def test_fit_rejects_too_short_curve():
    res = _model_result(AllanParams(n=2e-5), n=16)
    with pytest.raises(ValueError, match="usable taus"):
        ni.fit_noise(res)


@pytest.mark.slow
def test_monte_carlo_bias_and_coverage():
    """Reduced version of benchmarks/mc_noise_id.py: 30 seeded trials of white + flicker + RRW at 50 Hz, 1 h.

    Bias of N and K under 5 % and the 95 % intervals' coverage at least 80 % (under the nominal 95 %, fewer
    than 24 of 30 happens with probability < 1 %).
    """
    rate, hours, trials = 50.0, 1.0, 30
    p = AllanParams(n=0.07 * D2R / 60, b=0.5 * D2R / 3600, k=30 * D2R / 3600 / 60)
    rng = np.random.default_rng(20240611)
    n = int(hours * 3600 * rate)
    est = {"N": [], "K": []}
    cov = {"N": 0, "K": 0}
    for _ in range(trials):
        res = al.oadev(allan_noise(n, rate, p, rng), rate, "dense", channel="gyro_x")
        fit = ni.fit_noise(res)
        for name in est:
            k = fit.terms.index(name)
            est[name].append(math.sqrt(fit.theta[k]))
            q = fit.parameter(name)
            true = getattr(p, name.lower())
            cov[name] += q.ci_lo <= true <= q.ci_hi
    for name in est:
        bias = np.mean(est[name]) / getattr(p, name.lower()) - 1.0
        assert abs(bias) < 0.05, (name, bias)
        assert cov[name] / trials >= 0.8, (name, cov[name])


def test_docstrings_cite_only_listed_references():
    """Every [KEY] a docstring of the calibration, noise and fleet packages cites is an entry of docs/references.md,
    and no docstring points at private notes (allan.md, effects.md)."""
    import re
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    listed = set(re.findall(r"^- \*\*\[([A-Z0-9-]+)\]", (root / "docs" / "references.md").read_text(), re.M))
    assert {"IEEE952", "IEEE1293", "NIST1065", "SEED000", "SEED003", "GREENHALL2003"} <= listed
    for pkg in ("calibration", "noise", "fleet"):
        for path in (root / "assets_lib" / pkg).rglob("*.py"):
            text = path.read_text()
            cited = set(re.findall(r"\[([A-Z][A-Z0-9-]{2,})\]", text))
            assert cited <= listed, (path, cited - listed)
            assert not re.search(r"\b(allan|effects|anchors)\.md\b", text), path
