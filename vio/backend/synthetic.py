"""A small synthetic scene for checking the back end alone: exact IMU and perfect feature tracks.

The full simulator (`vio.sim`) renders images for the whole pipeline; this module skips images and
projects known landmarks straight into FeatureFrames, so a back-end test isolates the estimator from
front-end errors and runs in seconds. The motion is a smooth sum of sinusoids (optionally after a still
start); derivatives are central differences of the closed-form pose, accurate far beyond IMU noise.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from vio.calibration import CameraCalibration, ImuNoise, StereoCalibration
from vio.geometry import GRAVITY_M_S2, inv_T, make_T, so3_exp, so3_log
from vio.types import FeatureFrame, ImuSample

# camera looks along body +x; optical x right (= body -y), y down (= body -z)
_R_BODY_CAM = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


def synthetic_calibration(width: int = 752, height: int = 480, baseline_m: float = 0.11) -> StereoCalibration:
    """Distortion-free EuRoC-sized stereo head looking forward from the body."""
    T0 = make_T(_R_BODY_CAM, np.array([0.05, 0.0, 0.0]))
    T1 = T0 @ make_T(np.eye(3), np.array([baseline_m, 0.0, 0.0]))
    cams = [CameraCalibration(458.0, 457.0, width / 2, height / 2, width, height, "none", (0, 0, 0, 0), T)
            for T in (T0, T1)]
    return StereoCalibration(cams[0], cams[1], ImuNoise())


@dataclass
class Motion:
    """Smooth 6-DoF motion; `speed` scales amplitudes, `still_s` holds the start still."""

    speed: float = 1.0
    still_s: float = 0.0
    seed: int = 0

    def __post_init__(self) -> None:
        rng = np.random.default_rng(self.seed)
        self.w = rng.uniform(0.25, 0.6, size=6) * self.speed
        self.ph = rng.uniform(0, 2 * np.pi, size=6)
        self.amp = np.array([1.5, 1.2, 0.4, 0.8, 0.08, 0.08])

    def _ramp(self, t: float) -> float:
        x = np.clip((t - self.still_s) / 2.0, 0.0, 1.0)
        return float(x ** 3 * (10 - 15 * x + 6 * x * x))

    def _raw(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        s = self._ramp(t)
        tau = max(t - self.still_s, 0.0)
        f = self.amp * (np.sin(self.w * tau + self.ph) - np.sin(self.ph)) * s
        yaw, roll, pitch = f[3], f[4], f[5]
        R = so3_exp(np.array([0, 0, yaw])) @ so3_exp(np.array([0, pitch, 0])) @ so3_exp(np.array([roll, 0, 0]))
        return f[:3], R

    def pose(self, t: float) -> np.ndarray:
        p, R = self._raw(t)
        return make_T(R, p)

    def velocity(self, t: float, h: float = 1e-4) -> np.ndarray:
        return (self._raw(t + h)[0] - self._raw(t - h)[0]) / (2 * h)

    def imu(self, t: float, h: float = 1e-4) -> tuple[np.ndarray, np.ndarray]:
        """Exact (gyro, accel) in the body frame at t."""
        p0, R0 = self._raw(t - h)
        p1, R = self._raw(t)
        p2, R2 = self._raw(t + h)
        omega = so3_log(R0.T @ R2) / (2 * h)
        a_world = (p2 - 2 * p1 + p0) / (h * h)
        return omega, R.T @ (a_world + np.array([0.0, 0.0, GRAVITY_M_S2]))


class SyntheticScene:
    """Landmarks on the walls of a room around the motion, observed by a perfect stereo tracker."""

    def __init__(self, calib: StereoCalibration, n_points: int = 3000, seed: int = 0,
                 room: tuple[float, float, float] = (6.0, 6.0, 3.0)) -> None:
        rng = np.random.default_rng(seed)
        self.calib = calib
        hx, hy, hz = room
        pts = rng.uniform([-hx, -hy, -hz], [hx, hy, hz], size=(n_points, 3))
        face = rng.integers(0, 6, n_points)
        for k in range(6):
            axis, sign = k // 2, 1 if k % 2 else -1
            pts[face == k, axis] = sign * room[axis]
        self.points = pts
        self.track_len = np.zeros(n_points, np.int64)

    def observe(self, t_ns: int, T_world_body: np.ndarray, max_features: int = 150,
                pixel_sigma: float = 0.0, rng: np.random.Generator | None = None) -> FeatureFrame:
        """FeatureFrame of the landmarks visible in cam0 (and cam1 for stereo) at this pose."""
        c0, c1 = self.calib.cam0, self.calib.cam1
        uv = []
        for cam in (c0, c1):
            T_c_w = inv_T(T_world_body @ cam.T_body_cam)
            p_c = self.points @ T_c_w[:3, :3].T + T_c_w[:3, 3]
            z = p_c[:, 2]
            u = cam.fx * p_c[:, 0] / np.maximum(z, 1e-9) + cam.cx
            v = cam.fy * p_c[:, 1] / np.maximum(z, 1e-9) + cam.cy
            ok = (z > 0.3) & (u >= 0) & (u < cam.width) & (v >= 0) & (v < cam.height)
            uv.append((np.column_stack([u, v]), ok, z))
        (uv0, ok0, z0), (uv1, ok1, _) = uv
        self.track_len = np.where(ok0, self.track_len + 1, 0)
        idx = np.flatnonzero(ok0)
        # keep the longest tracks, as a tracker that tops up with new features would
        idx = idx[np.argsort(-self.track_len[idx], kind="stable")][:max_features]
        n = len(idx)
        noise0 = np.zeros((n, 2)) if rng is None else rng.normal(0, pixel_sigma, (n, 2))
        noise1 = np.zeros((n, 2)) if rng is None else rng.normal(0, pixel_sigma, (n, 2))
        stereo = ok1[idx]
        uv1_out = np.where(stereo[:, None], uv1[idx] + noise1, np.nan)
        depth = np.where(stereo, z0[idx], np.nan)
        return FeatureFrame(int(t_ns), idx.astype(np.int64), uv0[idx] + noise0, uv1_out, depth,
                            self.track_len[idx].copy(), parallax_px=0.0)


def imu_samples(motion: Motion, t0_s: float, t1_s: float, rate_hz: float = 200.0,
                gyro_bias: np.ndarray | None = None, accel_bias: np.ndarray | None = None,
                noise: ImuNoise | None = None, rng: np.random.Generator | None = None) -> list[ImuSample]:
    """IMU samples on [t0, t1] with constant biases and optional white noise from `noise`."""
    bg = np.zeros(3) if gyro_bias is None else np.asarray(gyro_bias, float)
    ba = np.zeros(3) if accel_bias is None else np.asarray(accel_bias, float)
    out = []
    n = int(round((t1_s - t0_s) * rate_hz)) + 1
    for k in range(n):
        t = t0_s + k / rate_hz
        g, a = motion.imu(t)
        g, a = g + bg, a + ba
        if noise is not None and rng is not None:
            g = g + rng.normal(0, noise.gyroscope_noise_density * np.sqrt(rate_hz), 3)
            a = a + rng.normal(0, noise.accelerometer_noise_density * np.sqrt(rate_hz), 3)
        out.append(ImuSample(int(round(t * 1e9)), g, a))
    return out
