"""The committed JSON Schema and the README example cannot drift from the pydantic manifest model."""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest

from raw_schemas.errors import RawDataError
from raw_schemas.manifest import Manifest, load_manifest, manifest_json_schema
from raw_schemas.tables import RAW_IMU_OPTIONAL, RAW_IMU_REQUIRED, RAW_TABLE_REQUIRED

PKG = Path(__file__).resolve().parents[1] / "raw_schemas"
SCHEMA_FILE = PKG / "manifest.schema.json"
README = PKG / "README.md"


def _fenced_blocks(text: str, lang: str) -> list[str]:
    return re.findall(rf"^```{lang}\n(.*?)^```$", text, flags=re.S | re.M)


def _readme_manifest_text() -> str:
    blocks = [b for b in _fenced_blocks(README.read_text(encoding="utf-8"), "json") if '"schema_version"' in b]
    assert len(blocks) == 1, f"expected one ```json manifest block in {README}, found {len(blocks)}"
    return blocks[0]


def test_committed_schema_equals_model_schema():
    committed = json.loads(SCHEMA_FILE.read_text(encoding="utf-8"))
    assert committed == manifest_json_schema(), (
        "raw_schemas/manifest.schema.json is stale: "
        "run `python -m raw_schemas.manifest > raw_schemas/manifest.schema.json`"
    )


def test_committed_schema_is_what_the_module_prints():
    # `python -m raw_schemas.manifest` prints json.dumps(schema, indent=2) and a newline
    assert SCHEMA_FILE.read_text(encoding="utf-8") == json.dumps(manifest_json_schema(), indent=2) + "\n"


def test_readme_example_manifest_validates(tmp_path):
    text = _readme_manifest_text()
    m = Manifest.model_validate_json(text)
    assert m.schema_version == "1.0"
    assert len(m.plan.steps) == 2
    # and through the loader ingestion uses (file errors would be RawDataError)
    (tmp_path / "manifest.json").write_text(text, encoding="utf-8")
    assert load_manifest(tmp_path / "manifest.json") == m


def test_readme_example_validates_against_committed_json_schema():
    jsonschema = pytest.importorskip("jsonschema")
    schema = json.loads(SCHEMA_FILE.read_text(encoding="utf-8"))
    jsonschema.Draft202012Validator.check_schema(schema)
    jsonschema.validate(json.loads(_readme_manifest_text()), schema, cls=jsonschema.Draft202012Validator)


def test_json_schema_rejects_what_the_model_rejects_structurally():
    jsonschema = pytest.importorskip("jsonschema")
    schema = json.loads(SCHEMA_FILE.read_text(encoding="utf-8"))
    good = json.loads(_readme_manifest_text())
    for mutate in (
        lambda m: m.update(schema_version="2.0"),
        lambda m: m["device"].update(grade="military"),
        lambda m: m.update(unknown_field=1),
        lambda m: m.pop("plan"),
    ):
        bad = json.loads(json.dumps(good))
        mutate(bad)
        with pytest.raises(jsonschema.ValidationError):
            jsonschema.validate(bad, schema, cls=jsonschema.Draft202012Validator)
        with pytest.raises((RawDataError, ValueError)):
            Manifest.model_validate(bad)


def test_readme_csv_examples_use_the_contract_columns():
    blocks = _fenced_blocks(README.read_text(encoding="utf-8"), "csv")
    headers = [b.splitlines()[0].split(",") for b in blocks]
    assert list(RAW_IMU_REQUIRED + RAW_IMU_OPTIONAL) in headers
    assert list(RAW_TABLE_REQUIRED) in headers
