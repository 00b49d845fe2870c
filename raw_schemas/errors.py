"""The one error type raised for bad raw input: it names the file, the row/field, and what was expected."""

from __future__ import annotations


class RawDataError(ValueError):
    """Raw capture data that violates the contract.

    ``str(err)`` reads like ``imu.csv, row 1203, column 'gyro_x': expected a finite number, found 'nan'``.
    """

    def __init__(self, file: str, where: str, expected: str, found: str | None = None):
        self.file = str(file)
        self.where = where
        self.expected = expected
        self.found = found
        msg = f"{self.file}"
        if where:
            msg += f", {where}"
        msg += f": expected {expected}"
        if found is not None:
            msg += f", found {found}"
        super().__init__(msg)
