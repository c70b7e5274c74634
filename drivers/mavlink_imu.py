"""The flight controller's own IMU over MAVLink (`[source] imu = "mavlink"`): HIGHRES_IMU, SCALED_IMU or RAW_IMU.

Many vehicles have no separate IMU for the companion: the flight controller's is good, already mounted
on dampers and calibrated. This source reads it from the autopilot's MAVLink stream and delivers
ImuSamples on the host clock like any other source (drivers/base.py).

* Connection: a drivers.mavlink_link.MavlinkLink, by default the SAME one the pose output uses (a serial
  port opens once only); the link's reader thread calls us for each IMU, TIMESYNC, HEARTBEAT and
  COMMAND_ACK message, and our own thread only sends (TIMESYNC requests, the rate request).
* Rate: MAV_CMD_SET_MESSAGE_INTERVAL for the configured message once the autopilot's heartbeat is seen,
  repeated until acknowledged, and again when the stream stops (an autopilot reboot forgets it). A
  refusal is logged once with the parameter that sets the rate instead (docs/autopilot.md).
* Units and axes: HIGHRES_IMU is SI; SCALED_IMU is mG and mrad/s; RAW_IMU needs the scales from the config.
  The autopilot reports body FRD axes (its board orientation already applied); `axes` = "flu" turns them
  into x forward, y left, z up. The estimator's body frame is then the flight controller's, so the camera
  extrinsics (T_body_cam0) must be given relative to it.
* Time: the message's time_usec (time_boot_ms for SCALED_IMU) is the autopilot's clock. TIMESYNC round
  trips at 10 Hz feed a drift-tracking fit (timesync.ClockSync in round-trip mode) that maps it onto
  CLOCK_MONOTONIC. Until the first answer the samples are HELD (at most HOLD_S; one log line, `holds` / `held` /
  `backlog` in health()) and then placed by it: a link delivers a backlog at once on (re)connection, and the
  arrival fit used until then put a sample that had waited 1.86 s at its arrival. If the autopilot never answers,
  the arrival-time lower envelope of the IMU messages themselves is used, never later than a sample's arrival
  (nor, for held ones, than a later sample's arrival less their device-time difference). A stamp that goes back
  by more than REBOOT_BACK_S is an autopilot reboot: both fits restart, the samples are held again, and answers
  to requests sent before it are ignored. A change of mapping (a refit, the first TIMESYNC answer replacing the
  arrival envelope after a hold that timed out) is slewed in over a few
  samples instead of stepped, so host stamps never go back and no sample is dropped for it.
* Honesty: a duplicate stamp or one older than the previous (UDP reordering) is dropped and counted; gaps,
  the measured rate, stamp jitter and transport latency are in health(). No IMU message after
  NO_DATA_WARN_S with another IMU message on the link, or an acceleration far from 1 g at the start,
  gives one log line naming the key to fix.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections import Counter, deque
from collections.abc import Callable
from typing import Any

import numpy as np

from drivers.base import DropOldestQueue, Message, ThreadedSource
from drivers.mavlink_link import MavlinkLink, is_autopilot_heartbeat, mavlink
from drivers.timesync import ClockSync, StreamMonitor
from vio.types import ImuSample

log = logging.getLogger(__name__)

IMU_MESSAGES = ("HIGHRES_IMU", "SCALED_IMU", "RAW_IMU")
# message -> (MAVLink id, default accel scale [m/s^2 per unit], default gyro scale [rad/s per unit]);
# RAW_IMU has none: its units are the sensor's own unless the autopilot says otherwise
_UNITS = {"HIGHRES_IMU": (105, 1.0, 1.0), "SCALED_IMU": (26, 9.80665e-3, 1e-3), "RAW_IMU": (27, 0.0, 0.0)}
R_BODY_FRD = {"frd": np.eye(3), "flu": np.diag([1.0, -1.0, -1.0])}
REBOOT_BACK_S = 0.5  # a stamp this far behind the previous one: the autopilot restarted (or its clock did)
TIMESYNC_PERIOD_S = 0.1
REQUEST_PERIOD_S = 1.0  # rate request repeated until acknowledged, at most REQUEST_TRIES times in a row
REQUEST_TRIES = 5
NO_DATA_WARN_S = 3.0  # heartbeat seen, no configured IMU message for this long: say why, once
STATS_WINDOW = 400  # samples behind the rate / jitter / latency figures
CLOCK_DISAGREE_S = 1.0  # TIMESYNC-mapped stamp this far from the arrival: the IMU stamps use another clock
SLEW_FRACTION = 0.5  # a mapping change moves the host stamps by at most this fraction of each sample interval
# At the start and after an autopilot reboot the samples are held until the first TIMESYNC round trip (normally
# 0.1-0.2 s), at most HOLD_S of arrivals (an autopilot that does not answer: then mapped by the arrivals of all the
# samples held) and HOLD_MAX samples (the oldest beyond it dropped, counted). Why: a link delivers a backlog at once
# on (re)connection, and the arrival fit placed a sample that waited 1.86 s at its arrival (docs/autopilot.md).
HOLD_S = 1.0
HOLD_MAX = 4000
BACKLOG_S = 0.1  # a held sample that arrived this long after its mapped stamp was in a backlog (said and counted)
# The newest samples against the mapping, for stamp_uncertainty_s: each one's latency L = arrival - mapped stamp. A
# sample cannot have been made after it arrived, so L falling below every earlier span's floor is a mapping that went
# late by as much (seen at once; L < 0 that has always been so is a constant bias, not a step: see _add_latency); and
# the smallest L
# of the newest samples (those that arrived or were made in the last ARRIVAL_SPAN_S, at least two) rising above the
# largest such smallest L of the spans that arrived ARRIVAL_HOLD_S to ARRIVAL_BASE_S before is a mapping that moved
# early by as much (a device clock that fell behind; seen within ARRIVAL_SPAN_S, and said for ARRIVAL_HOLD_S, by when
# the TIMESYNC measure has it). The TIMESYNC answers alone took 0.6-0.9 s to show a step (six answers at 10 Hz: single
# ones are stamped early on ArduPilot). A span, not a count: a reader that stalled reads its backlog at once, and the
# span then reaches back to a sample read in time. The largest of the earlier spans' floors, not the smallest: the
# rise is judged against the link's own spread (and one span mapped badly at a start does not count). A link whose
# latency rises for good reads as a clock step for ARRIVAL_HOLD_S.
ARRIVAL_SPAN_S = 0.1
ARRIVAL_HOLD_S = 1.0
ARRIVAL_BASE_S = 3.0
ARRIVAL_BASE_MIN_S = 0.5  # no rise is judged on less history than this (a start, a new mapping)
# ... and it is judged only at a sample that arrived in step with the one before (its arrival gap at least half its
# device-time gap and at most STEADY_SLACK_S more): not in the middle of a backlog read at once (a stalled reader,
# TCP), where the samples read so far are the late ones and the span reaches back only to those read before the
# stall; the rise found last is kept meanwhile.
STEADY_SLACK_S = 0.05


class MavlinkImuSource(ThreadedSource):
    """ImuSamples from the autopilot's IMU messages, stamped on the host monotonic clock."""

    name = "mavlink_imu"

    def __init__(self, link: MavlinkLink, *, message: str = "HIGHRES_IMU", rate_hz: float = 200.0,
                 request_rate: bool = True, accel_scale: float = 0.0, gyro_scale: float = 0.0,
                 axes: str = "frd", imu_id: int = 0, owns_link: bool = False, queue_size: int = 4000,
                 clock_ns: Callable[[], int] = time.monotonic_ns) -> None:
        from vio import VioError

        super().__init__()
        if message not in _UNITS:
            raise VioError(f"[source] mavlink_imu_message = {message!r}: expected one of {list(IMU_MESSAGES)}")
        if axes not in R_BODY_FRD:
            raise VioError(f"[source] mavlink_imu_axes = {axes!r}: expected 'frd' or 'flu'")
        msg_id, acc_unit, gyr_unit = _UNITS[message]
        self.accel_scale = accel_scale or acc_unit
        self.gyro_scale = gyro_scale or gyr_unit
        if not (self.accel_scale and self.gyro_scale):
            raise VioError(f"[source] mavlink_imu_message = {message!r} needs mavlink_imu_accel_scale and "
                           "mavlink_imu_gyro_scale (its units are the sensor's own)")
        self.link = link
        self.message, self.msg_id, self.rate_hz = message, msg_id, float(rate_hz)
        self.request_rate = request_rate
        self.axes = axes
        self._R = R_BODY_FRD[axes]
        self.imu_id = imu_id
        self._owns_link = owns_link
        self._clock = clock_ns
        self._queue = DropOldestQueue(queue_size)
        self.join_timeout_s = 2.0
        self.timesync = ClockSync(roundtrip=True)
        self.arrival = ClockSync()
        self.monitor = StreamMonitor(f"MAVLink {message}", rate_hz)
        self._lock = threading.Lock()  # the link thread writes, health() reads
        self._init_state()
        self.last_error = ""

    def _init_state(self) -> None:
        self.received = 0
        self.duplicates = 0
        self.out_of_order = 0
        self.reboots = 0
        self.other_imu = Counter()  # IMU messages of another type or id: the config may name the wrong one
        self.target: tuple[int, int] | None = None  # (system, component) of the autopilot
        self.request_sent = 0
        self.request_result = ""
        self._request_tries = 0
        self._next_request_ns = 0
        self._heartbeat_since_ns: int | None = None
        self._last_sample_arrival_ns: int | None = None
        self._last_dev_ns: int | None = None
        self._slew_state: tuple[int, int] | None = None  # (last device stamp, dev->host offset given out) [ns]
        self._slew_lag_ns = 0  # how far the offset given out still is from the mapping's (being slewed in)
        self._timesync_after_ns = 0  # answers to requests sent before this host time are ignored (reboot)
        self._pending_ts: deque[int] = deque(maxlen=64)
        self.timesync_sent = 0
        self.timesync_used = 0
        self._rtt_ns: deque[int] = deque(maxlen=100)
        self._dev_stamps: deque[int] = deque(maxlen=STATS_WINDOW)
        self._latency_ns: deque[int] = deque(maxlen=STATS_WINDOW)
        self._scale_checked: list[float] = []
        self._warned: set[str] = set()
        self.clock_source = "none"
        self.clock_disagreements = 0
        self._disagree_run = 0
        # holds over the whole run (health()), across reboots
        self.holds = self.held = self.hold_dropped = self.backlog = 0
        self._init_hold()
        self._init_latency_floor()

    def _init_latency_floor(self) -> None:
        """Forget the newest samples' latencies (a new mapping: another clock source, a fit restarted)."""
        self._lat_recent: deque[tuple[int, int, int]] = deque()  # (t_arrival, t_dev, L) of the newest samples
        self._lat_base: deque[list[int]] = deque()  # [first t_arrival, smallest L] per ARRIVAL_SPAN_S before them
        self._lat_key: tuple[str, int, int] | None = None  # the mapping they were taken against
        self._lat_rise_ns = 0  # the rise of their floor as last judged (at a sample that arrived in step)
        self._lat_fall_ns = 0  # how far the newest latencies fell below every earlier span's floor (at once)

    def _init_hold(self) -> None:
        """Hold the next samples until a TIMESYNC round trip places them (the start, an autopilot reboot)."""
        self._holding = True
        self._held: deque[tuple[int, int, np.ndarray, np.ndarray]] = deque()  # (t_dev, t_arrival, gyro, accel)
        self._hold_since_ns: int | None = None

    # ---------------------------------------------------------------- source interface
    def _before_start(self) -> None:
        self.link.subscribe({*IMU_MESSAGES, "TIMESYNC", "HEARTBEAT", "COMMAND_ACK"}, self.on_message)
        self.link.acquire()

    def stop(self) -> None:
        was_running = self._thread is not None
        super().stop()
        if was_running:
            self.link.unsubscribe(self.on_message)
            self.link.release()

    def poll(self) -> list[Message]:
        return self._queue.drain()

    # ---------------------------------------------------------------- our thread: requests only
    def _run(self) -> None:
        next_ts = 0
        while not self._stop.is_set():
            now = self._clock()
            if not self.link.connected:
                self.state = "connecting"
            if now >= next_ts:
                next_ts = now + int(TIMESYNC_PERIOD_S * 1e9)
                self._send_timesync(now)
            self._maybe_request_rate(now)
            self._check_stream(now)
            self._stop.wait(0.02)

    def _send_timesync(self, now: int) -> None:
        self._pending_ts.append(now)
        if self.link.send(mavlink.MAVLink_timesync_message(0, now)):
            self.timesync_sent += 1

    def _maybe_request_rate(self, now: int) -> None:
        if not self.request_rate or self.target is None or now < self._next_request_ns:
            return
        stale = (self._last_sample_arrival_ns is None
                 or now - self._last_sample_arrival_ns > int(NO_DATA_WARN_S * 1e9))
        if self.request_result == "MAV_RESULT_ACCEPTED" and not stale:
            return
        if self._request_tries >= REQUEST_TRIES:
            if stale:  # given up for now; try again later (the autopilot may be rebooting)
                self._request_tries = 0
                self._next_request_ns = now + int(10 * REQUEST_PERIOD_S * 1e9)
            return
        self._request_tries += 1
        self._next_request_ns = now + int(REQUEST_PERIOD_S * 1e9)
        cmd = mavlink.MAVLink_command_long_message(
            self.target[0], self.target[1], mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, 0,
            float(self.msg_id), float(round(1e6 / self.rate_hz)), 0, 0, 0, 0, 0)
        if self.link.send(cmd):
            self.request_sent += 1
            if self.request_sent == 1:
                log.info("requesting %s at %.0f Hz from the autopilot (MAV_CMD_SET_MESSAGE_INTERVAL)",
                         self.message, self.rate_hz)

    def _check_stream(self, now: int) -> None:
        """Set `state` and, once, say why no sample arrives."""
        if self._last_sample_arrival_ns is not None and now - self._last_sample_arrival_ns < int(1e9):
            self.state = "running"
            return
        if self._heartbeat_since_ns is None or not self.link.connected:
            if self.link.connected:
                self.state = "waiting for the autopilot"
            return
        self.state = "no imu"
        if now - self._heartbeat_since_ns < int(NO_DATA_WARN_S * 1e9) or self._last_sample_arrival_ns is not None:
            return
        others = ", ".join(f"{k} ({n})" for k, n in self.other_imu.most_common())
        if others:
            self._error_once("type", f"no {self.message} (id {self.imu_id}) from the autopilot in "
                             f"{NO_DATA_WARN_S:.0f} s, but it sends {others}: set [source] mavlink_imu_message "
                             "(and its scales) or mavlink_imu_id to match")
        else:
            self._error_once("none", f"no IMU message from the autopilot in {NO_DATA_WARN_S:.0f} s "
                             f"(rate request: {self.request_result or 'no answer'}): enable {self.message} "
                             "with its stream parameters (docs/autopilot.md)")

    def _error_once(self, key: str, text: str) -> None:
        self.last_error = text
        if key not in self._warned:
            self._warned.add(key)
            log.error("%s", text)

    # ---------------------------------------------------------------- link thread: every message
    def on_message(self, msg: Any, t_arrival_ns: int) -> None:
        """Handle one message from the link (public so that tests can drive the source without a link)."""
        kind = msg.get_type()
        # SCALED_IMU has no `id` field (pymavlink's message class has an `id` attribute: the message id)
        imu_id = msg.id if kind in IMU_MESSAGES and "id" in msg.get_fieldnames() else 0
        if kind == self.message and imu_id == self.imu_id:
            with self._lock:
                self._on_imu(msg, t_arrival_ns)
        elif kind in IMU_MESSAGES:
            self.other_imu[kind if kind == "SCALED_IMU" else f"{kind} id {imu_id}"] += 1
        elif kind == "TIMESYNC":
            self._on_timesync(msg, t_arrival_ns)
        elif kind == "HEARTBEAT" and is_autopilot_heartbeat(msg, None if self.target is None else self.target[0]):
            if self.target is None:
                self.target = (msg.get_srcSystem(), msg.get_srcComponent())
                self._heartbeat_since_ns = t_arrival_ns
                if self._owns_link:
                    self.link.set_source_system(msg.get_srcSystem())
        elif kind == "COMMAND_ACK" and msg.command == mavlink.MAV_CMD_SET_MESSAGE_INTERVAL:
            self._on_ack(msg)

    def _on_ack(self, msg: Any) -> None:
        result = mavlink.enums["MAV_RESULT"][msg.result].name if msg.result in mavlink.enums["MAV_RESULT"] \
            else str(msg.result)
        if result != self.request_result:
            if result == "MAV_RESULT_ACCEPTED":
                log.info("autopilot streams %s at %.0f Hz as requested", self.message, self.rate_hz)
            else:
                log.warning("autopilot answered %s to the %s rate request: set the rate with its stream "
                            "parameters (docs/autopilot.md)", result, self.message)
        self.request_result = result
        self._request_tries = 0 if result == "MAV_RESULT_ACCEPTED" else self._request_tries

    def _on_timesync(self, msg: Any, t_arrival_ns: int) -> None:
        if msg.tc1 == 0 or msg.ts1 not in self._pending_ts:  # a request to us (the output answers) or not ours
            return
        if msg.ts1 < self._timesync_after_ns:
            return  # asked before the autopilot restarted: its answer is on the old clock
        rtt = t_arrival_ns - msg.ts1
        if rtt < 0:  # answered before it was asked: an arrival stamp taken too early, which no fit may use
            return
        with self._lock:
            self._rtt_ns.append(rtt)
            self.timesync.add(int(msg.tc1), (msg.ts1 + t_arrival_ns) // 2, rtt // 2)
            self.timesync_used += 1
            if self._holding and self._held:
                self._release_held(t_arrival_ns, "the first TIMESYNC round trip")

    def _on_imu(self, msg: Any, t_arrival_ns: int) -> None:
        self.received += 1
        t_dev = int(msg.time_boot_ms) * 1_000_000 if self.message == "SCALED_IMU" else int(msg.time_usec) * 1000
        if self._last_dev_ns is not None and t_dev <= self._last_dev_ns:
            if t_dev == self._last_dev_ns:
                self.duplicates += 1
                return
            if self._last_dev_ns - t_dev <= int(REBOOT_BACK_S * 1e9):
                self.out_of_order += 1
                if StreamMonitor._should_log(self.out_of_order):
                    log.warning("%s stamp %.6f s is %.1f ms older than the previous one: sample dropped",
                                self.message, t_dev / 1e9, (self._last_dev_ns - t_dev) / 1e6)
                return
            self.reboots += 1
            if self._held:  # from before the restart: no round trip on that clock will come to place them
                self.hold_dropped += len(self._held)
                log.warning("%d %s samples held from before the autopilot restarted dropped: no TIMESYNC round trip "
                            "placed them", len(self._held), self.message)
            log.warning("%s stamps went back by %.3f s: the autopilot restarted; clock sync restarted",
                        self.message, (self._last_dev_ns - t_dev) / 1e9)
            self.timesync.reset()
            self.arrival.reset()
            self._slew_state = None
            self._timesync_after_ns = t_arrival_ns
            self._dev_stamps.clear()
            self.request_result = ""  # a rebooted autopilot has forgotten the requested rate
            self._request_tries = 0
            self._init_hold()
        self._last_dev_ns = t_dev
        self._last_sample_arrival_ns = t_arrival_ns
        raw_g = np.array([msg.xgyro, msg.ygyro, msg.zgyro], dtype=np.float64)
        raw_a = np.array([msg.xacc, msg.yacc, msg.zacc], dtype=np.float64)
        gyro = self._R @ (raw_g * self.gyro_scale)
        accel = self._R @ (raw_a * self.accel_scale)
        self._check_scale(accel, gyro)
        if self._holding:
            self._hold(t_dev, t_arrival_ns, gyro, accel)
            return
        self.arrival.add(t_dev, t_arrival_ns)
        self._emit(t_dev, t_arrival_ns, t_arrival_ns, gyro, accel)

    def _emit(self, t_dev: int, t_arrival_ns: int, t_bound_ns: int, gyro: np.ndarray, accel: np.ndarray) -> bool:
        """Map one sample onto the host clock and hand it on; False if it was not (no mapping, not after the
        previous one). `t_bound_ns`: the latest host time it can have been made (its arrival, or for a held sample
        less, from the arrivals of the samples after it)."""
        held = t_bound_ns != t_arrival_ns
        target = self._to_host(t_dev, t_bound_ns, held=held)
        if target is not None and not held:
            self._add_latency(t_arrival_ns, t_dev, t_arrival_ns - target)
        t_host = self._slew(t_dev, target)
        if t_host is None or not self.monitor.check(t_host):
            return False
        self._dev_stamps.append(t_dev)
        self._latency_ns.append(t_arrival_ns - t_host)
        self._queue.put(ImuSample(t_host, gyro, accel))
        return True

    def _hold(self, t_dev: int, t_arrival_ns: int, gyro: np.ndarray, accel: np.ndarray) -> None:
        """Keep a sample until the clock sync can place it: the first TIMESYNC round trip (answered after the hold
        began), or HOLD_S of arrivals without one."""
        if self._hold_since_ns is None:
            self._hold_since_ns = t_arrival_ns
        if len(self._held) >= HOLD_MAX:
            self._held.popleft()
            self.hold_dropped += 1
        self._held.append((t_dev, t_arrival_ns, gyro, accel))
        self.held += 1
        if self.timesync.to_host(t_dev) is not None:
            self._release_held(t_arrival_ns, "the first TIMESYNC round trip")
        elif t_arrival_ns - self._hold_since_ns >= HOLD_S * 1e9:
            self._release_held(t_arrival_ns, f"{HOLD_S:g} s without a TIMESYNC answer")

    def _release_held(self, now_ns: int, why: str) -> None:
        """Hand on the samples held, each mapped by the clock sync as it is now and no later than it can have been
        made: its arrival, or a later sample's arrival less their device-time difference, whichever is earlier (a
        sample that waited in a backlog arrived with the fresh ones after it, and is placed by them, never at its
        own arrival; the arrival fit gets it at that bound too). One log line per hold."""
        self._holding = False
        if not self._held:
            return
        held = list(self._held)
        self._held.clear()
        bounds = [0] * len(held)
        d_min: int | None = None
        for i in range(len(held) - 1, -1, -1):  # the smallest arrival - device offset of this sample and those after
            t_dev, t_arr = held[i][0], held[i][1]
            d_min = t_arr - t_dev if d_min is None else min(d_min, t_arr - t_dev)
            bounds[i] = t_dev + d_min
        # the arrival fit gets each at its bound: a backlog read at once is then no jump of the device clock to it
        for (t_dev, _, _, _), bound in zip(held, bounds):
            self.arrival.add(t_dev, bound)
        sent = late = 0
        worst = 0
        for (t_dev, t_arr, gyro, accel), bound in zip(held, bounds):
            if self._emit(t_dev, t_arr, bound, gyro, accel):
                sent += 1
                wait = t_arr - (self.monitor.last_t or t_arr)
                if wait > BACKLOG_S * 1e9:
                    late += 1
                    worst = max(worst, wait)
        self.backlog += late
        self.holds += 1
        text = (f"{len(held)} {self.message} samples held {(now_ns - held[0][1]) / 1e9:.2f} s until {why}: "
                f"{sent} handed on, mapped by {'TIMESYNC' if self.clock_source == 'timesync' else 'their arrivals'}")
        if late:
            text += f", {late} of them arrived up to {worst / 1e9:.2f} s after they were made (a link backlog)"
        if len(held) - sent:
            text += f", {len(held) - sent} not placed (dropped)"
        if late or sent < len(held):
            log.warning("%s", text)
        else:
            log.info("%s", text)

    def _slew(self, t_dev: int, t_host: int | None) -> int | None:
        """Apply a change of the dev->host mapping gradually, so that host stamps never step back.

        Why: the mapping changes when the first TIMESYNC answer replaces the arrival-time envelope (which
        includes the link's minimum latency, tens of ms on a busy UART) and a little at each refit. Stepping
        at once put the next samples at or before the last one given out, and they were dropped as
        non-monotonic (~9 at every start-up of the SITL stand-in). Here the offset in use moves towards the
        mapping's by at most SLEW_FRACTION of the sample interval per sample (45 ms in ~18 samples at 200 Hz),
        so no sample is lost and the spacing stays >= half the true one. A change beyond REBOOT_BACK_S is
        not a refinement but a new clock: applied at once."""
        if t_host is None:
            return None
        target = t_host - t_dev
        prev_dev, prev_off = self._slew_state if self._slew_state else (None, None)
        if prev_dev is None or t_dev <= prev_dev or abs(target - prev_off) > REBOOT_BACK_S * 1e9:
            off = target
        else:
            step = int(SLEW_FRACTION * (t_dev - prev_dev))
            off = prev_off + max(-step, min(step, target - prev_off))
        self._slew_state = (t_dev, off)
        self._slew_lag_ns = abs(target - off)
        return t_dev + off

    def _to_host(self, t_dev: int, t_bound_ns: int, held: bool = False) -> int | None:
        """TIMESYNC mapping when it has answers and agrees with the arrivals, else the arrival envelope.

        `t_bound_ns` is the latest host time the sample can have been made (its arrival; for a held sample a later
        one's arrival less their device-time difference). The arrival envelope is held to it (a fit that a backlog
        put late cannot put a sample after it arrived), and so is a held sample's TIMESYNC mapping (the first answer
        may be stamped early, docs/autopilot.md); a live sample's TIMESYNC mapping is left as the round trips
        place it (stamp_uncertainty_s says when it lies after the arrivals)."""
        t = self.timesync.to_host(t_dev) if self.timesync_used else None
        if t is not None and abs(t_bound_ns - t) <= CLOCK_DISAGREE_S * 1e9:
            self.clock_source = "timesync"
            self._disagree_run = 0
            return min(t, t_bound_ns) if held else t
        if t is not None:  # a few around a restart are normal; a run of them means another clock
            self.clock_disagreements += 1
            self._disagree_run += 1
            if self._disagree_run == STATS_WINDOW:
                self._error_once("clock", f"{self.message} stamps are {(t_bound_ns - t) / 1e9:.1f} s off the "
                                 "autopilot's TIMESYNC clock: they use another clock; mapped by arrival time")
        self.clock_source = "arrival"
        if self.arrival.problem:  # a rate the fit cannot follow: no stamp rather than a wrong one
            self._error_once("clock_rate", f"{self.message}: {self.arrival.problem}")
            return None
        t = self.arrival.to_host(t_dev)
        return None if t is None else min(t, t_bound_ns)

    def _add_latency(self, t_arrival_ns: int, t_dev: int, lat_ns: int) -> None:
        """Keep the newest samples' latencies against the mapping (ARRIVAL_SPAN_S of arrivals) and the smallest per
        ARRIVAL_SPAN_S of those of the ARRIVAL_BASE_S before; started afresh whenever the mapping is another one."""
        key = (self.clock_source, self.timesync.resets, self.arrival.resets)
        if key != self._lat_key:
            self._init_latency_floor()
            self._lat_key = key
        recent, base = self._lat_recent, self._lat_base
        steady = bool(recent) and (t_dev - recent[-1][1]) / 2 <= t_arrival_ns - recent[-1][0] \
            <= t_dev - recent[-1][1] + STEADY_SLACK_S * 1e9
        recent.append((t_arrival_ns, t_dev, lat_ns))
        span = int(ARRIVAL_SPAN_S * 1e9)
        while len(recent) > 1 and t_arrival_ns - recent[1][0] >= span and t_dev - recent[1][1] >= span:
            t, _, lat = recent.popleft()
            if base and t - base[-1][0] < span:
                base[-1][1] = min(base[-1][1], lat)
            else:
                base.append([t, lat])
        while base and base[0][0] < t_arrival_ns - int(ARRIVAL_BASE_S * 1e9):
            base.popleft()
        end = t_arrival_ns - int(ARRIVAL_HOLD_S * 1e9)
        judged = bool(base) and end - base[0][0] >= ARRIVAL_BASE_MIN_S * 1e9
        # a mapping that went late shows at once, in any sample (a backlog only makes latencies longer): the newest
        # latencies below the smallest floor of the spans before. Not L < 0 itself: a mapping that has always put the
        # samples a few ms after their arrival (ArduPilot SITL's TIMESYNC over TCP: 5.5-9 ms, every flight) is a
        # constant part, which cancels on the ODOMETRY stamps and which the camera-IMU offset takes; read as an error
        # it held a whole SITL flight degraded with its covariance grown (stop 57)
        newest = min(lat for _, _, lat in recent)
        earlier = [lat for t, lat in base if t <= end] if judged else []
        self._lat_fall_ns = min(earlier) - newest if earlier else 0
        if steady:
            self._lat_rise_ns = newest - max(earlier) if earlier else 0

    def _arrival_miss_ns(self) -> float:
        """How far the newest samples show the mapping off [ns]: their latencies fallen below the earlier floors (a late
        mapping), or their smallest latency risen above those of ARRIVAL_HOLD_S to ARRIVAL_BASE_S before (an early
        one, as last judged); 0 when they show nothing."""
        if not self._lat_recent:
            return 0.0
        return float(max(self._lat_fall_ns, self._lat_rise_ns, 0))

    def _check_scale(self, accel: np.ndarray, gyro: np.ndarray) -> None:
        """At the start the vehicle is (nearly) still: |accel| near 1 g. Far off means a wrong scale."""
        if len(self._scale_checked) >= 50:
            return
        self._scale_checked.append(float(np.linalg.norm(accel)))
        if len(self._scale_checked) == 50:
            g = float(np.median(self._scale_checked))
            if not 4.0 < g < 25.0:
                self._error_once("scale", f"{self.message} acceleration is {g:.4g} m/s^2 at the start (expected "
                                 f"~9.8) with mavlink_imu_accel_scale {self.accel_scale:g}: the scale is wrong for "
                                 "this message's units (mG: 9.80665e-3)")

    # ---------------------------------------------------------------- clock health
    def stamp_uncertainty_s(self) -> float:
        """How far the newest samples' host stamps may be off [s]: the clock fit in use (TIMESYNC, else the arrival
        envelope; timesync.ClockSync.uncertainty_ns) or what the newest samples' arrivals show of the mapping
        (_arrival_miss_ns: a step at once or within ARRIVAL_SPAN_S, where the fit's answers take 0.6-0.9 s), whichever
        is larger, plus what the slew has not applied yet; inf before any sample and while the arrival fit cannot
        place the stamps."""
        with self._lock:
            if self._last_dev_ns is None:
                return math.inf
            clock = self.timesync if self.clock_source == "timesync" else self.arrival
            fit = clock.uncertainty_ns(self._last_dev_ns)
            return (max(fit, self._arrival_miss_ns()) + self._slew_lag_ns) / 1e9

    # ---------------------------------------------------------------- health
    def health(self) -> dict[str, Any]:
        with self._lock:
            stamps = np.array(self._dev_stamps, dtype=np.int64)
            lat = np.array(self._latency_ns, dtype=np.float64)
            rtt = np.array(self._rtt_ns, dtype=np.float64)
        dt = np.diff(stamps) if len(stamps) > 2 else np.array([])
        return {"name": self.name, "state": self.state, "message": self.message, "url": self.link.url,
                "link": self.link.health(), "received": self.received,
                "rate_hz": round(1e9 / float(np.mean(dt)), 1) if len(dt) else None,
                "stamp_jitter_us": round(float(np.std(dt)) / 1e3, 1) if len(dt) else None,
                "latency_ms_median": round(float(np.median(lat)) / 1e6, 3) if len(lat) else None,
                "latency_ms_p99": round(float(np.percentile(lat, 99)) / 1e6, 3) if len(lat) else None,
                "duplicates": self.duplicates, "out_of_order": self.out_of_order, "reboots": self.reboots,
                "holds": self.holds, "held": self.held, "hold_dropped": self.hold_dropped, "backlog": self.backlog,
                "queue_dropped": self._queue.dropped, "stream": self.monitor.as_dict(),
                "rate_request": self.request_result or ("sent" if self.request_sent else "not sent"),
                "other_imu_messages": dict(self.other_imu), "clock_source": self.clock_source,
                "clock_disagreements": self.clock_disagreements,
                "timesync_rtt_ms_median": round(float(np.median(rtt)) / 1e6, 3) if len(rtt) else None,
                "clock": self.timesync.as_dict() if self.clock_source == "timesync" else self.arrival.as_dict(),
                "last_error": self.last_error}
