"""``imulab reprocess``: recompute only stale partitions (changed code version or changed raw input)."""

from __future__ import annotations

import os
import sys
import time
import warnings
from pathlib import Path

import click

from imulab.commands import workspace_options


def _short(v: str | None) -> str:
    return (v or "-")[:12]


@click.command("reprocess")
@workspace_options("Landing folder of the lab archive (default: <data>/landing).")
@click.option("--dry-run", is_flag=True, help="Only print what is stale and why.")
@click.option("--retry-no-output", is_flag=True,
              help="Also request partitions whose stage produced no output at their current expected version.")
@click.option("--limit", default=20, show_default=True, help="Partitions listed per stage (0: all).")
@click.option("--verbose", is_flag=True, help="Show Dagster's event log.")
def command(landing, store, data_dir, dagster_home, dry_run, retry_no_output, limit, verbose):
    """Find stale partitions, print why, recompute them in batched runs, and print what was rewritten.

    A partition is stale when its expected version (code version + input versions, walked down the stage graph
    from the raw file hashes) differs from its current one, or it was never materialized. Old versions stay on
    disk and readable (audit); nothing is rewritten when nothing changed.
    """
    data = Path(data_dir)
    landing = Path(landing or data / "landing").resolve()
    store = Path(store or data / "store").resolve()
    home = Path(dagster_home or os.environ.get("DAGSTER_HOME") or data / "dagster_home").resolve()
    if not landing.is_dir():
        raise click.ClickException(f"no archive at {landing}")
    _hold_workspace(home, store)  # the lock of `imulab run`: one at a time per workspace; released at the end
    if not verbose:
        warnings.filterwarnings("ignore")
    from assets_lib.stages.plan import outcome
    from assets_lib.stages.registry import STAGES
    from assets_lib.store import VersionedStore
    from pipelines import reprocess
    from pipelines.launch import open_instance, register_landed_runs
    from pipelines.location import build_definitions
    from pipelines.partitions import registered_keys
    from pipelines.resources import LabArchive
    from pipelines.workspace import RunState

    archive = LabArchive(landing_dir=str(landing))
    vstore = VersionedStore(store)
    defs = build_definitions(str(landing), str(store))
    t0 = time.time()
    with open_instance(home) as instance:
        RunState(clean=False, store=str(store)).write(home)  # killed from here on: the next `imulab run` checks
        new = register_landed_runs(instance, archive)
        if new:
            click.echo(f"registered {len(new)} newly landed runs")
        plan = reprocess.plan_for_instance(instance, STAGES, vstore, archive.archive, use_ledger=not retry_no_output)
        click.echo(f"checked {plan.up_to_date + len(plan.stale)} partitions in {time.time() - t0:.1f} s: "
                   f"{len(plan.stale)} stale, {plan.up_to_date} up to date, {plan.not_applicable} not applicable, "
                   f"{plan.waiting} waiting for inputs, {len(plan.no_output)} without output at this version")
        for stage, items in plan.by_stage().items():
            click.echo(f"  {stage}: {len(items)} stale")
            for s in items[: limit or None]:
                click.echo(f"    {s.key}: {s.reason} ({_short(s.current)} -> {_short(s.expected)})")
            if limit and len(items) > limit:
                click.echo(f"    ... {len(items) - limit} more")
        for stage, key, reason in plan.failed[: limit or None]:
            click.echo(f"  failed at this version (not retried; --retry-no-output retries): {stage} {key}: {reason}")
        cap, dev = registered_keys(instance)
        if plan.empty:
            RunState(clean=True, store=str(store), captures=cap).write(home)
            click.echo("nothing to reprocess")
            return
        runs = reprocess.planned_runs(plan, cap, dev)
        click.echo(f"{len(runs)} batched run(s): " + "; ".join(
            f"{r.job} [{r.first}..{r.last}] {','.join(r.stages)}" if r.first else f"{r.job} {','.join(r.stages)}"
            for r in runs))
        if dry_run:
            RunState(clean=True, store=str(store), captures=cap).write(home)
            click.echo("dry run: nothing executed")
            return
        t1 = time.time()
        summary = reprocess.run_plan(defs, instance, plan, vstore, quiet=not verbose)
        RunState(clean=True, store=str(store), captures=cap).write(home)
    for job, run_id, ok in summary.runs:
        click.echo(f"  {'ok  ' if ok else 'FAIL'} {job} run {run_id}")
    done = outcome(vstore, plan)
    rewritten = [s for s, o in done if o == "rewritten"]
    click.echo(f"rewrote {len(rewritten)} partition(s) in {time.time() - t1:.1f} s "
               f"({len(done) - len(rewritten)} produced no output):")
    shown: dict[str, int] = {}
    for s, o in done:
        shown[s.stage] = shown.get(s.stage, 0) + 1
        if limit and shown[s.stage] > limit:
            continue
        where = vstore.version_dir(s.stage, s.key, s.expected) if o == "rewritten" else "-"
        click.echo(f"  {o:9s} {s.stage}/{s.key}: {_short(s.current)} -> {_short(s.expected)}  {where}")
    for stage, n in shown.items():
        if limit and n > limit:
            click.echo(f"  ... {stage}: {n - limit} more")
    if not summary.success:
        sys.exit(1)


def _hold_workspace(home: Path, store: Path) -> None:
    """The run lock of ``imulab run`` (pipelines/workspace.py), held until the command ends: a reprocess never
    writes the store or the instance while a run (or another reprocess) does; it waits, then refuses."""
    from pipelines.workspace import RunLockedError, acquire_run_lock

    try:
        click.get_current_context().call_on_close(acquire_run_lock(home, store, echo=click.echo).close)
    except RunLockedError as e:
        raise click.ClickException(str(e)) from None
