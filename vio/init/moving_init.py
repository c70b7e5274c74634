"""Initialisation in motion: visual-inertial alignment with stereo-metric relative poses.

Stereo depth makes the visual motion metric, so unlike monocular VINS there is no scale to find:
1. relative camera poses between consecutive frames by PnP (previous frame's stereo points against the
   current frame's pixels), chained into body poses in the first body frame B0;
2. gyro bias: the bias that makes the pre-integrated rotations agree with the visual ones (Gauss-Newton,
   numeric Jacobian; the problem has three unknowns);
3. velocities and gravity in B0 from the linear position/velocity pre-integration equations
   v_k dt + g dt^2/2 = p_k+1 - p_k - R_k dp_k,   v_k+1 - v_k - g dt = R_k dv_k,
   then |g| is fixed to its known value and the velocities re-solved;
4. the world frame is B0 rotated so that gravity points down (yaw zero).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import cv2
import gtsam
import numpy as np

from vio.calibration import StereoCalibration
from vio.config import InitConfig
from vio.geometry import GRAVITY_M_S2, gravity_aligned_rotation, inv_T, make_T, so3_log
from vio.imu_buffer import MOTION_UNKNOWN_GAP_NS, ImuBuffer
from vio.init.static_init import InitialState
from vio.relative_pose import points_from_depth, solve_pnp
from vio.types import FeatureFrame

log = logging.getLogger(__name__)


@dataclass
class _Frame:
    t_ns: int
    ff: FeatureFrame
    T_b0_b: np.ndarray  # body pose in the first body frame of the window


def relative_pose_pnp(prev: FeatureFrame, cur: FeatureFrame, K: np.ndarray,
                      min_points: int = 12) -> np.ndarray | None:
    """T_cam0prev_cam0cur from the previous frame's stereo points seen again in the current frame."""
    _, ip, ic = np.intersect1d(prev.ids, cur.ids, return_indices=True)
    keep = np.isfinite(prev.depth_m[ip])
    ip, ic = ip[keep], ic[keep]
    if len(ip) < min_points:
        return None
    pose = solve_pnp(points_from_depth(prev.uv0[ip], prev.depth_m[ip], K), cur.uv0[ic], K, min_inliers=min_points,
                     iterations=100, reprojection_error=2.0, flags=cv2.SOLVEPNP_ITERATIVE, refine=False)
    if pose is None:
        return None
    return inv_T(make_T(pose.R_cur_prev, pose.tvec.reshape(3)))


class MovingInitializer:
    """Collects frames while the vehicle moves and aligns them with the IMU once enough are in."""

    def __init__(self, calib: StereoCalibration, cfg: InitConfig,
                 params: gtsam.PreintegrationCombinedParams) -> None:
        self.calib = calib
        self.cfg = cfg
        self.params = params
        self.K = calib.cam0.K
        self.T_body_cam0 = calib.cam0.T_body_cam
        self.frames: list[_Frame] = []
        # five sample periods at least: a 10 Hz serial or MAVLink IMU (allowed) is 100 ms apart with nothing lost
        self.max_imu_gap_ns = max(MOTION_UNKNOWN_GAP_NS, int(5e9 / calib.imu.rate_hz))

    def clear(self) -> None:
        self.frames = []

    def add(self, t_ns: int, ff: FeatureFrame, imu: ImuBuffer) -> InitialState | None:
        """Add a frame (stamp on the IMU clock); returns the initial state at this frame when aligned."""
        if not ff.tracking_ok or ff.n_stereo < 12:
            self.clear()
            return None
        if not self.frames:
            self.frames.append(_Frame(t_ns, ff, np.eye(4)))
            return None
        prev = self.frames[-1]
        gap = imu.largest_gap_ns(prev.t_ns, t_ns)
        if gap > self.max_imu_gap_ns:
            # the pre-integration would interpolate across it: the fitted bias and gravity absorb a motion nobody
            # measured (an ArduPilot SITL restart: a 1.9 s gap at the MAVLink IMU's clock jump, a 0.059 rad/s bias)
            log.debug("moving init: IMU gap of %.2f s before %d; restarting the window", gap * 1e-9, t_ns)
            self.frames = [_Frame(t_ns, ff, np.eye(4))]
            return None
        T_c0p_c0c = relative_pose_pnp(prev.ff, ff, self.K)
        if T_c0p_c0c is None:
            log.debug("moving init: no PnP pose at %d; restarting the window", t_ns)
            self.frames = [_Frame(t_ns, ff, np.eye(4))]
            return None
        T_bp_bc = self.T_body_cam0 @ T_c0p_c0c @ inv_T(self.T_body_cam0)
        self.frames.append(_Frame(t_ns, ff, prev.T_b0_b @ T_bp_bc))
        span_s = (t_ns - self.frames[0].t_ns) * 1e-9
        if span_s < self.cfg.moving_window_s or len(self.frames) < self.cfg.moving_min_frames:
            return None
        state = self._align(imu)
        if state is None:
            self.frames.pop(0)
        return state

    def _pims(self, imu: ImuBuffer, bg: np.ndarray) -> list[gtsam.PreintegratedCombinedMeasurements]:
        bias = gtsam.imuBias.ConstantBias(np.zeros(3), bg)
        out = []
        for a, b in zip(self.frames[:-1], self.frames[1:]):
            pim = gtsam.PreintegratedCombinedMeasurements(self.params, bias)
            imu.integrate(pim, a.t_ns, b.t_ns)
            out.append(pim)
        return out

    def _rotation_residuals(self, imu: ImuBuffer, bg: np.ndarray) -> np.ndarray:
        res = []
        for pim, a, b in zip(self._pims(imu, bg), self.frames[:-1], self.frames[1:]):
            R_vis = a.T_b0_b[:3, :3].T @ b.T_b0_b[:3, :3]
            res.append(so3_log(pim.deltaRij().matrix().T @ R_vis))
        return np.concatenate(res)

    def _align(self, imu: ImuBuffer) -> InitialState | None:
        bg = np.zeros(3)
        for _ in range(3):
            r = self._rotation_residuals(imu, bg)
            J = np.zeros((len(r), 3))
            for k in range(3):
                d = np.zeros(3)
                d[k] = 1e-4
                J[:, k] = (self._rotation_residuals(imu, bg + d) - r) / 1e-4
            bg = bg - np.linalg.lstsq(J, r, rcond=None)[0]
        rot_err = float(np.sqrt(np.mean(self._rotation_residuals(imu, bg) ** 2)))
        pims = self._pims(imu, bg)
        n = len(self.frames)
        A = np.zeros((6 * (n - 1), 3 * n + 3))
        y = np.zeros(6 * (n - 1))
        for k, pim in enumerate(pims):
            dt = pim.deltaTij()
            Tk, Tk1 = self.frames[k].T_b0_b, self.frames[k + 1].T_b0_b
            Rk = Tk[:3, :3]
            r0 = 6 * k
            A[r0:r0 + 3, 3 * k:3 * k + 3] = np.eye(3) * dt
            A[r0:r0 + 3, 3 * n:] = np.eye(3) * 0.5 * dt * dt
            y[r0:r0 + 3] = Tk1[:3, 3] - Tk[:3, 3] - Rk @ pim.deltaPij()
            A[r0 + 3:r0 + 6, 3 * (k + 1):3 * (k + 1) + 3] = np.eye(3)
            A[r0 + 3:r0 + 6, 3 * k:3 * k + 3] = -np.eye(3)
            A[r0 + 3:r0 + 6, 3 * n:] = -np.eye(3) * dt
            y[r0 + 3:r0 + 6] = Rk @ pim.deltaVij()
        x = np.linalg.lstsq(A, y, rcond=None)[0]
        g = x[3 * n:]
        g_norm = float(np.linalg.norm(g))
        if not (0.85 * GRAVITY_M_S2 < g_norm < 1.15 * GRAVITY_M_S2) or rot_err > 0.02:
            log.debug("moving init rejected: |g| %.2f m/s^2, rotation residual %.4f rad", g_norm, rot_err)
            return None
        g = g / g_norm * GRAVITY_M_S2
        x_v = np.linalg.lstsq(A[:, :3 * n], y - A[:, 3 * n:] @ g, rcond=None)[0]
        R_w_b0 = gravity_aligned_rotation(-g, self.calib.view_headings_body)
        last = self.frames[-1]
        T_w_b = make_T(R_w_b0, np.zeros(3)) @ last.T_b0_b
        v_w = R_w_b0 @ x_v[3 * (n - 1):]
        log.info("moving initialisation over %d frames: |g| %.3f m/s^2 before fixing, |v| %.2f m/s, "
                 "gyro bias (%.4f %.4f %.4f) rad/s", n, g_norm, float(np.linalg.norm(v_w)), *bg)
        return InitialState(last.t_ns, T_w_b, v_w, bg, np.zeros(3), "moving")
