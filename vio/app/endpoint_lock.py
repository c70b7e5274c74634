"""One sender per autopilot endpoint: the lock that `vio run` and `vio replay --mavlink` both take.

Two processes sending to one autopilot both send as component 197 (MAV_COMP_ID_VISUAL_INERTIAL_ODOMETRY): the
autopilot takes their poses as one stream, interleaved, time going back and forth. `vio run` refused a second
daemon on the same endpoint, but `vio replay --mavlink` took no lock, so a replay to the autopilot of a running
daemon (a bench that forgot the service) interleaved a recording's poses with the live ones. Both take the same
lock here, the first one holds it, the second is refused naming the first's pid and command.
"""

from __future__ import annotations

import errno
import hashlib
import logging
import os
import socket
import struct
import sys

from vio import VioError

log = logging.getLogger(__name__)


def output_endpoint_key(url: str) -> str | None:
    """What two MAVLink URLs that take one autopilot endpoint have in common, or None for a URL that is not one.

    A listening socket (udpin:, mavutil's udp:, tcpin:) takes its protocol's port on every address at once as far
    as the autopilot is concerned (mavutil's udpin binds with SO_REUSEADDR, so udpin:0.0.0.0:14550 and
    udpin:127.0.0.1:14550 both bind, and the autopilot's packets go to one of them): 'udpin:*:14550'. An outbound
    one (udpout:, tcp:, udpbcast:) is its peer, the host spelled one way ('udpout:127.0.0.1:14550' for
    udpout:localhost:14550 too); other peers are other endpoints. A serial device is its real path, the baud rate
    left out ('serial:/dev/ttyACM0' for /dev/serial/by-id/usb-...:115200 too; its flock,
    drivers.mavlink_link._hold_serial, holds it as well, but only once opened, and without naming the holder)."""
    import ipaddress

    from drivers.mavlink_link import _NETWORK_PREFIXES
    from vio.serial_url import split_serial_url

    if not url.startswith(_NETWORK_PREFIXES):
        device = split_serial_url(url)[0]
        if device.startswith("/dev/"):
            return f"serial:{os.path.realpath(device)}"
        return f"serial:{device.upper()}" if device.upper().startswith("COM") else None
    kind, _, where = url.partition(":")
    host, _, port = where.rpartition(":")
    kind = "udpin" if kind == "udp" else kind
    if kind in ("udpin", "tcpin"):
        return f"{kind}:*:{port}"
    host = host.strip("[]").lower()
    try:
        host = str(ipaddress.ip_address(host))
    except ValueError:
        host = "127.0.0.1" if host == "localhost" else host
    return f"{kind}:{host}:{port}"


def _holder(pid: int | None) -> str:
    """'vio run' or 'vio replay --mavlink' for the process holding an endpoint, read from its command line (the
    command is the first of its arguments that is one of the two), else 'vio process' (not Linux's /proc, another
    user's process hidden by hidepid, a pid unknown)."""
    try:
        with open(f"/proc/{pid}/cmdline", "rb") as f:
            argv = [a.decode(errors="replace") for a in f.read().split(b"\0")]
    except (OSError, TypeError):
        return "vio process"
    command = next((a for a in argv[1:] if a in ("run", "replay")), None)
    return {"run": "vio run", "replay": "vio replay --mavlink"}.get(command or "", "vio process")


def mavlink_endpoint_lock(url: str, given: str, other: str) -> socket.socket | None:
    """A socket held for the life of the process in Linux's abstract socket namespace, named after url's endpoint
    (output_endpoint_key), or None (not an endpoint, not Linux, no lock to be had: said).

    given says where the url came from in the refusal ("[mavlink] url = '...'", "--mavlink ..."), other what the
    refused one could do instead ("give this one another [mavlink] url").

    Two processes with their own configurations and status files (the service, and one started by hand from
    another folder; or the service and a replay) but one output endpoint both sent to the autopilot as component
    197, their poses interleaved, and the status file's lock (service.single_instance) could not see it: a udpout
    sender binds no port of its own and mavutil's udpin binds with SO_REUSEADDR, so the network says nothing
    either. The second is refused (VioError), naming the first's pid (SO_PEERCRED of a connection to its socket)
    and command. The abstract namespace has no files and no permissions: every user's process meets the same name
    (systemd's PrivateTmp would hide a lock file in /tmp), and the kernel releases it however the process ends."""
    key = output_endpoint_key(url)
    if key is None or not sys.platform.startswith("linux"):
        return None
    name = f"kestrel-vio/mavlink/{key}"
    if len(name) > 100:  # the abstract name's room (108 bytes less the leading NUL): a long host name is hashed
        name = f"kestrel-vio/mavlink/{hashlib.sha256(key.encode()).hexdigest()}"
    address = b"\0" + name.encode()
    s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    try:
        s.bind(address)
        s.listen(1)
        return s
    except OSError as e:
        s.close()
        if e.errno != errno.EADDRINUSE:
            log.warning("no MAVLink output lock (%s): a second vio run or vio replay --mavlink sending to %s would "
                        "not be refused", e.strerror or e, key)
            return None
    pid: int | None = None
    try:
        with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as probe:
            probe.settimeout(1.0)
            probe.connect(address)
            pid = struct.unpack("3i", probe.getsockopt(socket.SOL_SOCKET, socket.SO_PEERCRED,
                                                       struct.calcsize("3i")))[0]
    except OSError:  # the other one ended meanwhile, or will not say: refused all the same (a restart tries again)
        pass
    holder, shown = _holder(pid), "?" if pid is None else str(pid)
    stop = (f"the service: systemctl stop kestrel-vio; one started by hand: kill {shown}" if holder == "vio run"
            else f"kill {shown}, or wait for it to end")
    raise VioError(f"another {holder} (pid {shown}) sends to the autopilot at {key} ({given}): two would send to "
                   f"it as one component, their poses interleaved; stop it first ({stop}), or {other}")
