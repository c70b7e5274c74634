"""Camera and IMU calibration types and the project's calibration file (kalibr-style YAML).

Names follow kalibr: distortion models `radtan` (OpenCV's pinhole model: k1, k2, p1, p2[, k3[, k4, k5, k6
[, s1..s4[, tx, ty]]]], i.e. 4, 5, 8, 12 or 14 coefficients, so the rational model of OAK cameras is kept
exactly) and `equidistant` (k1..k4, OpenCV fisheye); IMU noise keys are kalibr's. `T_body_cam` maps
camera points into the body (= IMU) frame. `time_offset_ns` follows kalibr's timeshift: t_imu = t_cam + time_offset_ns.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field, replace
from pathlib import Path

import cv2
import numpy as np
import yaml

from vio import VioError
from vio.config import refuse_unknown_keys
from vio.geometry import inv_T, is_se3
from vio.io.inputs import read_user_file

DISTORTION_MODELS = ("radtan", "equidistant", "none")
# A side longer than this is no camera's (the largest machine-vision sensors are ~15000 pixels wide): a typo or
# another unit. And a focal length over FOCAL_MAX_SIDES image sides is a field of view under 0.6 deg.
MAX_IMAGE_SIDE = 32768
FOCAL_MAX_SIDES = 100
FOCAL_MIN_FRACTION = 20  # and a focal length under 1/20 of its side is a field of view no lens has (see validate)
# OpenCV's coefficients of a real lens are a few units (an OAK's rational model: -9 .. 16); none is a thousand
MAX_DISTORTION = 1000.0
# the rates a camera or an IMU has (the EuRoC reader's stamp check takes the same: camera to 1 kHz, IMU to 100 kHz)
MAX_CAMERA_RATE_HZ = 1e3
MAX_IMU_RATE_HZ = 1e5
# an IMU noise density or random walk above this is no IMU's (a consumer MEMS's is ~1e-2; x1000 mistakes are still
# taken here and said by `vio calib check`)
MAX_IMU_NOISE = 100.0
# and below this is no IMU's either: a navigation-grade fibre-optic gyro's noise density is ~3e-7 rad/s/sqrt(Hz) and
# its bias random walk ~1e-8 (a drone's MEMS: 1e-5 .. 1e-2). 1e-300 was taken and the pre-integration trusted the IMU
# beyond any sensor (a variance squared to 0); a variance given for a standard deviation is ~1e-8 .. 1e-10.
MIN_IMU_NOISE = 1e-9
RADTAN_LENGTHS = (4, 5, 8, 12, 14)  # the coefficient counts OpenCV's pinhole model accepts
_DISTORTION_ALIASES = {
    "radtan": "radtan",
    "radial-tangential": "radtan",
    "plumb_bob": "radtan",
    "equidistant": "equidistant",
    "fisheye": "equidistant",
    "kannala_brandt": "equidistant",
    "none": "none",
}


def normalise_distortion_model(name: str) -> str:
    """Map the many spellings used by kalibr/EuRoC/ROS onto our three model names."""
    key = str(name).strip().lower()
    if key not in _DISTORTION_ALIASES:
        raise VioError(f"unknown distortion model {name!r}; expected one of {sorted(_DISTORTION_ALIASES)}")
    return _DISTORTION_ALIASES[key]


@dataclass(frozen=True)
class CameraCalibration:
    """Pinhole camera with lens distortion and its mounting on the body."""

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int
    distortion_model: str = "radtan"
    distortion: tuple[float, ...] = (0.0, 0.0, 0.0, 0.0)
    T_body_cam: np.ndarray = field(default_factory=lambda: np.eye(4))
    rate_hz: float = 20.0

    def __post_init__(self) -> None:
        object.__setattr__(self, "distortion_model", normalise_distortion_model(self.distortion_model))
        object.__setattr__(self, "distortion", tuple(float(d) for d in self.distortion))
        object.__setattr__(self, "T_body_cam", np.asarray(self.T_body_cam, dtype=float))
        self.validate()

    def validate(self) -> None:
        """Raise VioError on values no real camera has; catches most typos in calibration files."""
        if not (0 < self.fx < math.inf and 0 < self.fy < math.inf):
            raise VioError(f"focal lengths must be positive and finite, got fx={self.fx}, fy={self.fy}")
        if not all(math.isfinite(d) for d in self.distortion):
            # NaN coefficients loaded fine and ended a replay in "SVD did not converge" (a review's finding)
            raise VioError(f"distortion coefficients must be finite, got {list(self.distortion)}")
        if any(abs(d) > MAX_DISTORTION for d in self.distortion):
            # p1 = 1e300 ended a replay in "SVD did not converge", k1 = 1e10 flew on with no stereo match (a review's)
            raise VioError(f"distortion coefficients {[f'{d:g}' for d in self.distortion]}: beyond any lens's (at "
                           f"most {MAX_DISTORTION:g} in size): a typo?")
        if not (self.width > 0 and self.height > 0):
            raise VioError(f"resolution must be positive, got {self.width}x{self.height}")
        if max(self.width, self.height) > MAX_IMAGE_SIDE:
            # 1e300 pixels wide was taken (calib show printed a 301-digit width and principal point offset)
            raise VioError(f"resolution {self.width:.6g}x{self.height:.6g} is beyond any camera's (at most "
                           f"{MAX_IMAGE_SIDE} pixels a side): a typo?")
        if max(self.fx, self.fy) > FOCAL_MAX_SIDES * max(self.width, self.height):
            raise VioError(f"focal lengths fx={self.fx:.6g}, fy={self.fy:.6g} px are over {FOCAL_MAX_SIDES} times the "
                           f"{self.width}x{self.height} image (a field of view under 0.6 deg): a typo?")
        if self.fx < self.width / FOCAL_MIN_FRACTION or self.fy < self.height / FOCAL_MIN_FRACTION:
            # fx = 4.58 (a typo of 458) was taken: a pinhole's field of view over 168 deg, or an equidistant (fisheye)
            # lens seeing 10 rad to its image's edge
            raise VioError(f"focal lengths fx={self.fx:.6g}, fy={self.fy:.6g} px: under 1/{FOCAL_MIN_FRACTION} of the "
                           f"{self.width}x{self.height} image (a field of view no lens has): a typo?")
        if not (isinstance(self.rate_hz, (int, float)) and 0 < self.rate_hz < math.inf):
            # the time-offset code divides by it; the IMU's was refused already, the camera's passed (a QA sweep)
            raise VioError(f"camera rate_hz must be a positive number, got {self.rate_hz!r}")
        if self.rate_hz > MAX_CAMERA_RATE_HZ:  # 1e300 ended vio replay in an OverflowError (a review's finding)
            raise VioError(f"camera rate_hz = {self.rate_hz:g} is beyond any camera's (at most "
                           f"{MAX_CAMERA_RATE_HZ:g} Hz): a typo?")
        if not (0 <= self.cx <= self.width and 0 <= self.cy <= self.height):
            raise VioError(f"principal point ({self.cx}, {self.cy}) lies outside the {self.width}x{self.height} image")
        n = len(self.distortion)
        if self.distortion_model == "radtan" and n not in RADTAN_LENGTHS:
            raise VioError(f"radtan distortion needs 4, 5, 8, 12 or 14 coefficients (OpenCV order), got {n}")
        if self.distortion_model == "equidistant" and n != 4:
            raise VioError(f"equidistant distortion needs 4 coefficients, got {n}")
        if not (np.isfinite(self.T_body_cam).all() and is_se3(self.T_body_cam, tol=1e-4)):
            raise VioError("T_body_cam is not a rigid transform (rotation not orthonormal or last row not 0 0 0 1)")

    @property
    def K(self) -> np.ndarray:
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def dist_coeffs(self) -> np.ndarray:
        if self.distortion_model == "none":
            return np.zeros(4)
        return np.asarray(self.distortion, dtype=float)

    def project(self, p_cam: np.ndarray) -> np.ndarray:
        """Pixel coordinates (N, 2) of camera-frame points (N, 3) with lens distortion applied.

        Points must be in front of the camera (z > 0); callers filter those first.
        """
        p = np.asarray(p_cam, dtype=np.float64).reshape(-1, 1, 3)
        if len(p) == 0:
            return np.zeros((0, 2))
        zero = np.zeros(3)
        if self.distortion_model == "equidistant":
            uv, _ = cv2.fisheye.projectPoints(p, zero, zero, self.K, self.dist_coeffs)
        else:
            uv, _ = cv2.projectPoints(p, zero, zero, self.K, self.dist_coeffs)
        return uv.reshape(-1, 2)

    def undistort_normalized(self, uv: np.ndarray) -> np.ndarray:
        """Normalised image coordinates (x/z, y/z), shape (N, 2), of distorted pixels (N, 2)."""
        pts = np.asarray(uv, dtype=np.float64).reshape(-1, 1, 2)
        if len(pts) == 0:
            return np.zeros((0, 2))
        if self.distortion_model == "equidistant":
            out = cv2.fisheye.undistortPoints(pts, self.K, self.dist_coeffs)
        else:
            crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 20, 1e-9)
            if hasattr(cv2, "undistortPointsIter"):  # OpenCV 4.x
                out = cv2.undistortPointsIter(pts, self.K, self.dist_coeffs, None, None, crit)
            else:  # OpenCV 5 folded the criteria into undistortPoints (needs explicit R, P)
                out = cv2.undistortPoints(pts, self.K, self.dist_coeffs, None, np.eye(3), np.eye(3), crit)
        return out.reshape(-1, 2)

    def with_T_body_cam(self, T: np.ndarray) -> CameraCalibration:
        return replace(self, T_body_cam=np.asarray(T, dtype=float))


@dataclass(frozen=True)
class ImuNoise:
    """Continuous-time IMU noise model (kalibr/EuRoC units).

    Discrete per-sample standard deviations are density * sqrt(rate) for white noise and
    random_walk / sqrt(rate) for the bias step, see `discrete_sigmas`.
    """

    gyroscope_noise_density: float = 1.6968e-04  # rad/s/sqrt(Hz)
    gyroscope_random_walk: float = 1.9393e-05  # rad/s^2/sqrt(Hz)
    accelerometer_noise_density: float = 2.0e-3  # m/s^2/sqrt(Hz)
    accelerometer_random_walk: float = 3.0e-3  # m/s^3/sqrt(Hz)
    rate_hz: float = 200.0

    def __post_init__(self) -> None:
        for name in ("gyroscope_noise_density", "gyroscope_random_walk", "accelerometer_noise_density",
                     "accelerometer_random_walk", "rate_hz"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise VioError(f"IMU noise {name} must be a positive number, got {v!r}")
            if name != "rate_hz" and v > MAX_IMU_NOISE:
                # 1e300 ended vio replay in "internal error: OverflowError" squaring it (a review's finding)
                raise VioError(f"IMU noise {name} = {v:g} is beyond any IMU's (at most {MAX_IMU_NOISE:g} in kalibr's "
                               "units, /sqrt(Hz)): in another unit?")
            if name != "rate_hz" and v < MIN_IMU_NOISE:
                raise VioError(f"IMU noise {name} = {v:g} is below any IMU's (at least {MIN_IMU_NOISE:g} in kalibr's "
                               "units, /sqrt(Hz)): a typo, a variance for a standard deviation, or another unit?")
        if self.rate_hz > MAX_IMU_RATE_HZ:  # 1e300 was taken
            raise VioError(f"IMU rate_hz = {self.rate_hz:g} is beyond any IMU's (at most {MAX_IMU_RATE_HZ:g} Hz): "
                           "a typo?")

    def discrete_sigmas(self) -> dict[str, float]:
        """Per-sample sigmas at `rate_hz`: white noise of one sample and the bias step between samples."""
        r = self.rate_hz
        return {
            "gyro": self.gyroscope_noise_density * math.sqrt(r),
            "accel": self.accelerometer_noise_density * math.sqrt(r),
            "gyro_bias_step": self.gyroscope_random_walk / math.sqrt(r),
            "accel_bias_step": self.accelerometer_random_walk / math.sqrt(r),
        }


@dataclass(frozen=True)
class StereoCalibration:
    """Everything the estimator needs to know about the sensor head."""

    cam0: CameraCalibration
    cam1: CameraCalibration
    imu: ImuNoise = field(default_factory=ImuNoise)
    time_offset_ns: int = 0  # t_imu = t_cam + time_offset_ns

    @property
    def T_cam1_cam0(self) -> np.ndarray:
        return inv_T(self.cam1.T_body_cam) @ self.cam0.T_body_cam

    @property
    def baseline_m(self) -> float:
        return float(np.linalg.norm(self.T_cam1_cam0[:3, 3]))

    @property
    def view_headings_body(self) -> tuple[np.ndarray, np.ndarray]:
        """cam0's optical axis and its image top in the body frame: the start yaw's reference where the IMU's
        x axis is vertical (geometry.gravity_aligned_rotation)."""
        R = self.cam0.T_body_cam[:3, :3]
        return R[:, 2].copy(), -R[:, 1]


MAX_TIME_OFFSET_S = 0.2  # a camera-IMU offset beyond this is a unit or sign mistake, not a clock


def calibration_unit_checks(calib: StereoCalibration, stereo: bool = True) -> list[tuple[str, float, str | None]]:
    """(name, metres, problem or None) of the stereo baseline (when `stereo`) and the camera-IMU lever arm."""
    from vio.sanity import baseline_units_problem, lever_arm_units_problem

    lever = float(np.linalg.norm(calib.cam0.T_body_cam[:3, 3]))
    out = [("camera-IMU lever arm", lever, lever_arm_units_problem(lever))]
    if stereo:
        out.insert(0, ("stereo baseline", calib.baseline_m, baseline_units_problem(calib.baseline_m)))
    off_s = calib.time_offset_ns * 1e-9
    out.append(("camera-IMU time offset", off_s, None if abs(off_s) <= MAX_TIME_OFFSET_S else
                f"time_offset_ns = {calib.time_offset_ns} is {off_s * 1e3:.0f} ms: beyond any camera-IMU offset "
                f"(+-{MAX_TIME_OFFSET_S * 1e3:.0f} ms; a USB camera's is tens of ms): in another unit?"))
    return [(name, v, f"calibration: {p}" if p else None) for name, v, p in out]


def calibration_units_problem(calib: StereoCalibration, stereo: bool = True) -> str | None:
    """The first unit mistake in a calibration (millimetres for metres...), or None."""
    return next((p for _, _, p in calibration_unit_checks(calib, stereo) if p), None)


def streamed_size_problem(calib: StereoCalibration, width: int, height: int, path: str) -> str | None:
    """Why the calibration file `path` cannot be used with a camera streaming width x height: every frame would be
    refused as unusable (`vio run`, whose status said only 'not initialised yet'), and a recording made with it is
    refused by `vio replay`. None when the sizes agree."""
    if (calib.cam0.width, calib.cam0.height) == (width, height):
        return None
    return (f"[source] calibration = {path!r} is for {calib.cam0.width}x{calib.cam0.height} images, but the camera "
            f"streams [source] width x height = {width}x{height}: set width/height to the calibrated size, or import "
            f"the calibration for the streamed one (vio calib import depthai FILE --size {width}x{height} -o "
            "CALIB.yaml)")


# a recalibration of one camera moves its focal lengths and baseline by a per cent or two; another camera model (a wide
# lens, a long baseline) by tens of per cents
OTHER_CAMERA_RATIO = 1.10


def other_camera_problem(given: StereoCalibration, device: StereoCalibration) -> str | None:
    """How a calibration file differs from the one the camera (or recording) reports itself, when by more than a
    recalibration of the same camera would: the file is another camera's, and every distance estimated with it is off
    by that ratio. None when they agree. The device's is taken at the file's image size."""
    scale = given.cam0.width / device.cam0.width
    pairs = (("stereo baseline", given.baseline_m * 1e3, device.baseline_m * 1e3, "mm"),
             ("cam0 focal length fx", given.cam0.fx, device.cam0.fx * scale, "px"))
    off = [f"its {name} is {a:.1f} {unit}, the camera's {b:.1f} {unit}" for name, a, b, unit in pairs
           if a > 0 and b > 0 and max(a / b, b / a) > OTHER_CAMERA_RATIO]
    return "; ".join(off) or None


# ---------------------------------------------------------------------------------------------- file I/O

def _camera_to_dict(cam: CameraCalibration) -> dict:
    return {
        "camera_model": "pinhole",
        "intrinsics": [float(cam.fx), float(cam.fy), float(cam.cx), float(cam.cy)],  # numpy scalars break yaml
        "distortion_model": cam.distortion_model,
        "distortion_coeffs": list(cam.distortion),
        "resolution": [int(cam.width), int(cam.height)],
        "rate_hz": float(cam.rate_hz),
        "T_body_cam": [list(map(float, row)) for row in cam.T_body_cam],
    }


def _need(d: dict, key: str, where: str):
    if key not in d:
        raise VioError(f"{where}: missing key '{key}'")
    return d[key]


CAMERA_KEYS = ("camera_model", "intrinsics", "distortion_model", "distortion_coeffs", "resolution", "rate_hz",
               "T_body_cam", "T_cam_imu")
# kalibr's camchain keys that camera_from_dict is handed too: read by the importer, or naming only what was recorded
KALIBR_CAMERA_KEYS = ("T_cn_cnm1", "timeshift_cam_imu", "cam_overlaps", "rostopic")
CALIBRATION_KEYS = ("cam0", "cam1", "imu", "time_offset_ns")
IMU_KEYS = ("gyroscope_noise_density", "gyroscope_random_walk", "accelerometer_noise_density",
            "accelerometer_random_walk", "update_rate", "rate_hz")


def camera_from_dict(d: dict, where: str, kalibr: bool = False) -> CameraCalibration:
    """Build a camera from our keys (`kalibr`: a kalibr camchain's camera); errors name `where` and the key."""
    if not isinstance(d, dict):
        raise VioError(f"{where}: expected a mapping of camera keys")
    if not kalibr and (kal := [k for k in d if k in KALIBR_CAMERA_KEYS]):
        raise VioError(f"{where}: kalibr's '{kal[0]}' in a project calibration file: convert the camchain with "
                       "`vio calib import kalibr CAMCHAIN.yaml IMU.yaml -o OUT.yaml` (it reads T_cn_cnm1 and "
                       "timeshift_cam_imu, which this file format would ignore)")
    refuse_unknown_keys(d, CAMERA_KEYS + (KALIBR_CAMERA_KEYS if kalibr else ()), where)
    try:
        model = str(d.get("camera_model", "pinhole"))
        if model.lower() != "pinhole":  # first: kalibr's omni has 5 intrinsics ("too many values to unpack")
            raise VioError(f"{where}: camera_model '{model}' is not supported (only 'pinhole')")
        intrinsics = _need(d, "intrinsics", where)
        if not isinstance(intrinsics, (list, tuple)):  # list('foo') said "got 3 values"
            raise VioError(f"{where}: intrinsics must be a list [fx, fy, cx, cy], got {intrinsics!r:.40}")
        if len(intrinsics) != 4:
            raise VioError(f"{where}: intrinsics must be [fx, fy, cx, cy], got {len(intrinsics)} values")
        if not all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in intrinsics):
            # float() took true for a focal length of 1 px and the text "458.6" for a number (a review's finding)
            raise VioError(f"{where}: intrinsics must be four numbers [fx, fy, cx, cy], got {intrinsics!r:.80}")
        fx, fy, cx, cy = (float(x) for x in intrinsics)
        res = list(_need(d, "resolution", where))
        if len(res) != 2 or not all(isinstance(x, int) and not isinstance(x, bool) or
                                    isinstance(x, float) and x.is_integer() for x in res):
            # int() truncated [320.5, 200] to 320: a size the images may not have, said nowhere
            raise VioError(f"{where}: resolution must be two whole numbers [width, height] in pixels, got {res}")
        w, h = (int(x) for x in res)
        if "T_body_cam" in d and "T_cam_imu" in d:
            raise VioError(f"{where}: both T_body_cam and T_cam_imu given (one is the other's inverse): keep one")
        key = "T_body_cam" if "T_body_cam" in d else "T_cam_imu"
        if key not in d:
            raise VioError(f"{where}: missing key 'T_body_cam' (or kalibr's 'T_cam_imu')")
        T = np.asarray(d[key], dtype=float).reshape(4, 4)
        if not (np.isfinite(T).all() and is_se3(T, tol=1e-4)):
            raise VioError(f"{where}: {key} is not a rigid transform (rotation not orthonormal, last row not 0 0 0 1, "
                           "or not finite)")
        T = T if key == "T_body_cam" else inv_T(T)
        return CameraCalibration(
            fx=fx, fy=fy, cx=cx, cy=cy, width=w, height=h,
            distortion_model=str(d.get("distortion_model", "radtan")),
            distortion=tuple(float(x) for x in (d.get("distortion_coeffs", []) if str(d.get("distortion_model"))
                                                == "none" else _need(d, "distortion_coeffs", where))),
            T_body_cam=T, rate_hz=float(d.get("rate_hz", 20.0)),
        )
    except VioError as e:
        if str(e).startswith(where):
            raise
        raise VioError(f"{where}: {e}") from None
    except (TypeError, ValueError) as e:
        raise VioError(f"{where}: malformed value ({e})") from None


def calibration_to_dict(calib: StereoCalibration) -> dict:
    imu = calib.imu
    return {
        "cam0": _camera_to_dict(calib.cam0),
        "cam1": _camera_to_dict(calib.cam1),
        "imu": {
            "gyroscope_noise_density": imu.gyroscope_noise_density,
            "gyroscope_random_walk": imu.gyroscope_random_walk,
            "accelerometer_noise_density": imu.accelerometer_noise_density,
            "accelerometer_random_walk": imu.accelerometer_random_walk,
            "update_rate": imu.rate_hz,
        },
        "time_offset_ns": int(calib.time_offset_ns),
    }


# another tool's calibration file, told by keys only it has -> what converts it (`vio calib import`)
FOREIGN_CALIBRATIONS = (
    (("sensor_type", "T_BS"), "a EuRoC sensor.yaml (one sensor of a dataset)",
     "vio calib import euroc DATASET -o OUT.yaml"),
    (("cameraData", "batchName", "boardName"), "a depthai (OAK) calibration",
     "vio calib import depthai FILE.json --size WxH -o OUT.yaml"),
    (("K1", "D1", "M1", "image_width", "imageSize"), "an OpenCV stereo calibration",
     "vio calib import opencv FILE.yaml -o OUT.yaml"),
    (("accelerometer_noise_density", "gyroscope_noise_density", "imu0"), "a Kalibr imu.yaml",
     "vio calib import kalibr CAMCHAIN.yaml IMU.yaml -o OUT.yaml"),
)


def calibration_from_dict(d: dict, where: str = "calibration") -> StereoCalibration:
    if not isinstance(d, dict):
        raise VioError(f"{where}: expected a mapping with cam0, cam1, imu")
    if "cam0" not in d:  # a first-time user's other file: "unknown key 'sensor_type'" said not what to do
        for keys, what, command in FOREIGN_CALIBRATIONS:
            if any(k in d for k in keys):
                raise VioError(f"{where}: {what}, not a Kestrel calibration file: convert it with `{command}`")
        if d and set(d) <= {"time_offset_ns"}:  # "missing key 'cam0'" said not where the calibration is
            raise VioError(f"{where}: a recording's kestrel.yaml (its time offset only), not a calibration: the "
                           "recording's calibration is in its sensor.yaml files (`vio calib import euroc DATASET -o "
                           "OUT.yaml`; `vio calib check - DATASET` reads them as they are)")
    refuse_unknown_keys(d, CALIBRATION_KEYS, where)
    cam0 = camera_from_dict(_need(d, "cam0", where), f"{where}: cam0")
    cam1 = camera_from_dict(_need(d, "cam1", where), f"{where}: cam1")
    imu_d = _need(d, "imu", where)  # without it the defaults flew as this IMU's noise, unsaid
    if not isinstance(imu_d, dict):
        raise VioError(f"{where}: imu: expected a mapping of the IMU's noise")
    refuse_unknown_keys(imu_d, IMU_KEYS, f"{where}: imu")
    try:
        imu = ImuNoise(
            gyroscope_noise_density=float(imu_d.get("gyroscope_noise_density", ImuNoise.gyroscope_noise_density)),
            gyroscope_random_walk=float(imu_d.get("gyroscope_random_walk", ImuNoise.gyroscope_random_walk)),
            accelerometer_noise_density=float(
                imu_d.get("accelerometer_noise_density", ImuNoise.accelerometer_noise_density)),
            accelerometer_random_walk=float(
                imu_d.get("accelerometer_random_walk", ImuNoise.accelerometer_random_walk)),
            rate_hz=float(imu_d.get("update_rate", imu_d.get("rate_hz", ImuNoise.rate_hz))),
        )
    except VioError as e:
        raise VioError(f"{where}: imu: {e}") from None
    except (TypeError, ValueError) as e:
        raise VioError(f"{where}: imu: malformed value ({e})") from None
    return StereoCalibration(cam0=cam0, cam1=cam1, imu=imu,
                             time_offset_ns=time_offset_ns_from(d.get("time_offset_ns", 0), where))


def time_offset_ns_from(off: object, where: str) -> int:
    """A file's time_offset_ns as whole nanoseconds (VioError otherwise): int() of 0.005, meant as seconds, was 0,
    unsaid (a review's finding)."""
    if isinstance(off, bool) or not isinstance(off, (int, float)) or off != off or \
            (isinstance(off, float) and not off.is_integer()):
        hint = f"; {off!r} s would be {round(off * 1e9)}" if isinstance(off, float) and off == off else ""
        raise VioError(f"{where}: time_offset_ns = {off!r}: whole nanoseconds (t_imu = t_cam + time_offset_ns)"
                       f"{hint}")
    if not -(2**63) < off < 2**63:  # added to int64 stamps: an OverflowError ("internal error", a review's finding)
        raise VioError(f"{where}: time_offset_ns = {off!r} is beyond int64 nanoseconds (a camera-IMU offset is "
                       f"milliseconds: {MAX_TIME_OFFSET_S * 1e3:.0f} ms at most)")
    return int(off)


class _DuplicateKey(yaml.YAMLError):
    """A mapping gives one key twice."""


class _Loader(yaml.SafeLoader):
    """PyYAML's safe loader with YAML 1.2's floats: under YAML 1.1 `5e6` and `-52e5` (no dot) are text, and
    `time_offset_ns: 5e6` was refused as "'5e6': whole nanoseconds". Quoted scalars stay text. A key given twice in
    one mapping is refused: PyYAML kept the last, unsaid (a camchain edited by hand, `intrinsics:` added below the
    old line)."""

    def construct_mapping(self, node: yaml.MappingNode, deep: bool = False) -> dict:
        seen: dict[object, int] = {}
        for key_node, _ in node.value:
            if not isinstance(key_node, yaml.ScalarNode) or key_node.tag == "tag:yaml.org,2002:merge":
                continue  # merge keys (<<) override by design; other key kinds: the constructor's own checks
            key = self.construct_object(key_node)
            line = key_node.start_mark.line + 1
            if key in seen:
                raise _DuplicateKey(f"key {key!r} given twice (lines {seen[key]} and {line})")
            seen[key] = line
        return super().construct_mapping(node, deep)


_Loader.add_implicit_resolver(
    "tag:yaml.org,2002:float",
    re.compile(r"^[-+]?(?:[0-9][0-9_]*)[eE][-+]?[0-9]+$"),
    list("-+0123456789"))


def load_yaml(path: Path) -> dict:
    """Read YAML, tolerating OpenCV's '%YAML:1.0' first line (EuRoC, VINS) that PyYAML rejects."""
    path = Path(path)
    try:
        text = read_user_file(path, "calibration").decode("utf-8")
    except OSError as e:
        raise VioError(f"{path}: cannot read ({e.strerror})") from None
    except UnicodeDecodeError as e:
        raise VioError(f"{path}: not a text file (byte {e.start} is not UTF-8)") from None
    lines = text.splitlines()
    if lines and lines[0].startswith("%YAML:"):
        lines[0] = "#"  # a comment, not removed: the lines a message names stay the file's
    text = "\n".join(lines).replace("!!opencv-matrix", "")
    try:
        data = yaml.load(text, Loader=_Loader)  # a SafeLoader
    except _DuplicateKey as e:
        raise VioError(f"{path}: {e}") from None
    except yaml.YAMLError as e:
        raise VioError(f"{path}: not valid YAML ({e})") from None
    except RecursionError:  # lists nested thousands deep: was an internal error (a review's finding)
        raise VioError(f"{path}: not a calibration (nested too deep to be one)") from None
    if not isinstance(data, dict):
        raise VioError(f"{path}: expected a YAML mapping at top level")
    return data


def load_calibration(path: str | Path) -> StereoCalibration:
    """Load the project's calibration file (see docs/formats.md)."""
    try:
        is_folder = Path(path).is_dir()
    except OSError:  # a name over the file system's limits: load_yaml says it in one line (was an internal error)
        is_folder = False
    if is_folder:  # a dataset folder: "cannot read (Is a directory)" said not what to give instead
        raise VioError(f"{path}: is a folder, not a calibration file (a EuRoC dataset's own calibration: convert it "
                       "with `vio calib import euroc DATASET -o OUT.yaml`)")
    return calibration_from_dict(load_yaml(Path(path)), where=str(path))


def calibration_yaml(calib: StereoCalibration) -> str:
    """The project's calibration file as text."""
    return ("# Kestrel VIO calibration (T_body_cam maps camera points into the body/IMU frame;\n"
            "# t_imu = t_cam + time_offset_ns)\n" + yaml.safe_dump(calibration_to_dict(calib), sort_keys=False))


def save_calibration(calib: StereoCalibration, path: str | Path) -> None:
    from vio.io.atomic import write_text_whole

    write_text_whole(path, calibration_yaml(calib))
