"""The smoother's motion against the stereo pair's own metric motion, keyframe to keyframe (a failure check).

Why: a replay started in a hover let go of cam1 on an implausible reading, the scale ran away, and for ~50 s the
estimate flew 12-26 m/s to 500+ m from a vehicle that stayed within 2 m, while its covariance said sigma_v 0.25 m/s
and quality 5. The smoother's covariance is its own opinion; the speed and bias bounds are far from such a runaway.
What the smoother cannot talk itself out of is the stereo pair's depth: the previous keyframe's stereo points
(front-end depths from the calibration, no IMU) seen again in this keyframe's left image give the camera's motion
by PnP, in metres. When the smoother's motion over the same interval disagrees with it by several sigma of that
reading, and by more than `motion_check_min_m_s` per second, on `motion_check_confirm` keyframes in a row, the
estimate has lost its scale or velocity: the estimator resets (no bridge: the state is not trusted).

Only read, never fed back: the check changes no estimate while it passes. Its PnP runs once a keyframe on the
previous keyframe's stereo points (a few hundred us; docs/estimator.md, "Motion check").
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import cv2
import numpy as np

from vio.relative_pose import points_from_depth, solve_pnp
from vio.types import FeatureFrame

log = logging.getLogger(__name__)

MIN_POINTS = 12  # stereo points seen again below which a PnP says too little (no reading, the streak unchanged)
REPROJECTION_PX = 2.0  # RANSAC inlier threshold (undistorted pixels)
PIXEL_FLOOR_PX = 0.3  # the reading's image noise is never taken below this (a handful of inliers can fit too well)
DISPARITY_SIGMA_PX = 0.5  # random error of one stereo disparity: its depth's error scales the PnP's translation


@dataclass(frozen=True)
class MotionReading:
    """One keyframe's comparison, in this keyframe's left-camera frame (metres)."""

    t_ns: int
    dt_s: float
    stereo_m: np.ndarray  # the camera's displacement from the stereo PnP
    smoother_m: np.ndarray  # the same from the smoother's two keyframe poses
    sigma_m: float  # 1-sigma of the stereo reading along the disagreement
    inliers: int

    @property
    def gap_m_s(self) -> float:
        """Disagreement as a speed (m/s over the interval)."""
        return float(np.linalg.norm(self.smoother_m - self.stereo_m)) / self.dt_s

    @property
    def n_sigma(self) -> float:
        return float(np.linalg.norm(self.smoother_m - self.stereo_m)) / self.sigma_m

    def describe(self) -> str:
        return (f"the smoother moved {np.linalg.norm(self.smoother_m) / self.dt_s:.2f} m/s, the stereo pair "
                f"{np.linalg.norm(self.stereo_m) / self.dt_s:.2f} m/s over {self.dt_s:.2f} s: "
                f"{self.gap_m_s:.2f} m/s apart, {self.n_sigma:.0f} sigma ({self.inliers} points)")


@dataclass(frozen=True)
class MotionTally:
    """The check's figures over a flight: a reset starts a new MotionCheck, so the stats add them up run by run."""

    readings: int = 0  # compared keyframes
    disagreeing: int = 0  # keyframes beyond motion_check_sigma and motion_check_min_m_s
    resets: int = 0  # confirmed disagreements (each reset the estimator)
    worst: MotionReading | None = None  # the most sigma
    widest: MotionReading | None = None  # the most m/s apart


def stereo_displacement(prev: FeatureFrame, cur: FeatureFrame, K: np.ndarray,
                        baseline_m: float) -> tuple[np.ndarray, np.ndarray, int] | None:
    """The left camera's displacement from prev to cur, in cur's camera frame, by PnP of prev's stereo points
    against cur's pixels, with its covariance [m^2] and inlier count; None with too few points.

    The covariance has two parts: the image noise through the projection Jacobian (the inliers' residuals, floored
    at PIXEL_FLOOR_PX) and the depths' own error, which scales the whole translation: each point's relative depth
    error is z * DISPARITY_SIGMA_PX / (fx * baseline), and the scale's is their inverse-variance mean."""
    _, ip, ic = np.intersect1d(prev.ids, cur.ids, assume_unique=True, return_indices=True)
    keep = np.isfinite(prev.depth_m[ip]) & (prev.depth_m[ip] > 0)
    ip, ic = ip[keep], ic[keep]
    if len(ip) < MIN_POINTS:
        return None
    pts = points_from_depth(prev.uv0[ip], prev.depth_m[ip], K)
    uv = cur.uv0[ic].astype(np.float64)
    pose = solve_pnp(pts, uv, K, min_inliers=MIN_POINTS, iterations=60, reprojection_error=REPROJECTION_PX,
                     flags=cv2.SOLVEPNP_EPNP)
    if pose is None:
        return None
    inl = pose.inliers
    proj, J = cv2.projectPoints(pts[inl], pose.rvec, pose.tvec, K, None)
    res = proj.reshape(-1, 2) - uv[inl]
    sigma_px = max(float(np.sqrt(np.mean(res ** 2))), PIXEL_FLOOR_PX)
    J = J[:, :6]
    try:
        cov6 = np.linalg.inv(J.T @ J) * sigma_px ** 2
    except np.linalg.LinAlgError:
        return None
    d = -pose.tvec.reshape(3)  # prev's camera centre seen from cur: the displacement, in cur's frame
    cov = cov6[3:, 3:]  # tvec's block: the rotation's uncertainty marginalised into it
    rel = pts[inl, 2] * DISPARITY_SIGMA_PX / (K[0, 0] * baseline_m)
    scale_var = 1.0 / float(np.sum(1.0 / rel ** 2))
    cov = cov + scale_var * np.outer(d, d)
    return d, cov, len(inl)


class MotionCheck:
    """Keyframe by keyframe: the smoother's displacement of the left camera against the stereo PnP's (one smoother
    run: a reset starts a new one). `add` returns the failure in words once `confirm` readings in a row disagree."""

    def __init__(self, K: np.ndarray, baseline_m: float, *, n_sigma: float, min_m_s: float, scale_sigma: float,
                 confirm: int) -> None:
        self.K = K
        self.baseline_m = baseline_m
        self.n_sigma = n_sigma
        self.min_m_s = min_m_s
        self.scale_sigma = scale_sigma
        self.confirm = confirm
        self._prev: tuple[int, FeatureFrame, np.ndarray] | None = None  # (t, features, T_world_cam0) at a keyframe
        self.streak: list[MotionReading] = []  # the disagreeing readings in a row
        self._streak_poses: list[np.ndarray] = []  # T_world_cam0 before the streak's first keyframe, then at each
        self.readings = 0  # compared keyframes (for the stats and tests)
        self.disagreeing = 0  # readings beyond both thresholds (in a streak or not)
        self.confirmed = 0  # failures returned (each one a reset)
        self.worst: MotionReading | None = None  # the largest disagreement in sigma, for the logs
        self.widest: MotionReading | None = None  # the largest disagreement in m/s

    def add(self, t_ns: int, ff: FeatureFrame, T_world_cam0: np.ndarray) -> str | None:
        """This keyframe (IMU-clock stamp, its features, the smoother's left-camera pose); the failure when the
        smoother's motion has disagreed with the stereo pair's for `confirm` keyframes in a row, else None."""
        prev, self._prev = self._prev, (t_ns, ff, T_world_cam0)
        if prev is None or not ff.tracking_ok or not prev[1].tracking_ok or t_ns <= prev[0]:
            return None
        got = stereo_displacement(prev[1], ff, self.K, self.baseline_m)
        if got is None:  # no reading: neither for nor against the smoother
            return None
        d, cov, n = got
        T_prev, T_cur = prev[2], T_world_cam0
        smoother = T_cur[:3, :3].T @ (T_cur[:3, 3] - T_prev[:3, 3])
        gap = smoother - d
        u = gap / max(float(np.linalg.norm(gap)), 1e-12)
        var = float(u @ cov @ u) + (self.scale_sigma * float(np.linalg.norm(d))) ** 2
        r = MotionReading(t_ns, (t_ns - prev[0]) * 1e-9, d, smoother, float(np.sqrt(max(var, 1e-12))), n)
        self.readings += 1
        if self.worst is None or r.n_sigma > self.worst.n_sigma:
            self.worst = r
        if self.widest is None or r.gap_m_s > self.widest.gap_m_s:
            self.widest = r
        if r.n_sigma <= self.n_sigma or r.gap_m_s <= self.min_m_s:
            if self.streak:
                log.debug("motion check t=%d: agrees again after %d (%s)", t_ns, len(self.streak), r.describe())
            self.streak = []
            return None
        self.disagreeing += 1
        if not self.streak:
            self._streak_poses = [T_prev]
        self.streak.append(r)
        self._streak_poses.append(T_cur)
        log.debug("motion check t=%d: disagrees (%d in a row): %s", t_ns, len(self.streak), r.describe())
        if len(self.streak) < self.confirm:
            return None
        self.confirmed += 1
        return (f"motion check: the estimate's motion disagrees with the stereo pair's on {len(self.streak)} "
                f"keyframes in a row ({r.describe()}): scale or velocity lost")

    def tally(self, before: MotionTally) -> MotionTally:
        """`before` (the flight's earlier smoother runs) with this run's readings added."""
        def most(a: MotionReading | None, b: MotionReading | None, key) -> MotionReading | None:
            return a if b is None or (a is not None and key(a) >= key(b)) else b

        return MotionTally(before.readings + self.readings, before.disagreeing + self.disagreeing,
                           before.resets + self.confirmed,
                           most(before.worst, self.worst, lambda r: r.n_sigma),
                           most(before.widest, self.widest, lambda r: r.gap_m_s))

    def stereo_anchor(self) -> np.ndarray | None:
        """T_world_cam0 at the newest keyframe with the position carried from the last keyframe before the streak by
        the stereo displacements (turned into the world by the smoother's orientations, which the gyro holds),
        instead of the smoother's: where a reset should continue from. None without a streak."""
        if not self.streak:
            return None
        T = self._streak_poses[-1].copy()
        p = self._streak_poses[0][:3, 3].copy()
        for r, T_k in zip(self.streak, self._streak_poses[1:]):
            p += T_k[:3, :3] @ r.stereo_m
        T[:3, 3] = p
        return T
