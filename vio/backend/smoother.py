"""Fixed-lag visual-inertial smoother on keyframes (GTSAM IncrementalFixedLagSmoother).

State per keyframe i: pose X(i) = T_world_body, velocity V(i) (world), IMU bias B(i); consecutive
keyframes are tied by a CombinedImuFactor (bias random walk inside). Each stereo track becomes a landmark
L(j) in the world, created from its stereo depth the first time it is seen at a keyframe and observed by
Huber-robust pinhole projection factors in cam0 (and cam1 where the front end found a stereo match),
with body_P_sensor = T_body_cam so the smoother works on body poses directly, and a weak prior at its
first position (`landmark_prior_sigma_m`) that keeps the linear system well posed.

Mono landmarks (`mono_landmarks`, or on a keyframe with fewer than `mono_below_stereo` stereo matches): a
track without usable stereo depth (no right image, beyond
`max_depth_m`, no stereo match) has its cam0 pixels remembered at each keyframe; once it has been seen at
MONO_MIN_VIEWS keyframes inside the lag whose rays differ by `mono_min_parallax_deg`, it is triangulated
from those keyframes' current estimates (gtsam.triangulatePoint3, refined) and becomes an ordinary landmark
with the same Huber-robust projection factors, one per remembered keyframe. So far points, which constrain
rotation best, and everything seen while the right camera is out keep feeding the smoother.

Online extrinsic refinement (`refine_extrinsics`): T_body_cam0 and T_body_cam1 become variables E(0),
E(1) with priors from the calibration's uncertainty (`extrinsic_sigma_rad`; the translation is held unless
`refine_extrinsic_translation`, then `extrinsic_sigma_m`), tied by
a between factor on T_cam0_cam1 that holds the stereo extrinsic (tight) or lets it move by
`stereo_sigma_*` (`refine_stereo_extrinsic`). Projection factors then read the camera pose as X(j) * E
(gtsam_unstable's ProjectionFactorPPP). The extrinsic is observable only when the body turns about two
axes and moves; the gate: the keyframes inside the lag must span `extrinsic_min_rotation_deg` of rotation
about the second most excited axis (smallest but one singular value of their rotation vectors about the
newest one). Keyframes that fail the gate (hover, straight flight) use fixed projection factors at the
current extrinsic estimate, so E only keeps its prior and what earlier motion taught it (marginalised
into it as keyframes leave the lag): hovering neither refines nor corrupts it. E's stamp moves with
every keyframe, so it never leaves the window. With `refine_intrinsics` the focal lengths of both cameras
are variables too (Cal3_S2, ProjectionFactorPPPC, under the same gate); the principal point is held unless
`refine_principal_point`, because shifting it moves the image as turning the camera does. With
`refine_stereo_rotation` alone, only E(1) is a variable (cam1's rotation, on every keyframe): a principal point
or mount that drifted biases every disparity, which only this takes out (docs/estimator.md).
With `refine_extrinsics` the stereo check holds cam1's rotation relative to cam0 instead (a removable tight
between factor E(0) -> E(1) over the loose stereo one): the rig turns on the body under the motion gate while the
pair stays as calibrated until the data show it off, read from the keyframes that pass the gate.
The stereo check (`stereo_check`, when neither refinement is asked for) keeps that E(1), and with
`stereo_check_focal` cam1's intrinsics K(1) too, but holds cam1's rotation and focal lengths at the calibration with
tight priors; every `stereo_check_every` keyframes the holds' pull and the joint marginal say where the data alone
would put them (a score test), and when that stands out (`stereo_check_px`, `stereo_check_sigma`) at
`stereo_check_confirm` checks in a row the hold factors are removed, so cam1 is refined from then on with everything
the flight has shown about it, while a good calibration is never moved by the refinement's wander.

Time offset as a state (`time_offset_state`): the images are stamped with the applied camera-IMU offset
(the calibration's, or the in-flight gyro estimate's), and what is left of it, d(i) = true - applied, is a
variable D(i) per keyframe, in ms, with its rate S(i) (a clock's skew, ms/s): d(j) = d(i) + s(i) dt plus a
random walk (`time_offset_walk_ms`), s a random walk of its own (`time_offset_rate_walk_ms`; 0: no rate,
d a plain random walk); a change of the applied offset between keyframes enters as a known step. The
projections then see a camera-time body pose C(i) = X(i) * Exp(xi(i) d(i)), with xi(i) = (gyro,
body-frame velocity) at the keyframe: the body's twist, so d is observed exactly where it matters (fast
turns, fast flight) and keeps its prior when hovering (xi ~ 0: the offset changes nothing there). Below
`time_offset_link_min_rate` and `time_offset_link_min_speed` xi is taken as 0 (C(i) = X(i), d only walks
on), and the state itself starts at the first keyframe above them: on survey flights (0.1 rad/s, 0.4 m/s)
a weakly observed d soaked up other errors (it ended up to 4 ms off, ATE up to 1.6x), and a survey that
never moves that fast has no time variables at all (the same trajectory as without the state). A tight
linear factor holds C(i) to that model (what VINS-Fusion does with its feature-velocity compensation,
written on the pose instead of on every observation: one factor per keyframe, not per pixel). X(i) stays
the IMU-time state that the outputs and the IMU factors use.

Landmark lifetime: every variable carries a time stamp and the smoother marginalises what falls out of
the lag. A landmark's stamp is moved to its newest observation, so it leaves the window together with
the last keyframe that saw it; a track seen again after its landmark left gets a fresh landmark. What falls
out of the lag leaves on every `marginalize_every_kf`-th keyframe (by default every third), the window growing
past the lag by up to two keyframes in between: a keyframe's factors touch most of the window anyway, and with a
marginalisation too iSAM2 re-linearises and re-eliminates all of it (gtsam switches to a batch step above 65 %
of the variables), which it then does on about one update in seven instead of three in four (an update 11.2 ->
9.5 ms on the 40 s aggressive flight). Variables past the lag take no new factors, so the lag keeps its meaning.
With `marginalize_between_frames` the estimator runs each marginalisation in an update of its own on the frame
after its keyframe (`marginalize`), so that no keyframe's solve carries one.
"""

from __future__ import annotations

import logging
from collections import deque
from dataclasses import dataclass

import gtsam
import numpy as np
from gtsam.symbol_shorthand import B, C, D, E, L, S, V, X

from vio.calibration import StereoCalibration
from vio.config import BackendConfig
from vio.types import FeatureFrame

log = logging.getLogger(__name__)

# gtsam's C++ exceptions (IndeterminantLinearSystemException, ValuesKeyDoesNotExist, ...) reach Python
# through pybind11 as these built-in types; nothing else is caught.
GTSAM_ERRORS = (RuntimeError, ValueError, IndexError)


class SmootherFailure(Exception):
    """The optimisation failed or produced an implausible state: the estimator must reset.

    `state_ok`: the last state before the failure can be trusted (a numerical failure), so the estimator
    may carry it across the reset with the IMU; False when the estimate itself went wrong."""

    def __init__(self, message: str, state_ok: bool = True) -> None:
        super().__init__(message)
        self.state_ok = state_ok


@dataclass
class KeyframeEstimate:
    """Optimised state of the newest keyframe."""

    t_ns: int
    index: int
    pose: gtsam.Pose3
    velocity: np.ndarray
    bias: gtsam.imuBias.ConstantBias
    n_visual: int  # projection factors added at this keyframe
    n_landmarks: int  # landmarks observed at this keyframe
    extra_passes: int = 0  # relinearisation passes after the first update
    T_body_cam0: np.ndarray | None = None  # the refined extrinsics (None: not refined)
    T_body_cam1: np.ndarray | None = None
    intrinsics: tuple[np.ndarray, np.ndarray] | None = None  # refined (fx, fy, cx, cy) of cam0, cam1 (None: held)


@dataclass
class StereoFinding:
    """The stereo check's newest reading: the disparity bias (and cam1's focal lengths) the data show against the
    calibration."""

    t_ns: int
    disparity_px: float  # positive: the calibration's disparities too large (its depths too short)
    sigma_px: float  # 1-sigma of that
    released: bool  # the holds were let go at this check: cam1 is refined from here on
    focal_px: tuple[tuple[float, float], ...] | None = None  # (reading, sigma) of cam1's fx, fy at the image edge
    implausible: bool = False  # beyond stereo_check_max_deg: not a calibration error, not acted on

    def describe(self) -> str:
        """The readings in words, e.g. 'disparity bias +0.49 +- 0.11 px; cam1's fx at the image edge +0.05 +- 0.10
        px, fy -0.02 +- 0.08 px'."""
        out = f"disparity bias {self.disparity_px:+.2f} +- {self.sigma_px:.2f} px"
        if self.focal_px:
            (fx, sx), (fy, sy) = self.focal_px
            out += f"; cam1's focal lengths at the image edge: fx {fx:+.2f} +- {sx:.2f} px, fy {fy:+.2f} +- {sy:.2f} px"
        return out


@dataclass
class _Landmark:
    key: int
    last_t_s: float


CONFIRM_AFTER_KF = 2  # keyframes from a stereo check whose reading stood out to the one that confirms it
# After the IMU noise was raised (the adaptive noise engaging on a shaking airframe) the IMU factors before it, which
# claimed the calibration's density, keep their pull on cam1 in its marginal (cam1's variables never leave the
# window): the score test reads it as a disparity bias that fades only as new data outweigh it. With 4 m/s^2 of
# vibration and an exact calibration: +0.73 +- 0.17, +0.68 +- 0.17, +0.55, +0.37 +- 0.14, +0.15 +- 0.09 px from the
# raise at ~4 s to 10 s; with 3 m/s^2, 30 % of the images lost and 15 ms of blur: +0.60 +- 0.16 at the raise, 4
# sigma and more to 10 s, +0.25 +- 0.08 at 14 s. Both let go of a right calibration (QA runs: ATE 48 mm for 28, 56
# for 17). From the raise on, a reading counts only once its sigma is down to this share of the first one after the
# raise: the data since then outweigh what came before three to one.
STEREO_SETTLE_SIGMA_SHARE = 0.5
MONO_MIN_VIEWS = 3  # keyframes (the current one included) that must see a mono track before it is triangulated
MONO_MAX_REPROJ_PX = 2.0  # a triangulated mono landmark must project this close to every view's pixel


STAMP_LINKS_KEPT = 4000  # keyframe numbers remembered as having a stamp link (far more than a window holds)
KEEP_ALL_LAG_S = 1e9  # a smoother lag that marginalises nothing (between marginalisations)
TIME_LINK_SIGMA = 1e-4  # rad, m: C(i) = X(i) Exp(xi d) held this tightly (a pixel is ~2e-3 rad; 1e-5 and the
# offset in seconds made iSAM2 report indeterminate systems on 5 of 18 matrix flights)


def _k_key(cam: int) -> int:
    """Key of camera `cam`'s intrinsics variable (refine_intrinsics)."""
    return gtsam.symbol("k", cam)


def _fxfycxcy(K: gtsam.Cal3_S2) -> np.ndarray:
    return np.array([K.fx(), K.fy(), K.px(), K.py()])


def _sigmas(values: list[float]) -> gtsam.noiseModel.Diagonal:
    return gtsam.noiseModel.Diagonal.Sigmas(np.asarray(values, dtype=float))


def level_prior(R_world_body: np.ndarray, sigma_tilt_rad: float, sigma_yaw_rad: float,
                sigma_p_m: float) -> gtsam.noiseModel.Gaussian:
    """Noise of a Pose3 prior that holds the turn about world z (yaw) and the tilt about world x, y with their
    own sigmas, and the position isotropically.

    Pose3's tangent is in the body frame, so the world-frame rotation covariance is turned into it
    (R^T S R). A body-frame diagonal [tilt, tilt, yaw] is the same only for a body whose z axis is up; on
    EuRoC's mount (IMU x up) it held a tilt axis at the yaw's 1 mrad and left the yaw at the tilt's 20."""
    R = np.asarray(R_world_body, float)
    cov = np.zeros((6, 6))
    cov[:3, :3] = R.T @ np.diag([sigma_tilt_rad ** 2, sigma_tilt_rad ** 2, sigma_yaw_rad ** 2]) @ R
    cov[3:, 3:] = np.eye(3) * sigma_p_m ** 2  # isotropic: the same in any frame
    return gtsam.noiseModel.Gaussian.Covariance(cov)


def stamp_link_noise(xi_ms: np.ndarray, sigma_ms: float) -> gtsam.noiseModel.Gaussian:
    """Noise of the link C = X Exp(xi d) (or C = X without the time state) when the frame's own stamp may be off by
    `sigma_ms` (1 sigma, white from frame to frame: vio.frame_clock): C may move along the twist xi (per ms) by it,
    TIME_LINK_SIGMA across. A stamp error moves the whole camera pose along the motion, one error for every pixel
    of the frame; as pixel noise it would have been averaged away over the frame's hundreds of points."""
    xi = np.asarray(xi_ms, float).reshape(6)
    return gtsam.noiseModel.Gaussian.Covariance(np.eye(6) * TIME_LINK_SIGMA ** 2 + sigma_ms ** 2 * np.outer(xi, xi))


def body_twist_ms(pose: gtsam.Pose3, v_world: np.ndarray, omega_body: np.ndarray | None) -> np.ndarray:
    """The body's twist (gyro, body-frame velocity) per ms: how far the camera-time pose moves per ms of offset."""
    omega = np.zeros(3) if omega_body is None else np.asarray(omega_body, float)
    return 1e-3 * np.r_[omega, pose.rotation().unrotate(np.asarray(v_world, float))]


def time_link_factor(x_key: int, c_key: int, d_key: int, xi: np.ndarray, X0: gtsam.Pose3, C0: gtsam.Pose3,
                     d0: float, noise: gtsam.noiseModel.Base | None = None) -> gtsam.LinearContainerFactor:
    """error = Log(X^-1 C) - xi d: the camera-time pose C is the IMU-time pose X moved along the body twist
    xi = (omega, v_body), given per unit of d (per ms, as the smoother keeps d).

    Linearised once, at (X0, C0, d0), and kept as a linear factor in the variables' local coordinates: X and C
    move together (the link holds them 1e-4 rad / m apart), so what this drops is second order, a pose correction
    times a change of the offset (on a 40 s aggressive replay at most 0.03 of the link's sigma, against the
    link's own residual of up to 0.5). A Python callback (`gtsam.CustomFactor`), re-linearised on every solve,
    cost 1.6-1.8 ms of a keyframe's 11.5 ms update: iSAM2 re-linearises the whole window whenever a keyframe
    touches most of it (three updates in four on that flight)."""
    xi = np.asarray(xi, float).reshape(6)
    delta = X0.between(C0)
    J = gtsam.Pose3.LogmapDerivative(delta)
    e0 = gtsam.Pose3.Logmap(delta) - xi * float(d0)
    A_x, A_c, A_d, b = -J @ delta.inverse().AdjointMap(), J, -xi.reshape(6, 1), -e0
    if noise is None:
        model = gtsam.noiseModel.Isotropic.Sigma(6, TIME_LINK_SIGMA)
    else:  # a full covariance (stamp_link_noise): whitened here, the binding takes diagonal models only
        R = np.asarray(noise.R(), float)
        A_x, A_c, A_d, b = R @ A_x, R @ A_c, R @ A_d, R @ b
        model = gtsam.noiseModel.Unit.Create(6)
    lin = gtsam.JacobianFactor(x_key, A_x, c_key, A_c, d_key, A_d, b, model)
    point = gtsam.Values()
    point.insert(x_key, X0)
    point.insert(c_key, C0)
    point.insert(d_key, float(d0))
    return gtsam.LinearContainerFactor(lin, point)


def offset_rate_factor(d_i: int, s_i: int, d_j: int, dt: float, step: float,
                       noise: gtsam.noiseModel.Diagonal) -> gtsam.LinearContainerFactor:
    """d(j) = d(i) + s(i) dt - step: the offset moves with its rate s (a clock's skew) between keyframes dt
    apart, and back by `step` where the applied offset moved. Linear, so a linear factor (at zero) is exact."""
    lin = gtsam.JacobianFactor(d_i, np.array([[-1.0]]), s_i, np.array([[-dt]]), d_j, np.array([[1.0]]),
                               np.array([-step]), noise)
    point = gtsam.Values()
    for k in (d_i, s_i, d_j):
        point.insert(k, 0.0)
    return gtsam.LinearContainerFactor(lin, point)


def _failure(what: str, e: Exception) -> SmootherFailure:
    """A gtsam error as a SmootherFailure with the error's first line (gtsam's messages run to many lines)."""
    first_line = next((ln.strip() for ln in str(e).splitlines() if ln.strip()), "")
    return SmootherFailure(f"smoother {what} failed: {type(e).__name__}: {first_line}")


class VioSmoother:
    """Keyframe graph + fixed-lag smoother. Create, `initialize` once, then `add_keyframe` per keyframe."""

    def __init__(self, calib: StereoCalibration, cfg: BackendConfig, time_state: bool | None = None) -> None:
        """`time_state`: the time offset state from the first keyframe on (default: `cfg.time_offset_state`);
        `start_time_state` switches it on later."""
        self.cfg = cfg
        self.calib = calib
        self.K0 = gtsam.Cal3_S2(calib.cam0.fx, calib.cam0.fy, 0.0, calib.cam0.cx, calib.cam0.cy)
        self.K1 = gtsam.Cal3_S2(calib.cam1.fx, calib.cam1.fy, 0.0, calib.cam1.cx, calib.cam1.cy)
        self._K_calib = (self.K0, self.K1)  # the calibration's, for priors set later (refine_extrinsics_auto)
        # the cameras' pose and intrinsics variables; refine_extrinsics_auto gives cam1 fresh ones at its switch
        self._e, self._k = [E(0), E(1)], [_k_key(0), _k_key(1)]
        self.P_body_cam0 = gtsam.Pose3(calib.cam0.T_body_cam)
        self.P_body_cam1 = gtsam.Pose3(calib.cam1.T_body_cam)
        self.T_body_cam0 = calib.cam0.T_body_cam
        pix = gtsam.noiseModel.Isotropic.Sigma(2, cfg.pixel_sigma)
        self.pixel_noise = gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Huber.Create(cfg.huber_k), pix)
        self.landmark_prior = gtsam.noiseModel.Isotropic.Sigma(3, cfg.landmark_prior_sigma_m) \
            if cfg.landmark_prior_sigma_m > 0 else None
        params = gtsam.ISAM2Params()
        params.setRelinearizeThreshold(0.01)
        params.relinearizeSkip = 1
        params.findUnusedFactorSlots = True
        self.smoother = gtsam.IncrementalFixedLagSmoother(cfg.lag_s, params)
        self.landmarks: dict[int, _Landmark] = {}
        self._mono: dict[int, list[tuple[int, np.ndarray]]] = {}  # track -> (keyframe, cam0 pixel) without landmark
        self._kf_t: dict[int, float] = {}  # keyframe index -> smoother time, for the mono observations' keyframes
        self.n_mono_landmarks = 0
        self.refine = bool(cfg.refine_extrinsics)
        self.refine_K = self.refine and bool(cfg.refine_intrinsics)
        # cam1's rotation on the body refined alone (cam0 and the camera-IMU extrinsic held): what a stereo
        # calibration that drifted does to the disparity (`refine_stereo_rotation`; with refine_extrinsics,
        # refine_stereo_extrinsic does it instead)
        self.refine_stereo = bool(cfg.refine_stereo_rotation) and not self.refine
        # The stereo check (module doc): E(1) (and K(1)) variables as above, held at the calibration by tight priors
        # whose pull measures what the data say about them; the holds are let go when the data show cam1 off.
        # With refine_extrinsics the check holds cam1's rotation *relative to cam0* (E(0) -> E(1)), so that the rig
        # can turn on the body under the motion gate while the stereo pair stays as calibrated until the data show
        # it off (`_relative_rotation_information`); refine_stereo_extrinsic lets that relative pose move from the
        # start instead.
        self.stereo_check = bool(cfg.stereo_check) and not self.refine_stereo and not (
            self.refine and cfg.refine_stereo_extrinsic)
        self.check_relative = self.stereo_check and self.refine
        self.refine_stereo = self.refine_stereo or (self.stereo_check and not self.refine)
        self._P_body_cam1_calib = self.P_body_cam1
        self._P_cam0_cam1_calib = self.P_body_cam0.between(self.P_body_cam1)
        # with stereo_check_focal, cam1's intrinsics K(1) are a variable too, their fx, fy held and let go with E(1)
        # (alone: with the rig refined, K(1) has its own prior and is refined under the gate with K(0))
        self.check_K1 = self.stereo_check and not self.refine and bool(cfg.stereo_check_focal)
        # refine_extrinsics_auto: the absolute check until the first keyframe that passes the motion gate, then the
        # rig refinement with the relative check (`_start_rig_refinement`)
        self._rig_pending = bool(cfg.refine_extrinsics_auto) and not self.refine and not cfg.refine_stereo_rotation
        self.marginalize_due = False  # the last keyframe's marginalisation waits for `marginalize`
        self._want_new: list[int] | None = None  # graph positions whose smoother factor indices the update keeps
        self._new_idx: list[int] = []
        self._holds: list[int] = []  # the holding priors' factor indices in the smoother, while they hold
        self.stereo_finding: StereoFinding | None = None  # the newest check's reading
        self._stood_out = 0  # consecutive checks whose reading stood out
        self._next_check = cfg.stereo_check_every  # keyframe index of the next check
        self._check_due: tuple[int, int] | None = None  # (stamp, index) of the keyframe whose check is due
        # after the IMU noise was raised: None, or the sigma of the first reading since (0: none yet), which the
        # readings' sigma must come down from before they count (`imu_noise_raised`)
        self._settle_sigma: float | None = None
        # first keyframe whose projections read the camera-time pose C(i); None: no time state (yet). A state
        # asked for starts at the first keyframe that moves fast enough to show the offset (`_shows_offset`)
        self.time_from: int | None = None
        self._stamp_linked: set[int] = set()  # keyframes whose projections read C(i) without the time state
        self.stamp_links = 0  # keyframes given a stamp link (stamp_link_noise) without the time state
        self._time_pending = bool(cfg.time_offset_state if time_state is None else time_state)
        self.time_links = 0  # keyframes whose camera pose was read at the offset (moving fast enough to show it)
        self._applied_ns = 0  # the applied offset at the newest keyframe (time state only)
        self._linked: tuple[int, int] | None = None  # (keyframe, applied offset ns) of the newest linked keyframe
        self.extrinsic_keyframes = 0  # keyframes whose factors refined the extrinsics (passed the motion gate)
        self._next_landmark = 0
        self.index = -1
        self.t0_ns = 0
        self.last: KeyframeEstimate | None = None
        self._estimate: gtsam.Values | None = None
        # keyframes still in the window (index, stamp ns, smoother time s) and those that left it since the caller
        # last asked, with the estimate they had just before (`take_settled`)
        self._unsettled: deque[tuple[int, int, float]] = deque()
        self._settled: list[tuple[int, np.ndarray]] = []

    # -- helpers -------------------------------------------------------------------------------------
    @property
    def time_state(self) -> bool:
        """Whether the time offset state is on (from keyframe `time_from` on)."""
        return self.time_from is not None

    def start_time_state(self) -> None:
        """The time offset state from the next keyframe that moves fast enough to show the offset (the in-flight
        estimate found the offset wrong: it may drift). Earlier keyframes keep reading X(i); the first D gets the
        prior of a first keyframe."""
        if self.time_from is None:
            self._time_pending = True

    def _shows_offset(self, omega_body: np.ndarray | None, v_world: np.ndarray) -> bool:
        """Whether a keyframe turns or moves fast enough for the offset to show in its projections
        (`time_offset_link_min_rate` / `time_offset_link_min_speed`)."""
        w = 0.0 if omega_body is None else float(np.linalg.norm(omega_body))
        return w >= self.cfg.time_offset_link_min_rate or \
            float(np.linalg.norm(v_world)) >= self.cfg.time_offset_link_min_speed

    def _time_state_at(self, j: int, omega_body: np.ndarray | None, v_world: np.ndarray) -> bool:
        """Whether keyframe j has the time state, starting a pending one here when j shows the offset."""
        if self._time_pending and self._shows_offset(omega_body, v_world):
            self.time_from, self._time_pending = j, False
        return self.time_from is not None

    def _pose_key(self, i: int) -> int:
        """The pose the projections of keyframe i read: the camera-time C(i) with the time state, else X(i)."""
        return C(i) if (self.time_from is not None and i >= self.time_from) or i in self._stamp_linked else X(i)

    def _add_time_state(self, graph: gtsam.NonlinearFactorGraph, values: gtsam.Values, stamps: dict[int, float],
                        j: int, t_s: float, pose: gtsam.Pose3, v_world: np.ndarray, omega_body: np.ndarray | None,
                        applied_ns: int, stamp_sigma_ms: float = 0.0) -> gtsam.Pose3:
        """D(j), C(j) and their factors (module doc); returns C(j)'s initial value. `stamp_sigma_ms`: the frame's own
        stamp error (stamp_link_noise), on top of the offset D follows."""
        cfg = self.cfg
        rate = cfg.time_offset_rate_walk_ms > 0
        if j == self.time_from:
            d = 0.0
            graph.add(gtsam.PriorFactorDouble(D(j), 0.0, _sigmas([cfg.time_offset_state_sigma_ms])))
            if rate:
                graph.add(gtsam.PriorFactorDouble(S(j), 0.0, _sigmas([cfg.time_offset_rate_sigma_ms])))
        else:
            step = (applied_ns - self._applied_ns) * 1e-6  # ms; the applied offset moved: the residual moves back
            dt = max(t_s - self._t_s(self.last.t_ns), 1e-3)  # since the previous keyframe
            walk = _sigmas([cfg.time_offset_walk_ms * np.sqrt(dt)])
            d = self._estimate.atDouble(D(j - 1)) - step
            if rate:
                r = self._estimate.atDouble(S(j - 1))
                d += r * dt
                graph.add(offset_rate_factor(D(j - 1), S(j - 1), D(j), dt, step, walk))
                graph.add(gtsam.BetweenFactorDouble(S(j - 1), S(j), 0.0, _sigmas(
                    [cfg.time_offset_rate_walk_ms * np.sqrt(dt)])))
            else:
                graph.add(gtsam.BetweenFactorDouble(D(j - 1), D(j), -step, walk))
        self._applied_ns = int(applied_ns)
        # d is in ms: the variables stay near unit scale (seconds upset iSAM2's Cholesky)
        twist_ms = body_twist_ms(pose, v_world, omega_body)
        if self._shows_offset(omega_body, v_world):
            self.time_links += 1
            self._linked = (j, int(applied_ns))
            xi_ms = twist_ms
        else:
            xi_ms = np.zeros(6)  # too slow to tell the offset: C(j) = X(j), d(j) only walks on (module doc)
        cam_pose = pose.compose(gtsam.Pose3.Expmap(xi_ms * d))
        noise = stamp_link_noise(twist_ms, stamp_sigma_ms) if stamp_sigma_ms > 0 else None
        graph.add(time_link_factor(X(j), C(j), D(j), xi_ms, pose, cam_pose, d, noise))
        values.insert(D(j), float(d))
        values.insert(C(j), cam_pose)
        stamps[D(j)] = stamps[C(j)] = t_s
        if rate:
            values.insert(S(j), float(0.0 if j == self.time_from else r))
            stamps[S(j)] = t_s
        return cam_pose

    def _camera_pose(self, graph: gtsam.NonlinearFactorGraph, values: gtsam.Values, stamps: dict[int, float], j: int,
                     t_s: float, pose: gtsam.Pose3, v_world: np.ndarray, omega_body: np.ndarray | None,
                     applied_ns: int, stamp_sigma_ms: float, visual: bool) -> gtsam.Pose3:
        """The pose keyframe j's projections read (the time state's C(j), a stamp link's, else X(j)) with its
        variables and factors; returns its initial value. A stamp link only where projections will read it
        (`visual`): on a keyframe without them (vision lost) its C(j) only doubled a pose in the window."""
        if self._time_state_at(j, omega_body, v_world):
            return self._add_time_state(graph, values, stamps, j, t_s, pose, v_world, omega_body, applied_ns,
                                        stamp_sigma_ms)
        if stamp_sigma_ms > 0 and visual:
            return self._add_stamp_link(graph, values, stamps, j, t_s, pose, v_world, omega_body, stamp_sigma_ms)
        return pose

    def _add_stamp_link(self, graph: gtsam.NonlinearFactorGraph, values: gtsam.Values, stamps: dict[int, float],
                        j: int, t_s: float, pose: gtsam.Pose3, v_world: np.ndarray, omega_body: np.ndarray | None,
                        sigma_ms: float) -> gtsam.Pose3:
        """Without the time state, a keyframe whose stamp may be off by `sigma_ms` gets a camera-time pose C(j) of its
        own, held to X(j) except along the body's motion (stamp_link_noise); returns C(j)'s initial value (X's). A
        keyframe that hardly moves (sigma x twist under the link's own sigma) keeps C(j) = X(j)."""
        xi_ms = body_twist_ms(pose, v_world, omega_body)
        if sigma_ms * float(np.linalg.norm(xi_ms)) < TIME_LINK_SIGMA:
            return pose
        graph.add(gtsam.BetweenFactorPose3(X(j), C(j), gtsam.Pose3(), stamp_link_noise(xi_ms, sigma_ms)))
        values.insert(C(j), pose)
        stamps[C(j)] = t_s
        if len(self._stamp_linked) > STAMP_LINKS_KEPT:  # those of keyframes long out of the window
            self._stamp_linked = {i for i in self._stamp_linked if i > j - STAMP_LINKS_KEPT // 2}
        self._stamp_linked.add(j)
        self.stamp_links += 1
        return pose

    def _t_s(self, t_ns: int) -> float:
        """Smoother time in seconds relative to the first keyframe (float64 keeps sub-us precision)."""
        return (t_ns - self.t0_ns) * 1e-9

    def _update(self, graph: gtsam.NonlinearFactorGraph, values: gtsam.Values, stamps: dict[int, float],
                j: int, pose_pred: gtsam.Pose3) -> int:
        """One iSAM2 update; extra relinearisation passes only when it moved the newest pose a lot (then
        the linearisation point was poor). Returns the number of extra passes made."""
        extra = 0
        # Marginalisation marks the subtrees under the leaving variables, which with a keyframe's new factors
        # leaves iSAM2 more than the 65 % of the window at which it re-linearises and re-eliminates all of it
        # (three updates in four on the aggressive flights when marginalising at every keyframe): done on every
        # N-th keyframe only, the updates in between stay incremental (module doc)
        every = self.cfg.marginalize_every_kf
        # a marginalisation still pending from the last keyframe (the caller had no frame between) goes with this
        # update; one due at this keyframe waits for the caller's next frame (`marginalize`) when it asks for that
        between = bool(self.cfg.marginalize_between_frames) and every > 1
        now = self.marginalize_due or (not between and j % every == 0)
        self.marginalize_due = between and j % every == 0
        self.smoother.setSmootherLag(self.cfg.lag_s if now else KEEP_ALL_LAG_S)
        if now:
            self._settle(max(stamps.values()) - self.cfg.lag_s)
        try:
            self.smoother.update(graph, values, stamps)
            if self._want_new is not None:
                new = self.smoother.getISAM2Result().getNewFactorsIndices()
                self._new_idx = [int(new[k]) for k in self._want_new]
                self._want_new = None
            # the whole estimate (0.07 ms) rather than calculateEstimatePose3 (0.25 ms a keyframe) for the gate
            self._estimate = self.smoother.calculateEstimate()
            if self.cfg.extra_iterations > 0:
                corr = pose_pred.localCoordinates(self._estimate.atPose3(X(j)))
                if float(np.max(np.abs(corr))) > self.cfg.extra_iteration_gate:
                    for _ in range(self.cfg.extra_iterations):
                        self.smoother.update()
                        extra += 1
                    self._estimate = self.smoother.calculateEstimate()
        except GTSAM_ERRORS as e:
            raise _failure("update", e) from None
        return extra

    def marginalize(self) -> None:
        """The marginalisation due at the last keyframe, in an update of its own (no new factors): the caller runs
        it on a frame that is no keyframe, so that a keyframe's solve never carries it (module doc)."""
        if not self.marginalize_due:
            return
        self.marginalize_due = False
        self.smoother.setSmootherLag(self.cfg.lag_s)
        if self.last is not None:
            self._settle(self._t_s(self.last.t_ns) - self.cfg.lag_s)
        try:
            self.smoother.update()
            self._estimate = self.smoother.calculateEstimate()
        except GTSAM_ERRORS as e:
            raise _failure("marginalisation", e) from None

    def _settle(self, horizon_s: float) -> None:
        """Before a marginalising update: the keyframes older than `horizon_s` (smoother time) are about to leave
        the window; their estimate now has seen lag_s of later data, which the estimate at their own solve had not
        (the loop stage's odometry edges are 12-20 % better for it, docs/loop-closure.md)."""
        est = self._estimate
        while self._unsettled and self._unsettled[0][2] < horizon_s:
            i, t_ns, _ = self._unsettled.popleft()
            if est is not None and est.exists(X(i)):
                self._settled.append((t_ns, est.atPose3(X(i)).matrix()))

    def settle_all(self) -> None:
        """End of a recording: the keyframes still in the window are settled with their current estimate (no
        later data will come)."""
        self._settle(float("inf"))

    def take_settled(self) -> list[tuple[int, np.ndarray]]:
        """(stamp ns, T_world_body) of the keyframes that left the window since the last call, each with its last
        estimate in it (smoothed), oldest first."""
        out, self._settled = self._settled, []
        return out

    # -- API -----------------------------------------------------------------------------------------
    def initialize(self, t_ns: int, T_world_body: np.ndarray, v_world: np.ndarray, gyro_bias: np.ndarray,
                   accel_bias: np.ndarray, *, sigma_rp_rad: float = 0.02, sigma_yaw_rad: float = 1e-3,
                   sigma_p_m: float = 1e-3, sigma_v_m_s: float = 0.05, sigma_bg: float = 0.005,
                   sigma_ba: float = 0.1, features: FeatureFrame | None = None,
                   omega_body: np.ndarray | None = None, applied_offset_ns: int = 0,
                   stamp_sigma_ms: float = 0.0) -> KeyframeEstimate:
        """First keyframe with priors: position and yaw are gauge freedoms (pinned), roll/pitch come
        from gravity, velocity and biases from the initialiser with honest uncertainty. `stamp_sigma_ms` as for
        `add_keyframe`: a restart in flight starts on a moving keyframe, whose stamp is no more exact than the
        next one's."""
        self.t0_ns = t_ns
        self.index = 0
        pose = gtsam.Pose3(np.asarray(T_world_body, dtype=float))
        bias = gtsam.imuBias.ConstantBias(np.asarray(accel_bias, float), np.asarray(gyro_bias, float))
        graph = gtsam.NonlinearFactorGraph()
        graph.add(gtsam.PriorFactorPose3(X(0), pose, level_prior(pose.rotation().matrix(), sigma_rp_rad,
                                                                 sigma_yaw_rad, sigma_p_m)))
        graph.add(gtsam.PriorFactorVector(V(0), np.asarray(v_world, float), _sigmas([sigma_v_m_s] * 3)))
        graph.add(gtsam.PriorFactorConstantBias(B(0), bias, _sigmas([sigma_ba] * 3 + [sigma_bg] * 3)))
        values = gtsam.Values()
        values.insert(X(0), pose)
        values.insert(V(0), np.asarray(v_world, float))
        values.insert(B(0), bias)
        stamps = {X(0): 0.0, V(0): 0.0, B(0): 0.0}
        if self.refine:
            self._add_extrinsic_variables(graph, values, stamps)
        elif self.refine_stereo:
            graph.add(gtsam.PriorFactorPose3(self._e[1], self.P_body_cam1,
                                             _sigmas([self.cfg.stereo_sigma_rad] * 3 + [1e-5] * 3)))
            values.insert(self._e[1], self.P_body_cam1)
            stamps[self._e[1]] = 0.0
            if self.check_K1:  # fx, fy within the stated uncertainty; skew and principal point held (see below)
                graph.add(gtsam.PriorFactorCal3_S2(self._k[1], self.K1,
                                                   _sigmas([self.cfg.intrinsics_sigma_px] * 2 + [1e-4] * 3)))
                values.insert(self._k[1], self.K1)
                stamps[self._k[1]] = 0.0
        cam_pose = self._camera_pose(graph, values, stamps, 0, 0.0, pose, np.asarray(v_world, float), omega_body,
                                     applied_offset_ns, stamp_sigma_ms, features is not None)
        n_vis, n_lm = 0, 0
        if features is not None:
            n_vis, n_lm = self._add_visual(graph, values, stamps, features, cam_pose, 0, 0.0)
        extra = self._update(graph, values, stamps, 0, pose)
        if self.stereo_check:
            self._hold_stereo()
        return self._finish(t_ns, n_vis, n_lm, extra)

    def add_keyframe(self, t_ns: int, pim: gtsam.PreintegratedCombinedMeasurements,
                     features: FeatureFrame | None, zero_velocity: bool = False,
                     omega_body: np.ndarray | None = None, applied_offset_ns: int = 0,
                     stamp_sigma_ms: float = 0.0) -> KeyframeEstimate:
        """Add keyframe i+1 tied to i by `pim` (integrated from i's stamp to t_ns with i's bias).

        `omega_body` (bias-corrected gyro at t_ns) and `applied_offset_ns` (the offset the frame stamps
        carry) feed the time offset state, when it is on; `stamp_sigma_ms` is how far the frame's own stamp may be
        off (vio.frame_clock: 0 for exact stamps), which lets its camera pose move along the motion by that much."""
        if self.last is None:
            raise SmootherFailure("add_keyframe before initialize")
        self.check_stereo()  # one the caller has not read yet
        prev = self.last
        i, j = self.index, self.index + 1
        t_s = self._t_s(t_ns)
        pred = pim.predict(gtsam.NavState(prev.pose, prev.velocity), prev.bias)
        graph = gtsam.NonlinearFactorGraph()
        graph.add(gtsam.CombinedImuFactor(X(i), V(i), X(j), V(j), B(i), B(j), pim))
        values = gtsam.Values()
        values.insert(X(j), pred.pose())
        values.insert(V(j), pred.velocity())
        values.insert(B(j), prev.bias)
        stamps = {X(j): t_s, V(j): t_s, B(j): t_s}
        if self.refine:
            stamps[self._e[0]] = stamps[self._e[1]] = t_s  # the extrinsics stay in the window for the whole flight
            if self.refine_K:
                stamps[self._k[0]] = stamps[self._k[1]] = t_s
        elif self.refine_stereo:
            stamps[self._e[1]] = t_s
            if self.check_K1:
                stamps[self._k[1]] = t_s
        if zero_velocity:
            # Still vehicle: zero velocity and no motion since the last keyframe. Pins the drift that
            # the IMU alone would integrate during hover-on-ground and before take-off.
            graph.add(gtsam.PriorFactorVector(V(j), np.zeros(3), _sigmas([0.01] * 3)))
            graph.add(gtsam.BetweenFactorPose3(X(i), X(j), gtsam.Pose3(), _sigmas([1e-3] * 3 + [2e-3] * 3)))
        cam_pose = self._camera_pose(graph, values, stamps, j, t_s, pred.pose(), pred.velocity(), omega_body,
                                     applied_offset_ns, stamp_sigma_ms, features is not None and features.tracking_ok)
        switch = self._rig_pending and features is not None and features.tracking_ok \
            and self._motion_excites_extrinsics(pred.pose(), t_s)
        if switch:
            self._start_rig_refinement(graph, values, stamps, t_s)
        n_vis, n_lm = 0, 0
        if features is not None and features.tracking_ok:
            n_vis, n_lm = self._add_visual(graph, values, stamps, features, cam_pose, j, t_s)
        self.index = j
        extra = self._update(graph, values, stamps, j, pred.pose())
        if switch and self._new_idx:
            self._holds = self._new_idx  # the relative hold, added with this keyframe
        return self._finish(t_ns, n_vis, n_lm, extra)

    def _start_rig_refinement(self, graph: gtsam.NonlinearFactorGraph, values: gtsam.Values,
                              stamps: dict[int, float], t_s: float) -> None:
        """refine_extrinsics_auto, at the first keyframe that passes the motion gate: from the absolute stereo
        check to the rig refinement with the relative one. E(0) (and K(0)) join with the calibration's priors;
        cam1 gets *fresh* variables E(2), K(2), tied to E(0) by the loose stereo between factor and, unless the
        check already let go, by the relative hold. Fresh, because the old E(1), K(1) carry what the check phase
        taught them with cam0 held at the stated calibration, which would hold the rig there (on the 40 s
        aggressive calibration-error flight of seed 3: 14.0 mm against 10.7 with the rig refined from
        take-off); they leave the window with the keyframes that saw them."""
        cfg = self.cfg
        checked = self._estimate.exists(self._e[1])  # the stereo check ran (held or let go)
        held = bool(self._holds) and not cfg.refine_stereo_extrinsic  # that one lets the pair move from here
        self.refine, self.refine_K, self.refine_stereo = True, bool(cfg.refine_intrinsics), False
        self._holds, self._rig_pending, self._new_idx = [], False, []
        self.check_relative, self.check_K1, self.stereo_check = held, False, held
        self._e, self._k = [E(0), E(2)], [_k_key(0), _k_key(2)]
        self._add_extrinsic_variables(graph, values, stamps, t_s, checked)
        if held:
            self._want_new = [graph.size()]
            graph.add(self._pose_hold())
        log.info("motion turns the rig enough to refine the camera-IMU rotation%s from here; the stereo pair %s",
                 " and the focal lengths" if self.refine_K else "",
                 "held relative to cam0 by the stereo check" if held else
                 "refined" if checked or cfg.refine_stereo_extrinsic else "held as calibrated")

    def _add_extrinsic_variables(self, graph: gtsam.NonlinearFactorGraph, values: gtsam.Values,
                                 stamps: dict[int, float], t_s: float = 0.0, pair_checked: bool = False) -> None:
        """The rig's variables E(0), cam1's pose self._e[1] (and with refine_K the intrinsics self._k) with the
        calibration's priors, from take-off or (t_s) from the automatic switch. The pair's rotation is loose
        (`stereo_sigma_rad`) where a stereo check holds or has let go of it (`pair_checked`, or check_relative),
        or with refine_stereo_extrinsic (its translation too); otherwise held."""
        cfg = self.cfg
        # translation held unless asked for: on the 40 s aggressive flight it wandered 4.2 mm from a 2 mm
        # error (absorbing what it cannot see: intrinsics, lever-arm directions the turns did not excite)
        prior = _sigmas([cfg.extrinsic_sigma_rad] * 3 +
                        [cfg.extrinsic_sigma_m if cfg.refine_extrinsic_translation else 1e-5] * 3)
        graph.add(gtsam.PriorFactorPose3(E(0), self.P_body_cam0, prior))
        free = cfg.refine_stereo_extrinsic
        # held: 1e-5; 1e-6 made the system numerically indeterminate
        loose_rot = free or pair_checked or self.check_relative
        stereo = _sigmas([cfg.stereo_sigma_rad if loose_rot else 1e-5] * 3 + [cfg.stereo_sigma_m if free else 1e-5] * 3)
        graph.add(gtsam.BetweenFactorPose3(self._e[0], self._e[1], self.P_body_cam0.between(self.P_body_cam1), stereo))
        values.insert(E(0), self.P_body_cam0)
        values.insert(self._e[1], self.P_body_cam1)  # as calibrated, or where a stereo check that let go put it
        stamps[self._e[0]] = stamps[self._e[1]] = t_s
        if self.refine_K:
            # fx, fy, skew, cx, cy; the skew is held (no lens has one), and so is the principal point: a cx/cy
            # error shifts the whole image as a turned camera does, so with both free they trade against the
            # extrinsic rotation (in tests/test_estimator.py: cy 2 -> 1.4 px off, the rotation 0.04 -> 0.16 deg)
            sp = cfg.intrinsics_sigma_px if cfg.refine_principal_point else 1e-4
            k_prior = _sigmas([cfg.intrinsics_sigma_px] * 2 + [1e-4] + [sp] * 2)
            for key, K, K_now in zip(self._k, self._K_calib, (self.K0, self.K1)):
                graph.add(gtsam.PriorFactorCal3_S2(key, K, k_prior))
                values.insert(key, K_now)
                stamps[key] = t_s

    def _motion_excites_extrinsics(self, pose_pred: gtsam.Pose3, t_s: float) -> bool:
        """The gate of the module doc: rotation about two axes among the keyframes inside the lag."""
        horizon = t_s - self.cfg.lag_s + 0.05
        R_new = pose_pred.rotation()
        thetas = [gtsam.Rot3.Logmap(R_new.between(self._estimate.atPose3(X(i)).rotation()))
                  for i, t in self._kf_t.items() if t >= horizon and self._estimate.exists(X(i))]
        if len(thetas) < 3:
            return False
        sv = np.linalg.svd(np.asarray(thetas) - np.mean(thetas, axis=0), compute_uv=False)
        spread = 2.0 * sv[1] / np.sqrt(len(thetas))  # ~ the peak-to-peak rotation about the second axis
        return bool(np.degrees(spread) >= self.cfg.extrinsic_min_rotation_deg)

    def _finish(self, t_ns: int, n_vis: int, n_lm: int, extra: int) -> KeyframeEstimate:
        est = self._estimate
        j = self.index
        try:
            pose = est.atPose3(X(j))
            vel = np.asarray(est.atVector(V(j)), float)
            bias = est.atConstantBias(B(j))
            if self.refine:
                self.P_body_cam0, self.P_body_cam1 = est.atPose3(self._e[0]), est.atPose3(self._e[1])
                self.T_body_cam0 = self.P_body_cam0.matrix()
            elif self.refine_stereo and not self._holds:  # held: cam1 stays as calibrated unless the check lets go
                self.P_body_cam1 = est.atPose3(self._e[1])
                if self.check_K1:
                    self.K1 = est.atCal3_S2(self._k[1])
            if self._holds and j >= self._next_check:
                self._check_due = (t_ns, j)  # read by the caller on a later frame (`check_stereo`)
            if self.refine_K:  # the fixed factors, gating and triangulation use the refined intrinsics from now on
                self.K0, self.K1 = est.atCal3_S2(self._k[0]), est.atCal3_S2(self._k[1])
        except GTSAM_ERRORS as e:
            raise SmootherFailure(f"newest keyframe missing from the estimate: {e}") from None
        # while the stereo check holds cam1, nothing is refined: the extrinsics are reported as held (None)
        refined = self.refine or (self.refine_stereo and not self._holds)
        self.last = KeyframeEstimate(t_ns, j, pose, vel, bias, n_vis, n_lm, extra,
                                     self.T_body_cam0.copy() if refined else None,
                                     self.P_body_cam1.matrix() if refined else None,
                                     tuple(_fxfycxcy(K) for K in (self.K0, self.K1))
                                     if self.refine_K or (self.check_K1 and refined) else None)
        self._unsettled.append((j, int(t_ns), self._t_s(t_ns)))
        self._forget_old_landmarks(self._t_s(t_ns))
        return self.last

    def _forget_old_landmarks(self, t_s: float) -> None:
        horizon = t_s - self.cfg.lag_s
        if len(self.landmarks) > 4 * self.cfg.max_landmarks:
            self.landmarks = {tid: lm for tid, lm in self.landmarks.items() if lm.last_t_s >= horizon}
        self._kf_t = {j: t for j, t in self._kf_t.items() if t >= horizon}
        if len(self._mono) > 4 * self.cfg.max_landmarks:
            self._mono = {tid: obs for tid, obs in self._mono.items() if obs[-1][0] in self._kf_t}

    def _active(self, track_id: int, t_s: float) -> _Landmark | None:
        """The track's landmark if it is still inside the smoother window (margin for round-off)."""
        lm = self.landmarks.get(track_id)
        if lm is None or lm.last_t_s < t_s - self.cfg.lag_s + 1e-3:
            return None
        return lm

    def _add_visual(self, graph: gtsam.NonlinearFactorGraph, values: gtsam.Values, stamps: dict[int, float],
                    ff: FeatureFrame, pose_pred: gtsam.Pose3, j: int, t_s: float) -> tuple[int, int]:
        """Projection factors for the tracks of one keyframe; new stereo tracks become landmarks.

        Observations of known landmarks whose reprojection from the predicted pose is far off are
        skipped (outlier or landmark gone wrong) before they can pull the solution.
        """
        cfg = self.cfg
        T_world_cam0 = pose_pred.matrix() @ self.T_body_cam0
        R_c_w = T_world_cam0[:3, :3].T
        t_c_w = -R_c_w @ T_world_cam0[:3, 3]
        K0 = self.K0.K()
        Kinv = np.linalg.inv(K0)
        gate2 = cfg.outlier_gate_px ** 2
        n_vis, n_lm, n_new = 0, 0, 0
        stereo = np.isfinite(ff.depth_m)
        # mono landmarks: always with mono_landmarks, else on keyframes whose stereo is starving (a right camera
        # out); their observations are remembered on every keyframe so that those start with earlier views
        mono_now = cfg.mono_landmarks or int(np.count_nonzero(stereo)) < cfg.mono_below_stereo
        mono_collect = mono_now or cfg.mono_below_stereo > 0
        self._kf_t[j] = t_s
        refine_now = self.refine and j > 0 and self._motion_excites_extrinsics(pose_pred, t_s)
        # keyframes whose factors refine a calibration variable (a stereo check that holds refines nothing)
        self.extrinsic_keyframes += int(refine_now or (self.refine_stereo and not self._holds))
        factor = self._factor_maker(refine_now)
        for k in spread_order(ff.uv0, ff.track_len, self.calib.cam0.width, self.calib.cam0.height):
            tid = int(ff.ids[k])
            uv0 = ff.uv0[k]
            lm = self._active(tid, t_s)
            if lm is not None:
                p_w = self._estimate.atPoint3(lm.key) if self._estimate.exists(lm.key) else None
                if p_w is None:
                    continue
                p_c = R_c_w @ p_w + t_c_w
                if p_c[2] <= 0.05:
                    continue
                du, dv = K0[:2, :2] @ (p_c[:2] / p_c[2]) + K0[:2, 2] - uv0
                if du * du + dv * dv > gate2:  # np.sum((.) ** 2) of two numbers, the same float at a tenth the cost
                    continue
                key = lm.key
            else:
                if n_new >= cfg.max_new_landmarks:
                    continue
                d = float(ff.depth_m[k]) if stereo[k] else float("nan")
                mono_obs: list[tuple[int, np.ndarray]] = []
                if cfg.min_depth_m <= d <= cfg.max_depth_m:
                    p_c = d * (Kinv @ np.array([uv0[0], uv0[1], 1.0]))
                    p_w = T_world_cam0[:3, :3] @ p_c + T_world_cam0[:3, 3]
                    self._mono.pop(tid, None)
                elif mono_collect:
                    horizon = t_s - cfg.lag_s + 0.05  # keyframes about to be marginalised take no new factors
                    mono_obs = [(i, uv) for i, uv in self._mono.get(tid, [])
                                if i != j and self._kf_t.get(i, -1e9) >= horizon and self._estimate.exists(X(i))]
                    p_w = self._triangulate(mono_obs, uv0, T_world_cam0) \
                        if mono_now and len(mono_obs) + 1 >= MONO_MIN_VIEWS else None
                    if p_w is None:
                        self._mono[tid] = mono_obs + [(j, uv0.copy())]
                        continue
                    del self._mono[tid]
                    self.n_mono_landmarks += 1
                else:
                    continue
                key = L(self._next_landmark)
                self._next_landmark += 1
                values.insert(key, p_w)
                for i, uv in mono_obs:  # the earlier keyframes that saw it, still inside the window
                    graph.add(factor(uv, i, key, 0))
                    n_vis += 1
                if self.landmark_prior is not None:
                    # Without it a landmark whose observations the Huber loss has turned down (or a far one)
                    # can leave the system indeterminate, and the smoother cannot recover from the failed
                    # update: the estimator had to reset (synthetic aggressive hard flight, seed 2).
                    graph.add(gtsam.PriorFactorPoint3(key, p_w, self.landmark_prior))
                lm = _Landmark(key, t_s)
                self.landmarks[tid] = lm
                n_new += 1
            graph.add(factor(uv0, j, key, 0))
            n_vis += 1
            if stereo[k]:
                graph.add(factor(ff.uv1[k], j, key, 1))
                n_vis += 1
            lm.last_t_s = t_s
            stamps[key] = t_s
            n_lm += 1
            if n_lm >= cfg.max_landmarks:
                break
        return n_vis, n_lm

    def _hold_stereo(self) -> None:
        """Add the priors that hold cam1's rotation (and focal lengths) at the calibration; remember their indices
        (to let go)."""
        g = gtsam.NonlinearFactorGraph()
        g.add(self._pose_hold())
        if self.check_K1:  # fx, fy to the same few thousandths of a pixel
            hold_px = self.cfg.stereo_hold_sigma_rad * self.calib.cam1.fx
            g.add(gtsam.PriorFactorCal3_S2(self._k[1], self.K1, _sigmas([hold_px] * 2 + [1e3] * 3)))
        try:
            self.smoother.update(g, gtsam.Values(), {})
            self._holds = [int(i) for i in self.smoother.getISAM2Result().getNewFactorsIndices()]
            self._estimate = self.smoother.calculateEstimate()
        except GTSAM_ERRORS as e:
            raise SmootherFailure(f"smoother update failed holding the stereo extrinsic: {type(e).__name__}") from None

    def _pose_hold(self):
        """The tight factor that holds cam1's rotation as calibrated: relative to cam0 with the rig refined, else
        on the body (its translation sigma, 1 km, leaves the translation to the other factors)."""
        hold = _sigmas([self.cfg.stereo_hold_sigma_rad] * 3 + [1e3] * 3)
        if self.check_relative:
            return gtsam.BetweenFactorPose3(self._e[0], self._e[1], self._P_cam0_cam1_calib, hold)
        return gtsam.PriorFactorPose3(self._e[1], self._P_body_cam1_calib, hold)

    def imu_noise_raised(self) -> None:
        """The IMU factors from now on carry more noise than those before (the adaptive IMU noise engaged): the stereo
        check starts counting again once the readings' sigma is down to STEREO_SETTLE_SIGMA_SHARE of the first one's
        after this."""
        if not self._holds:
            return
        self._stood_out = 0
        self._settle_sigma = 0.0

    @property
    def check_due(self) -> bool:
        """A stereo check is due (chosen at the last keyframe): `check_stereo` reads it."""
        return self._check_due is not None

    def check_stereo(self) -> StereoFinding | None:
        """The stereo check due since the last keyframe, on the smoother as that keyframe left it; returns its
        reading (stamped with that keyframe), None when none was due or it read nothing.

        Not part of the keyframe's solve: its joint marginal costs 1-10 ms, which on top of a solve set the slowest
        frames (issue 17's p99), so the estimator reads it on a later frame that has no other back-end work; a
        check still due when the next keyframe comes is read first thing there (`add_keyframe`). The smoother is
        as the keyframe left it until then, so the reading (and a release) is what it was inside the solve."""
        if self._check_due is None:
            return None
        t_ns, j = self._check_due  # due only while the holds hold: nothing lets go of them before it is read
        self._check_due = None
        # cam1 where the holds let it sit: relative to cam0 with the rig refined, else on the body
        held = self.P_body_cam0.between(self.P_body_cam1) if self.refine else self._estimate.atPose3(self._e[1])
        before = self.stereo_finding
        self._check_stereo(t_ns, held)
        # a reading that stood out is confirmed (or not) soon: every keyframe flown biased costs
        self._next_check = j + (CONFIRM_AFTER_KF if self._stood_out else self.cfg.stereo_check_every)
        return None if self.stereo_finding is before else self.stereo_finding

    def _check_stereo(self, t_ns: int, held: gtsam.Pose3) -> None:
        """Where cam1 would be without the holds, from where they let it sit and how much they tighten it.

        With the holds' information Lh and the posterior's joint information Lp of E(1) (and K(1)), the data
        (and the loose calibration priors) alone hold Ld = Lp - Lh, and in the linear(ised) problem the estimate
        without the holds is Ld^-1 Lp d, d being where the held estimate sits relative to the calibration: a score
        test that costs one marginal and leaves the trajectory alone. Read as pixels of disparity: the turn about
        cam1's y axis times fx (positive: the calibration's disparities too large), and a focal length's change
        times half the image width over fx (what it moves a pixel at the image's edge)."""
        cfg = self.cfg
        if self.check_relative:
            lam_post, d = self._relative_rotation_information(held)
            if lam_post is None:
                return
            hold = np.full(3, cfg.stereo_hold_sigma_rad ** -2.0)
        else:
            keys = [self._e[1]] + ([self._k[1]] if self.check_K1 else [])
            hold = np.zeros(6 + 5 * self.check_K1)
            hold[:3] = cfg.stereo_hold_sigma_rad ** -2.0
            if self.check_K1:
                hold[6:8] = (cfg.stereo_hold_sigma_rad * self.calib.cam1.fx) ** -2.0
            try:
                lam_post = np.asarray(self.smoother.getISAM2().jointMarginalInformation(keys).fullMatrix(), float)
            except GTSAM_ERRORS:
                return
            d = np.asarray(self._P_body_cam1_calib.localCoordinates(held), float)
            if self.check_K1:
                d = np.r_[d, np.asarray(self.K1.localCoordinates(self._estimate.atCal3_S2(self._k[1])), float)]
        try:
            S = np.linalg.inv(lam_post - np.diag(hold))
        except np.linalg.LinAlgError:
            return
        b = S @ (lam_post @ d)
        var = np.diag(S)
        if not (np.all(np.isfinite(b)) and np.all(np.isfinite(var)) and np.all(var[:3] > 0)):
            return
        fx = self.calib.cam1.fx
        # each reading in pixels, with its sigma: the disparity bias, then (K(1)) fx and fy at the image's edge
        px = [(b[1] * fx, np.sqrt(var[1]) * fx)]
        if self.check_K1 and np.all(var[6:8] > 0):
            edge = 0.5 * np.array([self.calib.cam1.width, self.calib.cam1.height]) / np.array([fx, self.calib.cam1.fy])
            px += [(b[6 + k] * edge[k], np.sqrt(var[6 + k]) * edge[k]) for k in (0, 1)]
        shows = [abs(v) >= cfg.stereo_check_px and abs(v) >= cfg.stereo_check_sigma * sg for v, sg in px]
        # A pull beyond any calibration drift is the estimate's, not the camera's: letting go of cam1 for it would
        # leave the scale to that estimate. (A replay started in a hover read 3.2 px at fx 190 px, 1 deg; let go,
        # it was 700 m off in 50 s.)
        implausible = max(abs(v) for v, _ in px) > np.tan(np.radians(cfg.stereo_check_max_deg)) * fx
        if implausible:
            shows = [False] * len(px)
        if self._settle_sigma is not None:  # the IMU noise was raised: the older factors' pull must fade first
            if self._settle_sigma == 0.0:
                self._settle_sigma = float(px[0][1])
            if px[0][1] > STEREO_SETTLE_SIGMA_SHARE * self._settle_sigma:
                shows = [False] * len(px)
            else:
                self._settle_sigma = None
        # a real calibration error stands out at every later check too; a transient (seen on EuRoC V1_01's real IMU
        # under rendered images: +0.65 +- 0.16 px at one check, 0.25 +- 0.14 at the next) does not
        self._stood_out = self._stood_out + 1 if any(shows) else 0
        release = self._stood_out >= cfg.stereo_check_confirm
        disp, sigma = (float(x) for x in px[0])
        focal = tuple((float(v), float(sg)) for v, sg in px[1:]) or None
        if release:
            try:
                self.smoother.update(gtsam.NonlinearFactorGraph(), gtsam.Values(), {}, self._holds)
                self._estimate = self.smoother.calculateEstimate()
                self.P_body_cam1 = self._estimate.atPose3(self._e[1])
                if self.check_K1:
                    self.K1 = self._estimate.atCal3_S2(self._k[1])
            except GTSAM_ERRORS as e:
                raise SmootherFailure(f"smoother update failed releasing the stereo extrinsic: "
                                      f"{type(e).__name__}") from None
            self._holds = []
        self.stereo_finding = StereoFinding(t_ns, disp, sigma, release, focal, implausible)

    def _relative_rotation_information(self, held: gtsam.Pose3) -> tuple[np.ndarray | None, np.ndarray]:
        """With the rig refined: the posterior information of cam1's rotation relative to cam0 (about cam1's axes),
        and where the held estimate `held` (E(0)^-1 E(1)) sits from the calibration's, for the score test.

        E(0) = E0^ Exp(x0), E(1) = E1^ Exp(x1) give E(0)^-1 E(1) = R^ Exp(-Ad(R^-1) x0 + x1) to first order, so the
        relative pose's covariance is A C A^T with A = [-Ad(R^-1), I] and C the joint marginal of E(0), E(1). The
        hold acts on the rotation alone (its translation sigma is 1 km), so the rotation's marginal information
        is the data's plus the hold's, as in the absolute check. (Conditioning on E(0) instead reads nothing where
        E(0) is free to turn with the pair; only the keyframes that pass the motion gate inform E(0), E(1).)"""
        try:
            lam = np.asarray(self.smoother.getISAM2().jointMarginalInformation(self._e).fullMatrix(), float)
            A = np.hstack([-np.asarray(held.inverse().AdjointMap(), float), np.eye(6)])
            lam_rot = np.linalg.inv((A @ np.linalg.inv(lam) @ A.T)[:3, :3])
        except (*GTSAM_ERRORS, np.linalg.LinAlgError):
            return None, np.zeros(3)
        return lam_rot, np.asarray(self._P_cam0_cam1_calib.localCoordinates(held), float)[:3]

    def _factor_maker(self, refine: bool):
        """Projection factor of pixel uv in camera `cam` of keyframe i on landmark `key`: with the extrinsic
        as a variable (E(cam), when refining) or fixed at its current estimate."""
        K = (self.K0, self.K1)
        if refine and self.refine_K:
            from gtsam_unstable import ProjectionFactorPPPCCal3_S2

            return lambda uv, i, key, cam: ProjectionFactorPPPCCal3_S2(uv, self.pixel_noise, self._pose_key(i),
                                                                       self._e[cam], key, self._k[cam], False, False)
        if refine:
            from gtsam_unstable import ProjectionFactorPPPCal3_S2

            return lambda uv, i, key, cam: ProjectionFactorPPPCal3_S2(uv, self.pixel_noise, self._pose_key(i),
                                                                      self._e[cam], key, K[cam], False, False)
        P = (self.P_body_cam0, self.P_body_cam1)

        def fixed(uv, i, key, cam):
            return gtsam.GenericProjectionFactorCal3_S2(uv, self.pixel_noise, self._pose_key(i), key, K[cam], False,
                                                        False, P[cam])
        if not self.refine_stereo:
            return fixed
        from gtsam_unstable import ProjectionFactorPPPCal3_S2

        # refine_stereo_rotation: cam0 fixed, cam1 through its variable pose on the body (and intrinsics)
        if self.check_K1:
            from gtsam_unstable import ProjectionFactorPPPCCal3_S2

            return lambda uv, i, key, cam: fixed(uv, i, key, 0) if cam == 0 else ProjectionFactorPPPCCal3_S2(
                uv, self.pixel_noise, self._pose_key(i), self._e[1], key, self._k[1], False, False)
        return lambda uv, i, key, cam: fixed(uv, i, key, 0) if cam == 0 else ProjectionFactorPPPCal3_S2(
            uv, self.pixel_noise, self._pose_key(i), self._e[1], key, K[1], False, False)

    def _triangulate(self, obs: list[tuple[int, np.ndarray]], uv0: np.ndarray,
                     T_world_cam0: np.ndarray) -> np.ndarray | None:
        """World point of a mono track from its keyframe pixels and the current one, or None when the rays are
        too parallel, the point lies outside the depth limits in a view, or does not reproject within
        MONO_MAX_REPROJ_PX (a track that slid along an edge)."""
        cfg = self.cfg
        poses = [self._estimate.atPose3(self._pose_key(i)).compose(self.P_body_cam0) for i, _ in obs]
        poses.append(gtsam.Pose3(T_world_cam0))
        pixels = [uv for _, uv in obs] + [uv0]
        K = self.K0.K()
        Kinv = np.linalg.inv(K)
        rays = [p.rotation().matrix() @ (Kinv @ np.array([u[0], u[1], 1.0])) for p, u in zip(poses, pixels)]
        cos = float(rays[0] @ rays[-1] / (np.linalg.norm(rays[0]) * np.linalg.norm(rays[-1])))
        if np.degrees(np.arccos(min(cos, 1.0))) < cfg.mono_min_parallax_deg:
            return None
        try:
            p_w = np.asarray(gtsam.triangulatePoint3(poses, self.K0, pixels, 1e-9, True), float).reshape(3)
        except GTSAM_ERRORS:  # cheirality or a degenerate system: not a usable point (yet)
            return None
        for pose, uv in zip(poses, pixels):
            p_c = pose.transformTo(p_w)
            if not (cfg.min_depth_m <= p_c[2] <= cfg.max_depth_m):
                return None
            if np.sum((K[:2, :2] @ (p_c[:2] / p_c[2]) + K[:2, 2] - uv) ** 2) > MONO_MAX_REPROJ_PX ** 2:
                return None
        return p_w

    def time_offset_ns(self) -> int | None:
        """The camera-IMU offset the time state measured (applied + residual) at the newest keyframe that moved
        fast enough to show it, while that keyframe is inside the lag; else None. The newest keyframe's own value
        is that one carried on by the rate through keyframes too slow to tell, which after a long slow stretch
        is an extrapolation, not a measurement: not what a reset should apply to every frame stamp."""
        if self._linked is None or self._estimate is None or not self._estimate.exists(D(self._linked[0])):
            return None
        j, applied = self._linked
        return applied + int(round(self._estimate.atDouble(D(j)) * 1e6))

    def marginal_covariances(self) -> tuple[np.ndarray, np.ndarray]:
        """Marginal covariance of the newest pose (6x6, rot then trans, body tangent) and velocity."""
        try:
            return (np.asarray(self.smoother.marginalCovariance(X(self.index))),
                    np.asarray(self.smoother.marginalCovariance(V(self.index))))
        except GTSAM_ERRORS as e:
            raise SmootherFailure(f"marginal covariance failed: {e}") from None

    def stereo_rotation_sigma_rad(self) -> np.ndarray | None:
        """1-sigma of cam1's refined rotation (about cam1's x, y, z) from the smoother's marginal of E(1); None
        unless cam1 is refined alone (`refine_stereo_rotation`), or when the marginal fails. What a refined
        stereo calibration can be trusted to: an interval, somewhat optimistic (the fixed lag marginalises)."""
        if not self.refine_stereo or self._holds:  # with refine_extrinsics, E(1)'s marginal is
            return None  # not the stereo extrinsic's; while the stereo check holds it, the hold's
        try:
            cov = np.asarray(self.smoother.marginalCovariance(self._e[1]))
        except GTSAM_ERRORS:
            return None
        return np.sqrt(np.maximum(np.diag(cov)[:3], 0.0))


def spread_order(uv: np.ndarray, track_len: np.ndarray, width: int, height: int, cols: int = 6,
                 rows: int = 4) -> np.ndarray:
    """Track indices ordered so that any prefix is spread over the image, long tracks first.

    Round-robin over a grid: the longest track of every occupied cell, then the second longest of every
    cell, ... A bounded number of landmarks then constrains rotation and translation as well as all of
    them would, instead of clustering on one textured corner. Vectorised (this runs per keyframe).
    """
    n = len(track_len)
    if n == 0:
        return np.zeros(0, np.int64)
    cx = np.clip((uv[:, 0] * cols / width).astype(np.int64), 0, cols - 1)
    cy = np.clip((uv[:, 1] * rows / height).astype(np.int64), 0, rows - 1)
    cell = cy * cols + cx
    by_len = np.argsort(-np.asarray(track_len), kind="stable")
    by_cell = by_len[np.argsort(cell[by_len], kind="stable")]  # grouped by cell, longest first inside
    cell_sorted = cell[by_cell]
    starts = np.flatnonzero(np.r_[True, cell_sorted[1:] != cell_sorted[:-1]])
    rank = np.arange(n) - np.repeat(starts, np.diff(np.r_[starts, n]))
    rank_of = np.empty(n, np.int64)
    rank_of[by_cell] = rank
    len_pos = np.empty(n, np.int64)
    len_pos[by_len] = np.arange(n)
    return np.lexsort((len_pos, rank_of))
