"""Kestrel VIO: stereo visual-inertial odometry for drones.

The core (everything in `vio` outside `vio.app`) never imports `drivers`, `calib`, pymavlink or depthai: it
runs from replayed data alone. `vio.app` (the commands, replay, the daemon) is the only code that imports
`drivers` and `calib`; tests/test_layering.py checks this from the import graph.
"""

import logging

__version__ = "0.1.0"

logging.getLogger(__name__).addHandler(logging.NullHandler())


class VioError(Exception):
    """The one exception type users see: its message says what is wrong and where (file, line, key)."""


class UsageError(VioError):
    """Options that contradict each other or do nothing as given: refused before any work with exit 2, the code
    argparse gives its own usage errors (a flag that silently did nothing let a user think it had acted)."""

    exit_code = 2
