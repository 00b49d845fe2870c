"""Simulated hand-moved (table-free) sessions with known truth: static poses of random attitude joined by
rotations about a fixed axis with a smooth sin^2 rate profile (exact attitude at every sample), raw readings
u = (T K)^-1 y + b + noise for accelerometer (y = specific force, gravity only) and gyro (y = body rate; earth
rate omitted, as the table-free fits assume). Used by tests and benchmarks/mc_tablefree_coverage.py."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation


@dataclass(frozen=True)
class HandSession:
    t_s: np.ndarray
    accel: np.ndarray
    gyro: np.ndarray
    truth: dict
    initial_static_s: float


def simulate_hand_session(rng: np.random.Generator, *, n_poses: int = 30, rate_hz: float = 100.0, pose_s=(3.0, 8.0),
                          move_s=(1.0, 2.0), initial_static_s: float = 30.0, gravity_mps2: float = 9.81,
                          accel_noise: float = 0.01, gyro_noise: float = 0.002, truth: dict | None = None) -> HandSession:
    tr = truth or {
        "accel_T": np.array([[1, 0.004, -0.006], [0, 1, 0.008], [0, 0, 1.0]]),
        "accel_k": np.array([1.01, 0.99, 1.005]),
        "accel_b": np.array([0.12, -0.08, 0.2]),
        "gyro_T": np.array([[1, 0.006, -0.004], [0.005, 1, 0.01], [-0.008, 0.003, 1.0]]),
        "gyro_k": np.array([1.02, 0.985, 1.01]),
        "gyro_b": np.array([0.01, -0.02, 0.015]),
    }
    dt = 1.0 / rate_hz
    C = Rotation.identity()
    ts, acc, gyr = [], [], []
    t0 = 0.0
    g_l = np.array([0.0, 0.0, gravity_mps2])

    def emit(n, rates, rots):
        nonlocal t0
        t = t0 + dt * np.arange(n)
        f = rots.inv().apply(g_l)
        ts.append(t); acc.append(f); gyr.append(rates)
        t0 = t[-1] + dt

    for i in range(n_poses):
        dur = initial_static_s if i == 0 else rng.uniform(*pose_s)
        n = int(dur * rate_hz)
        emit(n, np.zeros((n, 3)), Rotation.concatenate([C] * n) if n > 1 else C)
        if i == n_poses - 1:
            break
        T = rng.uniform(*move_s)
        n = int(T * rate_hz)
        axis = rng.standard_normal(3)
        axis /= np.linalg.norm(axis)
        angle = rng.uniform(np.radians(60), np.radians(150))
        tau = dt * np.arange(n)
        # angle(t) = angle * (tau/T - sin(2 pi tau/T)/(2 pi)), rate = angle/T * (1 - cos(2 pi tau/T)) (body frame)
        phi = angle * (tau / T - np.sin(2 * np.pi * tau / T) / (2 * np.pi))
        rate = angle / T * (1 - np.cos(2 * np.pi * tau / T))
        rots = C * Rotation.from_rotvec(np.outer(phi, axis))
        emit(n, np.outer(rate, axis), rots)
        C = C * Rotation.from_rotvec(angle * axis)
    t = np.concatenate(ts)
    f = np.vstack(acc)
    w = np.vstack(gyr)
    Ma = tr["accel_T"] * tr["accel_k"][None, :]
    Mg = tr["gyro_T"] * tr["gyro_k"][None, :]
    ua = np.linalg.solve(Ma, f.T).T + tr["accel_b"] + accel_noise * rng.standard_normal(f.shape)
    ug = np.linalg.solve(Mg, w.T).T + tr["gyro_b"] + gyro_noise * rng.standard_normal(w.shape)
    return HandSession(t, ua, ug, tr, initial_static_s)
