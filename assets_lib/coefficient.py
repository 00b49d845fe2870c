"""The one typed estimate every fit and table uses: value, standard error, unit, observability, interval."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from raw_schemas.units import LabUnit

#: two-sided 95 % normal quantile
Z95 = 1.959963984540054


@dataclass(frozen=True)
class Coefficient:
    """An estimated coefficient in SI: ``value`` +/- ``stderr`` (one standard error) in ``unit``.

    ``observable`` is False when the data cannot determine it (then value and stderr are NaN). ``ci_low`` /
    ``ci_high`` hold the reported interval at ``ci_level`` when it is not the normal ``value -/+ z stderr``
    (Student-t coverage factor of a fit with few degrees of freedom, chi-square interval of a noise term, a
    one-sided bound); NaN otherwise.
    """

    value: float
    stderr: float
    unit: str
    observable: bool = True
    ci_low: float = math.nan
    ci_high: float = math.nan
    ci_level: float = 0.95

    def __post_init__(self):
        if not self.observable:
            object.__setattr__(self, "value", math.nan)
            object.__setattr__(self, "stderr", math.nan)

    @classmethod
    def unobservable(cls, unit: str) -> "Coefficient":
        return cls(math.nan, math.nan, unit, observable=False)

    @classmethod
    def with_coverage(cls, value: float, stderr: float, unit: str, observable: bool = True,
                      k: float = Z95) -> "Coefficient":
        """The estimate with its 95 % interval ``value -/+ k stderr`` (``k``: the fit's coverage factor)."""
        value = float(value) if observable else math.nan
        stderr = float(stderr) if observable else math.nan
        return cls(value, stderr, unit, bool(observable), value - k * stderr, value + k * stderr, 0.95)

    def interval(self, z: float = Z95) -> tuple[float, float]:
        """The stored interval when there is one, else the symmetric normal ``value -/+ z * stderr``."""
        if not (math.isnan(self.ci_low) and math.isnan(self.ci_high)):
            return self.ci_low, self.ci_high
        return self.value - z * self.stderr, self.value + z * self.stderr

    def scaled(self, factor: float, unit: str) -> "Coefficient":
        """The same estimate in another unit (``value * factor``; intervals follow, reordered if factor < 0)."""
        lo, hi = self.ci_low * factor, self.ci_high * factor
        if factor < 0:
            lo, hi = hi, lo
        return Coefficient(self.value * factor, abs(self.stderr * factor), unit, self.observable, lo, hi, self.ci_level)

    def to_lab(self, lab: LabUnit) -> "Coefficient":
        """The estimate in lab units (``raw_schemas.units.lab_unit``): value and interval converted, stderr scaled."""
        return Coefficient(lab.to_lab(self.value), abs(lab.factor) * self.stderr, lab.lab, self.observable,
                           lab.to_lab(self.ci_low), lab.to_lab(self.ci_high), self.ci_level)


def ratio_with_stderr(num: float, den: float, var_num: float, var_den: float, cov_nd: float) -> tuple[float, float]:
    """num/den and its standard error by the first-order delta method ([GUM] 5.1.2)."""
    r = num / den
    var = (var_num + r**2 * var_den - 2 * r * cov_nd) / den**2
    return float(r), float(np.sqrt(max(var, 0.0)))
