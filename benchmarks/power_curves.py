"""Power curves of the sim-to-real diagnosis: detection probability against effect RMS over noise, per family
(issue 12, "a power curve per family"; docs/simreal.md sec. 1 reports the prototype's detection limits the same way).

    python benchmarks/power_curves.py --families temperature_bias,scale_factor_asymmetry,lever_arm \
        --scales 0.03,0.08,0.2,0.5 --replicates 4 --out /tmp/pc          # the small run (results/power_curves.*)
    python benchmarks/power_curves.py --families all --scales 0.01,0.02,0.05,0.1,0.2,0.5 --repeats 5 ...  # full

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
log(RMS/noise) between the grid points that bracket it.

Outputs (``--results``): ``power_curves.json`` (every point, wall times), ``power_curves.md`` (table),
``power_curves.png`` (one curve per family).
"""

from __future__ import annotations

import argparse
import hashlib
import json
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


def generate(root: Path, families, scales, repeats: int, seed: int) -> list[dict]:
    """``scales``: one list for every family, or {family: list}."""
    base = clear_cases()
    out = []
    wh.Hidden = _RecordingHidden  # the generator builds its effect by this name
    for fam in families:
        grid = scales[fam] if isinstance(scales, dict) else scales
        for s in grid:
            si = round(1000 * s)  # device id from the scale itself: grids can be extended and resumed
            for rep in range(repeats):
                c0 = base[fam]
                c = {k: v for k, v in c0.items() if k != "device_id"}
                c["params"] = _scaled_params(fam, c0["params"], s)
                c["magnitude"] = c0["magnitude"] * s
                c["category"] = "power"
                c["scale"] = s
                c["device_id"] = f"PC-{fam[:14]}-s{si:04d}-{rep}"
                truth_p = root / "truth" / f"{c['device_id']}.json"
                if truth_p.exists():
                    out.append(json.loads(truth_p.read_text()))
                    continue
                _CURRENT["device"] = c["device_id"]
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
                t.update({"scale": s, "effect_rms_si": float(rms[ch]), "effect_channel": ch,
                          "noise_sd_si": noise, "rms_over_noise": float(rms[ch] / noise)})
                truth_p.write_text(json.dumps(t, indent=1, default=float))
                out.append(t)
    return out


def diagnose(root: Path, truths, replicates: int, seed: int, workers) -> dict:
    from assets_lib.simreal.diagnose import diagnose_device
    from assets_lib.simreal.report import _clean, write_atomic

    walls = {}
    for t in truths:
        dev = t["device_id"]
        p = root / "reports" / f"{dev}.json"
        if p.exists():
            continue
        t0 = time.time()
        d = diagnose_device(root / "landing", dev, replicates=replicates, seed=seed, workers=workers,
                            aug_replicates=max(4, replicates // 2))
        walls[dev] = time.time() - t0
        write_atomic(p, json.dumps(_clean({**d.report, "wall_s": walls[dev]}), indent=1) + "\n")
        print(f"{dev}: {d.report['verdict']} {[e['family'] for e in d.report['effects']]} "
              f"x={t['rms_over_noise']:.3g} {walls[dev]:.0f} s", flush=True)
    return walls


def _level50(x: np.ndarray, p: np.ndarray) -> float | None:
    """log-linear interpolation of the 50 % crossing (first bracket from below)."""
    o = np.argsort(x)
    x, p = x[o], p[o]
    for i in range(len(x) - 1):
        if p[i] < 0.5 <= p[i + 1]:
            lx = np.log(x[i]) + (0.5 - p[i]) / (p[i + 1] - p[i]) * (np.log(x[i + 1]) - np.log(x[i]))
            return float(np.exp(lx))
    return None  # not bracketed by the grid: reported as "< smallest x" or "> largest x" (``_fmt_level``)


def _fmt_level(v, pts, key) -> str:
    if v is not None:
        return f"{v:.3g}"
    x = [r["rms_over_noise"] for r in pts]
    if pts and pts[int(np.argmin(x))][key] >= 0.5:
        return f"< {min(x):.3g} (every grid point >= 50 %)"
    return f"> {max(x):.3g} (no grid point reaches 50 %)"


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
                       "channel": wh.CHANNEL_NAMES[t["effect_channel"]] if hasattr(wh, "CHANNEL_NAMES") else
                       ("gyro_x", "gyro_y", "gyro_z", "accel_x", "accel_y", "accel_z")[t["effect_channel"]],
                       "verdict": r["verdict"], "detected": r["verdict"] != "no_gap",
                       "attributed": bool(fams and fams[0] == t["family"]), "top1": fams[0] if fams else None,
                       "gap_z": r["gap"]["z"], "wall_s": r.get("wall_s")})
    curves = {}
    for fam in sorted({q["family"] for q in points}):
        pts = [q for q in points if q["family"] == fam]
        by = {}
        for q in pts:
            by.setdefault(q["scale"], []).append(q)
        rows = []
        for s in sorted(by):
            g = by[s]
            rows.append({"scale": s, "rms_over_noise": float(np.median([q["rms_over_noise"] for q in g])),
                         "n": len(g), "p_detect": float(np.mean([q["detected"] for q in g])),
                         "p_attribute": float(np.mean([q["attributed"] for q in g]))})
        x = np.array([r["rms_over_noise"] for r in rows])
        curves[fam] = {"points": rows,
                       "rms_over_noise_at_50pct_detection": _level50(x, np.array([r["p_detect"] for r in rows])),
                       "rms_over_noise_at_50pct_attribution": _level50(x, np.array([r["p_attribute"] for r in rows]))}
    return {"points": points, "curves": curves}


def write_results(res: dict, out: Path, meta: dict) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out.mkdir(parents=True, exist_ok=True)
    (out / "power_curves.json").write_text(json.dumps({**meta, **res}, indent=1, default=float) + "\n")
    lines = ["# Power curves of the sim-to-real diagnosis (benchmarks/power_curves.py)", "",
             f"Command: `{meta['command']}`  ",
             (f"Wall time {meta['wall_s']:.0f} s for {len(res['points'])} devices ({meta['replicates']} replicates "
              f"each, {meta['workers']} workers; mean {meta['mean_device_s']:.0f} s per device), {meta['date']}."), "",
             ("x = RMS of what the sealed effect adds to its largest channel over the runs carrying it, over the "
              "white-noise sd of one sample of that channel. Detected: verdict not `no_gap`; attributed: first "
              "accepted effect is the true family."), "",
             "| family | scale | channel | effect RMS / noise | n | P(detect) | P(attribute) | verdicts |",
             "|---|---|---|---|---|---|---|---|"]
    for fam, c in res["curves"].items():
        for r in c["points"]:
            pts = [q for q in res["points"] if q["family"] == fam and q["scale"] == r["scale"]]
            v = ", ".join(f"{q['verdict']}" + (f" ({q['top1']})" if q["top1"] else "") for q in pts)
            lines.append(f"| {fam} | {r['scale']:g} | {pts[0]['channel']} | {r['rms_over_noise']:.3g} | {r['n']} | "
                         f"{r['p_detect']:.2f} | {r['p_attribute']:.2f} | {v} |")
    lines += ["", "| family | RMS/noise at 50 % detection | at 50 % attribution |", "|---|---|---|"]
    for fam, c in res["curves"].items():
        pts = c["points"]
        lines.append(f"| {fam} | {_fmt_level(c['rms_over_noise_at_50pct_detection'], pts, 'p_detect')} | "
                     f"{_fmt_level(c['rms_over_noise_at_50pct_attribution'], pts, 'p_attribute')} |")
    (out / "power_curves.md").write_text("\n".join(lines) + "\n")
    fig, ax = plt.subplots(figsize=(6.5, 4))
    for i, (fam, c) in enumerate(res["curves"].items()):
        x = [r["rms_over_noise"] for r in c["points"]]
        ax.plot(x, [r["p_detect"] for r in c["points"]], "o-", color=f"C{i}", label=f"{fam} detected")
        ax.plot(x, [r["p_attribute"] for r in c["points"]], "x--", color=f"C{i}", label=f"{fam} attributed")
    ax.set_xscale("log")
    ax.set_ylim(-0.05, 1.05)
    ax.set_xlabel("effect RMS / white-noise sd per sample")
    ax.set_ylabel("probability")
    ax.set_title(f"Power curves (R = {meta['replicates']}, {meta['repeats']} device(s) per point)", fontsize=9)
    ax.legend(fontsize=6)
    fig.tight_layout()
    fig.savefig(out / "power_curves.png", dpi=90)
    plt.close(fig)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--families", default="temperature_bias,scale_factor_asymmetry,lever_arm",
                    help="comma list of the generator's library families, or 'all'")
    ap.add_argument("--scales", default="0.03,0.08,0.2,0.5", help="multiples of the generator's clear magnitude")
    ap.add_argument("--family-scales", action="append", metavar="FAMILY=S1,S2,...",
                    help="a family's own grid (e.g. lever_arm=0.001,0.003,0.01,0.03: its signal is strong)")
    ap.add_argument("--repeats", type=int, default=1, help="devices (seeds) per grid point")
    ap.add_argument("--replicates", type=int, default=4)
    ap.add_argument("--seed", type=int, default=11)
    ap.add_argument("--workers", type=int, default=None)
    ap.add_argument("--out", default="/tmp/power_curves", help="work folder (archives, truth, reports)")
    ap.add_argument("--results", default=str(Path(__file__).resolve().parent / "results"))
    a = ap.parse_args(argv)
    fams = list(clear_cases()) if a.families == "all" else [f.strip() for f in a.families.split(",") if f.strip()]
    unknown = [f for f in fams if f not in clear_cases()]
    if unknown:
        ap.error(f"--families: unknown {unknown}; the generator has {sorted(clear_cases())}")
    scales = {f: [float(s) for s in a.scales.split(",")] for f in fams}
    for spec in a.family_scales or []:
        f, _, grid = spec.partition("=")
        if f not in scales:
            ap.error(f"--family-scales {spec}: {f} is not among --families")
        scales[f] = [float(x) for x in grid.split(",")]
    root = Path(a.out)
    t0 = time.time()
    had = {p.name for p in (root / "truth").glob("PC-*.json")} if (root / "truth").is_dir() else set()
    truths = generate(root, fams, scales, a.repeats, a.seed)
    gen_file = root / "generate_s.json"
    gen = json.loads(gen_file.read_text()) if gen_file.exists() else {}
    new_ = [t["device_id"] for t in truths if f"{t['device_id']}.json" not in had]
    if new_:
        gen.update({d: (time.time() - t0) / len(new_) for d in new_})
        gen_file.write_text(json.dumps(gen))
    t_gen = float(sum(gen.get(t["device_id"], 0.0) for t in truths))
    print(f"generated {len(truths)} devices in {t_gen:.0f} s", flush=True)
    diagnose(root, truths, a.replicates, 0, a.workers)
    res = score(root, truths)
    walls = [q["wall_s"] for q in res["points"] if q["wall_s"]]
    from datetime import datetime, timezone

    meta = {"command": "python benchmarks/power_curves.py " + " ".join(argv if argv is not None else sys.argv[1:]),
            "replicates": a.replicates, "repeats": a.repeats, "workers": a.workers or 2, "families": fams,
            "scales": scales, "generate_s": t_gen, "wall_s": t_gen + float(sum(walls)),  # resumable: summed per device
            "mean_device_s": float(np.mean(walls)) if walls else float("nan"),
            "date": datetime.now(timezone.utc).strftime("%Y-%m-%d"),
            "code": hashlib.sha256(Path(__file__).read_bytes()).hexdigest()[:12]}
    write_results(res, Path(a.results), meta)
    print(json.dumps(res["curves"], indent=1))
    print(f"wall time {meta['wall_s']:.0f} s")


if __name__ == "__main__":
    main()
