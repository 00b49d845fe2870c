"""Stage ``fleet_drift``: every device's calibration coefficients over time, with control limits from the device's
repeatability, drift and abrupt-shift flags (assets_lib.fleet.drift), a fleet summary and one control chart per
coefficient family; two non-blocking checks surface the warnings.

Upstreams are the fits and the repeatability stage when their modules exist (``pipelines.defs.calibration``,
``pipelines.defs.repeatability``); without coefficients the stage reports "not applicable" and writes nothing.
Run times come from ``ingested_run`` (the manifest's start time), so it is an upstream too.
"""


import importlib
import importlib.util

import dagster as dg
import pandas as pd

from assets_lib.fleet.drift import DriftConfig, fleet_drift
from pipelines.resources import ParquetStore
from pipelines.stage import FLEET_KEY, STAGES, StageInputs, StageOutput, stage

for _m in ("ingest", "calibration", "repeatability"):  # register upstream stages first when imported on its own
    if importlib.util.find_spec(f"pipelines.defs.{_m}") is not None:
        importlib.import_module(f"pipelines.defs.{_m}")

FIT_ASSETS = ("gyro_rate_fit", "accel_multiposition_fit")
CONFIG = DriftConfig()
UPSTREAM = tuple(a for a in ("ingested_run", *FIT_ASSETS, "repeatability") if a in STAGES)


@stage("fleet_drift", level="fleet", group="fleet", code_version="1", upstream=UPSTREAM)
def fleet_drift_stage(key: str, inputs: StageInputs) -> StageOutput | None:
    """Coefficient drift per device across runs: weighted trend with CI, control limits from repeatability,
    drift-beyond-limits and CUSUM abrupt-shift flags, fleet summary and control charts."""
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
    fd = fleet_drift(coefs, times, rep, CONFIG)
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
            "n_series": int(len(series)),
            "n_analyzed": int(series["status"].isin(["ok", "drift", "shift"]).sum()),
            "n_drift": int(series["drift_flag"].sum()),
            "n_shift": int(series["shift_flag"].sum()),
        },
        plots=fd.plots(),
    )


# ---------------------------------------------------------------------------------------------------------------
# Checks: warnings surfaced, never blocking (a drifting device is news for a person, not a broken pipeline)
# ---------------------------------------------------------------------------------------------------------------
def _warnings_check(kind: str, name: str, description: str):
    @dg.asset_check(asset=fleet_drift_stage, name=name, blocking=False, description=description)
    def _check(store: ParquetStore) -> dg.AssetCheckResult:
        st = store.store
        version = st.current_version("fleet_drift", FLEET_KEY)
        if version is None:
            return dg.AssetCheckResult(passed=True, metadata={"note": "no drift analysis stored yet (no coefficients)"})
        meta = st.read_meta("fleet_drift", FLEET_KEY, version)
        found = [w for w in meta.get("warnings", []) if w.get("kind") == kind]
        table = pd.DataFrame(found, columns=["device_id", "sensor", "axis", "coefficient", "method", "run_id", "message"])
        return dg.AssetCheckResult(
            passed=not found,
            severity=dg.AssetCheckSeverity.WARN,
            metadata={
                "n_flagged": len(found),
                "version": version,
                "flagged": dg.MetadataValue.md(table.to_markdown(index=False) if found else "none"),
            },
            description="; ".join(w["message"] for w in found)[:2000] or None,
        )

    return _check


drift_within_limits = _warnings_check(
    "drift", "no_drift_beyond_limits",
    "Warns (non-blocking) when a device's coefficient trend has moved beyond its control limits: lists device, "
    "coefficient and the last run.")
no_abrupt_shifts = _warnings_check(
    "shift", "no_abrupt_shifts",
    "Warns (non-blocking) when the CUSUM finds an abrupt shift in a device's coefficient: lists device, "
    "coefficient and the run where it shifted.")

ASSETS = [fleet_drift_stage]
CHECKS = [drift_within_limits, no_abrupt_shifts]
