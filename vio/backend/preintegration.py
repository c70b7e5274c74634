"""GTSAM pre-integration between keyframes (the IMU samples come from vio.imu_buffer.ImuBuffer).

The continuous-time noise densities of the calibration (kalibr units) become GTSAM's continuous
covariances by squaring; GTSAM then scales them by the integration interval itself. Samples are
integrated piecewise between consecutive stamps with the mean of the two end readings (trapezoid), and
interpolated at interval boundaries, so that a keyframe stamp that falls between IMU samples (camera-IMU
time offset, dropped frames) costs no accuracy.
"""

from __future__ import annotations

import logging

import gtsam
import numpy as np

from vio.calibration import ImuNoise
from vio.geometry import GRAVITY_M_S2

log = logging.getLogger(__name__)


def combined_params(noise: ImuNoise, noise_scale: float = 1.0, gravity_m_s2: float = GRAVITY_M_S2, *,
                    white_scale: np.ndarray | None = None) -> gtsam.PreintegrationCombinedParams:
    """CombinedImuFactor parameters for a z-up world from kalibr-style noise densities.

    `noise_scale` multiplies every density: datasheet/Allan values are optimistic for an IMU on a
    vibrating airframe, so real data usually needs a factor of a few. `white_scale` (6,: gyro x y z,
    accel x y z) replaces it for the white-noise densities, per axis (`measured_white_scale`); the bias
    random walks keep `noise_scale`.
    """
    p = gtsam.PreintegrationCombinedParams.MakeSharedU(gravity_m_s2)
    s2 = noise_scale ** 2
    w2 = np.full(6, s2) if white_scale is None else np.asarray(white_scale, float) ** 2
    eye = np.eye(3)
    p.setGyroscopeCovariance(np.diag(w2[:3]) * noise.gyroscope_noise_density ** 2)
    p.setAccelerometerCovariance(np.diag(w2[3:]) * noise.accelerometer_noise_density ** 2)
    p.setBiasOmegaCovariance(eye * noise.gyroscope_random_walk ** 2 * s2)
    p.setBiasAccCovariance(eye * noise.accelerometer_random_walk ** 2 * s2)
    p.setIntegrationCovariance(eye * 1e-8)
    return p


def measured_white_scale(noise: ImuNoise, t_ns: np.ndarray, gyro: np.ndarray, accel: np.ndarray) -> np.ndarray | None:
    """(6,) per-axis ratio of the white noise in these samples to the calibration's density (gyro, accel).

    A smooth motion hardly changes its third differences at IMU rates (a 1.5 Hz swing of 3 rad/s moves
    them by 3e-4 rad/s at 200 Hz, where first differences would be 0.14 rad/s: 60x the gyro's noise), white
    noise does (sqrt(20) sigma), so their robust spread (median absolute deviation) / sqrt(20) is the
    noise, against the calibration's per-sample sigma. On a flying drone it is mostly motor and airframe
    vibration, which the datasheet densities leave out: EuRoC's own recordings read 7-27x (gyro) and 19-51x
    (accel) their sensor.yaml on the same axes, hovering or not. None with fewer than 40 samples."""
    if len(t_ns) < 40:
        return None
    rate = 1e9 / float(np.median(np.diff(t_ns)))
    x = np.hstack([gyro, accel])
    d = np.diff(x, n=3, axis=0)
    sigma = 1.4826 * np.median(np.abs(d - np.median(d, axis=0)), axis=0) / np.sqrt(20.0)
    calib = np.repeat([noise.gyroscope_noise_density, noise.accelerometer_noise_density], 3) * np.sqrt(rate)
    return sigma / calib
