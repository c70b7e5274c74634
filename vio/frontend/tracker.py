"""Stereo KLT tracker: StereoFrame (+ gyro rotation prior) -> FeatureFrame.

Per frame: check the image, compensate brightness, track the previous left features with KLT started at
their gyro-predicted position, refine each against its first appearance with an affine warp (anchor.py: this
removes the drift of translational KLT and checks the match), drop matches that disagree with the common rigid
motion (RANSAC, frame to frame and over a longer baseline), top the features up with FAST corners spread over
a grid, match all of them into the right image and triangulate. Tracking runs on raw images; only the output
is undistorted (same K).
"""

from __future__ import annotations

import dataclasses
import logging
import time
from collections import deque
from collections.abc import Callable

import cv2
import numpy as np

from vio.calibration import StereoCalibration
from vio.config import FrontendConfig
from vio.frontend.anchor import AnchorRefiner, Anchors
from vio.frontend.median import median
from vio.frontend.quality import image_problem
from vio.frontend.ransac import temporal_inliers
from vio.frontend.stereo import StereoMatcher, klt_fb
from vio.frontend.undistort import distort_px, rotate_px, undistort_px
from vio.types import FeatureFrame, StereoFrame

log = logging.getLogger(__name__)

BORDER_PX = 8  # new features keep this far from the border so the KLT window stays inside
REFINE_MAX_SHIFT_PX = 2.0  # a refinement that moves the KLT result further found another patch
MAX_CONTRAST_CHANGE = 3.0  # patch std vs its anchor's (after gain compensation): beyond, blur or glare
STEREO_RETRY_EVERY = 4  # frames between stereo searches for a track whose last stereo match failed


class StereoTracker:
    """Feature tracks over a stereo stream; one instance per camera head (not thread-safe)."""

    def __init__(self, calib: StereoCalibration, cfg: FrontendConfig | None = None) -> None:
        self.calib = calib
        self.cfg = cfg or FrontendConfig()
        self.cam0 = calib.cam0
        self.K0 = calib.cam0.K
        self.stereo = StereoMatcher(calib, self.cfg)
        w = self.cfg.klt_window_px | 1
        self._klt = dict(winSize=(w, w), maxLevel=self.cfg.klt_pyramid_levels,
                         criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 30, 0.01))
        self._fast = cv2.FastFeatureDetector_create(self.cfg.fast_threshold, True)
        self._clahe = cv2.createCLAHE(clipLimit=2.0, tileGridSize=(8, 8)) if self.cfg.clahe else None
        c = self.cfg
        self._anchor = (AnchorRefiner(c.anchor_patch_px | 1, iterations=c.anchor_iterations, min_ncc=c.anchor_min_ncc,
                                      renew_deform=c.anchor_renew_deform) if c.anchor_patch_px else None)
        # KLT only has to bring a track within reach of the anchor refinement, which places it at full
        # resolution against its first appearance: on half-resolution images the tracking stage took 0.9 ms a
        # frame instead of 2.4 (docs/frontend.md)
        self._half = bool(c.klt_half_resolution and self._anchor is not None)
        wh = (w // 2) | 1
        self._klt_half = dict(self._klt, winSize=(wh, wh), maxLevel=max(0, c.klt_pyramid_levels - 1))
        self._next_id = 0
        self._last_t: int | None = None
        self._frame_count = 0
        self.frames_bad = 0
        self._bad_run = 0  # consecutive bad frames (one warning per run)
        self._reset()

    # ---------------------------------------------------------------------------------------- state
    def _reset(self) -> None:
        """Forget all tracks: the next good frame starts fresh (new ids, new keyframe reference)."""
        self._prev_img: np.ndarray | None = None
        self._prev_half: tuple[np.ndarray, np.ndarray] | None = None  # (full image, its pyrDown)
        self._ids = np.zeros(0, np.int64)
        self._raw = np.zeros((0, 2), np.float32)  # raw left pixels of the live tracks
        self._uv = np.zeros((0, 2))  # undistorted left pixels
        self._len = np.zeros(0, np.int64)
        self._depth = np.zeros(0)  # last stereo depth per track (NaN: none)
        self._tried = np.zeros(0, bool)  # stereo search made at least once (frames may skip stereo)
        self._anc = Anchors.empty(self._anchor.p ** 2) if self._anchor else None
        self._anc_rows: np.ndarray | None = None  # rows of _anc the tracks kept this frame (copied once, at its end)
        self._kf_ids = np.zeros(0, np.int64)
        self._kf_uv = np.zeros((0, 2))
        self._R_kf_cur = np.eye(3)
        self._want_keyframe = True
        self._prev_mean = 0.0
        self._hist: deque[tuple[np.ndarray, np.ndarray]] = deque(maxlen=self.cfg.drift_check_frames)

    @property
    def raw_uv0(self) -> np.ndarray:
        """Raw (distorted) left pixels of the tracks in the last FeatureFrame, same row order (debug view)."""
        return self._raw.astype(np.float64)

    def mark_keyframe(self) -> None:
        """The back end took the last processed frame as keyframe: measure parallax against it from now on."""
        self._kf_ids = self._ids.copy()
        self._kf_uv = self._uv.copy()
        self._R_kf_cur = np.eye(3)
        self._want_keyframe = False

    def _bad(self, t_ns: int, reason: str, reset: bool = True) -> FeatureFrame:
        """One warning per run of bad frames (a 2 s blackout is 40 frames), the end of the run at INFO."""
        self.frames_bad += 1
        if self._bad_run == 0:
            log.warning("front end: frame t=%d not used: %s", t_ns, reason)
        else:
            log.debug("front end: frame t=%d not used: %s", t_ns, reason)
        self._bad_run += 1
        if reset:
            self._reset()
        return FeatureFrame.empty(t_ns, reason)

    # ---------------------------------------------------------------------------------------- steps
    def _prepare(self, img: np.ndarray, which: str) -> tuple[np.ndarray | None, str]:
        """Grey uint8 image of the calibrated size, or None and the reason."""
        if img.ndim == 3:
            img = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
        if img.dtype != np.uint8:
            return None, f"{which} image has dtype {img.dtype}, expected uint8"
        cam = self.cam0
        if img.shape != (cam.height, cam.width):
            return None, f"{which} image is {img.shape[1]}x{img.shape[0]}, calibration says {cam.width}x{cam.height}"
        return img, ""

    def _predict(self, R_prev_cur: np.ndarray | None) -> np.ndarray:
        """Start positions (raw pixels) for KLT: the previous positions rotated by the gyro prior."""
        if R_prev_cur is None or not self.cfg.use_imu_prediction or len(self._uv) == 0:
            return self._raw.copy()
        uv_pred, front = rotate_px(self.K0, R_prev_cur.T, self._uv)
        raw_pred = distort_px(self.cam0, uv_pred).astype(np.float32)
        h, w = self._prev_img.shape
        inside = front & np.all(np.isfinite(raw_pred), axis=1)
        inside &= (raw_pred[:, 0] >= 0) & (raw_pred[:, 0] < w) & (raw_pred[:, 1] >= 0) & (raw_pred[:, 1] < h)
        return np.where(inside[:, None], raw_pred, self._raw)

    def _track(self, img: np.ndarray, R_prev_cur: np.ndarray | None) -> np.ndarray:
        """Track live features into `img`; returns the boolean mask of survivors and updates positions."""
        n = len(self._raw)
        if n == 0 or self._prev_img is None:
            return np.zeros(n, bool)
        # with anchor refinement, the NCC against the first appearance checks each match more strictly than the
        # forward-backward pass would, at a fraction of its cost
        guess = self._predict(R_prev_cur)
        if self._half:  # pyrDown's pixel i is centred on the full image's pixel 2i: coordinates halve exactly
            prev = self._prev_half
            prev_small = prev[1] if prev is not None and prev[0] is self._prev_img else cv2.pyrDown(self._prev_img)
            small = cv2.pyrDown(img)
            self._prev_half = (img, small)
            p1, ok = klt_fb(prev_small, small, self._raw * 0.5, guess * 0.5, self._klt_half, self.cfg.fb_check_px,
                            backward=False)
            p1 *= 2.0
        else:
            p1, ok = klt_fb(self._prev_img, img, self._raw, guess, self._klt, self.cfg.fb_check_px,
                            backward=self._anchor is None)
        self._raw = np.where(ok[:, None], p1, self._raw).astype(np.float32)
        return ok

    def _detect(self, img: np.ndarray) -> np.ndarray:
        """New raw corners (M, 2) that top the tracks up to max_features, spread over the grid cells."""
        cfg = self.cfg
        need_total = cfg.max_features - len(self._raw)
        if need_total <= 0:
            return np.zeros((0, 2), np.float32)
        h, w = img.shape
        mask = np.zeros((h, w), np.uint8)
        mask[BORDER_PX:h - BORDER_PX, BORDER_PX:w - BORDER_PX] = 255
        r = cfg.min_distance_px
        for x, y in np.rint(self._raw).astype(np.int64).tolist():  # (Python round per coordinate cost 0.3 ms)
            cv2.circle(mask, (x, y), r, 0, -1)
        taken = self._select(self._fast.detect(img, mask), mask, need_total)
        if len(taken) < need_total and cfg.fast_threshold > 2:
            # low-contrast scene: weaker corners are better than too few tracks
            self._fast.setThreshold(max(1, cfg.fast_threshold // 2))
            more = self._select(self._fast.detect(img, mask), mask, need_total - len(taken), taken)
            self._fast.setThreshold(cfg.fast_threshold)
            taken = np.concatenate([taken, more]) if len(more) else taken
        return taken

    def _select(self, kps: tuple, mask: np.ndarray, need_total: int, already: np.ndarray | None = None
                ) -> np.ndarray:
        """Pick up to `need_total` of the FAST corners `kps`: strongest first, spread over the grid cells,
        at least min_distance_px from existing tracks and each other (`mask` is updated as they are taken)."""
        cfg = self.cfg
        if not kps or need_total <= 0:
            return np.zeros((0, 2), np.float32)
        h, w = mask.shape
        pts = cv2.KeyPoint_convert(kps)
        resp = np.fromiter((k.response for k in kps), float, len(kps))
        order = np.argsort(-resp)
        pts = pts[order]
        cw, ch = w / cfg.grid_cols, h / cfg.grid_rows
        cells = cfg.grid_cols * cfg.grid_rows

        def cell_of(p: np.ndarray) -> np.ndarray:
            return (np.minimum(p[:, 1] // ch, cfg.grid_rows - 1) * cfg.grid_cols
                    + np.minimum(p[:, 0] // cw, cfg.grid_cols - 1)).astype(int)

        quota = -(-cfg.max_features // cells)
        live = self._raw if already is None else np.concatenate([self._raw, already])
        have = np.bincount(cell_of(live), minlength=cells) if len(live) else np.zeros(cells, int)
        need = np.maximum(quota - have, 0)
        cand_cell = cell_of(pts)
        xy = pts.astype(np.int64)
        # the mask only loses pixels and the quotas only shrink, so a corner that is masked out (or in a full
        # cell) now stays out: dropping those first leaves the Python loop below the few real candidates
        free = np.flatnonzero(mask[xy[:, 1], xy[:, 0]] != 0)
        taken: list[int] = []
        used = np.zeros(len(pts), bool)
        # pass 1 fills each cell up to its quota (spread); pass 2 tops up from the best corners anywhere
        for per_cell in (True, False):
            cand = free[need[cand_cell[free]] > 0] if per_cell else free
            for i in cand.tolist():
                if len(taken) >= need_total:
                    break
                if used[i] or (per_cell and need[cand_cell[i]] <= 0):
                    continue
                x, y = int(xy[i, 0]), int(xy[i, 1])
                if mask[y, x] == 0:
                    continue
                used[i] = True
                taken.append(i)
                need[cand_cell[i]] -= 1
                cv2.circle(mask, (x, y), cfg.min_distance_px, 0, -1)
        return pts[taken].astype(np.float32).reshape(-1, 2)

    def _drift_outliers(self) -> np.ndarray:
        """Mask of tracks inconsistent with the rigid motion since `drift_check_frames` ago.

        Frame-to-frame KLT errors of a tenth of a pixel add up (patches deform as the view changes); over a
        longer baseline the drift shows up against the epipolar geometry that the other tracks agree on.
        """
        bad = np.zeros(len(self._ids), bool)
        if len(self._hist) == self._hist.maxlen:
            old_ids, old_uv = self._hist[0]
            _, i_old, i_cur = np.intersect1d(old_ids, self._ids, assume_unique=True, return_indices=True)
            inl = temporal_inliers(old_uv[i_old], self._uv[i_cur], self.cfg.ransac_threshold_px)
            bad[i_cur[~inl]] = True
        return bad

    def _keep(self, keep: np.ndarray) -> None:
        """Keep only the tracks `keep` (index or mask) in every per-track array. The anchors' rows are only
        noted (`_anc_rows`): process() copies them once per frame, with the renewed and new ones."""
        self._ids, self._raw, self._len = self._ids[keep], self._raw[keep], self._len[keep]
        self._depth, self._uv, self._tried = self._depth[keep], self._uv[keep], self._tried[keep]
        if self._anc is not None:
            rows = np.arange(len(self._anc)) if self._anc_rows is None else self._anc_rows
            self._anc_rows = rows[keep]

    def _drop(self, bad: np.ndarray) -> None:
        if bad.any():
            self._keep(~bad)

    def _refine(self, img: np.ndarray, ok: np.ndarray) -> None:
        """Affine refinement of the KLT survivors against their anchor patches (anchor.py); clears `ok` of
        tracks whose patch no longer matches or that the refinement moved far from the KLT result."""
        if self._anc is None or not ok.any():
            return
        # all rows at once: the few KLT failures are dropped anyway, and subsetting would copy the anchors
        pos, ncc, contrast = self._anchor.refine(img, self._raw, self._anc)
        h, w = img.shape
        good = (ncc >= self._anchor.min_ncc) & np.all(np.isfinite(pos), axis=1)
        good &= (contrast > 1.0 / MAX_CONTRAST_CHANGE) & (contrast < MAX_CONTRAST_CHANGE)
        good &= (pos[:, 0] >= 0) & (pos[:, 0] <= w - 1) & (pos[:, 1] >= 0) & (pos[:, 1] <= h - 1)
        good &= np.linalg.norm(pos - self._raw, axis=1) < REFINE_MAX_SHIFT_PX
        ok &= good
        self._raw[ok] = pos[ok]

    def _parallax(self) -> float:
        """Median distance of shared tracks from their keyframe position rotated into this frame [px]."""
        if len(self._kf_ids) == 0 or len(self._ids) == 0:
            return 0.0
        common, i_kf, i_cur = np.intersect1d(self._kf_ids, self._ids, assume_unique=True, return_indices=True)
        if len(common) == 0:
            return 0.0
        pred, front = rotate_px(self.K0, self._R_kf_cur.T, self._kf_uv[i_kf])
        d = np.linalg.norm(self._uv[i_cur] - pred, axis=1)[front]
        return median(d) if len(d) else 0.0

    # ---------------------------------------------------------------------------------------- main
    def process(self, frame: StereoFrame, R_cam0prev_cam0cur: np.ndarray | None = None,
                stereo: bool | Callable[[FeatureFrame], bool] = True) -> FeatureFrame:
        """Track one stereo frame. `R_cam0prev_cam0cur` (from `GyroPrior`) maps current cam0 points into the
        previous frame's cam0; None when no gyro is available (tracking then starts from zero motion).

        `stereo=False` skips the right image (no uv1/depth in the result; the tracks keep their last depth
        as the next search start): the caller's promise that this frame's stereo is not used. A callable
        decides after tracking: it gets this frame's result without stereo (ids, tracks, parallax; uv1 and
        depth NaN), so the estimator asks for stereo on the frames that become keyframes only. Stereo (with
        the right image's decoding in a replay) was a third of the front-end time."""
        t_start = time.perf_counter()
        t_ns = int(frame.t_ns)
        if self._last_t is not None and t_ns <= self._last_t:
            # keep the tracks: the next in-order frame continues from the last good one
            return self._bad(t_ns, f"time stamp {t_ns} not after the previous frame {self._last_t}", reset=False)
        timings: dict[str, float] = {}

        def lap(name: str, t0: float) -> float:
            t1 = time.perf_counter()
            timings[name] = (t1 - t0) * 1e3
            return t1

        left, why = self._prepare(frame.left, "left")
        if left is None:
            return self._bad(t_ns, why)
        mean = float(cv2.mean(left)[0])
        why = image_problem(left, self.cfg, mean)
        if why:
            self._last_t = t_ns
            return self._bad(t_ns, why)
        t = lap("check", t_start)
        left = self._normalise(left, mean=mean)
        t = lap("preprocess", t)

        had_prev = self._prev_img is not None
        R = None if R_cam0prev_cam0cur is None else np.asarray(R_cam0prev_cam0cur, dtype=float)
        prev_uv = self._uv
        ok = self._track(left, R)
        t = lap("track", t)
        self._refine(left, ok)
        t = lap("refine", t)
        uv_cur = undistort_px(self.cam0, self._raw[ok])
        inl = temporal_inliers(prev_uv[ok], uv_cur, self.cfg.ransac_threshold_px)
        keep = np.flatnonzero(ok)[inl]
        n_tracked_klt, n_ransac_out = int(ok.sum()), int((~inl).sum())
        self._keep(keep)
        self._len += 1
        self._uv = uv_cur[inl]
        self._drop(self._drift_outliers())
        renew, renewed = None, None
        if self._anc is not None:
            renew = self._anchor.needs_renewal(self._anc.A[self._anc_rows])
            renewed = self._anchor.build(left, self._raw[renew]) if renew.any() else None
        if R is not None and had_prev:
            self._R_kf_cur = self._R_kf_cur @ R
        t = lap("ransac", t)

        new = self._detect(left)
        if len(new):
            m = len(new)
            self._ids = np.concatenate([self._ids, np.arange(self._next_id, self._next_id + m, dtype=np.int64)])
            self._next_id += m
            self._raw = np.concatenate([self._raw, new]).astype(np.float32)
            self._uv = np.concatenate([self._uv, undistort_px(self.cam0, new)])
            self._len = np.concatenate([self._len, np.ones(m, np.int64)])
            self._depth = np.concatenate([self._depth, np.full(m, np.nan)])
            self._tried = np.concatenate([self._tried, np.zeros(m, bool)])
        if self._anc is not None:  # the kept rows, renewed where due, then the new tracks' anchors: one copy
            self._anc = self._anc.assemble(self._anc_rows, renew if renewed is not None else None, renewed,
                                           self._anchor.build(left, new) if len(new) else None)
            self._anc_rows = None
        t = lap("detect", t)

        if self._want_keyframe:
            self.mark_keyframe()
        self._hist.append((self._ids.copy(), self._uv.copy()))
        parallax = self._parallax()
        n = len(self._ids)
        uv1, depth = np.full((n, 2), np.nan), np.full(n, np.nan)
        ff = FeatureFrame(t_ns, self._ids.copy(), self._uv.copy(), uv1, depth, self._len.copy(),
                          parallax_px=parallax, timings_ms=timings)
        if n < self.cfg.min_features_ok:  # reported bad below: no stereo
            stereo = False
        elif callable(stereo):
            stereo = bool(stereo(ff))
        try:
            right, note = self._right_image(frame) if stereo else (None, "")
        except (cv2.error, OSError, ValueError) as e:  # the tracks are updated already: keep them consistent
            right, note = None, f"right image unusable ({type(e).__name__}): mono only"
        if right is not None and n:
            # A track whose last stereo match failed is mostly occluded or outside the right view; searching
            # it again every frame doubled the stereo time on EuRoC. Tracks never searched are always searched,
            # failed ones every STEREO_RETRY_EVERY frames (staggered by id).
            search = ~self._tried | np.isfinite(self._depth)
            search |= (self._ids + self._frame_count) % STEREO_RETRY_EVERY == 0
            res = self.stereo.match(left, right, self._raw, self._uv, self._depth, search)
            uv1, depth = res.uv1, res.depth_m
            self._tried |= search
        if stereo:
            self._depth = depth.copy()
        t = lap("stereo", t)

        self._prev_img = left
        self._last_t = t_ns
        self._frame_count += 1
        timings["total"] = (time.perf_counter() - t_start) * 1e3
        ff = dataclasses.replace(ff, uv1=uv1, depth_m=depth, reason=note)
        log.debug("front end t=%d: %d features (%d tracked, %d RANSAC outliers, %d new), %d stereo, "
                  "parallax %.1f px, %.1f ms", t_ns, n, n_tracked_klt - n_ransac_out, n_ransac_out, len(new),
                  ff.n_stereo, parallax, timings["total"])
        if n < self.cfg.min_features_ok:
            return self._bad(t_ns, f"only {n} features (< {self.cfg.min_features_ok})")
        if self._bad_run:
            log.info("front end: frames usable again after %d bad ones", self._bad_run)
            self._bad_run = 0
        return ff

    def _normalise(self, img: np.ndarray, right: bool = False, mean: float | None = None) -> np.ndarray:
        """CLAHE, or a global gain that keeps brightness steady so KLT's constant-brightness model holds.

        The left image is held at the previous left image's mean (and sets it for the next frame); the right
        image gets the gain that matches it to this frame's left, so call it after the left. `mean`: img's mean
        grey level, when the caller has it (the image check computes it)."""
        if self._clahe is not None:
            return self._clahe.apply(img)
        if not self.cfg.gain_compensation:
            return img
        m = float(cv2.mean(img)[0]) if mean is None else mean
        if right or self._prev_img is not None:
            gain = self._prev_mean / max(m, 1.0)
            if abs(gain - 1.0) > (0.05 if right else 0.03):
                img = cv2.convertScaleAbs(img, alpha=gain)
                m *= gain
        if not right:
            self._prev_mean = m
        return img

    def _right_image(self, frame: StereoFrame) -> tuple[np.ndarray | None, str]:
        """The checked, normalised right image, or None and the note why this frame is mono only."""
        raw = frame.right_image()
        if raw is None:
            return None, "no right image: mono only"
        right, why = self._prepare(raw, "right")
        mean = None if why else float(cv2.mean(right)[0])
        why = why or image_problem(right, self.cfg, mean)
        if why:
            return None, f"right image unusable ({why}): mono only"
        return self._normalise(right, right=True, mean=mean), ""
