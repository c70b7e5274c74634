"""The daemon's source and estimator threads, and the adapters that read a driver's optional attributes."""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import math
import threading
import time
from collections import deque
from collections.abc import Callable, Iterable
from typing import TYPE_CHECKING, Any

import numpy as np

from vio import VioError
from vio.app.daemon.buffers import LatestState, Output, SensorBuffer, _now_ns
from vio.app.daemon.protocols import EstimatorApi, Source
from vio.app.daemon.status import _source_health
from vio.types import ImuSample, NavState, StereoFrame

if TYPE_CHECKING:
    from vio.estimator import EstimatorHealth, ProcessedFrame

log = logging.getLogger(__name__)

FIRST_DATA_TIMEOUT_S = 10.0  # an OAK boots its firmware before the first frame
# driver states (drivers/source.py health()) in which the driver is reconnecting by itself
SELF_HEALING_STATES = ("connecting", "no_device", "disconnected")
HEALTH_EVERY_S = 0.2  # the estimator thread snapshots estimator.health() this often (status reads the copy)


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

    def __init__(self, stop: threading.Event, open_source: Callable[[], Source], sinks: list[SensorBuffer],
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
        self.source: Source | None = None
        self._stamp_error_s = 0.0  # the last source's measure, kept while it is reopened (its data may still be queued)
        self._stamp_error_failed = False

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

    def stamp_uncertainty_s(self) -> float:
        """The source's own measure of how far its IMU stamps may be off [s] (SensorSource.stamp_uncertainty_s), read
        from the output thread; a source whose measure fails is taken as unable to place its stamps (inf, said
        once): no pose rather than one that may be off by any amount."""
        src = self.source
        if src is None:
            return self._stamp_error_s
        try:
            self._stamp_error_s = float(src.stamp_uncertainty_s())
        except Exception as e:  # a driver bug must not pass for a healthy clock
            if not self._stamp_error_failed:
                self._stamp_error_failed = True
                log.error("the source's stamp_uncertainty_s() failed (%s: %s): its stamps are taken as unplaceable",
                          type(e).__name__, e)
            self._stamp_error_s = math.inf
        return self._stamp_error_s

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
                self.calibration = self.source.calibration()
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
            if self.source.finished:
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
                 out: LatestState, max_imu_gap_s: float, loop: Any = None, loop_output: Any = None,
                 view: Any = None) -> None:
        super().__init__("estimator", stop)
        self.loop_worker = loop  # vio.app.loop_worker.LoopWorker: gets every keyframe, never waited for
        self.loop_output = loop_output  # vio.loop.output.CorrectedOutput: what the autopilot gets
        self._left: deque[tuple[int, Any]] = deque(maxlen=16)  # left images of frames not processed yet
        self.view = view  # a vio.app.view.LiveView: submit() never blocks
        self._view_frames: dict[int, Any] = {}  # frame stamp -> left image, until the estimator has processed it
        self._make = make_estimator
        self.buf = buf
        self.out = out
        self.max_gap_ns = int(max_imu_gap_s * 1e9)
        self.estimator: EstimatorApi | None = None
        self._verdict: str | None = None  # a run-final verdict handed in by another thread (stop_for_run)
        self._verdict_applied = False
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
        self._born = time.monotonic()  # for the operator's "first pose after N s" line
        self._reset_base = 0
        self._last_tracked_pose: np.ndarray | None = None  # the newest tracked state's pose, for a new estimator
        self._resets_before = 0  # estimator resets counted before a re-created estimator (status "resets")
        self._last_imu_t: int | None = None
        self._seen_overflow = 0
        # frame stamp -> its arrival time, for frames fed and not yet processed (they wait for IMU); keyed by the
        # stamp, since a frame the estimator drops or a reset clears never comes out (a queue then gave every later
        # frame an older one's arrival, and the latency reported for VISO_DELAY_MS grew: a review's finding)
        self._arrivals: dict[int, int] = {}

    def loop(self) -> None:
        self.estimator = self._make()
        if self.estimator is None:
            return
        while not self.stop_event.is_set():
            self.beat()
            if self._verdict is not None and not self._verdict_applied:
                self._verdict_applied = True
                self.estimator.stop_for_run(self._verdict)
                self._snapshot_health(force=True)
            self._snapshot_health()
            imu, item = self.buf.take(0.1)
            if self.buf.imu_overflow != self._seen_overflow:
                lost = self.buf.imu_overflow - self._seen_overflow
                self._seen_overflow = self.buf.imu_overflow
                self._reset(f"IMU buffer overflow: {lost} samples lost (estimator too slow)", keep_bias=True)
            if imu or item:
                self.last_input = time.monotonic()
            try:
                for s in imu:
                    if self._last_imu_t is not None and s.t_ns - self._last_imu_t > self.max_gap_ns:
                        gap_s = (s.t_ns - self._last_imu_t) / 1e9
                        # a short gap is the same IMU, powered on: its bias holds. A longer one may be a replug or
                        # a device reboot with a new power-on bias, which would block every static restart
                        self._reset(f"IMU gap of {gap_s:.2f} s", keep_bias=gap_s <= KEEP_BIAS_MAX_GAP_S)
                    self._last_imu_t = s.t_ns
                    self._emit(self.estimator.feed_imu(s))
                if item is not None:
                    self.frames += 1
                    result = self.estimator.feed_frame(item[1])
                    # keyed by the stamp the estimator gave the frame (its processed frames carry that one), taken
                    # before _emit collects them: a frame may be processed inside feed_frame
                    t = int(self.estimator.last_frame_stamp_ns)
                    _remember(self._arrivals, t, item[0])
                    if self.loop_worker is not None:
                        self._left.append((t, item[1].left))
                    if self.view is not None:
                        _remember(self._view_frames, t, item[1].left)
                    self._emit(result)
            except Exception as e:  # gtsam raises RuntimeError and friends; any failure means reset
                self.errors += 1
                self._reset(f"estimator failed: {type(e).__name__}: {e}")

    def stop_for_run(self, problem: str) -> None:
        """Stop the estimator for the rest of this run (no pose, no restart), from any thread: applied on this
        worker's thread before its next input, as the estimator's own verdict on the IMU is."""
        self._verdict = problem

    def _stopped_for_run(self) -> str | None:
        """The current estimator's run-final verdict (EstimatorHealth.stopped_for_run): asked of it, or, where its
        health() fails too, taken from the last snapshot."""
        try:
            return self.estimator.health().stopped_for_run
        except Exception as e:  # an estimator whose reset() raised may fail here too
            log.debug("estimator health() failed: %s", e)
            return self.health.stopped_for_run if self.health is not None else None

    def _to_view(self, pf: ProcessedFrame) -> None:
        """Hand a processed frame (image, features, state) to the live view."""
        t = pf.t_ns
        left = self._view_frames.pop(t, None)
        for old in [k for k in self._view_frames if k < t]:
            del self._view_frames[old]
        h = self.health
        self.view.submit(t, left, pf.features, pf.state or self.last_state, bool(pf.timings.keyframe),
                         {"resets": self.resets + (h.reset_counter if h else 0), "frames": self.frames,
                          "errors": self.errors})

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

    @property
    def resets_before(self) -> int:
        """Estimator resets before the current estimator was made (a re-created estimator counts from 0), loop
        correction steps left out."""
        return self._resets_before

    def _frame_arrival(self, done: list[ProcessedFrame]) -> int:
        """Arrival time of the newest frame finished by this call, or -1 (an IMU-rate state only).

        A frame waits inside the estimator until the IMU reaches its stamp, so its state may come out of a
        later feed_imu(); take_processed() says which call finished which frames."""
        arrival = -1
        for pf in done:
            arrival = self._arrivals.pop(int(pf.t_ns), -1)
            for old in [k for k in self._arrivals if k < pf.t_ns]:  # fed before it and never processed
                del self._arrivals[old]
        return arrival

    def _to_loop(self, pf: ProcessedFrame) -> None:
        """Hand a processed keyframe to the loop-closure thread."""
        kf = pf.keyframe  # solved in this frame's call: this frame's or (solve_next_frame) the last's
        if kf is not None:
            for t, left in self._left:
                if t == kf.t_ns:
                    st = kf.state
                    # the published counter: a re-created estimator counts from 0 again, and the loop stage must
                    # see it as a new odometry segment (it chained the new frame to the old one as one flight)
                    self.loop_worker.submit(st.t_ns, st.T_world_body, left, kf.features,
                                            st.reset_counter + self._reset_base)
        self.loop_worker.settle(pf.settled)  # after the keyframe: a full queue drops these first
        # this frame's image stays until the next frame: it may be a keyframe solved then
        while self._left and self._left[0][0] < pf.t_ns:
            self._left.popleft()

    def _emit(self, result: Any) -> None:
        done = self.estimator.take_processed()
        arrival_ns = self._frame_arrival(done)
        for pf in done:
            if self.loop_worker is not None:
                self._to_loop(pf)
            if self.view is not None:
                self._to_view(pf)
        for state in _as_states(result):
            if state.tracking and np.isfinite(state.T_world_body).all():
                self._last_tracked_pose = state.T_world_body  # the estimator's own frame (no loop correction)
            odometry = None
            if self.loop_output is not None:
                odometry = state
                state = self.loop_output.apply(state, *self.loop_worker.correction())
            if self._reset_base:
                state = dataclasses.replace(state, reset_counter=state.reset_counter + self._reset_base)
            self.states += 1
            self.last_state = state
            if state.tracking:
                if not self.good_states:
                    log.info("first pose after %.1f s: tracking", time.monotonic() - self._born)
                self.good_states += 1
                self.last_state_time = time.monotonic()
            self.out.publish(Output(state, arrival_ns, _now_ns(), odometry))

    def _reset(self, why: str, keep_bias: bool = False) -> None:
        """`keep_bias`: samples were lost but the estimate was sound (an IMU gap, a full buffer): the restart must
        agree with its gyro bias; after an exception nothing of the old estimate is trusted."""
        self.resets += 1
        log.warning("daemon-forced estimator reset #%d: %s", self.resets, why)
        last = self.last_state.reset_counter if self.last_state is not None else -1
        try:
            # keeps the last pose as the new origin and bumps the estimator's reset_counter; not carried
            # forward with the IMU: these resets follow lost IMU samples or an estimator in an unknown state
            self.estimator.reset(why, bridge=False, keep_bias=keep_bias)
            self._snapshot_health(force=True)  # the status counts the reset now, not at the next snapshot
            return
        except Exception as e:
            log.warning("estimator reset() failed (%s); creating a new estimator", e)
        verdict = self._stopped_for_run()
        self.estimator = self._make()
        go_on = getattr(self.estimator, "continue_from", None)
        if go_on is not None and self._last_tracked_pose is not None:
            # where the old one's frame had the vehicle last: started at its own origin, the new estimator sent a
            # position of all that was flown, which the autopilot takes at the new reset_counter (a review's note)
            go_on(self._last_tracked_pose)
        if verdict and self.estimator is not None:  # the sensor is as wrong as it was: a new start must not fly on it
            self.estimator.stop_for_run(verdict)
            log.error("the new estimator stays stopped for the rest of this run, as the old one was: %s", verdict)
        # the old estimator's resets, and this one, before the new estimator's own count (loop steps left out)
        old_resets = self.health.reset_counter if self.health is not None else 0
        self._resets_before += old_resets + 1
        self._reset_base = last + 1  # a new estimator counts from 0: keep the autopilot's counter moving
        if self.loop_output is not None:
            self.loop_output.restart(self._reset_base)  # no correction held maps the new estimator's frame
        self._last_imu_t = None
        self._arrivals.clear()
        self._snapshot_health(force=True)  # the status sees the new estimator's count, not the old one's twice


PENDING_FRAMES = 64  # frames fed and not processed yet that are remembered (3 s at 20 Hz)
KEEP_BIAS_MAX_GAP_S = 3.0  # an IMU gap up to this keeps the gyro bias for the restart to agree with


def _remember(pending: dict, t_ns: int, value: Any) -> None:
    """pending[t_ns] = value, forgetting the oldest beyond PENDING_FRAMES: frames the estimator never processes
    (it holds or drops them while the IMU is silent) must not pile up (full images: 300 MB a minute)."""
    pending[t_ns] = value
    while len(pending) > PENDING_FRAMES:
        del pending[next(iter(pending))]


def _iter_messages(source: Source, stop: threading.Event) -> Iterable[ImuSample | StereoFrame | None]:
    """Messages from a source; None when nothing arrived for a short while (lets the caller check timeouts)."""
    while not stop.is_set():
        batch = source.poll()
        if batch:
            yield from batch
            continue
        if source.finished:
            return
        yield None
        stop.wait(0.005)  # poll() never blocks: a short sleep keeps an idle source from spinning a core


def _as_states(result: Any) -> list[NavState]:
    if result is None:
        return []
    if isinstance(result, NavState):
        return [result]
    return [s for s in result if isinstance(s, NavState)]
