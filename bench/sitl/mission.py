"""The closed-loop mission: a time-parameterised path in the autopilot's local NED frame, and the pymavlink
calls that fly it in GUIDED (arm, take off, stream position targets, land).

Why a time-parameterised path: the harness must say where the vehicle *should* be at every instant (the
blackout check: "within 1 m of where it should be"), and a GUIDED vehicle fed SET_POSITION_TARGET_LOCAL_NED
with position and velocity feed-forward follows such a path with a small lag; the path itself is a pure
function, so its maths is tested without a SITL.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass

import numpy as np

log = logging.getLogger(__name__)

# SET_POSITION_TARGET_LOCAL_NED type_mask: use position and velocity, ignore acceleration, yaw and yaw rate
# (bits 6-8 accel, 10 yaw, 11 yaw rate): the vehicle keeps its heading, so vision yaw is not exercised by turns.
TYPE_MASK_POS_VEL = 0b0000_1101_1100_0000


@dataclass(frozen=True)
class Path:
    """Waypoints (N, 3) [m, NED, relative to the autopilot's origin] flown at `speed_m_s`, starting at t = 0,
    with `dwell_s` of hover at each waypoint."""

    waypoints: np.ndarray
    speed_m_s: float = 0.5
    dwell_s: float = 2.0

    def __post_init__(self) -> None:
        w = np.asarray(self.waypoints, dtype=float).reshape(-1, 3)
        if len(w) < 2 or self.speed_m_s <= 0:
            raise ValueError("a path needs at least two waypoints and a positive speed")
        object.__setattr__(self, "waypoints", w)

    def _schedule(self) -> tuple[np.ndarray, np.ndarray]:
        """(start of each leg's motion, end of its motion) [s]; leg k goes from waypoint k to k+1."""
        legs = np.linalg.norm(np.diff(self.waypoints, axis=0), axis=1) / self.speed_m_s
        starts, ends, t = [], [], 0.0
        for d in legs:
            t += self.dwell_s
            starts.append(t)
            t += d
            ends.append(t)
        return np.array(starts), np.array(ends)

    @property
    def duration_s(self) -> float:
        return float(self._schedule()[1][-1] + self.dwell_s)

    def target(self, t_s: float) -> tuple[np.ndarray, np.ndarray]:
        """(position, velocity) the vehicle should have at t_s after the path's start."""
        starts, ends = self._schedule()
        w = self.waypoints
        for k, (a, b) in enumerate(zip(starts, ends)):
            if t_s < a:
                return w[k].copy(), np.zeros(3)
            if t_s < b:
                s = (t_s - a) / (b - a)
                return w[k] + s * (w[k + 1] - w[k]), (w[k + 1] - w[k]) / (b - a)
        return w[-1].copy(), np.zeros(3)

    def positions(self, t_s: np.ndarray) -> np.ndarray:
        return np.array([self.target(float(t))[0] for t in np.atleast_1d(t_s)])


def box(side_n_m: float = 3.0, side_e_m: float = 2.4, alt_m: float = 1.5, laps: int = 1, **kw) -> Path:
    """A rectangle centred on the take-off point at `alt_m`, flown `laps` times, ending over the take-off point."""
    n, e, d = side_n_m / 2, side_e_m / 2, -alt_m
    lap = [(n, -e, d), (n, e, d), (-n, e, d), (-n, -e, d)]
    return Path(np.array([(0.0, 0.0, d)] + lap * laps + [(n, -e, d), (0.0, 0.0, d)]), **kw)


def figure_eight(radius_n_m: float = 1.5, radius_e_m: float = 1.0, alt_m: float = 1.5, points: int = 24,
                 laps: int = 1, **kw) -> Path:
    """A lemniscate (n = a sin s, e = b sin 2s) through the take-off point, as `points` waypoints per lap."""
    s = np.linspace(0.0, 2 * np.pi * laps, points * laps + 1)
    w = np.stack([radius_n_m * np.sin(s), radius_e_m * np.sin(2 * s), np.full_like(s, -alt_m)], axis=1)
    return Path(w, dwell_s=kw.pop("dwell_s", 0.0), **kw)


def chain(*paths: Path) -> Path:
    """Paths flown one after the other (each must start where the previous one ends)."""
    w = [paths[0].waypoints] + [p.waypoints[1:] for p in paths[1:]]
    return Path(np.concatenate(w), speed_m_s=paths[0].speed_m_s, dwell_s=paths[0].dwell_s)


# ------------------------------------------------------------------------------------------- flying it

# These only send and sleep: the harness's Recorder thread is the link's one reader and keeps the
# autopilot's own mode and armed state (`state.mode`, `state.armed`, from component 1's HEARTBEAT only:
# ArduPilot routes Kestrel's HEARTBEAT onto every link, so mavutil's "newest heartbeat" may be ours).
COPTER_MODES = {"GUIDED": 4, "LAND": 9}  # ArduCopter custom_mode numbers


def set_mode(conn, state, mode: str, timeout_s: float = 10.0) -> None:
    """Switch the autopilot's flight mode and wait until its HEARTBEAT shows it."""
    mode_id = COPTER_MODES[mode]
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        conn.mav.set_mode_send(conn.target_system, 1, mode_id)  # MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
        time.sleep(1.0)
        if state.mode == mode_id:
            return
    raise TimeoutError(f"autopilot did not enter {mode} within {timeout_s} s")


def arm_and_takeoff(conn, state, alt_m: float, timeout_s: float = 60.0) -> None:
    """GUIDED, arm (retrying while the pre-arm checks still wait for the EKF), MAV_CMD_NAV_TAKEOFF, and wait
    for the climb. Why wait: ArduCopter disarms again a few seconds after arming when the takeoff does not
    start (seen once in SITL, the command lost or refused), and a mission flown on the ground measures
    nothing; so arm and take off again until the local altitude shows the climb, or give up."""
    set_mode(conn, state, "GUIDED")
    deadline = time.monotonic() + timeout_s
    while True:
        while not state.armed:
            if time.monotonic() > deadline:
                raise TimeoutError("autopilot refused to arm (see its STATUSTEXT in the report)")
            conn.mav.command_long_send(conn.target_system, 1, 400, 0, 1, 0, 0, 0, 0, 0, 0)  # COMPONENT_ARM_DISARM
            time.sleep(2.0)
        conn.mav.command_long_send(conn.target_system, 1, 22, 0, 0, 0, 0, float("nan"), 0, 0, alt_m)  # NAV_TAKEOFF
        log.info("armed, taking off to %.1f m", alt_m)
        climb_by = time.monotonic() + 6.0
        while time.monotonic() < climb_by and state.armed:
            if state.local and -state.local[-1][3] > 0.3 * alt_m:
                return
            time.sleep(0.2)
        if time.monotonic() > deadline:
            raise TimeoutError(f"no climb to {alt_m:.1f} m after arming and NAV_TAKEOFF (see the STATUSTEXT)")
        log.warning("no climb after NAV_TAKEOFF: arming and taking off again")


def send_target(conn, pos_ned: np.ndarray, vel_ned: np.ndarray, boot_ms: int) -> None:
    conn.mav.set_position_target_local_ned_send(boot_ms, conn.target_system, 1, 1,
                                                TYPE_MASK_POS_VEL, *map(float, pos_ned), *map(float, vel_ned),
                                                0, 0, 0, 0, 0)
