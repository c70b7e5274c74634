"""IMU over a serial port (USB-UART or a microcontroller) speaking the protocol of serial_protocol.py.

A reader thread owns the port: it reads whatever bytes are waiting, parses them, converts the device
stamps to the host clock (timesync.ClockSync) and pushes ImuSamples into a bounded queue. So the camera
path never waits on the UART, and a slow consumer costs counted IMU drops rather than a stalled reader.
The port is reopened with exponential backoff when it disappears (cable pulled, MCU reset).
"""

from __future__ import annotations

import contextlib
import logging
import math
import time
from collections.abc import Callable
from typing import Any

from drivers.base import DropOldestQueue, Message, ThreadedSource
from drivers.serial_protocol import FrameParser
from drivers.timesync import ClockSync, StreamMonitor
from vio.types import ImuSample

log = logging.getLogger(__name__)

# a port open this long with not one byte, or this many bytes with not one valid frame, is said (the status, the log):
# silent, the status said only "IMU: no samples", whatever the reason (an integrator's walk-through)
SILENT_S = 2.0
GARBAGE_BYTES = 100 * 40  # a hundred frames' worth


def _default_serial_factory(port: str, baud: int, timeout: float) -> Any:
    from vio.extras import require  # pyserial, imported here so that the module loads without it

    serial = require("serial", "serial", '[source] imu = "serial"')

    # exclusive: flock the port, so that a second reader (a `vio record` beside the service, a second daemon) is
    # refused instead of splitting the bytes with the first: a recorder opened beside a running daemon took every
    # other read, the daemon's IMU fell from 400 to ~150 Hz (three resets) and the recording was as torn
    return serial.Serial(port, baud, timeout=timeout, exclusive=True)


class SerialImuSource(ThreadedSource):
    """ImuSamples from a serial IMU, stamped on the host monotonic clock."""

    name = "serial_imu"

    def __init__(self, port: str, baud: int = 921600, *, nominal_rate_hz: float = 400.0,
                 serial_factory: Callable[..., Any] | None = None, queue_size: int = 4000,
                 read_timeout_s: float = 0.02, backoff_max_s: float = 5.0,
                 clock: ClockSync | None = None) -> None:
        super().__init__()
        self.port = port
        self.baud = baud
        self._factory = serial_factory or _default_serial_factory
        self._read_timeout = read_timeout_s
        self._backoff_max = backoff_max_s
        self.parser = FrameParser()
        self.clock = clock or ClockSync()
        self.monitor = StreamMonitor("serial IMU", nominal_rate_hz)
        self._queue = DropOldestQueue(queue_size)
        self.join_timeout_s = 2.0
        self.open_failures = 0
        self.disconnects = 0
        self.last_error = ""
        self.clock_withheld = 0  # samples held back while the clock sync could not place their stamps
        # why an open port gives no sample: nothing arrives, or bytes that are no frame (wrong baud, wrong device)
        self.link_problem = ""
        self._last_byte_at = 0.0
        self._bytes_at_open = self._frames_at_open = 0
        self._last_dev_ns: int | None = None  # the newest frame's device stamp (the clock health is asked for it)

    def poll(self) -> list[Message]:
        return self._queue.drain()

    # -- reader thread -------------------------------------------------------------------------------------
    def _run(self) -> None:
        backoff = 0.1
        while not self._stop.is_set():
            try:
                ser = self._factory(self.port, self.baud, self._read_timeout)
            except Exception as e:  # pyserial raises SerialException/OSError/ValueError for a bad port
                self.open_failures += 1
                msg = f"cannot open serial IMU port {self.port} at {self.baud} baud: {e}"
                if "exclusively lock" in str(e):  # pyserial's words for a port another process holds (flock)
                    msg = (f"serial IMU port {self.port} is held by another process (a running vio run, or vio "
                           "record: one reader per port; stop the service first, sudo systemctl stop kestrel-vio)")
                if msg != self.last_error:
                    log.error("%s; retrying with backoff", msg)
                self.last_error = msg
                self.state = "disconnected"
                self._stop.wait(backoff)
                backoff = min(backoff * 2, self._backoff_max)
                continue
            log.info("serial IMU port %s open at %d baud", self.port, self.baud)
            self.state = "running"
            self._last_byte_at = time.monotonic()  # since it opened, or since its last byte
            self._bytes_at_open, self._frames_at_open = self.parser.stats.bytes_in, self.parser.stats.frames_ok
            self.link_problem = ""
            backoff = 0.1
            try:
                self._pump(ser)
            except Exception as e:  # unplugged mid-flight: SerialException / OSError from read()
                self.disconnects += 1
                self.last_error = f"serial IMU port {self.port} lost: {e}"
                log.error("%s; reconnecting", self.last_error)
                self.state = "disconnected"
            finally:
                with contextlib.suppress(Exception):  # closing a vanished port may fail too
                    ser.close()

    def _pump(self, ser: Any) -> None:
        while not self._stop.is_set():
            waiting = getattr(ser, "in_waiting", 0) or 0
            data = ser.read(max(1, min(waiting, 4096)))
            t_arrival = time.monotonic_ns()
            if data:
                self._last_byte_at = t_arrival / 1e9
                self.feed(data, t_arrival)
            self._check_link(t_arrival / 1e9)

    def _check_link(self, now_s: float) -> None:
        """Name why the open port gives no sample (logged once, in health()'s last_error until a frame comes)."""
        st = self.parser.stats
        got, ok = st.bytes_in - self._bytes_at_open, st.frames_ok - self._frames_at_open
        problem = ""
        if now_s - self._last_byte_at > SILENT_S:
            problem = (f"serial IMU port {self.port} is open but nothing arrives on it: is the IMU powered and "
                       "sending, its TX wired to this port's RX?")
        elif ok == 0 and got >= GARBAGE_BYTES:
            problem = (f"serial IMU port {self.port}: bytes arrive at {self.baud} baud but not one valid frame: the "
                       "sender at another baud rate than [source] serial_baud, or another device on [source] "
                       "serial_port?")
        if problem and problem != self.link_problem:
            log.error("%s", problem)
        elif self.link_problem and not problem:
            log.info("serial IMU port %s: frames arriving", self.port)
        self.link_problem = problem

    def feed(self, data: bytes, t_arrival_ns: int) -> None:
        """Parse bytes that arrived at `t_arrival_ns` (host clock) and queue the samples. Public so that
        tests and tools can drive the parser and clock sync without a port."""
        raws = self.parser.feed(data)
        # a device clock that runs back within the chunk (the MCU rebooted between two of its frames) splits it:
        # the frames before the reboot are placed with the clock fit they were made under; placed with the fit
        # restarted after it they were stamped seconds in the future, and every sample after them was then
        # dropped as out of order for as long as the device had been up (a QA sweep)
        cuts = [k for k in range(1, len(raws)) if raws[k].t_us < raws[k - 1].t_us]
        for a, b in zip([0, *cuts], [*cuts, len(raws)]):
            self._place(raws[a:b], t_arrival_ns)

    def _place(self, raws: list, t_arrival_ns: int) -> None:
        # add the whole run before converting: its last frame has the least latency, and early on (before the
        # first fit) converting frame by frame would collapse a burst onto one arrival stamp
        for raw in raws:
            self.clock.add(raw.t_us * 1000, t_arrival_ns)
        if raws:
            self._last_dev_ns = raws[-1].t_us * 1000
        if self.clock.problem:  # stamps the clock sync cannot place: none at all is safer than wrong ones
            self.clock_withheld += len(raws)
            return
        for raw in raws:
            t_host = self.clock.to_host(raw.t_us * 1000)
            if t_host is None or not self.monitor.check(t_host):
                continue
            self._queue.put(ImuSample(t_host, raw.gyro, raw.accel))

    def stamp_uncertainty_s(self) -> float:
        """How far the newest samples' host stamps may be off [s] (timesync.ClockSync.uncertainty_ns of the arrival
        fit); inf before the first frame and while the fit cannot place the stamps (then none is delivered)."""
        t_dev = self._last_dev_ns
        return math.inf if t_dev is None else self.clock.uncertainty_ns(t_dev) / 1e9

    def health(self) -> dict[str, Any]:
        return {"name": self.name, "state": self.state, "port": self.port, "baud": self.baud,
                "open_failures": self.open_failures, "disconnects": self.disconnects,
                # while the clock sync cannot place the stamps, that is why no sample comes (and it clears with it)
                "queue_dropped": self._queue.dropped,
                "last_error": self.clock.problem or self.link_problem or self.last_error,
                "clock_withheld": self.clock_withheld,
                "parser": self.parser.stats.as_dict(), "stream": self.monitor.as_dict(),
                "clock": self.clock.as_dict()}
