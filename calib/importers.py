"""Importers from other tools' calibration files into the project's StereoCalibration.

Each importer takes the files the tool writes, unmodified, and returns (StereoCalibration, ImportNotes):
notes list what had to be assumed (no IMU extrinsics, dropped distortion terms, ...). Conventions:
- kalibr: T_cam_imu maps IMU points into the camera (so T_body_cam = inv(T_cam_imu)); T_cn_cnm1 maps cam
  n-1 into cam n; timeshift_cam_imu is seconds with t_imu = t_cam + shift, the same as ours.
- EuRoC sensor.yaml: T_BS maps sensor points into the body.
- OpenCV stereoCalibrate: R, T map cam1 (left) points into cam2 (right): T_cam1_cam0 = [R | T].
"""

from __future__ import annotations

import logging
import math
import re
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np

from calib.depthai_import import ImportNotes, opencv_to_radtan, pinhole_from_K, stereo_from_depthai
from vio import VioError
from vio.calibration import CameraCalibration, ImuNoise, StereoCalibration, camera_from_dict, load_yaml
from vio.geometry import inv_T, is_se3, rotation_angle_deg

log = logging.getLogger(__name__)

IMU_KEYS = ("gyroscope_noise_density", "gyroscope_random_walk", "accelerometer_noise_density",
            "accelerometer_random_walk")
# T_cn_cnm1 and T_cam_imu of cam1 must agree to this (kalibr writes both from one solution).
CHAIN_TOL_M = 1e-3
CHAIN_TOL_DEG = 0.1


def _single_file(files: Sequence[Path], fmt: str, what: str) -> Path:
    """The one existing file a single-file format needs (importers are also called directly, not only
    through import_calibration, so they check for themselves)."""
    if len(files) != 1:
        raise VioError(f"{fmt}: give exactly one {what}")
    path = Path(files[0])
    if not path.is_file():
        raise VioError(f"{path}: file not found")
    return path


def _matrix(d: dict, key: str, where: str) -> np.ndarray:
    """d[key] as a rigid 4x4 transform (checked here: a bad one was first compared with the others, which warned
    of a '110 mm' disagreement before the real error, a QA sweep's finding)."""
    try:
        T = np.asarray(d[key], dtype=float).reshape(4, 4)
    except KeyError:
        raise VioError(f"{where}: missing key '{key}'") from None
    except (TypeError, ValueError):
        raise VioError(f"{where}: key '{key}' is not a 4x4 matrix") from None
    if not is_se3(T, tol=1e-4):
        raise VioError(f"{where}: {key} is not a rigid transform (rotation not orthonormal, or last row not 0 0 0 1)")
    return T


# ---------------------------------------------------------------------------------------------- kalibr

def imu_noise_from_kalibr(path: Path) -> ImuNoise:
    """kalibr imu.yaml (input form, flat keys) or its results form (nested under imu0)."""
    d = load_yaml(path)
    if "imu0" in d and isinstance(d["imu0"], dict):
        d = d["imu0"]
    missing = [k for k in IMU_KEYS if k not in d]
    if missing:
        raise VioError(f"{path}: missing key '{missing[0]}' (kalibr imu.yaml needs {', '.join(IMU_KEYS)})")
    try:
        return ImuNoise(**{k: float(d[k]) for k in IMU_KEYS}, rate_hz=float(d.get("update_rate", 200.0)))
    except (TypeError, ValueError) as e:
        raise VioError(f"{path}: malformed IMU noise value ({e})") from None
    except VioError as e:
        raise VioError(f"{path}: {e}") from None


def import_kalibr(files: Sequence[Path], cam_rate_hz: float = 20.0) -> tuple[StereoCalibration, ImportNotes]:
    """kalibr camchain-imucam.yaml (or camchain.yaml) [+ imu.yaml]; the order of files does not matter."""
    notes = ImportNotes(logger=log)
    chain_path, imu_path = None, None
    for f in files:
        d = load_yaml(f)
        if "cam0" in d:
            chain_path, chain = f, d
        else:
            imu_path = f
    if chain_path is None:
        raise VioError(f"kalibr: none of {[str(f) for f in files]} has a 'cam0' entry (camchain-imucam.yaml)")
    if "cam1" not in chain:
        raise VioError(f"{chain_path}: missing key 'cam1' (a stereo camera chain is needed)")
    where0, where1 = f"{chain_path}: cam0", f"{chain_path}: cam1"
    for key, where in (("cam0", where0), ("cam1", where1)):
        if not isinstance(chain[key], dict):  # dict() of a number or a list was an internal TypeError
            raise VioError(f"{where}: expected a mapping of camera keys (T_cam_imu, intrinsics, ...), got "
                           f"{type(chain[key]).__name__} {chain[key]!r:.40}")
    c0, c1 = dict(chain["cam0"]), dict(chain["cam1"])
    more = sorted(k for k in chain if k.startswith("cam") and k not in ("cam0", "cam1"))
    if more:
        notes.add(f"{chain_path}: {', '.join(more)} left out: Kestrel uses the stereo pair cam0 / cam1")
    for c, where in ((c0, where0), (c1, where1)):
        if "T_imu_cam" in c and "T_cam_imu" not in c:  # the inverse, under another tool's name
            raise VioError(f"{where}: T_imu_cam is not a Kalibr camchain key: Kalibr writes T_cam_imu (IMU points into "
                           "the camera frame); write the inverse of this matrix as T_cam_imu")
    if "T_cam_imu" not in c0:
        notes.add(f"{where0}: no T_cam_imu (camchain.yaml without IMU); body frame set to cam0")
        c0["T_cam_imu"] = np.eye(4)
    T_cam0_imu = _matrix(c0, "T_cam_imu", where0)
    if "T_cn_cnm1" in c1:
        T_c1_c0 = _matrix(c1, "T_cn_cnm1", where1)
        if "T_cam_imu" in c1:
            derived = T_c1_c0 @ T_cam0_imu
            given = _matrix(c1, "T_cam_imu", where1)
            dT = inv_T(derived) @ given
            if np.linalg.norm(dT[:3, 3]) > CHAIN_TOL_M or rotation_angle_deg(dT[:3, :3]) > CHAIN_TOL_DEG:
                notes.add(f"{where1}: T_cam_imu and T_cn_cnm1 @ cam0.T_cam_imu disagree by "
                          f"{np.linalg.norm(dT[:3, 3]) * 1000:.2f} mm / {rotation_angle_deg(dT[:3, :3]):.3f} deg; "
                          "using T_cn_cnm1 (the stereo extrinsic is what depth depends on)")
        c1["T_cam_imu"] = T_c1_c0 @ T_cam0_imu
    elif "T_cam_imu" not in c1:
        raise VioError(f"{where1}: missing key 'T_cn_cnm1' (or 'T_cam_imu')")
    for c in (c0, c1):
        c.setdefault("rate_hz", cam_rate_hz)
        c["T_cam_imu"] = np.asarray(c["T_cam_imu"], dtype=float).tolist()
    cam0 = camera_from_dict(c0, where0, kalibr=True)
    cam1 = camera_from_dict(c1, where1, kalibr=True)
    try:
        shifts = [float(c.get("timeshift_cam_imu", 0.0)) for c in (c0, c1)]
    except (TypeError, ValueError):  # a string or a list: was an internal ValueError
        raise VioError(f"{chain_path}: timeshift_cam_imu = {[c.get('timeshift_cam_imu') for c in (c0, c1)]}: "
                       "expected a number of seconds") from None
    if not all(math.isfinite(x) for x in shifts):
        raise VioError(f"{chain_path}: timeshift_cam_imu = {shifts}: seconds, finite")
    if not all(abs(x) * 1e9 < 2**63 for x in shifts):  # 1e300 ended in an OverflowError (a review's finding)
        raise VioError(f"{chain_path}: timeshift_cam_imu = {[f'{x:g}' for x in shifts]} s is beyond int64 "
                       "nanoseconds (a camera-IMU offset is milliseconds)")
    if abs(shifts[0] - shifts[1]) > 1e-4:
        notes.add(f"{chain_path}: cam0/cam1 timeshift_cam_imu differ ({shifts[0]:.6f} vs {shifts[1]:.6f} s); "
                  "using cam0's (stereo frames are hardware-synchronised here)")
    if imu_path is not None:
        imu = imu_noise_from_kalibr(imu_path)
    else:
        imu = ImuNoise()
        notes.add("kalibr: no imu.yaml given; IMU noise set to the project defaults")
    return StereoCalibration(cam0, cam1, imu, time_offset_ns=int(round(shifts[0] * 1e9))), notes


# ----------------------------------------------------------------------------------------------- EuRoC

def import_euroc(files: Sequence[Path], cam_rate_hz: float = 20.0) -> tuple[StereoCalibration, ImportNotes]:
    """A EuRoC dataset folder, or its cam0, cam1 [, imu0] sensor.yaml files in that order."""
    from vio.io.euroc import find_mav0, read_camera_yaml, read_imu_T_BS, read_imu_yaml

    notes = ImportNotes(logger=log)
    files = [Path(f) for f in files]
    if len(files) == 1 and files[0].is_dir():
        mav0 = find_mav0(files[0])
        files = [mav0 / "cam0" / "sensor.yaml", mav0 / "cam1" / "sensor.yaml", mav0 / "imu0" / "sensor.yaml"]
        files = [f for f in files if f.is_file() or "cam" in f.parent.name]
    if len(files) not in (2, 3):
        raise VioError("euroc: give the dataset folder or cam0/sensor.yaml cam1/sensor.yaml [imu0/sensor.yaml]")
    cam0, cam1 = read_camera_yaml(files[0]), read_camera_yaml(files[1])
    if len(files) == 3:
        imu = read_imu_yaml(files[2])
        T_B_imu = read_imu_T_BS(files[2])
        if T_B_imu is not None and not np.allclose(T_B_imu, np.eye(4)):
            # our body frame is the IMU: re-express camera mounts relative to it
            cam0 = cam0.with_T_body_cam(inv_T(T_B_imu) @ cam0.T_body_cam)
            cam1 = cam1.with_T_body_cam(inv_T(T_B_imu) @ cam1.T_body_cam)
            notes.add(f"{files[2]}: IMU T_BS is not identity; camera extrinsics re-expressed in the IMU frame")
    else:
        imu = ImuNoise()
        notes.add("euroc: no imu0/sensor.yaml; IMU noise set to the project defaults")
    return StereoCalibration(cam0, cam1, imu), notes


# ---------------------------------------------------------------------------------------------- OpenCV

_SIZE_KEYS = (("image_width", "image_height"), ("width", "height"))


def _fs_mat(fs, key: str, where: str, shape: tuple[int, ...] | None = None) -> np.ndarray:
    node = fs.getNode(key)
    if node.empty():
        raise VioError(f"{where}: missing key '{key}'")
    import cv2

    try:
        m = node.mat()
        if m is None:
            m = np.asarray([node.at(i).real() for i in range(node.size())]) if node.isSeq() else None
    except cv2.error:  # a mapping without rows/cols/data, a string: OpenCV's C++ assertion was an internal error
        m = None
    if m is None:
        raise VioError(f"{where}: key '{key}' is not a matrix")
    m = np.asarray(m, dtype=float)
    if shape is not None:
        if m.size != int(np.prod(shape)):
            raise VioError(f"{where}: key '{key}' has {m.size} values, expected {int(np.prod(shape))}")
        m = m.reshape(shape)
    return m


MAX_IMAGE_SIDE_PX = 100_000


def _fs_size(fs, where: str) -> tuple[int, int]:
    """The image size [w, h] of an OpenCV file, whole positive pixels (VioError otherwise): a word or a mapping
    there read as 1.8e308 through FileNode.real() and was written to the calibration as the width, exit 0."""
    import cv2

    def whole(values: list, key: str) -> tuple[int, ...]:
        if not all(isinstance(v, (int, float)) and math.isfinite(v) and v == int(v) and 0 < v <= MAX_IMAGE_SIDE_PX
                   for v in values):
            raise VioError(f"{where}: {key} must be whole numbers of pixels [width, height], got {values}")
        return tuple(int(v) for v in values)

    def number(node) -> object:
        kinds = {cv2.FileNode_MAP: "a mapping", cv2.FileNode_SEQ: "a list"}
        return node.real() if node.isInt() or node.isReal() else (node.string() or kinds.get(node.type(), "none"))

    for key in ("image_size", "imageSize", "size"):
        node = fs.getNode(key)
        if not node.empty():
            try:
                mat = node.mat() if node.isMap() else None
            except cv2.error:
                mat = None
            vals = mat.ravel().tolist() if mat is not None else \
                [number(node.at(i)) for i in range(node.size())] if node.isSeq() else [number(node)]
            if len(vals) == 2:
                return whole(vals, key)  # type: ignore[return-value]
    for kw, kh in _SIZE_KEYS:
        if not fs.getNode(kw).empty() and not fs.getNode(kh).empty():
            return whole([number(fs.getNode(kw)), number(fs.getNode(kh))], f"{kw} / {kh}")  # type: ignore
    raise VioError(f"{where}: missing image size (key 'image_size' [w, h] or 'image_width'/'image_height')")


_UNIT_TO_M = {"m": 1.0, "cm": 0.01, "mm": 0.001}


def _one_line_cv(e: Exception) -> str:
    """OpenCV's error without its source path: 'error: (-215:Assertion failed) isMap() in function ...'."""
    return str(getattr(e, "err", "") or e).strip().splitlines()[0] if str(e).strip() else type(e).__name__


def import_opencv(files: Sequence[Path], cam_rate_hz: float = 20.0,
                  translation_unit: str = "m") -> tuple[StereoCalibration, ImportNotes]:
    """OpenCV stereo YAML/XML (cv2.FileStorage) with K1 D1 K2 D2 R T and the image size.

    OpenCV files have no IMU: the body frame is cam0 (noted). T is in the unit of the calibration target,
    hence `translation_unit`; a baseline over 1 m is flagged as a likely unit mistake.
    """
    import cv2

    notes = ImportNotes(logger=log)
    path = _single_file(files, "opencv", "stereo calibration file")
    try:
        fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    except (cv2.error, SystemError) as e:  # a YAML that is not FileStorage's: SystemError from the binding
        err = e if isinstance(e, cv2.error) else e.__cause__
        # OpenCV's parser puts "FILE(LINE): what" where the function's name goes
        m = re.search(r"\((\d+)\): (.+)$", str(getattr(err, "func", "") or ""))
        why = f"line {m[1]}: {m[2]}" if m else "its parser refused it"
        raise VioError(f"{path}: not an OpenCV FileStorage file ({why}); `vio calib import opencv` reads the YAML/XML "
                       "of cv2.FileStorage with K1 D1 K2 D2 R T (a Kalibr camchain: `vio calib import kalibr`)") \
            from None
    if not fs.isOpened():
        raise VioError(f"{path}: cannot open as an OpenCV FileStorage file")
    where = str(path)
    try:
        if not fs.root().isMap():  # a YAML list or scalar: getNode's C++ assertion 'isMap()' was an internal error
            raise VioError(f"{where}: not an OpenCV stereo calibration (its top level is not a mapping of keys); `vio "
                           "calib import opencv` reads the YAML/XML of cv2.FileStorage with K1 D1 K2 D2 R T")
        K = [_fs_mat(fs, k, where, (3, 3)) for k in ("K1", "K2")]
        D = [_fs_mat(fs, k, where).ravel() for k in ("D1", "D2")]
        R = _fs_mat(fs, "R", where)
        if R.size == 3:  # Rodrigues vector
            R = cv2.Rodrigues(R.reshape(3, 1))[0]
        R = R.reshape(3, 3)
        t = _fs_mat(fs, "T", where, (3,)) * _UNIT_TO_M[translation_unit]
        w, h = _fs_size(fs, where)
        model_node = fs.getNode("distortion_model")
        model = model_node.string() if not model_node.empty() else "radtan"
    except cv2.error as e:  # a key of another shape than the reader asks of it (OpenCV asserts in C++)
        raise VioError(f"{where}: a value OpenCV cannot read as K1 D1 K2 D2 R T and the image size expect "
                       f"({_one_line_cv(e)})") from None
    finally:
        fs.release()
    # checked here, by name: "T_body_cam is not a rigid transform" named neither the file nor R / T
    if not np.all(np.isfinite(t)):
        raise VioError(f"{where}: T has a non-finite value: {t.tolist()}")
    if not (np.all(np.isfinite(R)) and is_se3(np.block([[R, np.zeros((3, 1))], [np.zeros((1, 3)), np.ones((1, 1))]]))):
        raise VioError(f"{where}: R is not a rotation matrix (orthonormal, determinant +1): {R.tolist()}")
    if np.linalg.norm(t) > 1.0:
        notes.add(f"{where}: baseline {np.linalg.norm(t):.3f} m is implausible for a drone stereo head; "
                  "was T in mm? (use --translation-unit mm)")
    T_c1_c0 = np.eye(4)
    T_c1_c0[:3, :3], T_c1_c0[:3, 3] = R, t
    notes.add(f"{where}: OpenCV stereo files have no IMU extrinsics; body frame set to cam0")
    cams = []
    for i in range(2):
        if model.lower() in ("fisheye", "equidistant"):
            dmodel, dcoef = "equidistant", tuple(D[i][:4])
        else:
            dmodel, dcoef = "radtan", opencv_to_radtan(D[i], f"{where}: D{i + 1}")
        T_body_cam = np.eye(4) if i == 0 else inv_T(T_c1_c0)
        fx, fy, cx, cy = pinhole_from_K(K[i], f"{where}: K{i + 1}")
        cams.append(CameraCalibration(fx=fx, fy=fy, cx=cx, cy=cy, width=w,
                                      height=h, distortion_model=dmodel, distortion=dcoef,
                                      T_body_cam=T_body_cam, rate_hz=cam_rate_hz))
    return StereoCalibration(cams[0], cams[1], ImuNoise()), notes


def write_opencv_stereo(calib: StereoCalibration, path: Path) -> None:
    """The inverse of import_opencv (for tools that want OpenCV's file); T in metres."""
    import cv2

    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    T = calib.T_cam1_cam0
    fs.write("image_width", calib.cam0.width)
    fs.write("image_height", calib.cam0.height)
    fs.write("K1", calib.cam0.K)
    fs.write("D1", calib.cam0.dist_coeffs.reshape(1, -1))
    fs.write("K2", calib.cam1.K)
    fs.write("D2", calib.cam1.dist_coeffs.reshape(1, -1))
    fs.write("R", T[:3, :3])
    fs.write("T", T[:3, 3].reshape(3, 1))
    if calib.cam0.distortion_model == "equidistant":
        fs.write("distortion_model", "fisheye")
    fs.release()


# --------------------------------------------------------------------------------------------- depthai

def import_depthai(files: Sequence[Path], cam_rate_hz: float = 20.0,
                   size: tuple[int, int] | None = None) -> tuple[StereoCalibration, ImportNotes]:
    """depthai calibration JSON (CalibrationHandler.eepromToJsonFile / the device's backup), read by depthai;
    `size` (w, h): the streamed resolution the intrinsics are scaled to."""
    path = _single_file(files, "depthai", "calibration JSON file")
    from calib.depthai_import import require_depthai

    dai = require_depthai()
    try:
        handler = dai.CalibrationHandler(str(path))
    except RuntimeError as e:
        raise VioError(f"{path}: depthai cannot read this calibration ({e})") from None
    notes = ImportNotes()
    # the sockets Kestrel's OAK driver streams as cam0 / cam1 (drivers/depthai_camera.py), whatever stereo pair the
    # file names: a file naming CAM_C as its stereo left imported CAM_C's intrinsics as cam0's, swapped against
    # the images the driver records (a QA sweep)
    left, right = dai.CameraBoardSocket.CAM_B, dai.CameraBoardSocket.CAM_C
    try:
        named = (handler.getStereoLeftCameraId(), handler.getStereoRightCameraId())
    except RuntimeError:
        named = (left, right)
    if named != (left, right):
        notes.add(f"{path}: its stereo pair is {named[0].name} / {named[1].name}; Kestrel's OAK driver streams "
                  f"{left.name} as cam0 and {right.name} as cam1, so those are imported")
    try:
        calib = stereo_from_depthai(handler, left, right, cam_rate_hz=cam_rate_hz, notes=notes, size=size)
    except VioError as e:
        raise VioError(f"{path}: {e}") from None
    except RuntimeError as e:  # depthai's own complaints about the file's contents (no intrinsics, ...)
        raise VioError(f"{path}: depthai cannot use this calibration ({e})") from None
    return calib, notes


IMPORTERS: dict[str, Callable[..., tuple[StereoCalibration, ImportNotes]]] = {
    "kalibr": import_kalibr,
    "euroc": import_euroc,
    "depthai": import_depthai,
    "opencv": import_opencv,
}


def import_calibration(fmt: str, files: Sequence[str | Path], **kwargs) -> tuple[StereoCalibration, ImportNotes]:
    if fmt not in IMPORTERS:
        raise VioError(f"unknown calibration format {fmt!r}; expected one of {sorted(IMPORTERS)}")
    paths = [Path(f) for f in files]
    for p in paths:
        if not p.exists():
            raise VioError(f"{p}: file not found")
    return IMPORTERS[fmt](paths, **kwargs)
