"""Camera-IMU time offset estimated in flight, from the front end's tracks and the gyro.

Why: a calibration's offset is often wrong on a new rig or after a firmware change, and at the yaw rates
of an aggressive flight 10 ms of error put the images ~1 deg behind the IMU, which the smoother cannot
absorb (synthetic aggressive flight: ATE 0.47 m instead of ~1 cm). VINS-Fusion makes the offset a state
of the optimiser; here it is a robust pre-alignment instead, which costs nothing per observation: the
camera rotation between frames `span_frames` apart is measured from the tracks they share (PnP on the
earlier frame's stereo points; essential matrix without stereo) and compared with the gyro integral
over the same interval shifted by candidate offsets (the method of `vio calib time-offset`,
`vio.backend.offset_solver.estimate_time_offset`: grid + parabola, bias solved, outlier
pairs dropped, bootstrap sigma). Pairs that barely turn are skipped; from MIN_PAIRS informative pairs on,
the newest `window_s` of pairs is solved every SOLVE_EVERY pairs, so the offset is known a few seconds
after take-off, before a wrong one has done much harm, and refined as the window fills. An estimate is
used when observable with a small sigma (and not much worse than the last one); collection stops once
sigma is below `final_sigma_s` on a full window, or after `max_solves`. While it runs it costs a PnP per
frame (~0.4 ms) and stereo on one frame in `span_frames` at least: a pair starts at the newest frame with
stereo depth that is `span_frames` or more back (stereo on every frame made a survey flight, which
collects for the whole `max_collect_s`, replay ~20 % slower).

Continuous tracking (`continuous=True`, `[backend] time_offset_continuous`): USB cameras and serial IMUs
drift by milliseconds over a minute, so instead of stopping, collection goes on from the first accepted
estimate on, on a shorter window (`track_window_s`: each estimate is the window's mean offset, so it lags by
half the window). The estimates of the last TRACK_HISTORY_WINDOWS windows are fitted with a line (weights
1/sigma^2, each estimate placed at its pairs' mean time); the newest estimate carried forward to the
newest frame along the line's slope is applied, so a drift is followed without the half-window lag (the
line's own value there overshot where the drift turned: extrapolated from its centre, 6 s back).
Hovering gives no informative pairs: no solve, the offset stays where it was (and the PnP per frame
goes on costing ~0.4 ms).

Re-checks (`recheck_s`, `[backend] time_offset_recheck_s`): once collection has stopped, the offset is
checked again every `recheck_s` on one window of pairs (at most twice its length of flight time, so a hover
does not keep it running). An estimate significantly off the applied offset (SIGNIFICANT_SIGMAS, with the
systematic error) from half a window on is applied: a clock that drifts slowly, or only later, is caught
within a re-check period instead of never. In between it costs nothing; during a re-check what collection
costs.

Why frames apart rather than consecutive: shifting an interval by d changes its gyro integral by
(w(t1) - w(t0)) d, so the signal grows with the interval while the visual rotation noise does not (at
50 ms it drowned in the noise: +-5 ms sigma per 8 s window).
"""

from __future__ import annotations

import logging
from collections import deque

import numpy as np

from vio import VioError
from vio.backend.offset_solver import (
    MIN_AXIS_RATE_RAD_S,
    VisualRotations,
    estimate_time_offset,
    fit_camera_imu_rotation,
    rotation_disagreement,
)
from vio.calibration import StereoCalibration
from vio.geometry import so3_log
from vio.imu_buffer import ImuBuffer
from vio.relative_pose import points_from_depth, relative_rotation, solve_pnp
from vio.sanity import GyroScaleCheck
from vio.types import FeatureFrame, ImuSample

log = logging.getLogger(__name__)

MIN_SHARED_TRACKS = 15  # frame pairs sharing fewer tracks give no rotation
MIN_PAIR_ROTATION_RAD = 0.01  # pairs turning less carry no offset information (standing still, straight flight)
MIN_PAIRS = 40  # first solve after this many informative pairs, then again every SOLVE_EVERY new ones
SOLVE_EVERY = 20
PNP_MAX_DEPTH_M = 40.0  # farther stereo points hardly constrain the rotation's PnP translation coupling
CHANGE_NS = 500_000  # smaller corrections are not applied (no jitter of the frame stamps)
SIGNIFICANT_SIGMAS = 2.5  # an estimate replaces the calibration's offset only when this many sigmas away from it
MIN_APPLY_RATE_STD_RAD_S = 0.2  # slower turning than this: an estimate is not applied (see _solve)
SLOW_READINGS_TO_WARN = 5  # estimates on slow turns that agree on an offset off the calibration's: said, not applied
SLOW_SIGNIFICANT_SIGMAS = 4.0  # ... each this many sigmas (with the systematic error) off it
SLOW_MAX_SIGMA_S = 0.010  # ... each at most this uncertain (slow turns give 3-7 ms where a turn gives under 2)
# The method's own systematic error, which its sigma (residual scatter, bootstrap) does not contain: on simulated
# flights whose true offset is 0 it answers -0.4 to -0.9 ms +- 0.1-0.4 ms (its PnP rotations carry errors that
# follow the motion; the front end's tracks show no lag). Added in quadrature to sigma when an estimate is
# weighed against the calibration. 0.5 ms also kept EuRoC V1_01's real -1.0 ms from being applied (ATE 1.17x).
SYSTEMATIC_SIGMA_S = 0.3e-3
# A camera-IMU rotation this far from the calibration's (beyond MOUNT_SIGMAS of the fit's uncertainty, on
# MOUNT_CONFIRM solves in a row) is a mount or axes mistake (an IMU turned 90 deg, upside down, T_cam_imu inverted, a
# rig knocked on its mount), not a calibration error: those are tenths of a degree, the extrinsic refinement's. A
# replay with the IMU's axes turned 90 deg went 1.1 m off, saying only that the right camera disagreed with the
# calibration; 5 deg about z took an aggressive flight's ATE from 6 to 85 mm. With exact calibrations the fit read at
# most 0.95 deg over turns about two axes and 0.99 deg about one (the hard survey) on the accuracy matrix's 60 s
# flights, real EuRoC IMUs among them: the limits leave four and fifteen times that. Turns about one axis only (a
# survey's yaw) show only where that axis lies in the body, hence the wider limit there.
MOUNT_MAX_DEG = 4.0
MOUNT_MAX_DEG_ONE_AXIS = 15.0
MOUNT_SIGMAS = 3.0
MOUNT_CONFIRM = 2
MOUNT_OFFSET_STEP_S = 0.005  # offsets searched again for a fit beyond them (half a step: a tenth of a degree or so)
TRACK_CHANGE_NS = 200_000  # while tracking, smaller changes of the predicted offset are not applied
TRACK_STEP_NS = 50_000  # between solves the offset follows the fitted drift in steps of this size
TRACK_HISTORY_WINDOWS = 1.5  # estimates of this many tracking windows back make the drift line
MAX_DRIFT_NS_PER_S = 2_000_000  # a fitted drift faster than 2 ms/s is noise, not a clock


def _has_depth(ff: FeatureFrame) -> bool:
    """Enough stereo points for a pair starting at this frame to use PnP."""
    return ff.n_stereo >= MIN_SHARED_TRACKS


class OnlineTimeOffset:
    """Collects (frame pair rotation, gyro) and answers the camera-IMU offset t_imu = t_cam + offset."""

    def __init__(self, calib: StereoCalibration, window_s: float = 8.0, max_offset_s: float = 0.05,
                 accept_sigma_s: float = 0.002, final_sigma_s: float = 0.0005, max_solves: int = 30,
                 span_frames: int = 4, max_collect_s: float = 120.0, imu: ImuBuffer | None = None,
                 continuous: bool = False, track_window_s: float = 4.0, coarse_only: bool = False,
                 recheck_s: float = 0.0, max_gyro_bias_rad_s: float = 0.3) -> None:
        """`imu`: a buffer someone else fills (the estimator's one buffer), which must then keep at least
        `keep_samples` samples while `done` is False; without one the solver keeps its own (`add_imu`).
        `coarse_only`: stop at the first accepted estimate (the smoother's time offset state refines and
        follows the offset from there, so collecting on costs a PnP per frame for nothing).
        `max_gyro_bias_rad_s`: the largest plausible gyro bias, which the gyro-against-camera check allows for."""
        cam = calib.cam0
        self.f_px = cam.fx
        self.c = np.array([cam.cx, cam.cy])
        self.fxy = np.array([cam.fx, cam.fy])
        self.K = cam.K
        self.cam_rate_hz = cam.rate_hz
        self.R_body_cam = cam.T_body_cam[:3, :3].copy()
        self.base_ns = int(calib.time_offset_ns)  # searched around the calibration's value
        self.max_offset_s = max_offset_s
        self.accept_sigma_s = accept_sigma_s
        self.final_sigma_s = final_sigma_s
        self.max_solves = max_solves
        self.span_frames = span_frames
        self.max_collect_ns = int(max_collect_s * 1e9)
        self._t_first: int | None = None
        self.offset_ns: int | None = None  # last accepted estimate
        self.applied_ns = self.base_ns  # offset the frames use: the calibration's until an estimate replaces it
        self.slow_readings: list[tuple[float, float, float]] = []  # (offset, sigma, newest pair end) [s], slow turns
        self.slow_warning: str | None = None  # said once when they agree on an offset off the calibration's
        self.sigma_s = float("inf")
        self.done = False
        self.solves = 0
        # frames back to 2 spans: a pair starts at the newest frame with stereo at least span_frames back,
        # so the front end needs stereo on one frame in span_frames only (see wants_stereo)
        self._recent: deque[FeatureFrame] = deque(maxlen=2 * span_frames)
        self._pairs: deque[tuple[int, int, np.ndarray, int, np.ndarray]] = deque(
            maxlen=max(int(round(window_s * cam.rate_hz)), MIN_PAIRS))
        self._new_pairs = 0
        self._postponed = 0  # pairs added while a due solve waited for a quiet frame
        self.window_s = window_s
        self.keep_samples = int((window_s + 4 * max_offset_s + 2.0) * 1000)  # the window at up to 1 kHz
        self.continuous = continuous
        self.coarse_only = coarse_only and not continuous
        self.tracking = False  # continuous mode after the first converged estimate
        self._track_pairs = max(int(round(track_window_s * cam.rate_hz)), MIN_PAIRS)
        self._history: deque[tuple[int, int, float]] = deque()  # (mean pair time ns, offset ns, sigma s)
        self._history_ns = int(TRACK_HISTORY_WINDOWS * track_window_s * 1e9)
        self._drift: tuple[int, float, float] | None = None  # (anchor ns, offset ns there, slope ns/ns)
        self._recheck_ns = int(recheck_s * 1e9)
        self._next_check_ns: int | None = None  # camera time of the next re-check (after collection stopped)
        self.rechecking = False
        self.rechecks = 0
        self._t_last: int | None = None
        self._owned = imu is None
        self.imu = ImuBuffer() if imu is None else imu
        # its pairs are these pairs: a gyro in the wrong units, or turning about other axes, shows here first
        self.gyro_scale = GyroScaleCheck(max_gyro_bias_rad_s)
        self.mount_problem: str | None = None
        self._mount_seen = 0  # solves in a row whose fit found the mount wrong
        self.mount_judged = False  # a fit over turns about two axes found the mount right

    def add_imu(self, s: ImuSample) -> None:
        """Feed a sample to the solver's own buffer (not needed, and not allowed, with a shared one)."""
        if not self._owned:
            raise VioError("OnlineTimeOffset reads a shared IMU buffer: feed that buffer, not the solver")
        if not self.done and self.imu.add(s) and len(self.imu) > self.keep_samples:
            del self.imu.t[0], self.imu.gyro[0], self.imu.accel[0]

    def add_frame(self, ff: FeatureFrame, solve: bool = True) -> int | None:
        """Add a front-end result (camera clock); returns a newly accepted offset [ns], else None.

        `solve=False` postpones a due solve (the caller's frame is busy) by up to SOLVE_EVERY more pairs.
        While tracking, the offset also moves between solves along the fitted drift (steps of
        TRACK_STEP_NS): held between solves, which are 1-4 s apart, it fell up to 0.8 ms behind."""
        new = self._collect(ff, solve)
        if new is None and self.tracking and self._drift is not None:
            t_anchor, off_anchor, slope = self._drift
            pred = int(round(off_anchor + slope * (int(ff.t_ns) + self.base_ns - t_anchor)))
            if abs(pred - self.applied_ns) >= TRACK_STEP_NS:
                self.offset_ns = self.applied_ns = new = pred
        return new

    def _collect(self, ff: FeatureFrame, solve: bool) -> int | None:
        checks_only = self.done  # the offset is settled; the IMU checks still want pairs (checks_pending)
        if checks_only and not self.checks_pending:
            return None
        if not checks_only:
            self._t_first = ff.t_ns if self._t_first is None else self._t_first
            self._t_last = int(ff.t_ns)
            limit = 2 * self._window_ns() if self.rechecking else self.max_collect_ns
            if ff.t_ns - self._t_first > limit and not self.tracking:  # hover: stop paying for it
                self._finish()
                return None
        if not ff.tracking_ok:
            self._recent.clear()
            return None
        prev = self._pair_start()
        self._recent.append(ff)
        if prev is None:
            return None
        _, i0, i1 = np.intersect1d(prev.ids, ff.ids, assume_unique=True, return_indices=True)
        if len(i0) < MIN_SHARED_TRACKS:
            return None
        res = self._pnp_rotation(prev, ff, i0, i1)
        if res is None:
            res = relative_rotation((prev.uv0[i0] - self.c) / self.fxy, (ff.uv0[i1] - self.c) / self.fxy, self.f_px,
                                    MIN_SHARED_TRACKS)
        if res is None:
            return None
        theta = so3_log(res[0])
        b = self.base_ns
        if self.gyro_scale.problem is None:  # before the rotation filter: a camera that barely turns says most
            a = self.applied_ns  # the gyro over the pair as the frames are stamped now
            self.gyro_scale.add(float(np.linalg.norm(theta)), self._gyro_angle(int(prev.t_ns) + a, int(ff.t_ns) + a),
                                (int(ff.t_ns) - int(prev.t_ns)) * 1e-9)
        if np.linalg.norm(theta) < MIN_PAIR_ROTATION_RAD:
            return None
        self._pairs.append((int(prev.t_ns) + b, int(ff.t_ns) + b, theta, int(res[1]), res[2]))
        self._new_pairs += 1
        if len(self._pairs) < MIN_PAIRS or self._new_pairs < SOLVE_EVERY:
            return None
        if checks_only:  # the mount fit at the pace the solves had, no offset solve
            self._new_pairs = 0
            self._check_mount(*self._window())
            return None
        if not solve and self._postponed < SOLVE_EVERY:
            self._postponed += 1
            return None
        return self._solve()

    def _window(self) -> tuple[VisualRotations, np.ndarray, np.ndarray]:
        """The window's frame pairs and the IMU history that covers them (t_ns, gyro)."""
        t0, t1, th, n, info = (np.array(x) for x in zip(*self._pairs))
        imu_t, gyro = self.imu.tail(self.keep_samples)
        return VisualRotations(t0.astype(np.int64), t1.astype(np.int64), th, n, info), imu_t, gyro

    def _gyro_angle(self, t0_ns: int, t1_ns: int) -> float:
        """|integral of the gyro| over [t0, t1] (IMU clock) [rad]: the pair's rotation as the gyro has it."""
        t, gyro, _ = self.imu.window(t0_ns, t1_ns)
        if len(t) < 2:
            return float("nan")
        dt = np.diff(t) * 1e-9
        return float(np.linalg.norm(((gyro[1:] + gyro[:-1]) * 0.5 * dt[:, None]).sum(axis=0)))

    @property
    def checks_pending(self) -> bool:
        """Whether the IMU-against-camera checks still want frame pairs after the offset is settled: no verdict yet,
        and not yet judged on enough turns (the scale on 3 x SCALE_PAIRS pairs that could tell, the mount on a fit
        over turns about two axes). A daemon started at boot can sit on the ground for minutes, beyond the offset
        estimate's `max_collect_s`, and a gyro in the wrong units must still be caught at the first turns; until
        they are judged this costs what collecting did (a PnP per frame), no stereo is asked for."""
        return self.imu_problem is None and not (self.gyro_scale.judged and self.mount_judged)

    @property
    def keeps_imu(self) -> bool:
        """Whether the shared IMU buffer must hold `keep_samples` (collecting, or the checks still running)."""
        return not self.done or self.checks_pending

    @property
    def imu_problem(self) -> str | None:
        """What the pairs found wrong with the IMU against the camera (units or scale, or axes), None if nothing."""
        return self.gyro_scale.problem or self.mount_problem

    def _check_mount(self, vis: VisualRotations, imu_t: np.ndarray, gyro: np.ndarray) -> None:
        """The camera-IMU rotation the window's turns show (the hand-eye fit `vio calib check` makes) against the
        calibration's: a mount or axes mistake is named (`mount_problem`) once MOUNT_CONFIRM solves in a row find
        it. One fit (a few 3x3 SVDs over the window's pairs) at each of the offset's solves; a fit beyond the limit
        is made again over the offsets searched and judged at the one that explains the turns best: an offset the
        calibration gets 45 ms wrong tilted the fit by 5 deg (+- 1.1) on an aggressive flight, and the applied
        offset is the calibration's until the first estimate replaces it."""
        if self.mount_problem is not None:
            return
        applied_s = (self.applied_ns - self.base_ns) * 1e-9  # the pairs are stamped at the calibration's offset
        fit = self._mount_fit(vis, imu_t, gyro, applied_s)
        problem = None if fit is None else self._mount_wrong(fit)
        if problem:
            grid = np.arange(-self.max_offset_s, self.max_offset_s + 1e-9, MOUNT_OFFSET_STEP_S)
            fits = [f for f in (self._mount_fit(vis, imu_t, gyro, float(o)) for o in grid) if f is not None]
            problem = self._mount_wrong(min(fits, key=lambda f: f.residual_rad_s, default=fit))
        self._mount_seen = self._mount_seen + 1 if problem else 0
        if problem and self._mount_seen >= MOUNT_CONFIRM:
            self.mount_problem = problem
        elif not problem and fit is not None and fit.axis_rates[1] >= MIN_AXIS_RATE_RAD_S:
            self.mount_judged = True

    @staticmethod
    def _mount_fit(vis: VisualRotations, imu_t: np.ndarray, gyro: np.ndarray, offset_s: float):
        if len(imu_t) < 2:
            return None
        try:
            return fit_camera_imu_rotation(vis, imu_t, gyro, offset_s)
        except (VioError, ValueError, np.linalg.LinAlgError):
            return None

    def _mount_wrong(self, fit) -> str | None:
        """What a fit says is wrong with the calibration's camera-IMU rotation; None if nothing (module constants)."""
        seen = rotation_disagreement(fit, self.R_body_cam)
        if seen is None:
            return None
        ang, sigma, what = seen
        limit = MOUNT_MAX_DEG if fit.axis_rates[1] >= MIN_AXIS_RATE_RAD_S else MOUNT_MAX_DEG_ONE_AXIS
        if ang <= limit or ang <= MOUNT_SIGMAS * sigma:
            return None
        why = ("the IMU's mount or axes in the calibration (T_body_cam0) are wrong, or T_cam_imu is inverted"
               if ang >= 45 else "the camera or the IMU sits differently on the airframe from when the calibration "
               "was made, or the calibration is another rig's")
        return (f"the camera turns about other axes than the calibration says: {what} {ang:.0f} deg (+- {sigma:.1f}) "
                f"from the gyro's, over {fit.n_pairs} frame pairs: {why} (vio calib check CALIB DATASET measures it)")

    def _window_ns(self) -> int:
        return int(self._pairs.maxlen / self.cam_rate_hz * 1e9)

    def collects(self, t_ns: int) -> bool:
        """Whether the frame at t_ns (camera clock) is collected: while collecting, or when a re-check is due
        (which then starts here)."""
        if not self.done:
            return True
        if self._next_check_ns is None or t_ns < self._next_check_ns:
            return self.checks_pending
        self.done, self.rechecking = False, True
        self.rechecks += 1
        self._next_check_ns = None
        self._t_first = int(t_ns)
        self._recent.clear()
        self._pairs.clear()
        self._new_pairs = self._postponed = 0
        log.debug("time offset: re-check %d (applied %+.2f ms)", self.rechecks, self.applied_ns * 1e-6)
        return True

    def wants_stereo(self) -> bool:
        """Whether the next frame needs stereo depth for the pairs to come: true when none of the newest
        span_frames - 1 frames has it. Stereo on every frame doubled the image work (right image decoding
        and matching) for the up to `max_collect_s` that collection lasts on a flight that barely turns."""
        if self.done or self.rechecking:  # a re-check uses the frames that have stereo anyway: it changes nothing
            return False
        newest = list(self._recent)[-(self.span_frames - 1):] if self.span_frames > 1 else []
        return not any(map(_has_depth, newest))

    def _pair_start(self) -> FeatureFrame | None:
        """The frame a pair ending at the next frame starts at: the newest one at least span_frames back that
        has stereo (PnP); without any (camera-only operation) the one exactly span_frames back, whose
        rotation then comes from the essential matrix."""
        frames = list(self._recent)
        if len(frames) < self.span_frames:
            return None
        starts = frames[:len(frames) - self.span_frames + 1]
        return next((f for f in reversed(starts) if _has_depth(f)), frames[-self.span_frames])

    def _pnp_rotation(self, prev: FeatureFrame, cur: FeatureFrame, i0: np.ndarray,
                      i1: np.ndarray) -> tuple[np.ndarray, int, np.ndarray] | None:
        """R_cam(prev)_cam(cur) from prev's stereo points and cur's pixels (RANSAC PnP).

        Preferred over the essential matrix, which picks wrong rotations on the (nearly) planar walls a
        drone often sees; the stereo depth makes the problem well posed."""
        d = prev.depth_m[i0]
        ok = np.isfinite(d) & (d > 0.1) & (d < PNP_MAX_DEPTH_M)
        if ok.sum() < MIN_SHARED_TRACKS:
            return None
        # EPnP alone is too noisy for a 1 ms offset (0.3 px noise gave offsets at the search bound): refined
        pose = solve_pnp(points_from_depth(prev.uv0[i0][ok], d[ok], self.K), cur.uv0[i1][ok], self.K,
                         min_inliers=MIN_SHARED_TRACKS, iterations=50, reprojection_error=2.0)
        if pose is None:
            return None
        n = pose.n_inliers
        return pose.R_prev_cur, n, n * np.eye(3)

    def _solve(self) -> int | None:
        """Solve on the newest window of pairs; report the offset when confident and changed."""
        self._new_pairs = 0
        self._postponed = 0
        self.solves += 1
        vis, imu_t, gyro = self._window()
        self._check_mount(vis, imu_t, gyro)
        try:
            est = estimate_time_offset(vis, imu_t, gyro, self.R_body_cam, max_offset_s=self.max_offset_s, n_boot=30)
        except (VioError, np.linalg.LinAlgError) as e:
            log.debug("time offset solve %d: no estimate (%s)", self.solves, e)
            est = None
        changed = None
        if self.tracking:
            return self._track(est, vis.t0_ns, vis.t1_ns)
        if self.rechecking:
            return self._recheck(est)
        if self._applicable(est, min(self.accept_sigma_s, self.sigma_s * 1.5)):
            new = self._offset_ns(est)
            self.offset_ns, self.sigma_s = new, est.sigma_s
            log.info("camera-IMU time offset %+.1f ms +- %.1f ms from %d frame pairs (solve %d, rotation std "
                     "%.2f rad/s)", new * 1e-6, est.sigma_s * 1e3, est.n_pairs, self.solves, est.rate_std_rad_s)
            self.done = (self.coarse_only or (est.sigma_s <= self.final_sigma_s
                                              and len(self._pairs) == self._pairs.maxlen)) \
                and self._mount_seen == 0  # a mount found wrong once is looked at again before collection stops
            # Only an estimate significantly off the calibration's value replaces it, and one that is not (any
            # more) puts the calibration's back: on the aggressive flights 0.5 ms of error costs ~2 cm of ATE,
            # estimates 1-2 sigma off a correct calibration replaced it with a worse value, and a 2.5-sigma
            # -1.0 ms on a hard flight whose later estimates came back to -0.5 +- 0.5 ms stayed applied
            # (ATE 20 -> 95 mm). Compared with the applied offset, not the last estimate: estimates that
            # creep by less than CHANGE_NS per solve must still get applied (they once left a 10 ms offset
            # stuck 1.2 ms short).
            # against the calibration the method's systematic error counts too; between two of its own
            # estimates (a correction already applied moving on) it is common to both, so only sigma counts
            off_calib_ns = float(np.hypot(est.sigma_s, SYSTEMATIC_SIGMA_S)) * 1e9
            target = new if abs(new - self.base_ns) >= SIGNIFICANT_SIGMAS * off_calib_ns else self.base_ns
            if abs(target - self.applied_ns) >= max(CHANGE_NS, SIGNIFICANT_SIGMAS * est.sigma_s * 1e9
                                                    if target != self.base_ns else 0):
                changed = self.applied_ns = target
            self.slow_readings.clear()  # an applied estimate breaks a run of slow ones
        elif est is not None:
            log.debug("time offset solve %d: %+.1f ms +- %.1f ms, rotation std %.2f rad/s: not used", self.solves,
                      self.base_ns * 1e-6 + est.offset_s * 1e3, est.sigma_s * 1e3, est.rate_std_rad_s)
            self._slow_reading(est, int(vis.t1_ns.max()))
        else:
            self.slow_readings.clear()  # so does a solve with no estimate
        if self.solves >= self.max_solves:
            self.done = True
        if self.continuous and self.offset_ns is not None:  # tracking from the first estimate on: waiting
            self.done = False                                 # for convergence (12 s) lagged a drift by 2 ms
            self._start_tracking()
        elif self.done:
            self._finish()
        return changed

    def _slow_reading(self, est, t_newest_ns: int) -> None:
        """An estimate not applied only because the vehicle turned too slowly: when SLOW_READINGS_TO_WARN in a row
        stand out from the calibration's offset on the same side, say so once (a warning and `slow_warning`, which
        the status shows). Not applied: on slow turns the method's errors are not known well enough (see _solve),
        but a QA run whose calibration said 0 ms against a true 30 ms read +31 ms +- 3 ms in 29 solves, all at
        DEBUG, while its ATE was 4.8x the right calibration's."""
        # the solver calls a reading under 0.1 rad/s of rotation std unobservable, and it is not applied; a run of
        # them well inside the searched span, each several sigma off the calibration on the same side, still says
        # the calibration's offset is off (the QA run's: 29 solves at +30.6 .. +43 ms +- 3-7 ms, truth +30)
        if self.slow_warning is not None:
            return
        # a reading refused on a fast turn (its sigma), one too uncertain or at the edge of the search, or one
        # that agrees with the calibration breaks the run: only consecutive slow readings off it count
        if est.rate_std_rad_s >= MIN_APPLY_RATE_STD_RAD_S or est.sigma_s > SLOW_MAX_SIGMA_S or \
                abs(est.offset_s) > 0.8 * self.max_offset_s or \
                abs(est.offset_s) < SLOW_SIGNIFICANT_SIGMAS * float(np.hypot(est.sigma_s, SYSTEMATIC_SIGMA_S)):
            self.slow_readings.clear()
            return
        # the newest pair's end, on the flight's clock: the estimate's own pair times count from its window's first
        # pair, which slides with the window, so that once the window was full consecutive readings stood as far
        # apart as their windows' newest pairs from their oldest (about the same: the run never covered half a
        # window, and no warning came; a QA run read +21..+26 ms at 4-6 sigma for 20 s against a calibration's 0)
        self.slow_readings.append((est.offset_s, est.sigma_s, t_newest_ns * 1e-9))
        if len({np.sign(r[0]) for r in self.slow_readings[-SLOW_READINGS_TO_WARN:]}) > 1:
            self.slow_readings = self.slow_readings[-1:]  # sides changed: a new run starts here
        last = self.slow_readings[-SLOW_READINGS_TO_WARN:]
        # consecutive solves share most of their window: the run must also cover half a window of new pairs
        if len(last) < SLOW_READINGS_TO_WARN or last[-1][2] - last[0][2] < 0.5 * self.window_s:
            return
        read_ms = (self.base_ns * 1e-9 + float(np.median([r[0] for r in last]))) * 1e3
        sigma_ms = max(r[1] for r in last) * 1e3
        self.slow_warning = (
            f"camera-IMU time offset: {SLOW_READINGS_TO_WARN} solves read {read_ms:+.1f} ms (+- {sigma_ms:.1f} ms) "
            f"against the calibration's {self.base_ns * 1e-6:+.1f} ms, on turns too slow to apply it (rotation std "
            f"{est.rate_std_rad_s:.2f} rad/s, {MIN_APPLY_RATE_STD_RAD_S} needed): the calibration's offset may be "
            "wrong; measure it (vio calib time-offset DATASET) and fix the calibration")
        log.warning("%s", self.slow_warning)

    @staticmethod
    def _applicable(est, max_sigma_s: float) -> bool:
        """An estimate that may replace the applied offset: observable, sigma <= max_sigma_s, and made while
        the vehicle turned enough (MIN_APPLY_RATE_STD_RAD_S)."""
        return (est is not None and est.observable and est.rate_std_rad_s >= MIN_APPLY_RATE_STD_RAD_S
                and est.sigma_s <= max_sigma_s)

    def _offset_ns(self, est) -> int:
        """The estimate as an offset t_imu = t_cam + offset [ns] (it is solved around the calibration's)."""
        return self.base_ns + int(round(est.offset_s * 1e9))

    def _recheck(self, est) -> int | None:
        """A re-check's solve: apply an estimate that is significantly off the applied offset (from half a
        window of pairs on: a first solve on 2 s of pairs is too easily a few sigma off); stop at a full window."""
        if self._applicable(est, self.accept_sigma_s) and 2 * len(self._pairs) >= self._pairs.maxlen:
            new = self._offset_ns(est)
            off_ns = float(np.hypot(est.sigma_s, SYSTEMATIC_SIGMA_S)) * 1e9
            if abs(new - self.applied_ns) >= max(CHANGE_NS, SIGNIFICANT_SIGMAS * off_ns):
                log.info("camera-IMU time offset re-checked: %+.1f ms +- %.1f ms from %d frame pairs, %+.1f ms "
                         "applied: it moved", new * 1e-6, est.sigma_s * 1e3, est.n_pairs, self.applied_ns * 1e-6)
                self.offset_ns = self.applied_ns = new
                self.sigma_s = est.sigma_s
                self._finish()
                return new
        if len(self._pairs) == self._pairs.maxlen:
            self._finish()
        return None

    def _start_tracking(self) -> None:
        self.tracking = True
        self._pairs = deque(list(self._pairs)[-self._track_pairs:], maxlen=self._track_pairs)
        log.info("time offset: %+.1f ms; tracking it from now on, on %d-pair windows", self.offset_ns * 1e-6,
                 self._track_pairs)

    def _track(self, est, t0: np.ndarray, t1: np.ndarray) -> int | None:
        """Tracking: add the window's estimate to the history, fit the drift line, apply its value now."""
        if est is None or not est.observable or est.sigma_s > self.accept_sigma_s:
            return None
        t_mid = int(np.mean(0.5 * (t0 + t1)))
        self._history.append((t_mid, self._offset_ns(est), est.sigma_s))
        t_now = int(t1.max())
        while self._history and self._history[0][0] < t_mid - self._history_ns:
            self._history.popleft()
        t, off, sig = (np.array(x, float) for x in zip(*self._history))
        pred = off[-1]
        if len(t) >= 3 and t[-1] - t[0] > 0.25 * self._history_ns:
            w = 1.0 / np.maximum(sig, 1e-5) ** 2
            tc = np.average(t, weights=w)
            slope = np.sum(w * (t - tc) * (off - np.average(off, weights=w))) / np.sum(w * (t - tc) ** 2)
            slope = float(np.clip(slope * 1e9, -MAX_DRIFT_NS_PER_S, MAX_DRIFT_NS_PER_S)) * 1e-9
            pred = off[-1] + slope * (t_now - t[-1])  # the line's slope, from the newest estimate on
            self._drift = (t_now, float(pred), slope)
        self.offset_ns, self.sigma_s = int(round(pred)), est.sigma_s
        if abs(self.offset_ns - self.applied_ns) < TRACK_CHANGE_NS:
            return None
        log.debug("time offset tracking: %+.2f ms at %.1f s (window estimate %+.2f +- %.2f ms)", pred * 1e-6,
                  (t_now - self.base_ns - self._t_first) * 1e-9, off[-1] * 1e-6, est.sigma_s * 1e3)
        self.applied_ns = self.offset_ns
        return self.applied_ns

    def stop_rechecks(self) -> None:
        """No re-checks from now on (someone else follows the offset once this estimate has finished)."""
        self._recheck_ns = 0
        self._next_check_ns = None
        if self.rechecking:
            self._finish()

    def _finish(self) -> None:
        self.done = True
        if self._recheck_ns > 0 and not self.tracking and self._t_last is not None:
            self._next_check_ns = self._t_last + self._recheck_ns
        if self.rechecking:
            self.rechecking = False
            log.debug("time offset: re-check %d done (applied %+.2f ms)", self.rechecks, self.applied_ns * 1e-6)
        else:
            log.info("time offset: estimation finished after %d solves (offset %s)", self.solves,
                     "unchanged" if self.offset_ns is None else f"{self.offset_ns * 1e-6:+.1f} ms")
        if self._owned:
            self.imu = ImuBuffer()
        self._pairs.clear()
