"""Helpers for the production tests (sensors, reprocessing, idempotency, scale-out): small simulated archives,
throw-away Dagster instances on tmpfs, a chain of toy stages covering every level, and store fingerprints."""

from __future__ import annotations

import contextlib
import hashlib
import os
import shutil
import socket
import tempfile
from pathlib import Path

import dagster as dg
import pandas as pd

from assets_lib.sim.simulator import example_device, simulate_run, write_run
from assets_lib.stages.engine import StageGraph
from assets_lib.stages.spec import StageOutput, stage
from assets_lib.store import capture_key

SHM = "/dev/shm" if os.path.isdir("/dev/shm") and os.access("/dev/shm", os.W_OK) else None
QUIET = {"loggers": {"console": {"config": {"log_level": "WARNING"}}}}

DEVICES = (("TST-A", "tactical"), ("TST-B", "navigation"), ("TST-C", "consumer"))


def small_run(device_id: str, grade: str, run_id: str, plan: str = "quick_24_position", seed: int = 7,
              duration_scale: float = 0.1):
    """A short simulated run (a tenth of the plan's dwell times): ~10^4 samples, ~0.1 s to simulate."""
    truth = example_device(device_id, grade, seed)
    return simulate_run(truth, plan, run_id, seed=seed, plan_kwargs={"duration_scale": duration_scale})


def write_small_archive(landing: Path, devices=DEVICES[:2], runs_per_device: int = 2) -> list[str]:
    """``runs_per_device`` short multi-position runs per device; returns their partition keys (sorted)."""
    keys = []
    for dev, grade in devices:
        for i in range(runs_per_device):
            run_id = f"pc{i:02d}-pos24"
            write_run(small_run(dev, grade, run_id, seed=7 + i), Path(landing))
            keys.append(capture_key(dev, run_id))
    return sorted(keys)


def write_realistic_archive(landing: Path, devices=DEVICES[:1], duration_scale: float = 0.3) -> list[str]:
    """Per device a multi-position and a rate run with dwell times long enough for the science stages' checks
    (a tenth of the dwell times is too short for the plateau checks)."""
    keys = []
    for dev, grade in devices:
        for plan, run_id in (("quick_24_position", "pc00-pos24"), ("quick_rate", "pc00-rate")):
            write_run(small_run(dev, grade, run_id, plan=plan, duration_scale=duration_scale), Path(landing))
            keys.append(capture_key(dev, run_id))
    return sorted(keys)


@contextlib.contextmanager
def temp_instance():
    """A persistent SQLite Dagster instance in a temp dir on tmpfs (5x faster than ext4 here)."""
    d = tempfile.mkdtemp(prefix="imulab-dg-", dir=SHM)
    try:
        Path(d, "dagster.yaml").write_text("telemetry:\n  enabled: false\n")
        with dg.DagsterInstance.from_config(d) as inst:
            yield inst
    finally:
        shutil.rmtree(d, ignore_errors=True)


def apply_partition_requests(instance: dg.DagsterInstance, result) -> None:
    """What the daemon does with a sensor's dynamic partition requests."""
    for req in getattr(result, "dynamic_partitions_requests", None) or []:
        instance.add_dynamic_partitions(req.partitions_def_name, list(req.partition_keys))


def tree_digest(root: Path, suffix: str | None = None) -> dict[str, str]:
    """sha256 of every file under ``root`` (optionally only names ending with ``suffix``), by relative path."""
    root = Path(root)
    out = {}
    for p in sorted(root.rglob("*")):
        if p.is_file() and (suffix is None or p.name.endswith(suffix)):
            out[str(p.relative_to(root))] = hashlib.sha256(p.read_bytes()).hexdigest()
    return out


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


# ---------------------------------------------------------------------------------------------------------------
# Toy stages: a capture chain a -> b, a side branch, a device stage and a fleet stage
# ---------------------------------------------------------------------------------------------------------------
TOY_GROUP = "toy"
TOY_STAGES = ("toy_capture_a", "toy_capture_b", "toy_side", "toy_device", "toy_fleet")


def _means(df: pd.DataFrame) -> pd.DataFrame:
    num = df.select_dtypes("number")
    return num.mean().to_frame("mean").reset_index(names="column")


def toy_stage_list(code_version_a: str = "1") -> list:
    """The toy stages (specs; nothing is registered anywhere)."""

    @stage("toy_capture_a", level="capture", group=TOY_GROUP, code_version=code_version_a, upstream=("ingested_run",))
    def toy_capture_a(key, inputs):
        """Toy: column means of the ingested IMU table."""
        return StageOutput(tables={"means": _means(inputs.table("ingested_run", "imu"))})

    @stage("toy_capture_b", level="capture", group=TOY_GROUP, code_version="1", upstream=("toy_capture_a",))
    def toy_capture_b(key, inputs):
        """Toy: means scaled by 2."""
        m = inputs.table("toy_capture_a", "means")
        return StageOutput(tables={"scaled": m.assign(mean=2 * m["mean"])})

    @stage("toy_side", level="capture", group=TOY_GROUP, code_version="1", upstream=("ingested_run",))
    def toy_side(key, inputs):
        """Toy: sample count of the ingested run."""
        return StageOutput(tables={"count": pd.DataFrame({"n": [len(inputs.table("ingested_run", "imu"))]})})

    @stage("toy_device", level="device", group=TOY_GROUP, code_version="1", upstream=("toy_capture_b",))
    def toy_device(key, inputs):
        """Toy: scaled means of every run of a device."""
        parts = [inputs.table("toy_capture_b", "scaled", k).assign(run=k) for k in inputs.keys_of("toy_capture_b")]
        return StageOutput(tables={"runs": pd.concat(parts, ignore_index=True)})

    @stage("toy_fleet", level="fleet", group=TOY_GROUP, code_version="1", upstream=("toy_device",))
    def toy_fleet(key, inputs):
        """Toy: number of rows per device."""
        rows = [{"device": k, "rows": len(inputs.table("toy_device", "runs", k))} for k in inputs.keys_of("toy_device")]
        return StageOutput(tables={"fleet": pd.DataFrame(rows)})

    return [toy_capture_a, toy_capture_b, toy_side, toy_device, toy_fleet]


def toy_graph(code_version_a: str = "1") -> StageGraph:
    """An orchestration-only stage graph: the real ingest stage plus the toy stages (the science stages are left
    out, so these tests exercise sensors, schedules and reprocessing independently of the fits)."""
    from assets_lib.stages.registry import STAGES

    return StageGraph([STAGES["ingested_run"], *toy_stage_list(code_version_a)])


@contextlib.contextmanager
def toy_stages(code_version_a: str = "1"):
    """``toy_graph`` as a context (kept for the tests' structure; nothing global is changed)."""
    yield toy_graph(code_version_a)


def toy_definitions(landing, store, graph: StageGraph) -> dg.Definitions:
    """The code location (``pipelines.definitions.build_definitions``) over the toy stage graph."""
    from pipelines.definitions import build_definitions

    return build_definitions(str(landing), str(store), stages=graph)
