"""Smooth flight trajectories with analytic derivatives, so that the simulated IMU is exact.

A trajectory is a closed curve in a "phase" variable sigma: position M(sigma) and Z-Y-X Euler angles
A(sigma) are sums of sinusoids. Time maps onto phase through sigma(t) = integral of a speed factor s(t)
that is 0 while the vehicle sits still at the start, rises along a septic smoothstep (zero first to third
derivative at both ends) and then stays 1. Hence

    p(t) = M(sigma),  v(t) = M'(sigma) s,  a(t) = M''(sigma) s^2 + M'(sigma) s',
    angles(t) = A(sigma),  angle rates = A'(sigma) s,

so the vehicle starts exactly at rest and the whole flight stays on the curve M, whose bounds are known
from the amplitudes (this is how profiles keep the cameras away from walls and boxes).
All functions take a time array t_s (seconds from the start of the flight) and are vectorised over it.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.spatial.transform import Rotation

from vio import VioError
from vio.geometry import GRAVITY_M_S2

PROFILES = ("hover", "survey", "aggressive", "mapping", "laps", "out-and-back")

# Region the body may occupy in the default room (see scene.default_scene): every camera stays >= 1 m from
# walls, floor, ceiling and boxes. Profiles are built to fit inside it; tests check that they do.
FLIGHT_BOX_LO = np.array([-2.6, -1.8, 1.1])
FLIGHT_BOX_HI = np.array([2.6, 1.8, 2.8])


@dataclass(frozen=True)
class Sinusoids:
    """f(sigma) = base + rate sigma + sum_k amp_k sin(omega_k sigma + phase_k), with its first two derivatives.

    `rate` is for a heading that keeps turning one way (laps); position terms leave it 0 (bounded curve)."""

    base: float
    amp: tuple[float, ...] = ()
    omega: tuple[float, ...] = ()
    phase: tuple[float, ...] = ()
    rate: float = 0.0

    def eval(self, sigma: np.ndarray, order: int) -> np.ndarray:
        s = np.asarray(sigma, dtype=float)
        out = np.full_like(s, self.base if order == 0 else 0.0)
        if order == 0:
            out += self.rate * s
        elif order == 1:
            out += self.rate
        for a, w, ph in zip(self.amp, self.omega, self.phase):
            x = w * s + ph
            if order == 0:
                out += a * np.sin(x)
            elif order == 1:
                out += a * w * np.cos(x)
            else:
                out -= a * w * w * np.sin(x)
        return out

    @property
    def bound(self) -> float:
        """Largest |f - base| the curve can reach."""
        if self.rate:
            raise ValueError("a term with a rate is unbounded")
        return float(np.sum(np.abs(self.amp)))


def _smoothstep(x: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Septic smoothstep S'(x) on [0, 1], its integral S and derivative S'', clamped outside."""
    x = np.clip(x, 0.0, 1.0)
    s = x**4 * (35 - 84 * x + 70 * x**2 - 20 * x**3)
    integral = x**5 * (7 - 14 * x + 10 * x**2 - 2.5 * x**3)
    ds = 140 * x**3 * (1 - x) ** 3
    return integral, s, ds


@dataclass(frozen=True)
class Motion:
    """A flight: position terms (x, y, z), Euler angle terms (roll, pitch, yaw), still start and ramp."""

    name: str
    pos_terms: tuple[Sinusoids, Sinusoids, Sinusoids]  # x, y, z
    ang_terms: tuple[Sinusoids, Sinusoids, Sinusoids]  # roll, pitch, yaw (Z-Y-X, world z up)
    duration_s: float
    still_s: float = 2.0
    ramp_s: float = 2.0
    meta: dict = field(default_factory=dict)

    # -- time warp -------------------------------------------------------------------------------------
    def _phase(self, t_s: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """sigma(t), s(t) = dsigma/dt and s'(t)."""
        t = np.asarray(t_s, dtype=float)
        x = (t - self.still_s) / self.ramp_s
        integral, s, ds = _smoothstep(x)
        sigma = self.ramp_s * integral + np.maximum(t - self.still_s - self.ramp_s, 0.0)
        return sigma, s, ds / self.ramp_s

    def _angles(self, t_s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        sigma, s, _ = self._phase(t_s)
        ang = np.stack([f.eval(sigma, 0) for f in self.ang_terms], axis=-1)
        rate = np.stack([f.eval(sigma, 1) for f in self.ang_terms], axis=-1) * s[..., None]
        return ang, rate

    # -- public API ------------------------------------------------------------------------------------
    def position(self, t_s: np.ndarray) -> np.ndarray:
        """Body position in the world, (..., 3) metres."""
        sigma, _, _ = self._phase(t_s)
        return np.stack([f.eval(sigma, 0) for f in self.pos_terms], axis=-1)

    def velocity(self, t_s: np.ndarray) -> np.ndarray:
        """Body velocity in the world, (..., 3) m/s."""
        sigma, s, _ = self._phase(t_s)
        return np.stack([f.eval(sigma, 1) for f in self.pos_terms], axis=-1) * s[..., None]

    def acceleration(self, t_s: np.ndarray) -> np.ndarray:
        """Body acceleration in the world (gravity not included), (..., 3) m/s^2."""
        sigma, s, ds = self._phase(t_s)
        d1 = np.stack([f.eval(sigma, 1) for f in self.pos_terms], axis=-1)
        d2 = np.stack([f.eval(sigma, 2) for f in self.pos_terms], axis=-1)
        return d2 * (s**2)[..., None] + d1 * ds[..., None]

    def rotation(self, t_s: np.ndarray) -> np.ndarray:
        """R_world_body, (..., 3, 3)."""
        ang, _ = self._angles(t_s)
        shape = ang.shape[:-1]
        R = Rotation.from_euler("ZYX", ang.reshape(-1, 3)[:, ::-1]).as_matrix()
        return R.reshape(*shape, 3, 3)

    def pose(self, t_s: np.ndarray) -> np.ndarray:
        """T_world_body, (..., 4, 4)."""
        t = np.asarray(t_s, dtype=float)
        T = np.zeros(t.shape + (4, 4))
        T[..., :3, :3] = self.rotation(t)
        T[..., :3, 3] = self.position(t)
        T[..., 3, 3] = 1.0
        return T

    def angular_velocity_body(self, t_s: np.ndarray) -> np.ndarray:
        """Body angular rate in the body frame (what a perfect gyro reads), (..., 3) rad/s.

        For R = Rz(yaw) Ry(pitch) Rx(roll): omega_body = E(roll, pitch) @ (roll', pitch', yaw')."""
        ang, rate = self._angles(t_s)
        roll, pitch = ang[..., 0], ang[..., 1]
        droll, dpitch, dyaw = rate[..., 0], rate[..., 1], rate[..., 2]
        sr, cr, sp, cp = np.sin(roll), np.cos(roll), np.sin(pitch), np.cos(pitch)
        return np.stack([droll - dyaw * sp,
                         dpitch * cr + dyaw * cp * sr,
                         -dpitch * sr + dyaw * cp * cr], axis=-1)

    def yaw_rate(self, t_s: np.ndarray) -> np.ndarray:
        """d(yaw)/dt in rad/s (for summaries)."""
        return self._angles(t_s)[1][..., 2]

    def specific_force_body(self, t_s: np.ndarray) -> np.ndarray:
        """What a perfect accelerometer reads: R_world_body^T (a_world + [0, 0, g]), (..., 3) m/s^2."""
        a = self.acceleration(t_s) + np.array([0.0, 0.0, GRAVITY_M_S2])
        return np.einsum("...ji,...j->...i", self.rotation(t_s), a)

    def position_bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """Axis-aligned box that contains the whole trajectory (from the amplitudes, not sampled)."""
        base = np.array([f.base for f in self.pos_terms])
        r = np.array([f.bound for f in self.pos_terms])
        return base - r, base + r


def _terms(rng: np.random.Generator, base: float, spec: list[tuple[float, float]], jitter: float = 0.1) -> Sinusoids:
    """Sinusoids from (amplitude, omega) pairs; amplitude and omega jittered by +-jitter, random phases."""
    amp = tuple(a * (1 - jitter * rng.random()) for a, _ in spec)  # only shrink: bounds stay valid
    omega = tuple(w * (1 + jitter * (2 * rng.random() - 1)) for _, w in spec)
    phase = tuple(2 * np.pi * rng.random() for _ in spec)
    return Sinusoids(base, amp, omega, phase)


_TWO_PI = 2 * np.pi
# (amplitude, angular frequency in phase units rad/s) per axis; position in m, angles in rad.
_PROFILE_SPECS: dict[str, dict[str, list[tuple[float, float]]]] = {
    # small slow drift around a point plus a few-Hz wobble like a real hover
    "hover": {
        "x": [(0.15, 0.31), (0.04, 1.1), (0.0015, _TWO_PI * 3.1)],
        "y": [(0.15, 0.27), (0.04, 0.9), (0.0015, _TWO_PI * 2.7)],
        "z": [(0.06, 0.23), (0.001, _TWO_PI * 3.7)],
        "roll": [(0.02, 0.7), (0.004, _TWO_PI * 4.3)],
        "pitch": [(0.02, 0.6), (0.004, _TWO_PI * 3.9)],
        "yaw": [(0.10, 0.2), (0.003, _TWO_PI * 2.3)],
    },
    # slow lissajous over the room (~0.5 m/s), gentle turns (< 0.4 rad/s)
    "survey": {
        "x": [(2.3, 0.19)],
        "y": [(1.5, 0.31)],
        "z": [(0.35, 0.15), (0.05, 0.7)],
        "roll": [(0.03, 0.45), (0.01, 1.3)],
        "pitch": [(0.03, 0.38), (0.01, 1.1)],
        "yaw": [(0.8, 0.25), (0.25, 0.55)],
    },
    # fast figure-eights, 1-2 m/s, yaw rate up to ~2 rad/s, visible tilt
    "aggressive": {
        "x": [(2.4, 0.55), (0.1, 2.1)],
        "y": [(1.6, 0.85), (0.1, 1.7)],
        "z": [(0.55, 0.6), (0.1, 2.3)],
        "roll": [(0.15, 0.9), (0.05, 3.1)],
        "pitch": [(0.15, 1.1), (0.05, 2.7)],
        "yaw": [(1.0, 1.3), (0.25, 2.9)],
    },
}
# a mapping pass: the survey's path with the heading swept through +-180 deg (0.1 rad/s, yaw rate < 0.35 rad/s),
# so that the map sees the room from every direction (a survey holds its heading within +-60 deg of a random
# one, and a later flight may look the other way)
_PROFILE_SPECS["mapping"] = {**_PROFILE_SPECS["survey"], "yaw": [(np.pi, 0.1), (0.1, 0.55)]}
_CENTRE_Z = {"hover": 1.5, "survey": 1.75, "aggressive": 1.8, "mapping": 1.75, "laps": 1.75, "out-and-back": 1.75}


def _loop_course(name: str, rng: np.random.Generator) -> tuple[tuple[Sinusoids, ...], Sinusoids]:
    """Position terms and heading of the two loop-closure courses, whose terms share one phase (so they are
    built here rather than from independent random sinusoids like the other profiles):

    - laps: an ellipse 4.6 m x 3 m round the room at ~0.7 m/s (a lap every ~20 s), clockwise or not by seed,
      heading turning with the course (the camera looks roughly where it flies), height drifting +-0.3 m;
    - out-and-back: 4.6 m along x and back, turning round at each end (the heading swings through 180 deg
      while the vehicle stops there), at a random y, so the way back sees the room from the other side."""
    w = 0.31 * (1 + 0.1 * (2 * rng.random() - 1))
    ph = 2 * np.pi * rng.random()
    z = _terms(rng, _CENTRE_Z[name], [(0.3, 0.13), (0.04, 0.7)])
    if name == "laps":
        turn = 1.0 if rng.random() < 0.5 else -1.0
        x = Sinusoids(0.0, (2.3,), (w,), (ph,))
        y = Sinusoids(0.0, (1.5 * turn,), (w,), (ph + np.pi / 2,))
        # travel direction of (A sin th, turn B cos th) is about -turn * th for A ~ B: turn with it
        yaw = Sinusoids(-turn * ph, (0.1,), (0.55,), (2 * np.pi * rng.random(),), rate=-turn * w)
        return (x, y, z), yaw
    w *= 0.85  # ~0.6 m/s on the straight
    x = Sinusoids(0.0, (2.3,), (w,), (ph,))
    y = _terms(rng, float(rng.uniform(-1.0, 1.0)), [(0.15, 0.23)])
    # heading 0 while x grows (cos th > 0), pi on the way back: pi/2 - pi/2 cos th
    yaw = Sinusoids(np.pi / 2, (np.pi / 2, 0.05), (w, 0.55), (ph - np.pi / 2, 2 * np.pi * rng.random()))
    return (x, y, z), yaw


def make_profile(name: str, duration: float, seed: int = 0, still_s: float = 2.0, ramp_s: float = 2.0) -> Motion:
    """A flight of the named profile (PROFILES), randomised (phases, +-10 % rates,
    start heading) by `seed`. `still_s` seconds at rest come first, then `ramp_s` seconds of speed-up."""
    if name not in PROFILES:
        raise VioError(f"unknown flight profile {name!r}; expected one of {list(PROFILES)}")
    if not (duration > 0):
        raise VioError(f"flight duration must be positive, got {duration}")
    if still_s < 0 or ramp_s <= 0:
        raise VioError(f"still start must be >= 0 and ramp > 0 s, got {still_s}, {ramp_s}")
    rng = np.random.default_rng([seed, 7411])
    if name in ("laps", "out-and-back"):
        pos, yaw = _loop_course(name, rng)
        wobble = _PROFILE_SPECS["survey"]  # the survey's roll and pitch
        ang = (_terms(rng, 0.0, wobble["roll"]), _terms(rng, 0.0, wobble["pitch"]), yaw)
        return Motion(name, pos, ang, float(duration), float(still_s), float(ramp_s), meta={"seed": seed})
    spec = _PROFILE_SPECS[name]
    centre = np.array([0.0, 0.0, _CENTRE_Z[name]])
    if name == "hover":  # hover somewhere in the middle part of the room
        centre[:2] = rng.uniform(FLIGHT_BOX_LO[:2] + 0.5, FLIGHT_BOX_HI[:2] - 0.5)
    pos = tuple(_terms(rng, float(c), spec[k]) for c, k in zip(centre, "xyz"))
    yaw0 = float(rng.uniform(-np.pi, np.pi))
    ang = (_terms(rng, 0.0, spec["roll"]), _terms(rng, 0.0, spec["pitch"]), _terms(rng, yaw0, spec["yaw"]))
    return Motion(name, pos, ang, float(duration), float(still_s), float(ramp_s), meta={"seed": seed})


class MountedMotion:
    """A vehicle's motion seen from an IMU mounted at its origin turned by R_vehicle_imu: poses, rates and
    specific force in the IMU's axes (what the estimator calls the body), positions and velocities unchanged."""

    def __init__(self, motion: Motion, R_vehicle_imu: np.ndarray) -> None:
        self.vehicle = motion
        self.R = np.asarray(R_vehicle_imu, float)

    def __getattr__(self, name: str):  # position, velocity, acceleration, yaw_rate (the vehicle's), bounds
        return getattr(self.vehicle, name)

    def rotation(self, t_s: np.ndarray) -> np.ndarray:
        return self.vehicle.rotation(t_s) @ self.R

    def pose(self, t_s: np.ndarray) -> np.ndarray:
        T = self.vehicle.pose(t_s).copy()
        T[..., :3, :3] = T[..., :3, :3] @ self.R
        return T

    def angular_velocity_body(self, t_s: np.ndarray) -> np.ndarray:
        return self.vehicle.angular_velocity_body(t_s) @ self.R  # R^T w, row-wise

    def specific_force_body(self, t_s: np.ndarray) -> np.ndarray:
        return self.vehicle.specific_force_body(t_s) @ self.R
