"""Camera-IMU time offset from a recording (`vio calib time-offset`). Convention: t_imu = t_cam + offset.

A tool over the core: this module measures the camera rotations between consecutive frames of a EuRoC
recording (stereo PnP when the right image is there, else KLT tracks with an essential matrix or a pure
rotation fit, vio/relative_pose.py) and hands them with the gyro to the solver in vio/backend/offset_solver.py,
whose module doc explains the method. The solver's names are re-exported here for existing callers.
"""

from __future__ import annotations

import logging
from pathlib import Path

import cv2
import numpy as np

from vio import VioError
from vio.backend.offset_solver import (  # noqa: F401  (re-exported)
    MIN_RATE_STD_RAD_S,
    OUTLIER_MADS,
    OffsetEstimate,
    VisualRotations,
    estimate_time_offset,
)
from vio.calibration import CameraCalibration, StereoCalibration
from vio.geometry import so3_log
from vio.relative_pose import ROTATION_ONLY_PX, rotation_information, solve_pnp  # noqa: F401
from vio.relative_pose import relative_rotation as _relative_rotation

log = logging.getLogger(__name__)

MIN_TRACKS = 15  # frame pairs with fewer surviving tracks are skipped
MAX_DEPTH_M = 60.0  # farther stereo points carry no depth information for PnP
_KLT = {"winSize": (21, 21), "maxLevel": 3,
        "criteria": (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 30, 0.01)}


def relative_rotation(x0: np.ndarray, x1: np.ndarray, f_px: float) -> tuple[np.ndarray, int, np.ndarray] | None:
    """R_c0_c1 from normalised image points x0 (frame 0) and x1 (frame 1); None when unreliable."""
    return _relative_rotation(x0, x1, f_px, MIN_TRACKS)


def stereo_pnp_rotation(calib: StereoCalibration, img0_left: np.ndarray, img0_right: np.ndarray,
                        img1_left: np.ndarray, f_px: float, max_corners: int = 300) -> tuple[np.ndarray, int] | None:
    """R_c0_c1 of cam0 between two frames from stereo-triangulated points of frame 0 seen in frame 1 (PnP).

    Metric 3D points remove the rotation/translation ambiguity that an essential matrix has with a
    narrow field of view (a sideways step looks much like a pan)."""
    from calib.stereo_match import _expected_shift_px, match_stereo, triangulate
    from vio.frontend.stereo import klt_fb

    uv0, uv0r = match_stereo(img0_left, img0_right, _expected_shift_px(calib), max_corners)
    if len(uv0) < MIN_TRACKS:
        return None
    X, front = triangulate(calib, uv0, uv0r)
    keep = front & (X[:, 2] < MAX_DEPTH_M)
    if keep.sum() < MIN_TRACKS:
        return None
    uv1, ok = klt_fb(img0_left, img1_left, uv0[keep], uv0[keep], _KLT, 0.5)
    if ok.sum() < MIN_TRACKS:
        return None
    X, x1 = X[keep][ok], calib.cam0.undistort_normalized(uv1[ok])
    pose = solve_pnp(X, x1, np.eye(3), min_inliers=MIN_TRACKS, iterations=200, reprojection_error=2.0 / f_px,
                     confidence=0.999)
    if pose is None:
        return None
    info = rotation_information(X, pose, np.eye(3))
    if info is None:
        return None
    return pose.R_prev_cur, pose.n_inliers, info


def visual_rotations(dataset, cam: CameraCalibration, step: int = 1, max_corners: int = 300,
                     t_start_ns: int | None = None, t_end_ns: int | None = None) -> VisualRotations:
    """Rotations of cam0 between frames k and k+step of a EurocDataset: stereo PnP when the right image is
    there, else from the left images alone (essential matrix or pure rotation)."""
    from calib.stereo_match import normalise_contrast
    from vio.frontend.stereo import klt_fb
    from vio.types import StereoFrame

    calib = dataset.calibration
    t0s, t1s, thetas, ns, infos = [], [], [], [], []
    prev = None
    for k in range(0, len(dataset), step):
        t = int(dataset.frame_t[k])
        if (t_start_ns is not None and t < t_start_ns) or (t_end_ns is not None and t > t_end_ns):
            continue
        frame = dataset.frame(k)
        if frame is None:
            prev = None
            continue
        frame = StereoFrame(frame.t_ns, normalise_contrast(frame.left),
                            None if frame.right is None else normalise_contrast(frame.right), frame.seq)
        if prev is not None:
            res = None
            if prev.right is not None:
                res = stereo_pnp_rotation(calib, prev.left, prev.right, frame.left, cam.fx, max_corners)
            if res is None:
                p0 = cv2.goodFeaturesToTrack(prev.left, max_corners, 0.01, 10)
                if p0 is not None and len(p0) >= MIN_TRACKS:
                    p0 = p0.reshape(-1, 2).astype(np.float64)
                    p1, ok = klt_fb(prev.left, frame.left, p0, p0, _KLT, 0.5)
                    if ok.sum() >= MIN_TRACKS:
                        res = relative_rotation(cam.undistort_normalized(p0[ok]),
                                                cam.undistort_normalized(p1[ok]), cam.fx)
            if res is not None:
                t0s.append(prev.t_ns)
                t1s.append(t)
                thetas.append(so3_log(res[0]))
                ns.append(res[1])
                infos.append(res[2])
        prev = frame
    if len(t0s) < 10:
        # images that could not be read were said as "too little texture?" (a review's finding)
        stats = getattr(dataset, "stats", None)
        bad = stats.missing_images + stats.unreadable_images if stats is not None else 0
        why = f"{bad} of {len(dataset)} frames' images missing or unreadable (warned above)" if bad else \
            "too little texture?"
        raise VioError(f"only {len(t0s)} usable frame pairs for the time offset (need 10); {why}")
    return VisualRotations(np.array(t0s, np.int64), np.array(t1s, np.int64), np.array(thetas), np.array(ns),
                           np.array(infos))


def estimate_time_offset_dataset(path: str | Path, calibration_path: str | Path | None = None,
                                 max_offset_s: float = 0.1) -> OffsetEstimate:
    """Open a EuRoC recording, measure the visual rotations of cam0 and estimate the offset."""
    from vio.calibration import load_calibration
    from vio.io.euroc import EurocDataset

    calib = load_calibration(calibration_path) if calibration_path else None
    ds = EurocDataset(path, calibration=calib, require_cam1=False)
    cam = ds.calibration.cam0
    vis = visual_rotations(ds, cam)
    est = estimate_time_offset(vis, ds.imu.t_ns, ds.imu.gyro, cam.T_body_cam, max_offset_s=max_offset_s)
    est.calibration_offset_s = ds.calibration.time_offset_ns * 1e-9  # what the summary compares it with
    log.info("time offset %+.2f ms +- %.2f ms from %d pairs (%d more rejected as outliers)", est.offset_s * 1e3,
             est.sigma_s * 1e3, est.n_pairs, est.n_outliers)
    return est


def plot_time_offset(est: OffsetEstimate, path: str | Path) -> None:
    from vio.extras import pyplot

    plt = pyplot("the time-offset plot")

    fig, (a, b) = plt.subplots(2, 1, figsize=(10, 7))
    a.plot(est.t_mid_s, est.vis_rate, ".-", ms=3, lw=0.7, label="camera |rotation| / dt")
    a.plot(est.t_mid_s, est.gyro_rate, lw=0.9, label=f"gyro (bias removed) at offset {est.offset_s * 1e3:+.2f} ms")
    a.set_xlabel("camera time [s]")
    a.set_ylabel("rotation rate [rad/s]")
    a.legend()
    a.grid(True, lw=0.3)
    b.plot(est.grid_s * 1e3, est.cost)
    b.axvline(est.offset_s * 1e3, color="r", lw=0.8)
    b.set_xlabel("offset [ms] (t_imu = t_cam + offset)")
    b.set_ylabel("cost J [rad^2]")
    b.grid(True, lw=0.3)
    from vio.evaluation import save_figure

    save_figure(plt, fig, path)  # under exactly the name given
