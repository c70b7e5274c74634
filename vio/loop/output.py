"""What the autopilot gets from loop closure (docs/autopilot.md#loop-closure): the odometry pose mapped with
the newest loop correction T_world_odom, delivered as `off` (the odometry, untouched), `jump` (the whole
correction at once, `reset_counter` incremented so that ArduPilot/PX4 re-reference instead of fighting the
jump) or `blend` (the applied correction walks towards the newest one at a bounded rate: position and yaw
move smoothly, reset_counter unchanged). Roll and pitch are never corrected (the IMU observes them).

In a frame that came through loop edges (a loaded map's, or the flight's own before an estimator reset) the
pose is only as good as those edges: the odometry's covariance knows nothing of them (it starts small at the new
segment's origin), so the correction's own uncertainty is added to what is sent (`CorrectionUncertainty`)."""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Callable

import numpy as np

from vio.geometry import make_T, so3_exp, yaw_of
from vio.types import NavState, covariance_quality

log = logging.getLogger(__name__)

UP = np.array([0.0, 0.0, 1.0])


@dataclasses.dataclass(frozen=True)
class CorrectionUncertainty:
    """How well a correction places the odometry in the frame it maps into: the covariance of a keyframe's
    corrected yaw and position there (4x4 over yaw [rad], x, y, z [m], world frame), and where that keyframe is.
    Roll and pitch are left out: the output never corrects them."""

    cov_yaw_position: np.ndarray
    p_world: np.ndarray

    @property
    def position_sigma_m(self) -> float:
        """sqrt of the position variances' sum (>= the largest axis), as `quality` reads a covariance."""
        return float(np.sqrt(max(np.trace(self.cov_yaw_position[1:, 1:]), 0.0)))

    @classmethod
    def from_pose(cls, T_world_body: np.ndarray, cov_pose: np.ndarray) -> CorrectionUncertainty:
        """From a pose and its covariance in GTSAM's Pose3 tangent (rotation then translation, body frame)."""
        R = T_world_body[:3, :3]
        G = np.zeros((4, 6))
        G[0, :3] = R[2, :]  # world yaw of a body-frame rotation perturbation: the z row of R
        G[1:, 3:] = R
        return cls(G @ cov_pose @ G.T, T_world_body[:3, 3].copy())

    def moved(self, T: np.ndarray) -> CorrectionUncertainty:
        """The same uncertainty in a world moved by T (a turn about up and a shift: world' = T @ world)."""
        G = np.eye(4)
        G[1:, 1:] = T[:3, :3]
        return CorrectionUncertainty(G @ self.cov_yaw_position @ G.T, T[:3, :3] @ self.p_world + T[:3, 3])

    def added_to(self, state: NavState, quality_sigma_m: float | None = None) -> NavState:
        """`state` (already corrected) with this uncertainty carried to its pose and velocity: a yaw error turns
        the path about the keyframe, so it grows with the distance from it. `quality` is capped as the
        estimator caps it (vio.types.covariance_quality), so it never says more than the covariance."""
        R, p = state.T_world_body[:3, :3], state.T_world_body[:3, 3]
        J = np.zeros((6, 4))
        J[:3, 0] = R.T @ UP
        J[3:, 0] = R.T @ np.cross(UP, p - self.p_world)
        J[3:, 1:] = R.T
        Jv = np.zeros((3, 4))
        Jv[:, 0] = np.cross(UP, state.v_world)
        cov_pose = state.cov_pose + J @ self.cov_yaw_position @ J.T
        quality = state.quality
        if quality_sigma_m is not None and quality > 0:
            quality = max(1, min(quality, round(100 * covariance_quality(cov_pose, quality_sigma_m))))
        return dataclasses.replace(state, cov_pose=cov_pose, cov_vel=state.cov_vel + Jv @ self.cov_yaw_position @ Jv.T,
                                   quality=quality)


MAX_BLEND_STEP_S = 0.25  # states come at 10-200 Hz; a longer gap walks no further than this


def _yaw_rot(yaw: float) -> np.ndarray:
    return so3_exp(np.array([0.0, 0.0, yaw]))


def _yaw_diff(a: float, b: float) -> float:
    """a - b wrapped to (-pi, pi]."""
    return float(np.angle(np.exp(1j * (a - b))))


def _yaw_only(C: np.ndarray) -> tuple[np.ndarray, float]:
    """(translation, yaw) of a correction; its roll/pitch part is dropped."""
    return C[:3, 3].copy(), yaw_of(C[:3, :3])


def _same_turn(a: np.ndarray | None, b: np.ndarray | None) -> bool:
    """Are two frame turns (or their absence) the same?"""
    if a is None or b is None:
        return a is None and b is None
    return bool(np.array_equal(a, b))


class CorrectedOutput:
    def __init__(self, mode: str = "off", blend_rate_m_s: float = 0.2, blend_rate_deg_s: float = 5.0,
                 quality_sigma_m: float | None = 0.05) -> None:
        if mode not in ("off", "jump", "blend"):
            raise ValueError(f"loop output mode {mode!r}: expected off, jump or blend")
        self.mode = mode
        self.rate_m_s = blend_rate_m_s
        self.rate_rad_s = np.radians(blend_rate_deg_s)
        self._t = np.zeros(3)  # applied correction: translation and yaw
        self._yaw = 0.0
        self._version = 0  # of the correction held (each new version is taken; see apply)
        self.jumps = 0  # reset_counter increments added (jump mode) since the estimator's (re)start
        self._jumps_before = 0  # those of the estimators before it (restart): in loop_jumps, not in reset_counter
        self._last_t_ns: int | None = None
        # blend: how far the sent pose still is from the held correction's: position at the vehicle, and heading
        self.remaining_m = 0.0
        self.remaining_deg = 0.0
        self._target: tuple[np.ndarray, float] = (np.zeros(3), 0.0)  # held correction: translation, yaw
        self._unc: CorrectionUncertainty | None = None  # of the correction held
        # the odometry segment (loop stage session) of the correction held, None until the first; after `restart`
        # only corrections solved with keyframes of reset_counter >= `_min_counter` are taken (the new estimator's)
        self._segment: int | None = None
        self._min_counter: int | None = None
        self.quality_sigma_m = quality_sigma_m  # [backend] quality_sigma_m: quality follows the added covariance
        self._refused_version: int | None = None  # a version whose correction was not finite (said once)
        # the MAVLink output's turn and shift of a start in flight (MavlinkOutput.world_frame_turn; None: none): it
        # turns every pose sent into the autopilot's frame, and a loaded map's frame (a checkpoint's) is the
        # autopilot's already (the process before sent it), so it is taken out of a correction into one here
        self.frame_turn: Callable[[], np.ndarray | None] | None = None
        # whether that turn is still to be chosen (MavlinkOutput.frame_pending: a start in flight before its first
        # tracked pose sent): a correction into a map's frame waits for it, or the turn chosen at a state of the
        # odometry's own frame still waiting to be sent was applied to map-frame poses too (turned twice)
        self.frame_pending: Callable[[], bool] | None = None
        # the correction held into a map's frame as solved (T_world_odom, its uncertainty), and the turn taken out of
        # it (None: none): taken out again when the output's turn changes (chosen after the correction was taken,
        # with no output open or before a start in flight's first pose: kept in, never taken out, a review's note)
        self._in_map: tuple[np.ndarray, CorrectionUncertainty | None] | None = None
        self._turn_out: np.ndarray | None = None

    def _takes(self, segment: int | None, own_frame: bool, counter: int | None) -> bool:
        """Is a new version's correction one for the odometry being sent? Not one of the old estimator's after
        `restart`, nor a later segment's own frame (an estimator reset not rejoined yet)."""
        if self._min_counter is not None and counter is not None and counter < self._min_counter:
            return False
        if segment is None:
            return True
        return self._segment is None or segment == self._segment or not own_frame

    @classmethod
    def from_config(cls, cfg) -> CorrectedOutput:
        """As a vio.config.VioConfig says: [loop] output and blend rates, [backend] quality_sigma_m."""
        return cls(cfg.loop.output, cfg.loop.blend_rate_m_s, cfg.loop.blend_rate_deg_s, cfg.backend.quality_sigma_m)

    def restart(self, first_counter: int) -> None:
        """A new estimator took over (the daemon re-created it), its keyframes handed to the loop stage with
        reset_counter >= `first_counter`: its odometry is in a frame of its own, which no correction held so far
        maps, so none is applied (the caller moves reset_counter past the last one published, jumps included), and
        a solve of the old estimator's keyframes still queued in the loop stage is not taken either (a segment number
        would not tell: the loop stage can be behind the estimator)."""
        self._t, self._yaw = np.zeros(3), 0.0
        self._target = (np.zeros(3), 0.0)
        self._unc, self._segment = None, None
        self._in_map, self._turn_out = None, None
        self.remaining_m = self.remaining_deg = 0.0
        self._min_counter = first_counter
        # the jumps so far are in first_counter already (the last counter published + 1): added again, the counter
        # moved by jumps + 1 at the new estimator's step, the same one mod 256 after 255 jumps (a review's note);
        # still counted in loop_jumps (the run's, for the status)
        self._jumps_before += self.jumps
        self.jumps = 0

    def _hold(self, T_world_odom: np.ndarray, uncertainty: CorrectionUncertainty | None,
              turn: np.ndarray | None) -> None:
        """Hold `T_world_odom` (jump: applied at once, a new reset_counter if it moves anything), the output's `turn`
        taken out of it (a correction into a map's frame)."""
        self._turn_out = turn
        if turn is not None:
            # turned and shifted again by the output, a relocalised pose went 3.2 m and 240 deg of yaw off the
            # map's frame at the jump (blend walked there): a review's finding
            back = np.linalg.inv(turn)
            T_world_odom = back @ T_world_odom
            uncertainty = uncertainty.moved(back) if uncertainty is not None else None
        self._target = _yaw_only(T_world_odom)
        self._unc = uncertainty
        if self.mode == "jump":
            turned = abs(_yaw_diff(self._target[1], self._yaw)) > 1e-8
            # absolute: a relative tolerance let a 9 mm step 1 km from the origin out without a count
            if turned or not np.allclose(self._target[0], self._t, rtol=0.0, atol=1e-8):
                self.jumps += 1
            self._t, self._yaw = self._target

    def apply(self, state: NavState, T_world_odom: np.ndarray, version: int,
              uncertainty: CorrectionUncertainty | None = None, segment: int | None = None,
              own_frame: bool = False, counter: int | None = None, in_map: bool = False) -> NavState:
        """`state` with the correction delivered as the mode says. `segment` is the odometry segment (the loop
        stage's session) the correction was solved for, `own_frame` whether that segment is still in a frame of its
        own (no loop edge joins it to another session), `counter` the reset_counter its newest keyframe was handed
        over with, `in_map` whether the frame it maps into is a loaded map's: LoopWorker.correction() gives all of
        them."""
        if self.mode == "off":
            return state
        # a gap in states (a stall) is not time to walk in: at most MAX_BLEND_STEP_S of blend per state
        dt = 0.0 if self._last_t_ns is None else min(max(state.t_ns - self._last_t_ns, 0) * 1e-9, MAX_BLEND_STEP_S)
        self._last_t_ns = state.t_ns
        if version != self._version and not np.isfinite(T_world_odom).all():
            # taken, it made every pose sent NaN (each refused by the MAVLink output) until the next solve: the
            # correction held stays, and reset_counter with it
            if version != self._refused_version:
                log.warning("loop correction version %d is not finite: not applied, the one held is kept", version)
                self._refused_version = version
        elif version != self._version and in_map and self.frame_pending is not None and self.frame_pending():
            pass  # into a map's frame, while the output's turn is still to be chosen: taken once it is
        elif version != self._version and self._takes(segment, own_frame, counter):
            # A new correction comes with a new version (a solve). After an estimator reset the newest segment is in
            # a frame of its own until a closure joins it, and the estimator's reset kept its last pose as the new
            # origin, so the correction held still maps it: both modes keep that correction, and its uncertainty,
            # while a solve (any closure, or deferred edges going in) gives only the new segment's own frame.
            # (Blend walked towards that frame, away from the map, and jump threw the map's frame away at the next
            # solve: two reviews' findings.)
            self._version = version
            self._segment = segment
            # a map's frame only: the flight's own first segment's (a reset's segment joined back to it) is the one
            # the output turned into the autopilot's
            self._in_map = (T_world_odom, uncertainty) if in_map else None
            turn = self.frame_turn() if self.frame_turn is not None and in_map else None
            self._hold(T_world_odom, uncertainty, turn)
        elif self._in_map is not None and self.frame_turn is not None:
            turn = self.frame_turn()
            if not _same_turn(turn, self._turn_out):  # chosen (or changed) since the correction was taken
                log.info("loop output: the MAVLink output's frame turn %s since the map correction was taken: taken "
                         "out of it now", "chosen" if self._turn_out is None else "changed")
                self._hold(*self._in_map, turn)
        # a state whose position is not finite (refused by the MAVLink output) does not walk the blend: it made the
        # applied correction NaN, and every pose after it, for the rest of the flight (a review's finding)
        if self.mode == "blend" and np.isfinite(state.T_world_body[:3, 3]).all():
            target_t, target_yaw = self._target
            # Bounded where it matters, at the vehicle: the sent position moves by the correction at most
            # rate_m_s * dt per step. A yaw change turns the odometry about its origin, so bounding the translation
            # alone let a vehicle 20 m out move at 1.75 m/s under a 30 deg yaw correction (a review's finding).
            p = state.T_world_body[:3, 3]
            q_now = _yaw_rot(self._yaw) @ p + self._t  # where the applied correction sends the vehicle now
            dyaw = _yaw_diff(target_yaw, self._yaw)
            turn = float(np.clip(dyaw, -self.rate_rad_s * dt, self.rate_rad_s * dt))
            self._yaw += turn
            self.remaining_deg = float(np.degrees(abs(dyaw - turn)))
            step = _yaw_rot(target_yaw) @ p + target_t - q_now
            n = float(np.linalg.norm(step))
            self.remaining_m = max(n - self.rate_m_s * dt, 0.0)
            if n > self.rate_m_s * dt:
                step *= self.rate_m_s * dt / n
            self._t = q_now + step - _yaw_rot(self._yaw) @ p
        C = make_T(_yaw_rot(self._yaw), self._t)
        R = C[:3, :3]
        # the velocity's covariance is world-frame like the velocity: it turns with it (left as it was, a yaw
        # correction made the odometry's uncertain axis read as its certain one: a review's finding)
        out = dataclasses.replace(state, T_world_body=C @ state.T_world_body, v_world=R @ state.v_world,
                                  cov_vel=R @ state.cov_vel @ R.T, reset_counter=state.reset_counter + self.jumps,
                                  loop_jumps=state.loop_jumps + self.jumps + self._jumps_before)
        return out if self._unc is None else self._unc.added_to(out, self.quality_sigma_m)
