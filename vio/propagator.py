"""IMU-rate state between optimised keyframes.

The autopilot wants poses faster and with less latency than the smoother delivers them; between solves
the last optimised state is pushed forward with each IMU sample (bias-corrected, midpoint rotation),
as VINS-Fusion's fast prediction does. Each smoother result restarts the propagation from the new
state and re-applies the IMU samples that arrived after it, so the output never lags behind the IMU.
"""

from __future__ import annotations

import numpy as np

from vio.geometry import GRAVITY_M_S2, skew
from vio.types import ImuSample

GRAVITY_WORLD = np.array([0.0, 0.0, -GRAVITY_M_S2])


def rodrigues(phi: np.ndarray) -> np.ndarray:
    """Rotation matrix of a small rotation vector; plain numpy because this runs at IMU rate."""
    a = float(np.sqrt(phi @ phi))
    K = skew(phi)
    if a < 1e-8:
        return np.eye(3) + K
    return np.eye(3) + (np.sin(a) / a) * K + ((1 - np.cos(a)) / (a * a)) * (K @ K)


class Propagator:
    """Dead-reckons (R, p, v) from a base state with IMU samples; biases are held constant."""

    def __init__(self) -> None:
        self.t_ns: int | None = None
        self.R = np.eye(3)
        self.p = np.zeros(3)
        self.v = np.zeros(3)
        self.gyro_bias = np.zeros(3)
        self.accel_bias = np.zeros(3)
        self.omega = np.zeros(3)
        self._last: tuple[np.ndarray, np.ndarray] | None = None

    @property
    def ready(self) -> bool:
        return self.t_ns is not None

    def reset(self, t_ns: int, T_world_body: np.ndarray, v_world: np.ndarray, gyro_bias: np.ndarray,
              accel_bias: np.ndarray, last_imu: tuple[np.ndarray, np.ndarray] | None = None) -> None:
        """Restart from an optimised state; `last_imu` = (gyro, accel) at t_ns for the first step."""
        self.t_ns = int(t_ns)
        self.R = np.array(T_world_body[:3, :3], dtype=float)
        self.p = np.array(T_world_body[:3, 3], dtype=float)
        self.v = np.array(v_world, dtype=float)
        self.gyro_bias = np.array(gyro_bias, dtype=float)
        self.accel_bias = np.array(accel_bias, dtype=float)
        self._last = None if last_imu is None else (np.asarray(last_imu[0], float), np.asarray(last_imu[1], float))

    def add(self, s: ImuSample) -> bool:
        """Advance to the sample's stamp; samples not after the current time are ignored."""
        if self.t_ns is None or s.t_ns <= self.t_ns:
            return False
        g1 = np.asarray(s.gyro, float) - self.gyro_bias
        a1 = np.asarray(s.accel, float) - self.accel_bias
        if self._last is None:
            g0, a0 = g1, a1
        else:
            g0, a0 = self._last[0] - self.gyro_bias, self._last[1] - self.accel_bias
        dt = (s.t_ns - self.t_ns) * 1e-9
        w = 0.5 * (g0 + g1)
        R1 = self.R @ rodrigues(w * dt)
        acc_w = 0.5 * (self.R @ a0 + R1 @ a1) + GRAVITY_WORLD
        self.p = self.p + self.v * dt + 0.5 * acc_w * dt * dt
        self.v = self.v + acc_w * dt
        self.R = R1
        self.t_ns = int(s.t_ns)
        self.omega = g1
        self._last = (np.asarray(s.gyro, float), np.asarray(s.accel, float))
        return True

    def pose(self) -> np.ndarray:
        T = np.eye(4)
        T[:3, :3] = self.R
        T[:3, 3] = self.p
        return T
