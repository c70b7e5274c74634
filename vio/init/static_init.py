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
from vio.geometry import gravity_aligned_rotation, make_T

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
    log.info("static initialisation: |a| %.3f m/s^2, gyro bias (%.4f %.4f %.4f) rad/s over %.2f s",
             float(np.linalg.norm(a_mean)), *g_mean, span_s)
    return InitialState(int(t_init_ns), make_T(R_wb, np.zeros(3)), np.zeros(3), g_mean, np.zeros(3), "static")
