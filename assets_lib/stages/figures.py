"""Figures of stage outputs, drawn on demand from what the store holds, off the critical path of ``imulab run``.

Drawing a stage's figures cost more CPU than the science it shows (issue 10 item 8: 47 % of a fresh run went to
matplotlib), so the stages listed here store tables only, and their figures are drawn when someone looks: by the
``certificate`` stage (the residual and Allan plots a certificate embeds) and by ``imulab plots`` (every figure,
into a folder). A figure function ``figures(key, view) -> {name: PNG bytes}`` takes the partition key and a
``StoreView`` holding the stage's own stored version and the versions it was computed from (``view_of``); it
reads the stored tables, or recomputes the in-memory result a figure needs from the same stored inputs with the
stage's own code (segmentation, Allan fits, fleet drift), so a figure shows exactly the stored numbers.

A new plotted stage adds one function and one line in ``FIGURES``; a stage not listed here keeps drawing its
plots into its version folder (``stored_pngs`` reads those).
"""

from __future__ import annotations

from collections.abc import Callable

from assets_lib.store import StoreView, VersionedStore


def plateau_figures(key: str, view: StoreView) -> dict[str, bytes]:
    """The run's traces with the plateau windows shaded (the segmentation recomputed from the ingested run)."""
    from assets_lib.calibration.segmentation import plot_segmentation_png, segment_run
    from assets_lib.stages.calibration import load_manifest

    imu = view.table("ingested_run", "imu")
    table = view.table("ingested_run", "table") if view.has_table("ingested_run", "table") else None
    res = segment_run(load_manifest(view), imu, table)
    return {"segmentation": plot_segmentation_png(imu, res, title=key)}


def rate_fit_figures(key: str, view: StoreView) -> dict[str, bytes]:
    """Gyro rate-fit residuals against the table rate (the stored residual table)."""
    from assets_lib.calibration.fit_report import plot_rate_residuals_png

    resid = view.table("gyro_rate_fit", "residuals")
    return {"residual_vs_rate": plot_rate_residuals_png(resid, title=f"{key}: gyro rate-fit residuals")}


def multiposition_figures(key: str, view: StoreView) -> dict[str, bytes]:
    """Multi-position fit residuals per position (the stored residual table)."""
    from assets_lib.calibration.fit_report import plot_multiposition_residuals_png

    resid = view.table("accel_multiposition_fit", "residuals")
    return {"position_residuals": plot_multiposition_residuals_png(resid, title=f"{key}: multi-position residuals")}


def allan_figures(key: str, view: StoreView) -> dict[str, bytes]:
    """Log-log Allan deviation with intervals and the fitted noise model, gyro and accel (recomputed from the
    ingested run by the stage's own ``allan_tables``: the curves and fits of the stored tables)."""
    from assets_lib.noise.identification import plot_allan
    from assets_lib.stages.noise import allan_tables
    from raw_schemas.tables import ACCEL_COLUMNS, GYRO_COLUMNS

    imu = view.table("ingested_run", "imu")
    *_, results, fits = allan_tables(key, imu, view.meta("ingested_run"))
    return {f"allan_{sensor}": plot_allan({c: results[c] for c in cols}, {c: fits[c] for c in cols},
                                          title=f"{key}: {sensor}")
            for sensor, cols in (("gyro", GYRO_COLUMNS), ("accel", ACCEL_COLUMNS))}


def fleet_figures(key: str, view: StoreView) -> dict[str, bytes]:
    """One control chart per coefficient family (the fleet drift recomputed from the same stored inputs)."""
    from assets_lib.stages.fleet import drift_of

    fd = drift_of(view)
    return {} if fd is None else fd.plots()


#: stage name -> its figure function (the stage itself stores no PNG)
FIGURES: dict[str, Callable[[str, StoreView], dict[str, bytes]]] = {
    "plateaus": plateau_figures,
    "gyro_rate_fit": rate_fit_figures,
    "accel_multiposition_fit": multiposition_figures,
    "allan_deviation": allan_figures,
    "fleet_drift": fleet_figures,
}


def view_of(store: VersionedStore, asset: str, key: str, version: str | None = None, archive=None) -> StoreView | None:
    """A view holding ``asset``'s version of ``key`` (default: CURRENT) and the upstream versions it was computed
    from (its stored ``inputs``); None when the partition has no version."""
    version = version or store.current_version(asset, key)
    if version is None or not store.exists(asset, key, version):
        return None
    inputs = store.read_meta(asset, key, version).get("inputs") or {}
    return StoreView(store, {**inputs, f"{asset}/{key}": version}, key, archive)


def stored_pngs(view: StoreView, asset: str, key: str | None = None) -> dict[str, bytes]:
    """PNGs a stage stored with its version (stages not in ``FIGURES``), by file stem."""
    if not view.has(asset, key):
        return {}
    return {p.stem: p.read_bytes() for p in sorted(view.version_dir(asset, key).glob("*.png"))}


def figures(asset: str, key: str, view: StoreView) -> dict[str, bytes]:
    """Figures of ``asset``'s partition ``key`` in ``view``: drawn by its figure function, else the PNGs stored
    with its version; {} when the view does not hold the partition."""
    if not view.has(asset, key):
        return {}
    if asset in FIGURES:
        bound = StoreView(view.store, view.versions, key, view.archive, view.run_id)
        return FIGURES[asset](key, bound)
    return stored_pngs(view, asset, key)
