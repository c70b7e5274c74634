"""Estimator initialisation: static start (gravity + gyro bias from a still IMU window) and start in
motion (visual-inertial alignment with stereo-metric relative poses)."""

from vio.init.static_init import InitialState, is_still, static_initialize

__all__ = ["InitialState", "is_still", "static_initialize"]
