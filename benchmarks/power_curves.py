"""Power curves of the sim-to-real diagnosis: detection probability against effect RMS over noise, per family
(issue 12, "a power curve per family"; docs/simreal.md sec. 1 reports the prototype's detection limits the same way).

    timeout 3600 python benchmarks/power_curves.py --families all --repeats 2 --replicates 5 --out /tmp/pc
    python benchmarks/power_curves.py --families all --repeats 2 --out /tmp/pc --score-only   # re-score

Every family on its own grid (``DEFAULT_GRIDS``: about 0.5x-4x the level where its clear-case held-out gain meets
the gate), in repeat-major order (central grid points first), results rewritten after every device (a run stopped by ``timeout`` keeps what it
measured; the work folder is resumable: device ids carry family, scale and repeat).

Each point is one sealed device written by the withheld-effect benchmark's own generator
(``benchmarks/withheld_effects.py``: ``cases`` for the family's clear-magnitude parameters, ``write_case`` for the
archive; its effect forms differ from the diagnoser's library), with the effect's parameters multiplied by
``scale`` (the compressive nonlinearity's full scale divided by sqrt(scale), as the generator's near cases do).
The diagnoser sees only the landing folder (``diagnose_device``, R replicates). Scored from the report alone:

* detected: verdict is not ``no_gap``;
* attributed: the first accepted effect is the true family.

x axis: **effect RMS over noise** = RMS of what the sealed effect adds to the raw stream of its largest channel,
over the runs that carry it (recorded inside the generator's effect chain, before quantization), divided by the
white-noise standard deviation of one sample of that channel (N sqrt(fs), the device truth's angle/velocity random
walk), the convention of the prototype in docs/simreal.md sec. 1. The 50 % detection level is interpolated on
log(RMS/noise) between the grid points that bracket it, and so is the 90 % level.

Outputs (``--results``): ``power_curves.json`` (every point, wall times), ``power_curves.md`` (table),
``power_curves.png`` (one curve per family).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

import withheld_effects as wh

from assets_lib.sim.simulator import example_device

#: effect RMS per (device id, run seed) -> (sum of squares per channel (6,), samples): filled inside the generator
_RECORD: dict = {}
_CURRENT: dict = {"device": None}


class _RecordingHidden(wh.Hidden):
    """The generator's sealed effect, unchanged, plus a record of what it adds to the six channels."""

    def apply(self, ctx, gyro, accel):
        g2, a2 = super().apply(ctx, gyro, accel)
        d = np.column_stack([g2 - gyro, a2 - accel])
        if self.kind == "timebase_error":  # acts on the time stamps: its rate signature is eps x omega
            d = np.column_stack([self.params["eps"] * ctx.inputs.omega_b_radps, np.zeros_like(accel)])
        key = (_CURRENT["device"], self.run_seed)
        _RECORD[key] = (np.sum(d * d, axis=0), d.shape[0])
        return g2, a2


def _scaled_params(fam: str, p: dict, s: float) -> dict:
    """The generator's rule for its near-limit cases, at any scale."""
    q = {k: (np.asarray(v) * s).tolist() if k in ("r", "eps_level") else
         (v * s if k in ("k", "a", "eps", "a2") else v) for k, v in p.items()}
    if fam == "scale_factor_nonlinearity":
        q["fs"] = p["fs"] / np.sqrt(s)
    return q


def clear_cases() -> dict:
    return {c["family"]: c for c in wh.cases("quick") if c["category"] == "family_clear"}


def _noise_sd(grade: str, device_id: str, seed: int, channel: int, fs: float = 100.0) -> float:
    dev = example_device(device_id, grade, seed)
    tri = dev.gyro if channel < 3 else dev.accel
    return float(tri.noise[channel % 3].n * np.sqrt(fs))


def device_id(fam: str, s: float, rep: int) -> str:
    """Device id from the family, the scale itself and the repeat: grids can be extended and runs resumed."""
    return f"PC-{fam[:14]}-s{s:.3g}-{rep}".replace("+", "")


def generate_one(root: Path, fam: str, s: float, rep: int, seed: int) -> dict:
    """One sealed device of ``fam`` at ``scale`` = s (the truth file is reused when it exists)."""
    wh.Hidden = _RecordingHidden  # the generator builds its effect by this name
    c0 = clear_cases()[fam]
    c = {k: v for k, v in c0.items() if k != "device_id"}
    c["params"] = _scaled_params(fam, c0["params"], s)
    c["magnitude"] = c0["magnitude"] * s
    c["category"] = "power"
    c["scale"] = s
    c["device_id"] = device_id(fam, s, rep)
    truth_p = root / "truth" / f"{c['device_id']}.json"
    if truth_p.exists():
        return json.loads(truth_p.read_text())
    _CURRENT["device"] = c["device_id"]
    t0 = time.time()
    t = wh.write_case(root, c, seed + 1000 * rep)
    ss = np.zeros(6)
    n = 0
    for (dev, _), (sq, m) in _RECORD.items():
        if dev == c["device_id"] and np.any(sq > 0):
            ss += sq
            n += m
    rms = np.sqrt(ss / max(n, 1))
    ch = int(np.argmax(rms))
    noise = _noise_sd(c["grade"], c["device_id"], seed + 1000 * rep, ch)
    t.update({"scale": s, "effect_rms_si": float(rms[ch]), "effect_channel": ch, "noise_sd_si": noise,
              "rms_over_noise": float(rms[ch] / noise), "generate_s": time.time() - t0})
    truth_p.write_text(json.dumps(t, indent=1, default=float))
    return t


def diagnose_one(root: Path, t: dict, replicates: int, aug_replicates: int, seed: int, workers) -> None:
    """The diagnoser on the landing folder alone; the report (plus its wall time) to ``reports/``."""
    from assets_lib.simreal.diagnose import diagnose_device
    from assets_lib.simreal.report import _clean, write_atomic

    dev = t["device_id"]
    p = root / "reports" / f"{dev}.json"
    if p.exists():
        return
    t0 = time.time()
    d = diagnose_device(root / "landing", dev, replicates=replicates, seed=seed, workers=workers,
                        aug_replicates=aug_replicates)
    wall = time.time() - t0
    write_atomic(p, json.dumps(_clean({**d.report, "wall_s": wall}), indent=1) + "\n")
    print(f"{dev}: {d.report['verdict']} {[e['family'] for e in d.report['effects']]} "
          f"x={t['rms_over_noise']:.3g} {wall:.0f} s", flush=True)


def _level(x: np.ndarray, p: np.ndarray, q: float) -> float | None:
    """Log-linear interpolation of the level where the detection fraction first reaches ``q`` from below."""
    o = np.argsort(x)
    x, p = x[o], p[o]
    for i in range(len(x) - 1):
        if p[i] < q <= p[i + 1]:
            lx = np.log(x[i]) + (q - p[i]) / (p[i + 1] - p[i]) * (np.log(x[i + 1]) - np.log(x[i]))
            return float(np.exp(lx))
    return None  # not bracketed by the grid: reported as "< smallest x" or "> largest x" (``_fmt_level``)


def _fmt_level(v, rows, key, q) -> str:
    if v is not None:
        return f"{v:.3g}"
    if not rows:
        return "n/a"
    x = [r["rms_over_noise"] for r in rows]
    if rows[int(np.argmin(x))][key] >= q:
        return f"<= {min(x):.3g}"
    return f"> {max(x):.3g}"


def score(root: Path, truths) -> dict:
    points = []
    for t in truths:
        p = root / "reports" / f"{t['device_id']}.json"
        if not p.exists():
            continue
        r = json.loads(p.read_text())
        fams = [e["family"] for e in r["effects"]]
        points.append({"device_id": t["device_id"], "family": t["family"], "scale": t["scale"],
                       "magnitude": t["magnitude"], "rms_over_noise": t["rms_over_noise"],
                       "effect_rms_si": t["effect_rms_si"], "noise_sd_si": t["noise_sd_si"],
                       "channel": CHANNELS[t["effect_channel"]],
                       "verdict": r["verdict"], "detected": r["verdict"] != "no_gap",
                       "attributed": bool(fams and fams[0] == t["family"]), "top1": fams[0] if fams else None,
                       "effects": fams, "gap_z": r["gap"]["z"], "wall_s": r.get("wall_s"),
                       "timings_s": r.get("timings_s")})
    curves = {}
    for fam in dict.fromkeys(q["family"] for q in points):
        pts = [q for q in points if q["family"] == fam]
        by = {}
        for q in pts:
            by.setdefault(q["scale"], []).append(q)
        rows = []
        for s in sorted(by):
            g = by[s]
            rows.append({"scale": s, "rms_over_noise": float(np.median([q["rms_over_noise"] for q in g])),
                         "n": len(g), "n_detect": int(sum(q["detected"] for q in g)),
                         "n_attribute": int(sum(q["attributed"] for q in g)),
                         "p_detect": float(np.mean([q["detected"] for q in g])),
                         "p_attribute": float(np.mean([q["attributed"] for q in g]))})
        x = np.array([r["rms_over_noise"] for r in rows])
        c = {"points": rows}
        for q in (0.5, 0.9):
            for key, name in (("p_detect", "detection"), ("p_attribute", "attribution")):
                v = _level(x, np.array([r[key] for r in rows]), q)
                c[f"rms_over_noise_at_{round(100 * q)}pct_{name}"] = v
                c[f"rms_over_noise_at_{round(100 * q)}pct_{name}_text"] = _fmt_level(v, rows, key, q)
        curves[fam] = c
    return {"points": points, "curves": curves}


CHANNELS = ("gyro_x", "gyro_y", "gyro_z", "accel_x", "accel_y", "accel_z")


def write_results(res: dict, out: Path, meta: dict) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out.mkdir(parents=True, exist_ok=True)
    (out / "power_curves.json").write_text(json.dumps({**meta, **res}, indent=1, default=float) + "\n")
    walls = [q["wall_s"] for q in res["points"] if q["wall_s"]]
    lines = ["# Power curves of the sim-to-real diagnosis (benchmarks/power_curves.py)", "",
             f"Command: `{meta['command']}`  ",
             (f"{len(res['points'])} devices, R = {meta['replicates']} base and {meta['aug_replicates']} augmented "
              f"replicates, {meta['workers']} workers; diagnosis {np.sum(walls):.0f} s in all "
              f"(per device median {np.median(walls) if walls else float('nan'):.0f} s, "
              f"range {min(walls, default=float('nan')):.0f}-{max(walls, default=float('nan')):.0f} s), "
              f"generation {meta['generate_s']:.0f} s; {meta['date']}, commit {meta['commit']}."), "",
             ("x = RMS of what the sealed effect adds to its largest channel over the runs carrying it, over the "
              "white-noise sd of one sample of that channel. Detected: verdict not `no_gap`; attributed: first "
              "accepted effect is the true family. Levels: log-linear interpolation between the grid points "
              "that bracket the fraction (`<= x`: every point from the smallest up detects; `> x`: never reached)."),
             "", ("| family | channel | RMS/noise at 50 % detection | at 90 % detection | at 50 % attribution | "
                  "points: RMS/noise (detected/attributed/n) |"), "|---|---|---|---|---|---|"]
    for fam, c in res["curves"].items():
        ch = next(q["channel"] for q in res["points"] if q["family"] == fam)
        pts = "; ".join(f"{r['rms_over_noise']:.3g} ({r['n_detect']}/{r['n_attribute']}/{r['n']})"
                        for r in c["points"])
        lines.append(f"| {fam} | {ch} | {c['rms_over_noise_at_50pct_detection_text']} | "
                     f"{c['rms_over_noise_at_90pct_detection_text']} | "
                     f"{c['rms_over_noise_at_50pct_attribution_text']} | {pts} |")
    lines += ["", "| family | scale | channel | effect RMS / noise | n | P(detect) | P(attribute) | verdicts |",
              "|---|---|---|---|---|---|---|---|"]
    for fam, c in res["curves"].items():
        for r in c["points"]:
            pts = [q for q in res["points"] if q["family"] == fam and q["scale"] == r["scale"]]
            v = ", ".join(f"{q['verdict']}" + (f" ({'+'.join(q['effects'])})" if q["effects"] else "") for q in pts)
            lines.append(f"| {fam} | {r['scale']:g} | {pts[0]['channel']} | {r['rms_over_noise']:.3g} | {r['n']} | "
                         f"{r['p_detect']:.2f} | {r['p_attribute']:.2f} | {v} |")
    (out / "power_curves.md").write_text("\n".join(lines) + "\n")
    fams = list(res["curves"])
    fig, axs = plt.subplots(1, 2, figsize=(11, 4.2), sharey=True)
    for i, fam in enumerate(fams):
        c = res["curves"][fam]
        x = [r["rms_over_noise"] for r in c["points"]]
        col, mk = f"C{i % 10}", "osD^v<>ph*X"[i % 11]
        axs[0].plot(x, [r["p_detect"] for r in c["points"]], marker=mk, color=col, ls="-", label=fam)
        axs[1].plot(x, [r["p_attribute"] for r in c["points"]], marker=mk, color=col, ls="--", label=fam)
    for ax, what in zip(axs, ("detected (verdict not no_gap)", "attributed (top-1 = truth)")):
        ax.set_xscale("log")
        ax.set_ylim(-0.05, 1.05)
        ax.set_xlabel("effect RMS / white-noise sd per sample")
        ax.set_title(f"{what}; R = {meta['replicates']}", fontsize=9)
        ax.grid(alpha=0.3)
    axs[0].set_ylabel("fraction of devices")
    axs[1].legend(fontsize=6, loc="lower right")
    fig.tight_layout()
    fig.savefig(out / "power_curves.png", dpi=90)
    plt.close(fig)


#: scale grids per family, multiples of the generator's clear tactical magnitude, set around the level where the
#: family's best held-out gain at the clear magnitude (quick tier run 5: temperature 762, temperature scale factor
#: 639, warm-up 694, bias ramp ~2-10, g^2 104 against a null-calibrated gate 42, nonlinearity 7.8e4, asymmetry
#: 4.6e4, lever arm 2.9e7, table ripple 1.5e5 against 47, wobble 5.6e3 against 26, timebase 8.3e7), scaled by the
#: magnitude squared, meets the 2 ln 1000 (or null-calibrated) gate: about 0.5x, 1x, 2x and 4x that level.
DEFAULT_GRIDS = {
    "temperature_bias": (0.06, 0.12, 0.2, 0.4),
    "temperature_scale_factor": (0.08, 0.15, 0.3, 0.6),
    "warmup_bias": (0.06, 0.12, 0.2, 0.4),
    "bias_ramp": (1.0, 2.5, 5.0, 10.0),
    "g_sensitivity": (0.25, 0.5, 0.8, 1.5),
    "scale_factor_nonlinearity": (0.005, 0.01, 0.02, 0.05),
    "scale_factor_asymmetry": (0.002, 0.005, 0.01, 0.03),
    "lever_arm": (0.0007, 0.0015, 0.003, 0.006),
    "table_rate_error": (0.007, 0.015, 0.03, 0.06),
    "table_wobble": (0.03, 0.06, 0.12, 0.25),
    "timebase_error": (0.0003, 0.0006, 0.0012, 0.003),  # not detected at 3e-4 / 6e-4 (session 5): moved up
}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--families", default="all", help="comma list of the generator's library families, or 'all'")
    ap.add_argument("--scales", default=None,
                    help="multiples of the generator's clear magnitude for every family (default: DEFAULT_GRIDS)")
    ap.add_argument("--family-scales", action="append", metavar="FAMILY=S1,S2,...", help="a family's own grid")
    ap.add_argument("--repeats", type=int, default=1, help="devices (seeds) per grid point")
    ap.add_argument("--replicates", type=int, default=5)
    ap.add_argument("--aug-replicates", type=int, default=3,
                    help="augmented-twin replicates (>= 3, the views' minimum; they set explained vs partly "
                         "explained and the intervals, neither of which a power curve reads)")
    ap.add_argument("--seed", type=int, default=11)
    ap.add_argument("--workers", type=int, default=None)
    ap.add_argument("--out", default="/tmp/power_curves", help="work folder (archives, truth, reports)")
    ap.add_argument("--results", default=str(Path(__file__).resolve().parent / "results"))
    ap.add_argument("--score-only", action="store_true", help="score the reports in --out, diagnose nothing")
    a = ap.parse_args(argv)
    fams = list(clear_cases()) if a.families == "all" else [f.strip() for f in a.families.split(",") if f.strip()]
    unknown = [f for f in fams if f not in clear_cases()]
    if unknown:
        ap.error(f"--families: unknown {unknown}; the generator has {sorted(clear_cases())}")
    scales = {f: ([float(s) for s in a.scales.split(",")] if a.scales else list(DEFAULT_GRIDS[f])) for f in fams}
    for spec in a.family_scales or []:
        f, _, grid = spec.partition("=")
        if f not in scales:
            ap.error(f"--family-scales {spec}: {f} is not among --families")
        scales[f] = [float(x) for x in grid.split(",")]
    root = Path(a.out)
    (root / "truth").mkdir(parents=True, exist_ok=True)
    import subprocess
    from datetime import datetime, timezone

    commit = subprocess.run(["git", "-C", str(Path(__file__).resolve().parent), "rev-parse", "--short", "HEAD"],
                            capture_output=True, text=True, check=False).stdout.strip() or os.environ.get("IMULAB_COMMIT", "")
    meta = {"command": "python benchmarks/power_curves.py " + " ".join(argv if argv is not None else sys.argv[1:]),
            "replicates": a.replicates, "aug_replicates": a.aug_replicates, "repeats": a.repeats,
            "workers": a.workers or 2, "families": fams, "scales": scales,
            "date": datetime.now(timezone.utc).strftime("%Y-%m-%d"), "commit": commit,
            "code": hashlib.sha256(Path(__file__).read_bytes()).hexdigest()[:12]}
    # repeat-major, then grid points from the middle of each family's grid outwards, then families: a run cut short
    # (``timeout``) still has the central points of every family
    n_max = max(len(v) for v in scales.values())
    order = [(rep, f, scales[f][i]) for rep in range(a.repeats)
             for i in sorted(range(n_max), key=lambda i: abs(i - (n_max - 1) / 2)) for f in fams if i < len(scales[f])]
    truths = []

    def finish():
        res = score(root, truths)
        meta["generate_s"] = float(sum(t.get("generate_s", 0.0) for t in truths))
        write_results(res, Path(a.results), meta)
        return res

    for rep, f, s in order:
        if a.score_only:
            p = root / "truth" / f"{device_id(f, s, rep)}.json"
            if p.exists():
                truths.append(json.loads(p.read_text()))
            continue
        t = generate_one(root, f, s, rep, a.seed)
        truths.append(t)
        diagnose_one(root, t, a.replicates, a.aug_replicates, 0, a.workers)
        finish()  # results after every device: a run stopped by ``timeout`` keeps what it measured
    res = finish()
    print(json.dumps({f: {k: v for k, v in c.items() if k.endswith("_text")} for f, c in res["curves"].items()},
                     indent=1))


if __name__ == "__main__":
    main()
