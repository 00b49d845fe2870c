"""``imulab`` command line: a click group whose sub-commands load lazily (``imulab allan`` never imports dagster)."""

from __future__ import annotations

import importlib

import click

from imulab import __version__

#: sub-command name -> (module, one-line help shown by ``imulab --help``)
COMMANDS: dict[str, tuple[str, str]] = {
    "simulate": ("imulab.commands.simulate", "Write a simulated lab archive (the embedded default data)."),
    "import": ("imulab.commands.import_", "Convert imu_tk, imucal, ROS bag/MCAP or profiled CSV logs into contract runs."),
    "ingest": ("imulab.commands.ingest", "Validate raw runs and convert them to canonical SI parquet."),
    "run": ("imulab.commands.run", "Materialize the Dagster pipeline over a lab archive."),
    "reprocess": ("imulab.commands.reprocess", "Recompute only stale partitions (changed code or raw input)."),
    "certificates": ("imulab.commands.certificates", "Render the HTML calibration certificates of the current records."),
    "plots": ("imulab.commands.plots", "Draw the figures of stored outputs (residual, Allan, segmentation, drift)."),
    "verify": ("imulab.commands.verify", "Recompute a calibration record from the raw archive and check it."),
    "fit": ("imulab.commands.fit", "Fit rate or tumble tables of plateau means (labs without raw logs)."),
    "allan": ("imulab.commands.allan", "Allan deviation and noise identification of a static record."),
    "repeatability": ("imulab.commands.repeatability", "Turn-on bias and noise-term repeatability of static runs."),
    "twin": ("imulab.commands.twin", "Build a device-model file (digital twin) from a device's calibration outputs."),
    "apply": ("imulab.commands.apply", "Calibrate IMU data with a calibration record or device calibration."),
    "records": ("imulab.commands.records", "List a device's records; pick the one valid at a date (staleness, drift)."),
    "export": ("imulab.commands.export", "Export a calibration for Kalibr/OpenVINS, imucal, or firmware (JSON, C header)."),
    "diagnose": ("imulab.commands.diagnose", "Sim-to-real gap diagnosis: where, which effect, how far it shrinks."),
}


class LazyGroup(click.Group):
    """Lists every entry of ``COMMANDS`` and imports a command's module only when it is invoked (a new command is
    a module under ``imulab/commands`` exposing ``command`` plus one line in ``COMMANDS``)."""

    def list_commands(self, ctx):
        return list(COMMANDS)

    def get_command(self, ctx, name):
        if name not in COMMANDS:
            return None
        return importlib.import_module(COMMANDS[name][0]).command

    def format_commands(self, ctx, formatter):
        rows = [(n, COMMANDS[n][1]) for n in self.list_commands(ctx)]
        if rows:
            with formatter.section("Commands"):
                formatter.write_dl(rows)


@click.group(cls=LazyGroup, context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(__version__, prog_name="imulab")
def main():
    """imulab: IMU calibration from turntable and multi-position tests, with audited records.

    \b
    Quick start:
      imulab run                      # simulate the default lab archive, then calibrate it
      imulab simulate --out ARCHIVE   # write a simulated lab archive
      imulab run --archive ARCHIVE    # ingest + calibrate every completed run in ARCHIVE
      imulab certificates --archive ARCHIVE   # render the HTML certificates of the records
      imulab allan FILE --plot a.png  # Allan deviation and noise terms of any static record
    """


if __name__ == "__main__":  # pragma: no cover
    main()
