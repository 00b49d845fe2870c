"""One module per ``imulab`` sub-command; each exposes a click command named ``command``."""

import click


def workspace_options(archive_help: str):
    """The options every pipeline command shares: --archive, --store, --data-dir, --dagster-home."""
    options = [
        click.option("--archive", "landing", type=click.Path(file_okay=False), default=None, help=archive_help),
        click.option("--store", "store", type=click.Path(file_okay=False), default=None,
                     help="Versioned parquet outputs (default: <data>/store)."),
        click.option("--data-dir", default="imulab_data", show_default=True,
                     help="Working folder for the default archive, store and Dagster instance."),
        click.option("--dagster-home", default=None,
                     help="Dagster instance folder (default $DAGSTER_HOME or <data>/dagster_home)."),
    ]

    def deco(f):
        for opt in reversed(options):
            f = opt(f)
        return f

    return deco
