"""Scale-out for real: PostgreSQL instance + Redis broker + two dagster-celery workers, all local on 127.0.0.1.

Two batched ``calibrate_captures`` runs (two blocks of partitions, launched at once with ``dagster job execute``
on ``pipelines.celery_defs``) execute their steps on the workers; the parquet they write must be byte-identical
to an in-process run of the same archive into another store. Every process started is stopped and checked gone.
Needs redis-server and postgresql (``.ci/services.sh``); skips with the reason otherwise.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import tempfile
import time
import warnings
from pathlib import Path

import dagster as dg
import pytest

from local_services import REPO, CeleryWorker, LocalPostgres, LocalRedis, alive, celery_yaml, missing, wait_for_workers
from prod_helpers import DEVICES, SHM, temp_instance, tree_digest, write_realistic_archive

pytestmark = pytest.mark.slow
warnings.filterwarnings("ignore")


def celery_workers_of(instance: dg.DagsterInstance, run_id: str) -> set[str]:
    """Worker host names that executed steps of a run (from dagster-celery's engine events)."""
    names = set()
    for entry in instance.all_logs(run_id, of_type=dg.DagsterEventType.ENGINE_EVENT):
        data = entry.dagster_event.event_specific_data
        md = getattr(data, "metadata", None) or {}
        if "Celery worker" in md:
            names.add(str(md["Celery worker"].value))
    return names


def test_two_celery_workers_match_in_process():
    miss = missing()
    if miss:
        pytest.skip("scale-out services not installed (run .ci/services.sh): " + "; ".join(miss))
    from pipelines.definitions import build_definitions
    from pipelines.jobs import range_tags
    from pipelines.launch import execute, register_landed_runs
    from pipelines.resources import LabArchive

    root = Path(tempfile.mkdtemp(prefix="imulab-dist-", dir=SHM))
    services: list = []
    try:
        landing = root / "landing"
        keys = write_realistic_archive(landing, devices=DEVICES[:2])
        pg = LocalPostgres().start()
        services.append(pg)
        rd = LocalRedis(root / "redis").start()
        services.append(rd)
        home = root / "dagster_home"
        home.mkdir()
        (home / "dagster.yaml").write_text(pg.dagster_yaml())
        store = root / "store_celery"
        env = {**os.environ, "DAGSTER_HOME": str(home), "IMULAB_LANDING": str(landing), "IMULAB_STORE": str(store),
               "IMULAB_CELERY_BROKER": rd.url(0), "IMULAB_CELERY_BACKEND": rd.url(1), "PYTHONWARNINGS": "ignore"}
        with dg.DagsterInstance.from_config(str(home)) as inst:  # a Postgres-backed instance
            assert type(inst.run_storage).__name__ == "PostgresRunStorage"
            register_landed_runs(inst, LabArchive(landing_dir=str(landing)))
            assert list(inst.get_dynamic_partitions("captures")) == keys

        cfg = celery_yaml(root / "celery.yaml", rd.url(0), rd.url(1))
        workers = [CeleryWorker(n, cfg, env, root).start() for n in ("imulab-w1", "imulab-w2")]
        services += workers
        wait_for_workers(rd.url(0), ["imulab-w1", "imulab-w2"])
        for w in workers:
            w.track()

        blocks = [(keys[0], keys[1]), (keys[2], keys[3])]  # one block per device
        t0 = time.time()
        coordinators = [subprocess.Popen(
            ["dagster", "job", "execute", "-m", "pipelines.celery_defs", "-a", "defs", "-j", "calibrate_captures",
             "--tags", json.dumps(range_tags(*b))], env=env, cwd=REPO, stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT, text=True, start_new_session=True) for b in blocks]
        outs = []
        for c in coordinators:
            try:
                outs.append(c.communicate(timeout=300)[0])
            except subprocess.TimeoutExpired:
                c.kill()
                outs.append(c.communicate()[0])
        elapsed = time.time() - t0
        for c, out in zip(coordinators, outs):
            assert c.returncode == 0, out[-4000:] + "\n" + "\n".join(w.tail() for w in workers)

        with dg.DagsterInstance.from_config(str(home)) as inst:
            runs = inst.get_runs(dg.RunsFilter(job_name="calibrate_captures"))
            assert len(runs) == 2 and all(r.status == dg.DagsterRunStatus.SUCCESS for r in runs)
            used = set().union(*(celery_workers_of(inst, r.run_id) for r in runs))
            assert {u.split("@", 1)[0] for u in used} == {"imulab-w1", "imulab-w2"}, used  # both workers worked
            for r in runs:  # no step ran in the coordinator
                assert celery_workers_of(inst, r.run_id)

        # the same archive in-process into another store
        ref = root / "store_inprocess"
        defs = build_definitions(str(landing), str(ref))
        with temp_instance() as inst:
            register_landed_runs(inst, LabArchive(landing_dir=str(landing)))
            assert execute(defs, inst, "calibrate_captures", "captures").success
        got, want = tree_digest(store, ".parquet"), tree_digest(ref, ".parquet")
        assert want and got == want
        stages = {p.split("/", 1)[0] for p in want}
        assert "ingested_run" in stages and len(stages) > 1
        print(f"\ncelery: 2 runs x {len(keys) // 2} partitions on 2 workers in {elapsed:.1f} s; "
              f"{len(want)} parquet files identical to the in-process run")
    finally:
        leftovers = {}
        for s in reversed(services):
            left = s.stop()
            if left:
                leftovers[s.name] = left
        for s in services:
            assert not alive(s.seen), f"{s.name}: processes left {alive(s.seen)}"
        shutil.rmtree(root, ignore_errors=True)
    assert not leftovers, f"processes needed SIGKILL: {leftovers}"
