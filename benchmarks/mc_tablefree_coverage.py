"""Monte Carlo coverage of the table-free fits' uncertainties (simulated hand-placed sessions, >= 200 trials).

Each trial draws a device (misalignments ~ N(0, 0.005), scales 1 + N(0, 0.01), biases) and a hand session
(``assets_lib.sim.hand_poses.simulate_hand_session``: 30 poses of 3-8 s, random rotations of 60-150 deg, white
noise), then runs static-pose detection, the Tedaldi accelerometer fit and the gyro integration fit, and scores
every coefficient: coverage of the 95 % interval the fit reports (``Coefficient.interval()``: value -/+ k95 SE
with k95 the Student-t quantile at the fit's residual degrees of freedom, 21 for the accelerometer, 49 for the
gyro) and z = (estimate - truth) / SE. Acceptance (issue 14): coverage 93-97 % pooled and per coefficient.

    python benchmarks/mc_tablefree_coverage.py --trials 200 [--seed0 N]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from assets_lib.calibration.gyro_integration import fit_gyro_integration  # noqa: E402
from assets_lib.calibration.poses import detect_static_poses  # noqa: E402
from assets_lib.calibration.tablefree import fit_accel_poses, pose_means  # noqa: E402
from assets_lib.sim.hand_poses import simulate_hand_session  # noqa: E402


def _truth(rng):
    ta = np.eye(3)
    ta[0, 1], ta[0, 2], ta[1, 2] = 0.005 * rng.standard_normal(3)
    tg = np.eye(3) + 0.005 * rng.standard_normal((3, 3)) * (1 - np.eye(3))
    return {"accel_T": ta, "accel_k": 1 + 0.01 * rng.standard_normal(3), "accel_b": 0.1 * rng.standard_normal(3),
            "gyro_T": tg, "gyro_k": 1 + 0.01 * rng.standard_normal(3), "gyro_b": 0.01 * rng.standard_normal(3)}


def trial(seed: int) -> list[tuple[str, float, float, float, bool]]:
    rng = np.random.default_rng(seed)
    tr = _truth(rng)
    s = simulate_hand_session(rng, truth=tr)
    ref = slice(0, int(s.initial_static_s * 100))
    p = detect_static_poses(s.t_s, s.accel, k=6, reference=ref)
    m = pose_means(s.t_s, s.accel, p.starts, p.ends)
    af = fit_accel_poses(m, 9.81, n_samples=np.asarray(p.ends) - np.asarray(p.starts))
    gf = fit_gyro_integration(s.t_s, s.gyro, p.starts, p.ends, af.apply(m), s.gyro[ref].mean(0), scale_start=np.ones(3),
                              bias_cov=np.cov(s.gyro[ref].T) / s.gyro[ref].shape[0])
    T, G = tr["accel_T"], tr["gyro_T"]
    ta = {"t01": T[0, 1], "t02": T[0, 2], "t12": T[1, 2], **{f"k_{a}": tr["accel_k"][i] for i, a in enumerate("xyz")},
          **{f"b_{a}": tr["accel_b"][i] for i, a in enumerate("xyz")}}
    tg = {"t01": G[0, 1], "t02": G[0, 2], "t10": G[1, 0], "t12": G[1, 2], "t20": G[2, 0], "t21": G[2, 1],
          **{f"k_{a}": tr["gyro_k"][i] for i, a in enumerate("xyz")}}
    out = []
    for prefix, fit, truth in (("accel", af, ta), ("gyro", gf, tg)):
        for n, c in fit.coefficients.items():
            lo, hi = c.interval()
            out.append((f"{prefix}_{n}", c.value, c.stderr, truth[n], bool(lo <= truth[n] <= hi)))
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--trials", type=int, default=200)
    ap.add_argument("--seed0", type=int, default=1000)
    ap.add_argument("--json", type=Path, default=None)
    a = ap.parse_args(argv)
    t0 = time.time()
    rows = [r for i in range(a.trials) for r in trial(a.seed0 + i)]
    names = sorted({r[0] for r in rows})
    z = {n: np.array([(v - t) / s for k, v, s, t, _ in rows if k == n]) for n in names}
    cov = {n: float(np.mean([h for k, *_, h in rows if k == n])) for n in names}
    cov_norm = {n: float(np.mean(np.abs(z[n]) <= 1.959963984540054)) for n in names}
    pooled = float(np.mean([r[-1] for r in rows]))
    for n in names:
        flag = "" if 0.93 <= cov[n] <= 0.97 else "  OUTSIDE 93-97 %"
        print(f"{n:12s} coverage {100 * cov[n]:5.1f} % (normal 1.96: {100 * cov_norm[n]:5.1f} %)  "
              f"mean z {z[n].mean():+.2f}  sd z {z[n].std():.2f}{flag}")
    inside = sum(0.93 <= c <= 0.97 for c in cov.values())
    ok = 0.93 <= pooled <= 0.97 and inside == len(names)
    print(f"pooled coverage {100 * pooled:.1f} % over {a.trials} trials x {len(names)} coefficients, seed0 {a.seed0} "
          f"({time.time() - t0:.0f} s); per coefficient {inside}/{len(names)} within 93-97 % "
          f"(binomial sd at 95 %: {100 * np.sqrt(0.95 * 0.05 / a.trials):.1f} points); "
          f"acceptance: {'PASS' if ok else 'FAIL'}")
    if a.json:
        a.json.write_text(json.dumps({"trials": a.trials, "seed0": a.seed0, "pooled": pooled, "per_coefficient": cov,
                                      "per_coefficient_normal_quantile": cov_norm}, indent=1))
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
