"""``imulab fit``: fit tables of plateau means (labs without raw logs): a gyro rate sweep or an accelerometer tumble.

\b
  imulab fit rate --means rate.csv --rate-unit deg/s --output-unit V
  imulab fit tumble --means tumble.csv --angle-unit deg --output-unit V --json tumble.json
  imulab fit rate --means rate.csv --sem-column sem_V --start-column t0_s --end-column t1_s \\
      --flicker-b 3e-4 --flicker-b-ci 2e-4 5e-4
  imulab fit rate ... --flicker-b-ci 0 4e-8       # a record that only bounds B (imulab allan: 'upper bound')
  imulab fit rate ... --flicker-b 3e-4 --sem-flicker-b 0   # sems that are white only (std / sqrt(n))

With each plateau's start and end time (and the sems) the fit models the 1/f (bias-instability) noise the plateaus
share (correlated-noise GLS, fit_core.flicker_gls): its level from the plateaus by REML, or the run's B from an Allan
analysis of the output (``imulab allan``) with its interval, integrated over, or only its upper bound (an interval
printed as [0, bound]: a record too short to resolve the 1/f floor), integrated over below it. ``--sem-flicker-b``
says which 1/f level the sems already contain (imulab's plateau table: ``<channel>_sem_flicker_b``; 0 for sems
computed as std / sqrt(n)), so that a plateau's white part is its sem less that floor; without it the sems are read
as containing the floor of the level the fit weighs. This is the fit the
coverage benchmark scores as ``imulab fit rate`` / ``fit tumble``; without times the plateaus are independent and a
warning says the intervals leave out the shared noise.
"""

from __future__ import annotations

import json
from pathlib import Path

import click
import numpy as np
import pandas as pd

from assets_lib.calibration.fit_core import flicker_dof_from_interval
from assets_lib.calibration.means_fit import (
    ANGLE_UNITS_TO_RAD,
    EXCLUSION_MODES,
    MeansFit,
    fit_rate_means,
    fit_tumble_means,
)
from raw_schemas.units import GYRO_UNITS_TO_RADPS


def _read(path: Path, in_col: str | None, out_col: str | None, sem_col: str | None, kind: str):
    try:
        df = pd.read_csv(path, sep=None, engine="python", comment="#")
    except Exception as e:  # noqa: BLE001 - report any parse problem to the user
        raise click.ClickException(f"cannot read {path}: {e}") from None
    df.columns = [str(c).strip() for c in df.columns]
    numeric = [c for c in df.columns if pd.api.types.is_numeric_dtype(df[c])]
    for opt, col in (("input", in_col), ("output", out_col), ("sem", sem_col)):
        if col is not None and col not in df.columns:
            raise click.ClickException(f"{path}: no column {col!r} for the {opt}; columns are {list(df.columns)}")
    if in_col is None or out_col is None:
        rest = [c for c in numeric if c not in (in_col, out_col, sem_col)]
        if in_col is None:
            if not rest:
                raise click.ClickException(f"{path}: no numeric column for the {kind}; columns are {list(df.columns)}")
            in_col = rest.pop(0)
        if out_col is None:
            if not rest:
                raise click.ClickException(f"{path}: no numeric column for the mean output; columns are {list(df.columns)}")
            out_col = rest.pop(0)
    x, y = _numbers(path, df, in_col), _numbers(path, df, out_col)
    s = _numbers(path, df, sem_col) if sem_col else None
    if len(x) < 3:
        raise click.ClickException(f"{path}: need at least 3 rows, found {len(x)}")
    return x, y, s, in_col, out_col, df


def _numbers(path: Path, df: pd.DataFrame, col: str) -> np.ndarray:
    """A column as floats; a non-empty cell that is not a number is an error naming its row (empty cells: NaN, the
    fit then excludes that plateau and says why)."""
    v = pd.to_numeric(df[col], errors="coerce")
    bad = np.flatnonzero(v.isna().to_numpy() & df[col].notna().to_numpy()
                         & (df[col].astype(str).str.strip() != "").to_numpy())
    if bad.size:
        raise click.ClickException(f"{path}: data row {int(bad[0]) + 1}, column {col!r}: {df[col].iloc[bad[0]]!r} is "
                                   f"not a number ({bad.size} such cells in that column)")
    return v.to_numpy(float)


def _noise_inputs(path: Path, df: pd.DataFrame, sem, start_col, end_col, flicker_b, flicker_b_dof, flicker_b_ci,
                  sem_flicker_b=None):
    """(times, flicker_b, flicker_b_dof, flicker_b_max, warnings) for the correlated-noise fit from the options
    (module doc)."""
    if (start_col is None) != (end_col is None):
        raise click.ClickException("--start-column and --end-column go together (each plateau's start and end time, s)")
    if flicker_b_dof is not None and flicker_b_ci is not None:
        raise click.ClickException("give B's degrees of freedom (--flicker-b-dof) or its interval (--flicker-b-ci), "
                                   "not both")
    bound = flicker_b_ci is not None and flicker_b_ci[0] <= 0
    if bound and (flicker_b is not None or flicker_b_dof is not None):
        raise click.ClickException(f"--flicker-b-ci {flicker_b_ci[0]:g} {flicker_b_ci[1]:g} is an upper bound "
                                   "(lower end <= 0: the record did not resolve B): give it alone, without "
                                   "--flicker-b / --flicker-b-dof")
    if bound and not (np.isfinite(flicker_b_ci[1]) and flicker_b_ci[1] > 0):
        raise click.ClickException(f"--flicker-b-ci: the upper bound must be a positive number, not {flicker_b_ci[1]}")
    if (flicker_b_dof is not None or (flicker_b_ci is not None and not bound)) and flicker_b is None:
        raise click.ClickException("--flicker-b-dof / --flicker-b-ci need --flicker-b")
    notes = []
    times = None
    if start_col is not None:
        if sem is None:
            raise click.ClickException("--start-column/--end-column model the 1/f noise shared between plateaus: "
                                       "they need the standard errors of the means (--sem-column)")
        for c in (start_col, end_col):
            if c not in df.columns:
                raise click.ClickException(f"{path}: no column {c!r} for the plateau times; columns are "
                                           f"{list(df.columns)}")
        times = tuple(_numbers(path, df, c) for c in (start_col, end_col))
        bad = np.flatnonzero(~np.isfinite(times[0]) | ~np.isfinite(times[1]) | (times[1] < times[0]))
        if bad.size:
            raise click.ClickException(f"{path}: data row {int(bad[0]) + 1}: plateau times {start_col!r}, "
                                       f"{end_col!r} must be numbers (s) with end >= start")
    elif sem is not None:
        notes.append("no plateau times (--start-column/--end-column): the plateaus are taken as independent, so "
                     "the 1/f (bias-instability) noise they share is not in the intervals, which are then too narrow "
                     "for a sensor whose bias wanders between plateaus")
    if (flicker_b is not None or bound) and times is None:
        raise click.ClickException("--flicker-b / --flicker-b-ci need the plateau times (--start-column/--end-column)")
    if sem_flicker_b is not None and times is None:
        raise click.ClickException("--sem-flicker-b (the 1/f level the sems contain) is read by the correlated-noise "
                                   "fit: it needs the plateau times (--start-column/--end-column)")
    if sem_flicker_b is not None and not (np.isfinite(sem_flicker_b) and sem_flicker_b >= 0):
        raise click.ClickException(f"--sem-flicker-b must be >= 0 (0: the sems are white only), not {sem_flicker_b}")
    if flicker_b is not None and not (np.isfinite(flicker_b) and flicker_b >= 0):
        raise click.ClickException(f"--flicker-b must be >= 0 (0: looked for and not detected), not {flicker_b}")
    if bound:
        return times, None, None, float(flicker_b_ci[1]), notes
    if flicker_b_ci is not None:
        lo, hi = flicker_b_ci
        try:
            flicker_b_dof = flicker_dof_from_interval(flicker_b, lo, hi)
        except ValueError as e:
            raise click.ClickException(f"--flicker-b-ci: {e}") from None
    return times, flicker_b, flicker_b_dof, None, notes


def _noise_json(times, b, b_dof, b_max, sem_b, notes) -> dict:
    return {"correlated_noise": times is not None, "flicker_b": b, "flicker_b_dof": b_dof, "flicker_b_max": b_max,
            "sem_flicker_b": sem_b, "input_warnings": list(notes)}


def _fmt(v: float) -> str:
    if v is None or not np.isfinite(v):
        return "n/a"
    return f"{v:.6g}"


def _print(res: MeansFit, header: str, input_warnings=()):
    click.echo(header)
    click.echo(f"points {res.n_points}, used {res.n_used}, dof {res.dof}, residual RMS {_fmt(res.residual_rms)} "
               f"{res.output_unit}, uncertainty from {res.cov_policy!r}")
    w = max(len(c.name) for c in res.coefficients)
    click.echo("")
    click.echo(f"{'coefficient':<{w}}  {'value':>13}  {'std. error':>11}  {'95 % interval':>27}  unit")
    for c in res.coefficients:
        if not c.observable:
            click.echo(f"{c.name:<{w}}  {'not observable':>13}  {'':>11}  {'':>27}  {c.unit}   ({c.note})")
            continue
        ci = f"[{_fmt(c.ci95_low)}, {_fmt(c.ci95_high)}]"
        click.echo(f"{c.name:<{w}}  {_fmt(c.value):>13}  {_fmt(c.stderr):>11}  {ci:>27}  {c.unit}")
    notes = [(c.name, c.note) for c in res.coefficients if c.observable and c.note]
    for name, note in notes:
        click.echo(f"  {name}: {note}")
    click.echo("")
    if res.excluded:
        click.echo(f"excluded points ({len(res.excluded)}):")
        for e in res.excluded:
            click.echo(f"  row {e.row}: input {_fmt(e.input)} {res.input_unit}, output {_fmt(e.output)} "
                       f"{res.output_unit}: {e.reason}")
    else:
        click.echo("excluded points: none")
    for wmsg in (*res.warnings, *input_warnings):
        click.echo(f"warning: {wmsg}")


def _write_json(res: MeansFit, path: str | None, extra: dict):
    if not path:
        return
    d = {**extra, **res.to_dict()}
    text = json.dumps(d, indent=2, allow_nan=False)
    if path == "-":
        click.echo(text)
    else:
        Path(path).write_text(text + "\n", encoding="utf-8")
        click.echo(f"wrote {path}")


def _plot(res: MeansFit, path: str | None, xlabel: str):
    if not path:
        return
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    r = res.residuals
    x = r.iloc[:, 1].to_numpy(float)
    ex = r["excluded"].to_numpy(bool)
    fig, ax = plt.subplots(figsize=(7, 3.2))
    ax.axhline(0, color="0.6", lw=0.8)
    ax.plot(x[~ex], r["residual"][~ex], "o", label="used")
    if ex.any():
        ax.plot(x[ex], r["residual"][ex], "x", color="red", ms=9, mew=2, label="excluded")
    ax.set_xlabel(xlabel)
    ax.set_ylabel(f"residual [{res.output_unit}]")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.savefig(path, dpi=110, bbox_inches="tight")
    plt.close(fig)
    click.echo(f"wrote {path}")


_common = [
    click.option("--means", "means", required=True, type=click.Path(exists=True, dir_okay=False, path_type=Path),
                 help="CSV (or other delimited text) with one row per plateau."),
    click.option("--output-unit", default="V", show_default=True, help="Unit of the mean output (free text: V, counts...)."),
    click.option("--output-column", default=None, help="Column of the mean output (default: the second numeric column)."),
    click.option("--sem-column", default=None, help="Optional column of standard errors of the means."),
    click.option("--start-column", default=None,
                 help="Column of each plateau's start time [s] (with --end-column and --sem-column): the 1/f noise "
                      "shared between plateaus enters the intervals (correlated-noise GLS, level by REML or "
                      "--flicker-b)."),
    click.option("--end-column", default=None, help="Column of each plateau's end time [s]."),
    click.option("--flicker-b", type=float, default=None,
                 help="The run's 1/f level B (bias instability) in the output unit, from an Allan analysis of the "
                      "output (imulab allan); 0 = looked for, not detected. Without it the plateaus' REML sets it."),
    click.option("--flicker-b-dof", type=float, default=None,
                 help="Degrees of freedom of B^2 (default: B taken as exact); or give --flicker-b-ci."),
    click.option("--flicker-b-ci", type=float, nargs=2, default=None,
                 help="B's 95 %% interval LOW HIGH as imulab allan prints it: its degrees of freedom are read "
                      "from it (B^2 as a scaled chi-square). An upper bound (LOW 0, given without --flicker-b): "
                      "the 1/f level is integrated over below HIGH."),
    click.option("--sem-flicker-b", type=float, default=None,
                 help="The 1/f level B the sems already contain (imulab's plateau table: <channel>_sem_flicker_b; "
                      "0 for sems that are white only, as std/sqrt(n)). Default: the sems are taken to contain the "
                      "Allan floor of the level the fit weighs."),
    click.option("--exclusion", type=click.Choice(EXCLUSION_MODES), default="auto", show_default=True,
                 help="auto: saturation (flat tops and plateaus at the rail) + Bonferroni outlier test; "
                      "saturation: no outlier test; flat-top: only plateaus whose output stopped following the "
                      "input; none."),
    click.option("--alpha", type=float, default=0.01, show_default=True, help="Family-wise level of the outlier test."),
    click.option("--json", "json_path", default=None, help="Also write the result as JSON to this path ('-' = stdout)."),
    click.option("--plot", "plot_path", default=None, help="Also write a residual plot (PNG) to this path."),
]


def _with_common(f):
    for opt in reversed(_common):
        f = opt(f)
    return f


@click.group(name="fit")
def command():
    """Fit tables of plateau means: `rate` (commanded rate, mean output) or `tumble` (table angle, mean output)."""


@command.command("rate", short_help="Gyro rate sweep: U = U0 + K w, nonlinearity, asymmetry.")
@_with_common
@click.option("--rate-unit", type=click.Choice(sorted(GYRO_UNITS_TO_RADPS)), default="deg/s", show_default=True)
@click.option("--rate-column", default=None, help="Column of the commanded rate (default: the first numeric column).")
def rate_cmd(means, output_unit, output_column, sem_column, start_column, end_column, flicker_b, flicker_b_dof,
             flicker_b_ci, sem_flicker_b, exclusion, alpha, json_path, plot_path, rate_unit, rate_column):
    """Seed 001 eq. 1-3: U = U0 + K w with nonlinearity, asymmetry and automatic exclusions."""
    x, y, s, ic, oc, df = _read(means, rate_column, output_column, sem_column, "commanded rate")
    times, b, b_dof, b_max, notes = _noise_inputs(means, df, s, start_column, end_column, flicker_b, flicker_b_dof,
                                                  flicker_b_ci, sem_flicker_b)
    res = fit_rate_means(x, y, s, rate_unit=rate_unit, output_unit=output_unit, exclusion=exclusion, alpha=alpha,
                         times=times, flicker_b=b, flicker_b_dof=b_dof, flicker_b_max=b_max,
                         sem_flicker_b=sem_flicker_b)
    _print(res, f"rate fit of {means} (rate column {ic!r} in {rate_unit}, output column {oc!r} in {output_unit})",
           notes)
    _write_json(res, json_path, {"file": str(means), "input_column": ic, "output_column": oc, "exclusion": exclusion,
                                 "alpha": alpha, "model": "U = U0 + K w", **_noise_json(times, b, b_dof, b_max, sem_flicker_b, notes)})
    _plot(res, plot_path, f"commanded rate [{rate_unit}]")


@command.command("tumble", short_help="Accelerometer tumble: U = K0 + K1 sin + K2 sin^2 + K3 sin cos.")
@_with_common
@click.option("--angle-unit", type=click.Choice(sorted(ANGLE_UNITS_TO_RAD)), default="deg", show_default=True)
@click.option("--angle-column", default=None, help="Column of the table angle (default: the first numeric column).")
@click.option("--misalignment-term/--no-misalignment-term", default=False, show_default=True,
              help="Add the IEEE 1293 cos(theta) misalignment term to seed 001's model.")
def tumble_cmd(means, output_unit, output_column, sem_column, start_column, end_column, flicker_b, flicker_b_dof,
               flicker_b_ci, sem_flicker_b, exclusion, alpha, json_path, plot_path, angle_unit, angle_column,
               misalignment_term):
    """Seed 001 eq. 5-7: U = K0 + K1 sin + K2 sin^2 + K3 sin cos (a_i = sin(theta) g)."""
    x, y, s, ic, oc, df = _read(means, angle_column, output_column, sem_column, "table angle")
    times, b, b_dof, b_max, notes = _noise_inputs(means, df, s, start_column, end_column, flicker_b, flicker_b_dof,
                                                  flicker_b_ci, sem_flicker_b)
    res = fit_tumble_means(x, y, s, angle_unit=angle_unit, output_unit=output_unit, misalignment_term=misalignment_term,
                           exclusion=exclusion, alpha=alpha, times=times, flicker_b=b, flicker_b_dof=b_dof,
                           flicker_b_max=b_max, sem_flicker_b=sem_flicker_b)
    _print(res, f"tumble fit of {means} (angle column {ic!r} in {angle_unit}, output column {oc!r} in {output_unit})",
           notes)
    _write_json(res, json_path, {"file": str(means), "input_column": ic, "output_column": oc, "exclusion": exclusion,
                                 "alpha": alpha, "model": "U = K0 + K1 sin + K2 sin^2 + K3 sin cos"
                                 + (" + d cos" if misalignment_term else ""),
                                 **_noise_json(times, b, b_dof, b_max, sem_flicker_b, notes)})
    _plot(res, plot_path, f"table angle [{angle_unit}]")



