"""Stochastic family: noise_model (noise stage): extra Allan terms plus a first-order Gauss-Markov process."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.signal import lfilter

from assets_lib.sim.effects.base import Effect, register
from assets_lib.sim.noise import AllanParams, allan_noise


def gauss_markov(n: int, rate_hz: float, sigma: float, tau_s: float, rng: np.random.Generator) -> np.ndarray:
    """[ELSHEIMY2008] first-order Gauss-Markov x_k = a x_(k-1) + w_k, a = exp(-dt/tau),
    stationary std ``sigma`` (w_k ~ N(0, sigma^2 (1 - a^2)), x_0 ~ N(0, sigma^2))."""
    if sigma == 0.0 or n == 0:
        return np.zeros(n)
    a = np.exp(-1.0 / (rate_hz * tau_s))
    w = sigma * np.sqrt(1 - a * a) * rng.standard_normal(n)
    x0 = sigma * rng.standard_normal()
    y, _ = lfilter([1.0], [1.0, -a], w, zi=[a * x0])
    return y


def gauss_markov_avar(tau: np.ndarray, sigma: float, tc_s: float) -> np.ndarray:
    """[ELSHEIMY2008] Allan variance of a first-order Gauss-Markov process (q_c = 2 sigma^2 / T_c)."""
    tau = np.asarray(tau, dtype=float)
    qc = 2 * sigma**2 / tc_s
    r = tau / tc_s
    return qc * tc_s**2 / tau * (1 - (3 - 4 * np.exp(-r) + np.exp(-2 * r)) / (2 * r))


@register
@dataclass(frozen=True)
class NoiseModel(Effect):
    """[IEEE952] Annex C Allan terms (Q, N, B, K, R) plus a first-order Gauss-Markov term ([ELSHEIMY2008]), added
    to the base noise of every axis of a triad (independent processes: Allan variances add).

    Units: gyro q [rad], n [rad/s/sqrt(Hz)], b [rad/s], k [rad/s/sqrt(s)], r [rad/s^2], gm_sigma [rad/s],
    gm_tau [s]; accelerometer the same with m/s for rad.
    """

    family = "noise_model"
    stage = "noise"
    gyro_q_rad: float = 0.0
    gyro_n_radps_per_rthz: float = 0.0
    gyro_b_radps: float = 0.0
    gyro_k_radps_per_rts: float = 0.0
    gyro_r_radps2: float = 0.0
    gyro_gm_sigma_radps: float = 0.0
    gyro_gm_tau_s: float = 1.0
    accel_q_mps: float = 0.0
    accel_n_mps2_per_rthz: float = 0.0
    accel_b_mps2: float = 0.0
    accel_k_mps2_per_rts: float = 0.0
    accel_r_mps3: float = 0.0
    accel_gm_sigma_mps2: float = 0.0
    accel_gm_tau_s: float = 1.0

    def allan(self, triad: str) -> AllanParams:
        if triad == "gyro":
            return AllanParams(self.gyro_q_rad, self.gyro_n_radps_per_rthz, self.gyro_b_radps, self.gyro_k_radps_per_rts,
                               self.gyro_r_radps2)
        return AllanParams(self.accel_q_mps, self.accel_n_mps2_per_rthz, self.accel_b_mps2, self.accel_k_mps2_per_rts,
                           self.accel_r_mps3)

    def apply(self, ctx, gyro, accel):
        n = ctx.t_s.size
        out = []
        for triad, y, sig, tc in (("gyro", gyro, self.gyro_gm_sigma_radps, self.gyro_gm_tau_s),
                                  ("accel", accel, self.accel_gm_sigma_mps2, self.accel_gm_tau_s)):
            p = self.allan(triad)
            y = y.copy()
            for i in range(3):
                y[:, i] += allan_noise(n, ctx.rate_hz, p, ctx.rng) + gauss_markov(n, ctx.rate_hz, sig, tc, ctx.rng)
            out.append(y)
        return out[0], out[1]
