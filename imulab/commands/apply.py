"""``imulab apply RECORD DATA --out FILE``: calibrate IMU data with a calibration record (or a device calibration
assembled by ``imulab records DEVICE --at DATE --out cal.json``).

\b
  imulab apply store/calibration_record/TAC-002/<version>/pc02-pos24.json landing/TAC-002/pc03-rate --out cal.parquet
  imulab apply cal.json imu.csv --manifest manifest.json --out cal.parquet
  imulab apply cal.json other.parquet --device TAC-002 --out cal.parquet   # canonical SI table without manifest
DATA: a run folder, a raw imu.csv|parquet stream with its manifest, or a canonical SI table (gyro_x_radps ...).
The output is canonical SI parquet; its metadata (key ``imulab.calibration``) holds the calibration's sha256, the
records (run id, sha256, store version) it was built from, the terms applied and the input's sha256.
Data of another device is refused unless --force; raw columns without a manifest, or non-SI values in SI-named
columns, are refused with the file and column named (exit status 1).
"""

from __future__ import annotations

import click

from imulab import __version__


@click.command("apply")
@click.argument("record", type=click.Path(exists=True, dir_okay=False))
@click.argument("data", type=click.Path(exists=True))
@click.option("--out", required=True, type=click.Path(dir_okay=False), help="Calibrated parquet to write (atomic).")
@click.option("--manifest", type=click.Path(exists=True, dir_okay=False), default=None,
              help="manifest.json of a raw stream (default: the one beside DATA).")
@click.option("--device", default=None, help="Device id of DATA when it has no manifest.")
@click.option("--force", is_flag=True, help="Apply even to another (or an unknown) device's data.")
def command(record, data, out, manifest, device, force):
    """Calibrate IMU data with a calibration record or device calibration."""
    from assets_lib.apply.files import apply_file
    from assets_lib.apply.model import CalibrationError, load_calibration
    from raw_schemas.errors import RawDataError

    try:
        cal = load_calibration(record)
        path, meta = apply_file(cal, data, out, manifest=manifest, device=device, force=force,
                                imulab_version=__version__)
    except (CalibrationError, RawDataError) as e:
        raise click.ClickException(str(e)) from None
    for w in meta["warnings"]:
        click.echo(f"WARNING: {w}", err=True)
    click.echo(f"calibrated {meta['input']['how']} {data} (device {meta['input']['device_id'] or device or '?'}) with "
               f"calibration {meta['calibration_sha256'][:16]}... of {cal.device_id}: "
               f"{len(meta['applied_terms'])} terms from " + ", ".join(
                   f"{r['run_id']} ({r['record_sha256'][:12]}...)" for r in meta["records"]))
    click.echo(f"wrote {path}")
