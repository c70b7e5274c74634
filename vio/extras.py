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

import importlib
from types import ModuleType

from vio import VioError

EXTRAS = {"depthai": "oak", "serial": "serial", "allantools": "tools", "matplotlib": "tools", "rosbags": "bags",
          "mcap": "bags", "rerun": "view", "ray": "fleet"}


class MissingExtra(VioError):
    """An optional dependency is not installed; the message names the extra that brings it."""

    def __init__(self, what: str, extra: str) -> None:
        super().__init__(f"{what} needs the [{extra}] extra: pip install 'kestrel-vio[{extra}]'")
        self.extra = extra


def require(module: str, extra: str, what: str) -> ModuleType:
    """Import `module` (from the `extra`) for `what` (the feature, as the user names it)."""
    try:
        return importlib.import_module(module)
    except ImportError:
        raise MissingExtra(what, extra) from None


def pyplot(what: str) -> ModuleType:
    """matplotlib.pyplot on the file-only Agg backend, for `what` (a plot)."""
    matplotlib = require("matplotlib", "tools", what)
    matplotlib.use("Agg")
    return require("matplotlib.pyplot", "tools", what)
