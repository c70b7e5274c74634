"""The daemon's output threads: MAVLink and the TUM pose log, and the recorder (EurocWriter or McapWriter)."""

from __future__ import annotations

import contextlib
import dataclasses
import datetime
import errno
import logging
import math
import os
import threading
import time
from collections import Counter, deque
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from vio import VioError
from vio.app.daemon.buffers import LatestState, Output, SensorBuffer, _now_ns
from vio.app.daemon.status import _mavlink_health
from vio.app.daemon.workers import Worker
from vio.geometry import rot_to_quat_wxyz
from vio.io.outputs import storage_diagnosis as _storage_diagnosis
from vio.trajectory import RUN_MARKER, format_tum_line
from vio.types import ImuSample, NavState, StereoFrame, covariance_quality

if TYPE_CHECKING:
    from vio.app.daemon.protocols import PoseOutput
    pass

log = logging.getLogger(__name__)

# a refusal ends once the stamp error is back under this share of the bound: one line per event, not one per
# state while it hovers at the bound
STAMP_RESUME_FRACTION = 0.8
ACCEL_BASE_NS = 50_000_000  # the acceleration (velocity error of a stamp error) from velocities this far apart
STAMPS_WITHHELD_TEXT = "VIO: IMU clock unsure, no poses"  # the STATUSTEXT of a refusal


class StampErrorGate:
    """What the IMU source's clock health does to the state sent: a stamp error dt (the source's own measure,
    SensorSource.stamp_uncertainty_s) while the body moves at v, turns at w and accelerates at a puts the pose about
    v*dt, the attitude w*dt and the velocity a*dt off. Over `tolerance_s` ([mavlink] stamp_tolerance_ms: what a
    healthy device-clock fit shows, and a constant part of it is the camera-IMU offset the estimator solves in
    flight) those go into the covariance sent (along
    the motion: position in the body frame, attitude about the turn axis, velocity in the world frame) and the
    quality is capped by the grown covariance ([backend] quality_sigma_m, as the estimator caps it) and by how close
    dt is to `max_error_s`, falling to 0 there; beyond `max_error_s` ([mavlink] max_stamp_error_ms) the state goes
    on as not tracking and the OutputWorker has the MAVLink output withhold every pose (not even lost_output's -1/0
    ones; a loss of tracking with its log line and STATUSTEXT, and one STATUSTEXT naming the clock), with one log
    line here on entering and one on leaving (once back under STAMP_RESUME_FRACTION of the bound). Under the
    tolerance the state is handed on untouched.

    Why in the output and not the estimator: a stamp error is no noise the estimator models (docs/autopilot.md, the
    c12373d r2 flight: IMU stamps ~0.2 s off for ~25 s went out at quality 100 and a 5 cm sigma)."""

    def __init__(self, uncertainty: Callable[[], float], max_error_s: float, quality_sigma_m: float | None,
                 tolerance_s: float) -> None:
        if not 0 <= tolerance_s < max_error_s:  # the config refuses it with the keys' names (vio.config)
            raise ValueError(f"stamp tolerance {tolerance_s * 1e3:g} ms must be below the bound "
                             f"{max_error_s * 1e3:g} ms")
        self._uncertainty = uncertainty
        self.max_error_s = max_error_s
        self.tolerance_s = tolerance_s
        self.quality_sigma_m = quality_sigma_m
        self.error_s = 0.0  # the measure as last read
        self.refusing = False  # the states go on as lost and the MAVLink output withholds them (its states_withheld)
        self.grown = 0  # tracked states sent with a grown covariance
        self._v_base: tuple[int, np.ndarray] | None = None  # (t_ns, v_world) the acceleration is taken against
        self._accel = np.zeros(3)

    def apply(self, s: NavState) -> NavState:
        """`s` as it may go to the autopilot with the source's stamp error now."""
        dt = self._uncertainty()
        self.error_s = dt
        self._track_accel(s)
        if not dt <= self.max_error_s:  # inf and nan too
            if not self.refusing:
                self.refusing = True
                log.warning("IMU stamps uncertain by %s (the IMU source's clock sync), beyond [mavlink] "
                            "max_stamp_error_ms = %.0f: no pose is sent until they are back under %.0f ms",
                            stamp_error_text(dt), self.max_error_s * 1e3,
                            STAMP_RESUME_FRACTION * self.max_error_s * 1e3)
        elif self.refusing and dt <= STAMP_RESUME_FRACTION * self.max_error_s:
            self.refusing = False
            log.info("IMU stamps uncertain by %s again (under %.0f ms): poses sent again (over %.0f ms with their "
                     "covariance grown by it)", stamp_error_text(dt), STAMP_RESUME_FRACTION * self.max_error_s * 1e3,
                     self.tolerance_s * 1e3)
        if not s.tracking:
            return s
        if self.refusing:
            return dataclasses.replace(s, tracking=False, quality=0)
        if dt <= self.tolerance_s:
            return s
        self.grown += 1
        return self.grown_by(s, dt)

    def grown_by(self, s: NavState, dt: float) -> NavState:
        """`s` with the errors of a stamp error `dt` [s] added to its covariance and its quality capped."""
        w = np.asarray(s.omega_body, dtype=float)
        v_body = s.T_world_body[:3, :3].T @ np.asarray(s.v_world, dtype=float)
        cov_pose = np.array(s.cov_pose, dtype=float)
        cov_pose[:3, :3] += dt * dt * np.outer(w, w)
        cov_pose[3:, 3:] += dt * dt * np.outer(v_body, v_body)
        cov_vel = np.asarray(s.cov_vel, dtype=float) + dt * dt * np.outer(self._accel, self._accel)
        share = (self.max_error_s - dt) / (self.max_error_s - self.tolerance_s)
        if self.quality_sigma_m is not None:
            share = min(share, covariance_quality(cov_pose, self.quality_sigma_m))
        quality = max(1, min(s.quality, round(100 * share)))
        return dataclasses.replace(s, cov_pose=cov_pose, cov_vel=cov_vel, quality=quality)

    def _track_accel(self, s: NavState) -> None:
        """The acceleration from the velocities of states at least ACCEL_BASE_NS apart (time going back, an
        estimator reset, starts over)."""
        v = np.asarray(s.v_world, dtype=float)
        base = self._v_base
        if base is None or s.t_ns < base[0]:
            self._v_base, self._accel = (s.t_ns, v), np.zeros(3)
        elif s.t_ns - base[0] >= ACCEL_BASE_NS:
            accel = (v - base[1]) / ((s.t_ns - base[0]) * 1e-9)
            self._accel = accel if np.isfinite(accel).all() else np.zeros(3)
            self._v_base = (s.t_ns, v)

    def status(self) -> dict:
        """For `vio status`: the stamp error now [ms], whether poses are refused for it, the states it grew. The
        states it refused are the MAVLink output's `states_withheld` (with `withheld_for`, the why): the one count of
        states withheld, every state of a spell, tracked or lost (a second count here read N beside the output's 0)."""
        return {"stamp_error_ms": round(self.error_s * 1e3, 1) if math.isfinite(self.error_s) else None,
                "max_stamp_error_ms": round(self.max_error_s * 1e3, 1),
                "stamp_tolerance_ms": round(self.tolerance_s * 1e3, 1), "refusing_uncertain_stamps": self.refusing,
                "states_grown_stamps": self.grown}


def stamp_error_text(dt: float) -> str:
    """'42 ms', or what an infinite / NaN stamp error means."""
    return f"{dt * 1e3:.0f} ms" if math.isfinite(dt) else "an unknown amount (the fit cannot place them)"


class TrajectoryLog:
    """The TUM pose log. An error (disk full, file-size limit, folder removed or read-only) ends it with ONE
    warning and a status entry; it never stops the output thread, so MAVLink goes on."""

    CHECK_EVERY_S = 1.0  # how often the file is checked to be still there (writes to a deleted file succeed)

    def __init__(self, path: str) -> None:
        self.path = path
        self.state = "ok" if path else "off"
        self.error = ""
        self.poses = 0
        self._f: Any = None
        self._checked = 0.0

    def start(self) -> None:
        if self.state != "ok":
            return
        try:
            Path(self.path).parent.mkdir(parents=True, exist_ok=True)
            self._f = open(self.path, "a", buffering=1)
            # the file is appended to across runs (no pose is lost), and each run starts a frame of its own at
            # its first pose: this line (a comment to TUM readers, evo's too) tells where one run ends
            started = datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds")
            self._f.write(f"{RUN_MARKER} {started} (pid {os.getpid()}): the poses below are in this run's odometry "
                          "frame\n")
        except OSError as e:
            self._failed(e)

    def write(self, s: NavState) -> None:
        if self._f is None:
            return
        try:
            self._f.write(format_tum_line(s.t_ns, s.T_world_body[:3, 3], rot_to_quat_wxyz(s.T_world_body[:3, :3])))
            self.poses += 1
            now = time.monotonic()
            if now - self._checked >= self.CHECK_EVERY_S:
                self._checked = now
                if os.fstat(self._f.fileno()).st_nlink == 0:
                    raise FileNotFoundError(f"{self.path} was removed while in use")
        except (OSError, ValueError) as e:
            self._failed(e)

    def _failed(self, e: Exception) -> None:
        self.state = "failed"
        self.error = _os_error_text(e)
        log.warning("trajectory file %s: %s; no more poses are logged there (MAVLink output goes on)",
                    self.path, self.error)
        self.close()

    def status(self) -> dict | None:
        if self.state == "off":
            return None
        return {"state": self.state, "path": self.path, "poses": self.poses, "error": self.error or None}

    def close(self) -> None:
        f, self._f = self._f, None
        if f is not None:
            with contextlib.suppress(OSError, ValueError):  # the buffered tail of a failed file is lost
                f.close()


def _os_error_text(e: BaseException) -> str:
    """What an output's failure says in the log and `vio status`: a VioError is a sentence already (the status read
    "recording failed: VioError: /var/lib/.../x.png: cannot write image (disk full ...)"); anything else is a bug
    and keeps its type."""
    if isinstance(e, OSError) and e.strerror:
        return f"{e.strerror} ({errno.errorcode.get(e.errno or 0, e.errno)})"
    if isinstance(e, VioError):
        return str(e)
    return f"{type(e).__name__}: {e}"


class OutputWorker(Worker):
    """Sends the newest state over MAVLink (the MAVLink class rate-limits) and appends the TUM log.

    `vision_ok()` is the daemon's own check that camera frames arrive: without it a state goes out as not
    tracking (quality 0), whatever the estimator said, so a stale IMU-only pose never reaches the autopilot
    as a good one."""

    def __init__(self, stop: threading.Event, latest: LatestState, open_mavlink: Callable[[], PoseOutput] | None,
                 trajectory_file: str, reconnect_max_s: float, vision_ok: Callable[[], bool] = lambda: True,
                 mount: Callable[[Any], bool] | None = None, stamps: StampErrorGate | None = None) -> None:
        super().__init__("output", stop)
        self.latest = latest
        self._open = open_mavlink
        self._mount = mount  # sets the camera mount of a freshly opened link once the calibration is known
        self._mount_pending = False
        self.trajectory = TrajectoryLog(trajectory_file)
        self.reconnect_max_s = reconnect_max_s
        self.vision_ok = vision_ok
        self.stamps = stamps  # the IMU source's clock health on what is sent (None: stamps on the host clock)
        self.quality_out: int | None = None  # of the newest state handed on: what the autopilot gets, 0 while lost
        self.mav: PoseOutput | None = None
        self.offered = 0  # states handed to the MAVLink output (it sends the newest at its own rate)
        self.withheld = 0  # tracking states turned into not-tracking ones because no camera frames arrive
        # the counts of the MAVLink outputs closed since start (a failed one is reopened, starting its own at 0), and
        # the last why of a withholding among them: the status counts the whole run, as the log does
        self._closed_counts: Counter[str] = Counter()
        self._closed_withheld_for = ""
        # the frame the closed output sent in (MavlinkOutput.autopilot_frame: a start in flight's turn into the
        # autopilot's), kept by the one reopened after it
        self._frame: Any = None
        # that frame's turn in the estimator's world (MavlinkOutput.world_frame_turn), for the loop output while no
        # output is open or the reopened one has not taken the frame yet
        self._turn: np.ndarray | None = None
        # what the reopened output goes on from (MavlinkOutput.continuity: reset_counter, tracking and loss clock)
        self._continuity: Any = None
        # the status thread reads the output and the closed counts (link(), sent) while this thread closes one and adds
        # its counts: one step each, or a read in between counted the closing output twice (or not at all)
        self._counts_lock = threading.Lock()
        self.link_closed = 0  # states handed over while no MAVLink output was open (a failed one not reopened yet)
        self.errors = 0
        self.latency_ms: deque[float] = deque(maxlen=200)
        self._seq = 0
        self._next_open = 0.0
        self._backoff = 0.5

    def loop(self) -> None:
        self.trajectory.start()
        try:
            while not self.stop_event.is_set():
                self.beat()
                self._ensure_mavlink()
                self._seq, out, frames = self.latest.wait_newer(self._seq, 0.02)
                if out is not None:
                    self._send(self._checked(out.state))
                for f in frames:
                    self._frame_done(f)
                self._poll()
        finally:
            self.close()

    def _checked(self, s: NavState) -> NavState:
        if s.tracking and not self.vision_ok():
            self.withheld += 1
            s = dataclasses.replace(s, tracking=False, quality=0)
        if self.stamps is not None:
            s = self.stamps.apply(s)
        self.quality_out = s.quality if s.tracking else 0
        return s

    def _ensure_mavlink(self) -> None:
        if self._open is None or self.mav is not None or time.monotonic() < self._next_open:
            return
        try:
            self.mav = self._open()
            keep = getattr(self.mav, "keep_autopilot_frame", None)
            if keep is not None and self._frame is not None:
                keep(self._frame)
            go_on = getattr(self.mav, "continue_from", None)
            if go_on is not None and self._continuity is not None:
                go_on(self._continuity)  # the closed one's counter and loss clock (a loss goes on, with its LAND)
            self._mount_pending = self._mount is not None
            self._backoff = 0.5
        except Exception as e:  # a missing serial port at boot: retry, the autopilot may power up later
            self.errors += 1
            log.warning("MAVLink open failed: %s; retrying in %.1f s", e, self._backoff)
            self._next_open = time.monotonic() + self._backoff
            self._backoff = min(self._backoff * 2, self.reconnect_max_s)

    def _send(self, s: NavState) -> None:
        if self.mav is None:  # none open: its open failed, or it failed and waits to be reopened
            self.link_closed += self._open is not None
            return
        try:
            if self._mount_pending and self._mount is not None:
                self._mount_pending = not self._mount(self.mav)
            self.mav.withhold(STAMPS_WITHHELD_TEXT if self.stamps is not None and self.stamps.refusing else None)
            self.mav.send_state(s)
            self.offered += 1
        except Exception as e:
            self._mav_failed(e)

    def _frame_done(self, out: Output) -> None:
        """Per camera frame: TUM line, and the latency from frame arrival until its state (or a newer one
        propagated from it) has been handed to the MAVLink output."""
        s = out.state
        if s.tracking and self.vision_ok():  # the odometry, as docs/autopilot.md says, not the loop-corrected output
            self.trajectory.write(out.odometry if out.odometry is not None else s)
        self.latency_ms.append((_now_ns() - out.arrival_ns) / 1e6)

    def _poll(self) -> None:
        if self.mav is None:
            return
        try:
            self.mav.poll()
        except Exception as e:
            self._mav_failed(e)

    def _mav_failed(self, e: Exception) -> None:
        self.errors += 1
        log.warning("MAVLink error: %s: %s; reopening", type(e).__name__, e)
        self._close_mav(final=False)
        self._next_open = time.monotonic() + self._backoff

    def _close_mav(self, final: bool = True) -> None:
        mav = self.mav
        if mav is None:
            return
        counts: dict[str, int] = {}
        why = ""
        try:
            counts = mav.counters()
            why = mav.health().get("withheld_for") or ""
            frame = getattr(mav, "autopilot_frame", None)
            self._frame = (frame() if frame is not None else None) or self._frame
            continuity = getattr(mav, "continuity", None)
            self._continuity = continuity() if continuity is not None else self._continuity
            turn = getattr(mav, "world_frame_turn", None)
            kept = turn() if turn is not None else None
            self._turn = kept if kept is not None else self._turn
        except Exception as e:  # a broken output's counts are lost, not the daemon
            log.warning("MAVLink output's counters lost at its close: %s: %s", type(e).__name__, e)
        with self._counts_lock:
            self.mav = None
            self._closed_counts.update(counts)
            self._closed_withheld_for = why or self._closed_withheld_for
        with contextlib.suppress(Exception):
            mav.close(final=final)

    def frame_turn(self) -> np.ndarray | None:
        """The MAVLink output's turn and shift of a start in flight in the estimator's world (MavlinkOutput.
        world_frame_turn), for the loop output (read from the estimator thread); None without one."""
        turn = getattr(self.mav, "world_frame_turn", None)
        got = turn() if turn is not None else None
        # none open (reopening after a failure: up to reconnect_max_s), or the new one has not taken the frame yet:
        # the closed one's, which the reopened one keeps. None here, a correction into a map's frame taken then stayed
        # turned twice, once reopened, until the next solve (a review's finding)
        return got if got is not None else self._turn

    def frame_pending(self) -> bool:
        """Is the MAVLink output's frame of a start in flight still to be chosen (at its first tracked pose)? Then
        frame_turn() says None though a turn may come: the open output's, or, while none is open, the closed one's,
        which the reopened one keeps."""
        pending = getattr(self.mav, "frame_pending", None)
        if pending is not None:
            return bool(pending())
        return self.mav is None and self._frame is not None and bool(self._frame[1])

    @property
    def sent(self) -> int:
        """Pose states that went out on the link (cumulative over reconnects)."""
        with self._counts_lock:
            mav, closed = self.mav, self._closed_counts["states_sent"]
        return closed + (mav.states_sent if mav is not None else 0)

    def link(self) -> dict:
        """The MAVLink output's status, its counts over the whole run (the closed outputs' added); "closed"
        between a failed output and its reopening, with the counts so far."""
        if self._open is None:
            return {"state": "off"}
        with self._counts_lock:  # the output and the counts of those closed before it, as of one moment
            mav, closed, closed_for = self.mav, dict(self._closed_counts), self._closed_withheld_for
        h = {"state": "closed"} if mav is None else _mavlink_health(mav)
        for k, n in closed.items():
            h[k] = h.get(k, 0) + n
        # one count of the states the link being closed stopped: at the output's send slot, or with no output at all
        h["states_link_closed"] = h.get("states_link_closed", 0) + self.link_closed
        if not h.get("withheld_for") and closed_for:
            h["withheld_for"] = closed_for
        return h

    def close(self) -> None:
        self._close_mav()
        self.trajectory.close()


class RecorderWorker(Worker):
    """Writes what the sensors deliver to a EuRoC dataset; PNG encoding must never slow the estimator.

    A write error (disk full, file-size limit, read-only or removed folder) stops the recording with ONE
    warning: the files are closed, each csv is cut back to its last complete row (so what was written is a
    readable dataset), the buffer is closed (nothing piles up, a paced source is not held) and the thread
    idles until shutdown. Recording does not resume until the service restarts (one dataset per start)."""

    def __init__(self, stop: threading.Event, buf: SensorBuffer, record_dir: str,
                 calibration: Callable[[], Any], fmt: str = "euroc", images: str = "png",
                 latest: Any = None, health: Callable[[], dict] | None = None, png_level: int = 0) -> None:
        super().__init__("recorder", stop)
        self.png_level = png_level
        self.buf = buf
        self.record_dir = record_dir
        self.fmt = fmt  # euroc | mcap (then also the newest estimator state and, every second, the health)
        self.images = images
        self._latest = latest
        self._health = health
        self._state_seq = -1
        self._health_t = 0.0
        self._calibration = calibration
        self.writer: Any = None
        self.root: Path | None = None
        self.state = "waiting for calibration"  # -> recording -> stopped, or failed
        self.error = ""
        self.frames = 0
        self.imu = 0

    def loop(self) -> None:
        calib = self._calibration()
        while calib is None and not self.stop_event.is_set():
            self.beat()
            self.stop_event.wait(0.1)
            calib = self._calibration()
        if calib is None:
            return
        try:
            self.root = _fresh_record_dir(self.record_dir)
            if self.fmt == "mcap":
                from vio.io.bag import McapWriter

                self.root.parent.mkdir(parents=True, exist_ok=True)
                self.root = self.root.with_suffix(".mcap")
                self.writer = McapWriter(self.root, self.images, calibration=calib)
            else:
                from vio.io.euroc import EurocWriter

                self.writer = EurocWriter(self.root, calib, png_level=self.png_level)
            self.state = "recording"
            log.info("recording to %s", self.root)
            while not self.stop_event.is_set():
                self.beat()
                self._write(*self.buf.take(0.1))
            deadline = time.monotonic() + 0.5  # flush what is queued, but within the shutdown budget
            while len(self.buf) and time.monotonic() < deadline:
                self._write(*self.buf.take(0.0))
            if self.fmt == "mcap":
                self._write_health(last=True)
            self.writer.close()
            self.state = "stopped"
        except Exception as e:  # OSError (ENOSPC, EFBIG, EROFS, ENOENT), VioError from cv2.imwrite, cv2.error
            self._failed(e)
        while not self.stop_event.is_set():  # a recorder that gave up is idle, not dead: keep the watchdog fed
            self.beat()
            self.stop_event.wait(0.2)

    def _write(self, imu: list[ImuSample], item: tuple[int, StereoFrame] | None) -> None:
        for s in imu:
            self.writer.write_imu(s)
            self.imu += 1
        if item is not None:
            self.writer.write_frame(item[1])
            self.frames += 1
        if self.fmt != "mcap":
            return
        if self._latest is not None:
            seq, out = self._latest.peek()
            if out is not None and seq != self._state_seq:
                self._state_seq = seq
                self.writer.write_state(out.state)
        self._write_health()

    def _write_health(self, last: bool = False) -> None:
        """The daemon's status snapshot on /vio/health (JSON) every second, and once more at the end."""
        now = time.monotonic()
        if self._health is not None and (last or now - self._health_t >= 1.0):
            self._health_t = now
            h = self._health()
            if h:
                self.writer.write_json("/vio/health", time.time_ns(), h)

    def _failed(self, e: Exception) -> None:
        self.state = "failed"
        # a writer that never opened never had its folder: "the recording folder was removed" said of a folder a
        # read-only disk never let it make (a QA sweep)
        said = _os_error_text(e)
        self.error = said + _storage_diagnosis(self.root if self.writer is not None else None, said)
        self.buf.close()
        if self.fmt == "mcap":  # an MCAP file without its summary is read up to its last complete chunk
            with contextlib.suppress(Exception):
                self.writer.close()
            kept = int(self.frames > 0)
        else:
            if self.writer is not None:
                _close_writer_files(self.writer)
            rows = _trim_partial_rows(self.root / "mav0") if self.root is not None else {}
            # what is on disk, not what was handed to the writer (its buffered tail is lost with the error)
            frames, imu = rows.get("cam0", 0), rows.get("imu0", 0)
            kept = frames + imu
            self.frames, self.imu = frames, imu
        log.warning("recording stopped: %s; %s kept in %s (pose output goes on)", self.error,
                    f"{self.frames} frames and {self.imu} IMU samples before the error" if kept else "nothing",
                    self.root)

    def status(self) -> dict:
        return {"state": self.state, "dir": str(self.root) if self.root else None, "error": self.error or None,
                "frames": self.frames, "imu": self.imu, "frames_dropped": self.buf.frames_dropped}


def _close_writer_files(writer: Any) -> None:
    """Close every csv of a EurocWriter whose flush failed. Its close() flushes first and stops at the first
    failing file, leaving the others open (a later flush could then write after our trim); closing a file
    object closes its descriptor even when that last flush fails, and the unwritten tail is dropped."""
    for f in (*writer._cam, writer._imu, writer._gt):
        if f is not None:
            with contextlib.suppress(OSError, ValueError):
                f.close()


def _trim_partial_rows(mav0: Path) -> dict[str, int]:
    """Cut each csv of a recording back to its last complete line (a failed write can leave half a row);
    returns the data rows left in each ("cam0", "cam1", "imu0")."""
    rows: dict[str, int] = {}
    for name in ("cam0", "cam1", "imu0"):
        try:
            with open(mav0 / name / "data.csv", "rb+") as f:
                data = f.read()
                end = data.rfind(b"\n") + 1
                if end < len(data):
                    f.truncate(end)
                rows[name] = max(data.count(b"\n", 0, end) - 1, 0)  # the header line is no row
        except OSError:  # the folder was removed, or the disk refuses even this: nothing more to save
            continue
    return rows


def _fresh_record_dir(base: str) -> Path:
    """One dataset per daemon start: <record_dir>/<UTC time>, so a restart never overwrites a flight. Free as a
    folder and as an MCAP file (<name>.mcap): a board without a real-time clock comes back at the same time after
    a power cut, and the MCAP of the flight before was written over (a QA sweep)."""
    root = Path(base) / time.strftime("%Y%m%dT%H%M%SZ", time.gmtime())
    k = 1
    while root.exists() or root.with_suffix(".mcap").exists():
        root = Path(base) / f"{time.strftime('%Y%m%dT%H%M%SZ', time.gmtime())}_{k}"
        k += 1
    return root
