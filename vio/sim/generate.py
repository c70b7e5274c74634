"""Write a synthetic flight as a EuRoC ASL dataset with exact ground truth.

Clocks: the truth (and the IMU) run on one clock; a frame exposed at true time t gets the camera stamp
t_cam = t - time_offset, so the dataset obeys the calibration's t_imu = t_cam + time_offset_ns (recorded in
mav0/kestrel.yaml). A positive `time_offset_ms` therefore stamps images *earlier* than the IMU samples
taken at the same instant. With `time_offset_drift_ms` the offset drifts as a slow sinusoid around that
value (USB cameras, serial IMUs); with `stamp_jitter_ms` each frame is stamped late by a random delay, as
a camera stamped on arrival at the host is (exponential: mostly short, now and then long; its mean is taken
off, as the calibration's latency). The calibration states the mean offset and `<out>/time_offset_truth.csv`
the true offset of every frame. The run's settings go to `<out>/simulation.yaml`.

Calibration error (`calib_error`): the images are rendered with the true calibration but the dataset's
sensor.yaml files state a perturbed one (vio.sim.perturbed_calibration); the truth is kept beside the
dataset in `<out>/calibration_truth.yaml` (the project's calibration format), where a replay does not
look for it. `stereo_error_px` states cam1's cx that far off instead (or as well): a disparity bias.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import shutil
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import yaml

from vio import VioError
from vio.calibration import ImuNoise, StereoCalibration, save_calibration
from vio.geometry import make_T, rot_to_quat_wxyz
from vio.sim import IMU_MOUNTS, default_calibration, perturbed_calibration
from vio.sim.imu import ImuModel, ImuStream, random_bias, synthesize
from vio.sim.motion import PROFILES, Motion, MountedMotion, make_profile
from vio.sim.render import CameraRenderer, Photometric
from vio.sim.scene import ALIASING_ROOM_ONLY, SCENES, Scene, make_scene
from vio.types import ImuSample, StereoFrame

log = logging.getLogger(__name__)

T0_NS = 1_600_000_000_000_000_000  # stamp of the flight start: EuRoC-like epoch nanoseconds

# Named presets of the realism knobs; explicit SimConfig/CLI values override them.
VARIANTS: dict[str, dict[str, float]] = {
    "clean": dict(gyro_bias=0.005, accel_bias=0.05, vibration=0.0, plain_fraction=0.0, exposure_ms=0.0,
                  image_noise=0.0, gain_drift=0.0, gain_jumps_hz=0.0, drop_frames=0.0),
    "realistic": dict(gyro_bias=0.02, accel_bias=0.1, vibration=0.3, plain_fraction=0.15, exposure_ms=4.0,
                      image_noise=1.5, gain_drift=0.1, gain_jumps_hz=0.05, drop_frames=0.0),
    "hard": dict(gyro_bias=0.08, accel_bias=0.3, vibration=1.0, plain_fraction=0.4, exposure_ms=12.0,
                 image_noise=4.0, gain_drift=0.25, gain_jumps_hz=0.3, drop_frames=0.05),
}


@dataclass(frozen=True)
class SimConfig:
    """Everything that defines a simulated flight; equal configs give byte-identical datasets.

    Realism fields left at None take the value of `variant` (see VARIANTS)."""

    profile: str = "survey"
    duration_s: float = 30.0
    seed: int = 0
    variant: str = "realistic"
    rate_hz: float = 20.0  # camera
    imu_rate_hz: float = 200.0
    still_start_s: float = 2.0
    time_offset_ms: float = 0.0  # t_imu = t_cam + offset
    camera_model: str = "radtan"
    width: int = 752
    height: int = 480
    texels_per_m: float = 200.0
    imu_noise: bool = True  # white noise and bias random walk with ImuNoise() (EuRoC) densities
    gyro_bias: float | None = None  # |b_g| at start [rad/s]
    accel_bias: float | None = None  # |b_a| at start [m/s^2]
    vibration: float | None = None  # motor vibration amplitude in accel [m/s^2]
    plain_fraction: float | None = None  # share of the room's wall area painted plain (low texture)
    exposure_ms: float | None = None  # motion blur from the motion during this exposure; 0 = none
    image_noise: float | None = None  # Gaussian pixel noise sigma [grey levels]
    gain_drift: float | None = None  # amplitude of slow log-gain drift
    gain_jumps_hz: float | None = None  # rate of sudden exposure jumps
    drop_frames: float | None = None  # probability that a frame loses left, right or both images
    aliasing_period_m: float | None = None  # the room's walls, floor, ceiling repeat every this many metres
    scene_seed: int | None = None  # room texture and boxes; None: `seed` (a second flight in the same room: set it)
    scene: str = "room"  # "room" (10 m x 8 m), "hall" (25 m x 20 m, dim, far walls) or "shelves" (aliasing)
    calib_error: float = 0.0  # scale of the error in the written calibration (1: 0.1 deg, 2 mm, 0.5 px)
    stereo_error_px: float = 0.0  # cam1's cx stated this far off in the written calibration (a drifted stereo pair)
    right_dropouts: tuple[tuple[float, float], ...] = ()  # (start_s, length_s): the right camera gives no image
    time_offset_drift_ms: float = 0.0  # amplitude of a sinusoidal drift of the time offset around time_offset_ms
    time_offset_period_s: float = 60.0  # period of that drift
    stamp_jitter_ms: float = 0.0  # frames stamped late by a random delay of this mean (and spread), mean taken off
    # the camera's transfer stalls now and then (a USB camera): every stamp_stall_every_s on average (Poisson), for
    # stamp_stall_ms; the frames due in a stall arrive together at its end, 1 ms apart (0: no stalls)
    stamp_stall_every_s: float = 0.0
    stamp_stall_ms: float = 0.0
    imu_mount: str = "flu"  # the IMU's axes on the vehicle (vio.sim.IMU_MOUNTS): "flu" square, "oak" x up
    imu_from: str | None = None  # a EuRoC recording: its IMU and ground truth replace profile and IMU model
    recorded_start_s: float = 0.0  # with imu_from: where in the recording's ground truth the flight starts

    def resolved(self) -> SimConfig:
        """Copy with the variant's values filled in and every value checked (VioError naming the field)."""
        if self.variant not in VARIANTS:
            raise VioError(f"simulate: unknown variant {self.variant!r}; expected one of {list(VARIANTS)}")
        if self.profile not in PROFILES:
            raise VioError(f"simulate: unknown profile {self.profile!r}; expected one of {list(PROFILES)}")
        filled = {k: v for k, v in VARIANTS[self.variant].items() if getattr(self, k) is None}
        cfg = dataclasses.replace(self, **filled)
        checks = {"duration_s": (0.1, 3600), "rate_hz": (1, 200), "imu_rate_hz": (10, 5000), "still_start_s": (0, 600),
                  "time_offset_ms": (-1000, 1000), "width": (16, 4096), "height": (16, 4096),
                  "texels_per_m": (10, 1000), "gyro_bias": (0, 1), "accel_bias": (0, 5), "vibration": (0, 20),
                  "plain_fraction": (0, 1), "exposure_ms": (0, 100), "image_noise": (0, 100),
                  "gain_drift": (0, 2), "gain_jumps_hz": (0, 10), "drop_frames": (0, 1)}
        for name, (lo, hi) in checks.items():
            v = getattr(cfg, name)
            if not (lo <= v <= hi):
                raise VioError(f"simulate: {name} = {v} is outside [{lo}, {hi}]")
        if cfg.imu_mount not in IMU_MOUNTS:
            raise VioError(f"simulate: unknown IMU mount {cfg.imu_mount!r}; expected one of {list(IMU_MOUNTS)}")
        if cfg.imu_mount != "flu" and cfg.imu_from is not None:
            raise VioError("simulate: an IMU mount applies to the simulated IMU only; --imu-from keeps the "
                           "recording's (EuRoC's IMU has its x axis up already)")
        if cfg.scene not in SCENES:
            raise VioError(f"simulate: unknown scene {cfg.scene!r}; expected one of {list(SCENES)}")
        if cfg.scene != "room" and cfg.aliasing_period_m:  # said before any work, as an option's mistake (exit 2)
            raise VioError(ALIASING_ROOM_ONLY)
        for name, (lo, hi) in {"calib_error": (0, 20), "stereo_error_px": (-20, 20), "time_offset_drift_ms": (0, 100),
                               "time_offset_period_s": (1, 36000), "stamp_jitter_ms": (0, 20),
                               "stamp_stall_ms": (0, 2000)}.items():
            if not (lo <= getattr(cfg, name) <= hi):
                raise VioError(f"simulate: {name} = {getattr(cfg, name)} is outside [{lo}, {hi}]")
        for start, length in cfg.right_dropouts:
            if not (start >= 0 and length > 0):
                raise VioError(f"simulate: right dropout {start}:{length} needs start >= 0 and length > 0 s")
        if (cfg.stamp_stall_ms > 0) != (cfg.stamp_stall_every_s > 0) or 0 < cfg.stamp_stall_every_s < 0.5 \
                or not math.isfinite(cfg.stamp_stall_every_s):
            raise VioError(f"simulate: stamp stalls need both a mean interval of at least 0.5 s and a length, got "
                           f"every {cfg.stamp_stall_every_s} s for {cfg.stamp_stall_ms} ms")
        if not cfg.recorded_start_s >= 0:  # NaN too
            raise VioError(f"simulate: recorded_start_s = {cfg.recorded_start_s} is negative or not a number")
        # numpy seeds are whole numbers >= 0 (-1 ended in "internal error: ValueError"); a repeat period that is not
        # a length in metres (NaN, inf: an internal error; -1: tiles of 8 texels, unsaid) (a review's finding)
        for name in ("seed", "scene_seed"):
            v = getattr(cfg, name)
            if v is not None and not (isinstance(v, (int, np.integer)) and v >= 0):
                raise VioError(f"simulate: {name} = {v} is not a whole number >= 0")
        if cfg.aliasing_period_m is not None and not 0 <= cfg.aliasing_period_m <= 1000:
            raise VioError(f"simulate: aliasing_period_m = {cfg.aliasing_period_m} is outside [0, 1000] (metres; 0: "
                           "no repetition)")
        # delays are capped at half a period (keep the cap rare: 8 % of frames at a fifth); over a tenth the
        # frame clock no longer restamps (its spread start bound), which is how a camera that jitters that much is flown
        if cfg.stamp_jitter_ms * 1e-3 * cfg.rate_hz > 0.2:
            raise VioError(f"simulate: stamp_jitter_ms = {cfg.stamp_jitter_ms} is over a fifth of the frame period "
                           f"({200 / cfg.rate_hz:.1f} ms at {cfg.rate_hz:g} Hz)")
        if cfg.imu_rate_hz < cfg.rate_hz:
            raise VioError(f"simulate: imu_rate_hz {cfg.imu_rate_hz} is below the camera rate {cfg.rate_hz}")
        return cfg


@dataclass
class SimSummary:
    path: Path
    frames: int
    imu_samples: int
    duration_s: float
    path_length_m: float
    max_speed_m_s: float
    max_yaw_rate_rad_s: float
    dropped_left: int
    dropped_right: int

    def line(self) -> str:
        return (f"{self.path}: {self.frames} stereo frames, {self.imu_samples} IMU samples, {self.duration_s:.1f} s, "
                f"path {self.path_length_m:.1f} m, max speed {self.max_speed_m_s:.2f} m/s, "
                f"max yaw rate {self.max_yaw_rate_rad_s:.2f} rad/s, dropped left/right images "
                f"{self.dropped_left}/{self.dropped_right}")


@dataclass
class Simulation:
    """The pieces of a resolved config, for callers that want truth without writing files."""

    config: SimConfig
    calibration: StereoCalibration
    motion: Motion
    scene: Scene
    imu: ImuStream
    frame_t_s: np.ndarray  # true exposure times (IMU clock), seconds from start
    written_calibration: StereoCalibration  # what the dataset's sensor.yaml states (calibration unless calib_error)

    def time_offset_ns(self, t_s: np.ndarray) -> np.ndarray:
        """True camera-IMU offset (t_imu = t_cam + offset) of frames exposed at true times t_s; with stamp
        jitter, t_s must be the flight's frame times (the k-th time gets the k-th frame's delay)."""
        c = self.config
        drift = c.time_offset_drift_ms * 1e6 * np.sin(2 * np.pi * np.asarray(t_s, float) / c.time_offset_period_s)
        if c.stamp_jitter_ms > 0 or c.stamp_stall_ms > 0:  # a later stamp is a smaller offset
            drift = drift - self.stamp_delays_ns(len(t_s))
        return np.round(self.calibration.time_offset_ns + drift).astype(np.int64)

    def stamp_delays_ns(self, n: int) -> np.ndarray:
        """The first n frames' arrival delays beyond the mean: exponential with mean and spread
        `stamp_jitter_ms`, capped at half a frame period so stamps keep their order, minus their mean."""
        c = self.config
        mean_ns = c.stamp_jitter_ms * 1e6
        delay = np.minimum(np.random.default_rng([c.seed, 7]).exponential(mean_ns, n), 0.5e9 / c.rate_hz)
        if c.stamp_stall_ms > 0:  # stalls on top: the frames due in one arrive together at its end, in order
            rng = np.random.default_rng([c.seed, 8])
            t = np.arange(n) * (1e9 / c.rate_hz)
            arrival = t + delay
            start = rng.exponential(c.stamp_stall_every_s * 1e9)
            while start < arrival[-1]:
                hit = np.flatnonzero((arrival >= start) & (arrival < start + c.stamp_stall_ms * 1e6))
                arrival[hit] = start + c.stamp_stall_ms * 1e6 + np.arange(len(hit)) * 1e6
                start += c.stamp_stall_ms * 1e6 + rng.exponential(c.stamp_stall_every_s * 1e9)
            for k in range(1, n):  # a frame due right after a stall queues behind its burst, 1 ms apart
                arrival[k] = max(arrival[k], arrival[k - 1] + 1e6)
            delay = arrival - t
        return delay - mean_ns

    def right_dropped(self, t_s: float) -> bool:
        return any(start <= t_s < start + length for start, length in self.config.right_dropouts)


def _grid(duration_s: float, rate_hz: float) -> np.ndarray:
    """Sample times [s] of a rate over the duration, rounded to whole ns so file stamps are exact."""
    n = int(np.floor(duration_s * rate_hz + 1e-9)) + 1
    return np.round(np.arange(n) * (1e9 / rate_hz)) * 1e-9


def build(cfg: SimConfig) -> Simulation:
    """Resolve the config and make calibration, trajectory, scene and IMU (no rendering yet)."""
    cfg = cfg.resolved()
    scene = make_scene(cfg.scene, cfg.seed if cfg.scene_seed is None else cfg.scene_seed, cfg.texels_per_m,
                       cfg.plain_fraction, cfg.aliasing_period_m)
    if cfg.imu_from is not None:
        from vio.sim.recorded import build_recorded

        cfg, calib, motion, imu = build_recorded(cfg, scene)
    else:
        rng = np.random.default_rng([cfg.seed, 1])
        noise = ImuNoise(rate_hz=cfg.imu_rate_hz)
        calib = default_calibration(cfg.camera_model, cfg.width, cfg.height, cfg.rate_hz, noise,
                                    int(round(cfg.time_offset_ms * 1e6)))
        motion = make_profile(cfg.profile, cfg.duration_s, cfg.seed, still_s=cfg.still_start_s)
        model = ImuModel(noise if cfg.imu_noise else None, tuple(random_bias(rng, cfg.gyro_bias)),
                         tuple(random_bias(rng, cfg.accel_bias)), cfg.vibration)
        imu = synthesize(motion, _grid(cfg.duration_s, cfg.imu_rate_hz), model, np.random.default_rng([cfg.seed, 2]))
        if cfg.imu_mount != "flu":
            # the same flight, samples and noise, read in the IMU's axes (the motor vibration stays on the
            # vehicle's); the rig stays on the vehicle: T_imu_cam = T_imu_vehicle T_vehicle_cam
            R = IMU_MOUNTS[cfg.imu_mount]
            imu = ImuStream(imu.t_s, imu.gyro @ R, imu.accel @ R, imu.gyro_bias @ R, imu.accel_bias @ R)
            motion = MountedMotion(motion, R)
            calib = dataclasses.replace(calib, **{k: dataclasses.replace(
                c, T_body_cam=make_T(R.T, np.zeros(3)) @ c.T_body_cam) for k, c in
                (("cam0", calib.cam0), ("cam1", calib.cam1))})
    written = calib if cfg.calib_error == 0 else \
        perturbed_calibration(calib, cfg.calib_error, np.random.default_rng([cfg.seed, 6]))
    if cfg.stereo_error_px:  # a disparity bias: every stereo depth off, which nothing but the stereo pair shows
        written = dataclasses.replace(written, cam1=dataclasses.replace(written.cam1,
                                                                        cx=written.cam1.cx + cfg.stereo_error_px))
    return Simulation(cfg, calib, motion, scene, imu, _grid(cfg.duration_s, cfg.rate_hz), written)


def _prepare_out(out: Path, overwrite: bool) -> None:
    mav0 = out / "mav0"
    if mav0.exists() and any(mav0.iterdir()):
        if not overwrite:
            raise VioError(f"{out}: already holds a dataset; pass --overwrite to replace it")
        if not (out / "simulation.yaml").is_file():  # a real recording: --overwrite replaced it (a QA sweep)
            raise VioError(f"{out}: holds a recording that is not a simulated flight (no simulation.yaml): not "
                           "replaced, even with --overwrite; give another folder or delete it yourself")
        shutil.rmtree(mav0)  # stale images of the old run would otherwise stay listed nowhere but on disk
    out.mkdir(parents=True, exist_ok=True)


def simulate(out: str | Path, cfg: SimConfig = SimConfig(), overwrite: bool = False,
             progress: bool = False) -> SimSummary:
    """Render and write the flight to `out` (EuRoC ASL layout, with ground truth at the IMU rate)."""
    from vio.io.euroc import EurocWriter
    from vio.io.outputs import folder_problem

    out = Path(out)
    problem = folder_problem(out, made=True)  # a file at OUT was "OUT: File exists"; said before the flight is built
    if problem:
        raise VioError(f"{out}: cannot write the dataset: {problem}")
    sim = build(cfg)
    cfg = sim.config
    _prepare_out(out, overwrite)
    settings = dataclasses.asdict(cfg)
    settings["right_dropouts"] = [list(w) for w in cfg.right_dropouts]  # safe_dump has no tuples
    (out / "simulation.yaml").write_text(yaml.safe_dump(settings, sort_keys=False))
    if cfg.calib_error > 0 or cfg.stereo_error_px:
        save_calibration(sim.calibration, out / "calibration_truth.yaml")
    calib, motion, imu = sim.calibration, sim.motion, sim.imu
    cams = [(CameraRenderer(c, sim.scene), c.T_body_cam) for c in (calib.cam0, calib.cam1)]
    photo_rng = np.random.default_rng([cfg.seed, 3])
    photometric = [Photometric(photo_rng, cfg.duration_s, cfg.gain_drift, cfg.gain_jumps_hz,
                               noise_sigma=cfg.image_noise, offset=off) for off in (0.0, 0.04)]
    drop_rng = np.random.default_rng([cfg.seed, 4])
    imu_ns = T0_NS + np.round(imu.t_s * 1e9).astype(np.int64)
    T_wb = motion.pose(sim.frame_t_s)
    v_w = motion.velocity(sim.frame_t_s)
    w_b = motion.angular_velocity_body(sim.frame_t_s)
    exposure_s = cfg.exposure_ms * 1e-3
    dropped = [0, 0]
    bar = None
    if progress:
        from tqdm import tqdm
        bar = tqdm(total=len(sim.frame_t_s), unit="frame", desc="rendering", leave=False)
    offsets_ns = sim.time_offset_ns(sim.frame_t_s)
    if cfg.time_offset_drift_ms > 0 or cfg.stamp_jitter_ms > 0 or cfg.stamp_stall_ms > 0:
        (out / "time_offset_truth.csv").write_text("#t_cam_ns,time_offset_ns\n" + "".join(
            f"{T0_NS + round(t * 1e9) - o},{o}\n" for t, o in zip(sim.frame_t_s, offsets_ns)))
    with EurocWriter(out, sim.written_calibration, overwrite=True) as writer:
        i_imu = 0
        for k, t in enumerate(sim.frame_t_s):
            t_cam = int(T0_NS + round(t * 1e9) - offsets_ns[k])
            while i_imu < len(imu_ns) and imu_ns[i_imu] <= t_cam:
                writer.write_imu(ImuSample(int(imu_ns[i_imu]), imu.gyro[i_imu], imu.accel[i_imu]))
                i_imu += 1
            images = []
            for (renderer, T_bc), photo in zip(cams, photometric):
                img, depth, _ = renderer.render(T_wb[k] @ T_bc)
                if exposure_s > 0:
                    R_wc = T_wb[k, :3, :3] @ T_bc[:3, :3]
                    v_cam_w = v_w[k] + T_wb[k, :3, :3] @ np.cross(w_b[k], T_bc[:3, 3])
                    flow = renderer.pixel_flow(depth, R_wc.T @ v_cam_w, T_bc[:3, :3].T @ w_b[k])
                    img = renderer.motion_blur(img, flow, exposure_s)
                images.append(photo.apply(img, t))
            if cfg.drop_frames > 0 and drop_rng.random() < cfg.drop_frames:
                which = int(drop_rng.integers(3))  # 0: left, 1: right, 2: both
                if which in (0, 2):
                    images[0] = None
                    dropped[0] += 1
                if which in (1, 2):
                    images[1] = None
                    dropped[1] += 1
            if images[1] is not None and sim.right_dropped(float(t)):
                images[1] = None
                dropped[1] += 1
            if images[0] is not None or images[1] is not None:
                writer.write_frame(StereoFrame(t_cam, images[0], images[1], seq=k))
            if bar is not None:
                bar.update(1)
        for i in range(i_imu, len(imu_ns)):
            writer.write_imu(ImuSample(int(imu_ns[i]), imu.gyro[i], imu.accel[i]))
        _write_truth(writer, imu_ns, motion, imu)
    if bar is not None:
        bar.close()
    p = motion.position(imu.t_s)
    summary = SimSummary(out, len(sim.frame_t_s), len(imu_ns), float(imu.t_s[-1]),
                         float(np.linalg.norm(np.diff(p, axis=0), axis=1).sum()),
                         float(np.linalg.norm(motion.velocity(imu.t_s), axis=1).max()),
                         float(np.abs(motion.yaw_rate(imu.t_s)).max()), dropped[0], dropped[1])
    log.debug("simulated %s", summary.line())  # the CLI prints the line itself
    return summary


def _write_truth(writer, imu_ns: np.ndarray, motion: Motion, imu: ImuStream) -> None:
    """Ground truth at every IMU sample: p, q_wxyz, v, gyro and accel bias (EuRoC column order)."""
    T = motion.pose(imu.t_s)
    q = rot_to_quat_wxyz(T[:, :3, :3])
    v = motion.velocity(imu.t_s)
    for i, t in enumerate(imu_ns):
        writer.write_groundtruth(int(t), T[i, :3, 3], q[i], v[i], imu.gyro_bias[i], imu.accel_bias[i])
