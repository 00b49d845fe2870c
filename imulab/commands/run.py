"""``imulab run``: bring every output of a lab archive up to date through Dagster, then print a summary.

Exit status: 0 when every partition of every stage is computed (warnings allowed), 1 when any partition failed
(an ingest error, a compute error, a quality gate) or a Dagster run failed, 2 for unusable arguments (e.g. an
``--archive`` that is not a folder of runs).
"""

from __future__ import annotations

import os
import sys
import time
import warnings
from pathlib import Path
from types import SimpleNamespace

import click

from imulab.commands import workspace_options


@click.command("run")
@workspace_options("Landing folder of the lab archive. Default: <data>/landing, simulated first if empty.")
@click.option("--verbose", is_flag=True, help="Show Dagster's event log.")
@click.option("--skip-stage", "skip", multiple=True, metavar="STAGE",
              help="Leave this stage (and what reads it) out of the run, e.g. the costly sim_to_real; repeatable.")
@click.option("--certificates", is_flag=True,
              help="Also render the HTML certificates (the certificate stage; left out by default, see "
                   "`imulab certificates`).")
def command(landing, store, data_dir, dagster_home, verbose, skip, certificates=False):
    """Ingest and calibrate every completed run of a lab archive through Dagster, then print a summary.

    With no --archive, the embedded default (a simulated lab archive) is written to <data>/landing first.
    The reprocessing plan runs first: only partitions whose code or inputs changed are computed, in batched runs
    (captures, then devices, then the fleet); an unchanged archive launches nothing. The summary names every
    failed partition with its reason, counts warnings, and the exit status is 1 when anything failed.
    The HTML certificates are rendered only with --certificates (or by `imulab certificates`): drawing them cost
    more than the calibration; the records (JSON) are always written.
    """
    skip = (*skip, *(() if certificates else ON_DEMAND))
    data = Path(data_dir)
    _hold_workspace(data, store, dagster_home)  # released when the command ends
    if landing is None:
        landing = data / "landing"
        if not landing.is_dir() or not any(p for p in landing.iterdir() if not p.name.startswith("_")):
            from assets_lib.sim.simulator import ArchiveSpec, write_archive

            t0 = time.time()
            n = len(write_archive(landing, ArchiveSpec()))
            click.echo(f"simulated the default lab archive: {n} runs -> {landing.resolve()} ({time.time() - t0:.1f} s)")
    elif not Path(landing).is_dir():
        raise click.BadParameter(f"{landing} is not a folder", param_hint="--archive")
    landing = Path(landing).resolve()
    store = Path(store or data / "store").resolve()
    home = Path(dagster_home or os.environ.get("DAGSTER_HOME") or data / "dagster_home").resolve()
    if not verbose:
        warnings.filterwarnings("ignore")
    from assets_lib.stages.plan import plan_reprocess
    from assets_lib.store import LandingArchive, VersionedStore
    from pipelines.workspace import RunState, note_archive

    archive = LandingArchive(landing)
    complete, waiting = archive.complete_runs(), archive.incomplete_runs()
    if not complete and not waiting:
        raise click.BadParameter(f"no run folders (<device>/<run>/) in {landing}", param_hint="--archive")
    vstore = VersionedStore(store)
    t0 = time.time()
    state = RunState.read(home)
    graph = _planning_graph(store, skip) if state.covers(store, complete) else None
    if graph is not None:
        # the last run finished and registered every completed run: plan without Dagster or the science imports
        cap = list(state.captures)
        plan = plan_reprocess(graph, vstore, archive, cap, sorted({k.split("__", 1)[0] for k in cap}))
        if plan.empty:
            note_archive(store, landing)
            click.echo(f"{len(cap)} captured runs registered (0 new) from {landing}")
            click.echo(f"everything up to date ({plan.up_to_date} partitions checked in {time.time() - t0:.1f} s): "
                       "nothing launched")
            _finish(plan, NOTHING_LAUNCHED, vstore, waiting, store, landing, home, t0)
    from assets_lib.stages import graph_cache
    from assets_lib.stages.registry import STAGES as ALL_STAGES
    from pipelines.instance import fail_abandoned_runs
    from pipelines.launch import LaunchSummary, open_instance, register_landed_runs
    from pipelines.partitions import registered_keys
    from pipelines.resources import LabArchive

    graph_cache.prime(ALL_STAGES, store / GRAPH_CACHE)  # when current, spares parsing every stage's sources
    stages = _without(ALL_STAGES, skip)
    note_archive(store, landing)  # lets `imulab verify` find the archive from the store
    with open_instance(home) as instance:
        RunState(clean=False, store=str(store)).write(home)  # a run killed from here on leaves clean: false
        for rid in fail_abandoned_runs(instance):
            click.echo(f"marked Dagster run {rid} failed: the process running it was killed before it finished")
        new = register_landed_runs(instance, LabArchive(landing_dir=str(landing)))
        cap, dev = registered_keys(instance)
        click.echo(f"{len(cap)} captured runs registered ({len(new)} new) from {landing}")
        plan = plan_reprocess(stages, vstore, archive, cap, dev)
        summary = LaunchSummary()
        if plan.empty:
            click.echo(f"everything up to date ({plan.up_to_date} partitions checked in {time.time() - t0:.1f} s): "
                       "nothing launched")
        else:
            from pipelines import reprocess
            from pipelines.location import build_definitions

            defs = build_definitions(str(landing), str(store), stages=stages)
            summary = reprocess.run_plan(defs, instance, plan, vstore, quiet=not verbose)
            plan = plan_reprocess(stages, vstore, archive, cap, dev)  # what the store holds now
        RunState(clean=True, store=str(store), captures=cap).write(home)
    save_planning_graph(ALL_STAGES, store)
    _finish(plan, summary, vstore, waiting, store, landing, home, t0)


#: stages ``imulab run`` leaves out unless asked (``--certificates``; ``imulab certificates``)
ON_DEMAND = ("certificate",)
#: the launch summary of a run that launched nothing (``print_summary`` reads ``runs`` and ``warnings``)
NOTHING_LAUNCHED = SimpleNamespace(runs=[], warnings=[])
#: the planning view of the stage graph, kept in the store (``assets_lib.stages.graph_cache``)
GRAPH_CACHE = ".imulab-stage-graph.json"


def _without(graph, skip):
    skip = [n for n in skip if n not in ON_DEMAND or n in graph]  # a graph from before a stage existed
    try:
        return graph.without(skip)
    except KeyError as e:
        raise click.BadParameter(str(e.args[0]), param_hint="--skip-stage") from None


def _planning_graph(store: Path, skip):
    """The stage graph (less ``skip``) from the store's planning cache when the sources are unchanged, else None."""
    from assets_lib.stages import graph_cache

    graph = graph_cache.load(Path(store) / GRAPH_CACHE)
    return None if graph is None else _without(graph, skip)


def save_planning_graph(graph, store: Path) -> None:
    from assets_lib.stages import graph_cache

    try:
        graph_cache.save(graph, Path(store) / GRAPH_CACHE)
    except OSError:  # a read-only store still works, only the next unchanged run is slower
        pass


def _finish(plan, summary, vstore, waiting, store, landing, home, t0):
    for job, run_id, ok in summary.runs:
        click.echo(f"  {'ok  ' if ok else 'FAIL'} {job} run {run_id}")
    click.echo(f"pipeline finished in {time.time() - t0:.1f} s")
    from imulab.report import print_outputs

    print_outputs(store, echo=click.echo)
    click.echo(f"Dagster instance: {home}  (browse: DAGSTER_HOME={home} IMULAB_LANDING={landing} "
               f"IMULAB_STORE={store} dagster dev -w workspace.yaml)")
    failed = print_summary(plan, summary, vstore, waiting, echo=click.echo)
    sys.exit(1 if failed else 0)


def record_warnings(vstore) -> list[str]:
    """Records whose content status is not valid (``content.status`` / ``content.status_reasons``)."""
    from imulab.report import record_statuses

    return [f"record {dev}/{run}: {status} ({reasons or 'no reason given'})"
            for (dev, run), (status, reasons) in record_statuses(vstore).items() if status != "valid"]


def print_summary(plan, summary, vstore, waiting: list[str], echo=print) -> bool:
    """Failed partitions with their reasons, waiting runs, warnings; returns True when anything failed."""
    failed = list(plan.failed)
    runs_failed = [f"{job} run {rid}" for job, rid, ok in summary.runs if not ok]
    warns = [*summary.warnings, *record_warnings(vstore)]
    echo("\nsummary:")
    for stage, key, reason in failed:
        echo(f"  FAILED  {stage} {key}: {reason}")
    for r in runs_failed:
        echo(f"  FAILED  Dagster {r} (see its event log)")
    if plan.blocked_by:
        echo(f"  {len(plan.blocked_by)} partition(s) not computed because an upstream partition failed")
    for key in waiting:
        echo(f"  WAITING {key}: no _COMPLETE marker yet (the capture job is still writing, or died)")
    echo(f"  {len(warns)} warning(s)" + (":" if warns else ""))
    for w in warns[:20]:
        echo(f"    {w}")
    if len(warns) > 20:
        echo(f"    ... {len(warns) - 20} more")
    bad = bool(failed or runs_failed)
    echo(f"  status: {'FAILED' if bad else 'ok'} ({len(failed)} failed partition(s); exit status {1 if bad else 0})")
    return bad


def _hold_workspace(data: Path, store, dagster_home):
    """One run at a time per Dagster home and store (pipelines/workspace.py): a second one waits, then refuses."""
    from pipelines.workspace import RunLockedError, acquire_run_lock

    home = Path(dagster_home or os.environ.get("DAGSTER_HOME") or data / "dagster_home")
    try:
        click.get_current_context().call_on_close(acquire_run_lock(home, Path(store or data / "store"),
                                                                   echo=click.echo).close)
    except RunLockedError as e:
        raise click.ClickException(str(e)) from None
