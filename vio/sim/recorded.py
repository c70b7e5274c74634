"""Flights whose motion and IMU are a real recording: images rendered along recorded ground truth.

The simulator's IMU is a model (white noise, random-walk biases, a sinusoidal motor vibration); a flying
drone's IMU is not: EuRoC V1_01's reads ~59x its datasheet's white noise, with structure no model here has.
`vio simulate OUT --imu-from EUROC_DIR` keeps the recording's raw IMU samples and its ground truth (pose,
velocity, biases) and renders the simulator's stereo images along that ground truth, so a replay meets a
real IMU against a known truth. What the recording's ground truth gets wrong (Vicon noise, its alignment
with the IMU) reaches the estimator as a disagreement between IMU and images, as it would in flight; it
is also the truth the replay is scored against, so read such figures as "real IMU, ideal-but-rendered
images", not as EuRoC results.

The cameras are EuRoC's VI-sensor rig (`vio.sim.default_calibration`) mounted on the recording's IMU
frame, which is exact for EuRoC recordings (the same ADIS16448 and rig); for another rig the images are
still consistent with the motion, only the mount is EuRoC's. The trajectory is turned about the vertical
and moved horizontally to where it is farthest from the scene's walls and boxes (`_placement`; its height
kept: EuRoC's z is above the floor) and must stay 0.3 m clear of them. The variant's image settings
(blur, noise, exposure, plain walls, dropped frames) apply; its IMU settings do not (the IMU is the
recording's).
"""

from __future__ import annotations

import dataclasses
import logging
from pathlib import Path

import numpy as np

from vio import VioError
from vio.calibration import ImuNoise, StereoCalibration
from vio.geometry import make_T
from vio.sim import _R_FLU_EUROC, default_calibration
from vio.sim.imu import ImuStream
from vio.sim.scene import Scene
from vio.trajectory import Trajectory, interp_columns

log = logging.getLogger(__name__)

CLEARANCE_M = 0.3  # the recorded path must stay this far from the scene's walls and boxes
IMU_MARGIN_NS = 50_000_000
GT_MAX_STEP_NS = 250_000_000  # a longer step in the ground truth is a dropout, not a pose rate (EuRoC: 5 or 50 ms)


@dataclasses.dataclass
class RecordedMotion:
    """The recording's ground truth, interpolated at any time in its span (seconds from the flight start).

    Offers what `vio.sim.generate` asks of a `Motion`: pose, position, velocity, body rates, yaw rate."""

    name: str
    truth: Trajectory  # stamps in ns from the flight start; positions already moved into the scene
    v_world: np.ndarray  # (N, 3) at the truth's stamps
    rate_t_s: np.ndarray  # IMU times [s], for the body rates
    rate_body: np.ndarray  # (M, 3) gyro minus the recorded gyro bias [rad/s]

    def _at(self, t_s: np.ndarray) -> Trajectory:
        t = np.atleast_1d(np.asarray(t_s, dtype=float))
        t_ns = np.clip(np.round(t * 1e9).astype(np.int64), self.truth.t_ns[0], self.truth.t_ns[-1])
        return self.truth.interpolate(t_ns)

    def pose(self, t_s: np.ndarray) -> np.ndarray:
        shape = np.shape(t_s)
        return self._at(t_s).poses().reshape(*shape, 4, 4)

    def position(self, t_s: np.ndarray) -> np.ndarray:
        shape = np.shape(t_s)
        return self._at(t_s).p.reshape(*shape, 3)

    def velocity(self, t_s: np.ndarray) -> np.ndarray:
        t = np.asarray(t_s, dtype=float)
        return interp_columns(t, self.truth.t_s, self.v_world)

    def angular_velocity_body(self, t_s: np.ndarray) -> np.ndarray:
        t = np.asarray(t_s, dtype=float)
        return interp_columns(t, self.rate_t_s, self.rate_body)

    def yaw_rate(self, t_s: np.ndarray) -> np.ndarray:
        """Rate about the world's vertical (EuRoC's body x points up: Euler yaw is ill-defined there)."""
        R = self._at(t_s).rotations()
        w = self.angular_velocity_body(np.atleast_1d(np.asarray(t_s, dtype=float)))
        return np.einsum("nj,nj->n", R[:, 2, :], w)


@dataclasses.dataclass
class Recording:
    """A EuRoC-format recording's IMU samples, ground truth and IMU noise densities."""

    path: Path
    imu_t_ns: np.ndarray
    gyro: np.ndarray
    accel: np.ndarray
    truth: Trajectory
    v_world: np.ndarray
    gyro_bias: np.ndarray
    accel_bias: np.ndarray
    noise: ImuNoise


def read_recording(path: str | Path) -> Recording:
    """IMU, ground truth (with velocities; biases where the file has them) and IMU yaml of a EuRoC folder."""
    from vio.io.euroc import find_mav0, read_groundtruth_csv, read_imu_csv, read_imu_yaml

    mav0 = find_mav0(path)
    imu_csv, gt_csv = mav0 / "imu0" / "data.csv", mav0 / "state_groundtruth_estimate0" / "data.csv"
    for f, what in ((imu_csv, "IMU samples"), (gt_csv, "ground truth")):
        if not f.is_file():
            raise VioError(f"--imu-from {path}: {f} is missing; a recorded flight needs its {what}")
    imu = read_imu_csv(imu_csv)
    gt = read_groundtruth_csv(gt_csv)
    traj = gt.trajectory
    if len(traj) < 2:
        raise VioError(f"--imu-from {path}: the ground truth has {len(traj)} pose(s); need a trajectory")
    v = gt.v_world if gt.v_world is not None else np.gradient(traj.p, traj.t_s, axis=0)
    zeros = np.zeros((len(traj), 3))
    yaml_path = mav0 / "imu0" / "sensor.yaml"
    noise = read_imu_yaml(yaml_path) if yaml_path.is_file() else ImuNoise()
    return Recording(mav0.parent, imu.t_ns, imu.gyro, imu.accel, traj, v,
                     gt.gyro_bias if gt.gyro_bias is not None else zeros,
                     gt.accel_bias if gt.accel_bias is not None else zeros, noise)


def _rig_on_recorded_imu(cfg, noise: ImuNoise) -> StereoCalibration:
    """EuRoC's stereo rig at the requested size, mounted on the recording's (EuRoC) IMU frame."""
    calib = default_calibration(cfg.camera_model, cfg.width, cfg.height, cfg.rate_hz, noise,
                                int(round(cfg.time_offset_ms * 1e6)))
    T_euroc_flu = make_T(_R_FLU_EUROC.T, np.zeros(3))  # default_calibration mounts the rig on a FLU body
    cams = [dataclasses.replace(c, T_body_cam=T_euroc_flu @ c.T_body_cam) for c in (calib.cam0, calib.cam1)]
    return dataclasses.replace(calib, cam0=cams[0], cam1=cams[1])


def _rot_z(yaw: float) -> np.ndarray:
    c, s = np.cos(yaw), np.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _placement(scene: Scene, p: np.ndarray, step_m: float = 0.25) -> tuple[float, np.ndarray, float]:
    """Where the recorded path fits the scene best: a turn about the vertical (a multiple of 90 deg: the
    IMU, in the body frame, does not see it) and a horizontal shift (heights kept: EuRoC's z is above the
    floor), chosen for the largest clearance from walls and boxes. Returns (yaw, shift, clearance)."""
    pts = p[:: max(1, len(p) // 400)]
    lo, hi = scene.lo[0], scene.hi[0]
    best = (0.0, np.zeros(3), -np.inf)
    for yaw in (0.0, np.pi / 2, np.pi, 3 * np.pi / 2):
        q = pts @ _rot_z(yaw).T
        xs = np.arange(lo[0] - q[:, 0].min(), hi[0] - q[:, 0].max() + 1e-9, step_m)
        ys = np.arange(lo[1] - q[:, 1].min(), hi[1] - q[:, 1].max() + 1e-9, step_m)
        for x in xs:
            for y in ys:
                shift = np.array([x, y, 0.0])
                margin = best[2] if np.isfinite(best[2]) else 0.0
                while scene.contains(q + shift, margin=margin + 0.05).all() and margin < 5.0:
                    margin += 0.05
                if scene.contains(q + shift, margin=margin).all() and margin > best[2]:
                    best = (yaw, shift, margin)
    return best


def build_recorded(cfg, scene: Scene) -> tuple:
    """The recording-specific parts of a `vio.sim.generate.Simulation` from `cfg.imu_from` (cfg already
    resolved), the path placed in `scene`: (cfg with the duration the recording allows, calibration, motion,
    IMU stream)."""
    rec = read_recording(cfg.imu_from)
    span_s = (rec.truth.t_ns[-1] - rec.truth.t_ns[0]) * 1e-9
    start_s = cfg.recorded_start_s
    if start_s >= span_s - 1.0:
        raise VioError(f"--imu-from {cfg.imu_from}: --recorded-start {start_s:g} s leaves less than 1 s of its "
                       f"{span_s:.1f} s of ground truth")
    duration_s = cfg.duration_s
    if start_s + duration_s > span_s:
        duration_s = float(np.floor((span_s - start_s) * cfg.rate_hz) / cfg.rate_hz)
        log.warning("the recording has %.1f s of ground truth after %.1f s: the flight is %.2f s long, not %.1f s",
                    span_s - start_s, start_s, duration_s, cfg.duration_s)
        cfg = dataclasses.replace(cfg, duration_s=duration_s)
    t0_ns = int(rec.truth.t_ns[0] + round(start_s * 1e9))
    t1_ns = t0_ns + int(round(duration_s * 1e9))
    keep = (rec.truth.t_ns >= t0_ns - 100_000_000) & (rec.truth.t_ns <= t1_ns + 100_000_000)  # 0.1 s margin
    # 50 ms of IMU beyond the frames at both ends: the first and last frame must lie inside the IMU's span
    sel = (rec.imu_t_ns >= t0_ns - IMU_MARGIN_NS) & (rec.imu_t_ns <= t1_ns + IMU_MARGIN_NS)
    imu_sel = rec.imu_t_ns[sel]
    # it must reach both ends too: an IMU that stopped early (a gap, a log cut short) passed, and the dataset had
    # 30 s of frames over 1.5 s of IMU
    if len(imu_sel) < 2 or imu_sel[0] > t0_ns or imu_sel[-1] < t1_ns or np.any(np.diff(imu_sel) > 50_000_000):
        span = "" if len(imu_sel) < 2 else (f" (its samples there run from {(imu_sel[0] - t0_ns) * 1e-9 + start_s:.2f}"
                                            f" s to {(imu_sel[-1] - t0_ns) * 1e-9 + start_s:.2f} s)")
        raise VioError(f"--imu-from {cfg.imu_from}: the IMU does not cover {start_s:g}-{start_s + duration_s:g} s "
                       f"of the ground truth without gaps over 50 ms{span}")
    inside = rec.truth.t_ns[keep]
    steps = np.diff(inside)
    if len(steps) and steps.max() > GT_MAX_STEP_NS:
        # interpolated across in a straight line, the images were rendered along a path the IMU never flew
        k = int(np.argmax(steps))
        raise VioError(f"--imu-from {cfg.imu_from}: the ground truth has a gap of {steps[k] * 1e-9:.3g} s at "
                       f"{(inside[k] - rec.truth.t_ns[0]) * 1e-9:.2f} s (a motion-capture dropout?): the images would "
                       "be rendered along a straight line across it; choose a span without it (--recorded-start, "
                       "--duration)")
    yaw, shift, margin = _placement(scene, rec.truth.p[keep])
    if margin < CLEARANCE_M:
        raise VioError(f"--imu-from {cfg.imu_from}: the recorded path does not fit in the {cfg.scene} scene "
                       f"{CLEARANCE_M} m clear of its walls and boxes (best placement {margin:.2f} m); "
                       "try another --scene")
    R = make_T(_rot_z(yaw), shift)
    truth = Trajectory.from_poses(rec.truth.t_ns[keep] - t0_ns, R @ rec.truth.poses()[keep])
    v_world = rec.v_world[keep] @ _rot_z(yaw).T
    imu_t_s = (rec.imu_t_ns[sel] - t0_ns) * 1e-9
    t_truth_all = (rec.truth.t_ns - t0_ns) * 1e-9
    bg = interp_columns(imu_t_s, t_truth_all, rec.gyro_bias)
    ba = interp_columns(imu_t_s, t_truth_all, rec.accel_bias)
    imu = ImuStream(imu_t_s, rec.gyro[sel], rec.accel[sel], bg, ba)
    motion = RecordedMotion(f"recorded:{rec.path.name}", truth, v_world, imu_t_s, rec.gyro[sel] - bg)
    calib = _rig_on_recorded_imu(cfg, rec.noise)
    log.info("recorded flight from %s: %.1f s from %.1f s on, %d IMU samples; path turned %d deg about the "
             "vertical and moved by %s m, %.2f m clear of the scene", rec.path, duration_s, start_s, len(imu_t_s),
             round(np.degrees(yaw)), shift.round(2).tolist(), margin)
    return cfg, calib, motion, imu
