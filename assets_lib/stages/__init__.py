"""Pipeline stages as pure functions (no Dagster): ``spec`` (what a stage is), ``engine`` (computing a partition,
versions), ``plan`` (reprocessing), one module per stage, and the ordered list in ``registry``."""
