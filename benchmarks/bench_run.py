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


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--baseline", default="/work/baseline", help="source tree of the peer (the old main)")
    ap.add_argument("--devices", type=int, default=3)
    ap.add_argument("--static-duration", type=float, default=1200.0)
    ap.add_argument("--same-as", default=None, help="a reference tree whose parquet outputs this tree must equal")
    ap.add_argument("--no-full", action="store_true", help="skip the full run (with sim_to_real)")
    ap.add_argument("--out", default=str(REPO / "benchmarks" / "results" / "run.json"))
    args = ap.parse_args(argv)
    root = Path(tempfile.mkdtemp(prefix="bench-run-"))
    base, this = Path(args.baseline), REPO
    like = ["--skip-stage", "sim_to_real"]
    report: dict = {"devices": args.devices, "static_duration_s": args.static_duration, "cpus": os.cpu_count(),
                    "load_avg_at_start": os.getloadavg(), "baseline_tree": str(base),
                    "compared_run": "this tree with --skip-stage sim_to_real (the baseline has no such stage)"}
    try:
        for label, tree in (("baseline", base), ("this", this)):
            report[f"captured_runs_{label}"] = simulate(tree, root / f"landing_{label}", args.devices,
                                                        args.static_duration)
            (root / f"data_{label}").mkdir()
        res: dict = {}
        for phase in ("fresh", "unchanged"):
            for label, tree in (("baseline", base), ("this", this)):
                r = run(tree, root / f"landing_{label}", root / f"data_{label}", like if label == "this" else ())
                res[(label, phase)] = r
                ingested = len(list((root / f"data_{label}" / "store" / "ingested_run").glob("*/CURRENT")))
                if ingested != report[f"captured_runs_{label}"]:  # the old main exits 0 on ingest errors
                    raise SystemExit(f"{label}: {ingested} of {report[f'captured_runs_{label}']} runs ingested:\n"
                                     + r["out"][-3000:])
                print(f"{label:8s} {phase:9s} wall {r['wall_s']:7.1f} s  cpu {r['cpu_s']:6.1f} s  exit {r['rc']}  "
                      f"runs launched {launched(r['out'])}", flush=True)
        for label in ("baseline", "this"):
            f, u = res[(label, "fresh")], res[(label, "unchanged")]
            report[label] = {"fresh_s": round(f["wall_s"], 1), "fresh_cpu_s": round(f["cpu_s"], 1),
                             "fresh_s_per_device": round(f["wall_s"] / args.devices, 1),
                             "fresh_cpu_s_per_device": round(f["cpu_s"] / args.devices, 1),
                             "unchanged_s": round(u["wall_s"], 2), "unchanged_cpu_s": round(u["cpu_s"], 2),
                             "unchanged_runs_launched": launched(u["out"]), "exit_codes": [f["rc"], u["rc"]]}
        b, t = report["baseline"], report["this"]
        report["fresh_speedup_wall"] = round(b["fresh_s"] / t["fresh_s"], 2)
        report["fresh_speedup_cpu"] = round(b["fresh_cpu_s"] / t["fresh_cpu_s"], 2)
        report["unchanged_speedup_wall"] = round(b["unchanged_s"] / t["unchanged_s"], 2)
        # the HTML certificates this tree renders on demand (the baseline rendered them inside its run)
        c = run(this, root / "landing_this", root / "data_this", like, command="certificates")
        n_html = len(list((root / "data_this" / "store" / "certificate").glob("*/*/*.html")))
        report["this_certificates"] = {"command": "imulab certificates --skip-stage sim_to_real", "wall_s":
                                       round(c["wall_s"], 1), "cpu_s": round(c["cpu_s"], 1), "exit": c["rc"],
                                       "certificates": n_html}
        report["fresh_plus_certificates_speedup_cpu"] = round(b["fresh_cpu_s"] / (t["fresh_cpu_s"] + c["cpu_s"]), 2)
        print(f"this     certificates wall {c['wall_s']:7.1f} s  cpu {c['cpu_s']:6.1f} s  exit {c['rc']}  "
              f"{n_html} certificates", flush=True)
        if not args.no_full:
            (root / "data_full").mkdir()
            f = run(this, root / "landing_this", root / "data_full")
            u = run(this, root / "landing_this", root / "data_full")
            report["this_full_run"] = {"fresh_s": round(f["wall_s"], 1), "fresh_cpu_s": round(f["cpu_s"], 1),
                                       "unchanged_s": round(u["wall_s"], 2), "unchanged_cpu_s": round(u["cpu_s"], 2),
                                       "unchanged_runs_launched": launched(u["out"]), "exit_codes": [f["rc"], u["rc"]]}
            print("this, full run (with sim_to_real):", report["this_full_run"], flush=True)
        if args.same_as:
            (root / "data_ref").mkdir()
            r = run(Path(args.same_as), root / "landing_this", root / "data_ref", like)
            report["same_outputs"] = {"reference_tree": args.same_as, "reference_exit": r["rc"],
                                      **compare_stores(root / "data_this" / "store", root / "data_ref" / "store")}
            print("same outputs:", report["same_outputs"], flush=True)
        report["load_avg_at_end"] = os.getloadavg()
        print(f"fresh run: {report['fresh_speedup_wall']}x the baseline in wall time, {report['fresh_speedup_cpu']}x "
              f"in CPU time; unchanged archive: {t['unchanged_s']} s wall, {t['unchanged_cpu_s']} s CPU, "
              f"{t['unchanged_runs_launched']} Dagster runs launched (baseline {b['unchanged_s']} s, "
              f"{b['unchanged_runs_launched']})")
    finally:
        shutil.rmtree(root, ignore_errors=True)
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(report, indent=1) + "\n")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
