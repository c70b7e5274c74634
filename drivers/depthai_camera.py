"""OAK (Luxonis) stereo camera + IMU through the depthai v3 API.

Pipeline: two mono `Camera` nodes (CAM_B = left = cam0, CAM_C = right = cam1) at the configured size and
rate, joined by a `Sync` node into hardware-synchronised pairs, and an `IMU` node streaming raw
accelerometer + gyroscope in batches. A reader thread moves the messages into bounded queues; poll()
drains them without blocking.

Time stamps: depthai keeps the device clock synchronised with the host's std::chrono::steady_clock,
which on Linux is CLOCK_MONOTONIC, the clock of `time.monotonic_ns()`. `getTimestamp()` is therefore
already on our host clock, while `getTimestampDevice()` is the raw device clock (never used here). Frames
are stamped at the middle of the exposure (`CameraExposureOffset.MIDDLE`): that is the instant the image
represents, and it does not move when auto-exposure changes the exposure time. IMU samples take the
gyroscope's stamp (the accelerometer of the same packet is within one sample period).

Failures: no device -> one clear log line and retries with exponential backoff; device lost mid-flight
(XLink error, pipeline stopped) -> reconnect with backoff, the count is in health(); device without an
IMU -> cameras only, `imu_absent` in health() and a log line saying to configure another IMU source.
"""

from __future__ import annotations

import datetime
import logging
from typing import Any

import numpy as np

from drivers.base import DropOldestQueue, Message, ThreadedSource
from drivers.timesync import StreamMonitor
from vio.calibration import StereoCalibration
from vio.types import ImuSample, StereoFrame

log = logging.getLogger(__name__)

_NO_IMU_NAMES = {"", "NONE", "NO_IMU"}


class NoDeviceError(RuntimeError):
    """No OAK device is visible on USB/network."""


def timedelta_ns(td: datetime.timedelta) -> int:
    """depthai's timedelta (microsecond resolution) -> integer ns, without float rounding."""
    return ((td.days * 86400 + td.seconds) * 1_000_000 + td.microseconds) * 1000


class OakSource(ThreadedSource):
    """Stereo frames and IMU samples from an OAK device (OAK-D, OAK-D Lite/Pro/W, ...)."""

    name = "oak"

    def __init__(self, cfg: Any = None, *, dai_module: Any = None, width: int = 640, height: int = 400,
                 fps: float = 20.0, imu_rate_hz: float = 200.0, enable_imu: bool = True, device_id: str = "",
                 frame_queue: int = 4, imu_queue: int = 4000, backoff_s: float = 0.5,
                 backoff_max_s: float = 10.0) -> None:
        super().__init__()
        if cfg is not None:
            width, height, fps, imu_rate_hz = cfg.width, cfg.height, cfg.fps, cfg.imu_rate_hz
            enable_imu = cfg.imu == "oak"
            device_id = getattr(cfg, "oak_device", "") or ""
        self._dai = dai_module
        self.size = (int(width), int(height))
        self.fps = float(fps)
        self.imu_rate_hz = float(imu_rate_hz)
        self.enable_imu = enable_imu
        self.device_id = device_id
        self._frames = DropOldestQueue(frame_queue)
        self._imu = DropOldestQueue(imu_queue)
        self._backoff = (backoff_s, backoff_max_s)
        self._calib: StereoCalibration | None = None
        self.frame_monitor = StreamMonitor("OAK frames", fps)
        self.imu_monitor = StreamMonitor("OAK IMU", imu_rate_hz)
        self.connects = 0
        self.disconnects = 0
        self.no_device_tries = 0
        self.imu_absent = False
        self.unsynced_pairs = 0
        self.max_pair_dt_ns = 0
        self.last_error = ""
        self.device_name = ""

    # -- interface -----------------------------------------------------------------------------------------
    def _before_start(self) -> None:
        if self._dai is None:
            from vio.extras import require  # imported here: `vio --help` and non-OAK setups must not need it

            self._dai = require("depthai", "oak", '[source] kind = "oak"')

    def poll(self) -> list[Message]:
        return self._imu.drain() + self._frames.drain()

    def calibration(self) -> StereoCalibration | None:
        return self._calib

    def health(self) -> dict[str, Any]:
        return {"name": self.name, "state": self.state, "device": self.device_name, "connects": self.connects,
                "disconnects": self.disconnects, "no_device_tries": self.no_device_tries,
                "imu_absent": self.imu_absent, "frames_dropped": self._frames.dropped,
                "imu_dropped": self._imu.dropped, "unsynced_pairs": self.unsynced_pairs,
                "max_pair_dt_us": self.max_pair_dt_ns / 1e3, "frames": self.frame_monitor.as_dict(),
                "imu": self.imu_monitor.as_dict(), "last_error": self.last_error}

    # -- reader thread -------------------------------------------------------------------------------------
    def _run(self) -> None:
        backoff = self._backoff[0]
        while not self._stop.is_set():
            try:
                self._session()
                backoff = self._backoff[0]
                continue
            except NoDeviceError as e:
                self.no_device_tries += 1
                self.state = "no_device"
                self._report(str(e))
            except Exception as e:  # depthai raises RuntimeError (XLink) for a lost/ crashed device
                if self.state == "running":
                    self.disconnects += 1
                self.state = "disconnected"
                self._report(f"OAK device lost or failed: {e}")
            self._stop.wait(backoff)
            backoff = min(backoff * 2, self._backoff[1])

    def _report(self, msg: str) -> None:
        if msg != self.last_error:  # one line per new problem, not one per retry
            log.error("%s; retrying with backoff", msg)
        self.last_error = msg

    def _open_device(self) -> Any:
        dai = self._dai
        if not dai.Device.getAllAvailableDevices():
            raise NoDeviceError("no OAK device found (check the USB cable/power and udev rules; "
                                "`lsusb | grep 03e7` should list it)")
        return dai.Device(self.device_id) if self.device_id else dai.Device()

    def _session(self) -> None:
        """One connection: read calibration, build and run the pipeline until stop() or device loss."""
        dai = self._dai
        device = self._open_device()
        try:
            self.device_name = str(device.getDeviceId()) if hasattr(device, "getDeviceId") else "oak"
            self._calib = self._read_calibration(device)
            imu_name = str(device.getConnectedIMU() or "").upper()
            use_imu = self.enable_imu and imu_name not in _NO_IMU_NAMES
            self.imu_absent = self.enable_imu and not use_imu
            if self.imu_absent:
                log.warning("OAK %s has no IMU: streaming cameras only; set [source] imu = \"serial\" to use "
                            "a serial IMU", self.device_name)
            with dai.Pipeline(device) as pipeline:
                q_stereo, q_imu = self._build(pipeline, use_imu)
                pipeline.start()
                self.connects += 1
                self.state = "running"
                self.last_error = ""
                log.info("OAK %s streaming %dx%d at %.0f Hz, IMU %s", self.device_name, *self.size, self.fps,
                         f"{imu_name} at {self.imu_rate_hz:.0f} Hz" if use_imu else "off")
                while not self._stop.is_set():
                    if not pipeline.isRunning():
                        raise RuntimeError("pipeline stopped")
                    got = False
                    if q_imu is not None:
                        msg = q_imu.tryGet()
                        if msg is not None:
                            self._on_imu(msg)
                            got = True
                    group = q_stereo.tryGet()
                    if group is not None:
                        self._on_stereo(group)
                        got = True
                    if not got:
                        self._stop.wait(0.002)
        finally:
            try:
                device.close()
            except Exception as e:  # closing a vanished device can fail; it is gone either way
                log.debug("closing OAK device: %s", e)

    def _read_calibration(self, device: Any) -> StereoCalibration:
        from calib.depthai_import import stereo_from_depthai

        dai = self._dai
        handler = device.readCalibration()
        return stereo_from_depthai(handler, dai.CameraBoardSocket.CAM_B, dai.CameraBoardSocket.CAM_C,
                                   size=self.size, cam_rate_hz=self.fps, imu_rate_hz=self.imu_rate_hz)

    def _build(self, pipeline: Any, use_imu: bool) -> tuple[Any, Any]:
        dai = self._dai
        sync = pipeline.create(dai.node.Sync)
        sync.setSyncThreshold(datetime.timedelta(seconds=0.5 / self.fps))
        for name, socket in (("left", dai.CameraBoardSocket.CAM_B), ("right", dai.CameraBoardSocket.CAM_C)):
            cam = pipeline.create(dai.node.Camera).build(socket, sensorFps=self.fps)
            out = cam.requestOutput(self.size, type=dai.ImgFrame.Type.GRAY8, fps=self.fps)
            out.link(sync.inputs[name])
        q_stereo = sync.out.createOutputQueue(maxSize=4, blocking=False)
        q_imu = None
        if use_imu:
            imu = pipeline.create(dai.node.IMU)
            imu.enableIMUSensor([dai.IMUSensor.ACCELEROMETER_RAW, dai.IMUSensor.GYROSCOPE_RAW],
                                int(self.imu_rate_hz))
            # ~10 ms batches: few USB transfers, little latency
            imu.setBatchReportThreshold(max(1, int(self.imu_rate_hz / 100)))
            imu.setMaxBatchReports(20)
            q_imu = imu.out.createOutputQueue(maxSize=50, blocking=False)
        return q_stereo, q_imu

    def _on_stereo(self, group: Any) -> None:
        mid = self._dai.CameraExposureOffset.MIDDLE
        left, right = group["left"], group["right"]
        t_left = timedelta_ns(left.getTimestamp(mid))
        t_right = timedelta_ns(right.getTimestamp(mid))
        dt = abs(t_left - t_right)
        self.max_pair_dt_ns = max(self.max_pair_dt_ns, dt)
        right_img = right.getCvFrame()
        if dt > 1_000_000:  # hardware sync keeps pairs within microseconds; this pair is not one exposure
            self.unsynced_pairs += 1
            right_img = None
            if self.unsynced_pairs <= 10 or self.unsynced_pairs % 100 == 0:
                log.warning("OAK stereo pair %.2f ms apart: right image dropped (%d so far)", dt / 1e6,
                            self.unsynced_pairs)
        if self.frame_monitor.check(t_left):
            self._frames.put(StereoFrame(t_left, left.getCvFrame(), right_img, seq=int(left.getSequenceNum())))

    def _on_imu(self, data: Any) -> None:
        for p in data.packets:
            g, a = p.gyroscope, p.acceleroMeter
            t = timedelta_ns(g.getTimestamp())
            if self.imu_monitor.check(t):
                self._imu.put(ImuSample(t, np.array([g.x, g.y, g.z], dtype=float),
                                        np.array([a.x, a.y, a.z], dtype=float)))
