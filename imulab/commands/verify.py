"""``imulab verify RECORD``: recompute a calibration record from the raw archive and check it and its hash chain.

For the record and (unless ``--shallow``) every earlier record of the same device:
1. the record validates against ``raw_schemas/record.schema.json`` and its ``record_sha256`` is the hash of its content;
2. every raw file of the run folder is re-hashed and compared with the recorded sha256 (changed, missing, extra);
3. ingestion and the fits are re-run from the raw folder by the pipeline's own engine (``assets_lib.stages``),
   into a temporary VersionedStore (never the production store), and the record's content is rebuilt from it with
   the same code that built it (``assets_lib.records.run_content``); every coefficient and noise term must match
   within a thousandth of its own precision (standard error, interval half-width; see ``assets_lib.records.diff``:
   ten times finer than a certificate prints, far above round-off or the choice of an optional kernel), and every
   unit, test condition, status and stage version must match;
4. the chain: the previous record's hash matches ``prev_record_sha256``, and no record between the device's first
   run and this one is missing or edited (records.parquet and the archive name the runs that must be there).
RECORD may be the JSON record or its HTML certificate: a certificate is first checked to show exactly the record
embedded in it (hash, every printed value; ``assets_lib.records.certificate``), then that record is verified.
The archive and the store are found from the record's location when it lies in a store (``<store>/ARCHIVE`` names
the archive ``imulab run`` read), so verify works from any directory.
Every difference is printed by name; the exit code is 1 when anything differs (2 for unusable input).
"""

import json
import sys
import tempfile
import warnings
from pathlib import Path

import click

from assets_lib.records import (
    FLOAT_RTOL,
    PRECISION_FRACTION,
    SCHEMA_PATH,
    StoreView,
    certificate_problems,
    chain_problems,
    content_differences,
    load_record,
    load_records_dir,
    run_content,
    run_order_key,
    self_hash_problem,
)


def schema_problems(record: dict) -> list[str]:
    """JSON Schema validation (needs the ``jsonschema`` package; without it, only the hash and content checks run)."""
    try:
        import jsonschema
    except ImportError:  # pragma: no cover - optional dependency
        return []
    schema = json.loads(SCHEMA_PATH.read_text())
    v = jsonschema.Draft202012Validator(schema)
    return [f"schema: {'/'.join(map(str, e.absolute_path)) or 'top level'}: {e.message}"
            for e in sorted(v.iter_errors(record), key=lambda e: list(map(str, e.absolute_path)))]


def raw_file_problems(record: dict, run_dir: Path) -> list[str]:
    from raw_schemas.readers import sha256_file

    recorded = record["content"]["raw_files"]
    if not run_dir.is_dir():
        return [f"raw run folder {run_dir} not found"]
    present = {p.name: p for p in sorted(run_dir.iterdir()) if p.is_file()}
    out = []
    for name in sorted(set(recorded) | set(present)):
        if name not in present:
            out.append(f"raw file {name}: recorded sha256 {recorded[name]}, missing from {run_dir}")
        elif name not in recorded:
            out.append(f"raw file {name}: in {run_dir} but not in the record")
        else:
            got = sha256_file(present[name])
            if got != recorded[name]:
                out.append(f"raw file {name}: recorded sha256 {recorded[name]}, archive file has {got}")
    return out


def recompute_capture(key: str, landing: Path, store, stages: set[str]) -> dict[str, str]:
    """Run the capture-level ``stages`` (and what they need) for ``key`` into ``store`` with the pipeline's own
    engine (``assets_lib.stages.engine.recompute_capture``); returns the versions written."""
    from assets_lib.stages.engine import recompute_capture as engine_recompute
    from assets_lib.stages.registry import STAGES
    from assets_lib.store import LandingArchive

    return engine_recompute(STAGES, key, store, LandingArchive(Path(landing)), stages)


def recompute_problems(record: dict, landing: Path, rtol: float = FLOAT_RTOL,
                       fraction: float = PRECISION_FRACTION) -> tuple[list[str], int]:
    """Rebuild the record's content from the raw archive in a temporary store; named differences and the number of
    coefficients compared."""
    from assets_lib.store import VersionedStore

    c = record["content"]
    key = f"{c['device']['id']}__{c['run']['run_id']}"
    with tempfile.TemporaryDirectory(prefix="imulab-verify-") as tmp:
        store = VersionedStore(Path(tmp))
        try:
            versions = recompute_capture(key, landing, store, set(c["stages"]))
            if f"ingested_run/{key}" not in versions:
                return [f"recomputation: run {key} could not be ingested from {landing}"], 0
            fresh = run_content(StoreView(store, versions), key, c.get("prev_record_sha256"), c.get("software", {}))
        except Exception as e:  # noqa: BLE001 - any failure of the recomputation is a verification failure
            return [f"recomputation from the raw archive failed: {type(e).__name__}: {e}"], 0
    return content_differences(c, fresh, rtol, fraction), len(fresh["coefficients"])


def chain_source(record_path: Path, device: str, store_dir: Path) -> Path | None:
    """Folder holding the device's chain: the record's own folder when it is a record version folder, else the
    device's current ``calibration_record`` version in the store."""
    if (record_path.parent / "records.parquet").is_file():
        return record_path.parent
    from assets_lib.store import VersionedStore

    st = VersionedStore(store_dir)
    v = st.current_version("calibration_record", device)
    return st.version_dir("calibration_record", device, v) if v else None


def archive_runs(landing: Path, store_dir: Path, device: str) -> list[tuple[str, str]]:
    """(run_id, start_time_utc) of the device's runs that are in the archive and were ingested into the store."""
    from assets_lib.store import VersionedStore

    st = VersionedStore(store_dir)
    out = []
    for p in sorted((landing / device).iterdir()) if (landing / device).is_dir() else []:
        key = f"{device}__{p.name}"
        if p.is_dir() and st.current_version("ingested_run", key):
            out.append((p.name, st.read_meta("ingested_run", key).get("start_time_utc", "")))
    return out


def verify_record(record: dict, landing: Path, rtol: float = FLOAT_RTOL, recompute: bool = True,
                  fraction: float = PRECISION_FRACTION) -> list[str]:
    problems = schema_problems(record)
    if (p := self_hash_problem(record)) is not None:
        problems.append(p)
    c = record.get("content", {})
    try:
        run_dir = landing / c["device"]["id"] / c["run"]["run_id"]
    except (KeyError, TypeError):
        return problems + ["record has no device id / run id"]
    problems += raw_file_problems(record, run_dir)
    if recompute:
        diffs, _ = recompute_problems(record, landing, rtol, fraction)
        problems += diffs
    return problems


def budget_calibration_problems(cert_path: Path, records: list[dict], run_id: str) -> list[str]:
    """A certificate's navigation budget is computed from the device calibration embedded in it; that calibration
    must be the one assembled from the device's (verified) records at the record's start."""
    from assets_lib.navigation.budget import certificate_calibration
    from assets_lib.records.certificate import parse_certificate

    emb = parse_certificate(cert_path.read_text(encoding="utf-8")).device_calibration
    want = certificate_calibration(records, run_id)
    want_sha = want.to_json()["calibration_sha256"] if want is not None else None
    got_sha = emb.get("calibration_sha256") if isinstance(emb, dict) else None
    if got_sha == want_sha:
        return []
    return [(f"certificate: the navigation budget's device calibration {str(got_sha)[:16]}... is not the one the "
             f"device's records assemble at this run's start ({str(want_sha)[:16]}...)")]


def locate_workspace(record_path: Path, landing, store_dir, data_dir) -> tuple[Path, Path]:
    """(archive, store) of a record: the options when given; else the store the record lies in
    (``<store>/calibration_record/<device>/<version>/<run>.json``, or a certificate's
    ``<store>/certificate/<device>/<version>/<run>.html``) and the archive that store names in its
    ``ARCHIVE`` file (written by ``imulab run``) or ``<data>/landing`` beside it; else ``--data-dir``, relative to
    the working directory."""
    rp = Path(record_path).resolve()
    in_store = len(rp.parents) > 3 and (
        ((rp.parent / "records.parquet").is_file() and rp.parents[2].name == "calibration_record")
        or ((rp.parent / "certificates.parquet").is_file() and rp.parents[2].name == "certificate"))
    if store_dir:
        store = Path(store_dir).resolve()
    else:
        store = rp.parents[3] if in_store else (Path(data_dir) / "store").resolve()
    if landing:
        return Path(landing).resolve(), store
    from pipelines.instance import recorded_archive

    named = recorded_archive(store)
    if named is not None:
        return named, store
    return (store.parent / "landing" if in_store and not store_dir else (Path(data_dir) / "landing")).resolve(), store


@click.command("verify")
@click.argument("record_path", metavar="RECORD", type=click.Path(exists=True, dir_okay=False, path_type=Path))
@click.option("--archive", "landing", type=click.Path(file_okay=False, path_type=Path), default=None,
              help="Landing folder of the lab archive. Default: the archive the record's store was computed from "
                   "(its ARCHIVE file), else <store>/../landing, else <data>/landing.")
@click.option("--store", "store_dir", type=click.Path(file_okay=False, path_type=Path), default=None,
              help="The production store (read only; the chain and the ingested runs). Default: the store the record "
                   "lies in, else <data>/store.")
@click.option("--data-dir", default="imulab_data", show_default=True, help="Working folder of `imulab run`.")
@click.option("--shallow", is_flag=True,
              help="Earlier records of the chain: check hashes, links and raw file hashes only (no recomputation).")
@click.option("--rtol", type=float, default=FLOAT_RTOL, show_default=True,
              help="Relative tolerance of recomputed numbers that carry no precision (conditions, durations).")
@click.option("--fraction", type=float, default=PRECISION_FRACTION, show_default=True,
              help="Tolerance of recomputed estimates, as a fraction of their standard error / interval half-width.")
def command(record_path: Path, landing, store_dir, data_dir, shallow, rtol, fraction):
    """Check RECORD (a calibration record JSON, or its HTML certificate) against the raw archive and its chain.

    For a certificate, first checks that every value it prints is the value of the record embedded in it. Then
    re-hashes the raw files, re-runs ingestion and the fits through the pipeline's own stage functions into a
    temporary store (never the production store), compares every coefficient and noise term at its precision,
    and checks that the previous record's hash matches and every earlier record of the device verifies. Exit code
    1 names what differs.
    """
    warnings.filterwarnings("ignore")
    landing, store_dir = locate_workspace(record_path, landing, store_dir, data_dir)
    failures: list[str] = []

    def report(label: str, problems: list[str], limit: int = 40) -> None:
        for p in problems[:limit]:
            click.echo(f"  FAIL {p}")
        if len(problems) > limit:
            click.echo(f"  FAIL ... and {len(problems) - limit} more differences")
        if not problems:
            click.echo(f"  ok   {label}")
        failures.extend(problems)

    is_html = record_path.suffix.lower() in (".html", ".htm")
    try:
        if is_html:
            record, cert_problems = certificate_problems(record_path.read_text(encoding="utf-8"))
            if record is None:
                click.echo(f"FAIL {record_path}: {cert_problems[0]}", err=True)
                sys.exit(2)
        else:
            record = load_record(record_path)
        device, run_id = record["content"]["device"]["id"], record["content"]["run"]["run_id"]
    except (json.JSONDecodeError, UnicodeDecodeError, KeyError, TypeError) as e:
        click.echo(f"FAIL {record_path}: not a calibration record ({type(e).__name__}: {e})", err=True)
        sys.exit(2)
    click.echo(f"record {device}/{run_id} ({record_path})")
    click.echo(f"  sha256 {record.get('record_sha256')}")
    click.echo(f"  archive {landing}, store {store_dir}")
    status = record["content"].get("status")
    if status == "invalid":
        click.echo("  NOTE this record is marked INVALID (not a valid calibration): "
                   + "; ".join(record["content"].get("status_reasons") or []))
    if is_html:
        report("certificate shows exactly its record (hash, every printed value)", cert_problems)
    report("schema and content hash", schema_problems(record) + [p for p in [self_hash_problem(record)] if p])
    run_dir = landing / device / run_id
    report(f"raw files ({len(record['content'].get('raw_files', {}))}) match {run_dir}", raw_file_problems(record, run_dir))
    diffs, n = recompute_problems(record, landing, rtol, fraction)
    report(f"recomputed from the raw archive: {n} coefficients, noise terms and all conditions match "
           f"(within {fraction:g} of each precision)", diffs)

    chain_dir = chain_source(record_path, device, store_dir)
    if chain_dir is None:
        report("chain", [f"no stored records of device {device} in {store_dir} to check the chain against"])
    else:
        records, listing = load_records_dir(chain_dir)
        stored = records.get(run_id)
        if stored is not None and stored.get("record_sha256") != record.get("record_sha256") \
                and Path(record_path).resolve().parent != chain_dir.resolve():
            failures.append(f"the stored chain's record of run {run_id} has sha256 {stored.get('record_sha256')}, "
                            "not this record's")
            click.echo(f"  FAIL {failures[-1]}")
        records[run_id] = record
        expected = archive_runs(landing, store_dir, device)
        probs = chain_problems(records, listing, expected, up_to_run=run_id)
        limit = run_order_key(record["content"]["run"]["start_time_utc"], run_id)
        earlier = sorted((r for rid, r in records.items() if rid != run_id and "content" in r
                          and run_order_key(r["content"]["run"]["start_time_utc"], rid) < limit),
                         key=lambda r: run_order_key(r["content"]["run"]["start_time_utc"], r["content"]["run"]["run_id"]))
        report(f"hash chain of {device} up to {run_id}: {len(earlier) + 1} records, links intact ({chain_dir})", probs)
        if is_html:
            report("navigation budget: its embedded device calibration is the one the chain assembles",
                   budget_calibration_problems(record_path, [r for r in records.values() if "content" in r], run_id))
        for r in earlier:
            rid = r["content"]["run"]["run_id"]
            p = verify_record(r, landing, rtol, recompute=not shallow, fraction=fraction)
            report(f"earlier record {rid} verifies" + (" (hashes only)" if shallow else ""),
                   [f"earlier record {rid}: {x}" for x in p])
    if failures:
        click.echo(f"FAILED: {len(failures)} problem(s) with the record of {device}/{run_id}")
        sys.exit(1)
    click.echo(f"VERIFIED: the record of {device}/{run_id} matches the raw archive and its chain is intact"
               + ("; the record itself says it is NOT a valid calibration (see NOTE)" if status == "invalid" else ""))
