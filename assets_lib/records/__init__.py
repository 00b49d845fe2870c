"""Audited calibration records (pure: no store, no Dagster): canonical hashing, record content, chain checks, diffs, certificates."""

from assets_lib.records.canonical import (
    RECORD_SCHEMA_VERSION,
    SCHEMA_PATH,
    canonical_json,
    content_sha256,
    load_record,
    record_file_bytes,
    sha256_hex,
    to_jsonable,
)
from assets_lib.records.certificate import certificate_html
from assets_lib.records.chain import chain_problems, load_records_dir, self_hash_problem
from assets_lib.records.content import (
    COEFFICIENT_SOURCES,
    NOISE_SOURCES,
    PLOT_SOURCES,
    RECORDS_TABLE_COLUMNS,
    StoreView,
    build_device_records,
    make_record,
    records_table,
    run_content,
    run_order_key,
    same_certified_content,
    software_info,
    utc_now_iso,
)
from assets_lib.records.diff import FLOAT_RTOL, coefficient_id, content_differences

__all__ = [
    "COEFFICIENT_SOURCES", "FLOAT_RTOL", "NOISE_SOURCES", "PLOT_SOURCES", "RECORDS_TABLE_COLUMNS",
    "RECORD_SCHEMA_VERSION", "SCHEMA_PATH", "StoreView", "build_device_records", "canonical_json", "certificate_html",
    "chain_problems", "coefficient_id", "content_differences", "content_sha256", "load_record", "load_records_dir",
    "make_record", "record_file_bytes", "records_table", "run_content", "run_order_key", "same_certified_content",
    "self_hash_problem", "sha256_hex", "software_info", "to_jsonable", "utc_now_iso",
]
