"""The fleet drift stage in the real pipeline: simulated archive (a device whose gyro bias ages fast, a stable
one), real Dagster runs through the launch helpers, real parquet and PNG outputs, the WARN checks."""

from __future__ import annotations

import json
import warnings
from dataclasses import replace
from datetime import datetime, timedelta, timezone
from pathlib import Path

import dagster as dg
import pandas as pd
import pytest

from assets_lib.sim.simulator import DEGPH, example_device, simulate_run, write_run
from assets_lib.store import VersionedStore

DRIFTING, STABLE = "DRF-001", "STB-002"
DRIFT_DEGPH_PER_DAY = 3.0  # vs a turn-on repeatability of 1 deg/h: 63 deg/h over the 21 days of the series


def _check_evals(instance: dg.DagsterInstance, run_id: str) -> dict:
    out = {}
    for rec in instance.get_records_for_run(run_id).records:
        ev = rec.event_log_entry.dagster_event
        if ev is not None and ev.event_type_value == "ASSET_CHECK_EVALUATION":
            out[ev.event_specific_data.check_name] = ev.event_specific_data
    return out


#: run in a second process from the start of the session (tests/conftest.py)
BACKGROUND_JOBS = ("fleet_archive_run",)


def fleet_archive_run(root: Path) -> None:
    """The fleet's archive (4 weekly rate runs of the drifting device, 3 of the stable one) and the main job on it
    (``materialize_archive``: per-run, per-device and fleet stages) with a persistent Dagster instance in ``root /
    "dagster_home"``; the launch summary's runs (job, Dagster run id, success) in ``root / "runs.json"``."""
    warnings.filterwarnings("ignore")
    landing, store = root / "landing", root / "store"
    t0 = datetime(2026, 3, 2, 8, tzinfo=timezone.utc)
    devices = [(DRIFTING, replace(example_device(DRIFTING, "tactical", 5),
                                  gyro_bias_drift_per_day=DRIFT_DEGPH_PER_DAY * DEGPH), 4),
               (STABLE, example_device(STABLE, "tactical", 5), 3)]
    for dev, base, n in devices:
        for c in range(n):
            truth = base.for_power_cycle(c, 5, 7.0 * c)
            write_run(simulate_run(truth, "quick_rate", f"pc{c:02d}-rate", power_cycle_index=c, seed=5,
                                   start_time_utc=t0 + timedelta(days=7 * c), plan_kwargs={"duration_scale": 0.3}),
                      landing)
    from pipelines.definitions import build_definitions
    from pipelines.launch import (
        materialize_archive,
        open_instance,
        register_landed_runs,
    )
    from pipelines.resources import LabArchive

    defs = build_definitions(str(landing), str(store))
    with open_instance(root / "dagster_home") as inst:
        register_landed_runs(inst, LabArchive(landing_dir=str(landing)))
        summary = materialize_archive(defs, inst, record_outcomes=False)
    (root / "runs.json").write_text(json.dumps(summary.runs))


@pytest.fixture(scope="module")
def fleet(background_job):
    """The background job's store and Dagster instance (reopened here), the fleet run's check evaluations."""
    warnings.filterwarnings("ignore")
    from pipelines.definitions import build_definitions
    from pipelines.launch import LaunchSummary, open_instance

    root = background_job("fleet_archive_run")
    summary = LaunchSummary(runs=[tuple(r) for r in json.loads((root / "runs.json").read_text())])
    defs = build_definitions(str(root / "landing"), str(root / "store"))
    with open_instance(root / "dagster_home") as inst:
        fleet_runs = [rid for job, rid, ok in summary.runs if job == "fleet_summary"]
        evals = _check_evals(inst, fleet_runs[-1])
        yield {"root": root, "defs": defs, "store": VersionedStore(root / "store"), "summary": summary,
               "evals": evals, "instance": inst}


def test_fleet_drift_stored_with_tables_and_plots(fleet):
    st = fleet["store"]
    assert [ok for job, _, ok in fleet["summary"].runs if job == "fleet_summary"] == [True]
    vdir = st.version_dir("fleet_drift", "fleet")
    drift = st.read("fleet_drift", "fleet", "drift")
    points = st.read("fleet_drift", "fleet", "drift_points")
    summary = st.read("fleet_drift", "fleet", "fleet_summary")
    assert set(drift["device_id"]) == {DRIFTING, STABLE}
    assert set(drift["coefficient"]) == {"bias", "scale_factor"}
    assert len(points) == drift["n_runs"].sum()
    assert not list(vdir.glob("*.png"))  # control charts are drawn on demand (issue 10 item 8)
    from assets_lib.stages.figures import figures, view_of

    pngs = figures("fleet_drift", "fleet", view_of(st, "fleet_drift", "fleet"))
    assert sorted(pngs) == ["drift_gyro_bias", "drift_gyro_scale_factor"]
    assert all(png[:8] == b"\x89PNG\r\n\x1a\n" for png in pngs.values())
    meta = st.read_meta("fleet_drift", "fleet")
    # the stage read every upstream partition: 7 ingested runs, 7 rate fits, 2 repeatability tables
    assert sum(k.startswith("ingested_run/") for k in meta["inputs"]) == 7
    assert sum(k.startswith("gyro_rate_fit/") for k in meta["inputs"]) == 7
    assert sum(k.startswith("repeatability/") for k in meta["inputs"]) == 2
    assert summary.set_index("family").loc["all", "n_series"] == len(drift)
    # the rate fits are in the series: values equal the stored coefficients
    c = st.read("gyro_rate_fit", f"{DRIFTING}__pc02-rate", "coefficients")
    want = c[(c.coefficient == "bias") & (c.axis == "z")]["value"].item()
    got = points[(points.device_id == DRIFTING) & (points.coefficient == "bias") & (points.axis == "z")
                 & (points.run_id == "pc02-rate")]["value"].item()
    assert got == want


def test_drifting_device_flagged_stable_device_not(fleet):
    drift = fleet["store"].read("fleet_drift", "fleet", "drift")
    bias = drift[(drift.device_id == DRIFTING) & (drift.coefficient == "bias")]
    assert len(bias) == 3 and bias["drift_flag"].all()
    assert (bias["sigma_source"] == "repeatability, detrended (in-sample)").all()
    # truth: 3 deg/h per day on every axis; the slope interval (t, 2 dof) covers it
    slope_degph = bias["slope_per_day"] / DEGPH
    lo, hi = bias["slope_ci_low"] / DEGPH, bias["slope_ci_high"] / DEGPH
    assert ((lo <= DRIFT_DEGPH_PER_DAY) & (DRIFT_DEGPH_PER_DAY <= hi)).all(), slope_degph.tolist()
    assert not drift.loc[drift.device_id == STABLE, ["drift_flag", "shift_flag"]].to_numpy().any()
    sf = drift[(drift.device_id == DRIFTING) & (drift.coefficient == "scale_factor")]
    assert not sf["drift_flag"].any()


def test_checks_warn_naming_device_coefficient_and_run(fleet):
    ev = fleet["evals"]
    d, s = ev["no_drift_beyond_limits"], ev["no_abrupt_shifts"]
    assert not d.passed and d.severity == dg.AssetCheckSeverity.WARN and not d.blocking
    assert d.metadata["n_flagged"].value == 3
    table = d.metadata["flagged"].value
    for axis in "xyz":
        assert f"| {DRIFTING} " in table and f"| {axis} " in table
    assert "bias" in table and "pc03-rate" in table and STABLE not in table
    assert s.passed


def test_rerun_reuses_the_fleet_version(fleet):
    from pipelines.launch import execute

    st = fleet["store"]
    before = st.versions("fleet_drift", "fleet")
    s = execute(fleet["defs"], fleet["instance"], "fleet_summary", None)
    assert s.success and st.versions("fleet_drift", "fleet") == before


def test_fleet_stage_skips_without_coefficients(tmp_path):
    """Empty store: the stage has no inputs, writes nothing, and the checks pass saying so."""
    from pipelines.definitions import build_definitions

    defs = build_definitions(str(tmp_path / "landing"), str(tmp_path / "store"))
    with dg.instance_for_test() as inst:
        res = defs.resolve_job_def("fleet_summary").execute_in_process(instance=inst, raise_on_error=False)
        assert res.success
        evals = {e.event_specific_data.check_name: e.event_specific_data for e in res.all_events
                 if e.event_type_value == "ASSET_CHECK_EVALUATION"}
        mats = [e for e in res.all_events if e.event_type_value == "ASSET_MATERIALIZATION"]
    assert VersionedStore(tmp_path / "store").partitions("fleet_drift") == []
    assert "skipped: inputs missing" in mats[0].event_specific_data.materialization.metadata["partitions"].value
    assert evals["no_drift_beyond_limits"].passed and "no drift analysis" in \
        evals["no_drift_beyond_limits"].metadata["note"].value


def test_fleet_tables_have_their_columns(fleet):
    from assets_lib.fleet.drift import POINT_COLUMNS, SERIES_COLUMNS, SUMMARY_COLUMNS

    st = fleet["store"]
    assert list(st.read("fleet_drift", "fleet", "drift").columns) == SERIES_COLUMNS
    assert list(st.read("fleet_drift", "fleet", "drift_points").columns) == POINT_COLUMNS
    assert list(st.read("fleet_drift", "fleet", "fleet_summary").columns) == SUMMARY_COLUMNS
    pts = st.read("fleet_drift", "fleet", "drift_points")
    assert pd.api.types.is_bool_dtype(pts["beyond_limits"]) and pts["run_id"].notna().all()
