"""``imulab certificates``: render the HTML calibration certificates of the current records (the ``certificate``
stage, through Dagster), after bringing everything else up to date. ``imulab run`` leaves this stage out: drawing
a certificate's plots and navigation budget cost more CPU than the calibration (issue 10 item 8).

Certificates land in ``<store>/certificate/<device>/<version>/<run>.html``; ``imulab verify CERT.html`` checks one.
Same options and exit status as ``imulab run``; an up-to-date store renders only the missing certificates.
"""

from __future__ import annotations

import click

from imulab.commands import run, workspace_options


@click.command("certificates")
@workspace_options("Landing folder of the lab archive (as for `imulab run`).")
@click.option("--verbose", is_flag=True, help="Show Dagster's event log.")
@click.option("--skip-stage", "skip", multiple=True, metavar="STAGE",
              help="As for `imulab run`: leave this stage (and what reads it) out, e.g. sim_to_real.")
@click.pass_context
def command(ctx, landing, store, data_dir, dagster_home, verbose, skip):
    """Render the HTML certificates of every device's current records (imulab run --certificates)."""
    ctx.invoke(run.command, landing=landing, store=store, data_dir=data_dir, dagster_home=dagster_home,
               verbose=verbose, skip=skip, certificates=True)
