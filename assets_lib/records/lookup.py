"""Which calibration was valid for a device at a date: list the device's records in the store, pick the newest at
or before the date, assemble the device calibration (``assets_lib.apply.model.assemble``), and warn when a term
is older than a maximum age (imucal's ``find_closest_calibration_info_to_date`` warns past 30 days, our default)
or when the fleet-drift stage has flagged the device since the record was made.

Store layout read (``assets_lib.store``, read as files):
``<store>/calibration_record/<device>/CURRENT`` names the version folder holding ``<run>.json`` records;
``<store>/fleet_drift/fleet/CURRENT`` names the version folder holding ``drift.parquet`` (one row per device and
coefficient series: ``drift_flag``, ``shift_flag``, ``shift_run_id``, ``cusum_alarm_run_id``, ``last_run_id``) and
``drift_points.parquet`` (one row per run: ``start_time_utc``, ``beyond_limits``, ``shift_here``).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import pandas as pd

from assets_lib.apply.model import (
    Calibration,
    CalibrationError,
    _groups_in_record,
    _start,
    assemble,
    to_utc,
)

DEFAULT_MAX_AGE_DAYS = 30.0
RECORD_ASSET = "calibration_record"
DRIFT_ASSET = "fleet_drift"


def _current_dir(store: Path, asset: str, partition: str) -> Path | None:
    pdir = Path(store) / asset / partition
    cur = pdir / "CURRENT"
    if not cur.is_file():
        return None
    d = pdir / cur.read_text().strip()
    return d if d.is_dir() else None


def device_records(store: str | Path, device: str) -> tuple[list[dict], str]:
    """The device's records in the store's current version (chain order) and that version's name."""
    d = _current_dir(Path(store), RECORD_ASSET, device)
    if d is None:
        known = sorted(p.name for p in (Path(store) / RECORD_ASSET).iterdir()) if (Path(store) / RECORD_ASSET).is_dir() else []
        raise CalibrationError(f"no calibration records of device {device!r} in {store} "
                               f"(devices with records: {', '.join(known) or 'none'})")
    recs = []
    for p in sorted(d.glob("*.json")):
        if p.name == "meta.json":
            continue
        try:
            r = json.loads(p.read_text(encoding="utf-8"))
        except (json.JSONDecodeError, UnicodeDecodeError) as e:
            raise CalibrationError(f"{p}: not valid JSON ({e})") from None
        if isinstance(r, dict) and "content" in r:
            recs.append(r)
    recs.sort(key=lambda r: (_start(r), r["content"]["run"]["run_id"]))
    return recs, d.name


def records_table(records: list[dict]) -> pd.DataFrame:
    """One row per record: run, kind, start, sha256, which calibration groups it holds."""
    rows = []
    for r in records:
        c = r["content"]
        groups = sorted(g.replace("gyro_bias_rate", "gyro_bias(rate)") for g in _groups_in_record(r))
        if c.get("noise"):
            groups.append("noise")
        rows.append({"run_id": c["run"]["run_id"], "test_kind": c["run"]["test_kind"],
                     "start_time_utc": _start(r), "record_sha256": r["record_sha256"], "status": c.get("status", ""),
                     "n_coefficients": len(c.get("coefficients", [])), "holds": ", ".join(groups) or "-"})
    return pd.DataFrame(rows, columns=["run_id", "test_kind", "start_time_utc", "record_sha256", "status",
                                       "n_coefficients", "holds"])


def drift_flags(store: str | Path, device: str) -> pd.DataFrame:
    """The device's fleet-drift events: (sensor, axis, coefficient, kind, run_id, start_time_utc, detail)."""
    cols = ["sensor", "axis", "coefficient", "kind", "run_id", "start_time_utc", "detail"]
    d = _current_dir(Path(store), DRIFT_ASSET, "fleet")
    if d is None or not (d / "drift.parquet").is_file():
        return pd.DataFrame(columns=cols)
    series = pd.read_parquet(d / "drift.parquet")
    series = series[series["device_id"] == device]
    pts = pd.read_parquet(d / "drift_points.parquet") if (d / "drift_points.parquet").is_file() else pd.DataFrame()
    pts = pts[pts["device_id"] == device] if len(pts) else pts
    start = {r: to_utc(t) for r, t in zip(pts.get("run_id", []), pts.get("start_time_utc", []))}
    out = []
    for s in series.itertuples():
        key = (s.sensor, s.axis, s.coefficient)
        if bool(s.drift_flag):
            out.append((*key, "drift", s.last_run_id, start.get(s.last_run_id),
                        f"trend {s.slope_per_day:.3g} {s.unit}/day (z = {s.trend_z:.2f})"))
        if bool(s.shift_flag):
            rid = s.shift_run_id or s.cusum_alarm_run_id
            out.append((*key, "shift", rid, start.get(rid), f"step {s.shift_size:.3g} {s.unit} (CUSUM max "
                                                             f"{s.cusum_max:.2f})"))
    if len(pts):
        for p in pts[pts["beyond_limits"].astype(bool)].itertuples():
            out.append((p.sensor, p.axis, p.coefficient, "beyond control limits", p.run_id, to_utc(p.start_time_utc),
                        f"value {p.value:.6g} {p.unit} outside [{p.lcl:.6g}, {p.ucl:.6g}]"))
    return pd.DataFrame(out, columns=cols)


@dataclass(frozen=True)
class Lookup:
    """Answer of ``lookup``: the device's records, the one valid at the date, the assembled calibration, warnings."""

    device_id: str
    at_utc: pd.Timestamp
    table: pd.DataFrame
    valid_run_id: str
    calibration: Calibration
    store_version: str
    warnings: tuple[str, ...]


def lookup(store: str | Path, device: str, at=None, max_age_days: float = DEFAULT_MAX_AGE_DAYS) -> Lookup:
    """The record valid for ``device`` at ``at`` (default now) and the device calibration assembled there; warnings
    for every used record older than ``max_age_days`` at ``at`` and every fleet-drift event of the device at or
    after the start of the oldest record whose coefficients are used (the device changed since it was calibrated)."""
    records, version = device_records(store, device)
    at_ts = to_utc(at) if at is not None else pd.Timestamp.now(tz="UTC")
    cal = assemble(records, at_ts, store_version=version)
    table = records_table(records)
    valid = table[(table["start_time_utc"] <= at_ts) & (table["status"] != "invalid")].iloc[-1]
    warnings = []
    for r in cal.records:
        age = (at_ts - to_utc(r["start_time_utc"])).total_seconds() / 86400.0
        if age > max_age_days:
            used_for = sorted({t.group for t in cal.terms if t.record_sha256 == r["record_sha256"]}) or ["noise"]
            warnings.append(f"record {r['run_id']} ({', '.join(used_for)}) is {age:.1f} days old at "
                            f"{at_ts.date()} (maximum age {max_age_days:g} days)")
    for r in records:
        c = r["content"]
        if c.get("status") == "invalid" and to_utc(_start(r)) <= at_ts:
            warnings.append(f"record {c['run']['run_id']} is marked invalid and not used: "
                            + "; ".join(c.get("status_reasons") or []))
    for g in cal.missing_groups:
        warnings.append(f"no record of {device} at or before {at_ts.date()} holds {g}: it stays uncalibrated")
    term_records = {t.record_sha256 for t in cal.terms}
    used = [r for r in cal.records if r["record_sha256"] in term_records]
    if used:
        since = min(to_utc(r["start_time_utc"]) for r in used)
        ev = drift_flags(store, device)
        for e in ev.itertuples():
            if e.start_time_utc is not None and not pd.isna(e.start_time_utc) and since <= e.start_time_utc <= at_ts:
                warnings.append(f"fleet drift flagged {device} {e.sensor} {e.axis} {e.coefficient} ({e.kind}) at run "
                                f"{e.run_id} ({e.start_time_utc.date()}), after the calibration used: {e.detail}")
    return Lookup(device, at_ts, table, str(valid["run_id"]), cal, version, tuple(warnings))
