"""imulab: audited IMU calibration pipeline (application shell: command line and calibration records)."""

from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("imulab")
except PackageNotFoundError:  # pragma: no cover - running from a source tree without install
    __version__ = "0.0.0+unknown"
