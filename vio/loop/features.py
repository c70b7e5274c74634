"""Keyframe descriptors: upright ORB (BRIEF at angle 0: a drone's camera hardly rolls about its axis) at the
front end's stereo points (which carry depth: the 3D landmarks for PnP) and at FAST corners spread over the
image on a grid.

By default the corners are found at full resolution only: on the simulator's flights at 752x480 and 376x240
this closes as many loops as ORB's 4-level pyramid did, 1.8x faster (docs/loop-closure.md, "Cheaper
detection"). `levels` > 1 adds pyramid levels, for maps revisited from other distances."""

from __future__ import annotations

import threading
from dataclasses import dataclass
from functools import cached_property
from itertools import compress, repeat
from operator import attrgetter

import cv2
import numpy as np

from vio.calibration import CameraCalibration
from vio.frontend.undistort import distort_px, undistort_px
from vio.types import FeatureFrame

PATCH = 19  # BRIEF patch size [px]; corners closer than BORDER to the image edge cannot be described
BORDER = 20
GRID = (8, 6)  # cells across, down: each gets its share of the corners before the strongest rest


@dataclass(frozen=True)
class KeyframeFeatures:
    desc: np.ndarray  # (N, 32) uint8
    uv: np.ndarray  # (N, 2) undistorted pixels in cam0
    p_cam: np.ndarray  # (N, 3) points in cam0 [m], NaN where no stereo depth

    @property
    def n_3d(self) -> int:
        return len(self.landmark_rows)

    # Verification asks these of a keyframe for every candidate it takes part in (as the new keyframe, then as an
    # old one for later keyframes): kept once computed (the arrays are never changed in place), 4-5 KB a keyframe
    # of int64 indices (counted in `nbytes`); the rows they pick are gathered again per call (caching those copies
    # too, ~20 KB a keyframe, saved only ~0.01 ms a keyframe more).
    @cached_property
    def landmark_rows(self) -> np.ndarray:
        """Rows with a stereo point (finite p_cam), ascending."""
        return np.flatnonzero(np.isfinite(self.p_cam[:, 0]))

    @cached_property
    def x_order(self) -> np.ndarray:
        """The rows sorted by pixel x (stably: equal x by row)."""
        return np.argsort(self.uv[:, 0], kind="stable")

    @property
    def by_x(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """`x_order`, and the rows' x and y in that order, for searches by position."""
        order = self.x_order
        return order, self.uv[order, 0], self.uv[order, 1]

    @property
    def nbytes(self) -> int:
        return self.desc.nbytes + self.uv.astype(np.float32).nbytes + self.p_cam.astype(np.float32).nbytes + \
            sum(self.__dict__[k].nbytes for k in ("landmark_rows", "x_order") if k in self.__dict__)


def spread_corners(uv: np.ndarray, response: np.ndarray, shape: tuple[int, int], n: int) -> np.ndarray:
    """Indices of at most n corners: the strongest n // cells in each grid cell first (texture anywhere in the
    view counts for retrieval, not only the busiest patch), then the strongest of the rest."""
    h, w = shape
    cx, cy = GRID
    cell = np.minimum((uv[:, 1] * cy / h).astype(np.int64), cy - 1) * cx + \
        np.minimum((uv[:, 0] * cx / w).astype(np.int64), cx - 1)
    # by cell, strongest first within it, ties in input order: one stable sort on a key that holds both (a
    # FAST response is an integer threshold below 256; any response below 2**20 keeps the cells apart)
    weak = _weakness(response) if cx * cy <= 256 else None
    if weak is not None:  # FAST's: the same order from a 16-bit key, which numpy sorts by radix (half the time)
        order = np.argsort((cell.astype(np.uint16) << 8) | weak, kind="stable")
    else:
        order = np.argsort(cell * float(1 << 20) - response, kind="stable")
    count = np.bincount(cell, minlength=cx * cy)
    # position within its cell, strongest first (the sorted corners come cell by cell)
    rank = np.arange(len(order)) - np.repeat(np.cumsum(count) - count, count)
    take = rank < max(1, n // (cx * cy))
    first, rest = order[take], order[~take]
    rest = rest[np.argsort(-response[rest] if weak is None else weak[rest], kind="stable")][:max(0, n - len(first))]
    return np.concatenate([first, rest])[:n]


def _weakness(response: np.ndarray) -> np.ndarray | None:
    """255 - response as uint16 when every response is an integer in [0, 255] (FAST's are), else None: sorting it
    ascending, stably, is sorting -response (cells below 256 fit beside it in one 16-bit key)."""
    if not len(response) or response.min() < 0 or response.max() > 255:
        return None
    r = response.astype(np.uint16)
    if not np.array_equal(r, response):
        return None
    return 255 - r


def same_pixel(uv: np.ndarray, ref: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """(N,) bool: does uv round to the pixel of a point of ref (points outside the image clamped to its edge)?"""
    h, w = shape

    def key(p: np.ndarray) -> np.ndarray:
        return np.clip(np.rint(p[:, 1]), 0, h).astype(np.int64) * (w + 1) + \
            np.clip(np.rint(p[:, 0]), 0, w).astype(np.int64)
    taken = np.zeros((h + 1) * (w + 1), bool)  # a pixel table: cheaper than np.isin's sort for an image's points
    taken[key(ref)] = True
    return taken[key(uv)]


def _points(kps: list) -> tuple[np.ndarray, np.ndarray]:
    """(N, 2) float32 pixels and (N,) responses of OpenCV keypoints."""
    if not kps:
        return np.zeros((0, 2), np.float32), np.zeros(0)
    return (cv2.KeyPoint.convert(kps).reshape(-1, 2),
            np.fromiter(map(attrgetter("response"), kps), np.float64, len(kps)))


def upright_keypoints(uv: np.ndarray, size: float) -> list:
    """`cv2.KeyPoint.convert(uv, size)`'s keypoints (angle -1, response 1, level 0, class_id -1) made one by one
    through `map`: the same keypoints in 30 % less time (the binding's convert costs ~0.4 us a point; 23 us for a
    keyframe's ~190 stereo points on the shelves flight)."""
    n = len(uv)
    return list(map(cv2.KeyPoint, uv[:, 0].tolist(), uv[:, 1].tolist(), repeat(float(size), n), repeat(-1.0, n),
                    repeat(1.0, n)))


_PIXEL_TABLES: dict[tuple, np.ndarray] = {}
# the newest cameras' tables kept: a process that makes loop stages for many calibrations (a `vio batch` worker
# over a calib_error sweep, a test session) kept every one, 5.8 MB each at 752x480 and 16 MB at 1280x800
PIXEL_TABLES_KEPT = 4
_PIXEL_TABLES_LOCK = threading.Lock()


def pixel_table(cam: CameraCalibration) -> np.ndarray:
    """(height * width, 2) undistorted pixels of every integer pixel of the camera's image (row y * width + x).

    FAST's corners lie on integer pixels, and OpenCV undistorts each point on its own (the same iterations for one
    as for a batch), so a corner's row of this table is exactly what undistort_px gives it: ~0.1 ms a keyframe
    saved on the simulator's 752x480 for 0.11 s and 5.8 MB once per camera (kept for the process: a second loop
    stage with the same camera, as the benches and tests make, shares it; the newest PIXEL_TABLES_KEPT cameras')."""
    key = (cam.distortion_model, cam.width, cam.height, cam.fx, cam.fy, cam.cx, cam.cy,
           tuple(np.asarray(cam.dist_coeffs, float).ravel().tolist()))
    with _PIXEL_TABLES_LOCK:  # loop stages in two threads (a daemon's, a test's) must not evict under each other
        table = _PIXEL_TABLES.pop(key, None)
        if table is None:
            y, x = np.divmod(np.arange(cam.width * cam.height), cam.width)
            table = undistort_px(cam, np.column_stack([x, y]).astype(np.float64))
        _PIXEL_TABLES[key] = table  # the newest last
        while len(_PIXEL_TABLES) > PIXEL_TABLES_KEPT:
            del _PIXEL_TABLES[next(iter(_PIXEL_TABLES))]
    return table


class FeatureExtractor:
    def __init__(self, cam: CameraCalibration, n_features: int = 300, fast_threshold: int = 16, levels: int = 1,
                 level_scale: float = 1.2) -> None:
        self.cam = cam
        self.levels, self.level_scale = levels, level_scale
        # corners per level as ORB shares them: each level 1 / level_scale of the one above
        share = level_scale ** -np.arange(levels)
        self.n_level = np.maximum(1, np.round(n_features * share / share.sum())).astype(int)
        self.fast_threshold = fast_threshold
        self.fast = cv2.FastFeatureDetector_create(fast_threshold, True)
        self.fast_dim = cv2.FastFeatureDetector_create(max(1, fast_threshold // 2), True)
        self._dim = [False] * levels  # per level: did the last image need the dim threshold?
        self.slow_describes = 0  # single-level descriptions whose kept rows were not as predicted
        self.orb = cv2.ORB_create(nfeatures=n_features, scaleFactor=level_scale, nlevels=levels,
                                  edgeThreshold=PATCH, patchSize=PATCH)
        self._pixels = pixel_table(cam) if levels == 1 else None  # a pyramid's corners are not on integer pixels

    def _level_corners(self, image: np.ndarray, n: int, lev: int = 0) -> tuple[np.ndarray, list]:
        """The level's corners as (M, 2) pixels and FAST's keypoints of them."""
        h, w = image.shape[:2]
        kps, uv, response = self._fast(image, n, lev)
        inside = np.flatnonzero((uv[:, 0] >= BORDER) & (uv[:, 0] < w - BORDER) &
                                (uv[:, 1] >= BORDER) & (uv[:, 1] < h - BORDER))
        pick = inside[spread_corners(uv[inside], response[inside], (h, w), n)]
        return uv[pick], [kps[i] for i in pick.tolist()]

    def _fast(self, image: np.ndarray, n: int, lev: int) -> tuple[tuple, np.ndarray, np.ndarray]:
        """FAST corners at the threshold, or at half of it when that finds fewer than 2n: their keypoints, (N, 2)
        pixels and responses.

        A FAST response is the largest threshold at which the point is still a corner, and non-maximum
        suppression compares responses, so the corners at the threshold are exactly those at half of it whose
        response reaches the threshold. Images come in runs (a dim hall stays dim), so after an image that
        needed the half threshold the next is searched at half first and its strong corners picked from that:
        one FAST pass instead of two, the same corners."""
        if self._dim[lev]:
            kps = self.fast_dim.detect(image, None)
            uv, response = _points(kps)
            strong = response >= self.fast_threshold
            if np.count_nonzero(strong) < 2 * n:
                return kps, uv, response
            self._dim[lev] = False
            return tuple(compress(kps, strong.tolist())), uv[strong], response[strong]
        kps = self.fast.detect(image, None)
        if len(kps) < 2 * n:
            kps = self.fast_dim.detect(image, None)
            self._dim[lev] = True
        return (kps, *_points(kps))

    def corners(self, image: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """FAST corners at least BORDER px inside each pyramid level, spread by `spread_corners`, as (M, 2)
        pixels of the full image and (M,) level; a dim or blurred level that gives fewer than twice its share
        is searched again at half the threshold."""
        uv, octave, _ = self._corners(image)
        return uv, octave

    def _corners(self, image: np.ndarray) -> tuple[np.ndarray, np.ndarray, list | None]:
        """`corners`, and on one level (the default) FAST's own keypoints of them, for the description."""
        h, w = image.shape[:2]
        uv, octave = [], []
        kps = None
        for lev, n in enumerate(self.n_level):
            scale = self.level_scale ** lev
            img = image if lev == 0 else cv2.resize(image, (round(w / scale), round(h / scale)),
                                                    interpolation=cv2.INTER_LINEAR)
            c, kps = self._level_corners(img, int(n), lev)
            uv.append(c * np.float32(scale))
            octave.append(np.full(len(c), lev, np.int64))
        return np.vstack(uv), np.concatenate(octave), kps if self.levels == 1 else None

    def extract(self, image: np.ndarray, ff: FeatureFrame | None) -> KeyframeFeatures:
        uv_all, octave, corner_kps = self._corners(image)
        uv0 = np.zeros((0, 2))  # the stereo points' undistorted pixels, as the front end gave them
        xyz = np.zeros((0, 3))  # and their 3D points
        if ff is not None and len(ff.ids):
            ok = np.isfinite(ff.depth_m)
            z = ff.depth_m[ok]
            uv0 = ff.uv0[ok]
            xyz = np.column_stack([(uv0[:, 0] - self.cam.cx) / self.cam.fx * z,
                                   (uv0[:, 1] - self.cam.cy) / self.cam.fy * z, z])
            uv_st = distort_px(self.cam, uv0).astype(np.float32)
            if len(uv_st) and len(uv_all):
                # a corner on a stereo point would be its twin descriptor and fail every match's ratio test
                apart = ~(same_pixel(uv_all, uv_st, image.shape[:2]) & (octave == 0))
                uv_all, octave = uv_all[apart], octave[apart]
                if corner_kps is not None:
                    corner_kps = list(compress(corner_kps, apart.tolist()))
            uv_all = np.vstack([uv_all, uv_st])
            octave = np.concatenate([octave, np.zeros(len(uv_st), np.int64)])
        uv_all = uv_all.astype(np.float32, copy=False)
        described = self._describe(image, uv_all, octave, corner_kps)
        if described is None:
            return KeyframeFeatures(np.zeros((0, 32), np.uint8), np.zeros((0, 2)), np.zeros((0, 3)))
        desc, keep = described
        # corners undistorted here; a stereo point keeps the front end's own undistorted pixel (undistorting
        # the pixel it was distorted to for the description gives it back within 1e-9 px, at a cost)
        # (a corner has no 3D point: NaN)
        n_corners = len(uv_all) - len(uv0)
        uv, p3 = np.empty((len(keep), 2)), np.empty((len(keep), 3))
        if self.levels == 1:
            # on one level every point is on level 0, so compute() keeps them in order: `keep` ascends and, the
            # corners coming first, its first k rows are the corners kept (slices instead of boolean masks)
            k = int(keep.searchsorted(n_corners))
            uv[:k] = self._undistort_corners(uv_all[keep[:k]], image.shape[:2])
            uv[k:] = uv0[keep[k:] - n_corners]
            p3[:k] = np.nan
            p3[k:] = xyz[keep[k:] - n_corners]
        else:  # compute() regroups a pyramid's points by level: the stereo points (level 0) among the corners
            corner = keep < n_corners
            uv[corner] = self._undistort_corners(uv_all[keep[corner]], image.shape[:2])
            uv[~corner] = uv0[keep[~corner] - n_corners]
            p3[corner] = np.nan
            p3[~corner] = xyz[keep[~corner] - n_corners]
        return KeyframeFeatures(desc, uv, p3)

    def _undistort_corners(self, uv: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
        """undistort_px of the corners: looked up in `pixel_table` when they are integer pixels of an image of the
        camera's size (FAST's, on one level)."""
        if self._pixels is not None and shape == (self.cam.height, self.cam.width) and len(uv):
            x, y = uv[:, 0].astype(np.int64), uv[:, 1].astype(np.int64)
            if np.array_equal(x, uv[:, 0]) and np.array_equal(y, uv[:, 1]) and x.min() >= 0 and y.min() >= 0 \
                    and x.max() < shape[1] and y.max() < shape[0]:
                return self._pixels[y * shape[1] + x]
        return undistort_px(self.cam, uv.astype(np.float64))

    def _describe(self, image: np.ndarray, uv: np.ndarray, octave: np.ndarray,
                  corner_kps: list | None = None) -> tuple[np.ndarray, np.ndarray] | None:
        """Upright descriptors of the points, and the rows they belong to (compute() drops points too near the
        border); None when none is left.

        On one level (the default) the keypoints are made in one call, which sets their angle to -1 deg instead
        of 0: BRIEF samples the pixel each rotated pattern point rounds to, and for integer pattern points within
        PATCH / 2 of the centre a 1 deg rotation moves none by more than 0.16 px, so the descriptors are the same.
        The rows kept are predicted from ORB's border rule (the pixel a point rounds to at least PATCH from the
        edge) and checked against the points compute() returns. Making a KeyPoint per point in Python, with its
        row in class_id, cost ~0.3 ms a keyframe; it remains for pyramid levels and when the check fails.

        `corner_kps`, FAST's keypoints of the first rows (the corners), are described as they are instead of
        being made again from their pixels (0.1-0.2 ms a keyframe): the same point, level 0 and angle -1; their
        size (FAST's 7) and response compute() does not read (the descriptors are the same, checked on the
        re-fed flights)."""
        h, w = image.shape[:2]
        if len(uv) and not octave.any():
            r = np.rint(uv)
            rows = np.flatnonzero((r[:, 0] >= PATCH) & (r[:, 0] < w - PATCH) & (r[:, 1] >= PATCH)
                                  & (r[:, 1] < h - PATCH))
            if corner_kps and len(uv) > len(corner_kps):
                pts = corner_kps + upright_keypoints(uv[len(corner_kps):], PATCH)
            elif corner_kps:
                pts = corner_kps
            else:
                pts = upright_keypoints(uv, PATCH)
            kps, desc = self.orb.compute(image, pts)
            if desc is not None and len(kps) == len(rows) and \
                    np.array_equal(cv2.KeyPoint.convert(kps).reshape(-1, 2), uv[rows]):
                return desc, rows
            self.slow_describes += 1
        sizes = PATCH * self.level_scale ** octave
        kps = [cv2.KeyPoint(u, v, sz, 0.0, 0.0, o, i)
               for i, ((u, v), sz, o) in enumerate(zip(uv.tolist(), sizes.tolist(), octave.tolist()))]
        kps, desc = self.orb.compute(image, kps)
        if desc is None or not kps:
            return None
        return desc, np.array([kp.class_id for kp in kps], np.int64)
