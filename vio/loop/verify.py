"""Geometric verification of a place-recognition candidate: descriptor matches of the old keyframe's stereo
landmarks against the new keyframe's image, PnP RANSAC, and the gravity (roll/pitch) check."""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from vio.geometry import inv_T
from vio.loop.features import KeyframeFeatures


@dataclass(frozen=True)
class PnpResult:
    T_old_new: np.ndarray  # body pose of the new keyframe in the old keyframe's body frame
    inliers: int
    matches: int
    reproj_rmse_px: float


_MATCHER = cv2.BFMatcher(cv2.NORM_HAMMING)


def match(old: KeyframeFeatures, new: KeyframeFeatures, max_hamming: int, ratio: float) -> np.ndarray:
    """(M, 2) index pairs (old landmark, new feature): ratio test and mutual best."""
    has3 = np.flatnonzero(np.isfinite(old.p_cam[:, 0]))
    if len(has3) < 4 or len(new.desc) < 4:
        return np.zeros((0, 2), np.int64)
    knn = _MATCHER.knnMatch(old.desc[has3], new.desc, k=2)
    cand = [(a.queryIdx, a.trainIdx) for m in knn if len(m) == 2
            for a, b in [m] if a.distance <= max_hamming and a.distance < ratio * b.distance]
    if not cand:
        return np.zeros((0, 2), np.int64)
    q, t = np.array(cand, np.int64).T
    # mutual best: only the new features that passed are matched back (the same answer as matching all of them)
    tu, inv = np.unique(t, return_inverse=True)
    back = np.array([m.trainIdx for m in _MATCHER.match(new.desc[tu], old.desc[has3])], np.int64)
    keep = back[inv] == q
    return np.column_stack([has3[q[keep]], t[keep]]).reshape(-1, 2)


def pnp(old: KeyframeFeatures, new: KeyframeFeatures, K: np.ndarray, T_body_cam: np.ndarray, *,
        max_hamming: int, ratio: float, reproj_px: float, min_inliers: int) -> PnpResult | None:
    pairs = match(old, new, max_hamming, ratio)
    if len(pairs) < min_inliers:
        return None
    obj = old.p_cam[pairs[:, 0]].astype(np.float64)
    img = new.uv[pairs[:, 1]].astype(np.float64)
    ok, rvec, tvec, inl = cv2.solvePnPRansac(obj, img, K, None, iterationsCount=60, reprojectionError=reproj_px,
                                             confidence=0.999, flags=cv2.SOLVEPNP_AP3P)
    if not ok or inl is None or len(inl) < min_inliers:
        return None
    inl = inl[:, 0]
    rvec, tvec = cv2.solvePnPRefineLM(obj[inl], img[inl], K, None, rvec, tvec)
    proj, _ = cv2.projectPoints(obj[inl], rvec, tvec, K, None)
    err = np.linalg.norm(proj[:, 0] - img[inl], axis=1)
    good = err <= reproj_px
    if np.count_nonzero(good) < min_inliers:
        return None
    T_newcam_oldcam = np.eye(4)
    T_newcam_oldcam[:3, :3] = cv2.Rodrigues(rvec)[0]
    T_newcam_oldcam[:3, 3] = tvec[:, 0]
    T_old_new = T_body_cam @ inv_T(T_newcam_oldcam) @ inv_T(T_body_cam)
    return PnpResult(T_old_new, int(np.count_nonzero(good)), len(pairs), float(np.sqrt(np.mean(err[good] ** 2))))


def gravity_disagreement_deg(R_world_old: np.ndarray, R_world_new: np.ndarray, R_old_new: np.ndarray) -> float:
    """Angle between the new keyframe's gravity direction from the odometry and through the loop edge.

    Roll and pitch are observed by the IMU in both keyframes, so a true edge must carry them over."""
    up = np.array([0.0, 0.0, 1.0])
    a = R_world_new.T @ up
    b = (R_world_old @ R_old_new).T @ up
    return float(np.degrees(np.arccos(np.clip(a @ b, -1.0, 1.0))))
