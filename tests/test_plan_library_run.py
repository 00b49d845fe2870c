"""Every plan of the plan library, for all three grades, through a real ``imulab run`` (issue 10, item 1): every
rate run gets a rate fit, every position or tumble run a multi-position fit, every static run an Allan analysis,
or the run fails alone and the summary names it with its reason. Dwell times are cut to a tenth (whole
revolutions are kept, so the seed 000 full-revolution plan keeps its length), to 0.3 for the short quick and
tumble plans, and the static record to 300 s.

The archive and its ``imulab run`` are this module's background job ``run_library`` (tests/conftest.py): it runs in
a second process from the start of the session, and the test makes its assertions on the store and summary it left."""

from __future__ import annotations

import json
import warnings
from pathlib import Path

import pytest

from assets_lib.store import VersionedStore, capture_key

warnings.filterwarnings("ignore")
DEVICES = (("NAV-001", "navigation"), ("TAC-002", "tactical"), ("CON-003", "consumer"))
RESULT_STAGE = {"rate": "gyro_rate_fit", "multiposition": "accel_multiposition_fit",
                "tumble": "accel_multiposition_fit", "static": "allan_deviation"}
BACKGROUND_JOBS = ("run_library",)  # run in a second process from the start of the session (tests/conftest.py)


def run_library(d: Path) -> None:
    """Every plan x grade into one landing folder, one ``imulab run`` over it; the run's output, exit status and
    the plan of every partition go to ``d / "result.json"``."""
    from click.testing import CliRunner

    from assets_lib.sim.plans import available_plans, build_plan, load_template
    from assets_lib.sim.simulator import example_device, simulate_run, write_run
    from imulab.commands.run import command

    landing, runs = d / "landing", {}
    for dev, grade in DEVICES:
        truth = example_device(dev, grade, 2026)
        for i, plan in enumerate(available_plans()):
            kind = load_template(plan)["test_kind"]
            # long plans at a tenth of their dwell times; short ones at 0.3 (a tenth leaves windows too short)
            scale = 0.1 if build_plan(load_template(plan)).end_s > 1000 else 0.3
            kwargs = {"static_duration_s": 300.0} if kind == "static" else {"duration_scale": scale}
            run = simulate_run(truth, plan, f"p{i}-{plan.replace('_', '-')}", seed=2026, plan_kwargs=kwargs,
                               table_log=kind != "static")
            write_run(run, landing, "parquet")
            runs[capture_key(dev, run.manifest.run_id)] = (plan, kind)
    # the calibration stages are under test: the costly sim-to-real diagnosis (tests/test_diagnosis.py) is left
    # out with --skip-stage, which must leave no trace of it
    res = CliRunner().invoke(command, ["--archive", str(landing), "--data-dir", str(d / "data"),
                                       "--skip-stage", "sim_to_real"])
    (d / "result.json").write_text(json.dumps({"exit_code": res.exit_code, "output": res.output, "runs": runs,
                                               "exception": repr(res.exception)}))


@pytest.mark.slow
def test_every_plan_every_grade_is_fitted_or_fails_alone_with_its_reason(background_job):
    d = background_job("run_library")
    result = json.loads((d / "result.json").read_text())
    runs = {k: tuple(v) for k, v in result["runs"].items()}
    out = result["output"]
    assert "summary:" in out, (result["exception"], out[-3000:])
    st = VersionedStore(d / "data" / "store")
    assert st.partitions("sim_to_real") == [], "--skip-stage sim_to_real ran the stage"
    failed_lines = [l for l in out.splitlines() if l.startswith("  FAILED  ")]
    fitted, failed = [], []
    for key, (plan, kind) in sorted(runs.items()):
        stage = RESULT_STAGE[kind]
        if st.current_version(stage, key) is not None and st.rejection(stage, key) is None:
            fitted.append(key)
            continue
        mine = [l for l in failed_lines if f" {key}: " in l]
        assert mine, f"{key} ({plan}): no {stage} and no failure named in the summary\n{out[-3000:]}"
        assert all(len(l.split(f" {key}: ", 1)[1]) > 10 for l in mine), mine  # a reason, not just a name
        failed.append((key, mine))
    assert result["exit_code"] == (1 if failed else 0), out[-3000:]
    print(f"\n{len(fitted)} of {len(runs)} runs fitted; failed alone: {failed}")
    # a failure never takes the other runs of its batch with it: every device's other runs are fitted
    for dev, _ in DEVICES:
        assert any(k.startswith(dev) for k in fitted)
    assert len(fitted) >= len(runs) - len(failed) and not failed, failed

