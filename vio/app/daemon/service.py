"""`vio run`: the onboard daemon. Sensors -> estimator -> MAVLink, supervised for systemd.

Threads and the bounded buffers between them:

    source thread --(SensorBuffer: frames drop-oldest, IMU large + counted overflow)--> estimator thread
          \\--(SensorBuffer for the recorder, same policy)--> recorder thread (EurocWriter)
    estimator thread --(LatestState: newest NavState only)--> output thread (MAVLink, TUM log)
    main thread: signals, status line + status file once a second, sd_notify READY/WATCHDOG/STATUS

Why drop the oldest frame: an autopilot needs the current pose; a pose for a frame that waited behind
others is stale on arrival. IMU samples are never dropped silently, because pre-integration needs every one;
the IMU buffer holds many seconds, and if it still overflows the estimator is far behind: the overflow is
counted, logged and the estimator is reset (its IMU chain is broken anyway).

Faults are survived, not fatal: a source that raises or goes quiet for `run.source_timeout_s` is closed
and reopened with backoff (a finite source that has ended is not reopened); an estimator exception resets
the estimator; a MAVLink error reopens the link; a recorder or trajectory-file error (disk full, file-size
limit, read-only or removed folder) stops that output with one warning and leaves the rest running.
Only an invalid configuration ends the process (exit code 3, `vio.app.cli.EXIT_CONFIG`).

Readiness and supervision: READY=1 goes to systemd once the threads run and the sensors deliver data (or
after `run.ready_timeout_s` without data: the daemon keeps reopening the sensors). Tracking is not needed:
a drone that cannot initialise (dark hangar, lens cap) reports `waiting for vision` and is not restarted.
The watchdog is fed while every loop beats; a wedged loop (no heartbeat for 5 s) stops it.

What reaches the autopilot is never more than the estimator knows: a state goes out as tracking only while
camera frames arrive (the daemon's own check, `VISION_STALE_S`) and the estimator says it is tracking.

The daemon is part of the application layer (`vio.app`), the only code in `vio` that imports `drivers`
(inside functions, so the other commands stay usable without them).
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import errno
import json
import logging
import math
import os
import shutil
import signal
import sys
import threading
import time
from collections import deque
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np

from vio import VioError
from vio.app.sdnotify import SdNotifier, watchdog_interval_s
from vio.config import VioConfig, load_config
from vio.geometry import rot_to_quat_wxyz
from vio.trajectory import format_tum_line
from vio.types import FeatureFrame, ImuSample, NavState, StereoFrame

if TYPE_CHECKING:
    from vio.calibration import StereoCalibration
    from vio.estimator import EstimatorHealth

log = logging.getLogger(__name__)

STATUS_VERSION = 1
FIRST_DATA_TIMEOUT_S = 10.0  # an OAK boots its firmware before the first frame
# driver states (drivers/source.py health()) in which the driver is reconnecting by itself
SELF_HEALING_STATES = ("connecting", "no_device", "disconnected")
JOIN_BUDGET_S = 1.6  # shutdown must finish within 2 s of SIGTERM; keep a margin for the final status write
STUCK_S = 5.0  # a loop without a heartbeat this long is wedged: the watchdog stops being fed
VISION_STALE_S = 1.0  # no camera frame for this long: not tracking, whatever the last state said
HEALTH_EVERY_S = 0.2  # the estimator thread snapshots estimator.health() this often (status reads the copy)


class EstimatorApi(Protocol):
    """What the daemon uses of vio.estimator.Estimator (tests pass stand-ins with the same shape)."""

    last_features: FeatureFrame | None

    def feed_imu(self, s: ImuSample) -> NavState | None: ...

    def feed_frame(self, frame: StereoFrame) -> NavState | None: ...

    def reset(self, reason: str, bridge: bool = True) -> None: ...

    def health(self) -> EstimatorHealth: ...


def _now_ns() -> int:
    return time.monotonic_ns()


# ------------------------------------------------------------------------------------------------ buffers

class SensorBuffer:
    """Frames and IMU samples from one producer to one consumer, bounded, with counted losses.

    `take()` hands out the IMU samples up to the oldest waiting frame and then that frame, so the estimator
    always has the IMU up to a frame before it sees the frame (the source yields in time order)."""

    def __init__(self, max_frames: int, max_imu: int) -> None:
        self._frames: deque[tuple[int, StereoFrame]] = deque()
        self._imu: deque[ImuSample] = deque()
        self.max_frames = max_frames
        self.max_imu = max_imu
        self._cv = threading.Condition()
        self.frames_in = 0
        self.frames_dropped = 0
        self.imu_in = 0
        self.imu_overflow = 0
        self.closed = False  # the consumer gave up (a failed recorder): puts are discarded, nothing is held

    def _push(self, q: deque, item: Any, limit: int) -> bool:
        """Append under the lock, dropping the oldest entry when full; True when nothing was dropped."""
        with self._cv:
            if self.closed:
                return True
            full = len(q) >= limit
            if full:
                q.popleft()
            q.append(item)
            self._cv.notify()
        return not full

    def put_frame(self, frame: StereoFrame, arrival_ns: int) -> bool:
        """Queue a frame; False when the oldest waiting frame had to be dropped for it."""
        self.frames_in += 1
        ok = self._push(self._frames, (arrival_ns, frame), self.max_frames)
        self.frames_dropped += not ok
        return ok

    def put_imu(self, sample: ImuSample) -> bool:
        """Queue an IMU sample; False on overflow (the oldest sample was lost; the caller must report it)."""
        self.imu_in += 1
        ok = self._push(self._imu, sample, self.max_imu)
        self.imu_overflow += not ok
        return ok

    def take(self, timeout_s: float) -> tuple[list[ImuSample], tuple[int, StereoFrame] | None]:
        """Wait up to `timeout_s` for data; return (IMU samples up to the next frame, (arrival_ns, frame))."""
        with self._cv:
            if not self._frames and not self._imu:
                self._cv.wait(timeout_s)
            item = self._frames[0] if self._frames else None
            imu: list[ImuSample] = []
            while self._imu and (item is None or self._imu[0].t_ns <= item[1].t_ns):
                imu.append(self._imu.popleft())
            if item is not None:
                self._frames.popleft()
            if imu or item is not None:
                self._cv.notify_all()  # a paced source may be waiting for room
            return imu, item

    def clear(self) -> None:
        with self._cv:
            self._frames.clear()
            self._imu.clear()
            self._cv.notify_all()

    def close(self) -> None:
        """No consumer any more: drop what is queued and discard what comes (never blocks a paced source)."""
        with self._cv:
            self.closed = True
        self.clear()

    def has_room(self) -> bool:
        """Room for a frame and for a second of IMU: a source paced by the consumer may deliver more."""
        with self._cv:
            return self.closed or (len(self._frames) < self.max_frames and len(self._imu) < self.max_imu // 2)

    def wait_room(self, timeout_s: float) -> bool:
        with self._cv:
            if not self.has_room():
                self._cv.wait(timeout_s)
            return self.has_room()

    def wake(self) -> None:
        with self._cv:
            self._cv.notify_all()

    def __len__(self) -> int:
        with self._cv:
            return len(self._frames) + len(self._imu)


@dataclasses.dataclass
class Output:
    state: NavState
    arrival_ns: int  # when the frame behind this state entered the daemon (host monotonic)
    produced_ns: int


class LatestState:
    """Mailbox from estimator to output: the newest state (MAVLink only wants that) plus a short queue of
    the per-frame states (the TUM log wants every one; 200 Hz IMU-rate states would otherwise hide them)."""

    def __init__(self, max_frames: int = 100) -> None:
        self._cv = threading.Condition()
        self._item: Output | None = None
        self._frames: deque[Output] = deque(maxlen=max_frames)
        self._seq = 0

    def publish(self, out: Output) -> None:
        with self._cv:
            self._item = out
            if out.arrival_ns >= 0:
                self._frames.append(out)
            self._seq += 1
            self._cv.notify_all()

    def wait_newer(self, seq: int, timeout_s: float) -> tuple[int, Output | None, list[Output]]:
        """(sequence number, newest state if newer than `seq`, frame states published since the last call)."""
        with self._cv:
            if self._seq == seq:
                self._cv.wait(timeout_s)
            frames = list(self._frames)
            self._frames.clear()
            return self._seq, (self._item if self._seq != seq else None), frames

    def wake(self) -> None:
        with self._cv:
            self._cv.notify_all()


class RateWindow:
    """Per-second rates and latency statistics computed from cumulative counters by the status loop."""

    def __init__(self) -> None:
        self._last: dict[str, int] = {}
        self._last_t = time.monotonic()

    def rates(self, counters: dict[str, int]) -> dict[str, float]:
        now = time.monotonic()
        dt = max(now - self._last_t, 1e-3)
        out = {k: (v - self._last.get(k, v)) / dt for k, v in counters.items()}
        self._last = dict(counters)
        self._last_t = now
        return out


# ------------------------------------------------------------------------------------------------ workers

class Worker(threading.Thread):
    """A supervised loop: `beat()` every iteration so the watchdog can tell a live loop from a wedged one."""

    def __init__(self, name: str, stop: threading.Event) -> None:
        super().__init__(name=name, daemon=True)
        self.stop_event = stop
        self._beat = time.monotonic()
        self.crashed: str | None = None

    def beat(self) -> None:
        self._beat = time.monotonic()

    def beat_age_s(self) -> float:
        return time.monotonic() - self._beat

    def run(self) -> None:
        try:
            self.loop()
        except Exception as e:  # a bug in a loop must show in status and stop the watchdog, not vanish
            self.crashed = f"{type(e).__name__}: {e}"
            log.exception("%s thread died: %s", self.name, e)

    def loop(self) -> None:
        raise NotImplementedError


class SourceWorker(Worker):
    """Owns the sensor source: reads it into the buffers, reopens it with backoff when it fails or goes quiet."""

    def __init__(self, stop: threading.Event, open_source: Callable[[], Any], sinks: list[SensorBuffer],
                 timeout_s: float, reconnect_max_s: float, paced: bool = False) -> None:
        super().__init__("source", stop)
        self._open = open_source
        self.sinks = sinks
        self.timeout_s = timeout_s
        self.reconnect_max_s = reconnect_max_s
        self.paced = paced  # a replay not tied to the clock: wait for room in the buffers instead of dropping
        self.finished = False  # a finite source (dataset, fake flight with a duration) delivered everything
        self.connected = False
        self.disconnects = 0
        self.last_data = time.monotonic()
        self.last_frame = 0.0
        self.last_imu = 0.0
        self.last_error = ""
        self._lost_at = 0.0
        self.calibration: Any = None
        self.calibration_ready = threading.Event()
        self.source: Any = None

    def loop(self) -> None:
        backoff = 0.2
        while not self.stop_event.is_set():
            self.beat()
            try:
                self.source = self._open()
                self._pump()
                backoff = 0.2
            except SourceFinished:
                self._close()
                self._idle_finished()
                return
            except VioError as e:
                self._lost(f"{e}; reopening")
            except Exception as e:  # driver bugs and device errors alike: log, back off, reopen
                self._lost(f"{type(e).__name__}: {e}; reopening")
            finally:
                self._close()
            if self.stop_event.is_set():
                break
            self.stop_event.wait(backoff)
            backoff = min(backoff * 2, self.reconnect_max_s)

    def _idle_finished(self) -> None:
        """The data are over and reopening would replay them from the start (a jump back in position, or in
        time): stay down and keep beating, so status says so and the watchdog is still fed."""
        self.finished = True
        self.connected = False
        self.last_error = "source finished (end of the recording or flight): not reopened"
        log.warning("source finished: no more sensor data; a finite source is not reopened")
        while not self.stop_event.is_set():
            self.beat()
            self.stop_event.wait(0.2)

    def _lost(self, why: str) -> None:
        if self.connected or why != self.last_error:  # one line per event, not per retry
            log.warning("source lost: %s", why)
        if self.connected:
            self.disconnects += 1
            self._lost_at = time.monotonic()
        self.connected = False
        self.last_error = why

    def _close(self) -> None:
        src, self.source = self.source, None
        if src is not None:
            with contextlib.suppress(Exception):
                src.stop()

    def _pump(self) -> None:
        opened = time.monotonic()
        got_data = False
        for msg in _iter_messages(self.source, self.stop_event):
            now = time.monotonic()
            self.beat()
            if msg is None:
                quiet = now - (self.last_data if got_data else opened)
                # an OAK needs seconds to boot its firmware: allow more before the first data
                if quiet > (self.timeout_s if got_data else max(self.timeout_s, FIRST_DATA_TIMEOUT_S)):
                    h = _source_health(self.source)
                    if h.get("state") in SELF_HEALING_STATES:  # the driver reconnects itself: let it
                        self._lost(f"driver {h['state']}: {h.get('last_error') or 'no data'}; waiting for it")
                        continue
                    raise VioError(f"no sensor data for {quiet:.1f} s")
                continue
            got_data = True
            if self.paced:
                self._wait_room()
            if not self.connected:
                log.info("source connected: data flowing%s",
                         f" again after {now - self._lost_at:.1f} s" if self.disconnects else "")
                self.connected = True
                self.last_error = ""
            self.last_data = now
            if self.calibration is None:  # an OAK knows its calibration only once the device is read
                self.calibration = _source_calibration(self.source)
                if self.calibration is not None:
                    self.calibration_ready.set()
            if isinstance(msg, ImuSample):
                self.last_imu = now
                for sink in self.sinks:
                    sink.put_imu(msg)
            elif isinstance(msg, StereoFrame):
                self.last_frame = now
                arrival = _now_ns()
                for sink in self.sinks:
                    sink.put_frame(msg, arrival)
        if not self.stop_event.is_set():
            if _source_finished(self.source):
                raise SourceFinished()
            raise VioError("source ended")

    def _wait_room(self) -> None:
        """Paced replay: hold the next message until every consumer has room (nothing is dropped)."""
        for sink in self.sinks:
            while not sink.wait_room(0.1) and not self.stop_event.is_set():
                self.beat()


class SourceFinished(Exception):
    """A finite source has delivered all its data."""


class EstimatorWorker(Worker):
    """Feeds the estimator in time order; an exception or an IMU gap resets it instead of ending the process."""

    def __init__(self, stop: threading.Event, make_estimator: Callable[[], EstimatorApi | None], buf: SensorBuffer,
                 out: LatestState, max_imu_gap_s: float) -> None:
        super().__init__("estimator", stop)
        self._make = make_estimator
        self.buf = buf
        self.out = out
        self.max_gap_ns = int(max_imu_gap_s * 1e9)
        self.estimator: EstimatorApi | None = None
        self.health: EstimatorHealth | None = None  # snapshot taken in this thread (status reads it)
        self.tracks: int | None = None  # features in the newest frame
        self._health_at = 0.0
        self.resets = 0  # resets made here (exceptions, gaps); the estimator counts its own internally
        self.errors = 0
        self.states = 0
        self.good_states = 0
        self.frames = 0
        self.last_state: NavState | None = None
        self.last_state_time = 0.0
        self.last_input = 0.0
        self._reset_base = 0
        self._last_imu_t: int | None = None
        self._seen_overflow = 0
        self._arrivals: deque[int] = deque(maxlen=64)  # frames fed, not yet processed (they wait for IMU)
        self._processed = 0

    def loop(self) -> None:
        self.estimator = self._make()
        if self.estimator is None:
            return
        while not self.stop_event.is_set():
            self.beat()
            self._snapshot_health()
            imu, item = self.buf.take(0.1)
            if self.buf.imu_overflow != self._seen_overflow:
                lost = self.buf.imu_overflow - self._seen_overflow
                self._seen_overflow = self.buf.imu_overflow
                self._reset(f"IMU buffer overflow: {lost} samples lost (estimator too slow)")
            if imu or item:
                self.last_input = time.monotonic()
            try:
                for s in imu:
                    if self._last_imu_t is not None and s.t_ns - self._last_imu_t > self.max_gap_ns:
                        self._reset(f"IMU gap of {(s.t_ns - self._last_imu_t) / 1e9:.2f} s")
                    self._last_imu_t = s.t_ns
                    self._emit(self.estimator.feed_imu(s))
                if item is not None:
                    self.frames += 1
                    self._arrivals.append(item[0])
                    self._emit(self.estimator.feed_frame(item[1]))
            except Exception as e:  # gtsam raises RuntimeError and friends; any failure means reset
                self.errors += 1
                self._reset(f"estimator failed: {type(e).__name__}: {e}")

    def _snapshot_health(self, force: bool = False) -> None:
        now = time.monotonic()
        if self.estimator is None or (not force and now - self._health_at < HEALTH_EVERY_S):
            return
        self._health_at = now
        try:
            self.health = self.estimator.health()
            ff = self.estimator.last_features
            self.tracks = None if ff is None else len(ff.ids)
        except Exception as e:  # display only: a failing health() must not stop the estimator
            log.debug("estimator health() failed: %s", e)

    def _frame_arrival(self) -> int:
        """Arrival time of the frame a state came from, or -1 for an IMU-rate state.

        A frame waits inside the estimator until the IMU reaches its stamp, so its state may come out of a
        later feed_imu(); the estimator's `frames_processed` counter tells which call finished a frame."""
        done = self.estimator.health().frames_processed
        arrival = -1
        while self._processed < done and self._arrivals:
            arrival = self._arrivals.popleft()
            self._processed += 1
        self._processed = done
        return arrival

    def _emit(self, result: Any) -> None:
        arrival_ns = self._frame_arrival()
        for state in _as_states(result):
            if self._reset_base:
                state = dataclasses.replace(state, reset_counter=state.reset_counter + self._reset_base)
            self.states += 1
            self.last_state = state
            if state.tracking:
                self.good_states += 1
                self.last_state_time = time.monotonic()
            self.out.publish(Output(state, arrival_ns, _now_ns()))

    def _reset(self, why: str) -> None:
        self.resets += 1
        log.warning("daemon-forced estimator reset #%d: %s", self.resets, why)
        last = self.last_state.reset_counter if self.last_state is not None else -1
        try:
            # keeps the last pose as the new origin and bumps the estimator's reset_counter; not carried
            # forward with the IMU: these resets follow lost IMU samples or an estimator in an unknown state
            self.estimator.reset(why, bridge=False)
            return
        except Exception as e:
            log.warning("estimator reset() failed (%s); creating a new estimator", e)
        self.estimator = self._make()
        self._reset_base = last + 1  # a new estimator counts from 0: keep the autopilot's counter moving
        self._last_imu_t = None
        self._arrivals.clear()
        self._processed = 0


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
    if isinstance(e, OSError) and e.strerror:
        return f"{e.strerror} ({errno.errorcode.get(e.errno or 0, e.errno)})"
    return f"{type(e).__name__}: {e}"


class OutputWorker(Worker):
    """Sends the newest state over MAVLink (the MAVLink class rate-limits) and appends the TUM log.

    `vision_ok()` is the daemon's own check that camera frames arrive: without it a state goes out as not
    tracking (quality 0), whatever the estimator said, so a stale IMU-only pose never reaches the autopilot
    as a good one."""

    def __init__(self, stop: threading.Event, latest: LatestState, open_mavlink: Callable[[], Any] | None,
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
        self.mav: Any = None
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
        if s.tracking and self.vision_ok():
            self.trajectory.write(s)
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
        self._close_mav()
        self._next_open = time.monotonic() + self._backoff

    def _close_mav(self) -> None:
        mav, self.mav = self.mav, None
        if mav is not None:
            self._sent_base += _mavlink_sent(mav)
            with contextlib.suppress(Exception):
                mav.close()

    @property
    def sent(self) -> int:
        """Pose states that went out on the link (cumulative over reconnects)."""
        mav = self.mav
        return self._sent_base + (_mavlink_sent(mav) if mav is not None else 0)

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
                 calibration: Callable[[], Any]) -> None:
        super().__init__("recorder", stop)
        self.buf = buf
        self.record_dir = record_dir
        self._calibration = calibration
        self.writer: Any = None
        self.root: Path | None = None
        self.state = "waiting for calibration"  # -> recording -> stopped, or failed
        self.error = ""
        self.frames = 0
        self.imu = 0

    def loop(self) -> None:
        from vio.io.euroc import EurocWriter

        calib = self._calibration()
        while calib is None and not self.stop_event.is_set():
            self.beat()
            self.stop_event.wait(0.1)
            calib = self._calibration()
        if calib is None:
            return
        try:
            self.root = _fresh_record_dir(self.record_dir)
            self.writer = EurocWriter(self.root, calib)
            self.state = "recording"
            log.info("recording to %s", self.root)
            while not self.stop_event.is_set():
                self.beat()
                self._write(*self.buf.take(0.1))
            deadline = time.monotonic() + 0.5  # flush what is queued, but within the shutdown budget
            while len(self.buf) and time.monotonic() < deadline:
                self._write(*self.buf.take(0.0))
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

    def _failed(self, e: Exception) -> None:
        self.state = "failed"
        self.error = _os_error_text(e) + _storage_diagnosis(self.root)
        self.buf.close()
        if self.writer is not None:
            _close_writer_files(self.writer)
        kept = _trim_partial_rows(self.root / "mav0") if self.root is not None else 0
        log.warning("recording stopped: %s; %s kept in %s (pose output goes on)", self.error,
                    f"{self.frames} frames and {self.imu} IMU samples before the error" if kept else "nothing",
                    self.root)

    def status(self) -> dict:
        return {"state": self.state, "dir": str(self.root) if self.root else None, "error": self.error or None,
                "frames": self.frames, "imu": self.imu, "frames_dropped": self.buf.frames_dropped}


def _storage_diagnosis(root: Path | None) -> str:
    """What an image write error (cv2.imwrite only says it failed) most likely was."""
    if root is None:
        return ""
    if not root.exists():
        return " (the recording folder was removed)"
    with contextlib.suppress(OSError):
        if shutil.disk_usage(root).free == 0:
            return " (disk full)"
    return ""


def _close_writer_files(writer: Any) -> None:
    """Close every csv of a EurocWriter whose flush failed. Its close() flushes first and stops at the first
    failing file, leaving the others open (a later flush could then write after our trim); closing a file
    object closes its descriptor even when that last flush fails, and the unwritten tail is dropped."""
    for f in (*writer._cam, writer._imu, writer._gt):
        if f is not None:
            with contextlib.suppress(OSError, ValueError):
                f.close()


def _trim_partial_rows(mav0: Path) -> int:
    """Cut each csv of a recording back to its last complete line (a failed write can leave half a row);
    returns how many csv files are left with data rows."""
    kept = 0
    for csv in (mav0 / "cam0" / "data.csv", mav0 / "cam1" / "data.csv", mav0 / "imu0" / "data.csv"):
        try:
            with open(csv, "rb+") as f:
                data = f.read()
                end = data.rfind(b"\n") + 1
                if end < len(data):
                    f.truncate(end)
                kept += data.count(b"\n", 0, end) > 1
        except OSError:  # the folder was removed, or the disk refuses even this: nothing more to save
            continue
    return kept


def _fresh_record_dir(base: str) -> Path:
    """One dataset per daemon start: <record_dir>/<UTC time>, so a restart never overwrites a flight."""
    root = Path(base) / time.strftime("%Y%m%dT%H%M%SZ", time.gmtime())
    k = 1
    while root.exists():
        root = Path(base) / f"{time.strftime('%Y%m%dT%H%M%SZ', time.gmtime())}_{k}"
        k += 1
    return root


# ------------------------------------------------------------------------------------- driver adapters

def _iter_messages(source: Any, stop: threading.Event) -> Iterable[ImuSample | StereoFrame | None]:
    """Messages from a source; None when nothing arrived for a short while (lets the caller check timeouts)."""
    while not stop.is_set():
        batch = source.poll()
        if batch:
            yield from batch
            continue
        if _source_finished(source):
            return
        yield None
        stop.wait(0.005)  # poll() never blocks: a short sleep keeps an idle source from spinning a core


def _source_finished(source: Any) -> bool:
    return bool(getattr(source, "finished", False))


def _source_calibration(source: Any) -> Any:
    calib = getattr(source, "calibration", None)
    return calib() if callable(calib) else calib


def _source_health(source: Any) -> dict:
    try:
        h = source.health() if source is not None else {}
    except Exception as e:  # health is for display only; never let it break the status loop
        h = {"error": str(e)}
    return json.loads(json.dumps(h, default=_json_default))


def _as_states(result: Any) -> list[NavState]:
    if result is None:
        return []
    if isinstance(result, NavState):
        return [result]
    return [s for s in result if isinstance(s, NavState)]


def _mavlink_sent(mav: Any) -> int:
    stats = getattr(mav, "stats", None)
    return int(getattr(stats, "states_sent", 0))


def _mavlink_health(mav: Any) -> dict:
    """Link state and the scalar counters of drivers.mavlink_out.MavlinkOutput (health(), else stats)."""
    stats = getattr(mav, "stats", None)
    try:
        h = mav.health() if hasattr(mav, "health") else dataclasses.asdict(stats) if dataclasses.is_dataclass(
            stats) else {}
    except Exception as e:  # display only
        h = {"health_error": str(e)}
    out = {k: v for k, v in h.items()
           if isinstance(v, (int, str, bool)) or (isinstance(v, float) and math.isfinite(v))}
    link_up = getattr(mav, "link_up", None)
    out["state"] = "up" if link_up else "down" if link_up is not None else "open"
    return out


def open_source(cfg: VioConfig) -> Any:
    """The configured sensor source, started."""
    from drivers.source import open_source as driver_open_source

    src = driver_open_source(cfg.source)
    src.start()
    return src


def load_run_calibration(cfg: VioConfig, source_calibration: Any) -> Any:
    """The calibration file named in the config wins over what the device or dataset reports."""
    if cfg.source.calibration:
        from vio.calibration import load_calibration

        return load_calibration(cfg.source.calibration)
    return source_calibration


# ------------------------------------------------------------------------------------------------ service

class Service:
    """Builds the pipeline, supervises it and reports its health; `run()` returns on SIGTERM/SIGINT."""

    def __init__(self, cfg: VioConfig, *, source_factory: Callable[[], Any] | None = None,
                 estimator_factory: Callable[[Any], Any] | None = None,
                 mavlink_factory: Callable[[], Any] | None = None, notifier: SdNotifier | None = None) -> None:
        self.cfg = cfg
        self.stop = threading.Event()
        self.notifier = notifier or SdNotifier()
        rc = cfg.run
        self.est_buf = SensorBuffer(rc.queue_frames, rc.queue_imu)
        self.rec_buf = SensorBuffer(rc.queue_frames * 4, rc.queue_imu) if rc.record_dir else None
        self.latest = LatestState()
        paced = cfg.source.kind in ("fake", "euroc") and not cfg.source.realtime
        self.source = SourceWorker(self.stop, source_factory or (lambda: open_source(cfg)),
                                   [b for b in (self.est_buf, self.rec_buf) if b is not None],
                                   rc.source_timeout_s, rc.reconnect_max_s, paced=paced)
        self._estimator_factory = estimator_factory or _default_estimator_factory(cfg)
        self.estimator = EstimatorWorker(self.stop, self._make_estimator, self.est_buf, self.latest,
                                         rc.max_imu_gap_s)
        mount = None
        if mavlink_factory is None and cfg.mavlink.url:
            mavlink_factory = _default_mavlink_factory(cfg, self._calibration_now)
            mount = self._set_mount
        self.output = OutputWorker(self.stop, self.latest, mavlink_factory, rc.trajectory_file, rc.reconnect_max_s,
                                   vision_ok=self.camera_fresh, mount=mount)
        self.recorder = (RecorderWorker(self.stop, self.rec_buf, rc.record_dir, self._calibration_now)
                         if self.rec_buf is not None else None)
        self.started = time.time()
        self.started_mono = time.monotonic()
        self.ready = False
        self.rates = RateWindow()
        self.watchdog_s = watchdog_interval_s()
        self._last_watchdog = 0.0
        self._last_status: dict = {}
        self._logged_overflow = 0
        self._logged_drops = 0
        self._stall_warned = False

    # -- wiring ---------------------------------------------------------------------------------------
    def _calibration_now(self) -> Any:
        if not self.source.calibration_ready.is_set() and not self.cfg.source.calibration:
            return None
        return load_run_calibration(self.cfg, self.source.calibration)

    def _set_mount(self, mav: Any) -> bool:
        """Give the MAVLink output the camera mount from the calibration once it is known (an OAK reports
        it only after boot); True when done."""
        calib = self._calibration_now()
        if calib is None:
            return False
        try:
            mav.set_camera_mount(calib.cam0.T_body_cam)
        except VioError as e:  # the calibration does not decide the mount: the output says so, once
            log.error("camera mount: %s; set [mavlink] mount = 'rpy' and mount_rpy_deg", e)
        return True

    def camera_fresh(self) -> bool:
        """The daemon's own fact: camera frames arrived within VISION_STALE_S (host time)."""
        last = self.source.last_frame
        return last > 0 and time.monotonic() - last <= VISION_STALE_S

    def _make_estimator(self) -> EstimatorApi | None:
        # the estimator needs the calibration, which an OAK only reports once it is open
        while not self.stop.is_set():
            calib = self._calibration_now()
            if calib is not None:
                return self._estimator_factory(calib)
            self.estimator.beat()
            self.source.calibration_ready.wait(0.1)
        return None  # stopping before the sensors ever came up

    @property
    def workers(self) -> list[Worker]:
        return [w for w in (self.source, self.estimator, self.output, self.recorder) if w is not None]

    # -- main loop ------------------------------------------------------------------------------------
    def run(self) -> int:
        self.notifier.status("starting: opening sensors")
        for w in self.workers:
            w.start()
        next_status = time.monotonic() + 1.0
        while not self.stop.is_set():
            self.stop.wait(0.05)
            self._check_ready()
            self._feed_watchdog()
            if time.monotonic() >= next_status:
                next_status += 1.0
                self.report()
        return self.shutdown()

    def request_stop(self, signum: int | None = None, _frame: Any = None) -> None:
        if signum is not None and not self.stop.is_set():
            log.info("received %s: stopping", signal.Signals(signum).name)
        self.stop.set()
        self.est_buf.wake()
        if self.rec_buf is not None:
            self.rec_buf.wake()
        self.latest.wake()

    def shutdown(self) -> int:
        t0 = time.monotonic()
        self.notifier.stopping()
        self.stop.set()
        deadline = t0 + JOIN_BUDGET_S
        stuck = []
        for w in self.workers:  # source first: no new data; recorder last: it flushes what was queued
            w.join(max(0.0, deadline - time.monotonic()))
            if w.is_alive():
                stuck.append(w.name)
        status = self.snapshot()
        status["state"] = "stopped"
        self._write_status(status)
        if stuck:
            log.warning("stopped with %s still busy after %.1f s (abandoned)", ", ".join(stuck), JOIN_BUDGET_S)
        log.info("stopped in %.2f s: %s", time.monotonic() - t0, self._summary(status))
        self.notifier.close()
        return 0

    def _check_ready(self) -> None:
        """READY=1 once the pipeline is up: threads started and sensor data flowing, or after
        `run.ready_timeout_s` without data (systemd would otherwise kill and restart a daemon whose camera
        is unplugged at boot; the daemon keeps reopening it by itself). A first pose is not needed."""
        if self.ready:
            return
        up = time.monotonic() - self.started_mono
        if self.source.connected:
            why = "sensors delivering"
        elif up >= self.cfg.run.ready_timeout_s:
            why = f"no sensor data after {up:.0f} s ({self.source.last_error or 'starting'}); still trying"
        else:
            return
        self.ready = True
        log.info("ready after %.1f s: %s", up, why)
        self.notifier.ready(why)

    def _warn_stall(self, tracking: bool, sensors_ok: bool) -> None:
        """Sensors deliver but no pose for `run.stall_timeout_s`: one warning naming why (lens cap, darkness,
        a sensor error). The watchdog is NOT stopped for it: a restart would not bring the pose back."""
        if tracking:
            self._stall_warned = False
            return
        since = time.monotonic() - (self.estimator.last_state_time or self.started_mono)
        if self._stall_warned or not sensors_ok or since < self.cfg.run.stall_timeout_s:
            return
        self._stall_warned = True
        log.warning("waiting for vision: sensors deliver but no tracked pose for %.0f s (%s)", since,
                    _not_tracking_reason(self.estimator.health, self.camera_fresh()))

    def healthy(self) -> tuple[bool, list[str]]:
        """Alive = every loop beat recently and no thread died. No pose is not a reason: see _warn_stall."""
        problems = []
        for w in self.workers:
            if w.crashed:
                problems.append(f"{w.name} thread died ({w.crashed})")
            elif not w.is_alive() and not self.stop.is_set():
                problems.append(f"{w.name} thread ended")
            elif w.beat_age_s() > STUCK_S:
                problems.append(f"{w.name} loop stuck for {w.beat_age_s():.0f} s")
        return not problems, problems

    def _feed_watchdog(self) -> None:
        if self.watchdog_s is None or time.monotonic() - self._last_watchdog < self.watchdog_s:
            return
        ok, problems = self.healthy()
        if ok:
            self.notifier.watchdog()
            self._last_watchdog = time.monotonic()
        elif self._last_watchdog >= 0:
            log.error("not feeding the systemd watchdog: %s", "; ".join(problems))
            self._last_watchdog = -1.0  # log once; systemd will restart us

    # -- status ---------------------------------------------------------------------------------------
    def snapshot(self) -> dict:
        now = time.monotonic()
        src, est, out = self.source, self.estimator, self.output
        counters = {
            "camera": self.est_buf.frames_in, "imu": self.est_buf.imu_in, "estimator": est.frames,
            "output": out.sent, "poses": est.good_states,
        }
        rates = {k: round(v, 1) for k, v in self.rates.rates(counters).items()}
        ok, problems = self.healthy()
        warnings = list(problems)
        frame_age = now - src.last_frame if src.last_frame else None
        imu_age = now - src.last_imu if src.last_imu else None
        camera_ok = self.camera_fresh()
        imu_ok = imu_age is not None and imu_age <= VISION_STALE_S
        if not src.connected:
            warnings.append(f"sensors not delivering ({src.last_error or 'starting'})")
        else:
            if not camera_ok:
                warnings.append("camera: no frames" + (f" for {frame_age:.1f} s" if frame_age is not None else ""))
            if not imu_ok:
                warnings.append("IMU: no samples" + (f" for {imu_age:.1f} s" if imu_age is not None else "")
                                + ": no poses")
        if self.est_buf.frames_dropped > self._logged_drops:
            warnings.append(f"{self.est_buf.frames_dropped - self._logged_drops} frames dropped (estimator behind)")
            self._logged_drops = self.est_buf.frames_dropped
        if self.est_buf.imu_overflow > self._logged_overflow:
            warnings.append(f"IMU buffer overflow: {self.est_buf.imu_overflow - self._logged_overflow} samples lost")
            self._logged_overflow = self.est_buf.imu_overflow
        state, h = est.last_state, est.health
        pose_age = now - est.last_state_time if est.last_state_time else None
        # the truth about tracking: the last state said so, it is fresh, camera frames arrive, and the
        # estimator (which knows whether a usable frame reached its back end) agrees
        tracking = bool(state is not None and state.tracking and pose_age is not None and pose_age <= VISION_STALE_S
                        and camera_ok and (h is None or h.tracking))
        if h is not None and h.sensor_error:
            warnings.append(f"sensor error: {h.sensor_error}")
        if self.ready and not tracking:
            warnings.append(f"not tracking: {_not_tracking_reason(h, camera_ok, imu_ok)}")
        self._warn_stall(tracking, src.connected and imu_ok)
        link = out.link()
        if link["state"] in ("down", "closed"):
            warnings.append(f"autopilot link {link['state']}")
        recording = self.recorder.status() if self.recorder is not None else None
        if recording is not None and recording["state"] == "failed":
            warnings.append(f"recording failed: {recording['error']}")
        trajectory = out.trajectory.status()
        if trajectory is not None and trajectory["state"] == "failed":
            warnings.append(f"trajectory file failed: {trajectory['error']}")
        lat = sorted(out.latency_ms)
        if not self.ready:
            mode = "starting"
        elif not ok:
            mode = "unhealthy"
        elif not tracking and src.connected and imu_ok:
            mode = "waiting for vision"  # the pipeline runs; no pose until the camera sees something usable
        elif warnings or not tracking:
            mode = "degraded"
        else:
            mode = "running"
        snap = {
            "version": STATUS_VERSION,
            "pid": os.getpid(),
            "state": mode,
            "healthy": mode == "running",  # `vio status` exits 0 only then
            "written_unix": time.time(),
            "started_unix": self.started,
            "uptime_s": round(now - self.started_mono, 1),
            "rates_hz": rates,
            "source": {"kind": self.cfg.source.kind, "connected": src.connected, "finished": src.finished,
                       "disconnects": src.disconnects, "last_error": src.last_error,
                       "last_frame_age_s": _round(frame_age), "last_imu_age_s": _round(imu_age),
                       "frames_dropped": self.est_buf.frames_dropped, "imu_overflow": self.est_buf.imu_overflow,
                       "driver": _source_health(src.source)},
            "estimator": {
                "tracking": tracking,
                "quality": (state.quality if tracking else 0) if state is not None else None,
                "initialized": h.initialized if h is not None else None,
                "reset_counter": state.reset_counter if state is not None else None,
                "daemon_resets": est.resets,
                "errors": est.errors,
                "tracks": est.tracks,
                "last_pose_age_s": _round(pose_age),
                "position_m": [round(float(x), 3) for x in state.T_world_body[:3, 3]] if state is not None else None,
                **(_health_fields(h) if h is not None else {}),
            },
            "latency_ms": {"p50": round(lat[len(lat) // 2], 1), "max": round(lat[-1], 1)} if lat else None,
            "mavlink": {**link, "sent": out.sent, "errors": out.errors, "withheld_no_camera": out.withheld},
            "recording": recording,
            "trajectory_file": trajectory,
            "watchdog": {"enabled": self.watchdog_s is not None, "fed": self._last_watchdog > 0},
            "warnings": warnings,
        }
        return snap

    def report(self) -> None:
        snap = self.snapshot()
        self._last_status = snap
        line = self._summary(snap)
        log.info("%s", line)
        self.notifier.status(line)
        self._write_status(snap)

    @staticmethod
    def _summary(s: dict) -> str:
        r, e = s["rates_hz"], s["estimator"]
        lat = s["latency_ms"]
        parts = [
            s["state"],
            f"cam {r['camera']:.1f} Hz imu {r['imu']:.0f} Hz out {r['output']:.1f} Hz",
            f"tracks {_dash(e['tracks'])} q {_dash(e['quality'])}",
            f"resets {e['reset_counter'] or 0}",
            f"latency {lat['p50']:.0f}/{lat['max']:.0f} ms" if lat else "latency -",
            f"mav {s['mavlink']['state']}",
        ]
        if s["warnings"]:
            parts.append("WARN " + "; ".join(s["warnings"]))
        return " | ".join(parts)

    def _write_status(self, snap: dict) -> None:
        path = self.cfg.run.status_file
        if not path:
            return
        try:
            write_status_file(Path(path), snap)
        except OSError as e:
            if not getattr(self, "_status_warned", False):
                log.warning("cannot write status file %s: %s", path, e.strerror)
                self._status_warned = True


def _round(v: float | None, nd: int = 2) -> float | None:
    return None if v is None else round(v, nd)


def _health_fields(h: EstimatorHealth) -> dict:
    """The estimator's own account (vio.estimator.EstimatorHealth) for the status file."""
    return {"vision_age_s": _round(h.vision_age_s), "frames_processed": h.frames_processed,
            "frames_unusable": h.frames_unusable, "unusable_reasons": dict(h.unusable_reasons),
            "frames_dropped": h.frames_dropped, "imu_rejected": h.imu_rejected,
            "imu_rejected_reasons": dict(h.imu_rejected_reasons), "last_reset_reason": h.last_reset_reason,
            "sensor_error": h.sensor_error}


def _not_tracking_reason(h: EstimatorHealth | None, camera_ok: bool, imu_ok: bool = True) -> str:
    """Why there is no pose, in the words a person at the drone needs."""
    if not camera_ok:
        return "no camera frames"
    if not imu_ok:
        return "no IMU samples (camera frames cannot be used without them)"
    if h is None:
        return "estimator starting"
    if h.sensor_error:
        return h.sensor_error
    top = sorted(h.unusable_reasons.items(), key=lambda kv: -kv[1])[:2]
    unusable = f"; unusable frames: {', '.join(f'{k} x{n}' for k, n in top)}" if top else ""
    if not h.initialized:
        return f"not initialised yet (keep the camera still, facing a textured, lit scene){unusable}"
    if h.vision_age_s is None:
        return f"no usable camera frame yet{unusable}"
    return f"last usable camera frame {h.vision_age_s:.1f} s ago (IMU time){unusable}"


def _dash(v: Any) -> str:
    return "-" if v is None else str(v)


def write_status_file(path: Path, snap: dict) -> None:
    """Atomic replace: a reader never sees half a file (temp file in the same folder, then rename)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    tmp.write_text(json.dumps(snap, indent=1, default=_json_default) + "\n")
    os.replace(tmp, path)


def _json_default(o: Any) -> Any:
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    return str(o)


def _default_estimator_factory(cfg: VioConfig) -> Callable[[Any], Any]:
    def make(calib: Any) -> Any:
        from vio.estimator import Estimator as VioEstimator

        return VioEstimator(calib, cfg)
    return make


def _default_mavlink_factory(cfg: VioConfig, calibration: Callable[[], StereoCalibration | None]
                             ) -> Callable[[], Any]:
    def make() -> Any:
        from drivers.mavlink_out import MavlinkOutput

        calib = calibration()  # the camera mount comes from it; unknown yet: Service._set_mount later
        # its own thread answers TIMESYNC within milliseconds (PX4 rejects slow round trips)
        return MavlinkOutput(cfg.mavlink, cfg.mavlink.url,
                             T_body_cam0=calib.cam0.T_body_cam if calib is not None else None).start()
    return make


# ---------------------------------------------------------------------------------------------- CLI glue

def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--config", required=True, help="TOML configuration (e.g. /etc/kestrel-vio/config.toml)")


def run(args: argparse.Namespace) -> int:
    from vio.app.cli import EXIT_CONFIG

    try:
        cfg = load_config(args.config)
        _check_run_config(cfg)
    except VioError as e:
        print(f"vio run: configuration error: {e}", file=sys.stderr)
        return EXIT_CONFIG
    if not (getattr(args, "verbose", False) or getattr(args, "quiet", False)):
        logging.getLogger().setLevel(cfg.run.log_level)
    service = Service(cfg)
    signal.signal(signal.SIGTERM, service.request_stop)
    signal.signal(signal.SIGINT, service.request_stop)
    log.info("kestrel-vio starting: source %s, MAVLink %s, recording %s, watchdog %s", cfg.source.kind,
             cfg.mavlink.url or "off", cfg.run.record_dir or "off",
             f"{service.watchdog_s:.1f} s" if service.watchdog_s else "off")
    return service.run()


def _check_run_config(cfg: VioConfig) -> None:
    """Problems the daemon cannot recover from by retrying: report them now, with the key to fix."""
    src = cfg.source
    if src.kind == "euroc" and not src.dataset:
        raise VioError("[source] kind = 'euroc' needs 'dataset' (path of a EuRoC folder)")
    if src.kind == "euroc" and not Path(src.dataset).exists():
        raise VioError(f"[source] dataset = {src.dataset!r}: folder not found")
    if src.calibration:
        from vio.calibration import load_calibration

        load_calibration(src.calibration)  # raises VioError naming the file and key
    for key in ("record_dir", "trajectory_file"):
        value = getattr(cfg.run, key)
        if not value:
            continue
        parent = Path(value) if key == "record_dir" else Path(value).parent
        existing = next((p for p in (parent, *parent.parents) if p.exists()), None)
        if existing is not None and not os.access(existing, os.W_OK):
            raise VioError(f"[run] {key} = {value!r}: {existing} is not writable")
