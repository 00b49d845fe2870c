"""Check of the noise stage (``assets_lib.stages.noise``): the fitted IEEE 952 model matches the Allan curve."""

import dagster as dg

from assets_lib.stages.noise import MODEL_INSIDE_CI_MIN
from pipelines.partitions import captures
from pipelines.resources import ParquetStore


@dg.asset_check(asset="allan_deviation", name="noise_model_matches_curve", partitions_def=captures,
                description=f"The fitted IEEE 952 model lies inside the Allan-deviation confidence interval at "
                            f">= {MODEL_INSIDE_CI_MIN:.0%} of the fitted taus, for every channel.")
def noise_model_matches_curve(context: dg.AssetCheckExecutionContext, store: ParquetStore) -> dg.AssetCheckResult:
    st = store.store
    bad, shares = [], {}
    for k in context.partition_keys:
        if st.current_version("allan_deviation", k) is None:
            continue
        inside = st.read_meta("allan_deviation", k).get("model_inside_ci", {})
        shares[k] = inside
        bad += [f"{k} {c}: {v:.0%}" for c, v in inside.items() if not v >= MODEL_INSIDE_CI_MIN]
    return dg.AssetCheckResult(passed=not bad, severity=dg.AssetCheckSeverity.WARN,
                               metadata={"inside_ci": dg.MetadataValue.json(shares), "failures": "\n".join(bad) or "none"})


CHECKS = [noise_model_matches_curve]
