"""Data contracts between a lab's capture jobs and imulab: manifest model, Arrow schemas, units, readers.

Everything a capture job must write, and everything ingestion checks, is defined here once
(see ``raw_schemas/README.md``). Nothing here imports ``assets_lib`` or ``pipelines``.
"""

from raw_schemas.errors import RawDataError
from raw_schemas.manifest import (
    SCHEMA_VERSION,
    ChannelSpec,
    Device,
    Manifest,
    PlanStep,
    Site,
    TestPlan,
)
from raw_schemas.tables import (
    CANONICAL_IMU_SCHEMA,
    CANONICAL_TABLE_SCHEMA,
    RAW_IMU_REQUIRED,
    RAW_TABLE_REQUIRED,
)

__all__ = [
    "SCHEMA_VERSION",
    "RawDataError",
    "ChannelSpec",
    "Device",
    "Manifest",
    "PlanStep",
    "Site",
    "TestPlan",
    "CANONICAL_IMU_SCHEMA",
    "CANONICAL_TABLE_SCHEMA",
    "RAW_IMU_REQUIRED",
    "RAW_TABLE_REQUIRED",
]
