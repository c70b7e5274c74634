"""OAK source code paths against a fake shaped like the depthai v3 API (no device is attached here).

The fake keeps depthai's real enums and a real `dai.CalibrationHandler` loaded from
tests/data/depthai_calib.json (an OAK-D style EEPROM export written by depthai itself), so the
calibration path runs exactly as on a device."""

from __future__ import annotations

import datetime
import json
import threading
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

dai = pytest.importorskip("depthai")

from drivers.depthai_camera import OakSource, timedelta_ns  # noqa: E402
from drivers.source import CombinedSource, open_source  # noqa: E402
from vio.config import SourceConfig  # noqa: E402
from vio.geometry import inv_T, make_T  # noqa: E402
from vio.types import ImuSample, StereoFrame  # noqa: E402

CALIB_JSON = Path(__file__).parent / "data" / "depthai_calib.json"
EXPOSURE_US = 4000


def _td(ns: int) -> datetime.timedelta:
    return datetime.timedelta(microseconds=ns // 1000)


class FakeWorld:
    """What the fake device does: which devices exist, when the cable is pulled, what it streams."""

    def __init__(self, *, devices: int = 1, imu: str = "BMI270", unplug_after: int | None = None,
                 right_offset_us: int = 0) -> None:
        self.devices = devices
        self.imu = imu
        self.unplug_after = unplug_after  # frames until the first session's queue raises (cable pulled)
        self.right_offset_us = right_offset_us
        self.sessions = 0
        self.built: list[tuple] = []
        self.frames_sent = 0
        self.exposure_starts: list[int] = []
        self.lock = threading.Lock()


class _Out:
    def __init__(self, world: FakeWorld, kind: str, node: object) -> None:
        self.world, self.kind, self.node, self.linked = world, kind, node, None

    def link(self, inp: object) -> None:
        self.linked = inp

    def createOutputQueue(self, maxSize: int = 16, blocking: bool = False) -> _Queue:  # noqa: N802 (depthai API)
        return _Queue(self.world, self.kind, self.node)


class _Queue:
    def __init__(self, world: FakeWorld, kind: str, node: object) -> None:
        self.world, self.kind, self.node = world, kind, node
        self.k = 0
        self.t0 = time.monotonic_ns()

    def tryGet(self):  # noqa: N802 (depthai API)
        w = self.world
        if w.unplug_after is not None and w.sessions == 1 and w.frames_sent >= w.unplug_after:
            raise RuntimeError("Communication exception - possible device error/misconfiguration. "
                               "Original message 'Couldn't read data from stream: '__x_0_out' (X_LINK_ERROR)'")
        if self.kind == "stereo":
            t = self.t0 + self.k * 50_000_000
            if time.monotonic_ns() < t + EXPOSURE_US * 1000:
                return None
            with w.lock:
                w.frames_sent += 1
                w.exposure_starts.append(t)
            self.k += 1
            return {"left": _Frame(t, self.k, 10), "right": _Frame(t + w.right_offset_us * 1000, self.k, 20)}
        t = self.t0 + self.k * 10_000_000  # IMU batch of two samples every 10 ms (200 Hz)
        if time.monotonic_ns() < t:
            return None
        self.k += 1
        return SimpleNamespace(packets=[_Packet(t - 5_000_000, 2 * self.k), _Packet(t, 2 * self.k + 1)])


class _Frame:
    def __init__(self, t_start_ns: int, seq: int, value: int) -> None:
        self.t_start_ns, self.seq, self.value = t_start_ns, seq, value

    def getTimestamp(self, offset=None) -> datetime.timedelta:  # noqa: N802 (depthai API)
        off = {None: 0, dai.CameraExposureOffset.START: 0, dai.CameraExposureOffset.MIDDLE: EXPOSURE_US // 2,
               dai.CameraExposureOffset.END: EXPOSURE_US}[offset]
        return _td(self.t_start_ns + off * 1000)

    def getCvFrame(self) -> np.ndarray:  # noqa: N802 (depthai API)
        return np.full((400, 640), self.value, np.uint8)

    def getSequenceNum(self) -> int:  # noqa: N802 (depthai API)
        return self.seq


class _Packet:
    def __init__(self, t_ns: int, k: int) -> None:
        ts = _td(t_ns)
        self.gyroscope = SimpleNamespace(x=0.01 * k, y=0.0, z=-0.01, getTimestamp=lambda: ts)
        self.acceleroMeter = SimpleNamespace(x=0.0, y=0.0, z=9.81, getTimestamp=lambda: ts)


class _Node:
    def __init__(self, world: FakeWorld, cls: type) -> None:
        self.world, self.cls = world, cls
        kind = "imu" if cls is FakeDai.node.IMU else "stereo"
        self.out = _Out(world, kind, self)
        self.inputs = {"left": "left-in", "right": "right-in"}

    def build(self, socket, sensorFps=None):  # noqa: N803 (depthai API)
        self.world.built.append(("camera", socket, sensorFps))
        return self

    def requestOutput(self, size, type=None, fps=None):  # noqa: N802,A002 (depthai API)
        self.world.built.append(("output", tuple(size), type, fps))
        return _Out(self.world, "cam", self)

    def setSyncThreshold(self, td) -> None:  # noqa: N802 (depthai API)
        self.world.built.append(("sync", td))

    def enableIMUSensor(self, sensors, rate) -> None:  # noqa: N802 (depthai API)
        self.world.built.append(("imu", tuple(sensors), rate))

    def setBatchReportThreshold(self, n) -> None:  # noqa: N802 (depthai API)
        pass

    def setMaxBatchReports(self, n) -> None:  # noqa: N802 (depthai API)
        pass


class _Pipeline:
    def __init__(self, device: _Device) -> None:
        self.world = device.world

    def __enter__(self) -> _Pipeline:
        return self

    def __exit__(self, *exc) -> None:
        pass

    def create(self, cls: type) -> _Node:
        return _Node(self.world, cls)

    def start(self) -> None:
        self.world.sessions += 1

    def isRunning(self) -> bool:  # noqa: N802 (depthai API)
        return True


class _Device:
    world: FakeWorld

    def __init__(self, *args) -> None:
        self.closed = False

    @classmethod
    def getAllAvailableDevices(cls) -> list:  # noqa: N802 (depthai API)
        return ["1844301011B546F500"] * cls.world.devices

    def readCalibration(self):  # noqa: N802 (depthai API)
        return dai.CalibrationHandler(str(CALIB_JSON))

    def getConnectedIMU(self) -> str:  # noqa: N802 (depthai API)
        return self.world.imu

    def getDeviceId(self) -> str:  # noqa: N802 (depthai API)
        return "1844301011B546F500"

    def close(self) -> None:
        self.closed = True


class FakeDai:
    """The subset of the depthai module the driver touches; enums are depthai's own."""

    CameraBoardSocket = dai.CameraBoardSocket
    CameraExposureOffset = dai.CameraExposureOffset
    IMUSensor = dai.IMUSensor
    ImgFrame = dai.ImgFrame
    node = SimpleNamespace(Camera=type("Camera", (), {}), Sync=type("Sync", (), {}), IMU=type("IMU", (), {}))

    def __init__(self, world: FakeWorld) -> None:
        self.Device = type("Device", (_Device,), {"world": world})
        self.Pipeline = _Pipeline


def _collect(src: OakSource, until, timeout_s: float = 5.0) -> list:
    got: list = []
    deadline = time.monotonic() + timeout_s
    while not until(got) and time.monotonic() < deadline:
        got += src.poll()
        time.sleep(0.01)
    return got


def _frames(msgs: list) -> list[StereoFrame]:
    return [m for m in msgs if isinstance(m, StereoFrame)]


def test_streams_pairs_and_imu_on_host_clock_at_mid_exposure() -> None:
    world = FakeWorld()
    src = OakSource(dai_module=FakeDai(world), width=640, height=400, fps=20, imu_rate_hz=200)
    t_before = time.monotonic_ns()
    src.start()
    try:
        got = _collect(src, lambda g: len(_frames(g)) >= 5)
    finally:
        src.stop()
    frames = _frames(got)
    imu = [m for m in got if isinstance(m, ImuSample)]
    assert len(frames) >= 5 and len(imu) >= 20
    f = frames[0]
    assert f.left.shape == (400, 640) and f.right is not None and int(f.right[0, 0]) == 20
    # stamps: host monotonic clock, exposure middle = start + 2 ms, 50 ms apart
    assert t_before < f.t_ns < time.monotonic_ns()
    assert f.t_ns == world.exposure_starts[0] // 1000 * 1000 + EXPOSURE_US // 2 * 1000
    np.testing.assert_array_equal(np.diff([fr.t_ns for fr in frames]), 50_000_000)
    assert np.all(np.diff([s.t_ns for s in imu]) == 5_000_000)
    # the pipeline asked for what the config says: CAM_B/CAM_C, GRAY8 640x400 at 20 Hz, raw IMU at 200 Hz
    built = world.built
    assert ("camera", dai.CameraBoardSocket.CAM_B, 20.0) in built
    assert ("camera", dai.CameraBoardSocket.CAM_C, 20.0) in built
    assert ("output", (640, 400), dai.ImgFrame.Type.GRAY8, 20.0) in built
    assert ("imu", (dai.IMUSensor.ACCELEROMETER_RAW, dai.IMUSensor.GYROSCOPE_RAW), 200) in built
    h = src.health()
    assert h["state"] == "stopped" and h["connects"] == 1 and h["imu"]["gaps"] == 0


def test_timedelta_ns_is_exact() -> None:
    assert timedelta_ns(datetime.timedelta(days=2, seconds=3, microseconds=7)) == (2 * 86400 + 3) * 10**9 + 7000


def test_calibration_from_eeprom_json_at_streamed_resolution() -> None:
    """Intrinsics scaled to 640x400, baseline in metres, T_body_cam from the IMU->CAM_C chain."""
    world = FakeWorld()
    src = OakSource(dai_module=FakeDai(world), width=640, height=400, fps=20)
    src.start()
    try:
        _collect(src, lambda g: src.calibration() is not None)
        calib = src.calibration()
    finally:
        src.stop()
    assert calib is not None
    raw = json.loads(CALIB_JSON.read_text())
    cams = dict((int(k), v) for k, v in raw["cameraData"])
    KB = np.array(cams[1]["intrinsicMatrix"])  # socket 1 = CAM_B (left, cam0), calibrated at 1280x800
    assert (calib.cam0.width, calib.cam0.height) == (640, 400)
    np.testing.assert_allclose([calib.cam0.fx, calib.cam0.fy], [KB[0, 0] / 2, KB[1, 1] / 2], rtol=1e-6)
    # depthai's pixel-centre convention shifts the principal point by up to half a pixel when scaling
    np.testing.assert_allclose([calib.cam0.cx, calib.cam0.cy], [KB[0, 2] / 2, KB[1, 2] / 2], atol=0.5)

    def T_from(ext: dict) -> np.ndarray:  # EEPROM extrinsics: rotation + translation in cm
        t = ext["translation"]
        return make_T(np.array(ext["rotationMatrix"]), np.array([t["x"], t["y"], t["z"]]) / 100.0)

    assert cams[1]["extrinsics"]["toCameraSocket"] == 2 and raw["imuExtrinsics"]["toCameraSocket"] == 2
    T_C_B = T_from(cams[1]["extrinsics"])  # maps CAM_B points into CAM_C
    T_C_imu = T_from(raw["imuExtrinsics"])
    assert abs(calib.baseline_m - 0.074963) < 2e-5
    np.testing.assert_allclose(calib.T_cam1_cam0, T_C_B, atol=1e-6)
    np.testing.assert_allclose(calib.cam0.T_body_cam, inv_T(T_C_imu) @ T_C_B, atol=1e-6)
    np.testing.assert_allclose(calib.cam1.T_body_cam, inv_T(T_C_imu), atol=1e-6)
    # OAK mono lenses use the rational model: all 8 non-zero coefficients are kept, in OpenCV order
    assert calib.cam0.distortion_model == "radtan" and len(calib.cam0.distortion) == 8
    np.testing.assert_allclose(calib.cam0.distortion, cams[1]["distortionCoeff"][:8], rtol=1e-6)


def test_no_device_then_plugged_in() -> None:
    world = FakeWorld(devices=0)
    src = OakSource(dai_module=FakeDai(world), backoff_s=0.01, backoff_max_s=0.02)
    src.start()
    try:
        _collect(src, lambda g: src.no_device_tries >= 3)
        h = src.health()
        assert h["state"] == "no_device" and "no OAK device found" in h["last_error"]
        world.devices = 1
        got = _collect(src, lambda g: len(_frames(g)) >= 2)
    finally:
        src.stop()
    assert len(_frames(got)) >= 2 and src.connects == 1 and src.last_error == ""


def test_unplugged_mid_flight_reconnects() -> None:
    world = FakeWorld(unplug_after=3)
    src = OakSource(dai_module=FakeDai(world), backoff_s=0.01)
    src.start()
    try:
        got = _collect(src, lambda g: len(_frames(g)) >= 6)
    finally:
        src.stop()
    assert len(_frames(got)) >= 6
    h = src.health()
    assert h["disconnects"] == 1 and h["connects"] == 2 and world.sessions == 2
    assert h["frames"]["non_monotonic"] == 0


def test_device_without_imu_streams_cameras_and_says_so() -> None:
    world = FakeWorld(imu="NONE")
    src = OakSource(dai_module=FakeDai(world))
    src.start()
    try:
        got = _collect(src, lambda g: len(_frames(g)) >= 2)
    finally:
        src.stop()
    assert not any(isinstance(m, ImuSample) for m in got)
    assert src.health()["imu_absent"] is True
    assert not any(b[0] == "imu" for b in world.built)


def test_unsynced_pair_loses_only_its_right_image() -> None:
    world = FakeWorld(right_offset_us=5000)
    src = OakSource(dai_module=FakeDai(world))
    src.start()
    try:
        got = _collect(src, lambda g: len(_frames(g)) >= 2)
    finally:
        src.stop()
    assert all(f.right is None for f in _frames(got))
    assert src.unsynced_pairs >= 2 and src.health()["max_pair_dt_us"] == 5000


def test_open_source_combines_oak_cameras_with_serial_imu() -> None:
    src = open_source(SourceConfig(kind="oak", imu="serial", serial_port="/dev/null-kestrel"),
                      dai_module=FakeDai(FakeWorld()))
    assert isinstance(src, CombinedSource)
    assert isinstance(src.camera, OakSource) and src.camera.enable_imu is False
