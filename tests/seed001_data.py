"""Seed 001 (MEMS lab report): the published plateau means, as printed, and their reconstruction.

The PDF text extraction garbled both vectors. What is printed, verbatim:

    wmean = [-4.1923 -1.2581 0.1924 1.6609 -0.7690 0.2032 2.1583 -3.7068 -0.5240 0.2507 2.6429 -3.2152
             -0.2850 0.4382 3.1271 -2.7302 -0.0398 0.6896 3.6081 -2.2342 0.1476 0.9318 4.0061 -1.7577
             0.1903 1.1769 4.0257]
    amean = [-0.1462 -0.2014 -1.4577 1.0498 -2.2696 1.9114 -2.5792 2.2374 -2.2488 1.9055 -1.3586] 1.0090

Gyro (27 plateaus). MATLAB prints a 1x27 row vector in blocks "Columns 1 through 7", "8 through 14",
"15 through 21", "22 through 27". Sorting the 27 values ascending gives four blocks B1..B4 of 7, 7, 7, 6
values, and the printed order is exactly B1[0], then the 7th row (B1[6], B2[6], B3[6]; B4 has no 7th
value), then rows 0..5 of B2, B3, B4, B1 interleaved: the extractor read the block layout row by row with
the last row moved up. So the true vector is the ascending sort, i.e. the rates were visited in ascending
order. The rates are not printed; the report says the sweep runs from -90 to 90 deg/s and that the 90 deg/s
point was dropped ("用-90°到80°的数据进行标定"). Inverting the published line (0.1957 V + 0.0486 V/(deg/s) w)
puts the 24 outer values within 0.5 deg/s of -90, -80, -70, -60, -50, -40, -30, -20, -15, -10, -5, -1, 1,
5, 10, 15, 20, 30, ..., 90 deg/s; the three central values (0.1903, 0.1924, 0.2032 V) invert to -0.1, -0.1,
+0.2 deg/s: an ascending triple around zero, taken here as -0.1, 0, +0.1 deg/s. Because the rate set is
symmetric, any symmetric central triple (e.g. 0, 0, 0) gives the same published line (tested).
The 90 deg/s mean (4.0257 V) is only 0.0196 V above the 80 deg/s mean: the output has hit its positive rail.

Accelerometer tumble (12 positions, 30 deg steps). The 11 bracketed values plus the trailing 1.0090 are the
12 means; MATLAB printed them as two blocks ("Columns 1 through 6", "7 through 12") and the extractor
interleaved the blocks: printed = [c1 c7 c2 c8 c3 c9 ...]. De-interleaving gives positions j = 1..12:

    -0.1462 -1.4577 -2.2696 -2.5792 -2.2488 -1.3586 -0.2014 1.0498 1.9114 2.2374 1.9055 1.0090

The readings fall to -2.58 V a quarter turn after the start and rise to +2.24 V three quarters on, so with
seed 001's model U = K0 + K1 sin(theta) + K2 sin^2 + K3 sin cos and a positive scale factor the model angle is
theta_j = -30 deg (j - 1): the table's positive (counter-clockwise) step turns the sensing axis towards -g.
With that convention the least-squares fit gives K1, K2, K3 with the published signs; K0 comes out at
-0.1847 V: the two horizontal positions read -0.1462 and -0.2014 V, so the zero bias is negative in the data
themselves, and the printed "0.1846" has lost its minus sign (the K vector is an equation object in the
PDF, and the extraction drops operators from equation objects, as all of seed 000's equations show). Any
other angle convention or output sign flips at least as many printed signs (the sin^2 term is invariant, so
K0 and K2 cannot both be positive with these means).
"""

from __future__ import annotations

import numpy as np

WMEAN_PRINTED = np.array(
    "-4.1923 -1.2581 0.1924 1.6609 -0.7690 0.2032 2.1583 -3.7068 -0.5240 0.2507 2.6429 -3.2152 -0.2850 0.4382 "
    "3.1271 -2.7302 -0.0398 0.6896 3.6081 -2.2342 0.1476 0.9318 4.0061 -1.7577 0.1903 1.1769 4.0257".split(),
    float,
)
AMEAN_PRINTED = np.array(
    "-0.1462 -0.2014 -1.4577 1.0498 -2.2696 1.9114 -2.5792 2.2374 -2.2488 1.9055 -1.3586 1.0090".split(), float
)
#: published results (seed 001): gyro K = [U0, K] = [0.1957 V, 0.0486 V/(deg/s)]; accelerometer K0..K3
GYRO_PUBLISHED = (0.1957, 0.0486)
TUMBLE_PUBLISHED = (0.1846, 2.4121, 0.0112, 0.0211)
PRINTED_HALF_UNIT = 0.5e-4  # all values printed to 4 decimals

_OUTER = (1, 5, 10, 15, 20, 30, 40, 50, 60, 70, 80, 90)


def gyro_table(central=(-0.1, 0.0, 0.1)) -> tuple[np.ndarray, np.ndarray]:
    """(rate_dps, mean_V) in the visiting (ascending) order, see the module docstring."""
    means = np.sort(WMEAN_PRINTED)
    rates = np.array([-r for r in _OUTER[::-1]] + list(central) + list(_OUTER), float)
    return rates, means


def gyro_table_from_printed_layout() -> np.ndarray:
    """Undo the extraction order explicitly (blocks of 7, 7, 7, 6; 7th row moved up) instead of sorting."""
    p = list(WMEAN_PRINTED)
    b1, b2, b3, b4 = [p[0]], [], [], []
    last_row = p[1:4]  # B1[6], B2[6], B3[6]
    rest = p[4:]  # rows 0..5 of B2, B3, B4 then row 1.. of B1, interleaved: [B2 B3 B4 B1] per row
    for r in range(6):
        quad = rest[4 * r: 4 * r + 4]
        b2.append(quad[0])
        b3.append(quad[1])
        b4.append(quad[2])
        if r < 5:
            b1.append(quad[3])
    b1.append(last_row[0])
    b2.append(last_row[1])
    b3.append(last_row[2])
    return np.array(b1 + b2 + b3 + b4)


def tumble_table() -> tuple[np.ndarray, np.ndarray]:
    """(theta_deg in seed 001's model convention, mean_V) for positions j = 1..12."""
    u = np.r_[AMEAN_PRINTED[0::2], AMEAN_PRINTED[1::2]]
    theta = -30.0 * np.arange(12)
    return theta, u
