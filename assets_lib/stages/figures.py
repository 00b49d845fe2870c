"""Figures of stage outputs, drawn on demand from what the store holds, off the critical path of ``imulab run``.

Drawing a stage's figures cost more CPU than the science it shows (issue 10 item 8: 47 % of a fresh run went to
matplotlib), so the stages listed here store tables only, and their figures are drawn when someone looks: by the
``certificate`` stage (the residual and Allan plots a certificate embeds) and by ``imulab plots`` (every figure,
into a folder). A figure function ``figures(key, view) -> {name: PNG bytes}`` takes the partition key and a
``StoreView`` holding the stage's own stored version and the versions it was computed from (``view_of``); it
reads the stored tables (residuals, Allan curves and noise fits), or recomputes the in-memory result a figure needs
from the same stored inputs with the stage's own code (segmentation, fleet drift), so a figure shows exactly the
stored numbers.

A new plotted stage adds one function and one line in ``FIGURES``; a stage not listed here keeps drawing its
plots into its version folder (``stored_pngs`` reads those).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import pandas as pd

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


@dataclass(frozen=True)
class StoredCurve:
    """One channel's stored Allan curve (the ``allan`` table of ``allan_deviation``): what ``plot_allan`` draws."""

    channel: str
    kind: str
    tau_s: np.ndarray
    adev: np.ndarray
    ci_lo: np.ndarray
    ci_hi: np.ndarray
    unit: str = ""  #: the stage passes no unit (plot label 'SI'), as ``allan_tables``


@dataclass(frozen=True)
class StoredNoiseModel:
    """One channel's fitted noise model rebuilt from the stored ``noise`` table: theta = value^2 for the IEEE 952
    terms and the sine, (markov_q T_c)^2 for the Markov term; its curves are NoiseFit's own code."""

    terms: tuple
    theta: np.ndarray
    parameters: tuple  #: (name, is_upper_bound) of the fit rows, as NoiseFit.parameters for the plot's labels
    markov_tc_s: float | None = None
    sin_f0_hz: float | None = None

    def term_avar(self, tau_s):
        from assets_lib.noise.identification import NoiseFit

        return NoiseFit.term_avar(self, tau_s)  # only reads terms, theta, markov_tc_s, sin_f0_hz

    def model_avar(self, tau_s):
        from assets_lib.noise.identification import NoiseFit

        return NoiseFit.model_avar(self, tau_s)


@dataclass(frozen=True)
class _Param:
    name: str
    is_upper_bound: bool


_TERM_OF = {"markov_q": "M", "sin_amplitude": "S"}


def stored_noise_model(rows: pd.DataFrame) -> StoredNoiseModel | None:
    """The drawn model of one channel from its ``noise`` rows (method 'fit'); None when the rows do not determine
    it: a term reported as an upper bound has theta 0 in the fit, except when every term is a bound (the last
    term standing is kept at its estimate) and for the Markov term (its estimate at the best T_c may be kept
    while the profile set of T_c makes it a bound)."""
    fit = rows[rows.method == "fit"]
    extra = {r.parameter: float(r.value) for r in fit.itertuples() if r.parameter in ("markov_tc", "sin_freq")}
    model = fit[~fit.parameter.isin(["markov_tc", "sin_freq"])]
    bound = model.is_upper_bound.astype(bool).to_numpy()
    if model.empty or bound.all() or bool(((model.parameter == "markov_q").to_numpy() & bound).any()):
        return None
    terms, theta = [], []
    for r in model.itertuples():
        t = _TERM_OF.get(r.parameter, r.parameter)
        v = 0.0 if r.is_upper_bound else float(r.value) * (extra["markov_tc"] if t == "M" else 1.0)
        terms.append(t)
        theta.append(v * v)
    return StoredNoiseModel(tuple(terms), np.array(theta), tuple(_Param(r.parameter, bool(r.is_upper_bound))
                                                                for r in fit.itertuples()),
                            extra.get("markov_tc"), extra.get("sin_freq"))


def allan_figures(key: str, view: StoreView) -> dict[str, bytes]:
    """Log-log Allan deviation with intervals and the fitted noise model, gyro and accel, drawn from the stored
    ``allan`` (curves) and ``noise`` (fit) tables; a channel whose stored rows do not determine the drawn model
    (``stored_noise_model``) is recomputed from the ingested run by the stage's own ``allan_tables``."""
    from assets_lib.noise.identification import plot_allan
    from raw_schemas.tables import ACCEL_COLUMNS, GYRO_COLUMNS

    allan, noise = view.table("allan_deviation", "allan"), view.table("allan_deviation", "noise")
    curves, fits = {}, {}
    for c in GYRO_COLUMNS + ACCEL_COLUMNS:
        a = allan[allan.channel == c]
        curves[c] = StoredCurve(c, str(a.kind.iloc[0]), *(a[k].to_numpy(float) for k in ("tau_s", "adev", "ci_lo",
                                                                                           "ci_hi")))
        fits[c] = stored_noise_model(noise[noise.channel == c])
    if any(f is None for f in fits.values()):
        from assets_lib.stages.noise import allan_tables

        *_, results, recomputed = allan_tables(key, view.table("ingested_run", "imu"), view.meta("ingested_run"))
        curves = {c: results[c] if fits[c] is None else curves[c] for c in curves}
        fits = {c: recomputed[c] if fits[c] is None else fits[c] for c in fits}
    return {f"allan_{sensor}": plot_allan({c: curves[c] for c in cols}, {c: fits[c] for c in cols},
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
