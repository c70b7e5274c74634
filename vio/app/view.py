"""Live view to Rerun (rerun-sdk, the [view] extra): `vio replay --view [FILE.rrd|serve]`, `[view]` for `vio run`.

The frame loop never waits for the viewer and does almost nothing for it: `LiveView.submit()` appends a tuple
of references (the image, the front end's output, the state, the counters; no copies, no conversion) to a
bounded deque and returns. No lock, no condition variable: nothing in submit() wakes the view thread, so the
frame loop is never switched out there (on a busy core a wake-up can cost it its time slice). When
`queue_frames` items wait (a stuck viewer) the oldest is dropped and counted. Everything else happens in the
view thread, which is kept cheap because on the companion computer it shares the cores (and in Python the GIL)
with the estimator: it wakes at twice its highest rate (every 100 ms by default), takes what waits, keeps the
path and keyframes of every frame, and logs only the newest frame at bounded wall-clock rates: the body pose
and landmarks at `[view] rate_hz` (default 5 Hz), the image, downscaled and JPEG-encoded by OpenCV (which
releases the GIL), with its tracks at `image_hz` (default 2 Hz), and what changes slowly or grows with the
flight (the path, keyframes, covariance, counters, loop closure) every second. Frames it passes over are
counted as thinned, not dropped. Each Rerun entity costs some 0.2 ms of Python per log (archetype, Arrow
arrays), so the rates, not the frame rate, set the view's CPU.

Entities (timeline `sensor_time`, the frame's stamp):

    camera/left                rr.EncodedImage, the left image (JPEG, scaled by image_scale)
    camera/left/tracks         rr.Points2D, tracked features (undistorted pixels, scaled as the image;
                               green: stereo, orange: mono), with each image
    world/body                 rr.Transform3D, T_world_body
    world/trajectory/odometry  rr.LineStrips3D, the odometry path so far
    world/keyframes            rr.Points3D, odometry keyframe positions
    world/landmarks            rr.Points3D, the newest keyframe's stereo points in the world frame
    world/covariance           rr.Ellipsoids3D, 3-sigma position covariance at the body
    world/trajectory/loop      rr.LineStrips3D, loop-corrected keyframe path (one strip per odometry segment),
                               with loop closure on
    world/loop/keyframes       rr.Points3D, loop-corrected keyframe positions
    world/loop/edges           rr.LineStrips3D, accepted loop edges (green; red: rejected by the GNC solve)
    health/<counter>           rr.Scalars: tracks, stereo, resets, keyframes, view frames dropped, loop closures

Rerun rather than Foxglove as the one default: one pip package with its own viewer, a saved .rrd opens offline
on a laptop after the flight, and `serve` gives a browser viewer on the companion computer without a ROS
stack; Foxglove users get the MCAP recording (`vio record --format mcap`) instead.
"""

from __future__ import annotations

import collections
import logging
import threading
import time

import cv2
import numpy as np

from vio import VioError
from vio.config import ViewConfig
from vio.extras import require

log = logging.getLogger(__name__)

_STEREO, _MONO = (60, 220, 60), (255, 150, 0)
_SLOW_S = 1.0  # path, keyframes, covariance, counters and loop closure: at most this often
_MAX_POINTS = 20_000  # path / keyframe points kept before every second one goes (bounded memory and log cost)
GRPC_PORT = 9876  # the gRPC port 'serve' opens (Rerun's default, given explicitly so that check_view probes it)


def check_view(target: str, settings: ViewConfig | None = None, what: str = "the live view") -> None:
    """What a live view to `target` needs, asked for before any work (as vio.evaluation.require_plot for a plot):
    the [view] extra, and for 'serve' its web and gRPC ports free on this computer. A port another program (or a
    second replay with --view) held ended the replay in "internal error: RuntimeError: Failed to create server:
    Address already in use", after the recording was opened and read (a review's finding). VioError, one line."""
    import errno
    import socket

    require("rerun", "view", what)
    if target != "serve":
        return
    s = settings or ViewConfig()
    if s.web_port == GRPC_PORT:  # each port alone is free, and then the two servers collide
        raise VioError(f"{what}: [view] web_port = {GRPC_PORT} is the port the live view's gRPC server takes: set "
                       "another [view] web_port (e.g. 9090)")
    for port, key, fix in ((s.web_port, "[view] web_port", "set another [view] web_port"),
                           (GRPC_PORT, "Rerun's gRPC port", "a second live view?")):
        with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as probe:
            probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # as a server binds: TIME_WAIT is no use
            try:
                probe.bind(("0.0.0.0", port))
            except OSError as e:
                if e.errno in (errno.EACCES, errno.EPERM):  # nothing holds it: ports below 1024 need privileges
                    raise VioError(f"{what}: port {port} ({key}) may not be opened by this user (ports below 1024 "
                                   f"need privileges): {fix}, or save to FILE.rrd instead of serving") from None
                why = "in use by another program" if e.errno == errno.EADDRINUSE else (e.strerror or str(e))
                raise VioError(f"{what}: port {port} ({key}) is {why}: stop what holds it ({fix}), or save "
                               "to FILE.rrd instead of serving") from None


class LiveView:
    def __init__(self, target: str, calibration, settings: ViewConfig | None = None, loop=None) -> None:
        """`target`: a path ending in .rrd (saved), or 'serve' (a gRPC server plus the web viewer).
        `calibration`: a StereoCalibration or a callable returning one (None: no landmarks yet).
        `settings`: the [view] section (rates, image size and quality, queue, port); `loop`: a
        vio.app.loop_worker.LoopWorker whose corrected keyframes are shown (it is asked to keep snapshots)."""
        self.rr = rr = require("rerun", "view", "the live view")
        self.settings = s = settings or ViewConfig()
        self.calibration = calibration
        self.loop = loop
        if loop is not None:
            loop.keep_snapshot = True
        _warm_up(rr)
        self.rec = rr.RecordingStream("kestrel-vio")
        self.url = None
        if target == "serve":
            try:  # a port taken since check_view (or not checked: the daemon) is one line, not an internal error
                self.url = self.rec.serve_grpc(grpc_port=GRPC_PORT, server_memory_limit=f"{s.serve_memory_mb}MB")
                rr.serve_web_viewer(web_port=s.web_port, open_browser=False, connect_to=self.url)
            except RuntimeError as e:
                raise VioError(f"the live view cannot serve: {e}") from None
            log.info("live view: open the web viewer (port %s), connected to %s", s.web_port, self.url)
        else:
            self.rec.save(target)
        self._q: collections.deque = collections.deque(maxlen=s.queue_frames)  # append/popleft: atomic in CPython
        self._stop = threading.Event()
        self.submitted = 0
        self.dropped = 0  # queue full: the view thread was stuck
        self.thinned = 0  # passed over by the view thread to keep its rate
        self.logged = 0  # frames logged (state and counters; images at image_hz)
        self.images = 0
        self.errors = 0
        self.thread_cpu_s = 0.0  # the view thread's own CPU time, when it has stopped (not Rerun's threads)
        self._submit_sum_ms = 0.0
        self._submit_max_ms = 0.0
        self._submit_recent: collections.deque = collections.deque(maxlen=10_000)  # p99 (a daemon runs for days)
        self._path: list[np.ndarray] = []
        self._kf: list[np.ndarray] = []
        self._kf_logged = 0
        self._next_slow = 0.0
        self._last_state_item = None  # the newest item logged with its state
        self._stereo_item = None  # the newest keyframe with stereo points not logged yet (world/landmarks)
        self._loop_version = -1
        self._thread = threading.Thread(target=self._loop, name="live-view", daemon=True)
        self._thread.start()

    # -- frame loop side ---------------------------------------------------------------------------------
    def submit(self, t_ns: int, left, features, state, keyframe: bool, counters: dict) -> None:
        """Hand one processed frame over; never blocks, never copies."""
        t0 = time.perf_counter()
        q = self._q
        if len(q) == q.maxlen:  # the view thread is stuck: the oldest waiting frame goes (a count, not a lock)
            self.dropped += 1
        q.append((t_ns, left, features, state, keyframe, counters))
        self.submitted += 1
        ms = (time.perf_counter() - t0) * 1e3
        self._submit_sum_ms += ms
        self._submit_max_ms = max(self._submit_max_ms, ms)
        self._submit_recent.append(ms)

    def close(self, timeout_s: float = 5.0) -> None:
        self._stop.set()
        self._thread.join(timeout_s)
        self.rec.flush()
        self.rec.disconnect()

    def stats(self) -> dict:
        recent = np.array(self._submit_recent or [0.0])
        return {"submitted": self.submitted, "logged": self.logged, "images": self.images, "thinned": self.thinned,
                "dropped": self.dropped, "errors": self.errors,
                "thread_cpu_s": self.thread_cpu_s,
                "submit_ms": {"mean": self._submit_sum_ms / max(1, self.submitted),
                              "p99": float(np.percentile(recent, 99)), "max": self._submit_max_ms}}

    # -- view thread --------------------------------------------------------------------------------------
    def _loop(self) -> None:
        s = self.settings
        poll_s = min(0.1, max(0.01, 0.5 / max(s.rate_hz, s.image_hz)))  # wake-ups cost CPU too: twice the rate
        next_state = next_image = 0.0
        pending = None  # the newest item not logged yet (logged at the end)
        while True:
            stop = self._stop.wait(poll_s)
            items = []
            while self._q:
                items.append(self._q.popleft())
            for it in items:  # the path and keyframes of every frame (cheap), whatever is logged
                st = it[3]
                if st is not None:
                    p = np.asarray(st.T_world_body)[:3, 3].copy()
                    self._path.append(p)
                    if it[4]:
                        self._kf.append(p)
                        if it[2] is not None and np.isfinite(it[2].depth_m).any():
                            self._stereo_item = it  # stereo depth comes with keyframes
            for pts in (self._path, self._kf):  # a daemon flies for hours: older history at half the density
                if len(pts) > _MAX_POINTS:
                    pts[:] = pts[::-2][::-1]  # every second one, the newest kept
                    self._kf_logged = -1
            if items:
                if pending is not None:
                    self.thinned += 1
                self.thinned += len(items) - 1
                pending = items[-1]
            now = time.monotonic()
            with_state = now >= next_state or stop
            with_image = (now >= next_image or stop) and pending is not None and pending[1] is not None
            logged_now = False
            if pending is not None and (with_state or with_image):
                self._log_safely(pending, with_state, with_image)
                logged_now = True  # at stop: with everything (the path, the loop closure's final state)
                if with_state:
                    self._last_state_item = pending
                    next_state = now + 1.0 / s.rate_hz
                if with_image:
                    next_image = now + 1.0 / s.image_hz
                pending = None
            if stop:
                if not logged_now:  # the newest frame was logged already: its slow part once more, complete
                    self._final(self._last_state_item)
                self.thread_cpu_s = time.thread_time()
                return

    def _log_safely(self, item, with_state: bool, with_image: bool) -> None:
        try:
            self._log(item, with_state, with_image)
            self.logged += 1
        except Exception as e:  # the view must never take the estimator down
            self.errors += 1
            if self.errors == 1:
                log.warning("live view: %s: %s (further errors counted)", type(e).__name__, e)

    def _log(self, item, with_state: bool, with_image: bool) -> None:
        t_ns, left, ff, st, _keyframe, counters = item
        rr, rec, s = self.rr, self.rec, self.settings
        rec.set_time("sensor_time", timestamp=np.datetime64(int(t_ns), "ns"))
        stereo = None if ff is None else np.isfinite(ff.depth_m)
        if with_image:
            img = left
            if s.image_scale != 1.0:
                img = cv2.resize(left, None, fx=s.image_scale, fy=s.image_scale, interpolation=cv2.INTER_AREA)
            ok, jpg = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, s.jpeg_quality])
            if ok:
                rec.log("camera/left", rr.EncodedImage(contents=jpg.tobytes(), media_type="image/jpeg"))
                self.images += 1
            if ff is not None and len(ff.ids):
                colors = np.where(stereo[:, None], [_STEREO], [_MONO]).astype(np.uint8)
                rec.log("camera/left/tracks", rr.Points2D(np.asarray(ff.uv0) * s.image_scale, colors=colors,
                                                          radii=2.0))
        if not with_state:
            return
        n_stereo = 0 if stereo is None else int(stereo.sum())
        if st is not None:
            T = np.asarray(st.T_world_body)
            rec.log("world/body", rr.Transform3D(translation=T[:3, 3], mat3x3=T[:3, :3]))
        lm, self._stereo_item = self._stereo_item, None
        calib = self.calibration() if callable(self.calibration) else self.calibration
        if lm is not None and calib is not None:  # the newest keyframe's stereo points, once
            ff_k, T = lm[2], np.asarray(lm[3].T_world_body)
            ok = np.isfinite(ff_k.depth_m)
            cam = calib.cam0
            uv, z = ff_k.uv0[ok], ff_k.depth_m[ok]
            xyz_c = np.column_stack([(uv[:, 0] - cam.cx) / cam.fx * z, (uv[:, 1] - cam.cy) / cam.fy * z, z])
            T_wc = T @ cam.T_body_cam
            rec.log("world/landmarks", rr.Points3D(xyz_c @ T_wc[:3, :3].T + T_wc[:3, 3], radii=0.01))
        now = time.monotonic()
        if now >= self._next_slow or self._stop.is_set():
            self._next_slow = now + _SLOW_S
            self._log_slow(st, ff, n_stereo, counters)

    def _log_slow(self, st, ff, n_stereo: int, counters: dict) -> None:
        """What changes slowly or costs more the longer the flight (the whole path): every _SLOW_S."""
        rr, rec = self.rr, self.rec
        if st is not None:
            T = np.asarray(st.T_world_body)
            if self._path:
                rec.log("world/trajectory/odometry", rr.LineStrips3D([np.array(self._path)]))
            if len(self._kf) != self._kf_logged:
                self._kf_logged = len(self._kf)
                rec.log("world/keyframes", rr.Points3D(np.array(self._kf), radii=0.02))
            cov = getattr(st, "cov_pose", None)
            if cov is not None:  # GTSAM order (rot, pos), body frame: position block rotated into the world
                P = T[:3, :3] @ np.asarray(cov)[3:, 3:] @ T[:3, :3].T
                w, V = np.linalg.eigh(0.5 * (P + P.T))
                q = _quat_xyzw(V if np.linalg.det(V) > 0 else -V)
                rec.log("world/covariance", rr.Ellipsoids3D(centers=[T[:3, 3]],
                                                            half_sizes=[3 * np.sqrt(np.maximum(w, 0))],
                                                            quaternions=[q]))
        counters = {**counters, "tracks": 0 if ff is None else len(ff.ids), "stereo": n_stereo,
                    "view_dropped": self.dropped}
        if self.loop is not None:
            counters["loop_closures"] = self._log_loop()
        for k, v in counters.items():
            rec.log(f"health/{k}", rr.Scalars(float(v)))

    def _final(self, item) -> None:
        """The complete path, keyframes, counters and the loop worker's final state, at the end."""
        try:
            if item is not None:
                t_ns, _left, ff, st, _kf, counters = item
                self.rec.set_time("sensor_time", timestamp=np.datetime64(int(t_ns), "ns"))
                n_stereo = 0 if ff is None else int(np.isfinite(ff.depth_m).sum())
                self._log_slow(st, ff, n_stereo, counters)
            elif self.loop is not None:
                self._log_loop()
        except Exception as e:  # as _log_safely
            self.errors += 1
            log.warning("live view: %s: %s", type(e).__name__, e)

    def _log_loop(self) -> int:
        """The loop-corrected keyframes and loop edges, when the loop worker has processed a new keyframe."""
        rr, rec = self.rr, self.rec
        snap = self.loop.snapshot()
        if snap is None or not len(snap.positions):
            return 0
        if snap.version != self._loop_version:
            self._loop_version = snap.version
            P = snap.positions
            cuts = np.flatnonzero(np.diff(snap.sessions)) + 1
            rec.log("world/trajectory/loop", rr.LineStrips3D(np.split(P, cuts), colors=[(80, 160, 255)]))
            rec.log("world/loop/keyframes", rr.Points3D(P, radii=0.03, colors=[(80, 160, 255)]))
            if snap.loop_edges:
                rec.log("world/loop/edges", rr.LineStrips3D(
                    [P[[i, j]] for i, j, _ in snap.loop_edges],
                    colors=[_STEREO if w >= 0.5 else (230, 40, 40) for _, _, w in snap.loop_edges]))
        return snap.closures


def _warm_up(rr) -> None:
    """Build each archetype once: the first construction imports rerun's component modules (about 0.25 s of
    CPU), which belongs to start-up, not to the view thread's first frames beside a flying estimator."""
    z3 = np.zeros((1, 3))
    rr.Transform3D(translation=z3[0], mat3x3=np.eye(3))
    rr.Points2D(np.zeros((1, 2)), colors=np.zeros((1, 3), np.uint8), radii=1.0)
    rr.Points3D(z3, radii=0.01)
    rr.LineStrips3D([np.zeros((2, 3))], colors=[(0, 0, 0)])
    rr.Ellipsoids3D(centers=z3, half_sizes=[[1.0, 1.0, 1.0]], quaternions=[[0.0, 0.0, 0.0, 1.0]])
    rr.EncodedImage(contents=b"", media_type="image/jpeg")
    rr.Scalars(0.0)


def _quat_xyzw(R: np.ndarray) -> np.ndarray:
    from vio.geometry import rot_to_quat_wxyz

    w, x, y, z = rot_to_quat_wxyz(R)
    return np.array([x, y, z, w])


def rrd_entities(path) -> dict[str, int]:
    """Entity path -> rows in a saved .rrd, read back with rerun's own chunk reader."""
    chunk = require("rerun.chunk", "view", "reading an .rrd")
    out: dict[str, int] = {}
    for ch in chunk.RrdReader(str(path)).stream():
        out[ch.entity_path] = out.get(ch.entity_path, 0) + ch.num_rows
    return out
