"""``imulab allan``: Allan deviation and IEEE 952 noise terms of any static record (CSV or parquet).

\b
  imulab allan imu.parquet                                   # every numeric column except time_s
  imulab allan log.csv --columns gx,gy --units deg/s --rate-hz 200 --taus dense
  imulab allan imu.parquet --plot allan.png --json allan.json
Large parquet files (more rows than --stream-rows) are streamed: memory stays bounded at any length.
The IMU stream of a contract run (a ``manifest.json`` beside it) is read in the manifest's units: counts times
the LSB, converted to SI, at the manifest's sample rate. Integer columns of any other file are refused as raw
counts unless --units says what they are.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import click
import numpy as np
import pandas as pd

from assets_lib.noise import allan as al
from assets_lib.noise import identification as ni
from raw_schemas.errors import RawDataError
from raw_schemas.manifest import COUNT_UNIT, load_manifest
from raw_schemas.units import ACCEL_UNITS_TO_MPS2, GYRO_UNITS_TO_RADPS, family_of, si_factor

TIME_COLUMNS = ("time_s", "time", "t", "timestamp", "t_s")
STREAM_ROWS_DEFAULT = 20_000_000


def _unit_info(unit: str | None, column: str) -> tuple[float, str, str]:
    """(factor to SI, SI unit, sensor) for a declared unit or, without one, from the column name."""
    if unit:
        if unit in GYRO_UNITS_TO_RADPS:
            return GYRO_UNITS_TO_RADPS[unit], "rad/s", "gyro"
        if unit in ACCEL_UNITS_TO_MPS2:
            return ACCEL_UNITS_TO_MPS2[unit], "m/s^2", "accel"
        known = sorted(GYRO_UNITS_TO_RADPS) + sorted(ACCEL_UNITS_TO_MPS2)
        raise click.BadParameter(f"unknown unit {unit!r}; known: {', '.join(known)}", param_hint="--units")
    sensor = ni.sensor_of(column)
    return 1.0, {"gyro": "rad/s", "accel": "m/s^2"}.get(sensor, ""), sensor


def _contract_channels(file: Path) -> tuple[dict[str, tuple[float, str, str]], str, float] | None:
    """For the IMU stream of a contract run (``manifest.json`` beside ``file``): per IMU channel of the manifest,
    (factor to SI = LSB x unit factor, SI unit, sensor), a one-line description, and the manifest's sample rate."""
    mpath = file.parent / "manifest.json"
    if not mpath.is_file():
        return None
    try:
        manifest = load_manifest(mpath)
    except RawDataError as e:
        raise click.ClickException(f"{file} lies in a run folder whose manifest is not valid, so its units are "
                                   f"unknown: {e}") from None
    out, said = {}, []
    for ch, spec in manifest.channels.items():
        try:
            fam = family_of(ch)
        except KeyError:
            continue
        if fam not in ("gyro", "accel"):
            continue
        out[ch] = (spec.physical_per_raw() * si_factor(fam, spec.physical_unit),
                   "rad/s" if fam == "gyro" else "m/s^2", fam)
        said.append(f"{ch} {'counts x ' + format(spec.lsb, 'g') + ' ' if spec.unit == COUNT_UNIT else ''}"
                    f"{spec.physical_unit}")
    return out, f"contract run {manifest.device.id}/{manifest.run_id} ({mpath}): " + ", ".join(said), \
        manifest.sample_rate_hz


def _parse_taus(value: str):
    v = value.strip().lower()
    if v in ("octave", "decade", "dense", "all"):
        return v
    try:
        n = int(v)
    except ValueError:
        raise click.BadParameter("octave, decade, dense, all or a number of log-spaced taus", param_hint="--taus")
    if n < 2:
        raise click.BadParameter("need at least 2 taus", param_hint="--taus")
    return n


def _rate_from_time(t: np.ndarray) -> float:
    dt = np.diff(np.asarray(t, dtype=float))
    dt = dt[np.isfinite(dt)]
    if len(dt) == 0 or not np.median(dt) > 0:
        raise click.ClickException("cannot infer the sample rate from the time column; pass --rate-hz")
    med = float(np.median(dt))
    if np.any(np.abs(dt - med) > 0.5 * med):
        click.echo("warning: irregular time stamps (gaps or jitter > 50%); the deviation assumes uniform sampling",
                   err=True)
    return 1.0 / med


def _is_integer(dtype) -> bool:
    """True for an integer column (pandas dtype or arrow type)."""
    if hasattr(dtype, "to_pandas_dtype"):
        dtype = dtype.to_pandas_dtype()
    return pd.api.types.is_integer_dtype(dtype)


def _fmt(v: float) -> str:
    return "n/a" if v is None or not np.isfinite(v) else f"{v:.4g}"


def _print_allan(r: al.AllanResult, unit: str):
    click.echo(f"\n{r.channel}: {r.kind.upper()} [{unit or 'SI'}], {r.n_samples} samples at {r.rate_hz:g} Hz, "
               f"{100 * r.ci_level:.1f}% chi-square interval (Greenhall EDF)")
    click.echo(f"  {'tau_s':>10} {'adev':>11} {'ci_lo':>11} {'ci_hi':>11} {'edf':>9} {'n_terms':>10} {'alpha':>5}")
    for j in range(len(r.m)):
        click.echo(f"  {r.tau_s[j]:10.4g} {r.adev[j]:11.4e} {r.ci_lo[j]:11.4e} {r.ci_hi[j]:11.4e} {r.edf[j]:9.4g} "
                   f"{int(r.n_terms[j]):10d} {int(r.alpha[j]):5d}")


def _print_fit(fit: ni.NoiseFit):
    click.echo(f"  noise terms (IEEE 952 Annex C; fit = non-negative GLS, slope = classic line reads), "
               f"{100 * fit.parameters[0].ci_level:.0f}% intervals:")
    for p in list(fit.parameters) + list(fit.slope_parameters):
        if p.is_upper_bound:
            txt = f"< {_fmt(p.ci_hi_lab)}"
            si = f"< {_fmt(p.ci_hi)}"
        else:
            txt = f"{_fmt(p.value_lab)} [{_fmt(p.ci_lo_lab)}, {_fmt(p.ci_hi_lab)}]"
            si = f"{_fmt(p.value)} [{_fmt(p.ci_lo)}, {_fmt(p.ci_hi)}]"
        click.echo(f"    {p.name:<14} {p.method:<5} {txt:<36} {p.unit_lab:<16} ({si} {p.unit})")


def _jsonable(v):
    if isinstance(v, np.ndarray):
        return [_jsonable(x) for x in v.tolist()]
    if isinstance(v, (float, np.floating)):
        return None if not math.isfinite(float(v)) else float(v)
    if isinstance(v, (np.integer,)):
        return int(v)
    if isinstance(v, (list, tuple)):
        return [_jsonable(x) for x in v]
    if isinstance(v, dict):
        return {k: _jsonable(x) for k, x in v.items()}
    return v


@click.command("allan")
@click.argument("file", type=click.Path(exists=True, dir_okay=False, path_type=Path))
@click.option("--columns", help="Comma list of columns (default: every numeric column except the time column).")
@click.option("--rate-hz", type=float, help="Sample rate; default: inferred from a time_s column.")
@click.option("--units", help="Unit of the columns (deg/s, rad/s, deg/h, g, mg, m/s^2 ...); one for all, or a "
              "comma list matching --columns. Default: SI, sensor from the column name.")
@click.option("--taus", default="octave", show_default=True, help="octave | decade | dense | all | N log-spaced.")
@click.option("--data-type", type=click.Choice(["rate", "angle"]), default="rate", show_default=True,
              help="rate samples (gyro rad/s, accel m/s^2) or integrated angle / velocity samples.")
@click.option("--ci", "ci_level", type=float, default=al.ONE_SIGMA_CI, show_default=True,
              help="Two-sided level of the per-tau chi-square interval.")
@click.option("--param-ci", type=float, default=0.95, show_default=True, help="Level of the noise-term intervals.")
@click.option("--fit/--no-fit", default=True, show_default=True, help="Fit the IEEE 952 noise terms.")
@click.option("--markov", is_flag=True, help="Add a first-order Markov term to the fit.")
@click.option("--sinusoid", is_flag=True, help="Add a sinusoidal term to the fit.")
@click.option("--tau-min", default="auto", show_default=True,
              help="Shortest tau [s] the noise fit uses, or 'auto' (the first tau from which the model matches the curve).")
@click.option("--tau-max", type=float, default=None, help="Longest tau [s] the noise fit uses (default: m <= N/4).")
@click.option("--plot", "plot_path", type=click.Path(dir_okay=False, path_type=Path), help="Write a log-log PNG.")
@click.option("--json", "json_path", type=click.Path(dir_okay=False, path_type=Path), help="Write everything as JSON.")
@click.option("--stream-rows", type=int, default=STREAM_ROWS_DEFAULT, show_default=True,
              help="Stream parquet files with more rows than this (bounded memory).")
@click.option("--backend", type=click.Choice(["auto", "numba", "numpy"]), default="auto", show_default=True)
def command(file: Path, columns, rate_hz, units, taus, data_type, ci_level, param_ci, fit, markov, sinusoid,
            tau_min, tau_max, plot_path, json_path, stream_rows, backend):
    """Allan deviation (overlapping, exact) with intervals, and the fitted noise terms, of a static record."""
    taus_v = _parse_taus(taus)
    suffix = file.suffix.lower()
    is_parquet = suffix in (".parquet", ".pq")
    if is_parquet:
        import pyarrow.parquet as pq

        pf = pq.ParquetFile(file)
        schema = pf.schema_arrow
        all_cols = [f.name for f in schema]
        numeric = [f.name for f in schema if pd.api.types.is_numeric_dtype(f.type.to_pandas_dtype())]
        n_rows = pf.metadata.num_rows
    else:
        try:
            df = pd.read_csv(file, sep=None, engine="python", comment="#") if suffix != ".csv" else pd.read_csv(
                file, comment="#")
        except Exception as e:  # noqa: BLE001 - report any parse problem to the user
            raise click.ClickException(f"cannot read {file}: {e}") from None
        df.columns = [str(c).strip() for c in df.columns]
        all_cols = list(df.columns)
        numeric = [c for c in df.columns if pd.api.types.is_numeric_dtype(df[c])]
        n_rows = len(df)
    time_col = next((c for c in TIME_COLUMNS if c in all_cols), None)
    contract = _contract_channels(file)
    if contract is not None:
        if units:
            raise click.BadParameter(f"{file} is the stream of a contract run: its units come from the manifest "
                                     "beside it (drop --units)", param_hint="--units")
        numeric = [c for c in numeric if c in contract[0]]
        rate_hz = rate_hz or contract[2]
        click.echo(contract[1], err=True)
    if columns:
        cols = [c.strip() for c in columns.split(",") if c.strip()]
        missing = [c for c in cols if c not in all_cols]
        if missing:
            raise click.ClickException(f"{file}: no column(s) {missing}; columns are {all_cols}")
    else:
        cols = [c for c in numeric if c != time_col and c not in ("counter", "step_index")]
    if not cols:
        raise click.ClickException(f"{file}: no numeric data column; columns are {all_cols}")
    unit_list = [u.strip() for u in units.split(",")] if units else [None]
    if len(unit_list) not in (1, len(cols)):
        raise click.BadParameter("give one unit, or one per column", param_hint="--units")
    if contract is not None:
        unknown = [c for c in cols if c not in contract[0]]
        if unknown:
            raise click.ClickException(f"{file}: column(s) {unknown} are not IMU channels of the run's manifest")
        info = {c: contract[0][c] for c in cols}
    else:
        counts = [c for c in cols if c in numeric and _is_integer(schema.field(c).type if is_parquet else df[c].dtype)]
        if counts and not units:
            raise click.ClickException(
                f"{file}: column(s) {counts} hold integers, i.e. raw counts, and there is no manifest.json beside "
                "the file to give their LSB and unit. Run imulab allan on the stream inside its contract run "
                "folder, or pass --units if the values are already in a physical unit.")
        info = {c: _unit_info(unit_list[0] if len(unit_list) == 1 else unit_list[k], c) for k, c in enumerate(cols)}

    if rate_hz is None:
        if time_col is None:
            raise click.ClickException("no time column (time_s): pass --rate-hz")
        if is_parquet:
            batch = next(pf.iter_batches(batch_size=100_000, columns=[time_col]))
            t = batch.column(0).to_numpy(zero_copy_only=False)
        else:
            t = df[time_col].to_numpy(float)
        rate_hz = _rate_from_time(t)
    if not rate_hz > 0:
        raise click.BadParameter("must be positive", param_hint="--rate-hz")

    stream = is_parquet and n_rows > stream_rows
    results: dict[str, al.AllanResult] = {}
    try:
        if stream:
            click.echo(f"streaming {file} ({n_rows} rows > --stream-rows {stream_rows})", err=True)
            results = al.allan_parquet(
                file, rate_hz, cols, taus_v, data_type=data_type, ci_level=ci_level, backend=backend,
                scale={c: info[c][0] for c in cols}, units={c: info[c][1] for c in cols},
            )
        else:
            if is_parquet:
                df = pf.read(columns=cols).to_pandas()
            for c in cols:
                y = pd.to_numeric(df[c], errors="coerce").to_numpy()
                r = al.allan_deviation(y, rate_hz, taus_v, data_type=data_type, ci_level=ci_level, backend=backend,
                                       channel=c, unit=info[c][1])
                results[c] = al.scaled_result(r, info[c][0]) if info[c][0] != 1.0 else r
    except ValueError as e:
        raise click.ClickException(str(e)) from None

    fits: dict[str, ni.NoiseFit] = {}
    for c, r in results.items():
        _print_allan(r, info[c][1])
        if fit:
            try:
                tmin = tau_min if tau_min == "auto" else float(tau_min)
                fits[c] = ni.fit_noise(r, markov=markov, sinusoid=sinusoid, ci_level=param_ci, sensor=info[c][2],
                                       tau_min_s=tmin, tau_max_s=tau_max)
            except ValueError as e:
                click.echo(f"  noise fit skipped: {e}")
                continue
            _print_fit(fits[c])
            click.echo(f"  fit tau range {fits[c].tau_range_s[0]:.4g}-{fits[c].tau_range_s[1]:.4g} s")
            for w in fits[c].warnings:
                click.echo(f"WARNING {w}", err=True)

    if plot_path is not None:
        ni.plot_allan(results, fits or None, path=plot_path, title=file.name)
        click.echo(f"\nplot written to {plot_path}")
    if json_path is not None:
        doc = {
            "file": str(file),
            "rate_hz": rate_hz,
            "streamed": stream,
            "data_type": data_type,
            "channels": {},
        }
        for c, r in results.items():
            entry = {
                "unit": info[c][1],
                "sensor": info[c][2],
                "allan": {k: _jsonable(v) for k, v in r.to_frame().drop(columns=["channel", "kind"]).to_dict("list").items()},
                "kind": r.kind,
                "n_samples": r.n_samples,
                "ci_level": r.ci_level,
                "backend": r.backend,
            }
            if c in fits:
                f = fits[c]
                entry["noise"] = [
                    _jsonable(p.as_dict())
                    for p in list(f.parameters) + list(f.slope_parameters)
                ]
                entry["fit"] = {"terms": list(f.terms), "theta": _jsonable(f.theta),
                                "theta_cov": _jsonable(f.theta_cov), "chi2": _jsonable(f.chi2), "dof": f.dof,
                                "tau_range_s": _jsonable(f.tau_range_s), "discrepancy": _jsonable(f.discrepancy),
                                "outside_tau_ranges": _jsonable(f.outside_tau_ranges), "warnings": list(f.warnings)}
            doc["channels"][c] = entry
        json_path.write_text(json.dumps(doc, indent=1))
        click.echo(f"json written to {json_path}")
