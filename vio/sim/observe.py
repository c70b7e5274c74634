"""Perfect feature observations of scene points: what an ideal front end would report (back-end tests)."""

from __future__ import annotations

import numpy as np

from vio.calibration import CameraCalibration, StereoCalibration
from vio.geometry import inv_T, transform_points
from vio.sim.scene import Scene
from vio.types import FeatureFrame


def project_visible(scene: Scene, cam: CameraCalibration, T_world_cam: np.ndarray, points_world: np.ndarray,
                    min_depth_m: float = 0.1) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Distorted pixels (N, 2), visibility (N,) and camera-frame points (N, 3) of world points.

    Visible = in front of the camera, inside the image and not hidden by any surface (a ray cast from the
    camera centre must not stop more than 0.01 % of the range before the point)."""
    P = np.asarray(points_world, dtype=float).reshape(-1, 3)
    p_cam = transform_points(inv_T(T_world_cam), P)
    uv = np.full((len(P), 2), np.nan)
    vis = p_cam[:, 2] > min_depth_m
    if vis.any():
        uv[vis] = cam.project(p_cam[vis])
        vis &= (uv[:, 0] >= 0) & (uv[:, 0] <= cam.width - 1) & (uv[:, 1] >= 0) & (uv[:, 1] <= cam.height - 1)
    if vis.any():
        o = T_world_cam[:3, 3]
        d = (P[vis] - o).T
        t, _ = scene.cast(o, (d[0], d[1], d[2]))
        idx = np.flatnonzero(vis)
        vis[idx[t < 1.0 - 1e-4]] = False
    return uv, vis, p_cam


def observe(scene: Scene, calib: StereoCalibration, T_world_body: np.ndarray, points_world: np.ndarray,
            ids: np.ndarray | None = None, t_ns: int = 0) -> FeatureFrame:
    """FeatureFrame with exact observations of the points visible in cam0 (front-end contract: undistorted
    pixels with each camera's K; uv1/depth NaN where cam1 cannot see the point)."""
    P = np.asarray(points_world, dtype=float).reshape(-1, 3)
    ids = np.arange(len(P), dtype=np.int64) if ids is None else np.asarray(ids, dtype=np.int64)
    _, vis0, p0 = project_visible(scene, calib.cam0, T_world_body @ calib.cam0.T_body_cam, P)
    _, vis1, p1 = project_visible(scene, calib.cam1, T_world_body @ calib.cam1.T_body_cam, P)
    p0, p1, both = p0[vis0], p1[vis0], vis1[vis0]
    uv0 = (p0[:, :2] / p0[:, 2:]) @ calib.cam0.K[:2, :2].T + calib.cam0.K[:2, 2]
    uv1 = np.full_like(uv0, np.nan)
    uv1[both] = (p1[both, :2] / p1[both, 2:]) @ calib.cam1.K[:2, :2].T + calib.cam1.K[:2, 2]
    depth = np.where(both, p0[:, 2], np.nan)
    n = len(p0)
    return FeatureFrame(int(t_ns), ids[vis0], uv0, uv1, depth, np.ones(n, np.int64))
