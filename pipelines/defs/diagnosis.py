"""Check of the diagnosis stage (``assets_lib.stages.sim_to_real``): warn when a gap remains unexplained."""

import dagster as dg

from assets_lib.stages.sim_to_real import WARN_VERDICTS
from pipelines.partitions import devices
from pipelines.resources import ParquetStore


@dg.asset_check(asset="sim_to_real", name="gap_explained", partitions_def=devices,
                description=f"Warns when a device's sim-to-real verdict is one of {WARN_VERDICTS}.")
def gap_explained(context: dg.AssetCheckExecutionContext, store: ParquetStore) -> dg.AssetCheckResult:
    st = store.store
    bad, verdicts = [], {}
    for k in context.partition_keys:
        if st.current_version("sim_to_real", k) is None:
            continue
        v = st.read_meta("sim_to_real", k).get("verdict")
        verdicts[k] = v
        if v in WARN_VERDICTS:
            bad.append(f"{k}: {v}")
    return dg.AssetCheckResult(passed=not bad, severity=dg.AssetCheckSeverity.WARN,
                               metadata={"verdicts": dg.MetadataValue.json(verdicts), "failures": "\n".join(bad) or "none"})


CHECKS = [gap_explained]
