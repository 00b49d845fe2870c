"""Navigation budget: the strapdown integration keeps an error-free IMU at rest; the closed forms (alignment:
level = accel error / g, heading = gyro east error / (Omega cos L); free-inertial Schuler drift) agree with the
strapdown integration and seed 004's analytic alignment within 5 %; a record's budget and certificate fragment."""

from __future__ import annotations

import base64
import re
from datetime import timedelta

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from assets_lib.apply import assemble
from assets_lib.navigation import alignment as al
from assets_lib.navigation import budget as bd
from assets_lib.navigation.strapdown import attitude_error_rad, strapdown
from assets_lib.sim.earth import EARTH_RATE_RADPS, normal_gravity_mps2
from assets_lib.sim.simulator import example_device
from tests.record_factory import T0, fitted_record

LAT = 34.25
G0 = normal_gravity_mps2(LAT, 0.0)
TIMES = (60.0, 600.0, 3600.0)
DEGPH = np.radians(1 / 3600)


@pytest.fixture(scope="module")
def static():
    return bd.static_profile(LAT, 3600.0)


def _run(profile, dw_b, df_b):
    """Strapdown of the error-free case and of each (gyro, accel) body error case; errors at TIMES."""
    k = len(dw_b)
    w = np.concatenate([np.zeros((1, 3)), np.asarray(dw_b)])[:, None, :] + profile.omega_step_radps
    f = np.concatenate([np.zeros((1, 3)), np.asarray(df_b)])[:, None, :] + profile.f_step_mps2
    steps = [int(np.argmin(np.abs(profile.t_end_s - t))) + 1 for t in TIMES]
    sol = strapdown(profile.dt_s, w, f, profile.c_b2n0, LAT, out_steps=steps)
    assert len(sol.t_s) == 3 and k >= 1
    return sol, sol.position_en_m[1:] - sol.position_en_m[0], attitude_error_rad(sol.c_b2n[1:], sol.c_b2n[0][None])


def test_error_free_imu_stays_at_rest(static):
    from assets_lib.sim.kinematics import trajectory
    from assets_lib.sim.plans import build_plan

    for profile in (static, bd.motion_profile(LAT, 1200.0)):
        n = len(profile.dt_s)
        sol = strapdown(profile.dt_s, profile.omega_step_radps, profile.f_step_mps2, profile.c_b2n0, LAT,
                        out_steps=[n // 2, n])
        assert np.abs(sol.position_en_m).max() < 1e-3  # m, after 1 h at rest / 20 min incl. the rate-table motion
        # the attitude follows the simulator's kinematics
        c_true = trajectory(build_plan(profile.name), sol.t_s).c_b2l
        assert np.abs(attitude_error_rad(sol.c_b2n[0], c_true)).max() < 1e-9
        # the step inputs are the true rates and forces to within the step's sampling (not a different motion)
        assert np.abs(profile.omega_step_radps - profile.omega_b_radps).max() < 0.05 * np.abs(profile.omega_b_radps).max()


def test_free_inertial_closed_forms_match_strapdown_within_5_percent(static):
    b, eps = 1e-3 * G0, 1.0 * DEGPH
    assert np.allclose(static.c_b2n0, np.eye(3))  # static_long: body axes = ENU, so body errors are nav errors
    cases = [([0, 0, 0], [0, b, 0]), ([0, 0, 0], [b, 0, 0]), ([eps, 0, 0], [0, 0, 0]), ([0, eps, 0], [0, 0, 0]),
             ([0, 0, eps], [0, 0, 0])]
    _, dp, phi = _run(static, [c[0] for c in cases], [c[1] for c in cases])
    t = np.array(TIMES)
    checks = [
        (dp[0, :, 1], bd.position_from_accel_bias_m(b, t, LAT, "north")),   # north accel bias -> north position
        (dp[1, :, 0], bd.position_from_accel_bias_m(b, t, LAT, "east")),    # east accel bias -> east position
        (dp[2, :, 1], bd.position_from_gyro_bias_m(eps, t, LAT, "east")),   # east gyro bias -> north position
        (dp[3, :, 0], bd.position_from_gyro_bias_m(eps, t, LAT, "north")),  # north gyro bias -> east position
        (phi[2, :, 0], bd.tilt_from_gyro_bias_rad(eps, t, LAT, "east")),    # east gyro bias -> east tilt
        (phi[3, :, 1], bd.tilt_from_gyro_bias_rad(eps, t, LAT, "north")),
        (phi[4, :, 2], bd.heading_from_gyro_bias_rad(eps, t)),              # up gyro bias -> heading
    ]
    for i, (num, closed) in enumerate(checks):
        rel = np.abs(num - closed) / np.abs(closed)
        assert rel.max() < 0.05, (i, num, closed, rel)
    # and the forms are not trivially equal: Schuler bounds the accelerometer case (1 h: far below b t^2 / 2)
    assert abs(dp[0, 2, 1]) < 0.2 * 0.5 * b * 3600**2


@pytest.mark.parametrize("euler_deg", [(0, 0, 0), (40, 3, -5), (200, -20, 10)])
def test_alignment_closed_forms_match_analytic_alignment(euler_deg):
    c = Rotation.from_euler("zyx", euler_deg, degrees=True).as_matrix()
    rng = np.random.default_rng(1)
    for _ in range(5):
        df_n = 2e-3 * rng.standard_normal(3)
        dw_n = 0.5 * DEGPH * rng.standard_normal(3)
        num = al.alignment_error_numerical(c, c.T @ df_n, c.T @ dw_n, LAT, G0)
        cf = al.alignment_error_closed_form(df_n, dw_n, LAT, G0)
        # 5 % of the size of the contributing terms (the heading is a sum of a gyro and an accelerometer term)
        head_scale = abs(dw_n[0]) / (EARTH_RATE_RADPS * np.cos(np.radians(LAT))) + abs(df_n[0]) / G0 * np.tan(np.radians(LAT))
        for a, b, scale in ((num.east_tilt_rad, cf.east_tilt_rad, abs(df_n[1]) / G0),
                            (num.north_tilt_rad, cf.north_tilt_rad, abs(df_n[0]) / G0),
                            (num.heading_rad, cf.heading_rad, head_scale)):
            assert abs(a - b) <= 0.05 * scale, (a, b, scale)
    # the heading closed form: 1 deg/h east gyro error at this latitude is 1/(15.04 cos L) rad
    h = al.alignment_error_closed_form(np.zeros(3), np.array([DEGPH, 0, 0]), LAT, G0).heading_rad
    assert h == pytest.approx(-DEGPH / (EARTH_RATE_RADPS * np.cos(np.radians(LAT))))


@pytest.fixture(scope="module")
def budget():
    truth = example_device("TAC-N01", "tactical", 5).for_power_cycle(0, 5)
    rate, _, _ = fitted_record(truth, "quick_rate", "a-rate", 1, T0)
    pos, _, _ = fitted_record(truth, "quick_24_position", "a-pos24", 1, T0 + timedelta(hours=1))
    cal = assemble([rate, pos], T0 + timedelta(days=1))
    return cal, bd.navigation_budget(cal, times_s=(60.0, 600.0), latitude_deg=LAT)


def test_record_budget(budget):
    cal, b = budget
    a = b.alignment
    # closed forms (certificate) vs the analytic alignment, calibrated 1 sigma
    assert a.level_calibrated_rad == pytest.approx(a.level_calibrated_numerical_rad, rel=0.05)
    assert a.heading_calibrated_rad == pytest.approx(a.heading_calibrated_numerical_rad, rel=0.05)
    # the calibration helps: level errors x10 smaller; the uncalibrated tactical gyro cannot gyrocompass here
    assert a.level_calibrated_rad < 0.1 * a.level_uncalibrated_numerical_rad
    assert a.uncalibrated_gyro_to_earth_rate > 1
    for d in b.drifts:
        assert np.all(d.position_calibrated_m < 0.2 * d.position_uncalibrated_m), d
        assert np.all(np.diff(d.position_calibrated_m) > 0)
    assert {d.profile for d in b.drifts} == {"static_long", "quick_rate"}
    # the calibrated static drift is dominated by the gyro bias standard errors: compare with the closed form of
    # the RSS of the horizontal gyro bias stderrs (a lower bound: other terms add)
    s = next(d for d in b.drifts if d.profile == "static_long")
    sig = np.hypot(*[t.stderr for t in cal.terms if t.coefficient == "bias" and t.sensor == "gyro" and t.axis in "xy"])
    lower = abs(bd.position_from_gyro_bias_m(sig, 600.0, LAT, "east"))
    assert lower < s.position_calibrated_m[1] < 10 * lower


def test_certificate_fragment(budget):
    _, b = budget
    frag = bd.budget_html(b)
    assert frag.startswith("<h2>") and frag.count("<tr>") == 1 + 2 + 2 * 2
    assert "cannot find north" in frag
    png = base64.b64decode(re.search(r"base64,([A-Za-z0-9+/=]+)'", frag).group(1))
    assert png[:8] == b"\x89PNG\r\n\x1a\n"


def test_certificate_section_uses_the_device_calibration_at_the_record():
    truth = example_device("TAC-N01", "tactical", 5).for_power_cycle(0, 5)
    rate, _, _ = fitted_record(truth, "quick_rate", "a-rate", 1, T0)
    pos, _, _ = fitted_record(truth, "quick_24_position", "a-pos24", 1, T0 + timedelta(hours=1))
    frag = bd.certificate_section([rate, pos], "a-pos24", times_s=(60.0,))
    assert "a-rate" in frag and "a-pos24" in frag and "not calibrated" not in frag
    first = bd.certificate_section([rate, pos], "a-rate", times_s=(60.0,))
    assert "not calibrated at that date: accel" in first


def test_certificate_budget_matches_the_fine_strapdown(budget):
    """The certificate integrates at rest in 2 s steps: within 2 % of 1 s steps (calibrated and uncalibrated)."""
    cal, _ = budget
    coarse = bd.certificate_budget(cal, times_s=TIMES).drifts[0]
    fine = bd.navigation_budget(cal, times_s=TIMES, profiles=("static",)).drifts[0]
    for f in ("position_calibrated_m", "position_uncalibrated_m", "tilt_calibrated_rad", "tilt_uncalibrated_rad",
              "heading_calibrated_rad", "heading_uncalibrated_rad"):
        np.testing.assert_allclose(getattr(coarse, f), getattr(fine, f), rtol=0.02, err_msg=f)


def test_certificate_shows_the_budget_and_verify_recomputes_it():
    """The budget on the certificate: a table and plot from the device calibration at the record's start, embedded
    as hashed JSON; certificate_problems (imulab verify CERT.html) recomputes every printed value from it."""
    import json

    from assets_lib.records.canonical import content_sha256
    from assets_lib.records.certificate import (
        DEVICE_CALIBRATION_ID,
        NAV_PLOT,
        certificate_html,
        certificate_problems,
        parse_certificate,
    )

    def full(rec, run):  # the factory's records lack the plan counts the certificate prints: filled in, re-hashed
        plan = rec["content"]["test_conditions"]["plan"]
        steps = run.manifest.plan.steps
        plan.update(n_steps=len(steps), n_rate_steps=sum(s.kind == "rate" for s in steps),
                    n_static_steps=sum(s.kind == "static" for s in steps), duration_s=float(run.manifest.plan.end_s))
        rec["record_sha256"] = content_sha256(rec["content"])
        return rec

    truth = example_device("TAC-N01", "tactical", 5).for_power_cycle(0, 5)
    rate = full(*fitted_record(truth, "quick_rate", "a-rate", 1, T0)[:2])
    pos = full(*fitted_record(truth, "quick_24_position", "a-pos24", 1, T0 + timedelta(hours=1))[:2])
    cal = bd.certificate_calibration([rate, pos], "a-pos24")
    assert {r["run_id"] for r in cal.records} == {"a-rate", "a-pos24"}
    page = certificate_html(pos, {}, cal)
    rec, problems = certificate_problems(page)
    assert problems == [] and rec["record_sha256"] == pos["record_sha256"]
    cert = parse_certificate(page)
    nav = {k: v[0] for k, v in cert.cells.items() if k.startswith("nav/")}
    assert len(nav) == 2 * (2 + 3) and NAV_PLOT in cert.plots and cert.plots[NAV_PLOT][:4] == b"\x89PNG"
    assert "cannot find north" in nav["nav/1/uncalibrated"] and "km" in nav["nav/4/calibrated"]
    # a certificate without a device calibration has no budget (and still verifies)
    assert certificate_problems(certificate_html(pos, {}))[1] == []
    # an edited budget value is caught
    bad = page.replace(f">{nav['nav/4/calibrated']}<", ">1 m / 1&prime; / 1&prime;<", 1)
    assert bad != page and any("nav/4/calibrated" in p for p in certificate_problems(bad)[1])
    # an edited embedded calibration (hash no longer matching) is caught
    doc = cert.device_calibration
    edited = json.loads(json.dumps(doc))
    edited["terms"][0]["stderr"] *= 0.1
    swap = lambda d: page.replace(json.dumps(doc, sort_keys=True, separators=(",", ":"), ensure_ascii=False),
                                  json.dumps(d, sort_keys=True, separators=(",", ":"), ensure_ascii=False))
    assert swap(edited) != page
    assert any("device calibration cannot be read" in p for p in certificate_problems(swap(edited))[1])
    # ... and so is one re-hashed to claim smaller uncertainties for this record's own terms
    import hashlib

    body = {k: v for k, v in edited.items() if k != "calibration_sha256"}
    i = next(i for i, t in enumerate(body["terms"]) if t["run_id"] == "a-pos24")
    body["terms"][i]["value"] += 1e-3
    body["calibration_sha256"] = hashlib.sha256(json.dumps(body, sort_keys=True, separators=(",", ":"),
                                                           ensure_ascii=False).encode()).hexdigest()
    assert any("is not this record's value" in p for p in certificate_problems(swap(body))[1])
    # the script id the stage and verify share
    assert f"id='{DEVICE_CALIBRATION_ID}'" in page
    # an invalid record gets no budget
    assert bd.certificate_calibration([rate, {**pos, "content": {**pos["content"], "status": "invalid"}}], "a-pos24") is None
