"""``imulab import``: convert a third-party IMU log into a run of the raw-log contract in a landing folder."""

from __future__ import annotations

import sys
import warnings
from pathlib import Path

import click


def _options(pairs) -> dict:
    out = {}
    for p in pairs:
        if "=" not in p:
            raise click.BadParameter(f"expected KEY=VALUE, got {p!r}", param_hint="-o/--option")
        k, v = p.split("=", 1)
        out[k.strip()] = v.strip()
    return out


def _help() -> str:
    """The command's help: the formats from the registry, each with the -o options its module declares (``OPTIONS``)."""
    from raw_schemas.importers import IMPORTERS, accepted_options

    lines = ["Read SOURCES in FORMAT and write one contract run (manifest.json, imu.parquet, _COMPLETE) to LANDING.",
             "", "\b", "Formats and the -o KEY=VALUE options each accepts (see docs/realdata.md):"]
    for fmt in IMPORTERS:
        lines.append(f"  {fmt}: {IMPORTERS[fmt][1]}")
        opts = accepted_options(fmt)
        width = max(map(len, opts))
        lines += [f"      {k:<{width}}  {d}" for k, d in sorted(opts.items())]
    lines += ["", "Any other option key stops the import with an error naming it and the accepted ones.",
              "", ("The sources are only read. Bad input stops with an error naming the file, the row or field, and "
                   "what was expected (exit status 2). Values that look mis-scaled (a mostly still session whose median "
                   "|f| is far from 1 g, or whose median |w| is far from 0) are written but named in a WARN line on "
                   "stderr, with the option to check.")]
    return "\n".join(lines)


def _formats() -> list[str]:
    from raw_schemas.importers import IMPORTERS

    return list(IMPORTERS)


@click.command("import", help=_help())
@click.argument("fmt", metavar="FORMAT", type=click.Choice(_formats()))
@click.argument("sources", nargs=-1, required=True, type=click.Path(exists=True))
@click.option("--landing", required=True, type=click.Path(file_okay=False), help="Landing folder to write <device>/<run>/ into.")
@click.option("--device-id", required=True, help="Device id (folder name, manifest device.id).")
@click.option("--run-id", default=None, help="Run id (default: the first source's file stem).")
@click.option("--model", "device_model", default="unknown", show_default=True, help="Device model.")
@click.option("--grade", default="consumer", show_default=True,
              type=click.Choice(["consumer", "industrial", "tactical", "navigation"]))
@click.option("--latitude-deg", default=0.0, show_default=True, type=float, help="Site latitude (earth rate, normal gravity).")
@click.option("--height-m", default=0.0, show_default=True, type=float)
@click.option("--gravity-mps2", default=None, type=float, help="Measured local gravity (else WGS-84 normal gravity).")
@click.option("--start-time-utc", default=None, help="ISO 8601 UTC time of the first sample (ROS sources carry it).")
@click.option("--power-cycle-index", default=0, show_default=True, type=int)
@click.option("-o", "--option", "opts", multiple=True, metavar="KEY=VALUE",
              help="Format option, e.g. -o profile=p.json, -o accel_lsb=0.0024, -o topic=/imu, -o sample_rate_hz=204.8.")
def command(fmt, sources, landing, device_id, run_id, device_model, grade, latitude_deg, height_m, gravity_mps2,
            start_time_utc, power_cycle_index, opts):
    from raw_schemas.errors import RawDataError
    from raw_schemas.importers import ImportedDataWarning, RunMeta, import_run

    meta = RunMeta(device_id=device_id, run_id=run_id or Path(sources[0]).stem.replace(" ", "_"),
                   device_model=device_model, grade=grade, latitude_deg=latitude_deg, height_m=height_m,
                   gravity_mps2=gravity_mps2, start_time_utc=start_time_utc, power_cycle_index=power_cycle_index)
    try:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always", ImportedDataWarning)
            out = import_run(fmt, list(sources), landing, meta, _options(opts))
    except RawDataError as e:
        click.echo(f"FAIL import {fmt}: {e}", err=True)
        sys.exit(2)
    for w in caught:
        if issubclass(w.category, ImportedDataWarning):
            click.echo(f"WARN import {fmt}: {w.message}", err=True)
        else:
            warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)
    click.echo(f"ok   {out}")
