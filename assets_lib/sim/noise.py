"""Sensor noise from the IEEE 952 Allan terms (Q, N, B, K, R), generated at a sample rate.

IEEE Std 952-1997 Annex C: sigma^2(tau) = 3Q^2/tau^2 + N^2/tau + (2 ln2/pi) B^2 + K^2 tau/3 + R^2 tau^2/2,
with two-sided rate PSDs S(f) = (2 pi f)^2 Q^2 tau0 (quantization), N^2, (B^2 / 2 pi) / f, K^2 / (2 pi f)^2.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class AllanParams:
    """Allan noise coefficients of one axis, SI units.

    gyro: q [rad], n [rad/s/sqrt(Hz)], b [rad/s], k [rad/s/sqrt(s)], r [rad/s^2];
    accel: q [m/s], n [m/s^2/sqrt(Hz)], b [m/s^2], k [m/s^2/sqrt(s)], r [m/s^3].
    """

    q: float = 0.0
    n: float = 0.0
    b: float = 0.0
    k: float = 0.0
    r: float = 0.0

    def avar(self, tau_s: np.ndarray) -> np.ndarray:
        """IEEE Std 952-1997 eq. C.23: the model Allan variance at ``tau_s``."""
        tau = np.asarray(tau_s, dtype=float)
        return (
            3 * self.q**2 / tau**2
            + self.n**2 / tau
            + 2 * np.log(2) / np.pi * self.b**2
            + self.k**2 * tau / 3
            + self.r**2 * tau**2 / 2
        )

    def scaled(self, factor: float) -> "AllanParams":
        return AllanParams(*(factor * v for v in (self.q, self.n, self.b, self.k, self.r)))


def flicker_noise(n_samples: int, rate_hz: float, b: float, rng: np.random.Generator) -> np.ndarray:
    """Flicker (bias-instability) rate noise with two-sided PSD B^2/(2 pi f), by spectral shaping (IEEE 952 C.3).

    The Allan deviation plateau of the result is sqrt(2 ln2 / pi) B = 0.664 B.
    """
    if b == 0.0 or n_samples < 2:
        return np.zeros(n_samples)
    m = 1 << int(np.ceil(np.log2(n_samples)))  # power of two >= n for a fast FFT
    f = np.fft.rfftfreq(m, d=1.0 / rate_hz)
    one_sided = np.zeros_like(f)
    one_sided[1:] = b**2 / (np.pi * f[1:])  # one-sided PSD = 2 x two-sided
    amp = np.sqrt(one_sided * rate_hz * m / 4.0)
    spec = amp * (rng.standard_normal(f.size) + 1j * rng.standard_normal(f.size))
    spec[-1] = spec[-1].real * np.sqrt(2.0)  # Nyquist bin is real
    return np.fft.irfft(spec, n=m)[:n_samples]


def allan_noise(
    n_samples: int, rate_hz: float, params: AllanParams, rng: np.random.Generator, t0_s: float = 0.0
) -> np.ndarray:
    """Rate-noise samples (float64) whose Allan variance follows ``params.avar`` (IEEE Std 952-1997 Annex C).

    Quantization: white angle noise of std Q differentiated; angle random walk: white rate of std N sqrt(fs);
    bias instability: :func:`flicker_noise`; rate random walk: cumulative sum of K sqrt(dt) steps;
    rate ramp: the deterministic R t (t from ``t0_s``).
    """
    dt = 1.0 / rate_hz
    out = np.zeros(n_samples)
    if params.q:
        angle = params.q * rng.standard_normal(n_samples + 1)
        out += np.diff(angle) / dt
    if params.n:
        out += params.n * np.sqrt(rate_hz) * rng.standard_normal(n_samples)
    if params.b:
        out += flicker_noise(n_samples, rate_hz, params.b, rng)
    if params.k:
        out += np.cumsum(params.k * np.sqrt(dt) * rng.standard_normal(n_samples))
    if params.r:
        out += params.r * (t0_s + dt * np.arange(n_samples))
    return out
