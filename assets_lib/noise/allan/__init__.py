"""Allan-family deviations ([ALLAN1966], [NIST1065]) of rate or angle records: exact, fast, bounded memory.

Layers, bottom up: :mod:`.kernels` (block sums of squared second differences, numpy or numba, identical bits),
:mod:`.phase` (float64 phase of a record), :mod:`.estimators` (one channel: tau grids, the six estimators,
EDF and intervals), :mod:`.streaming` (OADEV from parquet, memory independent of N) and :mod:`.channels`
(several channels in one call). This module re-exports the public API. The block-partition constants are
read from their own module at call time: set them there (``allan.streaming.SMALL_SPAN``), not here.
"""

from assets_lib.noise.allan.channels import allan_deviations, allan_table
from assets_lib.noise.allan.estimators import (
    DATA_TYPES,
    ID_MIN_POINTS,
    ID_POINTS,
    KINDS,
    AllanResult,
    adev,
    allan_deviation,
    averaging_factors,
    hdev,
    log_spaced_factors,
    mdev,
    n_terms_for,
    oadev,
    ohdev,
    tdev,
)
from assets_lib.noise.allan.kernels import HAVE_NUMBA, KERNEL_BLOCK, M_CHAIN, SUM_BLOCK
from assets_lib.noise.allan.phase import PHASE_BLOCK, build_phase
from assets_lib.noise.allan.streaming import SMALL_SPAN, allan_parquet, allan_stream_array, scaled_result
from assets_lib.noise.intervals import ONE_SIGMA_CI

__all__ = [
    "AllanResult", "DATA_TYPES", "HAVE_NUMBA", "ID_MIN_POINTS", "ID_POINTS", "KERNEL_BLOCK", "KINDS", "M_CHAIN",
    "ONE_SIGMA_CI", "PHASE_BLOCK", "SMALL_SPAN", "SUM_BLOCK", "adev", "allan_deviation", "allan_deviations",
    "allan_parquet", "allan_stream_array", "allan_table", "averaging_factors", "build_phase", "hdev",
    "log_spaced_factors", "mdev", "n_terms_for", "oadev", "ohdev", "scaled_result", "tdev",
]
