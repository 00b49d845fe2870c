"""Plateau segmentation of a run: clock alignment, plateau cutting, outlier rejection, means with honest SEMs.

Two ways to find the plateaus of a plan (``raw_schemas.TestPlan``; plan times are on the IMU clock):

* **with a turntable log** (canonical ``time_s`` on the table clock, ``angle_rad``, ``rate_radps``,
  ``step_index``): :mod:`.clock` aligns the table clock to the IMU clock ([SEED003]: "time-align table and IMU
  data, then cut each 2-minute plateau"); plateaus are cut where the table log says step k ran.
* **without a table log**: :mod:`.detection` finds quiet intervals in the IMU data alone ([TEDALDI2014] variance
  detector) and matches them to the plan steps.

:mod:`.plateaus` trims the windows, cuts whole table turns ([SEED000]), rejects outliers ([SEED001]) and builds
the PLATEAU TABLE; :mod:`.window_stats` gives the standard error of each mean under correlated noise from the
run's pooled [IEEE952] model (:mod:`assets_lib.noise.pooled`); :mod:`.plots` draws the run. The public names
are importable from here.
"""

from assets_lib.calibration.segmentation.clock import ClockAlignment, align_clocks
from assets_lib.calibration.segmentation.config import DetectorConfig, SegmentationConfig
from assets_lib.calibration.segmentation.detection import QuietDetection, detect_quiet_intervals, match_plan
from assets_lib.calibration.segmentation.plateaus import (
    CHANNELS,
    SegmentationResult,
    plateau_columns,
    segment_run,
    whole_revolution_window,
)
from assets_lib.calibration.segmentation.plots import plot_segmentation_png
from assets_lib.calibration.segmentation.window_stats import SemResult, plateau_sem
from assets_lib.noise.pooled import (
    MODEL_PENALTY,
    PooledAllanFit,
    fit_pooled_allan,
    mean_difference_variance,
    overlapping_avar,
)

__all__ = [
    "CHANNELS", "MODEL_PENALTY", "ClockAlignment", "DetectorConfig", "PooledAllanFit", "QuietDetection",
    "SegmentationConfig", "SegmentationResult", "SemResult", "align_clocks", "detect_quiet_intervals",
    "fit_pooled_allan", "match_plan", "mean_difference_variance", "overlapping_avar", "plateau_columns",
    "plateau_sem", "plot_segmentation_png", "segment_run", "whole_revolution_window",
]
