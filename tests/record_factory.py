"""Calibration records for the use-a-record tests, made by the real science code without Dagster: simulate a run,
ingest it (raw_schemas), segment it, fit it (assets_lib.calibration) and wrap the coefficient table as a record
(the JSON layout of raw_schemas/record.schema.json, hashed like assets_lib.records)."""

from __future__ import annotations

import copy
import hashlib
import json
import pickle
import warnings
from collections import OrderedDict
from datetime import datetime, timezone
from pathlib import Path

import numpy as np
import pandas as pd

from assets_lib.calibration.multiposition import (
    fit_accel_multiposition,
    fit_gyro_static,
)
from assets_lib.calibration.rate_fit import fit_gyro_rate
from assets_lib.calibration.segmentation import segment_run
from assets_lib.sim.simulator import SiteSpec, simulate_run
from raw_schemas.readers import ingest_frames

FIELDS = ("sensor", "axis", "coefficient", "value", "stderr", "unit", "value_lab", "stderr_lab", "unit_lab",
          "observable", "n_plateaus", "n_samples", "method")
SOURCE = {"rate": "gyro_rate_fit", "multiposition": "accel_multiposition_fit", "tumble": "accel_multiposition_fit"}


def plateaus_of(run) -> pd.DataFrame:
    warnings.filterwarnings("ignore")
    ing = ingest_frames(run.manifest, run.imu_raw, run.table_raw)
    return segment_run(run.manifest, ing.imu, ing.table).plateaus


def coefficients_of(plateaus: pd.DataFrame, kind: str) -> pd.DataFrame:
    if kind == "rate":
        return fit_gyro_rate(plateaus).coefficient_table()
    return pd.concat([fit_accel_multiposition(plateaus).coefficient_table(),
                      fit_gyro_static(plateaus).coefficient_table()], ignore_index=True)


def _clean(v):
    if isinstance(v, (np.floating, float)):
        return float(v) if np.isfinite(v) else None
    if isinstance(v, (np.integer,)):
        return int(v)
    if isinstance(v, np.bool_):
        return bool(v)
    return v


def make_record(run, coefficients: pd.DataFrame | None, noise: list[dict] | None = None,
                prev: str | None = None) -> dict:
    m = run.manifest
    rows = []
    for r in (coefficients.to_dict(orient="records") if coefficients is not None else []):
        row = {f: _clean(r.get(f)) for f in FIELDS}
        row["source"] = SOURCE[m.test_kind]
        rows.append(row)
    content = {
        "record_schema_version": "1.0",
        "device": {"id": m.device.id, "model": m.device.model, "grade": m.device.grade, "serial": None},
        "run": {"run_id": m.run_id, "test_kind": m.test_kind, "start_time_utc": m.start_time_utc.isoformat(),
                "power_cycle_index": m.power_cycle_index, "table_id": m.table_id, "sample_rate_hz": m.sample_rate_hz,
                "n_samples": int(len(run.imu_raw)), "duration_s": float(run.imu_raw["time_s"].iloc[-1])},
        "test_conditions": {"site": m.site.model_dump(mode="json"), "latitude_deg": m.site.latitude_deg,
                            "gravity_mps2": SiteSpec().gravity_mps2, "temperature_degc": None,
                            "plan": {"name": m.plan.name, "frame": m.plan.frame}},
        "raw_files": {"imu.parquet": "0" * 64}, "coefficients": rows, "noise": noise or [], "stages": {},
        "software": {"imulab_version": "test", "git_commit": "unknown", "git_dirty": None},
        "prev_record_sha256": prev,
    }
    sha = hashlib.sha256(json.dumps(content, sort_keys=True, separators=(",", ":"), ensure_ascii=False,
                                    allow_nan=False).encode()).hexdigest()
    return {"record_schema_version": "1.0", "record_sha256": sha, "content": content,
            "provenance": {"created_utc": "2026-01-01T00:00:00Z", "dagster_run_id": None}}


#: fitted_record's last few results by their arguments (a deterministic function of them: seeded simulation, fixed
#: fits): several tests of a module fit the same runs; each call gets its own deep copy (tests edit records in place)
_FITTED: OrderedDict[bytes, tuple[dict, object, pd.DataFrame]] = OrderedDict()
_FITTED_MAX = 4


def fitted_record(truth, plan: str, run_id: str, seed: int, start: datetime, **kw) -> tuple[dict, object, pd.DataFrame]:
    """(record, simulated run, plateaus) of one simulated and fitted run."""
    key = pickle.dumps((truth, plan, run_id, seed, start, sorted(kw.items())))
    if key not in _FITTED:
        run = simulate_run(truth, plan, run_id, seed=seed, start_time_utc=start, **kw)
        p = plateaus_of(run)
        _FITTED[key] = (make_record(run, coefficients_of(p, run.manifest.test_kind)), run, p)
        while len(_FITTED) > _FITTED_MAX:
            _FITTED.popitem(last=False)
    _FITTED.move_to_end(key)
    return copy.deepcopy(_FITTED[key])


def noise_rows(n_gyro: float, k_gyro: float | None, n_accel: float, k_accel_upper: float) -> list[dict]:
    """Allan noise rows in the record's layout (identified N and K, or K only as an upper bound)."""
    rows = []
    for sensor, n, k, kub in (("gyro", n_gyro, k_gyro, None), ("accel", n_accel, None, k_accel_upper)):
        unit = "radps" if sensor == "gyro" else "mps2"
        for i, ax in enumerate("xyz"):
            ch = f"{sensor}_{ax}_{unit}"
            rows.append({"channel": ch, "parameter": "N", "method": "fit", "value": n * (1 + 0.01 * i),
                         "ci_lo": n * 0.98, "ci_hi": n * 1.02, "ci_level": 0.95, "is_upper_bound": False})
            if k is not None:
                rows.append({"channel": ch, "parameter": "K", "method": "fit", "value": k * (1 + 0.1 * i),
                             "ci_lo": k * 0.5, "ci_hi": k * 2, "ci_level": 0.95, "is_upper_bound": False})
            else:
                rows.append({"channel": ch, "parameter": "K", "method": "fit", "value": None, "ci_lo": 0.0,
                             "ci_hi": kub * (1 + 0.1 * i), "ci_level": 0.95, "is_upper_bound": True})
    return rows


def write_store_records(store: Path, records: list[dict], version: str = "v0001") -> Path:
    """``<store>/calibration_record/<device>/<version>/<run>.json`` + CURRENT, as the pipeline stores them."""
    dev = records[0]["content"]["device"]["id"]
    d = Path(store) / "calibration_record" / dev / version
    d.mkdir(parents=True, exist_ok=True)
    for r in records:
        (d / f"{r['content']['run']['run_id']}.json").write_text(json.dumps(r, indent=1, sort_keys=True))
    pd.DataFrame({"run_id": [r["content"]["run"]["run_id"] for r in records],
                  "record_sha256": [r["record_sha256"] for r in records]}).to_parquet(d / "records.parquet")
    (d.parent / "CURRENT").write_text(version)
    return d


T0 = datetime(2026, 3, 2, 8, 0, tzinfo=timezone.utc)
