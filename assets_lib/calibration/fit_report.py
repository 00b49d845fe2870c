"""Reporting edge of the calibration fits: tidy COEFFICIENT TABLE rows, residual tables and PNG plots.

Values are SI in ``value``/``stderr``/``unit``; lab units only in ``value_lab``/``stderr_lab``/``unit_lab``:
ppm for scale-factor error (K - 1), nonlinearity and asymmetry; deg/h for gyro bias; mg for accelerometer
bias; arcsec for misalignment; ug/g^2 for K2 and cross-coupling; deg/h/g for gyro g-sensitivity.
g in lab units is standard gravity ([ISO80000-3], 9.80665 m/s^2): a unit, not the local gravity. Every
conversion comes from the one lab-unit table, ``raw_schemas.units.lab_unit``.
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from assets_lib.coefficient import Coefficient
from raw_schemas.units import RADPS_TO_DEGPH, RADPS_TO_DEGPS, lab_unit
from raw_schemas.units import STANDARD_GRAVITY_MPS2 as G0

COEFFICIENT_COLUMNS = [
    "device_id",
    "run_id",
    "sensor",
    "axis",
    "coefficient",
    "value",
    "stderr",
    "unit",
    "value_lab",
    "stderr_lab",
    "unit_lab",
    "observable",
    "n_plateaus",
    "n_samples",
    "method",
]
#: extra columns after the contract ones: 95 % interval (SI) with the right coverage factor, and the fit dof
EXTRA_COEFFICIENT_COLUMNS = ["ci95_low", "ci95_high", "dof", "cov_policy", "note"]

def coefficient_row(
    *,
    device_id: str,
    run_id: str,
    sensor: str,
    axis: str,
    coefficient: str,
    estimate: Coefficient,
    n_plateaus: int,
    n_samples: int,
    method: str,
    dof: int | float = np.nan,
    cov_policy: str = "",
    note: str = "",
) -> dict:
    """One COEFFICIENT TABLE row (docs/design.md) from a :class:`Coefficient`: SI, lab units, 95 % interval."""
    lab = lab_unit(sensor, coefficient)
    if estimate.unit != lab.si:
        raise ValueError(f"{sensor} {coefficient}: estimate in {estimate.unit!r}, the table holds {lab.si!r}")
    in_lab = estimate.to_lab(lab)
    lo, hi = estimate.interval()
    return {
        "device_id": device_id,
        "run_id": run_id,
        "sensor": sensor,
        "axis": axis,
        "coefficient": coefficient,
        "value": estimate.value,
        "stderr": estimate.stderr,
        "unit": estimate.unit,
        "value_lab": in_lab.value,
        "stderr_lab": in_lab.stderr,
        "unit_lab": lab.lab,
        "observable": bool(estimate.observable),
        "n_plateaus": int(n_plateaus),
        "n_samples": int(n_samples),
        "method": method,
        "ci95_low": lo,
        "ci95_high": hi,
        "dof": dof,
        "cov_policy": cov_policy,
        "note": note,
    }


def coefficient_frame(rows: list[dict]) -> pd.DataFrame:
    df = pd.DataFrame(rows, columns=COEFFICIENT_COLUMNS + EXTRA_COEFFICIENT_COLUMNS)
    return df.astype({"observable": bool})


RESIDUAL_COLUMNS = [
    "device_id",
    "run_id",
    "step_index",
    "kind",
    "sensor",
    "axis",
    "input_name",
    "input_value",
    "input_unit",
    "observed",
    "fitted",
    "residual",
    "sigma",
    "std_residual",
    "excluded",
    "reason",
    "unit",
]


def residual_frame(fit, meta: pd.DataFrame, *, sensor: str, axis: str, input_name: str, input_value, input_unit: str,
                   observed, unit: str) -> pd.DataFrame:
    """Residual table (one row per plateau of this sensor axis) from a :class:`fit_core.LinearFit`."""
    n = len(meta)
    sig = fit.sigma if fit.sigma is not None else np.full(n, np.nan)
    return pd.DataFrame(
        {
            "device_id": meta["device_id"].to_numpy() if "device_id" in meta else "",
            "run_id": meta["run_id"].to_numpy() if "run_id" in meta else "",
            "step_index": meta["step_index"].to_numpy() if "step_index" in meta else np.arange(n),
            "kind": meta["kind"].to_numpy() if "kind" in meta else "",
            "sensor": sensor,
            "axis": axis,
            "input_name": input_name,
            "input_value": np.asarray(input_value, float),
            "input_unit": input_unit,
            "observed": np.asarray(observed, float),
            "fitted": fit.fitted,
            "residual": fit.residual,
            "sigma": sig,
            "std_residual": fit.std_residual,
            "excluded": ~fit.used,
            "reason": list(fit.exclusion_reason),
            "unit": unit,
        },
        columns=RESIDUAL_COLUMNS,
    )


def _png(fig) -> bytes:
    from assets_lib.plotting import png

    return png(fig)


def plot_rate_residuals_png(residuals: pd.DataFrame, title: str = "Gyro rate fit residuals") -> bytes:
    """Residual vs reference rate (deg/s) per gyro axis, residual in deg/h; excluded plateaus as red crosses."""
    from assets_lib.plotting import figure

    df = residuals[residuals["sensor"] == "gyro"]
    axes_present = [a for a in ("x", "y", "z") if (df["axis"] == a).any()]
    fig, axs = figure(len(axes_present) or 1, 1, figsize=(7.5, 2.6 * max(len(axes_present), 1)), dpi=110,
                      margins_in=(0.95, 0.15, 0.6, 0.35))
    for ax, a in zip(axs[:, 0], axes_present):
        d = df[df["axis"] == a]
        x = d["input_value"].to_numpy() * RADPS_TO_DEGPS
        r = d["residual"].to_numpy() * RADPS_TO_DEGPH
        s = d["sigma"].to_numpy() * RADPS_TO_DEGPH
        ex = d["excluded"].to_numpy(bool)
        ax.axhline(0, color="0.6", lw=0.8)
        ax.errorbar(x[~ex], r[~ex], yerr=np.where(np.isfinite(s[~ex]), s[~ex], 0), fmt="o", ms=4, label="used")
        if ex.any():
            ax.plot(x[ex], r[ex], "x", color="red", ms=8, mew=2, label="excluded")
        ax.set_ylabel(f"gyro {a} residual [deg/h]")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8, loc="upper right")
    axs[-1, 0].set_xlabel("reference rate on the axis, earth rate included [deg/s]")
    axs[0, 0].set_title(title)
    return _png(fig)


def plot_multiposition_residuals_png(residuals: pd.DataFrame, title: str = "Multi-position fit residuals") -> bytes:
    """Residual per position (plan order) and axis: accelerometer in ug, gyro in deg/h; excluded in red."""
    from assets_lib.plotting import figure

    sensors = [s for s in ("accel", "gyro") if (residuals["sensor"] == s).any()]
    fig, axs = figure(len(sensors) or 1, 1, figsize=(8.5, 3.0 * max(len(sensors), 1)), dpi=110,
                      margins_in=(0.95, 0.15, 0.6, 0.35))
    for ax, s in zip(axs[:, 0], sensors):
        d = residuals[residuals["sensor"] == s]
        fac, unit = (1e6 / G0, "ug") if s == "accel" else (RADPS_TO_DEGPH, "deg/h")
        for k, a in enumerate(("x", "y", "z")):
            da = d[d["axis"] == a]
            if da.empty:
                continue
            pos = np.arange(len(da)) + (k - 1) * 0.18
            r = da["residual"].to_numpy() * fac
            sg = da["sigma"].to_numpy() * fac
            ex = da["excluded"].to_numpy(bool)
            ax.errorbar(pos[~ex], r[~ex], yerr=np.where(np.isfinite(sg[~ex]), sg[~ex], 0), fmt="o", ms=3.5, label=f"{a}")
            if ex.any():
                ax.plot(pos[ex], r[ex], "x", color="red", ms=8, mew=2)
        n = int(d.groupby("axis").size().max()) if len(d) else 0
        for b in range(8, n, 8):
            ax.axvline(b - 0.5, color="0.8", lw=0.8)
        ax.axhline(0, color="0.6", lw=0.8)
        ax.set_ylabel(f"{s} residual [{unit}]")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8, ncol=3, loc="upper right")
    axs[-1, 0].set_xlabel("position (plan order; groups of 8 for the 24-position plan)")
    axs[0, 0].set_title(title)
    return _png(fig)
