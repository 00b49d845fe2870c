"""imu_tk text logs (Tedaldi, Pretto & Menegatti 2014 demo format): two files, accelerometer then gyroscope, each
with four whitespace-separated columns ``t [s], x, y, z`` (the demo's ``.mat`` files are plain text).

Both files must share their time stamps (imu_tk reads them as one sequence). Values are taken as raw counts when
every value is an integer (declare the nominal count values with ``-o accel_lsb=... -o gyro_lsb=...`` in
``accel_lsb_unit`` / ``gyro_lsb_unit``, defaults m/s^2 and rad/s), otherwise as physical values in
``accel_unit`` / ``gyro_unit`` (defaults m/s^2, rad/s). Time stamps are kept as they are (the IMU clock).

Options: ``initial_static_s`` (default 0: none) declares the initial static interval (imu_tk's gyro-bias
window, 50 s in the demo) as a ``pose`` step; the rest of the record is one ``free`` step whose poses are found
by segmentation.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

from raw_schemas.errors import RawDataError
from raw_schemas.importers.common import ImportedSession, median_rate_hz, option_float, sha256_sources
from raw_schemas.importers.text_table import read_numeric_columns


def _spec(vals: np.ndarray, fam: str, options: dict, file: str) -> dict:
    if np.all(vals == np.round(vals)):
        lsb = option_float(options, f"{fam}_lsb", file, required_for=f"the value of one {fam} count: the data are integer counts")
        return {"unit": "counts", "lsb": lsb, "lsb_unit": options.get(f"{fam}_lsb_unit", "m/s^2" if fam == "accel" else "rad/s")}
    return {"unit": options.get(f"{fam}_unit", "m/s^2" if fam == "accel" else "rad/s")}


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
    imu = pd.DataFrame({
        "time_s": t,
        "gyro_x": gyro[:, 1], "gyro_y": gyro[:, 2], "gyro_z": gyro[:, 3],
        "accel_x": acc[:, 1], "accel_y": acc[:, 2], "accel_z": acc[:, 3],
    })
    channels = {}
    for fam, arr, path in (("gyro", gyro, gyro_path), ("accel", acc, acc_path)):
        spec = _spec(arr[:, 1:], fam, options, path.name)
        for ax in "xyz":
            channels[f"{fam}_{ax}"] = spec
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
    return ImportedSession(
        imu=imu, channels=channels, sample_rate_hz=rate, test_kind="tablefree", steps=steps, plan_name="imu_tk session",
        notes=f"imported from imu_tk text logs {acc_path.name}, {gyro_path.name}",
        sources=sha256_sources([acc_path, gyro_path]),
    )
