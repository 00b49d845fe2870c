"""Monte Carlo coverage of the calibration fits' uncertainties (>= 200 full device calibrations).

Each trial draws a new device (``assets_lib.sim.simulator.example_device``, grades cycled), then runs the full chain

    simulate (raw counts, Allan noise incl. bias instability and rate random walk, saturation)
    -> ingest (``raw_schemas.readers.ingest_frames``) -> segment (``assets_lib.calibration.segmentation.segment_run``)
    -> fit (gyro rate fit, accelerometer 24-position fit, gyro static biases with earth rate removed)

on the ``quick_rate`` and ``quick_24_position`` plans, and compares every observable coefficient with its truth:
coverage of the reported 95 % interval (``ci95_low``..``ci95_high``: Student-t with the dof of the
pooled sem/scatter variance factor, see assets_lib/calibration/fit_core.py), and z = (estimate - truth) / stderr. Acceptance: pooled coverage 94-96 %, no coefficient
below 90 %, |mean z| < 0.2 for every coefficient.

Truths: gyro rate-fit bias where g-sensitivity is not separable is b + G f_bar (the fit says so in its note);
asymmetry 0 (the simulated scale factor is symmetric). The nonlinearity (a max statistic) is not scored.

``--mode direct`` skips simulation and segmentation: plateau tables built straight from the error model with
independent N(0, sem^2) plateau noise (tests/synth_plateaus.py), for a fast check of the fits alone.

    python benchmarks/mc_calibration_coverage.py --trials 200 --workers 2
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np
import pandas as pd

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "tests"))

from assets_lib.calibration.multiposition import fit_accel_multiposition, fit_gyro_static  # noqa: E402
from assets_lib.calibration.rate_fit import fit_gyro_rate  # noqa: E402

AX = "xyz"
GRADES = ("navigation", "tactical", "consumer")


def _truth_records(rf, af, gs, Kg, Eg, bg, G, Ka, Ea, ba, K2, Kc):
    """Truth for every coefficient row of the three coefficient tables."""
    truth = {}
    for i, a in enumerate(AX):
        ax = rf.axis(a)
        tb = bg[i] + (G[i] @ ax.bias_reference_force_mps2 if ax.bias_reference_force_mps2 is not None else 0.0)
        truth[("gyro", a, "scale_factor", "rate")] = Kg[i]
        truth[("gyro", a, "scale_factor_pos", "rate")] = Kg[i]
        truth[("gyro", a, "scale_factor_neg", "rate")] = Kg[i]
        truth[("gyro", a, "sf_asymmetry", "rate")] = 0.0
        truth[("gyro", a, "bias", "rate")] = tb
        truth[("gyro", a, "bias", "static")] = bg[i]
        truth[("accel", a, "scale_factor", "accel")] = Ka[i]
        truth[("accel", a, "bias", "accel")] = ba[i]
        truth[("accel", a, "k2", "accel")] = K2[i]
        for j, b in enumerate(AX):
            truth[("gyro", a, f"g_sensitivity_{b}", "static")] = G[i, j]
            truth[("gyro", a, f"g_sensitivity_{b}", "rate")] = G[i, j]
            if j != i:
                truth[("gyro", a, f"misalignment_{a}{b}", "rate")] = Eg[i, j]
                truth[("accel", a, f"misalignment_{a}{b}", "accel")] = Ea[i, j]
                truth[("accel", a, f"cross_coupling_{a}{b}", "accel")] = Kc[i, j]
    return truth


def _score(trial, grade, rf, af, gs, truth):
    recs = []
    for tag, ct in (("rate", rf.coefficient_table()), ("accel", af.coefficient_table()), ("static", gs.coefficient_table())):
        for r in ct.itertuples():
            key = (r.sensor, r.axis, r.coefficient, tag)
            if key not in truth or not r.observable:
                continue
            t = truth[key]
            recs.append(dict(trial=trial, grade=grade, sensor=r.sensor, axis=r.axis, coefficient=r.coefficient,
                             fit=tag, method=r.method, value=r.value, stderr=r.stderr, truth=t,
                             z=(r.value - t) / r.stderr, covered=bool(r.ci95_low <= t <= r.ci95_high),
                             cov_policy=r.cov_policy, n_plateaus=r.n_plateaus))
    return recs


def trial_chain(k: int) -> list[dict]:
    from assets_lib.calibration.segmentation import segment_run
    from assets_lib.sim.simulator import example_device, simulate_run
    from raw_schemas.readers import ingest_frames

    grade = GRADES[k % len(GRADES)]
    dev = example_device(f"MC{k:04d}", grade, seed=10_000 + k)
    runs = {}
    for name, plan in (("rate", "quick_rate"), ("pos", "quick_24_position")):
        sim = simulate_run(dev, plan, f"mc{k}-{name}", seed=k)
        ing = ingest_frames(sim.manifest, sim.imu_raw, sim.table_raw)
        runs[name] = segment_run(ing.manifest, ing.imu, ing.table).plateaus
    rf = fit_gyro_rate(runs["rate"])
    af = fit_accel_multiposition(runs["pos"])
    gs = fit_gyro_static(runs["pos"], rate_fit=rf)
    g, a = dev.gyro, dev.accel
    truth = _truth_records(rf, af, gs, np.asarray(g.scale), np.asarray(g.misalignment_rad), np.asarray(g.bias),
                           np.asarray(dev.g_sensitivity), np.asarray(a.scale), np.asarray(a.misalignment_rad),
                           np.asarray(a.bias), np.asarray(a.k2), np.asarray(a.kc))
    return _score(k, grade, rf, af, gs, truth)


def trial_direct(k: int) -> list[dict]:
    from synth_plateaus import build_table, plan_24_position, random_truth, rate_steps, static_steps

    rng = np.random.default_rng(20_000 + k)
    grade = ("tactical", "mems")[k % 2]
    t = random_truth(rng, grade)
    gsem = np.radians(0.02 / 3600) * 60 if grade == "tactical" else np.radians(0.01)
    rate_tab = build_table(t, rate_steps((1, 5, 10, 20, 50, 100, 200, 400)), rng=rng, gyro_sem=gsem)
    pos_tab = build_table(t, static_steps(plan_24_position()), rng=rng, gyro_sem=gsem / 30,
                          accel_sem=2e-5 if grade == "tactical" else 2e-4)
    rf = fit_gyro_rate(rate_tab)
    af = fit_accel_multiposition(pos_tab)
    gs = fit_gyro_static(pos_tab, rate_fit=rf)
    truth = _truth_records(rf, af, gs, t.Kg, t.Eg, t.bg, t.Gg, t.Ka, t.Ea, t.ba, t.K2a, t.Kca)
    return _score(k, grade, rf, af, gs, truth)


def summarize(df: pd.DataFrame) -> tuple[pd.DataFrame, dict]:
    df = df.copy()
    df["group"] = df["sensor"] + ":" + df["fit"] + ":" + df["coefficient"].str.replace(r"_[xyz]{1,2}$", "", regex=True)
    rows = []
    for (grp, ax), d in df.groupby(["group", "axis"]):
        rows.append(dict(coefficient=grp, axis=ax, n=len(d), coverage=d["covered"].mean(), mean_z=d["z"].mean(),
                         std_z=d["z"].std(ddof=1)))
    tab = pd.DataFrame(rows)
    pooled = float(df["covered"].mean())
    summary = {
        "n_records": int(len(df)),
        "n_trials": int(df["trial"].nunique()),
        "pooled_coverage": pooled,
        "pooled_mean_z": float(df["z"].mean()),
        "pooled_std_z": float(df["z"].std(ddof=1)),
        "min_coverage": float(tab["coverage"].min()),
        "min_coverage_coefficient": tab.loc[tab["coverage"].idxmin(), ["coefficient", "axis"]].tolist(),
        "max_abs_mean_z": float(tab["mean_z"].abs().max()),
        "max_abs_mean_z_coefficient": tab.loc[tab["mean_z"].abs().idxmax(), ["coefficient", "axis"]].tolist(),
        "by_grade": {g: float(d["covered"].mean()) for g, d in df.groupby("grade")},
    }
    summary["pass"] = bool(0.94 <= pooled <= 0.96 and summary["min_coverage"] >= 0.90 and summary["max_abs_mean_z"] < 0.2)
    return tab, summary


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--trials", type=int, default=200)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--mode", choices=("chain", "direct", "auto"), default="auto")
    ap.add_argument("--out", type=Path, default=REPO / "benchmarks" / "results" / "calibration_coverage")
    ap.add_argument("--records", action="store_true", help="also write every estimate to <out>.records.csv")
    args = ap.parse_args(argv)
    mode = args.mode
    if mode == "auto":
        have = (REPO / "assets_lib" / "sim" / "simulator.py").exists() and (REPO / "assets_lib" / "calibration" / "segmentation.py").exists()
        mode = "chain" if have else "direct"
    fn = trial_chain if mode == "chain" else trial_direct
    t0 = time.time()
    recs: list[dict] = []
    if args.workers > 1:
        with ProcessPoolExecutor(args.workers) as ex:
            for r in ex.map(fn, range(args.trials), chunksize=2):
                recs.extend(r)
    else:
        for k in range(args.trials):
            recs.extend(fn(k))
    df = pd.DataFrame(recs)
    tab, summary = summarize(df)
    summary.update(mode=mode, trials=args.trials, seconds=round(time.time() - t0, 1))
    args.out.parent.mkdir(parents=True, exist_ok=True)
    pd.set_option("display.width", 200)
    lines = [
        "# Calibration coverage (Monte Carlo)",
        "",
        f"Mode `{mode}` ({'simulate -> ingest -> segment -> fit' if mode == 'chain' else 'plateau tables from the model'}), "
        f"{summary['n_trials']} trials, {summary['n_records']} coefficient estimates, {summary['seconds']} s. "
        f"Generated by `python benchmarks/mc_calibration_coverage.py --trials {args.trials} --mode {mode}`.",
        "",
        f"- pooled 95 % coverage: **{summary['pooled_coverage']:.4f}** (target 0.94-0.96)",
        f"- lowest coefficient coverage: **{summary['min_coverage']:.3f}** ({' '.join(summary['min_coverage_coefficient'])}; "
        "target >= 0.90)",
        f"- largest |mean z|: **{summary['max_abs_mean_z']:.3f}** ({' '.join(summary['max_abs_mean_z_coefficient'])}; target < 0.2)",
        f"- pooled z: mean {summary['pooled_mean_z']:+.3f}, std {summary['pooled_std_z']:.3f}",
        f"- coverage by grade: " + ", ".join(f"{g} {v:.4f}" for g, v in summary["by_grade"].items()),
        f"- verdict: **{'PASS' if summary['pass'] else 'FAIL'}**",
        "",
        "| coefficient | axis | n | coverage | mean z | std z |",
        "|---|---|---:|---:|---:|---:|",
    ]
    for r in tab.itertuples():
        lines.append(f"| {r.coefficient} | {r.axis} | {r.n} | {r.coverage:.3f} | {r.mean_z:+.3f} | {r.std_z:.3f} |")
    text = "\n".join(lines) + "\n"
    args.out.with_suffix(".md").write_text(text)
    if args.records:
        df.to_csv(args.out.with_suffix(".records.csv"), index=False)
    args.out.with_suffix(".json").write_text(json.dumps({"summary": summary, "table": tab.to_dict(orient="records")},
                                                        indent=1, default=float) + "\n")
    print(text)
    return 0 if summary["pass"] else 1


if __name__ == "__main__":
    raise SystemExit(main())
