"""Calibration records (no Dagster): hashing, content, validity, chain, diffs, certificates, look-up, export."""

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
from assets_lib.records.certificate import (
    CERTIFICATE_FORMAT,
    certificate_html,
    certificate_problems,
    certified_cells,
    parse_certificate,
    round_to_uncertainty,
)
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
from assets_lib.records.diff import FLOAT_RTOL, PRECISION_FRACTION, coefficient_id, content_differences, noise_id
from assets_lib.records.validity import CHI2_BAND, MODEL_INSIDE_CI_MIN, RecordStatus, record_status

__all__ = [
    "CERTIFICATE_FORMAT", "CHI2_BAND", "MODEL_INSIDE_CI_MIN", "PRECISION_FRACTION", "RecordStatus",
    "certificate_problems",
    "certified_cells", "noise_id", "parse_certificate", "record_status", "round_to_uncertainty",
    "COEFFICIENT_SOURCES", "FLOAT_RTOL", "NOISE_SOURCES", "PLOT_SOURCES", "RECORDS_TABLE_COLUMNS",
    "RECORD_SCHEMA_VERSION", "SCHEMA_PATH", "StoreView", "build_device_records", "canonical_json", "certificate_html",
    "chain_problems", "coefficient_id", "content_differences", "content_sha256", "load_record", "load_records_dir",
    "make_record", "record_file_bytes", "records_table", "run_content", "run_order_key", "same_certified_content",
    "self_hash_problem", "sha256_hex", "software_info", "to_jsonable", "utc_now_iso",
]
