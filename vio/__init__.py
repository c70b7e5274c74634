"""Kestrel VIO: stereo visual-inertial odometry for drones.

The core (`vio`) never imports drivers, pymavlink or depthai: it runs from replayed data alone.
"""

import logging

__version__ = "0.1.0"

logging.getLogger(__name__).addHandler(logging.NullHandler())


class VioError(Exception):
    """The one exception type users see: its message says what is wrong and where (file, line, key)."""
