"""Turn-on to turn-on repeatability of bias and scale factor over a device's power-cycled runs.

Bias repeatability ([SEED000] eq. 23; [GJB2426A] B_r): the sample standard deviation of the per-run biases,
B_r = sqrt( sum (B_i - mean B)^2 / (Q - 1) ). Scale-factor repeatability ([SEED003] eq. 9; GJB K_r):
K_r = sqrt( sum (K_i - mean K)^2 / (Q - 1) ) / mean K. Both with the number of runs Q and a chi-square
confidence interval on the standard deviation, assuming normally distributed run values:
sigma in [s sqrt(nu / chi2_{1-a/2}(nu)), s sqrt(nu / chi2_{a/2}(nu))], nu = Q - 1.

The sample standard deviation includes each run's own estimation noise. When the per-run standard errors are
known, the noise-corrected value sqrt(max(0, s^2 - mean(se^2))) is also reported (method of moments): it is
what the device itself repeats to, whereas s is the seed's (and the standards') definition. Its interval is the
modified large-sample (MLS) interval of a difference of two variance estimates ([BURDICK1992] sec. 3.3, eqs.
3.19-3.20, after [TING1990]): theta = E(s^2) - E(mean se^2) with s^2 on nu_1 degrees of freedom (Satterthwaite's
[SATTERTHWAITE1946] nu_1 when the runs' noise variances differ) and mean(se^2) on nu_2 (Satterthwaite over the
runs' standard-error degrees of freedom; infinite when the standard errors are taken as known, where the interval
is the exact chi-square interval of E(s^2) shifted by mean(se^2)). The limits on theta are truncated at zero and
square-rooted (an interval on a standard deviation).

Turn-on bias standard errors (issue 15, session 7): each run's se^2 is the Allan variance at the record length T,
sigma_A^2(T) ([IEEE952] C.1). Read from each run's own noise fit it held an unidentified flicker floor B at zero
(gyro B only a bound in 78 % of the 200 s power-cycled runs): median 0.58 of the truth's sigma_A^2(T) on
tactical gyros, mean(se^2) too small and the noise-corrected value too large (gyro mean z +0.09, tactical
+0.22). Per run, any non-negative estimate of an unresolved floor is biased, and refitting B unconstrained per
run over-corrected (tactical coverage 1.000, navigation mean z -0.39). :func:`pooled_bias_stderrs` instead
fits ONE noise model per channel to the EDF-weighted mean Allan variance of all the device's static records
(the power-cycled runs and any longer static record: one device, one noise;
:func:`assets_lib.noise.pooled.fit_pooled_curves`: Q, N, and B, K, R each selected by ``MODEL_PENALTY``,
non-negative) and reads every run's se^2 from it at T without the rate ramp (a ramp restarting at each turn-on
offsets every equal-length run's mean alike: no scatter). Pooled, the floor is resolved where the runs resolve it
together. mean(se^2) then comes from one fit, not from independent per-run estimates: its degrees of freedom
nu_2 are the fit's (2 mean(se^2)^2 / Var, Var from the fit's Wald covariance), not Satterthwaite's sum over
runs, which would count the one estimate q times.

Measured on benchmarks/coverage_noise.py's trials (seed 16021, the 162 device/extra_terms trials of k < 240,
486 rows per sensor, trial-clustered SEs), per-run fit -> pooled fit (coverage, mean z, sd z):
gyro 0.953 +0.091 1.04 -> 0.949 +0.007 (+-0.044) 1.06; tactical 0.957 +0.215 0.99 -> 0.963 +0.056 (+-0.065) 1.00;
consumer unchanged (0.951 +0.086 1.05); navigation 0.951 -0.030 1.07 -> 0.932 -0.122 (+-0.081) 1.12;
accelerometer 0.951 +0.075 1.00 -> 0.953 +0.036 1.01 (navigation 0.920 +0.202 -> 0.932 +0.090, tactical
0.981 -> 0.975, sd 0.88 -> 0.93). Not met: navigation gyro (mean z -0.12 +- 0.08, 1.5 SE from 0, within one SE of the 0.1 limit; sd 1.12) and
tactical accelerometer coverage 0.975 (+-0.012). Navigation gyro: se^2 is ~3x the turn-on variance there, so
any error in se^2 moves z; on the extra_terms plan the ramp of a short record is partly taken for rate random
walk (K selected instead of R on the 82 s longest tau) and K extrapolated to T over-states se^2 (one channel:
6x). Alternatives measured on the same trials: B kept when not selected (gyro navigation -0.21/-0.27, the
non-negative estimate of an unresolved floor is biased up); unconstrained B (unbiased sigma_A^2(T), but its
noise gave z sd 1.5-2.1 and clipped negative predictions, navigation coverage 0.68-0.75); power-cycled runs only,
without the 1200 s record (gyro sd 1.105, navigation -0.14, extra_terms -0.21).
The ``imulab repeatability`` command takes the same pooled standard errors (:func:`static_run_allan` per run,
then :func:`pooled_bias_stderrs`); each run's N and B still come from its own fit (:func:`static_run_terms`).
"""

from __future__ import annotations

import math
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
    noise_corrected_ci_low: float = float("nan")  #: MLS interval ([BURDICK1992] 3.19-3.20) at ``confidence``
    noise_corrected_ci_high: float = float("nan")

    def estimate(self, unit: str) -> Coefficient:
        """The repeatability as a :class:`Coefficient` with its chi-square interval at ``confidence``."""
        return Coefficient(self.std, self.std_stderr, unit, bool(np.isfinite(self.std)), self.ci_low, self.ci_high,
                           self.confidence)


def mls_difference_interval(s1: float, nu1: float, s2: float, nu2: float, confidence: float = 0.95
                            ) -> tuple[float, float]:
    """[BURDICK1992] eqs. 3.19-3.20 ([TING1990]): MLS interval on theta = E(s1) - E(s2) for independent variance
    estimates s1 ~ E(s1) chi2_nu1 / nu1 and s2 ~ E(s2) chi2_nu2 / nu2 (nu2 = inf: s2 known, exact shift)."""
    a = 1.0 - confidence
    th = s1 - s2
    c1lo, c1hi = stats.chi2.ppf(1 - a / 2, nu1), stats.chi2.ppf(a / 2, nu1)
    g1, h1 = 1.0 - nu1 / c1lo, nu1 / c1hi - 1.0
    if not np.isfinite(nu2) or s2 == 0.0:
        return th - g1 * s1, th + h1 * s1
    c2lo, c2hi = stats.chi2.ppf(1 - a / 2, nu2), stats.chi2.ppf(a / 2, nu2)
    g2, h2 = 1.0 - nu2 / c2lo, nu2 / c2hi - 1.0
    f_hi = stats.f.ppf(1 - a / 2, nu1, nu2)
    f_lo = stats.f.ppf(a / 2, nu1, nu2)
    g12 = ((f_hi - 1.0) ** 2 - g1**2 * f_hi**2 - h2**2) / f_hi
    h12 = ((1.0 - f_lo) ** 2 - h1**2 * f_lo**2 - g2**2) / f_lo
    vl = g1**2 * s1**2 + h2**2 * s2**2 + g12 * s1 * s2
    vu = h1**2 * s1**2 + g2**2 * s2**2 + h12 * s1 * s2
    return th - math.sqrt(max(vl, 0.0)), th + math.sqrt(max(vu, 0.0))


def satterthwaite_dof(values, stderrs) -> float:
    """[SATTERTHWAITE1946] degrees of freedom nu_1 of the sample variance s^2 of ``values`` when the runs' variances
    v_i = sigma^2 + se_i^2 differ (sigma^2 estimated as max(s^2 - mean se^2, 0); s^2 is a quadratic form
    x'(I - J/q)x / (q - 1) of independent normals): E(s^2) = mean(v),
    Var(s^2) = 2 (sum v^2 (1 - 2/q) + (sum v)^2 / q^2) / (q - 1)^2, nu_1 = 2 E^2 / Var (= q - 1 if all equal)."""
    v = np.asarray(values, float)
    e2 = np.asarray(stderrs, float) ** 2
    q = len(v)
    vi = max(float(np.var(v, ddof=1)) - float(e2.mean()), 0.0) + e2
    var_s2 = 2.0 * (np.sum(vi**2) * (1 - 2 / q) + np.sum(vi) ** 2 / q**2) / (q - 1) ** 2
    return float(2.0 * np.mean(vi) ** 2 / var_s2) if var_s2 > 0 else float(q - 1)


def repeatability(values, stderrs=None, *, relative: bool = False, confidence: float = 0.95,
                  stderr_dofs=None, stderr_mean_dof: float | None = None) -> Repeatability:
    """[SEED000] eq. 23 (and [SEED003] eq. 9 when ``relative``): sample std over runs with a chi-square CI; with
    ``stderrs`` also the noise-corrected std and its MLS interval (module doc; ``stderr_dofs``: degrees of
    freedom of each run's squared standard error, independent across runs, default infinite = known;
    ``stderr_mean_dof``: instead, the degrees of freedom of mean(se^2) itself, when all the standard errors come
    from one shared fit and are fully dependent, so Satterthwaite's sum over runs does not apply)."""
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
    have_se = se is not None and np.all(np.isfinite(se))
    rms_se = float(np.sqrt(np.mean(se**2))) if have_se else nan
    corr = float(np.sqrt(max(s**2 - rms_se**2, 0.0))) if np.isfinite(rms_se) else nan
    c_lo = c_hi = nan
    if have_se:
        e2 = se**2
        nu1 = satterthwaite_dof(v, se)
        d = None if stderr_dofs is None else np.asarray(stderr_dofs, float)[ok]
        if stderr_mean_dof is not None:
            nu2 = float(stderr_mean_dof) if np.isfinite(stderr_mean_dof) and stderr_mean_dof > 0 else math.inf
        elif d is None or not np.all(np.isfinite(d)):
            nu2 = math.inf
        else:
            den = float(np.sum(e2**2 / np.maximum(d, 1e-9)))
            nu2 = float(np.sum(e2) ** 2 / den) if den > 0 else math.inf
        t_lo, t_hi = mls_difference_interval(s**2, nu1, rms_se**2, nu2, confidence)
        c_lo, c_hi = math.sqrt(max(t_lo, 0.0)), math.sqrt(max(t_hi, 0.0))
    if relative:
        d = abs(m)
        s, lo, hi, sse = s / d, lo / d, hi / d, sse / d
        rms_se, corr, c_lo, c_hi = rms_se / d, corr / d, c_lo / d, c_hi / d
    return Repeatability(q, m, float(s), float(sse), float(lo), float(hi), confidence, rms_se, corr, relative,
                         float(c_lo), float(c_hi))


def bias_repeatability(biases, stderrs=None, *, confidence: float = 0.95) -> Repeatability:
    """[SEED000] eq. 23: bias repeatability [rad/s or m/s^2] from per-run biases."""
    return repeatability(biases, stderrs, relative=False, confidence=confidence)


def scale_factor_repeatability(scale_factors, stderrs=None, *, confidence: float = 0.95) -> Repeatability:
    """[SEED003] eq. 9: scale-factor repeatability std(K_i)/mean(K) (dimensionless; x 1e6 = ppm)."""
    return repeatability(scale_factors, stderrs, relative=True, confidence=confidence)


REPEATABILITY_COLUMNS = [
    "device_id", "sensor", "axis", "coefficient", "method", "n_runs", "run_ids", "value", "stderr", "ci_low", "ci_high",
    "confidence", "unit", "value_lab", "stderr_lab", "ci_low_lab", "ci_high_lab", "unit_lab",
    "within_run_stderr_rms", "value_noise_corrected", "value_noise_corrected_lab", "noise_corrected_ci_low",
    "noise_corrected_ci_high", "noise_corrected_ci_low_lab", "noise_corrected_ci_high_lab",
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
            noise_corrected_ci_low=r.noise_corrected_ci_low, noise_corrected_ci_high=r.noise_corrected_ci_high,
            noise_corrected_ci_low_lab=lab.to_lab(r.noise_corrected_ci_low),
            noise_corrected_ci_high_lab=lab.to_lab(r.noise_corrected_ci_high),
        ))
    return pd.DataFrame(rows, columns=REPEATABILITY_COLUMNS)


# ------------------------------------------------------------------------------------------------------------
# Static power-cycled runs: turn-on bias and noise-term repeatability ([SEED000], the turn-on to turn-on test)
# ------------------------------------------------------------------------------------------------------------
STATIC_RUN_COLUMNS = ["run_id", "power_cycle_index", "channel", "duration_s", "bias", "bias_stderr", "bias_stderr_dof",
                      "N", "N_stderr", "B", "B_stderr", "unit", "noise_warnings"]


def static_run_terms(run_id: str, power_cycle_index: int, data: dict, rate_hz: float, units: dict | None = None,
                     results: dict | None = None) -> pd.DataFrame:
    """One static run: per channel the turn-on bias (record mean) with its standard error sqrt(sigma_A^2(T)) read
    from the fitted noise model at the record length T ([IEEE952] C.1: the scatter of a T-long mean;
    white-noise sigma/sqrt(n) would be too small under bias instability), and the N and B terms of the fit
    (:func:`assets_lib.noise.identification.fit_noise`, standard errors from the 95 % intervals / 3.92).
    ``results``: the run's :func:`static_run_allan` when the caller already has it."""
    from assets_lib.noise import identification as ni

    results = results if results is not None else static_run_allan(data, rate_hz, units)
    rows = []
    for ch, y in data.items():
        y = np.asarray(y, float)
        rows.append(static_terms_row(run_id, power_cycle_index, ch, float(y.mean()), y.size / rate_hz,
                                     ni.fit_noise(results[ch]), (units or {}).get(ch, "")))
    return pd.DataFrame(rows, columns=STATIC_RUN_COLUMNS)


def static_run_allan(data: dict, rate_hz: float, units: dict | None = None) -> dict:
    """Per channel of one static run the octave-spaced overlapping Allan deviation ([SEED002] eq. 4), as the
    ``allan_deviation`` stage computes it; ``pd.concat([r.to_frame() for r in result.values()])`` is the run's
    ``allan`` table that :func:`pooled_bias_stderrs` takes."""
    from assets_lib.noise import allan as al

    return {ch: al.allan_deviation(np.asarray(y, float), rate_hz, "octave", channel=ch, unit=(units or {}).get(ch, ""))
            for ch, y in data.items()}


def static_terms_row(run_id: str, power_cycle_index: int, channel: str, mean: float, duration_s: float, fit,
                     unit: str = "") -> dict:
    """One row of :data:`STATIC_RUN_COLUMNS` from a channel's record mean and its fitted noise model ``fit``
    (a ``NoiseFit``): bias standard error sqrt(sigma_A^2(T)) at the record length T with the degrees of freedom of
    sigma_A^2(T) (Satterthwaite, 2 sigma_A^4 / Var from the fit's theta covariance), N and B with standard errors
    from their 95 % intervals / 3.92 (NaN when only bounded)."""
    avar_t, dof_t = fit.model_avar_dof(np.array([duration_s]))
    se_bias = float(np.sqrt(max(avar_t[0], 0.0)))
    n, b = fit.parameter("N"), fit.parameter("B")

    def val(p):
        return (np.nan, np.nan) if p.is_upper_bound else (p.value, (p.ci_hi - p.ci_lo) / 3.92)

    return dict(run_id=run_id, power_cycle_index=power_cycle_index, channel=channel, duration_s=duration_s,
                bias=mean, bias_stderr=se_bias, bias_stderr_dof=float(dof_t[0]), N=val(n)[0], N_stderr=val(n)[1], B=val(b)[0], B_stderr=val(b)[1],
                unit=unit, noise_warnings=" | ".join(fit.warnings))


STATIC_REPEATABILITY_COLUMNS = ["channel", "quantity", "n_runs", "mean", "value", "ci_low", "ci_high", "relative",
                                "within_run_stderr_rms", "value_noise_corrected", "noise_corrected_ci_low",
                                "noise_corrected_ci_high", "unit", "confidence"]


#: terms of the pooled model (Q, N, B, K; not the rate ramp R) whose AVAR at T is a run mean's scatter: a ramp
#: restarting at each turn-on offsets every equal-length run's mean by the same R T / 2 (no scatter between runs)
NOISE_TERMS = (0, 1, 2, 3)


def pooled_bias_stderrs(runs: pd.DataFrame, allan_by_run: dict, nonnegative: bool = True,
                        keep_flicker: bool = False) -> pd.DataFrame:
    """The static run table (:data:`STATIC_RUN_COLUMNS`) with each run's turn-on bias standard error
    sqrt(sigma_A^2(T)) re-read from ONE noise model per channel fitted to the Allan variances of all the device's
    static records (:func:`assets_lib.noise.pooled.fit_pooled_curves`, module doc "Turn-on bias standard errors"):
    the flicker floor is estimated once over all of them instead of held at zero per run.

    ``allan_by_run``: run_id -> the ``allan`` table of one static record of the device (``allan_deviation`` stage:
    channel, tau_s, adev, edf); every table enters the fit (records not in ``runs``, e.g. a longer static run,
    too); runs without a table keep their own standard errors. ``nonnegative`` / ``keep_flicker``: the fit's
    constraint and whether B stays in it when the selection does not admit it (defaults: the measured choice).
    Adds ``bias_stderr_mean_dof`` (degrees of freedom of the channel's mean(se^2): one fit's, the runs' standard
    errors are not independent) and ``bias_stderr_model`` ('pooled' or 'per_run'); ``bias_stderr_dof`` becomes
    each run's sigma_A^2(T) dof under the pooled fit."""
    from assets_lib.noise.pooled import fit_pooled_curves

    out = runs.copy()
    out["bias_stderr_mean_dof"] = np.nan
    out["bias_stderr_model"] = "per_run"
    have = out["run_id"].astype(str).isin({str(k) for k in allan_by_run})
    for ch, g in out[have].groupby("channel", sort=True):
        curves = []
        for a in allan_by_run.values():  # every static record of the device: one noise, one fit
            a = a[a["channel"] == ch]
            if a.empty:
                continue
            curves.append((a["tau_s"].to_numpy(float), a["adev"].to_numpy(float) ** 2, a["edf"].to_numpy(float)))
        if len(curves) < 2:
            continue
        fit = fit_pooled_curves(*zip(*curves), nonnegative=nonnegative, keep_flicker=keep_flicker)
        t = g["duration_s"].to_numpy(float)
        avar, dof = fit.avar_dof(t, terms=NOISE_TERMS)
        out.loc[g.index, "bias_stderr"] = np.sqrt(np.maximum(avar, 0.0))
        out.loc[g.index, "bias_stderr_dof"] = dof
        out.loc[g.index, "bias_stderr_mean_dof"] = fit.mean_avar_dof(t, terms=NOISE_TERMS)
        out.loc[g.index, "bias_stderr_model"] = "pooled"
    return out


def static_repeatability(runs: pd.DataFrame, *, confidence: float = 0.95) -> pd.DataFrame:
    """[SEED000] eq. 23 over power-cycled static runs: per channel the bias repeatability (std of the turn-on
    biases, absolute, with the noise-corrected value and its MLS interval) and the repeatability of the N and B
    terms (relative std). Bias standard errors from one shared fit (:func:`pooled_bias_stderrs`) give mean(se^2)
    the fit's degrees of freedom."""
    rows = []
    for ch, g in runs.groupby("channel", sort=True):
        for q, rel in (("bias", False), ("N", True), ("B", True)):
            dofs = g["bias_stderr_dof"] if (q == "bias" and "bias_stderr_dof" in g) else None
            mean_dof = None
            if q == "bias" and "bias_stderr_mean_dof" in g and (g.get("bias_stderr_model") == "pooled").all():
                mean_dof = float(g["bias_stderr_mean_dof"].iloc[0])
            r = repeatability(g[q], g[f"{q}_stderr"], relative=rel, confidence=confidence, stderr_dofs=dofs,
                              stderr_mean_dof=mean_dof)
            rows.append(dict(channel=ch, quantity=f"{q}_repeatability", n_runs=r.n_runs, mean=r.mean, value=r.std,
                             ci_low=r.ci_low, ci_high=r.ci_high, relative=rel,
                             within_run_stderr_rms=r.within_run_stderr_rms, value_noise_corrected=r.std_noise_corrected,
                             noise_corrected_ci_low=r.noise_corrected_ci_low,
                             noise_corrected_ci_high=r.noise_corrected_ci_high,
                             unit="1" if rel else str(g["unit"].iloc[0]), confidence=confidence))
    return pd.DataFrame(rows, columns=STATIC_REPEATABILITY_COLUMNS)
