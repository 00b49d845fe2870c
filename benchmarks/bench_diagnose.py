"""Speed of the sim-to-real diagnosis: one default-archive device at R replicates, cost per stage.

    python benchmarks/bench_diagnose.py --device TAC-002 --replicates 100 --workers 2

Target (issue 12): R = 100 within 5 minutes on 2 cores. Prints the stage timings of the report
(load + twin fit, base replicates, views + selection, augmented or noise-re-fit replicates), the wall time per
replicate, the CPU seconds of the worker processes per replicate (comparable across machine loads) and the
1-minute load average before and after (the machine is shared: a figure taken under load says so).
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def main(argv=None):
    ap = argparse.ArgumentParser()
    ap.add_argument("--device", default="TAC-002")
    ap.add_argument("--replicates", type=int, default=100)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--archive", default=None, help="existing landing folder (default: simulate the default archive)")
    a = ap.parse_args(argv)
    from assets_lib.sim.simulator import write_archive
    from assets_lib.simreal.diagnose import diagnose_device

    with tempfile.TemporaryDirectory() as tmp:
        landing = Path(a.archive) if a.archive else Path(tmp) / "landing"
        if not a.archive:
            write_archive(landing)
        load0 = os.getloadavg()[0]
        t0 = time.time()
        c0 = resource.getrusage(resource.RUSAGE_CHILDREN).ru_utime + resource.getrusage(resource.RUSAGE_SELF).ru_utime
        d = diagnose_device(landing, a.device, replicates=a.replicates, seed=0, workers=a.workers)
        wall = time.time() - t0
        cpu = resource.getrusage(resource.RUSAGE_CHILDREN).ru_utime + resource.getrusage(resource.RUSAGE_SELF).ru_utime - c0
    tm = d.report["timings_s"]
    print(json.dumps({"device": a.device, "replicates": a.replicates, "workers": a.workers, "verdict": d.report["verdict"],
                      "wall_s": round(wall, 1), "per_replicate_s": round(tm["replicates_base"] / a.replicates, 2),
                      "cpu_s": round(cpu, 1), "load_average_1min": [round(load0, 2), round(os.getloadavg()[0], 2)],
                      "stages_s": {k: round(v, 1) for k, v in tm.items()}}, indent=1))


if __name__ == "__main__":
    main()
