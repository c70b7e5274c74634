"""Front-end quality figures: per-frame counts and track statistics on any dataset, and errors against the
exact truth of a simulated flight (`vio simulate` writes `simulation.yaml`, from which the scene and
trajectory are rebuilt: true depth comes from ray casting the scene at each feature's raw pixel).

An observation is an outlier when it lies more than OUTLIER_PX from where the true motion moves the track's
first 3D point (true depth at the first observation, true camera poses after it). The figures are also split by
where a track was born: within EDGE_PX of a depth discontinuity (a corner there may be a T-junction of two
surfaces, and the true depth of a pixel-accurate corner is ambiguous) or clear of it.
"""

from __future__ import annotations

from collections import defaultdict
from pathlib import Path

import cv2
import numpy as np

from vio.calibration import StereoCalibration
from vio.frontend.undistort import bearings, distort_px
from vio.geometry import inv_T
from vio.types import FeatureFrame

OUTLIER_PX = 2.0
NEAR_M = 5.0  # depth errors are reported for points closer than this
EDGE_PX = 3.0  # tracks born this close to a depth discontinuity (> 3 % jump between neighbours) are "edge-born"


def track_stats(ffs: list[FeatureFrame]) -> dict:
    """Counts per frame, track lengths (final length of every track) and frame-to-frame survival."""
    ok = [f for f in ffs if f.tracking_ok]
    final_len: dict[int, int] = {}
    survival = []
    prev_ids = None
    for f in ok:
        for i, n in zip(f.ids.tolist(), f.track_len.tolist()):
            final_len[i] = n
        if prev_ids is not None and len(prev_ids):
            survival.append(np.isin(prev_ids, f.ids).mean())
        prev_ids = f.ids
    lens = np.array(list(final_len.values())) if final_len else np.zeros(1)
    feats = np.array([len(f.ids) for f in ok]) if ok else np.zeros(1)
    stereo = np.array([f.n_stereo for f in ok]) if ok else np.zeros(1)
    return {
        "frames": len(ffs), "frames_not_ok": len(ffs) - len(ok),
        "features_per_frame_median": float(np.median(feats)), "features_per_frame_min": int(feats.min()),
        "stereo_per_frame_mean": float(stereo.mean()), "stereo_per_frame_median": float(np.median(stereo)),
        "stereo_per_frame_min": int(stereo.min()),
        "tracks": len(final_len), "track_length_median": float(np.median(lens)),
        "track_length_mean": float(lens.mean()),
        "survival_frame_to_frame": float(np.mean(survival)) if survival else float("nan"),
    }


class SimTruth:
    """Exact truth of a `vio simulate` dataset: camera poses and depth images at the frame times."""

    def __init__(self, dataset_root: str | Path, calib: StereoCalibration) -> None:
        import yaml

        from vio.sim.generate import SimConfig, build
        from vio.sim.render import CameraRenderer

        cfg = yaml.safe_load((Path(dataset_root) / "simulation.yaml").read_text())
        self.sim = build(SimConfig(**cfg))
        self.calib = calib
        self.renderer = CameraRenderer(calib.cam0, self.sim.scene)

    def pose_and_depth(self, t_cam_ns: int) -> tuple[np.ndarray, np.ndarray]:
        """T_world_cam0 and cam0's depth image for the frame stamped t_cam_ns (camera clock)."""
        from vio.sim.generate import T0_NS

        t_s = (t_cam_ns + self.calib.time_offset_ns - T0_NS) * 1e-9
        T_wc = self.sim.motion.pose(np.array([t_s]))[0] @ self.calib.cam0.T_body_cam
        _, depth, _ = self.renderer.render(T_wc)
        return T_wc, depth


def _depth_at(depth_img: np.ndarray, uv_raw: np.ndarray) -> np.ndarray:
    """Depth at raw pixels; NaN on depth edges (3x3 neighbourhood spans > 2 %) where the truth is ambiguous."""
    h, w = depth_img.shape
    x = np.clip(np.round(uv_raw[:, 0]).astype(int), 1, w - 2)
    y = np.clip(np.round(uv_raw[:, 1]).astype(int), 1, h - 2)
    patch = np.stack([depth_img[y + dy, x + dx] for dy in (-1, 0, 1) for dx in (-1, 0, 1)])
    d = depth_img[y, x].astype(float)
    edge = (patch.max(0) - patch.min(0)) > 0.02 * d
    # inverse depth is affine in the image over a plane: interpolate it at the exact (sub-pixel) position, as
    # the nearest pixel's depth was off by up to ~1 % on slanted walls, which later frames see as parallax
    inv = cv2.remap((1.0 / np.maximum(depth_img, 1e-6)).astype(np.float32),
                    uv_raw[:, :1].astype(np.float32), uv_raw[:, 1:2].astype(np.float32), cv2.INTER_LINEAR)
    return np.where(edge, np.nan, 1.0 / inv.ravel().astype(float))


def _edge_distance(depth_img: np.ndarray, uv_raw: np.ndarray) -> np.ndarray:
    """Distance [px] of raw pixels from the nearest depth discontinuity (neighbours differing by > 3 %)."""
    jump = np.zeros(depth_img.shape, bool)
    jump[:, 1:] |= np.abs(np.diff(depth_img, axis=1)) > 0.03 * depth_img[:, 1:]
    jump[1:, :] |= np.abs(np.diff(depth_img, axis=0)) > 0.03 * depth_img[1:, :]
    dist = cv2.distanceTransform((~jump).astype(np.uint8), cv2.DIST_L2, 3)
    h, w = depth_img.shape
    x = np.clip(np.round(uv_raw[:, 0]).astype(int), 0, w - 1)
    y = np.clip(np.round(uv_raw[:, 1]).astype(int), 0, h - 1)
    return dist[y, x]


def truth_errors(ffs: list[FeatureFrame], truth: SimTruth) -> dict:
    """Stereo depth error and outlier rate of the tracks against the simulation's truth."""
    calib = truth.calib
    cam0 = calib.cam0
    first: dict[int, np.ndarray] = {}  # track id -> true world point of its first observation
    edge_born: set[int] = set()
    rel_err, obs_err, obs_edge = [], [], []
    bad_tracks: set[int] = set()
    seen: set[int] = set()
    for f in ffs:
        if not f.tracking_ok or len(f.ids) == 0:
            continue
        T_wc, depth_img = truth.pose_and_depth(f.t_ns)
        raw = distort_px(cam0, f.uv0)
        d_true = _depth_at(depth_img, raw)
        rays = bearings(cam0, f.uv0)
        st = np.isfinite(f.depth_m) & np.isfinite(d_true) & (d_true < NEAR_M)
        rel_err.extend((np.abs(f.depth_m[st] - d_true[st]) / d_true[st]).tolist())
        T_cw = inv_T(T_wc)
        born = (f.track_len == 1) & np.isfinite(d_true)
        near_edge = np.zeros(len(f.ids), bool)
        if born.any():
            near_edge[born] = _edge_distance(depth_img, raw[born]) < EDGE_PX
        for k, tid in enumerate(f.ids.tolist()):
            if tid not in first:
                if born[k]:
                    first[tid] = T_wc[:3, :3] @ (rays[k] * d_true[k]) + T_wc[:3, 3]
                    if near_edge[k]:
                        edge_born.add(tid)
                continue
            p = T_cw[:3, :3] @ first[tid] + T_cw[:3, 3]
            if p[2] <= 0.05:
                continue
            uv = p[:2] / p[2] * [cam0.fx, cam0.fy] + [cam0.cx, cam0.cy]
            e = float(np.linalg.norm(uv - f.uv0[k]))
            obs_err.append(e)
            obs_edge.append(tid in edge_born)
            seen.add(tid)
            if e > OUTLIER_PX:
                bad_tracks.add(tid)
    rel = np.array(rel_err) if rel_err else np.full(1, np.nan)
    obs = np.array(obs_err) if obs_err else np.full(1, np.nan)
    edge = np.array(obs_edge, bool) if obs_err else np.zeros(1, bool)
    return {
        "depth_rel_error_median_within_5m": float(np.median(rel)),
        "depth_rel_error_p90_within_5m": float(np.percentile(rel, 90)),
        "depth_samples": len(rel_err),
        "reprojection_error_median_px": float(np.median(obs)),
        "reprojection_error_p90_px": float(np.percentile(obs, 90)),
        "outlier_observations_fraction": float(np.mean(obs > OUTLIER_PX)),
        "outlier_tracks_fraction": len(bad_tracks) / max(len(seen), 1),
        "edge_born_observations_fraction": float(edge.mean()),
        "outlier_observations_fraction_edge_born": float(np.mean(obs[edge] > OUTLIER_PX)) if edge.any() else 0.0,
        "outlier_observations_fraction_clear": float(np.mean(obs[~edge] > OUTLIER_PX)) if (~edge).any() else 0.0,
        "tracks_checked": len(seen),
    }


def stage_timings(ffs: list[FeatureFrame]) -> dict[str, dict[str, float]]:
    """mean / p50 / p99 [ms] of each front-end stage over the frames that were tracked."""
    per: dict[str, list[float]] = defaultdict(list)
    for f in ffs:
        for k, v in f.timings_ms.items():
            per[k].append(v)
    return {k: {"mean": float(np.mean(v)), "p50": float(np.percentile(v, 50)), "p99": float(np.percentile(v, 99))}
            for k, v in per.items()}
