"""Three-axis bookkeeping shared by the triad fits: axis names and 3x3 matrices from per-axis coefficients."""

from __future__ import annotations

import numpy as np

AXES = ("x", "y", "z")


def off_diagonal_matrix(axes, attr: str, names=AXES) -> np.ndarray:
    """3x3 matrix M[i, j] = ``getattr(axes[i], attr)[names[j]].value`` (a :class:`Coefficient` per pair), zero diagonal."""
    m = np.zeros((3, 3))
    for i, ax in enumerate(axes):
        for j, a in enumerate(names):
            if j != i:
                m[i, j] = getattr(ax, attr)[a].value
    return m
