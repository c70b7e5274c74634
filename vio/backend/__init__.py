"""Estimator back end: IMU pre-integration and the fixed-lag visual-inertial smoother (GTSAM)."""
