"""Plain messages passed between stages (source -> front end -> back end -> outputs).

All time stamps are integer nanoseconds on one host clock. Poses are 4x4 homogeneous matrices
`T_a_b` that map points from frame b into frame a (p_a = T_a_b @ p_b).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass(frozen=True)
class ImuSample:
    """One IMU reading in the body (= IMU) frame: angular rate [rad/s] and specific force [m/s^2]."""

    t_ns: int
    gyro: np.ndarray  # (3,) rad/s
    accel: np.ndarray  # (3,) m/s^2


@dataclass(frozen=True)
class StereoFrame:
    """A hardware-synchronised stereo pair (8-bit grayscale). `right` may be None when the right image
    was lost; the front end then reports no stereo for this frame instead of failing."""

    t_ns: int
    left: np.ndarray
    right: np.ndarray | None
    seq: int = 0


@dataclass(frozen=True)
class NavState:
    """Estimator output for one time stamp.

    `cov_pose` is 6x6 over (rotation [rad], position [m]) in the body frame's tangent space, GTSAM's Pose3
    ordering; `cov_vel` is 3x3 in the world frame. `reset_counter` increments at every estimator reset so
    that the autopilot can discard its old reference. `quality` is 0..100 tracking health.
    """

    t_ns: int
    T_world_body: np.ndarray
    v_world: np.ndarray
    gyro_bias: np.ndarray = field(default_factory=lambda: np.zeros(3))
    accel_bias: np.ndarray = field(default_factory=lambda: np.zeros(3))
    cov_pose: np.ndarray = field(default_factory=lambda: np.eye(6) * 1e-2)
    cov_vel: np.ndarray = field(default_factory=lambda: np.eye(3) * 1e-2)
    reset_counter: int = 0
    quality: int = 100
    omega_body: np.ndarray = field(default_factory=lambda: np.zeros(3))
    tracking: bool = True
