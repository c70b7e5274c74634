"""systemd notification protocol (sd_notify) without a dependency.

systemd passes a datagram socket in $NOTIFY_SOCKET to Type=notify services; the service sends newline-
separated `KEY=VALUE` assignments (READY=1, WATCHDOG=1, STATUS=..., STOPPING=1). Outside systemd the
variable is unset and every call is a cheap no-op, so the daemon runs the same under a shell or a test.
"""

from __future__ import annotations

import logging
import os
import socket

log = logging.getLogger(__name__)


class SdNotifier:
    """Sends sd_notify datagrams; never raises and never blocks (a broken or full notify socket must not
    stop the daemon's main loop: a datagram that does not fit is dropped, like a lost one)."""

    def __init__(self, address: str | None = None) -> None:
        address = os.environ.get("NOTIFY_SOCKET", "") if address is None else address
        self.address: str | bytes | None = None
        if address:
            # '@' marks a Linux abstract-namespace socket, spelled with a leading NUL byte.
            self.address = b"\0" + address[1:].encode() if address.startswith("@") else address
        self._sock: socket.socket | None = None
        self._warned = False

    @property
    def enabled(self) -> bool:
        return self.address is not None

    def notify(self, **fields: str | int) -> bool:
        """Send `KEY=VALUE` fields (keyword names are upper-cased); True when the datagram went out."""
        if self.address is None:
            return False
        msg = "\n".join(f"{k.upper()}={v}" for k, v in fields.items()).encode()
        try:
            if self._sock is None:
                self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC)
                self._sock.setblocking(False)  # a full receive queue (10 datagrams) would otherwise block us
            self._sock.sendto(msg, self.address)
            return True
        except OSError as e:
            if not self._warned:  # once: the watchdog calls this every few seconds
                log.warning("sd_notify to %r failed: %s", self.address, e)
                self._warned = True
            return False

    def ready(self, status: str = "") -> bool:
        return self.notify(ready=1, status=status) if status else self.notify(ready=1)

    def watchdog(self) -> bool:
        return self.notify(watchdog=1)

    def status(self, text: str) -> bool:
        return self.notify(status=text)

    def stopping(self) -> bool:
        return self.notify(stopping=1)

    def close(self) -> None:
        if self._sock is not None:
            self._sock.close()
            self._sock = None


def watchdog_interval_s() -> float | None:
    """Half the systemd watchdog period ($WATCHDOG_USEC) when it is meant for this process, else None.

    systemd recommends pinging at half the period; WATCHDOG_PID guards against a child inheriting it."""
    usec = os.environ.get("WATCHDOG_USEC")
    pid = os.environ.get("WATCHDOG_PID")
    if not usec or (pid and pid.isdigit() and int(pid) != os.getpid()):
        return None
    try:
        value = int(usec)
    except ValueError:
        return None
    return value / 2e6 if value > 0 else None
