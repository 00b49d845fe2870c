"""``imulab run`` end to end, this tree against a baseline tree (the old main), in one process run.

Each tree simulates the same archive spec with its own simulator (the manifest contract moved on since the old
main, so one tree's archive does not ingest in the other) and runs ``python -m imulab.cli run`` on it as a
subprocess with its own PYTHONPATH, on fresh data folders. Runs are interleaved (baseline, this, baseline, this)
so both see the same machine load. Figures, per tree: wall and CPU seconds (user + sys of the subprocess) of a
fresh run (everything computed) and of a rerun on the unchanged archive, whether the rerun launched any Dagster
run, and the ratios baseline / this.

Like with like: the old main has no ``sim_to_real`` stage, so this tree's compared run leaves it out
(``--skip-stage sim_to_real``); the full default run (with ``sim_to_real``) is measured after and reported
apart. ``--same-as TREE`` also runs TREE (e.g. a worktree of this branch's merge base) on this tree's archive
and compares every parquet table both stores hold (same asset, partition and table; versions differ when code
differs), except the calibration records, whose hashes cover stage versions and creation times.

    python benchmarks/bench_run.py --baseline /work/baseline --devices 3 [--same-as /tmp/merge-base-tree]

This tree's ``imulab run`` renders no HTML certificate and no plot (``imulab certificates`` / ``imulab plots`` do,
on demand; the baseline drew both inside its run): ``imulab certificates`` on the fresh store is timed after the
unchanged rerun and reported apart (``this_certificates``), with the CPU ratio of run + certificates.

Per device, as issue 10 item 8 words the target: ``--devices 1,4`` simulates and runs fresh archives of both sizes
(sizes in the order given, the trees interleaved at each size); the marginal cost per device is the slope
(T(4) - T(1)) / 3 of wall and CPU seconds for each tree (the fixed cost per run, imports, instance and planning, is
the intercept T(1) - slope, reported apart), and the per-device ratio is baseline slope / this slope. The
unchanged rerun, the certificates, the full run and ``--same-as`` use the largest size; the total-run ratios are
reported at every size. ``imulab certificates`` is timed at every size too (its own slope and the slope ratio of
run + certificates).

    python benchmarks/bench_run.py --baseline /work/baseline --devices 1,4 --no-full

Before anything is timed, each tree runs once, untimed, on its smallest archive into a scratch folder: a fresh
checkout otherwise byte-compiles its modules and fills numba's on-disk JIT cache inside its first timed run.

Targets (issue 10, item 8): fresh run per device >= 3x faster, unchanged archive < 3 s launching nothing.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
GRADES = ("navigation", "tactical", "consumer")

SIMULATE = r"""
import sys
from pathlib import Path
try:
    from assets_lib.sim.simulator import ArchiveSpec, write_archive
except ImportError:  # the old main's layout
    from assets_lib.simulator import ArchiveSpec, write_archive
devices, static_s = int(sys.argv[2]), float(sys.argv[3])
grades = ("navigation", "tactical", "consumer")
spec = ArchiveSpec(devices=tuple((f"BEN-{i:03d}", grades[i % 3]) for i in range(devices)), power_cycles=1,
                   static_duration_s=static_s)
print(len(write_archive(Path(sys.argv[1]), spec)))
"""


def _env(tree: Path) -> dict:
    return {**os.environ, "PYTHONPATH": str(tree), "PYTHONWARNINGS": "ignore"}


def simulate(tree: Path, landing: Path, devices: int, static_s: float) -> int:
    # cwd = the tree: ``python -c`` puts the working directory first on sys.path
    out = subprocess.run([sys.executable, "-c", SIMULATE, str(landing), str(devices), str(static_s)], env=_env(tree),
                         cwd=tree, capture_output=True, text=True, check=True)
    return int(out.stdout.strip().splitlines()[-1])


def run(tree: Path, landing: Path, data: Path, extra=(), command: str = "run") -> dict:
    """One ``imulab run`` (or ``command``) subprocess: wall and CPU seconds, exit code, output."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    res = subprocess.run([sys.executable, "-m", "imulab.cli", command, "--archive", str(landing), "--data-dir",
                          str(data), *extra], env=_env(tree), cwd=data.parent, capture_output=True, text=True,
                         check=False)
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return {"wall_s": wall, "cpu_s": cpu, "rc": res.returncode, "out": res.stdout + res.stderr}


def launched(output: str) -> int:
    return sum(1 for line in output.splitlines() if line.strip().startswith(("ok ", "FAIL")) and " run " in line)


def compare_stores(a: Path, b: Path, skip=("calibration_record",)) -> dict:
    """Every parquet table of the CURRENT versions both stores hold, compared value by value."""
    import pandas as pd

    def tables(root: Path) -> dict:
        out = {}
        for cur in root.glob("*/*/CURRENT"):
            asset, part = cur.parent.parent.name, cur.parent.name
            if asset in skip:
                continue
            for f in (cur.parent / cur.read_text().strip()).glob("*.parquet"):
                out[(asset, part, f.stem)] = f
        return out

    ta, tb = tables(a), tables(b)
    common = sorted(set(ta) & set(tb))
    differ = []
    for k in common:
        try:
            pd.testing.assert_frame_equal(pd.read_parquet(ta[k]), pd.read_parquet(tb[k]), check_exact=True)
        except AssertionError as e:
            differ.append(f"{'/'.join(k)}: {str(e).splitlines()[0][:200]}")
    return {"tables_compared": len(common), "only_in_this": sorted("/".join(k) for k in set(ta) - set(tb)),
            "only_in_reference": sorted("/".join(k) for k in set(tb) - set(ta)), "tables_differing": differ,
            "skipped_assets": list(skip)}


def slope_intercept(sizes: list[int], values: list[float]) -> tuple[float, float]:
    """Marginal cost per device (slope between the smallest and the largest size) and the fixed cost (intercept)."""
    (n0, v0), (n1, v1) = (sizes[0], values[0]), (sizes[-1], values[-1])
    slope = (v1 - v0) / (n1 - n0)
    return slope, v0 - slope * n0


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--baseline", default="/work/baseline", help="source tree of the peer (the old main)")
    ap.add_argument("--devices", default="3", help="devices per archive; a comma list (e.g. 1,4) for the cost per "
                                                   "device (slope) and per run (intercept)")
    ap.add_argument("--static-duration", type=float, default=1200.0)
    ap.add_argument("--same-as", default=None, help="a reference tree whose parquet outputs this tree must equal")
    ap.add_argument("--no-full", action="store_true", help="skip the full run (with sim_to_real)")
    ap.add_argument("--out", default=str(REPO / "benchmarks" / "results" / "run.json"))
    args = ap.parse_args(argv)
    sizes = sorted({int(x) for x in str(args.devices).split(",")})
    big = sizes[-1]
    root = Path(tempfile.mkdtemp(prefix="bench-run-"))
    base, this = Path(args.baseline), REPO
    like = ["--skip-stage", "sim_to_real"]
    report: dict = {"devices": big, "device_sizes": sizes, "static_duration_s": args.static_duration,
                    "cpus": os.cpu_count(), "load_avg_at_start": os.getloadavg(), "baseline_tree": str(base),
                    "compared_run": "this tree with --skip-stage sim_to_real (the baseline has no such stage)"}

    def folders(label: str, n: int) -> tuple[Path, Path]:
        return root / f"landing_{label}_{n}", root / f"data_{label}_{n}"

    def certificates(n: int) -> dict:
        landing, data = folders("this", n)
        c = run(this, landing, data, like, command="certificates")
        n_html = len(list((data / "store" / "certificate").glob("*/*/*.html")))
        print(f"this     certificates ({n} devices) wall {c['wall_s']:7.1f} s  cpu {c['cpu_s']:6.1f} s  "
              f"exit {c['rc']}  {n_html} certificates", flush=True)
        return {"command": "imulab certificates --skip-stage sim_to_real", "wall_s": round(c["wall_s"], 1),
                "cpu_s": round(c["cpu_s"], 1), "exit": c["rc"], "certificates": n_html}

    try:
        for n in sizes:
            for label, tree in (("baseline", base), ("this", this)):
                landing, data = folders(label, n)
                report.setdefault("captured_runs", {})[f"{label}_{n}"] = simulate(tree, landing, n,
                                                                                   args.static_duration)
                data.mkdir()
        # warm-up, not timed: one run per tree on its smallest archive into a scratch folder, so that no timed run
        # byte-compiles modules or fills numba's on-disk JIT cache (the Allan kernels; several seconds of CPU in
        # a fresh checkout, which would land in the smallest size and shrink the per-device slope)
        for label, tree in (("baseline", base), ("this", this)):
            scratch = root / f"warmup_{label}"
            scratch.mkdir()
            run(tree, folders(label, sizes[0])[0], scratch, like if label == "this" else ())
            shutil.rmtree(scratch, ignore_errors=True)
        report["captured_runs_baseline"] = report["captured_runs"][f"baseline_{big}"]
        report["captured_runs_this"] = report["captured_runs"][f"this_{big}"]
        res: dict = {}
        for n, phase in [(n, "fresh") for n in sizes] + [(big, "unchanged")]:
            for label, tree in (("baseline", base), ("this", this)):
                landing, data = folders(label, n)
                r = run(tree, landing, data, like if label == "this" else ())
                res[(label, phase, n)] = r
                ingested = len(list((data / "store" / "ingested_run").glob("*/CURRENT")))
                if ingested != report["captured_runs"][f"{label}_{n}"]:  # the old main exits 0 on ingest errors
                    raise SystemExit(f"{label}: {ingested} of {report['captured_runs'][f'{label}_{n}']} runs "
                                     "ingested:\n" + r["out"][-3000:])
                print(f"{label:8s} {phase:9s} {n} devices  wall {r['wall_s']:7.1f} s  cpu {r['cpu_s']:6.1f} s  "
                      f"exit {r['rc']}  runs launched {launched(r['out'])}", flush=True)
        for label in ("baseline", "this"):
            f, u = res[(label, "fresh", big)], res[(label, "unchanged", big)]
            report[label] = {"fresh_s": round(f["wall_s"], 1), "fresh_cpu_s": round(f["cpu_s"], 1),
                             "fresh_s_per_device": round(f["wall_s"] / big, 1),
                             "fresh_cpu_s_per_device": round(f["cpu_s"] / big, 1),
                             "unchanged_s": round(u["wall_s"], 2), "unchanged_cpu_s": round(u["cpu_s"], 2),
                             "unchanged_runs_launched": launched(u["out"]), "exit_codes": [f["rc"], u["rc"]]}
        b, t = report["baseline"], report["this"]
        report["fresh_speedup_wall"] = round(b["fresh_s"] / t["fresh_s"], 2)
        report["fresh_speedup_cpu"] = round(b["fresh_cpu_s"] / t["fresh_cpu_s"], 2)
        report["unchanged_speedup_wall"] = round(b["unchanged_s"] / t["unchanged_s"], 2)
        report["fresh_by_size"] = {}
        for n in sizes:
            fb, ft = res[("baseline", "fresh", n)], res[("this", "fresh", n)]
            report["fresh_by_size"][str(n)] = {
                **{f"{label}_{k}_s": round(r[f"{k}_s"], 1) for label, r in (("baseline", fb), ("this", ft))
                   for k in ("wall", "cpu")},
                **{f"speedup_{k}": round(fb[f"{k}_s"] / ft[f"{k}_s"], 2) for k in ("wall", "cpu")}}
        # the HTML certificates this tree renders on demand (the baseline rendered them inside its run)
        certs = {n: certificates(n) for n in sizes}
        report["this_certificates"] = certs[big]
        report["fresh_plus_certificates_speedup_cpu"] = round(b["fresh_cpu_s"]
                                                              / (t["fresh_cpu_s"] + certs[big]["cpu_s"]), 2)
        if len(sizes) > 1:
            report["this_certificates_by_size"] = {str(n): certs[n] for n in sizes}
            per: dict = {"sizes": [sizes[0], big], "definition": "slope = (T(largest) - T(smallest)) / (devices "
                         "difference), intercept = T(smallest) - slope * smallest; ratio = baseline / this"}
            for k in ("wall", "cpu"):
                sb, ib = slope_intercept(sizes, [res[("baseline", "fresh", n)][f"{k}_s"] for n in sizes])
                st, it = slope_intercept(sizes, [res[("this", "fresh", n)][f"{k}_s"] for n in sizes])
                sc, ic = slope_intercept(sizes, [certs[n][f"{k}_s"] for n in sizes])
                per[k] = {"baseline_s_per_device": round(sb, 2), "this_s_per_device": round(st, 2),
                          "speedup_per_device": round(sb / st, 2) if st > 0 else None,
                          "baseline_fixed_s_per_run": round(ib, 2), "this_fixed_s_per_run": round(it, 2),
                          "this_certificates_s_per_device": round(sc, 2),
                          "this_certificates_fixed_s": round(ic, 2),
                          "speedup_per_device_run_plus_certificates":
                              round(sb / (st + sc), 2) if st + sc > 0 else None}
            report["per_device"] = per
            for k in ("wall", "cpu"):
                p = per[k]
                ratio = "n/a (slope not positive: load noise)" if p["speedup_per_device"] is None else \
                    f"{p['speedup_per_device']}x"
                print(f"per device ({k}): baseline {p['baseline_s_per_device']} s, this {p['this_s_per_device']} s "
                      f"-> {ratio} (with certificates "
                      f"{p['speedup_per_device_run_plus_certificates']}x); fixed per run: baseline "
                      f"{p['baseline_fixed_s_per_run']} s, this {p['this_fixed_s_per_run']} s", flush=True)
        if not args.no_full:
            landing, _ = folders("this", big)
            (root / "data_full").mkdir()
            f = run(this, landing, root / "data_full")
            u = run(this, landing, root / "data_full")
            report["this_full_run"] = {"fresh_s": round(f["wall_s"], 1), "fresh_cpu_s": round(f["cpu_s"], 1),
                                       "unchanged_s": round(u["wall_s"], 2), "unchanged_cpu_s": round(u["cpu_s"], 2),
                                       "unchanged_runs_launched": launched(u["out"]), "exit_codes": [f["rc"], u["rc"]]}
            print("this, full run (with sim_to_real):", report["this_full_run"], flush=True)
        if args.same_as:
            landing, data = folders("this", big)
            (root / "data_ref").mkdir()
            r = run(Path(args.same_as), landing, root / "data_ref", like)
            report["same_outputs"] = {"reference_tree": args.same_as, "reference_exit": r["rc"],
                                      **compare_stores(data / "store", root / "data_ref" / "store")}
            print("same outputs:", report["same_outputs"], flush=True)
        report["load_avg_at_end"] = os.getloadavg()
        print(f"fresh run ({big} devices): {report['fresh_speedup_wall']}x the baseline in wall time, "
              f"{report['fresh_speedup_cpu']}x in CPU time; unchanged archive: {t['unchanged_s']} s wall, "
              f"{t['unchanged_cpu_s']} s CPU, {t['unchanged_runs_launched']} Dagster runs launched (baseline "
              f"{b['unchanged_s']} s, {b['unchanged_runs_launched']}); load {report['load_avg_at_start']} -> "
              f"{report['load_avg_at_end']}")
    finally:
        shutil.rmtree(root, ignore_errors=True)
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(report, indent=1) + "\n")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
