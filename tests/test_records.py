"""Audited calibration records: the real pipeline (Dagster, in process) on a small simulated archive, then
``imulab verify`` on good and tampered records, archives and chains."""

from __future__ import annotations

import json
import re
import shutil
import tempfile
import warnings
from datetime import datetime, timedelta, timezone
from pathlib import Path

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq
import pytest
from click.testing import CliRunner

from assets_lib.sim.simulator import example_device, simulate_run, write_run
from assets_lib.records import (
    SCHEMA_PATH,
    StoreView,
    build_device_records,
    canonical_json,
    certificate_problems,
    chain_problems,
    coefficient_id,
    content_differences,
    content_sha256,
    load_record,
    load_records_dir,
    noise_id,
    parse_certificate,
    record_file_bytes,
    round_to_uncertainty,
)
from assets_lib.store import VersionedStore

DEVICE = "TAC-007"
RUNS = ("pc00-rate", "pc01-rate", "pc02-rate")
#: a second device: a multi-position run whose manifest declares the accelerometer LSB twice its true value
#: (the scale factor comes out ~2) and a static run (Allan noise terms)
BAD_DEVICE, BAD_RUN, STATIC_RUN = "TAC-008", "pc00-pos24", "pc00-static"


def write_doubled_lsb_run(landing: Path, t0: datetime) -> None:
    truth = example_device(BAD_DEVICE, "tactical", 12).for_power_cycle(0, 12, 0.0)
    d = write_run(simulate_run(truth, "quick_24_position", BAD_RUN, start_time_utc=t0, seed=12,
                               plan_kwargs={"duration_scale": 0.3}), landing)
    m = json.loads((d / "manifest.json").read_text())
    for ch in ("accel_x", "accel_y", "accel_z"):
        m["channels"][ch]["lsb"] *= 2
    (d / "manifest.json").write_text(json.dumps(m, indent=2) + "\n")
    write_run(simulate_run(truth, "static_long", STATIC_RUN, start_time_utc=t0 + timedelta(hours=1), seed=12,
                           table_log=False, plan_kwargs={"static_duration_s": 600.0}), landing)


@pytest.fixture(scope="module")
def lab():
    """3 power-cycled rate runs of one tactical device, weekly, through the real pipeline (per-run and per-device
    jobs, as ``imulab run`` launches them), on tmpfs when there is one (fsync is slow on this disk)."""
    warnings.filterwarnings("ignore")
    shm = Path("/dev/shm")
    root = Path(tempfile.mkdtemp(prefix="imulab-records-", dir=shm if shm.is_dir() else None))
    landing, store = root / "landing", root / "store"
    base = example_device(DEVICE, "tactical", 11)
    t0 = datetime(2026, 2, 2, 8, tzinfo=timezone.utc)
    for c, run_id in enumerate(RUNS):
        truth = base.for_power_cycle(c, 11, 7.0 * c)
        write_run(simulate_run(truth, "quick_rate", run_id, power_cycle_index=c, start_time_utc=t0 + timedelta(days=7 * c),
                               seed=11, plan_kwargs={"duration_scale": 0.3}), landing)
    write_doubled_lsb_run(landing, t0)
    from pipelines.definitions import build_definitions
    from pipelines.launch import execute, open_instance, register_landed_runs
    from pipelines.resources import LabArchive

    defs = build_definitions(str(landing), str(store))
    with open_instance(root / "dagster_home") as inst:
        register_landed_runs(inst, LabArchive(landing_dir=str(landing)))
        summary = execute(defs, inst, "calibrate_captures", "captures")
        execute(defs, inst, "calibrate_devices", "devices", summary=summary)
    dev_runs = [r for r in summary.runs if r[0] == "calibrate_devices"]
    assert dev_runs and all(ok for _, _, ok in dev_runs), summary.runs
    st = VersionedStore(store)
    vdir = st.version_dir("calibration_record", DEVICE)
    cdir = st.version_dir("certificate", DEVICE)  # the certificate stage ran in the devices job
    yield {"root": root, "landing": landing, "store": store, "st": st, "vdir": vdir, "cdir": cdir, "defs": defs,
           "dagster_run_ids": [rid for _, rid, _ in dev_runs]}
    shutil.rmtree(root, ignore_errors=True)


def _verify(*args):
    from imulab.cli import main

    return CliRunner().invoke(main, ["verify", *map(str, args)], catch_exceptions=False)


# ------------------------------------------------------------------------------------------------ the records
def test_records_stored_and_chained(lab):
    st, vdir = lab["st"], lab["vdir"]
    table = st.read("calibration_record", DEVICE, "records")
    assert list(table["run_id"]) == list(RUNS)  # ordered by start time
    assert pd.isna(table["prev_record_sha256"].iloc[0])
    assert list(table["prev_record_sha256"].iloc[1:]) == list(table["record_sha256"].iloc[:-1])
    for row in table.itertuples():
        rec = load_record(vdir / f"{row.run_id}.json")
        assert rec["record_schema_version"] == "1.1" and rec["content"]["status"] == "valid", rec["content"].get("status_reasons")
        assert rec["record_sha256"] == row.record_sha256 == content_sha256(rec["content"])
        assert rec["provenance"]["dagster_run_id"] in lab["dagster_run_ids"]
        c = rec["content"]
        assert set(c["raw_files"]) == {"imu.parquet", "table.parquet", "manifest.json", "_COMPLETE"}
        ing = st.read_meta("ingested_run", f"{DEVICE}__{row.run_id}")
        assert c["raw_files"] == ing["file_sha256"]
        assert c["test_conditions"]["plan"]["name"] and c["test_conditions"]["plan"]["n_steps"] > 10
        assert 9.79 < c["test_conditions"]["gravity_mps2"] < 9.80
        t = c["test_conditions"]["temperature_degc"]
        assert t["min"] < t["mean"] < t["max"]
        coef = st.read("gyro_rate_fit", f"{DEVICE}__{row.run_id}", "coefficients")
        rec_bias = {(r["axis"]): r["value"] for r in c["coefficients"] if r["coefficient"] == "bias"}
        assert rec_bias == dict(zip(coef.loc[coef.coefficient == "bias", "axis"],
                                    coef.loc[coef.coefficient == "bias", "value"]))
        assert {"ingested_run", "plateaus", "gyro_rate_fit"} <= set(c["stages"])
        assert len(c["software"]["git_commit"]) in (7, 40, 64) or c["software"]["git_commit"] == "unknown"
    assert chain_problems(*load_records_dir(vdir)) == []


def test_canonical_json_is_stable():
    obj = {"b": [1.0, 0.1, -0.0, 1e-300, 2.5e17], "a": {"z": None, "y": "é"}, "n": float("nan")}
    text = canonical_json(obj)
    assert text == '{"a":{"y":"é","z":null},"b":[1.0,0.1,-0.0,1e-300,2.5e+17],"n":null}'.encode()
    assert canonical_json(json.loads(text)) == text  # parse -> serialize is the identity


def test_record_json_validates_against_schema(lab):
    jsonschema = pytest.importorskip("jsonschema")
    schema = json.loads(SCHEMA_PATH.read_text())
    jsonschema.Draft202012Validator.check_schema(schema)
    v = jsonschema.Draft202012Validator(schema)
    rec = load_record(lab["vdir"] / f"{RUNS[1]}.json")
    assert list(v.iter_errors(rec)) == []
    broken = json.loads(json.dumps(rec))
    broken["content"]["coefficients"][0]["stderr"] = -1.0
    del broken["content"]["raw_files"]
    assert len(list(v.iter_errors(broken))) >= 2


def test_certificate_html_has_coefficients_and_plots(lab):
    html = (lab["cdir"] / f"{RUNS[1]}.html").read_text(encoding="utf-8")
    rec = load_record(lab["vdir"] / f"{RUNS[1]}.json")
    assert rec["record_sha256"] in html and rec["content"]["prev_record_sha256"] in html
    cells = {k: v[0] for k, v in parse_certificate(html).cells.items()}
    assert cells["record_sha256"] == rec["record_sha256"] and cells["record_id"] == f"{DEVICE}/{RUNS[1]}"
    shown = [c for c in rec["content"]["coefficients"] if c["observable"]]
    assert len(shown) >= 12
    for c in shown:
        assert f"coef/{coefficient_id(c)}/value_lab" in cells
    assert re.search(r"<img [^>]*src='data:image/png;base64,iVBORw0KGgo", html)  # an embedded PNG (residuals)
    assert "gyro_rate_fit" in html and "deg/h" in html and "ppm" in html
    assert "banner valid" in html and "banner invalid" not in html



def test_certificates_are_their_own_stage_with_plots_drawn_from_the_store(lab):
    """Issue 10 item 8: the record stage writes JSON and records.parquet only (no HTML, no plot); the certificate
    stage renders one HTML per record of the current record version, with the residual and Allan plots drawn from
    the stored outputs (the fit and Allan stages store no PNG) and the navigation budget."""
    st = lab["st"]
    for dev in (DEVICE, BAD_DEVICE):
        rdir, cdir = st.version_dir("calibration_record", dev), st.version_dir("certificate", dev)
        assert not list(rdir.glob("*.html")) and not list(rdir.glob("*.png"))
        assert st.read_meta("certificate", dev)["record_version"] == st.current_version("calibration_record", dev)
        listing = st.read("certificate", dev, "certificates")
        records = st.read("calibration_record", dev, "records")
        assert list(listing["run_id"]) == list(records["run_id"])
        assert list(listing["record_sha256"]) == list(records["record_sha256"])
        for row in listing.itertuples():
            page = (cdir / row.file).read_text(encoding="utf-8")
            rec, problems = certificate_problems(page)
            assert problems == [] and rec == load_record(rdir / f"{row.run_id}.json")
            assert len(parse_certificate(page).plots) == row.n_plots + (1 if row.navigation_budget else 0)
    for asset in ("gyro_rate_fit", "accel_multiposition_fit", "allan_deviation", "plateaus"):
        for key in st.partitions(asset):
            assert not list(st.version_dir(asset, key).glob("*.png")), (asset, key)
    plots = parse_certificate((st.version_dir("certificate", DEVICE) / f"{RUNS[0]}.html").read_text()).plots
    assert set(plots) == {"gyro_rate_fit: residual_vs_rate", "navigation budget"}
    static = parse_certificate((st.version_dir("certificate", BAD_DEVICE) / f"{STATIC_RUN}.html").read_text()).plots
    assert {"allan_deviation: allan_gyro", "allan_deviation: allan_accel"} <= set(static)
    assert all(png[:8] == b"\x89PNG\r\n\x1a\n" and len(png) > 5000 for png in [*plots.values(), *static.values()])


def test_plots_command_draws_every_figure_from_the_store(lab, tmp_path):
    """``imulab plots`` draws the figures the run no longer draws (segmentation, residuals, Allan) from the stored
    versions; --asset/--partition narrow it; an unknown stage is a usage error."""
    from imulab.cli import main

    out = tmp_path / "plots"
    res = CliRunner().invoke(main, ["plots", "--store", str(lab["store"]), "--out", str(out)], catch_exceptions=False)
    assert res.exit_code == 0, res.output
    got = sorted(str(p.relative_to(out)) for p in out.rglob("*.png"))
    for run_id in RUNS:
        assert f"plateaus/{DEVICE}__{run_id}/segmentation.png" in got
        assert f"gyro_rate_fit/{DEVICE}__{run_id}/residual_vs_rate.png" in got
    assert f"accel_multiposition_fit/{BAD_DEVICE}__{BAD_RUN}/position_residuals.png" in got
    assert {f"allan_deviation/{BAD_DEVICE}__{STATIC_RUN}/allan_{s}.png" for s in ("gyro", "accel")} <= set(got)
    assert all(p.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" for p in out.rglob("*.png"))
    assert f"{len(got)} figure(s) drawn" in res.output
    one = tmp_path / "one"
    res = CliRunner().invoke(main, ["plots", "--store", str(lab["store"]), "--out", str(one), "--asset",
                                    "gyro_rate_fit", "--partition", f"{DEVICE}__{RUNS[0]}"], catch_exceptions=False)
    assert res.exit_code == 0 and [p.name for p in one.rglob("*.png")] == ["residual_vs_rate.png"], res.output
    res = CliRunner().invoke(main, ["plots", "--store", str(lab["store"]), "--asset", "calibration_record"])
    assert res.exit_code == 2 and "no figures for" in res.output

def _significant_digits(text: str) -> int:
    mant = text.split("e")[0].lstrip("-").replace(".", "").lstrip("0")
    return len(mant)


def _last_digit_exponent(text: str) -> int:
    mant, _, ex = text.partition("e")
    decimals = len(mant.split(".")[1]) if "." in mant else 0
    return (int(ex) if ex else 0) - decimals


def test_certificate_values_rounded_to_their_uncertainty(lab):
    """Issue 10 item 7: the certificate prints each value to the decimal place of its standard uncertainty, the
    uncertainty to two significant digits (GUM 7.2.6), not 17 digits."""
    html = (lab["cdir"] / f"{RUNS[1]}.html").read_text(encoding="utf-8")
    rec = load_record(lab["vdir"] / f"{RUNS[1]}.json")
    visible = html.split("<script type='application/json'")[0]
    cells = {k: v[0] for k, v in parse_certificate(html).cells.items()}
    n = 0
    for c in rec["content"]["coefficients"]:
        if not c["observable"]:
            continue
        for f, u in (("value_lab", "stderr_lab"), ("value", "stderr")):
            k = f"coef/{coefficient_id(c)}"
            shown_v, shown_u = cells[f"{k}/{f}"], cells[f"{k}/{u}"]
            assert _significant_digits(shown_u) == 2, (k, shown_u)
            last = _last_digit_exponent(shown_u)
            assert _last_digit_exponent(shown_v) == last, (k, shown_v, shown_u)
            assert abs(float(shown_v) - c[f]) <= 0.5000001 * 10.0**last, (k, shown_v, c[f])
            assert abs(float(shown_u) - c[u]) <= 0.5000001 * 10.0**last, (k, shown_u, c[u])
            assert repr(c[f]) not in visible
            n += 1
    assert n >= 24
    assert round_to_uncertainty(1.0000123456, 3.4e-6) == ("1.0000123", "0.0000034")
    assert round_to_uncertainty(2.3012e-6, 1.04e-8) == ("2.301e-06", "0.010e-06")
    assert round_to_uncertainty(9.996, 0.0996) == ("10.00", "0.10")
    assert round_to_uncertainty(286.495243, 3.0575) == ("286.5", "3.1")


def test_rebuild_reuses_unchanged_records_byte_for_byte(lab):
    """Idempotency: rebuilding a device's records later, by another run, reuses every unchanged record (same
    hash, creation time and bytes); only a changed record (and the links after it) is re-certified."""
    st, vdir = lab["st"], lab["vdir"]
    previous, _ = load_records_dir(vdir)
    meta = st.read_meta("calibration_record", DEVICE)
    view = StoreView(st, dict(meta["inputs"]))
    keys = [k.split("/", 1)[1] for k in meta["inputs"] if k.startswith("ingested_run/")]
    again = build_device_records(view, keys, previous, created_utc="2099-01-01T00:00:00Z", dagster_run_id="other")
    assert all(reused for _, reused in again)
    for rec, _ in again:
        assert record_file_bytes(rec) == (vdir / f"{rec['content']['run']['run_id']}.json").read_bytes()
    fresh = build_device_records(view, keys, {}, software={"imulab_version": "9", "git_commit": "unknown",
                                                           "git_dirty": None},
                                 created_utc="2099-01-01T00:00:00Z", dagster_run_id="other")
    assert not any(reused for _, reused in fresh)
    assert fresh[0][0]["record_sha256"] != again[0][0]["record_sha256"]  # software is certified, hence hashed
    assert fresh[1][0]["content"]["prev_record_sha256"] == fresh[0][0]["record_sha256"]
    strip = lambda r: {k: v for k, v in r["content"].items() if k not in ("software", "prev_record_sha256")}  # noqa: E731
    assert [strip(r) for r, _ in fresh] == [strip(r) for r, _ in again]
    # and the pipeline itself: a second materialization writes nothing new
    versions_before = st.versions("calibration_record", DEVICE)
    from pipelines.launch import execute, open_instance

    with open_instance(lab["root"] / "dagster_home") as inst:
        s = execute(lab["defs"], inst, "calibrate_devices", "devices")
    assert s.success and st.versions("calibration_record", DEVICE) == versions_before


# ------------------------------------------------------------------------------------------------- verification
def test_good_record_verifies(lab):
    res = _verify(lab["vdir"] / f"{RUNS[1]}.json", "--archive", lab["landing"], "--store", lab["store"])
    assert res.exit_code == 0, res.output
    assert "VERIFIED" in res.output and "earlier record pc00-rate verifies" in res.output
    assert "FAIL" not in res.output


def test_tampered_coefficient_fails_naming_it(lab, tmp_path):
    rec = load_record(lab["vdir"] / f"{RUNS[2]}.json")
    row = next(c for c in rec["content"]["coefficients"] if c["coefficient"] == "bias" and c["axis"] == "y")
    recorded = row["value"]
    row["value"] = recorded * 1.001
    # a careful forger also re-hashes the record: the recomputation and the stored chain still catch it
    rec["record_sha256"] = content_sha256(rec["content"])
    forged = tmp_path / f"{RUNS[2]}.json"
    forged.write_bytes(record_file_bytes(rec))
    res = _verify(forged, "--archive", lab["landing"], "--store", lab["store"], "--shallow")
    assert res.exit_code == 1, res.output
    assert f"coefficient gyro_rate_fit/gyro_y/bias: value recorded {recorded * 1.001!r}, recomputed {recorded!r}" \
        in res.output
    assert "the stored chain's record of run pc02-rate has sha256" in res.output
    # edited without re-hashing: the record's own hash names the edit as well
    rec["record_sha256"] = load_record(lab["vdir"] / f"{RUNS[2]}.json")["record_sha256"]
    forged.write_bytes(record_file_bytes(rec))
    res = _verify(forged, "--archive", lab["landing"], "--store", lab["store"], "--shallow")
    assert res.exit_code == 1 and "the record was edited" in res.output
    assert "gyro_rate_fit/gyro_y/bias" in res.output


def test_tampered_raw_file_fails_naming_it(lab, tmp_path):
    archive = tmp_path / "landing"
    shutil.copytree(lab["landing"], archive)
    imu = archive / DEVICE / RUNS[1] / "imu.parquet"
    df = pd.read_parquet(imu)
    df.loc[len(df) // 2, "gyro_x"] += 1  # one sample, one count
    pq.write_table(pa.Table.from_pandas(df, preserve_index=False), imu)
    res = _verify(lab["vdir"] / f"{RUNS[1]}.json", "--archive", archive, "--store", lab["store"], "--shallow")
    assert res.exit_code == 1, res.output
    assert re.search(r"FAIL raw file imu\.parquet: recorded sha256 [0-9a-f]{64}, archive file has [0-9a-f]{64}",
                     res.output)
    assert "raw file table.parquet" not in res.output  # only the changed file is named
    # an earlier run's file changed: verifying a later record names it through the chain
    res = _verify(lab["vdir"] / f"{RUNS[2]}.json", "--archive", archive, "--store", lab["store"], "--shallow")
    assert res.exit_code == 1 and "earlier record pc01-rate: raw file imu.parquet" in res.output


def test_deleted_record_in_the_middle_is_detected(lab, tmp_path):
    copy = tmp_path / "records"
    shutil.copytree(lab["vdir"], copy)
    (copy / f"{RUNS[1]}.json").unlink()
    recs, listing = load_records_dir(copy)
    problems = chain_problems(recs, listing)
    assert any("record of run pc01-rate is missing" in p for p in problems)
    assert any("chain link broken before run pc02-rate" in p and "run pc01-rate (missing)" in p for p in problems)
    res = _verify(copy / f"{RUNS[2]}.json", "--archive", lab["landing"], "--store", lab["store"], "--shallow")
    assert res.exit_code == 1, res.output
    assert "record of run pc01-rate is missing" in res.output and "chain link broken before run pc02-rate" in res.output
    # the first record has no predecessor: it still verifies on its own
    res = _verify(copy / f"{RUNS[0]}.json", "--archive", lab["landing"], "--store", lab["store"], "--shallow")
    assert res.exit_code == 0, res.output


def test_chain_check_blocks_on_a_deleted_record(lab, tmp_path):
    """The Dagster check (blocking) on a store whose current version lost a record: the device run fails and
    the check names the run."""
    import dagster as dg

    from pipelines.definitions import build_definitions

    store = tmp_path / "store"
    shutil.copytree(lab["store"], store)
    vdir = VersionedStore(store).version_dir("calibration_record", DEVICE)
    (vdir / f"{RUNS[1]}.json").unlink()
    defs = build_definitions(str(lab["landing"]), str(store))
    job = defs.resolve_job_def("calibrate_devices")
    with dg.instance_for_test() as inst:
        inst.add_dynamic_partitions("devices", [DEVICE])
        res = job.execute_in_process(instance=inst, partition_key=DEVICE, raise_on_error=False)
        assert not res.success  # blocking with ERROR severity: the device run fails (``imulab run`` exits 1)
        evals = [e.event_specific_data for e in res.all_events if e.event_type_value == "ASSET_CHECK_EVALUATION"]
    chain = [e for e in evals if e.check_name == "record_chain_intact"]
    assert chain and not chain[0].passed
    assert "pc01-rate" in chain[0].metadata["problems"].value



# ------------------------------------------------------------------------------- validity, certificates, precision
def test_doubled_lsb_record_is_marked_invalid(lab):
    """Issue 10 item 5: a manifest declaring the accelerometer LSB twice its value gives scale factors ~2; the
    record says it is not a valid calibration (JSON, records.parquet, certificate banner) and verify says so."""
    st = lab["st"]
    vdir = st.version_dir("calibration_record", BAD_DEVICE)
    rec = load_record(vdir / f"{BAD_RUN}.json")
    c = rec["content"]
    sf = [x for x in c["coefficients"] if x["sensor"] == "accel" and x["coefficient"] == "scale_factor"]
    assert len(sf) == 3 and all(1.9 < x["value"] < 2.1 for x in sf)  # the reproduction: K ~ 2
    assert c["status"] == "invalid"
    assert len([r for r in c["status_reasons"] if "accel" in r and "scale_factor" in r
                and "exceeds the tactical envelope" in r]) == 3, c["status_reasons"]
    table = st.read("calibration_record", BAD_DEVICE, "records").set_index("run_id")
    assert table.loc[BAD_RUN, "status"] == "invalid" and "scale_factor" in table.loc[BAD_RUN, "status_reasons"]
    assert table.loc[STATIC_RUN, "status"] == "valid" and table.loc[STATIC_RUN, "status_reasons"] == ""
    html = (st.version_dir("certificate", BAD_DEVICE) / f"{BAD_RUN}.html").read_text(encoding="utf-8")
    banner = re.search(r"<div class='banner invalid' role='alert'>(.*?)</div>", html, re.S)
    assert banner and "NOT A VALID CALIBRATION" in banner.group(1) and "scale_factor" in banner.group(1)
    assert "banner valid" not in html
    jsonschema = pytest.importorskip("jsonschema")
    v = jsonschema.Draft202012Validator(json.loads(SCHEMA_PATH.read_text()))
    assert list(v.iter_errors(rec)) == []
    no_reason = json.loads(json.dumps(rec))
    no_reason["content"]["status_reasons"] = []
    assert list(v.iter_errors(no_reason))  # invalid without a reason is not a record
    res = _verify(vdir / f"{BAD_RUN}.json", "--shallow")
    assert res.exit_code == 0, res.output  # a genuine record of an invalid calibration
    assert "NOTE this record is marked INVALID" in res.output and "NOT a valid calibration" in res.output


def test_certificate_verifies_and_edits_are_detected(lab, tmp_path):
    """Issue 10 item 6: ``imulab verify CERT.html`` checks the printed values against the record; an edited number,
    added text or an edited embedded record fails, naming the cell."""
    cert = lab["cdir"] / f"{RUNS[1]}.html"
    res = _verify(cert, "--shallow")
    assert res.exit_code == 0, res.output
    assert "ok   certificate shows exactly its record" in res.output and "VERIFIED" in res.output
    html = cert.read_text(encoding="utf-8")
    rec, problems = certificate_problems(html)
    assert problems == [] and rec == load_record(lab["vdir"] / f"{RUNS[1]}.json")
    # one printed number edited (the gyro x scale factor in the lab unit)
    sf = next(c for c in rec["content"]["coefficients"] if c["sensor"] == "gyro" and c["axis"] == "x"
              and c["coefficient"] == "scale_factor")
    key = f"coef/{coefficient_id(sf)}/value_lab"
    m = re.search(rf"data-k='{re.escape(key)}'>([^<]+)<", html)
    shown = m.group(1)
    edited = shown[:-1] + ("1" if shown[-1] != "1" else "2")
    forged = tmp_path / cert.name
    forged.write_text(html.replace(m.group(0), m.group(0).replace(shown, edited)), encoding="utf-8")
    res = _verify(forged, "--shallow")
    assert res.exit_code == 1, res.output
    assert f"certificate: {key} shows {edited!r}, the record gives {shown!r}" in res.output
    # text added outside the value cells
    forged.write_text(html.replace("<h2>Coefficients</h2>", "<h2>Coefficients</h2><p>Scale factor: 1.000</p>"),
                      encoding="utf-8")
    res = _verify(forged, "--shallow")
    assert res.exit_code == 1 and "differs from the rendering of its record" in res.output
    # the embedded record edited to match an edited cell: its hash no longer matches
    text = html.replace(m.group(0), m.group(0).replace(shown, edited))
    text = text.replace(repr(sf["value_lab"]), repr(sf["value_lab"] + 1e-3))
    forged.write_text(text, encoding="utf-8")
    res = _verify(forged, "--shallow")
    assert res.exit_code == 1 and "the embedded record was edited" in res.output


def test_certificate_navigation_budget_verifies_against_the_chain(lab, tmp_path):
    """The certificate's navigation budget (issue 13) is recomputed by verify from the device calibration embedded
    in the page, and that calibration must be the one the device's verified records assemble at the run's start:
    a page re-rendered consistently around another calibration fails."""
    import hashlib

    from assets_lib.apply.model import calibration_from_json
    from assets_lib.records.certificate import certificate_html, parse_certificate

    cert = lab["cdir"] / f"{RUNS[1]}.html"
    html = cert.read_text(encoding="utf-8")
    assert "What the calibration buys in navigation" in html
    res = _verify(cert, "--shallow")
    assert res.exit_code == 0 and "ok   navigation budget" in res.output, res.output
    parsed = parse_certificate(html)
    body = {k: v for k, v in parsed.device_calibration.items() if k != "calibration_sha256"}
    body["terms"] = [t for t in body["terms"] if t["coefficient"] != "misalignment_xy"]  # a term dropped
    body["calibration_sha256"] = hashlib.sha256(json.dumps(body, sort_keys=True, separators=(",", ":"),
                                                           ensure_ascii=False).encode()).hexdigest()
    forged = tmp_path / cert.name
    forged.write_text(certificate_html(parsed.record, parsed.plots, calibration_from_json(body)), encoding="utf-8")
    assert certificate_problems(forged.read_text(encoding="utf-8"))[1] == []  # self-consistent page ...
    res = _verify(forged, "--archive", lab["landing"], "--store", lab["store"], "--shallow")
    assert res.exit_code == 1 and "is not the one the device's records assemble" in res.output, res.output


def test_verify_tolerance_follows_each_precision(lab):
    """Issue 10 item 4: recomputed numbers are compared at their own precision (standard error, interval
    half-width): a kernel-sized difference (2.5e-8 relative) passes, a hundredth of an uncertainty does not."""
    vdir = lab["st"].version_dir("calibration_record", BAD_DEVICE)
    content = load_record(vdir / f"{STATIC_RUN}.json")["content"]
    noise = [r for r in content["noise"] if not r["is_upper_bound"] and r["value"] is not None]
    assert noise
    kernel = json.loads(json.dumps(content))
    for r in kernel["noise"]:
        for f in ("value", "ci_lo", "ci_hi", "value_lab", "ci_lo_lab", "ci_hi_lab"):
            if r[f] is not None:
                r[f] *= 1 + 2.5e-8
    assert content_differences(content, kernel) == []
    assert content_differences(content, kernel, fraction=0.0)  # the old fixed 1e-9 relative rule failed here
    moved = json.loads(json.dumps(content))
    r = next(x for x in moved["noise"] if noise_id(x) == noise_id(noise[0]))
    r["value"] += 0.01 * (r["ci_hi"] - r["ci_lo"]) / 2
    diffs = content_differences(content, moved)
    assert len(diffs) == 1 and diffs[0].startswith(f"noise term {noise_id(noise[0])}: value recorded")
    coef = load_record(lab["vdir"] / f"{RUNS[0]}.json")["content"]
    small, big = json.loads(json.dumps(coef)), json.loads(json.dumps(coef))
    small["coefficients"][0]["value"] += 1e-4 * coef["coefficients"][0]["stderr"]
    big["coefficients"][0]["value"] += 1e-2 * coef["coefficients"][0]["stderr"]
    assert content_differences(coef, small) == []
    assert content_differences(coef, big) and "value recorded" in content_differences(coef, big)[0]


def test_static_record_verifies_with_the_numpy_kernel(lab, monkeypatch):
    """Issue 10 item 4: a record computed with the installed Allan kernel verifies when recomputed with the
    numpy kernel (the optional numba one disabled)."""
    from assets_lib.noise import allan

    monkeypatch.setattr(allan.kernels, "HAVE_NUMBA", False)  # the kernel module decides (allan is a package)
    vdir = lab["st"].version_dir("calibration_record", BAD_DEVICE)
    res = _verify(vdir / f"{STATIC_RUN}.json", "--shallow")
    assert res.exit_code == 0, res.output
    assert "noise terms and all conditions match" in res.output


def test_verify_from_another_directory(lab, tmp_path, monkeypatch):
    """Issue 10 item 7: with no --archive / --store, verify finds the store the record lies in and the archive
    beside it, whatever the working directory."""
    monkeypatch.chdir(tmp_path)
    res = _verify(lab["vdir"] / f"{RUNS[1]}.json")
    assert res.exit_code == 0, res.output
    assert f"archive {lab['landing'].resolve()}, store {lab['store'].resolve()}" in res.output


def test_genuine_correlated_noise_run_is_not_marked_invalid():
    """No false alarm: NAV-001's second multi-position run of the default archive, whose plateau means carry
    correlated (flicker) noise, is fitted by GLS; its standardized residuals used to mix the whitened chi-square
    with diagonal weights (|z| ~ 1e150), so the record would have been marked invalid. They are now ~N(0, 1)."""
    from assets_lib.calibration.multiposition import fit_accel_multiposition, fit_gyro_static
    from assets_lib.calibration.segmentation import segment_run
    from assets_lib.records.validity import CHI2_BAND, reduced_chi_square
    from raw_schemas.readers import ingest_frames

    truth = example_device("NAV-001", "navigation", 2026).for_power_cycle(1, 2026, 7.0)
    run = simulate_run(truth, "quick_24_position", "pc01-pos24", power_cycle_index=1, seed=2026,
                       start_time_utc=datetime(2026, 1, 12, 9, tzinfo=timezone.utc))
    ing = ingest_frames(run.manifest, run.imu_raw, run.table_raw)
    p = segment_run(run.manifest, ing.imu, ing.table).plateaus
    resid = pd.concat([fit_accel_multiposition(p).residual_table(), fit_gyro_static(p).residual_table()])
    z = resid.loc[~resid["excluded"].astype(bool), "std_residual"].to_numpy(float)
    assert np.nanmax(np.abs(z)) < 10
    chi2 = reduced_chi_square(resid["std_residual"].to_numpy(float), resid["excluded"].to_numpy(bool))
    assert CHI2_BAND[0] < chi2 < CHI2_BAND[1]


def test_record_of_an_earlier_schema_version_is_compared_on_what_it_certifies(lab):
    """A 1.0 record (before status existed) is compared without the fields 1.1 added; its numbers still count."""
    c = load_record(lab["vdir"] / f"{RUNS[0]}.json")["content"]
    old = {k: v for k, v in c.items() if k not in ("status", "status_reasons")}
    old["record_schema_version"] = "1.0"
    assert content_differences(old, c) == []
    old["coefficients"] = json.loads(json.dumps(old["coefficients"]))
    old["coefficients"][0]["value"] += old["coefficients"][0]["stderr"]
    assert len(content_differences(old, c)) == 1


def test_invalid_record_is_never_used_as_a_calibration(lab):
    """Issue 10 item 5: an invalid record is refused by ``calibration_from_record`` (``imulab apply``) and skipped,
    with a warning, when a device calibration is looked up at a date (``imulab records``)."""
    from assets_lib.apply.model import CalibrationError, calibration_from_record
    from assets_lib.records.lookup import lookup

    vdir = lab["st"].version_dir("calibration_record", BAD_DEVICE)
    bad = load_record(vdir / f"{BAD_RUN}.json")
    with pytest.raises(CalibrationError, match="marked invalid, not a valid calibration: .*scale_factor"):
        calibration_from_record(bad)
    res = lookup(lab["store"], BAD_DEVICE, "2026-03-01T00:00:00Z")
    assert res.valid_run_id == STATIC_RUN
    assert bad["record_sha256"] not in {t.record_sha256 for t in res.calibration.terms}
    assert "accel" in res.calibration.missing_groups
    assert any(w.startswith(f"record {BAD_RUN} is marked invalid and not used") for w in res.warnings)
    assert dict(zip(res.table["run_id"], res.table["status"])) == {BAD_RUN: "invalid", STATIC_RUN: "valid"}
