"""Sensor noise from the IEEE 952 Allan terms (Q, N, B, K, R), generated at a sample rate.

IEEE Std 952-1997 Annex C: sigma^2(tau) = 3Q^2/tau^2 + N^2/tau + (2 ln2/pi) B^2 + K^2 tau/3 + R^2 tau^2/2,
with two-sided rate PSDs S(f) = (2 pi f)^2 Q^2 tau0 (quantization), N^2, (B^2 / 2 pi) / f, K^2 / (2 pi f)^2.
"""

from __future__ import annotations

from contextlib import contextmanager
from dataclasses import dataclass

import numpy as np
from scipy import fft as sp_fft

FLICKER_SPAN_FACTOR = 6.0  # spectral block / run length (flicker_noise)


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

    def scaled(self, factor: float) -> AllanParams:
        return AllanParams(*(factor * v for v in (self.q, self.n, self.b, self.k, self.r)))


def flicker_noise(n_samples: int, rate_hz: float, b: float, rng: np.random.Generator,
                  span_factor: float = FLICKER_SPAN_FACTOR) -> np.ndarray:
    """Flicker (bias-instability) rate noise with two-sided PSD B^2/(2 pi f), by spectral shaping (IEEE 952 C.3).

    The Allan deviation plateau of the result is sqrt(2 ln2 / pi) B = 0.664 B.

    The spectrum is shaped on a block ``span_factor`` times longer than the run (its mean, the DC bin, is zero)
    and the run is the start of the block. The block length sets how far the run's mean wanders from the
    device's bias: on a block as long as the run (the previous power-of-two block) the run mean is exactly the
    bias and contrasts between the run's halves keep only 58 % of their 1/f variance; with the default 6 the
    run mean wanders by the Allan floor at the run length, (2 ln2 / pi) B^2 (measured 1.03 and 1.09 of it over
    1,500 runs of 2,000 and 3,001 samples): the convention of the fits' bias uncertainty
    (calibration.fit_core.flicker_gls). Memory: one
    complex spectrum of span_factor * n_samples / 2 bins.
    """
    if b == 0.0 or n_samples < 2:
        return np.zeros(n_samples)
    m = sp_fft.next_fast_len(int(np.ceil(max(span_factor, 1.0) * n_samples)), real=True)
    amp = _flicker_amplitude(m, float(rate_hz), float(b))
    spec = np.empty(amp.size, dtype=complex)  # amp (re + i im), without complex temporaries (same arithmetic)
    spec.real = rng.standard_normal(amp.size)
    spec.imag = rng.standard_normal(amp.size)
    spec *= amp
    if m % 2 == 0:
        spec[-1] = spec[-1].real * np.sqrt(2.0)  # Nyquist bin is real
    return np.fft.irfft(spec, n=m)[:n_samples]


_SHAPES: dict | None = None


def _flicker_amplitude(m: int, rate_hz: float, b: float) -> np.ndarray:
    """Spectral amplitude of :func:`flicker_noise` on an m-point block; memoised inside :func:`flicker_shape_cache`."""
    if _SHAPES is not None and (m, rate_hz, b) in _SHAPES:
        return _SHAPES[(m, rate_hz, b)]
    f = np.fft.rfftfreq(m, d=1.0 / rate_hz)
    one_sided = np.zeros_like(f)
    one_sided[1:] = b**2 / (np.pi * f[1:])  # one-sided PSD = 2 x two-sided
    amp = np.sqrt(one_sided * rate_hz * m / 4.0)
    if _SHAPES is not None:
        amp.flags.writeable = False
        _SHAPES[(m, rate_hz, b)] = amp
    return amp


@contextmanager
def flicker_shape_cache():
    """Within this block the flicker spectral amplitude of each (block length, rate, B) is computed once: replicates
    of a device redraw only the random phases (the same arithmetic on the same values, so bit-identical)."""
    global _SHAPES
    prev = _SHAPES
    _SHAPES = {} if prev is None else prev
    try:
        yield _SHAPES
    finally:
        _SHAPES = prev


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
