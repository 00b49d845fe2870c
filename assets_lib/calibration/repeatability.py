"""Turn-on to turn-on repeatability of bias and scale factor over a device's power-cycled runs.

Bias repeatability ([SEED000] eq. 23; [GJB2426A] B_r): the sample standard deviation of the per-run biases,
B_r = sqrt( sum (B_i - mean B)^2 / (Q - 1) ). Scale-factor repeatability ([SEED003] eq. 9; GJB K_r):
K_r = sqrt( sum (K_i - mean K)^2 / (Q - 1) ) / mean K. Both with the number of runs Q and a chi-square
confidence interval on the standard deviation, assuming normally distributed run values:
sigma in [s sqrt(nu / chi2_{1-a/2}(nu)), s sqrt(nu / chi2_{a/2}(nu))], nu = Q - 1.

The sample standard deviation includes each run's own estimation noise. When the per-run standard errors are
known, the noise-corrected value sqrt(max(0, s^2 - mean(se^2))) is also reported (method of moments): it is
what the device itself repeats to, whereas s is the seed's (and the standards') definition.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pandas as pd
from scipy import stats

from assets_lib.coefficient import Coefficient
from raw_schemas.units import lab_unit


@dataclass(frozen=True)
class Repeatability:
    """[SEED000] eq. 23: std of the per-run values (relative to their mean when ``relative``)."""

    n_runs: int
    mean: float
    std: float
    std_stderr: float  # s / sqrt(2 nu), large-sample
    ci_low: float
    ci_high: float
    confidence: float
    within_run_stderr_rms: float  # RMS of the per-run standard errors (NaN if not given)
    std_noise_corrected: float
    relative: bool

    def estimate(self, unit: str) -> Coefficient:
        """The repeatability as a :class:`Coefficient` with its chi-square interval at ``confidence``."""
        return Coefficient(self.std, self.std_stderr, unit, bool(np.isfinite(self.std)), self.ci_low, self.ci_high,
                           self.confidence)


def repeatability(values, stderrs=None, *, relative: bool = False, confidence: float = 0.95) -> Repeatability:
    """[SEED000] eq. 23 (and [SEED003] eq. 9 when ``relative``): sample std over runs with a chi-square CI."""
    v = np.asarray(values, float)
    ok = np.isfinite(v)
    v = v[ok]
    q = len(v)
    se = None if stderrs is None else np.asarray(stderrs, float)[ok]
    nan = float("nan")
    if q < 2:
        return Repeatability(q, float(v.mean()) if q else nan, nan, nan, nan, nan, confidence, nan, nan, relative)
    nu = q - 1
    m = float(v.mean())
    s = float(v.std(ddof=1))
    a = 1 - confidence
    lo = s * np.sqrt(nu / stats.chi2.ppf(1 - a / 2, nu))
    hi = s * np.sqrt(nu / stats.chi2.ppf(a / 2, nu))
    sse = s / np.sqrt(2 * nu)
    rms_se = float(np.sqrt(np.mean(se**2))) if se is not None and np.all(np.isfinite(se)) else nan
    corr = float(np.sqrt(max(s**2 - rms_se**2, 0.0))) if np.isfinite(rms_se) else nan
    if relative:
        d = abs(m)
        s, lo, hi, sse = s / d, lo / d, hi / d, sse / d
        rms_se, corr = rms_se / d, corr / d
    return Repeatability(q, m, float(s), float(sse), float(lo), float(hi), confidence, rms_se, corr, relative)


def bias_repeatability(biases, stderrs=None, *, confidence: float = 0.95) -> Repeatability:
    """[SEED000] eq. 23: bias repeatability [rad/s or m/s^2] from per-run biases."""
    return repeatability(biases, stderrs, relative=False, confidence=confidence)


def scale_factor_repeatability(scale_factors, stderrs=None, *, confidence: float = 0.95) -> Repeatability:
    """[SEED003] eq. 9: scale-factor repeatability std(K_i)/mean(K) (dimensionless; x 1e6 = ppm)."""
    return repeatability(scale_factors, stderrs, relative=True, confidence=confidence)


REPEATABILITY_COLUMNS = [
    "device_id", "sensor", "axis", "coefficient", "method", "n_runs", "run_ids", "value", "stderr", "ci_low", "ci_high",
    "confidence", "unit", "value_lab", "stderr_lab", "ci_low_lab", "ci_high_lab", "unit_lab",
    "within_run_stderr_rms", "value_noise_corrected", "value_noise_corrected_lab",
]


def repeatability_table(coefficients: pd.DataFrame, *, confidence: float = 0.95) -> pd.DataFrame:
    """Per device, sensor, axis and method: bias and scale-factor repeatability over the runs of a COEFFICIENT
    TABLE (rows with coefficient 'bias' / 'scale_factor', observable, one per run)."""
    c = coefficients[coefficients["coefficient"].isin(["bias", "scale_factor"]) & coefficients["observable"]]
    rows = []
    for (dev, sensor, axis, coef, method), g in c.groupby(["device_id", "sensor", "axis", "coefficient", "method"],
                                                          sort=True):
        rel = coef == "scale_factor"
        r = repeatability(g["value"], g["stderr"], relative=rel, confidence=confidence)
        name = "scale_factor_repeatability" if rel else "bias_repeatability"
        lab = lab_unit(sensor, name)
        est = r.estimate(lab.si)
        in_lab = est.to_lab(lab)
        rows.append(dict(
            device_id=dev, sensor=sensor, axis=axis, coefficient=name, method=method, n_runs=r.n_runs,
            run_ids=",".join(map(str, g["run_id"])), value=r.std, stderr=r.std_stderr, ci_low=r.ci_low,
            ci_high=r.ci_high, confidence=confidence, unit=lab.si, value_lab=lab.to_lab(r.std),
            stderr_lab=in_lab.stderr, ci_low_lab=in_lab.ci_low, ci_high_lab=in_lab.ci_high, unit_lab=lab.lab,
            within_run_stderr_rms=r.within_run_stderr_rms, value_noise_corrected=r.std_noise_corrected,
            value_noise_corrected_lab=lab.to_lab(r.std_noise_corrected),
        ))
    return pd.DataFrame(rows, columns=REPEATABILITY_COLUMNS)


# ------------------------------------------------------------------------------------------------------------
# Static power-cycled runs: turn-on bias and noise-term repeatability ([SEED000], the turn-on to turn-on test)
# ------------------------------------------------------------------------------------------------------------
STATIC_RUN_COLUMNS = ["run_id", "power_cycle_index", "channel", "duration_s", "bias", "bias_stderr", "N", "N_stderr",
                      "B", "B_stderr", "unit", "noise_warnings"]


def static_run_terms(run_id: str, power_cycle_index: int, data: dict, rate_hz: float, units: dict | None = None
                     ) -> pd.DataFrame:
    """One static run: per channel the turn-on bias (record mean) with its standard error sqrt(sigma_A^2(T)) read
    from the fitted noise model at the record length T ([IEEE952] C.1: the scatter of a T-long mean;
    white-noise sigma/sqrt(n) would be too small under bias instability), and the N and B terms of the fit
    (:func:`assets_lib.noise.identification.fit_noise`, standard errors from the 95 % intervals / 3.92)."""
    from assets_lib.noise import allan as al
    from assets_lib.noise import identification as ni

    rows = []
    for ch, y in data.items():
        y = np.asarray(y, float)
        r = al.allan_deviation(y, rate_hz, "octave", channel=ch, unit=(units or {}).get(ch, ""))
        rows.append(static_terms_row(run_id, power_cycle_index, ch, float(y.mean()), y.size / rate_hz, ni.fit_noise(r),
                                     (units or {}).get(ch, "")))
    return pd.DataFrame(rows, columns=STATIC_RUN_COLUMNS)


def static_terms_row(run_id: str, power_cycle_index: int, channel: str, mean: float, duration_s: float, fit,
                     unit: str = "") -> dict:
    """One row of :data:`STATIC_RUN_COLUMNS` from a channel's record mean and its fitted noise model ``fit``
    (a ``NoiseFit``): bias standard error sqrt(sigma_A^2(T)) at the record length T, N and B with standard errors
    from their 95 % intervals / 3.92 (NaN when only bounded)."""
    se_bias = float(np.sqrt(max(fit.model_avar(np.array([duration_s]))[0], 0.0)))
    n, b = fit.parameter("N"), fit.parameter("B")

    def val(p):
        return (np.nan, np.nan) if p.is_upper_bound else (p.value, (p.ci_hi - p.ci_lo) / 3.92)

    return dict(run_id=run_id, power_cycle_index=power_cycle_index, channel=channel, duration_s=duration_s,
                bias=mean, bias_stderr=se_bias, N=val(n)[0], N_stderr=val(n)[1], B=val(b)[0], B_stderr=val(b)[1],
                unit=unit, noise_warnings=" | ".join(fit.warnings))


STATIC_REPEATABILITY_COLUMNS = ["channel", "quantity", "n_runs", "mean", "value", "ci_low", "ci_high", "relative",
                                "within_run_stderr_rms", "value_noise_corrected", "unit", "confidence"]


def static_repeatability(runs: pd.DataFrame, *, confidence: float = 0.95) -> pd.DataFrame:
    """[SEED000] eq. 23 over power-cycled static runs: per channel the bias repeatability (std of the turn-on
    biases, absolute, with the noise-corrected value) and the repeatability of the N and B terms (relative std)."""
    rows = []
    for ch, g in runs.groupby("channel", sort=True):
        for q, rel in (("bias", False), ("N", True), ("B", True)):
            r = repeatability(g[q], g[f"{q}_stderr"], relative=rel, confidence=confidence)
            rows.append(dict(channel=ch, quantity=f"{q}_repeatability", n_runs=r.n_runs, mean=r.mean, value=r.std,
                             ci_low=r.ci_low, ci_high=r.ci_high, relative=rel,
                             within_run_stderr_rms=r.within_run_stderr_rms, value_noise_corrected=r.std_noise_corrected,
                             unit="1" if rel else str(g["unit"].iloc[0]), confidence=confidence))
    return pd.DataFrame(rows, columns=STATIC_REPEATABILITY_COLUMNS)
