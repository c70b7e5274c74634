"""Left-to-right stereo matching and depth for the features of one stereo pair.

Matching is KLT from the left to the right raw image, started where the calibration says the point
appears for a guessed depth (its last depth when the track had one), then checked three ways: forward-
backward KLT consistency, distance from the epipolar line given by T_cam1_cam0, and the triangulated depth
lying in [min_depth_m, max_depth_m] in front of both cameras (which also bounds the disparity).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from vio.calibration import StereoCalibration
from vio.config import FrontendConfig
from vio.frontend.median import median
from vio.frontend.undistort import bearings, undistort_px
from vio.geometry import skew


@dataclass
class StereoResult:
    """Per left feature: right raw pixel, undistorted right pixel and cam0 depth; NaN where rejected."""

    uv1_raw: np.ndarray  # (N, 2)
    uv1: np.ndarray  # (N, 2)
    depth_m: np.ndarray  # (N,)
    n_klt_fail: int = 0
    n_epipolar: int = 0
    n_depth: int = 0


def triangulate_depth(x0: np.ndarray, x1: np.ndarray, R_1_0: np.ndarray, t_1_0: np.ndarray
                      ) -> tuple[np.ndarray, np.ndarray]:
    """Depths (d0, d1) along z of cam0 and cam1 for rays x0, x1 (N, 3, z = 1).

    Least squares of d1 x1 = R_1_0 d0 x0 + t_1_0 (the midpoint method written in the two unknown depths);
    the 2x2 normal equations are solved in closed form for all points at once.
    """
    a = x0 @ R_1_0.T
    b = -x1
    aa, ab, bb = (a * a).sum(1), (a * b).sum(1), (b * b).sum(1)
    ra, rb = -(a @ t_1_0), -(b @ t_1_0)
    det = aa * bb - ab * ab
    det = np.where(np.abs(det) < 1e-12, np.nan, det)
    d0 = (bb * ra - ab * rb) / det
    d1 = (aa * rb - ab * ra) / det
    return d0, d1


def klt_fb(img0: np.ndarray, img1: np.ndarray, p0: np.ndarray, guess: np.ndarray, params: dict,
           fb_max_px: float, backward: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """KLT from img0 to img1 started at `guess`, with the forward-backward check (both (N, 2) pixels).

    Returns the positions in img1 and a mask of points that converged both ways, came back to within
    `fb_max_px` of where they started and lie inside img1. `backward=False` skips the backward pass (half the
    cost) for callers that verify the matches otherwise.
    """
    a = np.ascontiguousarray(p0, dtype=np.float32).reshape(-1, 1, 2)
    b0 = np.ascontiguousarray(guess, dtype=np.float32).reshape(-1, 1, 2)
    b, st, _ = cv2.calcOpticalFlowPyrLK(img0, img1, a, b0, flags=cv2.OPTFLOW_USE_INITIAL_FLOW, **params)
    ok = st.ravel() == 1
    if backward:
        back, st_back, _ = cv2.calcOpticalFlowPyrLK(img1, img0, b, a.copy(), flags=cv2.OPTFLOW_USE_INITIAL_FLOW,
                                                    **params)
        ok &= st_back.ravel() == 1
        ok &= np.linalg.norm(back.reshape(-1, 2) - a.reshape(-1, 2), axis=1) < fb_max_px
    b = b.reshape(-1, 2).astype(np.float64)
    h, w = img1.shape[:2]
    ok &= (b[:, 0] >= 0) & (b[:, 0] <= w - 1) & (b[:, 1] >= 0) & (b[:, 1] <= h - 1)
    return b, ok


class StereoMatcher:
    """Matches left features into the right image of the same stereo pair."""

    default_depth_m = 4.0  # search start when no feature of this frame has a depth yet

    def __init__(self, calib: StereoCalibration, cfg: FrontendConfig) -> None:
        self.calib = calib
        self.cfg = cfg
        T = calib.T_cam1_cam0
        self.R_1_0 = T[:3, :3].copy()
        self.t_1_0 = T[:3, 3].copy()
        self.E = skew(self.t_1_0) @ self.R_1_0  # x1^T E x0 = 0 for normalised rays
        w = cfg.klt_window_px | 1
        crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 30, 0.01)
        # A point with a depth from the last frame starts within a pixel or two of its match: a coarse pyramid
        # only adds chances to lock onto a similar patch elsewhere (seen on EuRoC's floor mats) and costs time.
        self.klt_known = dict(winSize=(w, w), maxLevel=min(1, cfg.klt_pyramid_levels), criteria=crit)
        self.klt_new = dict(winSize=(w, w), maxLevel=min(2, cfg.klt_pyramid_levels), criteria=crit)

    def guess_right(self, uv0: np.ndarray, depth_guess: np.ndarray) -> np.ndarray:
        """Raw right pixels where undistorted left pixels `uv0` appear at depths `depth_guess`."""
        p0 = bearings(self.calib.cam0, uv0) * depth_guess[:, None]
        p1 = p0 @ self.R_1_0.T + self.t_1_0
        p1[:, 2] = np.maximum(p1[:, 2], 1e-3)
        return self.calib.cam1.project(p1)

    def _local_depth(self, uv0: np.ndarray, depth: np.ndarray, w: int, h: int, min_count: int = 3) -> np.ndarray:
        """Per point without depth: median depth of the points with depth in its detection-grid cell (NaN where
        the cell has fewer than `min_count`)."""
        gc, gr = self.cfg.grid_cols, self.cfg.grid_rows
        cell = (np.clip(uv0[:, 1] * gr // h, 0, gr - 1) * gc + np.clip(uv0[:, 0] * gc // w, 0, gc - 1)).astype(int)
        known = np.isfinite(depth)
        out = np.full(len(uv0), np.nan)
        for c in np.unique(cell[~known]):
            d = depth[known & (cell == c)]
            if len(d) >= min_count:
                out[~known & (cell == c)] = median(d)
        return out

    def match(self, left: np.ndarray, right: np.ndarray, uv0_raw: np.ndarray, uv0: np.ndarray,
              depth_guess: np.ndarray, search: np.ndarray | None = None) -> StereoResult:
        """Match raw left pixels `uv0_raw` (undistorted: `uv0`) into `right`; see the module doc.

        `depth_guess` is each track's last depth (NaN when it had none): known depths get a short search.
        `search` (default all) selects the points to match at all; the others stay NaN.
        """
        n = len(uv0_raw)
        out = StereoResult(np.full((n, 2), np.nan), np.full((n, 2), np.nan), np.full(n, np.nan))
        if n == 0:
            return out
        h, w = right.shape[:2]
        known = np.isfinite(depth_guess)
        fallback = median(depth_guess[known]) if known.any() else self.default_depth_m
        # A point without a depth of its own starts at its neighbours' depth, or the frame's median depth: close
        # enough for the short search. Only a frame without any depth yet (start, reset) needs the coarse pyramid;
        # a second KLT call per frame cost a third of the stereo time on EuRoC.
        local = self._local_depth(uv0, depth_guess, w, h)
        start = np.where(known, depth_guess, np.where(np.isfinite(local), local, fallback))
        guess = self.guess_right(uv0, start)
        guess = np.clip(np.nan_to_num(guess, nan=0.0), 0, [w - 1, h - 1])
        p1 = np.zeros((n, 2))
        ok = np.zeros(n, bool)
        sel = np.ones(n, bool) if search is None else search
        if sel.any():
            params = self.klt_known if known.any() else self.klt_new
            p1[sel], ok[sel] = klt_fb(left, right, uv0_raw[sel], guess[sel], params, self.cfg.fb_check_px)
        out.n_klt_fail = int(n - ok.sum())
        idx = np.flatnonzero(ok)
        if len(idx) == 0:
            return out
        cam1 = self.calib.cam1
        uv1 = undistort_px(cam1, p1[idx])
        x0 = bearings(self.calib.cam0, uv0[idx])
        x1 = bearings(cam1, uv1)
        line = x0 @ self.E.T  # epipolar lines in cam1 normalised coordinates
        epi_px = np.abs((x1 * line).sum(1)) / np.hypot(line[:, 0], line[:, 1]) * cam1.fx
        good_epi = epi_px < self.cfg.stereo_max_epipolar_px
        d0, d1 = triangulate_depth(x0, x1, self.R_1_0, self.t_1_0)
        with np.errstate(invalid="ignore"):
            good_depth = (d0 >= self.cfg.min_depth_m) & (d0 <= self.cfg.max_depth_m) & (d1 > 0)
        out.n_epipolar = int((~good_epi).sum())
        out.n_depth = int((good_epi & ~good_depth).sum())
        keep = good_epi & good_depth
        k = idx[keep]
        out.uv1_raw[k] = p1[k]
        out.uv1[k] = uv1[keep]
        out.depth_m[k] = d0[keep]
        return out
