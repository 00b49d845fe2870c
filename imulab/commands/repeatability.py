"""``imulab repeatability``: turn-on bias and noise-term repeatability over a set of power-cycled static runs."""

from __future__ import annotations

import sys
from pathlib import Path

import click


@click.command("repeatability")
@click.argument("paths", nargs=-1, required=True, type=click.Path(exists=True, file_okay=False, path_type=Path))
@click.option("--csv", "csv_path", type=click.Path(dir_okay=False, path_type=Path), help="Write the table as CSV.")
@click.option("--runs-csv", type=click.Path(dir_okay=False, path_type=Path), help="Write the per-run terms as CSV.")
@click.option("--confidence", type=float, default=0.95, show_default=True)
def command(paths, csv_path, runs_csv, confidence):
    """Bias and noise-term repeatability of static runs (run folders of the raw-log contract, or landing folders).

    Every run is ingested (validated, read-only); per channel its mean is the turn-on bias (standard error from
    one noise model fitted to all the runs' Allan curves, at the record length, as the pipeline's repeatability
    stage) and its own Allan fit gives N and B. The table gives the standard
    deviation over runs (seed 000 eq. 23) with a chi-square interval and the value corrected for the per-run
    estimation noise with its interval (noise_corrected_ci_low/high). At least two runs are needed.
    """
    import pandas as pd

    from assets_lib.calibration.repeatability import (
        pooled_bias_stderrs,
        static_repeatability,
        static_run_allan,
        static_run_terms,
    )
    from raw_schemas.errors import RawDataError
    from raw_schemas.readers import discover_runs, ingest_run, is_complete

    dirs = []
    for p in paths:
        dirs += [p] if is_complete(p) or (p / "manifest.json").exists() else discover_runs(p)
    if len(dirs) < 2:
        raise click.ClickException(f"need at least two completed runs, found {len(dirs)}")
    frames, allan = [], {}
    for d in dirs:
        try:
            run = ingest_run(d)
        except RawDataError as e:
            click.echo(f"FAIL {d}: {e}", err=True)
            sys.exit(2)
        if run.manifest.test_kind != "static":
            click.echo(f"skip {d}: test kind {run.manifest.test_kind!r} (static runs only)", err=True)
            continue
        cols = [c for c in run.imu.columns if c.startswith(("gyro_", "accel_"))]
        units = {c: ("rad/s" if c.startswith("gyro") else "m/s^2") for c in cols}
        t = run.imu.time_s.to_numpy()
        data, rate_hz = {c: run.imu[c].to_numpy() for c in cols}, 1.0 / float(pd.Series(t).diff().median())
        res = static_run_allan(data, rate_hz, units)
        frames.append(static_run_terms(run.manifest.run_id, run.manifest.power_cycle_index, data, rate_hz, units, res))
        allan[str(run.manifest.run_id)] = pd.concat([r.to_frame() for r in res.values()], ignore_index=True)
        click.echo(f"ok   {d}: {len(t)} samples")
    if len(frames) < 2:
        raise click.ClickException("need at least two static runs")
    runs = pd.concat(frames, ignore_index=True)
    # as the pipeline's repeatability stage: the turn-on bias standard errors from one noise model per channel over
    # all the runs' Allan curves (the flicker floor estimated once, not held at zero per run)
    runs = pooled_bias_stderrs(runs, allan)
    table = static_repeatability(runs, confidence=confidence)
    with pd.option_context("display.width", 200, "display.max_columns", 20):
        click.echo(table[["channel", "quantity", "n_runs", "mean", "value", "ci_low", "ci_high",
                          "value_noise_corrected", "noise_corrected_ci_low", "noise_corrected_ci_high",
                          "unit"]].to_string(index=False))
    for w in sorted(set(w for s in runs["noise_warnings"] if s for w in s.split(" | "))):
        click.echo(f"WARNING {w}", err=True)
    if csv_path:
        table.to_csv(csv_path, index=False)
    if runs_csv:
        runs.to_csv(runs_csv, index=False)
