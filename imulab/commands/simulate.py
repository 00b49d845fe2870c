"""``imulab simulate``: write a simulated lab archive (the embedded default data)."""

from __future__ import annotations

import time
from pathlib import Path

import click


@click.command("simulate")
@click.option("--out", "out_dir", type=click.Path(file_okay=False), default="imulab_data/landing", show_default=True,
              help="Landing folder to write <device>/<run>/ folders into.")
@click.option("--power-cycles", type=click.IntRange(1), default=3, show_default=True,
              help="Power-cycled repeats of the rate and 24-position tests per device.")
@click.option("--static-duration", "static_duration_s", type=click.FloatRange(60), default=1200.0, show_default=True,
              help="Length of each device's long static record [s].")
@click.option("--rate-plan", default="quick_rate", show_default=True, help="Rate plan from the plan library.")
@click.option("--position-plan", default="quick_24_position", show_default=True, help="Multi-position plan.")
@click.option("--seed", type=int, default=2026, show_default=True, help="Seed: the same seed writes the same bytes.")
def command(out_dir, power_cycles, static_duration_s, rate_plan, position_plan, seed):
    """Write a simulated lab archive: three devices (navigation FOG, tactical MEMS, consumer MEMS), each with
    power-cycled rate and 24-position runs, a long static record and a 12-position tumble, in the raw-log
    contract (manifest.json, imu.csv|parquet, table log, _COMPLETE). The truth goes to <out>/_truth/."""
    from assets_lib.sim.plans import available_plans
    from assets_lib.sim.simulator import ArchiveSpec, write_archive

    for p in (rate_plan, position_plan):
        if p not in available_plans():
            raise click.BadParameter(f"unknown plan {p!r}; available: {', '.join(available_plans())}")
    spec = ArchiveSpec(power_cycles=power_cycles, static_duration_s=static_duration_s, rate_plan=rate_plan,
                       position_plan=position_plan, seed=seed)
    t0 = time.time()
    paths = write_archive(Path(out_dir), spec)
    click.echo(f"wrote {len(paths)} runs of {len(spec.devices)} devices to {Path(out_dir).resolve()} "
               f"in {time.time() - t0:.1f} s (truth in {Path(out_dir).resolve() / '_truth'})")
