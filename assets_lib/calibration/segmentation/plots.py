"""Figure of a segmented run for the asset metadata: traces with the plateau windows shaded."""

from __future__ import annotations

import numpy as np
import pandas as pd

from assets_lib.calibration.segmentation.plateaus import SegmentationResult
from raw_schemas.tables import ACCEL_COLUMNS, GYRO_COLUMNS
from raw_schemas.units import RADPS_TO_DEGPS


def plot_segmentation_png(imu: pd.DataFrame, result: SegmentationResult, title: str = "", max_points: int = 4000,
                          dpi: int = 90) -> bytes:
    """PNG of the run's gyro [deg/s] and accel [m/s^2] traces with the plateau windows shaded (red: flagged)."""
    from assets_lib.plotting import envelope, figure, png

    t = imu["time_s"].to_numpy(dtype=float)
    fig, axs = figure(2, 1, figsize=(11, 5.5), dpi=dpi, sharex=True, margins_in=(0.8, 0.15, 0.5, 0.5), hspace=0.12)
    ax_g, ax_a = axs[:, 0]
    p = result.plateaus
    spans = p[np.isfinite(p["t_start_s"].to_numpy(dtype=float))]
    panels = ((ax_g, GYRO_COLUMNS, RADPS_TO_DEGPS, "gyro [deg/s]"), (ax_a, ACCEL_COLUMNS, 1.0, "accel [m/s^2]"))
    for ax, cols, scale, label in panels:
        for c, color in zip(cols, ("tab:red", "tab:green", "tab:blue")):
            ax.plot(*envelope(t, imu[c].to_numpy(dtype=float) * scale, max_points), lw=0.6, color=color,
                    label=c.split("_")[1])
        ax.set_ylabel(label)
        ax.legend(loc="upper right", fontsize=7, ncol=3)
        for flagged, color in ((False, "tab:olive"), (True, "tab:red")):  # one collection per colour, not a patch each
            w = spans[spans["flagged"].astype(bool) == flagged]
            if len(w):
                ax.broken_barh(list(zip(w["t_start_s"], w["t_end_s"] - w["t_start_s"])), (0, 1),
                               transform=ax.get_xaxis_transform(), color=color, alpha=0.18, lw=0)
    for _, r in spans.iterrows():
        ax_g.text(0.5 * (r["t_start_s"] + r["t_end_s"]), 1.0, str(r["step_index"]), transform=ax_g.get_xaxis_transform(),
                  ha="center", va="bottom", fontsize=6)
    ax_a.set_xlabel("IMU time [s]")
    fig.suptitle(title or f"segmentation ({result.method}); shaded: plateau windows, red = flagged", fontsize=9)
    return png(fig)
