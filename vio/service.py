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
and reopened with backoff; an estimator exception resets the estimator; a MAVLink error reopens the link.
Only an invalid configuration ends the process (exit code 3, `vio.cli.EXIT_CONFIG`).

This module is the only place in `vio` that imports `drivers` (inside functions, so `vio` stays usable
without them).
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import json
import logging
import math
import os
import signal
import sys
import threading
import time
from collections import deque
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Any

import numpy as np

from vio import VioError
from vio.config import VioConfig, load_config
from vio.geometry import rot_to_quat_wxyz
from vio.sdnotify import SdNotifier, watchdog_interval_s
from vio.trajectory import format_tum_line
from vio.types import ImuSample, NavState, StereoFrame

log = logging.getLogger(__name__)

STATUS_VERSION = 1
FIRST_DATA_TIMEOUT_S = 10.0  # an OAK boots its firmware before the first frame
# driver states (drivers/source.py health()) in which the driver is reconnecting by itself
SELF_HEALING_STATES = ("connecting", "no_device", "disconnected")
JOIN_BUDGET_S = 1.6  # shutdown must finish within 2 s of SIGTERM; keep a margin for the final status write


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

    def _push(self, q: deque, item: Any, limit: int) -> bool:
        """Append under the lock, dropping the oldest entry when full; True when nothing was dropped."""
        with self._cv:
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
            return imu, item

    def clear(self) -> None:
        with self._cv:
            self._frames.clear()
            self._imu.clear()

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
                 timeout_s: float, reconnect_max_s: float) -> None:
        super().__init__("source", stop)
        self._open = open_source
        self.sinks = sinks
        self.timeout_s = timeout_s
        self.reconnect_max_s = reconnect_max_s
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
            raise VioError("source ended")


class EstimatorWorker(Worker):
    """Feeds the estimator in time order; an exception or an IMU gap resets it instead of ending the process."""

    def __init__(self, stop: threading.Event, make_estimator: Callable[[], Any], buf: SensorBuffer,
                 out: LatestState, max_imu_gap_s: float) -> None:
        super().__init__("estimator", stop)
        self._make = make_estimator
        self.buf = buf
        self.out = out
        self.max_gap_ns = int(max_imu_gap_s * 1e9)
        self.estimator: Any = None
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

    def _frame_arrival(self) -> int:
        """Arrival time of the frame a state came from, or -1 for an IMU-rate state.

        A frame waits inside the estimator until the IMU reaches its stamp, so its state may come out of a
        later feed_imu(); the estimator's `frames_processed` counter tells which call finished a frame."""
        done = getattr(self.estimator, "frames_processed", None)
        if done is None:  # an estimator without the counter: only feed_frame results count as frame states
            return self._arrivals.pop() if self._arrivals else -1
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
        reset = getattr(self.estimator, "reset", None)
        if callable(reset):
            try:
                # keeps the last pose as the new origin and bumps the estimator's reset_counter; not carried
                # forward with the IMU: these resets follow lost IMU samples or an estimator in an unknown state
                reset(why, bridge=False)
                return
            except Exception as e:
                log.warning("estimator reset() failed (%s); creating a new estimator", e)
        self.estimator = self._make()
        self._reset_base = last + 1  # a new estimator counts from 0: keep the autopilot's counter moving
        self._last_imu_t = None
        self._arrivals.clear()
        self._processed = 0


class OutputWorker(Worker):
    """Sends the newest state over MAVLink (the MAVLink class rate-limits) and appends the TUM log."""

    def __init__(self, stop: threading.Event, latest: LatestState, open_mavlink: Callable[[], Any] | None,
                 trajectory_file: str, reconnect_max_s: float) -> None:
        super().__init__("output", stop)
        self.latest = latest
        self._open = open_mavlink
        self.trajectory_file = trajectory_file
        self.reconnect_max_s = reconnect_max_s
        self.mav: Any = None
        self.offered = 0  # states handed to the MAVLink output (it sends the newest at its own rate)
        self._sent_base = 0  # states sent by MAVLink outputs closed since start
        self.errors = 0
        self.latency_ms: deque[float] = deque(maxlen=200)
        self._seq = 0
        self._tum: Any = None
        self._next_open = 0.0
        self._backoff = 0.5

    def loop(self) -> None:
        if self.trajectory_file:
            Path(self.trajectory_file).parent.mkdir(parents=True, exist_ok=True)
            self._tum = open(self.trajectory_file, "a", buffering=1)
        try:
            while not self.stop_event.is_set():
                self.beat()
                self._ensure_mavlink()
                self._seq, out, frames = self.latest.wait_newer(self._seq, 0.02)
                if out is not None:
                    self._send(out.state)
                for f in frames:
                    self._frame_done(f)
                self._poll()
        finally:
            self.close()

    def _ensure_mavlink(self) -> None:
        if self._open is None or self.mav is not None or time.monotonic() < self._next_open:
            return
        try:
            self.mav = self._open()
            self._backoff = 0.5
        except Exception as e:  # a missing serial port at boot: retry, the autopilot may power up later
            self.errors += 1
            log.warning("MAVLink open failed: %s; retrying in %.1f s", e, self._backoff)
            self._next_open = time.monotonic() + self._backoff
            self._backoff = min(self._backoff * 2, self.reconnect_max_s)

    def _send(self, s: NavState) -> None:
        if self.mav is not None:
            try:
                self.mav.send_state(s)
                self.offered += 1
            except Exception as e:
                self._mav_failed(e)

    def _frame_done(self, out: Output) -> None:
        """Per camera frame: TUM line, and the latency from frame arrival until its state (or a newer one
        propagated from it) has been handed to the MAVLink output."""
        s = out.state
        if self._tum is not None and s.tracking:
            self._tum.write(format_tum_line(s.t_ns, s.T_world_body[:3, 3], rot_to_quat_wxyz(s.T_world_body[:3, :3])))
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
        if self._tum is not None:
            self._tum.close()
            self._tum = None


class RecorderWorker(Worker):
    """Writes what the sensors deliver to a EuRoC dataset; PNG encoding must never slow the estimator."""

    def __init__(self, stop: threading.Event, buf: SensorBuffer, record_dir: str,
                 calibration: Callable[[], Any]) -> None:
        super().__init__("recorder", stop)
        self.buf = buf
        self.record_dir = record_dir
        self._calibration = calibration
        self.writer: Any = None
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
        self.writer = EurocWriter(_fresh_record_dir(self.record_dir), calib)
        log.info("recording to %s", self.writer.root)
        try:
            while not self.stop_event.is_set():
                self.beat()
                self._write(*self.buf.take(0.1))
            deadline = time.monotonic() + 0.5  # flush what is queued, but within the shutdown budget
            while len(self.buf) and time.monotonic() < deadline:
                self._write(*self.buf.take(0.0))
        finally:
            self.writer.close()

    def _write(self, imu: list[ImuSample], item: tuple[int, StereoFrame] | None) -> None:
        for s in imu:
            self.writer.write_imu(s)
            self.imu += 1
        if item is not None:
            self.writer.write_frame(item[1])
            self.frames += 1


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
        if getattr(source, "finished", False):
            return
        yield None
        stop.wait(0.005)  # poll() never blocks: a short sleep keeps an idle source from spinning a core


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
        self.source = SourceWorker(self.stop, source_factory or (lambda: open_source(cfg)),
                                   [b for b in (self.est_buf, self.rec_buf) if b is not None],
                                   rc.source_timeout_s, rc.reconnect_max_s)
        self._estimator_factory = estimator_factory or _default_estimator_factory(cfg)
        self.estimator = EstimatorWorker(self.stop, self._make_estimator, self.est_buf, self.latest,
                                         rc.max_imu_gap_s)
        if mavlink_factory is None and cfg.mavlink.url:
            mavlink_factory = _default_mavlink_factory(cfg)
        self.output = OutputWorker(self.stop, self.latest, mavlink_factory, rc.trajectory_file, rc.reconnect_max_s)
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

    # -- wiring ---------------------------------------------------------------------------------------
    def _calibration_now(self) -> Any:
        if not self.source.calibration_ready.is_set() and not self.cfg.source.calibration:
            return None
        return load_run_calibration(self.cfg, self.source.calibration)

    def _make_estimator(self) -> Any:
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
        if not self.ready and self.estimator.good_states > 0:
            self.ready = True
            log.info("first pose after %.1f s: ready", time.monotonic() - self.started_mono)
            self.notifier.ready("tracking")

    def healthy(self) -> tuple[bool, list[str]]:
        """Alive = every loop beat recently and no thread died; the estimator is not stalled on live input."""
        problems = []
        for w in self.workers:
            if w.crashed:
                problems.append(f"{w.name} thread died ({w.crashed})")
            elif not w.is_alive() and not self.stop.is_set():
                problems.append(f"{w.name} thread ended")
            elif w.beat_age_s() > 5.0:
                problems.append(f"{w.name} loop stuck for {w.beat_age_s():.0f} s")
        now = time.monotonic()
        est = self.estimator
        inputs_flow = est.last_input > 0 and now - est.last_input < 2.0
        since_pose = now - (est.last_state_time or self.started_mono)
        if inputs_flow and since_pose > self.cfg.run.stall_timeout_s:
            problems.append(f"stalled: sensor data but no pose for {since_pose:.0f} s")
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
        if not src.connected:
            warnings.append(f"sensors not delivering ({src.last_error or 'starting'})")
        else:
            if now - (src.last_frame or now) > 1.0 or src.last_frame == 0:
                warnings.append("camera: no frames")
            if now - (src.last_imu or now) > 1.0 or src.last_imu == 0:
                warnings.append("IMU: no samples")
        if self.est_buf.frames_dropped > self._logged_drops:
            warnings.append(f"{self.est_buf.frames_dropped - self._logged_drops} frames dropped (estimator behind)")
            self._logged_drops = self.est_buf.frames_dropped
        if self.est_buf.imu_overflow > self._logged_overflow:
            warnings.append(f"IMU buffer overflow: {self.est_buf.imu_overflow - self._logged_overflow} samples lost")
            self._logged_overflow = self.est_buf.imu_overflow
        state = est.last_state
        pose_age = now - est.last_state_time if est.last_state_time else None
        if state is not None and not state.tracking:
            warnings.append("tracking lost")
        link = out.link()
        if link["state"] in ("down", "closed"):
            warnings.append(f"autopilot link {link['state']}")
        lat = sorted(out.latency_ms)
        if not self.ready:
            mode = "starting"
        elif not ok:
            mode = "unhealthy"
        elif warnings or pose_age is None or pose_age > 1.0:
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
            "source": {"kind": self.cfg.source.kind, "connected": src.connected,
                       "disconnects": src.disconnects, "last_error": src.last_error,
                       "frames_dropped": self.est_buf.frames_dropped, "imu_overflow": self.est_buf.imu_overflow,
                       "driver": _source_health(src.source)},
            "estimator": {
                "reset_counter": state.reset_counter if state is not None else None,
                "daemon_resets": est.resets,
                "errors": est.errors,
                "tracking": state.tracking if state is not None else None,
                "quality": state.quality if state is not None else None,
                "tracks": _estimator_tracks(est.estimator),
                "last_pose_age_s": round(pose_age, 2) if pose_age is not None else None,
                "position_m": [round(float(x), 3) for x in state.T_world_body[:3, 3]] if state is not None else None,
            },
            "latency_ms": {"p50": round(lat[len(lat) // 2], 1), "max": round(lat[-1], 1)} if lat else None,
            "mavlink": {**link, "sent": out.sent, "errors": out.errors},
            "recording": ({"dir": str(self.recorder.writer.root) if self.recorder.writer else None,
                           "frames": self.recorder.frames, "imu": self.recorder.imu,
                           "frames_dropped": self.rec_buf.frames_dropped}
                          if self.recorder is not None else None),
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


def _estimator_tracks(est: Any) -> int | None:
    """Tracked features in the newest frame (the estimator's `n_tracks`, else its last FeatureFrame)."""
    v = getattr(est, "n_tracks", None)
    if isinstance(v, (int, np.integer)):
        return int(v)
    ff = getattr(est, "last_features", None)
    ids = getattr(ff, "ids", None)
    return len(ids) if ids is not None else None


def _default_estimator_factory(cfg: VioConfig) -> Callable[[Any], Any]:
    def make(calib: Any) -> Any:
        from vio.estimator import Estimator as VioEstimator

        return VioEstimator(calib, cfg)
    return make


def _default_mavlink_factory(cfg: VioConfig) -> Callable[[], Any]:
    def make() -> Any:
        from drivers.mavlink_out import MavlinkOutput

        # its own thread answers TIMESYNC within milliseconds (PX4 rejects slow round trips)
        return MavlinkOutput(cfg.mavlink, cfg.mavlink.url).start()
    return make


# ---------------------------------------------------------------------------------------------- CLI glue

def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--config", required=True, help="TOML configuration (e.g. /etc/kestrel-vio/config.toml)")


def run(args: argparse.Namespace) -> int:
    from vio.cli import EXIT_CONFIG

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
