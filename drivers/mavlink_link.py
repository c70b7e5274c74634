"""One MAVLink connection shared by the pose output (drivers/mavlink_out.py) and the IMU source
(drivers/mavlink_imu.py), with ONE reader thread that hands each message to whoever subscribed to its type.

Why: a serial port can be opened once only, and the flight controller's IMU usually arrives on the same
TELEM port that takes our ODOMETRY. Two readers on one mavutil object would steal each other's bytes and
two writers would interleave packets and sequence numbers, so reading happens here only and every send
goes through one lock. The link reconnects by itself (back-off 0.5 s doubling to 5 s, one log line per
outage); users see `connected` and never hold the mavutil object.

Usage::

    link = MavlinkLink("/dev/ttyAMA0:921600")
    link.subscribe({"HEARTBEAT", "TIMESYNC"}, on_message)  # on_message(msg, t_arrival_ns), reader thread
    link.acquire()                                          # first user opens it and starts the reader
    link.send(mavlink.MAVLink_heartbeat_message(...))       # thread-safe; False while disconnected
    link.release()                                          # last user closes it

Callbacks run in the reader thread and must be quick (queue the message, answer a TIMESYNC); an
exception in one is logged once and does not stop the others. `t_arrival_ns` is CLOCK_MONOTONIC taken
when the bytes were read, before parsing.
"""

from __future__ import annotations

import contextlib
import errno
import logging
import os
import select
import struct
import threading
import time
from collections.abc import Callable, Iterable
from typing import Any

from vio import VioError
from vio.serial_url import split_serial_url

os.environ["MAVLINK20"] = "1"  # ODOMETRY (id 331) exists only in MAVLink 2; must precede the dialect import
from pymavlink import mavutil  # noqa: E402

mavutil.set_dialect("ardupilotmega")  # re-import as the v2.0 dialect even if mavutil was imported before
mavlink = mavutil.mavlink

log = logging.getLogger(__name__)

# a field out of its type's range (struct.error), or of the wrong type: the message cannot be packed; raised before
# anything is written, so it says nothing about the link (a bad origin reconnected it every second: a review's)
UNPACKABLE = (struct.error, OverflowError, TypeError)


def unpackable(msg: Any, e: Exception, said: set[str]) -> None:
    """Log once per message type (`said`: the sender's own record) that it could not be packed (and is not
    sent)."""
    name = msg.get_type() if hasattr(msg, "get_type") else type(msg).__name__
    if name not in said:
        said.add(name)
        log.error("%s not sent: a field cannot be packed (%s)", name, e)

OUR_COMPONENT = mavlink.MAV_COMP_ID_VISUAL_INERTIAL_ODOMETRY  # 197
RECONNECT_MIN_S, RECONNECT_MAX_S = 0.5, 5.0
Callback = Callable[[Any, int], None]
# Heartbeats from these vehicle types are not an autopilot (GCS, other companions, cameras...).
_NOT_AUTOPILOT_TYPES = {mavlink.MAV_TYPE_GCS, mavlink.MAV_TYPE_ONBOARD_CONTROLLER, mavlink.MAV_TYPE_GIMBAL,
                        mavlink.MAV_TYPE_CAMERA, mavlink.MAV_TYPE_ADSB}


def is_autopilot_heartbeat(msg: Any, system: int | None = None) -> bool:
    """True for a HEARTBEAT from a flight controller: component MAV_COMP_ID_AUTOPILOT1, a vehicle type, a
    real autopilot; with `system`, from that system only.

    Why all three: ArduPilot forwards every heartbeat it hears on every link, so Kestrel's own (component
    197, ONBOARD_CONTROLLER, sent with the autopilot's system id) comes back, as do a GCS's, a gimbal's, a
    peripheral's (components other than 1 that may claim a vehicle type) and, over a shared radio, other
    vehicles' (`system` keeps the one the link locked onto)."""
    return (msg.get_srcComponent() == mavlink.MAV_COMP_ID_AUTOPILOT1 and msg.type not in _NOT_AUTOPILOT_TYPES
            and msg.autopilot != mavlink.MAV_AUTOPILOT_INVALID
            and (system is None or msg.get_srcSystem() == system))


_NETWORK_PREFIXES = ("tcp:", "udpout:", "udpin:", "udp:", "tcpin:", "udpbcast:")


def check_url(url: str, key: str = "[mavlink] url") -> None:
    """Raise VioError, naming `key`, for a connection string that could never be opened (nothing is opened)."""
    if url.startswith(_NETWORK_PREFIXES):
        _, _, where = url.partition(":")
        host, sep, port = where.rpartition(":")
        if not sep or not host or not port.isdigit() or not 1 <= int(port) <= 65535:
            raise VioError(f"{key} {url!r}: expected {url.partition(':')[0]}:HOST:PORT with a port 1-65535 "
                           "(e.g. udpout:127.0.0.1:14550)")
        return
    if url.startswith("/dev/") or url.upper().startswith("COM"):
        baud = split_serial_url(url)[1]
        if baud and not (baud.isdigit() and int(baud) > 0):  # ':0' opened the port at 0 baud, retried for ever
            raise VioError(f"{key} {url!r}: baud rate {baud!r} is not a positive whole number (e.g. 921600)")
        return
    raise VioError(f"{key} {url!r}: expected udpout:HOST:PORT, udpin:HOST:PORT, tcp:HOST:PORT "
                   "or a serial device such as /dev/ttyAMA0:921600")


def open_connection(url: str, source_system: int) -> mavutil.mavfile:
    """Open a mavutil connection from `udpout:H:P`, `udpin:H:P`, `tcp:H:P` or a serial `DEVICE[:BAUD]`.

    mavutil would read `/dev/ttyAMA0:921600` as a UDP address, so serial devices are split here.
    """
    check_url(url)
    kw = {"source_system": source_system, "source_component": OUR_COMPONENT, "dialect": "ardupilotmega"}
    if url.startswith("tcp:"):  # one attempt: mavutil's own retries sleep (and print) inside our loop
        conn = mavutil.mavlink_connection(url, retries=0, **kw)
        # mavutil only prints on a closed peer and returns no data forever; make it an error we handle.
        conn.handle_eof = conn.handle_disconnect = _peer_closed
        return conn
    if url.startswith(_NETWORK_PREFIXES):
        return mavutil.mavlink_connection(url, **kw)
    device, baud = split_serial_url(url)
    hold = _hold_serial(device)  # before mavutil opens it: its open sets the line's speed
    try:
        # mavutil's own dispatch takes any name with a colon for a UDP address (a by-path device): opened as serial
        conn = mavutil.mavserial(device, baud=int(baud or 921600), source_system=source_system,
                                 source_component=OUR_COMPONENT)
    except BaseException:
        _release(hold)
        raise
    if hold is not None:
        close = conn.close

        def close_and_release() -> None:
            try:
                close()
            finally:
                _release(hold)
        conn.close = close_and_release
    return conn


def _hold_serial(device: str) -> int | None:
    """A descriptor of the serial device holding it exclusively (flock, released when it is closed or the process
    ends however it ends), taken before the port is opened and configured: two daemons on one flight controller's
    UART both opened it, interleaved their poses and reset counters and split the autopilot's bytes between them,
    unsaid (a QA sweep); and a lock taken after mavutil's open would let the refused one set the flying link's
    speed first (a review's finding). None where flock does not exist (Windows: a COM port is exclusive)."""
    try:
        import fcntl
    except ImportError:
        return None
    try:
        fd = os.open(device, os.O_RDONLY | os.O_NOCTTY | os.O_NONBLOCK)  # reads nothing, changes no setting
    except OSError:
        return None  # missing, or no permission: mavutil's own open says which
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        os.close(fd)
        raise OSError(errno.EBUSY, f"{device} is held by another connection (another `vio run`?): two senders on "
                      "one autopilot link would interleave their poses") from None
    return fd


def _release(fd: int | None) -> None:
    if fd is not None:
        os.close(fd)


def _peer_closed() -> None:
    raise ConnectionResetError("peer closed the connection")


class MavlinkLink:
    """A reference-counted MAVLink connection with one reader thread dispatching messages by type."""

    def __init__(self, url: str, source_system: int = 1,
                 open_fn: Callable[[str, int], Any] = open_connection, key: str = "[mavlink] url") -> None:
        check_url(url, key)
        self.url = url
        self._unpackable_said: set[str] = set()  # message types that could not be packed (said once each)
        self._source_system = source_system
        self._open_fn = open_fn
        self._conn: Any = None
        self._subs: list[tuple[frozenset[str] | None, Callback]] = []
        self._send_lock = threading.Lock()
        self._users = 0
        self._users_lock = threading.Lock()
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self._failed_logged = False
        self._cb_errors_logged: set[int] = set()
        self.received = 0
        self.sent = 0
        self.io_errors = 0
        self.reconnects = 0
        self.last_error = ""

    # ------------------------------------------------------------------ users
    def subscribe(self, types: Iterable[str] | None, callback: Callback) -> None:
        """Call `callback(msg, t_arrival_ns)` for each message whose type is in `types` (None: all)."""
        self._subs = [*self._subs, (None if types is None else frozenset(types), callback)]

    def unsubscribe(self, callback: Callback) -> None:
        self._subs = [s for s in self._subs if s[1] is not callback]

    def acquire(self) -> MavlinkLink:
        """Count one user; the first one starts the reader thread (which opens the connection)."""
        with self._users_lock:
            self._users += 1
            if self._thread is None:
                self._stop.clear()
                self._thread = threading.Thread(target=self._run, name="mavlink-link", daemon=True)
                self._thread.start()
        return self

    def release(self) -> None:
        """Uncount one user; the last one stops the reader and closes the connection."""
        with self._users_lock:
            self._users = max(0, self._users - 1)
            if self._users or self._thread is None:
                return
            self._stop.set()
            self._thread.join(timeout=2.0)
            self._thread = None
            self._close()

    @property
    def connected(self) -> bool:
        return self._conn is not None

    @property
    def source_system(self) -> int:
        return self._source_system

    def set_source_system(self, sysid: int) -> None:
        """Our system id on the link (the output adopts the autopilot's, see [mavlink] system_id)."""
        self._source_system = sysid
        conn = self._conn
        if conn is not None:
            conn.mav.srcSystem = sysid

    def send(self, msg: Any) -> bool:
        """Pack and send one pymavlink message; False (and a reconnect) when the link is down or fails."""
        with self._send_lock:
            conn = self._conn
            if conn is None:
                return False
            try:
                conn.mav.send(msg)
                if getattr(conn, "portdead", False):  # mavutil's serial write swallows the error
                    raise OSError("serial write failed")
            except UNPACKABLE as e:  # the message, not the link: dropped, the link stays
                unpackable(msg, e, self._unpackable_said)
                return False
            except Exception as e:  # serial unplugged, socket reset: pyserial/socket raise various types
                self._failed(e, conn)
                return False
            self.sent += 1
            return True

    def health(self) -> dict:
        return {"url": self.url, "connected": self.connected, "users": self._users, "received": self.received,
                "sent": self.sent, "io_errors": self.io_errors, "reconnects": self.reconnects,
                "last_error": self.last_error}

    # ------------------------------------------------------------------ reader thread
    def _run(self) -> None:
        backoff = RECONNECT_MIN_S
        while not self._stop.is_set():
            if self._conn is None:
                if not self._open():
                    self._stop.wait(backoff)
                    backoff = min(backoff * 2, RECONNECT_MAX_S)
                    continue
                backoff = RECONNECT_MIN_S
            conn = self._conn
            fd = getattr(conn, "fd", None)
            with contextlib.suppress(OSError, ValueError, TypeError):
                if fd is not None:
                    select.select([fd], [], [], 0.05)
                else:
                    time.sleep(0.002)
            for _ in range(1000):  # bounded, so that stop is seen under a flood
                try:
                    msg = conn.recv_match(blocking=False)
                except Exception as e:  # noqa: BLE001 - any transport error means reconnect
                    self._failed(e, conn)
                    break
                # stamped as read, never before: recv_match reads the socket again whenever its buffer runs out,
                # so a loop behind a backlog also takes messages that came in after it began. One stamp for the
                # whole loop (until 2026-12) put those up to 0.4 s before they arrived: TIMESYNC answers came out
                # with a negative round trip that the clock fit took as its tightest, and the MAVLink IMU's time
                # base ran 0.5 % off for the fit's 20 s window (up to -5 % at first) after a start under load.
                t_arrival = time.monotonic_ns()
                if msg is None:
                    break
                if msg.get_type() == "BAD_DATA":
                    continue
                self.received += 1
                self._dispatch(msg, t_arrival)

    def _dispatch(self, msg: Any, t_arrival: int) -> None:
        kind = msg.get_type()
        for types, cb in self._subs:
            if types is not None and kind not in types:
                continue
            try:
                cb(msg, t_arrival)
            except Exception:
                if id(cb) not in self._cb_errors_logged:  # once per subscriber: a bug must not flood the log
                    self._cb_errors_logged.add(id(cb))
                    log.exception("MAVLink %s handler failed (logged once)", kind)

    def _open(self) -> bool:
        try:
            conn = self._open_fn(self.url, self._source_system)
        except VioError:
            raise
        except Exception as e:  # missing device, refused socket
            self.last_error = f"cannot open {self.url}: {e}"
            if not self._failed_logged:
                log.warning("%s; retrying every <= %.0f s", self.last_error, RECONNECT_MAX_S)
                self._failed_logged = True
            return False
        if self._failed_logged:
            log.info("MAVLink link %s open again", self.url)
            self.reconnects += 1
        self._failed_logged = False
        with self._send_lock:
            self._conn = conn
        return True

    def _failed(self, e: Exception, conn: Any) -> None:
        self.io_errors += 1
        self.last_error = f"link error on {self.url}: {type(e).__name__}: {e}"
        if not self._failed_logged:
            log.warning("%s; reconnecting", self.last_error)
            self._failed_logged = True
        if self._conn is conn:
            self._close()

    def _close(self) -> None:
        conn, self._conn = self._conn, None
        if conn is not None:
            try:
                conn.close()
            except Exception as e:  # closing a dead port may fail too; nothing left to do
                log.debug("close failed: %s", e)
