"""The one interface every sensor source implements (the factory that opens one is drivers/source.py).

A source delivers `ImuSample` and `StereoFrame` messages (vio/types.py) stamped in integer nanoseconds on
ONE host clock, `time.monotonic_ns()` (CLOCK_MONOTONIC; depthai's steady clock is the same clock on
Linux). Usage by the daemon::

    src = open_source(cfg.source)          # nothing touches hardware yet
    src.start()                            # spawns the source's own reader thread(s); never blocks long
    calib = src.calibration()              # may be None until the device has been read
    while running:
        for msg in src.poll():             # non-blocking; returns what arrived since the last call
            estimator.feed(msg)
        log(src.health())                  # counters, state, clock sync: plain dict, JSON-serialisable
        src.stamp_uncertainty_s()          # how far the newest stamps may be off the host clock [s]
    src.stop()                             # joins threads, closes ports; safe to call twice

Each source keeps IMU and camera data in separate bounded queues so a slow consumer drops stale frames
(counted) but IMU samples only when its much larger queue overflows (counted too). Within one `poll()`
IMU samples come before frames, each stream in time order; streams from different devices are not
merged here (the estimator buffers IMU up to the frame time).
"""

from __future__ import annotations

import logging
import queue
import threading
from abc import ABC, abstractmethod
from typing import Any

from vio.calibration import StereoCalibration
from vio.types import ImuSample, StereoFrame

log = logging.getLogger(__name__)

Message = ImuSample | StereoFrame


class SensorSource(ABC):
    """Base of every source: start/stop, non-blocking poll, calibration, health."""

    name = "source"

    @abstractmethod
    def start(self) -> None:
        """Begin acquiring (open device, spawn reader thread). Returns quickly; errors after start show in
        health() and the log rather than as exceptions, so a flaky cable does not kill the daemon."""

    @abstractmethod
    def stop(self) -> None:
        """Stop acquiring and release the device. Idempotent."""

    @abstractmethod
    def poll(self) -> list[Message]:
        """All messages that arrived since the last call, IMU first, each stream in time order. Never blocks."""

    def calibration(self) -> StereoCalibration | None:
        """The sensor head's calibration when the source knows it (device EEPROM, dataset), else None."""
        return None

    def health(self) -> dict[str, Any]:
        """Counters and state for logs and `vio status`."""
        return {"name": self.name}

    def stamp_uncertainty_s(self) -> float:
        """How far the host stamps of the samples delivered now may be off the truth [s]: 0 for a source stamped on
        the host clock itself (an OAK: depthai maps its clock; the fake flight; a dataset), the clock fit's own
        measure for a device with a clock of its own (serial and MAVLink IMU, drivers/timesync.py), inf while it
        cannot place them. The daemon's output grows the covariance sent by the motion over this time and sends
        nothing beyond [mavlink] max_stamp_error_ms (docs/autopilot.md "IMU clock health")."""
        return 0.0

    @property
    def finished(self) -> bool:
        """True when a finite source (dataset, fake with a duration) has delivered everything."""
        return False

    def __enter__(self) -> SensorSource:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()


class ThreadedSource(SensorSource):
    """A source whose device is read by its own thread (`_run`, which must return soon after `_stop` is
    set). Subclasses set up their fields before calling this __init__ or after; start/stop are shared."""

    join_timeout_s = 5.0

    def __init__(self) -> None:
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.state = "stopped"

    def _before_start(self) -> None:
        """Hook for imports or checks that must happen in the caller's thread."""

    @abstractmethod
    def _run(self) -> None:
        """Reader loop: connect, read, reconnect with backoff until `_stop` is set."""

    def start(self) -> None:
        if self._thread is not None:
            return
        self._before_start()
        self._stop.clear()
        self.state = "connecting"
        self._thread = threading.Thread(target=self._run, name=self.name, daemon=True)
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=self.join_timeout_s)
            self._thread = None
        self.state = "stopped"


class DropOldestQueue:
    """Thread-safe bounded FIFO that drops the OLDEST item when full: for sensors, fresh data beats stale.

    Why not queue.Queue: its put() either blocks (stalls the reader thread, so the device buffer
    overflows instead) or raises; neither is what a driver wants."""

    def __init__(self, maxsize: int) -> None:
        self._q: queue.Queue = queue.Queue(maxsize=max(1, maxsize))
        self._lock = threading.Lock()
        self.dropped = 0

    def put(self, item: Any) -> None:
        with self._lock:
            while True:
                try:
                    self._q.put_nowait(item)
                    return
                except queue.Full:
                    try:
                        self._q.get_nowait()
                        self.dropped += 1
                    except queue.Empty:
                        pass

    def drain(self) -> list:
        out = []
        while True:
            try:
                out.append(self._q.get_nowait())
            except queue.Empty:
                return out

    def qsize(self) -> int:
        return self._q.qsize()


class CombinedSource(SensorSource):
    """Cameras from one source and IMU from another (e.g. an OAK without IMU + a serial IMU).

    IMU messages of the camera source are discarded so that exactly one IMU feeds the estimator."""

    name = "combined"

    def __init__(self, camera: SensorSource, imu: SensorSource) -> None:
        self.camera = camera
        self.imu = imu

    def start(self) -> None:
        self.imu.start()
        self.camera.start()

    def stop(self) -> None:
        self.camera.stop()
        self.imu.stop()

    def poll(self) -> list[Message]:
        imu = [m for m in self.imu.poll() if isinstance(m, ImuSample)]
        frames = [m for m in self.camera.poll() if isinstance(m, StereoFrame)]
        return imu + frames

    def calibration(self) -> StereoCalibration | None:
        return self.camera.calibration()

    def health(self) -> dict[str, Any]:
        return {"name": self.name, "camera": self.camera.health(), "imu": self.imu.health()}

    def stamp_uncertainty_s(self) -> float:
        """The less certain of the two sources' stamps (the IMU's: the cameras here stamp on the host clock)."""
        return max(self.camera.stamp_uncertainty_s(), self.imu.stamp_uncertainty_s())

    @property
    def finished(self) -> bool:
        return self.camera.finished or self.imu.finished
