"""End to end: ``imulab import imucal ... && imulab run --archive ...`` calibrates a real hand-moved session and
writes its record and certificate with the table-free coefficients."""

from __future__ import annotations

import json

import numpy as np
import pytest
from click.testing import CliRunner

from imulab.cli import main


@pytest.mark.slow
def test_import_then_run_writes_record_with_tablefree_coefficients(shared_data, tmp_path, monkeypatch):
    monkeypatch.delenv("DAGSTER_HOME", raising=False)
    land = tmp_path / "land"
    r = CliRunner().invoke(main, ["import", "imucal", str(shared_data / "imucal_example" / "annotated_session.csv"),
                                  "--landing", str(land), "--device-id", "bmi160", "--run-id", "ferraris1",
                                  "--gravity-mps2", "9.81", "-o", "sample_rate_hz=204.8",
                                  "-o", f"accel_lsb={1 / 2048}", "-o", f"gyro_lsb={1 / 16.4}"])
    assert r.exit_code == 0, r.output
    r = CliRunner().invoke(main, ["run", "--certificates", "--archive", str(land), "--data-dir", str(tmp_path / "data")])
    assert r.exit_code == 0, r.output
    recs = list((tmp_path / "data" / "store" / "calibration_record" / "bmi160").glob("*/ferraris1.json"))
    assert len(recs) == 1
    rec = json.loads(recs[0].read_text())
    coefs = [c for c in rec["content"]["coefficients"] if c["source"] == "tablefree_fit"]
    assert len(coefs) == 2 * (3 + 3 + 6) + 9 and all(c["method"] == "ferraris" for c in coefs)
    ref = json.loads((shared_data / "imucal_example" / "example_cal.json").read_text())
    kx = next(c for c in coefs if c["sensor"] == "accel" and c["axis"] == "x" and c["coefficient"] == "scale_factor")
    # K_a in canonical (nominal) m/s^2 per m/s^2 = imucal's counts per m/s^2 x the declared lsb
    assert kx["value"] == pytest.approx(ref["K_a"][0][0] * 9.80665 / 2048, rel=1e-9)
    assert np.isfinite(kx["stderr"]) and kx["stderr"] > 0
    html = next((tmp_path / "data" / "store" / "certificate" / "bmi160").glob("*/ferraris1.html")).read_text()
    assert "No coefficients are fitted from this test kind" not in html and "tablefree" in html
