"""Reading the small text files a user names (configuration, calibration, trajectories): a device named where a file
belongs (a serial port given as the calibration, /dev/zero) is refused, not read for ever."""

from __future__ import annotations

import os
import stat
from pathlib import Path

from vio import VioError

SETTINGS_LIMIT = 64 << 20  # no configuration or calibration file comes near 64 MiB


def is_device(path: Path) -> bool:
    """Is `path` a character or block device (reading one may never end)? False for a path that cannot be looked at
    (its reader says why)."""
    try:
        mode = os.stat(path).st_mode
    except OSError:
        return False
    return stat.S_ISCHR(mode) or stat.S_ISBLK(mode)


def refuse_device(path: Path, what: str) -> None:
    """VioError naming `path` when it is a device; anything else passes."""
    if is_device(path):
        raise VioError(f"{path}: is a device, not a {what} file")


def read_user_file(path: Path, what: str, limit: int | None = SETTINGS_LIMIT) -> bytes:
    """The bytes of `path`, a `what` ("configuration", "calibration") file. A character or block device is a VioError
    naming it (reading /dev/zero or a serial port never ended: `vio run`'s start hung, memory growing); a pipe is
    read (`--config <(...)`). Over `limit` bytes (None: no limit) is a VioError too. OSError as raised."""
    refuse_device(path, what)
    with open(path, "rb") as f:
        data = f.read() if limit is None else f.read(limit + 1)
    if limit is not None and len(data) > limit:
        raise VioError(f"{path}: over {limit >> 20} MiB: not a {what} file")
    return data
