"""Conversions between raw (distorted) pixels and undistorted pixels of the same K.

We track in the raw image (no remap of every frame) and undistort only the few hundred tracked points; the
back end then sees an ideal pinhole camera with the real K. Both directions go through the camera model in
`vio.calibration` (OpenCV radtan / fisheye), so there is one implementation of each lens model.
"""

from __future__ import annotations

import numpy as np

from vio.calibration import CameraCalibration


def undistort_px(cam: CameraCalibration, uv_raw: np.ndarray) -> np.ndarray:
    """Undistorted pixels (N, 2) of raw pixels (N, 2): normalised coordinates mapped through K again."""
    xy = cam.undistort_normalized(uv_raw)
    return np.column_stack([cam.fx * xy[:, 0] + cam.cx, cam.fy * xy[:, 1] + cam.cy]) if len(xy) else xy


def distort_px(cam: CameraCalibration, uv_undist: np.ndarray) -> np.ndarray:
    """Raw pixels (N, 2) where the undistorted pixels (N, 2) appear in the real image."""
    uv = np.asarray(uv_undist, dtype=np.float64).reshape(-1, 2)
    if len(uv) == 0:
        return np.zeros((0, 2))
    return cam.project(np.column_stack([(uv[:, 0] - cam.cx) / cam.fx, (uv[:, 1] - cam.cy) / cam.fy,
                                        np.ones(len(uv))]))


def bearings(cam: CameraCalibration, uv_undist: np.ndarray) -> np.ndarray:
    """Homogeneous normalised rays (N, 3) with z = 1 of undistorted pixels."""
    uv = np.asarray(uv_undist, dtype=np.float64).reshape(-1, 2)
    return np.column_stack([(uv[:, 0] - cam.cx) / cam.fx, (uv[:, 1] - cam.cy) / cam.fy, np.ones(len(uv))])


def rotate_px(K: np.ndarray, R_cur_prev: np.ndarray, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Apply the infinite homography K R K^-1 to undistorted pixels (N, 2).

    Returns the mapped pixels and a mask of points that stay in front of the camera (a far point seen before a
    pure rotation `R_cur_prev` lands there afterwards).
    """
    H = K @ R_cur_prev @ np.linalg.inv(K)
    uvh = np.column_stack([uv, np.ones(len(uv))]) @ H.T
    ok = uvh[:, 2] > 1e-6
    w = np.where(ok, uvh[:, 2], 1.0)
    return uvh[:, :2] / w[:, None], ok
