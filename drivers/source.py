"""The factory that opens the source the config asks for; the interface itself is drivers/base.py.

The sources (drivers/fake.py, depthai_camera.py, serial_imu.py, mavlink_imu.py) import only drivers/base.py,
and this module imports them when a config asks for them, so there is no import cycle and no hardware library
is loaded for a source that is not used. The base names are re-exported here for existing callers.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING, Any

from drivers.base import (  # noqa: F401  (re-exported)
    CombinedSource,
    DropOldestQueue,
    Message,
    SensorSource,
    ThreadedSource,
)

if TYPE_CHECKING:
    from vio.config import SourceConfig


def open_source(cfg: SourceConfig, dai_module: Any = None,
                serial_factory: Callable[..., Any] | None = None, mavlink_link: Any = None) -> SensorSource:
    """Build (not start) the source the config asks for. `dai_module`/`serial_factory` let tests inject
    fakes of depthai and pyserial. `mavlink_link` (drivers.mavlink_link.MavlinkLink) is the connection
    an `imu = "mavlink"` source shares with the pose output; without it the source opens its own on
    `mavlink_imu_url`."""
    from vio import VioError

    if cfg.kind == "fake":
        from drivers.fake import FakeSource

        cam: SensorSource = FakeSource(width=cfg.width, height=cfg.height, fps=cfg.fps,
                                       imu_rate_hz=cfg.imu_rate_hz, realtime=cfg.realtime,
                                       duration_s=cfg.fake_duration_s or None, seed=cfg.fake_seed,
                                       profile=cfg.fake_profile)
    elif cfg.kind == "euroc":
        from drivers.fake import EurocSource

        if not cfg.dataset:
            raise VioError("[source] kind = 'euroc' needs 'dataset' (path of a EuRoC folder)")
        cam = EurocSource(cfg.dataset, realtime=cfg.realtime)
    elif cfg.kind == "sitl":
        from drivers.sitl_camera import SitlCameraSource

        cam = SitlCameraSource(cfg.sitl_url, tuple(cfg.sitl_home), width=cfg.width, height=cfg.height, fps=cfg.fps,
                               blackout_file=cfg.sitl_blackout_file, seed=cfg.fake_seed)
    elif cfg.kind == "oak":
        from drivers.depthai_camera import OakSource

        cam = OakSource(cfg, dai_module=dai_module)
    else:  # config validation makes this unreachable; keep a clear message anyway
        raise VioError(f"[source] kind = {cfg.kind!r} is not supported")

    if cfg.imu == "serial":
        from drivers.serial_imu import SerialImuSource

        return CombinedSource(cam, SerialImuSource(cfg.serial_port, cfg.serial_baud,
                                                   nominal_rate_hz=cfg.serial_imu_rate_hz,
                                                   serial_factory=serial_factory))
    if cfg.imu == "mavlink":
        return CombinedSource(cam, mavlink_imu_source(cfg, mavlink_link))
    if cfg.imu == "none" and hasattr(cam, "enable_imu"):
        cam.enable_imu = False
    return cam


def mavlink_imu_source(cfg: SourceConfig, link: Any = None) -> SensorSource:
    """The `imu = "mavlink"` source: on `link` when given (shared with the output), else on its own link
    to `mavlink_imu_url`."""
    from drivers.mavlink_imu import MavlinkImuSource
    from drivers.mavlink_link import MavlinkLink
    from vio import VioError

    owns = link is None
    if owns:
        if not cfg.mavlink_imu_url:
            raise VioError("[source] imu = 'mavlink' needs [source] mavlink_imu_url here (the daemon shares "
                           "its [mavlink] url when mavlink_imu_url is empty)")
        link = MavlinkLink(cfg.mavlink_imu_url, key="[source] mavlink_imu_url")
    return MavlinkImuSource(link, message=cfg.mavlink_imu_message, rate_hz=cfg.mavlink_imu_rate_hz,
                            request_rate=cfg.mavlink_imu_request_rate, accel_scale=cfg.mavlink_imu_accel_scale,
                            gyro_scale=cfg.mavlink_imu_gyro_scale, axes=cfg.mavlink_imu_axes,
                            imu_id=cfg.mavlink_imu_id, owns_link=owns)
