"""A calibration ready to apply: the sensor error model of docs/design.md with each term's value, standard error
and the record it came from, built from one calibration record or assembled from a device's records at a date.

Model (docs/design.md "Sensor error model", [SEED000] eq. 1-2)::

    gyro:  y_g = diag(K_g) (I + E_g) w + b_g + G f + n_g
    accel: y_a = diag(K_a) (I + E_a) f + b_a + K2 * f**2 + sum_{j!=i} Kc[i, j] f_i f_j + n_a

Record coefficient names -> terms (sensor, axis i): ``scale_factor`` -> K[i], ``misalignment_ij`` -> E[i, j],
``bias`` -> b[i], ``g_sensitivity_j`` -> G[i, j] (gyro), ``k2`` -> K2[i], ``cross_coupling_ij`` -> Kc[i, j]
(accel). Summary statistics that are not model terms (``sf_nonlinearity``: a maximum deviation; ``sf_asymmetry``,
``scale_factor_pos/neg``: the +/- split of K) are listed as not applied.

Terms come in GROUPS that one fit estimates jointly (their errors are correlated), and a group is always taken
whole from one record:

- ``gyro_scale_misalignment`` (K_g, E_g) from a rate run (``gyro_rate_fit``);
- ``gyro_bias_g`` (b_g, G) from a position or tumble run (``accel_multiposition_fit``: static gyro means with the
  earth rate removed, G separable); when no such record exists, b_g from a rate run (which the rate fit reports
  at the schedule's mean specific force, b + G f_bar) and G absent;
- ``accel`` (K_a, E_a, b_a, K2, Kc) from a position or tumble run;
- ``noise`` (Allan Q, N, B, K, R per channel) from a static run.

A device calibration at date ``at`` takes each group from the device's newest record started at or before
``at`` that holds it (observable), and lists which record (run id, sha256) every term came from. A missing group
leaves the nominal model (K = 1, everything else 0) and is named in ``missing_groups``.
"""

from __future__ import annotations

import hashlib
import json
import math
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
import pandas as pd

AXES = ("x", "y", "z")
SI_UNITS = {("gyro", "bias"): "rad/s", ("accel", "bias"): "m/s^2", ("gyro", "scale_factor"): "1",
            ("accel", "scale_factor"): "1", ("gyro", "misalignment"): "rad", ("accel", "misalignment"): "rad",
            ("gyro", "g_sensitivity"): "rad/s/(m/s^2)", ("accel", "k2"): "1/(m/s^2)",
            ("accel", "cross_coupling"): "1/(m/s^2)"}
GROUPS = {
    "gyro_scale_misalignment": ("gyro", ("scale_factor", "misalignment")),
    "gyro_bias_g": ("gyro", ("bias", "g_sensitivity")),
    "accel": ("accel", ("scale_factor", "misalignment", "bias", "k2", "cross_coupling")),
}
#: record coefficients that are summaries, not terms of the model: never applied (listed in ``not_applied``)
NOT_MODEL_TERMS = ("scale_factor_pos", "scale_factor_neg", "sf_asymmetry", "sf_nonlinearity")
DEVICE_CALIBRATION_KIND = "imulab_device_calibration"


class CalibrationError(ValueError):
    """A record or device calibration that cannot be used (named field and what was expected)."""


def _canonical(obj) -> bytes:
    return json.dumps(obj, sort_keys=True, separators=(",", ":"), ensure_ascii=False, allow_nan=False).encode()


def term_of(sensor: str, axis: str, coefficient: str) -> tuple[str, tuple[int, ...]] | None:
    """(term family, index) of a record coefficient: ('misalignment', (0, 1)) for gyro x misalignment_xy."""
    i = AXES.index(axis)
    if coefficient in ("scale_factor", "bias", "k2"):
        if coefficient == "k2" and sensor != "accel":
            return None
        return coefficient, (i,)
    for fam in ("misalignment", "cross_coupling", "g_sensitivity"):
        if coefficient.startswith(fam + "_"):
            if (fam == "g_sensitivity") != (sensor == "gyro") and fam != "misalignment":
                return None
            tail = coefficient[len(fam) + 1:]
            if fam == "g_sensitivity" and len(tail) == 1 and tail in AXES:
                return fam, (i, AXES.index(tail))
            if fam != "g_sensitivity" and len(tail) == 2 and tail[0] == axis and tail[1] in AXES and tail[1] != axis:
                return fam, (i, AXES.index(tail[1]))
    return None


def group_of(sensor: str, family: str) -> str | None:
    if sensor == "gyro":
        return "gyro_scale_misalignment" if family in ("scale_factor", "misalignment") else "gyro_bias_g"
    return "accel"


@dataclass(frozen=True)
class Triad:
    """One sensor triad's terms (SI) with standard errors; unset terms are nominal with zero standard error."""

    scale: np.ndarray  # (3,) K, dimensionless
    misalignment_rad: np.ndarray  # (3, 3) E, zero diagonal
    bias: np.ndarray  # (3,) rad/s or m/s^2
    scale_stderr: np.ndarray
    misalignment_stderr_rad: np.ndarray
    bias_stderr: np.ndarray
    g_sensitivity: np.ndarray = field(default_factory=lambda: np.zeros((3, 3)))  # gyro: rad/s per m/s^2
    g_sensitivity_stderr: np.ndarray = field(default_factory=lambda: np.zeros((3, 3)))
    k2: np.ndarray = field(default_factory=lambda: np.zeros(3))  # accel: 1/(m/s^2)
    k2_stderr: np.ndarray = field(default_factory=lambda: np.zeros(3))
    cross_coupling: np.ndarray = field(default_factory=lambda: np.zeros((3, 3)))  # accel Kc: 1/(m/s^2)
    cross_coupling_stderr: np.ndarray = field(default_factory=lambda: np.zeros((3, 3)))

    @classmethod
    def nominal(cls) -> Triad:
        z3, z33 = np.zeros(3), np.zeros((3, 3))
        return cls(np.ones(3), z33.copy(), z3.copy(), z3.copy(), z33.copy(), z3.copy())

    def matrix(self) -> np.ndarray:
        """diag(K) (I + E): the linear part of the model."""
        return np.diag(self.scale) @ (np.eye(3) + self.misalignment_rad)


FAMILY_FIELDS = {"scale_factor": ("scale", "scale_stderr"), "misalignment": ("misalignment_rad", "misalignment_stderr_rad"),
                 "bias": ("bias", "bias_stderr"), "g_sensitivity": ("g_sensitivity", "g_sensitivity_stderr"),
                 "k2": ("k2", "k2_stderr"), "cross_coupling": ("cross_coupling", "cross_coupling_stderr")}


@dataclass(frozen=True)
class TermSource:
    """Where one applied term came from."""

    sensor: str
    axis: str
    coefficient: str
    value: float
    stderr: float
    unit: str
    group: str
    run_id: str
    record_sha256: str
    source: str  # the stage that fitted it (gyro_rate_fit, accel_multiposition_fit)


@dataclass(frozen=True)
class Calibration:
    """What ``apply`` needs: both triads, where each term came from, the noise terms, and identity."""

    device_id: str
    gyro: Triad
    accel: Triad
    terms: tuple[TermSource, ...]
    missing_groups: tuple[str, ...]
    not_applied: tuple[str, ...]
    noise: tuple[dict, ...]
    records: tuple[dict, ...]  # run_id, record_sha256, test_kind, start_time_utc, store_version of each used record
    latitude_deg: float | None
    gravity_mps2: float | None
    sample_rate_hz: float | None
    at_utc: str | None = None  # assembled device calibrations: the date it is valid at
    #: (input accel, input gyro, output accel, output gyro) units: SI for records; other tools' calibrations
    #: imported for comparison (``assets_lib.records.export.calibration_from_imucal``) may map counts to deg/s
    units: tuple[str, str, str, str] = ("m/s^2", "rad/s", "m/s^2", "rad/s")
    #: turn-on to turn-on bias repeatability ([SEED000] eq. 23, noise-corrected) from the device's records of
    #: several power cycles up to ``at_utc`` (``turn_on_repeatability``), or None when fewer than 3 cycles
    turn_on_repeatability: dict | None = None

    @property
    def identity_sha256(self) -> str:
        """The one hash naming this calibration: the record's own sha256 for a single record, else the sha256 of the
        canonical device-calibration JSON (which lists every record's sha256)."""
        if len(self.records) == 1 and self.at_utc is None:
            return self.records[0]["record_sha256"]
        return hashlib.sha256(_canonical(self.to_json(with_hash=False))).hexdigest()

    def stderr_vector(self) -> tuple[list[tuple[str, str, str, tuple]], np.ndarray]:
        """Every applied term with a finite standard error, as (sensor, field, family, index) and its stderr."""
        keys, sig = [], []
        for t in self.terms:
            fam, idx = term_of(t.sensor, t.axis, t.coefficient)
            if math.isfinite(t.stderr) and t.stderr > 0:
                keys.append((t.sensor, FAMILY_FIELDS[fam][0], fam, idx))
                sig.append(t.stderr)
        return keys, np.asarray(sig, dtype=float)

    def to_json(self, with_hash: bool = True) -> dict:
        """The device-calibration file (``imulab records DEVICE --at DATE --out``), loadable with ``load_calibration``."""
        out = {
            "kind": DEVICE_CALIBRATION_KIND,
            "format_version": "1.0",
            "device_id": self.device_id,
            "at_utc": self.at_utc,
            "records": list(self.records),
            "terms": [{k: (None if isinstance(v, float) and not math.isfinite(v) else v) for k, v in t.__dict__.items()}
                      for t in self.terms],
            "missing_groups": list(self.missing_groups),
            "not_applied": list(self.not_applied),
            "noise": list(self.noise),
            "latitude_deg": self.latitude_deg,
            "gravity_mps2": self.gravity_mps2,
            "sample_rate_hz": self.sample_rate_hz,
        }
        if self.turn_on_repeatability is not None:  # absent when unknown: files written before it still verify
            out["turn_on_repeatability"] = self.turn_on_repeatability
        if with_hash:
            out["calibration_sha256"] = hashlib.sha256(_canonical(out)).hexdigest()
        return out


# ---------------------------------------------------------------------------------------------------------------
# Building
# ---------------------------------------------------------------------------------------------------------------
def _record_info(record: dict, store_version: str | None = None) -> dict:
    c = record["content"]
    return {"run_id": c["run"]["run_id"], "record_sha256": record["record_sha256"],
            "record_schema_version": record.get("record_schema_version"),
            "test_kind": c["run"]["test_kind"], "start_time_utc": c["run"]["start_time_utc"],
            "power_cycle_index": c["run"].get("power_cycle_index"), "store_version": store_version}


def check_record(record: dict, name: str = "record") -> None:
    """Structure and SI units of a record's coefficients (a record in lab units would be applied wrongly)."""
    if not isinstance(record, dict) or "content" not in record or "record_sha256" not in record:
        raise CalibrationError(f"{name}: expected a calibration record (keys 'record_sha256', 'content'), found keys "
                               f"{sorted(record)[:8] if isinstance(record, dict) else type(record).__name__}")
    for k, c in enumerate(record["content"].get("coefficients", [])):
        t = term_of(c["sensor"], c["axis"], c["coefficient"])
        if t is None:
            continue
        want = SI_UNITS[(c["sensor"], t[0])]
        if c.get("unit") != want:
            raise CalibrationError(f"{name}: coefficients[{k}] ({c['sensor']} {c['axis']} {c['coefficient']}): "
                                   f"expected SI unit {want!r}, found {c.get('unit')!r}")


def _groups_in_record(record: dict) -> dict[str, list[dict]]:
    """group -> the record's observable coefficient rows of that group (rate-fit gyro biases are kept apart)."""
    out: dict[str, list[dict]] = {}
    for c in record["content"].get("coefficients", []):
        t = term_of(c["sensor"], c["axis"], c["coefficient"])
        if t is None or not c.get("observable") or c.get("value") is None:
            continue
        g = group_of(c["sensor"], t[0])
        if g == "gyro_bias_g" and c.get("source") == "gyro_rate_fit":
            g = "gyro_bias_rate"  # b + G f_bar of the rate schedule: a fallback only
        out.setdefault(g, []).append(c)
    return out


def _complete(group: str, rows: list[dict]) -> bool:
    """A group counts as held by a record when its primary terms are there for all three axes."""
    have = {(r["axis"], term_of(r["sensor"], r["axis"], r["coefficient"])[0]) for r in rows}
    need = {"gyro_scale_misalignment": ("scale_factor",), "gyro_bias_g": ("bias",), "gyro_bias_rate": ("bias",),
            "accel": ("scale_factor", "bias")}[group]
    return all((a, f) in have for a in AXES for f in need)


def _build(device_id: str, picks: dict[str, tuple[dict, list[dict], str | None]], all_records: list[dict],
           at_utc: str | None, noise_record: dict | None) -> Calibration:
    fields = {"gyro": {k: v for k, v in Triad.nominal().__dict__.items()},
              "accel": {k: v for k, v in Triad.nominal().__dict__.items()}}
    for s in fields:
        fields[s] = {k: np.array(v, dtype=float) for k, v in fields[s].items()}
    terms, used = [], {}
    for group, (rec, rows, ver) in picks.items():
        used[rec["record_sha256"]] = _record_info(rec, ver)
        for c in rows:
            fam, idx = term_of(c["sensor"], c["axis"], c["coefficient"])
            vf, sf = FAMILY_FIELDS[fam]
            fields[c["sensor"]][vf][idx] = float(c["value"])
            se = c.get("stderr")
            fields[c["sensor"]][sf][idx] = float(se) if se is not None else np.nan
            terms.append(TermSource(c["sensor"], c["axis"], c["coefficient"], float(c["value"]),
                                    float(se) if se is not None else math.nan, c["unit"],
                                    "gyro_bias_g" if group == "gyro_bias_rate" else group,
                                    rec["content"]["run"]["run_id"], rec["record_sha256"], c.get("source", "")))
    if noise_record is not None:
        used.setdefault(noise_record["record_sha256"], _record_info(noise_record))
    have = {("gyro_bias_g" if g == "gyro_bias_rate" else g) for g in picks}
    missing = tuple(g for g in GROUPS if g not in have) + (() if noise_record is not None else ("noise",))
    not_applied = sorted({f"{c['sensor']} {c['axis']} {c['coefficient']}" for r in all_records
                          for c in r["content"].get("coefficients", [])
                          if c.get("observable") and c["coefficient"] in NOT_MODEL_TERMS})
    ref = (noise_record or next(iter(picks.values()))[0] if (picks or noise_record) else None)
    tc = ref["content"]["test_conditions"] if ref else {}
    rate = ref["content"]["run"].get("sample_rate_hz") if ref else None
    noise = tuple(n for n in (noise_record["content"].get("noise", []) if noise_record else []))
    return Calibration(device_id, Triad(**fields["gyro"]), Triad(**fields["accel"]),
                       tuple(sorted(terms, key=lambda t: (t.sensor, t.axis, t.coefficient))), missing,
                       tuple(not_applied), noise, tuple(used.values()), tc.get("latitude_deg"), tc.get("gravity_mps2"),
                       (noise_record["content"]["run"]["sample_rate_hz"] if noise_record else rate), at_utc)


def calibration_from_record(record: dict, store_version: str | None = None, name: str = "record") -> Calibration:
    """The calibration held by ONE record (its groups only; the others stay nominal and are listed missing)."""
    check_record(record, name)
    if record["content"].get("status") == "invalid":
        raise CalibrationError(f"{name}: the record of run {record['content']['run']['run_id']} is marked invalid, "
                               "not a valid calibration: " + "; ".join(record["content"].get("status_reasons") or []))
    groups = _groups_in_record(record)
    picks = {g: (record, rows, store_version) for g, rows in groups.items() if _complete(g, rows)}
    if "gyro_bias_g" in picks:
        picks.pop("gyro_bias_rate", None)
    noise = record if record["content"].get("noise") else None
    return _build(record["content"]["device"]["id"], picks, [record], None, noise)


def _start(record: dict) -> pd.Timestamp:
    return pd.Timestamp(record["content"]["run"]["start_time_utc"]).tz_convert("UTC")


def to_utc(at) -> pd.Timestamp:
    ts = pd.Timestamp(at)
    return ts.tz_localize("UTC") if ts.tzinfo is None else ts.tz_convert("UTC")


def assemble(records: list[dict], at=None, store_version: str | None = None) -> Calibration:
    """Device calibration valid at ``at`` (default: now): each group from the newest record started at or before
    ``at`` that holds it; records of other devices are refused."""
    if not records:
        raise CalibrationError("no calibration records given")
    devices = {r["content"]["device"]["id"] for r in records}
    if len(devices) != 1:
        raise CalibrationError(f"records of several devices given: {sorted(devices)}")
    for r in records:
        check_record(r, r["content"]["run"]["run_id"])
    at_ts = to_utc(at) if at is not None else pd.Timestamp.now(tz="UTC")
    valid = sorted((r for r in records if _start(r) <= at_ts and r["content"].get("status") != "invalid"),
                   key=lambda r: (_start(r), r["content"]["run"]["run_id"]), reverse=True)  # never an invalid record
    if not valid:
        first = min(_start(r) for r in records)
        raise CalibrationError(f"device {devices.pop()}: no record started at or before {at_ts.isoformat()} "
                               f"(first record {first.isoformat()})")
    picks: dict[str, tuple[dict, list[dict], str | None]] = {}
    for g in ("gyro_scale_misalignment", "gyro_bias_g", "accel"):
        for r in valid:
            rows = _groups_in_record(r).get(g, [])
            if rows and _complete(g, rows):
                picks[g] = (r, rows, store_version)
                break
    if "gyro_bias_g" not in picks:
        for r in valid:
            rows = _groups_in_record(r).get("gyro_bias_rate", [])
            if rows and _complete("gyro_bias_rate", rows):
                picks["gyro_bias_rate"] = (r, rows, store_version)
                break
    noise = next((r for r in valid if r["content"].get("noise")), None)
    cal = _build(next(iter(devices)), picks, valid, at_ts.isoformat(), noise)
    rep = turn_on_repeatability(valid)
    return replace(cal, turn_on_repeatability=rep) if rep is not None else cal


#: power cycles needed before a turn-on repeatability is stated (2 give one degree of freedom: +/-100 % on sigma)
MIN_POWER_CYCLES = 3


def turn_on_repeatability(records: list[dict]) -> dict | None:
    """Bias repeatability per triad and axis over the device's power cycles ([SEED000] eq. 23, noise-corrected:
    sqrt(max(0, s^2 - mean stderr^2)), ``assets_lib.calibration.repeatability``): for each power cycle the newest
    record holding the group's bias (accelerometer: position/tumble runs; gyro: static gyro biases of those runs).
    None when no triad has ``MIN_POWER_CYCLES`` cycles."""
    from assets_lib.calibration.repeatability import bias_repeatability

    out = {}
    for sensor, group in (("accel", "accel"), ("gyro", "gyro_bias_g")):
        per_cycle: dict[int, dict] = {}
        for r in sorted(records, key=lambda r: (_start(r), r["content"]["run"]["run_id"]), reverse=True):
            rows = _groups_in_record(r).get(group, [])
            pc = r["content"]["run"].get("power_cycle_index")
            if pc is None or pc in per_cycle or not (rows and _complete(group, rows)):
                continue
            per_cycle[pc] = {c["axis"]: (float(c["value"]), c.get("stderr")) for c in rows if c["coefficient"] == "bias"}
        if len(per_cycle) < MIN_POWER_CYCLES:
            continue
        sig = []
        for a in AXES:
            v = [d[a][0] for d in per_cycle.values()]
            se = [np.nan if d[a][1] is None else float(d[a][1]) for d in per_cycle.values()]
            rep = bias_repeatability(v, se)
            sig.append(rep.std_noise_corrected if math.isfinite(rep.std_noise_corrected) else rep.std)
        out[sensor] = sig
        out[sensor + "_power_cycles"] = sorted(per_cycle)
    return out or None


def calibration_from_json(doc: dict) -> Calibration:
    """Inverse of ``Calibration.to_json`` (a device-calibration file); its hash is checked."""
    if doc.get("kind") != DEVICE_CALIBRATION_KIND:
        raise CalibrationError(f"expected 'kind': {DEVICE_CALIBRATION_KIND!r}, found {doc.get('kind')!r}")
    want = doc.get("calibration_sha256")
    body = {k: v for k, v in doc.items() if k != "calibration_sha256"}
    got = hashlib.sha256(_canonical(body)).hexdigest()
    if want != got:
        raise CalibrationError(f"calibration_sha256 {str(want)[:16]}... is not the sha256 of the file's content "
                               f"({got[:16]}...): the file was edited")
    tri = {s: {k: np.array(v, dtype=float) for k, v in Triad.nominal().__dict__.items()} for s in ("gyro", "accel")}
    terms = []
    for t in doc["terms"]:
        fam, idx = term_of(t["sensor"], t["axis"], t["coefficient"])
        vf, sf = FAMILY_FIELDS[fam]
        tri[t["sensor"]][vf][idx] = t["value"]
        tri[t["sensor"]][sf][idx] = t["stderr"] if t["stderr"] is not None else np.nan
        terms.append(TermSource(**{k: (math.nan if (k == "stderr" and v is None) else v) for k, v in t.items()}))
    return Calibration(doc["device_id"], Triad(**tri["gyro"]), Triad(**tri["accel"]), tuple(terms),
                       tuple(doc["missing_groups"]), tuple(doc["not_applied"]), tuple(doc["noise"]),
                       tuple(doc["records"]), doc["latitude_deg"], doc["gravity_mps2"], doc["sample_rate_hz"],
                       doc["at_utc"], turn_on_repeatability=doc.get("turn_on_repeatability"))


def load_calibration(path: str | Path) -> Calibration:
    """A record JSON (``<run>.json`` of the calibration_record store) or a device-calibration JSON."""
    p = Path(path)
    try:
        doc = json.loads(p.read_text(encoding="utf-8"))
    except (OSError, json.JSONDecodeError, UnicodeDecodeError) as e:
        raise CalibrationError(f"{p}: not a readable JSON file ({e})") from None
    if isinstance(doc, dict) and doc.get("kind") == DEVICE_CALIBRATION_KIND:
        return calibration_from_json(doc)
    version = p.parent.name if (p.parent / "records.parquet").is_file() else None
    return calibration_from_record(doc, store_version=version, name=str(p))
