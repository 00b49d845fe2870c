"""imucal annotated Ferraris sessions (Kuederle et al., imucal, JOSS): a CSV with a ``part`` column naming the
section of every row (``x_p``, ``x_a``, ``y_p``, ``y_a``, ``z_p``, ``z_a``: that axis up / down; ``x_rot``,
``y_rot``, ``z_rot``: one hand turn about that axis), an optional sample counter ``samples`` (or ``n_samples``)
and the columns ``acc_x, acc_y, acc_z, gyr_x, gyr_y, gyr_z``.

Rows are ordered by the sample counter (imucal writes the file sorted by section name); the time axis is
``samples / sample_rate_hz`` (option ``sample_rate_hz``, required: the file does not carry it). Every section
becomes a plan step: ``pose`` with ``up_axis_body`` for ``*_p`` / ``*_a``, ``rotation`` with
``rotation_axis_body`` and ``rotation_angle_deg`` (option ``expected_angle_deg``, imucal's default -360) for
``*_rot``. Integer-valued data are counts (options ``accel_lsb``/``accel_lsb_unit``, ``gyro_lsb``/
``gyro_lsb_unit``); otherwise options ``accel_unit`` (default m/s^2) and ``gyro_unit`` (default deg/s).
Sections must be contiguous in the counter: a hole inside a section is a gap the contract refuses.

A continuous recording without a ``part`` column (imucal's ``example_ferraris_session.csv``) is imported with
its section list (option ``sections=LIST.json``, imucal's ``{"x_p": {"start": s, "end": e}, ...}`` with
``end`` exclusive, as imucal slices ``data.iloc[start:end]``): every row is kept, the sections become steps.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

from raw_schemas.errors import RawDataError
from raw_schemas.importers.common import ImportedSession, option_float, sha256_sources

SECTIONS = ("x_p", "x_a", "y_p", "y_a", "z_p", "z_a", "x_rot", "y_rot", "z_rot")
DATA_COLUMNS = ("acc_x", "acc_y", "acc_z", "gyr_x", "gyr_y", "gyr_z")

#: the ``-o KEY=VALUE`` options this importer reads (key -> one-line description); any other key is refused
OPTIONS = {
    "sample_rate_hz": "the session's sample rate in Hz (required: imucal files do not store it)",
    "sections": "section list JSON for a continuous recording without a 'part' column",
    "expected_angle_deg": "angle of each hand rotation in deg (default -360)",
    "accel_lsb": "value of one accelerometer count (required for integer counts)",
    "accel_lsb_unit": "unit of accel_lsb (default g)",
    "accel_unit": "unit of non-integer accelerometer values (default m/s^2)",
    "gyro_lsb": "value of one gyro count (required for integer counts)",
    "gyro_lsb_unit": "unit of gyro_lsb (default deg/s)",
    "gyro_unit": "unit of non-integer gyro values (default deg/s)",
}


def _spec(vals: np.ndarray, fam: str, options: dict, file: str) -> dict:
    if np.all(vals == np.round(vals)):
        lsb = option_float(options, f"{fam}_lsb", file, required_for=f"the value of one {fam} count: the data are integer counts")
        return {"unit": "counts", "lsb": lsb, "lsb_unit": options.get(f"{fam}_lsb_unit", "g" if fam == "accel" else "deg/s")}
    return {"unit": options.get(f"{fam}_unit", "m/s^2" if fam == "accel" else "deg/s")}


def _label_from_section_list(df: pd.DataFrame, path: Path, data_name: str) -> pd.DataFrame:
    import json

    try:
        sec = json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise RawDataError(str(path), "", "a section list JSON (option 'sections')", "no such file") from None
    except json.JSONDecodeError as e:
        raise RawDataError(path.name, f"line {e.lineno}", "valid JSON", e.msg) from None
    part = np.full(len(df), "", dtype=object)
    for k in SECTIONS:
        if k not in sec:
            raise RawDataError(path.name, f"section {k!r}", f"all nine sections {list(SECTIONS)}", "missing")
        try:
            a, b = int(sec[k]["start"]), int(sec[k]["end"])
        except (KeyError, TypeError, ValueError):
            raise RawDataError(path.name, f"section {k!r}", "{'start': int, 'end': int}", repr(sec[k])) from None
        if not 0 <= a < b <= len(df):
            raise RawDataError(path.name, f"section {k!r}", f"0 <= start < end <= {len(df)} rows of {data_name}", f"{a}..{b}")
        if np.any(part[a:b] != ""):
            raise RawDataError(path.name, f"section {k!r}", "sections that do not overlap", f"{a}..{b} overlaps another")
        part[a:b] = k
    out = df.copy()
    out["part"] = part
    return out


def read(sources: list[Path], options: dict) -> ImportedSession:
    if len(sources) != 1:
        raise RawDataError("(sources)", "command line", "one annotated session CSV", f"{len(sources)} files")
    path = sources[0]
    if not path.is_file():
        raise RawDataError(str(path), "", "an existing file", "no such file")
    df = pd.read_csv(path)
    name = path.name
    if "part" not in df.columns and "sections" in options:
        df = _label_from_section_list(df, Path(options["sections"]), name)
    if "part" not in df.columns:
        raise RawDataError(name, "header", "a 'part' column naming each row's section (imucal annotated session)",
                           f"columns {list(df.columns)}")
    missing = [c for c in DATA_COLUMNS if c not in df.columns]
    if missing:
        raise RawDataError(name, "header", f"columns {list(DATA_COLUMNS)}", f"missing {missing}")
    bad = ~df["part"].isin(SECTIONS + ("",))
    if bad.any():
        i = int(np.flatnonzero(bad.to_numpy())[0])
        raise RawDataError(name, f"row {i + 1} (line {i + 2}), column 'part'", f"one of {list(SECTIONS)}", repr(df['part'].iloc[i]))
    absent = [s for s in SECTIONS if s not in set(df["part"])]
    if absent:
        raise RawDataError(name, "column 'part'", f"all nine sections {list(SECTIONS)}", f"none for {absent}")
    counter = next((c for c in ("samples", "n_samples") if c in df.columns), None)
    for c in DATA_COLUMNS + ((counter,) if counter else ()):
        v = pd.to_numeric(df[c], errors="coerce").to_numpy(float)
        nb = np.flatnonzero(~np.isfinite(v))
        if nb.size:
            i = int(nb[0])
            raise RawDataError(name, f"row {i + 1} (line {i + 2}), column '{c}'", "a finite number", repr(df[c].iloc[i]))
    rate = option_float(options, "sample_rate_hz", name, required_for="the session's sample rate; imucal files do not store it")
    if counter:
        df = df.sort_values(counter, kind="stable").reset_index(drop=True)
        n = df[counter].to_numpy(float)
        dup = np.flatnonzero(np.diff(n) <= 0)
        if dup.size:
            raise RawDataError(name, f"column '{counter}'", "a unique sample counter per row", f"{n[dup[0] + 1]!r} repeated")
    else:
        n = np.arange(len(df), dtype=float)
    t = (n - n[0]) / rate
    acc = df[list(DATA_COLUMNS[:3])].to_numpy(float)
    gyr = df[list(DATA_COLUMNS[3:])].to_numpy(float)
    imu = pd.DataFrame({"time_s": t, "gyro_x": gyr[:, 0], "gyro_y": gyr[:, 1], "gyro_z": gyr[:, 2],
                        "accel_x": acc[:, 0], "accel_y": acc[:, 1], "accel_z": acc[:, 2]})
    channels = {}
    for fam, arr in (("gyro", gyr), ("accel", acc)):
        spec = _spec(arr, fam, options, name)
        for ax in "xyz":
            channels[f"{fam}_{ax}"] = spec
    angle = option_float(options, "expected_angle_deg", name, default=-360.0)
    parts = df["part"].to_numpy()
    change = np.flatnonzero(parts[1:] != parts[:-1]) + 1
    starts = np.r_[0, change]
    ends = np.r_[change, len(df)]
    seen = set()
    steps = []
    for a, b in zip(starts, ends):
        p = str(parts[a])
        if not p:
            continue
        if p in seen:
            raise RawDataError(name, f"row {a + 1} (after sorting by '{counter}')", f"section {p!r} in one contiguous block",
                               "a second block")
        seen.add(p)
        step = {"index": len(steps), "kind": "rotation" if p.endswith("_rot") else "pose", "start_s": float(t[a]),
                "duration_s": float(t[b - 1] - t[a] + 1.0 / rate), "label": p}
        if p.endswith("_rot"):
            step.update(rotation_axis_body=p[0], rotation_angle_deg=angle)
        else:
            step.update(up_axis_body=("+" if p.endswith("_p") else "-") + p[0])
        if steps:
            prev = steps[-1]
            step["start_s"] = max(step["start_s"], prev["start_s"] + prev["duration_s"])
        steps.append(step)
    # the last step may end one period after the last sample; keep it inside the data + one period
    return ImportedSession(
        imu=imu, channels=channels, sample_rate_hz=rate, test_kind="tablefree", steps=steps,
        plan_name="Ferraris six positions + three rotations", notes=f"imported from imucal session {name}",
        sources=sha256_sources([path]),
    )
