"""A stereo camera rendered by the project's simulator at the pose an autopilot SITL reports as its truth.

`[source] kind = "sitl"`: for the closed-loop test (bench/sitl/, docs/autopilot.md "Closed-loop SITL test")
the autopilot's simulator flies the vehicle, and this source is its camera. It listens to the SITL's own
truth message SIM_STATE (ArduPilot sends it on request; q = FRD body in NED, lat/lon in 1e-7 degrees,
altitude AMSL), asks for it at the camera rate, and renders each pose with vio/sim's CameraRenderer in
vio/sim's default room. It delivers frames only: the IMU must come from the autopilot too (`imu =
"mavlink"`), so that images and IMU describe the same simulated flight.

Frames (why the conversions look as they do):
- NED offsets from `home` (the SITL's `--home`) by a flat-earth approximation: errors are micrometres over
  the few metres a room allows.
- world (z up) = (north, -east, -down) + `HOME_WORLD_M`: the vehicle starts in the middle of the room, its
  reference point a little above the floor. R_world_ned is the half turn about x that docs/autopilot.md
  uses at the MAVLink edge, so the estimator's world x is north.
- body = the autopilot's FRD IMU frame (the IMU samples come from the autopilot unrotated), so the
  simulator's forward stereo head (defined on an FLU body) is re-expressed in FRD: T_frd_cam = R_frd_flu @
  T_flu_cam. `[mavlink] mount = "camera-forward"` then finds the IMU square to the airframe.

Stamps: a frame is stamped with the host clock when its SIM_STATE arrived. A thread of its own reads and
stamps the stream, and the rendering takes the newest state: read between renders, a SIM_STATE that waited in
the socket while a frame was rendered (tens of ms at 320x200) was stamped that much late, and the frames of
the 2026-12-07 restart flight came 35-99 ms apart around a 65 ms period. The SITL must run in real time
(`--speedup 1`), since the IMU source maps the autopilot's clock onto the host clock with a drift estimator
made for crystal errors, not for a simulation running at half speed.

Faults: while `blackout_file` exists every frame is black (a covered lens: the front end rejects it as too
dark), for the harness's 2 s and 10 s camera blackouts.
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import math
import os
import threading
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from drivers.base import DropOldestQueue, Message, ThreadedSource
from vio import VioError
from vio.calibration import StereoCalibration
from vio.geometry import make_T, quat_wxyz_to_rot
from vio.types import StereoFrame

log = logging.getLogger(__name__)

EARTH_RADIUS_M = 6_378_137.0  # WGS-84 equatorial radius: the flat-earth offsets' scale
HOME_WORLD_M = np.array([0.0, 0.0, 0.2])  # where the SITL home lies in the simulator's room (centre, 0.2 m up)
R_WORLD_NED = np.diag([1.0, -1.0, -1.0])  # half turn about x (docs/autopilot.md, "Frames")
R_FRD_FLU = np.diag([1.0, -1.0, -1.0])
SIM_STATE_ID = 108
READ_TIMEOUT_S = 0.2
REQUEST_EVERY_S = 5.0  # SIM_STATE stream re-requested this often


def ned_from_geodetic(home: tuple[float, float, float], lat_e7: int, lon_e7: int, alt_m: float) -> np.ndarray:
    """(north, east, down) [m] of a position given as lat/lon in 1e-7 degrees and altitude AMSL, relative
    to `home` = (lat_deg, lon_deg, alt_m); flat earth, which is exact to micrometres within a room."""
    lat0, lon0, alt0 = home
    dlat = math.radians(lat_e7 * 1e-7 - lat0)
    dlon = math.radians(lon_e7 * 1e-7 - lon0)
    return np.array([dlat * EARTH_RADIUS_M, dlon * EARTH_RADIUS_M * math.cos(math.radians(lat0)), alt0 - alt_m])


def world_from_ned(ned: np.ndarray) -> np.ndarray:
    """World (z up) position(s) of NED offsets from home: (N, 3) or (3,)."""
    return np.asarray(ned, dtype=float) @ R_WORLD_NED.T + HOME_WORLD_M


def T_world_body_from_sim(q_wxyz_ned_frd: np.ndarray, ned: np.ndarray) -> np.ndarray:
    """T_world_body (body = FRD) from the SITL's attitude quaternion (FRD body -> NED, w first) and NED position."""
    R_ned_frd = quat_wxyz_to_rot(np.asarray(q_wxyz_ned_frd, dtype=float))
    return make_T(R_WORLD_NED @ R_ned_frd, world_from_ned(ned))


def frd_calibration(width: int, height: int, fps: float) -> StereoCalibration:
    """The simulator's forward-looking EuRoC-like stereo head, with its extrinsics on an FRD body (the autopilot's
    IMU axes). IMU noise: the defaults (a SITL IMU is quieter than that, and the estimator only needs bounds)."""
    from vio.sim import default_calibration

    calib = default_calibration(width=width, height=height, rate_hz=fps)
    T_frd_flu = make_T(R_FRD_FLU, np.zeros(3))
    cams = [dataclasses.replace(c, T_body_cam=T_frd_flu @ c.T_body_cam) for c in (calib.cam0, calib.cam1)]
    return StereoCalibration(cams[0], cams[1], calib.imu, calib.time_offset_ns)


class SitlCameraSource(ThreadedSource):
    """Stereo frames rendered at the pose of a SITL's SIM_STATE stream (frames only, no IMU)."""

    name = "sitl-camera"

    def __init__(self, url: str, home: tuple[float, float, float], *, width: int = 320, height: int = 200,
                 fps: float = 15.0, blackout_file: str = "", seed: int = 0, queue_frames: int = 4,
                 connect: Callable[[str], Any] | None = None, clock_ns: Callable[[], int] = time.monotonic_ns) -> None:
        super().__init__()
        if len(home) != 3 or not all(math.isfinite(float(x)) for x in home):
            raise VioError(f"[source] sitl_home must be [lat_deg, lon_deg, alt_m], got {list(home)!r}")
        self.url = url
        self.home = tuple(float(x) for x in home)
        self.width, self.height, self.fps = int(width), int(height), float(fps)
        self.blackout_file = blackout_file
        self.seed = seed
        self._connect = connect
        self._clock_ns = clock_ns
        self._frames = DropOldestQueue(queue_frames)
        self._calib = frd_calibration(self.width, self.height, self.fps)
        self._cams: list | None = None  # [(CameraRenderer, T_body_cam)], built on first use (about a second)
        self._next_ns = 0
        self.seq = 0
        self.states = 0  # SIM_STATEs the renderer took (the newest at each look)
        self.states_received = 0
        self.frames_black = 0
        self.render_ms = 0.0
        self.last_T_world_body: np.ndarray | None = None
        self._latest: tuple[Any, int] | None = None  # the newest SIM_STATE and its arrival stamp, for the renderer
        self._arrived = threading.Condition()

    # -- rendering (no I/O: tests call these directly) -----------------------------------------------------
    def _renderers(self) -> list:
        if self._cams is None:
            from vio.sim.render import CameraRenderer
            from vio.sim.scene import default_scene

            scene = default_scene(seed=self.seed)
            self._cams = [(CameraRenderer(c, scene), c.T_body_cam) for c in (self._calib.cam0, self._calib.cam1)]
        return self._cams

    def blacked_out(self) -> bool:
        return bool(self.blackout_file) and os.path.exists(self.blackout_file)

    def render(self, T_world_body: np.ndarray, t_ns: int) -> StereoFrame:
        """Both cameras at T_world_body, 8-bit; black while the blackout file exists."""
        t0 = time.perf_counter()
        if self.blacked_out():
            black = np.zeros((self.height, self.width), np.uint8)
            self.frames_black += 1
            frame = StereoFrame(t_ns, black, black.copy(), seq=self.seq)
        else:
            left, right = (np.clip(r.render(T_world_body @ T_bc)[0] + 0.5, 0, 255).astype(np.uint8)
                           for r, T_bc in self._renderers())
            frame = StereoFrame(t_ns, left, right, seq=self.seq)
        self.seq += 1
        self.render_ms += 0.1 * ((time.perf_counter() - t0) * 1e3 - self.render_ms)
        return frame

    def on_sim_state(self, msg: Any, t_ns: int) -> StereoFrame | None:
        """A SIM_STATE arrived at host time t_ns: a frame when one is due at the camera rate, else None."""
        self.states += 1
        lat = getattr(msg, "lat_int", 0) or int(round(msg.lat * 1e7))  # older SITLs: float degrees only
        lon = getattr(msg, "lon_int", 0) or int(round(msg.lon * 1e7))
        T = T_world_body_from_sim(np.array([msg.q1, msg.q2, msg.q3, msg.q4]),
                                  ned_from_geodetic(self.home, lat, lon, msg.alt))
        self.last_T_world_body = T
        period = int(1e9 / self.fps)
        # the stream comes at the camera rate, a state up to a quarter period early is this frame's (a faster
        # stream is thinned to the rate); keep the frame grid, after a stall (or at the start) re-anchor it
        # instead of bursting to catch up
        if t_ns < self._next_ns - period // 4:
            return None
        self._next_ns = self._next_ns + period if abs(t_ns - self._next_ns) < period else t_ns + period
        return self.render(T, t_ns)

    # -- source interface ----------------------------------------------------------------------------------
    def calibration(self) -> StereoCalibration:
        return self._calib

    def _open(self) -> Any:
        if self._connect is not None:
            return self._connect(self.url)
        from drivers.mavlink_link import open_connection

        return open_connection(self.url, source_system=255)

    def _request_stream(self, conn: Any) -> None:
        """MAV_CMD_SET_MESSAGE_INTERVAL for SIM_STATE at the camera rate: each state a frame, exposed as regularly
        as the SITL sends them (at twice the rate, the first state after each grid point made frames 33, 66 or
        100 ms apart at 15 Hz: the grid's phase against the stream's)."""
        conn.mav.command_long_send(1, 0, 511, 0, SIM_STATE_ID, 1e6 / self.fps, 0, 0, 0, 0, 0)

    def _run(self) -> None:
        self._renderers()
        backoff = 0.5
        while not self._stop.is_set():
            try:
                conn = self._open()
            except (OSError, ConnectionError) as e:
                self.state = f"connecting ({e})"
                self._stop.wait(backoff)
                backoff = min(5.0, backoff * 2)
                continue
            log.info("sitl camera: reading SIM_STATE from %s, rendering %dx%d at %.0f Hz", self.url, self.width,
                     self.height, self.fps)
            self.state = "running"
            with self._arrived:
                self._latest = None  # a state of the connection before, read after its last frame: not this one's
            heard_before = self.states_received
            done = threading.Event()
            failed: list[BaseException] = []
            reader = threading.Thread(target=self._receive, args=(conn, done, failed), name="sitl-camera-rx",
                                      daemon=True)
            reader.start()
            try:
                while not self._stop.is_set() and reader.is_alive():
                    with self._arrived:
                        if self._latest is None:
                            self._arrived.wait(READ_TIMEOUT_S)
                        item, self._latest = self._latest, None
                    if item is not None and (frame := self.on_sim_state(*item)) is not None:
                        self._frames.put(frame)
            finally:
                done.set()
                reader.join(timeout=2 * READ_TIMEOUT_S + 1)
                with contextlib.suppress(OSError, AttributeError):
                    conn.close()
            if failed and not self._stop.is_set():
                e = failed[0]
                log.warning("sitl camera: link to %s lost (%s); reconnecting in %.1f s", self.url,
                            e if isinstance(e, OSError) else f"{type(e).__name__}: {e}", backoff)
                self.state = "connecting"
                # backed off as a failed open is: a reader that fails at once (a reset socket, a decoding error)
                # reopened the link at once, thousands of times a second
                if self.states_received > heard_before:
                    backoff = 0.5
                self._stop.wait(backoff)
                backoff = min(5.0, backoff * 2)

    def _receive(self, conn: Any, done: threading.Event, failed: list[BaseException]) -> None:
        """Read and stamp SIM_STATE as it arrives, keeping only the newest for the renderer; ask for the stream
        every REQUEST_EVERY_S (a rebooted autopilot forgets message intervals) and right after the first message
        (a udpin link can only answer once the peer is known)."""
        requested_ns, heard = 0, False
        try:
            while not done.is_set() and not self._stop.is_set():
                now = self._clock_ns()
                if requested_ns == 0 or now - requested_ns > REQUEST_EVERY_S * 1e9:
                    self._request_stream(conn)
                    requested_ns = now
                msg = conn.recv_match(type="SIM_STATE", blocking=True, timeout=READ_TIMEOUT_S)
                if msg is None:
                    continue
                t_ns = self._clock_ns()
                self.states_received += 1
                if not heard:
                    heard, requested_ns = True, 0
                with self._arrived:
                    self._latest = (msg, t_ns)
                    self._arrived.notify()
        except Exception as e:  # noqa: BLE001 - an OSError, or pymavlink's own (ValueError...): either way, reconnect
            # any error, not only OSError: one that ended this thread silently had the renderer see it dead and
            # reopen the link at once, each time a thread traceback (17,572 opens in 3 s; a review's finding)
            failed.append(e)

    def poll(self) -> list[Message]:
        return self._frames.drain()

    def health(self) -> dict[str, Any]:
        return {"name": self.name, "state": self.state, "url": self.url, "sim_states": self.states,
                "sim_states_received": self.states_received, "frames": self.seq, "frames_black": self.frames_black,
                "frames_dropped": self._frames.dropped,
                "render_ms": round(self.render_ms, 1), "blackout": self.blacked_out()}

