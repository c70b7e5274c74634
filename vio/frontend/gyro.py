"""Camera rotation between two frames from the gyro: the prior that lets KLT follow fast yaw.

Between frames at 20 Hz a drone yawing at 3 rad/s turns 8.6 deg, about 70 px at 752x480: beyond what a
3-level KLT pyramid recovers from a zero-motion start, but easy once the start is rotated by the gyro.
"""

from __future__ import annotations

import bisect

import numpy as np

from vio import VioError
from vio.geometry import so3_exp
from vio.imu_buffer import ImuBuffer
from vio.types import ImuSample


def integrate_gyro(t_ns: np.ndarray, gyro: np.ndarray, t0_ns: int, t1_ns: int,
                   gyro_bias: np.ndarray | None = None) -> np.ndarray:
    """R_body0_body1 over [t0_ns, t1_ns] (IMU clock) from samples (t_ns (N,), gyro (N, 3) rad/s).

    The rate is interpolated linearly between samples and held at the ends outside the sample span; each
    piece is integrated with its mid-point rate.
    """
    t = np.asarray(t_ns, dtype=np.int64)
    w = np.asarray(gyro, dtype=float) - (0.0 if gyro_bias is None else np.asarray(gyro_bias, dtype=float))
    R = np.eye(3)
    if t1_ns <= t0_ns or len(t) == 0:
        return R
    inner = t[(t > t0_ns) & (t < t1_ns)]
    knots = np.concatenate([[t0_ns], inner, [t1_ns]]).astype(np.int64)
    ts = (t - t[0]).astype(float)
    rel = (knots - t[0]).astype(float)
    rates = np.column_stack([np.interp(rel, ts, w[:, k]) for k in range(3)])
    dt = np.diff(knots)[:, None] * 1e-9
    # all pieces' rotations in one call (one scipy call per piece was 1.7 ms of every frame), then the product
    for Ri in so3_exp(0.5 * (rates[:-1] + rates[1:]) * dt):
        R = R @ Ri
    return R


def body_to_camera_rotation(R_body0_body1: np.ndarray, T_body_cam: np.ndarray) -> np.ndarray:
    """R_cam0_cam1 = R_body_cam^T R_body0_body1 R_body_cam for a camera rigidly mounted at T_body_cam."""
    R_bc = np.asarray(T_body_cam)[:3, :3]
    return R_bc.T @ R_body0_body1 @ R_bc


class GyroPrior:
    """Answers R_cam0prev_cam0cur between two camera time stamps from recent gyro samples.

    `rotation(t_prev_cam, t_cur_cam)` converts camera stamps to the IMU clock (t_imu = t_cam +
    time_offset_ns). The samples come from `imu`, a buffer someone else fills and trims (the estimator's
    one buffer); without one the prior keeps its own, fed with `add` and trimmed to `keep_s`.
    """

    def __init__(self, T_body_cam: np.ndarray, time_offset_ns: int = 0, keep_s: float = 2.0,
                 imu: ImuBuffer | None = None) -> None:
        self.T_body_cam = np.asarray(T_body_cam, dtype=float)
        self.time_offset_ns = int(time_offset_ns)
        self.keep_ns = int(keep_s * 1e9)
        self._owned = imu is None
        self.imu = ImuBuffer() if imu is None else imu
        self.gyro_bias = np.zeros(3)  # set_gyro_bias() keeps it at the back end's estimate

    def set_gyro_bias(self, gyro_bias: np.ndarray) -> None:
        """Use the back end's gyro bias estimate [rad/s, body frame] from now on.

        Without it the bias rotates the KLT start by bias * dt per frame and the parallax measure sees the
        accumulated rotation error as fake parallax. Call after each back-end update (cheap: a copy)."""
        b = np.asarray(gyro_bias, dtype=float).reshape(-1)
        if b.shape != (3,) or not np.all(np.isfinite(b)):
            raise VioError(f"gyro bias must be 3 finite numbers [rad/s], got {gyro_bias!r}")
        self.gyro_bias = b.copy()

    def add(self, s: ImuSample) -> None:
        """Feed a sample to the prior's own buffer (not needed, and not allowed, with a shared one)."""
        if not self._owned:
            raise VioError("GyroPrior reads a shared IMU buffer: feed that buffer, not the prior")
        if self.imu.add(s):  # duplicates and out-of-order samples are dropped: the stream stays monotonic
            self._trim(s.t_ns)

    def _trim(self, t_ns: int) -> None:
        t = self.imu.t
        i = bisect.bisect_left(t, t_ns - self.keep_ns)  # drop samples older than keep_s
        if i > 0:
            del t[:i], self.imu.gyro[:i], self.imu.accel[:i]

    def rotation(self, t_prev_cam_ns: int, t_cur_cam_ns: int) -> np.ndarray | None:
        """R_cam_prev_cam_cur, or None when the buffer does not cover the interval (no prior then)."""
        t0 = t_prev_cam_ns + self.time_offset_ns
        t1 = t_cur_cam_ns + self.time_offset_ns
        t = self.imu.t
        if len(t) < 2 or t[0] > t0 or t[-1] < t1 - 10_000_000:
            return None
        # the samples from the one before t0 to the one after t1: integrate_gyro interpolates between them
        i = max(bisect.bisect_right(t, t0) - 1, 0)
        j = bisect.bisect_left(t, t1) + 1
        R_b = integrate_gyro(np.array(t[i:j], np.int64), np.array(self.imu.gyro[i:j]), t0, t1, self.gyro_bias)
        return body_to_camera_rotation(R_b, self.T_body_cam)
