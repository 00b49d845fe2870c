"""The imulab code location: every asset, check, sensor, schedule, job and resource, in one place.

Each module of ``pipelines/defs/`` contributes module-level lists (``ASSETS``, ``CHECKS``, ``SENSORS``,
``SCHEDULES``); stage assets register themselves in ``pipelines.stage.STAGES`` so the three jobs below select
them by level. Paths come from the environment: ``IMULAB_LANDING`` (the lab archive's landing folder, read-only)
and ``IMULAB_STORE`` (versioned parquet outputs), defaults under ``./imulab_data``. The default executor is
in-process: partitions are batched into single runs (docs/dagster.md 4).
"""

import importlib
import importlib.util
import os

import dagster as dg

from pipelines import checks
from pipelines.resources import LabArchive, ParquetStore
from pipelines.stage import STAGES

DATA_DIR = os.environ.get("IMULAB_DATA", "imulab_data")
#: stage modules in dependency order (a module that does not exist yet is skipped)
DEFS_MODULES = ("ingest", "calibration", "noise", "repeatability", "records", "fleet", "sensors", "schedules")


def default_paths() -> tuple[str, str]:
    landing = os.environ.get("IMULAB_LANDING", os.path.join(DATA_DIR, "landing"))
    store = os.environ.get("IMULAB_STORE", os.path.join(DATA_DIR, "store"))
    return os.path.abspath(landing), os.path.abspath(store)


def _modules():
    for name in DEFS_MODULES:
        full = f"pipelines.defs.{name}"
        if importlib.util.find_spec(full) is not None:
            yield importlib.import_module(full)


def _collect(attr: str) -> list:
    return [x for m in _modules() for x in getattr(m, attr, [])]


def _stage_job(name: str, level: str, description: str):
    names = [s.name for s in STAGES.values() if s.level == level]
    return dg.define_asset_job(name, selection=dg.AssetSelection.assets(*names), description=description) if names else None


def resources(landing_dir: str, store_dir: str) -> dict:
    return {"archive": LabArchive(landing_dir=landing_dir), "store": ParquetStore(root=store_dir)}


def build_definitions(landing_dir: str | None = None, store_dir: str | None = None, extra_resources: dict | None = None,
                      executor=dg.in_process_executor) -> dg.Definitions:
    landing, store = default_paths()
    assets = _collect("ASSETS")
    jobs = [j for j in (
        _stage_job("calibrate_captures", "capture", "Every per-run stage for a batch of captured runs (one run per partition range)."),
        _stage_job("calibrate_devices", "device", "Per-device stages (repeatability, records) over a range of devices."),
        _stage_job("fleet_summary", "fleet", "Fleet-wide coefficient drift."),
    ) if j is not None]
    return dg.Definitions(
        assets=assets,
        asset_checks=checks.all_checks() + _collect("CHECKS"),
        jobs=jobs + _collect("JOBS"),
        sensors=_collect("SENSORS"),
        schedules=_collect("SCHEDULES"),
        resources={**resources(landing_dir or landing, store_dir or store), **(extra_resources or {})},
        executor=executor,
    )


defs = build_definitions()
