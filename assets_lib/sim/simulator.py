"""Digital twin of the calibration experiment: writes runs in the raw-log contract with known truth.

The sensor is a chain of composable effects applied to the true body-frame inputs from the plan's
kinematics (``kinematics.body_inputs``): the deterministic error model of docs/design.md ([SEED000] eq. 1-2),
Allan noise (IEEE 952 Annex C), then any extra effect (saturation, a disturbed plateau, temperature, latency,
nonlinearity ...), then count quantization at write time. New effects implement :class:`SensorEffect` and plug
into ``simulate_run(effects=[...])`` without changing anything here. Everything is seeded and deterministic.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import asdict, dataclass, field, replace
from datetime import datetime, timedelta, timezone
from pathlib import Path
from typing import Protocol

import numpy as np
import pandas as pd

from assets_lib.sim.earth import normal_gravity_mps2
from assets_lib.sim.earth import earth_rate_level, specific_force_level
from assets_lib.sim.effects.base import TableMotion, split_stages
from assets_lib.sim.effects.core import DEFAULT_EFFECTS, AllanNoise, ErrorModel, PlateauDisturbance, Saturation  # noqa: F401
from assets_lib.sim.kinematics import BodyInputs, Trajectory, body_inputs, trajectory
from assets_lib.sim.noise import AllanParams
from assets_lib.sim.plans import build_plan
from raw_schemas.manifest import SCHEMA_VERSION, Manifest, TestPlan
from raw_schemas.units import DEG_TO_RAD as DEG, DEGPH_TO_RADPS as DEGPH, MG_TO_MPS2 as MG, UG_TO_MPS2 as UG, si_factor


# ----------------------------------------------------------------------------------------------------------
# Truth model
# ----------------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class TriadTruth:
    """Error model of one sensor triad in SI (docs/design.md): y = diag(K)(I+E) x + b + noise (+ second order)."""

    scale: tuple[float, float, float]
    misalignment_rad: tuple[tuple[float, ...], ...]  # 3x3, zero diagonal
    bias: tuple[float, float, float]
    noise: tuple[AllanParams, AllanParams, AllanParams]
    lsb: float  # value of one output count, in ``lsb_unit``
    lsb_unit: str
    full_scale: float | None = None  # saturation limit, SI
    k2: tuple[float, float, float] = (0.0, 0.0, 0.0)  # accel: 1/(m/s^2)
    kc: tuple[tuple[float, ...], ...] = ((0.0,) * 3,) * 3  # accel cross-coupling Kc[i][j] f_i f_j, 1/(m/s^2)

    def matrix(self) -> np.ndarray:
        """diag(K)(I + E)."""
        return np.diag(self.scale) @ (np.eye(3) + np.asarray(self.misalignment_rad))


@dataclass(frozen=True)
class DeviceTruth:
    """Truth of one device for one power cycle; ``g_sensitivity`` is gyro rad/s per m/s^2 (3x3)."""

    device_id: str
    model: str
    grade: str
    gyro: TriadTruth
    accel: TriadTruth
    g_sensitivity: tuple[tuple[float, ...], ...] = ((0.0,) * 3,) * 3
    #: turn-on to turn-on 1-sigma spreads (bias SI, scale dimensionless), and bias ageing per day (SI)
    bias_repeatability: tuple[float, float] = (0.0, 0.0)  # (gyro, accel)
    scale_repeatability: tuple[float, float] = (0.0, 0.0)
    gyro_bias_drift_per_day: float = 0.0
    sample_rate_hz: float = 100.0
    temperature_degc: float = 25.0

    def to_json(self) -> dict:
        return asdict(self)

    def for_power_cycle(self, cycle: int, seed: int, days_since_first: float = 0.0) -> "DeviceTruth":
        """Truth after a turn-on: biases and scale factors redrawn with the repeatability spreads (seeded)."""
        rng = np.random.default_rng([seed, _stable_int(self.device_id), cycle, 7])

        def turn_on(tri: TriadTruth, sb: float, ss: float, drift: float) -> TriadTruth:
            return replace(
                tri,
                bias=tuple(np.asarray(tri.bias) + sb * rng.standard_normal(3) + drift * days_since_first),
                scale=tuple(np.asarray(tri.scale) + ss * rng.standard_normal(3)),
            )

        return replace(
            self,
            gyro=turn_on(self.gyro, self.bias_repeatability[0], self.scale_repeatability[0], self.gyro_bias_drift_per_day),
            accel=turn_on(self.accel, self.bias_repeatability[1], self.scale_repeatability[1], 0.0),
        )


def _stable_int(text: str) -> int:
    return int.from_bytes(hashlib.sha256(text.encode()).digest()[:4], "little")


def _offdiag(rng: np.random.Generator, sigma: float) -> tuple:
    e = sigma * rng.standard_normal((3, 3))
    np.fill_diagonal(e, 0.0)
    return tuple(map(tuple, e))


def example_device(device_id: str, grade: str, seed: int = 0) -> DeviceTruth:
    """A plausible device of the given grade (navigation FOG + quartz, tactical MEMS, consumer MEMS), seeded.

    Magnitudes follow docs effects.md and typical datasheets; the draw is random so every device differs.
    """
    rng = np.random.default_rng([seed, _stable_int(device_id)])
    r3 = lambda s: tuple(s * rng.standard_normal(3))  # noqa: E731
    if grade == "navigation":
        gn = AllanParams(q=0.02 / 3600 * DEG, n=0.002 * DEG / 60, b=0.003 * DEGPH, k=0.0005 * DEGPH / 60)
        an = AllanParams(n=5e-6 * 9.80665, b=5 * UG, k=0.0)
        gyro = TriadTruth(tuple(1 + np.array(r3(30e-6))), _offdiag(rng, 30e-6), r3(0.05 * DEGPH), (gn,) * 3, 2e-6, "deg/s")
        accel = TriadTruth(
            tuple(1 + np.array(r3(80e-6))), _offdiag(rng, 50e-6), r3(60 * UG), (an,) * 3, 1e-6, "g",
            k2=r3(10e-6 / 9.80665), kc=_offdiag(rng, 5e-6 / 9.80665),
        )
        return DeviceTruth(device_id, "FOG-900 / QA-2000", grade, gyro, accel, _offdiag(rng, 0.001 * DEGPH / 9.80665),
                           (0.005 * DEGPH, 10 * UG), (5e-6, 10e-6), sample_rate_hz=100.0)
    if grade == "tactical":
        gn = AllanParams(n=0.15 * DEG / 60, b=0.8 * DEGPH, k=0.5 * DEGPH / 60)
        an = AllanParams(n=0.03 / 60, b=20 * UG, k=0.0)
        gyro = TriadTruth(tuple(1 + np.array(r3(400e-6))), _offdiag(rng, 0.5e-3), r3(5 * DEGPH), (gn,) * 3, 1e-4, "deg/s",
                          full_scale=1000 * DEG)
        accel = TriadTruth(
            tuple(1 + np.array(r3(300e-6))), _offdiag(rng, 0.5e-3), r3(1.5 * MG), (an,) * 3, 1e-5, "g",
            full_scale=20 * 9.80665, k2=r3(50e-6 / 9.80665), kc=_offdiag(rng, 20e-6 / 9.80665),
        )
        return DeviceTruth(device_id, "ADIS-like tactical MEMS", grade, gyro, accel, _offdiag(rng, 0.01 * DEG / 9.80665),
                           (1.0 * DEGPH, 0.3 * MG), (50e-6, 40e-6), gyro_bias_drift_per_day=0.0, sample_rate_hz=100.0)
    if grade == "consumer":
        gn = AllanParams(n=0.005 * DEG, b=10 * DEGPH, k=5 * DEGPH / 60)
        an = AllanParams(n=150 * UG, b=0.1 * MG)
        gyro = TriadTruth(tuple(1 + np.array(r3(0.01))), _offdiag(rng, 5e-3), r3(0.5 * DEG), (gn,) * 3, 1 / 131.0, "deg/s",
                          full_scale=250 * DEG)
        accel = TriadTruth(
            tuple(1 + np.array(r3(0.01))), _offdiag(rng, 5e-3), r3(30 * MG), (an,) * 3, 1 / 16384.0, "g",
            full_scale=2 * 9.80665, k2=r3(300e-6 / 9.80665),
        )
        return DeviceTruth(device_id, "MPU-like consumer MEMS", grade, gyro, accel, _offdiag(rng, 0.05 * DEG / 9.80665),
                           (0.05 * DEG, 5 * MG), (1e-3, 1e-3), sample_rate_hz=100.0)
    raise ValueError(f"unknown grade {grade!r}")


# ----------------------------------------------------------------------------------------------------------
# Effects
# ----------------------------------------------------------------------------------------------------------
@dataclass
class SimContext:
    """What an effect may look at: times, true inputs, temperature, step index, the truth and a seeded rng."""

    t_s: np.ndarray
    inputs: BodyInputs
    truth: DeviceTruth
    rate_hz: float
    rng: np.random.Generator
    temperature_degc: np.ndarray
    step_index: np.ndarray
    time_since_power_on_s: np.ndarray | None = None
    accel_inputs: BodyInputs | None = None  # the accelerometer triad's inputs when clock effects split the triads


class SensorEffect(Protocol):
    """One composable piece of the sensor: maps (gyro, accel) outputs (n,3) SI to new outputs."""

    name: str

    def apply(self, ctx: SimContext, gyro: np.ndarray, accel: np.ndarray) -> tuple[np.ndarray, np.ndarray]: ...




# ----------------------------------------------------------------------------------------------------------
# One run
# ----------------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class SiteSpec:
    name: str = "Xi'an test hall"
    latitude_deg: float = 34.25
    longitude_deg: float = 108.95
    height_m: float = 400.0

    def manifest_site(self) -> dict:
        return {
            "name": self.name,
            "latitude_deg": self.latitude_deg,
            "longitude_deg": self.longitude_deg,
            "height_m": self.height_m,
            "gravity_mps2": None,
            "gravity_model": "wgs84_normal",
        }

    @property
    def gravity_mps2(self) -> float:
        return normal_gravity_mps2(self.latitude_deg, self.height_m)


@dataclass(frozen=True)
class SimulatedRun:
    """A run as a capture job would write it (raw columns, counts) plus the truth that made it."""

    manifest: Manifest
    imu_raw: pd.DataFrame
    table_raw: pd.DataFrame | None
    truth: DeviceTruth
    table_clock_offset_s: float
    effects: tuple[str, ...] = field(default=())
    effect_params: tuple[dict, ...] = field(default=())  # to_dict() of every registered effect family in the chain
    power_on_s: float = 0.0
    seed: int | None = None

    @property
    def partition_key(self) -> str:
        return self.manifest.partition_key


def _channels(truth: DeviceTruth) -> dict:
    ch = {}
    for ax in "xyz":
        ch[f"gyro_{ax}"] = {"unit": "counts", "lsb": truth.gyro.lsb, "lsb_unit": truth.gyro.lsb_unit}
        ch[f"accel_{ax}"] = {"unit": "counts", "lsb": truth.accel.lsb, "lsb_unit": truth.accel.lsb_unit}
    ch["temperature"] = {"unit": "degC"}
    return ch


def to_counts(values_si: np.ndarray, lsb: float, lsb_unit: str, family: str) -> np.ndarray:
    """Quantize SI values to integer counts of ``lsb`` ``lsb_unit`` (round to nearest)."""
    return np.rint(values_si / (lsb * si_factor(family, lsb_unit))).astype(np.int64)


@dataclass(frozen=True)
class ReplayInputs:
    """What a recorded run fixes for its replay (built by ``assets_lib.sim.replay.load_replay``).

    ``time_s`` are the recorded IMU timestamps (kinematics are evaluated at them; a nominal grid rounded to ns is
    taken as the exact grid); ``temperature`` (the recorded thermometer column) drives the thermal effects and is
    written back verbatim, as are ``table_raw`` (the recorded table log) and ``counter``; ``power_on_s`` is the
    time from power-on to the first sample; ``plan_time_shift_s`` places the plan on the IMU clock
    (t_plan = t_imu - shift; 0 for a simulated run). Plan, orientations, site, start time, run id, test kind,
    power cycle and table id come from ``manifest``.
    """

    manifest: Manifest
    time_s: np.ndarray
    temperature: np.ndarray | None
    counter: np.ndarray | None
    table_raw: pd.DataFrame | None
    power_on_s: float = 0.0
    plan_time_shift_s: float = 0.0


def _site_values(site) -> tuple[float, float, dict]:
    """(latitude, gravity, manifest site dict) of a ``SiteSpec`` or a manifest ``Site``."""
    if isinstance(site, SiteSpec):
        return site.latitude_deg, site.gravity_mps2, site.manifest_site()
    from assets_lib.sim.earth import site_gravity_mps2

    return site.latitude_deg, site_gravity_mps2(site), site.model_dump()


def true_inputs(plan, t_s: np.ndarray, latitude_deg: float, gravity_mps2: float, table_effects=()) -> tuple[BodyInputs, TableMotion]:
    """Body inputs of the *true* table motion at true times ``t_s``: the plan's kinematics ([SEED000] eq. 3-5)
    perturbed by table-stage effects (rate error, wobble), then omega_b = C^T (omega_l + omega_ie), f_b = C^T f^l."""
    tr = trajectory(plan, t_s)
    m = TableMotion(tr.t_s, tr.c_b2l, tr.omega_motion_level_radps, tr.table_angle_rad, tr.table_rate_radps,
                    tr.step_index, np.asarray(plan.table_axis_level, dtype=float))
    for e in table_effects:
        m = e.perturb(m)
    ct = np.swapaxes(m.c_b2l, 1, 2)
    w_e = ct @ earth_rate_level(latitude_deg, plan.frame)
    w_motion = np.einsum("nij,nj->ni", ct, m.omega_motion_level_radps)
    f = ct @ specific_force_level(gravity_mps2, plan.frame)
    traj = Trajectory(m.t_s, m.c_b2l, m.omega_motion_level_radps, m.table_angle_rad, m.table_rate_radps, m.step_index)
    return BodyInputs(w_motion + w_e, w_e, f, traj), m


def sensed_inputs(plan, t_imu_s: np.ndarray, latitude_deg: float, gravity_mps2: float, effects=()
                  ) -> tuple[BodyInputs, BodyInputs | None]:
    """(gyro inputs, accel inputs or None when both triads sense the same): clock effects map the IMU sample
    times to each triad's true times and input gain, table effects perturb the motion, input effects add to it."""
    st = split_stages(effects)
    if not (st["clock"] or st["table"] or st["input"]):
        return body_inputs(plan, t_imu_s, latitude_deg, gravity_mps2), None
    out = {}
    for triad in ("gyro", "accel"):
        tt, gain = t_imu_s, 1.0
        for e in st["clock"]:
            tt = e.true_time_s(tt, triad)
            gain *= e.input_gain(triad)
        if triad == "accel" and np.array_equal(tt, out["gyro"][2]):
            bi, m = out["gyro"][3], out["gyro"][4]
        else:
            bi, m = true_inputs(plan, tt, latitude_deg, gravity_mps2, st["table"])
        raw_bi = bi
        for e in st["input"]:
            bi = e.add_inputs(triad, bi, m)
        if gain != 1.0:
            bi = BodyInputs(bi.omega_b_radps * gain, bi.omega_earth_b_radps * gain, bi.f_b_mps2 * gain, bi.trajectory)
        out[triad] = (bi, gain, tt, raw_bi, m)
    return out["gyro"][0], out["accel"][0]


def housing_temperature_degc(truth: DeviceTruth, time_since_power_on_s: np.ndarray) -> np.ndarray:
    """Default thermometer temperature: ambient + 1.5 K self-heating with a 900 s time constant from power-on."""
    return truth.temperature_degc + 1.5 * (1 - np.exp(-time_since_power_on_s / 900.0))


def simulate_run(
    truth: DeviceTruth,
    plan: TestPlan | str,
    run_id: str,
    *,
    test_kind: str | None = None,
    site: SiteSpec = SiteSpec(),
    start_time_utc: datetime = datetime(2026, 1, 5, 8, 0, tzinfo=timezone.utc),
    power_cycle_index: int = 0,
    seed: int = 0,
    effects=DEFAULT_EFFECTS,
    table_log: bool = True,
    table_rate_hz: float = 50.0,
    table_clock_offset_s: float | None = None,
    tail_s: float = 2.0,
    plan_kwargs: dict | None = None,
    power_on_s: float = 0.0,
    temperature_degc=None,
    replay: ReplayInputs | None = None,
) -> SimulatedRun:
    """Simulate one run of ``plan`` for ``truth`` (already drawn for its power cycle), seeded and deterministic.

    ``effects`` is the chain (``DEFAULT_EFFECTS`` = error model, Allan noise, saturation); add effect families
    with ``effects.sensor_chain([...])``. ``power_on_s`` is the time from power-on to the first sample (warm-up,
    ramps and the housing temperature continue across the runs of a power cycle). ``temperature_degc`` is a
    function of the time since power-on [s] giving the thermometer temperature (a chamber profile; default
    :func:`housing_temperature_degc`). ``replay`` drives the run with
    a recorded run's inputs (its plan, timestamps, table log, temperature log and power-on time; ``plan``,
    ``site`` and the other run descriptors are then taken from it).
    """
    table_df = None
    if replay is not None:
        man = replay.manifest
        plan, kind, site_obj = man.plan, man.test_kind, man.site
        run_id, start_time_utc, power_cycle_index = man.run_id, man.start_time_utc, man.power_cycle_index
        power_on_s = replay.power_on_s
        table_id = man.table_id
    else:
        if isinstance(plan, str):
            kind = test_kind or _template_kind(plan)
            plan = build_plan(plan, **(plan_kwargs or {}))
        else:
            kind = test_kind or "multiposition"
        site_obj = site
        table_id = "TT-3AX-01" if table_log else None
    lat, g, site_dict = _site_values(site_obj)
    fs = truth.sample_rate_hz
    rng = np.random.default_rng([seed, _stable_int(truth.device_id), _stable_int(run_id)])
    if replay is not None:
        t_written = np.asarray(replay.time_s, dtype=float)
        n = t_written.size
        grid = np.arange(n) / fs
        t = grid if np.array_equal(np.round(grid, 9), t_written) else t_written
        t_plan = t - replay.plan_time_shift_s if replay.plan_time_shift_s else t
    else:
        n = int(np.floor((plan.end_s + tail_s) * fs)) + 1
        t = np.arange(n) / fs
        t_written = np.round(t, 9)
        t_plan = t
    inputs, accel_inputs = sensed_inputs(plan, t_plan, lat, g, effects)
    t_on = t + power_on_s if power_on_s else t
    if replay is not None and replay.temperature is not None:
        temp = np.asarray(replay.temperature, dtype=float)
    elif temperature_degc is not None:
        temp = np.asarray(temperature_degc(t_on), dtype=float) * np.ones(n)
    else:
        temp = housing_temperature_degc(truth, t_on)  # warm-up of the housing
    ctx = SimContext(t, inputs, truth, fs, rng, temp, inputs.trajectory.step_index, t_on, accel_inputs)
    gyro = np.zeros((n, 3))
    accel = np.zeros((n, 3))
    for eff in effects:
        if getattr(type(eff), "stage", None) in ("clock", "table", "input"):
            continue  # applied to the inputs above
        gyro, accel = eff.apply(ctx, gyro, accel)
    imu = {"time_s": t_written}
    for i, ax in enumerate("xyz"):
        imu[f"gyro_{ax}"] = to_counts(gyro[:, i], truth.gyro.lsb, truth.gyro.lsb_unit, "gyro")
    for i, ax in enumerate("xyz"):
        imu[f"accel_{ax}"] = to_counts(accel[:, i], truth.accel.lsb, truth.accel.lsb_unit, "accel")
    if replay is not None:
        if replay.temperature is not None:
            imu["temperature"] = np.asarray(replay.temperature)
        if replay.counter is not None:
            imu["counter"] = np.asarray(replay.counter)
        table_df = replay.table_raw
        offset = float("nan") if table_clock_offset_s is None else float(table_clock_offset_s)
    else:
        imu["temperature"] = np.round(temp + 0.02 * rng.standard_normal(n), 3)
        imu["counter"] = np.arange(n, dtype=np.int64)
        offset = float(table_clock_offset_s if table_clock_offset_s is not None else rng.uniform(0.2, 2.0))
        if table_log:
            tt = np.arange(0.0, plan.end_s + tail_s, 1.0 / table_rate_hz)
            ttr = trajectory(plan, tt)  # the nominal (commanded) motion: table effects do not reach the log
            table_df = pd.DataFrame(
                {
                    "time_s": np.round(tt + offset, 6),  # the table clock reads true (plan) time + offset
                    "angle_deg": np.degrees(ttr.table_angle_rad) % 360.0,
                    "rate_dps": np.degrees(ttr.table_rate_radps),
                    "step_index": ttr.step_index,
                }
            )
    imu_df = pd.DataFrame(imu)
    channels = _channels(truth)
    if "temperature" not in imu:
        channels.pop("temperature")
    manifest = Manifest.model_validate(
        {
            "schema_version": SCHEMA_VERSION,
            "device": {"id": truth.device_id, "model": truth.model, "grade": truth.grade, "serial": None},
            "run_id": run_id,
            "test_kind": kind,
            "start_time_utc": start_time_utc,
            "site": site_dict,
            "sample_rate_hz": fs,
            "channels": channels,
            "plan": plan.model_dump(),
            "power_cycle_index": power_cycle_index,
            "table_id": table_id,
            "notes": "simulated by imulab " + ",".join(e.name for e in effects),
        }
    )
    params = tuple(e.to_dict() for e in effects if getattr(type(e), "family", ""))
    return SimulatedRun(manifest, imu_df, table_df, truth, offset, tuple(e.name for e in effects), params,
                        float(power_on_s), seed)


def _template_kind(name: str) -> str:
    from assets_lib.sim.plans import load_template

    return load_template(name)["test_kind"]


# ----------------------------------------------------------------------------------------------------------
# Writing runs and archives
# ----------------------------------------------------------------------------------------------------------
def write_run(run: SimulatedRun, landing: Path, fmt: str = "parquet", truth_dir: Path | None = None) -> Path:
    """Write ``<landing>/<device>/<run>/`` like a capture job: streams, manifest, then ``_COMPLETE`` last.

    The truth goes to ``truth_dir`` (default ``<landing>/_truth``), outside any run folder.
    """
    d = Path(landing) / run.manifest.device.id / run.manifest.run_id
    d.mkdir(parents=True, exist_ok=True)
    if fmt == "csv":
        run.imu_raw.to_csv(d / "imu.csv", index=False)
        if run.table_raw is not None:
            run.table_raw.to_csv(d / "table.csv", index=False)
    elif fmt == "parquet":
        run.imu_raw.to_parquet(d / "imu.parquet", index=False)
        if run.table_raw is not None:
            run.table_raw.to_parquet(d / "table.parquet", index=False)
    else:
        raise ValueError(f"format must be csv or parquet, not {fmt!r}")
    (d / "manifest.json").write_text(run.manifest.model_dump_json(indent=2) + "\n")
    tdir = Path(truth_dir) if truth_dir else Path(landing) / "_truth"
    (tdir / run.manifest.device.id).mkdir(parents=True, exist_ok=True)
    doc = {"truth": run.truth.to_json(), "table_clock_offset_s": run.table_clock_offset_s, "effects": list(run.effects)}
    if run.effect_params or run.power_on_s:  # only then: the default archive's truth files stay as they were
        doc.update(effect_params=list(run.effect_params), power_on_s=run.power_on_s, seed=run.seed)
    (tdir / run.manifest.device.id / f"{run.manifest.run_id}.json").write_text(
        json.dumps(doc, indent=1, default=float) + "\n"
    )
    (d / "_COMPLETE").write_text("")
    return d


@dataclass(frozen=True)
class TruthFile:
    """A ``_truth/<device>/<run>.json`` read back: the device truth, the effect chain that made the run, the table
    clock offset, the power-on time and (when recorded) the seed."""

    truth: DeviceTruth
    effects: tuple
    table_clock_offset_s: float
    power_on_s: float = 0.0
    seed: int | None = None


def truth_from_json(d: dict) -> DeviceTruth:
    """Inverse of ``DeviceTruth.to_json``."""

    def tup(v):
        return tuple(tup(x) for x in v) if isinstance(v, list) else v

    def triad(t: dict) -> TriadTruth:
        t = dict(t)
        t["noise"] = tuple(AllanParams(**a) for a in t["noise"])
        return TriadTruth(**{k: (v if k == "noise" else tup(v)) for k, v in t.items()})

    d = dict(d)
    d["gyro"], d["accel"] = triad(d["gyro"]), triad(d["accel"])
    return DeviceTruth(**{k: (v if k in ("gyro", "accel") else tup(v)) for k, v in d.items()})


_BASE_EFFECTS = {"error_model": ErrorModel, "allan_noise": AllanNoise, "saturation": Saturation}


def load_truth(path: str | Path) -> TruthFile:
    """Read a truth file written by :func:`write_run`; the effect chain is rebuilt (registered families from their
    parameters). A chain element that carries parameters but is not a registered family cannot be rebuilt."""
    from assets_lib.sim.effects import EFFECTS, effect_from_dict

    path = Path(path)
    doc = json.loads(path.read_text())
    params = list(doc.get("effect_params", []))
    chain = []
    for name in doc.get("effects", []):
        if name in _BASE_EFFECTS:
            chain.append(_BASE_EFFECTS[name]())
        elif name in EFFECTS:
            if not params or params[0].get("family") != name:
                raise ValueError(f"{path}: effect {name!r} listed without its parameters in 'effect_params'")
            chain.append(effect_from_dict(params.pop(0)))
        else:
            raise ValueError(f"{path}: effect {name!r} is neither a base effect {sorted(_BASE_EFFECTS)} nor a "
                             f"registered family; it cannot be rebuilt")
    return TruthFile(truth_from_json(doc["truth"]), tuple(chain), float(doc["table_clock_offset_s"]),
                     float(doc.get("power_on_s", 0.0)), doc.get("seed"))


@dataclass(frozen=True)
class ArchiveSpec:
    """What ``imulab simulate`` writes: devices (id, grade), power cycles, plans, static duration."""

    devices: tuple[tuple[str, str], ...] = (("NAV-001", "navigation"), ("TAC-002", "tactical"), ("CON-003", "consumer"))
    power_cycles: int = 3
    rate_plan: str = "quick_rate"
    position_plan: str = "quick_24_position"
    tumble_plan: str = "seed001_12_position_tumble"
    static_duration_s: float = 1200.0
    tumble_duration_scale: float = 0.5
    days_between_cycles: float = 7.0
    seed: int = 2026


def default_archive_runs(spec: ArchiveSpec = ArchiveSpec()):
    """Yield every simulated run of the archive (several devices, power-cycled repeats, every test kind)."""
    t0 = datetime(2026, 1, 5, 8, 0, tzinfo=timezone.utc)
    for dev_id, grade in spec.devices:
        base = example_device(dev_id, grade, spec.seed)
        for cycle in range(spec.power_cycles):
            day = cycle * spec.days_between_cycles
            truth = base.for_power_cycle(cycle, spec.seed, day)
            start = t0 + timedelta(days=day)
            yield simulate_run(truth, spec.rate_plan, f"pc{cycle:02d}-rate", power_cycle_index=cycle,
                               start_time_utc=start, seed=spec.seed)
            yield simulate_run(truth, spec.position_plan, f"pc{cycle:02d}-pos24", power_cycle_index=cycle,
                               start_time_utc=start + timedelta(hours=1), seed=spec.seed)
            if cycle == 0:
                yield simulate_run(truth, "static_long", f"pc{cycle:02d}-static", power_cycle_index=cycle,
                                   start_time_utc=start + timedelta(hours=2), seed=spec.seed, table_log=False,
                                   plan_kwargs={"static_duration_s": spec.static_duration_s})
                yield simulate_run(truth, spec.tumble_plan, f"pc{cycle:02d}-tumble", power_cycle_index=cycle,
                                   start_time_utc=start + timedelta(hours=3), seed=spec.seed,
                                   plan_kwargs={"duration_scale": spec.tumble_duration_scale})


def write_archive(landing: Path, spec: ArchiveSpec = ArchiveSpec(), fmt_by_grade: dict | None = None) -> list[Path]:
    """Write the default lab archive; consumer devices as CSV, others as parquet unless ``fmt_by_grade`` says."""
    fmts = fmt_by_grade or {"consumer": "csv"}
    return [write_run(r, landing, fmts.get(r.truth.grade, "parquet")) for r in default_archive_runs(spec)]
