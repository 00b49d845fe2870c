"""``imulab twin``: build a device-model file (the digital twin's input) from a device's calibration outputs."""

from __future__ import annotations

from pathlib import Path

import click


@click.command("twin")
@click.argument("device")
@click.option("--store", "store", type=click.Path(file_okay=False), default="imulab_data/store", show_default=True,
              help="Versioned output store of the pipeline (<store>/<asset>/<partition>/<version>/).")
@click.option("--out", "out_file", type=click.Path(dir_okay=False), required=True,
              help="Device-model JSON file to write (raw_schemas/device_model.schema.json).")
@click.option("--effects", "effects_file", type=click.Path(dir_okay=False, exists=True), default=None,
              help="JSON list of effect families to add, [{\"family\": ..., \"params\": {...}}, ...].")
def command(device, store, out_file, effects_file):
    """Build DEVICE's model from its calibration outputs in the store: per power cycle the gyro rate fit and
    accelerometer multi-position fit coefficients (inverse-variance means over the cycle's runs), the static
    gyro biases and g-sensitivity, and the Allan noise terms of its static record. Then
    `imulab simulate --device-model FILE` writes runs of this unit."""
    import json

    from assets_lib.sim.device_model import model_from_calibration, read_store_tables
    from assets_lib.sim.effects import effects_from_list
    from raw_schemas.device_model import DeviceModel, EffectSpec, write_device_model

    try:
        runs = read_store_tables(store, device)
        model = model_from_calibration(runs, provenance={"source": "calibration outputs", "store": str(Path(store).resolve()),
                                                         "runs": sorted(r.run_id for r in runs)})
        if effects_file:
            items = json.loads(Path(effects_file).read_text())
            effects_from_list(items)  # unknown families / parameters fail here, with their names
            model = DeviceModel.model_validate({**model.model_dump(), "effects": [EffectSpec(**e).model_dump() for e in items]})
    except (FileNotFoundError, ValueError) as e:
        raise click.ClickException(str(e)) from None
    path = write_device_model(model, out_file)
    pcs = ", ".join(f"{p.index} ({len(p.sources)} runs)" for p in model.power_cycles)
    click.echo(f"wrote the model of {device} to {Path(path).resolve()}: power cycles {pcs}; "
               f"noise from {'a static record' if any(getattr(model.noise.gyro, a).n for a in 'xyz') else 'none'}")
