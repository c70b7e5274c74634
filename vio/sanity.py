"""Sensor sanity: is this IMU sample physically possible, and do these readings have the units we assume?

One implementation for the runtime (estimator: every sample, and at initialisation), the replay (a whole
IMU file before the flight starts) and `vio calib check`. A unit mistake (g instead of m/s^2, deg/s
instead of rad/s, mm instead of m) does not crash anything: it makes an estimator that drifts by metres
and reports itself healthy. So the checks name the likely mistake and the fix, instead of a bare "out of
range".
"""

from __future__ import annotations

import math

import numpy as np

GRAVITY_M_S2 = 9.80665
# Full-scale ranges of the IMUs drones carry (BMI270/ICM-42688: +-16 g, +-2000 deg/s); a reading beyond
# them is a broken sample, not motion.
MAX_ACCEL_M_S2 = 16 * GRAVITY_M_S2 * 1.1
MAX_GYRO_RAD_S = math.radians(2000.0) * 1.1
# Still: |mean accel| within this share of g (a tilted, biased, vibrating IMU still passes).
GRAVITY_TOLERANCE = 0.15
DEG = 180.0 / math.pi


def imu_sample_problem(gyro: np.ndarray, accel: np.ndarray) -> str | None:
    """Why one IMU sample cannot be used (None when it can)."""
    g = np.asarray(gyro, dtype=float)
    a = np.asarray(accel, dtype=float)
    if g.shape != (3,) or a.shape != (3,):
        return "not 3 gyro and 3 accel values"
    if not (np.all(np.isfinite(g)) and np.all(np.isfinite(a))):
        return "non-finite value"
    if float(np.max(np.abs(a))) > MAX_ACCEL_M_S2:
        # the units this reading most likely is in (one reading: a hint, the units check decides on many)
        norm = float(np.linalg.norm(a))
        hint = "; milli-g instead of m/s^2?" if 500 < norm < 2000 else \
            "; mm/s^2 instead of m/s^2?" if 5000 < norm < 20000 else ""
        return f"accel {float(np.max(np.abs(a))):.0f} m/s^2 beyond any IMU's range (+-16 g){hint}"
    if float(np.max(np.abs(g))) > MAX_GYRO_RAD_S:
        return (f"gyro {float(np.max(np.abs(g))):.0f} rad/s beyond any IMU's range (+-2000 deg/s); "
                "deg/s instead of rad/s?")
    return None


def accel_units_problem(mean_accel_norm: float) -> str | None:
    """The accelerometer's |mean| over a still span, against g: None when plausible, else the likely mistake."""
    n = float(mean_accel_norm)
    if not math.isfinite(n):
        return "accelerometer mean is not finite"
    if n < 0.05:
        return (f"accelerometer reads zero while still (|mean| {n:.3f} m/s^2): the IMU delivers no data "
                "(all-zero samples), or it is not connected")
    if abs(n - 1.0) < GRAVITY_TOLERANCE:
        return (f"accelerometer reads {n:.3f} while still: the data look like units of g, not m/s^2 "
                f"(multiply by {GRAVITY_M_S2})")
    if abs(n / 1000.0 - GRAVITY_M_S2) < GRAVITY_TOLERANCE * GRAVITY_M_S2:
        return f"accelerometer reads {n:.0f} while still: the data look like mm/s^2, not m/s^2"
    if abs(n / 1000.0 - 1.0) < GRAVITY_TOLERANCE:
        return f"accelerometer reads {n:.0f} while still: the data look like milli-g, not m/s^2"
    if abs(n - GRAVITY_M_S2) > GRAVITY_TOLERANCE * GRAVITY_M_S2:
        return (f"accelerometer |mean| {n:.2f} m/s^2 while still, expected about {GRAVITY_M_S2:.2f} "
                "(wrong units or scale, or the IMU was not still)")
    return None


def gyro_units_problem(gyro: np.ndarray, still: bool, max_bias_rad_s: float = 0.3) -> str | None:
    """Gyro samples (N, 3) over a span: None when plausible for rad/s, else the likely mistake.

    Still: the mean is the bias, which no MEMS gyro has above `max_bias_rad_s` on any axis (the largest component,
    as the back end's plausibility check and the start's bias check read it, so a start this passes is one they
    take). Moving or not: sustained
    rates above 20 rad/s (1150 deg/s) are not a drone's. The spread is not compared with the noise
    density: motors running on the ground make a gyro spread 20-100x its datasheet noise, which would read
    as deg/s and block the start."""
    g = np.asarray(gyro, dtype=float).reshape(-1, 3)
    if len(g) == 0 or not np.all(np.isfinite(g)):
        return None
    rates = np.linalg.norm(g, axis=1)
    if len(g) >= 20 and float(np.percentile(rates, 90)) > 20.0:
        return (f"gyro reads {float(np.percentile(rates, 90)):.0f} rad/s in 10 % of samples: no drone turns that "
                "fast; the data look like deg/s, not rad/s")
    if not still:
        return None
    bias = float(np.max(np.abs(g.mean(axis=0))))
    if bias > max_bias_rad_s:
        hint = "; the data look like deg/s, not rad/s" if bias / DEG < max_bias_rad_s else ""
        return f"gyro reads {bias:.3f} rad/s about one axis while still (a bias beyond {max_bias_rad_s} rad/s){hint}"
    return None


# Gyro against the camera (GyroScaleCheck). A right gyro's angle over a frame pair is the camera's give or take the
# bias's angle over the pair (the bias is unknown here, but its components never beyond [backend]
# max_gyro_bias_rad_s, so its norm never beyond sqrt(3) times that); a deg/s gyro reads 57x the camera, a dead one 0.
SCALE_FACTOR = 4.0  # "too much": beyond 4x the camera plus twice the bias's angle; "too little": under a quarter
SCALE_MIN_RAD = 0.03  # of what the camera turned beyond the bias's angle, which must be at least this much
SCALE_PAIRS = 12  # pairs that can tell, before a verdict ...
SCALE_AGREE = 0.75  # ... of which this share (of up to the last 3 x SCALE_PAIRS) must agree


class GyroScaleCheck:
    """The gyro's rotation over frame pairs against the rotation the camera sees (PnP or essential matrix).

    Why: a gyro in deg/s whose bias at rest is small passes every check at rest (its mean is the bias, under the
    plausible 0.3 rad/s), starts the estimator, and from the first turn on reads 57x the motion: a survey replay
    went 9 m off with poses going out for 6 s until a speed check reset it; a gyro that reads nothing (dead, or
    scaled as if it were deg/s) went 1.7 m off on an aggressive flight and never said so. The camera measures the
    same rotation in radians. Each pair is judged against the largest plausible bias, so that no right gyro can
    read "too much" or "too little" however biased; a pair where neither side can show (the camera barely turned,
    the gyro no more than a bias explains) is not counted. The verdict is final for the run (units do not
    change in flight)."""

    def __init__(self, max_bias_rad_s: float = 0.3) -> None:
        self.max_bias_rad_s = float(max_bias_rad_s) * math.sqrt(3.0)  # the norm of a bias at the limit on each axis
        # pairs that can show a gyro reading too much / too little: (it did, camera angle, gyro angle)
        self.high: list[tuple[bool, float, float]] = []
        self.low: list[tuple[bool, float, float]] = []
        self.problem: str | None = None

    @property
    def judged(self) -> bool:
        """Enough pairs that could show a gyro reading too much have, and none decided it did."""
        return self.problem is None and len(self.high) >= 3 * SCALE_PAIRS

    def add(self, camera_rad: float, gyro_rad: float, span_s: float) -> str | None:
        """One frame pair: its rotation angle from the camera and from the gyro integral over its `span_s`; returns
        the problem once decided. (Pairs of frames 4 apart come every frame, so 12 in a row see about 0.75 s; counting
        only pairs overlapping by half a span or less let a deg/s gyro fly on 1.6 s longer, to 7.7 m off, and missed a
        dead gyro on a 6 s flight: a misread rotation has to hold for 0.75 s to decide.)"""
        c, g = float(camera_rad), float(gyro_rad)
        if self.problem is not None or not (np.isfinite(c) and np.isfinite(g)):
            return self.problem
        bias = self.max_bias_rad_s * max(float(span_s), 0.0)
        if c >= SCALE_MIN_RAD or g > 2 * bias:
            self.high.append((g > SCALE_FACTOR * c + 2 * bias, c, g))
            self.problem = self._verdict(self.high, "high")
        if self.problem is None and c - bias >= SCALE_MIN_RAD:
            self.low.append((g < (c - bias) / SCALE_FACTOR, c, g))
            self.problem = self._verdict(self.low, "low")
        return self.problem

    @staticmethod
    def _verdict(pairs: list[tuple[bool, float, float]], side: str) -> str | None:
        recent = pairs[-3 * SCALE_PAIRS:]
        off = [(c, g) for wrong, c, g in recent if wrong]
        if len(recent) < SCALE_PAIRS or len(off) < SCALE_AGREE * len(recent):
            return None
        g, c = (float(np.median(x)) for x in zip(*[(g, c) for c, g in off]))
        ratio = float(np.median([g / max(c, 1e-9) for c, g in off]))
        if side == "low":
            hint = "a dead gyro, or a scale error in the IMU driver (rad/s taken for deg/s?)"
        elif 30 < ratio < 110:
            hint = "deg/s instead of rad/s (57.3x)?"
        elif c < SCALE_MIN_RAD:  # the camera barely turned: the gyro's angle may be mostly a bias in the wrong units
            hint = "more than any bias explains: deg/s instead of rad/s, or a scale error in the IMU driver"
        else:
            hint = "a scale error in the IMU driver or its configuration (raw counts?)"
        return (f"the gyro turns {ratio:.2g}x what the camera sees ({g:.3g} rad against {c:.3g} rad, the median of "
                f"{len(off)} of the last {len(recent)} frame pairs that could tell): {hint}")


def baseline_units_problem(baseline_m: float) -> str | None:
    """Stereo baseline |t_cam1_cam0|: drone stereo heads have 2 cm..60 cm (OAK-D 7.5 cm, EuRoC 11 cm)."""
    b = float(baseline_m)
    if not math.isfinite(b) or b <= 0:
        return f"stereo baseline {b} m is not a positive length"
    if 5.0 <= b <= 1000.0:
        return f"stereo baseline {b:.1f} m: the extrinsics look like millimetres, not metres (divide by 1000)"
    if b > 2.0:
        return f"stereo baseline {b:.2f} m is implausible for a drone's stereo camera"
    if b < 0.005:
        return f"stereo baseline {b * 1000:.2f} mm is too short for stereo depth (wrong units?)"
    return None


def lever_arm_units_problem(t_body_cam_m: float) -> str | None:
    """|t_body_cam0|: the camera sits within a metre of the IMU on any drone."""
    d = float(t_body_cam_m)
    if not math.isfinite(d):
        return "camera-IMU translation is not finite"
    if d >= 5.0:
        return f"camera-IMU translation {d:.1f} m: the extrinsics look like millimetres, not metres"
    if d > 1.0:
        return f"camera-IMU translation {d:.2f} m is implausible (the camera sits within a metre of the IMU)"
    return None
