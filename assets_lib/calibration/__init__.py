"""Calibration science: outlier rejection, plateau segmentation, gyro rate and multi-position fits, repeatability."""
