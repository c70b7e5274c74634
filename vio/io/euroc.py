"""EuRoC ASL dataset reader and writer.

Layout: `<root>/mav0/{cam0,cam1}/{data.csv,data/<ts>.png,sensor.yaml}`, `imu0/{data.csv,sensor.yaml}`,
optional `state_groundtruth_estimate0/data.csv`. The reader streams frames lazily (one image pair in
memory) merged in time order with IMU samples. Structural problems (missing folders, bad csv rows, unsorted
or duplicate stamps) raise VioError naming the file and line; a missing or unreadable image, which a real
recorder can drop, is skipped with a warning and counted in `stats`.
"""

from __future__ import annotations

import functools
import logging
import math
import os
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from vio import VioError
from vio.calibration import CameraCalibration, ImuNoise, StereoCalibration, load_yaml
from vio.trajectory import Trajectory
from vio.types import ImuSample, StereoFrame

log = logging.getLogger(__name__)

IMU_HEADER = ("#timestamp [ns],w_RS_S_x [rad s^-1],w_RS_S_y [rad s^-1],w_RS_S_z [rad s^-1],"
              "a_RS_S_x [m s^-2],a_RS_S_y [m s^-2],a_RS_S_z [m s^-2]")
CAM_HEADER = "#timestamp [ns],filename"
GT_HEADER = ("#timestamp, p_RS_R_x [m], p_RS_R_y [m], p_RS_R_z [m], q_RS_w [], q_RS_x [], q_RS_y [], "
             "q_RS_z [], v_RS_R_x [m s^-1], v_RS_R_y [m s^-1], v_RS_R_z [m s^-1], b_w_RS_S_x [rad s^-1], "
             "b_w_RS_S_y [rad s^-1], b_w_RS_S_z [rad s^-1], b_a_RS_S_x [m s^-2], b_a_RS_S_y [m s^-2], "
             "b_a_RS_S_z [m s^-2]")


@dataclass
class ImuData:
    """All IMU samples of a dataset as arrays (cheap: 200 Hz * 1 h is 50 MB)."""

    t_ns: np.ndarray
    gyro: np.ndarray
    accel: np.ndarray

    def __len__(self) -> int:
        return len(self.t_ns)

    def sample(self, i: int) -> ImuSample:
        return ImuSample(int(self.t_ns[i]), self.gyro[i].copy(), self.accel[i].copy())


@dataclass
class GroundTruth:
    """Ground-truth poses plus (when the file has them) velocity and IMU biases."""

    trajectory: Trajectory
    v_world: np.ndarray | None = None
    gyro_bias: np.ndarray | None = None
    accel_bias: np.ndarray | None = None


@dataclass
class DatasetStats:
    missing_images: int = 0
    unreadable_images: int = 0
    unpaired_frames: int = 0
    warnings: list[str] = field(default_factory=list)


def _read_csv(path: Path, min_cols: int, max_cols: int | None = None,
              numeric: int = 0) -> tuple[np.ndarray, list[list[str]]]:
    """Parse a EuRoC csv: '#' header, integer-ns first column. Returns (stamps, other columns as text).

    Enforces strictly increasing stamps: duplicates or reordering mean a broken file, not dropped data.
    The first `numeric` columns after the stamp must be finite numbers (checked here to name the line).
    """
    if not path.is_file():
        raise VioError(f"{path}: file not found")
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as e:
        raise VioError(f"{path}: cannot read ({e})") from None
    stamps: list[int] = []
    rest: list[list[str]] = []
    for lineno, line in enumerate(text.splitlines(), start=1):
        s = line.strip()
        if not s or s.startswith("#"):
            continue
        parts = [x.strip() for x in s.split(",")]
        if len(parts) < min_cols or (max_cols is not None and len(parts) > max_cols):
            want = f"{min_cols}" if max_cols == min_cols else f"{min_cols}..{max_cols or 'more'}"
            raise VioError(f"{path}:{lineno}: expected {want} comma-separated values, got {len(parts)}")
        try:
            t = int(parts[0])
        except ValueError:
            raise VioError(f"{path}:{lineno}: time stamp {parts[0]!r} is not an integer (ns)") from None
        if stamps and t <= stamps[-1]:
            what = "duplicate" if t == stamps[-1] else "out-of-order"
            raise VioError(f"{path}:{lineno}: {what} time stamp {t} (previous {stamps[-1]})")
        for k in range(1, min(numeric, len(parts) - 1) + 1):
            try:
                ok = math.isfinite(float(parts[k]))
            except ValueError:
                ok = False
            if not ok:
                raise VioError(f"{path}:{lineno}: column {k + 1} value {parts[k]!r} is not a finite number")
        stamps.append(t)
        rest.append(parts[1:])
    return np.array(stamps, dtype=np.int64), rest


def _floats(path: Path, stamps: np.ndarray, rows: list[list[str]], ncols: int, text: str) -> np.ndarray:
    try:
        arr = np.array([[float(x) for x in r[:ncols]] for r in rows], dtype=float).reshape(-1, ncols)
    except ValueError:
        # find the offending row for the message
        for i, r in enumerate(rows):
            try:
                [float(x) for x in r[:ncols]]
            except ValueError:
                raise VioError(f"{path}: row with time stamp {stamps[i]}: {text} not a number: {r}") from None
        raise
    bad = ~np.all(np.isfinite(arr), axis=1)
    if bad.any():
        raise VioError(f"{path}: row with time stamp {stamps[np.argmax(bad)]}: non-finite {text}")
    return arr


def read_imu_csv(path: Path) -> ImuData:
    stamps, rows = _read_csv(path, 7, 7, numeric=6)
    vals = _floats(path, stamps, rows, 6, "gyro/accel value")
    if len(stamps) < 2:
        raise VioError(f"{path}: fewer than 2 IMU samples")
    return ImuData(stamps, vals[:, 0:3], vals[:, 3:6])


def read_groundtruth_csv(path: Path) -> GroundTruth:
    stamps, rows = _read_csv(path, 8, numeric=16)
    ncols = min(len(r) for r in rows) if rows else 7
    ncols = 16 if ncols >= 16 else 7
    vals = _floats(path, stamps, rows, ncols, "ground-truth value")
    traj = Trajectory(stamps, vals[:, 0:3], vals[:, 3:7])
    if ncols == 16:
        return GroundTruth(traj, vals[:, 7:10], vals[:, 10:13], vals[:, 13:16])
    return GroundTruth(traj)


def read_camera_yaml(path: Path) -> CameraCalibration:
    d = load_yaml(path)
    try:
        T = np.asarray(d["T_BS"]["data"], dtype=float).reshape(4, 4)
        fx, fy, cx, cy = (float(x) for x in d["intrinsics"])
        w, h = (int(x) for x in d["resolution"])
        return CameraCalibration(
            fx=fx, fy=fy, cx=cx, cy=cy, width=w, height=h,
            distortion_model=d.get("distortion_model", "radial-tangential"),
            distortion=tuple(float(x) for x in d.get("distortion_coefficients", [0, 0, 0, 0])),
            T_body_cam=T, rate_hz=float(d.get("rate_hz", 20)),
        )
    except KeyError as e:
        raise VioError(f"{path}: missing key {e}") from None
    except (TypeError, ValueError) as e:
        raise VioError(f"{path}: malformed camera calibration ({e})") from None
    except VioError as e:
        raise VioError(f"{path}: {e}") from None


def read_imu_yaml(path: Path) -> ImuNoise:
    d = load_yaml(path)
    keys = ("gyroscope_noise_density", "gyroscope_random_walk", "accelerometer_noise_density",
            "accelerometer_random_walk")
    try:
        return ImuNoise(**{k: float(d[k]) for k in keys}, rate_hz=float(d.get("rate_hz", 200)))
    except KeyError as e:
        raise VioError(f"{path}: missing key {e}") from None
    except (TypeError, ValueError) as e:
        raise VioError(f"{path}: malformed IMU noise ({e})") from None
    except VioError as e:
        raise VioError(f"{path}: {e}") from None


def find_mav0(path: str | Path) -> Path:
    """Accept the dataset folder or its mav0 folder."""
    p = Path(path)
    if not p.exists():
        raise VioError(f"{p}: dataset folder not found")
    if not p.is_dir():
        raise VioError(f"{p}: not a folder (expected a EuRoC dataset with mav0/)")
    if (p / "mav0").is_dir():
        return p / "mav0"
    if p.name == "mav0" or (p / "imu0").is_dir():
        return p
    raise VioError(f"{p}: no mav0/ folder: not a EuRoC ASL dataset")


class EurocDataset:
    """A EuRoC ASL dataset opened for streaming.

    Everything but the images is read and checked when opened, so structural errors surface before a long
    replay starts. `calibration` comes from the sensor.yaml files unless one is given.
    """

    def __init__(self, path: str | Path, calibration: StereoCalibration | None = None,
                 require_cam1: bool = True) -> None:
        self.mav0 = find_mav0(path)
        self.root = self.mav0.parent
        self.stats = DatasetStats()
        for sub in ("cam0", "imu0") + (("cam1",) if require_cam1 else ()):
            if not (self.mav0 / sub).is_dir():
                raise VioError(f"{self.mav0 / sub}: folder missing (EuRoC needs mav0/cam0, cam1, imu0)")
        self.imu = read_imu_csv(self.mav0 / "imu0" / "data.csv")
        self.cam0_t, self.cam0_files = self._read_cam("cam0")
        has_cam1 = (self.mav0 / "cam1").is_dir()
        self.cam1_t, self.cam1_files = self._read_cam("cam1") if has_cam1 else (np.zeros(0, np.int64), [])
        if calibration is None:
            calibration = self._read_calibration(has_cam1)
        self.calibration = calibration
        gt_path = self.mav0 / "state_groundtruth_estimate0" / "data.csv"
        self.groundtruth = read_groundtruth_csv(gt_path) if gt_path.is_file() else None
        self._pair()

    # -- loading ---------------------------------------------------------------------------------------
    def _read_cam(self, cam: str) -> tuple[np.ndarray, list[Path | None]]:
        csv = self.mav0 / cam / "data.csv"
        stamps, rows = _read_csv(csv, 2, 2)
        folder = self.mav0 / cam / "data"
        if not folder.is_dir():
            raise VioError(f"{folder}: image folder missing")
        present = set(os.listdir(folder))
        files: list[Path | None] = []
        for t, r in zip(stamps, rows):
            name = r[0]
            if name in present:
                files.append(folder / name)
            else:
                files.append(None)
                self._warn(f"{csv}: image {name} (t={t}) listed but missing; frame skipped")
                self.stats.missing_images += 1
        return stamps, files

    def _read_calibration(self, has_cam1: bool) -> StereoCalibration:
        cam0 = read_camera_yaml(self.mav0 / "cam0" / "sensor.yaml")
        cam1 = read_camera_yaml(self.mav0 / "cam1" / "sensor.yaml") if has_cam1 else cam0
        imu_yaml = self.mav0 / "imu0" / "sensor.yaml"
        imu = read_imu_yaml(imu_yaml) if imu_yaml.is_file() else ImuNoise()
        extra = self.mav0 / "kestrel.yaml"  # written by our writer: time offset etc.
        offset = int(load_yaml(extra).get("time_offset_ns", 0)) if extra.is_file() else 0
        return StereoCalibration(cam0, cam1, imu, time_offset_ns=offset)

    def _warn(self, msg: str) -> None:
        self.stats.warnings.append(msg)
        if len(self.stats.warnings) <= 10:
            log.warning(msg)
        elif len(self.stats.warnings) == 11:
            log.warning("more image warnings suppressed; see the summary at the end")

    def _pair(self) -> None:
        """Pair left and right images by equal stamp (1 us tolerance); keep left-only frames."""
        self.frame_t = self.cam0_t
        idx = np.searchsorted(self.cam1_t, self.cam0_t)
        right: list[Path | None] = []
        for t, i in zip(self.cam0_t, idx):
            best = None
            for j in (i - 1, i):
                if 0 <= j < len(self.cam1_t) and abs(int(self.cam1_t[j]) - int(t)) <= 1000:
                    best = self.cam1_files[j]
            if best is None and len(self.cam1_t):
                self.stats.unpaired_frames += 1
            right.append(best)
        self._right_files = right

    # -- streaming -------------------------------------------------------------------------------------
    def __len__(self) -> int:
        return len(self.frame_t)

    def _load(self, path: Path | None) -> np.ndarray | None:
        if path is None:
            return None
        # IMREAD_UNCHANGED skips the colour-conversion path: 2.5 vs 2.7 ms per 752x480 PNG on one core;
        # a colour or 16-bit file is converted afterwards as IMREAD_GRAYSCALE would
        img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if img is None:
            self.stats.unreadable_images += 1
            self._warn(f"{path}: unreadable image; skipped")
            return None
        if img.ndim == 3:
            img = cv2.cvtColor(img, cv2.COLOR_BGRA2GRAY if img.shape[2] == 4 else cv2.COLOR_BGR2GRAY)
        if img.dtype == np.uint16:
            img = (img >> 8).astype(np.uint8)
        return img

    def frame(self, i: int, lazy_right: bool = False) -> StereoFrame | None:
        """Load frame i; None when its left image is missing or unreadable (counted in stats). `lazy_right`
        defers the right image's decoding to `frame.right_image()` (a missing one: no loader)."""
        left = self._load(self.cam0_files[i])
        if left is None:
            return None
        path = self._right_files[i]
        if not lazy_right:
            return StereoFrame(int(self.frame_t[i]), left, self._load(path), seq=i)
        return StereoFrame(int(self.frame_t[i]), left, None, seq=i,
                           load_right=None if path is None else functools.partial(self._load, path))

    def frames(self, start: int = 0, stop: int | None = None) -> Iterator[StereoFrame]:
        for i in range(start, len(self) if stop is None else min(stop, len(self))):
            f = self.frame(i)
            if f is not None:
                yield f

    def events(self, t_start_ns: int | None = None, t_end_ns: int | None = None,
               lazy_right: bool = False) -> Iterator[ImuSample | StereoFrame]:
        """IMU samples and stereo frames merged in time order (IMU first on equal stamps, so the
        estimator already has the IMU up to the frame time). Frame stamps are on the camera clock; the
        estimator applies the calibration's time offset.

        `lazy_right`: right images are decoded only when `frame.right_image()` asks for them. PNG decoding
        is the largest single cost of a replay, and the front end uses the right image of few frames."""
        imu_t = self.imu.t_ns
        lo = 0 if t_start_ns is None else int(np.searchsorted(imu_t, t_start_ns))
        hi = len(imu_t) if t_end_ns is None else int(np.searchsorted(imu_t, t_end_ns, side="right"))
        # Python ints and one bulk copy: one numpy scalar compare and two array copies per
        # sample were a visible share of a replay (12 000 samples per minute)
        ts = imu_t[lo:hi].tolist()
        gyro = self.imu.gyro[lo:hi].copy()  # rows handed out are views of this private copy
        accel = self.imu.accel[lo:hi].copy()
        i, n = 0, hi - lo
        for k, t in enumerate(self.frame_t.tolist()):
            if (t_start_ns is not None and t < t_start_ns) or (t_end_ns is not None and t > t_end_ns):
                continue
            while i < n and ts[i] <= t:
                yield ImuSample(ts[i], gyro[i], accel[i])
                i += 1
            f = self.frame(k, lazy_right)
            if f is not None:
                yield f
        while i < n:
            yield ImuSample(ts[i], gyro[i], accel[i])
            i += 1


# ------------------------------------------------------------------------------------------------ writer

def _camera_yaml(cam: CameraCalibration, name: str) -> str:
    T = cam.T_body_cam
    rows = ",\n         ".join(", ".join(f"{v:.12g}" for v in T[r]) for r in range(4))
    model = {"radtan": "radial-tangential", "equidistant": "equidistant", "none": "radial-tangential"}
    dist = list(cam.distortion) if cam.distortion_model != "none" else [0.0, 0.0, 0.0, 0.0]
    return (
        "%YAML:1.0\n"
        "sensor_type: camera\n"
        f"comment: {name}\n"
        "T_BS:\n  cols: 4\n  rows: 4\n"
        f"  data: [{rows}]\n"
        f"rate_hz: {cam.rate_hz:g}\n"
        f"resolution: [{cam.width}, {cam.height}]\n"
        "camera_model: pinhole\n"
        f"intrinsics: [{cam.fx:.12g}, {cam.fy:.12g}, {cam.cx:.12g}, {cam.cy:.12g}]\n"
        f"distortion_model: {model[cam.distortion_model]}\n"
        f"distortion_coefficients: [{', '.join(f'{d:.12g}' for d in dist)}]\n"
    )


def _imu_yaml(imu: ImuNoise) -> str:
    return (
        "%YAML:1.0\n"
        "sensor_type: imu\n"
        "comment: IMU\n"
        "T_BS:\n  cols: 4\n  rows: 4\n"
        "  data: [1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0]\n"
        f"rate_hz: {imu.rate_hz:g}\n"
        f"gyroscope_noise_density: {imu.gyroscope_noise_density:.6g}\n"
        f"gyroscope_random_walk: {imu.gyroscope_random_walk:.6g}\n"
        f"accelerometer_noise_density: {imu.accelerometer_noise_density:.6g}\n"
        f"accelerometer_random_walk: {imu.accelerometer_random_walk:.6g}\n"
    )


class EurocWriter:
    """Writes a EuRoC ASL dataset incrementally (recording, simulation, tests).

    Images are lossless PNG. CSV rows are written as they come and flushed at least every
    `flush_interval_s` of data time, so a killed recorder loses at most that much; each image file is
    complete before its csv row is written, so a csv row never points at a half-written image.
    """

    def __init__(self, root: str | Path, calibration: StereoCalibration, *, flush_interval_s: float = 0.5,
                 overwrite: bool = False) -> None:
        self.root = Path(root)
        self.mav0 = self.root / "mav0"
        if self.mav0.exists() and any(self.mav0.iterdir()) and not overwrite:
            raise VioError(f"{self.root}: already holds a dataset; refusing to overwrite recorded data")
        for sub in ("cam0/data", "cam1/data", "imu0"):
            (self.mav0 / sub).mkdir(parents=True, exist_ok=True)
        (self.mav0 / "cam0" / "sensor.yaml").write_text(_camera_yaml(calibration.cam0, "cam0"))
        (self.mav0 / "cam1" / "sensor.yaml").write_text(_camera_yaml(calibration.cam1, "cam1"))
        (self.mav0 / "imu0" / "sensor.yaml").write_text(_imu_yaml(calibration.imu))
        (self.mav0 / "kestrel.yaml").write_text(f"time_offset_ns: {int(calibration.time_offset_ns)}\n")
        self._cam = [self._open(self.mav0 / c / "data.csv", CAM_HEADER) for c in ("cam0", "cam1")]
        self._imu = self._open(self.mav0 / "imu0" / "data.csv", IMU_HEADER)
        self._gt = None
        self._flush_ns = int(flush_interval_s * 1e9)
        self._last_flush_t: int | None = None
        self.frames_written = 0
        self.imu_written = 0

    @staticmethod
    def _open(path: Path, header: str):
        f = open(path, "w", buffering=1 << 16)
        f.write(header + "\n")
        return f

    def _maybe_flush(self, t_ns: int) -> None:
        if self._last_flush_t is None:
            self._last_flush_t = t_ns
        elif t_ns - self._last_flush_t >= self._flush_ns:
            self.flush()
            self._last_flush_t = t_ns

    def write_frame(self, frame: StereoFrame) -> None:
        name = f"{frame.t_ns}.png"
        for k, img in enumerate((frame.left, frame.right_image())):  # a deferred right image is decoded
            if img is None:
                continue
            cam = f"cam{k}"
            path = self.mav0 / cam / "data" / name
            if not cv2.imwrite(str(path), img):
                raise VioError(f"{path}: cannot write image")
            self._cam[k].write(f"{frame.t_ns},{name}\n")
        self.frames_written += 1
        self._maybe_flush(frame.t_ns)

    def write_imu(self, s: ImuSample) -> None:
        g, a = s.gyro, s.accel
        self._imu.write(f"{s.t_ns},{g[0]:.17g},{g[1]:.17g},{g[2]:.17g},{a[0]:.17g},{a[1]:.17g},{a[2]:.17g}\n")
        self.imu_written += 1
        self._maybe_flush(s.t_ns)

    def write_groundtruth(self, t_ns: int, p: np.ndarray, q_wxyz: np.ndarray, v: np.ndarray,
                          gyro_bias: np.ndarray, accel_bias: np.ndarray) -> None:
        if self._gt is None:
            (self.mav0 / "state_groundtruth_estimate0").mkdir(exist_ok=True)
            self._gt = self._open(self.mav0 / "state_groundtruth_estimate0" / "data.csv", GT_HEADER)
        vals = np.concatenate([p, q_wxyz, v, gyro_bias, accel_bias])
        self._gt.write(f"{int(t_ns)}," + ",".join(f"{x:.12g}" for x in vals) + "\n")

    def flush(self) -> None:
        for f in (*self._cam, self._imu, self._gt):
            if f is not None:
                f.flush()
                os.fsync(f.fileno())

    def close(self) -> None:
        self.flush()
        for f in (*self._cam, self._imu, self._gt):
            if f is not None:
                f.close()

    def __enter__(self) -> EurocWriter:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
