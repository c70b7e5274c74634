"""`vio replay DATASET --output traj.tum [--stats stats.json] [--realtime] [--config FILE] [--show-tracks DIR]`

Runs the whole pipeline (front end + estimator) on a recorded EuRoC dataset. The command line is a
contract other tools call. Outputs are sinks: callables that receive every frame's NavState, so more
outputs (MAVLink, a status file) plug in without touching the loop. When the dataset has ground truth,
ATE/RPE are printed at the end.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import logging
import os
import re
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from vio import UsageError, VioError
from vio.argtypes import path_arg, positive_int, topic_arg, url_arg
from vio.io.outputs import check_outputs
from vio.types import NavState

if TYPE_CHECKING:
    from drivers.mavlink_out import MavlinkStats
    from vio.config import VioConfig

log = logging.getLogger(__name__)

Sink = Callable[[NavState], None]
# Estimator.health() fields the stats JSON carries
_HEALTH_STATS = ("initialized", "reset_counter", "frames_processed", "frames_unusable", "unusable_reasons",
                 "imu_rejected", "imu_rejected_reasons", "frames_dropped", "last_reset_reason", "sensor_error",
                 "calibration_warning", "stereo_warning")
_DETAIL = re.compile(r"\s*\([^()]*\d[^()]*\)\s*$")  # "image too dark (mean grey 3.1 < 12)": the figures


CALIB_FORMATS = ("project", "kalibr", "euroc", "opencv", "depthai")  # --calib-format: ours, `vio calib import`'s
REALTIME_MAX_WAIT_S = 5.0  # realtime: a longer gap in the data is not waited out
MAX_THREADS = 1024  # more OpenCV threads than any companion computer has cores


def _threads(text: str) -> int:
    """--threads: a whole number >= 0."""
    try:
        n = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a whole number") from None
    if n < 0:
        raise argparse.ArgumentTypeError(f"{n} is below 0 (0: OpenCV's default pool)")
    if n > MAX_THREADS:  # beyond a C int, cv2.setNumThreads ended the replay in an internal error (a review's)
        raise argparse.ArgumentTypeError(f"{n} is above {MAX_THREADS}")
    return n


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("dataset", type=path_arg,
                   help="EuRoC ASL dataset folder (with mav0/), ROS 1 .bag, ROS 2 bag folder or .mcap file")
    p.add_argument("--output", "-o", type=path_arg, metavar="TUM",
                   help="write the trajectory here (TUM: t x y z qx qy qz qw)")
    p.add_argument("--stats", type=path_arg, metavar="JSON",
                   help="write per-frame timings and the real-time factor here")
    p.add_argument("--realtime", action="store_true", help="pace the replay at sensor rate")
    p.add_argument("--mavlink", type=url_arg, metavar="URL", help="also send the states to an autopilot "
                   "(udpout:HOST:PORT, /dev/ttyAMA0:921600, ...); implies --realtime")
    p.add_argument("--config", type=path_arg, metavar="FILE", help="TOML configuration (defaults otherwise)")
    p.add_argument("--calibration", type=path_arg, metavar="YAML",
                   help="our calibration YAML in place of the recording's own (a EuRoC folder's sensor.yaml files, "
                   "the one an MCAP file from vio record carries)")
    p.add_argument("--calib", nargs="+", metavar="FILE", help="calibration: our YAML, or the files `vio calib import` "
                   "reads, with --calib-format; needed for a bag (a bag has none); for a EuRoC folder or an MCAP file "
                   "from vio record it replaces their own, as --calibration does (said in the log)")
    p.add_argument("--calib-format", default=None, choices=CALIB_FORMATS,
                   help="format of --calib: project (default), kalibr, euroc, opencv, depthai")
    p.add_argument("--left-topic", type=topic_arg,
                   help="bag topic of the left images (default: [bag] left_topic, /cam0/image_raw)")
    p.add_argument("--right-topic", type=topic_arg,
                   help="bag topic of the right images (default: [bag], /cam1/image_raw)")
    p.add_argument("--imu-topic", type=topic_arg, help="bag topic of the IMU (default: [bag] imu_topic, /imu0)")
    p.add_argument("--view", nargs="?", const="serve", type=url_arg, metavar="FILE.rrd|serve",
                   help="stream a live view to Rerun: save to FILE.rrd, or serve a web viewer (default: serve)")
    p.add_argument("--show-tracks", type=path_arg, metavar="DIR", help="write front-end track images (PNG) to DIR")
    p.add_argument("--max-frames", type=positive_int, metavar="N", help="stop after N camera frames")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument("--threads", type=_threads, default=1, metavar="N",
                   help="OpenCV worker threads (default 1: the same trajectory on every run; with OpenCV's pool a "
                   "replay that shared the machine with other work came out different in 3 of 6 runs; 0: "
                   "OpenCV's default pool, ~3 %% faster on 2 cores)")
    p.add_argument("--loop", action="store_true", help="run loop closure (as [loop] enabled = true)")
    p.add_argument("--loop-output", type=path_arg, metavar="TUM", help="write the loop-corrected trajectory here "
                   "(final pose graph; the odometry goes to --output)")
    p.add_argument("--save-map", type=path_arg, metavar="FILE", help="write the loop-closure map here (implies --loop)")
    p.add_argument("--load-map", type=path_arg, metavar="FILE", help="relocalise in this map (implies --loop; poses in "
                   "--loop-output come out in the map's frame)")
    p.add_argument("--overwrite-map", action="store_true", help="let --save-map (or [map] save) replace a file "
                   "there that this replay does not load (without it such a file is refused: a map grows only "
                   "through --load-map FILE --save-map FILE)")
    p.add_argument("--loop-plot", type=path_arg, metavar="PNG", help="top view of odometry, loop-corrected "
                   "trajectory, ground truth and the loop edges (implies --loop)")


class TumSink:
    """Appends each state's pose to a TUM file as it comes (a crash keeps what was estimated).

    `keep_existing`: a regular file at `path` is not replaced until the run succeeds (`commit()`): the poses go to
    PATH.partial, renamed over it then. A replay that failed had replaced an earlier run's trajectory with its own
    IMU-only poses, lost for nothing; a failed one leaves PATH as it was and its poses in PATH.partial."""

    def __init__(self, path: str | Path, keep_existing: bool = False) -> None:
        from vio.trajectory import format_tum_line

        self._fmt = format_tum_line
        self.final: Path | None = None  # the file the partial one is renamed over at commit()
        if keep_existing and os.path.isfile(path):  # not a device or pipe (-o /dev/stdout streams as ever)
            self.final = Path(os.path.realpath(path))  # a link is written through
            path = f"{self.final}.partial"
        try:
            self._f = open(path, "w")
        except OSError as e:
            raise VioError(f"{path}: cannot write the trajectory ({e.strerror})") from None
        self._path = path
        self._f.write("# timestamp[s] x y z qx qy qz qw  (T_world_body)\n")
        self.count = 0

    def __call__(self, st: NavState) -> None:
        from vio.geometry import rot_to_quat_wxyz

        try:
            self._f.write(self._fmt(st.t_ns, st.T_world_body[:3, 3], rot_to_quat_wxyz(st.T_world_body[:3, :3])))
        except OSError as e:
            self._failed(e)
        self.count += 1

    def close(self) -> None:
        """Flush and close; a write error (disk full) names the file: it ended as a bare "No space left on
        device", the trajectory unnamed."""
        if self._f.closed:
            return
        try:
            self._f.close()
        except OSError as e:
            self._failed(e)

    def commit(self) -> None:
        """The run succeeded: the partial file (if any) replaces the one it was kept beside."""
        self.close()
        if self.final is not None:
            try:
                os.replace(self._path, self.final)
            except OSError as e:
                raise VioError(f"{self.final}: cannot replace it with the trajectory in {self._path} "
                               f"({e.strerror or e})") from None
            self._path, self.final = str(self.final), None

    def kept_note(self) -> str:
        """What a failed run left where (empty when the poses went to the named file itself)."""
        return "" if self.final is None else f"the poses so far are in {self._path}; {self.final} is kept as it was"

    def _failed(self, e: OSError) -> None:
        with contextlib.suppress(OSError):
            self._f.close()  # the buffer fails again; the file is closed all the same
        raise VioError(f"{self._path}: cannot write the trajectory ({e.strerror or e})") from None


@dataclass
class ReplayResult:
    states: list[NavState]
    frame_stats: list[dict]
    data_s: float  # the replayed frames' span, less the gaps a realtime replay skipped (not data time)
    wall_s: float
    frames: int
    resets: int
    init_t_ns: int | None
    first_frame_t_ns: int | None
    extra: dict = field(default_factory=dict)
    frames_listed: int = 0  # camera rows in the replayed span, loadable or not
    unusable_reasons: dict[str, int] = field(default_factory=dict)  # frames without vision, by reason
    sensor_error: str | None = None  # the estimator's diagnosis of a sensor problem that blocked initialisation
    ended_blocked: bool = False  # the estimator stopped for the rest of the run (EstimatorHealth.stopped_for_run)

    @property
    def frames_unusable(self) -> int:
        return sum(self.unusable_reasons.values())

    def unusable_summary(self) -> str | None:
        """'3 of 95 frames unusable: 2 image missing, 1 ...' (None when every frame was usable)."""
        if not self.unusable_reasons:
            return None
        top = sorted(self.unusable_reasons.items(), key=lambda kv: -kv[1])
        more = f", {len(top) - 4} other reasons" if len(top) > 4 else ""
        return (f"{self.frames_unusable} of {self.frames_listed} frames unusable: "
                + ", ".join(f"{n} {why}" for why, n in top[:4]) + more)

    def vision_problem(self) -> str | None:
        """Why this replay is not visual-inertial odometry at all (None when vision worked at least once)."""
        if self.frames_listed == 0:
            return "no camera frame in the replayed span"
        if self.frames_unusable >= self.frames_listed:
            return f"vision never worked ({self.unusable_summary()}); any trajectory is from the IMU alone"
        if not self.states:
            return "the estimator never initialised: no trajectory" + (f" ({self.sensor_error})" if self.sensor_error
                                                                       else "")
        if self.ended_blocked:
            return (f"the estimator stopped for the rest of the run ({self.sensor_error}): the trajectory ends "
                    f"{(self.states[-1].t_ns - self.states[0].t_ns) * 1e-9:.1f} s after its start")
        return None

    @property
    def realtime_factor(self) -> float:
        return self.data_s / self.wall_s if self.wall_s > 0 else float("inf")

    def trajectory(self):
        from vio.trajectory import Trajectory

        if not self.states:
            raise VioError("the estimator never initialised: no trajectory")
        return Trajectory.from_poses(np.array([s.t_ns for s in self.states]),
                                     np.array([s.T_world_body for s in self.states]))

    def stats_dict(self) -> dict:
        def summary(key: str) -> dict:
            x = np.array([f[key] for f in self.frame_stats]) if self.frame_stats else np.zeros(1)
            return {"mean": float(x.mean()), "p50": float(np.percentile(x, 50)), "p95": float(np.percentile(x, 95)),
                    "p99": float(np.percentile(x, 99)), "max": float(x.max())}

        return {
            "frames": self.frames,
            "states": len(self.states),
            "data_s": self.data_s,
            "wall_s": self.wall_s,
            "realtime_factor": self.realtime_factor,
            "resets": self.resets,
            "init_delay_s": None if self.init_t_ns is None or self.first_frame_t_ns is None
            else (self.init_t_ns - self.first_frame_t_ns) * 1e-9,
            "keyframes": int(sum(f["keyframe"] for f in self.frame_stats)),
            "timing_ms": {k: summary(k) for k in ("frontend_ms", "backend_ms", "total_ms", "total_cpu_ms")},
            "frames_listed": self.frames_listed,
            "frames_unusable": self.frames_unusable,
            "unusable_reasons": dict(self.unusable_reasons),
            **self.extra,
            "per_frame": self.frame_stats,
        }


def replay(dataset, cfg=None, sinks: list[Sink] | None = None, realtime: bool = False,
           show_tracks: str | None = None, max_frames: int | None = None, progress: bool = True,
           loop=None, view=None) -> ReplayResult:
    """Stream a EurocDataset through a fresh Estimator; every frame's state goes to `sinks`.

    `loop`: a vio.app.loop_worker.LoopWorker that gets every keyframe (its image, features and odometry
    pose); the odometry does not depend on it. `view` (a vio.app.view.LiveView) gets each processed frame
    without the loop waiting for it."""
    preflight(dataset)  # before the estimator's imports: a data problem is said at once
    from vio.config import VioConfig
    from vio.estimator import Estimator
    from vio.types import ImuSample

    cfg = cfg or VioConfig()
    est = Estimator(dataset.calibration, cfg.estimator)
    states: list[NavState] = []
    est.listeners.append(states.append)
    for s in sinks or []:
        est.listeners.append(s)
    writer = None
    if show_tracks:
        from vio.frontend.debug_view import TrackImageWriter

        writer = TrackImageWriter(show_tracks, dataset.calibration)
    n_total = len(dataset) if max_frames is None else min(max_frames, len(dataset))
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=n_total, unit="frame", desc="replay", leave=False)
    frame_stats: list[dict] = []
    frames = 0
    t_first = None
    wall0 = time.perf_counter()
    skipped_s = 0.0  # realtime: data gaps not waited out
    skips: list[tuple[int, float]] = []  # realtime: (data stamp after a gap not waited out, seconds skipped)
    # IMU beyond the last frame (EuRoC excerpts carry the whole flight's IMU) would only be propagated
    t_end = int(dataset.frame_t[n_total - 1]) + max(dataset.calibration.time_offset_ns, 0) if n_total else None
    waiting: dict[int, object] = {}  # frames fed but not processed yet (they wait for the IMU), for the writer
    unusable: dict[str, int] = {}
    right_unusable: dict[str, int] = {}  # frames whose right image could not be used (they ran mono), by reason
    unreadable0 = dataset.stats.unreadable_images
    loop_images: dict[int, np.ndarray] = {}  # frames fed but not processed yet, for the loop worker
    loop_submit_ms: list[float] = []
    # right images are decoded only where the front end uses them (the debug view shows them all)
    try:  # an interrupted replay clears its progress bar (the message after it starts a clean line)
        for ev in dataset.events(t_end_ns=t_end, lazy_right=writer is None):
            if realtime:
                t_data = ev.t_ns
                if t_first is None:
                    t_first = t_data
                lag = (t_data - t_first) * 1e-9 - skipped_s - (time.perf_counter() - wall0)
                if lag > REALTIME_MAX_WAIT_S:
                    # a gap in the recording (a clock jump, a recorder paused) was waited out: 1000 s of silence,
                    # no message, looked like a hang (a review's finding); the data after it follow at once
                    log.warning("realtime: a gap of %.3g s in the data before t=%d ns: not waited out", lag, t_data)
                    skipped_s += lag
                    skips.append((t_data, lag))
                elif lag > 0:
                    time.sleep(lag)
            t0, c0 = time.perf_counter(), time.thread_time()
            if isinstance(ev, ImuSample):
                est.feed_imu(ev, want_state=False)  # the replay keeps frame states only
            else:
                if max_frames is not None and frames >= max_frames:
                    break
                est.feed_frame(ev)
                t_est = int(est.last_frame_stamp_ns)  # the stamp its processed frames carry (vio.frame_clock)
                if writer is not None or view is not None:
                    waiting[t_est] = ev
                if loop is not None:
                    loop_images[t_est] = ev.left
                frames += 1
                if bar is not None:
                    bar.update(1)
            # A frame is processed once the IMU has reached its stamp: in this call or in a later feed_imu
            # (a positive time offset), so its cost is recorded wherever it happened.
            for pf in est.take_processed():
                tm, ff, t_cam = pf.timings, pf.features, pf.t_ns
                if not ff.tracking_ok:  # counted without the figures, so that one cause is one count
                    why = _DETAIL.sub("", ff.reason) or "rejected by the front end"
                    unusable[why] = unusable.get(why, 0) + 1
                elif ff.reason.startswith("right image unusable"):  # that frame ran mono: nothing said at -q before
                    why = ff.reason.removeprefix("right image unusable (").removesuffix("): mono only")
                    right_unusable[why] = right_unusable.get(why, 0) + 1
                frame_stats.append({"t_ns": t_cam, "frontend_ms": tm.frontend_ms, "backend_ms": tm.backend_ms,
                                    "total_ms": (time.perf_counter() - t0) * 1e3,
                                    "total_cpu_ms": (time.thread_time() - c0) * 1e3, "keyframe": bool(tm.keyframe),
                                    "stereo": ff.n_stereo})
                if loop is not None:
                    kf = pf.keyframe  # solved in this frame's call: this frame's or (solve_next_frame) the last's
                    if kf is not None and kf.t_ns in loop_images:
                        t_l = time.perf_counter()
                        loop.submit(kf.state.t_ns, kf.state.T_world_body, loop_images[kf.t_ns], kf.features,
                                    kf.state.reset_counter)
                        loop_submit_ms.append((time.perf_counter() - t_l) * 1e3)
                    loop.settle(pf.settled)  # after the keyframe, as the daemon does
                    # this frame's image stays until the next frame: it may be a keyframe solved then
                    for t in [t for t in loop_images if t < t_cam]:
                        del loop_images[t]
                if t_cam in waiting:
                    fr = waiting.pop(t_cam)
                    if writer is not None:
                        writer.write(fr, ff)
                    if view is not None:
                        view.submit(t_cam, fr.left, ff, pf.state or (states[-1] if states else None), bool(tm.keyframe),
                                    {"resets": est.reset_counter, "keyframes": est.keyframes})
                    for t in [t for t in waiting if t < t_cam]:
                        del waiting[t]
    finally:
        if bar is not None:
            bar.close()
    est.flush()
    if loop is not None:  # what settled in the frames flush() processed, then the window as it ends
        for pf in est.take_processed():
            loop.settle(pf.settled)
        loop.settle(est.settled_at_end)
    wall = time.perf_counter() - wall0
    ft = dataset.frame_t[:frames] if frames else np.zeros(0, np.int64)
    data_s = float((ft[-1] - ft[0]) * 1e-9) if len(ft) > 1 else 0.0
    # a gap skipped between the frames is no data time (the real-time factor said 300 after a 1000 s gap)
    data_s = max(data_s - sum(lag for t, lag in skips if len(ft) > 1 and ft[0] < t <= ft[-1]), 0.0)
    h = est.health()
    # frames the dataset could not load never reached the estimator
    listed = n_total if t_end is None else int(np.count_nonzero(dataset.frame_t[:n_total] <= t_end))
    missing = sum(f is None for f in dataset.cam0_files[:listed])
    for why, n in (("image missing", missing), ("image unreadable", dataset.stats.unreadable_images - unreadable0)):
        if n:
            unusable[why] = unusable.get(why, 0) + n
    if loop is not None:
        loop.close()
    res = ReplayResult(states, frame_stats, data_s, wall, frames, est.reset_counter,
                       states[0].t_ns if states else None,
                       int(ft[0]) + dataset.calibration.time_offset_ns if len(ft) else None,
                       extra={"time_offset_ms": {"calibration": dataset.calibration.time_offset_ns * 1e-6,
                                                 "final": est.time_offset_estimate_ns * 1e-6,
                                                 "state": est.time_state, "linked_keyframes": est.time_links},
                              "imu_white_scale": None if est.white_scale is None
                              else [round(float(x), 2) for x in est.white_scale],
                              "imu_rows_skipped": dict(dataset.stats.imu_rows_skipped),
                              "data_notes": list(dataset.stats.notes),
                              "right_image_unusable": right_unusable,
                              "estimator": {k: getattr(h, k) for k in _HEALTH_STATS},
                              "calibration_refined": est.refinement_stats(),
                              "stereo_check": est.stereo_check_stats(),
                              "motion_check": est.motion_check_stats(),
                              "frame_stamps": est.frame_clock.stats.as_dict()},
                       frames_listed=listed, unusable_reasons=unusable, sensor_error=h.sensor_error,
                       ended_blocked=bool(states) and h.stopped_for_run is not None)
    summary = res.unusable_summary()
    if summary:
        log.warning(summary)
    if right_unusable:
        top = sorted(right_unusable.items(), key=lambda kv: -kv[1])
        log.warning("%d of %d frames ran on the left camera alone, their right image unusable: %s",
                    sum(right_unusable.values()), listed, ", ".join(f"{n} {why}" for why, n in top[:4])
                    + (f", {len(top) - 4} other reasons" if len(top) > 4 else ""))
    return res


def corrected_sink(sink: Sink, loop, cfg) -> Sink:
    """`sink` fed with states mapped by the loop worker's newest correction, as [loop] output says."""
    from vio.loop.output import CorrectedOutput

    out = CorrectedOutput.from_config(cfg)
    return lambda st: sink(out.apply(st, *loop.correction()))


def _loop_outputs(loop, res: ReplayResult, dataset, path: str | None,
                  plot_path: str | None = None) -> tuple[dict, Callable[[], None] | None]:
    """Loop-closure summary, the corrected trajectory (TUM), its accuracy and end-of-flight drift beside the
    odometry's; and the loop-edge plot as a call for the caller to make after the map and stats are written."""
    from vio.geometry import inv_T, rot_to_quat_wxyz
    from vio.trajectory import Trajectory, format_tum_line

    closer = loop.closer
    d = closer.stats.to_dict()
    if closer.map_keyframes:
        own = closer.keyframes[closer.map_keyframes:]
        d["relocalisation"] = {"map_keyframes": closer.map_keyframes, "relocalised": closer.relocalised,
                               "delay_s": None if closer.relocalised_t_ns is None or not own
                               else (closer.relocalised_t_ns - own[0].t_ns) * 1e-9,
                               "camera_mismatch": closer.map_camera_warning}
        r = d["relocalisation"]
        if r["relocalised"]:
            after = "" if r["delay_s"] is None else f" {r['delay_s']:.2f} s after this flight's first keyframe"
            print(f"relocalisation: placed in the map ({r['map_keyframes']} keyframes){after}; the loop-corrected "
                  "trajectory is in the map's frame")
        else:
            log.warning("relocalisation: this flight never matched the map (%d keyframes): its loop-corrected "
                        "trajectory is in its own frame, not the map's", r["map_keyframes"])
            print(f"relocalisation: NOT placed in the map ({r['map_keyframes']} keyframes): the loop-corrected "
                  "trajectory stays in this flight's own frame"
                  + (f" ({closer.map_camera_warning})" if closer.map_camera_warning else ""))
    d.update(dropped=loop.dropped, error=loop.error, memory_per_keyframe_bytes=closer.memory_per_keyframe_bytes(),
             loop_edges=[[int(e.i), int(e.j), float(e.weight)] for e in closer.graph.edges if e.kind == "loop"])
    T_gt = None
    draw = None
    if res.states:
        t = np.array([s.t_ns for s in res.states])
        T_odom = np.array([s.T_world_body for s in res.states])
        T = closer.corrected_trajectory(t, T_odom)
        if path:
            try:
                with open(path, "w") as f:
                    f.write("# timestamp[s] x y z qx qy qz qw  (T_world_body, loop-corrected)\n")
                    for ti, Ti in zip(t, T):
                        f.write(format_tum_line(int(ti), Ti[:3, 3], rot_to_quat_wxyz(Ti[:3, :3])))
            except OSError as e:
                raise VioError(f"{path}: cannot write the trajectory ({e.strerror})") from None
        if dataset.groundtruth is not None and len(t) >= 3:
            from vio.evaluation import end_drift_m, evaluate

            gt = dataset.groundtruth.trajectory
            try:
                ev = evaluate(Trajectory.from_poses(t, T), gt)
                d["evaluation"] = ev.to_dict()
                print("loop-corrected: " + ev.summary().splitlines()[3])
                d["end_drift_m"] = {"odometry": end_drift_m(t, T_odom, gt), "loop": end_drift_m(t, T, gt)}
                dr = d["end_drift_m"]
                print(f"end-of-flight drift (aligned on the first pose): odometry {dr['odometry']:.4f} m, "
                      f"loop-corrected {dr['loop']:.4f} m")
                A = ev.ate_4dof.T_gtworld_estworld  # ground truth into the estimate's frame, for the plot
                G = gt.poses()
                T_gt = inv_T(A) @ G[np.clip(np.searchsorted(gt.t_ns, t), 0, len(G) - 1)]
            except VioError as e:
                print(f"replay: no accuracy figures for the loop-corrected trajectory: {e}")
        if plot_path:
            from vio.loop.plot import plot_loop

            edges = [(e.i, e.j, e.weight) for e in closer.graph.edges if e.kind == "loop"]
            estimate = list(closer.graph.estimate)
            title = f"{d['accepted']} loop edges accepted, {d['switched_off']} switched off"

            def draw() -> None:
                plot_loop(plot_path, T_odom, T, estimate, edges, T_gt, title)
                print(f"loop-closure plot -> {plot_path}")
    refused = ", ".join(f"{n} {why}" for why, n in d["refused"].items() if n) or "none"
    print(f"loop closure: {d['keyframes']} keyframes, {d['accepted']} loop edges accepted "
          f"({d['switched_off']} switched off by GNC), refused: {refused}; detection {d['detect_ms_mean']:.1f} ms "
          f"per keyframe (p95 {d['detect_ms_p95']:.1f}), pose graph {d['graph_ms_mean']:.1f} ms per keyframe, "
          f"optimisation after a closure max {d['optimize_ms_max']:.0f} ms")
    return d, draw


def mavlink_summary(ms: MavlinkStats, url: str) -> tuple[dict, str]:
    """What `vio replay --mavlink` sent and why the rest was not (its counts for the result, and its summary line)."""
    extra = {"states_sent": ms.states_sent, "states_refused_armed": ms.states_refused_armed,
             "states_refused_unheard": ms.states_refused_unheard, "states_link_closed": ms.states_link_closed,
             "autopilot_heartbeats": ms.autopilot_heartbeats}
    line = (f"mavlink: {ms.states_sent} poses sent to {url}"
            + (f"; {ms.states_refused_armed} not sent: the autopilot said it was armed" if ms.states_refused_armed
               else "")
            + (f"; {ms.states_refused_unheard} not sent: no autopilot heartbeat said it was disarmed"
               if ms.states_refused_unheard else "")
            + (f"; {ms.states_link_closed} not sent: no connection (the link was closed)" if ms.states_link_closed
               else ""))
    return extra, line


def preflight(dataset) -> None:
    """Stop before replaying what cannot work: a unit mistake in the IMU data or the calibration, no camera
    frame, images of another size than the calibration's (the front end would refuse every frame)."""
    if dataset.units_problem:
        raise VioError(dataset.units_problem)
    if not len(dataset):
        raise VioError(f"{dataset.where('cam0')}: no camera frames")
    problem = dataset.first_image_size_problem()
    if problem:
        raise VioError(problem)


def check_calib_format(args: argparse.Namespace) -> None:
    """--calib-format without --calib was ignored, unsaid: the recording's own calibration was flown."""
    if args.calib_format is not None and not args.calib:
        raise UsageError(f"--calib-format {args.calib_format}: there is no --calib to read")


def load_calib_args(files: list[str] | None, fmt: str | None = "project"):
    """--calib FILE... in our YAML or any format `vio calib import` reads (None without files)."""
    if not files:
        return None
    if fmt in ("project", None):
        from vio.calibration import load_calibration

        if len(files) != 1:
            raise UsageError("--calib: our calibration is one YAML file; give --calib-format for other formats")
        return load_calibration(files[0])
    from calib.importers import import_calibration

    return import_calibration(fmt, files)[0]


def open_dataset(path: str, calibration=None, topics: tuple[str | None, str | None, str | None] | None = None,
                 bag=None):
    """A EuRoC folder, or a bag / MCAP file (vio.io.bag): `bag` is the [bag] config section (None: its
    defaults, EuRoC's names), and the (left, right, imu) `topics` given on the command line win over it."""
    from vio.io.bag import BAG_SUFFIXES, BagDataset, BagTopics, is_bag

    if Path(path).suffix in BAG_SUFFIXES and not Path(path).exists():
        raise VioError(f"{path}: file not found")
    if is_bag(path):
        from vio.config import BagConfig

        return BagDataset(path, calibration, BagTopics.from_config(bag or BagConfig(), *(topics or ())))
    from vio.io.euroc import EurocDataset

    return EurocDataset(path, calibration)


def check_map_not_replaced(save: str, load: str | None, key: str) -> None:
    """Refuse (VioError, one line) to save a map over a file this run did not load: a map is the work of every
    flight that grew it, and `--save-map room.npz` without `--load-map room.npz` replaced it with this flight's
    alone, unsaid. Growing it (the same file loaded, by any name, link or hard link) is fine; --overwrite-map allows
    the rest."""
    from vio.io.outputs import same_file

    if not os.path.exists(save) or (load and same_file(load, save)):
        return
    raise VioError(f"{key}: a file is there already and this replay does not load it: not replaced "
                   f"(--load-map {save} grows that map, --overwrite-map replaces it)")


def run(args: argparse.Namespace) -> int:
    from vio.config import load_config

    if args.threads:  # 0: OpenCV's own pool
        from vio.frontend.runner import set_opencv_threads

        set_opencv_threads(args.threads)
    cfg = load_config(args.config)
    save_map = args.save_map or cfg.map.save
    load_map = args.load_map or cfg.map.load
    if args.calibration and args.calib:  # --calib was ignored, unsaid: the replay ran on --calibration alone
        raise UsageError("--calibration and --calib both give the calibration: give one")
    check_calib_format(args)
    if args.overwrite_map and not save_map:  # it was accepted and did nothing: the user thought a map was written
        raise UsageError("--overwrite-map: there is no map to write; give --save-map FILE (or [map] save)")
    if args.mavlink:  # a connection string that can never open: said before any output file is opened
        from drivers.mavlink_link import check_url

        check_url(args.mavlink, "--mavlink")
    view_file = args.view if args.view and args.view != "serve" else None
    if view_file and not view_file.endswith(".rrd"):  # it is written over: never a recording or a calibration
        raise UsageError(f"--view {view_file}: a live view recording is an .rrd file (or 'serve' for a web viewer)")
    check_outputs({"the trajectory": args.output, "the loop-corrected trajectory": args.loop_output,
                   "the map": save_map, "the stats": args.stats, "the loop plot": args.loop_plot,
                   "the live view recording": view_file},
                  reads={"the map it loads": load_map, "the calibration": args.calibration,
                         "the recording it replays": args.dataset, **{f"--calib {c}": c for c in args.calib or []},
                         "the vocabulary": cfg.loop.vocabulary, "the configuration": args.config},
                  grows={"the map": "the map it loads"}, recordings=(args.dataset,),
                  folders={"the track images": args.show_tracks}, renamed=("the map",))
    if save_map and not args.overwrite_map:
        check_map_not_replaced(save_map, load_map, f"--save-map {save_map}" if args.save_map
                               else f"[map] save = {save_map!r}")
    if args.loop_plot:  # the [tools] extra and the plot's format, asked for now rather than after the replay
        from vio.evaluation import require_plot

        require_plot(args.loop_plot, "loop-closure plot (--loop-plot)")
    if args.view:  # the [view] extra and the ports to serve on, asked for before the recording is opened and read
        from vio.app.view import check_view

        check_view(args.view, cfg.view, "the live view (--view)")
    endpoint_lock = None
    if args.mavlink:  # before the recording is read: a daemon (or a replay) already sends to that autopilot
        from vio.app.endpoint_lock import mavlink_endpoint_lock

        endpoint_lock = mavlink_endpoint_lock(args.mavlink, f"--mavlink {args.mavlink}",
                                              "replay to another autopilot (or without --mavlink)")
    try:
        return _run(args, cfg, save_map, load_map, view_file)
    finally:
        if endpoint_lock is not None:  # held to the replay's end, past its last pose (mav.close() in _run)
            endpoint_lock.close()


def _run(args: argparse.Namespace, cfg: VioConfig, save_map: str, load_map: str, view_file: str | None) -> int:
    """run()'s replay itself, once the options are checked (and --mavlink's endpoint held)."""
    from vio.calibration import load_calibration

    calib = load_calibration(args.calibration) if args.calibration else load_calib_args(args.calib,
                                                                                          args.calib_format)
    if calib is not None:  # --calib, meant for bags, replaced a EuRoC folder's calibration unsaid
        log.info("calibration: %s (%s); the recording's own, if it has one, is not used",
                 " ".join(args.calib or [args.calibration]), "--calib" if args.calib else "--calibration")
    dataset = open_dataset(args.dataset, calib, (args.left_topic, args.right_topic, args.imu_topic), cfg.bag)
    preflight(dataset)  # before any output is opened: a data problem must not empty an earlier run's files
    loop = None
    if args.loop or cfg.loop.enabled or args.loop_output or args.loop_plot or save_map or load_map:
        from vio.app.loop_worker import LoopWorker
        from vio.loop.closer import LoopCloser

        closer = LoopCloser(dataset.calibration, cfg.loop)
        if load_map:  # read before any output file is opened: a bad map must not cost an old trajectory file
            from vio.loop.mapfile import load_map as read_map

            closer.load_map(read_map(load_map))
        loop = LoopWorker(closer, max_queue=100000)  # replay: keep every keyframe
    view = None
    if args.view:  # before any output file is opened (checked above, a port may have been taken since)
        from vio.app.view import LiveView

        view = LiveView(args.view, dataset.calibration, cfg.view, loop=loop)
    sinks: list[Sink] = []
    tum = TumSink(args.output, keep_existing=True) if args.output else None
    if tum is not None:
        sinks.append(tum)
    mav = None
    if args.mavlink:
        from drivers.mavlink_out import MavlinkOutput, restamp_to_host_clock

        mav = MavlinkOutput(cfg.mavlink, args.mavlink, T_body_cam0=dataset.calibration.cam0.T_body_cam,
                            max_state_age_ms=cfg.mavlink.max_state_age_ms, poses_to_armed=False).start()
        sink = restamp_to_host_clock(mav)
        if loop is not None and cfg.loop.output != "off":  # the autopilot gets the loop-corrected pose
            sink = corrected_sink(sink, loop, cfg)
        sinks.append(sink)
    try:
        res = replay(dataset, cfg, sinks, realtime=args.realtime or bool(args.mavlink),
                     show_tracks=args.show_tracks, max_frames=args.max_frames, progress=not args.no_progress,
                     loop=loop, view=view)
    except BaseException:  # a data error or Ctrl-C mid-replay: where its poses are, beside the file kept
        if tum is not None and tum.kept_note():
            log.warning("replay stopped: %s", tum.kept_note())
        raise
    finally:
        if view is not None:
            view.close()
        if tum is not None:
            tum.close()
        if mav is not None:
            mav.close()
    if tum is not None and res.vision_problem() is None:  # else an earlier run's file stays (kept_note says so)
        tum.commit()
    print(f"replay: {res.frames} frames, {len(res.states)} poses, {res.data_s:.1f} s of data in {res.wall_s:.1f} s "
          f"(real-time factor {res.realtime_factor:.2f}), {res.resets} resets")
    if view is not None:
        vs = view.stats()
        res.extra["view"] = vs
        print(f"view: {vs['logged']} of {vs['submitted']} frames logged ({vs['images']} images), {vs['thinned']} "
              f"thinned to [view] rate_hz/image_hz, {vs['dropped']} dropped (viewer stuck), cost in the frame loop "
              f"mean {vs['submit_ms']['mean']:.3f} ms, max {vs['submit_ms']['max']:.3f} ms"
              + (f"; {args.view}" if args.view != "serve" else ""))
    if mav is not None:
        res.extra["mavlink"], line = mavlink_summary(mav.stats, args.mavlink)
        print(line)
    from vio.estimator import motion_check_line, stereo_check_line
    from vio.frame_clock import frame_stamps_line

    for line in (stereo_check_line(res.extra.get("stereo_check")), motion_check_line(res.extra.get("motion_check")),
                 frame_stamps_line(res.extra.get("frame_stamps"))):
        if line:
            print(line)
    refined = res.extra.get("calibration_refined")
    if refined:  # [backend] refine_stereo_rotation / refine_extrinsics: what the flight taught about the rig
        if "disparity_sigma_px" in refined:
            print(f"calibration: cam1 turned {refined['stereo_change_deg']:.4f} deg, a disparity bias of "
                  f"{refined['disparity_px']:+.2f} +- {refined['disparity_sigma_px']:.2f} px (1 sigma) taken out")
        else:
            print(f"calibration: T_body_cam0 moved {refined['cam0_change_deg']:.3f} deg, "
                  f"{refined['cam0_change_mm']:.2f} mm; cam1 relative to cam0 {refined['stereo_change_deg']:.4f} "
                  f"deg, over {refined['refining_keyframes']} refining keyframes")
    if res.frame_stats:
        sd = res.stats_dict()["timing_ms"]
        print("per frame [ms]: " + ", ".join(f"{k[:-3]} mean {v['mean']:.1f} p95 {v['p95']:.1f}"
                                             for k, v in sd.items()))
    eval_dict = None
    if dataset.groundtruth_problem:
        print("replay: no accuracy figures: the ground truth was not usable")
    if dataset.groundtruth is not None and len(res.states) >= 3:
        from vio.evaluation import evaluate

        try:
            ev = evaluate(res.trajectory(), dataset.groundtruth.trajectory)
            print(ev.summary())
            eval_dict = ev.to_dict()
        except VioError as e:
            print(f"replay: no accuracy figures: {e}")
    loop_dict, draw, map_problem = None, None, None
    kept = [tum.kept_note()] if tum is not None and tum.kept_note() else []
    if loop is not None:
        loop_path = args.loop_output
        if loop_path and res.vision_problem() and os.path.isfile(loop_path):  # an earlier run's stays, as for -o
            real = os.path.realpath(loop_path)
            loop_path = f"{real}.partial"
            kept.append(f"the loop-corrected poses are in {loop_path}; {real} is kept as it was")
        loop_dict, draw = _loop_outputs(loop, res, dataset, loop_path, args.loop_plot)
        if save_map:
            try:
                h = loop.closer.save_map(save_map, cfg.map.prune_m, cfg.map.prune_deg)
            except VioError as e:  # the stats and plot are still written; the exit status says it
                map_problem = str(e)
            else:
                print(f"map: {h['keyframes']} keyframes, {h['descriptors']} descriptors -> {h['path']}"
                      + (f", {h['pruned_keyframes']} of this flight's not saved (views the map has: [map] prune_m)"
                         if h["pruned_keyframes"] else "")
                      + (f" ({h['note']})" if h["left_out_keyframes"] else ""))
                if h["conflict"]:
                    print(f"vio replay: {h['conflict']}", file=sys.stderr)
    if args.stats:
        d = res.stats_dict()
        if loop_dict is not None:
            d["loop"] = loop_dict
        if eval_dict is not None:
            d["evaluation"] = eval_dict
        try:
            Path(args.stats).write_text(json.dumps(d, indent=1))
        except OSError as e:
            raise VioError(f"{args.stats}: cannot write stats ({e.strerror})") from None
    if draw is not None:  # last: the map and the stats are written whatever the plot does
        draw()
    problem = res.vision_problem()
    if problem and map_problem:
        print(f"vio replay: error: {map_problem}", file=sys.stderr)
    if problem and kept:
        problem = f"{problem} ({'; '.join(kept)})"
    if problem or map_problem:
        raise VioError(problem or map_problem)
    return 0
