"""Noise: Allan deviations (``allan``), their intervals, [IEEE952] noise identification, the pooled short-window model."""
