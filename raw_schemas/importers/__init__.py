"""Importers: third-party IMU logs -> runs in the raw-log contract (manifest.json, imu.parquet, _COMPLETE).

One module per source format, all with the same signature ``read(sources: list[Path], options: dict[str, str])
-> ImportedSession``, collected in :data:`IMPORTERS` (a new format touches this table and its own module).
:func:`import_run` reads, validates the result against the contract in memory (the same checks as
``ingest_run``), and writes the run folder atomically into a landing area. Sources are only read.
"""

from __future__ import annotations

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


def import_run(fmt: str, sources: list[str | Path], landing: str | Path, meta: RunMeta,
               options: dict[str, str] | None = None) -> Path:
    """Read ``sources`` with the ``fmt`` importer and write ``<landing>/<device>/<run>/`` (returns that folder).

    The session's plausibility warnings (e.g. a static |f| far from 1 g: counts with an offset or a wrong lsb) are
    issued as :class:`ImportedDataWarning`; the run is written all the same (``imulab import`` prints them)."""
    session = reader(fmt)([Path(s) for s in sources], dict(options or {}))
    out = write_run(session, Path(landing), meta)
    for msg in session.warnings:
        warnings.warn(msg, ImportedDataWarning, stacklevel=2)
    return out


__all__ = ["IMPORTERS", "ImportedDataWarning", "ImportedSession", "RunMeta", "import_run", "reader", "write_run"]
