"""depthai (OAK) calibration -> StereoCalibration: the one conversion used by `vio calib import depthai` and
by the live camera driver, so both read the device EEPROM the same way.

depthai stores extrinsics in centimetres and with OpenCV's convention (getCameraExtrinsics(a, b) maps
points of camera a into camera b, i.e. it is T_b_a); we ask for metres explicitly. Lenses are either
OpenCV's 14-coefficient rational model (k1 k2 p1 p2 k3 k4 k5 k6 s1..s4 tx ty) or fisheye (k1..k4). Our
radtan model is OpenCV's own pinhole model, so the coefficients are kept exactly; only trailing zero groups
are trimmed (14 -> 8 or 5), which keeps the file readable by tools that know only 5.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np

from vio import VioError
from vio.calibration import MIN_IMU_NOISE, RADTAN_LENGTHS, CameraCalibration, ImuNoise, StereoCalibration
from vio.geometry import inv_T

log = logging.getLogger(__name__)


OAK_MAX_BASELINE_M = 0.3  # the widest OAK board (OAK-D LR) is 15 cm apart; more is a custom rig or a unit slip


def require_depthai():
    """The depthai module, or a VioError naming the [oak] extra."""
    from vio.extras import require

    return require("depthai", "oak", "reading an OAK (depthai) calibration")



@dataclass
class ImportNotes:
    """Things an importer had to approximate or assume; shown to the user and logged."""

    messages: list[str] = field(default_factory=list)
    # the importer's own logger: kalibr, EuRoC and OpenCV notes were logged as calib.depthai_import
    logger: logging.Logger = field(default=log, repr=False, compare=False)

    def add(self, msg: str) -> None:
        self.messages.append(msg)
        self.logger.warning(msg)


def pinhole_from_K(K: np.ndarray, where: str) -> tuple[float, float, float, float]:
    """fx, fy, cx, cy of a camera matrix [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] (VioError for another: a skew or
    another last row was dropped unsaid, and the calibration was of another camera)."""
    K = np.asarray(K, dtype=float).reshape(3, 3)
    fx = float(K[0, 0])
    if not np.all(np.isfinite(K)):
        raise VioError(f"{where} has a non-finite value: {K.tolist()}")
    if abs(K[0, 1]) > 1e-6 * max(abs(fx), 1.0):
        raise VioError(f"{where} has a skew of {K[0, 1]:g} px (K[0][1]): Kestrel's pinhole model has none; "
                       "calibrate without skew (OpenCV's default)")
    if abs(K[1, 0]) > 1e-9 or abs(K[2, 0]) > 1e-9 or abs(K[2, 1]) > 1e-9 or abs(K[2, 2] - 1.0) > 1e-9:
        raise VioError(f"{where}'s last row is [{K[2, 0]:g}, {K[2, 1]:g}, {K[2, 2]:g}]"
                       + (f" and K[1][0] = {K[1, 0]:g}" if abs(K[1, 0]) > 1e-9 else "")
                       + ": not a camera matrix [[fx, 0, cx], [0, fy, cy], [0, 0, 1]]")
    return fx, float(K[1, 1]), float(K[0, 2]), float(K[1, 2])


def opencv_to_radtan(coeffs, where: str, tol: float = 1e-12) -> tuple[float, ...]:
    """OpenCV distortion vector (4, 5, 8, 12 or 14 values) -> our radtan coefficients, exactly.

    Trailing groups that are all zero are dropped (14 -> 12 -> 8 -> 5), so a plain 5-coefficient lens stays
    a 5-coefficient lens in the file; nothing non-zero is ever cut (cutting OAK's k4..k6 moves border pixels
    by tens of pixels).
    """
    d = [float(x) for x in np.asarray(coeffs, dtype=float).ravel()]
    if len(d) not in RADTAN_LENGTHS:
        raise VioError(f"{where}: OpenCV distortion needs 4, 5, 8, 12 or 14 coefficients, got {len(d)}")
    if not all(np.isfinite(d)):
        raise VioError(f"{where}: non-finite distortion coefficient in {d}")
    for n in (5, 8, 12):
        if len(d) > n and all(abs(v) <= tol for v in d[n:]):
            return tuple(d[:n])
    return tuple(d)


def _camera(handler, socket, T_body_cam: np.ndarray, where: str, notes: ImportNotes, rate_hz: float,
            size: tuple[int, int] | None) -> CameraCalibration:
    dai = require_depthai()

    K, w, h = handler.getDefaultIntrinsics(socket)
    if size is not None and tuple(size) != (w, h):  # depthai scales/crops K for the resolution streamed
        w, h = int(size[0]), int(size[1])
        K = handler.getCameraIntrinsics(socket, w, h)
    K = np.asarray(K, dtype=float)
    if w <= 0 or h <= 0:
        raise VioError(f"{where}: calibration has no image size")
    dist = handler.getDistortionCoefficients(socket)
    model = handler.getDistortionModel(socket)
    if model == dai.CameraModel.Fisheye:
        dmodel, dcoef = "equidistant", tuple(float(x) for x in dist[:4])
    elif model == dai.CameraModel.Perspective:
        dmodel, dcoef = "radtan", opencv_to_radtan(dist, where)
    else:
        raise VioError(f"{where}: depthai camera model {model.name} is not supported (Perspective or Fisheye)")
    fx, fy, cx, cy = pinhole_from_K(K, f"{where}: its camera matrix")
    return CameraCalibration(fx=fx, fy=fy, cx=cx, cy=cy, width=w, height=h,
                             distortion_model=dmodel, distortion=dcoef, T_body_cam=T_body_cam, rate_hz=rate_hz)


def _imu_noise(handler, notes: ImportNotes, rate_hz: float) -> ImuNoise:
    """IMU noise from the EEPROM when it was filled in (most devices leave it zero): mean over axes."""
    default = ImuNoise(rate_hz=rate_hz)
    try:
        n = handler.getImuNoiseParameters()
    except RuntimeError:
        n = None

    def mean(sensor, attr: str) -> float:
        vals = [getattr(getattr(sensor, ax), attr) for ax in ("x", "y", "z")]
        vals = [float(v) for v in vals if v > 0]
        return float(np.mean(vals)) if vals else 0.0

    if n is None:
        notes.add("depthai: no IMU noise parameters; using the project defaults (run `vio calib imu-noise`)")
        return default
    vals = {
        "gyroscope_noise_density": mean(n.gyroscope, "noiseDensity"),
        "gyroscope_random_walk": mean(n.gyroscope, "randomWalk"),
        "accelerometer_noise_density": mean(n.accelerometer, "noiseDensity"),
        "accelerometer_random_walk": mean(n.accelerometer, "randomWalk"),
    }
    # under MIN_IMU_NOISE is no IMU's (ImuNoise refuses it): garbage where most devices leave 0, taken as not there
    missing = [k for k, v in vals.items() if v < MIN_IMU_NOISE]
    if missing:
        notes.add(f"depthai: IMU noise {', '.join(missing)} not in the calibration (0, or below any IMU's); using "
                  "project defaults for those (measure them with `vio calib imu-noise`)")
        for k in missing:
            vals[k] = getattr(default, k)
    return ImuNoise(**vals, rate_hz=rate_hz)


def stereo_from_depthai(handler, left=None, right=None, *, size: tuple[int, int] | None = None,
                        cam_rate_hz: float = 20.0, imu_rate_hz: float = 200.0,
                        notes: ImportNotes | None = None) -> StereoCalibration:
    """Convert a `dai.CalibrationHandler` (device EEPROM or JSON export) into our StereoCalibration.

    cam0/cam1 are the stereo left/right sockets recorded in the calibration unless given; `size` (w, h)
    rescales the intrinsics to the streamed resolution (default: the calibrated one). Without IMU
    extrinsics the body frame is put at cam0 (a warning says so), which is only right for vision-only use.
    """
    dai = require_depthai()

    notes = notes if notes is not None else ImportNotes()
    try:
        left = left if left is not None else handler.getStereoLeftCameraId()
        right = right if right is not None else handler.getStereoRightCameraId()
    except RuntimeError:
        left, right = dai.CameraBoardSocket.CAM_B, dai.CameraBoardSocket.CAM_C
    meter = dai.LengthUnit.METER
    try:
        T_right_left = np.asarray(handler.getCameraExtrinsics(left, right, unit=meter), dtype=float)
    except RuntimeError as e:
        raise VioError(f"depthai: no extrinsics between {left.name} and {right.name} ({e})") from None
    baseline = float(np.linalg.norm(T_right_left[:3, 3]))
    if baseline > OAK_MAX_BASELINE_M:
        # a JSON written in mm where depthai reads cm imported at 0.75 m unsaid (a review's finding)
        notes.add(f"depthai: stereo baseline {baseline:.3f} m, more than any OAK board's (4-15 cm): right for a "
                  "custom FFC rig only; else the file's translations are in mm where depthai reads cm")
    try:
        T_body_cam0 = np.asarray(handler.getCameraToImuExtrinsics(left, unit=meter), dtype=float)
    except RuntimeError:
        notes.add(f"depthai: calibration has no IMU extrinsics; body frame set to {left.name} (cam0)")
        T_body_cam0 = np.eye(4)
    T_body_cam1 = T_body_cam0 @ inv_T(T_right_left)
    cam0 = _camera(handler, left, T_body_cam0, f"depthai {left.name}", notes, cam_rate_hz, size)
    cam1 = _camera(handler, right, T_body_cam1, f"depthai {right.name}", notes, cam_rate_hz, size)
    return StereoCalibration(cam0, cam1, _imu_noise(handler, notes, imu_rate_hz), time_offset_ns=0)
