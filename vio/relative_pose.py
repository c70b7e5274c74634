"""Relative camera motion between two frames: the one PnP and relative-rotation helper of the core.

Used by the moving initialisation (poses between consecutive frames), the in-flight time offset (rotations
between frames a few apart) and `vio calib time-offset` (rotations from raw recordings). The callers differ
in their solver settings (iterations, inlier threshold, EPnP or iterative, LM refinement), which are
parameters here so that each keeps its tuned behaviour; the mechanics live once.

Conventions: `prev` is the frame whose 3D points are known (camera coordinates of prev), `cur` the one whose
pixels see them; the PnP result is T_cur_prev (maps prev's points into cur), as OpenCV returns it.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

ROTATION_ONLY_PX = 1.0  # a pure-rotation fit explaining matches to this median error means no parallax


@dataclass(frozen=True)
class PnpPose:
    """A PnP solution: rvec/tvec map prev's camera coordinates into cur's; `inliers` index the points."""

    rvec: np.ndarray
    tvec: np.ndarray
    inliers: np.ndarray

    @property
    def n_inliers(self) -> int:
        return len(self.inliers)

    @property
    def R_cur_prev(self) -> np.ndarray:
        return cv2.Rodrigues(self.rvec)[0]

    @property
    def R_prev_cur(self) -> np.ndarray:
        return self.R_cur_prev.T


def points_from_depth(uv: np.ndarray, depth: np.ndarray, K: np.ndarray) -> np.ndarray:
    """3D points (camera frame) of pixels `uv` (N, 2) at z-depths `depth` (N,) for a pinhole K."""
    rays = np.column_stack([(uv - K[:2, 2]) / np.array([K[0, 0], K[1, 1]]), np.ones(len(uv))])
    return rays * depth[:, None]


def solve_pnp(points: np.ndarray, uv: np.ndarray, K: np.ndarray, *, min_inliers: int, iterations: int,
              reprojection_error: float, flags: int = cv2.SOLVEPNP_EPNP, confidence: float = 0.99,
              refine: bool = True) -> PnpPose | None:
    """RANSAC PnP of prev's `points` against cur's pixels `uv` (in the units of K; np.eye(3) for normalised
    coordinates, then `reprojection_error` is in normalised units too). None with fewer than `min_inliers`
    inliers. `refine` polishes the pose on the inliers with Levenberg-Marquardt (EPnP alone is noisy)."""
    uv = uv.astype(np.float64)
    found, rvec, tvec, inliers = cv2.solvePnPRansac(points, uv, K, None, iterationsCount=iterations,
                                                    reprojectionError=reprojection_error,
                                                    confidence=confidence, flags=flags)
    if not found or inliers is None or len(inliers) < min_inliers:
        return None
    inl = inliers.ravel()
    if refine:
        rvec, tvec = cv2.solvePnPRefineLM(points[inl], uv[inl], K, None, rvec, tvec)
    return PnpPose(rvec, tvec, inl)


def rotation_information(points: np.ndarray, pose: PnpPose, K: np.ndarray) -> np.ndarray | None:
    """Information (inverse covariance, unit image noise) of the PnP rotation with the translation
    marginalised, from the inliers' projection Jacobian; None when singular. Few or clustered points leave
    the rotation entangled with the translation, and such pairs must count for less."""
    _, J = cv2.projectPoints(points[pose.inliers], pose.rvec, pose.tvec, K, None)
    J = J[:, :6]
    try:
        return np.linalg.inv(np.linalg.inv(J.T @ J)[:3, :3])
    except np.linalg.LinAlgError:
        return None


def _rotation_from_bearings(b0: np.ndarray, b1: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """R minimising sum |b0 - R b1|^2 (R = R_c0_c1 for pure rotation), refit on inliers twice."""
    keep = np.ones(len(b0), dtype=bool)
    R = np.eye(3)
    for _ in range(3):
        H = b0[keep].T @ b1[keep]
        U, _, Vt = np.linalg.svd(H)
        R = U @ np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))]) @ Vt
        err = np.linalg.norm(b0 - b1 @ R.T, axis=1)
        keep = err < max(3.0 * np.median(err), 1e-4)
    return R, err


def relative_rotation(x0: np.ndarray, x1: np.ndarray, f_px: float,
                      min_tracks: int = 15) -> tuple[np.ndarray, int, np.ndarray] | None:
    """R_c0_c1 from normalised image points x0 (frame 0) and x1 (frame 1) without depth: a pure-rotation fit
    when it explains the matches (no parallax), else the essential matrix. Returns (R, inliers,
    information = inliers * I); None when unreliable."""
    b0 = np.column_stack([x0, np.ones(len(x0))])
    b1 = np.column_stack([x1, np.ones(len(x1))])
    b0 /= np.linalg.norm(b0, axis=1, keepdims=True)
    b1 /= np.linalg.norm(b1, axis=1, keepdims=True)
    R_rot, err = _rotation_from_bearings(b0, b1)
    if np.median(err) * f_px < ROTATION_ONLY_PX:
        n_in = int(np.sum(err * f_px < 3 * ROTATION_ONLY_PX))
        return (R_rot, n_in, n_in * np.eye(3)) if n_in >= min_tracks else None
    E, mask = cv2.findEssentialMat(x0, x1, np.eye(3), method=cv2.RANSAC, prob=0.999, threshold=1.0 / f_px)
    if E is None or E.shape != (3, 3):
        return None
    n, R_1_0, _, mask = cv2.recoverPose(E, x0, x1, np.eye(3), mask=mask)
    if n < min_tracks:
        return None
    return R_1_0.T, int(n), int(n) * np.eye(3)
