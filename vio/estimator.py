"""The estimator facade: IMU samples and stereo frames in, NavStates out. No I/O, no threads.

`feed_imu` returns the IMU-rate propagated state; `feed_frame` runs the front end and the back end and
returns the state at the frame (also handed to every `listeners` callback, the replay's output sinks).
Frame stamps are on the camera clock and are moved onto the IMU clock with the calibration's
`time_offset_ns` (t_imu = t_cam + offset); a frame waits until the IMU has reached its stamp. With
`backend.estimate_time_offset` the offset is re-estimated in flight (vio.backend.time_offset) and replaces
the calibration's once confident.

Life cycle (`Estimator.phase`, one state object per side of it: `_Waiting` before a start, `_Running` while
the smoother runs): uninitialised -> initialising (static or in-motion) -> tracking <-> lost (no usable
frame for vision_timeout_s; still propagating, `tracking` false) -> reset -> bridging (the last trusted
state carried forward with the IMU) -> tracking. Keyframes go through the fixed-lag smoother; other frames
get the IMU prediction from the last keyframe. Failures (smoother exception, implausible velocity/bias, no
usable frame for lost_timeout_s) reset the estimator: it re-initialises on evidence, keeps the last position
and heading as the new origin, and bumps `reset_counter`.
"""

# Why one file of ~700 lines: the facade owns the life cycle (Phase, _Waiting/_Running), and every
# transition (start, keyframe, loss, reset, bridge) reads and writes the same few fields; split across
# files, a transition would be read in pieces. The math lives elsewhere (backend/, init/, propagator,
# sanity); what is here is the sequencing.

from __future__ import annotations

import dataclasses
import enum
import logging
import re
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field

import gtsam
import numpy as np

from vio import VioError
from vio.backend.preintegration import combined_params, measured_white_scale
from vio.backend.smoother import SmootherFailure, StereoFinding, VioSmoother
from vio.backend.time_offset import OnlineTimeOffset
from vio.calibration import StereoCalibration, calibration_units_problem
from vio.config import EstimatorConfig, VioConfig
from vio.frame_clock import SIGMAS_KEPT, FrameClock
from vio.frontend.gyro import GyroPrior
from vio.frontend.median import median
from vio.geometry import so3_log, yaw_between, yaw_position_alignment
from vio.imu_buffer import MOTION_UNKNOWN_GAP_NS, ImuBuffer
from vio.init.moving_init import MovingInitializer
from vio.init.static_init import InitialState, is_still, rotation_reading, static_initialize
from vio.motion_check import MotionCheck, MotionReading, MotionTally
from vio.propagator import Propagator
from vio.sanity import MAX_ACCEL_M_S2, MAX_GYRO_RAD_S, accel_units_problem, gyro_units_problem, imu_sample_problem
from vio.types import FeatureFrame, ImuSample, NavState, StereoFrame, covariance_quality

log = logging.getLogger(__name__)

IMU_KEEP_S = 3.0  # IMU history kept behind the newest sample (init windows, pending frames)
IMU_KEEP_NS = int(IMU_KEEP_S * 1e9)
IMU_NOISE_WINDOW_NS = 2_000_000_000  # IMU history measured at each keyframe (adaptive noise)
IMU_NOISE_HISTORY_NS = 10_000_000_000  # keyframe measurements whose per-axis median sets the noise (adaptive noise)
IMU_NOISE_MIN_READINGS = 10  # keyframe measurements before the adaptive noise may engage (a median of a few is noisy)
# one 2 s window reads up to ~2x its airframe's typical level: one above this many times the threshold is a shaking
# airframe on its own, before the median may decide (_provisional_params)
IMU_NOISE_ALONE_ABOVE = 2.0
BRIDGE_POSITION_MAX_S = 3.0  # longest reset gap whose IMU-only position prediction is used (error ~ t^2)
OMEGA_WINDOW_NS = 10_000_000  # gyro averaged over this much before a keyframe for the time offset state's twist
# a stereo-check reading beyond stereo_check_max_deg, said in the log once and in the status while it is the newest
IMPLAUSIBLE_STEREO_WHY = ("either the estimate is off (a start while moving) or the stereo calibration is grossly "
                          "wrong (vio calib check CALIB DATASET --disparity)")


@dataclass
class _ResetBridge:
    """The last trusted state before a reset, carried forward with the IMU until re-initialisation.

    Why: re-initialising takes a while (a still window, or frames of motion), and the vehicle keeps turning
    and moving meanwhile. Continuing from the last pose put the heading off by everything turned in the gap
    (up to 2 rad/s on an aggressive flight) and the position by the distance flown."""

    t0_ns: int
    start: gtsam.NavState
    bias: gtsam.imuBias.ConstantBias
    pim: gtsam.PreintegratedCombinedMeasurements
    t_ns: int  # integrated up to here


class Phase(enum.Enum):
    """Where the estimator is in its life cycle (`Estimator.phase`)."""

    UNINITIALISED = "uninitialised"  # nothing seen yet
    INITIALISING = "initialising"  # collecting a still window or frames of motion for a first start
    TRACKING = "tracking"  # running, a usable frame within vision_timeout_s
    LOST = "lost"  # running on the IMU alone: no usable frame for vision_timeout_s (reset at lost_timeout_s)
    BRIDGING = "bridging a reset"  # after a reset: the last trusted state carried forward until re-initialised


@dataclass
class _Waiting:
    """State while not running: what a reset left behind for the next start."""

    anchor: np.ndarray | None = None  # pose to continue from (position and heading)
    bridge: _ResetBridge | None = None  # that pose carried forward with the IMU
    trusted_bias: tuple[int, np.ndarray] | None = None  # (t, gyro bias) a re-initialisation must agree with


@dataclass
class _Running:
    """State while the smoother runs: everything that a reset throws away."""

    smoother: VioSmoother
    last_kf_t: int
    last_vision_t: int | None  # IMU-clock time of the last usable frame in the back end
    pim: gtsam.PreintegratedCombinedMeasurements | None = None  # since the last keyframe (None: just started)
    kf_cov_pose: np.ndarray = field(default_factory=lambda: np.eye(6) * 1e-2)  # at the last keyframe
    kf_cov_vel: np.ndarray = field(default_factory=lambda: np.eye(3) * 1e-2)
    marginal_due: bool = False  # the last keyframe's marginal is computed on the next frame (spreads the cost)
    deferred: _DeferredKeyframe | None = None  # a keyframe chosen on the last frame, solved on this one
    just_solved: bool = False  # this frame's call solved the last frame's keyframe (its dues wait a frame)
    motion: MotionCheck | None = None  # the smoother's motion against the stereo pair's (backend.motion_check)


@dataclass
class _DeferredKeyframe:
    """A keyframe chosen on its own frame and solved on the next (`solve_next_frame`): what its solve needs besides
    the running pre-integration, which stops at t until the solve (the next frame solves before integrating)."""

    t: int  # IMU-clock time of the keyframe
    ff: FeatureFrame
    still: bool  # zero-velocity keyframe
    omega_body: np.ndarray | None
    applied_offset_ns: int


@dataclass
class FrameTimings:
    """Wall-clock cost of the last processed frame."""

    frontend_ms: float = 0.0
    backend_ms: float = 0.0
    keyframe: bool = False
    extra: dict = field(default_factory=dict)


@dataclass
class EstimatorHealth:
    """What the estimator knows about its own inputs and state, for status, logs and the replay summary."""

    initialized: bool
    tracking: bool  # a usable camera frame reached the back end within vision_timeout_s
    reset_counter: int
    frames_processed: int
    frames_unusable: int  # front end gave no usable observations (bad image, too few tracks...)
    unusable_reasons: dict[str, int]
    imu_rejected: int  # non-finite or out-of-range samples
    imu_rejected_reasons: dict[str, int]
    frames_dropped: int  # never processed: queue full, stamp far ahead of the IMU, or not after the previous
    vision_age_s: float | None  # IMU time since the last usable frame reached the back end
    last_reset_reason: str
    sensor_error: str | None  # a diagnosed sensor problem (unit mistake, dead IMU) that blocks initialisation
    calibration_warning: str | None = None  # the flight showed the calibration wrong (the stereo check let go)
    stereo_warning: str | None = None  # frames that asked for stereo found none for a while (right camera, calib)
    stopped_for_run: str | None = None  # why the estimator stopped for the rest of the run (the IMU against the camera)
    frame_stamps: dict | None = None  # what the frame clock did (vio.frame_clock.FrameClockStats.as_dict)


@dataclass(frozen=True)
class ProcessedFrame:
    """One frame the estimator has finished, for whoever consumes frames (replay stats, debug views, the
    loop-closure and live-view threads, the daemon's latency): a frame may finish inside a later
    feed_imu() (it waits for the IMU to reach its stamp), so callers collect these with take_processed()
    after each feed instead of reading the estimator's latest fields."""

    t_ns: int  # camera stamp of the frame
    features: FeatureFrame
    timings: FrameTimings
    state: NavState | None  # the frame-rate state (None before initialisation or after a reset)
    keyframe: SolvedKeyframe | None = None  # the keyframe solved in this frame's call (this frame or the one before)
    # (stamp ns, T_world_body) of keyframes that left the smoother's window in this frame's call, each with its
    # last (smoothed) estimate: the loop stage's odometry edges between keyframes use these once they come
    settled: tuple[tuple[int, np.ndarray], ...] = ()


@dataclass
class SolvedKeyframe:
    """A keyframe as solved by the smoother, for the stages that want keyframes (loop closure): with
    `solve_next_frame` it is solved while the frame after it is processed, so it comes with that frame."""

    t_ns: int  # camera stamp of the keyframe's own frame
    features: FeatureFrame  # that frame's front-end output
    state: NavState  # the smoother's state at the keyframe


STEREO_LOSS_MIN_TRACKS = 30  # a frame with fewer tracked points says little about the right camera
STEREO_LOSS_FRAMES = 10  # frames that looked for stereo (keyframes, the starts: 2-3 s of flight) with none


def _reason_key(reason: str) -> str:
    """A reason without its numbers, so that counts group: "image too dark (mean grey 3.1 < 12)" -> "image too dark"."""
    key = reason.split(" (")[0].strip() or "unknown"
    return re.sub(r"[-+]?\d[\d.e+-]*", "N", key)


def reanchored(T_world_body: np.ndarray, v_world: np.ndarray, anchor: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A restart's initial pose and velocity turned about world z and moved so that it continues from
    `anchor` (the last pose, or its IMU prediction): same position and heading, the restart's own roll/pitch.

    The heading is compared in the world frame (`yaw_between`), not as Euler yaws, which for a body whose
    z axis is not up (EuRoC's IMU: x up) turn the restart by degrees."""
    A = yaw_position_alignment(T_world_body, anchor)
    return A @ T_world_body, A[:3, :3] @ np.asarray(v_world, float)


def make_tracker(calib: StereoCalibration, cfg: EstimatorConfig):
    """The project's stereo front end; imported lazily so the back end runs (and is tested) without it."""
    from vio.frontend.tracker import StereoTracker

    return StereoTracker(calib, cfg.frontend)


class Estimator:
    """Stereo-inertial odometry: feed IMU samples and frames in time order."""

    def __init__(self, calib: StereoCalibration, cfg: EstimatorConfig | None = None, tracker=None) -> None:
        # a calibration in millimetres flies a 1000x baseline: poses 10x off with sigmas that claim otherwise, on any
        # path that reaches the estimator (a dataset reader refuses it sooner, a device's own report does not)
        problem = calibration_units_problem(calib)
        if problem:
            raise VioError(problem)
        if np.allclose(calib.cam0.T_body_cam, np.eye(4), atol=1e-9):
            # what an import without camera-IMU extrinsics writes (kalibr's camchain.yaml, an OAK without IMU
            # extrinsics); flown, a real rig's rotation turned the gyro's axes: metres of error (a review's finding)
            log.warning("calibration: T_body_cam0 is the identity (the IMU exactly at cam0, axes aligned), which no "
                        "real rig has: most likely the camera-IMU extrinsic was never imported; `vio calib check "
                        "CALIB RECORDING` compares it with the gyro")
        self.calib = calib
        if isinstance(cfg, VioConfig):  # keep only the sections the estimator reads
            cfg = cfg.estimator
        self.cfg = cfg or EstimatorConfig()
        self.bcfg = self.cfg.backend
        self.tracker = tracker
        self.params = combined_params(calib.imu, self.bcfg.imu_noise_scale)
        self.imu = ImuBuffer()
        self.propagator = Propagator()
        # KLT rotation prior for the front end, on the IMU clock (offset applied here), with our gyro bias
        self.gyro_prior = GyroPrior(calib.cam0.T_body_cam, 0, imu=self.imu)
        self.time_offset_ns = int(calib.time_offset_ns)  # t_imu = t_cam + offset; may be re-estimated
        b = self.bcfg
        # frames stamped on arrival restamped on the camera's own clock; kept across resets (the camera's clock
        # does not change when the estimator does)
        # (each stamp's sigma kept for every frame that may wait for the IMU, the deferred keyframe and a margin)
        self.frame_clock = FrameClock(b.frame_stamps, b.frame_stamp_window_s,
                                      max(SIGMAS_KEPT, b.max_pending_frames + 8))
        self.frame_clock.stats.stamp_link = bool(b.frame_stamp_link)  # what the replay and the status say of them
        # the stamp this estimator gave the frame fed last (the frame clock's, where it moved it): its ProcessedFrame
        # and SolvedKeyframe carry that one, so a caller keys the frame's image and arrival by it, not by the stamp
        # it fed (keyed so, every restamped frame's image, arrival and TUM line were lost: a review's finding)
        self.last_frame_stamp_ns: int | None = None
        self.offset_estimator = OnlineTimeOffset(calib, b.time_offset_window_s, b.time_offset_max_ms * 1e-3,
                                                 imu=self.imu, continuous=b.time_offset_continuous,
                                                 track_window_s=b.time_offset_track_window_s,
                                                 recheck_s=b.time_offset_recheck_s,
                                                 max_gyro_bias_rad_s=b.max_gyro_bias_rad_s) \
            if b.estimate_time_offset else None
        # the smoother's time offset state: on from the start, or switched on by the in-flight estimate (auto)
        self._time_state = bool(b.time_offset_state)
        # the smoother's state starts only at a keyframe whose motion shows the offset, which a slow flight may
        # never have: until then the gyro-based estimate is the only one and runs as without the state. Without
        # the state asked for there is nothing to hand over (time_offset_state_auto's own switch keeps the
        # estimate going to convergence, `_start_time_state`)
        self._offset_handed_over = not b.time_offset_state
        self._time_links_before = 0  # keyframes linked to the offset by smoothers dropped at resets
        self.moving_init = MovingInitializer(calib, self.cfg.init, self.params)
        # smoother's T_body_cam0/1, keyframes that refined them, refined (fx, fy, cx, cy) of both cameras or None
        self._refined: tuple[np.ndarray, np.ndarray, int, tuple | None] | None = None
        self._stereo_finding: StereoFinding | None = None  # the stereo check's newest reading (backend.stereo_check)
        self._stereo_released: list[StereoFinding] = []  # the readings at which it let go, over the flight
        self._stereo_implausible = 0  # readings beyond stereo_check_max_deg, over the flight (not acted on)
        self._reset_anchor: np.ndarray | None = None  # T_world_body the next reset continues from (motion check)
        self._motion_before = MotionTally()  # the motion checks of smoother runs ended by resets, for the stats
        self._t_first_ns: int | None = None  # the first frame's stamp: flight times in the stats count from it
        self.listeners: list[Callable[[NavState], None]] = []
        self._processed: deque[ProcessedFrame] = deque(maxlen=64)  # bounded: a caller that never takes them
        self.reset_counter = 0
        self.timings = FrameTimings()
        self.frames_processed = 0
        self.keyframes = 0
        self._pending: deque[StereoFrame | FeatureFrame] = deque()
        self._state: _Waiting | _Running = _Waiting()
        self._last_frame_t: int | None = None
        self._cov_pose = np.eye(6) * 1e-2  # reported with the newest frame state
        self._cov_vel = np.eye(3) * 1e-2
        self.marginals = 0  # marginal covariances computed (diagnostics)
        self._latest: NavState | None = None
        self._track_quality = 0.0
        self._tracking = False
        self._was_keyframe = False
        self._solved_kf: SolvedKeyframe | None = None  # set by a solve, handed out with the frame that made it
        self.settled_at_end: list[tuple[int, np.ndarray]] = []  # flush(): keyframes still in the window, as they end
        self._settled_before_reset: list[tuple[int, np.ndarray]] = []  # settled in a call that then reset
        self._prev_ff: FeatureFrame | None = None
        self.last_features: FeatureFrame | None = None  # front-end output of the last frame (debug views)
        self._flow_px = float("inf")  # median feature motion since the previous frame
        self._still_frames: deque[FeatureFrame] = deque()  # usable frames of the last static_window_s
        self._last_usable_frame_t: int | None = None  # camera clock
        self._turn_refused_t: int | None = None  # the last still start refused as a turn (camera clock)
        self._cov_state: tuple[int, np.ndarray] | None = None  # (t, R_world_body) the frame covariance belongs to
        # continuous noise densities (variance per second), for the IMU-rate covariance growth
        self.white_scale: np.ndarray | None = None  # adaptive IMU noise: the scale in use (gyro xyz, accel xyz)
        self._white_readings: deque[tuple[int, np.ndarray]] = deque()  # (t, measured scale) per keyframe
        self._provisional_scale: np.ndarray | None = None  # before the adaptive noise may engage (_provisional_params)
        self._use_params(self.params)
        self._g2_horizontal = np.diag([9.81 ** 2, 9.81 ** 2, 0.0])
        self.frames_unusable = 0
        self.unusable_reasons: dict[str, int] = {}
        self.imu_rejected = 0
        self.imu_rejected_reasons: dict[str, int] = {}
        self.frames_dropped = 0
        self.last_reset_reason = ""
        self.sensor_error: str | None = None
        self._imu_camera_error: str | None = None  # the gyro against the camera: final for the run
        self._start_bias_refused = False  # the last start found was refused for its gyro bias (said once)
        self._no_stereo = 0  # frames in a row that looked for stereo among many tracks and found none
        self._stereo_loss: str | None = None  # what the stereo warning found (None: stereo fine)

    # -- public API ------------------------------------------------------------------------------------
    @property
    def initialized(self) -> bool:
        return isinstance(self._state, _Running)

    @property
    def phase(self) -> Phase:
        st = self._state
        if isinstance(st, _Running):
            t = self.imu.last_t_ns
            return Phase.TRACKING if t is not None and self._tracking_at(t) else Phase.LOST
        if st.bridge is not None:
            return Phase.BRIDGING
        return Phase.INITIALISING if self.frames_processed or self.reset_counter else Phase.UNINITIALISED

    def latest(self) -> NavState | None:
        """Newest frame-rate state (None before initialisation)."""
        return self._latest

    def take_processed(self) -> list[ProcessedFrame]:
        """The frames finished since the last call, oldest first (at most the last 64)."""
        out = list(self._processed)
        self._processed.clear()
        return out

    def feed_imu(self, s: ImuSample, want_state: bool = True) -> NavState | None:
        """Add one IMU sample; returns the IMU-rate propagated state once initialised.

        `want_state=False` (a replay that keeps only frame states) skips the propagation and the state's
        covariance, about a third of the per-sample cost; the propagator catches up with the buffered
        samples when a later call wants a state again."""
        prev_t = self.imu.last_t_ns
        g, a = s.gyro, s.accel
        # NaN fails both comparisons; two reductions instead of imu_sample_problem() on the hot path
        if not (np.abs(g).max() <= MAX_GYRO_RAD_S and np.abs(a).max() <= MAX_ACCEL_M_S2):
            self._reject_imu(s)
            return None
        if not self.imu.add(s):
            return None
        st = self._state
        if isinstance(st, _Running) and prev_t is not None and (s.t_ns - prev_t) * 1e-9 > self.bcfg.max_imu_gap_s:
            # the frames in the gap would be solved with an IMU factor across it: a motion nobody measured, which the
            # stereo check then took for a camera fault (a review's finding); start again from the images instead
            self.reset(f"IMU gap of {(s.t_ns - prev_t) * 1e-9:.2f} s: the motion in it is unknown", bridge=False)
            st = self._state
        if isinstance(st, _Waiting) and st.bridge is not None and prev_t is not None and \
                s.t_ns - prev_t > MOTION_UNKNOWN_GAP_NS:
            log.warning("IMU gap of %.2f s after the reset: the last pose is kept as it was", (s.t_ns - prev_t) * 1e-9)
            st.bridge = None
        # one buffer for all readers: pre-integration, initialisers, gyro prior, and the offset solver's window
        off = self.offset_estimator
        self.imu.trim_before(s.t_ns - IMU_KEEP_NS, off.keep_samples if off is not None and off.keeps_imu else 0)
        self._drain(final=False)
        run = self._state
        if not isinstance(run, _Running):
            return None
        if run.last_vision_t is not None and (s.t_ns - run.last_vision_t) * 1e-9 > self.bcfg.lost_timeout_s:
            self.reset(f"no usable camera frame for {(s.t_ns - run.last_vision_t) * 1e-9:.2f} s")
            return None
        if want_state and self._propagate_to(s.t_ns):
            return self._propagated_state()
        return None

    def _propagate_to(self, t_ns: int) -> bool:
        """Advance the propagator through the buffered samples up to t_ns; True when it reached t_ns.

        Lazy, so that samples nobody asks a state for cost nothing. The samples since the propagator's time
        are in the buffer while that time is within IMU_KEEP_S (keyframes restart it; without any, a caller
        that skipped states for longer gets one step across the trimmed part, held at its last sample)."""
        p = self.propagator
        if not p.ready or p.t_ns >= t_ns:
            return False
        if self.imu.t[-2:-1] == [p.t_ns]:  # the usual case: one new sample, the one just added
            p.add(ImuSample(self.imu.t[-1], self.imu.gyro[-1], self.imu.accel[-1]))
        else:
            ts, g, a = self.imu.window(p.t_ns + 1, t_ns)
            for k in range(len(ts)):
                p.add(ImuSample(int(ts[k]), g[k], a[k]))
        return p.t_ns == t_ns

    def _reject_imu(self, s: ImuSample) -> None:
        why = imu_sample_problem(s.gyro, s.accel) or "invalid sample"
        self.imu_rejected += 1
        key = _reason_key(why)
        self.imu_rejected_reasons[key] = self.imu_rejected_reasons.get(key, 0) + 1
        if self.imu_rejected_reasons[key] == 1 or self.imu_rejected in (10, 100, 1000):
            log.warning("IMU sample at %d rejected (%s); %d rejected so far", s.t_ns, why, self.imu_rejected)

    def health(self) -> EstimatorHealth:
        t = self.imu.last_t_ns
        vt = self._state.last_vision_t if isinstance(self._state, _Running) else None
        age = None if t is None or vt is None else max(t - vt, 0) * 1e-9
        return EstimatorHealth(self.initialized, self._tracking_at(t) if t is not None else False,
                               self.reset_counter, self.frames_processed, self.frames_unusable,
                               dict(self.unusable_reasons), self.imu_rejected, dict(self.imu_rejected_reasons),
                               self.frames_dropped, age, self.last_reset_reason, self.sensor_error,
                               self._calibration_warning(), self.stereo_warning, self._imu_camera_error,
                               self.frame_clock.stats.as_dict())

    def _calibration_warning(self) -> str | None:
        said = []
        if self._stereo_released:
            f = self._stereo_released[-1]
            said.append(f"the right camera disagrees with the stereo calibration ({f.describe()}, found in flight): "
                        "cam1 refined in flight since; fix the stereo calibration")
        f = self._stereo_finding
        if f is not None and f.implausible:
            said.append(f"the stereo check reads the right camera off the calibration ({f.describe()}), more than a "
                        f"stereo pair bends in flight: held as calibrated; {IMPLAUSIBLE_STEREO_WHY}")
        if self.offset_estimator is not None and self.offset_estimator.slow_warning:
            said.append(self.offset_estimator.slow_warning)
        return "; ".join(said) or None

    def _tracking_at(self, t: int) -> bool:
        """Tracking means vision: a usable frame reached the back end within vision_timeout_s of t."""
        run = self._state
        return (isinstance(run, _Running) and self._tracking and run.last_vision_t is not None
                and (t - run.last_vision_t) * 1e-9 <= self.bcfg.vision_timeout_s)

    def feed_frame(self, frame: StereoFrame) -> NavState | None:
        """Add a stereo frame; returns the state at the newest frame processed by this call."""
        self._enqueue(frame)
        return self._drain(final=False)

    def feed_features(self, ff: FeatureFrame) -> NavState | None:
        """Add a front-end result directly (tests, or a front end running elsewhere)."""
        self._enqueue(ff)
        return self._drain(final=False)

    def _enqueue(self, item: StereoFrame | FeatureFrame) -> None:
        """Bounded wait for the IMU: a frame stamped far ahead of it, or one that would grow the queue past
        max_pending_frames (an IMU that stopped), is dropped and counted instead of waiting forever."""
        t_ns = self.frame_clock.restamp(item.t_ns)
        if t_ns != item.t_ns:  # a stamp the camera's fitted clock puts elsewhere (vio.frame_clock)
            item = dataclasses.replace(item, t_ns=t_ns)
        self.last_frame_stamp_ns = t_ns
        if self._t_first_ns is None:
            self._t_first_ns = int(item.t_ns)
        b = self.bcfg
        last_imu = self.imu.last_t_ns
        t_imu = int(item.t_ns) + self.time_offset_ns
        if last_imu is not None and (t_imu - last_imu) * 1e-9 > b.max_frame_lead_s:
            self._drop_frame(f"frame at {item.t_ns} is {(t_imu - last_imu) * 1e-9:.2f} s ahead of the newest IMU "
                             "sample (IMU stopped, or a stamp jump)")
            return
        if len(self._pending) >= b.max_pending_frames:
            old = self._pending.popleft()
            self._drop_frame(f"{b.max_pending_frames} frames wait for the IMU; the oldest ({old.t_ns}) is dropped")
        self._pending.append(item)

    def _drop_frame(self, why: str) -> None:
        self.frames_dropped += 1
        if self.frames_dropped == 1 or self.frames_dropped % 100 == 0:
            log.warning("%s; %d frames dropped so far", why, self.frames_dropped)

    def flush(self) -> NavState | None:
        """Process frames still waiting for IMU (end of a recording): the IMU is held at its last value. A
        keyframe still waiting for its solve (`solve_next_frame`) is solved, and a stereo check still due is read,
        so that the flight's statistics and refined calibration include them; no frame comes with it."""
        out = self._drain(final=True)
        run = self._state
        if isinstance(run, _Running) and run.deferred is not None:
            try:
                self._solve_deferred(run)
            except SmootherFailure as e:
                self.reset(str(e), bridge=e.state_ok)
            self._solved_kf = None
        run = self._state
        if isinstance(run, _Running) and run.smoother.check_due:  # the last keyframe's, for the flight's stats
            self._note_stereo_check(run.smoother.check_stereo())
        self.settled_at_end = []
        if isinstance(run, _Running):  # the window's keyframes as they end (ProcessedFrame.settled for the rest)
            run.smoother.settle_all()
            self.settled_at_end = run.smoother.take_settled()
        return out

    def reset(self, reason: str, bridge: bool = True, keep_bias: bool | None = None) -> None:
        """Drop the smoother and re-initialise; the last pose becomes the new start (yaw and position).

        `bridge`: the last state is trustworthy and the IMU continuous, so it is carried forward with the
        IMU until the re-initialisation (heading always, position over gaps up to BRIDGE_POSITION_MAX_S).
        `keep_bias` (default: as `bridge`): the last state's gyro bias is trustworthy though the IMU was not
        continuous (an IMU gap): the restart must agree with it (`_bias_continuous`). Dropped, a static restart in a
        steady turn took the turn for a 0.08 rad/s bias and flew on at 1.7x scale with quality 100 (a review's
        finding)."""
        if keep_bias is None:
            keep_bias = bridge
        self.reset_counter += 1
        if isinstance(self._state, _Running):
            self._time_links_before += self._state.smoother.time_links  # the flight's count outlives the smoother
            # keyframes that left the window before the failure keep their settled poses (the rest never settle)
            self._settled_before_reset += self._state.smoother.take_settled()
            if self._state.motion is not None:  # the flight's motion check figures outlive the run's check
                self._motion_before = self._state.motion.tally(self._motion_before)
        learnt = self.time_offset_estimate_ns if bridge else self.time_offset_ns
        if learnt != self.time_offset_ns:  # the time state's offset outlives its smoother
            log.info("camera-IMU time offset: %.2f ms -> %.2f ms (the smoother's time state, kept across the reset)",
                     self.time_offset_ns * 1e-6, learnt * 1e-6)
            self.time_offset_ns = learnt
        # a running bridge (and its anchor) survives a failed restart: the last trusted state is older
        w = self._state if isinstance(self._state, _Waiting) else _Waiting()
        if not bridge:
            w.bridge = None
        if self._latest is not None and w.bridge is None:
            w.anchor = self._latest.T_world_body.copy()
            st = self._latest
            # the IMU since that state is still here (and not older than IMU_KEEP_S: the offset solver may
            # hold a longer history, but a bridge over more than that is not trusted)
            if bridge and self.imu.t and self.imu.t[0] <= st.t_ns and self.imu.t[-1] - st.t_ns <= IMU_KEEP_NS:
                bias = gtsam.imuBias.ConstantBias(st.accel_bias, st.gyro_bias)
                w.bridge = _ResetBridge(st.t_ns, gtsam.NavState(gtsam.Pose3(st.T_world_body), st.v_world), bias,
                                        gtsam.PreintegratedCombinedMeasurements(self.params, bias), st.t_ns)
        if self._reset_anchor is not None:  # a better pose than the last one (the motion check's; never bridged)
            w.anchor, self._reset_anchor = self._reset_anchor, None
        # re-armed only from a running estimate: a failed restart (`_try_init`'s SmootherFailure) must not bring
        # back a bias the reset before it chose not to keep
        if keep_bias and isinstance(self._state, _Running) and self._latest is not None and \
                (bridge or self._latest.tracking) and \
                float(np.max(np.abs(self._latest.gyro_bias))) <= self.bcfg.max_gyro_bias_rad_s:
            w.trusted_bias = (self._latest.t_ns, np.asarray(self._latest.gyro_bias, float).copy())
        elif not keep_bias:
            w.trusted_bias = None
        self._state = w
        if self._last_frame_t is not None:
            self._advance_bridge(self._last_frame_t)
        log.warning("estimator reset #%d: %s", self.reset_counter, reason)
        self.last_reset_reason = reason
        self._pending.clear()
        self._tracking = False
        self.moving_init.clear()

    def _advance_bridge(self, t: int) -> None:
        """Integrate the reset bridge up to the frame time t (not beyond: the start that uses it is at t)."""
        b = self._state.bridge if isinstance(self._state, _Waiting) else None
        if b is not None and t > b.t_ns:
            self.imu.integrate(b.pim, b.t_ns, t)
            b.t_ns = t

    # -- frame pipeline --------------------------------------------------------------------------------
    def _drain(self, final: bool) -> NavState | None:
        out = None
        last_imu = self.imu.last_t_ns
        while self._pending:
            t_imu = self._pending[0].t_ns + self.time_offset_ns
            if not final and (last_imu is None or last_imu < t_imu):
                break
            st = self._process(self._pending.popleft())
            if st is not None:
                out = st
        return out

    def _process(self, item: StereoFrame | FeatureFrame) -> NavState | None:
        t = int(item.t_ns) + self.time_offset_ns
        if not self.imu.t:
            return None
        if self._last_frame_t is not None and t <= self._last_frame_t:
            self._drop_frame(f"frame at {t} not after the previous one ({self._last_frame_t})")
            return None
        solve_ms = self._solve_deferred_first()
        t_start = time.perf_counter()
        if isinstance(item, FeatureFrame):
            ff = item
        else:
            if self.tracker is None:
                self.tracker = make_tracker(self.calib, self.cfg)
            prior = None if self._last_frame_t is None else self.gyro_prior.rotation(self._last_frame_t, t)
            import cv2  # already loaded by the tracker

            asked: list[bool] = []

            def wants_stereo(preview: FeatureFrame) -> bool:
                asked.append(self._needs_stereo(t, preview))
                return asked[-1]
            try:
                ff = self.tracker.process(item, prior, stereo=wants_stereo)
            except cv2.error as e:  # one frame OpenCV cannot handle must not end the flight
                msg = str(e).strip().splitlines()[-1] if str(e).strip() else type(e).__name__
                log.warning("front end failed on the frame at %d: %s", item.t_ns, msg)
                ff = FeatureFrame.empty(item.t_ns, f"front end error: {msg}")
        t_front = time.perf_counter()
        if not isinstance(item, FeatureFrame) and asked and asked[-1]:
            self._note_stereo(ff)
        if not self._usable(ff):
            self.frames_unusable += 1
            key = _reason_key(ff.reason) if not ff.tracking_ok else f"fewer than {self.bcfg.min_tracks_ok} tracks"
            self.unusable_reasons[key] = self.unusable_reasons.get(key, 0) + 1
        offset_solved = self._update_time_offset(ff, t)
        prev_t = self._last_frame_t
        self._last_frame_t = t
        self._flow_px = median_flow_px(self._prev_ff, ff)
        self._keep_still_window_frame(ff)
        self.last_features = ff
        self._prev_ff = ff
        self.frames_processed += 1
        if not self.initialized:
            self._advance_bridge(t)
        try:
            st = self._track(t, prev_t, ff, offset_solved) if self.initialized else self._try_init(t, ff)
        except SmootherFailure as e:
            self.reset(str(e), bridge=e.state_ok)
            st = None
        t_end = time.perf_counter()
        self.timings = FrameTimings((t_front - t_start) * 1e3, (t_end - t_front) * 1e3 + solve_ms,
                                    self.timings.keyframe if st is None else self._was_keyframe)
        if st is not None:
            self._latest = st
            for sink in self.listeners:
                sink(st)
        settled = tuple(self._settled_before_reset)
        self._settled_before_reset = []
        if isinstance(self._state, _Running):
            settled += tuple(self._state.smoother.take_settled())
        self._processed.append(ProcessedFrame(int(ff.t_ns), ff, self.timings, st, self._solved_kf, settled))
        self._solved_kf = None
        return st

    def _note_stereo(self, ff: FeatureFrame) -> None:
        """Say when frames that asked for stereo find none among many tracked points, and when it is back.

        With cam0 and cam1 swapped in the calibration (or the right camera dark, covered or unplugged) a flight ran
        on mono landmarks and the IMU alone, with quality 100 and nothing said (a review's finding: 4.3 cm ATE for
        0.5 cm with the calibration right). Poses still go out, with the smoother's own covariance; the status says
        degraded, and why."""
        if len(ff.ids) < STEREO_LOSS_MIN_TRACKS:
            return
        if ff.n_stereo > 0:
            if self._stereo_loss is not None:
                log.info("stereo: matches again (%d of %d tracked points)", ff.n_stereo, len(ff.ids))
            self._no_stereo, self._stereo_loss = 0, None
            return
        self._no_stereo += 1
        if self._no_stereo == STEREO_LOSS_FRAMES:
            # the front end's note says when there was no right image to match, or none it could use: then the
            # calibration is not in question (a right camera out for seconds was told to check for swapped cameras)
            if ff.reason.startswith("no right image"):
                why = "no right image arrived: the right camera is disconnected or not delivering"
            elif ff.reason.startswith("right image unusable"):
                why = f"{ff.reason.removesuffix(': mono only')}: the right camera is dark, covered or failing"
            else:
                why = ("the right camera is dark, covered or disconnected, or cam0 and cam1 are swapped in the "
                       "calibration (vio calib check CALIB)")
            self._stereo_loss = (f"no stereo match in the last {STEREO_LOSS_FRAMES} frames that looked for one "
                                 f"({len(ff.ids)} points tracked): {why}")
            log.warning("stereo: %s", self.stereo_warning)

    @property
    def stereo_warning(self) -> str | None:
        """What the stereo loss found and what the estimator does about it now (before the start, running, after a
        reset); None while stereo is fine."""
        return None if self._stereo_loss is None else f"{self._stereo_loss}; {self._without_stereo()}"

    def _without_stereo(self) -> str:
        """What the estimator does without stereo: a start in motion needs stereo depth (the moving initialiser
        triangulates its landmarks from it), so before the start nothing is estimated; a QA run (right camera out
        for the first 8 s of an aggressive flight that starts moving) said "running on the IMU and the left camera
        alone" for the 9 s it sent no pose."""
        if self.initialized:
            return "running on the IMU and the left camera alone"
        if not self.cfg.init.allow_moving_start:
            return "not started: waiting for the vehicle to be at rest (a start at rest does not need stereo)"
        return ("not started: a start in motion waits for stereo depth, so no pose is sent until the right camera "
                "matches again (a start at rest does not need it)")

    def _needs_stereo(self, t: int, preview: FeatureFrame) -> bool:
        """Stereo is used by the initialisers, the time-offset estimator (PnP on stereo points) and keyframes
        only. `preview` is the frame's front-end result before stereo, which is all the keyframe choice
        looks at, so the choice is known here: on a survey flight about one frame in five needs stereo."""
        return (self.bcfg.stereo_every_frame or not self.initialized or self._is_keyframe(t, preview)
                or (self.offset_estimator is not None and self.offset_estimator.wants_stereo()))

    @property
    def time_offset_estimate_ns(self) -> int:
        """Best knowledge of the offset: the applied one, or with the time state what the smoother puts on
        its newest keyframe."""
        run = self._state
        state = run.smoother.time_offset_ns() if isinstance(run, _Running) else None
        return self.time_offset_ns if state is None else state

    @property
    def time_links(self) -> int:
        """Keyframes of the flight whose camera pose the time state read at the offset (those moving fast
        enough to show it: `time_offset_link_min_rate` / `_speed`), across resets as `keyframes` counts."""
        run = self._state
        return self._time_links_before + (run.smoother.time_links if isinstance(run, _Running) else 0)

    @property
    def time_state(self) -> bool:
        """Whether the smoother follows the time offset as a state (configured, or switched on in flight)."""
        return self._time_state

    def _omega(self, t: int, gyro_bias: np.ndarray) -> np.ndarray | None:
        """Bias-corrected body rate at t for the time offset state's twist (None without the state): the
        gyro's mean over the last OMEGA_WINDOW_NS (one sample is mostly motor vibration)."""
        if not self._time_state:
            return None
        _, gyro, _ = self.imu.window(t - OMEGA_WINDOW_NS, t)
        if len(gyro) == 0:
            return np.zeros(3)
        return np.mean(gyro, axis=0) - np.asarray(gyro_bias, float)

    def _update_time_offset(self, ff: FeatureFrame, t: int) -> bool:
        """Feed the in-flight offset estimator; a confident new offset applies from the next frame on. Returns
        whether it solved on this frame (a stereo check due then waits for the next one).

        Its solves (tens of ms) wait for a frame that is no keyframe and computes no marginal, so that they
        never add to a keyframe solve."""
        if self.offset_estimator is None or not self.offset_estimator.collects(int(ff.t_ns)):
            return False
        run = self._state
        quiet = not isinstance(run, _Running) or not (self._is_keyframe(t, ff) or run.marginal_due
                                                      or run.smoother.marginalize_due or run.just_solved)
        solves = self.offset_estimator.solves
        new = self.offset_estimator.add_frame(ff, solve=quiet)
        if self.offset_estimator.imu_problem is not None and self._imu_camera_error is None:
            units = self.offset_estimator.gyro_scale.problem is not None
            self._imu_disagrees(self.offset_estimator.imu_problem, "IMU units" if units else "IMU mount",
                                "fix the IMU's units or scale" if units else
                                "fix the calibration's camera-IMU rotation (vio calib check CALIB DATASET)")
            return False
        if new is not None and new != self.time_offset_ns and self.offset_estimator.tracking:
            log.debug("camera-IMU time offset tracked: %.2f ms", new * 1e-6)
            self.time_offset_ns = new
        elif new is not None and new != self.time_offset_ns:
            log.info("camera-IMU time offset: %.1f ms -> %.1f ms (calibration %.1f ms)", self.time_offset_ns * 1e-6,
                     new * 1e-6, self.calib.time_offset_ns * 1e-6)
            self.time_offset_ns = new
            if self.bcfg.time_offset_state_auto and not self._time_state:
                self._start_time_state()
        return self.offset_estimator.solves > solves

    def _imu_disagrees(self, problem: str, what: str, fix: str) -> None:
        """The gyro measured against the camera is in the wrong units (or dead), or turns about other axes than the
        calibration says: nothing it feeds can be trusted, and no start can fix it, so the estimator stops and
        stays stopped for this run, and says why (status, log, replay summary). A deg/s gyro with a small bias at
        rest had passed the checks at rest and flown 9 m off before a speed check reset it; an IMU whose axes were
        turned 90 deg from the calibration's flew 1.1 m off blaming the right camera."""
        self._imu_camera_error = self.sensor_error = problem
        log.error("%s: %s; no pose is estimated for the rest of this run: %s", what, problem, fix)
        if self.initialized:
            self.reset(f"{what}: {problem}", bridge=False, keep_bias=False)

    def continue_from(self, T_world_body: np.ndarray) -> None:
        """Start at this pose's position and heading (with its own roll and pitch), as a reset continues from the last
        pose: for a new estimator replacing one whose reset() raised (the daemon's), which otherwise started at its
        own origin, a step of all that was flown at the autopilot's new reset_counter. No effect once running."""
        if isinstance(self._state, _Waiting) and np.isfinite(T_world_body).all():
            self._state.anchor = np.array(T_world_body, dtype=float)

    def stop_for_run(self, problem: str) -> None:
        """A run-final verdict from outside (`EstimatorHealth.stopped_for_run`): the one on the IMU of an estimator
        this one replaces (the daemon makes a new one when reset() raises, and the sensor is still as wrong as it
        was), or the daemon's on a calibration file of another camera. This one stays stopped for the run, saying
        the same; a running one ends its output now."""
        self._imu_camera_error = self.sensor_error = problem
        if self.initialized:
            self.reset(problem, bridge=False, keep_bias=False)

    def _hand_offset_to_state(self) -> None:
        """The smoother's time offset state has started (a keyframe passed its motion gate) and follows the
        offset from here on: the gyro-based estimate stops at its next accepted solve (collecting on costs a PnP
        per frame for nothing) and makes no re-checks. Before that it is the only estimate, so a flight that never
        moves fast enough for the state keeps the full estimate and its re-checks."""
        self._offset_handed_over = True
        if self.offset_estimator is not None:
            self.offset_estimator.coarse_only = not self.offset_estimator.continuous
            self.offset_estimator.stop_rechecks()

    def _start_time_state(self) -> None:
        """The calibration's offset proved wrong: this rig's clocks are not what its file says, and clocks that
        disagree often drift (USB cameras, serial IMUs). The smoother follows the offset as a state from the next
        keyframe on. The gyro-based estimate goes on until it has converged (on the +-10 ms matrix flights the
        state alone from the first correction ended 1.3x worse), but makes no re-checks after it: the state
        follows. A rig whose offset the calibration gets right never pays for the state."""
        self._time_state = True
        if isinstance(self._state, _Running):
            self._state.smoother.start_time_state()
        if self.offset_estimator is not None:
            self.offset_estimator.stop_rechecks()
        log.info("time offset: the smoother follows it as a state from the next keyframe on")

    def _try_init(self, t: int, ff: FeatureFrame) -> NavState | None:
        if self._imu_camera_error is not None:  # final for the run (_imu_disagrees): no start to attempt
            return None
        icfg = self.cfg.init
        ts, gyro, accel = self.imu.window(t - int(icfg.static_window_s * 1e9), t)
        plausible = self._sensors_plausible(ts, gyro, accel, ff)
        # a smooth constant-velocity motion looks still to the IMU: the images must agree
        init = static_initialize(ts, gyro, accel, t, icfg, self.calib.view_headings_body) \
            if plausible and self._looks_still_visually(ff) else None
        if init is not None and self._turn_taken_for_bias(init, ff):
            init = None
        if init is not None and not self._bias_continuous(init):
            init = None
        if init is None and icfg.allow_moving_start:
            init = self.moving_init.add(t, ff, self.imu)  # fed always: it needs a window of consecutive frames
            if init is not None and not plausible:
                init = None
            elif init is not None and not self._bias_continuous(init):
                # the visual alignment's bias is noisy (+-0.03 rad/s over 1 s), but it cannot take a turn for
                # a bias: keep the start, with the last trusted bias
                init = dataclasses.replace(init, gyro_bias=self._state.trusted_bias[1].copy())
        if init is not None and not self._start_bias_plausible(init):
            init = None
        if init is None:
            return None
        return self._start(init, ff)

    def _start_bias_plausible(self, init: InitialState) -> bool:
        """A start whose gyro bias the back end would refuse at its first solve (`_check_plausible`) is not taken:
        a gyro in deg/s is too noisy to look still, so the units check came and went, a moving start took the
        rotation for a 4 rad/s bias, and poses with quality 100 went out until the first solve reset (a review's
        finding). Said once per spell. (The units error is not held across windows that cannot judge it: a reset
        in a steady turn, which looks still, would then block every start until the vehicle hovers.)"""
        bg = float(np.max(np.abs(init.gyro_bias)))
        if bg <= self.bcfg.max_gyro_bias_rad_s:
            self._start_bias_refused = False
            return True
        if not self._start_bias_refused:
            log.error("not initialising: the start's gyro bias is %.3f rad/s, beyond [backend] max_gyro_bias_rad_s "
                      "(%g): a gyro in deg/s, or a start in a steady turn", bg, self.bcfg.max_gyro_bias_rad_s)
        self._start_bias_refused = True
        return False

    def _sensors_plausible(self, ts: np.ndarray, gyro: np.ndarray, accel: np.ndarray, ff: FeatureFrame) -> bool:
        """No initialisation on an IMU whose units or values are wrong: name the likely mistake once.

        A unit mistake (g for m/s^2, deg/s for rad/s) or a dead IMU would otherwise initialise and drift by
        metres while reporting itself healthy."""
        if self._imu_camera_error is not None:
            return False
        if len(ts) < 4:
            return self.sensor_error is None
        icfg = self.cfg.init
        still = is_still(ts, gyro, accel, icfg)
        a_norm = float(np.linalg.norm(accel.mean(axis=0)))
        # still: the norm must be g; in flight only a reading far below g (units of g) is sure to be wrong
        problem = accel_units_problem(a_norm) if still or a_norm < 0.3 * 9.81 else None
        if problem is None:
            # usable images decide whether the vehicle is still, the IMU only where they cannot tell: a steady turn
            # looks still to the IMU (a constant rate), and its rate is no bias. A moving start in a 0.48 rad/s turn
            # logged "not initialising: gyro reads 0.477 rad/s while still ...; the data look like deg/s" as an ERROR
            # on a right gyro (a QA run)
            images_tell = self._usable(ff) and np.isfinite(self._flow_px)
            at_rest = self._flow_px <= self.bcfg.zupt_max_flow_px if images_tell else still
            problem = gyro_units_problem(gyro, at_rest, self.bcfg.max_gyro_bias_rad_s)
        if (problem and _reason_key(problem)) != (self.sensor_error and _reason_key(self.sensor_error)):
            if problem:
                log.error("not initialising: %s", problem)
            elif self.sensor_error:
                log.info("IMU plausible again: initialisation resumes")
        self.sensor_error = problem
        return problem is None

    def _keep_still_window_frame(self, ff: FeatureFrame) -> None:
        """The usable frames of the last `static_window_s` (camera clock), for `_turn_taken_for_bias`, kept on every
        frame so that a start after a reset finds them too. An unusable frame breaks the run: tracks across it are
        not compared (a frame seconds old would stretch the window's rate over its age)."""
        frames = self._still_frames
        if not self._usable(ff):
            frames.clear()
            return
        frames.append(ff)
        t_first = ff.t_ns - int(self.cfg.init.static_window_s * 1e9)
        while len(frames) > 1 and frames[1].t_ns <= t_first:
            frames.popleft()
        self._last_usable_frame_t = ff.t_ns

    def _turn_taken_for_bias(self, init: InitialState, ff: FeatureFrame) -> bool:
        """A still start whose gyro mean the tracks follow as a turn is refused (`rotation_reading`): its bias
        would be the turn. Judged where the turn would move the tracks `static_turn_visible_px` over the window.
        Until the usable frames span the window (the IMU started first, a reset, a bad frame) a start whose rate
        the images could judge waits for them, quietly; one with no usable frame for a window (a covered lens on
        the ground) is the IMU's to decide, as before. A refusal is said once per spell (none for a window before)."""
        icfg = self.cfg.init
        window_s = icfg.static_window_s
        cam = self.calib.cam0
        if not self._usable(ff):
            last = self._last_usable_frame_t
            return self._quiet_wait(ff, last is not None and (ff.t_ns - last) * 1e-9 <= window_s)
        frames = self._still_frames
        span_s = (ff.t_ns - frames[0].t_ns) * 1e-9
        if span_s < 0.9 * window_s:  # the most the rate could move a track over the window, as a turn
            bound_px = float(np.linalg.norm(init.gyro_bias)) * window_s * max(cam.fx, cam.fy) * 1.5
            return self._quiet_wait(ff, bound_px >= icfg.static_turn_visible_px)
        reading = rotation_reading(frames[0], ff, init.gyro_bias, cam.T_body_cam, cam.K)
        if reading is None or reading.predicted_px < icfg.static_turn_visible_px or not reading.rate_is_turn:
            return False
        last, self._turn_refused_t = self._turn_refused_t, ff.t_ns
        if last is None or (ff.t_ns - last) * 1e-9 > window_s:  # a new spell
            log.info("not a still start: the tracks follow the gyro's %.3f rad/s as a turn (moved %.1f px over "
                     "%.2f s, %.1f px from where that turn puts them; a bias would leave them): waiting for a still "
                     "or moving start", reading.rate_rad_s, reading.moved_px, reading.span_s,
                     reading.turn_residual_px)
        return True

    def _quiet_wait(self, ff: FeatureFrame, wait: bool) -> bool:
        """`wait` for the images, unsaid; a wait inside a spell of refusals carries the spell on."""
        last = self._turn_refused_t
        if wait and last is not None and (ff.t_ns - last) * 1e-9 <= self.cfg.init.static_window_s:
            self._turn_refused_t = ff.t_ns
        return wait

    def _bias_continuous(self, init: InitialState) -> bool:
        """After a reset the gyro bias is known: a new one that differs by more than its random walk allows
        is a rotation taken for a bias (a constant-rate turn looks still to the IMU), so it is refused."""
        trusted = self._state.trusted_bias if isinstance(self._state, _Waiting) else None
        if trusted is None:
            return True
        t0, bg0 = trusted
        gap_s = max(init.t_ns - t0, 0) * 1e-9
        rw = self.calib.imu.gyroscope_random_walk
        allowed = self.bcfg.reinit_max_gyro_bias_jump_rad_s + 3.0 * rw * np.sqrt(gap_s)
        jump = float(np.linalg.norm(np.asarray(init.gyro_bias) - bg0))
        if jump <= allowed:
            return True
        if init.method == "static":
            log.info("static re-initialisation refused: gyro bias would jump by %.4f rad/s (allowed %.4f after "
                     "%.1f s): the vehicle is likely turning", jump, allowed, gap_s)
        else:
            log.info("in-motion re-initialisation keeps the last gyro bias: its own differs by %.4f rad/s "
                     "(allowed %.4f after %.1f s)", jump, allowed, gap_s)
        return False

    def _start(self, init: InitialState, ff: FeatureFrame) -> NavState:
        T = init.T_world_body
        v = init.v_world
        w = self._state
        assert isinstance(w, _Waiting)
        if w.anchor is not None:
            # Continue from where the estimate was (carried forward with the IMU when it could be): same
            # position and heading, fresh roll/pitch.
            anchor = w.anchor
            if w.bridge is not None:
                pred = w.bridge.pim.predict(w.bridge.start, w.bridge.bias).pose().matrix()
                gap_s = (init.t_ns - w.bridge.t0_ns) * 1e-9
                if gap_s > BRIDGE_POSITION_MAX_S:
                    pred[:3, 3] = anchor[:3, 3]
                log.info("reset bridged with the IMU over %.2f s: heading %+.1f deg, position %+.2f m", gap_s,
                         np.degrees(yaw_between(pred[:3, :3], anchor[:3, :3])),
                         float(np.linalg.norm(pred[:3, 3] - anchor[:3, 3])))
                anchor = pred
            T, v = reanchored(T, v, anchor)
        static = init.method == "static"
        # a reset keeps what was learnt (the calibration refined, the time state once switched on)
        smoother = VioSmoother(self.refined_calibration(), self.bcfg, time_state=self._time_state)
        est = smoother.initialize(init.t_ns, T, v, init.gyro_bias, init.accel_bias,
                                  sigma_v_m_s=0.01 if static else 0.1, sigma_bg=0.005 if static else 0.02, features=ff,
                                  omega_body=self._omega(init.t_ns, init.gyro_bias),
                                  applied_offset_ns=int(init.t_ns) - int(ff.t_ns),
                                  stamp_sigma_ms=self._stamp_sigma_ms(ff))
        # only now: a restart that fails keeps the waiting state (and its bridge) for the next attempt
        self._state = _Running(smoother, init.t_ns, init.t_ns if self._usable(ff) else None)
        self._start_motion_check(init.t_ns, est, ff)
        self.moving_init.clear()
        # "up" in the IMU's axes rather than Euler roll/pitch, which read -50/-89 deg for an IMU with x up
        log.info("initialised (%s) at t=%d: up is (%+.3f %+.3f %+.3f) in the IMU frame, gyro bias (%.4f %.4f %.4f) "
                 "rad/s", init.method, init.t_ns, *T[2, :3], *init.gyro_bias)
        if self._stereo_loss is not None:  # started at rest with the right camera still out: say what runs now
            log.warning("stereo: still none at the start: %s", self._without_stereo())
        return self._after_keyframe(init.t_ns, est, ff)

    def _after_keyframe(self, t: int, est, ff: FeatureFrame, deferred: bool = False) -> NavState:
        """Book-keeping after a keyframe's solve; `deferred`: the solve ran on the frame after the keyframe's, which
        has already done what belongs to the keyframe's own frame (the keyframe time, the tracker's mark)."""
        run = self._state
        run.last_kf_t = t
        self.keyframes += 1
        self._was_keyframe = not deferred
        first = run.pim is None  # (re)start: always a marginal, at once
        if not first:  # grown up to this keyframe; replaced on the next frame when a marginal is due
            run.kf_cov_pose, run.kf_cov_vel = self._grown_covariance(run.pim)
        run.marginal_due = False
        if first:
            self._marginal()
        elif (self.keyframes - 1) % self.bcfg.covariance_every_kf == 0:
            run.marginal_due = True
        self._cov_pose, self._cov_vel = run.kf_cov_pose, run.kf_cov_vel
        run.pim = gtsam.PreintegratedCombinedMeasurements(self._interval_params(t), est.bias)
        if not deferred:
            self._mark_keyframe()
        pose = est.pose.matrix()
        bias = est.bias
        self.gyro_prior.set_gyro_bias(bias.gyroscope())  # no gyro-bias rotation as fake parallax
        # the newer samples are applied when an IMU-rate state is asked for (_propagate_to)
        self.propagator.reset(t, pose, est.velocity, bias.gyroscope(), bias.accelerometer(), self.imu.at(t))
        self._update_health(t, ff)
        st = self._frame_state(t, pose, est.velocity, bias)
        self._solved_kf = SolvedKeyframe(int(ff.t_ns), ff, st)
        return st

    def _mark_keyframe(self) -> None:
        if self.tracker is not None and hasattr(self.tracker, "mark_keyframe"):
            self.tracker.mark_keyframe()

    def _use_params(self, params: gtsam.PreintegrationCombinedParams) -> None:
        """Noise of the pre-integration from here on; the IMU-rate covariance growth follows it."""
        self._params_now = params
        self._gyro_var_diag = np.diag(np.diag(np.asarray(params.getGyroscopeCovariance())))
        self._gyro_var_mean = float(np.trace(self._gyro_var_diag)) / 3.0
        self._accel_var_diag = np.diag(np.diag(np.asarray(params.getAccelerometerCovariance())))

    def _interval_params(self, t: int) -> gtsam.PreintegrationCombinedParams:
        """Pre-integration noise for the keyframe interval starting at t.

        With `imu_noise_adaptive`, once the IMU samples (2 s windows, per-axis median over the last 10 s) show a
        white noise above `imu_noise_adaptive_above` times the calibration's density on some axis, each axis's
        white noise is `imu_noise_adaptive_gain` times what it shows (never below `imu_noise_scale`), until the
        noisiest axis falls below 0.8 of the threshold. Why: an IMU factor that claims datasheet noise on a
        shaking airframe outweighs the images it should be checked against, and the smoother's covariance then
        claims more than it knows (docs/estimator.md, "IMU noise on a shaking airframe"). Below the threshold (a
        normal airframe: the simulator's realistic variant reads 7-12x) the configured noise is left exactly as
        it is. Before the median may decide, `_provisional_params`."""
        b = self.bcfg
        if not b.imu_noise_adaptive:
            return self.params
        k = measured_white_scale(self.calib.imu, *self.imu.window(t - IMU_NOISE_WINDOW_NS, t))
        if k is None:
            return self._params_now
        readings = self._white_readings
        readings.append((t, k))
        while readings and readings[0][0] < t - IMU_NOISE_HISTORY_NS:
            readings.popleft()
        # median over ~10 s: a 2 s window of a normal airframe reads up to ~2x its typical level
        now = k
        k = np.median(np.array([r for _, r in readings]), axis=0)
        level = float(np.max(k))
        if self.white_scale is None and len(readings) < IMU_NOISE_MIN_READINGS:
            return self._provisional_params(now)
        if self.white_scale is None and level <= b.imu_noise_adaptive_above:
            return self._configured_params()  # a provisional noise the median did not confirm goes too
        if self.white_scale is not None and level < 0.8 * b.imu_noise_adaptive_above:
            log.info("IMU white noise down to %.1fx the calibration's density: pre-integration noise back to "
                     "imu_noise_scale %.1f", level, b.imu_noise_scale)
            self.white_scale = None
            return self._configured_params()
        if self.white_scale is None:
            log.info("IMU white noise reads %.1fx the calibration's density (gyro %s, accel %s: vibration): "
                     "pre-integration noise follows it", level, np.round(k[:3], 1), np.round(k[3:], 1))
            if isinstance(self._state, _Running):  # what the quieter factors said about cam1 is overconfident
                self._state.smoother.imu_noise_raised()
        self.white_scale = self._follow_white_noise(k, self.white_scale)
        return self._params_now

    def _configured_params(self) -> gtsam.PreintegrationCombinedParams:
        """The configured noise (the same parameter object, so that its replays stay bit for bit)."""
        if self._params_now is not self.params:
            self._use_params(self.params)
        return self._params_now

    def _follow_white_noise(self, reading: np.ndarray, held: np.ndarray | None) -> np.ndarray:
        """The white-noise scale a reading asks for (gain, clipped to [imu_noise_scale, imu_noise_max_scale]), in
        use from now on; `held` kept as it is when the new one is within 5 % of it (no new parameter object)."""
        b = self.bcfg
        scale = np.clip(reading * b.imu_noise_adaptive_gain, b.imu_noise_scale, b.imu_noise_max_scale)
        if held is not None and np.all(np.abs(scale / held - 1.0) < 0.05):
            return held
        self._use_params(combined_params(self.calib.imu, b.imu_noise_scale, white_scale=scale))
        return scale

    def _provisional_params(self, now: np.ndarray) -> gtsam.PreintegrationCombinedParams:
        """Before the adaptive noise may engage (IMU_NOISE_MIN_READINGS keyframes), an interval whose own 2 s window
        reads above IMU_NOISE_ALONE_ABOVE times the threshold gets the white noise it reads; otherwise the configured
        noise.

        Why: the first keyframes of a shaking airframe come before the median decides, and factors claiming the
        configured 2x density against 30-85x in the samples pulled the accelerometer bias 0.16-0.28 m/s^2 off within
        1-2 s (a 1.3 deg tilt that took ~6 s to fade) and, once, cam1 (an exact stereo calibration let go at 3.2 s):
        QA flights 208, 216 and 304, docs/estimator.md. One window varies up to ~2x about its airframe's level, so
        one above twice the threshold cannot be an airframe below it; between once and twice (the hard variant's
        14-37x, V1_02's motors starting) one window does not decide, and the quiet factors there sped the gyro bias's
        convergence from the static start (aggressive-hard-s1 30 mm, 42 with them raised at 1x). The first windows
        of a normal airframe (4-11x realistic, 3-16x EuRoC V1_01/V1_02) keep the configured noise object exactly;
        the median alone still engages the noise (the log line, the stereo check's restart) and lets it go."""
        if float(np.max(now)) <= IMU_NOISE_ALONE_ABOVE * self.bcfg.imu_noise_adaptive_above:
            return self._configured_params()
        held = self._provisional_scale if self._params_now is not self.params else None
        self._provisional_scale = self._follow_white_noise(now, held)
        return self._params_now

    def _marginal(self) -> None:
        """The newest keyframe's marginal covariances replace the grown ones (a few ms, up to ~10)."""
        run = self._state
        run.marginal_due = False
        self.marginals += 1
        try:
            run.kf_cov_pose, run.kf_cov_vel = run.smoother.marginal_covariances()
        except SmootherFailure as e:
            log.debug("no covariance at keyframe: %s", e)

    def _usable(self, ff: FeatureFrame | None) -> bool:
        return ff is not None and ff.tracking_ok and len(ff.ids) >= self.bcfg.min_tracks_ok

    def _update_health(self, t: int, ff: FeatureFrame | None) -> None:
        n = len(ff.ids) if ff is not None and ff.tracking_ok else 0
        self._track_quality = float(np.clip(n / (4 * self.bcfg.min_tracks_ok), 0.0, 1.0))
        run = self._state
        if self._usable(ff):
            run.last_vision_t = t
        self._tracking = run.last_vision_t is not None and \
            (t - run.last_vision_t) * 1e-9 <= self.bcfg.vision_timeout_s

    def _quality_of(self, cov_pose: np.ndarray, tracking: bool) -> int:
        """0..100: the share of good tracks, capped by the position uncertainty (halves per doubling of the
        sigma beyond quality_sigma_m), so the autopilot's quality gate sees what the covariance says."""
        if not tracking:
            return 0
        q_cov = covariance_quality(cov_pose, self.bcfg.quality_sigma_m)
        return max(1, min(100, round(100 * min(self._track_quality, q_cov))))

    def _looks_still_visually(self, ff: FeatureFrame) -> bool:
        """Images agree with stillness. Without tracks they carry no information: at the first start the IMU
        alone decides (a covered lens on the ground); after a reset it does not, because a constant-rate
        turn or a constant-velocity flight looks still to the IMU and would become a bias."""
        if not self._usable(ff):
            return self.reset_counter == 0
        return self._flow_px <= self.bcfg.zupt_max_flow_px

    def _stamp_too_uncertain(self, t: int, ff: FeatureFrame) -> bool:
        """Is the frame's stamp too uncertain for a keyframe (`keyframe_max_stamp_sigma_ms`)? Such a frame (a USB
        stall's burst, 50-300 ms late) puts its observations anywhere along ~sigma x speed of the path: the stamp
        link frees its camera pose, but keyframes on them still took a flight with a 150 ms stall every second to
        162 mm (37 without them) and let the stereo check go on another. The next frame, on time, is the keyframe;
        the bound (2 x keyframe_max_interval_s since the last) keeps a camera whose every stamp is that bad tracked."""
        b = self.bcfg
        off_ns = max(self.frame_clock.stamp_sigma_ns(int(ff.t_ns)), self.frame_clock.stamp_late_ns(int(ff.t_ns)))
        return 0 < b.keyframe_max_stamp_sigma_ms * 1e6 < off_ns \
            and (t - self._state.last_kf_t) * 1e-9 < 2 * b.keyframe_max_interval_s

    def _is_keyframe(self, t: int, ff: FeatureFrame) -> bool:
        return self._keyframe_by_motion(t, ff) and not self._stamp_too_uncertain(t, ff)

    def _keyframe_by_motion(self, t: int, ff: FeatureFrame) -> bool:
        """Would the frame be a keyframe by its time, parallax and tracks alone (its stamp aside)?"""
        b = self.bcfg
        dt = (t - self._state.last_kf_t) * 1e-9
        if dt >= b.keyframe_max_interval_s:
            return True
        if dt < b.keyframe_min_interval_s:  # the solve is the expensive part: bounded rate
            return False
        if not ff.tracking_ok:
            return False
        return ff.parallax_px >= b.keyframe_min_parallax_px or len(ff.ids) < b.keyframe_min_tracks

    def refined_calibration(self) -> StereoCalibration:
        """The calibration with the smoother's refined extrinsics (`backend.refine_extrinsics`), else as given."""
        if self._refined is None:
            return self.calib
        T0, T1, _, k = self._refined
        cams = [c.with_T_body_cam(T) for c, T in ((self.calib.cam0, T0), (self.calib.cam1, T1))]
        if k is not None:
            cams = [dataclasses.replace(c, fx=float(v[0]), fy=float(v[1]), cx=float(v[2]), cy=float(v[3]))
                    for c, v in zip(cams, k)]
        return dataclasses.replace(self.calib, cam0=cams[0], cam1=cams[1])

    def _note_stereo_check(self, f: StereoFinding | None) -> None:
        """Keep the stereo check's newest reading; say it once when it lets go of the calibration."""
        if f is None or f is self._stereo_finding:
            return
        self._stereo_finding = f
        log.debug("stereo check t=%d: %s%s", f.t_ns, f.describe(),
                  " -> let go" if f.released else " -> implausible, held" if f.implausible else "")
        if f.implausible:
            self._stereo_implausible += 1
            if self._stereo_implausible == 1:
                log.warning("stereo check: the data pull the right camera further from the calibration (%s) than "
                            "a stereo pair bends in flight (stereo_check_max_deg %g deg): held as calibrated, since "
                            "the pair is what holds the scale; %s", f.describe(), self.bcfg.stereo_check_max_deg,
                            IMPLAUSIBLE_STEREO_WHY)
        if f.released:
            self._stereo_released.append(f)
            log.warning("stereo check: the right camera disagrees with the calibration (%s): depths and scale were "
                        "biased until now; refining cam1 in flight from here. Fix the stereo calibration "
                        "(docs/calibration.md: vio calib check CALIB DATASET --disparity)", f.describe())

    def stereo_check_stats(self) -> dict | None:
        """The stereo check's newest reading and when it let go of the calibration (None: check off or no
        reading yet), for the replay's stats and status."""
        f = self._stereo_finding
        if f is None and not self._stereo_released:
            return None
        def at_s(r: StereoFinding) -> float | None:
            return round((r.t_ns - self._t_first_ns) * 1e-9, 3) if self._t_first_ns is not None else None

        out: dict = {"released_at_s": [at_s(r) for r in self._stereo_released],
                     "released_readings": [r.describe() for r in self._stereo_released],
                     "released_disparity_px": [r.disparity_px for r in self._stereo_released],
                     "implausible_readings": self._stereo_implausible}
        if f is not None:
            out.update(disparity_px=f.disparity_px, sigma_px=f.sigma_px, at_s=at_s(f), reading=f.describe(),
                       focal_px=[list(x) for x in f.focal_px] if f.focal_px else None)
        return out

    def motion_check_stats(self) -> dict | None:
        """What the motion check (`[backend] motion_check`) read over the flight, every smoother run's check added up,
        for the replay's stats (None: the check is off)."""
        if not self.bcfg.motion_check:
            return None
        run = self._state
        t = run.motion.tally(self._motion_before) if isinstance(run, _Running) and run.motion is not None \
            else self._motion_before

        def at_s(r: MotionReading) -> float | None:
            return round((r.t_ns - self._t_first_ns) * 1e-9, 3) if self._t_first_ns is not None else None

        return {"readings": t.readings, "disagreeing_keyframes": t.disagreeing, "resets": t.resets,
                "max_sigma": None if t.worst is None else round(t.worst.n_sigma, 2),
                "max_sigma_at_s": None if t.worst is None else at_s(t.worst),
                "max_sigma_reading": None if t.worst is None else t.worst.describe(),
                "max_m_s": None if t.widest is None else round(t.widest.gap_m_s, 3),
                "max_m_s_at_s": None if t.widest is None else at_s(t.widest)}

    def refinement_stats(self) -> dict | None:
        """Refined extrinsics and how far they moved from the calibration, for the replay's stats."""
        if self._refined is None:  # nothing refined (a stereo check that held: stereo_check_stats says why)
            return None
        T0, T1, n, k = self._refined
        d0 = np.linalg.inv(self.calib.cam0.T_body_cam) @ T0
        turn = so3_log((self.calib.T_cam1_cam0 @ np.linalg.inv(T0) @ T1)[:3, :3])  # about cam1's own axes
        out = {"T_body_cam0": T0.tolist(), "T_body_cam1": T1.tolist(), "refining_keyframes": int(n),
               "cam0_change_deg": float(np.degrees(np.linalg.norm(so3_log(d0[:3, :3])))),
               "cam0_change_mm": float(1e3 * np.linalg.norm(d0[:3, 3])),
               "stereo_change_deg": float(np.degrees(np.linalg.norm(turn))),
               # a turn about cam1's y axis moves every right pixel sideways: the disparity bias taken out
               # (positive: the calibration's disparities were too large, its depths too short)
               "disparity_px": float(turn[1] * self.calib.cam1.fx)}
        sigma = self._state.smoother.stereo_rotation_sigma_rad() if isinstance(self._state, _Running) else None
        if sigma is not None:
            out["stereo_sigma_deg"] = np.degrees(sigma).tolist()
            out["disparity_sigma_px"] = float(sigma[1] * self.calib.cam1.fx)
        if k is not None:
            out["intrinsics_fx_fy_cx_cy"] = [np.asarray(v, float).tolist() for v in k]
        return out

    def _track(self, t: int, prev_t: int, ff: FeatureFrame, offset_solved: bool) -> NavState | None:
        run = self._state
        self.imu.integrate(run.pim, prev_t, t)
        if run.just_solved:  # the last frame's keyframe was this frame's back-end work: its dues wait a frame
            run.just_solved = False
        elif run.smoother.marginalize_due:  # the last keyframe's marginalisation, here rather than in its solve
            run.smoother.marginalize()
        elif run.marginal_due:  # the last keyframe's marginal, computed here rather than on top of its solve
            self._marginal()
        elif run.smoother.check_due and not offset_solved:
            # the last keyframe's stereo check, on a frame that carries no other back-end work (the time-offset
            # solves do not wait for it, so they fall on the frames they fell on before the check moved here)
            self._note_stereo_check(run.smoother.check_stereo())
        self._was_keyframe = False
        if not self._is_keyframe(t, ff):
            # said in the stats: a frame the stamp rule kept from being a keyframe (not every uncertain frame: the
            # count said 15 of each 16 frames where 8 would have been one, a review's finding)
            self.frame_clock.stats.keyframes_skipped += self._keyframe_by_motion(t, ff)
            st = self._predicted_state(t, ff)
        else:
            icfg = self.cfg.init
            ts, gyro, accel = self.imu.window(t - int(icfg.static_window_s * 1e9), t)
            # Slow forward flight looks still to both the IMU (constant velocity) and the images (little flow
            # near the focus of expansion), so the estimated speed must agree too.
            last = run.smoother.last
            v_pred = run.pim.predict(gtsam.NavState(last.pose, last.velocity), last.bias).velocity()
            still = (is_still(ts, gyro, accel, icfg) and ff.tracking_ok and self._flow_px <= self.bcfg.zupt_max_flow_px
                     and float(np.linalg.norm(v_pred)) <= self.bcfg.zupt_max_speed_m_s)
            omega = self._omega(t, last.bias.gyroscope())
            if self.bcfg.solve_next_frame:
                # This frame sends the IMU prediction, as a frame that is no keyframe does; the next frame solves
                # before its front end (`_solve_deferred_first`), so no frame pays stereo matching and the solve
                # together. The tracker measures parallax from this frame on.
                st = self._predicted_state(t, ff)
                run.deferred = _DeferredKeyframe(t, ff, still, omega, t - int(ff.t_ns))
                run.last_kf_t = t
                self._was_keyframe = True
                self._mark_keyframe()
            else:
                est = run.smoother.add_keyframe(t, run.pim, ff, zero_velocity=still, omega_body=omega,
                                                applied_offset_ns=t - int(ff.t_ns),  # the stamp's offset
                                                stamp_sigma_ms=self._stamp_sigma_ms(ff))
                st = self._after_solve(t, est, ff)
        vt = run.last_vision_t
        if vt is None or (t - vt) * 1e-9 > self.bcfg.lost_timeout_s:
            lost = "since the start" if vt is None else f"for {(t - vt) * 1e-9:.2f} s"
            self.reset(f"tracking lost: no usable camera frame {lost}")
        return st

    def _stamp_sigma_ms(self, ff: FeatureFrame) -> float:
        """How far the keyframe's stamp may be off its exposure (the frame clock's measure; `frame_stamp_link`)."""
        return self.frame_clock.stamp_sigma_ns(int(ff.t_ns)) * 1e-6 if self.bcfg.frame_stamp_link else 0.0

    def _predicted_state(self, t: int, ff: FeatureFrame) -> NavState:
        """The frame's state from the last solved keyframe and the IMU since then (a frame that is not solved)."""
        run = self._state
        last = run.smoother.last
        nav = run.pim.predict(gtsam.NavState(last.pose, last.velocity), last.bias)
        self._cov_pose, self._cov_vel = self._grown_covariance(run.pim)
        self._update_health(t, ff)
        return self._frame_state(t, nav.pose().matrix(), np.asarray(nav.velocity()), last.bias)

    def _solve_deferred_first(self) -> float:
        """Solve the keyframe chosen on the last frame before this frame's front end, which then gets the solved
        gyro bias for its rotation prior (as after a solve on the keyframe's own frame; a bias one solve old
        changed the tracks and cost surveys 10-40 % of ATE); returns the ms it took (back-end time)."""
        run = self._state
        if not isinstance(run, _Running) or run.deferred is None:
            return 0.0
        t0 = time.perf_counter()
        try:
            self._solve_deferred(run)
            run.just_solved = True
        except SmootherFailure as e:
            self.reset(str(e), bridge=e.state_ok)
        return (time.perf_counter() - t0) * 1e3

    def _solve_deferred(self, run: _Running) -> None:
        """Solve the keyframe chosen on the last frame: the same factors, and the next interval's pre-integration
        started at it with the solved bias, as a solve on the keyframe's own frame gives."""
        d, run.deferred = run.deferred, None
        est = run.smoother.add_keyframe(d.t, run.pim, d.ff, zero_velocity=d.still, omega_body=d.omega_body,
                                        applied_offset_ns=d.applied_offset_ns,
                                        stamp_sigma_ms=self._stamp_sigma_ms(d.ff))
        self._after_solve(d.t, est, d.ff, deferred=True)

    def _after_solve(self, t: int, est, ff: FeatureFrame, deferred: bool = False) -> NavState:
        run = self._state
        self._check_plausible(est)
        if run.smoother.time_state and not self._offset_handed_over:
            self._hand_offset_to_state()
        if est.T_body_cam0 is not None:
            self._refined = (est.T_body_cam0, est.T_body_cam1, run.smoother.extrinsic_keyframes, est.intrinsics)
        self._check_motion(t, est, ff)
        self._note_stereo_check(run.smoother.stereo_finding)  # one the solve read (a check still due there)
        return self._after_keyframe(t, est, ff, deferred)

    def _start_motion_check(self, t: int, est, ff: FeatureFrame) -> None:
        """A new smoother run's motion check, from its first keyframe (vio.motion_check)."""
        b = self.bcfg
        if not b.motion_check:
            return
        run = self._state
        run.motion = MotionCheck(self.calib.cam0.K, self.calib.baseline_m, n_sigma=b.motion_check_sigma,
                                 min_m_s=b.motion_check_min_m_s, scale_sigma=b.motion_check_scale_sigma,
                                 confirm=b.motion_check_confirm)
        self._check_motion(t, est, ff)

    def _check_motion(self, t: int, est, ff: FeatureFrame) -> None:
        """The smoother's keyframe against the stereo pair's own motion: a SmootherFailure (not bridged: the state
        is what is wrong) once they have disagreed for motion_check_confirm keyframes. Reads only."""
        chk = self._state.motion
        if chk is None:
            return
        T_body_cam0 = self._refined[0] if self._refined is not None else self.calib.cam0.T_body_cam
        failure = chk.add(t, ff, est.pose.matrix() @ T_body_cam0)
        if failure is not None:
            # the restart continues from where the stereo pair says the vehicle is, not from the runaway's pose
            self._reset_anchor = chk.stereo_anchor() @ np.linalg.inv(T_body_cam0)
            raise SmootherFailure(failure, state_ok=False)

    def _grown_covariance(self, pim: gtsam.PreintegratedCombinedMeasurements) -> tuple[np.ndarray, np.ndarray]:
        """Last keyframe covariance grown by the IMU pre-integration since then.

        A marginal from the smoother costs milliseconds, so it is computed only every
        `covariance_every_kf` keyframes; in between, the pre-integration noise (rotation, position,
        velocity) and the keyframe's velocity uncertainty times dt are added, with the keyframe
        covariance rotated into the new body frame (translation coupling of the adjoint ignored).
        Conservative: it grows until the next marginal replaces it.
        """
        C = np.asarray(pim.preintMeasCov())
        dR = pim.deltaRij().matrix()
        dt = pim.deltaTij()
        run = self._state
        R_wi = run.smoother.last.pose.rotation().matrix()
        R_wj = R_wi @ dR
        A = np.zeros((6, 6))
        A[:3, :3] = A[3:, 3:] = dR.T
        cov = A @ run.kf_cov_pose @ A.T
        cov[:3, :3] += C[:3, :3]
        cov[3:, 3:] += dR.T @ C[3:6, 3:6] @ dR + dt * dt * (R_wj.T @ run.kf_cov_vel @ R_wj)
        cov_v = run.kf_cov_vel + R_wi @ C[6:9, 6:9] @ R_wi.T
        return 0.5 * (cov + cov.T), 0.5 * (cov_v + cov_v.T)

    def _check_plausible(self, est) -> None:
        b = self.bcfg
        speed = float(np.linalg.norm(est.velocity))
        bg = float(np.max(np.abs(est.bias.gyroscope())))
        ba = float(np.max(np.abs(est.bias.accelerometer())))
        if not np.all(np.isfinite(est.pose.matrix())) or speed > b.max_speed_m_s:
            raise SmootherFailure(f"implausible speed {speed:.1f} m/s", state_ok=False)
        if bg > b.max_gyro_bias_rad_s or ba > b.max_accel_bias_m_s2:
            raise SmootherFailure(f"implausible bias: gyro {bg:.3f} rad/s, accel {ba:.3f} m/s^2", state_ok=False)

    # -- outputs ---------------------------------------------------------------------------------------
    def _frame_state(self, t: int, T_world_body: np.ndarray, v_world: np.ndarray,
               bias: gtsam.imuBias.ConstantBias) -> NavState:
        gyro_bias = np.asarray(bias.gyroscope(), float)
        T = np.asarray(T_world_body, float)
        self._cov_state = (int(t), T[:3, :3].copy())
        tracking = self._tracking_at(t)
        return NavState(t_ns=int(t), T_world_body=T, v_world=np.asarray(v_world, float),
                        gyro_bias=gyro_bias, accel_bias=np.asarray(bias.accelerometer(), float),
                        cov_pose=self._cov_pose, cov_vel=self._cov_vel, reset_counter=self.reset_counter,
                        quality=self._quality_of(self._cov_pose, tracking), omega_body=self.imu.at(t)[0] - gyro_bias,
                        tracking=tracking)

    def _propagated_state(self) -> NavState:
        p = self.propagator
        cov_pose, cov_vel = self._imu_rate_covariance(int(p.t_ns), p.R)
        tracking = self._tracking_at(int(p.t_ns))
        return NavState(t_ns=int(p.t_ns), T_world_body=p.pose(), v_world=p.v.copy(), gyro_bias=p.gyro_bias,
                        accel_bias=p.accel_bias, cov_pose=cov_pose, cov_vel=cov_vel,
                        reset_counter=self.reset_counter, quality=self._quality_of(cov_pose, tracking),
                        omega_body=p.omega.copy(), tracking=tracking)

    def _imu_rate_covariance(self, t: int, R_now: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The newest frame state's covariance grown by dead reckoning up to t (IMU-rate states).

        Between frames this adds little; when frames stop it is what grows: gyro noise into attitude,
        velocity uncertainty and accel noise into position, and the attitude error times gravity into
        velocity and position (first order, cross terms ignored, so it errs large). The frame covariance
        is not re-rotated into the newer body axes (it changes little within the second this runs for).
        Lean on purpose: it runs for every IMU sample (about 10 us)."""
        if self._cov_state is None or t <= self._cov_state[0]:
            return self._cov_pose, self._cov_vel
        dt = (t - self._cov_state[0]) * 1e-9
        cov = self._cov_pose.copy()
        var_th = float(np.trace(cov[:3, :3])) / 3.0 + self._gyro_var_mean * dt  # attitude variance per axis
        cov[:3, :3] += self._gyro_var_diag * dt
        # tilt: an attitude error dtheta makes a horizontal accel error g*dtheta (vertical: second order)
        tilt = self._g2_horizontal * var_th
        acc = self._accel_var_diag + tilt * dt  # accel-like variance rate in world axes
        cov_v = self._cov_vel + acc * dt
        cov_p_w = self._cov_vel * (dt * dt) + self._accel_var_diag * (dt ** 3 / 3.0) + tilt * (dt ** 4 / 4.0)
        cov[3:, 3:] += R_now.T @ cov_p_w @ R_now
        return cov, cov_v


def median_flow_px(prev: FeatureFrame | None, cur: FeatureFrame) -> float:
    """Median image motion of the tracks shared by two frames (inf when there is nothing to compare)."""
    if prev is None or not (prev.tracking_ok and cur.tracking_ok):
        return float("inf")
    _, ip, ic = np.intersect1d(prev.ids, cur.ids, return_indices=True)
    if len(ip) < 5:
        return float("inf")
    return median(np.linalg.norm(cur.uv0[ic] - prev.uv0[ip], axis=1))


def stereo_check_line(check: dict | None, then: str = " (calibration line below)") -> str | None:
    """One line on what the stereo check (`[backend] stereo_check`) found: whether the flight showed the stereo
    calibration's disparities off (None: no check, or no reading yet); `then` follows a let-go's line."""
    if not check:
        return None
    if check["released_at_s"]:
        return (f"stereo check: the right camera disagreed with the calibration at {check['released_at_s'][0]:.1f} s "
                f"({check['released_readings'][0]}): cam1 refined in flight from then{then}")
    held = check.get("implausible_readings", 0)
    held_said = (f"; {held} reading{'s' * (held > 1)} beyond stereo_check_max_deg (the estimate's pull, not the "
                 "camera's) held") if held else ""
    if "disparity_px" in check:
        return f"stereo check: {check['reading']} (1 sigma) at {check['at_s']:.1f} s: calibration kept{held_said}"
    return None


def motion_check_line(check: dict | None) -> str | None:
    """One line on what the motion check (`[backend] motion_check`) read over the flight (None: check off)."""
    if not check:
        return None
    if not check["readings"]:
        return "motion check: no keyframe compared (no stereo points seen again)"
    resets = check["resets"]
    return (f"motion check: {check['readings']} keyframes compared, {check['disagreeing_keyframes']} disagreeing, "
            f"{resets} reset{'s' * (resets != 1)}; largest {check['max_sigma']:.1f} sigma "
            f"at {check['max_sigma_at_s']:.1f} s, {check['max_m_s']:.3f} m/s apart at {check['max_m_s_at_s']:.1f} s")
