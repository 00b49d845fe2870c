"""Noise: Allan deviation estimators and kernels, their confidence intervals, IEEE 952 noise identification."""
