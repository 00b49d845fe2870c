"""Checks of the calibration stages (``assets_lib.stages.calibration``), reporting only: partitions rejected by
the plateau gate, residuals consistent with the noise model, coefficients plausible for the device grade.
Checks carry the assets' ``partitions_def`` so they never load all partitions (docs/dagster.md 6.1)."""

import dagster as dg

from assets_lib.calibration.grades import implausible
from assets_lib.stages.calibration import CHI2_BAND, MIN_PLATEAU_FRACTION, reduced_chi2
from pipelines.partitions import captures
from pipelines.resources import ParquetStore


def _keys(context, store, asset):
    return [k for k in context.partition_keys if store.current_version(asset, k) is not None]


@dg.asset_check(asset="plateaus", name="enough_plateaus_kept", blocking=False, partitions_def=captures,
                description=f"Reports the partitions whose plateaus failed the engine's gate (at least "
                            f"{MIN_PLATEAU_FRACTION:.0%} of the plan's steps give an unflagged plateau). The gate "
                            "itself runs per partition in the engine: a failing run is rejected alone and the rest "
                            "of the batch goes on.")
def enough_plateaus_kept(context: dg.AssetCheckExecutionContext, store: ParquetStore) -> dg.AssetCheckResult:
    st = store.store
    bad = [f"{k}: {why}" for k in _keys(context, st, "plateaus") if (why := st.rejection("plateaus", k))]
    return dg.AssetCheckResult(passed=not bad, severity=dg.AssetCheckSeverity.ERROR,
                               metadata={"failures": "\n".join(bad) or "none"},
                               description="; ".join(bad)[:2000] or None)


def _chi2_check(asset: str):
    @dg.asset_check(asset=asset, name="residuals_consistent_with_noise", partitions_def=captures,
                    description=f"Reduced chi-square of the standardized plateau residuals within {CHI2_BAND}.")
    def _check(context: dg.AssetCheckExecutionContext, store: ParquetStore) -> dg.AssetCheckResult:
        st = store.store
        bad, values = [], {}
        for k in _keys(context, st, asset):
            chi2 = reduced_chi2(st.read(asset, k, "residuals"))
            if chi2 is None:
                continue
            values[k] = round(chi2, 3)
            if not CHI2_BAND[0] <= chi2 <= CHI2_BAND[1]:
                bad.append(f"{k}: reduced chi-square {chi2:.2f}")
        return dg.AssetCheckResult(passed=not bad, severity=dg.AssetCheckSeverity.WARN,
                                   metadata={"chi2": dg.MetadataValue.json(values), "failures": "\n".join(bad) or "none"})

    return _check


def _plausible_check(asset: str):
    @dg.asset_check(asset=asset, name="coefficients_plausible_for_grade", partitions_def=captures,
                    description="Bias, scale factor and misalignment inside the device grade's envelope (assets_lib.calibration.grades).")
    def _check(context: dg.AssetCheckExecutionContext, store: ParquetStore) -> dg.AssetCheckResult:
        st = store.store
        bad = []
        for k in _keys(context, st, asset):
            grade = st.read_meta("ingested_run", k).get("grade", "consumer")
            c = st.read(asset, k, "coefficients")
            for r in c[c.observable.astype(bool)].itertuples(index=False):
                why = implausible(grade, r.sensor, r.coefficient, float(r.value))
                if why:
                    bad.append(f"{k} axis {r.axis}: {why}")
        return dg.AssetCheckResult(passed=not bad, metadata={"failures": "\n".join(bad) or "none"})

    return _check


@dg.asset_check(asset="tablefree_fit", name="tablefree_fit_matches_poses", blocking=True, partitions_def=captures,
                description="Table-free fit: static |f| - g RMS within tolerance of local gravity, every term observable.")
def tablefree_fit_matches_poses(context: dg.AssetCheckExecutionContext, store: ParquetStore) -> dg.AssetCheckResult:
    st = store.store
    bad = [f"{k}: {p}" for k in _keys(context, st, "tablefree_fit") if (p := st.read_meta("tablefree_fit", k).get("problem"))]
    return dg.AssetCheckResult(passed=not bad, metadata={"failures": "\n".join(bad) or "none"})


CHECKS = [
    enough_plateaus_kept,
    tablefree_fit_matches_poses,
    *[_chi2_check(a) for a in ("gyro_rate_fit", "accel_multiposition_fit")],
    *[_plausible_check(a) for a in ("gyro_rate_fit", "accel_multiposition_fit")],
]
