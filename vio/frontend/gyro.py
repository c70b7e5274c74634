"""Camera rotation between two frames from the gyro: the prior that lets KLT follow fast yaw.

Between frames at 20 Hz a drone yawing at 3 rad/s turns 8.6 deg, about 70 px at 752x480: beyond what a
3-level KLT pyramid recovers from a zero-motion start, but easy once the start is rotated by the gyro.
"""

from __future__ import annotations

from collections import deque

import numpy as np

from vio import VioError
from vio.geometry import so3_exp
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
    for i in range(len(knots) - 1):
        dt = (knots[i + 1] - knots[i]) * 1e-9
        R = R @ so3_exp(0.5 * (rates[i] + rates[i + 1]) * dt)
    return R


def body_to_camera_rotation(R_body0_body1: np.ndarray, T_body_cam: np.ndarray) -> np.ndarray:
    """R_cam0_cam1 = R_body_cam^T R_body0_body1 R_body_cam for a camera rigidly mounted at T_body_cam."""
    R_bc = np.asarray(T_body_cam)[:3, :3]
    return R_bc.T @ R_body0_body1 @ R_bc


class GyroPrior:
    """Keeps recent gyro samples and answers R_cam0prev_cam0cur between two camera time stamps.

    Feed every ImuSample with `add`; `rotation(t_prev_cam, t_cur_cam)` converts camera stamps to the IMU clock
    (t_imu = t_cam + time_offset_ns) and drops samples no longer needed.
    """

    def __init__(self, T_body_cam: np.ndarray, time_offset_ns: int = 0, keep_s: float = 2.0) -> None:
        self.T_body_cam = np.asarray(T_body_cam, dtype=float)
        self.time_offset_ns = int(time_offset_ns)
        self.keep_ns = int(keep_s * 1e9)
        self._t: deque[int] = deque()
        self._w: deque[np.ndarray] = deque()
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
        if self._t and s.t_ns <= self._t[-1]:
            return  # duplicate or out-of-order sample: keep the stream monotonic
        self._t.append(int(s.t_ns))
        self._w.append(np.asarray(s.gyro, dtype=float))
        while self._t and self._t[0] < s.t_ns - self.keep_ns:
            self._t.popleft()
            self._w.popleft()

    def rotation(self, t_prev_cam_ns: int, t_cur_cam_ns: int) -> np.ndarray | None:
        """R_cam_prev_cam_cur, or None when the buffer does not cover the interval (no prior then)."""
        t0 = t_prev_cam_ns + self.time_offset_ns
        t1 = t_cur_cam_ns + self.time_offset_ns
        if len(self._t) < 2 or self._t[0] > t0 or self._t[-1] < t1 - 10_000_000:
            return None
        R_b = integrate_gyro(np.fromiter(self._t, np.int64), np.array(self._w), t0, t1, self.gyro_bias)
        return body_to_camera_rotation(R_b, self.T_body_cam)
