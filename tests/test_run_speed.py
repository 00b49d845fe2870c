"""What makes ``imulab run`` fast without changing its outputs (issue 10, item 8, and its leftovers): cheap
figures drawn without pyplot, an unchanged archive answered without importing Dagster or the science, the
planning cache invalidated by any source change, ``imulab reprocess`` under the run lock, and the headline table
skipping runs whose record is invalid. Speed figures themselves live in ``benchmarks/bench_run.py``."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from prod_helpers import write_realistic_archive

ROOT = Path(__file__).resolve().parents[1]


def _env(**extra) -> dict:
    env = dict(os.environ, PYTHONPATH=str(ROOT), PYTHONWARNINGS="ignore")
    env.pop("DAGSTER_HOME", None)
    env.update({k: str(v) for k, v in extra.items()})
    return env


def _imulab(*args, python_flags=(), **env) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, *python_flags, "-m", "imulab.cli", *map(str, args)], cwd=ROOT,
                            env=_env(**env), stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)


def _finish(p: subprocess.Popen, timeout: float = 600) -> tuple[int, str]:
    out, _ = p.communicate(timeout=timeout)
    return p.returncode, out


# ---------------------------------------------------------------------------------------------------------------
# figures
# ---------------------------------------------------------------------------------------------------------------
def test_envelope_keeps_every_bins_extremes_in_time_order():
    from assets_lib.plotting import envelope

    rng = np.random.default_rng(3)
    t = np.arange(100_003) * 0.01
    y = rng.standard_normal(t.size)
    y[51_234] = 40.0  # a spike a stride decimation would miss
    y[77_777] = -35.0
    tt, yy = envelope(t, y, 2000)
    assert tt.size <= 2002 and np.all(np.diff(tt) >= 0)
    assert yy.max() == 40.0 and yy.min() == -35.0
    assert set(np.round(tt[[np.argmax(yy), np.argmin(yy)]], 2)) == {512.34, 777.77}
    short = np.arange(10.0)
    assert np.array_equal(envelope(short, short, 2000)[1], short)


def test_stage_figures_are_drawn_without_pyplot():
    """Every figure a stage draws uses an Agg canvas of its own (no pyplot figure manager, no layout pass that
    draws twice): rendering them leaves ``matplotlib.pyplot`` unimported."""
    code = r"""
import sys
import numpy as np, pandas as pd
from assets_lib.noise.allan import allan_deviations
from assets_lib.noise.identification import fit_all, plot_allan
from assets_lib.calibration.fit_report import plot_rate_residuals_png, plot_multiposition_residuals_png
rng = np.random.default_rng(1)
df = pd.DataFrame({"gyro_x_radps": 1e-4 * rng.standard_normal(40000)})
res = allan_deviations(df, 100.0, taus="octave", channels=["gyro_x_radps"])
pngs = [plot_allan(res, fit_all(res), title="t")]
r = pd.DataFrame({"sensor": ["gyro"] * 4, "axis": ["x"] * 4, "input_value": [-1.0, -0.5, 0.5, 1.0],
                  "residual": [1e-6, -1e-6, 2e-6, 0.0], "sigma": [1e-6] * 4, "excluded": [False, False, True, False]})
pngs.append(plot_rate_residuals_png(r))
pngs.append(plot_multiposition_residuals_png(r.assign(sensor="accel")))
assert all(p[:8] == b"\x89PNG\r\n\x1a\n" and len(p) > 5000 for p in pngs)
print("pyplot" if "matplotlib.pyplot" in sys.modules else "no pyplot")
"""
    out = subprocess.run([sys.executable, "-c", code], env=_env(), capture_output=True, text=True, timeout=300,
                         check=False)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip().splitlines()[-1] == "no pyplot"


# ---------------------------------------------------------------------------------------------------------------
# the planning cache
# ---------------------------------------------------------------------------------------------------------------
def test_planning_graph_round_trips_and_any_source_change_invalidates_it(tmp_path):
    from assets_lib.stages import graph_cache
    from assets_lib.stages.registry import STAGES

    path = tmp_path / "graph.json"
    graph_cache.save(STAGES, path, fingerprint="abc")
    loaded = graph_cache.load(path, fingerprint="abc")
    assert loaded is not None and loaded.names == STAGES.names
    for a, b in zip(loaded, STAGES):
        assert (a.level, a.upstream, a.applies_to, a.code_version) == (b.level, b.upstream, b.applies_to,
                                                                         b.code_version)
    with pytest.raises(RuntimeError, match="plans, it does not compute"):
        loaded[STAGES.names[0]].compute("k", None)
    assert graph_cache.load(path, fingerprint="abd") is None  # a source changed: the real graph is imported
    import dataclasses

    from assets_lib.stages.engine import StageGraph

    fresh = StageGraph([dataclasses.replace(s) for s in STAGES])  # specs whose code versions are not computed yet
    assert graph_cache.prime(fresh, path, fingerprint="abd") == 0
    assert graph_cache.prime(fresh, path, fingerprint="abc") == len(STAGES)
    assert [s.code_version for s in fresh] == [s.code_version for s in STAGES]
    # the fingerprint covers every project source: a copy of the tree with one byte changed differs
    tree = tmp_path / "tree"
    for pkg in ("assets_lib", "raw_schemas"):
        for f in (ROOT / pkg).rglob("*.py"):
            dst = tree / f.relative_to(ROOT)
            dst.parent.mkdir(parents=True, exist_ok=True)
            dst.write_bytes(f.read_bytes())
    before = graph_cache.sources_fingerprint(tree)
    assert before == graph_cache.sources_fingerprint(ROOT)
    f = tree / "raw_schemas" / "units.py"
    f.write_text(f.read_text() + "\n# edited\n")
    assert graph_cache.sources_fingerprint(tree) != before


# ---------------------------------------------------------------------------------------------------------------
# the per-process read cache of small tables
# ---------------------------------------------------------------------------------------------------------------
def test_small_tables_are_read_once_and_served_as_independent_copies(tmp_path, monkeypatch):
    from assets_lib.store import versioned
    from assets_lib.store.versioned import write_parquet_deterministic

    path = tmp_path / "coefficients.parquet"
    write_parquet_deterministic(pd.DataFrame({"coefficient": ["a", "b"], "value": [1.0, 2.0]}), path)
    reads = []
    real = pd.read_parquet
    monkeypatch.setattr(versioned.pd, "read_parquet", lambda *a, **k: reads.append(a) or real(*a, **k))
    first = versioned.read_table(path)
    first.loc[0, "value"] = -1.0  # a caller's change never reaches the cache
    first["extra"] = 0
    again = versioned.read_table(path)
    pd.testing.assert_frame_equal(again, real(path), check_exact=True)
    assert len(reads) == 1
    assert list(versioned.read_table(path, columns=["value"]).columns) == ["value"] and len(reads) == 2
    # a file rewritten in place, even at once and to the same size, is read anew
    write_parquet_deterministic(pd.DataFrame({"coefficient": ["a", "b"], "value": [1.0, 3.0]}), path)
    assert versioned.read_table(path)["value"].tolist() == [1.0, 3.0] and len(reads) == 3


# ---------------------------------------------------------------------------------------------------------------
# the headline table
# ---------------------------------------------------------------------------------------------------------------
def _coef(value: float) -> pd.DataFrame:
    return pd.DataFrame({"sensor": ["gyro"], "axis": ["x"], "coefficient": ["scale_factor"], "value_lab": [value],
                         "stderr_lab": [0.5], "unit_lab": ["ppm"]})


def test_headline_table_skips_runs_whose_record_is_invalid(tmp_path):
    """The latest rate run of DEV has an invalid record: the table shows the latest valid run's value and says
    which run it left out and why; before, it printed the invalid run's value as the device's headline."""
    from assets_lib.store import VersionedStore
    from imulab.report import headline_coefficients, print_outputs

    st = VersionedStore(tmp_path / "store")
    st.write("gyro_rate_fit", "DEV__pc00-rate", "v0", {"coefficients": _coef(111.0)})
    st.write("gyro_rate_fit", "DEV__pc01-rate", "v1", {"coefficients": _coef(999999.0)})
    rec = {"pc00-rate": {"status": "valid"},
           "pc01-rate": {"status": "invalid", "status_reasons": ["gyro x scale_factor implausible for the grade"]}}
    st.write("calibration_record", "DEV", "r1", {}, files={f"{k}.json": json.dumps({"content": v}).encode()
                                                          for k, v in rec.items()})
    skipped: list[str] = []
    head = headline_coefficients(st, skipped)
    assert head["gyro scale_factor"].tolist() == ["111 +- 0.5 ppm"]
    assert skipped == ["DEV pc01-rate: record invalid (gyro x scale_factor implausible for the grade); not shown"]
    lines: list[str] = []
    print_outputs(tmp_path / "store", echo=lines.append)
    text = "\n".join(lines)
    assert "999999" not in text and "skipped, invalid record: DEV pc01-rate" in text


def test_outputs_name_each_devices_sim_to_real_verdict(tmp_path):
    """The run's closing listing gives every diagnosed device's verdict and its report (the README promises it)."""
    from assets_lib.store import VersionedStore
    from imulab.report import print_outputs

    st = VersionedStore(tmp_path / "store")
    st.write("sim_to_real", "DEV", "v0", {}, meta={"verdict": "partly_explained"},
             files={"DEV.html": b"<html></html>"})
    lines: list[str] = []
    print_outputs(tmp_path / "store", echo=lines.append)
    row = [ln for ln in lines if ln.strip().startswith("DEV ")]
    assert row and "partly_explained" in row[0] and row[0].rstrip().endswith("DEV.html")


def test_outputs_say_where_the_certificates_are_or_how_to_render_them(tmp_path):
    """The run's closing listing names each device's certificate folder when the certificates were rendered from
    its current record version; otherwise (never rendered, or rendered from an older record version) it says
    how to render them."""
    from assets_lib.store import VersionedStore
    from imulab.report import print_outputs

    st = VersionedStore(tmp_path / "store")
    for dev in ("A", "B", "C"):
        st.write("calibration_record", dev, "r1", {}, files={"pc00.json": json.dumps({"content": {}}).encode()})
    st.write("certificate", "A", "c1", {}, meta={"record_version": "r1"}, files={"pc00.html": b"<html></html>"})
    st.write("certificate", "C", "c0", {}, meta={"record_version": "r0"}, files={"pc00.html": b"<html></html>"})
    lines: list[str] = []
    print_outputs(tmp_path / "store", echo=lines.append)
    text = "\n".join(lines)
    assert f"certificates: {st.version_dir('certificate', 'A', 'c1')}  (1 HTML" in text
    assert "not rendered for the current records of 2 device(s) (B, C): `imulab certificates`" in text
    assert "`imulab plots`" in text


# ---------------------------------------------------------------------------------------------------------------
# real processes: the unchanged archive, the reprocess lock
# ---------------------------------------------------------------------------------------------------------------
BACKGROUND_JOBS = ("first_runs",)  # run in a second process from the start of the session (tests/conftest.py)


def first_runs(root: Path) -> None:
    """Two realistic archives (``archive``, ``archive-new``) and a first ``imulab run`` on each (data dirs ``data``,
    ``data-new``); their exit statuses and outputs in ``root / "first_runs.json"``."""
    runs = {}
    for archive, data in (("archive", "data"), ("archive-new", "data-new")):
        write_realistic_archive(root / archive)
        runs[archive] = _finish(_imulab("run", "--archive", root / archive, "--data-dir", root / data))
    (root / "first_runs.json").write_text(json.dumps(runs))


@pytest.fixture(scope="module")
def workspace(background_job):
    """This module's background job: two archives after their first ``imulab run``."""
    return background_job("first_runs")


def _first_run(workspace: Path, archive: str) -> tuple[int, str]:
    rc, out = json.loads((workspace / "first_runs.json").read_text())[archive]
    return rc, out


@pytest.mark.slow
def test_unchanged_archive_answers_without_importing_dagster(workspace):
    """After a finished run, a second ``imulab run`` on the unchanged archive plans from the store and the
    planning cache: no Dagster import, no science import, nothing launched, the same outputs and summary."""
    archive, data = workspace / "archive", workspace / "data"
    rc, first = _first_run(workspace, "archive")
    assert rc == 0, first
    rc, again = _finish(_imulab("run", "--archive", archive, "--data-dir", data, python_flags=("-X", "importtime")))
    assert rc == 0, again
    imported = {line.split("|")[-1].strip() for line in again.splitlines() if line.startswith("import time:")}
    assert "dagster" not in imported and "scipy.stats" not in imported and "matplotlib" not in imported
    text = "\n".join(line for line in again.splitlines() if not line.startswith("import time:"))
    assert "(0 new)" in text and "nothing launched" in text and "status: ok" in text

    def outputs(out: str) -> str:  # what the run prints about the store, before its summary
        return out[out.index("outputs under"):out.index("\nsummary:")]

    assert outputs(text) == outputs(first)


@pytest.mark.slow
def test_certificates_render_on_demand_and_verify(workspace):
    """``imulab run`` renders no certificate (issue 10 item 8); ``imulab certificates`` renders one per record of
    the current record versions, launching only the devices' certificate stage; ``imulab verify`` accepts one;
    afterwards both commands answer on the unchanged archive without launching anything."""
    archive, data = workspace / "archive", workspace / "data"
    if not (data / "store" / "ARCHIVE").is_file():
        rc, out = _finish(_imulab("run", "--archive", archive, "--data-dir", data))
        assert rc == 0, out
    store = data / "store"
    assert not (store / "certificate").exists() and not list((store / "calibration_record").rglob("*.html"))
    rc, out = _finish(_imulab("certificates", "--archive", archive, "--data-dir", data))
    assert rc == 0, out
    assert "ok   calibrate_devices run" in out and "calibrate_captures run" not in out, out
    records = [p for p in (store / "calibration_record").glob("*/*/*.json") if p.name != "meta.json"
               and (p.parent.parent / "CURRENT").read_text().strip() == p.parent.name]
    certs = sorted((store / "certificate").glob("*/*/*.html"))
    assert len(certs) == len(records) > 0 and "certificates: " in out and "not rendered" not in out
    from click.testing import CliRunner

    from imulab.cli import main

    res = CliRunner().invoke(main, ["verify", str(certs[0]), "--shallow"], catch_exceptions=False)
    assert res.exit_code == 0 and "ok   certificate shows exactly its record" in res.output, res.output
    for cmd in ("run", "certificates"):
        rc, again = _finish(_imulab(cmd, "--archive", archive, "--data-dir", data))
        assert rc == 0 and "nothing launched" in again and "certificates: " in again, again


@pytest.mark.slow
def test_a_new_run_in_the_archive_takes_the_dagster_path(workspace):
    """The fast path applies only when the last run registered every completed run: a newly landed run is
    registered on the instance and computed."""
    from prod_helpers import small_run

    from assets_lib.sim.simulator import write_run

    archive, data = workspace / "archive-new", workspace / "data-new"
    rc, out = _first_run(workspace, "archive-new")
    assert rc == 0, out
    write_run(small_run("TST-A", "tactical", "pc09-pos24"), archive)  # a short run: its plateau gate fails (exit 1)
    rc, out = _finish(_imulab("run", "--archive", archive, "--data-dir", data))
    assert "(1 new)" in out and "nothing launched" not in out and "ok   calibrate_captures run" in out, out
    assert (data / "store" / "ingested_run" / "TST-A__pc09-pos24" / "CURRENT").is_file()


@pytest.mark.slow
def test_reprocess_waits_for_the_run_lock(workspace):
    """``imulab reprocess`` takes the lock of ``imulab run``: while a run holds the workspace it waits (and says
    for whom), then does its work; told not to wait, it refuses with the holder's pid. Before, it wrote the store
    and the instance alongside the run."""
    from pipelines.workspace import run_lock

    archive, data = workspace / "archive", workspace / "data-reprocess"
    with run_lock(data / "dagster_home", data / "store"):
        rc, out = _finish(_imulab("reprocess", "--archive", archive, "--data-dir", data, IMULAB_LOCK_TIMEOUT_S=0))
        assert rc == 1 and f"(pid {os.getpid()}" in out and "refusing to start" in out, out
        waiting = _imulab("reprocess", "--archive", archive, "--data-dir", data)
        time.sleep(3.0)
        assert waiting.poll() is None  # still waiting for the lock
        assert not (data / "store" / "ingested_run").exists()
    rc, out = _finish(waiting)
    assert rc == 0, out
    assert "another imulab run is using" in out and "waiting for it to finish" in out
    assert "rewrote" in out and (data / "store" / "ingested_run").is_dir()


@pytest.mark.slow
def test_a_run_launched_outside_imulab_holds_the_workspace_lock(tmp_path, monkeypatch):
    """A run the Dagster daemon or the UI launches carries no imulab pid tag: its ``WorkspaceLock`` resource takes
    the run lock, so it cannot write the store while ``imulab run`` / ``imulab reprocess`` hold it (told not to
    wait, it fails naming the holder); once free, it runs. A run imulab executes in its own process (tagged with
    its pid) never waits on the lock its process holds. Before, such runs ignored the lock."""
    from prod_helpers import QUIET, toy_definitions, toy_graph, write_small_archive

    from pipelines.jobs import CAPTURES_JOB, range_tags
    from pipelines.launch import open_instance, process_tags, register_landed_runs
    from pipelines.resources import LabArchive
    from pipelines.workspace import run_lock

    landing, store, home = tmp_path / "landing", tmp_path / "store", tmp_path / "home"
    keys = write_small_archive(landing, runs_per_device=1)
    defs = toy_definitions(landing, store, toy_graph())
    job = defs.resolve_job_def(CAPTURES_JOB)
    monkeypatch.setenv("IMULAB_LOCK_TIMEOUT_S", "0")
    with open_instance(home) as inst:
        register_landed_runs(inst, LabArchive(landing_dir=str(landing)))
        tags = range_tags(keys[0], keys[-1])
        with run_lock(home, store):
            res = job.execute_in_process(instance=inst, tags=tags, run_config=QUIET, raise_on_error=False)
            assert not res.success
            assert any("another imulab run is using" in f"{e.message} {e.event_specific_data}" for e in res.all_events)
            assert not (store / "ingested_run").exists()
            mine = job.execute_in_process(instance=inst, tags={**tags, **process_tags()}, run_config=QUIET,
                                          raise_on_error=False)
            assert mine.success  # imulab's own in-process run: its process holds the lock already
        again = job.execute_in_process(instance=inst, tags=tags, run_config=QUIET, raise_on_error=False)
        assert again.success


def test_summary_counts_each_invalid_record_with_its_reasons(tmp_path):
    """The run summary's warnings name every record that is not valid, with its reasons (one reader of record
    statuses serves the headline table and the summary)."""
    from assets_lib.store import VersionedStore
    from imulab.commands.run import record_warnings

    st = VersionedStore(tmp_path / "store")
    rec = {"pc00-rate": {"status": "valid"}, "pc01-rate": {"status": "invalid", "status_reasons": ["a", "b"]},
           "pc02-rate": {"status": "invalid"}}
    st.write("calibration_record", "DEV", "r1", {}, files={f"{k}.json": json.dumps({"content": v}).encode()
                                                          for k, v in rec.items()})
    assert record_warnings(st) == ["record DEV/pc01-rate: invalid (a; b)",
                                   "record DEV/pc02-rate: invalid (no reason given)"]

