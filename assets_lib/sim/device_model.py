"""Device models as files: convert between ``raw_schemas.device_model.DeviceModel`` and the simulator's truth and
effect chain, build a model from a device's calibration outputs, and simulate runs from a model.

- :func:`truth_for_cycle` / :func:`effects_of`: what ``simulate_run`` needs for one power cycle of a model.
- :func:`model_from_truth`: the model of a simulated device (its truths per cycle and its effects).
- :func:`model_from_calibration`: the model of a calibrated device from its coefficient tables
  (``gyro_rate_fit`` / ``accel_multiposition_fit``, docs/design.md coefficient table) and its Allan noise table
  (``allan_deviation``), grouped by power cycle; :func:`read_store_tables` reads them from the versioned store
  (``<store>/<asset>/<device>__<run>/<CURRENT version>/<table>.parquet``) with pandas.
- :func:`simulate_model_runs`: runs of a model for plans or recorded runs (replay), power cycles kept continuous
  (time since power-on runs on across the runs of a cycle).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from datetime import datetime, timedelta, timezone
from pathlib import Path

import numpy as np
import pandas as pd

from assets_lib.sim.effects import effects_from_list, sensor_chain
from assets_lib.sim.noise import AllanParams
from assets_lib.sim.simulator import DeviceTruth, TriadTruth, simulate_run
from raw_schemas.device_model import (
    AccelModel,
    AxisNoise,
    DeviceModel,
    EffectSpec,
    GyroModel,
    NoiseModel,
    Outputs,
    PowerCycleModel,
    TriadNoise,
)

AXES = ("x", "y", "z")


# ------------------------------------------------------------------------------------------------------------
# model <-> truth
# ------------------------------------------------------------------------------------------------------------
def _allan(a: AxisNoise) -> AllanParams:
    return AllanParams(a.q, a.n, a.b, a.k, a.r)


def _gm_effect(model: DeviceModel):
    """The per-triad Gauss-Markov terms as a ``noise_model`` effect (the truth's Allan terms carry the rest).
    The effect family takes one GM term per triad: the largest axis' (sigma, tau) is used."""
    from assets_lib.sim.effects import EFFECTS

    kw = {}
    for tri, nm in (("gyro", "radps"), ("accel", "mps2")):
        axes = [getattr(getattr(model.noise, tri), a) for a in AXES]
        best = max(axes, key=lambda a: a.gm_sigma)
        if best.gm_sigma > 0:
            kw[f"{tri}_gm_sigma_{nm}"] = best.gm_sigma
            kw[f"{tri}_gm_tau_s"] = best.gm_tau_s
    return EFFECTS["noise_model"](**kw) if kw else None


def truth_for_cycle(model: DeviceModel, index: int) -> DeviceTruth:
    """DeviceTruth of power cycle ``index`` (docs/design.md error model; noise from the model's Allan terms)."""
    pc = model.cycle(index)
    o = model.outputs
    g, a = pc.gyro, pc.accel
    gyro = TriadTruth(tuple(g.scale_factor), tuple(map(tuple, g.misalignment_rad)), tuple(g.bias_radps),
                      tuple(_allan(getattr(model.noise.gyro, ax)) for ax in AXES), o.gyro_lsb, o.gyro_lsb_unit,
                      o.gyro_full_scale_radps)
    accel = TriadTruth(tuple(a.scale_factor), tuple(map(tuple, a.misalignment_rad)), tuple(a.bias_mps2),
                       tuple(_allan(getattr(model.noise.accel, ax)) for ax in AXES), o.accel_lsb, o.accel_lsb_unit,
                       o.accel_full_scale_mps2, tuple(a.k2_per_mps2), tuple(map(tuple, a.cross_coupling_per_mps2)))
    d = model.device
    return DeviceTruth(d.id, d.model, d.grade, gyro, accel, tuple(map(tuple, g.g_sensitivity_radps_per_mps2)),
                       sample_rate_hz=model.sample_rate_hz, temperature_degc=model.temperature_degc)


def effects_of(model: DeviceModel) -> tuple:
    """The simulator chain of a model: base chain + Gauss-Markov noise + the model's effect families."""
    extra = list(effects_from_list([e.model_dump() for e in model.effects]))
    gm = _gm_effect(model)
    if gm is not None:
        extra.append(gm)
    return sensor_chain(extra)


def _noise_of(tri: TriadTruth) -> TriadNoise:
    return TriadNoise(**{ax: AxisNoise(q=p.q, n=p.n, b=p.b, k=p.k, r=p.r) for ax, p in zip(AXES, tri.noise)})


def model_from_truth(truths: dict[int, DeviceTruth], effects=(), provenance: dict | None = None) -> DeviceModel:
    """Device model of simulated truths (one per power cycle) and effect families (registered ones only)."""
    first = truths[min(truths)]
    cycles = []
    for i, t in sorted(truths.items()):
        cycles.append(PowerCycleModel(
            index=i,
            gyro=GyroModel(scale_factor=list(t.gyro.scale), misalignment_rad=[list(r) for r in t.gyro.misalignment_rad],
                           bias_radps=list(t.gyro.bias), g_sensitivity_radps_per_mps2=[list(r) for r in t.g_sensitivity]),
            accel=AccelModel(scale_factor=list(t.accel.scale), misalignment_rad=[list(r) for r in t.accel.misalignment_rad],
                             bias_mps2=list(t.accel.bias), k2_per_mps2=list(t.accel.k2),
                             cross_coupling_per_mps2=[list(r) for r in t.accel.kc]),
            sources=["truth"]))
    return DeviceModel(
        device={"id": first.device_id, "model": first.model, "grade": first.grade},
        sample_rate_hz=first.sample_rate_hz, temperature_degc=first.temperature_degc,
        outputs=Outputs(gyro_lsb=first.gyro.lsb, gyro_lsb_unit=first.gyro.lsb_unit, accel_lsb=first.accel.lsb,
                        accel_lsb_unit=first.accel.lsb_unit, gyro_full_scale_radps=first.gyro.full_scale,
                        accel_full_scale_mps2=first.accel.full_scale),
        noise=NoiseModel(gyro=_noise_of(first.gyro), accel=_noise_of(first.accel)),
        power_cycles=cycles,
        effects=[EffectSpec(**e.to_dict()) for e in effects if getattr(type(e), "family", "")],
        provenance=provenance or {"source": "simulator truth"},
    )


# ------------------------------------------------------------------------------------------------------------
# model from calibration outputs
# ------------------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class RunOutputs:
    """Calibration outputs of one run: its manifest (dict) and the tables found for it."""

    run_id: str
    manifest: dict
    coefficients: pd.DataFrame | None = None
    noise: pd.DataFrame | None = None


def _current(store: Path, asset: str, partition: str) -> Path | None:
    cur = store / asset / partition / "CURRENT"
    return store / asset / partition / cur.read_text().strip() if cur.is_file() else None


def read_store_tables(store: str | Path, device_id: str) -> list[RunOutputs]:
    """Every run of ``device_id`` in the versioned store with its CURRENT coefficient and noise tables."""
    store = Path(store)
    ing = store / "ingested_run"
    if not ing.is_dir():
        raise FileNotFoundError(f"{ing}: no ingested runs in store {store}")
    out = []
    for part in sorted(p.name for p in ing.iterdir() if p.name.startswith(f"{device_id}__")):
        vdir = _current(store, "ingested_run", part)
        if vdir is None or not (vdir / "manifest.json").is_file():
            continue
        man = json.loads((vdir / "manifest.json").read_text())
        coefs = [pd.read_parquet(d / "coefficients.parquet") for a in ("gyro_rate_fit", "accel_multiposition_fit")
                 if (d := _current(store, a, part)) is not None and (d / "coefficients.parquet").is_file()]
        nd = _current(store, "allan_deviation", part)
        noise = pd.read_parquet(nd / "noise.parquet") if nd is not None and (nd / "noise.parquet").is_file() else None
        out.append(RunOutputs(man["run_id"], man, pd.concat(coefs, ignore_index=True) if coefs else None, noise))
    if not out:
        raise FileNotFoundError(f"no runs of device {device_id!r} in store {store}")
    return out


def _pick(c: pd.DataFrame, sensor: str, axis: str, name: str) -> tuple[float, float] | None:
    r = c[(c.sensor == sensor) & (c.axis == axis) & (c.coefficient == name) & c.observable.astype(bool)]
    r = r[np.isfinite(r.value.astype(float))]
    if r.empty:
        return None
    w = 1.0 / np.square(r.stderr.astype(float).clip(lower=1e-300))  # inverse-variance mean over the cycle's runs
    v = float(np.sum(w * r.value) / np.sum(w))
    return v, float(1.0 / np.sqrt(np.sum(w)))


def _triad_values(c: pd.DataFrame, sensor: str, name, default: float, pairs=False):
    vals, ses = [], []
    for i, a in enumerate(AXES):
        if pairs:
            row, srow = [], []
            for j, b in enumerate(AXES):
                got = None if i == j else _pick(c, sensor, a, name.format(a=a, b=b))
                row.append(got[0] if got else default)
                srow.append(got[1] if got else None)
            vals.append(row)
            ses.append(srow)
        else:
            got = _pick(c, sensor, a, name.format(a=a))
            vals.append(got[0] if got else default)
            ses.append(got[1] if got else None)
    return vals, ses


def _se(m):
    """Stderr array (null where a term was not fitted), or None when nothing was fitted."""
    flat = [x for r in m for x in (r if isinstance(r, list) else [r])]
    return None if all(x is None for x in flat) else m


_NOISE_PARAMS = {"Q": "q", "N": "n", "B": "b", "K": "k", "R": "r"}


def _noise_from_table(noise: pd.DataFrame | None, dropped: list | None = None) -> NoiseModel:
    """Allan terms of the fit (method 'fit'); terms the record only bounds are left out (listed in ``dropped``)."""
    if noise is None or noise.empty:
        return NoiseModel()
    fit = noise[noise["method"] == "fit"]
    tri = {}
    for sensor, unit in (("gyro", "radps"), ("accel", "mps2")):
        axes = {}
        for a in AXES:
            rows = fit[fit.channel == f"{sensor}_{a}_{unit}"]
            kw = {}
            for _, r in rows.iterrows():
                if r.parameter not in _NOISE_PARAMS:
                    continue
                if not bool(r.is_upper_bound) and np.isfinite(r.value):
                    kw[_NOISE_PARAMS[r.parameter]] = abs(float(r.value))
                elif dropped is not None:
                    dropped.append(f"{r.channel}:{r.parameter} <= {float(r.ci_hi if np.isfinite(r.ci_hi) else r.value):.3g} {r.unit}")
            axes[a] = AxisNoise(**kw)
        tri[sensor] = TriadNoise(**axes)
    return NoiseModel(**tri)


def model_from_calibration(runs: list[RunOutputs], provenance: dict | None = None) -> DeviceModel:
    """Device model from calibration outputs: per power cycle, inverse-variance means over the cycle's runs of
    gyro scale factor, misalignment and bias (rate fit; bias and g-sensitivity from the static positions when
    fitted there) and accelerometer scale factor, misalignment, bias, K2 and cross-coupling (multi-position fit);
    Allan noise terms from the device's static records (upper bounds dropped). Terms no run observed stay at
    their nominal values (1, 0) with a null standard error."""
    if not runs:
        raise ValueError("no calibration outputs")
    man0 = runs[0].manifest
    ch = man0["channels"]
    by_cycle: dict[int, list[RunOutputs]] = {}
    for r in runs:
        by_cycle.setdefault(int(r.manifest.get("power_cycle_index", 0)), []).append(r)
    cycles = []
    for idx, rr in sorted(by_cycle.items()):
        tabs = [r.coefficients for r in rr if r.coefficients is not None and len(r.coefficients)]
        if not tabs:
            continue
        c = pd.concat(tabs, ignore_index=True)
        gyr = c[c.sensor == "gyro"]
        g_sf, g_sf_se = _triad_values(gyr, "gyro", "scale_factor", 1.0)
        g_m, g_m_se = _triad_values(gyr, "gyro", "misalignment_{a}{b}", 0.0, pairs=True)
        static = c[(c.sensor == "gyro") & c.coefficient.str.startswith("g_sensitivity") & c.observable.astype(bool)]
        gsrc = c[c.run_id.isin(static.run_id.unique())] if len(static) else c
        g_b, g_b_se = _triad_values(gsrc[gsrc.sensor == "gyro"], "gyro", "bias", 0.0)
        g_g, g_g_se = [], []
        for a in AXES:
            row, srow = [], []
            for b in AXES:
                got = _pick(c, "gyro", a, f"g_sensitivity_{b}")
                row.append(got[0] if got else 0.0)
                srow.append(got[1] if got else None)
            g_g.append(row)
            g_g_se.append(srow)
        acc = c[c.sensor == "accel"]
        a_sf, a_sf_se = _triad_values(acc, "accel", "scale_factor", 1.0)
        a_m, a_m_se = _triad_values(acc, "accel", "misalignment_{a}{b}", 0.0, pairs=True)
        a_b, a_b_se = _triad_values(acc, "accel", "bias", 0.0)
        a_k2, a_k2_se = _triad_values(acc, "accel", "k2", 0.0)
        a_kc, a_kc_se = _triad_values(acc, "accel", "cross_coupling_{a}{b}", 0.0, pairs=True)
        for m in (g_m, a_m, a_kc):
            for i in range(3):
                m[i][i] = 0.0
        cycles.append(PowerCycleModel(
            index=idx,
            gyro=GyroModel(scale_factor=g_sf, misalignment_rad=g_m, bias_radps=g_b, g_sensitivity_radps_per_mps2=g_g,
                           scale_factor_stderr=_se(g_sf_se), misalignment_stderr_rad=_se(g_m_se),
                           bias_stderr_radps=_se(g_b_se), g_sensitivity_stderr_radps_per_mps2=_se(g_g_se)),
            accel=AccelModel(scale_factor=a_sf, misalignment_rad=a_m, bias_mps2=a_b, k2_per_mps2=a_k2,
                             cross_coupling_per_mps2=a_kc, scale_factor_stderr=_se(a_sf_se),
                             misalignment_stderr_rad=_se(a_m_se), bias_stderr_mps2=_se(a_b_se),
                             k2_stderr_per_mps2=_se(a_k2_se), cross_coupling_stderr_per_mps2=_se(a_kc_se)),
            sources=sorted(r.run_id for r in rr if r.coefficients is not None)))
    if not cycles:
        raise ValueError("no coefficient tables among the calibration outputs")
    noise_runs = [r.noise for r in runs if r.noise is not None and len(r.noise)]
    dropped: list[str] = []
    noise = _noise_from_table(noise_runs[-1] if noise_runs else None, dropped)
    prov = dict(provenance or {"source": "calibration outputs", "runs": sorted(r.run_id for r in runs)})
    prov["noise_terms_only_bounded"] = dropped  # not simulated: the static record only bounds them
    def lsb(name: str, fam: str) -> tuple[float, str]:
        spec = ch[name]
        if spec.get("unit") == "counts":
            return float(spec["lsb"]), spec["lsb_unit"]
        return 1e-9, spec["unit"]  # a unit logging physical values: a count grid far below its noise

    glsb, gunit = lsb("gyro_x", "gyro")
    alsb, aunit = lsb("accel_x", "accel")
    return DeviceModel(
        device=man0["device"], sample_rate_hz=float(man0["sample_rate_hz"]),
        outputs=Outputs(gyro_lsb=glsb, gyro_lsb_unit=gunit, accel_lsb=alsb, accel_lsb_unit=aunit),
        noise=noise,
        power_cycles=cycles,
        provenance=prov,
    )


# ------------------------------------------------------------------------------------------------------------
# simulate from a model
# ------------------------------------------------------------------------------------------------------------
def simulate_model_runs(model: DeviceModel, plans: list[str] | None = None, *, replay_dirs=(), seed: int = 2026,
                        start_time_utc: datetime = datetime(2026, 1, 5, 8, 0, tzinfo=timezone.utc),
                        gap_s: float = 600.0, days_between_cycles: float = 7.0):
    """Yield simulated runs of ``model``: for each power cycle, each plan in turn (``gap_s`` apart, power-on at the
    first run: warm-up, ramps and housing temperature run on); or, with ``replay_dirs``, each recorded run
    replayed with the truth of its power cycle. Default plans: the default archive's (rate, 24-position;
    static and tumble in the first cycle)."""
    from assets_lib.sim.plans import build_plan, load_template
    from assets_lib.sim.replay import load_replay

    chain = effects_of(model)
    if replay_dirs:
        for d in replay_dirs:
            rep = load_replay(d)
            truth = truth_for_cycle(model, rep.manifest.power_cycle_index)
            yield simulate_run(truth, rep.manifest.plan, rep.manifest.run_id, effects=chain, seed=seed, replay=rep)
        return
    for k, pc in enumerate(sorted(model.power_cycles, key=lambda p: p.index)):
        truth = truth_for_cycle(model, pc.index)
        t0 = start_time_utc + timedelta(days=days_between_cycles * k)
        names = plans or (["quick_rate", "quick_24_position"] + (["static_long", "seed001_12_position_tumble"] if k == 0 else []))
        t_on = 0.0
        for name in names:
            kw = {"static_duration_s": 1200.0} if name == "static_long" and not plans else {}
            if name == "seed001_12_position_tumble" and not plans:
                kw = {"duration_scale": 0.5}
            kind = load_template(name)["test_kind"]
            plan = build_plan(name, **kw)
            rid = f"pc{pc.index:02d}-{name.replace('_', '-')}"
            run = simulate_run(truth, plan, rid, test_kind=kind, power_cycle_index=pc.index, seed=seed, effects=chain,
                               start_time_utc=t0 + timedelta(seconds=t_on), power_on_s=t_on,
                               table_log=kind != "static")
            yield run
            t_on += plan.end_s + gap_s


def write_model_runs(model: DeviceModel, landing: str | Path, runs=None, **kw) -> list[Path]:
    from assets_lib.sim.simulator import write_run

    fmt = "csv" if model.device.grade == "consumer" else "parquet"
    return [write_run(r, Path(landing), fmt) for r in (runs if runs is not None else simulate_model_runs(model, **kw))]

