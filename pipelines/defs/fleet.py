"""Checks of the fleet stage (``assets_lib.stages.fleet``): warnings surfaced, never blocking (a drifting device
is news for a person, not a broken pipeline)."""

import dagster as dg
import pandas as pd

from assets_lib.store import FLEET_KEY
from pipelines.resources import ParquetStore


def _warnings_check(kind: str, name: str, description: str):
    @dg.asset_check(asset="fleet_drift", name=name, blocking=False, description=description)
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

CHECKS = [drift_within_limits, no_abrupt_shifts]
