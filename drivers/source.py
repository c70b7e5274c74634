"""The factory that opens the source the config asks for; the interface itself is drivers/base.py.

The sources (drivers/fake.py, depthai_camera.py, serial_imu.py) import only drivers/base.py, and this module
imports them when a config asks for them, so there is no import cycle and no hardware library is loaded for
a source that is not used. The base names are re-exported here for existing callers.
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
                serial_factory: Callable[..., Any] | None = None) -> SensorSource:
    """Build (not start) the source the config asks for. `dai_module`/`serial_factory` let tests inject
    fakes of depthai and pyserial."""
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
        raise VioError("[source] imu = 'mavlink' is not implemented yet; use 'oak' or 'serial'")
    if cfg.imu == "none" and hasattr(cam, "enable_imu"):
        cam.enable_imu = False
    return cam
