"""Monte Carlo coverage of the coefficient repeatability the ``repeatability`` stage prints (issue 15).

The stage's ``repeatability`` table gives, per device, sensor, axis and fit, the turn-on to turn-on spread of each
bias and scale factor over the device's power-cycled runs ([SEED000] eq. 23, [SEED003] eq. 9): the sample standard
deviation of the runs' estimates with its chi-square interval, and the noise-corrected spread (the within-run
standard errors removed) with its modified-large-sample interval ([BURDICK1992] sec. 3.3, via
``assets_lib.calibration.repeatability.mls_difference_interval``). benchmarks/coverage_noise.py scores the turn-on
bias repeatability of static runs; this script scores the rate and position runs' rows, on the pipeline's own code
path.

Each trial draws a device of one grade (``example_device``; grades cycled) whose turn-on spreads (the simulator's
``bias_repeatability`` and ``scale_repeatability``, gyro and accelerometer) are the grade's own, each multiplied by a
factor drawn log-uniform in [1/``--spread``, ``--spread``] per trial, so that the spread ranges from below the
runs' standard errors to well above them. ``--cycles`` power cycles (``DeviceTruth.for_power_cycle``) each give one
rate run (``--rate-plan``) and one position run (``--pos-plan``), simulated as raw counts, ingested
(``ingest_frames``), segmented (``segment_run``; a run failing the plateaus stage's blocking gate gets no fit, as in
the pipeline) and fitted as the stages fit them (``fit_gyro_rate``, ``fit_accel_multiposition``,
``fit_gyro_static``, with the device's static record of ``--static-s`` seconds as their 1/f level B where it
resolves it, as the stages' sibling read does, ``mc_calibration_coverage.static_prior``; without it each run's own
B); the stage's ``repeatability_table`` over the concatenated coefficient tables gives the rows scored.

Scored per row (family ``sensor:fit:coefficient`` and ``...:coefficient_noise_corrected``):

- noise-corrected spread: truth the simulated turn-on spread sigma (bias: SI; scale factor: sigma / |K|, the
  device's nominal K, as the stage divides by the runs' mean); covered when the printed MLS interval contains it;
  z the interval's pivot, Phi^-1(F_chi2(nu_1 s^2 / (sigma^2 + mean se^2); nu_1)) with nu_1 the Satterthwaite degrees
  of freedom the stage uses (as benchmarks/coverage_noise.py scores the static runs' repeatability);
- sample spread (the estimates' own scatter, noise included): truth sqrt(sigma^2 + mean se^2) with the fits' own
  standard errors (their honesty is scored by benchmarks/mc_calibration_coverage.py); its chi-square interval with
  q - 1 degrees of freedom; z = Phi^-1(F_chi2((q - 1) s^2 / truth^2; q - 1)).

The rate fit's bias truth includes G f_bar (g-sensitivity not separable in a rate plan), the same for every cycle, so
its spread is the turn-on spread. Bias ageing between cycles is zero here (``gyro_bias_drift_per_day`` 0).

    python benchmarks/coverage_repeatability.py --seed 71023 --trials 600 --workers 2 \
        --static-s navigation=10800,tactical=10800,consumer=1200
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import pandas as pd

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "benchmarks"))

from coverage_stats import chi2_pivot_z, clustered, meets_two_sided, run_budgeted, table_lines, write_results  # noqa: E402
from coverage_stats import TARGET_COVERAGE, TARGET_MEAN_Z, TARGET_SD_Z  # noqa: E402

GRADES = ("navigation", "tactical", "consumer")
SENSOR_INDEX = {"gyro": 0, "accel": 1}


def trial_device(seed: int, k: int, spread: float):
    """Trial k's device: the grade's example device with each turn-on spread scaled by a log-uniform factor."""
    from assets_lib.sim.simulator import example_device

    grade = GRADES[k % len(GRADES)]
    dev = example_device(f"RC{seed}-{k:05d}", grade, seed=seed)
    f = np.exp(np.random.default_rng([seed, k, 23]).uniform(-math.log(spread), math.log(spread), 4))
    return replace(dev, gyro_bias_drift_per_day=0.0,
                   bias_repeatability=(dev.bias_repeatability[0] * f[0], dev.bias_repeatability[1] * f[1]),
                   scale_repeatability=(dev.scale_repeatability[0] * f[2], dev.scale_repeatability[1] * f[3]))


def trial_coefficients(seed: int, k: int, cycles: int, rate_plan: str, pos_plan: str, spread: float, static_s=None):
    """(device, coefficient tables of every cycle's fits, runs failing the plateaus gate) of trial k; ``static_s``
    (``--static-s``): the device's static record, whose B the fits take (``mc_calibration_coverage.static_prior``)."""
    from assets_lib.calibration.multiposition import fit_accel_multiposition, fit_gyro_static
    from assets_lib.calibration.rate_fit import fit_gyro_rate
    from assets_lib.calibration.segmentation import segment_run
    from assets_lib.sim.simulator import simulate_run
    from assets_lib.stages.calibration import MIN_PLATEAU_FRACTION
    from raw_schemas.readers import ingest_frames

    from mc_calibration_coverage import _static_seconds, static_prior  # benchmarks/ is on sys.path

    dev = trial_device(seed, k, spread)
    prior = static_prior(dev, seed, k, _static_seconds(static_s, dev.grade))  # the stages' sibling read
    tables, failed = [], 0
    for c in range(cycles):
        tr = dev.for_power_cycle(c, seed)
        for m, plan in enumerate((rate_plan, pos_plan)):
            sim = simulate_run(tr, plan, f"pc{c:02d}-{'rate' if m == 0 else 'pos'}", power_cycle_index=c,
                               seed=seed * 1_000_000 + 100 * k + 2 * c + m)
            ing = ingest_frames(sim.manifest, sim.imu_raw, sim.table_raw)
            p = segment_run(ing.manifest, ing.imu, ing.table).plateaus
            if float((~p["flagged"].astype(bool)).mean()) < MIN_PLATEAU_FRACTION:  # the plateaus stage's gate
                failed += 1
                continue
            if m == 0:
                tables.append(fit_gyro_rate(p, noise_prior=prior).coefficient_table())  # stage gyro_rate_fit
            else:  # stage accel_multiposition_fit
                tables += [fit_accel_multiposition(p, noise_prior=prior).coefficient_table(),
                           fit_gyro_static(p, noise_prior=prior).coefficient_table()]
    return dev, tables, failed


def score(dev, coefficients: pd.DataFrame, rep: pd.DataFrame, base: dict) -> list[dict]:
    """Rows for every repeatability row with finite intervals (module docstring)."""
    from assets_lib.calibration.repeatability import satterthwaite_dof

    rows = []
    c = coefficients[coefficients["observable"].astype(bool)]
    runs = {k: g for k, g in c.groupby(["device_id", "sensor", "axis", "method", "coefficient"])}
    for r in rep.itertuples():
        s_idx = SENSOR_INDEX[r.sensor]
        i = "xyz".index(r.axis)
        rel = r.coefficient == "scale_factor_repeatability"
        tri = dev.gyro if r.sensor == "gyro" else dev.accel
        sigma = (dev.scale_repeatability[s_idx] / abs(tri.scale[i]) if rel else dev.bias_repeatability[s_idx])
        g = runs[(r.device_id, r.sensor, r.axis, r.method, "scale_factor" if rel else "bias")]  # the runs it used
        v, se = g["value"].to_numpy(float), g["stderr"].to_numpy(float)
        q = len(v)
        if q < 2 or not np.all(np.isfinite(se)):
            continue
        d = abs(v.mean()) if rel else 1.0
        v, se = v / d, se / d
        s2, mse2 = float(np.var(v, ddof=1)), float(np.mean(se**2))
        fam = f"{r.sensor}:{r.method}:{r.coefficient}"
        common = dict(base, sensor=r.sensor, axis=r.axis, n_runs=q, spread_over_se=sigma / math.sqrt(mse2))
        t_plain = math.sqrt(sigma**2 + mse2)
        if np.isfinite(r.ci_low) and np.isfinite(r.ci_high):
            rows.append(dict(common, family=fam, value=r.value, lo=r.ci_low, hi=r.ci_high, truth=t_plain,
                             z=chi2_pivot_z((q - 1) * s2 / t_plain**2, q - 1), covered=bool(r.ci_low <= t_plain <= r.ci_high)))
        lo, hi = r.noise_corrected_ci_low, r.noise_corrected_ci_high
        if np.isfinite(lo) and np.isfinite(hi):
            nu1 = satterthwaite_dof(v, se)
            rows.append(dict(common, family=fam + "_noise_corrected", value=r.value_noise_corrected, lo=lo, hi=hi,
                             truth=sigma, z=chi2_pivot_z(nu1 * s2 / (sigma**2 + mse2), nu1), covered=bool(lo <= sigma <= hi)))
    return rows


def trial(args: tuple) -> list[dict]:
    """Trial k: the stage's repeatability table over the device's power-cycled runs, scored."""
    from assets_lib.calibration.repeatability import repeatability_table

    seed, k, cycles, rate_plan, pos_plan, spread, static_s = args
    dev, tables, failed = trial_coefficients(seed, k, cycles, rate_plan, pos_plan, spread, static_s)
    base = {"seed": seed, "trial": k, "grade": dev.grade, "runs_failed_gate": failed}
    if not tables:
        return []
    coef = pd.concat(tables, ignore_index=True)
    return score(dev, coef, repeatability_table(coef), base)  # stage repeatability


def run(seed: int, trials: int, workers: int, cycles: int, rate_plan: str, pos_plan: str, spread: float,
        budget_s: float | None = None, static_s=None) -> pd.DataFrame:
    """Rows of trials 0..trials-1; with ``budget_s`` no trial starts after that many seconds."""
    jobs = [(seed, k, cycles, rate_plan, pos_plan, spread, static_s) for k in range(trials)]
    return pd.DataFrame(run_budgeted(trial, jobs, workers, budget_s))


def summarize(df: pd.DataFrame) -> dict[str, pd.DataFrame]:
    """Per family, per family and grade, and per family and spread regime (sigma over the runs' rms standard error
    below 1, 1-3, above 3), with trial-clustered standard errors."""
    df = df.assign(regime=pd.cut(df["spread_over_se"], [0, 1, 3, np.inf], labels=["<1", "1-3", ">3"]).astype(str))
    tabs = {}
    for name, keys in (("family", ["family"]), ("family_grade", ["family", "grade"]),
                       ("family_regime", ["family", "regime"])):
        t = pd.DataFrame([dict(zip(keys, kk if isinstance(kk, tuple) else (kk,)), **clustered(d))
                          for kk, d in df.groupby(keys)])
        t["meets"] = [meets_two_sided(r) for r in t.to_dict("records")]
        tabs[name] = t
    return tabs


def markdown(tabs: dict, meta: dict) -> str:
    fam = tabs["family"]
    lines = ["# Coefficient repeatability coverage (Monte Carlo, pipeline code path)", "",
             f"{meta['trials']} trials (seed {meta['seed']}; per trial {meta['cycles']} power cycles of a "
             f"{meta['rate_plan']} and a {meta['pos_plan']} run; turn-on spreads the grade's x log-uniform "
             f"[1/{meta['spread']:g}, {meta['spread']:g}]), {int(fam['n'].sum())} scored intervals, {meta['seconds']} s; "
             f"{meta['runs_failed_gate']} runs failed the plateaus gate. Generated by `{meta['command']}`.", "",
             f"Targets: 95 % coverage {TARGET_COVERAGE[0]:.2f}-{TARGET_COVERAGE[1]:.2f}, |mean z| < {TARGET_MEAN_Z}, "
             f"z sd {TARGET_SD_Z[0]}-{TARGET_SD_Z[1]} (z the interval's chi-square pivot; module docstring). ± are "
             f"trial-clustered standard errors. Families meeting every target: **{int(fam['meets'].sum())} of "
             f"{len(fam)}**; family x grade cells: {int(tabs['family_grade']['meets'].sum())} of "
             f"{len(tabs['family_grade'])}.", "", *table_lines(fam, ["family"])]
    for name, col in (("family_grade", "grade"), ("family_regime", "regime")):
        lines += ["", f"Per family and {col}" + (" (turn-on spread over the runs' rms standard error)" if col == "regime"
                                                 else "") + ":", "", *table_lines(tabs[name], ["family", col])]
    lines += ["", "Definitions and truths: the docstring of benchmarks/coverage_repeatability.py."]
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seed", type=int, default=0, help="base seed; use new seeds for acceptance")
    ap.add_argument("--trials", type=int, default=60)
    ap.add_argument("--workers", type=int, default=1)
    ap.add_argument("--cycles", type=int, default=5, help="power cycles per device (one rate and one position run each)")
    ap.add_argument("--rate-plan", default="quick_rate")
    ap.add_argument("--pos-plan", default="quick_24_position")
    ap.add_argument("--spread", type=float, default=4.0,
                    help="turn-on spreads are the grade's times a factor log-uniform in [1/SPREAD, SPREAD]")
    ap.add_argument("--static-s", default=None,
                    help="the device's static record (seconds, or per grade 'navigation=10800,...'), whose B the fits "
                         "take, as in benchmarks/mc_calibration_coverage.py; default none: each run's own B")
    ap.add_argument("--budget-s", type=float, default=None, help="start no trial after this many seconds")
    ap.add_argument("--out", type=Path, default=REPO / "benchmarks" / "results" / "repeatability_coverage")
    ap.add_argument("--records", action="store_true", help="also write every row to <out>.records.csv")
    args = ap.parse_args(argv)
    if args.cycles < 2 or args.spread < 1:
        ap.error("--cycles must be >= 2 and --spread >= 1")
    from mc_calibration_coverage import parse_static

    t0 = time.time()
    df = run(args.seed, args.trials, args.workers, args.cycles, args.rate_plan, args.pos_plan, args.spread, args.budget_s,
             parse_static(args.static_s))
    tabs = summarize(df)
    cmd = (f"python benchmarks/coverage_repeatability.py --seed {args.seed} --trials {args.trials} "
           f"--workers {args.workers} --cycles {args.cycles} --rate-plan {args.rate_plan} --pos-plan {args.pos_plan} "
           f"--spread {args.spread:g}" + (f" --static-s {args.static_s}" if args.static_s else "")
           + (f" --budget-s {args.budget_s:g}" if args.budget_s is not None else ""))
    failed = int(df.groupby("trial")["runs_failed_gate"].first().sum()) if len(df) else 0
    meta = {"seed": args.seed, "trials": int(df["trial"].nunique()) if len(df) else 0, "trials_requested": args.trials,
            "cycles": args.cycles, "rate_plan": args.rate_plan, "pos_plan": args.pos_plan, "spread": args.spread,
            "runs_failed_gate": failed, "seconds": round(time.time() - t0, 1), "command": cmd}
    text = markdown(tabs, meta)
    write_results(args.out, tabs, meta, text, df if args.records else None)
    print(text)
    return 0 if bool(tabs["family"]["meets"].all()) else 1


if __name__ == "__main__":
    raise SystemExit(main())
