"""Asset checks generated from the schemas in ``raw_schemas`` (PUDL style): a stored table whose columns or types
differ from its contract fails a blocking check, so a bad upstream never feeds downstream stages."""


import dagster as dg
import pyarrow as pa
import pyarrow.parquet as pq

from pipelines.partitions import captures
from pipelines.resources import ParquetStore
from raw_schemas.tables import CANONICAL_IMU_SCHEMA, CANONICAL_TABLE_SCHEMA

#: (asset, stored table, Arrow schema, required?) contracts checked after every materialization
SCHEMA_CONTRACTS: list[tuple[str, str, pa.Schema, bool]] = [
    ("ingested_run", "imu", CANONICAL_IMU_SCHEMA, True),
    ("ingested_run", "table", CANONICAL_TABLE_SCHEMA, False),
]


def schema_problems(path, schema: pa.Schema) -> list[str]:
    """Differences between a parquet file's schema and the contract (names, order, types)."""
    got = pq.read_schema(path)
    problems = []
    if got.names != schema.names:
        problems.append(f"columns {got.names} != {schema.names}")
    for f in schema:
        if f.name in got.names and not got.field(f.name).type.equals(f.type):
            problems.append(f"column {f.name!r} has type {got.field(f.name).type}, expected {f.type}")
    return problems


def build_schema_check(asset: str, table: str, schema: pa.Schema, required: bool, partitions_def=captures):
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
            bad += [f"{k}: {p}" for p in schema_problems(path, schema)]
        return dg.AssetCheckResult(passed=not bad, metadata={"checked": checked, "problems": "\n".join(bad) or "none"})

    return _check


def all_checks() -> list:
    return [build_schema_check(*c) for c in SCHEMA_CONTRACTS]
