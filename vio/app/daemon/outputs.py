"""The daemon's output threads: MAVLink and the TUM pose log, and the recorder (EurocWriter or McapWriter)."""

from __future__ import annotations

import contextlib
import dataclasses
import datetime
import errno
import logging
import os
import threading
import time
from collections import deque
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

from vio import VioError
from vio.app.daemon.buffers import LatestState, Output, SensorBuffer, _now_ns
from vio.app.daemon.status import _mavlink_health
from vio.app.daemon.workers import Worker
from vio.geometry import rot_to_quat_wxyz
from vio.io.outputs import storage_diagnosis as _storage_diagnosis
from vio.trajectory import RUN_MARKER, format_tum_line
from vio.types import ImuSample, NavState, StereoFrame

if TYPE_CHECKING:
    from vio.app.daemon.protocols import PoseOutput
    pass

log = logging.getLogger(__name__)

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
                 mount: Callable[[Any], bool] | None = None) -> None:
        super().__init__("output", stop)
        self.latest = latest
        self._open = open_mavlink
        self._mount = mount  # sets the camera mount of a freshly opened link once the calibration is known
        self._mount_pending = False
        self.trajectory = TrajectoryLog(trajectory_file)
        self.reconnect_max_s = reconnect_max_s
        self.vision_ok = vision_ok
        self.mav: PoseOutput | None = None
        self.offered = 0  # states handed to the MAVLink output (it sends the newest at its own rate)
        self.withheld = 0  # tracking states turned into not-tracking ones because no camera frames arrive
        self._sent_base = 0  # states sent by MAVLink outputs closed since start
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
            return dataclasses.replace(s, tracking=False, quality=0)
        return s

    def _ensure_mavlink(self) -> None:
        if self._open is None or self.mav is not None or time.monotonic() < self._next_open:
            return
        try:
            self.mav = self._open()
            self._mount_pending = self._mount is not None
            self._backoff = 0.5
        except Exception as e:  # a missing serial port at boot: retry, the autopilot may power up later
            self.errors += 1
            log.warning("MAVLink open failed: %s; retrying in %.1f s", e, self._backoff)
            self._next_open = time.monotonic() + self._backoff
            self._backoff = min(self._backoff * 2, self.reconnect_max_s)

    def _send(self, s: NavState) -> None:
        if self.mav is not None:
            try:
                if self._mount_pending and self._mount is not None:
                    self._mount_pending = not self._mount(self.mav)
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
        mav, self.mav = self.mav, None
        if mav is not None:
            self._sent_base += mav.states_sent
            with contextlib.suppress(Exception):
                mav.close(final=final)

    @property
    def sent(self) -> int:
        """Pose states that went out on the link (cumulative over reconnects)."""
        mav = self.mav
        return self._sent_base + (mav.states_sent if mav is not None else 0)

    def link(self) -> dict:
        if self._open is None:
            return {"state": "off"}
        if self.mav is None:
            return {"state": "closed"}
        return _mavlink_health(self.mav)

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
        self.error = _os_error_text(e) + _storage_diagnosis(self.root if self.writer is not None else None)
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
