"""Optional dependencies (the package's extras) imported at the point of use, with one clear line when absent.

`pip install kestrel-vio` gives replay, evaluation and the simulator; the extras add the rest:

    [oak]     depthai       OAK cameras (`[source] kind = "oak"`, `vio calib import depthai`)
    [serial]  pyserial      serial IMUs (`[source] imu = "serial"`, the reference sender)
    [tools]   allantools    `vio calib imu-noise` (Allan deviation)
              matplotlib    every plot (evaluation, Allan deviation, time offset, benchmark)
    [bags]    rosbags, mcap ROS bags and MCAP files: `vio replay FILE.bag|.mcap`, `vio record --format mcap`
    [view]    rerun-sdk     the live view (`vio replay --view`, `[view]` in the daemon's config)
    [fleet]   ray           `vio batch --ray ADDRESS` (local worker processes need nothing)

`require("allantools", "tools", "vio calib imu-noise")` returns the module, or raises a VioError saying
"vio calib imu-noise needs the [tools] extra: pip install 'kestrel-vio[tools]'".
"""

from __future__ import annotations

import contextlib
import importlib
import logging
import os
import sys
import tempfile
from types import ModuleType

from vio import VioError

log = logging.getLogger(__name__)

EXTRAS = {"depthai": "oak", "serial": "serial", "allantools": "tools", "matplotlib": "tools", "rosbags": "bags",
          "mcap": "bags", "rerun": "view", "ray": "fleet"}
# modules whose native library prints on import, straight to the process's stdout/stderr (not through Python),
# and the line it always prints there: depthai's logger says "USB protocol not available" on stdout wherever USB
# is not mapped in (a container, a CI runner), which landed in `vio config check`'s "FILE: OK" output
NOISY_IMPORTS = {"depthai": "USB protocol not available"}


class MissingExtra(VioError):
    """An optional dependency is not installed; the message names the extra that brings it."""

    def __init__(self, what: str, extra: str) -> None:
        super().__init__(f"{what} needs the [{extra}] extra: pip install 'kestrel-vio[{extra}]'")
        self.extra = extra


def require(module: str, extra: str, what: str) -> ModuleType:
    """Import `module` (from the `extra`) for `what` (the feature, as the user names it)."""
    try:
        if module in NOISY_IMPORTS and module not in sys.modules:
            return _quiet_import(module, NOISY_IMPORTS[module])
        return importlib.import_module(module)
    except ImportError:
        raise MissingExtra(what, extra) from None


def _flush_python_streams() -> None:
    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(AttributeError, OSError, ValueError):  # None, closed, or a stand-in
            stream.flush()


def _quiet_import(module: str, harmless: str) -> ModuleType:
    """Import `module` with file descriptor 1 (stdout, where depthai's logger prints) sent to a temporary file, then
    restored (also when the import fails), and log what its native code printed there: its known `harmless` line at
    DEBUG, anything else at WARNING. Python's own streams are flushed on both sides, so its text lands where it was
    meant to. Descriptor 2 is left alone: a native abort's last words go there, and a temporary file would take them
    with it when the process dies (a review's finding: a silent exit in a systemd restart loop)."""
    _flush_python_streams()
    saved: list[tuple[int, int]] = []  # (descriptor, its copy)
    with tempfile.TemporaryFile() as sink:
        try:
            with contextlib.suppress(OSError):  # a descriptor that is closed (a daemon without stdout): left so
                for fd in (1,):
                    saved.append((fd, os.dup(fd)))
                    os.dup2(sink.fileno(), fd)
            return importlib.import_module(module)
        finally:
            _flush_python_streams()
            for fd, copy in saved:
                os.dup2(copy, fd)
                os.close(copy)
            sink.seek(0)
            for line in sink.read().decode(errors="replace").splitlines():
                if line.strip():
                    log.log(logging.DEBUG if harmless in line else logging.WARNING, "%s (on import): %s", module,
                            line.strip())


def pyplot(what: str) -> ModuleType:
    """matplotlib.pyplot on the file-only Agg backend, for `what` (a plot)."""
    matplotlib = require("matplotlib", "tools", what)
    matplotlib.use("Agg")
    return require("matplotlib.pyplot", "tools", what)
