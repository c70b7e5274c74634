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


def combined_params(noise: ImuNoise, noise_scale: float = 1.0,
                    gravity_m_s2: float = GRAVITY_M_S2) -> gtsam.PreintegrationCombinedParams:
    """CombinedImuFactor parameters for a z-up world from kalibr-style noise densities.

    `noise_scale` multiplies every density: datasheet/Allan values are optimistic for an IMU on a
    vibrating airframe, so real data usually needs a factor of a few.
    """
    p = gtsam.PreintegrationCombinedParams.MakeSharedU(gravity_m_s2)
    s2 = noise_scale ** 2
    eye = np.eye(3)
    p.setGyroscopeCovariance(eye * noise.gyroscope_noise_density ** 2 * s2)
    p.setAccelerometerCovariance(eye * noise.accelerometer_noise_density ** 2 * s2)
    p.setBiasOmegaCovariance(eye * noise.gyroscope_random_walk ** 2 * s2)
    p.setBiasAccCovariance(eye * noise.accelerometer_random_walk ** 2 * s2)
    p.setIntegrationCovariance(eye * 1e-8)
    return p
