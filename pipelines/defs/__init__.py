"""Dagster-only definitions per concern: the checks of each stage (``calibration``, ``noise``, ``records``,
``fleet``), the ``sensors`` and the reprocessing ``schedules``; ``pipelines.definitions`` lists them."""
