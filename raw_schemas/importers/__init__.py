"""Importers: third-party IMU logs -> runs in the raw-log contract (manifest.json, imu.parquet, _COMPLETE).

One module per source format, all with the same signature ``read(sources: list[Path], options: dict[str, str])
-> ImportedSession`` and a module-level ``OPTIONS`` (the ``-o KEY=VALUE`` keys it reads -> one-line description),
collected in :data:`IMPORTERS` (a new format touches this table and its own module). :func:`import_run` refuses
an option key the format does not declare (a mistyped ``-o acel_lsb`` would otherwise leave the counts unscaled),
reads, validates the result against the contract in memory (the same checks as
``ingest_run``), and writes the run folder atomically into a landing area. Sources are only read.
"""

from __future__ import annotations

import dataclasses
import difflib
import importlib
import warnings
from pathlib import Path

from raw_schemas.errors import RawDataError
from raw_schemas.importers.common import ImportedDataWarning, ImportedSession, RunMeta, write_run

#: format name -> (module, one-line description)
IMPORTERS: dict[str, tuple[str, str]] = {
    "profile": ("raw_schemas.importers.profile", "generic CSV/parquet described by a profile JSON (-o profile=FILE)"),
    "imu_tk": ("raw_schemas.importers.imu_tk", "imu_tk text logs: ACC_FILE GYRO_FILE (t x y z, raw counts)"),
    "imucal": ("raw_schemas.importers.imucal", "imucal annotated Ferraris session CSV (part, samples, acc_*, gyr_*)"),
    "ros": ("raw_schemas.importers.ros", "sensor_msgs/Imu in a ROS 1 bag, ROS 2 bag folder or MCAP file"),
}


def reader(fmt: str):
    """The ``read`` function of a format; RawDataError naming the known formats when unknown."""
    if fmt not in IMPORTERS:
        raise RawDataError("(format)", f"format {fmt!r}", f"one of {sorted(IMPORTERS)}", repr(fmt))
    return importlib.import_module(IMPORTERS[fmt][0]).read


def accepted_options(fmt: str) -> dict[str, str]:
    """The ``-o`` options of a format (key -> one-line description), as its module declares them in ``OPTIONS``."""
    reader(fmt)  # unknown format: RawDataError naming the known ones
    return dict(importlib.import_module(IMPORTERS[fmt][0]).OPTIONS)


def check_options(fmt: str, options: dict[str, str]) -> None:
    """RawDataError naming every option key ``fmt`` does not accept, the accepted ones (sorted) and, for each
    unknown key, the closest accepted key when one is close (``did you mean 'accel_lsb'?``)."""
    accepted = sorted(accepted_options(fmt))
    unknown = [k for k in options if k not in accepted]
    if not unknown:
        return
    meta_fields = {f.name for f in dataclasses.fields(RunMeta)}
    found = []
    for k in unknown:
        close = difflib.get_close_matches(k, accepted, n=1)
        if k in meta_fields:  # e.g. gravity_mps2: run metadata, given apart from the format's options
            flag = {"device_model": "--model"}.get(k, "--" + k.replace("_", "-"))
            found.append(f"{k!r} (run metadata, not a format option: RunMeta({k}=...)"
                         + (f", imulab import {flag}" if k != "serial" else "") + ")")
        else:
            elsewhere = [f for f in IMPORTERS if f != fmt and k in accepted_options(f)]
            notes = ([f"did you mean {close[0]!r}?"] if close else []) + \
                ([f"accepted by format{'s' if len(elsewhere) > 1 else ''} {', '.join(repr(f) for f in elsewhere)}"]
                 if elsewhere else [])
            found.append(f"{k!r} ({'; '.join(notes)})" if notes else repr(k))
    where = ("option " if len(unknown) == 1 else "options ") + ", ".join(repr(k) for k in unknown)
    raise RawDataError("(options)", where, f"an option of format {fmt!r}, one of {accepted}",
                       f"unknown {'option' if len(unknown) == 1 else 'options'} " + ", ".join(found))


def import_run(fmt: str, sources: list[str | Path], landing: str | Path, meta: RunMeta,
               options: dict[str, str] | None = None) -> Path:
    """Read ``sources`` with the ``fmt`` importer and write ``<landing>/<device>/<run>/`` (returns that folder).

    The session's plausibility warnings (e.g. a static |f| far from 1 g: counts with an offset or a wrong lsb) are
    issued as :class:`ImportedDataWarning`; the run is written all the same (``imulab import`` prints them)."""
    options = dict(options or {})
    check_options(fmt, options)  # before anything is read: an unknown key would be silently ignored
    session = reader(fmt)([Path(s) for s in sources], options)
    out = write_run(session, Path(landing), meta)
    for msg in session.warnings:
        warnings.warn(msg, ImportedDataWarning, stacklevel=2)
    return out


__all__ = ["IMPORTERS", "ImportedDataWarning", "ImportedSession", "RunMeta", "accepted_options", "check_options",
           "import_run", "reader", "write_run"]
