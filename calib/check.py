"""`vio calib check CALIB DATASET`: does a calibration fit a EuRoC recording? PASS / WARN / FAIL per check.

Checks and thresholds (pixels are cam1 pixels; "median" is over all stereo matches of the sampled frames):
- stereo epipolar error: distance of the right match from the epipolar line of T_cam1_cam0 after
  undistortion. A good calibration gives well under a pixel; a cam1 rotation error of 0.1 deg already adds
  0.1 * pi / 180 * f, about 0.8 px at f = 460.  PASS median < 0.5 px, WARN < 1.5 px, else FAIL.
- rectified row alignment: the same matches found again in images rectified with cv2.stereoRectify/remap;
  rows must agree.  PASS median |dy| < 0.5 px, WARN < 1.5 px, else FAIL.
- reprojection consistency: stereo matches triangulated and reprojected (with distortion) into both
  cameras; also the share of points in front of both cameras (a swapped pair or a sign error in the
  baseline puts them behind).  PASS median < 0.5 px and >= 95 % in front, WARN < 1.5 px and >= 80 %.
- gravity when still: on the longest still span, |mean accel| must be g (PASS within 0.2 m/s^2, WARN
  0.5); with ground truth, the accel direction must match gravity seen through the GT attitude (PASS < 2
  deg, WARN < 5 deg). The accel spread and gyro mean are reported (vibration, gyro bias).
- stereo disparity bias and focal lengths (`--disparity`: the recording is replayed with the estimator's
  stereo check reading, without ever letting go, where cam1's rotation and focal lengths would be if refined):
  the bias a drifted stereo calibration adds to every disparity, and cam1's fx, fy against cam0's (at the image
  edge), which the epipolar checks cannot see.  PASS under 0.1 px or under 3 sigma of the reading's own
  uncertainty, WARN < 0.3 px, else FAIL.
- camera-IMU rotation: the camera's rotations between frames (stereo PnP, as `vio calib time-offset` measures
  them) against the gyro's over the same times (the calibration's time offset applied), fitted by the rotation
  that maps one onto the other (orthogonal Procrustes, gyro bias solved with it): its angle to the calibration's
  R_body_cam0. An inverted T_cam_imu, a file with body = cam0, or a mount turned by a few degrees fly on at
  decimetres to metres of error while every stereo check passes. PASS under 1 deg or under 3 sigma of the
  reading, WARN under 2.5 deg, else FAIL; with turns about one axis only (a survey's yaw) only where that axis
  lies in the camera is checked, and with too little rotation it is skipped.
- units: the IMU recording (accel in g or mm/s^2, gyro in deg/s, an all-zero IMU), the stereo baseline and
  the camera-IMU lever arm (millimetres for metres) with vio/sanity.py's diagnosis, the one `vio replay`
  stops on: FAIL naming the likely mistake, else PASS.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from calib.stereo_match import DEFAULT_DEPTH_M, _expected_shift_px, match_stereo, normalise_contrast, triangulate
from vio import VioError
from vio.backend.offset_solver import fit_camera_imu_rotation, rotation_disagreement
from vio.calibration import StereoCalibration
from vio.geometry import GRAVITY_M_S2, skew

log = logging.getLogger(__name__)

PX_PASS, PX_WARN = 0.5, 1.5
IN_FRONT_PASS, IN_FRONT_WARN = 0.95, 0.80
G_PASS, G_WARN = 0.2, 0.5  # m/s^2
TILT_PASS_DEG, TILT_WARN_DEG = 2.0, 5.0
DISPARITY_PASS_PX, DISPARITY_WARN_PX = 0.1, 0.3  # 1 % / 3 % of a depth at 5 m (f B ~ 50 px m)
NOISE_OVER, NOISE_UNDER = 10.0, 0.01  # stated IMU noise per sample vs the still span's spread
ROT_PASS_DEG, ROT_WARN_DEG = 1.0, 2.5  # camera-IMU rotation against the gyro
ROT_MAX_PAIRS = 1200  # frame pairs measured at most (a minute at 20 Hz): the check stays a check, not a replay
DISPARITY_SIGNIFICANT = 3.0  # sigmas under which a refined bias is not told from zero
@dataclass
class CheckResult:
    name: str
    verdict: str  # PASS, WARN, FAIL or SKIP
    value: float
    unit: str
    detail: str


def _grade(value: float, pass_max: float, warn_max: float) -> str:
    if not np.isfinite(value):
        return "FAIL"
    return "PASS" if value < pass_max else "WARN" if value < warn_max else "FAIL"


# ------------------------------------------------------------------------------------------ matching

@dataclass
class StereoMatches:
    uv0: np.ndarray  # (N, 2) raw pixels in cam0
    uv1: np.ndarray  # (N, 2) raw pixels in cam1
    frame_of: np.ndarray  # (N,) index into the sampled frames


def collect_matches(dataset, calib: StereoCalibration, max_frames: int) -> tuple[StereoMatches, list[int]]:
    n = len(dataset)
    idx = sorted(set(np.linspace(0, n - 1, min(max_frames, n)).round().astype(int).tolist()))
    shift = _expected_shift_px(calib)
    uv0, uv1, fr, used = [], [], [], []
    for k in idx:
        f = dataset.frame(k)
        if f is None or f.right is None:
            continue
        a, b = match_stereo(normalise_contrast(f.left), normalise_contrast(f.right), shift)
        uv0.append(a)
        uv1.append(b)
        fr.append(np.full(len(a), len(used)))
        used.append(k)
    if not used:
        raise VioError("no stereo pair could be read from the dataset")
    return StereoMatches(np.vstack(uv0), np.vstack(uv1), np.concatenate(fr)), used


# -------------------------------------------------------------------------------------------- checks

def epipolar_errors_px(calib: StereoCalibration, uv0: np.ndarray, uv1: np.ndarray) -> np.ndarray:
    """Distance (cam1 pixels) of each right point from the epipolar line of its left point."""
    T = calib.T_cam1_cam0
    E = skew(T[:3, 3]) @ T[:3, :3]  # x1^T E x0 = 0 for x1 = R x0 + t
    x0 = np.column_stack([calib.cam0.undistort_normalized(uv0), np.ones(len(uv0))])
    x1 = np.column_stack([calib.cam1.undistort_normalized(uv1), np.ones(len(uv1))])
    lines = x0 @ E.T
    num = np.abs(np.sum(x1 * lines, axis=1))
    return num / np.linalg.norm(lines[:, :2], axis=1) * calib.cam1.fx


def check_epipolar(calib: StereoCalibration, m: StereoMatches) -> CheckResult:
    e = epipolar_errors_px(calib, m.uv0, m.uv1)
    med = float(np.median(e))
    return CheckResult("stereo epipolar error", _grade(med, PX_PASS, PX_WARN), med, "px",
                       f"median of {len(e)} matches; 90% {np.percentile(e, 90):.2f} px, "
                       f"{np.mean(e < 1.0) * 100:.0f}% under 1 px")


def rectify_maps(calib: StereoCalibration):
    """cv2 rectification maps and projection matrices for the calibrated pair (radtan or equidistant)."""
    c0, c1 = calib.cam0, calib.cam1
    T = calib.T_cam1_cam0
    R, t = np.ascontiguousarray(T[:3, :3]), np.ascontiguousarray(T[:3, 3]).reshape(3, 1)
    size = (c0.width, c0.height)
    if c0.distortion_model == "equidistant":
        R0, R1, P0, P1, _ = cv2.fisheye.stereoRectify(c0.K, c0.dist_coeffs, c1.K, c1.dist_coeffs, size, R, t,
                                                      flags=cv2.CALIB_ZERO_DISPARITY, balance=0.0)
        maps = [cv2.fisheye.initUndistortRectifyMap(c.K, c.dist_coeffs, R, P, size, cv2.CV_32FC1)
                for c, R, P in ((c0, R0, P0), (c1, R1, P1))]
    else:
        R0, R1, P0, P1, *_ = cv2.stereoRectify(c0.K, c0.dist_coeffs, c1.K, c1.dist_coeffs, size, R, t,
                                               flags=cv2.CALIB_ZERO_DISPARITY, alpha=0)
        maps = [cv2.initUndistortRectifyMap(c.K, c.dist_coeffs, R, P, size, cv2.CV_32FC1)
                for c, R, P in ((c0, R0, P0), (c1, R1, P1))]
    return maps, P0, P1


def check_rectified_rows(calib: StereoCalibration, dataset, frames: list[int]) -> CheckResult:
    maps, P0, P1 = rectify_maps(calib)
    # disparity start: horizontal shift of a point at DEFAULT_DEPTH_M in the rectified pair
    shift = np.array([P1[0, 3] / DEFAULT_DEPTH_M, 0.0])
    dys = []
    for k in frames:
        f = dataset.frame(k)
        if f is None or f.right is None:
            continue
        r0 = cv2.remap(f.left, *maps[0], cv2.INTER_LINEAR)
        r1 = cv2.remap(f.right, *maps[1], cv2.INTER_LINEAR)
        a, b = match_stereo(normalise_contrast(r0), normalise_contrast(r1), shift)
        dys.append(b[:, 1] - a[:, 1])
    dy = np.concatenate(dys) if dys else np.zeros(0)
    if len(dy) == 0:
        return CheckResult("rectified row alignment", "FAIL", float("nan"), "px", "no matches after rectification")
    med = float(np.median(np.abs(dy)))
    return CheckResult("rectified row alignment", _grade(med, PX_PASS, PX_WARN), med, "px",
                       f"median |dy| of {len(dy)} matches in {len(dys)} rectified pairs; mean dy {np.mean(dy):+.2f} px "
                       "(a constant dy means a rotation about the baseline)")


def check_reprojection(calib: StereoCalibration, m: StereoMatches) -> CheckResult:
    T = calib.T_cam1_cam0
    X, front = triangulate(calib, m.uv0, m.uv1)
    X1 = X @ T[:3, :3].T + T[:3, 3]
    share = float(np.mean(front)) if len(front) else 0.0
    if front.sum() < 10:
        return CheckResult("reprojection consistency", "FAIL", float("nan"), "px",
                           f"only {front.sum()} of {len(front)} triangulated points lie in front of both cameras "
                           "(cam0/cam1 swapped or baseline sign wrong?)")
    e0 = np.linalg.norm(calib.cam0.project(X[front]) - m.uv0[front], axis=1)
    e1 = np.linalg.norm(calib.cam1.project(X1[front]) - m.uv1[front], axis=1)
    med = float(np.median(np.concatenate([e0, e1])))
    verdict = _grade(med, PX_PASS, PX_WARN)
    if share < IN_FRONT_WARN:
        verdict = "FAIL"
    elif share < IN_FRONT_PASS and verdict == "PASS":
        verdict = "WARN"
    depth = np.median(X[front, 2])
    return CheckResult("reprojection consistency", verdict, med, "px",
                       f"{share * 100:.0f}% of points in front of both cameras, median depth {depth:.2f} m")


def check_units(dataset) -> list[CheckResult]:
    """IMU data and calibration units: the diagnosis `vio replay` stops on (vio/sanity.py via vio.io.euroc)."""
    from vio.calibration import calibration_unit_checks
    from vio.io.euroc import imu_units_problem

    calib = dataset.calibration
    problem = imu_units_problem(dataset.imu, dataset.mav0 / "imu0" / "data.csv")
    out = [CheckResult("IMU units", "FAIL" if problem else "PASS", float("nan"), "",
                       problem or "accel about g and gyro plausible for rad/s on the quietest second")]
    for name, value, why in calibration_unit_checks(calib, dataset.has_cam1):
        unit, ok = ("s", "plausible time offset") if "time" in name else ("m", "plausible length in metres")
        out.append(CheckResult(name, "FAIL" if why else "PASS", value, unit, why or ok))
    return out


def check_camera_imu_rotation(dataset, calib: StereoCalibration) -> CheckResult:
    """The calibration's camera-IMU rotation against the one the recording's turns show (module doc)."""
    from calib.time_offset import visual_rotations

    name = "camera-IMU rotation vs gyro"
    step = max(1, -(-len(dataset) // ROT_MAX_PAIRS))
    try:
        vis = visual_rotations(dataset, calib.cam0, step=step)
        fit = fit_camera_imu_rotation(vis, dataset.imu.t_ns, dataset.imu.gyro, calib.time_offset_ns * 1e-9)
    except VioError as e:
        return CheckResult(name, "SKIP", float("nan"), "deg", f"not checked: {e}")
    said = (f"from {fit.n_pairs} frame pairs, turn rates {', '.join(f'{r:.2f}' for r in fit.axis_rates)} rad/s "
            f"rms about the principal axes, residual {fit.residual_rad_s:.3f} rad/s")
    disagreement = rotation_disagreement(fit, calib.cam0.T_body_cam)
    if disagreement is None:
        return CheckResult(name, "SKIP", float("nan"), "deg", f"not checked: too little rotation ({said})")
    ang, sigma, what = disagreement
    if ang < 3 * sigma:
        if 3 * sigma >= ROT_WARN_DEG:
            return CheckResult(name, "SKIP", ang, "deg", f"not decided by this recording: {what} {ang:.2f} deg from "
                               f"the gyro's, 3 sigma {3 * sigma:.2f} deg; {said}")
        return CheckResult(name, "PASS", ang, "deg", f"{what} {ang:.2f} deg from the gyro's, within its "
                           f"{sigma:.2f} deg (1 sigma) uncertainty; {said}")
    verdict = _grade(ang, ROT_PASS_DEG, ROT_WARN_DEG)
    remedy = ("" if verdict == "PASS" else "; check T_cam_imu is not inverted (kalibr's maps IMU points into "
              "the camera), that the file states the camera-IMU extrinsic at all, and the camera's mount; a few "
              "degrees can also be a wrong time_offset_ns on a wobbling flight (`vio calib time-offset` measures it)")
    return CheckResult(name, verdict, ang, "deg", f"{what} {ang:.2f} deg (+- {sigma:.2f}) from the gyro's{remedy}; "
                       f"{said}")


def _still_span(dataset) -> tuple[int, int, str]:
    """The longest still span (ground truth or gyro), else the quietest second of the accelerometer."""
    from calib.allan import find_still_span
    from vio.io.euroc import quietest_window

    imu = dataset.imu
    try:
        return find_still_span(imu, dataset.groundtruth)
    except VioError as e:
        sl, spread = quietest_window(imu)
        return (int(imu.t_ns[sl.start]), int(imu.t_ns[sl.stop - 1]),
                f"quietest second of the accelerometer, spread {spread:.3f} of |mean| ({e})")


def check_gravity(dataset) -> list[CheckResult]:
    from vio.sanity import accel_units_problem

    imu = dataset.imu
    a, b, how = _still_span(dataset)
    sel = (imu.t_ns >= a) & (imu.t_ns <= b)
    acc, gyr = imu.accel[sel], imu.gyro[sel]
    mean = acc.mean(axis=0)
    norm = float(np.linalg.norm(mean))
    g_err = abs(norm - GRAVITY_M_S2)
    span = f"{(b - a) / 1e9:.1f} s still ({how})"
    units = accel_units_problem(norm)
    out = [CheckResult("gravity magnitude when still", _grade(g_err, G_PASS, G_WARN), g_err, "m/s^2",
                       (f"{units}; " if units else "") +
                       f"|mean accel| {norm:.3f} vs g {GRAVITY_M_S2}; {span}; accel spread "
                       f"{np.linalg.norm(acc.std(axis=0)):.3f} m/s^2, gyro mean {np.linalg.norm(gyr.mean(axis=0)):.4f} "
                       "rad/s (bias)")]
    out.append(check_imu_noise(dataset.calibration.imu, acc, gyr, span))
    gt = dataset.groundtruth
    if gt is not None and norm > 0.05:
        traj = gt.trajectory
        tsel = (traj.t_ns >= a) & (traj.t_ns <= b)
        if tsel.any():
            from vio.geometry import quat_wxyz_to_rot

            R_wb = quat_wxyz_to_rot(traj.q_wxyz[tsel])
            g_body = np.einsum("nji,j->ni", R_wb, np.array([0.0, 0.0, 1.0])).mean(axis=0)  # R^T z, averaged
            ang = float(np.degrees(np.arccos(np.clip(g_body @ mean / np.linalg.norm(g_body) / np.linalg.norm(mean),
                                                     -1, 1))))
            out.append(CheckResult("gravity direction vs ground truth", _grade(ang, TILT_PASS_DEG, TILT_WARN_DEG),
                                   ang, "deg", "angle between mean accel and world z seen through the GT attitude "
                                   "(tests IMU axes/GT alignment, and the accel bias)"))
    return out


def check_imu_noise(imu, acc: np.ndarray, gyr: np.ndarray, span: str) -> CheckResult:
    """The calibration's IMU noise densities as per-sample sigmas (density * sqrt(rate)) against the spread of the
    still span. The spread holds the noise and whatever shook the vehicle, so a stated sigma NOISE_OVER times above
    it cannot be the sensor's (per-sample values taken for densities, another unit), and one NOISE_UNDER times
    below it is more than vibration explains. Densities in the wrong unit imported and passed every check (a
    review's finding: x1000 flew, /1000 reset 14 times)."""
    rate = imu.rate_hz
    rows = []
    for what, density, x in (("accel", imu.accelerometer_noise_density, acc), ("gyro", imu.gyroscope_noise_density,
                                                                               gyr)):
        spread = float(np.sqrt(np.mean(x.var(axis=0)))) if len(x) > 10 else float("nan")
        rows.append((what, density * np.sqrt(rate), spread))
    if not all(np.isfinite(sp) and sp > 0 for _, _, sp in rows):
        return CheckResult("IMU noise vs still spread", "SKIP", float("nan"), "", f"no still span to compare ({span})")
    said = "; ".join(f"{w} stated {st:.3g} per sample vs {sp:.3g} spread" for w, st, sp in rows)
    bad = [(w, st / sp) for w, st, sp in rows if not NOISE_UNDER <= st / sp <= NOISE_OVER]
    if not bad:
        return CheckResult("IMU noise vs still spread", "PASS", max(st / sp for _, st, sp in rows), "x",
                           f"{said} ({span})")
    w, r = bad[0]
    why = ("above what the sensor shows: per-sample (discrete) values given as densities, or another unit (kalibr's "
           "are per sqrt(Hz))" if r > NOISE_OVER else "below what the sensor shows, beyond vibration: another unit?")
    return CheckResult("IMU noise vs still spread", "WARN", r, "x", f"the {w} noise density is {r:.3g}x {why}; "
                       f"{said}; `vio calib imu-noise` measures them")


def disparity_told_from_zero(bias_px: float, sigma_px: float | None) -> bool:
    """Does a refined disparity bias stand out of its 1-sigma (DISPARITY_SIGNIFICANT)? Without a sigma (the
    estimator was not running at the end) it is taken at its word."""
    return sigma_px is None or abs(bias_px) >= DISPARITY_SIGNIFICANT * sigma_px


def check_disparity(dataset_path: str | Path, calib: StereoCalibration | None = None,
                    config=None) -> list[CheckResult]:
    """The recording replayed with the estimator's stereo check (`[backend] stereo_check`) held for the whole
    flight: its last reading of where cam1's rotation and focal lengths would sit if refined, with their 1-sigma
    (a score test on everything the smoother saw; the trajectory is the calibration's own).

    A cam1 turned about its own vertical axis (or a principal point off sideways) moves every right pixel
    along its epipolar line, and two cameras' focal lengths stated differently scale the disparities across the
    image, so the epipolar and rectification checks cannot see either; both bias the depths (0.1 px is 1 % at 5 m
    for a 50 px m baseline) and the trajectory's scale with them: 0.5 px cost 3-35x of the ATE on the simulator's
    flights (docs/estimator.md, "The stereo check"). A reading under 3 sigma is what the recording cannot tell
    from zero: PASS, with that said. Two rows: the disparity bias, and the larger of fx, fy at the image edge."""
    import dataclasses

    from vio.config import load_config
    from vio.consistency import replay_states

    names = ("stereo disparity bias", "stereo focal lengths")
    cfg = load_config(config)
    # the check on, never letting go (20 px, 100 sigma: its bounds), nothing else refined
    cfg = dataclasses.replace(cfg, backend=dataclasses.replace(
        cfg.backend, refine_extrinsics=False, refine_extrinsics_auto=False, refine_stereo_rotation=False,
        stereo_check=True, stereo_check_focal=True, stereo_check_px=20.0, stereo_check_sigma=100.0))
    try:
        run = replay_states(dataset_path, cfg.estimator, calibration=calib)
    except VioError as e:  # e.g. an IMU in the wrong units, which the units check below names
        return [CheckResult(n, "SKIP", float("nan"), "px", f"the replay refused the recording: {e}") for n in names]
    check = run.estimator.stereo_check_stats()
    if check is None or "disparity_px" not in check:
        return [CheckResult(n, "SKIP", float("nan"), "px", "the estimator never read the stereo calibration on this "
                            "recording (too short, or it never initialised): nothing to measure") for n in names]
    fB = run.dataset.calibration.cam1.fx * float(np.linalg.norm(run.dataset.calibration.T_cam1_cam0[:3, 3]))
    at = f"at {check['at_s']:.1f} s" if check.get("at_s") is not None else "at the end"
    bias, sigma = check["disparity_px"], check["sigma_px"]
    out = [_reading_row(names[0], bias, sigma, f"{bias:+.2f} +- {sigma:.2f} px (1 sigma) {at}",
                        f"depths {'short' if bias > 0 else 'long'} by {100 * abs(bias) * 5.0 / fB:.1f} % at 5 m",
                        "`vio calib refine DATASET -o OUT.yaml --stereo-only` writes the calibration with it taken out "
                        "(a cam1 turned or shifted sideways); first make sure the baseline's length is the rig's "
                        "(a wrong length scales every depth, which this reading takes for a bias)",
                        " (one that moves further, past near and far texture, tells more)")]
    if not check.get("focal_px"):
        return out + [CheckResult(names[1], "SKIP", float("nan"), "px", "no reading of cam1's focal lengths")]
    (fx, sfx), (fy, sfy) = check["focal_px"]
    worst, sw, axis = max((abs(fx), sfx, "fx"), (abs(fy), sfy, "fy"))
    return out + [_reading_row(names[1], worst, sw, f"cam1 fx {fx:+.2f} +- {sfx:.2f} px, fy {fy:+.2f} +- {sfy:.2f} px "
                               f"at the image edge (1 sigma) {at}", f"{axis} of the two cameras disagree",
                               "calibrate the stereo pair again (both cameras in one fit)")]


def _reading_row(name: str, value: float, sigma: float, told: str, shown: str, remedy: str,
                 unseen_hint: str = "") -> CheckResult:
    """One stereo-check reading as a row: PASS when the recording cannot tell it from zero, else graded on its
    size in pixels, with `shown` (what it means) and, unless it passes, `remedy`."""
    if not disparity_told_from_zero(value, sigma):
        if sigma is not None and DISPARITY_SIGNIFICANT * sigma >= DISPARITY_WARN_PX:
            # under its 3 sigma, but a 3 sigma that would hide what matters: nothing decided, not a pass
            return CheckResult(name, "SKIP", abs(value), "px", f"{told}: not decided by this recording (3 sigma "
                               f"{DISPARITY_SIGNIFICANT * sigma:.2f} px, beyond the {DISPARITY_WARN_PX} px that "
                               f"matters){unseen_hint}")
        return CheckResult(name, "PASS", abs(value), "px", f"{told}: not told from zero by this recording{unseen_hint}")
    verdict = _grade(abs(value), DISPARITY_PASS_PX, DISPARITY_WARN_PX)
    detail = f"{told}: {shown}" + (f"; {remedy}" if verdict != "PASS" else "")
    return CheckResult(name, verdict, abs(value), "px", detail)


def check_calibration(dataset_path: str | Path, calib: StereoCalibration | None = None,
                      max_frames: int = 40, disparity: bool = False, config=None) -> list[CheckResult]:
    """All checks; `calib` None uses the dataset's own sensor.yaml calibration. `disparity`: also replay the
    recording for the disparity-bias check (a replay's time: about a quarter of the recording's length)."""
    from vio.io.euroc import EurocDataset

    ds = EurocDataset(dataset_path, calibration=calib)
    calib = ds.calibration
    results: list[CheckResult] = []
    problem = ds.first_image_size_problem()
    if problem:
        raise VioError(problem)
    if not len(ds):  # the camera checks would vanish from the report and leave the IMU's to say PASS
        raise VioError(f"{dataset_path}: the recording has no camera frames (cam0/data.csv lists none): the stereo "
                       "and camera-IMU checks need images")
    m, frames = collect_matches(ds, calib, max_frames)
    if len(m.uv0) < 20:
        results.append(CheckResult("stereo matching", "FAIL", len(m.uv0), "matches",
                                   "too few left-right matches to check the stereo calibration"))
    else:
        results += [check_epipolar(calib, m), check_rectified_rows(calib, ds, frames),
                    check_reprojection(calib, m)]
    results += check_disparity(dataset_path, calib, config) if disparity else [CheckResult(
        "stereo disparity bias", "SKIP", float("nan"), "px", "not checked: add --disparity, which replays the "
        "recording; a disparity bias leaves the epipolar lines where they are")]
    results.append(check_camera_imu_rotation(ds, calib))
    results += check_gravity(ds) + check_units(ds)
    return results


def format_report(results: list[CheckResult]) -> str:
    # a check with no figure (IMU units), or one not made (SKIP), says no "nan"
    lines = [f"{r.verdict:4s}  {r.name}: " + (f"{r.value:.3g} {r.unit}  " if np.isfinite(r.value) else "")
             + f"({r.detail})" for r in results]
    worst = "FAIL" if any(r.verdict == "FAIL" for r in results) else \
        "WARN" if any(r.verdict == "WARN" for r in results) else "PASS"
    skipped = [r.name for r in results if r.verdict == "SKIP"]
    lines.append(f"overall: {worst}" + (f" (not checked or not decided: {', '.join(skipped)})" if skipped else ""))
    return "\n".join(lines)
