"""``imulab run``: materialize the Dagster pipeline over a lab archive (the main job)."""

from __future__ import annotations

import os
import sys
import time
import warnings
from pathlib import Path

import click

from imulab.commands import workspace_options


@click.command("run")
@workspace_options("Landing folder of the lab archive. Default: <data>/landing, simulated first if empty.")
@click.option("--verbose", is_flag=True, help="Show Dagster's event log.")
def command(landing, store, data_dir, dagster_home, verbose):
    """Ingest and calibrate every completed run of a lab archive through Dagster, then print where outputs are.

    With no --archive, the embedded default (a simulated lab archive) is written to <data>/landing first.
    Runs are batched: one Dagster run for all per-run stages, one for per-device stages, one for the fleet.
    Re-running reuses every unchanged output (nothing is rewritten).
    """
    data = Path(data_dir)
    _hold_workspace(data, store, dagster_home)  # released when the command ends
    if landing is None:
        landing = data / "landing"
        if not landing.is_dir() or not any(p for p in landing.iterdir() if not p.name.startswith("_")):
            from assets_lib.sim.simulator import ArchiveSpec, write_archive

            t0 = time.time()
            n = len(write_archive(landing, ArchiveSpec()))
            click.echo(f"simulated the default lab archive: {n} runs -> {landing.resolve()} ({time.time() - t0:.1f} s)")
    landing = Path(landing).resolve()
    store = Path(store or data / "store").resolve()
    home = Path(dagster_home or os.environ.get("DAGSTER_HOME") or data / "dagster_home").resolve()
    if not verbose:
        warnings.filterwarnings("ignore")
    from pipelines.definitions import build_definitions
    from pipelines.instance import fail_abandoned_runs, note_archive
    from pipelines.launch import materialize_archive, open_instance, register_landed_runs
    from pipelines.resources import LabArchive

    defs = build_definitions(str(landing), str(store))
    t0 = time.time()
    note_archive(store, landing)  # lets `imulab verify` find the archive from the store
    with open_instance(home) as instance:
        for rid in fail_abandoned_runs(instance):
            click.echo(f"marked Dagster run {rid} failed: the process running it was killed before it finished")
        new = register_landed_runs(instance, LabArchive(landing_dir=str(landing)))
        n_all = len(instance.get_dynamic_partitions("captures"))
        click.echo(f"{n_all} captured runs registered ({len(new)} new) from {landing}")
        summary = materialize_archive(defs, instance, quiet=not verbose)
    for job, run_id, ok in summary.runs:
        click.echo(f"  {'ok  ' if ok else 'FAIL'} {job} run {run_id}")
    click.echo(f"pipeline finished in {time.time() - t0:.1f} s")
    from imulab.report import print_outputs

    print_outputs(store, echo=click.echo)
    click.echo(f"Dagster instance: {home}  (browse: DAGSTER_HOME={home} IMULAB_LANDING={landing} "
               f"IMULAB_STORE={store} dagster dev -w workspace.yaml)")
    if not summary.success:
        sys.exit(1)


def _hold_workspace(data: Path, store, dagster_home):
    """One run at a time per Dagster home and store (pipelines/instance.py): a second one waits, then refuses."""
    from pipelines.instance import RunLockedError, acquire_run_lock

    home = Path(dagster_home or os.environ.get("DAGSTER_HOME") or data / "dagster_home")
    try:
        click.get_current_context().call_on_close(acquire_run_lock(home, Path(store or data / "store"),
                                                                   echo=click.echo).close)
    except RunLockedError as e:
        raise click.ClickException(str(e)) from None
