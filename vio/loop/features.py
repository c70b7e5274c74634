"""Keyframe descriptors: upright ORB (BRIEF at angle 0: a drone's camera hardly rolls about its axis) at the
front end's stereo points (which carry depth: the 3D landmarks for PnP) and at detected ORB corners."""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from vio.calibration import CameraCalibration
from vio.frontend.undistort import distort_px, undistort_px
from vio.types import FeatureFrame


@dataclass(frozen=True)
class KeyframeFeatures:
    desc: np.ndarray  # (N, 32) uint8
    uv: np.ndarray  # (N, 2) undistorted pixels in cam0
    p_cam: np.ndarray  # (N, 3) points in cam0 [m], NaN where no stereo depth

    @property
    def n_3d(self) -> int:
        return int(np.count_nonzero(np.isfinite(self.p_cam[:, 0])))

    @property
    def nbytes(self) -> int:
        return self.desc.nbytes + self.uv.astype(np.float32).nbytes + self.p_cam.astype(np.float32).nbytes


class FeatureExtractor:
    def __init__(self, cam: CameraCalibration, n_features: int = 300) -> None:
        self.cam = cam
        self.orb = cv2.ORB_create(nfeatures=n_features, scaleFactor=1.2, nlevels=4, edgeThreshold=19, patchSize=19,
                                  fastThreshold=12)

    def extract(self, image: np.ndarray, ff: FeatureFrame | None) -> KeyframeFeatures:
        det = self.orb.detect(image, None)
        uv_det = cv2.KeyPoint.convert(det).reshape(-1, 2) if det else np.zeros((0, 2), np.float32)
        p3 = np.full((len(uv_det), 3), np.nan)
        uv_all = uv_det
        if ff is not None and len(ff.ids):
            ok = np.isfinite(ff.depth_m)
            z = ff.depth_m[ok]
            xyz = np.column_stack([(ff.uv0[ok, 0] - self.cam.cx) / self.cam.fx * z,
                                   (ff.uv0[ok, 1] - self.cam.cy) / self.cam.fy * z, z])
            uv_all = np.vstack([uv_det, distort_px(self.cam, ff.uv0[ok]).astype(np.float32)])
            p3 = np.vstack([p3, xyz])
        # upright descriptors (angle 0; detected corners keep their pyramid level); class_id carries the row
        # through compute(), which drops points near the border
        for i, kp in enumerate(det):
            kp.angle = 0.0
            kp.class_id = i
        n = len(det)
        kps = list(det) + [cv2.KeyPoint(u, v, 19.0, 0.0, 0.0, 0, n + i)
                           for i, (u, v) in enumerate(uv_all[n:].tolist())]
        kps, desc = self.orb.compute(image, kps)
        if desc is None or not kps:
            return KeyframeFeatures(np.zeros((0, 32), np.uint8), np.zeros((0, 2)), np.zeros((0, 3)))
        keep = np.array([kp.class_id for kp in kps], np.int64)
        uv_raw = uv_all[keep].astype(np.float64)
        return KeyframeFeatures(desc, undistort_px(self.cam, uv_raw), p3[keep].reshape(-1, 3))
