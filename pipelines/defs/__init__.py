"""Dagster definitions by stage: ``ingest``, ``calibration``, ``noise``, ``fleet``; sensors and schedules."""
