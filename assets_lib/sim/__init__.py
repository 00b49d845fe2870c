"""Simulator of a lab IMU test: earth model, turntable kinematics, plan library, Allan noise, device effects."""
