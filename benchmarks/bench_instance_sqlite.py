"""Dagster event writes on an instance opened by ``pipelines.instance.open_instance`` (SQLite tuned: synchronous=NORMAL,
an idle reader per database) against a plain SQLite instance (``DagsterInstance.from_config``), in one process run.

Each side runs the same event-heavy job (two partitioned assets over a 40-partition range, single-run backfill: a
materialization and a planned event per partition, like ``calibrate_captures``) ``--runs`` times on a fresh
instance, in a subprocess; sides are interleaved (plain, tuned, plain, tuned) so both see the same machine load.
Figures: wall and CPU seconds (user + sys) per side, events per run, and the ratios plain / tuned.

    python benchmarks/bench_instance_sqlite.py [--runs 3] [--repeat 2]
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]

JOB = r"""
import sys
import dagster as dg
from pipelines.instance import open_instance, release_sqlite
mode, home, runs = sys.argv[1], sys.argv[2], int(sys.argv[3])
if mode == "plain":
    import os
    os.makedirs(home, exist_ok=True)
    with open(os.path.join(home, "dagster.yaml"), "w") as f:
        f.write("telemetry:\n  enabled: false\n")
    inst = dg.DagsterInstance.from_config(home)
else:
    inst = open_instance(home)
parts = dg.StaticPartitionsDefinition([f"p{i:02d}" for i in range(40)])
@dg.asset(partitions_def=parts, backfill_policy=dg.BackfillPolicy.single_run())
def a(context):
    return dg.MaterializeResult(metadata={"n": len(context.partition_keys)})
@dg.asset(partitions_def=parts, backfill_policy=dg.BackfillPolicy.single_run(), deps=[a])
def b(context):
    return dg.MaterializeResult(metadata={"n": len(context.partition_keys)})
defs = dg.Definitions(assets=[a, b], jobs=[dg.define_asset_job("j", selection=[a, b])])
job = defs.resolve_job_def("j")
quiet = {"loggers": {"console": {"config": {"log_level": "WARNING"}}}}
for _ in range(runs):
    res = job.execute_in_process(instance=inst, run_config=quiet, tags={
        "dagster/asset_partition_range_start": "p00", "dagster/asset_partition_range_end": "p39"})
    assert res.success
print(len(inst.all_logs(res.run_id)))
release_sqlite()
"""


def one(mode: str, home: Path, runs: int) -> dict:
    env = {**os.environ, "PYTHONPATH": str(REPO), "PYTHONWARNINGS": "ignore"}
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    out = subprocess.run([sys.executable, "-c", JOB, mode, str(home), str(runs)], env=env, cwd=REPO,
                         capture_output=True, text=True, check=True)
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return {"wall_s": wall, "cpu_s": cpu, "events_per_run": int(out.stdout.strip().splitlines()[-1])}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--runs", type=int, default=3, help="Dagster runs per side and repeat")
    ap.add_argument("--repeat", type=int, default=2)
    ap.add_argument("--out", default=str(REPO / "benchmarks" / "results" / "instance_sqlite.json"))
    args = ap.parse_args(argv)
    tot = {"plain": {"wall_s": 0.0, "cpu_s": 0.0}, "tuned": {"wall_s": 0.0, "cpu_s": 0.0}}
    events = {}
    with tempfile.TemporaryDirectory(prefix="bench-sqlite-") as tmp:
        for i in range(args.repeat):
            for mode in ("plain", "tuned"):
                r = one(mode, Path(tmp) / f"{mode}{i}", args.runs)
                tot[mode]["wall_s"] += r["wall_s"]
                tot[mode]["cpu_s"] += r["cpu_s"]
                events[mode] = r["events_per_run"]
                print(f"{mode:6s} repeat {i}: wall {r['wall_s']:6.1f} s  cpu {r['cpu_s']:5.2f} s  "
                      f"events/run {r['events_per_run']}", flush=True)
    report = {"runs_per_side": args.runs * args.repeat, "events_per_run": events, "load_avg": os.getloadavg(),
              **{m: {k: round(v, 2) for k, v in d.items()} for m, d in tot.items()},
              "speedup_wall": round(tot["plain"]["wall_s"] / tot["tuned"]["wall_s"], 2),
              "speedup_cpu": round(tot["plain"]["cpu_s"] / tot["tuned"]["cpu_s"], 2)}
    print(json.dumps(report, indent=1))
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(report, indent=1) + "\n")


if __name__ == "__main__":
    main()
