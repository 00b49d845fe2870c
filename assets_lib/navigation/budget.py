"""What a calibration buys in navigation: its coefficients' standard errors (calibrated, 1 sigma) and, for
comparison, the errors left uncorrected (the coefficients themselves), propagated into

(a) stationary alignment errors: level (accelerometer horizontal error / g) and heading (gyro east error /
    (Omega cos L)), closed forms of ``alignment`` checked against [SEED004]'s analytic alignment;
(b) free-inertial position and attitude drift after given times (default 1 min, 10 min, 1 h), by strapdown
    integration (``strapdown``) of the simulator's own profiles: ``static_long`` (at rest, level) and
    ``quick_rate`` (the rate-table motion, then at rest), at the record's site latitude.

Propagation: each term's residual error after calibration is the change of the calibrated outputs for a one-
standard-error change of the term (``assets_lib.apply.compensate.sensitivities``, GUM JCGM 100:2008 eq. 10); each
is integrated as its own case and the navigation errors are summed in quadrature (terms independent, errors small:
linear). The uncalibrated case integrates y - truth with y the record's model outputs (``forward``). Closed forms
for the free-inertial drift of a constant error at rest (single-channel Schuler loop, omega_s = sqrt(g / R);
Titterton & Weston sec. 12.3): accelerometer bias b -> position b (1 - cos omega_s t) / omega_s^2; gyro
horizontal bias eps -> position R eps (t - sin(omega_s t) / omega_s), tilt eps sin(omega_s t) / omega_s; vertical
gyro bias -> heading eps t. Sensor noise is not in this budget (it is in the record's Allan terms).
"""

from __future__ import annotations

import base64
import html
from dataclasses import dataclass

import numpy as np

from assets_lib.apply.compensate import forward, sensitivities
from assets_lib.apply.model import Calibration
from assets_lib.navigation.alignment import (
    alignment_error_closed_form,
    alignment_error_numerical,
)
from assets_lib.navigation.strapdown import (
    attitude_error_rad,
    exp_so3,
    radii_m,
    strapdown,
)
from assets_lib.sim.earth import EARTH_RATE_RADPS, normal_gravity_mps2

DEFAULT_TIMES_S = (60.0, 600.0, 3600.0)
MOTION_RATE_HZ = 20.0
AT_REST_STEP_S = 1.0


# ---------------------------------------------------------------------------------------------------------------
# Profiles
# ---------------------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Profile:
    """True body inputs at the midpoint of each integration step (what the sensor model is evaluated at), the
    equivalent step inputs that make the strapdown reproduce the true attitude and rest exactly, and the initial
    attitude (ENU)."""

    name: str
    dt_s: np.ndarray
    omega_b_radps: np.ndarray
    f_b_mps2: np.ndarray
    c_b2n0: np.ndarray
    latitude_deg: float
    height_m: float
    omega_step_radps: np.ndarray
    f_step_mps2: np.ndarray

    @property
    def t_end_s(self) -> np.ndarray:
        return np.cumsum(self.dt_s)


def plan_profile(plan_name: str, latitude_deg: float, duration_s: float, height_m: float = 0.0,
                 rate_hz: float = MOTION_RATE_HZ, rest_step_s: float = AT_REST_STEP_S, **plan_kwargs) -> Profile:
    """A plan of the simulator's library (``assets_lib.sim.plans``) as a navigation profile: steps of 1/rate_hz
    while the plan runs, then 1 s steps at rest (the table stopped) up to ``duration_s``."""
    from scipy.spatial.transform import Rotation

    from assets_lib.sim.earth import earth_rate_level, specific_force_level
    from assets_lib.sim.kinematics import body_inputs, trajectory
    from assets_lib.sim.plans import build_plan

    plan = build_plan(plan_name, **plan_kwargs)
    if plan.frame != "ENU":
        raise ValueError(f"plan {plan_name}: navigation profiles use ENU plans, this one is {plan.frame}")
    g = normal_gravity_mps2(latitude_deg, height_m)
    moving = [s for s in plan.steps if s.kind == "rate" and s.table_rate_dps != 0]
    t_motion = min(duration_s, plan.end_s + 2.0) if moving or len(plan.steps) > 1 else 0.0
    n1 = int(round(t_motion * rate_hz))
    dt = [np.full(n1, 1.0 / rate_hz)]
    rest = duration_s - n1 / rate_hz
    n2 = int(np.ceil(rest / rest_step_s - 1e-9))
    if n2 > 0:
        dt.append(np.full(n2, rest / n2))
    dt = np.concatenate(dt)
    t_mid = np.cumsum(dt) - 0.5 * dt
    bi = body_inputs(plan, t_mid, latitude_deg, g)
    # exact step increments from the kinematics (no coning or sampling error in the error-free case): the body
    # turns by Exp(w dt) = C_k^T Exp(w_ie^n dt) C_{k+1} per step (the strapdown's attitude update at rest), and
    # the step's specific force is the one its midpoint attitude needs to cancel gravity
    c = trajectory(plan, np.concatenate([[0.0], np.cumsum(dt)])).c_b2l
    w_ie = earth_rate_level(latitude_deg, "ENU")
    dth = Rotation.from_matrix(np.swapaxes(c[:-1], 1, 2) @ exp_so3(w_ie[None] * dt[:, None]) @ c[1:]).as_rotvec()
    c_mid = exp_so3(-0.5 * w_ie[None] * dt[:, None]) @ c[:-1] @ exp_so3(0.5 * dth)
    f_step = np.einsum("kji,j->ki", c_mid, specific_force_level(g, "ENU"))
    return Profile(plan_name, dt, bi.omega_b_radps, bi.f_b_mps2, c[0], latitude_deg, height_m, dth / dt[:, None], f_step)


def static_profile(latitude_deg: float, duration_s: float = DEFAULT_TIMES_S[-1], height_m: float = 0.0,
                   rest_step_s: float = AT_REST_STEP_S) -> Profile:
    return plan_profile("static_long", latitude_deg, duration_s, height_m, rest_step_s=rest_step_s,
                        static_duration_s=max(duration_s, 10.0))


def motion_profile(latitude_deg: float, duration_s: float = DEFAULT_TIMES_S[-1], height_m: float = 0.0,
                   plan_name: str = "quick_rate") -> Profile:
    return plan_profile(plan_name, latitude_deg, duration_s, height_m)


# ---------------------------------------------------------------------------------------------------------------
# Propagation
# ---------------------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class DriftResult:
    """Free-inertial errors at ``t_s``: horizontal position [m], tilt and heading [rad]; ``calibrated`` = 1-sigma
    from the terms' standard errors, ``uncalibrated`` = with the coefficients left uncorrected."""

    profile: str
    t_s: np.ndarray
    position_calibrated_m: np.ndarray
    position_uncalibrated_m: np.ndarray
    tilt_calibrated_rad: np.ndarray
    tilt_uncalibrated_rad: np.ndarray
    heading_calibrated_rad: np.ndarray
    heading_uncalibrated_rad: np.ndarray


def sensor_error_cases(cal: Calibration, profile: Profile) -> tuple[np.ndarray, np.ndarray, list[str]]:
    """(gyro, accel) error time series (cases, steps, 3): [uncalibrated, one per term with a standard error]."""
    y = forward(cal, profile.omega_b_radps, profile.f_b_mps2)
    s = sensitivities(cal, y.gyro_radps, y.accel_mps2)
    dg = np.concatenate([(y.gyro_radps - profile.omega_b_radps)[None], s.gyro])
    da = np.concatenate([(y.accel_mps2 - profile.f_b_mps2)[None], s.accel])
    names = ["uncalibrated"] + [f"{sen} {fam}{list(idx)}" for sen, _f, fam, idx in s.terms]
    return dg, da, names


def drift(cal: Calibration, profile: Profile, times_s=DEFAULT_TIMES_S) -> DriftResult:
    """Strapdown integration of the error-free case, the uncalibrated case and every term's 1-sigma case."""
    dg, da, _ = sensor_error_cases(cal, profile)
    w = np.concatenate([np.zeros((1, *profile.omega_b_radps.shape)), dg]) + profile.omega_step_radps
    f = np.concatenate([np.zeros((1, *profile.f_b_mps2.shape)), da]) + profile.f_step_mps2
    t_end = profile.t_end_s
    steps = np.array([int(np.argmin(np.abs(t_end - t))) + 1 for t in times_s])
    sol = strapdown(profile.dt_s, w, f, profile.c_b2n0, profile.latitude_deg, profile.height_m, out_steps=steps)
    dp = sol.position_en_m[1:] - sol.position_en_m[0]
    phi = attitude_error_rad(sol.c_b2n[1:], sol.c_b2n[0][None])
    pos = np.linalg.norm(dp, axis=-1)
    tilt = np.linalg.norm(phi[..., :2], axis=-1)
    head = np.abs(phi[..., 2])
    rss = lambda x: np.sqrt((x[1:] ** 2).sum(axis=0))
    return DriftResult(profile.name, sol.t_s, np.sqrt(rss(dp[..., 0]) ** 2 + rss(dp[..., 1]) ** 2), pos[0],
                       np.sqrt(rss(phi[..., 0]) ** 2 + rss(phi[..., 1]) ** 2), tilt[0], rss(phi[..., 2]), head[0])


@dataclass(frozen=True)
class AlignmentBudget:
    """Stationary alignment errors [rad] (level = RSS of both tilts), closed form and numerical ([SEED004])."""

    level_calibrated_rad: float
    level_uncalibrated_rad: float
    heading_calibrated_rad: float
    heading_uncalibrated_rad: float
    level_calibrated_numerical_rad: float
    heading_calibrated_numerical_rad: float
    level_uncalibrated_numerical_rad: float
    heading_uncalibrated_numerical_rad: float
    #: horizontal gyro error of the uncalibrated sensor / horizontal earth rate: >= 1 means it cannot find north
    uncalibrated_gyro_to_earth_rate: float


def alignment_budget(cal: Calibration, latitude_deg: float, gravity_mps2: float,
                     c_b2n: np.ndarray | None = None) -> AlignmentBudget:
    """Level and heading errors of a stationary alignment with the body at ``c_b2n`` (default level, axes ENU)."""
    c_b2n = np.eye(3) if c_b2n is None else np.asarray(c_b2n, float)
    lat = np.radians(latitude_deg)
    f_b = c_b2n.T @ np.array([0.0, 0.0, gravity_mps2])
    w_b = c_b2n.T @ (EARTH_RATE_RADPS * np.array([0.0, np.cos(lat), np.sin(lat)]))
    y = forward(cal, w_b, f_b)
    s = sensitivities(cal, y.gyro_radps, y.accel_mps2)
    df_b = np.concatenate([(y.accel_mps2 - f_b)[None, 0], s.accel[:, 0]])
    dw_b = np.concatenate([(y.gyro_radps - w_b)[None, 0], s.gyro[:, 0]])
    cf = alignment_error_closed_form(df_b @ c_b2n.T, dw_b @ c_b2n.T, latitude_deg, gravity_mps2)
    nu = alignment_error_numerical(c_b2n, df_b, dw_b, latitude_deg, gravity_mps2)

    def split(e):
        level = np.hypot(e.east_tilt_rad, e.north_tilt_rad)
        rss_level = float(np.sqrt((e.east_tilt_rad[1:] ** 2).sum() + (e.north_tilt_rad[1:] ** 2).sum()))
        return rss_level, float(level[0]), float(np.sqrt((e.heading_rad[1:] ** 2).sum())), float(abs(e.heading_rad[0]))

    a, b = split(cf), split(nu)
    ratio = float(np.hypot(*(c_b2n @ dw_b[0])[:2]) / (EARTH_RATE_RADPS * np.cos(lat)))
    return AlignmentBudget(a[0], a[1], a[2], a[3], b[0], b[2], b[1], b[3], ratio)


# ---------------------------------------------------------------------------------------------------------------
# Closed forms of free-inertial drift at rest (checked against the strapdown integration in the tests)
# ---------------------------------------------------------------------------------------------------------------
def schuler_rate_radps(latitude_deg: float, height_m: float = 0.0, channel: str = "north") -> float:
    rm, rn = radii_m(np.radians(latitude_deg))
    r = (rm if channel == "north" else rn) + height_m
    return float(np.sqrt(normal_gravity_mps2(latitude_deg, height_m) / r))


def position_from_accel_bias_m(bias_mps2, t_s, latitude_deg: float, channel: str = "north") -> np.ndarray:
    """Horizontal accelerometer bias b (along ``channel``): b (1 - cos w_s t) / w_s^2 along the same axis."""
    ws = schuler_rate_radps(latitude_deg, channel=channel)
    return np.asarray(bias_mps2) * (1 - np.cos(ws * np.asarray(t_s))) / ws**2


def position_from_gyro_bias_m(bias_radps, t_s, latitude_deg: float, axis: str = "east") -> np.ndarray:
    """Horizontal gyro bias eps about ``axis``: east -> north position -R eps (t - sin(w_s t)/w_s); north -> east
    position +R eps (t - sin(w_s t)/w_s)."""
    channel = "north" if axis == "east" else "east"
    rm, rn = radii_m(np.radians(latitude_deg))
    r = rm if channel == "north" else rn
    ws = schuler_rate_radps(latitude_deg, channel=channel)
    t = np.asarray(t_s, float)
    sign = -1.0 if axis == "east" else 1.0
    return sign * r * np.asarray(bias_radps) * (t - np.sin(ws * t) / ws)


def tilt_from_gyro_bias_rad(bias_radps, t_s, latitude_deg: float, axis: str = "east") -> np.ndarray:
    """Tilt about the biased horizontal axis: -eps sin(w_s t) / w_s."""
    ws = schuler_rate_radps(latitude_deg, channel="north" if axis == "east" else "east")
    return -np.asarray(bias_radps) * np.sin(ws * np.asarray(t_s)) / ws


def heading_from_gyro_bias_rad(bias_radps, t_s) -> np.ndarray:
    """Vertical gyro bias: heading error -eps t."""
    return -np.asarray(bias_radps) * np.asarray(t_s)


def tilt_from_accel_bias_rad(bias_mps2, t_s, latitude_deg: float, channel: str = "north") -> np.ndarray:
    """Horizontal accelerometer bias b along ``channel``: tilt (b / g)(1 - cos w_s t) about the other horizontal
    axis (north bias: about east, sign -; east bias: about north, sign +)."""
    ws = schuler_rate_radps(latitude_deg, channel=channel)
    sign = -1.0 if channel == "north" else 1.0
    g = normal_gravity_mps2(latitude_deg, 0.0)
    return sign * np.asarray(bias_mps2) / g * (1 - np.cos(ws * np.asarray(t_s)))


def rest_drift_closed_form(cal: Calibration, latitude_deg: float, times_s=DEFAULT_TIMES_S) -> DriftResult:
    """Free-inertial drift at rest, level, body axes ENU (the ``static_long`` profile) by the closed forms above,
    for the uncalibrated case and every term's 1-sigma case (constant body errors at rest: ``sensitivities`` at
    the static inputs), summed in quadrature over the terms. Milliseconds, against seconds for the strapdown
    (``drift``), which tests/test_navigation.py checks it against (within 5 %)."""
    lat = np.radians(latitude_deg)
    g = normal_gravity_mps2(latitude_deg, 0.0)
    f_b = np.array([0.0, 0.0, g])
    w_b = EARTH_RATE_RADPS * np.array([0.0, np.cos(lat), np.sin(lat)])
    y = forward(cal, w_b, f_b)
    s = sensitivities(cal, y.gyro_radps, y.accel_mps2)
    dw = np.concatenate([(y.gyro_radps - w_b)[None, 0], s.gyro[:, 0]])  # (cases, 3) E N U
    df = np.concatenate([(y.accel_mps2 - f_b)[None, 0], s.accel[:, 0]])
    t = np.asarray(times_s, float)[None, :]
    c = lambda v: np.asarray(v)[:, None]
    north = position_from_accel_bias_m(c(df[:, 1]), t, latitude_deg, "north") \
        + position_from_gyro_bias_m(c(dw[:, 0]), t, latitude_deg, "east")
    east = position_from_accel_bias_m(c(df[:, 0]), t, latitude_deg, "east") \
        + position_from_gyro_bias_m(c(dw[:, 1]), t, latitude_deg, "north")
    tilt_e = tilt_from_gyro_bias_rad(c(dw[:, 0]), t, latitude_deg, "east") \
        + tilt_from_accel_bias_rad(c(df[:, 1]), t, latitude_deg, "north")
    tilt_n = tilt_from_gyro_bias_rad(c(dw[:, 1]), t, latitude_deg, "north") \
        + tilt_from_accel_bias_rad(c(df[:, 0]), t, latitude_deg, "east")
    head = heading_from_gyro_bias_rad(c(dw[:, 2]), t)
    rss = lambda x: np.sqrt((x[1:] ** 2).sum(axis=0))
    return DriftResult("at rest (closed forms)", t[0], np.hypot(rss(north), rss(east)), np.hypot(north[0], east[0]),
                       np.hypot(rss(tilt_e), rss(tilt_n)), np.hypot(tilt_e[0], tilt_n[0]), rss(head), np.abs(head[0]))


# ---------------------------------------------------------------------------------------------------------------
# Certificate fragment
# ---------------------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class NavigationBudget:
    alignment: AlignmentBudget
    drifts: tuple[DriftResult, ...]
    latitude_deg: float
    gravity_mps2: float
    calibration_sha256: str


def navigation_budget(cal: Calibration, times_s=DEFAULT_TIMES_S, latitude_deg: float | None = None,
                      profiles=("static", "motion"), rest_step_s: float = AT_REST_STEP_S) -> NavigationBudget:
    """Alignment and drift budget of ``cal`` at the record's site (or ``latitude_deg``)."""
    lat = float(latitude_deg if latitude_deg is not None else (cal.latitude_deg if cal.latitude_deg is not None else 45.0))
    g = normal_gravity_mps2(lat, 0.0)
    dur = float(max(times_s))
    makers = {"static": lambda la, du: static_profile(la, du, rest_step_s=rest_step_s), "motion": motion_profile}
    drifts = tuple(drift(cal, makers[p](lat, dur), times_s) for p in profiles)
    return NavigationBudget(alignment_budget(cal, lat, g), drifts, lat, g, cal.identity_sha256)


def _fmt_angle(rad: float) -> str:
    deg = np.degrees(rad)
    return f"{deg * 3600:.3g}&Prime;" if deg < 1 / 60 else (f"{deg * 60:.3g}&prime;" if deg < 1 else f"{deg:.3g}&deg;")


def _fmt_len(m: float) -> str:
    return f"{m * 1000:.3g} mm" if m < 1 else (f"{m:.3g} m" if m < 1000 else f"{m / 1000:.3g} km")


def _fmt_t(t: float) -> str:
    t = round(float(t), 3)
    return f"{t / 3600:g} h" if t >= 3600 else (f"{t / 60:g} min" if t >= 60 else f"{t:g} s")


def budget_plot_png(budget: NavigationBudget) -> bytes:
    """Position and heading error against free-inertial time, calibrated (1 sigma) and uncalibrated (PNG), on the
    cheap Agg canvas of ``assets_lib.plotting`` (no pyplot, fixed margins, major log ticks only)."""
    from assets_lib.plotting import figure, log_axes, png

    fig, axes = figure(1, 2, figsize=(9, 3.4), dpi=90, margins_in=(0.72, 0.18, 0.51, 0.14))
    ax = axes[0]
    for d, style in zip(budget.drifts, ("-", "--")):
        ax[0].plot(d.t_s, d.position_uncalibrated_m, "r" + style, marker="o", label=f"uncalibrated, {d.profile}")
        ax[0].plot(d.t_s, d.position_calibrated_m, "b" + style, marker="o", label=f"calibrated 1σ, {d.profile}")
        ax[1].plot(d.t_s, np.degrees(d.heading_uncalibrated_rad), "r" + style, marker="o")
        ax[1].plot(d.t_s, np.degrees(d.heading_calibrated_rad), "b" + style, marker="o")
    ax[0].set(xlabel="free-inertial time [s]", ylabel="horizontal position error [m]")
    ax[1].set(xlabel="free-inertial time [s]", ylabel="heading error [deg]")
    ax[0].legend(fontsize=7, loc="upper left")
    for a in ax:
        log_axes(a)
        a.grid(True, which="major", alpha=0.3)
    return png(fig)


def budget_rows(budget: NavigationBudget) -> list[tuple[str, str, str]]:
    """(quantity (HTML), calibrated 1 sigma, uncalibrated) texts of the budget table."""
    a = budget.alignment
    rows = [("Alignment: level (accelerometer error / g)", _fmt_angle(a.level_calibrated_rad),
             _fmt_angle(a.level_uncalibrated_numerical_rad)),
            ("Alignment: heading (gyro east error / (&Omega; cos L))", _fmt_angle(a.heading_calibrated_rad),
             _fmt_angle(a.heading_uncalibrated_numerical_rad) if a.uncalibrated_gyro_to_earth_rate < 1 else
             f"cannot find north (gyro error {a.uncalibrated_gyro_to_earth_rate:.3g} x the horizontal earth rate)")]
    for d in budget.drifts:
        for i, t in enumerate(d.t_s):
            rows.append((f"Free inertial, {d.profile} profile, {_fmt_t(t)}: position / tilt / heading",
                         f"{_fmt_len(d.position_calibrated_m[i])} / {_fmt_angle(d.tilt_calibrated_rad[i])} / "
                         f"{_fmt_angle(d.heading_calibrated_rad[i])}",
                         f"{_fmt_len(d.position_uncalibrated_m[i])} / {_fmt_angle(d.tilt_uncalibrated_rad[i])} / "
                         f"{_fmt_angle(d.heading_uncalibrated_rad[i])}"))
    return rows


def budget_note(budget: NavigationBudget) -> str:
    """The section's explanation (plain text)."""
    names = " and ".join({"static_long": "static_long (at rest, level)",
                          "quick_rate": "quick_rate (rate-table motion, then at rest)"}.get(d.profile, d.profile)
                         for d in budget.drifts)
    return (f"Latitude {budget.latitude_deg:.4g} deg, g = {budget.gravity_mps2:.6g} m/s^2. Calibrated: the "
            "coefficients' standard errors propagated (1 sigma, terms independent); uncalibrated: the coefficients "
            "left uncorrected. Alignment by the closed forms; drift by strapdown integration of the simulator's "
            f"{names} profile{'s' if len(budget.drifts) > 1 else ''}, height aided; sensor noise not included.")


def budget_html(budget: NavigationBudget) -> str:
    """A certificate section: alignment and drift table (calibrated 1 sigma vs uncalibrated) and a PNG plot."""
    png = base64.b64encode(budget_plot_png(budget)).decode()
    return ("<h2>What the calibration buys in navigation</h2>"
            f"<p class=muted>{html.escape(budget_note(budget))}</p>"
            "<table><tr><th>Quantity</th><th>Calibrated (1&sigma;)</th><th>Uncalibrated</th></tr>"
            + "".join(f"<tr><td>{q}</td><td class=num>{c}</td><td class=num>{u}</td></tr>"
                      for q, c, u in budget_rows(budget))
            + f"</table><img alt='navigation budget' src='data:image/png;base64,{png}'>")


def certificate_calibration(device_records: list[dict], run_id: str) -> Calibration | None:
    """The device calibration a record's certificate budgets: assembled at the record's start from the device's
    records up to then (each term from the newest record holding it, so a rate run's certificate also counts the
    accelerometer terms of the position run before it). None for an invalid record or when nothing is calibrated."""
    from assets_lib.apply.model import CalibrationError, _start, assemble

    rec = next((r for r in device_records if r["content"]["run"]["run_id"] == run_id), None)
    if rec is None:
        raise ValueError(f"no record of run {run_id!r} among the device's records")
    if rec["content"].get("status") == "invalid":
        return None
    try:
        cal = assemble([r for r in device_records if _start(r) <= _start(rec)], _start(rec))
    except CalibrationError:
        return None
    return cal if cal.terms else None


#: the certificate integrates at rest in 2 s steps (the Schuler period is 84 min; tests/test_navigation.py checks
#: the result against 1 s steps: within 2 %)
CERTIFICATE_REST_STEP_S = 2.0


def certificate_budget(cal: Calibration, times_s=DEFAULT_TIMES_S) -> NavigationBudget:
    """The certificate's budget: alignment closed forms and the static_long strapdown in 2 s steps (the
    motion profile's 20 Hz strapdown, ~10 s per calibration, stays in ``navigation_budget``)."""
    return navigation_budget(cal, times_s, profiles=("static",), rest_step_s=CERTIFICATE_REST_STEP_S)


def certificate_section(device_records: list[dict], run_id: str, times_s=DEFAULT_TIMES_S) -> str:
    """The certificate's navigation section for the record of ``run_id`` (``certificate_calibration``), naming the
    records used."""
    cal = certificate_calibration(device_records, run_id)
    if cal is None:
        return ""
    return budget_html(navigation_budget(cal, times_s)).replace(
        "</p><table>", html.escape(used_records_note(cal)) + "</p><table>", 1)


def used_records_note(cal: Calibration) -> str:
    used = ", ".join(f"{r['run_id']} ({r['record_sha256'][:12]}...)" for r in cal.records)
    missing = (f"; not calibrated at that date: {', '.join(g for g in cal.missing_groups if g != 'noise')}"
               if set(cal.missing_groups) - {"noise"} else "")
    return f" Device calibration at this run's start from records {used}{missing}."
