"""``imulab diagnose``: sim-to-real gap diagnosis of every device in a landing folder (docs/simreal.md).

\b
  imulab diagnose --archive imulab_data/landing --out diagnosis/
  imulab diagnose --archive LANDING --device TAC-002 --replicates 100 --seed 3 --out DIR
Writes DIR/<device>.json (raw_schemas/diagnosis_report.schema.json), DIR/<device>.html and DIR/<device>.twin.json.
"""

from __future__ import annotations

import time
from pathlib import Path

import click


@click.command("diagnose")
@click.option("--archive", "archive", type=click.Path(exists=True, file_okay=False), required=True,
              help="Landing folder <archive>/<device>/<run>/ (raw-log contract).")
@click.option("--device", "devices", multiple=True, help="Device id (repeatable); default every device.")
@click.option("--out", "out_dir", type=click.Path(file_okay=False), required=True, help="Output folder.")
@click.option("--replicates", type=click.IntRange(3), default=20, show_default=True,
              help="Replicates of the fitted twin per device (>= 100 for decisions near a threshold).")
@click.option("--seed", type=int, default=0, show_default=True, help="Seed: the same seed gives the same report.")
@click.option("--workers", type=click.IntRange(1), default=None, help="Worker processes (default: up to 2).")
def command(archive, devices, out_dir, replicates, seed, workers):
    """Where the real data differ from the fitted twin, which unmodelled effect explains it, how far the gap
    shrinks once it is modelled; one report per device."""
    from assets_lib.simreal.diagnose import diagnose_device
    from assets_lib.simreal.experiment import list_devices
    from assets_lib.simreal.report import write_outputs

    devs = list(devices) or list_devices(archive)
    if not devs:
        raise click.ClickException(f"{archive}: no completed run (expected <archive>/<device>/<run>/_COMPLETE)")
    known = set(list_devices(archive))
    missing = [d for d in devs if d not in known]
    if missing:
        raise click.ClickException(f"{archive}: no completed run of device(s) {', '.join(missing)}; "
                                   f"available: {', '.join(sorted(known))}")
    failed = []
    for dev in devs:
        t0 = time.time()
        try:
            diag = diagnose_device(archive, dev, replicates=replicates, seed=seed, workers=workers,
                                   progress=lambda m: click.echo(m, err=True))
        except (ValueError, FileNotFoundError) as exc:
            click.echo(f"{dev}: FAILED: {exc}", err=True)
            failed.append(dev)
            continue
        paths = write_outputs(diag, Path(out_dir))
        r = diag.report
        eff = ", ".join(f"{e['family']}{'/' + e['channel'] if e['channel'] else ''}" for e in r["effects"]) or "-"
        click.echo(f"{dev}: verdict {r['verdict']}; effects {eff}; gap z {r['gap']['z']:.1f}; "
                   f"shrink {r['shrink']['ratio']:.2f}; {time.time() - t0:.0f} s -> {paths['html']}")
    if failed:
        raise click.ClickException(f"diagnosis failed for {', '.join(failed)}")
