"""``imulab fit``: fit tables of plateau means (labs without raw logs): a gyro rate sweep or an accelerometer tumble.

\b
  imulab fit rate --means rate.csv --rate-unit deg/s --output-unit V
  imulab fit tumble --means tumble.csv --angle-unit deg --output-unit V --json tumble.json
"""

from __future__ import annotations

import json

from pathlib import Path

import click
import numpy as np
import pandas as pd

from assets_lib.calibration.means_fit import ANGLE_UNITS_TO_RAD, EXCLUSION_MODES, MeansFit, fit_rate_means, fit_tumble_means
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
    x = pd.to_numeric(df[in_col], errors="coerce").to_numpy(float)
    y = pd.to_numeric(df[out_col], errors="coerce").to_numpy(float)
    s = pd.to_numeric(df[sem_col], errors="coerce").to_numpy(float) if sem_col else None
    if len(x) < 3:
        raise click.ClickException(f"{path}: need at least 3 rows, found {len(x)}")
    return x, y, s, in_col, out_col


def _fmt(v: float) -> str:
    if v is None or not np.isfinite(v):
        return "n/a"
    return f"{v:.6g}"


def _print(res: MeansFit, header: str):
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
    for wmsg in res.warnings:
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
def rate_cmd(means, output_unit, output_column, sem_column, exclusion, alpha, json_path, plot_path, rate_unit, rate_column):
    """Seed 001 eq. 1-3: U = U0 + K w with nonlinearity, asymmetry and automatic exclusions."""
    x, y, s, ic, oc = _read(means, rate_column, output_column, sem_column, "commanded rate")
    res = fit_rate_means(x, y, s, rate_unit=rate_unit, output_unit=output_unit, exclusion=exclusion, alpha=alpha)
    _print(res, f"rate fit of {means} (rate column {ic!r} in {rate_unit}, output column {oc!r} in {output_unit})")
    _write_json(res, json_path, {"file": str(means), "input_column": ic, "output_column": oc, "exclusion": exclusion,
                                 "alpha": alpha, "model": "U = U0 + K w"})
    _plot(res, plot_path, f"commanded rate [{rate_unit}]")


@command.command("tumble", short_help="Accelerometer tumble: U = K0 + K1 sin + K2 sin^2 + K3 sin cos.")
@_with_common
@click.option("--angle-unit", type=click.Choice(sorted(ANGLE_UNITS_TO_RAD)), default="deg", show_default=True)
@click.option("--angle-column", default=None, help="Column of the table angle (default: the first numeric column).")
@click.option("--misalignment-term/--no-misalignment-term", default=False, show_default=True,
              help="Add the IEEE 1293 cos(theta) misalignment term to seed 001's model.")
def tumble_cmd(means, output_unit, output_column, sem_column, exclusion, alpha, json_path, plot_path, angle_unit,
               angle_column, misalignment_term):
    """Seed 001 eq. 5-7: U = K0 + K1 sin + K2 sin^2 + K3 sin cos (a_i = sin(theta) g)."""
    x, y, s, ic, oc = _read(means, angle_column, output_column, sem_column, "table angle")
    res = fit_tumble_means(x, y, s, angle_unit=angle_unit, output_unit=output_unit, misalignment_term=misalignment_term,
                           exclusion=exclusion, alpha=alpha)
    _print(res, f"tumble fit of {means} (angle column {ic!r} in {angle_unit}, output column {oc!r} in {output_unit})")
    _write_json(res, json_path, {"file": str(means), "input_column": ic, "output_column": oc, "exclusion": exclusion,
                                 "alpha": alpha, "model": "U = K0 + K1 sin + K2 sin^2 + K3 sin cos"
                                 + (" + d cos" if misalignment_term else "")})
    _plot(res, plot_path, f"table angle [{angle_unit}]")



