"""Stage ``fleet_drift``: every device's calibration coefficients over time, with control limits from the device's
repeatability, drift and abrupt-shift flags (assets_lib.fleet.drift) and a fleet summary; one control chart per
coefficient family is drawn on demand (assets_lib.stages.figures). Run times come from ``ingested_run`` (the
manifest's start time), so it is an upstream too; without coefficients the stage produces no output."""

from __future__ import annotations

import pandas as pd

from assets_lib.fleet.drift import DriftConfig, fleet_drift
from assets_lib.stages.spec import StageOutput, stage

FIT_ASSETS = ("gyro_rate_fit", "accel_multiposition_fit")
CONFIG = DriftConfig()


@stage("fleet_drift", level="fleet", group="fleet", code_version="1",
       upstream=("ingested_run", *FIT_ASSETS, "repeatability"))
def fleet_drift_stage(key: str, inputs) -> StageOutput | None:
    """Coefficient drift per device across runs: weighted trend with CI, control limits from repeatability,
    drift-beyond-limits and CUSUM abrupt-shift flags and the fleet summary (control charts: ``imulab plots``,
    assets_lib.stages.figures)."""
    fd = drift_of(inputs)
    if fd is None:
        return None
    series = fd.series_table()
    warnings = fd.warnings()
    return StageOutput(
        tables={"drift": series, "drift_points": fd.points_table(), "fleet_summary": fd.summary_table()},
        meta={
            "warnings": warnings,
            "config": {k: getattr(CONFIG, k) for k in CONFIG.__dataclass_fields__},
            "n_devices": int(series["device_id"].nunique()) if len(series) else 0,
            "repeatability_devices": sorted(inputs.keys_of("repeatability")),
        },
        summary={
            "n_series": len(series),
            "n_analyzed": int(series["status"].isin(["ok", "drift", "shift"]).sum()),
            "n_drift": int(series["drift_flag"].sum()),
            "n_shift": int(series["shift_flag"].sum()),
        },
    )


def drift_of(inputs):
    """The ``FleetDrift`` of the coefficients, run times and repeatability in ``inputs`` (None without coefficients):
    the stage's computation, shared with its figures (``assets_lib.stages.figures``)."""
    frames = []
    for asset in FIT_ASSETS:
        for k in inputs.keys_of(asset):
            frames.append(inputs.table(asset, "coefficients", key=k).assign(source=asset))
    if not frames:
        return None
    coefs = pd.concat(frames, ignore_index=True)
    times = pd.DataFrame([
        {f: inputs.meta("ingested_run", key=k).get(f) for f in ("device_id", "run_id", "start_time_utc")}
        for k in inputs.keys_of("ingested_run")
    ], columns=["device_id", "run_id", "start_time_utc"])
    reps = [inputs.table("repeatability", "repeatability", key=k) for k in inputs.keys_of("repeatability")]
    rep = pd.concat(reps, ignore_index=True) if reps else None
    return fleet_drift(coefs, times, rep, CONFIG)
