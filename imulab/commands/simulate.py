"""``imulab simulate``: write a simulated lab archive (the embedded default data), or runs of a device model."""

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
@click.option("--device-model", "device_model", type=click.Path(dir_okay=False, exists=True), default=None,
              help="Simulate this device-model file (raw_schemas/device_model.schema.json) instead of the example "
                   "devices: every power cycle of the model, with its effect families.")
@click.option("--plan", "plans", multiple=True,
              help="With --device-model: plan(s) from the plan library to run in each power cycle (repeatable; "
                   "default: rate, 24-position, and static + tumble in the first cycle).")
@click.option("--replay", "replay_dirs", multiple=True, type=click.Path(file_okay=False, exists=True),
              help="With --device-model: replay these recorded run folders (their timestamps, table log, "
                   "temperature log, power-on time) instead of running plans (repeatable).")
def command(out_dir, power_cycles, static_duration_s, rate_plan, position_plan, seed, device_model, plans, replay_dirs):
    """Write a simulated lab archive: three devices (navigation FOG, tactical MEMS, consumer MEMS), each with
    power-cycled rate and 24-position runs, a long static record and a 12-position tumble, in the raw-log
    contract (manifest.json, imu.csv|parquet, table log, _COMPLETE). The truth goes to <out>/_truth/.

    With --device-model FILE the runs are those of the model's unit (its fitted base model per power cycle, its
    noise terms and effect families), for --plan or --replay."""
    from assets_lib.sim.plans import available_plans

    t0 = time.time()
    if device_model is None:
        if plans or replay_dirs:
            raise click.UsageError("--plan and --replay need --device-model")
        from assets_lib.sim.simulator import ArchiveSpec, write_archive

        for p in (rate_plan, position_plan):
            if p not in available_plans():
                raise click.BadParameter(f"unknown plan {p!r}; available: {', '.join(available_plans())}")
        spec = ArchiveSpec(power_cycles=power_cycles, static_duration_s=static_duration_s, rate_plan=rate_plan,
                           position_plan=position_plan, seed=seed)
        paths = write_archive(Path(out_dir), spec)
        click.echo(f"wrote {len(paths)} runs of {len(spec.devices)} devices to {Path(out_dir).resolve()} "
                   f"in {time.time() - t0:.1f} s (truth in {Path(out_dir).resolve() / '_truth'})")
        return
    from assets_lib.sim.device_model import simulate_model_runs, write_model_runs
    from raw_schemas.device_model import load_device_model
    from raw_schemas.errors import RawDataError

    for p in plans:
        if p not in available_plans():
            raise click.BadParameter(f"unknown plan {p!r}; available: {', '.join(available_plans())}", param_hint="--plan")
    try:
        model = load_device_model(device_model)
        runs = simulate_model_runs(model, list(plans) or None, replay_dirs=replay_dirs, seed=seed)
        paths = write_model_runs(model, Path(out_dir), runs)
    except (RawDataError, ValueError) as e:
        raise click.ClickException(str(e)) from None
    fams = ", ".join(e.family for e in model.effects) or "none"
    click.echo(f"wrote {len(paths)} runs of {model.device.id} ({len(model.power_cycles)} power cycles; effects: {fams}) "
               f"to {Path(out_dir).resolve()} in {time.time() - t0:.1f} s (truth in {Path(out_dir).resolve() / '_truth'})")
