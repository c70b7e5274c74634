"""Bounded, thread-safe hand-overs between the daemon's threads: sensor data, the newest state, rates."""

from __future__ import annotations

import dataclasses
import logging
import threading
import time
from collections import deque
from typing import TYPE_CHECKING, Any

from vio.types import ImuSample, NavState, StereoFrame

if TYPE_CHECKING:
    pass

log = logging.getLogger(__name__)

def _now_ns() -> int:
    return time.monotonic_ns()


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
    odometry: NavState | None = None  # the state before a loop correction ([loop] output), for the TUM log


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

    def peek(self) -> tuple[int, Output | None]:
        """(sequence number, newest state) without taking the frame states (the recorder's view)."""
        with self._cv:
            return self._seq, self._item

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
