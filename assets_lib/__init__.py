"""The science of imulab, pure numpy/scipy/pandas (no Dagster), in packages by concern:

- ``sim``: the simulator (earth model, kinematics, plan library, Allan noise, device effects);
- ``calibration``: outlier rejection, plateau segmentation, rate and multi-position fits, repeatability, grades;
- ``noise``: Allan deviation estimators, their intervals, IEEE 952 noise identification;
- ``fleet``: coefficient drift across a fleet.

Imports run one way: ``raw_schemas`` -> ``assets_lib`` -> ``pipelines`` -> ``imulab``.
"""
