"""Drive the front end over a recorded dataset with the gyro prior, as the estimator does live.

Shared by the bench, the debug view and the tests so that all of them measure the same loop.
"""

from __future__ import annotations

from collections.abc import Iterator

from vio.config import FrontendConfig
from vio.frontend.gyro import GyroPrior
from vio.frontend.tracker import StereoTracker
from vio.types import FeatureFrame, ImuSample, StereoFrame


def set_opencv_threads(n: int = 1) -> None:
    """OpenCV's worker threads for a replay. One (the default) keeps it reproducible: OpenCV's pool hands out work
    as threads come free, and on a machine busy with other work a replay came out different from the same replay
    alone (docs/evaluation.md, "Reproducible replays"); one thread per process also keeps parallel replays from
    competing for the cores."""
    import cv2

    cv2.setNumThreads(n)


def run_frontend(dataset, cfg: FrontendConfig | None = None, max_frames: int | None = None,
                 tracker: StereoTracker | None = None, use_gyro: bool = True,
                 keyframe_every: int = 0) -> Iterator[tuple[StereoFrame, FeatureFrame]]:
    """Yield (frame, FeatureFrame) for the frames of a EurocDataset-like object (`events()`, `calibration`).

    `keyframe_every` > 0 calls mark_keyframe() every that many frames, standing in for the back end.
    """
    calib = dataset.calibration
    tracker = tracker or StereoTracker(calib, cfg)
    gyro = GyroPrior(calib.cam0.T_body_cam, calib.time_offset_ns)
    t_prev: int | None = None
    n = 0
    for ev in dataset.events():
        if isinstance(ev, ImuSample):
            gyro.add(ev)
            continue
        R = gyro.rotation(t_prev, ev.t_ns) if (use_gyro and t_prev is not None) else None
        ff = tracker.process(ev, R)
        if ff.tracking_ok:
            t_prev = ev.t_ns
        n += 1
        if keyframe_every and n % keyframe_every == 0:
            tracker.mark_keyframe()
        yield ev, ff
        if max_frames is not None and n >= max_frames:
            return
