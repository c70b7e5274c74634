"""A serial device named as `DEVICE[:BAUD]`: the one parser for `[mavlink] url`, `[source] mavlink_imu_url` and
`[source] serial_port`.

Why in the core: vio.config checks `[source] serial_port` and may not import drivers (tests/test_layering.py), which
open the ports (drivers.mavlink_link); a second, hand-made split in the config read udev's by-path names and a
tail that is no baud rate otherwise than the link that opens them.
"""

from __future__ import annotations

import os

UDEV_SERIAL = "/dev/serial/"  # by-path/ and by-id/: udev allows colons in both (a port, a serial number)


def split_serial_url(url: str) -> tuple[str, str]:
    """A serial `DEVICE[:BAUD]` as (device, baud text, '' when none): the baud is what follows the LAST colon.

    udev's /dev/serial/by-path/ names, the way to say which USB port when two adapters look alike, hold colons
    themselves (`platform-xhci-hcd.1-usb-0:2:1.0`): split at the first colon, such a name was refused as a bad baud
    rate ('2:1.0:921600') with or without one; by-id names may too (an ESP32's USB serial number is its MAC address,
    `usb-Espressif_USB_JTAG_serial_debug_unit_F4:12:FA:5A:B2:C8-if00`). So a tail that is no whole number is part of
    the device name under /dev/serial/ (present or not: an adapter may enumerate after the service starts) or where
    a device of that full name exists; elsewhere it stays a (bad) baud rate, said by the caller."""
    device, sep, tail = url.rpartition(":")
    if not sep or tail.isdigit():
        return (device, tail) if sep else (url, "")
    if url.startswith(UDEV_SERIAL) or os.path.exists(url):
        return url, ""
    device, _, baud = url.partition(":")
    return device, baud
