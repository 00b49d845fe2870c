"""The withheld-effect benchmark's case list and scorer (benchmarks/withheld_effects.py), without any diagnosis:
the single-effect device ids stay put when pair cases are appended, and a pair device's truth and scoring work on
fabricated reports (the pair figures, and the single-family figures left as they were)."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "benchmarks"))

import withheld_effects as wh

RUNS = ["pc00-rate", "pc00-pos24", "pc00-static", "pc01-rate", "pc01-pos24", "pc02-rate", "pc02-pos24"]

#: the quick tier's ids and kinds before the pair cases (session 6, commit c4ad61d): results of earlier runs are
#: keyed by these ids
QUICK_BEFORE_PAIRS = (
    ["none"] * 10
    + ["temperature_bias", "temperature_scale_factor", "warmup_bias", "bias_ramp", "g_sensitivity",
       "scale_factor_nonlinearity", "scale_factor_asymmetry", "lever_arm", "table_rate_error", "table_wobble",
       "timebase_error"]
    + ["temperature_bias", "temperature_scale_factor", "warmup_bias", "bias_ramp", "g_sensitivity"]
    + ["temperature_bias"] * 2 + ["noise_gm"] * 3 + ["omega_abs_omega", "vibration", "bias_step", "latency"])
CATEGORY_TAGS = ["NULL"] * 10 + ["FAMI"] * 16 + ["CONF"] * 2 + ["NOIS"] * 3 + ["OUTS"] * 3 + ["NOT_"]


def test_single_effect_ids_unchanged_and_pairs_appended():
    quick = wh.cases("quick")
    assert [(c["device_id"], c["kind"]) for c in quick[:35]] == \
        [(f"WH-{i:03d}-{tag}", k) for i, (tag, k) in enumerate(zip(CATEGORY_TAGS, QUICK_BEFORE_PAIRS))]
    pairs = [c for c in quick if c["category"] == "pair"]
    assert [c["device_id"] for c in pairs] == ["WH-035-PAIR", "WH-036-PAIR"] and quick[35:] == pairs
    full = wh.cases("full")
    fp = [c for c in full if c["category"] == "pair"]
    assert len(fp) == 6 and full[-6:] == fp and {c["grade"] for c in fp} > {"tactical"}
    for c in fp:  # two different families, each a library family with its clear magnitude
        assert len(set(c["families"])) == 2 and c["family"] == c["families"][0]
        assert all(m > 0 for m in c["magnitudes"])


def _truth(root: Path, c: dict) -> dict:
    t = wh.case_truth(c, RUNS)
    (root / "truth").mkdir(parents=True, exist_ok=True)
    (root / "truth" / f"{c['device_id']}.json").write_text(json.dumps(t, default=float))
    return t


def _report(root: Path, dev: str, verdict: str, effects: list[dict], where=None, shrink=0.97) -> None:
    (root / "reports").mkdir(parents=True, exist_ok=True)
    r = {"device_id": dev, "verdict": verdict, "effects": effects, "ambiguity": [[e["family"]] for e in effects],
         "where": where or [], "shrink": {"ratio": shrink}}
    (root / "reports" / f"{dev}.json").write_text(json.dumps(r))


def _eff(family, channel, mag, lo, hi):
    return {"family": family, "channel": channel, "magnitude": mag, "ci_lo": lo, "ci_hi": hi}


def test_pair_truth_is_the_union_and_pairs_score_apart(tmp_path):
    quick = {c["device_id"]: c for c in wh.cases("quick")}
    p1, p2 = quick["WH-035-PAIR"], quick["WH-036-PAIR"]
    t1 = _truth(tmp_path, p1)
    t2 = _truth(tmp_path, p2)
    # temperature bias (gyro_z, every run) + lever arm (accelerometers, rate runs): the union
    assert t1["families"] == ["temperature_bias", "lever_arm"] and t1["channels"] == ["gyro_z", None]
    assert t1["affected_runs"] == RUNS and t1["sensor"] == ["accel", "gyro"]
    assert t1["library_forms"] == [False, True]  # the thermal lag is not the library's form
    # g-sensitivity (gyro_x, position runs) + asymmetry (gyro_y, rate runs): every run but the static one
    assert t2["affected_runs"] == [r for r in RUNS if r != "pc00-static"] and t2["sensor"] == "gyro"
    lever = t1["magnitudes"][1]
    asym = t2["magnitudes"][1]
    # pair 1: both accepted, lever-arm interval covers; pair 2: only the asymmetry, interval misses, plus a
    # spurious bias ramp
    _report(tmp_path, p1["device_id"], "explained",
            [_eff("lever_arm", None, lever, 0.99 * lever, 1.01 * lever),
             _eff("temperature_bias", "gyro_z", 1e-5, 0.5e-5, 1.5e-5)],  # not library form: not in coverage
            where=[{"view": "accel_rate_run_centripetal_x", "run_id": None, "channel": "accel_x", "z": 40.0}])
    _report(tmp_path, p2["device_id"], "partly_explained",
            [_eff("scale_factor_asymmetry", "gyro_y", 2 * asym, 1.5 * asym, 2.5 * asym),
             _eff("bias_ramp", "gyro_z", 1e-8, 0.5e-8, 1.5e-8)],
            where=[{"view": "residual_vs_abs_rate", "run_id": "pc00-static", "channel": "gyro_y", "z": 30.0}])
    # beside them a null device with a false alarm and a clear single-family device, as before pairs
    _truth(tmp_path, quick["WH-000-NULL"])
    _report(tmp_path, "WH-000-NULL", "explained", [_eff("bias_ramp", "gyro_x", 1e-8, 0.5e-8, 1.5e-8)])
    t16 = _truth(tmp_path, quick["WH-016-FAMI"])
    _report(tmp_path, "WH-016-FAMI", "explained",
            [_eff("scale_factor_asymmetry", "gyro_y", t16["magnitude"], 0.9 * t16["magnitude"], 1.1 * t16["magnitude"])],
            where=[{"view": "residual_vs_abs_rate", "run_id": "pc01-rate", "channel": "gyro_y", "z": 50.0}])

    s = wh.score(tmp_path)
    assert s["pair_both_accepted"].startswith("1/2 ") and s["pair_at_least_one"].startswith("2/2 ")
    assert s["pair_detected"].startswith("2/2 ") and s["pair_spurious_effect"].startswith("1/2 ")
    # library-form intervals of the found pair families: lever arm covers, asymmetry misses (g^2 not found)
    assert s["pair_magnitude_ci_coverage_library_form"].startswith("1/2 ")
    assert s["magnitude_ci_coverage_library_form"].startswith("2/3 ")  # + WH-016's covering interval
    # the pair's top view on the static run is off its affected runs: localised 1 of 2
    assert s["pair_localisation"].startswith("1/2 ")
    # single-family figures see no pair device
    assert s["top1_clear"].startswith("1/1 ") and s["localisation"].startswith("1/1 ")
    assert s["null_false_positive"].startswith("1/1 ")
    assert s["top1_per_family"] == {"scale_factor_asymmetry": "1/1"}
    assert s["median_shrink_correct"] == pytest.approx(0.97) and s["median_shrink_pair_both"] == pytest.approx(0.97)
    assert s["wrong_family_accepted"].startswith("1/3 ")  # pair 2's bias ramp
    rows = {r["device"]: r for r in s["rows"]}
    assert rows["WH-036-PAIR"]["found"] == [False, True] and rows["WH-036-PAIR"]["spurious"] == ["bias_ramp/gyro_z"]


def test_reports_without_pairs_still_score(tmp_path):
    quick = {c["device_id"]: c for c in wh.cases("quick")}
    _truth(tmp_path, quick["WH-000-NULL"])
    _report(tmp_path, "WH-000-NULL", "no_gap", [])
    s = wh.score(tmp_path)
    assert s["null_false_positive"].startswith("0/1 ")
    assert s["pair_both_accepted"] == "n/a" and s["median_shrink_pair_both"] is None
