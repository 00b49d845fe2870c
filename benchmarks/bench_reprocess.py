"""Reprocessing throughput: runs per minute through Dagster, the share of wall time that is Dagster bookkeeping,
and 1 vs 2 dagster-celery workers.

What is measured (all on this machine, SQLite instance on tmpfs, store on tmpfs):
1. ``reprocess`` of a fresh archive of >= 200 simulated runs (short plans: ``--scale`` of the dwell times) through
   the real code location: plan (hash every raw file, walk the stage graph) + batched runs, captures then devices
   then fleet (``pipelines.reprocess.run_plan``). Runs per minute = captured runs / wall minutes.
2. Where the wall time goes: time spent inside ``pipelines.assets.run_stage`` (versions, the stage compute, parquet
   writes), the asset-check steps (from Dagster's step stats), and the rest (Dagster bookkeeping: run and step
   set-up, event log writes, the per-partition materialization events). Cross-check: the engine's
   ``compute_partition`` over every stage in plain Python, without Dagster, on a fresh store.
3. An unchanged archive: plan only (the weekly no-op cost).
4. With Redis + PostgreSQL installed (``.ci/services.sh``): the same batched ``calibrate_captures`` runs for a subset
   of the archive, launched concurrently with ``dagster job execute`` on ``pipelines.celery_defs`` against 1 and
   then 2 celery workers (concurrency 1 each).

    python benchmarks/bench_reprocess.py                  # full benchmark, writes benchmarks/results/reprocess.json
    python benchmarks/bench_reprocess.py --devices 5 --cycles 2 --no-celery   # a quick look
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import subprocess
import sys
import tempfile
import time
import warnings
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "tests"))  # the local-service helpers of the scale-out test
warnings.filterwarnings("ignore")
os.environ.setdefault("PYTHONWARNINGS", "ignore")

GRADES = ("tactical", "navigation", "consumer")


def simulate(landing: Path, devices: int, cycles: int, scale: float) -> list[str]:
    from assets_lib.sim.simulator import example_device, simulate_run, write_run

    keys = []
    for d in range(devices):
        dev = f"BEN-{d:03d}"
        base = example_device(dev, GRADES[d % 3], 2026)
        for c in range(cycles):
            truth = base.for_power_cycle(c, 2026, 7.0 * c)
            for plan, rid in (("quick_24_position", "pos24"), ("quick_rate", "rate")):
                run = simulate_run(truth, plan, f"pc{c:02d}-{rid}", power_cycle_index=c, seed=2026,
                                   plan_kwargs={"duration_scale": scale})
                write_run(run, landing, "parquet")
                keys.append(f"{dev}__pc{c:02d}-{rid}")
    return sorted(keys)


class Timer:
    """Accumulates the time spent inside ``pipelines.assets.run_stage`` (the asset bodies call it by name)."""

    def __init__(self):
        import pipelines.assets as st

        self.st, self.orig, self.seconds, self.calls = st, st.run_stage, {}, 0

    def __enter__(self):
        def timed(context, graph, spec, store, archive):
            t = time.perf_counter()
            try:
                return self.orig(context, graph, spec, store, archive)
            finally:
                self.seconds[spec.name] = self.seconds.get(spec.name, 0.0) + time.perf_counter() - t
                self.calls += 1

        self.st.run_stage = timed
        return self

    def __exit__(self, *exc):
        self.st.run_stage = self.orig


def check_step_seconds(instance, run_ids) -> float:
    total = 0.0
    for rid in run_ids:
        for s in instance.get_run_step_stats(rid):
            if s.start_time and s.end_time and s.step_key not in _stage_names():
                total += s.end_time - s.start_time
    return total


def _stage_names() -> set[str]:
    from assets_lib.stages.registry import STAGES

    return set(STAGES.names)


def in_process(landing: Path, store: Path, keys: list[str]) -> dict:
    import dagster as dg

    from assets_lib.stages.plan import outcome
    from assets_lib.stages.registry import STAGES
    from assets_lib.store import VersionedStore
    from pipelines import reprocess
    from pipelines.definitions import build_definitions
    from pipelines.launch import register_landed_runs
    from pipelines.resources import LabArchive

    home = Path(tempfile.mkdtemp(prefix="bench-dg-", dir="/dev/shm" if os.path.isdir("/dev/shm") else None))
    (home / "dagster.yaml").write_text("telemetry:\n  enabled: false\n")
    archive, vstore = LabArchive(landing_dir=str(landing)), VersionedStore(store)
    defs = build_definitions(str(landing), str(store))
    out: dict = {}
    try:
        with dg.DagsterInstance.from_config(str(home)) as inst:
            register_landed_runs(inst, archive)
            t0 = time.perf_counter()
            plan = reprocess.plan_for_instance(inst, STAGES, vstore, archive.archive)
            t_plan = time.perf_counter() - t0
            with Timer() as timer:
                t1 = time.perf_counter()
                summary = reprocess.run_plan(defs, inst, plan, vstore)
                t_runs = time.perf_counter() - t1
            wall = t_plan + t_runs
            checks = check_step_seconds(inst, [r for _, r, _ in summary.runs])
            stage_s = sum(timer.seconds.values())
            written = sum(o == "rewritten" for _, o in outcome(vstore, plan))
            out["reprocess"] = {
                "captured_runs": len(keys), "stale_partitions": len(plan.stale), "partitions_written": written,
                "dagster_runs": len(summary.runs),
                "runs_ok": summary.success, "wall_s": round(wall, 2), "plan_s": round(t_plan, 2),
                "runs_s": round(t_runs, 2), "runs_per_minute": round(len(keys) / wall * 60, 1),
                "inside_run_stage_s": round(stage_s, 2),
                "inside_run_stage_by_stage_s": {k: round(v, 2) for k, v in sorted(timer.seconds.items())},
                "asset_check_steps_s": round(checks, 2),
                "dagster_bookkeeping_s": round(t_runs - stage_s - checks, 2),
                "dagster_bookkeeping_share": round((t_runs - stage_s - checks) / wall, 3),
                "computation_share": round((t_plan + stage_s + checks) / wall, 3),
            }
            t2 = time.perf_counter()
            noop = reprocess.plan_for_instance(inst, STAGES, vstore, archive.archive)
            out["unchanged"] = {"stale_partitions": len(noop.stale), "plan_s": round(time.perf_counter() - t2, 2)}
    finally:
        shutil.rmtree(home, ignore_errors=True)
    return out


def plain_python(landing: Path, store: Path, keys: list[str]) -> dict:
    """The same partitions computed by the engine without Dagster (fresh store), in stage order."""
    from assets_lib.stages.engine import compute_partition, stage_keys
    from assets_lib.stages.registry import STAGES
    from assets_lib.store import LandingArchive, VersionedStore, split_capture_key

    archive, vstore = LandingArchive(landing), VersionedStore(store)
    devices = sorted({split_capture_key(k)[0] for k in keys})
    t0 = time.perf_counter()
    written = 0
    for spec in STAGES:
        for k in stage_keys(spec, keys, devices):
            written += compute_partition(STAGES, spec, k, vstore, archive).status == "written"
    return {"wall_s": round(time.perf_counter() - t0, 2), "partitions_written": written}


def celery_scaling(landing: Path, root: Path, keys: list[str], n_runs: int, blocks: int) -> dict:
    import dagster as dg
    from local_services import (
        CeleryWorker,
        LocalPostgres,
        LocalRedis,
        celery_yaml,
        missing,
        wait_for_workers,
    )

    from pipelines.jobs import range_tags
    from pipelines.launch import register_landed_runs
    from pipelines.resources import LabArchive

    miss = missing()
    if miss:
        return {"skipped": "; ".join(miss)}
    sub = root / "landing_subset"
    for k in keys[:n_runs]:
        dev, run = k.split("__", 1)
        shutil.copytree(landing / dev / run, sub / dev / run)
    subkeys = keys[:n_runs]
    size = -(-len(subkeys) // blocks)
    block_ranges = [(subkeys[i], subkeys[min(i + size, len(subkeys)) - 1]) for i in range(0, len(subkeys), size)]
    services, result = [], {"captured_runs": len(subkeys), "concurrent_runs": len(block_ranges)}
    try:
        pg = LocalPostgres().start()
        services.append(pg)
        rd = LocalRedis(root / "redis").start()
        services.append(rd)
        cfg = celery_yaml(root / "celery.yaml", rd.url(0), rd.url(1))
        for n_workers in (1, 2):
            home = root / f"home{n_workers}"
            home.mkdir()
            db = f"bench{n_workers}"
            import psycopg2

            con = psycopg2.connect(host="127.0.0.1", port=pg.port, user=pg.user, dbname="postgres")
            con.autocommit = True
            con.cursor().execute(f"CREATE DATABASE {db}")
            con.close()
            (home / "dagster.yaml").write_text(pg.dagster_yaml().replace(f"db_name: {pg.db}", f"db_name: {db}"))
            store = root / f"store{n_workers}"
            env = {**os.environ, "DAGSTER_HOME": str(home), "IMULAB_LANDING": str(sub), "IMULAB_STORE": str(store),
                   "IMULAB_CELERY_BROKER": rd.url(0), "IMULAB_CELERY_BACKEND": rd.url(1)}
            with dg.DagsterInstance.from_config(str(home)) as inst:
                register_landed_runs(inst, LabArchive(landing_dir=str(sub)))
            names = [f"bench-w{i}-{n_workers}" for i in range(n_workers)]
            workers = [CeleryWorker(n, cfg, env, root).start() for n in names]
            services += workers
            wait_for_workers(rd.url(0), names)
            t0 = time.perf_counter()
            procs = [subprocess.Popen(["dagster", "job", "execute", "-m", "pipelines.celery_defs", "-a", "defs", "-j",
                                       "calibrate_captures", "--tags", json.dumps(range_tags(*b))], env=env, cwd=REPO,
                                      stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL) for b in block_ranges]
            rcs = [p.wait() for p in procs]
            wall = time.perf_counter() - t0
            for w in workers:
                w.stop()
            result[f"workers_{n_workers}"] = {"wall_s": round(wall, 2), "all_ok": all(r == 0 for r in rcs),
                                              "runs_per_minute": round(len(subkeys) / wall * 60, 1)}
        w1, w2 = result["workers_1"]["wall_s"], result["workers_2"]["wall_s"]
        result["speedup_2_vs_1"] = round(w1 / w2, 2)
    finally:
        for s in reversed(services):
            s.stop()
    return result


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--devices", type=int, default=25)
    ap.add_argument("--cycles", type=int, default=4, help="power cycles per device (2 runs each)")
    ap.add_argument("--scale", type=float, default=0.3, help="duration_scale of the plans' dwell times")
    ap.add_argument("--celery-runs", type=int, default=24, help="captured runs in the celery comparison")
    ap.add_argument("--celery-blocks", type=int, default=4, help="concurrent batched runs in the celery comparison")
    ap.add_argument("--no-celery", action="store_true")
    ap.add_argument("--no-baseline", action="store_true", help="skip the plain-Python cross-check")
    ap.add_argument("--out", default=str(REPO / "benchmarks" / "results" / "reprocess.json"))
    args = ap.parse_args(argv)

    root = Path(tempfile.mkdtemp(prefix="bench-reprocess-", dir="/dev/shm" if os.path.isdir("/dev/shm") else None))
    report: dict = {"machine": {"cpus": os.cpu_count(), "python": platform.python_version(),
                                "load_avg_at_start": [round(x, 2) for x in os.getloadavg()]}}
    try:
        t0 = time.perf_counter()
        keys = simulate(root / "landing", args.devices, args.cycles, args.scale)
        report["archive"] = {"captured_runs": len(keys), "devices": args.devices, "power_cycles": args.cycles,
                             "plans": ["quick_24_position", "quick_rate"], "duration_scale": args.scale,
                             "simulate_s": round(time.perf_counter() - t0, 1)}
        print(f"simulated {len(keys)} runs in {report['archive']['simulate_s']} s", flush=True)
        from assets_lib.stages.registry import STAGES

        report["stages"] = sorted(STAGES.names)
        report.update(in_process(root / "landing", root / "store", keys))
        r = report["reprocess"]
        print(f"reprocess: {r['captured_runs']} runs, {r['stale_partitions']} partitions in {r['wall_s']} s "
              f"= {r['runs_per_minute']} runs/min; inside run_stage {r['inside_run_stage_s']} s, checks "
              f"{r['asset_check_steps_s']} s, plan {r['plan_s']} s; Dagster bookkeeping "
              f"{r['dagster_bookkeeping_share']:.0%} of wall", flush=True)
        print(f"unchanged archive: {report['unchanged']['stale_partitions']} stale, plan {report['unchanged']['plan_s']} s")
        if not args.no_baseline:
            report["plain_python"] = plain_python(root / "landing", root / "store_plain", keys)
            pp = report["plain_python"]["wall_s"]
            report["plain_python"]["dagster_overhead_share_vs_plain"] = round(1 - pp / r["runs_s"], 3)
            print(f"plain Python (the engine over the same partitions, no Dagster, no checks): {pp} s "
                  f"-> Dagster + checks = {report['plain_python']['dagster_overhead_share_vs_plain']:.0%} of run time")
        if not args.no_celery:
            report["celery"] = celery_scaling(root / "landing", root, keys, args.celery_runs, args.celery_blocks)
            print(f"celery: {json.dumps(report['celery'])}")
    finally:
        shutil.rmtree(root, ignore_errors=True)
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(report, indent=1) + "\n")
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
