"""One validated configuration for the whole program, read from a TOML file.

Every section is a frozen dataclass; each field carries its help text and bounds, so that the loader can
reject a bad file with a message naming the file, the key and the reason, and `vio config show` can print
the effective values. Unknown keys are errors (a typo must not silently fall back to a default).
"""

from __future__ import annotations

import dataclasses
import difflib
import math
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, get_type_hints

from vio import VioError
from vio.io.inputs import read_user_file
from vio.serial_url import split_serial_url

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib


def refuse_unknown_keys(d: dict, known: tuple[str, ...] | list[str], where: str) -> None:
    """A misspelt key (`max_featurs` here; `distortion_coefs`, `time_offset_ms` in a calibration file, which were
    read as absent and their defaults used, unsaid: a review's finding) is refused, with the key meant where one is
    close."""
    for key in d:
        if key not in known:
            hint = difflib.get_close_matches(str(key), known, n=1, cutoff=0.6)
            raise VioError(f"{where}: unknown key '{key}'" + (f" (did you mean '{hint[0]}'?)" if hint else
                                                              f"; known keys: {', '.join(known)}"))


def opt(default: Any, help: str, *, min: float | None = None, max: float | None = None,
        choices: tuple | None = None) -> Any:
    """A config field with its documentation and validation bounds."""
    meta = {"help": help, "min": min, "max": max, "choices": choices}
    if isinstance(default, (list, dict)):
        return field(default_factory=lambda: type(default)(default), metadata=meta)
    return field(default=default, metadata=meta)


@dataclass(frozen=True)
class FrontendConfig:
    max_features: int = opt(200, "features kept per left image", min=10, max=2000)
    min_distance_px: int = opt(15, "minimum spacing between detected features", min=1, max=200)
    grid_cols: int = opt(8, "detection grid columns (spreads features over the image)", min=1, max=64)
    grid_rows: int = opt(6, "detection grid rows", min=1, max=64)
    klt_window_px: int = opt(21, "KLT window size (odd)", min=5, max=99)
    klt_pyramid_levels: int = opt(3, "KLT pyramid levels", min=0, max=8)
    klt_half_resolution: bool = opt(True, "frame-to-frame KLT on half-resolution images (window and levels halved "
                                    "to the same reach); the anchor refinement then places each track at full "
                                    "resolution. Full resolution when anchor_patch_px = 0")
    fb_check_px: float = opt(1.0, "forward-backward KLT error above which a match is dropped (stereo; temporal "
                             "only with anchor_patch_px = 0)", min=0.05, max=20)
    ransac_threshold_px: float = opt(0.35, "RANSAC inlier threshold on temporal matches", min=0.1, max=20)
    drift_check_frames: int = opt(10, "baseline (frames) of the second RANSAC that catches slowly sliding tracks",
                                  min=2, max=100)
    anchor_patch_px: int = opt(15, "patch of the affine refinement against each track's first appearance; 0 = off",
                               min=0, max=41)
    anchor_iterations: int = opt(3, "Gauss-Newton steps of the anchor refinement per frame", min=1, max=10)
    anchor_min_ncc: float = opt(0.85, "NCC with the first appearance below which a track is dropped", min=-1, max=1)
    anchor_renew_deform: float = opt(0.4, "patch scale/shear change at which the anchor patch is renewed",
                                     min=0.05, max=2)
    stereo_max_epipolar_px: float = opt(2.0, "max distance of a right match from the epipolar line", min=0.1, max=20)
    min_depth_m: float = opt(0.2, "stereo depth below which a match is rejected", min=0.01, max=100)
    max_depth_m: float = opt(40.0, "stereo depth beyond which a match is rejected", min=0.5, max=1000)
    use_imu_prediction: bool = opt(True, "predict feature motion from the gyro (keeps tracks in fast yaw)")
    clahe: bool = opt(False, "contrast-limited histogram equalisation before tracking")
    fast_threshold: int = opt(20, "FAST corner threshold (halved once when too few corners)", min=1, max=255)
    gain_compensation: bool = opt(True, "scale each image to the previous one's mean brightness before KLT")
    min_mean_intensity: float = opt(12.0, "mean grey level below which a frame is too dark", min=0, max=255)
    max_saturated_fraction: float = opt(0.7, "fraction of pixels >= 250 above which a frame is saturated",
                                        min=0.0, max=1.0)
    min_gradient_energy: float = opt(2.0, "mean |gradient| (grey levels/px, half resolution) below which a "
                                     "frame is too blurred or textureless", min=0.0, max=255)
    min_features_ok: int = opt(10, "tracked features below which the frame is reported as not ok", min=0, max=2000)


@dataclass(frozen=True)
class BackendConfig:
    lag_s: float = opt(2.0, "fixed-lag smoother window length", min=0.2, max=60)
    marginalize_every_kf: int = opt(3, "keyframes between marginalisations: the window grows past lag_s by up to "
                                    "N-1 keyframes, which then leave together (each marginalisation makes iSAM2 "
                                    "re-linearise and re-eliminate the whole window; 1: every keyframe)",
                                    min=1, max=20)
    marginalize_between_frames: bool = opt(False, "run each marginalisation on the frame after its keyframe, in an "
                                           "update of its own: no keyframe solve carries one (frame p99 -9 %), at "
                                           "~3 % of the real-time factor")
    solve_next_frame: bool = opt(False, "solve a keyframe before the next frame's front end instead of on its "
                                 "own frame, which then sends the IMU prediction as a frame that is no keyframe "
                                 "does: no frame pays both stereo matching and the solve (frame p99 -3 to -4 ms "
                                 "at the same work), but the keyframe frames' poses are predictions (ATE +1-3 %, "
                                 "RPE +5 %); for a slow companion computer whose keyframe frames overrun the "
                                 "frame period")
    keyframe_min_parallax_px: float = opt(10.0, "median parallax that makes a new keyframe", min=0.0, max=200)
    keyframe_max_interval_s: float = opt(0.4, "longest time between keyframes", min=0.01, max=10)
    keyframe_min_interval_s: float = opt(0.2, "shortest time between keyframes (caps the solver rate)", min=0, max=10)
    keyframe_min_tracks: int = opt(50, "tracked features below which a keyframe is forced", min=0, max=2000)
    keyframe_max_stamp_sigma_ms: float = opt(25.0, "a frame whose stamp may be off its exposure by more than this "
                                             "(the frame clock's sigma: a USB stall's burst, 50-300 ms late) is "
                                             "not made a keyframe while the last one is younger than 2 x "
                                             "keyframe_max_interval_s; 0: off", min=0.0, max=10_000)
    pixel_sigma: float = opt(0.5, "std of a feature measurement [px] (the Huber loss starts at huber_k of it); the "
                             "front end's anchor-refined tracks sit 0.1-0.25 px RMS from their true points (1.0 until "
                             "2026-12-05: vision under-weighted against the IMU, docs/estimator.md)", min=0.05, max=20)
    huber_k: float = opt(1.345, "Huber threshold (in sigmas) of the robust visual loss", min=0.1, max=100)
    min_tracks_ok: int = opt(15, "tracked features below which tracking is lost", min=3, max=1000)
    max_speed_m_s: float = opt(30.0, "velocity above which the estimate is implausible (reset)", min=1, max=1000)
    max_gyro_bias_rad_s: float = opt(0.3, "gyro bias (its largest component) above which the estimate, or a "
                                 "still start, is implausible", min=0.01, max=10)
    max_accel_bias_m_s2: float = opt(1.5, "accel bias above which the estimate is implausible", min=0.01, max=50)
    motion_check: bool = opt(True, "compare the smoother's motion between keyframes with the stereo pair's own metric "
                             "motion (PnP of the last keyframe's stereo points, no IMU) and reset when they "
                             "disagree (a lost scale or velocity the covariance does not show)")
    motion_check_sigma: float = opt(5.0, "how many sigma of the stereo reading (image noise, depth noise, "
                                    "motion_check_scale_sigma) the smoother's displacement must be off", min=1, max=100)
    motion_check_min_m_s: float = opt(1.0, "disagreement [m/s over the keyframe interval] below which the motion "
                                      "check never acts, however small the stereo reading's sigma", min=0.05, max=100)
    motion_check_scale_sigma: float = opt(0.1, "relative 1-sigma allowed the stereo reading's scale for a stereo "
                                          "calibration off by up to stereo_check_max_deg (correlated depth errors)",
                                          min=0.0, max=10)
    motion_check_confirm: int = opt(3, "consecutive keyframes that must disagree before the motion check resets "
                                    "(~1 s at keyframe_max_interval_s 0.4; one bad PnP does not)", min=1, max=100)
    imu_noise_scale: float = opt(2.0, "multiplier on the calibration's IMU noise densities (with imu_noise_adaptive: "
                                 "the least the white noise is scaled by)", min=0.1, max=100)
    imu_noise_adaptive: bool = opt(True, "on an airframe that shakes the IMU (its white noise, measured over the last "
                                   "2 s, above imu_noise_adaptive_above x the calibration's density on some axis), "
                                   "set the pre-integration's white noise per axis from that measurement")
    imu_noise_adaptive_above: float = opt(15.0, "measured white noise, in multiples of the calibration's density on "
                                          "the noisiest axis, above which the adaptive IMU noise engages (it lets "
                                          "go below 0.8x this)", min=1, max=1000)
    imu_noise_adaptive_gain: float = opt(1.0, "share of the measured white noise the adaptive IMU noise takes (1: all "
                                         "of it; smaller trusts that motor harmonics integrate out)", min=0.01,
                                         max=10)
    imu_noise_max_scale: float = opt(100.0, "largest multiplier the adaptive IMU noise may put on the calibration's "
                                     "densities", min=1, max=10000)
    extra_iterations: int = opt(1, "extra relinearisation passes per keyframe, only when the solve moved the newest "
                                "pose by more than extra_iteration_gate", min=0, max=10)
    extra_iteration_gate: float = opt(0.02, "newest-pose correction [m, rad] that triggers the extra passes",
                                      min=0, max=10)
    max_landmarks: int = opt(60, "landmarks observed per keyframe (spread over the image, long tracks first)",
                             min=10, max=2000)
    max_new_landmarks: int = opt(60, "new landmarks created per keyframe", min=1, max=2000)
    min_depth_m: float = opt(0.3, "stereo depth below which a track does not become a landmark", min=0.01, max=100)
    max_depth_m: float = opt(40.0, "depth beyond which a track does not become a landmark (the front end's stereo "
                             "limit by default)", min=0.5, max=1000)
    mono_landmarks: bool = opt(False, "tracks without usable stereo depth become landmarks triangulated over "
                               "keyframes (far points, right camera out)")
    mono_below_stereo: int = opt(15, "with mono_landmarks off, mono landmarks are still made on keyframes with "
                                 "fewer stereo matches than this (a right camera failing); 0: never", min=0, max=2000)
    refine_extrinsics: bool = opt(False, "refine T_body_cam0/T_body_cam1 as smoother variables while the motion "
                                  "makes them observable (see docs/estimator.md)")
    refine_extrinsics_auto: bool = opt(True, "without refine_extrinsics: start with the stereo check watching the "
                                       "pair on every keyframe and switch to refine_extrinsics (with "
                                       "refine_intrinsics as set, the pair held relative to cam0) at the first "
                                       "keyframe that passes the motion gate; a flight that never turns enough "
                                       "is not refined")
    refine_extrinsic_translation: bool = opt(False, "refine the camera-IMU translation too (poorly observable: "
                                             "it wandered by 2x its error in tests); else only the rotation")
    refine_stereo_extrinsic: bool = opt(False, "let T_cam0_cam1 move too (within stereo_sigma_*); else it is held")
    refine_stereo_rotation: bool = opt(False, "without refine_extrinsics: refine cam1's rotation relative to cam0 "
                                       "(within stereo_sigma_rad) on every keyframe, the rest held: a principal "
                                       "point or stereo mount that drifted biases every disparity")
    stereo_check: bool = opt(True, "hold cam1's rotation at the calibration by a tight prior and test every few "
                             "keyframes whether the data pull it away (a disparity bias); when they do beyond "
                             "stereo_check_px and stereo_check_sigma, let go and refine it for the rest of the flight "
                             "(with refine_extrinsics: cam1's rotation relative to cam0, read on the keyframes that "
                             "pass the motion gate)")
    stereo_check_focal: bool = opt(True, "the stereo check holds and lets go cam1's focal lengths with its rotation "
                                   "(two cameras' fx stated differently scale the disparities across the image)")
    stereo_check_px: float = opt(0.15, "disparity bias [px] below which the stereo check lets the calibration "
                                 "stand", min=0.0, max=20)
    stereo_check_max_deg: float = opt(0.5, "largest calibration error the stereo check takes for one [deg of turn: "
                                      "the disparity bias, or a focal length's change at the image edge, over fx]; "
                                      "a reading beyond it is not let go: a stereo pair does not bend that far in "
                                      "flight, the estimate disagrees with it (a start in a hover read 1 deg and, "
                                      "let go, lost its scale: 700 m off in 50 s)", min=0.01, max=10)
    stereo_check_sigma: float = opt(4.0, "how many sigma the disparity bias must stand out before the check acts",
                                    min=1.0, max=100)
    stereo_check_confirm: int = opt(2, "consecutive stereo checks whose reading must stand out before it acts (a "
                                    "passing transient does not)", min=1, max=100)
    stereo_check_every: int = opt(2, "keyframes between stereo checks (each reads a marginal of the smoother): "
                                  "a drifted pair is found sooner, and the odometry flown before is what it costs",
                                  min=1, max=1000)
    stereo_hold_sigma_rad: float = opt(5e-6, "1-sigma of the priors that hold cam1's rotation (and, times fx, its "
                                       "focal lengths) while checking: a few thousandths of a pixel",
                                       min=1e-7, max=1e-3)
    refine_intrinsics: bool = opt(True, "with the rig refinement (refine_extrinsics or refine_extrinsics_auto): "
                                  "refine fx, fy of both cameras too (the principal "
                                  "point only with refine_principal_point)")
    refine_principal_point: bool = opt(False, "with refine_intrinsics: cx, cy too (they trade against the extrinsic "
                                       "rotation: nearly the same image change)")
    intrinsics_sigma_px: float = opt(1.0, "stated 1-sigma uncertainty of the refined intrinsics", min=1e-3,
                                     max=100)
    extrinsic_sigma_rad: float = opt(0.0035, "stated 1-sigma rotation uncertainty of T_body_cam (0.2 deg)",
                                     min=1e-6, max=1)
    extrinsic_sigma_m: float = opt(0.005, "stated 1-sigma translation uncertainty of T_body_cam", min=1e-6, max=1)
    stereo_sigma_rad: float = opt(0.0017, "1-sigma rotation uncertainty of T_cam0_cam1 when refined", min=1e-6, max=1)
    stereo_sigma_m: float = opt(0.002, "1-sigma translation uncertainty of T_cam0_cam1 when refined", min=1e-6, max=1)
    extrinsic_min_rotation_deg: float = opt(2.0, "rotation about the second most excited axis, among the keyframes "
                                            "in the lag, that lets a keyframe refine the extrinsics", min=0, max=180)
    mono_min_parallax_deg: float = opt(1.0, "ray angle between a mono track's first and newest keyframe before it "
                                       "is triangulated", min=0.05, max=45)
    landmark_prior_sigma_m: float = opt(10.0, "weak prior on each landmark's first position, which keeps the solve "
                                        "well posed when its observations are turned down; 0 = none", min=0, max=1e6)
    outlier_gate_px: float = opt(15.0, "skip observations this far from the predicted projection", min=1, max=1000)
    lost_timeout_s: float = opt(1.0, "no usable camera frame (IMU time) for this long -> reset; the IMU-only "
                                "state is carried forward and re-initialisation waits for vision", min=0.05, max=60)
    max_imu_gap_s: float = opt(0.5, "an IMU gap (no samples) this long -> reset without a bridge: the motion in it "
                               "is unknown, and integrating across it was blamed on the cameras (the daemon's "
                               "[run] max_imu_gap_s checks arrivals too: raise both)", min=0.02, max=60)
    vision_timeout_s: float = opt(0.3, "no usable camera frame (IMU time) for this long -> not tracking: no pose "
                                  "goes to the autopilot (see [mavlink] lost_output)", min=0.02, max=60)
    quality_sigma_m: float = opt(0.05, "position sigma at which the reported quality falls below 100 (it halves "
                                 "at twice this sigma) [m]; at most 1 m (5 meant as cm kept quality 100 up to 5 m)",
                                 min=0.001, max=1.0)
    max_pending_frames: int = opt(20, "frames waiting for the IMU to reach their stamp; beyond it the oldest is "
                                  "dropped (an IMU that stops must not grow memory)", min=1, max=1000)
    max_frame_lead_s: float = opt(1.0, "a frame stamped this far ahead of the newest IMU sample is dropped",
                                  min=0.05, max=60)
    reinit_max_gyro_bias_jump_rad_s: float = opt(0.01, "after a reset, a static re-initialisation whose gyro bias "
                                                 "differs from the last estimate by more than this (plus the bias "
                                                 "random walk since) is refused: the vehicle is likely turning",
                                                 min=1e-4, max=1)
    zupt_max_speed_m_s: float = opt(0.05, "estimated speed above which no zero-velocity update is made", min=0, max=5)
    covariance_every_kf: int = opt(5, "marginal covariances every N keyframes (they cost a few ms); grown with "
                                   "the IMU in between", min=1, max=1000)
    estimate_time_offset: bool = opt(True, "re-estimate the camera-IMU time offset in flight (gyro vs track rotation)")
    frame_stamps: str = opt("auto", "frame stamps as given ('raw'), or restamped on the camera's own clock, a line "
                            "fitted to the last frame_stamp_window_s of stamps ('regular': a camera stamped on "
                            "arrival at the host, whose stamps jitter by milliseconds); 'auto' restamps only while the "
                            "stamps jitter by 0.25 ms or more from frame to frame around that line (device-stamped "
                            "cameras and datasets such as EuRoC fit it to microseconds, and a smoothly drifting "
                            "offset is the time offset state's: kept as given)", choices=("auto", "raw", "regular"))
    frame_stamp_window_s: float = opt(10.0, "stamps the camera clock is fitted to [s] (never fewer than the last 20 "
                                      "frames): longer averages the jitter down further, and a clock that drifts "
                                      "is still a line over seconds",
                                      min=1, max=120)
    frame_stamp_link: bool = opt(True, "let each keyframe's camera pose move along the body's motion by its frame "
                                 "stamp's uncertainty, as the frame clock measures it (stamps kept as given while "
                                 "they jitter, the fitted line's error for restamped ones): neither the poses nor the "
                                 "covariance sent then take a jittering stamp as exact; stamps that keep to their "
                                 "line (a device's, a dataset's) and 'raw' ones are exact and get none")
    stereo_every_frame: bool = opt(False, "stereo (and right-image decoding) on every frame, not only where a keyframe "
                                   "is possible: ~20 % slower, ATE a few mm lower on some flights")
    time_offset_max_ms: float = opt(50.0, "largest offset error searched for", min=1, max=500)
    time_offset_window_s: float = opt(8.0, "frames per in-flight offset estimate", min=1, max=120)
    time_offset_continuous: bool = opt(False, "keep tracking the time offset after it converged (a drifting camera "
                                        "or IMU clock) instead of freezing it; costs a PnP per frame all flight")
    time_offset_recheck_s: float = opt(0.0, "once the in-flight estimate has finished, check the offset again every "
                                       "this many seconds on one window (a clock that drifts, or drifts later); "
                                       "0 = never", min=0, max=3600)
    time_offset_track_window_s: float = opt(4.0, "frames per offset estimate while tracking", min=1, max=120)
    time_offset_state: bool = opt(True, "the residual camera-IMU offset as a smoother state per keyframe (a "
                                  "random walk with a rate, observed through the projections of the turning, "
                                  "moving body; it follows a drifting offset), from the first keyframe that "
                                  "moves fast enough to show it")
    time_offset_state_auto: bool = opt(False, "with time_offset_state off: switch the state on, from the next "
                                       "keyframe, when the in-flight estimate finds the calibration's offset "
                                       "wrong (a rig whose clocks disagree may also drift)")
    time_offset_state_sigma_ms: float = opt(3.0, "prior 1-sigma of that residual at the first keyframe", min=0.01,
                                            max=100)
    time_offset_walk_ms: float = opt(0.05, "random walk of the offset [ms per sqrt(s)] around what its rate "
                                     "predicts", min=1e-4, max=100)
    time_offset_rate_walk_ms: float = opt(0.1, "random walk of the offset's rate [ms/s per sqrt(s)]: a clock skew "
                                          "that itself changes slowly; 0 = no rate state", min=0, max=100)
    time_offset_rate_sigma_ms: float = opt(0.5, "prior 1-sigma of that rate at the first keyframe [ms/s]", min=1e-4,
                                           max=100)
    time_offset_link_min_rate: float = opt(0.5, "the time offset state reads a keyframe's camera pose at its "
                                           "offset only when the body turns at least this fast [rad/s] or moves "
                                           "at least time_offset_link_min_speed; slower, the offset barely shows "
                                           "and the state soaked up other errors instead", min=0, max=100)
    time_offset_link_min_speed: float = opt(0.8, "see time_offset_link_min_rate [m/s]", min=0, max=100)
    zupt_max_flow_px: float = opt(0.5, "median frame-to-frame feature motion under which the images look still",
                                  min=0, max=20)


@dataclass(frozen=True)
class InitConfig:
    static_window_s: float = opt(0.5, "still IMU needed for a static start (the IMU buffer keeps 3 s)", min=0.05,
                                 max=2.5)
    static_gyro_std_rad_s: float = opt(0.02, "gyro std under which the vehicle counts as still", min=1e-4, max=1)
    static_accel_std_m_s2: float = opt(0.5, "accel std under which the vehicle counts as still", min=1e-3, max=10)
    static_turn_visible_px: float = opt(2.0, "a still start's gyro mean is checked against the tracks when, were it a "
                                        "turn, it would move them at least this far over the window [px]: a "
                                        "slow turn the tracks follow is not taken for a gyro bias", min=0.1, max=100)
    allow_moving_start: bool = opt(True, "initialise in motion by visual-inertial alignment")
    moving_window_s: float = opt(1.0, "frames collected for the in-motion alignment (the IMU buffer keeps 3 s)",
                                 min=0.2, max=2.5)
    moving_min_frames: int = opt(6, "frames with a visual pose needed for the in-motion alignment", min=3, max=100)


@dataclass(frozen=True)
class MavlinkConfig:
    url: str = opt("", "mavutil connection string (udpout:127.0.0.1:14550, /dev/ttyAMA0:921600); empty = off")
    rate_hz: float = opt(30.0, "output rate of pose messages", min=1, max=200)
    messages: list = opt(["ODOMETRY"], "messages to send: ODOMETRY (PX4 and ArduPilot) or "
                         "VISION_POSITION_ESTIMATE + VISION_SPEED_ESTIMATE (older ArduPilot); not both kinds")
    system_id: int = opt(0, "our system id; 0 = take the autopilot's from its heartbeat", min=0, max=255)
    target_system: int = opt(1, "autopilot system id used until its heartbeat is seen", min=1, max=255)
    mount: str = opt("camera-forward", "how the IMU sits in the vehicle: 'camera-forward' (stereo camera looks "
                     "along the nose, pitched down by camera_tilt_deg, image right = vehicle right; the IMU "
                     "follows from the calibration's T_body_cam0), 'camera-down' (camera looks down, image top = "
                     "nose), or 'rpy' (mount_rpy_deg below)", choices=("camera-forward", "camera-down", "rpy"))
    camera_tilt_deg: float = opt(0.0, "with mount = 'camera-forward': how far the camera looks down from the "
                                 "vehicle's nose direction [deg] (an OAK on a 20 deg down-tilted mount: 20)",
                                 min=-90, max=90)
    mount_rpy_deg: list = opt([0.0, 0.0, 0.0], "with mount = 'rpy': the IMU's orientation in the vehicle FRD frame, "
                              "roll/pitch/yaw [deg] (an IMU mounted z-up, x forward is [180, 0, 0])")
    lost_output: str = opt("none", "while not tracking: 'none' sends no pose; 'failed' keeps sending ODOMETRY "
                           "with quality -1 (MAVLink's 'failed': ArduPilot's VISO_QUAL_MIN rejects it at its default "
                           "0; PX4 fuses any quality unless EKF2_EV_QMIN >= 1); 'quality0' with quality 0 "
                           "('unknown': fused by both unless their minimum is >= 1)",
                           choices=("none", "failed", "quality0"))
    counter_file: str = opt("/var/lib/kestrel-vio/reset_counter", "where `vio run` keeps the last reset_counter "
                            "sent: a restarted daemon (systemd after a crash or the watchdog) starts at the next "
                            "value, so the autopilot re-references to its new origin; empty, or a folder that "
                            "does not exist: a random start (one naming a folder is refused at start)")
    mount_offset_m: list = opt([0.0, 0.0, 0.0], "IMU position in the vehicle FRD frame [m]")
    delay_ms: float = opt(0.0, "extra latency to report/document for VISO_DELAY_MS", min=0, max=1000)
    origin_lat_deg: float = opt(float("nan"), "SET_GPS_GLOBAL_ORIGIN latitude; nan = do not send")
    origin_lon_deg: float = opt(float("nan"), "SET_GPS_GLOBAL_ORIGIN longitude")
    origin_alt_m: float = opt(0.0, "SET_GPS_GLOBAL_ORIGIN altitude (AMSL)")
    link_timeout_s: float = opt(3.0, "autopilot heartbeat silence after which the link counts as lost",
                                min=0.5, max=60)
    max_state_age_ms: float = opt(500.0, "a pose older than this when it would be sent (its measurement time on the "
                                  "host clock against now: the estimator behind, a stalled process) is not sent "
                                  "and counts as a loss of tracking [ms]; 0 = off", min=0, max=5000)
    land_after_loss_s: float = opt(0.0, "once tracking has been lost this long while the autopilot is armed, "
                                   "ask it to LAND (MAV_CMD_NAV_LAND) rather than let it dead-reckon on its IMU "
                                   "until its own EKF failsafe [s]; 0 = off", min=0, max=600)
    max_stamp_error_ms: float = opt(50.0, "the IMU source's own measure of how far its sample stamps may be off the "
                                    "host clock (its device-clock fit: TIMESYNC or arrival times; 0 for an OAK) "
                                    "beyond which no pose is sent, a loss of tracking until it is back within [ms]. "
                                    "Between stamp_tolerance_ms and this the covariance sent grows by the motion "
                                    "over that time (speed x error in position, turn rate x error in attitude) and "
                                    "the quality falls towards 0", min=10, max=1000)
    stamp_tolerance_ms: float = opt(5.0, "an IMU stamp error up to this changes nothing sent (a healthy device-clock "
                                    "fit's own scatter: TIMESYNC on the ArduPilot SITL within 1.4 ms, a USB serial "
                                    "IMU's arrival envelope within about 1 ms; a constant part is the camera-IMU "
                                    "offset the estimator solves); from it to max_stamp_error_ms the quality falls "
                                    "linearly from 100 to 0 [ms]; must be below max_stamp_error_ms", min=0, max=1000)


@dataclass(frozen=True)
class SourceConfig:
    kind: str = opt("oak", "sensor source ('sitl': cameras rendered at an autopilot SITL's truth pose, for "
                    "bench/sitl/)", choices=("oak", "euroc", "fake", "sitl"))
    dataset: str = opt("", "EuRoC dataset path when kind = 'euroc'")
    calibration: str = opt("", "calibration file; empty = from the device / dataset")
    fps: float = opt(20.0, "camera frame rate", min=1, max=120)
    width: int = opt(640, "camera width", min=64, max=4096)
    height: int = opt(400, "camera height", min=64, max=4096)
    imu_rate_hz: float = opt(200.0, "IMU rate", min=50, max=2000)
    imu: str = opt("oak", "IMU source", choices=("oak", "serial", "mavlink", "none"))
    serial_port: str = opt("/dev/ttyUSB0", "serial IMU port")
    serial_baud: int = opt(921600, "serial IMU baud rate", min=1200, max=12_000_000)
    serial_imu_rate_hz: float = opt(400.0, "serial IMU sample rate (gap detection)", min=10, max=4000)
    mavlink_imu_url: str = opt("", "imu = 'mavlink': connection to the flight controller; empty = the [mavlink] url "
                               "(one connection for the IMU and the pose output: a serial port opens once only)")
    mavlink_imu_message: str = opt("HIGHRES_IMU", "imu = 'mavlink': the message read (SI units), or SCALED_IMU "
                                   "(mG, mrad/s) or RAW_IMU (needs both scales)",
                                   choices=("HIGHRES_IMU", "SCALED_IMU", "RAW_IMU"))
    mavlink_imu_rate_hz: float = opt(200.0, "imu = 'mavlink': rate requested with MAV_CMD_SET_MESSAGE_INTERVAL "
                                     "(and the nominal rate for gap detection)", min=10, max=2000)
    mavlink_imu_request_rate: bool = opt(True, "imu = 'mavlink': request the rate (false: the autopilot's "
                                         "stream parameters set it)")
    mavlink_imu_accel_scale: float = opt(0.0, "imu = 'mavlink': m/s^2 per message unit; 0 = the message's own "
                                         "(HIGHRES_IMU 1, SCALED_IMU 9.80665e-3 for mG)", min=0, max=1e3)
    mavlink_imu_gyro_scale: float = opt(0.0, "imu = 'mavlink': rad/s per message unit; 0 = the message's own "
                                        "(HIGHRES_IMU 1, SCALED_IMU 1e-3 for mrad/s)", min=0, max=1e3)
    mavlink_imu_axes: str = opt("frd", "imu = 'mavlink': axes of the estimator's body frame, which is the flight "
                                "controller's (its IMU data are FRD): 'frd' or 'flu' (x forward, y left, z up); "
                                "the calibration's T_body_cam0 must be given in these axes", choices=("frd", "flu"))
    mavlink_imu_id: int = opt(0, "imu = 'mavlink': HIGHRES_IMU/RAW_IMU `id` to read (0 = the first IMU)",
                              min=0, max=255)
    oak_device: str = opt("", "OAK device id or name; empty = the first one found")
    realtime: bool = opt(True, "fake/euroc: release data at the pace of its stamps (false = as fast as the "
                         "estimator takes it: `vio run` then waits for room in its buffers, nothing is dropped)")
    fake_profile: str = opt("survey", "kind = 'fake': simulated flight profile (vio/sim)",
                            choices=("hover", "survey", "aggressive"))
    fake_duration_s: float = opt(0.0, "kind = 'fake': flight length; 0 = endless (the flight never repeats)",
                                 min=0, max=1e7)
    fake_seed: int = opt(0, "kind = 'fake': seed of the simulated flight and room", min=0, max=2**31 - 1)
    sitl_url: str = opt("tcp:127.0.0.1:5763", "kind = 'sitl': MAVLink link on which the SITL sends its truth "
                        "(SIM_STATE); not the autopilot link of [mavlink]")
    sitl_home: list = opt([-35.363261, 149.165230, 584.0], "kind = 'sitl': the SITL's --home [lat_deg, lon_deg, "
                          "alt_m]; it is placed in the middle of the simulated room")
    sitl_blackout_file: str = opt("", "kind = 'sitl': while this file exists the cameras are black (fault tests)")


@dataclass(frozen=True)
class RunConfig:
    record_dir: str = opt("", "record sensors to this EuRoC folder while running; empty = off")
    record_format: str = opt("euroc", "recording format: euroc (a folder of PNGs and csv) or mcap (one .mcap file "
                             "on ROS 2 schemas with the estimator states and health, Foxglove opens it)",
                             choices=("euroc", "mcap"))
    record_images: str = opt("png", "mcap images: png (lossless CompressedImage), jpeg (lossy, smaller) or raw "
                             "(sensor_msgs/Image)", choices=("png", "jpeg", "raw"))
    record_png_level: int = opt(0, "euroc recordings: PNG zlib level; 0 = stored, unfiltered (a tenth of the CPU of "
                                "level 1, 1.9x the bytes: 14 MB/s for 752x480 stereo at 20 Hz)", min=0, max=9)
    trajectory_file: str = opt("", "append the estimated trajectory (TUM) here, each run after a '# kestrel-vio run "
                               "started' line (its own odometry frame); empty = off")
    status_file: str = opt("/run/kestrel-vio/status.json", "health file read by `vio status`")
    queue_frames: int = opt(4, "camera frames buffered before the oldest is dropped", min=1, max=100)
    queue_imu: int = opt(4000, "IMU samples buffered (20 s at 200 Hz); overflow is counted and logged",
                         min=100, max=1_000_000)
    source_timeout_s: float = opt(2.0, "no sensor data for this long = source lost; it is reopened", min=0.2, max=60)
    reconnect_max_s: float = opt(5.0, "longest wait between attempts to reopen a lost source", min=0.1, max=300)
    max_imu_gap_s: float = opt(0.5, "IMU gap after which the estimator is reset", min=0.02, max=60)
    stall_timeout_s: float = opt(20.0, "sensors delivering but no tracked pose for this long: one warning in the "
                                 "log naming why (the watchdog is still fed: a restart would not help)",
                                 min=1, max=3600)
    ready_timeout_s: float = opt(30.0, "READY=1 to systemd when sensor data flow, or after this long without "
                                 "(the daemon keeps reopening the sensors; TimeoutStartSec must be longer)",
                                 min=1, max=3600)
    log_level: str = opt("INFO", "logging level", choices=("DEBUG", "INFO", "WARNING", "ERROR"))


@dataclass(frozen=True)
class ViewConfig:
    enabled: bool = opt(False, "stream a live view to Rerun (the [view] extra): left image with tracks, trajectory, "
                        "keyframes, landmarks, covariance, health counters; the estimator never waits for it")
    target: str = opt("serve", "'serve' (gRPC server + web viewer on this computer) or a path ending in .rrd")
    web_port: int = opt(9090, "web viewer port (target = 'serve')", min=1, max=65535)
    queue_frames: int = opt(16, "frames waiting for the view thread (it takes them at twice its highest rate) "
                            "before the oldest is dropped", min=1, max=100)
    rate_hz: float = opt(5.0, "body pose and landmarks logged at most this often (wall clock; each entity costs some "
                         "0.2 ms of CPU per log): the view thread shares the cores and the GIL with the estimator",
                         min=0.1, max=200)
    image_hz: float = opt(2.0, "left image (with its tracks) logged at most this often", min=0.1, max=200)
    image_scale: float = opt(0.5, "left image scaled by this before JPEG encoding", min=0.1, max=1)
    jpeg_quality: int = opt(75, "JPEG quality of the logged image", min=10, max=100)
    serve_memory_mb: int = opt(256, "target = 'serve': what Rerun's gRPC server buffers for viewers that connect "
                               "late, in MB (the oldest data goes first; Rerun's own default is 1 GiB)",
                               min=16, max=65536)


@dataclass(frozen=True)
class BagConfig:
    """What `vio replay FILE.bag|FILE.mcap|BAG_DIR` (and `vio batch`) read; --left-topic/--right-topic/
    --imu-topic win over these."""

    left_topic: str = opt("/cam0/image_raw", "left camera topic (sensor_msgs/Image or CompressedImage)")
    right_topic: str = opt("/cam1/image_raw", "right camera topic")
    imu_topic: str = opt("/imu0", "IMU topic (sensor_msgs/Imu)")
    images: str = opt("auto", "camera messages: auto (Image or CompressedImage; TOPIC/compressed when the bag "
                      "has no TOPIC), raw (sensor_msgs/Image only), compressed (CompressedImage only: TOPIC "
                      "or image_transport's TOPIC/compressed)", choices=("auto", "raw", "compressed"))


@dataclass(frozen=True)
class EstimatorConfig:
    """The sections the estimator reads (front end, back end, initialisation): each stage gets only its own,
    so the MAVLink, source and daemon settings cannot leak into the estimate."""

    frontend: FrontendConfig = field(default_factory=FrontendConfig)
    backend: BackendConfig = field(default_factory=BackendConfig)
    init: InitConfig = field(default_factory=InitConfig)


@dataclass(frozen=True)
class LoopConfig:
    enabled: bool = opt(False, "run loop closure beside the odometry (docs/loop-closure.md)")
    vocabulary: str = opt("", "vocabulary file (npz); empty: the one shipped with the package")
    orb_features: int = opt(300, "FAST corners described per keyframe (plus the front end's stereo points)",
                            min=50, max=3000)
    fast_threshold: int = opt(16, "FAST corner threshold (grey levels); an image with too few corners is "
                              "searched again at half of it", min=1, max=255)
    orb_levels: int = opt(1, "image pyramid levels the corners are found and described on (scale steps of "
                          "orb_level_scale: views of a place from other distances still match)", min=1, max=8)
    orb_level_scale: float = opt(1.2, "scale between pyramid levels", min=1.05, max=2.0)
    spacing_m: float = opt(0.2, "an odometry keyframe joins the loop stage only this far (or spacing_deg, or "
                           "spacing_s) from the last one that did; 0: every keyframe", min=0, max=100)
    spacing_deg: float = opt(7.0, "or turned this much (with spacing_m > 0)", min=0.1, max=180)
    spacing_s: float = opt(2.0, "or this long after it (with spacing_m > 0)", min=0.1, max=3600)
    candidates: int = opt(1, "best retrieval candidates verified per keyframe", min=1, max=20)
    min_score: float = opt(0.05, "bag-of-words L1 score below which a candidate is not verified", min=0, max=1)
    exclude_recent_s: float = opt(10.0, "keyframes of the same flight newer than this are no candidates",
                                  min=0, max=3600)
    max_hamming: int = opt(60, "largest descriptor distance of a match (of 256 bits)", min=1, max=256)
    match_ratio: float = opt(0.8, "ratio test between the best and second-best match", min=0.1, max=1)
    min_inliers: int = opt(20, "PnP RANSAC inliers a candidate needs", min=6, max=1000)
    reproj_threshold_px: float = opt(2.0, "PnP inlier reprojection threshold", min=0.1, max=20)
    guided_radius_px: float = opt(8.0, "a verified PnP pose is refined on the old keyframe's points matched again "
                                  "by projection: to the new features within this radius, no ratio test (about "
                                  "twice the inliers across a wide change of view), and the edge's other "
                                  "direction is matched the same way from that pose instead of by a second "
                                  "RANSAC; 0: off (ratio test and RANSAC both ways)", min=0, max=100)
    prior_radius_px: float = opt(40.0, "a same-flight candidate whose ratio-test matches fail PnP is matched again "
                                 "by projection from where the pose graph puts the new keyframe, within this "
                                 "radius, and PnP RANSAC runs on those (repeated textures, blur; "
                                 "docs/loop-closure.md); 0: off", min=0, max=500)
    settled_odometry: bool = opt(True, "odometry edges between keyframes from the odometry smoother's estimate as "
                                 "each keyframe leaves its window (lag_s of later data) rather than at the "
                                 "keyframe's own solve (loop-corrected ATE 12-20 % lower; docs/loop-closure.md)")
    refine_edges: bool = opt(False, "re-estimate a verified edge from both PnPs' inliers in one two-view bundle "
                             "adjustment that weighs each stereo depth by its disparity (edges ~15 % more "
                             "accurate, +1.2 ms per keyframe; docs/loop-closure.md)")
    two_way_m: float = opt(0.03, "PnP both ways (old landmarks in the new image and new in the old) must agree "
                           "within this distance", min=0.001, max=10)
    two_way_deg: float = opt(0.5, "and this angle", min=0.01, max=90)
    gravity_max_deg: float = opt(2.0, "largest roll/pitch disagreement between the loop edge and the IMU",
                                 min=0.01, max=90)
    drift_gate_m: float = opt(0.3, "correction always allowed within one flight [m]", min=0, max=1000)
    drift_gate_per_m: float = opt(0.05, "plus this share of the path flown since the candidate", min=0, max=10)
    drift_gate_deg: float = opt(10.0, "largest yaw correction within one flight", min=0, max=180)
    min_consistent: int = opt(2, "verified candidates with agreeing corrections before edges are used",
                              min=1, max=20)
    consistency_window: int = opt(5, "keyframes over which those candidates are gathered", min=1, max=100)
    consistency_m: float = opt(0.1, "corrections agree within this distance", min=0.001, max=100)
    consistency_deg: float = opt(2.0, "and this yaw", min=0.01, max=180)
    odom_sigma_per_m: float = opt(0.005, "odometry edge sigma per metre flown (pose graph)", min=1e-5, max=1)
    loop_sigma_m: float = opt(0.06, "loop edge position sigma", min=1e-4, max=10)
    loop_sigma_deg: float = opt(0.7, "loop edge rotation sigma", min=1e-3, max=90)
    segment_prior_m: float = opt(100.0, "prior sigma of a new segment (after a reset, or on a loaded map)",
                                 min=1e-3, max=1e6)
    segment_prior_deg: float = opt(180.0, "its rotation prior sigma (roll/pitch are held by gravity)",
                                   min=1e-3, max=1e4)
    reloc_min_consistent: int = opt(3, "as min_consistent, for an edge to another session (a loaded map, the "
                                    "flight before a reset): no drift gate can check it", min=1, max=20)
    reloc_candidates: int = opt(4, "best retrieval candidates from other sessions verified per keyframe while "
                                "this one is not joined to them (relocalising)", min=0, max=20)
    reloc_min_inliers: int = opt(12, "as min_inliers, for an edge to another session: a second flight sees the "
                                 "map's places from further off (fewer matches)", min=6, max=1000)
    reloc_two_way_m: float = opt(0.06, "as two_way_m, for an edge to another session (its guard is "
                                 "reloc_min_consistent agreeing edges; it corrects metres, not millimetres)",
                                 min=0.001, max=10)
    reloc_two_way_deg: float = opt(1.0, "as two_way_deg, for an edge to another session", min=0.01, max=90)
    reloc_confirm_edges: int = opt(10, "a session joined to another (a loaded map) by fewer active loop edges than "
                                   "this is still searched with the relocalisation rules (reloc_candidates, reloc_* "
                                   "gates, reloc_min_consistent, no matching guided by its placement), so that a wrong "
                                   "first join can be out-voted by GNC; 0 = off", min=0, max=1000)
    output_join_edges: int = opt(8, "the corrected output ([loop] output) takes a flight's place in another frame (a "
                                 "loaded map, the flight before a reset) only once this many active loop edges hold "
                                 "it: a first join can be a look-alike place; 0 = at the first join", min=0, max=1000)
    sigma_inliers: int = opt(60, "a loop edge within one flight has its sigmas scaled by sqrt(this / inliers), "
                             "between 0.5x and 2x (a PnP pose's error goes as 1 / sqrt(inliers)); 0 = off",
                             min=0, max=10000)
    reloc_sigma_inliers: int = opt(60, "an edge to another session with fewer PnP inliers than this has its "
                                   "sigmas scaled by sqrt(this / inliers), at most 2x; 0 = off", min=0, max=10000)
    output: str = opt("off", "what the autopilot gets: off (odometry), jump, blend (docs/autopilot.md)",
                      choices=("off", "jump", "blend"))
    blend_rate_m_s: float = opt(0.2, "blend: correction applied at most this fast [m/s]", min=1e-3, max=100)
    blend_rate_deg_s: float = opt(5.0, "blend: and this fast in yaw [deg/s]", min=1e-3, max=1000)


@dataclass(frozen=True)
class MapConfig:
    load: str = opt("", "map file to relocalise in at start (docs/loop-closure.md#map-files); empty: none")
    save: str = opt("", "write the map here at the end of the run; empty: not saved")
    prune_m: float = opt(0.0, "a keyframe of this flight is not saved in the map when one already kept (the "
                         "loaded map's, or this flight's before it) saw from within this distance and prune_deg: "
                         "a map grown by every flight in one place stays the size of that place; 0: all saved",
                         min=0, max=10)
    prune_deg: float = opt(10.0, "with prune_m: the largest turn between the two cameras", min=0.1, max=180)
    checkpoint_s: float = opt(30.0, "vio run with save: also write the map there this often while flying, marked as a "
                              "checkpoint (the loop-closure thread writes it), so a run killed without a clean stop "
                              "loses at most this much of the map, and its restart on the same boot grows it "
                              "(docs/loop-closure.md#map-files); 0: only at stop", min=0, max=3600)


@dataclass(frozen=True)
class VioConfig:
    frontend: FrontendConfig = field(default_factory=FrontendConfig)
    backend: BackendConfig = field(default_factory=BackendConfig)
    init: InitConfig = field(default_factory=InitConfig)
    mavlink: MavlinkConfig = field(default_factory=MavlinkConfig)
    source: SourceConfig = field(default_factory=SourceConfig)
    run: RunConfig = field(default_factory=RunConfig)
    loop: LoopConfig = field(default_factory=LoopConfig)
    map: MapConfig = field(default_factory=MapConfig)
    view: ViewConfig = field(default_factory=ViewConfig)
    bag: BagConfig = field(default_factory=BagConfig)

    @property
    def estimator(self) -> EstimatorConfig:
        return EstimatorConfig(self.frontend, self.backend, self.init)




def _section_types() -> dict[str, type]:
    return get_type_hints(VioConfig)


def _check_value(where: str, name: str, fld: dataclasses.Field, typ: Any, value: Any) -> Any:
    """Coerce int->float, check type, bounds and choices; raise VioError naming the key."""
    tname = getattr(typ, "__name__", str(typ))
    if typ is float and isinstance(value, int) and not isinstance(value, bool):
        value = float(value)
    ok = (typ is bool and isinstance(value, bool)) or (
        typ is not bool and not isinstance(value, bool) and isinstance(value, typ))
    if not ok:
        raise VioError(f"{where}: '{name}' must be {tname}, got {type(value).__name__} {value!r}")
    meta = fld.metadata
    if isinstance(value, float) and math.isnan(value) and meta.get("min") is None:
        return value
    if meta.get("min") is not None and isinstance(value, float) and math.isnan(value):
        # "nan is below the minimum" read as a number too small; nan is none
        wanted = f"at least {meta['min']}" if meta.get("max") is None else f"from {meta['min']} to {meta['max']}"
        raise VioError(f"{where}: '{name}' = nan is not a number; give one {wanted}")
    if meta.get("min") is not None and value < meta["min"]:
        raise VioError(f"{where}: '{name}' = {value!r} is below the minimum {meta['min']}")
    if meta.get("max") is not None and value > meta["max"]:
        raise VioError(f"{where}: '{name}' = {value!r} is above the maximum {meta['max']}")
    if meta.get("choices") and value not in meta["choices"]:
        raise VioError(f"{where}: '{name}' = {value!r} is not one of {list(meta['choices'])}")
    return value


def _build_section(cls: type, data: Any, where: str) -> Any:
    if not isinstance(data, dict):
        raise VioError(f"{where}: expected a table of settings, got {type(data).__name__}")
    hints = get_type_hints(cls)
    fields = {f.name: f for f in dataclasses.fields(cls)}
    kwargs = {}
    refuse_unknown_keys(data, list(fields), where)
    for key, value in data.items():
        kwargs[key] = _check_value(where, key, fields[key], hints[key], value)
    return cls(**kwargs)


def _top_level_key_problem(name: str, types: dict[str, type]) -> str:
    """A key above the first [section] header (`rate_hz = 5`) is no section: it was called 'unknown section
    [rate_hz]'. Said as a key, with the sections that have it (or a key close to it)."""
    keys = {sec: [f.name for f in dataclasses.fields(cls)] for sec, cls in types.items()}
    problem = f"unknown key '{name}' at top level (above any [section] header)"
    owners = [f"[{sec}]" for sec, names in keys.items() if name in names]
    if len(owners) == 1:
        return f"{problem}: it is a key of {owners[0]}; move it there"
    if owners:
        return f"{problem}: it is a key of {' and of '.join(owners)}; move it to the one meant"
    everywhere = {f"[{sec}] {k}": k for sec, names in keys.items() for k in names}
    hint = difflib.get_close_matches(name, list(set(everywhere.values())), n=1)
    if hint:
        return f"{problem}: did you mean " + " or ".join(w for w, k in everywhere.items() if k == hint[0]) + "?"
    return f"{problem}; known sections: {', '.join(types)}"


def config_from_dict(data: dict, source: str = "config") -> VioConfig:
    """Validate a parsed TOML mapping into a VioConfig; every error names `source`, section and key."""
    types = _section_types()
    sections = {}
    for name, value in data.items():
        if isinstance(value, list) and value and all(isinstance(v, dict) for v in value):
            # [[name]] (a TOML array of tables) is a section header too: it was called an unknown key "at top
            # level (above any [section] header)", or "expected a table of settings, got list" for [[source]]
            if name in types:
                raise VioError(f"{source}: [[{name}]] is a list of sections; write [{name}] (one pair of "
                               "brackets): there is one such section")
            hint = difflib.get_close_matches(name, list(types), n=1)
            more = f" (did you mean [{hint[0]}]?)" if hint else f"; known sections: {', '.join(types)}"
            raise VioError(f"{source}: unknown section [[{name}]]{more}")
        if name not in types and not isinstance(value, dict):
            raise VioError(f"{source}: {_top_level_key_problem(name, types)}")
        if name not in types:
            hint = difflib.get_close_matches(name, list(types), n=1)
            more = f" (did you mean [{hint[0]}]?)" if hint else f"; known sections: {', '.join(types)}"
            raise VioError(f"{source}: unknown section [{name}]{more}")
        sections[name] = _build_section(types[name], value, f"{source}: [{name}]")
    cfg = VioConfig(**sections)
    _check_cross_fields(cfg, source)
    return cfg


# the settings that name a file or folder
PATH_KEYS = {"source": ("dataset", "calibration", "serial_port", "sitl_blackout_file"),
             "run": ("record_dir", "trajectory_file", "status_file"), "mavlink": ("counter_file",),
             "map": ("load", "save"), "loop": ("vocabulary",), "view": ("target",)}


def _check_paths(cfg: VioConfig, source: str) -> None:
    """A path starting with '~' is taken as it is written (nothing here expands it, as a shell would): `record_dir =
    "~/records"` passed the check and `vio run` recorded into a folder named '~' in its working directory (an
    integrator's walk-through); `calibration = "~/calib.yaml"` said 'No such file' of a file the user's shell shows."""
    import os

    for section, keys in PATH_KEYS.items():
        for key in keys:
            value = getattr(getattr(cfg, section), key)
            if value.startswith("~"):
                raise VioError(f"{source}: [{section}] {key} = {value!r}: '~' is not expanded in a configuration (the "
                               "service's home is not yours either): give the whole path, e.g. "
                               f"{os.path.expanduser(value)!r}")


def _check_cross_fields(cfg: VioConfig, source: str) -> None:
    """Settings that are valid alone but contradict each other."""
    _check_paths(cfg, source)
    m = cfg.mavlink
    for key in ("mount_rpy_deg", "mount_offset_m"):  # ['a', 0, 0] ended in an internal error (float('a') below)
        v = getattr(m, key)
        if len(v) != 3 or not all(isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x)
                                  for x in v):
            raise VioError(f"{source}: [mavlink] {key} must be 3 finite numbers, got {v!r}")
    if m.mount != "rpy" and [float(x) for x in m.mount_rpy_deg] != [0.0, 0.0, 0.0]:
        raise VioError(f"{source}: [mavlink] mount_rpy_deg is set but mount = {m.mount!r} derives the mounting from "
                       "the calibration; set mount = 'rpy' to use mount_rpy_deg")
    rpy = [float(x) for x in m.mount_rpy_deg]
    near = next((v for v in rpy if v and min(abs(abs(v) - k * math.pi / 2) for k in (1, 2, 3, 4)) < 0.01), None)
    if near is not None:
        # 1.5708 deg is no mounting anyone makes; 1.5708 rad is a quarter turn (its tilt under 45 deg, the
        # first-pose check would not catch it either)
        turn = math.copysign(min((k * math.pi / 2 for k in (1, 2, 3, 4)), key=lambda q: abs(abs(near) - q)), near)
        away = round(turn + math.copysign(0.02, (near - turn) or near), 2)  # the side of it near is on
        raise VioError(f"{source}: [mavlink] mount_rpy_deg = {m.mount_rpy_deg} looks like radians (a multiple of "
                       f"pi/2): give degrees, e.g. {[round(math.degrees(v), 1) for v in rpy]}; only if you measured "
                       f"a tilt of {near:g} degrees (it cannot be told from radians here), write {away:g}: 0.02 deg "
                       "makes no difference")
    if not m.stamp_tolerance_ms < m.max_stamp_error_ms:  # the quality ramp between them would divide by <= 0
        raise VioError(f"{source}: [mavlink] stamp_tolerance_ms = {m.stamp_tolerance_ms:g} must be below "
                       f"max_stamp_error_ms = {m.max_stamp_error_ms:g}: the quality falls from 100 at the first to 0 "
                       "at the second (poses withheld beyond it)")
    src = cfg.source
    if src.imu == "mavlink" and not (src.mavlink_imu_url or m.url):
        raise VioError(f"{source}: [source] imu = 'mavlink' needs a connection: [mavlink] url (shared with the pose "
                       "output) or [source] mavlink_imu_url")
    if src.imu == "serial" and not src.serial_port.strip():
        raise VioError(f"{source}: [source] imu = 'serial' needs [source] serial_port (e.g. /dev/ttyUSB0)")
    if src.imu == "serial":
        _check_serial_imu_link(src, source)
    if src.imu == "mavlink" and src.mavlink_imu_message == "RAW_IMU" and not (
            src.mavlink_imu_accel_scale and src.mavlink_imu_gyro_scale):
        raise VioError(f"{source}: [source] mavlink_imu_message = 'RAW_IMU' is in the sensor's own units: set "
                       "mavlink_imu_accel_scale [m/s^2 per unit] and mavlink_imu_gyro_scale [rad/s per unit] "
                       "(ArduPilot's RAW_IMU: 9.80665e-3 and 1e-3)")
    if src.kind == "sitl" and src.imu != "mavlink":
        raise VioError(f"{source}: [source] kind = 'sitl' renders cameras only; set imu = 'mavlink' (the SITL's IMU, "
                       "so that images and IMU are of the same flight)")
    h = src.sitl_home
    # ['a', 0, 0] passed the check and stopped the source at its start (float('a')); 1e300 or 91 deg passed unsaid
    if src.kind == "sitl" and (len(h) != 3 or not all(isinstance(x, (int, float)) and not isinstance(x, bool)
                                                      and math.isfinite(x) for x in h)
                               or not (-90 <= h[0] <= 90 and -180 <= h[1] <= 180 and abs(h[2]) <= 10_000)):
        raise VioError(f"{source}: [source] sitl_home must be [lat_deg, lon_deg, alt_m] (latitude within +-90, "
                       f"longitude within +-180, altitude within +-10 km), got {h!r}")
    for key in ("left_topic", "right_topic", "imu_topic"):  # "" passed, and a bag's replay said "no left  topic"
        if not getattr(cfg.bag, key).strip():
            raise VioError(f"{source}: [bag] {key} is empty: name the topic (e.g. {getattr(BagConfig(), key)})")
    if cfg.loop.output != "off" and not (cfg.loop.enabled or cfg.map.load or cfg.map.save):
        raise VioError(f"{source}: [loop] output = {cfg.loop.output!r} needs the loop stage, which is off: set [loop] "
                       "enabled = true (it would be ignored)")
    lp = cfg.loop
    if lp.output_join_edges and not (0 < lp.output_join_edges <= lp.reloc_confirm_edges):
        # a joined flight searched with the ordinary rules finds few more edges to the map: the output could wait
        raise VioError(f"{source}: [loop] output_join_edges = {lp.output_join_edges} needs reloc_confirm_edges >= it "
                       f"(now {lp.reloc_confirm_edges}): a join is searched for the edges that confirm it only that "
                       "long")
    b, f = cfg.backend, cfg.frontend
    if b.imu_noise_adaptive and b.imu_noise_max_scale < b.imu_noise_scale:
        raise VioError(f"{source}: [backend] imu_noise_max_scale = {b.imu_noise_max_scale} is below imu_noise_scale "
                       f"= {b.imu_noise_scale}, the least the adaptive IMU noise uses")
    if b.max_depth_m > f.max_depth_m or b.min_depth_m < f.min_depth_m:
        raise VioError(f"{source}: [backend] depth range {b.min_depth_m}..{b.max_depth_m} m must lie inside the "
                       f"front end's {f.min_depth_m}..{f.max_depth_m} m (points outside it are never matched)")
    if b.keyframe_min_interval_s > b.keyframe_max_interval_s:
        raise VioError(f"{source}: [backend] keyframe_min_interval_s ({b.keyframe_min_interval_s}) must not exceed "
                       f"keyframe_max_interval_s ({b.keyframe_max_interval_s}): no keyframe interval meets both")
    if f.klt_window_px % 2 == 0:  # it was made odd unsaid (20 ran as 21)
        raise VioError(f"{source}: [frontend] klt_window_px = {f.klt_window_px} must be odd (a window centred on its "
                       f"pixel): {f.klt_window_px - 1} or {f.klt_window_px + 1}")
    if b.vision_timeout_s > b.lost_timeout_s:
        raise VioError(f"{source}: [backend] vision_timeout_s ({b.vision_timeout_s}) must not exceed lost_timeout_s "
                       f"({b.lost_timeout_s}): output would continue after the estimator gave up")


SERIAL_FRAME_BITS = 40 * 10  # one IMU frame of the serial protocol: 40 bytes, 10 bits each on the wire (8N1)


def _check_serial_imu_link(src: SourceConfig, source: str) -> None:
    """A serial IMU's port and baud rate as `vio run` would open them: these passed the check and were retried for
    ever (a port that can never open), or lost frames for the whole flight (an integrator's walk-through)."""
    port = src.serial_port
    device, tail = split_serial_url(port)  # as the MAVLink link splits a url: by-path names keep their colons
    if tail.isdigit():  # [mavlink] url's DEVICE:BAUD carried over: pyserial opens a device of that name
        raise VioError(f"{source}: [source] serial_port = {port!r} names the device only (the baud rate is "
                       f"serial_baud): serial_port = {device!r}, serial_baud = {tail}")
    if tail or port.endswith(":"):  # no baud rate either, and no device of that full name: retried for ever
        after = f"{tail!r} after the colon is no baud rate (that is serial_baud)" if tail else \
            "it ends in a colon (the baud rate is serial_baud)"
        raise VioError(f"{source}: [source] serial_port = {port!r}: no device of that name, and {after}: "
                       f"serial_port = {device!r}?")
    if not (port.startswith("/") or port.upper().startswith("COM")):
        raise VioError(f"{source}: [source] serial_port = {port!r} is not a device path: give it whole, e.g. "
                       f"'/dev/{port.rpartition('/')[2]}'")
    most = src.serial_baud / SERIAL_FRAME_BITS
    if most < src.serial_imu_rate_hz:
        raise VioError(f"{source}: [source] serial_baud = {src.serial_baud} carries at most {most:.0f} IMU frames a "
                       f"second (40 bytes of 10 bits each), fewer than serial_imu_rate_hz = {src.serial_imu_rate_hz:g}:"
                       " use 460800 or 921600 baud on both sides, or set serial_imu_rate_hz to the rate the IMU sends")


def load_config(path: str | Path | None) -> VioConfig:
    """Load and validate a TOML config file; None gives the defaults."""
    if path is None:
        return VioConfig()
    path = Path(path)
    try:
        raw = read_user_file(path, "configuration")
    except OSError as e:
        raise VioError(f"{path}: cannot read config ({e.strerror})") from None
    try:
        # utf-8-sig: a byte-order mark (Notepad's UTF-8) was "not valid TOML (Invalid statement (at line 1, column 1))"
        data = tomllib.loads(raw.decode("utf-8-sig"))
    except (UnicodeDecodeError, tomllib.TOMLDecodeError) as e:
        raise VioError(f"{path}: not valid TOML ({e})") from None
    except RecursionError:  # arrays or tables nested thousands deep: was an internal error (a review's finding)
        raise VioError(f"{path}: not a configuration (nested too deep to be one)") from None
    return config_from_dict(data, str(path))


def _toml_value(v: Any) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, float) and math.isnan(v):
        return "nan"
    if isinstance(v, str):
        # escape quote, backslash and control characters (a raw newline would make invalid TOML)
        return '"' + "".join("\\" + c if c in '"\\' else f"\\u{ord(c):04x}" if ord(c) < 0x20 or ord(c) == 0x7F
                             else c for c in v) + '"'
    if isinstance(v, list):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    return repr(v)


def config_to_toml(cfg: VioConfig, with_help: bool = True) -> str:
    """Effective configuration as TOML (loadable again), with each key's help as a comment."""
    out = []
    for sec in dataclasses.fields(cfg):
        section = getattr(cfg, sec.name)
        out.append(f"[{sec.name}]")
        for f in dataclasses.fields(section):
            line = f"{f.name} = {_toml_value(getattr(section, f.name))}"
            if with_help and f.metadata.get("help"):
                line = f"{line:<48} # {f.metadata['help']}"
            out.append(line)
        out.append("")
    return "\n".join(out)
