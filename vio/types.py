"""Plain messages passed between stages (source -> front end -> back end -> outputs).

All time stamps are integer nanoseconds on one host clock. Poses are 4x4 homogeneous matrices
`T_a_b` that map points from frame b into frame a (p_a = T_a_b @ p_b).
"""

from __future__ import annotations

import math
from collections.abc import Callable
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
    was lost; the front end then reports no stereo for this frame instead of failing.

    A recording may leave `right` None and give `load_right` instead, which decodes it: the front end
    uses the right image of about one frame in four, and decoding is a replay's largest single cost."""

    t_ns: int
    left: np.ndarray
    right: np.ndarray | None
    seq: int = 0
    load_right: Callable[[], np.ndarray | None] | None = field(default=None, repr=False, compare=False)

    def right_image(self) -> np.ndarray | None:
        """The right image, decoded now if it was deferred (each call decodes again)."""
        if self.right is not None or self.load_right is None:
            return self.right
        return self.load_right()


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
    loop_jumps: int = 0  # of reset_counter's increments, those a loop correction made ([loop] output = jump)


def covariance_quality(cov_pose: np.ndarray, quality_sigma_m: float) -> float:
    """0..1: 1 up to a position sigma of quality_sigma_m, halving per doubling beyond it, so that `quality`, which
    the autopilots gate on, never says more than the covariance sent beside it."""
    var = float(cov_pose[3, 3] + cov_pose[4, 4] + cov_pose[5, 5])
    if not math.isfinite(var) or min(cov_pose[3, 3], cov_pose[4, 4], cov_pose[5, 5]) < 0:
        return 0.0  # NaN compares false both ways (min/max made it 1), and a negative variance is no sigma
    sigma = math.sqrt(var)  # >= the largest axis
    return min(1.0, quality_sigma_m / max(sigma, 1e-9))


@dataclass(frozen=True)
class FeatureFrame:
    """Front-end output for one stereo frame: the contract between front end and back end.

    Row k describes the track `ids[k]` (ids are unique for the life of a track and never reused).
    Coordinates are *undistorted pixels* of an ideal pinhole camera with the same K as the real one
    (cam0 K for `uv0`, cam1 K for `uv1`), so the back end can use plain pinhole projection factors with
    `Cal3_S2(K)` and `T_body_cam` as body_P_sensor. `uv1` and `depth_m` are NaN where no stereo match
    passed the checks. `depth_m` is the triangulated depth along cam0's optical axis.
    """

    t_ns: int  # camera time stamp (camera clock; the estimator applies the calibration's time offset)
    ids: np.ndarray  # (N,) int64 track ids
    uv0: np.ndarray  # (N, 2) float undistorted pixels in cam0
    uv1: np.ndarray  # (N, 2) float undistorted pixels in cam1, NaN without stereo match
    depth_m: np.ndarray  # (N,) float depth in cam0, NaN without stereo match
    track_len: np.ndarray  # (N,) int number of frames this track has been seen (1 = new)
    parallax_px: float = 0.0  # median parallax of tracks shared with the last keyframe (rotation-compensated)
    tracking_ok: bool = True  # False: bad frame (black, blurred, out of order...): no usable observations
    reason: str = ""  # why tracking_ok is False, for logs
    timings_ms: dict = field(default_factory=dict)  # per-stage front-end timings

    @property
    def n_stereo(self) -> int:
        return int(np.count_nonzero(np.isfinite(self.depth_m)))

    @staticmethod
    def empty(t_ns: int, reason: str) -> FeatureFrame:
        z = np.zeros((0, 2))
        return FeatureFrame(t_ns, np.zeros(0, np.int64), z, z.copy(), np.zeros(0), np.zeros(0, np.int64),
                            tracking_ok=False, reason=reason)
