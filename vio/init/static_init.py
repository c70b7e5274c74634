"""Static initialisation from a still IMU window.

While the vehicle stands still the accelerometer measures only gravity (plus bias) and the gyro only
its bias. So the mean specific force gives roll and pitch, the mean rate gives the gyro bias, and the
velocity is zero. Yaw and position are free: we start at the origin with zero yaw. The accelerometer
bias is not separable from a tilt here; it starts at zero and the smoother estimates it once moving.

Stillness is judged on 50 ms block means, not raw samples: motor and airframe vibration make single
samples noisy (EuRoC V1_01 shows 0.45 m/s^2 std standing still) while the vehicle does not move.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from vio.config import InitConfig
from vio.frontend.gyro import body_to_camera_rotation
from vio.frontend.undistort import rotate_px
from vio.geometry import gravity_aligned_rotation, make_T, so3_exp
from vio.types import FeatureFrame

log = logging.getLogger(__name__)

BLOCK_S = 0.05


@dataclass(frozen=True)
class InitialState:
    """Start state of the estimator at `t_ns` (IMU clock) and how it was found."""

    t_ns: int
    T_world_body: np.ndarray
    v_world: np.ndarray
    gyro_bias: np.ndarray
    accel_bias: np.ndarray
    method: str  # "static" or "moving"


def _block_means(t_ns: np.ndarray, x: np.ndarray) -> np.ndarray:
    """Means of consecutive BLOCK_S blocks, leaving out partial blocks."""
    edges = ((t_ns - t_ns[0]) // int(BLOCK_S * 1e9)).astype(np.int64)
    n = int(edges[-1]) + 1
    sums = np.zeros((n, x.shape[1]))
    np.add.at(sums, edges, x)
    counts = np.bincount(edges, minlength=n)
    full = counts >= max(1, counts.max() // 2)  # a partial block of one or two samples is only noise
    return sums[full] / counts[full, None]


def is_still(t_ns: np.ndarray, gyro: np.ndarray, accel: np.ndarray, cfg: InitConfig) -> bool:
    """True when the block-averaged gyro and accel stay within the configured spreads."""
    if len(t_ns) < 4:
        return False
    g = _block_means(t_ns, gyro)
    a = _block_means(t_ns, accel)
    if len(g) < 2:
        return False
    g_std = float(np.max(np.std(g, axis=0)))
    a_std = float(np.max(np.std(a, axis=0)))
    return g_std < cfg.static_gyro_std_rad_s and a_std < cfg.static_accel_std_m_s2


def static_initialize(t_ns: np.ndarray, gyro: np.ndarray, accel: np.ndarray, t_init_ns: int,
                      cfg: InitConfig, headings: tuple = ()) -> InitialState | None:
    """Initial state at `t_init_ns` from IMU samples of the window before it, or None if not still
    or the window is not yet covered. `headings`: body axes for the start yaw after body x
    (geometry.gravity_aligned_rotation)."""
    if len(t_ns) < 2:
        return None
    span_s = (t_ns[-1] - t_ns[0]) * 1e-9
    if span_s < 0.9 * cfg.static_window_s or not is_still(t_ns, gyro, accel, cfg):
        return None
    g_mean = gyro.mean(axis=0)
    a_mean = accel.mean(axis=0)
    R_wb = gravity_aligned_rotation(a_mean, headings)
    # a candidate: the estimator may still refuse it (a turn, a bias jump), every frame; the start says its bias
    log.debug("static initialisation: |a| %.3f m/s^2, gyro bias (%.4f %.4f %.4f) rad/s over %.2f s",
             float(np.linalg.norm(a_mean)), *g_mean, span_s)
    return InitialState(int(t_init_ns), make_T(R_wb, np.zeros(3)), np.zeros(3), g_mean, np.zeros(3), "static")


@dataclass(frozen=True)
class RotationReading:
    """What the tracks of a still window say about the gyro's mean rate (`rate_is_turn`)."""

    rate_rad_s: float  # |gyro mean|: the bias a static start would take
    span_s: float  # time between the two frames compared
    predicted_px: float  # median track motion that rate would cause were it a real rotation
    moved_px: float  # median track motion measured (the still hypothesis' residual)
    turn_residual_px: float  # median distance of the tracks from where that rotation puts them

    @property
    def rate_is_turn(self) -> bool:
        """The tracks follow the rotation better than they stay put: the mean rate is the vehicle turning."""
        return self.turn_residual_px < self.moved_px


def rotation_reading(old: FeatureFrame, new: FeatureFrame, gyro_mean: np.ndarray, T_body_cam: np.ndarray,
                     K: np.ndarray, min_shared: int = 10) -> RotationReading | None:
    """Compare the tracks of two frames with where a body turn at `gyro_mean` would have moved them.

    A slow steady turn (a hovering vehicle braking, a pilot yawing gently) is still to the IMU's spread test and
    under the per-frame flow gate at low resolution (0.05 rad/s is 0.6 px a frame at fx 190 and 15 Hz), so a
    start in flight took the turn for a gyro bias (an ArduPilot SITL restart: 0.049 rad/s). Over the whole window
    the turn moves the tracks by pixels while a bias moves nothing, and which of the two the tracks follow answers
    the question. Pure rotation: the old pixels through the turn's infinite homography (`rotate_px`, as the front
    end's gyro prior predicts tracks). None when the frames share fewer than `min_shared` tracks (no judgement)."""
    _, i0, i1 = np.intersect1d(old.ids, new.ids, return_indices=True)
    if len(i0) < min_shared:
        return None
    dt = (new.t_ns - old.t_ns) * 1e-9
    R_new_old = body_to_camera_rotation(so3_exp(np.asarray(gyro_mean, float) * dt), T_body_cam).T
    pred, ok = rotate_px(K, R_new_old, old.uv0[i0])
    if np.count_nonzero(ok) < min_shared:
        return None
    pred, u0, u1 = pred[ok], old.uv0[i0][ok], new.uv0[i1][ok]
    return RotationReading(float(np.linalg.norm(gyro_mean)), dt,
                           float(np.median(np.linalg.norm(pred - u0, axis=1))),
                           float(np.median(np.linalg.norm(u1 - u0, axis=1))),
                           float(np.median(np.linalg.norm(u1 - pred, axis=1))))
