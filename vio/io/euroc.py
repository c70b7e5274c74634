"""EuRoC ASL dataset reader and writer.

Layout: `<root>/mav0/{cam0,cam1}/{data.csv,data/<ts>.png,sensor.yaml}`, `imu0/{data.csv,sensor.yaml}`,
optional `state_groundtruth_estimate0/data.csv`. The reader streams frames lazily (one image pair in
memory) merged in time order with IMU samples. Structural problems (missing folders, bad csv rows, unsorted
or duplicate stamps) raise VioError naming the file and line; a missing or unreadable image, which a real
recorder can drop, is skipped with a warning and counted in `stats`.

Why one file of ~800 lines: reader, repair rules and writer share the layout constants and the csv
dialect, and a change to one (a column, a header, what counts as a cut line) must be made beside the
others; the writer is the last section and has no state shared with the reader.
"""

from __future__ import annotations

import functools
import logging
import math
import os
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from vio import VioError
from vio.calibration import (
    CameraCalibration,
    ImuNoise,
    StereoCalibration,
    calibration_units_problem,
    load_yaml,
    time_offset_ns_from,
)
from vio.config import refuse_unknown_keys
from vio.geometry import is_se3
from vio.io.atomic import set_aside, settle_aside
from vio.io.images import Uint16To8, grey
from vio.trajectory import MAX_POSITION_M, Trajectory
from vio.types import ImuSample, StereoFrame

log = logging.getLogger(__name__)

IMU_HEADER = ("#timestamp [ns],w_RS_S_x [rad s^-1],w_RS_S_y [rad s^-1],w_RS_S_z [rad s^-1],"
              "a_RS_S_x [m s^-2],a_RS_S_y [m s^-2],a_RS_S_z [m s^-2]")
CAM_HEADER = "#timestamp [ns],filename"
PAIR_TOLERANCE_NS = 1000  # a left and a right image within this of each other are one stereo frame
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
    imu_rows_skipped: dict[str, int] = field(default_factory=dict)  # reason -> rows
    notes: list[str] = field(default_factory=list)  # data repaired or skipped when the dataset was opened
    warnings: list[str] = field(default_factory=list)


@dataclass
class CsvTable:
    """A parsed EuRoC csv: integer-ns stamps, the other columns as text, and what was repaired."""

    path: Path
    stamps: np.ndarray
    rows: list[list[str]]
    lines: list[int]  # line number of each row (for messages)
    notes: list[str] = field(default_factory=list)
    last_unterminated: bool = False  # the last row has no newline after it


# plausible sample steps: IMU 1 Hz..100 kHz, camera 0.1 Hz..1 kHz
_STEP_NS = {"imu": (1e4, 1e9), "camera": (1e6, 1e10)}
_STAMP_UNITS = ((1e3, "microseconds"), (1e6, "milliseconds"), (1e9, "seconds"))


def _short(value: object, limit: int = 40) -> str:
    """repr() of a value for a message, cut to `limit` characters (a line of NUL bytes must not flood it)."""
    r = repr(value)
    return r if len(r) <= limit else r[:limit - 3] + "..."


def _stamp_text_problem(text: str) -> str:
    try:
        v = float(text)
    except ValueError:
        return f"time stamp {_short(text)} is not an integer (ns)"
    if math.isfinite(v) and 0 < v < 1e11 and ("." in text or "e" in text.lower()):
        return (f"time stamp {_short(text)} is not an integer: the stamps look like seconds, not integer nanoseconds "
                "(EuRoC stamps are ns; multiply by 1e9)")
    return f"time stamp {_short(text)} is not an integer (ns)"


def _looks_cut(parts: list[str], previous: list[list[str]]) -> bool:
    """An unterminated last row that parses but has a field shorter than that column ever is in the rows
    before it (a number cut mid-write)."""
    if not previous:
        return False
    if len(parts) < len(previous[-1]):  # fewer columns than the row before (ground truth allows 7 or 16)
        return True
    if any(len(r) != len(parts) for r in previous):
        return False
    return any(len(x) < min(len(r[k]) for r in previous) for k, x in enumerate(parts))


def _read_csv(path: Path, min_cols: int, max_cols: int | None = None, numeric: int = 0,
              finite: bool = True) -> CsvTable:
    """Parse a EuRoC csv: '#' header, integer-ns first column.

    Enforces strictly increasing stamps: reordering or a repeated stamp with other values means a broken
    file, not dropped data (an exact repeat of the previous line is dropped and noted). The first `numeric`
    columns after the stamp must be numbers (finite unless `finite` is False), checked here to name the line.
    Tolerated: CRLF, a BOM, blanks around values, trailing commas, NUL bytes at the end. A damaged last line
    (a recorder killed mid-write) is skipped and noted; damage anywhere else raises VioError with file:line.
    """
    if path.is_dir():
        raise VioError(f"{path}: is a folder, expected a csv file")
    if not path.is_file():
        raise VioError(f"{path}: file not found")
    try:
        text = path.read_bytes().decode("utf-8-sig")
    except OSError as e:
        raise VioError(f"{path}: cannot read ({e.strerror or e})") from None
    except UnicodeDecodeError as e:
        raise VioError(f"{path}: not a text file (byte {e.start} is not UTF-8)") from None
    table = CsvTable(path, np.zeros(0, np.int64), [], [])
    stripped = text.rstrip("\x00")
    if len(stripped) < len(text):
        table.notes.append(f"{path}: {len(text) - len(stripped)} NUL bytes at the end (power cut while "
                           "recording?) ignored")
        text = stripped
    lines = text.splitlines()
    data = [k for k, line in enumerate(lines) if line.strip() and not line.lstrip().startswith("#")]
    last = data[-1] if data else -1
    terminated = text.endswith(("\n", "\r"))
    stamps: list[int] = []
    rest: list[list[str]] = []
    prev_parts: list[str] | None = None
    duplicates = 0
    for k in data:
        lineno = k + 1
        parts = [x.strip() for x in lines[k].split(",")]
        while len(parts) > 1 and parts[-1] == "":
            parts.pop()
        problem = _row_problem(parts, min_cols, max_cols, numeric, finite, stamps, prev_parts)
        if problem is None and k == last and not terminated and _looks_cut(parts[1:], rest[-20:]):
            problem = ("cut", "a value is shorter than in every row before it")
        if problem == ("repeat", ""):
            duplicates += 1
            continue
        if problem is not None:
            kind, msg = problem
            if k == last and (not terminated or kind == "cut"):
                why = "no newline at the end" if not terminated else "damaged"
                table.notes.append(f"{path}:{lineno}: last line cut short ({why}: a recorder stopped mid-write?) "
                                   f"skipped: {msg}")
                break
            raise VioError(f"{path}:{lineno}: {msg}")
        stamps.append(int(parts[0]))
        rest.append(parts[1:])
        table.lines.append(lineno)
        prev_parts = parts
    if duplicates:
        table.notes.append(f"{path}: {duplicates} exact repeats of the line before dropped")
    table.stamps = np.array(stamps, dtype=np.int64)
    table.rows = rest
    table.last_unterminated = not terminated and bool(table.lines) and table.lines[-1] == last + 1
    return table


def _row_problem(parts: list[str], min_cols: int, max_cols: int | None, numeric: int, finite: bool,
                 stamps: list[int], prev_parts: list[str] | None) -> tuple[str, str] | None:
    """Why a row cannot be used, as (kind, message); kind 'cut' is what a write stopped midway leaves,
    ('repeat', '') an exact repeat of the previous row."""
    if len(parts) < min_cols or (max_cols is not None and len(parts) > max_cols):
        want = f"{min_cols}" if max_cols == min_cols else f"{min_cols}..{max_cols}" if max_cols else f"{min_cols}+"
        sep = next((f" (the file uses {c!r} as separator?)" for c in (";", "\t") if c in parts[0]), "")
        return ("cut" if len(parts) < min_cols else "columns",
                f"expected {want} comma-separated values, got {len(parts)}{sep}")
    try:
        t = int(parts[0])
    except ValueError:
        return "cut" if parts[0] == "" else "stamp", _stamp_text_problem(parts[0])
    if t <= 0:
        return "stamp", f"time stamp {t} is not positive"
    if t >= 2**63:  # was an OverflowError ("internal error") where the stamps became int64
        return "stamp", f"time stamp {_short(parts[0])} is beyond int64 nanoseconds (2^63 - 1, the year 2262)"
    if stamps and t == stamps[-1]:
        if parts == prev_parts:
            return "repeat", ""
        hint = " (the stamps look like whole seconds, not ns)" if t < 10**11 else ""
        return "stamp", f"duplicate time stamp {t} with other values than the line before{hint}"
    if stamps and t < stamps[-1]:
        # a stamp cut mid-write has fewer digits; a whole one that goes back is out of order, not cut
        kind = "cut" if len(parts[0]) < len(str(stamps[-1])) else "order"
        return kind, f"out-of-order time stamp {t} (previous {stamps[-1]})"
    for k in range(1, min(numeric, len(parts) - 1) + 1):
        try:
            ok = math.isfinite(float(parts[k])) or not finite
        except ValueError:
            return "cut", f"column {k + 1} value {_short(parts[k])} is not a number"
        if not ok:
            return "value", f"column {k + 1} value {_short(parts[k])} is not a finite number"
    return None


def _floats(table: CsvTable, ncols: int) -> np.ndarray:
    """The first ncols value columns as floats (already checked to parse)."""
    return np.array([[float(x) for x in r[:ncols]] for r in table.rows], dtype=float).reshape(-1, ncols)


def _step_problem(name: str, stamps: np.ndarray, kind: str) -> str | None:
    """The median stamp step against the rates a sensor of this kind has: names a unit mistake."""
    if len(stamps) < 3:
        return None
    dt = float(np.median(np.diff(stamps)))
    lo, hi = _STEP_NS[kind]
    if lo <= dt <= hi:
        return None
    for scale, unit in _STAMP_UNITS:
        if lo <= dt * scale <= hi:
            return (f"{name}: time stamps step by {dt:.6g} per sample: they look like {unit}, not nanoseconds "
                    "(EuRoC stamps are integer ns)")
    return f"{name}: time stamps step by {dt:.6g} ns per sample ({1e9 / dt:.3g} Hz), implausible for a {kind}"


def _gap_note(name: str, table: CsvTable, max_gap_s: float) -> str | None:
    t = table.stamps
    if len(t) < 2:
        return None
    d = np.diff(t)
    big = np.flatnonzero(d > max_gap_s * 1e9)
    if not len(big):
        return None
    k = int(big[np.argmax(d[big])])
    return (f"{name}: {len(big)} gap(s) over {max_gap_s:g} s in the time stamps, the largest {d[k] * 1e-9:.3g} s "
            f"before line {table.lines[k + 1]}")


def read_imu_csv(path: Path, notes: list[str] | None = None, skipped: dict[str, int] | None = None) -> ImuData:
    """The IMU samples. Rows with a non-finite value are dropped (counted in `skipped`, described in
    `notes`, else logged) unless they are most of the file."""
    table = _read_csv(path, 7, 7, numeric=6, finite=False)
    own = notes is None
    notes = [] if notes is None else notes
    notes.extend(table.notes)
    vals = _floats(table, 6)
    bad = ~np.all(np.isfinite(vals), axis=1)
    if bad.any():
        n_bad, first = int(bad.sum()), table.lines[int(np.argmax(bad))]
        if n_bad * 2 > len(vals):
            raise VioError(f"{path}: {n_bad} of {len(vals)} IMU rows have a non-finite value (first at line {first})")
        notes.append(f"{path}: {n_bad} of {len(vals)} IMU rows with a non-finite value skipped (first at line "
                     f"{first})")
        if skipped is not None:
            skipped["non-finite value"] = skipped.get("non-finite value", 0) + n_bad
        keep = ~bad
        vals = vals[keep]
        table.stamps = table.stamps[keep]
        table.lines = [ln for ln, ok in zip(table.lines, keep) if ok]
    if len(table.stamps) < 2:
        raise VioError(f"{path}: fewer than 2 IMU samples")
    problem = _step_problem(str(path), table.stamps, "imu")
    if problem:
        raise VioError(problem)
    gap = _gap_note(str(path), table, 0.5)
    if gap:
        notes.append(gap)
    if own:
        for n in notes:
            log.warning(n)
    return ImuData(table.stamps, vals[:, 0:3], vals[:, 3:6])


def read_groundtruth_csv(path: Path, notes: list[str] | None = None) -> GroundTruth:
    """Ground truth (pose, and velocity and biases when every row has them); repairs go to `notes`, else
    they are logged."""
    table = _read_csv(path, 8, numeric=16)
    for n in table.notes:
        if notes is None:
            log.warning(n)
        else:
            notes.append(n)
    if not table.rows:
        raise VioError(f"{path}: no ground-truth rows")
    ncols = min(len(r) for r in table.rows)
    ncols = 16 if ncols >= 16 else 7
    vals = _floats(table, ncols)
    qn = np.linalg.norm(vals[:, 3:7], axis=1)
    off = np.abs(qn - 1.0) > 0.01
    if off.any():
        k = int(np.argmax(off))
        raise VioError(f"{path}:{table.lines[k]}: quaternion q_RS has norm {qn[k]:.4g}, not 1 (columns 5-8 must be "
                       "w, x, y, z of a unit quaternion)")
    far = np.abs(vals[:, 0:3]).max(axis=1) > MAX_POSITION_M
    if far.any():
        k = int(np.argmax(far))
        raise VioError(f"{path}:{table.lines[k]}: position {' '.join(f'{v:.3g}' for v in vals[k, 0:3])} is beyond "
                       f"{MAX_POSITION_M:.0e} m (metres are expected; no place on Earth is that far)")
    traj = Trajectory(table.stamps, vals[:, 0:3], vals[:, 3:7])
    if ncols == 16:
        return GroundTruth(traj, vals[:, 7:10], vals[:, 10:13], vals[:, 13:16])
    return GroundTruth(traj)


def _yaml_numbers(d: dict, key: str, n: int | tuple[int, ...], kind=float, what: str = "") -> list:
    """d[key] as a list of n numbers; VioError naming the key otherwise (KeyError when it is missing)."""
    v = d[key]
    if isinstance(v, dict) and key == "T_BS":
        v = v.get("data")
    if not isinstance(v, (list, tuple)):
        raise VioError(f"{key}: expected a list of numbers{what}, got {_short(v)}")
    sizes = (n,) if isinstance(n, int) else n
    if len(v) not in sizes:
        raise VioError(f"{key}: expected {' or '.join(map(str, sizes))} values{what}, got {len(v)}")
    out = []
    for x in v:
        if isinstance(x, bool) or not isinstance(x, (int, float)):
            raise VioError(f"{key}: value {_short(x)} is not a number")
        if not math.isfinite(x) or (kind is int and x != int(x)):
            raise VioError(f"{key}: value {_short(x)} is not a{'n integer' if kind is int else ' finite number'}")
        out.append(kind(x))
    return out


def _yaml_T_BS(d: dict) -> np.ndarray:
    """A sensor.yaml's T_BS as a 4x4 matrix (its 16 numbers checked; rigidity is _check_rigid's)."""
    return np.array(_yaml_numbers(d, "T_BS", 16, what=" (a 4x4 matrix in data)")).reshape(4, 4)


def _check_rigid(T: np.ndarray) -> None:
    if not is_se3(T, tol=1e-4):
        raise VioError("T_BS: not a rigid transform (rotation not orthonormal, or last row not 0 0 0 1)")


def _camera_from_yaml(d: dict) -> CameraCalibration:
    T = _yaml_T_BS(d)
    fx, fy, cx, cy = _yaml_numbers(d, "intrinsics", 4, what=" [fx, fy, cx, cy]")
    w, h = _yaml_numbers(d, "resolution", 2, int, " [width, height]")
    dist = _yaml_numbers(d, "distortion_coefficients", tuple(range(1, 15)), what="") \
        if "distortion_coefficients" in d else [0.0, 0.0, 0.0, 0.0]
    rate = _yaml_numbers({"rate_hz": [d.get("rate_hz", 20)]}, "rate_hz", 1)[0]
    _check_rigid(T)
    return CameraCalibration(fx=fx, fy=fy, cx=cx, cy=cy, width=w, height=h,
                             distortion_model=str(d.get("distortion_model", "radial-tangential")),
                             distortion=tuple(dist), T_body_cam=T, rate_hz=rate)


def read_camera_yaml(path: Path) -> CameraCalibration:
    if not path.is_file():
        raise VioError(f"{path}: file not found (each camera folder needs its sensor.yaml, or give --calibration)")
    d = load_yaml(path)
    try:
        return _camera_from_yaml(d)
    except KeyError as e:
        raise VioError(f"{path}: missing key {e}") from None
    except (TypeError, ValueError) as e:
        raise VioError(f"{path}: malformed camera calibration ({e})") from None
    except VioError as e:
        raise VioError(f"{path}: {e}") from None


def read_imu_T_BS(path: Path) -> np.ndarray | None:
    """The IMU's T_BS of an imu0/sensor.yaml (None when the file has none), checked as the cameras' are: a list
    there, or a matrix of the wrong size, was an internal AttributeError / ValueError of `vio calib import euroc`."""
    d = load_yaml(path)
    if "T_BS" not in d:
        return None
    try:
        T = _yaml_T_BS(d)
        _check_rigid(T)
    except VioError as e:
        raise VioError(f"{path}: {e}") from None
    return T


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


STILL_WINDOW_S = 1.0
STILL_SPREAD = 0.1  # accel spread / |mean| below which the quietest window counts as still


def quietest_window(imu: ImuData, seconds: float = STILL_WINDOW_S) -> tuple[slice, float]:
    """The window of `seconds` whose accelerometer varies least relative to its mean (unit-free, so data in
    g or mm/s^2 pick the same window), and that relative spread. All-zero windows are taken only when the
    whole recording is zero."""
    n_all = len(imu)
    dt = float(np.median(np.diff(imu.t_ns))) if n_all > 1 else 5e6
    win = max(int(round(seconds / max(dt * 1e-9, 1e-6))), 10)
    n = n_all // win
    if n == 0:
        return slice(0, n_all), float("inf")
    acc = imu.accel[: n * win].reshape(n, win, 3)
    norm = np.linalg.norm(acc.mean(axis=1), axis=1)
    spread = np.linalg.norm(acc.std(axis=1), axis=1) / np.maximum(norm, 1e-12)
    live = norm >= 0.05
    if live.any():
        spread = np.where(live, spread, np.inf)
    i = int(np.argmin(spread))
    still = np.flatnonzero(spread < STILL_SPREAD)
    if len(still) > 1:
        # a steady turn has a steady accelerometer too (a 40 s simulated survey flight's quietest window
        # turned at 0.3 rad/s and read as a deg/s gyro): of the still-looking windows, the one turning least
        rate = np.linalg.norm(imu.gyro[: n * win].reshape(n, win, 3).mean(axis=1), axis=1)
        i = int(still[np.argmin(rate[still])])
    return slice(i * win, (i + 1) * win), float(spread[i])


def imu_units_problem(imu: ImuData, where: str | Path = "IMU") -> str | None:
    """The likely unit mistake of a whole IMU recording (vio/sanity.py's diagnosis on its quietest window
    and on all its gyro samples), or None. A window that is not still is trusted only for readings no flight
    averages (below g/2 or above 2 g)."""
    from vio.sanity import GRAVITY_M_S2, accel_units_problem, gyro_units_problem

    if len(imu) < 2:
        return None
    sl, spread = quietest_window(imu)
    still = spread < STILL_SPREAD
    n = float(np.linalg.norm(imu.accel[sl].mean(axis=0)))
    problem = accel_units_problem(n)
    if problem and not still and 0.5 * GRAVITY_M_S2 <= n <= 2 * GRAVITY_M_S2:
        problem = None
    problem = problem or gyro_units_problem(imu.gyro, still=False) or gyro_units_problem(imu.gyro[sl], still)
    return f"{where}: {problem}" if problem else None


def _imread(path: Path) -> np.ndarray | None:
    """cv2.imread(path, IMREAD_UNCHANGED), None for what is not a regular file (a pipe, a device: cv2.imread of a
    named pipe waited for a writer for ever) as for what it cannot read."""
    return cv2.imread(str(path), cv2.IMREAD_UNCHANGED) if Path(path).is_file() else None


def image_size_problem(where, img: np.ndarray, calib: CameraCalibration, hint: str) -> str | None:
    """An image of another size than its calibration's, as one line (None when they agree)."""
    h, w = img.shape[:2]
    if (w, h) == (calib.width, calib.height):
        return None
    return f"{where}: images are {w}x{h} but the calibration is for {calib.width}x{calib.height} ({hint})"


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
    inside = sorted([*p.glob("*.db3"), *p.glob("*.mcap")])
    if len(inside) > 1 and all(f.suffix == ".mcap" for f in inside):  # the daemon's record_dir: one per flight
        raise VioError(f"{p}: a folder of {len(inside)} MCAP recordings, not a dataset: give one, e.g. vio replay "
                       f"{inside[-1]}")
    if inside:  # a ROS 2 bag folder whose metadata.yaml is missing (`ros2 bag record` cut off by a power cut)
        raise VioError(f"{p}: no mav0/ folder and no metadata.yaml: a ROS 2 bag cut short? give its file alone: "
                       f"vio replay {inside[0]}")
    try:  # the daemon's record_dir in EuRoC format: one recording per start, each with its mav0/
        recordings = sorted(d for d in p.iterdir() if (d / "mav0").is_dir())
    except OSError:
        recordings = []
    if recordings:
        raise VioError(f"{p}: a folder of {len(recordings)} EuRoC recording{'s' if len(recordings) > 1 else ''}, "
                       f"not a dataset: give one, e.g. vio replay {recordings[-1]}")
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
        # 16-bit images: one scale for the whole recording, decided on images it opens with and spreads over
        self._to8 = Uint16To8(str(self.mav0), self._scale_samples, self._warn)
        for sub in ("cam0", "imu0") + (("cam1",) if require_cam1 else ()):
            if not (self.mav0 / sub).is_dir():
                raise VioError(f"{self.mav0 / sub}: folder missing (EuRoC needs mav0/cam0, cam1, imu0)")
        notes = self.stats.notes
        self.imu = read_imu_csv(self.mav0 / "imu0" / "data.csv", notes, self.stats.imu_rows_skipped)
        self.cam0_t, self.cam0_files = self._read_cam("cam0")
        self.has_cam1 = has_cam1 = (self.mav0 / "cam1").is_dir()
        self.cam1_t, self.cam1_files = self._read_cam("cam1") if has_cam1 else (np.zeros(0, np.int64), [])
        if calibration is None:
            calibration = self._read_calibration(has_cam1)
        self.calibration = calibration
        self._check_overlap()
        # a unit mistake is diagnosed on the data as recorded (mm/s^2 rows are all "out of range")
        self.units_problem = imu_units_problem(self.imu, self.mav0 / "imu0" / "data.csv") or \
            calibration_units_problem(calibration, has_cam1)
        if self.units_problem is None:
            self.imu = self._drop_out_of_range(self.imu)
        gt_path = self.mav0 / "state_groundtruth_estimate0" / "data.csv"
        self.groundtruth: GroundTruth | None = None
        self.groundtruth_problem: str | None = None  # why a ground-truth file present was not used
        if gt_path.exists():
            try:
                self.groundtruth = read_groundtruth_csv(gt_path, notes)
            except VioError as e:
                self.groundtruth_problem = str(e)
                notes.append(f"ground truth not used (no evaluation): {e}")
        for n in notes:
            log.warning(n)
        self._pair()

    # -- loading ---------------------------------------------------------------------------------------
    def _read_cam(self, cam: str) -> tuple[np.ndarray, list[Path | None]]:
        csv = self.mav0 / cam / "data.csv"
        table = _read_csv(csv, 2, 2)
        self.stats.notes.extend(table.notes)
        folder = self.mav0 / cam / "data"
        if not folder.is_dir():
            raise VioError(f"{folder}: image folder missing")
        present = set(os.listdir(folder))
        stamps, files = table.stamps, []
        for t, r in zip(stamps, table.rows):
            name = r[0]
            if name in present:
                files.append(folder / name)
            else:
                files.append(None)
                self._warn(f"{csv}: image {name} (t={t}) listed but missing; frame skipped")
                self.stats.missing_images += 1
        if table.last_unterminated and files and files[-1] is None:  # a file name cut mid-write
            self.stats.missing_images -= 1
            self.stats.warnings.pop()
            self.stats.notes.append(f"{csv}:{table.lines[-1]}: last line cut short (no newline at the end, no such "
                                    "image): skipped")
            stamps, files = stamps[:-1], files[:-1]
        problem = _step_problem(str(csv), stamps, "camera")
        if problem:
            raise VioError(problem)
        return stamps, files

    def _read_calibration(self, has_cam1: bool) -> StereoCalibration:
        cam0 = read_camera_yaml(self.mav0 / "cam0" / "sensor.yaml")
        cam1 = read_camera_yaml(self.mav0 / "cam1" / "sensor.yaml") if has_cam1 else cam0
        imu_yaml = self.mav0 / "imu0" / "sensor.yaml"
        if imu_yaml.is_file():
            imu = read_imu_yaml(imu_yaml)
        else:
            imu = ImuNoise()
            self.stats.notes.append(f"{imu_yaml}: missing; the default IMU noise (EuRoC's ADIS16448) is used")
        extra = self.mav0 / "kestrel.yaml"  # written by our writer: time offset etc.
        offset = 0
        if extra.is_file():
            d = load_yaml(extra)
            # `time_offset_ms: 5` here flew with no offset, unsaid (a QA sweep): as in the calibration file, a key
            # this reader does not know is refused, with the one it probably meant
            refuse_unknown_keys(d, ("time_offset_ns",), str(extra))
            offset = time_offset_ns_from(d.get("time_offset_ns", 0), str(extra))
        return StereoCalibration(cam0, cam1, imu, time_offset_ns=offset)

    def _check_overlap(self) -> None:
        """cam0 and IMU must share a clock: no overlap at all is a clock or unit mistake."""
        t, imu = self.cam0_t, self.imu.t_ns
        if not len(t):
            return
        t_imu = t + self.calibration.time_offset_ns
        inside = (t_imu >= imu[0]) & (t_imu <= imu[-1])
        if not inside.any():
            off = self.calibration.time_offset_ns
            if off and ((t >= imu[0]) & (t <= imu[-1])).any():
                # the stamps overlap, the offset moves them apart: "1600000000..1600000006 s and 1600000000..
                # 1600000006 s do not overlap" told the operator nothing (a QA walk-through)
                raise VioError(f"{self.mav0}: the calibration's time_offset_ns = {off} ({off * 1e-9:+.3f} s, t_imu = "
                               f"t_cam + offset) moves every cam0 stamp outside the IMU's {imu[0] * 1e-9:.3f}.."
                               f"{imu[-1] * 1e-9:.3f} s (an offset in another unit?)")
            raise VioError(f"{self.mav0}: cam0 stamps {t[0] * 1e-9:.3f}..{t[-1] * 1e-9:.3f} s and IMU stamps "
                           f"{imu[0] * 1e-9:.3f}..{imu[-1] * 1e-9:.3f} s do not overlap (different clocks, or one "
                           "stream stamped in other units?)")
        if not inside.all():
            self.stats.notes.append(f"{self.mav0}: {int((~inside).sum())} of {len(t)} camera frames lie outside the "
                                    "IMU's time span (no IMU for them)")

    def _drop_out_of_range(self, imu: ImuData) -> ImuData:
        """Samples beyond any IMU's full scale are broken samples: skipped and counted, unless most are."""
        from vio.sanity import MAX_ACCEL_M_S2, MAX_GYRO_RAD_S, imu_sample_problem

        acc = np.max(np.abs(imu.accel), axis=1) > MAX_ACCEL_M_S2
        gyr = np.max(np.abs(imu.gyro), axis=1) > MAX_GYRO_RAD_S
        bad = acc | gyr
        if not bad.any():
            return imu
        path, n = self.where("imu"), int(bad.sum())
        k = int(np.argmax(bad))
        why = imu_sample_problem(imu.gyro[k], imu.accel[k])
        if 2 * n > len(imu):
            raise VioError(f"{path}: {n} of {len(imu)} IMU samples are out of range, first at t={imu.t_ns[k]}: {why}")
        for key, mask in (("accel out of range", acc), ("gyro out of range", gyr & ~acc)):
            if mask.any():
                self.stats.imu_rows_skipped[key] = self.stats.imu_rows_skipped.get(key, 0) + int(mask.sum())
        self.stats.notes.append(f"{path}: {n} of {len(imu)} IMU samples out of range skipped (first at "
                                f"t={imu.t_ns[k]}: {why})")
        keep = ~bad
        return ImuData(imu.t_ns[keep], imu.gyro[keep], imu.accel[keep])

    def first_image_size_problem(self) -> str | None:
        """The first readable left and right images against the calibrated resolution (one line, or None)."""
        for cam, files, calib in (("cam0", self.cam0_files, self.calibration.cam0),
                                  ("cam1", self.cam1_files, self.calibration.cam1)):
            for path in [f for f in files if f is not None][:5]:
                img = _imread(path)
                if img is None:
                    continue
                problem = image_size_problem(path, img, calib, f"{cam}: wrong sensor.yaml resolution, or the "
                                             "camera streams another size")
                if problem:
                    return problem
                break
        return None

    def where(self, stream: str) -> str:
        """Where a stream ('imu', 'cam0', 'cam1') comes from, for messages."""
        return str(self.mav0 / ("imu0" if stream == "imu" else stream) / "data.csv")

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
                if 0 <= j < len(self.cam1_t) and abs(int(self.cam1_t[j]) - int(t)) <= PAIR_TOLERANCE_NS:
                    best = self.cam1_files[j]
            if best is None and len(self.cam1_t):
                self.stats.unpaired_frames += 1
            right.append(best)
        self._right_files = right
        # said, never silent: frames without a right image run without stereo depth (a bag whose right camera
        # stamps 5 ms off the left replayed as mono, 4.5x the error, with nothing in the output or the stats)
        note = None
        if len(self.cam0_t) and not len(self.cam1_t):
            note = f"{self.where('cam1')}: no right images: the replay runs on the left camera alone, no stereo depth"
        elif self.stats.unpaired_frames:
            n = self.stats.unpaired_frames
            share = f"{n} of {len(self.cam0_t)} left frames ({100 * n / len(self.cam0_t):.1f} %)"
            lone_right = self._lone_right_images()
            if len(self.cam0_t) - n >= len(self.cam1_t):  # every right image has its left one: the right dropped some
                note = (f"{self.where('cam1')}: {share} have no right image (every right image pairs with a left "
                        "one: the right camera dropped or lost frames) and run without stereo depth")
            elif lone_right is not None:  # both cameras dropped some: a lone right image is a whole frame off
                note = (f"{self.where('cam1')}: {share} have no right image and {lone_right} right images no left "
                        "one, each a frame apart from every left image (the cameras dropped or lost frames, on "
                        "both sides): those frames run without stereo depth")
            else:
                note = (f"{self.where('cam1')}: {share} have no right image within 1 us of their stamp and run "
                        "without stereo depth: are the two cameras triggered together, and stamped alike?")
        if note:
            self.stats.notes.append(note)
            log.warning("%s", note)

    def _lone_right_images(self) -> int | None:
        """How many right images pair with no left one, when each of them is far (a quarter of the frame period or
        more) from every left stamp: images the left camera dropped, the cameras triggered together. None when one
        is near a left stamp but not on it (the cameras stamp or trigger apart), or the period is unknown. The hard
        simulated flights lose left, right or both images: the note asked whether the cameras were triggered
        together for the right images whose left one was lost (a QA run)."""
        left = np.asarray(self.cam0_t, np.int64)
        right = np.asarray(self.cam1_t, np.int64)
        if len(left) < 2 or not len(right):
            return None
        period = float(np.median(np.diff(left)))
        i = np.clip(np.searchsorted(left, right), 1, len(left) - 1)
        gap = np.minimum(np.abs(right - left[i - 1]), np.abs(right - left[i]))
        lone = gap > PAIR_TOLERANCE_NS
        if period <= 0 or np.any(gap[lone] < 0.25 * period):
            return None
        return int(np.count_nonzero(lone))

    # -- streaming -------------------------------------------------------------------------------------
    def __len__(self) -> int:
        return len(self.frame_t)

    @staticmethod
    def _read_grey(path: Path) -> np.ndarray | None:
        """An image file as grey at its own depth (8 or 16 bits); None if unreadable."""
        # IMREAD_UNCHANGED skips the colour-conversion path: 2.5 vs 2.7 ms per 752x480 PNG on one core;
        # a colour file is converted afterwards as IMREAD_GRAYSCALE would
        img = _imread(path)
        return None if img is None else grey(img)

    def _scale_samples(self) -> list[np.ndarray]:
        """Left images from which a 16-bit depth is decided: the first readable one and four spread over the
        recording (a dark first frame alone gave too small a scale for the rest)."""
        files = [f for f in self.cam0_files if f is not None]
        picks = [files[round(k * (len(files) - 1) / 4)] for k in range(1, 5)] if files else []
        out = [img for img in map(self._read_grey, picks) if img is not None]
        first = next((img for img in map(self._read_grey, files[:5]) if img is not None), None)
        return out if first is None else [first, *out]

    def _load(self, path: Path | None) -> np.ndarray | None:
        if path is None:
            return None
        img = self._read_grey(path)  # None for what is not a regular file too (_imread): why, asked only then
        if img is None:
            self.stats.unreadable_images += 1
            self._warn(f"{path}: unreadable image; skipped" if Path(path).is_file()
                       else f"{path}: not a regular file (a pipe, device or folder); skipped")
            return None
        if img.dtype == np.uint16:
            img = self._to8.convert(img)
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


def png_write_params(level: int) -> list[int]:
    """cv2.imwrite parameters for a PNG at zlib `level`; 0 = stored without row filters (fastest both ways:
    a filter only helps deflate, and undoing it costs the reader as much as inflating)."""
    if level == 0:
        return [cv2.IMWRITE_PNG_COMPRESSION, 0, cv2.IMWRITE_PNG_FILTER, cv2.IMWRITE_PNG_FILTER_NONE]
    return [cv2.IMWRITE_PNG_COMPRESSION, level]


class FlushPacer:
    """When a recording writer flushes: at least every `interval_s` of sensor-data time (a source replayed or
    simulated faster than real time is paced by its data too), so a killed recorder loses at most that much. The
    EuRoC and MCAP writers share it."""

    def __init__(self, interval_s: float) -> None:
        self._interval_ns = int(interval_s * 1e9)
        self._last_t: int | None = None

    def __call__(self, t_ns: int, flush: Callable[[], None]) -> None:
        """Call `flush` if `interval_s` of data time has passed since the last flush (or the first sample)."""
        if self._last_t is None:
            self._last_t = t_ns
        elif t_ns - self._last_t >= self._interval_ns:
            flush()
            self._last_t = t_ns


REMOVED_TEXT = "the recording folder was removed"  # how a write error into a removed folder is said (storage_diagnosis)


class EurocWriter:
    """Writes a EuRoC ASL dataset incrementally (recording, simulation, tests).

    Images are lossless PNG. CSV rows are written as they come and flushed at least every
    `flush_interval_s` of data time, so a killed recorder loses at most that much; each image file is
    complete before its csv row is written, so a csv row never points at a half-written image.

    `png_level` 0 (default) writes the PNG stored: no deflate and no row filter, as EuRoC's own files are
    nearly. A 752x480 image then takes 0.3 ms to write and 0.2 ms to read on one core, against 3.0 and 2.6 ms
    at zlib level 1 with adaptive filters (OpenCV's default), for 1.9x the bytes (docs/formats.md); levels
    1-9 are zlib's, for a disk that cannot take 14 MB/s of 752x480 stereo at 20 Hz.
    """

    def __init__(self, root: str | Path, calibration: StereoCalibration, *, flush_interval_s: float = 0.5,
                 overwrite: bool = False, png_level: int = 0) -> None:
        if not 0 <= int(png_level) <= 9:
            raise VioError(f"PNG compression level must be 0-9, got {png_level}")
        self._png_params = png_write_params(int(png_level))
        self.root = Path(root)
        self.mav0 = self.root / "mav0"
        # the recording --overwrite replaces, kept beside until this one has data (`close`)
        self._replaced: Path | None = None
        if self.mav0.exists() and any(self.mav0.iterdir()):
            if not overwrite:
                raise VioError(f"{self.root}: already holds a dataset; refusing to overwrite recorded data")
            # the old recording goes whole: its images beside the new CSVs made one dataset of two (a review's). It
            # was deleted here, before any data came: a source that failed at once (a camera unplugged, a serial
            # port taken) left nothing where a recording had been (an input review's note). It is moved beside
            # (mav0.replaced, an older one there left by a killed run removed) and removed once this recording
            # closes with data, put back if it closes with none.
            self._replaced = set_aside(self.mav0)
        for sub in ("cam0/data", "cam1/data", "imu0"):
            (self.mav0 / sub).mkdir(parents=True, exist_ok=True)
        (self.mav0 / "cam0" / "sensor.yaml").write_text(_camera_yaml(calibration.cam0, "cam0"))
        (self.mav0 / "cam1" / "sensor.yaml").write_text(_camera_yaml(calibration.cam1, "cam1"))
        (self.mav0 / "imu0" / "sensor.yaml").write_text(_imu_yaml(calibration.imu))
        (self.mav0 / "kestrel.yaml").write_text(f"time_offset_ns: {int(calibration.time_offset_ns)}\n")
        self._cam = [self._open(self.mav0 / c / "data.csv", CAM_HEADER) for c in ("cam0", "cam1")]
        self._imu = self._open(self.mav0 / "imu0" / "data.csv", IMU_HEADER)
        self._gt = None
        self._flush_pacer = FlushPacer(flush_interval_s)
        self.frames_written = 0
        self.imu_written = 0

    @staticmethod
    def _open(path: Path, header: str):
        f = open(path, "w", buffering=1 << 16)
        f.write(header + "\n")
        return f

    def write_frame(self, frame: StereoFrame) -> None:
        name = f"{frame.t_ns}.png"
        for k, img in enumerate((frame.left, frame.right_image())):  # a deferred right image is decoded
            if img is None:
                continue
            cam = f"cam{k}"
            path = self.mav0 / cam / "data" / name
            if not cv2.imwrite(str(path), img, self._png_params):
                # said here: a folder removed under a recording is still being removed (its root last) when the
                # caller looks at the root (storage_diagnosis), which then found nothing to say (a flaky CI run)
                gone = "" if path.parent.is_dir() else f" ({REMOVED_TEXT})"
                raise VioError(f"{path}: cannot write image{gone}")
            self._cam[k].write(f"{frame.t_ns},{name}\n")
        self.frames_written += 1
        self._flush_pacer(frame.t_ns, self.flush)

    def write_imu(self, s: ImuSample) -> None:
        g, a = s.gyro, s.accel
        self._imu.write(f"{s.t_ns},{g[0]:.17g},{g[1]:.17g},{g[2]:.17g},{a[0]:.17g},{a[1]:.17g},{a[2]:.17g}\n")
        self.imu_written += 1
        self._flush_pacer(s.t_ns, self.flush)

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
        old, self._replaced = self._replaced, None
        # nothing recorded: the recording --overwrite was to replace is put back rather than lost for nothing
        if old is not None and settle_aside(old, self.mav0, bool(self.frames_written or self.imu_written)):
            log.warning("%s: nothing was recorded; the recording that was there is kept (--overwrite replaces it only "
                        "with data)", self.root)

    def __enter__(self) -> EurocWriter:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
