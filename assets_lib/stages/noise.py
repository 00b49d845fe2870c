"""Stage ``allan_deviation``: Allan deviation with confidence intervals and IEEE 952 noise identification of every
long static record, and the share of taus where the fitted model matches the curve. Its log-log plots are drawn
on demand from the stored inputs (assets_lib.stages.figures), not during the run."""

from __future__ import annotations

import numpy as np
import pandas as pd

from assets_lib.calibration.repeatability import STATIC_RUN_COLUMNS, static_terms_row
from assets_lib.noise.allan import allan_deviations
from assets_lib.noise.identification import fit_all, noise_table
from assets_lib.records.validity import MODEL_INSIDE_CI_MIN  # one threshold for the gate and the record's status
from assets_lib.stages.spec import StageOutput, stage
from raw_schemas.tables import ACCEL_COLUMNS, GYRO_COLUMNS

#: confidence level of the stored Allan-deviation intervals
CI_LEVEL = 0.95


@stage("allan_deviation", level="capture", group="noise", code_version="1", upstream=["ingested_run"],
       applies_to=("static",))
def allan_deviation(key: str, inputs) -> StageOutput:
    """Overlapping Allan deviation ([SEED002] eq. 4) per channel with chi-square intervals, and the IEEE 952
    Annex C fit (Q, N, B, K, R with intervals; unsupported terms as upper bounds) beside the slope readings."""
    imu = inputs.table("ingested_run", "imu")
    m = inputs.meta("ingested_run")
    tables, meta, summary, _, _ = allan_tables(key, imu, m)
    return StageOutput(tables=tables, meta=meta, summary=summary)


def allan_tables(key: str, imu: pd.DataFrame, m: dict):
    """The stage's computation without its plots (benchmarks/coverage_noise.py scores exactly this): tables
    ``allan``, ``noise``, ``static_terms``, the meta and summary, and the per-channel results and fits."""
    rate_hz = float(m.get("sample_rate_hz") or 1.0 / np.median(np.diff(imu.time_s)))
    channels = list(GYRO_COLUMNS + ACCEL_COLUMNS)
    results = allan_deviations(imu[channels], rate_hz, taus="octave", channels=channels, ci_level=CI_LEVEL)
    fits = fit_all(results)
    allan = pd.concat([r.to_frame() for r in results.values()], ignore_index=True).assign(ci_level=CI_LEVEL)
    noise = noise_table(fits)
    inside = {c: _model_inside_ci(results[c], fits[c]) for c in channels}
    summary = {}
    for _, r in noise[(noise.method == "fit") & noise.parameter.isin(["N", "B"])].iterrows():
        summary[f"{r.channel}_{r.parameter}_{r.unit_lab}"] = float(r.value_lab)
    dur = len(imu) / rate_hz
    units = {c: ("rad/s" if c in GYRO_COLUMNS else "m/s^2") for c in channels}
    static_terms = pd.DataFrame([static_terms_row(m.get("run_id", key), int(m.get("power_cycle_index", 0) or 0), c,
                                                  float(imu[c].mean()), dur, fits[c], units[c]) for c in channels],
                                columns=STATIC_RUN_COLUMNS)
    warnings = [w for c in channels for w in fits[c].warnings]
    return ({"allan": allan, "noise": noise, "static_terms": static_terms},
            {"model_inside_ci": inside, "rate_hz": rate_hz, "warnings": warnings}, summary, results, fits)


def _model_inside_ci(res, fit) -> float:
    """Share of the fitted taus at which the model deviation lies inside the measured interval."""
    model = np.sqrt(sum(fit.term_avar(res.tau_s).values()))
    ok = (model >= res.ci_lo) & (model <= res.ci_hi)
    used = np.isin(res.tau_s, fit.tau_s)
    return float(ok[used].mean()) if used.any() else float("nan")
