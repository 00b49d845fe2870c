"""Stage ``repeatability``: per device, bias and scale-factor repeatability over its power-cycled runs
(seed 000 eq. 23, seed 003)."""

from __future__ import annotations

import pandas as pd

from assets_lib.calibration.repeatability import repeatability_table
from assets_lib.stages.spec import StageOutput, stage


@stage("repeatability", level="device", group="calibration", code_version="1",
       upstream=["gyro_rate_fit", "accel_multiposition_fit"])
def repeatability(device: str, inputs) -> StageOutput | None:
    """Turn-on to turn-on spread of each bias and scale factor of one device, with the number of runs used."""
    frames = [inputs.table(a, "coefficients", key=k)
              for a in ("gyro_rate_fit", "accel_multiposition_fit") for k in inputs.keys_of(a)]
    if not frames:
        return None
    table = repeatability_table(pd.concat(frames, ignore_index=True))
    return StageOutput(tables={"repeatability": table}, summary={"n_rows": len(table)})
