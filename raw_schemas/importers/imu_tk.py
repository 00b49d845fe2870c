"""imu_tk text logs (Tedaldi, Pretto & Menegatti 2014 demo format): two files, accelerometer then gyroscope, each
with four whitespace-separated columns ``t [s], x, y, z`` (the demo's ``.mat`` files are plain text).

Both files must share their time stamps (imu_tk reads them as one sequence). Values are taken as raw counts when
every value is an integer (declare the nominal count values with ``-o accel_lsb=... -o gyro_lsb=...`` in
``accel_lsb_unit`` / ``gyro_lsb_unit``, defaults m/s^2 and rad/s), otherwise as physical values in
``accel_unit`` / ``gyro_unit`` (defaults m/s^2, rad/s). Time stamps are kept as they are (the IMU clock).

Counts and their zero: unsigned ADC counts (imu_tk's Xsens data: 16-bit, zero near mid-scale 32768) read 0 at
the bottom of the range, not at zero input. ``-o accel_zero_count=N`` / ``-o gyro_zero_count=N`` (default 0:
none) declare the count that stands for zero input; it is subtracted from every count before the lsb scales it,
so the run's counts are signed and ``value = (count - zero) * lsb``. The import never guesses it: when the
record's median |f| is outside 0.5-2 g (a session that is mostly still reads ~1 g), or its median |w| is above
1 rad/s, it warns (:class:`~raw_schemas.importers.common.ImportedDataWarning`, naming the file and the figure)
that the counts likely carry an offset or a wrong lsb, and which option to give. imu_tk estimates a bias in
counts itself (its demo starts the accelerometer bias at 32768), so the fitted bias is the residual about the
declared zero.

Options: ``initial_static_s`` (default 0: none) declares the initial static interval (imu_tk's gyro-bias
window, 50 s in the demo) as a ``pose`` step; the rest of the record is one ``free`` step whose poses are found
by segmentation.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

from raw_schemas.errors import RawDataError
from raw_schemas.importers.common import (ImportedSession, channel_si, gravity_check, median_rate_hz, option_float,
                                          sha256_sources, still_gyro_check)
from raw_schemas.importers.text_table import read_numeric_columns

#: the ``-o KEY=VALUE`` options this importer reads (key -> one-line description); any other key is refused
OPTIONS = {
    "accel_lsb": "value of one accelerometer count (required for integer counts)",
    "accel_lsb_unit": "unit of accel_lsb (default m/s^2)",
    "accel_zero_count": "accelerometer count that stands for zero input (default 0)",
    "accel_unit": "unit of non-integer accelerometer values (default m/s^2)",
    "gyro_lsb": "value of one gyro count (required for integer counts)",
    "gyro_lsb_unit": "unit of gyro_lsb (default rad/s)",
    "gyro_zero_count": "gyro count that stands for zero input (default 0)",
    "gyro_unit": "unit of non-integer gyro values (default rad/s)",
    "initial_static_s": "length of the initial static interval in s (default 0: none)",
}


def _spec(vals: np.ndarray, fam: str, options: dict, file: str) -> tuple[dict, float]:
    """The channel spec of a family and the zero count to subtract (0 for physical values)."""
    zero_key = f"{fam}_zero_count"
    if np.all(vals == np.round(vals)):
        lsb = option_float(options, f"{fam}_lsb", file, required_for=f"the value of one {fam} count: the data are integer counts")
        zero = option_float(options, zero_key, file, default=0.0)
        if not np.isfinite(zero):
            raise RawDataError(file, f"option {zero_key!r}", "a finite count", repr(options[zero_key]))
        spec = {"unit": "counts", "lsb": lsb, "lsb_unit": options.get(f"{fam}_lsb_unit", "m/s^2" if fam == "accel" else "rad/s")}
        return spec, zero
    if zero_key in options:
        raise RawDataError(file, f"option {zero_key!r}", "integer counts in the file (a zero count applies to counts only)",
                           "non-integer values: the file holds physical values")
    return {"unit": options.get(f"{fam}_unit", "m/s^2" if fam == "accel" else "rad/s")}, 0.0


def _hint(fam: str, spec: dict, zero: float) -> str:
    if spec.get("unit") != "counts":
        return f"check -o {fam}_unit (the values are taken as {spec['unit']})"
    if zero == 0.0:
        return (f"the counts likely carry a zero offset (unsigned ADC counts: give -o {fam}_zero_count=N, e.g. 32768 "
                f"for 16-bit mid-scale) or a wrong -o {fam}_lsb (given {spec['lsb']:g} {spec['lsb_unit']})")
    return (f"check -o {fam}_zero_count (given {zero:g}) and -o {fam}_lsb (given {spec['lsb']:g} {spec['lsb_unit']})")


def read(sources: list[Path], options: dict) -> ImportedSession:
    if len(sources) != 2:
        raise RawDataError("(sources)", "command line", "two files: ACC_FILE GYRO_FILE", f"{len(sources)} file(s)")
    acc_path, gyro_path = sources
    acc = read_numeric_columns(acc_path, 4)
    gyro = read_numeric_columns(gyro_path, 4)
    if acc.shape[0] != gyro.shape[0]:
        raise RawDataError(gyro_path.name, "file", f"{acc.shape[0]} rows, as in {acc_path.name}", f"{gyro.shape[0]} rows")
    bad = np.flatnonzero(acc[:, 0] != gyro[:, 0])
    if bad.size:
        i = int(bad[0])
        raise RawDataError(gyro_path.name, f"data row {i + 1}", f"time {acc[i, 0]!r} as in {acc_path.name}", repr(gyro[i, 0]))
    t = acc[:, 0]
    rate = median_rate_hz(t, acc_path.name)
    channels, values, hints = {}, {}, {}
    for fam, arr, path in (("gyro", gyro, gyro_path), ("accel", acc, acc_path)):
        spec, zero = _spec(arr[:, 1:], fam, options, path.name)
        values[fam] = arr[:, 1:] - zero if zero else arr[:, 1:]  # the zero count comes off before the lsb scales
        hints[fam] = _hint(fam, spec, zero)
        for ax in "xyz":
            channels[f"{fam}_{ax}"] = spec
    imu = pd.DataFrame({
        "time_s": t,
        "gyro_x": values["gyro"][:, 0], "gyro_y": values["gyro"][:, 1], "gyro_z": values["gyro"][:, 2],
        "accel_x": values["accel"][:, 0], "accel_y": values["accel"][:, 1], "accel_z": values["accel"][:, 2],
    })
    init = option_float(options, "initial_static_s", acc_path.name, default=0.0)
    steps = []
    t0, t1 = float(t[0]), float(t[-1])
    start = t0
    if init > 0:
        steps.append({"index": 0, "kind": "pose", "start_s": t0, "duration_s": init - t0 if init > t0 else init,
                      "label": "initial static interval"})
        start = steps[0]["start_s"] + steps[0]["duration_s"]
    steps.append({"index": len(steps), "kind": "free", "start_s": start, "duration_s": max(t1 - start, 1.0 / rate),
                  "label": "hand-placed static poses joined by rotations"})
    # plausibility of the declared scale: a mostly still session reads ~1 g and ~0 rad/s (over the initial
    # static interval when one is declared)
    still = t < steps[0]["start_s"] + steps[0]["duration_s"] if init > 0 else np.ones(t.size, bool)
    warns = [w for w in (
        gravity_check(channel_si(values["accel"], channels["accel_x"], "accel"), acc_path.name, hints["accel"]),
        still_gyro_check(channel_si(values["gyro"][still], channels["gyro_x"], "gyro"), gyro_path.name, hints["gyro"],
                         "the initial static interval" if init > 0 else "the record"),
    ) if w]
    zeros = "".join(f"; {fam} zero count {float(options[f'{fam}_zero_count']):g} subtracted from the counts"
                    for fam in ("accel", "gyro") if f"{fam}_zero_count" in options)
    return ImportedSession(
        imu=imu, channels=channels, sample_rate_hz=rate, test_kind="tablefree", steps=steps, plan_name="imu_tk session",
        notes=f"imported from imu_tk text logs {acc_path.name}, {gyro_path.name}{zeros}",
        sources=sha256_sources([acc_path, gyro_path]), warnings=tuple(warns),
    )
