"""``imulab`` command line: a click group whose sub-commands load lazily (``imulab allan`` never imports dagster)."""

from __future__ import annotations

import importlib
import importlib.util

import click

from imulab import __version__

#: sub-command name -> (module, one-line help shown by ``imulab --help``)
COMMANDS: dict[str, tuple[str, str]] = {
    "simulate": ("imulab.commands.simulate", "Write a simulated lab archive (the embedded default data)."),
    "ingest": ("imulab.commands.ingest", "Validate raw runs and convert them to canonical SI parquet."),
    "run": ("imulab.commands.run", "Materialize the Dagster pipeline over a lab archive."),
    "reprocess": ("imulab.commands.reprocess", "Recompute only stale partitions (changed code or raw input)."),
    "verify": ("imulab.commands.verify", "Recompute a calibration record from the raw archive and check it."),
    "fit": ("imulab.commands.fit", "Fit rate or tumble tables of plateau means (labs without raw logs)."),
    "allan": ("imulab.commands.allan", "Allan deviation and noise identification of a static record."),
    "diagnose": ("imulab.commands.diagnose", "Sim-to-real gap diagnosis: where, which effect, how far it shrinks."),
}


class LazyGroup(click.Group):
    def list_commands(self, ctx):
        return [n for n, (mod, _) in COMMANDS.items() if importlib.util.find_spec(mod) is not None]

    def get_command(self, ctx, name):
        if name not in COMMANDS or importlib.util.find_spec(COMMANDS[name][0]) is None:
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
      imulab allan FILE --plot a.png  # Allan deviation and noise terms of any static record
    """


if __name__ == "__main__":  # pragma: no cover
    main()
