"""Monte Carlo of the IEEE 952 noise fit (assets_lib.noise.identification) against the classic slope reads.

Simulated gyro rate noise: white (ARW N) + flicker (bias instability B) + rate random walk (K), 3 h per trial,
overlapping ADEV on 100 log-spaced taus, fit by iterated non-negative GLS. Reports per parameter: bias of the
point estimate sqrt(theta_hat) (all trials, including those reported only as upper bounds), its standard error,
the spread, the coverage of the 95 % interval as reported (two-sided interval, or [0, upper bound]), the number
of upper-bound reports, and the slope method's bias on the same trials.

    python benchmarks/mc_noise_id.py                      # 200 trials at 100 Hz, 3 h
    python benchmarks/mc_noise_id.py --trials 50 --rate-hz 400
Writes benchmarks/results/noise_id_mc.json (or --out).
"""

from __future__ import annotations

import argparse
import json
import math
import platform
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from assets_lib.noise import allan as al  # noqa: E402
from assets_lib.noise import identification as ni  # noqa: E402
from assets_lib.sim.noise import AllanParams, allan_noise  # noqa: E402

D2R = math.pi / 180.0
#: a tactical MEMS gyro: ARW 0.07 deg/sqrt(h), BI 2 deg/h, RRW 14 deg/h/sqrt(h) (all three visible in 3 h)
TRUTH = AllanParams(n=0.07 * D2R / 60.0, b=2.0 * D2R / 3600.0, k=14.0 * D2R / 3600.0 / 60.0)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--trials", type=int, default=200)
    ap.add_argument("--rate-hz", type=float, default=100.0)
    ap.add_argument("--hours", type=float, default=3.0)
    ap.add_argument("--seed", type=int, default=20240611)
    ap.add_argument("--taus", default="dense")
    ap.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "results" / "noise_id_mc.json")
    args = ap.parse_args(argv)

    n = int(round(args.hours * 3600 * args.rate_hz))
    rng = np.random.default_rng(args.seed)
    names = ("N", "B", "K")
    truth = {"N": TRUTH.n, "B": TRUTH.b, "K": TRUTH.k}
    est = {k: [] for k in names}
    slope = {k: [] for k in names}
    covered = {k: 0 for k in names}
    upper = {k: 0 for k in names}
    width = {k: [] for k in names}
    t0 = time.perf_counter()
    for t in range(args.trials):
        y = allan_noise(n, args.rate_hz, TRUTH, rng)
        res = al.oadev(y, args.rate_hz, args.taus, channel="gyro_x")
        fit = ni.fit_noise(res, ci_level=0.95)
        for k in names:
            j = fit.terms.index(k)
            est[k].append(math.sqrt(fit.theta[j]) / truth[k])
            p = fit.parameter(k)
            covered[k] += p.ci_lo <= truth[k] <= p.ci_hi
            upper[k] += p.is_upper_bound
            if not p.is_upper_bound:
                width[k].append((p.ci_hi - p.ci_lo) / truth[k])
            try:
                slope[k].append(fit.parameter(k, "slope").value / truth[k])
            except KeyError:
                slope[k].append(float("nan"))
        if (t + 1) % 20 == 0:
            print(f"{t + 1}/{args.trials} trials, {time.perf_counter() - t0:.0f} s", flush=True)
    elapsed = time.perf_counter() - t0
    summary = {}
    for k in names:
        e = np.array(est[k])
        s = np.array(slope[k])
        summary[k] = {
            "truth_si": truth[k],
            "bias": float(e.mean() - 1.0),
            "bias_se": float(e.std(ddof=1) / math.sqrt(len(e))),
            "rel_sd": float(e.std(ddof=1)),
            "coverage_95": covered[k] / args.trials,
            "upper_bound_reports": upper[k],
            "median_rel_ci_width": float(np.median(width[k])) if width[k] else None,
            "slope_bias": float(np.nanmean(s) - 1.0),
            "slope_rel_sd": float(np.nanstd(s, ddof=1)),
            "slope_reads_available": int(np.isfinite(s).sum()),
        }
    doc = {
        "what": "IEEE 952 noise fit Monte Carlo (white + flicker + RRW gyro rate noise)",
        "trials": args.trials,
        "rate_hz": args.rate_hz,
        "hours": args.hours,
        "n_samples": n,
        "taus": args.taus,
        "seed": args.seed,
        "truth_lab": {"N_deg_per_sqrt_h": 0.07, "B_deg_per_h": 2.0, "K_deg_per_h_per_sqrt_h": 14.0},
        "results": summary,
        "goals": {"bias_abs_lt": 0.05, "coverage_95_ge": 0.90},
        "goals_met": {k: bool(abs(summary[k]["bias"]) < 0.05 and summary[k]["coverage_95"] >= 0.90)
                      for k in ("N", "K")},
        "seconds": elapsed,
        "backend": "numba" if al.HAVE_NUMBA else "numpy",
        "python": platform.python_version(),
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(doc, indent=1))
    for k in names:
        r = summary[k]
        print(f"{k}: bias {100 * r['bias']:+.2f} % (se {100 * r['bias_se']:.2f} %), sd {100 * r['rel_sd']:.1f} %, "
              f"95% coverage {100 * r['coverage_95']:.1f} %, upper bounds {r['upper_bound_reports']}, "
              f"slope-method bias {100 * r['slope_bias']:+.1f} %")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
