"""Arrow schemas of the raw streams a capture job writes and of the canonical SI tables ingestion produces.

Raw IMU stream (``imu.csv`` or ``imu.parquet``): ``time_s``, the six channels of ``manifest.IMU_CHANNELS`` in the
units the manifest declares, optional ``temperature`` and optional integer ``counter``. No other column.
Raw turntable log (``table.csv`` or ``table.parquet``): ``time_s`` (table clock), ``angle_deg``, ``rate_dps``,
``step_index`` (-1 between steps); optional ``state``.
"""

from __future__ import annotations

import pyarrow as pa

RAW_IMU_REQUIRED = ("time_s", "gyro_x", "gyro_y", "gyro_z", "accel_x", "accel_y", "accel_z")
RAW_IMU_OPTIONAL = ("temperature", "counter")
RAW_TABLE_REQUIRED = ("time_s", "angle_deg", "rate_dps", "step_index")
RAW_TABLE_OPTIONAL = ("state",)

#: Numeric kind expected for each raw column ("float": any int/float; "int": integer-valued; "str").
RAW_COLUMN_KIND = {
    **{c: "float" for c in RAW_IMU_REQUIRED},
    "temperature": "float",
    "counter": "int",
    "angle_deg": "float",
    "rate_dps": "float",
    "step_index": "int",
    "state": "str",
}

CANONICAL_IMU_SCHEMA = pa.schema(
    [
        pa.field("time_s", pa.float64(), nullable=False, metadata={"unit": "s"}),
        pa.field("gyro_x_radps", pa.float64(), nullable=False, metadata={"unit": "rad/s"}),
        pa.field("gyro_y_radps", pa.float64(), nullable=False, metadata={"unit": "rad/s"}),
        pa.field("gyro_z_radps", pa.float64(), nullable=False, metadata={"unit": "rad/s"}),
        pa.field("accel_x_mps2", pa.float64(), nullable=False, metadata={"unit": "m/s^2"}),
        pa.field("accel_y_mps2", pa.float64(), nullable=False, metadata={"unit": "m/s^2"}),
        pa.field("accel_z_mps2", pa.float64(), nullable=False, metadata={"unit": "m/s^2"}),
        pa.field("temperature_degc", pa.float64(), nullable=True, metadata={"unit": "degC"}),
        pa.field("counter", pa.int64(), nullable=True, metadata={"unit": "1"}),
    ]
)
GYRO_COLUMNS = ("gyro_x_radps", "gyro_y_radps", "gyro_z_radps")
ACCEL_COLUMNS = ("accel_x_mps2", "accel_y_mps2", "accel_z_mps2")

CANONICAL_TABLE_SCHEMA = pa.schema(
    [
        pa.field("time_s", pa.float64(), nullable=False, metadata={"unit": "s", "clock": "table"}),
        pa.field("angle_rad", pa.float64(), nullable=False, metadata={"unit": "rad"}),
        pa.field("rate_radps", pa.float64(), nullable=False, metadata={"unit": "rad/s"}),
        pa.field("step_index", pa.int64(), nullable=False, metadata={"unit": "1"}),
    ]
)
