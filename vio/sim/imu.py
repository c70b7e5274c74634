"""IMU measurements from an analytic trajectory: exact signal + biases + white noise + motor vibration.

    gyro  = omega_body(t) + b_g(t) + n_g + vibration_g
    accel = R_world_body(t)^T (a_world(t) + [0, 0, g]) + b_a(t) + n_a + vibration_a

White noise per sample has sigma = density * sqrt(rate); the biases random-walk with steps
random_walk / sqrt(rate) (kalibr/EuRoC continuous-time units, `ImuNoise.discrete_sigmas`). Vibration is
what propeller imbalance adds: sinusoids at the motor frequency (~100-200 Hz, wandering slowly with thrust)
and its second harmonic, sampled at the IMU rate with no anti-alias filter (so they alias, as on real
MEMS parts), plus broadband noise. It is a measurement disturbance: the ground truth does not contain it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from vio.calibration import ImuNoise
from vio.sim.motion import Motion


@dataclass(frozen=True)
class ImuModel:
    """What to add to the exact IMU signal. `noise=None` gives exact measurements (tests)."""

    noise: ImuNoise | None = ImuNoise()
    gyro_bias0: tuple[float, float, float] = (0.0, 0.0, 0.0)  # rad/s at t = 0
    accel_bias0: tuple[float, float, float] = (0.0, 0.0, 0.0)  # m/s^2 at t = 0
    vibration_m_s2: float = 0.0  # accel vibration amplitude; the gyro gets 0.03 rad/s per m/s^2
    motor_hz: float = 150.0


@dataclass
class ImuStream:
    """Samples at times t_s (seconds from flight start) and the true biases at those times."""

    t_s: np.ndarray
    gyro: np.ndarray
    accel: np.ndarray
    gyro_bias: np.ndarray
    accel_bias: np.ndarray


def random_bias(rng: np.random.Generator, magnitude: float) -> np.ndarray:
    """A bias vector of the given norm in a random direction (so '--gyro-bias 0.08' means |b_g| = 0.08)."""
    v = rng.standard_normal(3)
    return magnitude * v / np.linalg.norm(v)


def _vibration(rng: np.random.Generator, t_s: np.ndarray, amplitude: float, motor_hz: float) -> np.ndarray:
    """(N, 6) gyro+accel vibration; zero amplitude gives zeros without consuming randomness."""
    n = len(t_s)
    if amplitude <= 0:
        return np.zeros((n, 6))
    # motor frequency wanders +-15 % with thrust; integrate it for a continuous phase
    f = motor_hz * (1 + 0.15 * np.sin(2 * np.pi * t_s / rng.uniform(3, 7) + rng.uniform(0, 2 * np.pi)))
    phase = 2 * np.pi * np.concatenate([[0.0], np.cumsum(0.5 * (f[1:] + f[:-1]) * np.diff(t_s))])
    gains = np.array([0.03, 0.03, 0.02, 0.6, 0.6, 1.0])  # gyro [rad/s] and accel [m/s^2] per unit amplitude
    out = np.zeros((n, 6))
    for harmonic, weight in ((1, 1.0), (2, 0.35)):
        offsets = rng.uniform(0, 2 * np.pi, 6)
        out += weight * np.sin(harmonic * phase[:, None] + offsets[None, :])
    out += 0.3 * rng.standard_normal((n, 6))  # broadband part
    return amplitude * gains * out


def synthesize(motion: Motion, t_s: np.ndarray, model: ImuModel, rng: np.random.Generator) -> ImuStream:
    """IMU samples at times `t_s` (uniform spacing assumed for the noise discretisation)."""
    t_s = np.asarray(t_s, dtype=float)
    n = len(t_s)
    gyro = motion.angular_velocity_body(t_s)
    accel = motion.specific_force_body(t_s)
    bg = np.tile(np.asarray(model.gyro_bias0, float), (n, 1))
    ba = np.tile(np.asarray(model.accel_bias0, float), (n, 1))
    if model.noise is not None:
        rate = 1.0 / float(np.median(np.diff(t_s))) if n > 1 else model.noise.rate_hz
        sig = ImuNoise(model.noise.gyroscope_noise_density, model.noise.gyroscope_random_walk,
                       model.noise.accelerometer_noise_density, model.noise.accelerometer_random_walk,
                       rate).discrete_sigmas()
        steps = rng.standard_normal((n, 6))
        steps[0] = 0.0
        bg += np.cumsum(steps[:, :3] * sig["gyro_bias_step"], axis=0)
        ba += np.cumsum(steps[:, 3:] * sig["accel_bias_step"], axis=0)
        white = rng.standard_normal((n, 6))
        gyro = gyro + white[:, :3] * sig["gyro"]
        accel = accel + white[:, 3:] * sig["accel"]
    vib = _vibration(rng, t_s, model.vibration_m_s2, model.motor_hz)
    return ImuStream(t_s, gyro + bg + vib[:, :3], accel + ba + vib[:, 3:], bg, ba)
