"""``imulab run`` reports what failed and exits non-zero (issue 10, item 2), and one bad partition fails alone
(item 1): a malformed run among good ones, a run still being written, a mistyped archive, a rerun on an unchanged
archive. Real Dagster runs through the command, on a short simulated archive."""

from __future__ import annotations

import shutil
import tempfile
import warnings
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from click.testing import CliRunner

from assets_lib.sim.simulator import write_run
from assets_lib.store import VersionedStore
from imulab.commands.run import command
from prod_helpers import SHM, small_run, write_realistic_archive

warnings.filterwarnings("ignore")


@pytest.fixture(scope="module")
def lab():
    d = Path(tempfile.mkdtemp(prefix="imulab-summary-", dir=SHM))
    landing = d / "landing"
    good = write_realistic_archive(landing)
    bad_dir = write_run(small_run("TST-A", "tactical", "pc01-pos24", plan="quick_24_position", duration_scale=0.3),
                        landing)
    imu = pd.read_parquet(bad_dir / "imu.parquet")
    imu.loc[1203, "gyro_x"] = np.nan  # a corrupt sample
    imu.to_parquet(bad_dir / "imu.parquet", index=False)
    partial = write_run(small_run("TST-A", "tactical", "pc02-pos24", duration_scale=0.1), landing)
    (partial / "_COMPLETE").unlink()  # the capture job is still writing
    runner = CliRunner()
    args = ["--archive", str(landing), "--data-dir", str(d / "data")]
    first = runner.invoke(command, args)
    second = runner.invoke(command, args)
    yield {"dir": d, "good": good, "first": first, "second": second, "store": VersionedStore(d / "data" / "store"),
           "args": args}
    shutil.rmtree(d, ignore_errors=True)


def test_failed_partition_is_named_with_file_row_and_expectation(lab):
    out = lab["first"]
    assert out.exit_code == 1, out.output
    line = next(l for l in out.output.splitlines() if "FAILED  ingested_run TST-A__pc01-pos24" in l)
    assert "imu.parquet" in line and "row" in line and "expected" in line, line
    assert "status: FAILED (1 failed partition(s); exit status 1)" in out.output


def test_the_good_runs_of_the_batch_are_fitted(lab):
    st = lab["store"]
    assert st.partitions("gyro_rate_fit") == ["TST-A__pc00-rate"]
    assert st.partitions("accel_multiposition_fit") == ["TST-A__pc00-pos24"]
    assert st.partitions("calibration_record") == ["TST-A"]


def test_incomplete_run_reported_as_waiting_and_warnings_counted(lab):
    out = lab["first"].output
    assert "WAITING TST-A__pc02-pos24: no _COMPLETE marker" in out
    assert " warning(s)" in out


def test_unchanged_archive_launches_nothing_and_still_reports_the_failure(lab):
    out = lab["second"]
    assert out.exit_code == 1, out.output
    assert "nothing launched" in out.output
    assert not any(job in out.output for job in ("calibrate_captures run", "calibrate_devices run", "fleet_summary run"))
    assert "FAILED  ingested_run TST-A__pc01-pos24" in out.output


def test_mistyped_archive_is_an_error(lab, tmp_path):
    out = CliRunner().invoke(command, ["--archive", str(lab["dir"] / "landnig"), "--data-dir", str(tmp_path)])
    assert out.exit_code == 2 and "is not a folder" in out.output
    (tmp_path / "empty").mkdir()
    out = CliRunner().invoke(command, ["--archive", str(tmp_path / "empty"), "--data-dir", str(tmp_path)])
    assert out.exit_code == 2 and "no run folders" in out.output


def test_gate_failure_fails_alone(lab, tmp_path):
    """A run whose plateaus fail the gate is rejected with the gate's figure; the other runs are still fitted."""
    landing = tmp_path / "landing"
    shutil.copytree(lab["dir"] / "landing" / "TST-A" / "pc00-rate", landing / "TST-A" / "pc00-rate")
    shutil.copytree(lab["dir"] / "landing" / "TST-A" / "pc00-pos24", landing / "TST-A" / "pc00-pos24")
    # a rate run whose turntable log runs 5 % slow: no table step lasts as planned, every plateau is flagged
    slow = write_run(small_run("TST-B", "navigation", "pc00-rate", plan="quick_rate", duration_scale=0.3), landing)
    table = pd.read_parquet(slow / "table.parquet")
    table["time_s"] *= 1.05
    table.to_parquet(slow / "table.parquet", index=False)
    out = CliRunner().invoke(command, ["--archive", str(landing), "--data-dir", str(tmp_path / "data")])
    assert out.exit_code == 1, out.output
    line = next((l for l in out.output.splitlines() if "FAILED  plateaus TST-B__pc00-rate" in l), out.output[-1500:])
    assert "gate enough_plateaus_kept" in line and "usable plateau" in line, line
    st = VersionedStore(tmp_path / "data" / "store")
    assert st.partitions("gyro_rate_fit") == ["TST-A__pc00-rate"]
    assert st.partitions("accel_multiposition_fit") == ["TST-A__pc00-pos24"]
    assert st.rejection("plateaus", "TST-B__pc00-rate")  # kept for diagnosis, marked rejected
    assert "not computed because an upstream partition failed" in out.output
