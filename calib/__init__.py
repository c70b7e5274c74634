"""Calibration tools behind `vio calib`: importers (kalibr, EuRoC, depthai, OpenCV), a human-readable
summary, checks on recorded data, IMU noise from Allan deviation and the camera-IMU time offset.

Everything here produces or consumes `vio.calibration.StereoCalibration`; the project's calibration file
is the one written by `vio.calibration.save_calibration`.
"""
