"""Which simulated noise term widens the rate fit's gyro-bias z (issue 15 diagnosis; benchmarks/README.md, session 11).

Each device of ``--grade`` runs ``--plan`` (the coverage benchmark's rate plans and dwell scales) with its gyro noise
edited per variant, is ingested, segmented and fitted as the ``gyro_rate_fit`` stage fits it
(``fit_gyro_rate(plateaus, noise_prior=...)``), and its bias (and scale factor) rows are scored as
``mc_calibration_coverage.score`` scores them, twice: with the run's own 1/f level B (no prior) and with the true B
as an exact two-sided prior. Variants: ``full`` (the grade's N, B, K), ``noK`` (rate random walk K = 0),
``G0`` (full noise, g-sensitivity zeroed).

    python benchmarks/rate_bias_noise_terms.py --grade consumer --plan quick_rate --devices 300 --variants full noK
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np
import pandas as pd

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import mc_calibration_coverage as mc  # noqa: E402

VARIANTS = ("full", "noK", "G0")


def device(k: int, grade: str, variant: str):
    """Device k of the diagnosis with its gyro noise / g-sensitivity edited per ``variant``."""
    from assets_lib.sim.simulator import example_device

    dev = example_device(f"RB-{k}", grade, seed=77)
    gn = dev.gyro.noise[0]
    if variant == "noK":
        gn = dataclasses.replace(gn, k=0.0)
    G = ((0.0,) * 3,) * 3 if variant == "G0" else dev.g_sensitivity
    return dataclasses.replace(dev, gyro=dataclasses.replace(dev.gyro, noise=(gn,) * 3), g_sensitivity=G)


def one(args) -> list[dict]:
    from assets_lib.calibration.noise_prior import ChannelNoisePrior, DeviceNoisePrior
    from assets_lib.calibration.rate_fit import fit_gyro_rate
    from assets_lib.calibration.segmentation import segment_run
    from assets_lib.sim.simulator import DEFAULT_EFFECTS, simulate_run
    from raw_schemas.readers import ingest_frames

    k, variant, plan, grade = args
    dev = device(k, grade, variant)
    sim = simulate_run(dev, mc._plan(plan, mc.RATE_PLANS[plan]), f"rb{k}", seed=1000 + k, effects=DEFAULT_EFFECTS)
    ing = ingest_frames(sim.manifest, sim.imu_raw, sim.table_raw)
    p = segment_run(ing.manifest, ing.imu, ing.table).plateaus
    b = dev.gyro.noise[0].b
    exact = DeviceNoisePrior(tuple(ChannelNoisePrior(f"gyro_{a}_radps", b, 0.999 * b, 1.001 * b, False, "truth", 1e5)
                                   for a in mc.AX))
    out = []
    for name, prior in (("run_B", None), ("true_B", exact)):
        rf = fit_gyro_rate(p, noise_prior=prior)
        truth = mc.device_truth(rf, dev)
        for r in mc.score({"trial": k, "grade": grade}, rf, None, None, truth):
            if r["fit"] == "rate" and r["coefficient"] in ("bias", "scale_factor"):
                out.append(dict(trial=k, variant=variant, prior=name, coefficient=r["coefficient"], axis=r["axis"],
                                z=r["z"], covered=r["covered"]))
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--grade", default="consumer", choices=mc.GRADES)
    ap.add_argument("--plan", default="quick_rate", choices=tuple(mc.RATE_PLANS))
    ap.add_argument("--devices", type=int, default=300)
    ap.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=VARIANTS)
    ap.add_argument("--workers", type=int, default=2)
    args = ap.parse_args(argv)
    jobs = [(k, v, args.plan, args.grade) for v in args.variants for k in range(args.devices)]
    with ProcessPoolExecutor(args.workers) as ex:
        rows = [r for rr in ex.map(one, jobs) for r in rr]
    d = pd.DataFrame(rows)
    tab = d.groupby(["variant", "prior", "coefficient"]).agg(
        n=("z", "size"), coverage=("covered", "mean"), mean_z=("z", "mean"), sd_z=("z", "std")).round(3)
    print(f"{args.grade}, {args.plan}, {args.devices} devices (3 axes each)")
    print(tab.to_string())
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
