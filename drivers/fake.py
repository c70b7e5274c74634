"""Sources without hardware: a deterministic synthetic sensor head and EuRoC playback.

`FakeSource` renders a fixed random texture seen by a stereo pair that pans slowly (constant disparity,
so features track and match), plus a smooth IMU signal. Everything is a pure function of the sample
index and `seed`, so two instances with the same `t0_ns` produce bit-identical streams: tests compare a
recording against a fresh instance. `realtime=True` releases data as the host clock reaches its stamps
(like a device); `realtime=False` releases `batch_s` of data per poll() as fast as the caller polls.

`EurocSource` plays a EuRoC dataset through the same interface (`[source] kind = "euroc"`).
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from drivers.source import Message, SensorSource
from vio.calibration import CameraCalibration, ImuNoise, StereoCalibration
from vio.geometry import make_T
from vio.types import ImuSample, StereoFrame

# camera looking along body x (forward), optical x right = -body y, optical y down = -body z
R_BODY_CAM_FORWARD = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


def imu_signal(k: int, rate_hz: float) -> tuple[np.ndarray, np.ndarray]:
    """Gentle deterministic motion: slow sinusoidal rates, gravity plus a small oscillation."""
    t = k / rate_hz
    gyro = np.array([0.10 * np.sin(2.0 * t), 0.05 * np.cos(1.3 * t), 0.02 * np.sin(0.7 * t)])
    accel = np.array([0.3 * np.sin(1.1 * t), 0.2 * np.cos(0.9 * t), 9.81 + 0.1 * np.sin(3.0 * t)])
    return gyro, accel


class FakeSource(SensorSource):
    """Synthetic stereo camera + IMU with a known calibration."""

    name = "fake"

    def __init__(self, width: int = 640, height: int = 400, fps: float = 20.0, imu_rate_hz: float = 200.0, *,
                 duration_s: float | None = None, t0_ns: int | None = None, realtime: bool = True,
                 batch_s: float = 0.05, disparity_px: int = 8, seed: int = 0, enable_imu: bool = True) -> None:
        self.width, self.height = width, height
        self.fps, self.imu_rate_hz = fps, imu_rate_hz
        self.duration_ns = None if duration_s is None else int(duration_s * 1e9)
        self.t0_ns = t0_ns
        self.realtime = realtime
        self.batch_ns = int(batch_s * 1e9)
        self.disparity_px = disparity_px
        self.enable_imu = enable_imu
        self.seed = seed
        self._texture: np.ndarray | None = None
        self._k_frame = 0
        self._k_imu = 0
        self._virtual_now = 0
        self._started = False
        self.frames_sent = 0
        self.imu_sent = 0

    # -- deterministic content -----------------------------------------------------------------------------
    def _tex(self) -> np.ndarray:
        if self._texture is None:
            rng = np.random.default_rng(self.seed)
            h, w = self.height + 64, self.width + 512
            noise = rng.integers(0, 256, size=(h // 4, w // 4), dtype=np.uint8)
            self._texture = cv2.GaussianBlur(cv2.resize(noise, (w, h), interpolation=cv2.INTER_CUBIC), (3, 3), 0)
        return self._texture

    def frame_t_ns(self, k: int) -> int:
        return int(self._t0() + round(k * 1e9 / self.fps))

    def imu_t_ns(self, k: int) -> int:
        return int(self._t0() + round(k * 1e9 / self.imu_rate_hz))

    def render(self, k: int) -> StereoFrame:
        """Frame k: both views are crops of the texture; the right one shifted by the disparity."""
        tex = self._tex()
        span = tex.shape[1] - self.width - self.disparity_px
        x = int(abs((k * 2) % (2 * span) - span))  # pan back and forth, 2 px per frame
        y = 32 + int(round(16 * np.sin(k / 25.0)))
        left = np.ascontiguousarray(tex[y:y + self.height, x + self.disparity_px:x + self.disparity_px + self.width])
        right = np.ascontiguousarray(tex[y:y + self.height, x:x + self.width])
        return StereoFrame(self.frame_t_ns(k), left, right, seq=k)

    def imu(self, k: int) -> ImuSample:
        gyro, accel = imu_signal(k, self.imu_rate_hz)
        return ImuSample(self.imu_t_ns(k), gyro, accel)

    def calibration(self) -> StereoCalibration:
        f = 0.7 * self.width
        baseline = 0.075
        cams = []
        for i in range(2):
            T = make_T(R_BODY_CAM_FORWARD, np.array([0.02, 0.0375 - i * baseline, 0.0]))
            cams.append(CameraCalibration(fx=f, fy=f, cx=self.width / 2, cy=self.height / 2, width=self.width,
                                          height=self.height, distortion_model="radtan",
                                          distortion=(0.0, 0.0, 0.0, 0.0), T_body_cam=T, rate_hz=self.fps))
        return StereoCalibration(cams[0], cams[1], ImuNoise(rate_hz=self.imu_rate_hz))

    # -- source interface ----------------------------------------------------------------------------------
    def _t0(self) -> int:
        if self.t0_ns is None:
            self.t0_ns = time.monotonic_ns()
        return self.t0_ns

    def start(self) -> None:
        self._t0()
        self._started = True

    def stop(self) -> None:
        self._started = False

    def _end_ns(self) -> int | None:
        return None if self.duration_ns is None else self._t0() + self.duration_ns

    def poll(self) -> list[Message]:
        if not self._started:
            return []
        if self.realtime:
            now = time.monotonic_ns()
        else:
            self._virtual_now = max(self._virtual_now, self._t0()) + self.batch_ns
            now = self._virtual_now
        end = self._end_ns()
        if end is not None:
            now = min(now, end)
        out: list[Message] = []
        while self.enable_imu and self.imu_t_ns(self._k_imu) <= now:
            out.append(self.imu(self._k_imu))
            self._k_imu += 1
        while self.frame_t_ns(self._k_frame) <= now:
            out.append(self.render(self._k_frame))
            self._k_frame += 1
        self.imu_sent = self._k_imu
        self.frames_sent = self._k_frame
        return out

    def messages(self) -> Iterator[Message]:
        """The whole (finite) stream in poll order, without the clock: for tests comparing recordings."""
        assert self.duration_ns is not None, "messages() needs duration_s"
        self.start()
        while not self.finished:
            yield from self.poll()

    @property
    def finished(self) -> bool:
        end = self._end_ns()
        return end is not None and self.imu_t_ns(self._k_imu) > end and self.frame_t_ns(self._k_frame) > end

    def health(self) -> dict[str, Any]:
        return {"name": self.name, "state": "running" if self._started else "stopped",
                "frames": self.frames_sent, "imu": self.imu_sent}


class EurocSource(SensorSource):
    """A EuRoC dataset played as a live source. With `realtime` the stamps are moved onto the host clock
    (first sample = start time) and released at that pace; otherwise the dataset's stamps are kept and
    `batch` messages are released per poll()."""

    name = "euroc"

    def __init__(self, path: str | Path, *, realtime: bool = True, batch: int = 200) -> None:
        from vio.io.euroc import EurocDataset

        self.dataset = EurocDataset(path)
        self.realtime = realtime
        self.batch = batch
        self._it: Iterator[ImuSample | StereoFrame] | None = None
        self._pending: ImuSample | StereoFrame | None = None
        self._shift_ns = 0
        self._done = False
        self.frames = 0
        self.imu = 0

    def start(self) -> None:
        if self._it is not None:
            return
        self._it = self.dataset.events()
        if self.realtime:
            t_first = min(int(self.dataset.imu.t_ns[0]), int(self.dataset.frame_t[0]) if len(self.dataset) else 2**62)
            self._shift_ns = time.monotonic_ns() - t_first

    def stop(self) -> None:
        self._it = None

    def _shifted(self, m: ImuSample | StereoFrame) -> ImuSample | StereoFrame:
        if not self._shift_ns:
            return m
        if isinstance(m, ImuSample):
            return ImuSample(m.t_ns + self._shift_ns, m.gyro, m.accel)
        return dataclasses.replace(m, t_ns=m.t_ns + self._shift_ns)

    def poll(self) -> list[Message]:
        if self._it is None or self._done:
            return []
        now = time.monotonic_ns()
        imu: list[Message] = []
        frames: list[Message] = []
        while len(imu) + len(frames) < self.batch:
            if self._pending is not None:
                m, self._pending = self._pending, None
            else:
                raw = next(self._it, None)
                if raw is None:
                    self._done = True
                    break
                m = self._shifted(raw)
            if self.realtime and m.t_ns > now:
                self._pending = m
                break
            (imu if isinstance(m, ImuSample) else frames).append(m)
        self.imu += len(imu)
        self.frames += len(frames)
        return imu + frames

    def calibration(self) -> StereoCalibration:
        return self.dataset.calibration

    @property
    def finished(self) -> bool:
        return self._done

    def health(self) -> dict[str, Any]:
        return {"name": self.name, "dataset": str(self.dataset.root), "frames": self.frames, "imu": self.imu,
                "finished": self._done}
