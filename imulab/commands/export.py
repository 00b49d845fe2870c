"""``imulab export RECORD --format F [--out FILE]``: a calibration record (or a device calibration from
``imulab records DEVICE --out cal.json``) in the file format another tool reads.

\b
  imulab export cal.json --format kalibr --out imu.yaml              # Kalibr noise model (Allan N and K)
  imulab export cal.json --format openvins --out kalibr_imu_chain.yaml
  imulab export cal.json --format imucal --out cal_imucal.json       # imucal.management.load_calibration_info
  imulab export cal.json --format c-header --out imu_cal.h           # firmware compensation matrices
Formats: kalibr, openvins (model kalibr), openvins-rpng, imucal, firmware-json, c-header. Conventions (units,
frames, signs, what each tool cannot represent) are written into every file; see docs/using_a_record.md.
"""

from __future__ import annotations

import click

from assets_lib.records.export import EXPORTERS


@click.command("export")
@click.argument("record", type=click.Path(exists=True, dir_okay=False))
@click.option("--format", "fmt", required=True, type=click.Choice(list(EXPORTERS)), help="Output format.")
@click.option("--out", type=click.Path(dir_okay=False), default=None, help="File to write (default: stdout).")
def command(record, fmt, out):
    """Export a calibration for Kalibr/OpenVINS, imucal, or firmware (JSON, C header)."""
    from assets_lib.apply.files import write_text_atomic
    from assets_lib.apply.model import CalibrationError, load_calibration
    from assets_lib.records.export import export

    try:
        text = export(load_calibration(record), fmt)
    except CalibrationError as e:
        raise click.ClickException(str(e)) from None
    if out:
        write_text_atomic(out, text)
        click.echo(f"wrote {out} ({fmt})")
    else:
        click.echo(text, nl=False)
