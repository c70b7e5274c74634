"""Stereo matching shared by the calibration tools (`vio calib check`, `vio calib time-offset`): corners of the
left image matched into the right one with KLT on contrast-normalised images, and triangulated."""

from __future__ import annotations

import cv2
import numpy as np

from vio.calibration import StereoCalibration

DEFAULT_DEPTH_M = 4.0  # where the right-image search starts
_KLT = {"winSize": (21, 21), "maxLevel": 4,
        "criteria": (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 30, 0.01)}


def _expected_shift_px(calib: StereoCalibration) -> np.ndarray:
    """Pixel shift of a point at DEFAULT_DEPTH_M straight ahead from cam0 to cam1 (the KLT start)."""
    T = calib.T_cam1_cam0
    p1 = T[:3, :3] @ np.array([0.0, 0.0, DEFAULT_DEPTH_M]) + T[:3, 3]
    uv1 = calib.cam1.K @ (p1 / p1[2])
    return uv1[:2] - calib.cam0.K[:2, 2]


def normalise_contrast(img: np.ndarray, sigma_px: float = 6.0) -> np.ndarray:
    """Local zero-mean, unit-contrast 8-bit image. KLT assumes equal brightness; left/right gain differences
    and exposure drift otherwise bias the matches by tenths of a pixel, enough to skew depths and, through
    them, PnP rotations (on the simulator's realistic variant: 8 ms -> 10 ms time offset)."""
    f = img.astype(np.float32)
    d = f - cv2.GaussianBlur(f, (0, 0), sigma_px)
    s = np.sqrt(cv2.GaussianBlur(d * d, (0, 0), sigma_px)) + 2.0
    return np.clip(128.0 + 40.0 * d / s, 0, 255).astype(np.uint8)


def match_stereo(img0: np.ndarray, img1: np.ndarray, shift: np.ndarray, max_corners: int = 400):
    """Corners of img0 and their KLT matches in img1 (forward-backward checked)."""
    from vio.frontend.stereo import klt_fb

    p0 = cv2.goodFeaturesToTrack(img0, max_corners, 0.01, 12)
    if p0 is None:
        return np.zeros((0, 2)), np.zeros((0, 2))
    p0 = p0.reshape(-1, 2).astype(np.float64)
    p1, ok = klt_fb(img0, img1, p0, p0 + shift, _KLT, 0.5)
    return p0[ok], p1[ok]


def triangulate(calib: StereoCalibration, uv0: np.ndarray, uv1: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Points (N, 3) in cam0 from raw stereo pixels, and the mask of those in front of both cameras."""
    T = calib.T_cam1_cam0
    x0 = calib.cam0.undistort_normalized(uv0)
    x1 = calib.cam1.undistort_normalized(uv1)
    X = cv2.triangulatePoints(np.hstack([np.eye(3), np.zeros((3, 1))]), T[:3, :4], x0.T, x1.T)
    X = (X[:3] / X[3]).T
    X1 = X @ T[:3, :3].T + T[:3, 3]
    return X, (X[:, 2] > 0) & (X1[:, 2] > 0)
