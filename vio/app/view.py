"""Live view to Rerun (rerun-sdk, the [view] extra): `vio replay --view [FILE.rrd|serve]`, `[view]` for `vio run`.

The frame loop never waits for the viewer: `LiveView.submit()` puts a small tuple (references to the image,
the front-end output and the state, no copies) into a bounded queue and returns; a daemon thread turns the
items into Rerun log calls. When the queue is full (a slow viewer, a slow disk) the item is dropped and
counted, never waited for. `submit_ms` records the cost each call had in the frame loop.

Entities (timeline `sensor_time`, the frame's stamp):

    camera/left            rr.Image, the left image (8-bit grey)
    camera/left/tracks     rr.Points2D, tracked features (undistorted pixels; green: stereo, orange: mono)
    world/body             rr.Transform3D, T_world_body
    world/trajectory/odometry  rr.LineStrips3D, the estimated path so far (a loop-corrected path will go beside it
                           as world/trajectory/loop once loop closure exists)
    world/keyframes        rr.Points3D, keyframe positions
    world/landmarks        rr.Points3D, this frame's stereo points in the world frame
    world/covariance       rr.Ellipsoids3D, 3-sigma position covariance at the body
    health/<counter>       rr.Scalars: tracks, stereo, resets, keyframes, frames dropped by the view

Rerun rather than Foxglove as the one default: one pip package with its own viewer, a saved .rrd opens offline
on a laptop after the flight, and `serve` gives a browser viewer on the companion computer without a ROS
stack; Foxglove users get the MCAP recording (`vio record --format mcap`) instead.
"""

from __future__ import annotations

import logging
import queue
import threading
import time

import numpy as np

from vio.extras import require

log = logging.getLogger(__name__)


class LiveView:
    def __init__(self, target: str, calibration, queue_size: int = 4, web_port: int | None = None,
                 trajectory_every: int = 5) -> None:
        """`target`: a path ending in .rrd (saved), or 'serve' (a gRPC server plus the web viewer).
        `calibration`: a StereoCalibration or a callable returning one (None: no landmarks yet)."""
        self.rr = rr = require("rerun", "view", "the live view")
        self.calibration = calibration
        self.rec = rr.RecordingStream("kestrel-vio")
        self.url = None
        if target == "serve":
            self.url = self.rec.serve_grpc()
            rr.serve_web_viewer(web_port=web_port, open_browser=False, connect_to=self.url)
            log.info("live view: open the web viewer (port %s), connected to %s", web_port or 9090, self.url)
        else:
            self.rec.save(target)
        self._q: queue.Queue = queue.Queue(maxsize=queue_size)
        self.dropped = 0
        self.logged = 0
        self.submit_ms: list[float] = []
        self._path: list[np.ndarray] = []
        self._kf: list[np.ndarray] = []
        self._every = max(1, trajectory_every)
        self.errors = 0
        self._thread = threading.Thread(target=self._loop, name="live-view", daemon=True)
        self._thread.start()

    # -- frame loop side ---------------------------------------------------------------------------------
    def submit(self, t_ns: int, left, features, state, keyframe: bool, counters: dict) -> None:
        t0 = time.perf_counter()
        try:
            self._q.put_nowait((t_ns, left, features, state, keyframe, counters))
        except queue.Full:
            self.dropped += 1
        self.submit_ms.append((time.perf_counter() - t0) * 1e3)

    def close(self, timeout_s: float = 5.0) -> None:
        deadline = time.monotonic() + timeout_s
        while self._thread.is_alive() and time.monotonic() < deadline:
            try:
                self._q.put(None, timeout=0.1)
                break
            except queue.Full:
                continue
        self._thread.join(max(0.0, deadline - time.monotonic()))
        self.rec.flush()
        self.rec.disconnect()

    def stats(self) -> dict:
        x = np.array(self.submit_ms or [0.0])
        return {"logged": self.logged, "dropped": self.dropped, "errors": self.errors,
                "submit_ms": {"mean": float(x.mean()), "p99": float(np.percentile(x, 99)), "max": float(x.max())}}

    # -- viewer thread ------------------------------------------------------------------------------------
    def _loop(self) -> None:
        while True:
            item = self._q.get()
            if item is None:
                return
            try:
                self._log(*item)
                self.logged += 1
            except Exception as e:  # the view must never take the estimator down
                self.errors += 1
                if self.errors == 1:
                    log.warning("live view: %s: %s (further errors counted)", type(e).__name__, e)

    def _log(self, t_ns: int, left, ff, st, keyframe: bool, counters: dict) -> None:
        rr, rec = self.rr, self.rec
        rec.set_time("sensor_time", timestamp=np.datetime64(int(t_ns), "ns"))
        if left is not None:
            rec.log("camera/left", rr.Image(left))
        if ff is not None and len(ff.ids):
            stereo = np.isfinite(ff.depth_m)
            colors = np.where(stereo[:, None], [[60, 220, 60]], [[255, 150, 0]]).astype(np.uint8)
            rec.log("camera/left/tracks", rr.Points2D(ff.uv0, colors=colors, radii=2.0))
        n_stereo = 0 if ff is None else int(np.isfinite(ff.depth_m).sum())
        if st is not None:
            T = np.asarray(st.T_world_body)
            p = T[:3, 3]
            rec.log("world/body", rr.Transform3D(translation=p, mat3x3=T[:3, :3]))
            self._path.append(p.copy())
            if keyframe:
                self._kf.append(p.copy())
                rec.log("world/keyframes", rr.Points3D(np.array(self._kf), radii=0.02))
            if len(self._path) % self._every == 1 or keyframe:
                rec.log("world/trajectory/odometry", rr.LineStrips3D([np.array(self._path)]))
            cov = getattr(st, "cov_pose", None)
            if cov is not None:  # GTSAM order (rot, pos), body frame: position block rotated into the world
                P = T[:3, :3] @ np.asarray(cov)[3:, 3:] @ T[:3, :3].T
                w, V = np.linalg.eigh(0.5 * (P + P.T))
                q = _quat_xyzw(V if np.linalg.det(V) > 0 else -V)
                rec.log("world/covariance", rr.Ellipsoids3D(centers=[p], half_sizes=[3 * np.sqrt(np.maximum(w, 0))],
                                                            quaternions=[q]))
            calib = self.calibration() if callable(self.calibration) else self.calibration
            if ff is not None and n_stereo and calib is not None:
                cam = calib.cam0
                uv, z = ff.uv0[np.isfinite(ff.depth_m)], ff.depth_m[np.isfinite(ff.depth_m)]
                xyz_c = np.column_stack([(uv[:, 0] - cam.cx) / cam.fx * z, (uv[:, 1] - cam.cy) / cam.fy * z, z])
                T_wc = T @ cam.T_body_cam
                rec.log("world/landmarks", rr.Points3D(xyz_c @ T_wc[:3, :3].T + T_wc[:3, 3], radii=0.01))
        counters = {**counters, "tracks": 0 if ff is None else len(ff.ids), "stereo": n_stereo,
                    "view_dropped": self.dropped}
        for k, v in counters.items():
            rec.log(f"health/{k}", rr.Scalars(float(v)))


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
