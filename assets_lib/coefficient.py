"""The one typed estimate every fit and table uses: value, standard error, unit, observability."""

from __future__ import annotations

import math
from dataclasses import dataclass

#: two-sided 95 % normal quantile
Z95 = 1.959963984540054


@dataclass(frozen=True)
class Coefficient:
    """An estimated coefficient in SI: ``value`` +/- ``stderr`` (one standard error) in ``unit``.

    ``observable`` is False when the data cannot determine it (then value and stderr are NaN)."""

    value: float
    stderr: float
    unit: str
    observable: bool = True

    def __post_init__(self):
        if not self.observable:
            object.__setattr__(self, "value", math.nan)
            object.__setattr__(self, "stderr", math.nan)

    @classmethod
    def unobservable(cls, unit: str) -> "Coefficient":
        return cls(math.nan, math.nan, unit, observable=False)

    def interval(self, z: float = Z95) -> tuple[float, float]:
        """Symmetric normal interval ``value -/+ z * stderr`` (95 % by default)."""
        return self.value - z * self.stderr, self.value + z * self.stderr

    def scaled(self, factor: float, unit: str) -> "Coefficient":
        """The same estimate in another unit (``value * factor``)."""
        return Coefficient(self.value * factor, abs(self.stderr * factor), unit, self.observable)
