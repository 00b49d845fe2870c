"""Replay of a recorded run: drive the twin with what was recorded (timestamps, table log, orientations from the
plan, temperature log, power-on time), so a replicate of a real run has the real run's inputs.

``load_replay(run_dir)`` reads a run folder of the raw-log contract into ``simulator.ReplayInputs``;
``replay_run(run_dir, truth, effects, seed)`` simulates it. The recorded table log, temperature column and
sample counter are written back verbatim; the IMU outputs are simulated at the recorded timestamps along the
plan's kinematics. Power-on time: given, else declared by the run's truth file (a simulated run), else inferred
as the start of the first run of the same device and power cycle in the landing folder (time since power-on =
this run's start - that start).

Replaying a simulated run with its own truth, effect chain and seed reproduces its raw files byte for byte
(``tests/test_replay.py``) as long as no effect reads the temperature: a simulation drives thermal effects with
the noise-free thermometer temperature, a replay with the recorded (noisy, rounded) log.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from assets_lib.sim.simulator import (
    ReplayInputs,
    SimulatedRun,
    load_truth,
    simulate_run,
)
from raw_schemas.manifest import load_manifest
from raw_schemas.readers import find_stream, read_stream


def infer_power_on_s(run_dir: str | Path) -> float:
    """Seconds from power-on to this run's start: the earliest start_time_utc among the runs of the same device
    and power cycle beside it (``<landing>/<device>/*/manifest.json``); 0 for the first run of its cycle."""
    run_dir = Path(run_dir)
    man = load_manifest(run_dir / "manifest.json")
    first = man.start_time_utc
    for m in sorted(run_dir.parent.glob("*/manifest.json")):
        if m.parent.name.startswith(("_", ".")):
            continue
        try:
            other = load_manifest(m)
        except Exception:  # noqa: BLE001 - a sibling that does not parse cannot be the first run of the cycle
            continue
        if other.device.id == man.device.id and other.power_cycle_index == man.power_cycle_index:
            first = min(first, other.start_time_utc)
    return float((man.start_time_utc - first).total_seconds())


def load_replay(run_dir: str | Path, *, power_on_s: float | None = None, plan_time_shift_s: float = 0.0) -> ReplayInputs:
    """Recorded inputs of one run folder (manifest, imu stream, optional table log)."""
    run_dir = Path(run_dir)
    man = load_manifest(run_dir / "manifest.json")
    imu = read_stream(find_stream(run_dir, "imu", required=True))
    tpath = find_stream(run_dir, "table", required=False)
    table = read_stream(tpath) if tpath else None
    temp = imu["temperature"].to_numpy() if "temperature" in imu else None
    counter = imu["counter"].to_numpy() if "counter" in imu else None
    if power_on_s is None:
        power_on_s = infer_power_on_s(run_dir)
    return ReplayInputs(man, imu["time_s"].to_numpy(dtype=float), temp, counter, table, float(power_on_s),
                        float(plan_time_shift_s))


def truth_path(run_dir: str | Path) -> Path:
    run_dir = Path(run_dir)
    return run_dir.parent.parent / "_truth" / run_dir.parent.name / f"{run_dir.name}.json"


def replay_run(run_dir: str | Path, truth=None, effects=None, seed: int | None = None, *,
               power_on_s: float | None = None, plan_time_shift_s: float = 0.0) -> SimulatedRun:
    """Simulate ``run_dir``'s experiment for ``truth`` with ``effects`` (both default to the run's own truth file
    ``<landing>/_truth/<device>/<run>.json``); ``seed`` defaults to the truth file's seed (else 0)."""
    tf = None
    if truth is None or effects is None or seed is None or power_on_s is None:
        p = truth_path(run_dir)
        if p.is_file():
            tf = load_truth(p)
        elif truth is None or effects is None:
            raise FileNotFoundError(f"{p}: no truth file; pass the device truth and effects to replay {run_dir}")
    if tf is not None:
        truth = truth if truth is not None else tf.truth
        effects = effects if effects is not None else tf.effects
        seed = seed if seed is not None else tf.seed
        if power_on_s is None and "power_on_s" in _keys(truth_path(run_dir)):
            power_on_s = tf.power_on_s
    rep = load_replay(run_dir, power_on_s=power_on_s, plan_time_shift_s=plan_time_shift_s)
    return simulate_run(truth, rep.manifest.plan, rep.manifest.run_id, effects=effects, seed=seed or 0, replay=rep,
                        table_clock_offset_s=tf.table_clock_offset_s if tf is not None else None)


def replicates(rep: ReplayInputs, truth, effects, seeds):
    """Replicates of one recorded run (load it once with :func:`load_replay`): one simulated run per noise seed,
    with the kinematics cached across them (``kinematics_cache``; bit-identical to computing them each time)."""
    from assets_lib.sim.kinematics import kinematics_cache

    with kinematics_cache():
        for s in seeds:
            yield simulate_run(truth, rep.manifest.plan, rep.manifest.run_id, effects=effects, seed=int(s), replay=rep)


def _keys(path: Path) -> set:
    import json

    return set(json.loads(path.read_text())) if path.is_file() else set()


def replay_differs(a: SimulatedRun, b: SimulatedRun) -> list[str]:
    """Columns of the IMU stream that differ between two runs (empty when equal)."""
    return [c for c in a.imu_raw.columns if c not in b.imu_raw or not np.array_equal(a.imu_raw[c], b.imu_raw[c])]
