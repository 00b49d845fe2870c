"""``imulab run`` end to end, this tree against a baseline tree (the old main), in one process run.

Both trees run the same simulated archive as subprocesses (``python -m imulab.cli run``) with their own
PYTHONPATH, on fresh data folders: a fresh run (everything computed) and a rerun on the unchanged archive. Figures:
wall seconds per device (fresh), the ratio baseline / this, and the rerun's wall time and whether it launched any
Dagster run. Targets (issue 10, item 8): fresh run per device >= 3x faster, unchanged archive < 3 s launching
nothing.

    python benchmarks/bench_run.py --baseline /work/baseline --devices 3
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def simulate(landing: Path, devices: int, static_s: float) -> int:
    sys.path.insert(0, str(REPO))
    from assets_lib.sim.simulator import ArchiveSpec, write_archive

    grades = ("navigation", "tactical", "consumer")
    spec = ArchiveSpec(devices=tuple((f"BEN-{i:03d}", grades[i % 3]) for i in range(devices)), power_cycles=1,
                       static_duration_s=static_s)
    return len(write_archive(landing, spec))


def run(tree: Path, landing: Path, data: Path) -> tuple[float, int, str]:
    env = {**os.environ, "PYTHONPATH": str(tree), "PYTHONWARNINGS": "ignore"}
    t0 = time.perf_counter()
    res = subprocess.run([sys.executable, "-m", "imulab.cli", "run", "--archive", str(landing), "--data-dir", str(data)],
                         env=env, cwd=data.parent, capture_output=True, text=True, check=False)
    return time.perf_counter() - t0, res.returncode, res.stdout + res.stderr


def launched(output: str) -> int:
    return sum(1 for line in output.splitlines() if line.strip().startswith(("ok ", "FAIL")) and " run " in line)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--baseline", default="/work/baseline", help="source tree of the peer (the old main)")
    ap.add_argument("--devices", type=int, default=3)
    ap.add_argument("--static-duration", type=float, default=1200.0)
    ap.add_argument("--out", default=str(REPO / "benchmarks" / "results" / "run.json"))
    args = ap.parse_args(argv)
    root = Path(tempfile.mkdtemp(prefix="bench-run-"))
    report: dict = {"devices": args.devices, "cpus": os.cpu_count(), "load_avg_at_start": os.getloadavg()}
    try:
        report["captured_runs"] = simulate(root / "landing", args.devices, args.static_duration)
        for label, tree in (("baseline", Path(args.baseline)), ("this", REPO)):
            data = root / f"data_{label}"
            data.mkdir()
            fresh, rc1, _ = run(tree, root / "landing", data)
            again, rc2, out2 = run(tree, root / "landing", data)
            report[label] = {"fresh_s": round(fresh, 1), "fresh_s_per_device": round(fresh / args.devices, 1),
                             "unchanged_s": round(again, 2), "unchanged_runs_launched": launched(out2),
                             "exit_codes": [rc1, rc2]}
            print(label, report[label], flush=True)
        b, t = report["baseline"], report["this"]
        report["fresh_speedup"] = round(b["fresh_s"] / t["fresh_s"], 2)
        report["unchanged_speedup"] = round(b["unchanged_s"] / t["unchanged_s"], 2)
        print(f"fresh run: {report['fresh_speedup']}x the baseline; unchanged archive: {t['unchanged_s']} s, "
              f"{t['unchanged_runs_launched']} Dagster runs launched (baseline {b['unchanged_s']} s, "
              f"{b['unchanged_runs_launched']})")
    finally:
        shutil.rmtree(root, ignore_errors=True)
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(report, indent=1) + "\n")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
