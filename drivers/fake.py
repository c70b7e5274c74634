"""Sources without hardware: a simulated flight played as a live sensor head, and EuRoC playback.

`FakeSource` (`[source] kind = "fake"`) plays a flight of the project's simulator (vio/sim): the motion,
scene, IMU and calibration come from `vio.sim.generate.build()`, the images from its `CameraRenderer`
and `Photometric`, so IMU and images agree and the estimator can track them (a bench test that flies).
The flight is endless unless `duration_s` is given: the simulator's trajectories are sums of sinusoids
that stay inside the room for any time, so the source never loops (no discontinuity); the IMU is made
in chunks of `IMU_CHUNK_S` whose biases continue from the previous chunk. A finite flight simply ends
(`finished`), and the daemon does not reopen a finished source.

Stamps are on the host clock: the flight starts at `t0_ns` (default: `time.monotonic_ns()` at start()).
`realtime=True` releases data as the host clock reaches its stamps, with images rendered ahead by a
background thread (a stereo pair costs ~6 ms at 320x200 and ~21 ms at 640x400 on one core, so 20 Hz keeps
up on a Raspberry-Pi-class machine at the default size; a frame the renderer could not finish within
`MAX_RENDER_LAG_S` of its stamp is skipped and counted as `frames_late`). `realtime=False` releases `batch_s`
of data per poll() as fast as the caller polls, rendering in the caller's thread. Startup (scene,
calibration, the first IMU chunk) takes about one second; builds are cached per flight in the process.

Everything is a pure function of the settings and `seed`: two instances with the same `t0_ns` produce
bit-identical streams (tests compare a recording against a fresh instance), and `truth(t_ns)` gives the
simulator's pose at any stamp (tests evaluate the daemon's trajectory with it).

`EurocSource` plays a EuRoC dataset through the same interface (`[source] kind = "euroc"`).
"""
from __future__ import annotations

import dataclasses
import functools
import logging
import threading
import time
from collections import deque
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

from drivers.base import Message, SensorSource
from vio.calibration import StereoCalibration
from vio.types import ImuSample, StereoFrame

log = logging.getLogger(__name__)

IMU_CHUNK_S = 120.0  # IMU synthesised per chunk (an endless flight never holds more than two)
MAX_RENDER_LAG_S = 0.25  # realtime: a frame not rendered this long after its stamp is skipped
RENDER_AHEAD = 6  # realtime: frames rendered ahead of the clock
# realtime EuRoC playback: a longer gap in the recording's stamps is shortened to this (not waited out, as `vio replay
# --realtime` does not wait one out). It stays a gap to the estimator, which restarts across it as after any IMU gap
# past [run] max_imu_gap_s, and is shorter than [run] source_timeout_s (2 s), past which the daemon would reopen the
# source and play the recording from its start again.
GAP_KEPT_S = 1.0


def imu_signal(k: int, rate_hz: float) -> tuple[np.ndarray, np.ndarray]:
    """Gentle deterministic IMU-like signal (slow sinusoidal rates, gravity plus a small oscillation); the
    reference sender's test pattern (drivers/reference_sender.py). Not a trajectory: FakeSource uses the
    simulator instead."""
    t = k / rate_hz
    gyro = np.array([0.10 * np.sin(2.0 * t), 0.05 * np.cos(1.3 * t), 0.02 * np.sin(0.7 * t)])
    accel = np.array([0.3 * np.sin(1.1 * t), 0.2 * np.cos(0.9 * t), 9.81 + 0.1 * np.sin(3.0 * t)])
    return gyro, accel


@functools.lru_cache(maxsize=4)
def _flight(profile: str, seed: int, width: int, height: int, fps: float, imu_rate_hz: float) -> tuple:
    """(Simulation, [(CameraRenderer, T_body_cam, Photometric)] for cam0 and cam1), built once per flight.

    The simulator's 'clean' variant: EuRoC IMU noise and small biases, sharp noise-free images (blur and
    exposure effects would cost render time a bench test does not need)."""
    from vio.sim.generate import SimConfig, build
    from vio.sim.render import CameraRenderer, Photometric

    sim = build(SimConfig(profile=profile, duration_s=IMU_CHUNK_S, seed=seed, variant="clean", rate_hz=fps,
                          imu_rate_hz=imu_rate_hz, width=width, height=height))
    cfg = sim.config
    photo_rng = np.random.default_rng([seed, 3])
    cams = [(CameraRenderer(c, sim.scene), c.T_body_cam,
             Photometric(photo_rng, cfg.duration_s, cfg.gain_drift, cfg.gain_jumps_hz, noise_sigma=cfg.image_noise,
                         offset=off))
            for c, off in ((sim.calibration.cam0, 0.0), (sim.calibration.cam1, 0.04))]
    return sim, cams


class FakeSource(SensorSource):
    """A simulated flight (vio/sim) as a live stereo camera + IMU with its calibration."""

    name = "fake"

    def __init__(self, width: int = 640, height: int = 400, fps: float = 20.0, imu_rate_hz: float = 200.0, *,
                 duration_s: float | None = None, t0_ns: int | None = None, realtime: bool = True,
                 batch_s: float = 0.05, seed: int = 0, profile: str = "survey", enable_imu: bool = True) -> None:
        self.width, self.height = int(width), int(height)
        self.fps, self.imu_rate_hz = float(fps), float(imu_rate_hz)
        self.duration_ns = None if not duration_s else int(duration_s * 1e9)
        self.t0_ns = t0_ns
        self.realtime = realtime
        self.batch_ns = int(batch_s * 1e9)
        self.enable_imu = enable_imu
        self.seed, self.profile = seed, profile
        self._imu_n = int(round(IMU_CHUNK_S * self.imu_rate_hz))  # samples per IMU chunk
        self._chunks: dict[int, Any] = {}  # chunk index -> vio.sim.imu.ImuStream (at most two kept)
        self._k_frame = 0
        self._k_imu = 0
        self._virtual_now = 0
        self._started = False
        self._ahead: deque[StereoFrame] = deque()  # realtime: rendered, not yet due
        self._cv = threading.Condition()
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self.frames_sent = 0
        self.imu_sent = 0
        self.frames_late = 0
        self.render_ms = 0.0  # mean render time of a stereo pair (exponential average)
        # what stamp_uncertainty_s() says: the simulated stamps are exact (0), a test sets it to act out an IMU whose
        # clock sync has gone wrong mid-flight (the daemon's output then grows the covariance or sends nothing)
        self.clock_uncertainty_s = 0.0

    # -- deterministic content -----------------------------------------------------------------------------
    @property
    def _sim(self) -> tuple:
        return _flight(self.profile, self.seed, self.width, self.height, self.fps, self.imu_rate_hz)

    def frame_t_ns(self, k: int) -> int:
        return int(self._t0() + round(k * 1e9 / self.fps))

    def imu_t_ns(self, k: int) -> int:
        return int(self._t0() + round(k * 1e9 / self.imu_rate_hz))

    def truth(self, t_ns: np.ndarray) -> np.ndarray:
        """The simulator's T_world_body at host stamps `t_ns` (N,) -> (N, 4, 4)."""
        return self._sim[0].motion.pose((np.asarray(t_ns, dtype=np.int64) - self._t0()) * 1e-9)

    def render(self, k: int) -> StereoFrame:
        """Frame k: both cameras rendered at the flight's pose at the frame time."""
        t0 = time.perf_counter()
        t_ns = self.frame_t_ns(k)
        t_s = (t_ns - self._t0()) * 1e-9
        T_wb = self._sim[0].motion.pose(np.array([t_s]))[0]
        left, right = (photo.apply(renderer.render(T_wb @ T_bc)[0], t_s) for renderer, T_bc, photo in self._sim[1])
        self.render_ms += 0.1 * ((time.perf_counter() - t0) * 1e3 - self.render_ms)
        return StereoFrame(t_ns, left, right, seq=k)

    def _imu_chunk(self, c: int) -> Any:
        """IMU chunk c (samples c*N .. (c+1)*N-1); chunk 0 is the simulation's, later ones continue its biases."""
        if c not in self._chunks:
            if c == 0:
                self._chunks[0] = self._sim[0].imu
            else:
                from vio.sim.imu import ImuModel, synthesize

                prev = self._imu_chunk(c - 1)
                sim = self._sim[0]
                model = ImuModel(sim.calibration.imu, tuple(prev.gyro_bias[self._imu_n - 1]),
                                 tuple(prev.accel_bias[self._imu_n - 1]))
                i = np.arange(c * self._imu_n, (c + 1) * self._imu_n)
                t_s = np.round(i * (1e9 / self.imu_rate_hz)) * 1e-9
                self._chunks[c] = synthesize(sim.motion, t_s, model, np.random.default_rng([self.seed, 2, c]))
            for old in [k for k in self._chunks if k < c - 1]:
                del self._chunks[old]
        return self._chunks[c]

    def imu(self, k: int) -> ImuSample:
        c, i = divmod(k, self._imu_n)
        chunk = self._imu_chunk(c)
        return ImuSample(self.imu_t_ns(k), chunk.gyro[i].copy(), chunk.accel[i].copy())

    def calibration(self) -> StereoCalibration:
        return self._sim[0].calibration

    def stamp_uncertainty_s(self) -> float:
        return self.clock_uncertainty_s

    # -- source interface ----------------------------------------------------------------------------------
    def _t0(self) -> int:
        if self.t0_ns is None:
            self.t0_ns = time.monotonic_ns()
        return self.t0_ns

    def start(self) -> None:
        if self._started:
            return
        self._sim  # noqa: B018 - build (about a second) before the clock starts
        log.info("fake source: simulated %s flight (seed %d, %dx%d, %s), t0_ns=%d", self.profile, self.seed,
                 self.width, self.height, "realtime" if self.realtime else "as fast as read", self._t0())
        self._started = True
        if self.realtime and self._thread is None:
            self._stop.clear()
            self._thread = threading.Thread(target=self._render_ahead, name="fake-render", daemon=True)
            self._thread.start()

    def stop(self) -> None:
        self._started = False
        self._stop.set()
        with self._cv:
            self._cv.notify_all()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
            self._thread = None

    def _end_ns(self) -> int | None:
        return None if self.duration_ns is None else self._t0() + self.duration_ns

    def _render_ahead(self) -> None:
        """Realtime: keep up to RENDER_AHEAD frames rendered before they are due; skip frames it is late for."""
        k = 0
        end = self._end_ns()
        while not self._stop.is_set():
            with self._cv:
                while len(self._ahead) >= RENDER_AHEAD and not self._stop.is_set():
                    self._cv.wait(0.1)
            due = int((time.monotonic_ns() - self._t0() - MAX_RENDER_LAG_S * 1e9) * self.fps / 1e9)
            if due > k:  # behind the clock: jump to the frames that can still be on time
                self.frames_late += due - k
                k = due
            if end is not None and self.frame_t_ns(k) > end:
                return
            frame = self.render(k)
            with self._cv:
                self._ahead.append(frame)
            k += 1

    def _due_frames(self, now: int) -> list[Message]:
        if not self.realtime:
            out: list[Message] = []
            while self.frame_t_ns(self._k_frame) <= now:
                out.append(self.render(self._k_frame))
                self._k_frame += 1
            return out
        with self._cv:
            out = []
            while self._ahead and self._ahead[0].t_ns <= now:
                out.append(self._ahead.popleft())
            if out:
                self._k_frame = out[-1].seq + 1
                self._cv.notify_all()
        return out

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
        if not self.enable_imu:  # still advance, so that `finished` means "the flight is over"
            self._k_imu = max(self._k_imu, int((now - self._t0()) * self.imu_rate_hz / 1e9) + 1)
        out.extend(self._due_frames(now))
        self.imu_sent = self._k_imu if self.enable_imu else 0
        self.frames_sent += sum(isinstance(m, StereoFrame) for m in out)
        return out

    def messages(self) -> Iterator[Message]:
        """The whole (finite) stream in poll order, without the clock: for tests comparing recordings."""
        assert self.duration_ns is not None, "messages() needs duration_s"
        self.realtime = False
        self.start()
        while not self.finished:
            yield from self.poll()

    @property
    def finished(self) -> bool:
        end = self._end_ns()
        return end is not None and self.imu_t_ns(self._k_imu) > end and self.frame_t_ns(self._k_frame) > end

    def health(self) -> dict[str, Any]:
        return {"name": self.name, "state": "running" if self._started else "stopped", "profile": self.profile,
                "t0_ns": self.t0_ns, "frames": self.frames_sent, "imu": self.imu_sent,
                "frames_late": self.frames_late, "render_ms": round(self.render_ms, 1)}


class EurocSource(SensorSource):
    """A EuRoC dataset played as a live source. With `realtime` the stamps are moved onto the host clock
    (first sample = start time) and released at that pace, a gap in them longer than GAP_KEPT_S shortened to it;
    otherwise the dataset's stamps are kept and `batch` messages are released per poll()."""

    name = "euroc"

    def __init__(self, path: str | Path, *, realtime: bool = True, batch: int = 200) -> None:
        from vio.io.euroc import EurocDataset

        self.dataset = EurocDataset(path)
        self.realtime = realtime
        self.batch = batch
        self._it: Iterator[ImuSample | StereoFrame] | None = None
        self._pending: ImuSample | StereoFrame | None = None
        self._shift_ns = 0
        self._last_raw_ns: int | None = None  # realtime: the dataset's stamp of the last message taken
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
        if not self.realtime:
            return m
        if self._last_raw_ns is not None and m.t_ns - self._last_raw_ns > GAP_KEPT_S * 1e9:
            gap_ns = m.t_ns - self._last_raw_ns
            log.warning("euroc source: a gap of %.3g s in the recording before t=%d ns: shortened to %g s, not "
                        "waited out", gap_ns * 1e-9, m.t_ns, GAP_KEPT_S)
            self._shift_ns -= gap_ns - int(GAP_KEPT_S * 1e9)
        self._last_raw_ns = max(m.t_ns, self._last_raw_ns or m.t_ns)
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
