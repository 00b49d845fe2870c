"""The imulab code location Dagster loads (``workspace.yaml``, ``dagster dev -m pipelines.definitions``): the
stage assets, their checks, the jobs per level, sensors, schedules and resources (``pipelines.location``)."""

from pipelines.location import DATA_DIR, STAGE_CHECKS, build_definitions, default_paths, resources  # noqa: F401

defs = build_definitions()
