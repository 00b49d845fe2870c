"""The imulab code location: every asset, check, sensor, schedule, job and resource, in one place.

Paths come from the environment: ``IMULAB_LANDING`` (the lab archive's landing folder, read-only) and
``IMULAB_STORE`` (versioned parquet outputs); defaults under ``./imulab_data``. The default executor is
in-process: partitions are batched into single runs (docs/dagster.md 4).
"""

from __future__ import annotations

import os

import dagster as dg

from pipelines import checks
from pipelines.defs import ingest, sensors
from pipelines.resources import LabArchive, ParquetStore

DATA_DIR = os.environ.get("IMULAB_DATA", "imulab_data")


def default_paths() -> tuple[str, str]:
    landing = os.environ.get("IMULAB_LANDING", os.path.join(DATA_DIR, "landing"))
    store = os.environ.get("IMULAB_STORE", os.path.join(DATA_DIR, "store"))
    return os.path.abspath(landing), os.path.abspath(store)


CAPTURE_ASSETS = [ingest.ingested_run]
DEVICE_ASSETS: list = []
FLEET_ASSETS: list = []

calibrate_captures = dg.define_asset_job(
    "calibrate_captures",
    selection=dg.AssetSelection.assets(*CAPTURE_ASSETS),
    description="Every per-run stage for a batch of captured runs (one run for a whole partition range).",
)


def resources(landing_dir: str, store_dir: str) -> dict:
    return {"archive": LabArchive(landing_dir=landing_dir), "store": ParquetStore(root=store_dir)}


def build_definitions(landing_dir: str | None = None, store_dir: str | None = None) -> dg.Definitions:
    landing, store = default_paths()
    return dg.Definitions(
        assets=[*CAPTURE_ASSETS, *DEVICE_ASSETS, *FLEET_ASSETS],
        asset_checks=checks.all_checks(),
        jobs=[calibrate_captures],
        sensors=[sensors.landing_sensor],
        resources=resources(landing_dir or landing, store_dir or store),
        executor=dg.in_process_executor,
    )


defs = build_definitions()
