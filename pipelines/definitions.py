"""The imulab code location Dagster loads (``workspace.yaml``, ``dagster dev -m pipelines.definitions``): the
stage assets, their checks, the jobs per level, sensors, schedules and resources (``pipelines.location``)."""

from pipelines.location import (  # noqa: F401
    DATA_DIR,
    STAGE_CHECKS,
    build_definitions,
    default_paths,
    resources,
)

defs = build_definitions()
