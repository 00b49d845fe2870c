"""Using a calibration: build it from a record or a device's records at a date (``model``), apply it to data
(``compensate``), with the record's own model convention (docs/design.md "Sensor error model")."""

from assets_lib.apply.compensate import (
    ACCEL_COLUMNS,
    GYRO_COLUMNS,
    Corrected,
    correct,
    correct_frame,
    correction_stderr,
    forward,
    sensitivities,
)
from assets_lib.apply.model import (
    Calibration,
    CalibrationError,
    Triad,
    assemble,
    calibration_from_json,
    calibration_from_record,
    load_calibration,
)

__all__ = ["ACCEL_COLUMNS", "GYRO_COLUMNS", "Calibration", "CalibrationError", "Corrected", "Triad", "assemble",
           "calibration_from_json", "calibration_from_record", "correct", "correct_frame", "correction_stderr",
           "forward", "load_calibration", "sensitivities"]
