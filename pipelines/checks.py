"""Asset checks generated from the schemas in ``raw_schemas`` (PUDL style): a stored table whose columns or types
differ from its contract fails a blocking check, so a bad upstream never feeds downstream stages."""

import dagster as dg
import pyarrow as pa
import pyarrow.parquet as pq

from assets_lib.stages.engine import StageGraph
from pipelines.partitions import captures
from pipelines.resources import ParquetStore
from raw_schemas.derived import (
    ALLAN_SCHEMA,
    COEFFICIENT_SCHEMA,
    NOISE_SCHEMA,
    PLATEAU_SCHEMA,
    conformance_problems,
)
from raw_schemas.tables import CANONICAL_IMU_SCHEMA, CANONICAL_TABLE_SCHEMA

#: (asset, stored table, Arrow schema, required?, exact?) contracts checked after every materialization
SCHEMA_CONTRACTS: list[tuple[str, str, pa.Schema, bool, bool]] = [
    ("ingested_run", "imu", CANONICAL_IMU_SCHEMA, True, True),
    ("ingested_run", "table", CANONICAL_TABLE_SCHEMA, False, True),
    ("plateaus", "plateaus", PLATEAU_SCHEMA, True, False),
    ("gyro_rate_fit", "coefficients", COEFFICIENT_SCHEMA, True, False),
    ("accel_multiposition_fit", "coefficients", COEFFICIENT_SCHEMA, True, False),
    ("allan_deviation", "allan", ALLAN_SCHEMA, True, False),
    ("allan_deviation", "noise", NOISE_SCHEMA, True, False),
]


def schema_problems(path, schema: pa.Schema, exact: bool = True) -> list[str]:
    """Differences between a parquet file's schema and the contract."""
    return conformance_problems(pq.read_schema(path), schema, exact)


def build_schema_check(asset: str, table: str, schema: pa.Schema, required: bool, exact: bool = True,
                       partitions_def=captures):
    @dg.asset_check(asset=asset, name=f"{table}_matches_schema", blocking=True, partitions_def=partitions_def,
                    description=f"Stored '{table}' tables of {asset} match the Arrow contract in raw_schemas.")
    def _check(context: dg.AssetCheckExecutionContext, store: ParquetStore) -> dg.AssetCheckResult:
        st = store.store
        keys = context.partition_keys if context.has_partition_key_range or context.has_partition_key else st.partitions(asset)
        bad, checked = [], 0
        for k in keys:
            if st.current_version(asset, k) is None:
                continue
            path = st.version_dir(asset, k) / f"{table}.parquet"
            if not path.is_file():
                if required:
                    bad.append(f"{k}: {table}.parquet missing")
                continue
            checked += 1
            bad += [f"{k}: {p}" for p in schema_problems(path, schema, exact)]
        return dg.AssetCheckResult(passed=not bad, metadata={"checked": checked, "problems": "\n".join(bad) or "none"})

    return _check


def schema_checks(graph: StageGraph) -> list:
    """The schema checks of the contracts whose asset is a stage of ``graph``."""
    return [build_schema_check(*c) for c in SCHEMA_CONTRACTS if c[0] in graph]
