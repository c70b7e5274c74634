"""Track images for eyeballing the front end: trails coloured by track length, stereo matches beside.

`TrackImageWriter` is what `vio replay --show-tracks DIR` feeds frame by frame; `write_track_images` runs
the tracker over a EuRoC dataset on its own (bench/frontend.py --show-tracks uses it).
"""

from __future__ import annotations

import logging
from pathlib import Path

import cv2
import numpy as np

from vio import VioError
from vio.calibration import CameraCalibration, StereoCalibration
from vio.frontend.undistort import distort_px
from vio.types import FeatureFrame, StereoFrame

log = logging.getLogger(__name__)

TRAIL_FRAMES = 10
LONG_TRACK = 20  # track length drawn fully green


def _colour(track_len: int) -> tuple[int, int, int]:
    """BGR from red (new) through yellow to green (>= LONG_TRACK frames)."""
    a = min(max(track_len - 1, 0) / (LONG_TRACK - 1), 1.0)
    return (0, int(255 * min(1.0, 2 * a)), int(255 * min(1.0, 2 * (1 - a))))


def draw_tracks(frame: StereoFrame, ff: FeatureFrame, cam0: CameraCalibration, cam1: CameraCalibration,
                trails: dict[int, list[np.ndarray]] | None = None) -> np.ndarray:
    """BGR image: left with tracks (filled dot = stereo match, ring = mono), right with the stereo matches.

    FeatureFrame holds undistorted pixels; they are re-distorted here to land on the raw images.
    """
    left = cv2.cvtColor(frame.left, cv2.COLOR_GRAY2BGR)
    raw_right = frame.right_image()
    right = cv2.cvtColor(raw_right, cv2.COLOR_GRAY2BGR) if raw_right is not None else np.zeros_like(left)
    uv0 = distort_px(cam0, ff.uv0) if len(ff.ids) else np.zeros((0, 2))
    stereo = np.isfinite(ff.depth_m)
    uv1 = np.full_like(uv0, np.nan)
    if stereo.any():
        uv1[stereo] = distort_px(cam1, ff.uv1[stereo])
    for k, tid in enumerate(ff.ids):
        c = _colour(int(ff.track_len[k]))
        p = tuple(int(round(v)) for v in uv0[k])
        if trails is not None:
            hist = trails.get(int(tid), [])
            for a, b in zip(hist[-TRAIL_FRAMES:], hist[-TRAIL_FRAMES + 1:] + [uv0[k]]):
                cv2.line(left, tuple(int(round(v)) for v in a), tuple(int(round(v)) for v in b), c, 1, cv2.LINE_AA)
        cv2.circle(left, p, 3, c, -1 if stereo[k] else 1, cv2.LINE_AA)
        if stereo[k]:
            cv2.circle(right, tuple(int(round(v)) for v in uv1[k]), 3, c, -1, cv2.LINE_AA)
    status = (f"t={ff.t_ns}  features {len(ff.ids)}  stereo {ff.n_stereo}  parallax {ff.parallax_px:.1f}px"
              if ff.tracking_ok else f"t={ff.t_ns}  NOT OK: {ff.reason}")
    img = np.hstack([left, right])
    cv2.putText(img, status, (8, 20), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (0, 0, 0), 3, cv2.LINE_AA)
    cv2.putText(img, status, (8, 20), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (255, 255, 255), 1, cv2.LINE_AA)
    return img


class TrackImageWriter:
    """Writes one PNG per frame (`<t_ns>.png`) into `out_dir`; remembers recent positions for the trails."""

    def __init__(self, out_dir: str | Path, calib: StereoCalibration, every: int = 1) -> None:
        self.out_dir = Path(out_dir)
        try:
            self.out_dir.mkdir(parents=True, exist_ok=True)
        except OSError as e:
            raise VioError(f"{self.out_dir}: cannot create the track image folder ({e.strerror})") from None
        self.calib = calib
        self.every = max(1, int(every))
        self._trails: dict[int, list[np.ndarray]] = {}
        self._count = 0
        self.written = 0

    def write(self, frame: StereoFrame, ff: FeatureFrame) -> None:
        if self._count % self.every == 0:
            img = draw_tracks(frame, ff, self.calib.cam0, self.calib.cam1, self._trails)
            path = self.out_dir / f"{ff.t_ns}.png"
            if not cv2.imwrite(str(path), img):
                raise VioError(f"{path}: cannot write track image")
            self.written += 1
        self._count += 1
        uv0 = distort_px(self.calib.cam0, ff.uv0) if len(ff.ids) else np.zeros((0, 2))
        self._trails = {int(t): (self._trails.get(int(t), []) + [uv0[k]])[-TRAIL_FRAMES:]
                        for k, t in enumerate(ff.ids)}


def write_track_images(dataset, out_dir: str | Path, cfg=None, max_frames: int | None = None,
                       every: int = 1) -> int:
    """Run a fresh tracker (with the gyro prior) over a EurocDataset and write track images; returns count."""
    from vio.frontend.runner import run_frontend

    writer = TrackImageWriter(out_dir, dataset.calibration, every)
    for frame, ff in run_frontend(dataset, cfg, max_frames=max_frames):
        writer.write(frame, ff)
    log.info("wrote %d track images to %s", writer.written, out_dir)
    return writer.written
