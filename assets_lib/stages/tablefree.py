"""Stage ``tablefree_fit``: table-free calibration of a hand-moved session (test kind ``tablefree``): Ferraris for
annotated six-position + three-rotation sessions, otherwise static poses + Tedaldi accelerometer fit + gyro
integration between poses (``assets_lib.calibration.tablefree_session``); one COEFFICIENT TABLE per run."""

from __future__ import annotations

from assets_lib.calibration.tablefree_session import calibrate_tablefree, coefficient_table, plot_tablefree_png
from assets_lib.sim.earth import site_gravity_mps2
from assets_lib.stages.spec import StageOutput, stage
from raw_schemas.manifest import Manifest

#: a Tedaldi fit whose static |f| - g RMS exceeds this fraction of g contradicts its data (poses not static,
#: wrong gravity or units): the run is rejected with the figure
MAX_NORM_RMS_FRACTION = 2e-3


def fit_problem(m: dict) -> str | None:
    """Check on a stored ``tablefree_fit`` meta: None when the calibrated static specific-force magnitudes agree
    with local gravity and every term is observable, else the reason naming the figure."""
    rms = m["diagnostics"].get("accel_norm_rms_mps2", m["diagnostics"].get("static_norm_rms_mps2"))
    g = m["gravity_mps2"]
    if rms > MAX_NORM_RMS_FRACTION * g:
        return f"static |f| - g RMS {rms:.4g} m/s^2 > {MAX_NORM_RMS_FRACTION:g} g: the poses or the gravity do not fit"
    if m["diagnostics"].get("unobservable"):
        return f"terms the pose set cannot determine: {', '.join(m['diagnostics']['unobservable'])}"
    return None


@stage("tablefree_fit", level="capture", group="calibration", code_version="1", upstream=["ingested_run"],
       applies_to=("tablefree",))
def tablefree_fit(key: str, inputs) -> StageOutput:
    """Table-free accelerometer and gyro calibration with uncertainties and observability (Tedaldi 2014 / Ferraris 1995)."""
    manifest = Manifest.model_validate_json(inputs.file("ingested_run", "manifest.json"))
    imu = inputs.table("ingested_run", "imu")
    g = site_gravity_mps2(manifest.site)
    res = calibrate_tablefree(manifest, imu, g)
    coef = coefficient_table(res, manifest.device.id, manifest.run_id, len(imu))
    diag = {k: (v if not hasattr(v, "item") else v.item()) for k, v in res.diagnostics.items()}
    meta = {"method": res.method, "gravity_mps2": g, "diagnostics": diag, "warnings": list(res.warnings)}
    meta["problem"] = fit_problem(meta)
    return StageOutput(
        tables={"coefficients": coef},
        meta=meta,
        summary={"method": res.method, "n_coefficients": int(coef["observable"].sum()),
                 **{k: v for k, v in diag.items() if isinstance(v, (int, float))}},
        plots={"tablefree": plot_tablefree_png(imu, res, title=key)},
    )
