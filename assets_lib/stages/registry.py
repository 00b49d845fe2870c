"""The stages of imulab, in dependency order: the one list the Dagster code location, ``imulab verify`` and the
reprocessing planner walk. A new stage is a module in this package plus one line here."""

from assets_lib.stages import calibration, fleet, ingest, noise, records, repeatability, sim_to_real, tablefree
from assets_lib.stages.engine import StageGraph

STAGES = StageGraph([
    ingest.ingested_run,
    noise.allan_deviation,  # before the fits: they read the device's static runs' noise (siblings)
    calibration.plateaus,
    calibration.gyro_rate_fit,
    calibration.accel_multiposition_fit,
    tablefree.tablefree_fit,
    repeatability.repeatability,
    records.calibration_record,
    records.certificate,
    fleet.fleet_drift_stage,
    sim_to_real.sim_to_real,
])
