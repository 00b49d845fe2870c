"""Static poses of a hand-moved (table-free) session: where the IMU was held still, without a plan of timings.

The statistic is imu_tk's ([TEDALDI2014] Sec. IV-A): the norm of the
per-axis variances of the accelerometer over a centred sliding window, here also (optionally) of the gyro. A
sample is static when the statistic is below ``k`` times its static level. The static level is the variance
over a declared initial static interval when there is one (imu_tk), otherwise a low quantile of the windowed
statistic (the quietest part of the record).

Quantized and interpolated streams (an accelerometer sampled slower than the gyro and repeated or linearly
interpolated, so many consecutive samples carry one value) make the windowed variance of a still sensor
collapse towards zero in some windows and not in others; a threshold derived from such a level rejects genuine
poses. The level is therefore floored at the variance of a uniform quantizer, q^2/12 per axis (q estimated from
the data), and the windowed statistic is computed on the whole record (a pose of any length >= ``min_pose_s``
is kept: no nominal pose length is assumed).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.ndimage import uniform_filter1d

from assets_lib.calibration.outliers import estimate_resolution


@dataclass(frozen=True)
class StaticPoses:
    """Static intervals as sample index ranges ``[start, end)`` with the detector's statistic and threshold."""

    starts: np.ndarray
    ends: np.ndarray
    statistic: np.ndarray          # windowed accel variance norm per sample (input units^2)
    level: float                   # static level of the statistic
    threshold: float               # k * level
    k: float
    window: int

    @property
    def count(self) -> int:
        return int(self.starts.size)

    def mask(self, n: int) -> np.ndarray:
        m = np.zeros(n, bool)
        for a, b in zip(self.starts, self.ends):
            m[a:b] = True
        return m


def moving_variance_norm(x: np.ndarray, window: int) -> np.ndarray:
    """Norm over axes of the centred moving variance (window samples, edges reflected)."""
    x = np.asarray(x, float)
    x = x - np.median(x, axis=0)
    m1 = uniform_filter1d(x, window, axis=0, mode="reflect")
    m2 = uniform_filter1d(x * x, window, axis=0, mode="reflect")
    return np.sqrt(np.sum(np.maximum(m2 - m1 * m1, 0.0) ** 2, axis=1))


def quantizer_variance_norm(x: np.ndarray) -> float:
    """Norm over axes of q^2/12 (the variance of a uniform quantizer) with q estimated per axis (0 if unquantized)."""
    q = np.array([estimate_resolution(x[:, j]) or 0.0 for j in range(x.shape[1])])
    return float(np.sqrt(np.sum((q * q / 12.0) ** 2)))


def _runs(mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    d = np.diff(np.r_[0, mask.astype(np.int8), 0])
    return np.flatnonzero(d == 1), np.flatnonzero(d == -1)


def detect_static_poses(
    t_s: np.ndarray,
    accel: np.ndarray,
    *,
    window_s: float = 1.0,
    k: float = 6.0,
    min_pose_s: float = 1.0,
    reference: slice | None = None,
    level_quantile: float = 0.05,
    gyro: np.ndarray | None = None,
    k_gyro: float | None = None,
) -> StaticPoses:
    """Static intervals: windowed accelerometer variance norm < k x static level ([TEDALDI2014] Sec. IV-A).

    ``reference`` (a sample slice of a known static interval, e.g. imu_tk's initial 50 s) sets the static level
    to the variance norm of that interval; otherwise the ``level_quantile`` quantile of the windowed statistic
    is used. Both are floored at the quantizer variance (module docstring). With ``gyro`` the same test on the
    gyro (factor ``k_gyro``, default ``k``) must pass too. Intervals shorter than ``min_pose_s`` are dropped.
    """
    t = np.asarray(t_s, float)
    a = np.asarray(accel, float)
    n = t.size
    dt = float(np.median(np.diff(t)))
    w = max(3, int(round(window_s / dt)) | 1)
    stat = moving_variance_norm(a, w)
    floor = quantizer_variance_norm(a)
    if reference is not None:
        ref = a[reference]
        level = float(np.sqrt(np.sum(np.var(ref, axis=0) ** 2)))
    else:
        level = float(np.quantile(stat, level_quantile))
    level = max(level, floor, np.finfo(float).tiny)
    quiet = stat < k * level
    if gyro is not None:
        g = np.asarray(gyro, float)
        gstat = moving_variance_norm(g, w)
        glevel = (float(np.sqrt(np.sum(np.var(g[reference], axis=0) ** 2))) if reference is not None
                  else float(np.quantile(gstat, level_quantile)))
        glevel = max(glevel, quantizer_variance_norm(g), np.finfo(float).tiny)
        quiet &= gstat < (k_gyro or k) * glevel
    s, e = _runs(quiet)
    keep = (t[np.minimum(e, n) - 1] - t[s]) >= min_pose_s
    return StaticPoses(s[keep], e[keep], stat, level, k * level, k, w)
