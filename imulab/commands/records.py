"""``imulab records DEVICE [--at DATE] [--max-age DAYS]``: a device's calibration records, the one valid at a date,
and the device calibration assembled there (each term from the newest record holding it), with warnings.

\b
  imulab records TAC-002                                # list; valid now
  imulab records TAC-002 --at 2026-01-15 --max-age 90   # what was valid on that date
  imulab records TAC-002 --at 2026-01-20 --out cal.json # save the device calibration (for imulab apply / export)
Warnings (stderr): a record used is older than --max-age days at the date (default 30, imucal's threshold); a
calibration group has no record; fleet drift has flagged the device (trend, shift or a run beyond the control
limits) since the calibration used. --strict makes any warning exit with status 1.
"""

from __future__ import annotations

import sys
from pathlib import Path

import click


@click.command("records")
@click.argument("device")
@click.option("--at", "at", default=None, help="Date (ISO 8601, UTC unless it says otherwise); default: now.")
@click.option("--max-age", "max_age_days", type=float, default=None,
              help="Warn when a record used is older than this many days (default 30).")
@click.option("--store", type=click.Path(file_okay=False), default=None, help="Store folder (default <data>/store).")
@click.option("--data-dir", default="imulab_data", show_default=True, help="Working folder of imulab run.")
@click.option("--out", type=click.Path(dir_okay=False), default=None,
              help="Write the assembled device calibration JSON here (input of imulab apply / export).")
@click.option("--strict", is_flag=True, help="Exit with status 1 when there is any warning.")
def command(device, at, max_age_days, store, data_dir, out, strict):
    """List a device's records; pick the one valid at a date (staleness and drift warnings)."""
    import pandas as pd

    from assets_lib.apply.model import CalibrationError
    from assets_lib.records.lookup import DEFAULT_MAX_AGE_DAYS, lookup

    store = Path(store or Path(data_dir) / "store")
    try:
        res = lookup(store, device, at, DEFAULT_MAX_AGE_DAYS if max_age_days is None else max_age_days)
    except (CalibrationError, ValueError) as e:
        raise click.ClickException(str(e)) from None
    t = res.table.copy()
    t["valid"] = (t["run_id"] == res.valid_run_id).map({True: "<- valid", False: ""})
    t["record_sha256"] = t["record_sha256"].str[:16] + "..."
    t["start_time_utc"] = t["start_time_utc"].dt.strftime("%Y-%m-%d %H:%M")
    with pd.option_context("display.width", 200, "display.max_colwidth", 80):
        click.echo(f"records of {device} (store version {res.store_version}):")
        click.echo(t.to_string(index=False))
    click.echo(f"\nvalid at {res.at_utc.isoformat()}: record {res.valid_run_id}; device calibration "
               f"{res.calibration.identity_sha256[:16]}... from:")
    groups = {}
    for term in res.calibration.terms:
        groups.setdefault(term.group, term.run_id)
    for g, rid in groups.items():
        click.echo(f"  {g:<24} {rid}")
    noise = next((r["run_id"] for r in res.calibration.records if r["test_kind"] == "static"), None)
    click.echo(f"  {'noise':<24} {noise or '-'}")
    for w in res.warnings:
        click.echo(f"WARNING: {w}", err=True)
    if out:
        from assets_lib.apply.files import write_json_atomic

        write_json_atomic(out, res.calibration.to_json())
        click.echo(f"wrote {out}")
    if strict and res.warnings:
        sys.exit(1)
