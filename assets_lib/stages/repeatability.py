"""Stage ``repeatability``: per device, bias and scale-factor repeatability over its power-cycled runs
([SEED000] eq. 23, [SEED003])."""

from __future__ import annotations

import pandas as pd

from assets_lib.calibration.repeatability import (
    REPEATABILITY_COLUMNS,
    pooled_bias_stderrs,
    repeatability_table,
    static_repeatability,
)
from assets_lib.stages.spec import StageOutput, stage


@stage("repeatability", level="device", group="calibration", code_version="1",
       upstream=["gyro_rate_fit", "accel_multiposition_fit", "allan_deviation"])
def repeatability(device: str, inputs) -> StageOutput | None:
    """Turn-on to turn-on spread of each bias and scale factor of one device, with the number of runs used."""
    frames = [inputs.table(a, "coefficients", key=k)
              for a in ("gyro_rate_fit", "accel_multiposition_fit") for k in inputs.keys_of(a)]
    # power-cycled static runs: turn-on bias and noise-term repeatability ([SEED000] eq. 23)
    keys = [k for k in inputs.keys_of("allan_deviation") if inputs.has_table("allan_deviation", "static_terms", key=k)]
    static = [inputs.table("allan_deviation", "static_terms", key=k) for k in keys]
    # the runs' Allan curves: one noise model per channel over all runs gives the turn-on bias standard errors
    allan = {str(s["run_id"].iloc[0]): inputs.table("allan_deviation", "allan", key=k)
             for k, s in zip(keys, static) if len(s) and inputs.has_table("allan_deviation", "allan", key=k)}
    if not frames and len(static) < 2:
        return None
    tables = {"repeatability": (repeatability_table(pd.concat(frames, ignore_index=True)) if frames
                                else pd.DataFrame(columns=REPEATABILITY_COLUMNS))}
    if len(static) >= 2:
        tables["static_repeatability"] = static_repeatability(pooled_bias_stderrs(pd.concat(static, ignore_index=True),
                                                                                  allan))
    return StageOutput(tables=tables, summary={f"n_rows_{k}": len(v) for k, v in tables.items()})
