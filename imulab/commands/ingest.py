"""``imulab ingest``: validate raw run folders against the contract and write canonical SI parquet."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import click


@click.command("ingest")
@click.argument("run_dirs", nargs=-1, required=True, type=click.Path(exists=True, file_okay=False))
@click.option("--out", "out_dir", type=click.Path(file_okay=False), default=None,
              help="Write <out>/<device>__<run>/imu.parquet (+ table.parquet, manifest.json, sha256.json).")
def command(run_dirs, out_dir):
    """Validate each RUN_DIR (<landing>/<device>/<run>/) and convert it to canonical SI parquet.

    A landing folder may be given instead of run folders: every completed run below it is ingested.
    Bad input stops with an error naming the file, the row/column or field, and what was expected.
    The raw folders are only read.
    """
    from assets_lib.store import write_parquet_deterministic
    from raw_schemas.errors import RawDataError
    from raw_schemas.readers import discover_runs, ingest_run, is_complete

    runs = []
    for d in map(Path, run_dirs):
        runs += [d] if (d / "manifest.json").exists() or is_complete(d) else discover_runs(d)
    if not runs:
        raise click.ClickException("no run folders found (a run folder holds manifest.json and _COMPLETE)")
    failed = 0
    for d in runs:
        try:
            run = ingest_run(d)
        except RawDataError as e:
            failed += 1
            click.echo(f"FAIL {d}: {e}", err=True)
            continue
        msg = f"ok   {d}: {run.manifest.test_kind}, {len(run.imu)} samples"
        if out_dir:
            o = Path(out_dir) / run.partition_key
            o.mkdir(parents=True, exist_ok=True)
            write_parquet_deterministic(run.imu, o / "imu.parquet")
            if run.table is not None:
                write_parquet_deterministic(run.table, o / "table.parquet")
            (o / "manifest.json").write_text(run.manifest.model_dump_json(indent=2) + "\n")
            (o / "sha256.json").write_text(json.dumps(run.file_sha256, indent=1, sort_keys=True) + "\n")
            msg += f" -> {o}"
        click.echo(msg)
    if failed:
        click.echo(f"{failed} of {len(runs)} runs failed validation", err=True)
        sys.exit(2)
