"""Known-truth PLATEAU TABLES straight from the sensor error model of docs/design.md (test helper).

Deliberately independent of the fitting code: orientations are built from the plan descriptions in the seeds
(ENU axes named N/W/Up...), earth rate Omega [0, cos lat, sin lat], f^l = [0, 0, g], f_b = C_b^l.T f^l, and

    gyro:  y_g = diag(K_g) (I + E_g) omega_b + b_g + G_g f_b + n_g
    accel: y_a = diag(K_a) (I + E_a) f_b + b_a + K2_a f_b**2 + sum_{j!=i} Kc_a[i, j] f_b[i] f_b[j] + n_a

Rate plateaus are whole revolutions about the local vertical, so the horizontal earth rate averages to zero
and the body-axis reference input is (table rate + Omega sin lat) along the vertical body axis.
Noise: each plateau mean gets N(0, sem^2) with the sem reported in the table (optionally the sem is scaled
by ``sem_misreport`` to emulate an estimated sem), plus optional correlated drift across plateaus.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import pandas as pd

OMEGA_E = 7.2921150e-5
AX = ("x", "y", "z")
ENU = {"E": (1, 0, 0), "W": (-1, 0, 0), "N": (0, 1, 0), "S": (0, -1, 0), "U": (0, 0, 1), "D": (0, 0, -1)}


def mount(x: str, y: str, z: str) -> np.ndarray:
    """C_b^l whose columns are the body axes expressed in ENU (e.g. mount('N', 'W', 'U'))."""
    C = np.column_stack([ENU[x], ENU[y], ENU[z]]).astype(float)
    assert np.allclose(C.T @ C, np.eye(3)) and np.linalg.det(C) > 0
    return C


def rot(axis: int, ang: float) -> np.ndarray:
    c, s = np.cos(ang), np.sin(ang)
    R = np.eye(3)
    j, k = [(1, 2), (2, 0), (0, 1)][axis]
    R[j, j], R[j, k], R[k, j], R[k, k] = c, -s, s, c
    return R


def plan_24_position() -> list[np.ndarray]:
    """Seed 003: (a) x N, y W, z Up about x; (b) x Up, y N, z W about y; (c) x W, y Up, z N about z; 8 x 45 deg."""
    out = []
    for (m, axis) in ((mount("N", "W", "U"), 0), (mount("U", "N", "W"), 1), (mount("W", "U", "N"), 2)):
        for k in range(8):
            out.append(m @ rot(axis, np.radians(45.0 * k)))
    return out


def plan_8_position() -> list[np.ndarray]:
    """Seed 000: (a) x N, y W, z Up; (b) x E, y N, z Up; (c) x Up, y E, z N; each turned about the north-pointing
    body axis through 0, 1, 4, 8, 15, 25, 35, 45 deg."""
    angles = (0, 1, 4, 8, 15, 25, 35, 45)
    out = []
    for (m, axis) in ((mount("N", "W", "U"), 0), (mount("E", "N", "U"), 1), (mount("U", "E", "N"), 2)):
        for a in angles:
            out.append(m @ rot(axis, np.radians(a)))
    return out


def plan_6_position() -> list[np.ndarray]:
    """Each body axis up and down."""
    return [mount("E", "N", "U"), mount("W", "N", "D"), mount("N", "U", "E"), mount("S", "D", "E"),
            mount("U", "E", "N"), mount("D", "W", "N")]


def plan_tumble_12(axis_in: int = 0) -> list[np.ndarray]:
    """Seed 001 style: the sensing axis tumbled about a horizontal axis in 30 deg steps (a_i = g sin theta)."""
    # body z along north (horizontal, the tumble axis), x starts horizontal east -> a_x = g sin(theta)
    m = mount("E", "U", "S") if axis_in == 0 else None
    return [m @ rot(2, np.radians(30.0 * k)) for k in range(12)]


@dataclass
class Truth:
    Kg: np.ndarray = field(default_factory=lambda: np.ones(3))
    Eg: np.ndarray = field(default_factory=lambda: np.zeros((3, 3)))
    bg: np.ndarray = field(default_factory=lambda: np.zeros(3))
    Gg: np.ndarray = field(default_factory=lambda: np.zeros((3, 3)))
    Ka: np.ndarray = field(default_factory=lambda: np.ones(3))
    Ea: np.ndarray = field(default_factory=lambda: np.zeros((3, 3)))
    ba: np.ndarray = field(default_factory=lambda: np.zeros(3))
    K2a: np.ndarray = field(default_factory=lambda: np.zeros(3))
    Kca: np.ndarray = field(default_factory=lambda: np.zeros((3, 3)))


def random_truth(rng: np.random.Generator, grade: str = "tactical") -> Truth:
    """Plausible coefficients: tactical FOG + quartz-like accelerometer, or MEMS."""
    if grade == "mems":
        sk, se, sb, sg = 3e-3, 2e-3, np.radians(0.2), np.radians(0.05) / 9.8
        ska, sea, sba, sk2 = 3e-3, 2e-3, 0.05, 2e-4
    else:
        sk, se, sb, sg = 1e-4, 1e-4, np.radians(1.0 / 3600), np.radians(0.2 / 3600) / 9.8
        ska, sea, sba, sk2 = 2e-4, 1e-4, 5e-3, 2e-5
    off = ~np.eye(3, dtype=bool)
    t = Truth()
    t.Kg = 1 + sk * rng.standard_normal(3)
    t.Eg = np.where(off, se * rng.standard_normal((3, 3)), 0.0)
    t.bg = sb * rng.standard_normal(3)
    t.Gg = sg * rng.standard_normal((3, 3))
    t.Ka = 1 + ska * rng.standard_normal(3)
    t.Ea = np.where(off, sea * rng.standard_normal((3, 3)), 0.0)
    t.ba = sba * rng.standard_normal(3)
    t.K2a = sk2 * rng.standard_normal(3)
    t.Kca = np.where(off, sk2 * rng.standard_normal((3, 3)), 0.0)
    return t


def gyro_out(t: Truth, w: np.ndarray, f: np.ndarray) -> np.ndarray:
    return (np.diag(t.Kg) @ (np.eye(3) + t.Eg) @ w.T).T + t.bg + (t.Gg @ f.T).T


def accel_out(t: Truth, f: np.ndarray) -> np.ndarray:
    y = (np.diag(t.Ka) @ (np.eye(3) + t.Ea) @ f.T).T + t.ba + t.K2a * f**2
    for i in range(3):
        for j in range(3):
            if i != j:
                y[:, i] += t.Kca[i, j] * f[:, i] * f[:, j]
    return y


def _frame(rows: list[dict]) -> pd.DataFrame:
    return pd.DataFrame(rows)


def build_table(
    truth: Truth,
    steps: list[dict],
    *,
    rng: np.random.Generator,
    lat_deg: float = 45.0,
    g: float = 9.80,
    gyro_sem: float | np.ndarray = 1e-6,
    accel_sem: float | np.ndarray = 1e-4,
    device_id: str = "DEV1",
    run_id: str = "R1",
    sem_misreport: float = 1.0,
    drift_gyro: float = 0.0,
    drift_accel: float = 0.0,
    clip_gyro: float | None = None,
) -> pd.DataFrame:
    """Plateau table for steps [{'kind': 'rate'|'static', 'C': C_b^l, 'rate': rad/s about local Up}].

    ``drift_*``: standard deviation of a random-walk increment per plateau added to every channel (correlated
    noise across plateaus, not described by the sems). ``clip_gyro``: output saturation level [rad/s].
    """
    lat = np.radians(lat_deg)
    w_ie = OMEGA_E * np.array([0.0, np.cos(lat), np.sin(lat)])
    f_l = np.array([0.0, 0.0, g])
    rows = []
    n = len(steps)
    gs = np.broadcast_to(np.asarray(gyro_sem, float), (n, 3)) if np.ndim(gyro_sem) < 2 else np.asarray(gyro_sem)
    as_ = np.broadcast_to(np.asarray(accel_sem, float), (n, 3)) if np.ndim(accel_sem) < 2 else np.asarray(accel_sem)
    W = np.zeros((n, 3))
    F = np.zeros((n, 3))
    WE = np.zeros((n, 3))
    for k, s in enumerate(steps):
        C = s["C"]
        f_b = C.T @ f_l
        e_b = C.T @ w_ie
        if s["kind"] == "rate":
            up_b = C.T @ np.array([0.0, 0.0, 1.0])
            # whole revolutions about local Up: horizontal earth rate averages out
            we = (e_b @ up_b) * up_b
            W[k] = s["rate"] * up_b + we
            WE[k] = we
        else:
            W[k] = e_b
            WE[k] = e_b
        F[k] = f_b
    yg = gyro_out(truth, W, F) + gs * rng.standard_normal((n, 3))
    ya = accel_out(truth, F) + as_ * rng.standard_normal((n, 3))
    if drift_gyro:
        yg += np.cumsum(drift_gyro * rng.standard_normal((n, 3)), axis=0)
    if drift_accel:
        ya += np.cumsum(drift_accel * rng.standard_normal((n, 3)), axis=0)
    if clip_gyro is not None:
        yg = np.clip(yg, -clip_gyro, clip_gyro)
    t0 = 0.0
    for k, s in enumerate(steps):
        dur = s.get("duration", 60.0)
        row = dict(device_id=device_id, run_id=run_id, step_index=k, kind=s["kind"], t_start_s=t0, t_end_s=t0 + dur,
                   n_samples=int(dur * 100), n_rejected=0, rejected_fraction=0.0,
                   commanded_rate_radps=float(s.get("rate", 0.0)),
                   revolutions=float(abs(s.get("rate", 0.0)) * dur / (2 * np.pi)))
        for i, a in enumerate(AX):
            row[f"gyro_{a}_radps_mean"] = yg[k, i]
            row[f"gyro_{a}_radps_sem"] = gs[k, i] * sem_misreport
        for i, a in enumerate(AX):
            row[f"accel_{a}_mps2_mean"] = ya[k, i]
            row[f"accel_{a}_mps2_sem"] = as_[k, i] * sem_misreport
        row["temperature_degc_mean"] = 25.0
        for i, a in enumerate(AX):
            row[f"omega_ref_{a}_radps"] = W[k, i]
            row[f"omega_earth_{a}_radps"] = WE[k, i]
            row[f"f_ref_{a}_mps2"] = F[k, i]
        row["flagged"] = False
        row["flag_reason"] = ""
        rows.append(row)
        t0 += dur + 10.0
    return _frame(rows)


def rate_steps(rates_dps=(1, 5, 10, 20, 50, 100, 200, 300), axes=("z", "x", "y"), zero: bool = True) -> list[dict]:
    """Seed 000 rate test: each body axis up in turn (z up: x E, y N; x up; y up), +/- rates about Up."""
    mounts = {"z": mount("E", "N", "U"), "x": mount("U", "E", "N"), "y": mount("N", "U", "E")}
    steps = []
    for a in axes:
        C = mounts[a]
        if zero:
            steps.append({"kind": "static", "C": C})
        for r in rates_dps:
            for sgn in (+1, -1):
                steps.append({"kind": "rate", "C": C, "rate": sgn * np.radians(r)})
    return steps


def static_steps(orientations: list[np.ndarray]) -> list[dict]:
    return [{"kind": "static", "C": C} for C in orientations]
