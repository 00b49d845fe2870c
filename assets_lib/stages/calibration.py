"""Stages ``plateaus``, ``gyro_rate_fit``, ``accel_multiposition_fit``: plateau segmentation with outlier rejection,
the gyro rate fit, the accelerometer multi-position fit (with static gyro biases), per captured run; and the
figures their quality gates judge (``plateau_gate_figure``, ``reduced_chi2``)."""

from __future__ import annotations

import numpy as np
import pandas as pd

from assets_lib.calibration.multiposition import (
    fit_accel_multiposition,
    fit_gyro_static,
)
from assets_lib.calibration.noise_prior import DeviceNoisePrior, device_noise_prior
from assets_lib.calibration.rate_fit import fit_gyro_rate
from assets_lib.calibration.segmentation import segment_run
from assets_lib.calibration.fit_core import CHI2_BAND  # noqa: F401 - one band for the check and the record's status
from assets_lib.stages.spec import Gate, StageOutput, stage
from raw_schemas.manifest import Manifest

CALIBRATION_KINDS = ("rate", "multiposition", "tumble")
MIN_PLATEAU_FRACTION = 0.8  # a run whose usable plateaus fall below this share of the plan fails the gate


def load_manifest(inputs) -> Manifest:
    return Manifest.model_validate_json(inputs.file("ingested_run", "manifest.json"))


def enough_plateaus_kept(out: StageOutput) -> str | None:
    """Gate: at least ``MIN_PLATEAU_FRACTION`` of the plan's steps give an unflagged plateau."""
    p = out.tables["plateaus"]
    frac = usable_plateau_fraction(p)
    if frac >= MIN_PLATEAU_FRACTION:
        return None
    flagged = p.loc[p["flagged"].astype(bool), "flag_reason"].astype(str)
    reasons = flagged.str.replace(r"\s*\([^)]*\)", "", regex=True).value_counts()
    why = "; ".join(f"{n} x {r}" for r, n in reasons.items())
    return (f"{frac:.0%} of {len(p)} plan steps gave a usable plateau (at least {MIN_PLATEAU_FRACTION:.0%} needed); "
            f"flagged: {why}")[:400]


@stage("plateaus", level="capture", group="calibration", code_version="2", upstream=["ingested_run"],
       applies_to=CALIBRATION_KINDS,
       gates=[Gate("enough_plateaus_kept", enough_plateaus_kept,
                   f"At least {MIN_PLATEAU_FRACTION:.0%} of the plan's steps give an unflagged plateau.")])
def plateaus(key: str, inputs) -> StageOutput:
    """Plateau table per run: clock alignment to the table log (or detection from the data), settle trimming,
    whole revolutions, polynomial-residual outlier rejection, means with correlated-noise standard errors."""
    manifest = load_manifest(inputs)
    imu = inputs.table("ingested_run", "imu")
    table = inputs.table("ingested_run", "table") if inputs.has_table("ingested_run", "table") else None
    res = segment_run(manifest, imu, table)
    p = res.plateaus
    al = res.alignment
    rejected = p[["step_index", "n_samples", "n_rejected", "rejected_fraction", "flagged", "flag_reason"]]
    meta = {
        "method": res.method,
        "clock_offset_s": None if al is None else float(al.offset_s),
        "unmatched_steps": list(map(int, res.unmatched_steps)),
        "warnings": list(res.warnings),
        "outliers_per_plateau": rejected.to_dict(orient="records"),
    }
    return StageOutput(
        tables={"plateaus": p},
        meta=meta,
        summary={
            "n_plateaus": len(p),
            "n_flagged": int(p["flagged"].sum()),
            "rejected_fraction_max": float(p["rejected_fraction"].max()) if len(p) else 0.0,
            "segmentation": res.method,
        },
    )


def static_noise_prior(inputs) -> DeviceNoisePrior | None:
    """The device's 1/f level B per channel from its static runs' ``allan_deviation`` outputs (sibling reads: every
    static capture of the device that passed its gates), :func:`device_noise_prior`; None without a static run."""
    keys = inputs.sibling_keys("allan_deviation")
    noise = inputs.sibling_tables("allan_deviation", "noise")
    terms = inputs.sibling_tables("allan_deviation", "static_terms")
    return device_noise_prior([noise[k] for k in keys], [terms[k] for k in keys], keys)


def _prior_meta(prior: DeviceNoisePrior | None) -> dict:
    """Where each channel's B came from (the device's static record, or the run's plateaus when absent)."""
    return {"noise_prior": {} if prior is None else {c.channel: c.source for c in prior.channels}}


@stage("gyro_rate_fit", level="capture", group="calibration", code_version="5", upstream=["plateaus"],
       siblings=["allan_deviation"], applies_to=("rate",))
def gyro_rate_fit(key: str, inputs) -> StageOutput:
    """Gyro scale factor, bias, misalignment, nonlinearity and asymmetry from the rate plateaus ([SEED003] eq. 3,
    [SEED000] eq. 6-13); saturated or wild plateaus excluded automatically and reported; the 1/f level B of the
    correlated-noise model from the device's static records (:func:`static_noise_prior`: their B where they resolve
    it, else their bound truncating the run's own B)."""
    prior = static_noise_prior(inputs)
    fit = fit_gyro_rate(inputs.table("plateaus", "plateaus"), noise_prior=prior)
    coef = fit.coefficient_table()
    resid = fit.residual_table()
    return StageOutput(
        tables={"coefficients": coef, "residuals": resid},
        meta={"excluded": _excluded(resid), **_prior_meta(prior)},
        summary=_coef_summary(coef, "gyro", ("scale_factor",)),
    )


@stage("accel_multiposition_fit", level="capture", group="calibration", code_version="4", upstream=["plateaus"],
       siblings=["allan_deviation"], applies_to=("multiposition", "tumble"))
def accel_multiposition_fit(key: str, inputs) -> StageOutput:
    """Accelerometer scale, bias, misalignment, K2 and cross-coupling from any position schedule ([SEED000] eq.
    21-22, [SEED003]), unobservable terms reported as such; gyro biases from the static positions (eq. 17-20); B as
    in ``gyro_rate_fit``."""
    p = inputs.table("plateaus", "plateaus")
    prior = static_noise_prior(inputs)
    acc = fit_accel_multiposition(p, noise_prior=prior)
    gyr = fit_gyro_static(p, noise_prior=prior)
    coef = pd.concat([acc.coefficient_table(), gyr.coefficient_table()], ignore_index=True)
    resid = pd.concat([acc.residual_table(), gyr.residual_table()], ignore_index=True)
    return StageOutput(
        tables={"coefficients": coef, "residuals": resid},
        meta={"excluded": _excluded(resid), **_prior_meta(prior)},
        summary=_coef_summary(coef, "accel", ("bias",)),
    )


def _excluded(resid: pd.DataFrame) -> list[dict]:
    if "excluded" not in resid:
        return []
    cols = [c for c in ("sensor", "axis", "step_index", "reason") if c in resid]
    return resid.loc[resid["excluded"].astype(bool), cols].to_dict(orient="records")


def _coef_summary(coef: pd.DataFrame, sensor: str, names) -> dict:
    out = {}
    for _, r in coef[(coef.sensor == sensor) & coef.coefficient.isin(names)].iterrows():
        out[f"{r.sensor}_{r.axis}_{r.coefficient}_{r.unit_lab}"] = float(r.value_lab)
    return out



def usable_plateau_fraction(p: pd.DataFrame) -> float:
    """Share of the plan's steps that gave an unflagged plateau."""
    return float((~p["flagged"].astype(bool)).mean()) if len(p) else 0.0


def reduced_chi2(resid: pd.DataFrame) -> float | None:
    """Mean square of the standardized residuals of the plateaus used by a fit (None without any)."""
    z = resid.loc[~resid["excluded"].astype(bool), "std_residual"].to_numpy(dtype=float)
    z = z[np.isfinite(z)]
    return float(np.mean(z**2)) if z.size else None
