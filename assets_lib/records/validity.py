"""Whether a record is a valid calibration: coefficients plausible for the device grade and residuals consistent
with the noise model; otherwise the record is marked ``invalid`` with one line per reason.

Criteria (the same figures the pipeline's quality gates use, defined here once):
- every observable bias, scale factor and misalignment lies inside the grade envelope
  (``assets_lib.calibration.grades.implausible``);
- the reduced chi-square of a fit's standardized plateau residuals, mean(z^2) over the kept plateaus (IEEE Std
  1293-1998 / IEEE Std 952-1997 least-squares fit: E[chi^2 / dof] = 1 when the standard errors describe the
  scatter), lies inside ``CHI2_BAND``;
- the fitted IEEE 952 noise model lies inside the Allan-deviation confidence interval at a share of at least
  ``MODEL_INSIDE_CI_MIN`` of the fitted taus, for every channel.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass

import numpy as np

from assets_lib.calibration.fit_core import CHI2_BAND
from assets_lib.calibration.grades import implausible

#: the fitted noise model must lie inside the per-tau interval at this share of the fitted taus
MODEL_INSIDE_CI_MIN = 0.8

VALID, INVALID = "valid", "invalid"


@dataclass(frozen=True)
class RecordStatus:
    status: str  # "valid" | "invalid"
    reasons: tuple[str, ...]


def reduced_chi_square(std_residual: np.ndarray, excluded: np.ndarray | None = None) -> float | None:
    """mean(z^2) of the standardized residuals of the kept plateaus; None when there is none."""
    z = np.asarray(std_residual, dtype=float)
    if excluded is not None:
        z = z[~np.asarray(excluded, dtype=bool)]
    z = z[np.isfinite(z)]
    return float(np.mean(z**2)) if z.size else None


def record_status(grade: str, coefficients: Iterable[Mapping], chi2_by_fit: Mapping[str, float | None],
                  model_inside_ci: Mapping[str, float]) -> RecordStatus:
    """Status of a record from its coefficient rows (``sensor, axis, coefficient, value, observable, source``),
    the reduced chi-square of each fit and the Allan model's share inside its intervals per channel."""
    reasons = []
    for c in coefficients:
        if not c.get("observable") or c.get("value") is None:
            continue
        why = implausible(grade, c["sensor"], c["coefficient"], float(c["value"]))
        if why:
            reasons.append(f"{c.get('source', '')} {c['sensor']}_{c['axis']} {c['coefficient']}: {why}".strip())
    lo, hi = CHI2_BAND
    for fit, chi2 in sorted(chi2_by_fit.items()):
        if chi2 is not None and not lo <= chi2 <= hi:
            reasons.append(f"{fit}: reduced chi-square of the plateau residuals {chi2:.3g} outside [{lo:g}, {hi:g}]: "
                           "the residuals contradict the noise model")
    for ch, share in sorted(model_inside_ci.items()):
        if share is None or not share >= MODEL_INSIDE_CI_MIN:
            shown = "n/a" if share is None or not np.isfinite(share) else f"{share:.0%}"
            reasons.append(f"allan_deviation {ch}: noise model inside the Allan-deviation interval at {shown} of the "
                           f"fitted taus (< {MODEL_INSIDE_CI_MIN:.0%})")
    return RecordStatus(INVALID if reasons else VALID, tuple(reasons))
