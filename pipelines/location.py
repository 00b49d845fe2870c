"""How the imulab code location is assembled (``build_definitions``), from explicit lists: the stage assets (one per stage of
``assets_lib.stages.registry.STAGES``), their checks, the jobs per level, sensors, schedules and resources.

Paths come from the environment: ``IMULAB_LANDING`` (the lab archive's landing folder, read-only) and
``IMULAB_STORE`` (versioned parquet outputs), defaults under ``./imulab_data``. The default executor is
in-process: partitions are batched into single runs (docs/dagster.md 4). ``build_definitions(stages=...)``
builds the same location over another stage graph (tests use toy stages). ``pipelines.definitions`` holds the
location Dagster loads; commands build their own from here without building that one too.
"""

import os

import dagster as dg

from assets_lib.stages.engine import StageGraph
from assets_lib.stages.registry import STAGES
from pipelines import assets, checks, jobs
from pipelines.defs import calibration, diagnosis, fleet, noise, records, schedules, sensors
from pipelines.resources import LabArchive, ParquetStore, WorkspaceLock

DATA_DIR = os.environ.get("IMULAB_DATA", "imulab_data")
#: the checks of the stages (each names its stage's asset; a graph without that stage has no such check)
STAGE_CHECKS = [*calibration.CHECKS, *noise.CHECKS, *records.CHECKS, *fleet.CHECKS, *diagnosis.CHECKS]


def default_paths() -> tuple[str, str]:
    landing = os.environ.get("IMULAB_LANDING", os.path.join(DATA_DIR, "landing"))
    store = os.environ.get("IMULAB_STORE", os.path.join(DATA_DIR, "store"))
    return os.path.abspath(landing), os.path.abspath(store)


def resources(landing_dir: str, store_dir: str, stages: StageGraph = STAGES) -> dict:
    """``archive``, ``store`` and ``workspace_lock`` for the assets; ``stages`` (the graph itself) for launchers reading the location."""
    return {"archive": LabArchive(landing_dir=landing_dir), "store": ParquetStore(root=store_dir),
            "workspace_lock": WorkspaceLock(store_dir=store_dir), "stages": stages}


def _checks_of(graph: StageGraph) -> list:
    out = checks.schema_checks(graph)
    for c in STAGE_CHECKS:
        if all(k.asset_key.to_user_string() in graph for k in c.check_keys):
            out.append(c)
    return out


def build_definitions(landing_dir: str | None = None, store_dir: str | None = None, extra_resources: dict | None = None,
                      executor=dg.in_process_executor, stages: StageGraph = STAGES) -> dg.Definitions:
    landing, store = default_paths()
    return dg.Definitions(
        assets=assets.stage_assets(stages),
        asset_checks=_checks_of(stages),
        jobs=jobs.stage_jobs(stages),
        sensors=sensors.sensors(stages),
        schedules=schedules.schedules(stages),
        resources={**resources(landing_dir or landing, store_dir or store, stages), **(extra_resources or {})},
        executor=executor,
    )
