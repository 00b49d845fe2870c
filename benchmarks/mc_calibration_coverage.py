"""Monte Carlo coverage of the calibration intervals, on the pipeline's own code path (issue 15).

Each trial draws a new device (``assets_lib.sim.simulator.example_device``; grades cycled), simulates one rate run
and one position run (raw counts, Allan noise incl. bias instability and rate random walk, saturation), ingests
them (``raw_schemas.readers.ingest_frames``), segments them (``segment_run``, the ``plateaus`` stage) and fits them
**exactly as the Dagster stages do** (``pipelines/defs/calibration.py``):

    gyro_rate_fit            fit_gyro_rate(plateaus)
    accel_multiposition_fit  fit_accel_multiposition(plateaus), fit_gyro_static(plateaus)   # no rate_fit

so what a record says is what is scored; a run failing the plateaus stage's blocking gate (fewer than
``MIN_PLATEAU_FRACTION`` usable plateaus) gets no record and is counted, not scored. Every interval-bearing row of the three coefficient tables is compared
with its truth: coverage of the printed 95 % interval (``ci95_low``..``ci95_high``) and z = (value - truth) /
stderr. Also scored, from the same result objects:

- the seed 000 full-revolution difference method (``GyroRateFit.difference``, printed in the cross-check
  table): scale factor and misalignment, normal 95 % intervals;
- ``imulab fit rate`` (``fit_rate_means``, seed 001's plateau-means fit) on each axis' sweep tabulated as a lab
  would (one mounting: the sweep's rate plateaus and the zero-rate plateaus in the same orientation; table rate,
  plateau mean and sem, plateau start/end times and the 1/f level B for the correlated-noise model, the
  command's ``--sem-column --start-column --end-column --flicker-b --flicker-b-dof`` or ``--flicker-b-ci 0 BOUND``;
  B from the device's static record when the trial has one, as the stages take it, else the run's own,
  :func:`flicker_options`): scale factor, K+, K-, asymmetry;
- the nonlinearity statistic (max |residual| / full scale, rate fit and means fit) at zero: on linear sensors
  (trials with neither asymmetry nor nonlinearity injected) the fraction of fits whose statistic stays below the
  printed 95 % noise floor is the floor's coverage (target 95 %), families ``*nonlinearity_below_floor``;
- the means fit's nonlinearity away from zero (family ``gyro:means:nonlinearity``): the digital twin's
  ``ScaleFactorNonlinearity`` (quadratic and cubic per axis, ``NONLINEARITY_SD`` of full scale) is injected into
  the rate run of one plan-cycle pair in four (no asymmetry there); its printed interval is scored against the
  same statistic of the same fit on the noise-free output (:func:`nonlinearity_rows`). In those trials the rate
  run's other rows (rate fit, difference method, means K, K+-, asymmetry, the rate fit's nonlinearity) are not
  scored: they absorb the injected curve, so their truth is not the device's coefficient;
- ``imulab fit tumble --misalignment-term`` (``fit_tumble_means``, seed 001's K0-K3 model) on the accelerometer
  axes a position plan tumbles through a full turn (the seed 001 12-position plan; every trial whose position plan
  is another one runs that plan too, :func:`tumble_trial_rows`): K0-K3, delta_o and the
  derived bias, K2/K1, K3/K1, misalignment (see :func:`tumble_rows` for the truth), with the 1/f level B as above
  (:func:`flicker_options`: the device's static record, else the run's B and its degrees of freedom);
- the table-free fits (``fit 'tablefree'``; benchmarks/mc_tablefree_coverage.py's trial on a trial-specific seed:
  a hand-placed session, static-pose detection, the Tedaldi accelerometer fit and the gyro integration fit):
  accelerometer bias, scale factor, misalignment; gyro scale factor, misalignment. That device is not graded
  (grade 'ungraded') and has no plan;
- noise terms and noise-corrected repeatability through one hook, ``score_noise(noise_trial(seed, k))`` of
  benchmarks/coverage_noise.py (see :func:`noise_rows`), on every ``--noise-every``-th trial (its static runs are
  long: 0 turns it off); skipped with a message while that module does not exist.

Truths: gyro rate-fit bias where g-sensitivity is not separable is b + G f_bar (the record says so in its note);
the static gyro bias is b. Scale-factor asymmetry eps (the digital twin's ``ScaleFactorAsymmetry``, drawn per
axis with the grade's ``ASYMMETRY_SD``) is injected into the rate run of every other pair of plan cycles, so
asymmetry is tested away from zero: K+- = K (1 +- eps/2), K = mean(K+, K-), asymmetry eps; the rate model has the
|w| term, so its bias (at zero rate) keeps its truth. Elsewhere K+ = K- = K, asymmetry 0.

Schedules: the rate plan and the position plan of trial k cycle through ``RATE_PLANS`` and ``POS_PLANS`` (the quick
plans, a 6-position subset of the 24 positions, the seeds' 8-, 12- and 24-position plans and rate sequence, their
dwell times scaled so a trial stays short), so every grade meets every plan. ``--plans quick`` keeps the quick plans.
``--budget-s``: no trial starts after that many seconds; the report says how many of the requested trials ran.

Report: coverage, mean and standard deviation of z per coefficient family (sensor:fit:coefficient, axes and
off-diagonal indices pooled), per family and grade, per family and plan, with **trial-clustered** standard
errors (estimates of one trial share its device and its noise). Targets (issue 15): coverage 0.93-0.97, |mean z|
< 0.1, z sd 0.9-1.1 for every family (and every family x grade).

Not scored here (stated, so no printed interval passes unchecked):
- rate-fit g-sensitivity: scored when observable; the rate plans here excite it too little (reported unobservable,
  its effect carried by the bias at f_bar);
- ``imulab fit tumble`` without ``--misalignment-term``: on a tumble through a full turn the cos theta term is
  orthogonal to the others, so K0-K3 keep their values, but the misalignment left in the residuals widens them
  (the fit warns: chi-square); scored with the term (below);
- the rate fit's nonlinearity away from zero (its straight line spans every axis' plateaus; only the means fit's
  statistic is scored there, see above);
- the noise terms' own definitions and what they leave out (slope reads, sin_freq): benchmarks/coverage_noise.py;
- the ``repeatability`` stage's bias and scale-factor repeatability over power-cycled rate and position runs (sample
  spread and noise-corrected spread with their intervals): benchmarks/coverage_repeatability.py.

    python benchmarks/mc_calibration_coverage.py --seed 2027 --trials 2000 --workers 2 --records --noise-every 0 --budget-s 2700
"""

from __future__ import annotations

import argparse
import re
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np
import pandas as pd

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "benchmarks"))

from coverage_stats import (  # benchmarks/ is on sys.path
    TARGET_COVERAGE,
    TARGET_MEAN_Z,
    TARGET_SD_Z,
    Z95,
    clustered,
    meets_two_sided,
    write_results,
)
from coverage_stats import fmt as _fmt

AX = "xyz"
GRADES = ("navigation", "tactical", "consumer")
#: plan name -> dwell-time scale (the seeds' full plans last hours; the scale keeps a trial at a few minutes)
RATE_PLANS = {"quick_rate": 1.0, "seed003_rate_sequence": 0.1}
POS_PLANS = {"quick_24_position": 1.0, "six_position": 1.0, "seed000_8_position": 0.05,
             "seed001_12_position_tumble": 1.0, "seed003_24_position": 0.125}
QUICK = (("quick_rate",), ("quick_24_position",))
#: 1-sigma of the injected gyro scale-factor asymmetry (K+ - K-)/K per grade (odd plan cycles; effects.md magnitudes)
ASYMMETRY_SD = {"navigation": 20e-6, "tactical": 300e-6, "consumer": 3e-3}


def _plan(name: str, scale: float):
    """A TestPlan: a library plan with its dwell times scaled, or the 6-position subset of the 24 positions
    (each sensing axis up and down: rotations 0 and 180 deg of each of the three mounting groups)."""
    from assets_lib.sim.plans import build_plan, load_template

    if name == "six_position":
        t = load_template("quick_24_position")
        steps = [s for s in t["steps"] if float(s["rotate_body"][0][1]) in (0.0, 180.0)]
        return build_plan({**t, "name": "six_position", "steps": steps,
                           "source": "imulab: 6-position subset of quick_24_position"}, duration_scale=scale)
    return build_plan(name, duration_scale=scale)


def device_truth(rf, dev, eps=None) -> dict:
    """:func:`_truth` from a simulated device's DeviceTruth (and the injected asymmetry ``eps``)."""
    g, a = dev.gyro, dev.accel
    return _truth(rf, np.asarray(g.scale), np.asarray(g.misalignment_rad), np.asarray(g.bias),
                  np.asarray(dev.g_sensitivity), np.asarray(a.scale), np.asarray(a.misalignment_rad),
                  np.asarray(a.bias), np.asarray(a.k2), np.asarray(a.kc), eps)


def _truth(rf, Kg, Eg, bg, G, Ka, Ea, ba, K2, Kc, eps=None):
    """Truth for every coefficient row of the three coefficient tables, keyed (sensor, axis, coefficient, fit)."""
    truth = {}
    for i, a in enumerate(AX):
        fbar = None if rf is None else rf.axis(a).bias_reference_force_mps2
        tb = bg[i] + (G[i] @ fbar if fbar is not None else 0.0)
        e = 0.0 if eps is None else eps[i]
        truth[("gyro", a, "scale_factor", "rate")] = Kg[i]
        truth[("gyro", a, "scale_factor_pos", "rate")] = Kg[i] * (1 + e / 2)
        truth[("gyro", a, "scale_factor_neg", "rate")] = Kg[i] * (1 - e / 2)
        truth[("gyro", a, "sf_asymmetry", "rate")] = e
        truth[("gyro", a, "bias", "rate")] = tb  # the rate model has the |w| (asymmetry) term: bias at zero rate
        truth[("gyro", a, "bias", "static")] = bg[i]
        truth[("accel", a, "scale_factor", "accel")] = Ka[i]
        truth[("accel", a, "bias", "accel")] = ba[i]
        truth[("accel", a, "k2", "accel")] = K2[i]
        for j, b in enumerate(AX):
            truth[("gyro", a, f"g_sensitivity_{b}", "static")] = G[i, j]
            truth[("gyro", a, f"g_sensitivity_{b}", "rate")] = G[i, j]
            if j != i:
                truth[("gyro", a, f"misalignment_{a}{b}", "rate")] = Eg[i, j]
                truth[("accel", a, f"misalignment_{a}{b}", "accel")] = Ea[i, j]
                truth[("accel", a, f"cross_coupling_{a}{b}", "accel")] = Kc[i, j]
    return truth


def _row(base, sensor, axis, coefficient, fit, value, stderr, lo, hi, t, **extra):
    return dict(base, sensor=sensor, axis=axis, coefficient=coefficient, fit=fit, value=value, stderr=stderr,
                truth=t, z=(value - t) / stderr, covered=bool(lo <= t <= hi), **extra)


def score(base: dict, rf, af, gs, truth: dict, means: dict | None = None) -> list[dict]:
    """Records for every observable, interval-bearing estimate (see the module docstring)."""
    recs = []
    tables = ([("rate", rf.coefficient_table())] if rf is not None else []) + (
        [("accel", af.coefficient_table()), ("static", gs.coefficient_table())] if af is not None else [])
    for tag, ct in tables:
        for r in ct.itertuples():
            key = (r.sensor, r.axis, r.coefficient, tag)
            if key not in truth or not r.observable or not np.isfinite(r.stderr) or r.stderr <= 0:
                continue
            recs.append(_row(base, r.sensor, r.axis, r.coefficient, tag, r.value, r.stderr, r.ci95_low, r.ci95_high,
                             truth[key], n_plateaus=r.n_plateaus))
    d = None if rf is None else rf.difference
    if d is not None:
        for i, a in enumerate(AX):
            items = [("scale_factor", d.scale_factor[i], d.scale_factor_stderr[i], truth[("gyro", a, "scale_factor", "rate")])]
            items += [(f"misalignment_{a}{b}", d.misalignment[i, j], d.misalignment_stderr[i, j],
                       truth[("gyro", a, f"misalignment_{a}{b}", "rate")]) for j, b in enumerate(AX) if j != i]
            for name, v, s, t in items:
                if np.isfinite(v) and np.isfinite(s) and s > 0:
                    recs.append(_row(base, "gyro", a, name, "difference", v, s, v - Z95 * s, v + Z95 * s, t))
    for a, mf in (means or {}).items():
        K = truth[("gyro", a, "scale_factor", "rate")]
        for c, t in (("scale_factor", K), ("scale_factor_pos", truth[("gyro", a, "scale_factor_pos", "rate")]),
                     ("scale_factor_neg", truth[("gyro", a, "scale_factor_neg", "rate")]),
                     ("asymmetry", 1e6 * truth[("gyro", a, "sf_asymmetry", "rate")])):
            co = mf.coefficient(c)
            if co.observable and np.isfinite(co.stderr) and co.stderr > 0:
                recs.append(_row(base, "gyro", a, c, "means", co.value, co.stderr, co.ci95_low, co.ci95_high, t))
        nl = mf.coefficient("nonlinearity")
        fl = re.search(r"noise floor \(95 %\) ([0-9.eE+-]+) ppm", nl.note)
        if nl.observable and fl and not base.get("asymmetry_injected"):
            recs.append(dict(base, sensor="gyro", axis=a, coefficient="nonlinearity_below_floor", fit="means",
                             value=nl.value, stderr=np.nan, truth=0.0, z=np.nan, covered=bool(nl.value <= float(fl.group(1)))))
    for ax in (rf.axes if rf is not None else ()):
        sw = ax.sweep
        nl = float(getattr(sw.nonlinearity, "value", sw.nonlinearity))  # a typed Coefficient or a float
        if np.isfinite(nl) and np.isfinite(sw.nonlinearity_floor) and not base.get("asymmetry_injected"):
            # a statistic with a floor: covered = below the 95 % noise floor (truth: linear sensor)
            recs.append(dict(base, sensor="gyro", axis=ax.axis, coefficient="sf_nonlinearity_below_floor",
                             fit="rate", value=nl, stderr=np.nan, truth=0.0, z=np.nan,
                             covered=bool(nl <= sw.nonlinearity_floor)))
    return recs


def trial(args: tuple) -> list[dict]:
    """One device, one rate run and one position run, fitted as the stages fit them; args (seed, k, quick[,
    noise_every[, static_s]]): the noise scoring runs on trials with k % noise_every == 0 (0: never); ``static_s``
    (see ``--static-s``) gives the device a static record whose B the fits take where it is resolved."""
    from assets_lib.calibration.multiposition import (
        fit_accel_multiposition,
        fit_gyro_static,
    )
    from assets_lib.calibration.rate_fit import fit_gyro_rate
    from assets_lib.sim.effects import sensor_chain
    from assets_lib.sim.effects.response import ScaleFactorAsymmetry
    from assets_lib.sim.simulator import DEFAULT_EFFECTS, example_device

    seed, k, quick = args[:3]
    noise_every = args[3] if len(args) > 3 else 1
    static_s = args[4] if len(args) > 4 else None  # --static-s: the device's static record (none: the run's own B)
    rate_names, pos_names = QUICK if quick else (tuple(RATE_PLANS), tuple(POS_PLANS))
    grade = GRADES[k % len(GRADES)]
    rate_plan = rate_names[(k // len(GRADES)) % len(rate_names)]
    pos_plan = pos_names[(k // len(GRADES)) % len(pos_names)]
    dev = example_device(f"MC{seed}-{k:05d}", grade, seed=seed)
    eps, nonlin = None, None
    # scale-factor asymmetry injected (digital twin effect) in every other pair of plan cycles, so that every
    # rate plan meets both cases; scale-factor nonlinearity in the other half of the cycles without asymmetry
    cycle = k // (len(GRADES) * len(RATE_PLANS))
    if cycle % 2 == 1:
        eps = ASYMMETRY_SD[grade] * np.random.default_rng([seed, k, 15]).standard_normal(3)
    elif cycle % 4 == 2:
        nonlin = nonlinearity_effect(grade, np.random.default_rng([seed, k, 16]))
    rate_fx = DEFAULT_EFFECTS
    if eps is not None:
        rate_fx = sensor_chain([ScaleFactorAsymmetry(gyro=tuple(eps))])
    elif nonlin is not None:
        rate_fx = sensor_chain([nonlin])
    plates, passed = zip(*(run_plateaus(dev, name, scales[name], seed, k, m, rate_fx if m == 0 else DEFAULT_EFFECTS)
                           for m, (name, scales) in enumerate(((rate_plan, RATE_PLANS), (pos_plan, POS_PLANS)))))
    prior = static_prior(dev, seed, k, _static_seconds(static_s, grade))  # the stages' sibling read of it
    rf = fit_gyro_rate(plates[0], noise_prior=prior) if passed[0] else None  # stage gyro_rate_fit
    af = fit_accel_multiposition(plates[1], noise_prior=prior) if passed[1] else None  # stage accel_multiposition_fit
    gs = fit_gyro_static(plates[1], noise_prior=prior) if passed[1] else None  # same stage: no rate_fit
    truth = device_truth(rf, dev, eps)
    base = {"seed": seed, "trial": k, "grade": grade, "rate_plan": rate_plan, "pos_plan": pos_plan,
            "asymmetry_injected": eps is not None, "nonlinearity_injected": nonlin is not None}
    gate = [dict(base, sensor="gate", axis="", coefficient=f"{kind}_run_passed", fit="gate", value=np.nan,
                 stderr=np.nan, truth=np.nan, z=np.nan, covered=ok) for kind, ok in zip(("rate", "position"), passed)]
    means = rate_means(plates[0], prior) if passed[0] else None
    if nonlin is None:
        rows = gate + score(base, rf, af, gs, truth, means)
    else:  # the rate run's other coefficients absorb the injected curve (truth not the device's): scored elsewhere
        rows = gate + score(base, None, af, gs, truth) + nonlinearity_rows(base, plates[0], means or {}, dev, nonlin)
    rows += tumble_trial_rows(base, plates[1] if passed[1] else None, dev, prior, seed, k)
    rows += tablefree_rows(base, seed, k)
    if noise_every > 0 and k % noise_every == 0:
        rows += noise_rows(base, seed, k)
    return rows


def run_plateaus(dev, plan: str, scale: float, seed: int, k: int, m: int, effects):
    """Run m of trial k (0 rate, 1 position, 2 the tumble run): simulated, ingested and segmented as the stages do;
    (plateaus, passed) with ``passed`` the plateaus stage's blocking gate (a run with too few usable plateaus gets
    no fit and no record)."""
    from assets_lib.calibration.segmentation import segment_run
    from assets_lib.sim.simulator import simulate_run
    from assets_lib.stages.calibration import MIN_PLATEAU_FRACTION
    from raw_schemas.readers import ingest_frames

    sim = simulate_run(dev, _plan(plan, scale), f"mc{seed}-{k}-{m}", seed=seed * 1_000_000 + 10 * k + m, effects=effects)
    ing = ingest_frames(sim.manifest, sim.imu_raw, sim.table_raw)
    p = segment_run(ing.manifest, ing.imu, ing.table).plateaus
    return p, float((~p["flagged"].astype(bool)).mean()) >= MIN_PLATEAU_FRACTION


#: the position plan whose accelerometer axes tumble through a full turn (``imulab fit tumble``)
TUMBLE_PLAN = "seed001_12_position_tumble"


def tumble_trial_rows(base: dict, pos_plateaus, dev, prior, seed: int, k: int) -> list[dict]:
    """The tumble fit's rows of trial k: on its position run when that is the tumble plan, else on a run of the
    tumble plan of its own (same device and static record, its own noise seed, the plateaus stage's gate), so that
    every trial scores the tumble fit (one plan in five gave 266 estimates per family and grade: a coverage
    standard error of 0.013 against the 0.93-0.97 band)."""
    from assets_lib.sim.simulator import DEFAULT_EFFECTS

    if base["pos_plan"] == TUMBLE_PLAN:
        return [] if pos_plateaus is None else tumble_rows(base, pos_plateaus, dev, prior)
    base = dict(base, pos_plan=TUMBLE_PLAN)
    p, ok = run_plateaus(dev, TUMBLE_PLAN, POS_PLANS[TUMBLE_PLAN], seed, k, 2, DEFAULT_EFFECTS)
    gate = [dict(base, sensor="gate", axis="", coefficient="tumble_run_passed", fit="gate", value=np.nan,
                 stderr=np.nan, truth=np.nan, z=np.nan, covered=ok)]
    return gate + (tumble_rows(base, p, dev, prior) if ok else [])


def _static_seconds(static_s, grade: str) -> float:
    """Seconds of the trial device's static record: ``static_s`` a number for every grade or {grade: seconds}."""
    if not static_s:
        return 0.0
    return float(static_s.get(grade, 0.0)) if isinstance(static_s, dict) else float(static_s)


def parse_static(text: str | None):
    """``--static-s``: '0' (no static record), '10800' (every grade) or 'navigation=28800,tactical=10800,...'."""
    if not text:
        return None
    if "=" not in text:
        return float(text)
    out = {}
    for part in text.split(","):
        g, v = part.split("=")
        if g.strip() not in GRADES:
            raise SystemExit(f"--static-s: grade {g.strip()!r} is not one of {GRADES}")
        out[g.strip()] = float(v)
    return out


def static_prior(dev, seed: int, k: int, seconds: float):
    """The device's static record of ``seconds`` (none at 0) through the ``allan_deviation`` stage's computation and
    the prior the calibration stages build from it (``assets_lib.calibration.noise_prior.device_noise_prior``, what
    ``gyro_rate_fit`` and ``accel_multiposition_fit`` read as siblings); None without a record."""
    if not seconds > 0:
        return None
    from assets_lib.calibration.noise_prior import device_noise_prior
    from assets_lib.sim.simulator import simulate_run
    from assets_lib.stages.noise import allan_tables
    from raw_schemas.readers import ingest_frames

    sim = simulate_run(dev, "static_long", f"mc{seed}-{k}-static", seed=seed * 1_000_000 + 10 * k + 5, table_log=False,
                       plan_kwargs={"static_duration_s": float(seconds)})
    ing = ingest_frames(sim.manifest, sim.imu_raw, sim.table_raw)
    tables = allan_tables(f"{dev.device_id}__{ing.manifest.run_id}", ing.imu,
                          {"sample_rate_hz": ing.manifest.sample_rate_hz, "run_id": ing.manifest.run_id})[0]
    return device_noise_prior([tables["noise"]], [tables["static_terms"]], [ing.manifest.run_id])


def nonlinearity_effect(grade: str, rng: np.random.Generator):
    """The digital twin's ``ScaleFactorNonlinearity`` (polynomial form: quadratic and cubic per axis, each drawn
    with the grade's ``NONLINEARITY_SD`` of full scale, full scale ``NONLINEARITY_FS_DPS``)."""
    from assets_lib.sim.effects.response import ScaleFactorNonlinearity

    sd = NONLINEARITY_SD[grade]
    return ScaleFactorNonlinearity(sensor="gyro", full_scale=float(np.radians(NONLINEARITY_FS_DPS)),
                                   quadratic=tuple(sd * rng.standard_normal(3)), cubic=tuple(sd * rng.standard_normal(3)))


def nonlinearity_rows(base: dict, p: pd.DataFrame, means: dict, dev, nonlin) -> list[dict]:
    """The means fit's nonlinearity (max |residual| / full scale, with its interval) on a sensor with injected
    scale-factor nonlinearity. Truth: the same statistic of the same fit (same plateaus, sems, times and the fit's
    1/f level tau^2: the straight line it draws)
    applied to the noise-free output at the plateaus' sensed rates x = diag(K)(I + E) omega_ref (the effect's own
    input), x + deviation(x), less the constant bias (absorbed by the fit's zero output)."""
    from assets_lib.calibration.means_fit import fit_rate_means

    om = p[[f"omega_ref_{a}_radps" for a in AX]].to_numpy(float)
    ea = p[[f"omega_earth_{a}_radps" for a in AX]].to_numpy(float)
    sensed = om @ np.asarray(dev.gyro.matrix()).T
    true_y = sensed + nonlin.deviation(sensed)  # noise-free output less the constant bias
    rows_of = means_rows(p)
    out = []
    for a, mf in means.items():
        i = AX.index(a)
        rows = rows_of[a]
        used = mf.fit.used
        co = mf.coefficient("nonlinearity")
        if not (co.observable and np.isfinite(co.stderr) and co.stderr > 0):
            continue
        q = p.loc[rows]
        # the fit's own line: its weights (sems) and its 1/f level (tau^2 = B^2 / pi, REML'd or the run's)
        tau2, ts = mf.fit.flicker_tau2, mf.fit.sem_flicker_tau2
        times = (q["t_start_s"].to_numpy(float)[used], q["t_end_s"].to_numpy(float)[used]) if tau2 > 0 else None
        tru = fit_rate_means((om - ea)[rows, i][used], true_y[rows, i][used],
                             q[f"gyro_{a}_radps_sem"].to_numpy(float)[used], rate_unit="rad/s", output_unit="rad/s",
                             times=times, flicker_b=float(np.sqrt(np.pi * tau2)) if tau2 > 0 else None,
                             sem_flicker_b=None if ts is None else float(np.sqrt(np.pi * ts)), exclusion="none")
        t = tru.coefficient("nonlinearity").value
        out.append(_row(base, "gyro", a, "nonlinearity", "means", co.value, co.stderr, co.ci95_low, co.ci95_high, t))
    return out


#: 1-sigma of the injected gyro scale-factor nonlinearity coefficients (quadratic, cubic; fraction of full scale
#: NONLINEARITY_FS_DPS) per grade, in the cycles without asymmetry (effects.md magnitudes: FOG ~10 ppm, tactical
#: MEMS ~100-500 ppm, consumer MEMS 0.1-0.5 %)
NONLINEARITY_SD = {"navigation": 20e-6, "tactical": 300e-6, "consumer": 2e-3}
NONLINEARITY_FS_DPS = 400.0


#: default --noise-every: one trial in ten also runs the noise scoring (~8 s of static runs and Allan fits, as much as
#: the calibration trial itself; every trial would halve the calibration trials a time budget buys)
NOISE_EVERY = 10


def _noise_module():
    """benchmarks/coverage_noise.py (the noise part of issue 15), or None while it does not exist."""
    try:
        import coverage_noise  # benchmarks/ is on sys.path when this script runs
    except ModuleNotFoundError as e:
        if e.name != "coverage_noise":
            raise
        return None
    return coverage_noise


def noise_rows(base: dict, seed: int, k: int) -> list[dict]:
    """The noise intervals through benchmarks/coverage_noise.py's hook, ``score_noise(noise_trial(seed, k))``:
    a device of the trial's grade, static runs through the allan_deviation and repeatability stages' own
    computations (noise terms Q, N, B, K, R, the Markov term, gyro and accelerometer; noise-corrected turn-on bias
    repeatability), scored there (z on the log scale for a noise term; upper bounds: coverage only). Their rows
    become this script's: fit 'noise', coefficient = the family after the sensor (':' -> '_', e.g. N_markov_fit,
    K_bound), axis = channel. [] when that module is absent."""
    mod = _noise_module()
    if mod is None:
        return []
    out = []
    for r in mod.score_noise(mod.noise_trial(seed, k, grade=base["grade"])):
        sensor, coef = str(r["family"]).split(":", 1)
        out.append(dict(base, sensor=sensor, axis=str(r.get("channel", "")), coefficient=coef.replace(":", "_"),
                        fit="noise", value=float(r.get("estimate", np.nan)), stderr=np.nan, truth=float(r["truth"]),
                        z=float(r["z"]), covered=bool(r["covered"]), noise_plan=r.get("plan"), noise_run=r.get("run")))
    return out


#: coefficients of ``imulab fit tumble --misalignment-term`` that carry an interval
TUMBLE_COEFFICIENTS = ("K0", "K1", "K2", "K3", "delta_o_term", "bias", "K2_per_K1", "K3_per_K1", "misalignment")


def tumble_rows(base: dict, p: pd.DataFrame, dev, prior=None) -> list[dict]:
    """``imulab fit tumble --misalignment-term`` (fit_tumble_means, [SEED001] eq. 5-7) on every accelerometer axis
    that a position plan tumbles through a full turn in one plane (the seed 001 plan: x and z about y): angle
    theta with f_i = g sin theta, plateau mean, sem, times and the 1/f level. Truth: the same model fitted to
    the noise-free error model (docs/design.md: M f + b + K2 f^2 + f_i Kc_i.f) at the plateaus' reference forces;
    exact, because on one plane every quadratic in (sin, cos) lies in the span of 1, sin, cos, sin^2, sin cos.
    The 1/f level: :func:`flicker_options` (the device's static record, else the run's own)."""
    from assets_lib.calibration.means_fit import fit_tumble_means

    ok = ~p["flagged"].astype(bool).to_numpy() & (p["kind"].to_numpy() == "static")
    f = p[[f"f_ref_{a}_mps2" for a in AX]].to_numpy(float)[ok]
    q = p[ok]
    if len(q) < 8:
        return []
    g = float(np.median(np.linalg.norm(f, axis=1)))
    a_t = dev.accel
    M = np.asarray(a_t.matrix())
    det = f @ M.T + np.asarray(a_t.bias) + np.asarray(a_t.k2) * f**2 + f * (f @ np.asarray(a_t.kc).T)
    out = []
    for j in range(3):  # tumble axis j: f_j ~ 0 on every plateau, the other two sweep a full circle
        i, m = [c for c in range(3) if c != j]
        if np.max(np.abs(f[:, j])) > 0.02 * g:
            continue
        for ax, other in ((i, m), (m, i)):
            th = np.degrees(np.arctan2(f[:, ax], f[:, other]))
            if np.ptp(np.sort(np.mod(th, 360.0))) < 270.0 or len(np.unique(np.round(th, 3))) < 6:
                continue  # not a full turn
            a = AX[ax]
            times = (q["t_start_s"].to_numpy(float), q["t_end_s"].to_numpy(float))
            fit = fit_tumble_means(th, q[f"accel_{a}_mps2_mean"].to_numpy(float), q[f"accel_{a}_mps2_sem"].to_numpy(float),
                                   output_unit="m/s^2", misalignment_term=True, times=times,
                                   **flicker_options(p, f"accel_{a}_mps2", prior))
            tru = fit_tumble_means(th, det[:, ax], None, output_unit="m/s^2", misalignment_term=True, exclusion="none")
            for c in TUMBLE_COEFFICIENTS:
                co, ct = fit.coefficient(c), tru.coefficient(c)
                if co.observable and ct.observable and np.isfinite(co.stderr) and co.stderr > 0:
                    out.append(_row(base, "accel", a, c, "tumble", co.value, co.stderr, co.ci95_low, co.ci95_high,
                                    ct.value))
    return out


def tablefree_rows(base: dict, seed: int, k: int) -> list[dict]:
    """The table-free fits (benchmarks/mc_tablefree_coverage.py's trial: a hand-placed session, static-pose
    detection, the Tedaldi accelerometer fit and the gyro integration fit) on a trial-specific seed; fit
    'tablefree', coefficients renamed to the families used here (t_ij -> misalignment_ij, k_a -> scale_factor_a,
    b_a -> bias_a). The hand-session device is not graded: grade 'ungraded'."""
    import mc_tablefree_coverage as tf

    out = []
    for name, v, s, t, hit in tf.trial(seed * 1_000_003 + k + 7):
        sensor, c = name.split("_", 1)
        if c.startswith("t") and c[1:].isdigit():
            coef, axis = f"misalignment_{AX[int(c[1])]}{AX[int(c[2])]}", AX[int(c[1])]
        else:
            kind, axis = c.split("_")
            coef = {"k": "scale_factor", "b": "bias"}[kind] + f"_{axis}"
        out.append(dict(base, grade="ungraded", sensor=sensor, axis=axis, coefficient=coef, fit="tablefree", value=v,
                        stderr=s, truth=t, z=(v - t) / s, covered=bool(hit)))
    return out


def means_rows(p: pd.DataFrame) -> dict[str, np.ndarray]:
    """Per axis, the plateaus a lab tabulates for ``imulab fit rate``: the axis' sweep in one mounting."""
    from assets_lib.calibration.rate_fit import on_axis_rows

    om = p[[f"omega_ref_{a}_radps" for a in AX]].to_numpy(float)
    fr = p[[f"f_ref_{a}_mps2" for a in AX]].to_numpy(float)
    ok = ~p["flagged"].astype(bool).to_numpy()
    rate = p["kind"].to_numpy() == "rate"
    out = {}
    for i, a in enumerate(AX):
        rows = on_axis_rows(om, i) & ok
        # one mounting, as a lab tabulates a sweep: the zero-rate plateaus of the other orientations carry a
        # different g-sensitivity bias G f, which the means model (no force columns) would read as asymmetry
        if (rows & rate).any():
            f0 = np.median(fr[rows & rate], axis=0)
            rows &= np.linalg.norm(fr - f0, axis=1) < 1.0
        out[a] = rows
    return out


def flicker_options(p: pd.DataFrame, channel: str, prior=None) -> dict:
    """The 1/f level a lab passes to ``imulab fit`` for ``channel``: the device's static record as ``imulab allan``
    prints it when it has one (``--flicker-b B --flicker-b-ci LO HI``, or ``--flicker-b-ci 0 BOUND`` where the record
    only bounds B), as the pipeline's stages read it; else the run's own (segmentation's ``*_flicker_b``, with its
    degrees of freedom); and ``--sem-flicker-b``, the level the table's sems contain (``*_sem_flicker_b``)."""
    from assets_lib.calibration.fit_core import flicker_b, flicker_b_dof, flicker_dof_from_interval, sem_flicker_tau2

    c = None if prior is None else prior.get(channel)
    ts = None if p is None else sem_flicker_tau2(p, channel)  # the table's *_sem_flicker_b (None: none, or not a level)
    sem_b = {} if ts is None else {"sem_flicker_b": float(np.sqrt(np.pi * ts))}
    if c is not None and c.is_upper_bound:
        return {"flicker_b_max": c.bound, **sem_b}
    if c is not None:
        return {"flicker_b": c.b, "flicker_b_dof": flicker_dof_from_interval(c.b, c.ci_lo, c.ci_hi, c.ci_level), **sem_b}
    return {"flicker_b": flicker_b(p, channel), "flicker_b_dof": flicker_b_dof(p, channel), **sem_b}


def rate_means(p: pd.DataFrame, prior=None) -> dict:
    """``imulab fit rate`` (fit_rate_means) on each axis' sweep as a lab would tabulate it: table rate about the
    axis, plateau mean and sem of that axis, plateau start/end times and the 1/f level B for the correlated-noise
    model (:func:`flicker_options`: the device's static record, else the run's own)."""
    from assets_lib.calibration.means_fit import fit_rate_means

    om = p[[f"omega_ref_{a}_radps" for a in AX]].to_numpy(float)
    ea = p[[f"omega_earth_{a}_radps" for a in AX]].to_numpy(float)
    out = {}
    for i, (a, rows) in enumerate(means_rows(p).items()):
        if rows.sum() >= 5:
            times = None
            if "t_start_s" in p and "t_end_s" in p:
                times = (p.loc[rows, "t_start_s"].to_numpy(float), p.loc[rows, "t_end_s"].to_numpy(float))
            out[a] = fit_rate_means((om - ea)[rows, i], p.loc[rows, f"gyro_{a}_radps_mean"].to_numpy(float),
                                    p.loc[rows, f"gyro_{a}_radps_sem"].to_numpy(float), rate_unit="rad/s",
                                    output_unit="rad/s", times=times, **flicker_options(p, f"gyro_{a}_radps", prior))
    return out


def family(df: pd.DataFrame) -> pd.Series:
    """sensor:fit:coefficient with the axis / axis-pair suffix removed (misalignment_xy -> misalignment)."""
    return df["sensor"] + ":" + df["fit"] + ":" + df["coefficient"].str.replace(r"_[xyz]{1,2}$", "", regex=True)


def summarize(df: pd.DataFrame) -> dict[str, pd.DataFrame]:
    gate = df[df["fit"] == "gate"]
    df = df[df["fit"] != "gate"]
    df = df.assign(family=family(df))
    tabs = {}
    for name, keys in (("family", ["family"]), ("family_grade", ["family", "grade"]),
                       ("family_rate_plan", ["family", "rate_plan"]), ("family_pos_plan", ["family", "pos_plan"]),
                       ("grade", ["grade"]), ("axis", ["family", "axis"])):
        rows = [dict(zip(keys, k if isinstance(k, tuple) else (k,)), **clustered(d)) for k, d in df.groupby(keys)]
        t = pd.DataFrame(rows)
        if name.startswith("family_"):  # a rate-fit family depends on the rate plan only, and so on
            plan = name.removeprefix("family_")
            if plan in ("rate_plan", "pos_plan"):
                keep = t["family"].str.contains(":rate:|:difference:|:means:") == (plan == "rate_plan")  # tumble: pos
                t = t[keep & ~t["family"].str.contains(":tablefree:|:noise:")]  # hand sessions, static runs: no plan
        t["meets"] = [meets_two_sided(r) for r in t.to_dict("records")]
        tabs[name] = t.reset_index(drop=True)
    gate = gate.assign(plan=np.where(gate["coefficient"].str.startswith("rate"), gate["rate_plan"], gate["pos_plan"]))
    rows = [{"run": c.split("_")[0], "plan": plan, "grade": g, "runs": len(d), "passed": int(d["covered"].sum())}
            for (c, plan, g), d in gate.groupby(["coefficient", "plan", "grade"])]
    tabs["gate"] = pd.DataFrame(rows, columns=["run", "plan", "grade", "runs", "passed"])
    return tabs


def markdown(tabs: dict, meta: dict) -> str:
    fam = tabs["family"]
    lines = [
        "# Calibration coverage (Monte Carlo, pipeline code path)",
        "",
        (f"{meta['trials']} trials (seed {meta['seed']}, plans {meta['plans']}), {int(fam['n'].sum())} estimates, "
        f"{meta['seconds']} s. Generated by `{meta['command']}`."
         + (f" Stopped by the time budget after {meta['trials']} of {meta['trials_requested']} requested trials."
            if meta.get("trials_requested", meta["trials"]) > meta["trials"] else "")
         + ("" if meta.get("noise_scored") else " Noise terms not scored (benchmarks/coverage_noise.py absent or "
                                                "--noise-every 0).")),
        "",
        (f"Targets per family: 95 % coverage {TARGET_COVERAGE[0]:.2f}-{TARGET_COVERAGE[1]:.2f}, |mean z| < "
        f"{TARGET_MEAN_Z}, z sd {TARGET_SD_Z[0]}-{TARGET_SD_Z[1]}. ± are trial-clustered standard errors. "
        f"Families meeting all targets: **{int(fam['meets'].sum())} of {len(fam)}**; family x grade cells: "
        f"{int(tabs['family_grade']['meets'].sum())} of {len(tabs['family_grade'])}."),
        "",
        "| family | n | coverage | mean z | sd z | meets |",
        "|---|---:|---:|---:|---:|---|",
    ]
    for r in fam.itertuples():
        lines.append(f"| {r.family} | {r.n} | {_fmt(r.coverage, r.coverage_se)} | {_fmt(r.mean_z, r.mean_z_se, '{:+.3f}')} "
                     f"| {_fmt(r.sd_z, r.sd_z_se)} | {'yes' if r.meets else 'no'} |")
    lines += ["", "By grade (all families pooled):", "", "| grade | n | coverage | mean z | sd z |", "|---|---:|---:|---:|---:|"]
    for r in tabs["grade"].itertuples():
        lines.append(f"| {r.grade} | {r.n} | {_fmt(r.coverage, r.coverage_se)} | {_fmt(r.mean_z, r.mean_z_se, '{:+.3f}')} "
                     f"| {_fmt(r.sd_z, r.sd_z_se)} |")
    for name, col in (("family_grade", "grade"), ("family_rate_plan", "rate_plan"), ("family_pos_plan", "pos_plan")):
        t = tabs[name]
        lines += ["", f"Per family and {col.replace('_', ' ')}:", "",
                  f"| family | {col} | n | coverage | mean z | sd z | meets |", "|---|---|---:|---:|---:|---:|---|"]
        for r in t.to_dict("records"):
            lines.append(f"| {r['family']} | {r[col]} | {r['n']} | {_fmt(r['coverage'], r['coverage_se'])} | "
                         f"{_fmt(r['mean_z'], r['mean_z_se'], '{:+.3f}')} | {_fmt(r['sd_z'], r['sd_z_se'])} | "
                         f"{'yes' if r['meets'] else 'no'} |")
    g = tabs["gate"]
    bad = g[g["passed"] < g["runs"]]
    lines += ["", "Runs failing the plateaus stage's blocking gate (too few usable plateaus: no record, not scored): "
              f"{int((g['runs'] - g['passed']).sum())} of {int(g['runs'].sum())}"
              + ("; " + ", ".join(f"{r.plan} {r.grade} {r.runs - r.passed}/{r.runs}" for r in bad.itertuples())
                 if len(bad) else "") + "."]
    lines += ["", ("Not scored here (bounds or statistics without coverage, or not yet in this benchmark): see the "
              "docstring of benchmarks/mc_calibration_coverage.py.")]
    return "\n".join(lines) + "\n"


def run(seed: int, trials: int, workers: int = 1, quick: bool = False, budget_s: float | None = None,
        noise_every: int = NOISE_EVERY, static_s=None) -> pd.DataFrame:
    """Trials 0..trials-1; with ``budget_s`` no trial starts after that many seconds (the trials done are scored:
    a shared machine's honest partial run instead of a killed one)."""
    t0 = time.time()
    jobs = [(seed, k, quick, noise_every, static_s) for k in range(trials)]
    recs: list[dict] = []

    def in_time():
        return budget_s is None or time.time() - t0 < budget_s

    if workers > 1:
        from concurrent.futures import FIRST_COMPLETED, wait

        with ProcessPoolExecutor(workers) as ex:
            it = iter(jobs)
            pending = set()
            for j in it:
                pending.add(ex.submit(trial, j))
                if len(pending) >= workers:
                    break
            while pending:
                done, pending = wait(pending, return_when=FIRST_COMPLETED)
                for f in done:
                    recs.extend(f.result())
                    j = next(it, None) if in_time() else None
                    if j is not None:
                        pending.add(ex.submit(trial, j))
    else:
        for j in jobs:
            if not in_time():
                break
            recs.extend(trial(j))
    return pd.DataFrame(recs)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seed", type=int, default=0, help="base seed (devices, noise); use new seeds for acceptance")
    ap.add_argument("--trials", type=int, default=200)
    ap.add_argument("--workers", type=int, default=1)
    ap.add_argument("--plans", choices=("all", "quick"), default="all")
    ap.add_argument("--out", type=Path, default=REPO / "benchmarks" / "results" / "calibration_coverage")
    ap.add_argument("--records", action="store_true", help="also write every estimate to <out>.records.csv")
    ap.add_argument("--budget-s", type=float, default=None,
                    help="start no trial after this many seconds; the trials done are scored and reported")
    ap.add_argument("--noise-every", type=int, default=NOISE_EVERY,
                    help="score the noise intervals (benchmarks/coverage_noise.py) on every N-th trial; 0: never "
                         f"(default {NOISE_EVERY}: a noise trial costs about as much as a calibration trial, and the "
                         "noise families have their own acceptance run, benchmarks/coverage_noise.py)")
    ap.add_argument("--static-s", default=None,
                    help="each trial's device also has a static record of this many seconds ('10800', or per grade "
                         "'navigation=28800,tactical=10800,consumer=3600'), whose allan_deviation output the fits "
                         "take as the device's B (the stages' sibling read); default none: the run's own B")
    args = ap.parse_args(argv)
    static_s = parse_static(args.static_s)
    t0 = time.time()
    noise_on = args.noise_every > 0 and _noise_module() is not None
    if _noise_module() is None:
        print("benchmarks/coverage_noise.py (score_noise) not found: noise terms not scored in this run", file=sys.stderr)
    df = run(args.seed, args.trials, args.workers, args.plans == "quick", args.budget_s, args.noise_every, static_s)
    tabs = summarize(df)
    done = int(df["trial"].nunique()) if len(df) else 0
    cmd = (f"python benchmarks/mc_calibration_coverage.py --seed {args.seed} --trials {args.trials} "
           f"--workers {args.workers} --plans {args.plans}"
           + (f" --budget-s {args.budget_s:g}" if args.budget_s is not None else "")
           + (f" --noise-every {args.noise_every}" if args.noise_every != NOISE_EVERY else "")
           + (f" --static-s {args.static_s}" if args.static_s else ""))
    meta = {"seed": args.seed, "trials": done, "trials_requested": args.trials, "plans": args.plans,
            "seconds": round(time.time() - t0, 1), "command": cmd, "noise_scored": noise_on}
    text = markdown(tabs, meta)
    write_results(args.out, tabs, meta, text, df if args.records else None)
    print(text)
    return 0 if bool(tabs["family"]["meets"].all()) else 1


if __name__ == "__main__":
    raise SystemExit(main())
