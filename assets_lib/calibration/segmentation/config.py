"""Settings of the plateau segmentation: the quiet-interval detector and :func:`segment_run`."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from assets_lib.calibration.outliers import OutlierConfig


@dataclass(frozen=True)
class DetectorConfig:
    """Quiet-interval (static / constant-rate) detector without a table log (imu_tk-style variance detector).

    ``window_s`` 1.0: imu_tk's 101-sample window at 100 Hz. ``k_threshold`` 6: imu_tk's best multiplier on its
    own Xsens set, here applied to the ``floor_quantile`` (10 %) quantile of the moving variance; for white noise
    a 1-s moving variance exceeds 6 x its 10 % quantile with negligible probability, while ramps and rotations
    exceed it by orders of magnitude. ``center`` "median" subtracts per-axis medians before taking norms (raw
    counts with large offsets); "none" keeps the norms rotation-invariant (canonical SI data).
    """

    window_s: float = 1.0
    k_threshold: float = 6.0
    floor_quantile: float = 0.1
    min_quiet_s: float = 1.0
    refine_edges: bool = True
    edge_k_sigma: float = 5.0
    merge_gap_s: float = 0.5
    use_accel: bool = True
    center: str = "none"
    static_max_rate_radps: float = np.radians(1.0)


@dataclass(frozen=True)
class SegmentationConfig:
    """Settings of :func:`segment_run`.

    Windows: ``settle_s`` of the step plus ``guard_s`` at the start, ``guard_s`` at the end (ramp edges), then
    whole table turns (``whole_revolutions``). Table log: the offset search covers every lag with at least
    ``min_overlap_fraction`` overlap, or ``clock_offset_prior_s +- max_clock_offset_s`` when that is given; a
    peak below ``min_correlation`` falls back to step centres; a table step lasting more than
    ``step_duration_tolerance_s`` (+ 2 log periods) longer or shorter than planned is flagged; the measured table
    rate (angle over the window) replaces the commanded one in ``omega_ref`` when ``use_measured_table_rate``.
    No table log: a common plan shift within ``max_plan_shift_s``; a step matches a quiet interval covering at
    least ``min_match_fraction`` of it, with the mean gyro within ``gyro_rate_abs_tol_radps`` +
    ``gyro_rate_rel_tol`` |omega| of the plan's and the mean specific force within ``accel_direction_tol_deg`` of
    its direction (wide enough for consumer-grade biases and scale errors, narrow enough to tell 45-degree
    positions apart). Windows shorter than ``min_window_s`` are flagged.
    """

    guard_s: float = 0.5
    whole_revolutions: bool = True
    use_measured_table_rate: bool = True
    max_clock_offset_s: float | None = None
    clock_offset_prior_s: float = 0.0
    min_overlap_fraction: float = 0.5
    min_correlation: float = 0.5
    step_duration_tolerance_s: float = 1.0
    max_plan_shift_s: float = 120.0
    min_match_fraction: float = 0.5
    accel_direction_tol_deg: float = 15.0
    gyro_rate_abs_tol_radps: float = np.radians(5.0)
    gyro_rate_rel_tol: float = 0.1
    min_window_s: float = 1.0
    sem_max_cluster_fraction: float = 0.5
    outliers: OutlierConfig = field(default_factory=OutlierConfig)
    detector: DetectorConfig = field(default_factory=DetectorConfig)
