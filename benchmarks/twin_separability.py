"""Which effect families the test plans can and cannot separate: numbers from the simulator (docs/twin.md).

1. Injected into simulated runs and pushed through segmentation and the fits (same seed with and without the
   effect, so the noise cancels in the differences): common latency vs the table clock offset, mean table-rate
   error and timebase error vs the gyro and accelerometer scale factors.
2. Alias R^2 between family signatures on the plans' inputs (after projecting out the base model's columns):
   w^2 vs |w| over the rate plans' plateau rates, centripetal g-sensitivity vs w^2, warm-up and bias ramp vs
   temperature under the default self-heating profile and under a chamber cycle.

    python benchmarks/twin_separability.py [--json out.json]
"""

from __future__ import annotations

import argparse
import json

import numpy as np

from assets_lib.calibration.multiposition import fit_accel_multiposition
from assets_lib.calibration.rate_fit import fit_gyro_rate
from assets_lib.calibration.segmentation import segment_run
from assets_lib.sim.effects import EFFECTS, sensor_chain
from assets_lib.sim.plans import build_plan
from assets_lib.sim.simulator import (
    example_device,
    housing_temperature_degc,
    simulate_run,
)
from raw_schemas.readers import ingest_frames


def _seg(run):
    ing = ingest_frames(run.manifest, run.imu_raw, run.table_raw)
    return segment_run(ing.manifest, ing.imu, ing.table)


def _coefs(fit, sensor: str, name: str) -> tuple[list, list]:
    """(values, stderrs) per axis x, y, z from a fit's tidy coefficient table."""
    c = fit.coefficient_table()
    rows = [c[(c.sensor == sensor) & (c.axis == a) & (c.coefficient == name)].iloc[0] for a in "xyz"]
    return [float(r.value) for r in rows], [float(r.stderr) for r in rows]


def _diff(fa, fb, sensor: str, name: str) -> tuple[list, list]:
    (va, _), (vb, sb) = _coefs(fa, sensor, name), _coefs(fb, sensor, name)
    return [b - a for a, b in zip(va, vb)], sb


def _r2(x: np.ndarray, y: np.ndarray, base: np.ndarray) -> float:
    """Alias R^2: share of y's variance (after projecting out ``base``) that x reproduces (after the same)."""
    q, _ = np.linalg.qr(base)
    rx, ry = x - q @ (q.T @ x), y - q @ (q.T @ y)
    if rx @ rx == 0 or ry @ ry == 0:
        return float("nan")
    return float((rx @ ry) ** 2 / ((rx @ rx) * (ry @ ry)))


def injected(dev, plan_name, kind, extra, seed=4, scale=0.5):
    plan = build_plan(plan_name, duration_scale=scale)
    a = simulate_run(dev, plan, "sep", test_kind=kind, seed=seed, table_clock_offset_s=0.8)
    b = simulate_run(dev, plan, "sep", test_kind=kind, seed=seed, table_clock_offset_s=0.8, effects=sensor_chain(extra))
    return _seg(a), _seg(b)


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json", default=None)
    args = ap.parse_args(argv)
    dev = example_device("NAV-001", "navigation", 2026)
    out: dict = {}

    # -- common latency == table clock offset ------------------------------------------------------------
    d = 5e-3
    sa, sb = injected(dev, "quick_rate", "rate", [EFFECTS["latency"](gyro_s=d, accel_s=d)])
    fa, fb = fit_gyro_rate(sa.plateaus), fit_gyro_rate(sb.plateaus)
    out["common_latency"] = {
        "injected_s": d,
        "clock_offset_change_s": sb.alignment.offset_s - sa.alignment.offset_s,
        "clock_offset_stderr_s": sb.alignment.offset_stderr_s,
        "gyro_scale_factor_change": _diff(fa, fb, "gyro", "scale_factor")[0],
        "gyro_scale_factor_stderr": _diff(fa, fb, "gyro", "scale_factor")[1],
    }

    # -- mean table-rate error == gyro scale factor; timebase error == gyro and accel scale factor -------
    eps = 3e-4
    for fam, kw in (("table_rate_error", {"mean_error": eps}), ("timebase_error", {"clock_rate_error": eps})):
        sa, sb = injected(dev, "quick_rate", "rate", [EFFECTS[fam](**kw)])
        fa, fb = fit_gyro_rate(sa.plateaus), fit_gyro_rate(sb.plateaus)
        pa, pb = injected(dev, "quick_24_position", "multiposition", [EFFECTS[fam](**kw)])
        aa, ab = fit_accel_multiposition(pa.plateaus), fit_accel_multiposition(pb.plateaus)
        out[fam] = {
            "injected": eps,
            "gyro_scale_factor_change": _diff(fa, fb, "gyro", "scale_factor")[0],
            "gyro_scale_factor_stderr": _diff(fa, fb, "gyro", "scale_factor")[1],
            "accel_scale_factor_change": _diff(aa, ab, "accel", "scale_factor")[0],
            "accel_scale_factor_stderr": _diff(aa, ab, "accel", "scale_factor")[1],
            "clock_drift_ppm": sb.alignment.clock_drift_ppm,
            "clock_drift_stderr_ppm": sb.alignment.clock_drift_stderr_ppm,
        }

    # -- signature aliases on the plans' plateau inputs ------------------------------------------------
    for name in ("quick_rate", "seed003_rate_sequence", "seed000_rate_full_revolution"):
        w = np.unique([np.radians(s.table_rate_dps) for s in build_plan(name).steps])
        base = np.column_stack([np.ones_like(w), w])
        out[f"alias_r2_{name}"] = {
            "w2_vs_abs_w": _r2(w**2, np.abs(w), base),
            "w3_vs_w": _r2(w**3, w, np.ones((w.size, 1))),
            "centripetal_g_sensitivity_vs_w2": _r2(-(w**2) * 0.05, w**2, base),  # G (-w^2 r) on plateaus
            "plateau_rates_dps": np.degrees(w).round(3).tolist(),
        }

    # -- thermal / time families under self-heating and under a chamber cycle ---------------------------
    t = np.arange(0, 1200.0, 1.0)
    heat = housing_temperature_degc(dev, t) - 25.0
    chamber = 8.0 * np.sin(2 * np.pi * t / 600.0)
    one = np.ones((t.size, 1))
    out["thermal_aliases_1200s_static"] = {
        "self_heating": {f"warmup_tau_{tau:g}s_vs_temperature": _r2(np.exp(-t / tau), heat, one) for tau in (300, 900, 1800)}
        | {"bias_ramp_vs_temperature": _r2(t, heat, one), "temperature_sq_vs_temperature": _r2(heat**2, heat, one)},
        "chamber_cycle_600s": {f"warmup_tau_{tau:g}s_vs_temperature": _r2(np.exp(-t / tau), chamber, one)
                               for tau in (300, 900, 1800)} | {"bias_ramp_vs_temperature": _r2(t, chamber, one)},
    }
    print(json.dumps(out, indent=1, default=float))
    if args.json:
        with open(args.json, "w") as f:
            json.dump(out, f, indent=1, default=float)
    return out


if __name__ == "__main__":
    main()
