"""Trajectories (time stamps + poses T_world_body) and the TUM file format used by evo.

TUM lines are `t x y z qx qy qz qw` with t in seconds; inside we keep integer nanoseconds. Seconds are
written with 9 decimals so that a round trip keeps the nanoseconds exactly.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from vio import VioError
from vio.geometry import quat_wxyz_to_rot
from vio.io.inputs import read_user_file

log = logging.getLogger(__name__)


def interp_columns(tq: np.ndarray, ts: np.ndarray, values: np.ndarray) -> np.ndarray:
    """Each column of `values` (N, K), sampled at times `ts`, linearly interpolated at times `tq`: (..., K)."""
    return np.stack([np.interp(tq, ts, values[:, k]) for k in range(values.shape[1])], axis=-1)


@dataclass
class Trajectory:
    """N poses of the body in the world: t_ns (N,) int64, p (N, 3) metres, q_wxyz (N, 4) Hamilton."""

    t_ns: np.ndarray
    p: np.ndarray
    q_wxyz: np.ndarray

    def __post_init__(self) -> None:
        self.t_ns = np.asarray(self.t_ns, dtype=np.int64).reshape(-1)
        self.p = np.asarray(self.p, dtype=float).reshape(-1, 3)
        q = np.asarray(self.q_wxyz, dtype=float).reshape(-1, 4)
        n = np.linalg.norm(q, axis=1, keepdims=True)
        if len(q) and (not np.all(np.isfinite(q)) or np.any(n < 1e-9)):
            raise VioError("trajectory has an invalid (zero or non-finite) quaternion")
        self.q_wxyz = q / np.where(n > 0, n, 1.0)
        if not (len(self.t_ns) == len(self.p) == len(self.q_wxyz)):
            raise VioError("trajectory arrays differ in length")

    def __len__(self) -> int:
        return len(self.t_ns)

    @classmethod
    def from_poses(cls, t_ns: np.ndarray, T_world_body: np.ndarray) -> Trajectory:
        T = np.asarray(T_world_body, dtype=float).reshape(-1, 4, 4)
        q = Rotation.from_matrix(T[:, :3, :3]).as_quat()[:, [3, 0, 1, 2]]
        return cls(t_ns, T[:, :3, 3], q)

    @property
    def t_s(self) -> np.ndarray:
        return self.t_ns * 1e-9

    def rotations(self) -> np.ndarray:
        """(N, 3, 3) rotation matrices R_world_body."""
        return quat_wxyz_to_rot(self.q_wxyz) if len(self) else np.zeros((0, 3, 3))

    def poses(self) -> np.ndarray:
        """(N, 4, 4) transforms T_world_body."""
        T = np.tile(np.eye(4), (len(self), 1, 1))
        T[:, :3, :3] = self.rotations()
        T[:, :3, 3] = self.p
        return T

    def subset(self, idx: np.ndarray) -> Trajectory:
        return Trajectory(self.t_ns[idx], self.p[idx], self.q_wxyz[idx])

    def path_length_m(self) -> float:
        return float(np.sum(np.linalg.norm(np.diff(self.p, axis=0), axis=1))) if len(self) > 1 else 0.0

    def interpolate(self, t_ns: np.ndarray) -> Trajectory:
        """Poses at `t_ns` (linear in position, slerp in rotation); times must lie inside the span."""
        t_ns = np.asarray(t_ns, dtype=np.int64)
        if len(self) < 2:
            raise VioError("need at least two poses to interpolate")
        if t_ns.min() < self.t_ns[0] or t_ns.max() > self.t_ns[-1]:
            raise VioError("interpolation times lie outside the trajectory")
        rel = (self.t_ns - self.t_ns[0]).astype(float)
        q_rel = (t_ns - self.t_ns[0]).astype(float)
        p = interp_columns(q_rel, rel, self.p)
        slerp = Slerp(rel, Rotation.from_quat(self.q_wxyz[:, [1, 2, 3, 0]]))
        q = slerp(q_rel).as_quat()[:, [3, 0, 1, 2]]
        return Trajectory(t_ns, p, q)


def write_tum(traj: Trajectory, path: str | Path) -> None:
    """Write `t x y z qx qy qz qw` lines (t in seconds, 9 decimals)."""
    with open(path, "w") as f:
        f.write("# timestamp[s] x y z qx qy qz qw  (T_world_body)\n")
        for t, p, q in zip(traj.t_ns, traj.p, traj.q_wxyz):
            f.write(format_tum_line(int(t), p, q))


def format_tum_line(t_ns: int, p: np.ndarray, q_wxyz: np.ndarray) -> str:
    sign = "-" if t_ns < 0 else ""
    sec, ns = divmod(abs(int(t_ns)), 1_000_000_000)
    return (f"{sign}{sec}.{ns:09d} {p[0]:.6f} {p[1]:.6f} {p[2]:.6f} "
            f"{q_wxyz[1]:.9f} {q_wxyz[2]:.9f} {q_wxyz[3]:.9f} {q_wxyz[0]:.9f}\n")


def _seconds_to_ns(text: str) -> int:
    """Exact seconds->ns for decimal strings (float64 would lose ns at epoch-scale stamps); digits beyond
    the ns are rounded."""
    text = text.strip()
    if "e" in text.lower():
        v = float(text)
        if not np.isfinite(v * 1e9):  # 1e300 s is finite, its nanoseconds are not
            raise ValueError(f"not a finite time: {text!r}")
        return int(round(v * 1e9))
    neg = text.startswith("-")
    whole, _, frac = text.lstrip("+-").partition(".")
    if not (whole + frac).isdigit():
        raise ValueError(f"not a decimal number: {text!r}")
    ns = int(whole or "0") * 1_000_000_000 + int((frac + "000000000")[:9]) + (frac[9:10] >= "5")
    return -ns if neg else ns


RUN_MARKER = "# kestrel-vio run started"  # `vio run` appends each run to its trajectory file after this line


def _one_run(path: Path, runs: list[tuple[str | None, list, list, list]], run: int | None
             ) -> tuple[list, list, list]:
    """(t, p, q) of run number `run` of a file's runs (1 = the first RUN_MARKER line's, or the poses before any
    marker when there are some; every marker counts, a run that wrote no pose too, as the file shows them), by
    default the last one with poses; which one is said when the file holds more than one."""
    if not runs[0][1]:
        runs = runs[1:]  # no poses before the first marker: the runs are the markers'
    if not runs:
        return [], [], []
    if run is None and len(runs) == 1:
        return runs[0][1:]
    if run is not None and not 1 <= run <= len(runs):
        raise VioError(f"{path}: holds {len(runs)} run{'s' if len(runs) != 1 else ''}, not run {run}")
    k = run if run is not None else max((n for n, r in enumerate(runs, 1) if r[1]), default=len(runs))
    marker, t, p, q = runs[k - 1]
    which = marker[len(RUN_MARKER) - len("started"):].split(": the poses")[0] if marker else "before any marker"
    if not t:
        raise VioError(f"{path}: run {k} of {len(runs)} ({which}) holds no pose (a start that never tracked?)")
    if len(runs) > 1:
        log.warning("%s holds %d runs of `vio run`, each in its own odometry frame: run %d read (%s, %d poses)%s",
                    path, len(runs), k, which, len(t), "; --run N picks another" if run is None else "")
    return t, p, q


# A position no trajectory on Earth has (ECEF coordinates reach 6.4e6 m): beyond it a file is damaged or not in
# metres, and its squares overflowed into "ATE inf"
MAX_POSITION_M = 1e9


def read_tum(path: str | Path, run: int | None = None) -> Trajectory:
    """Read a TUM trajectory; errors name the file and line.

    A file `vio run` appended several runs to (a RUN_MARKER line before each; every run has an odometry frame of its
    own, so their poses together are no trajectory) gives one run: `run` (1 = the first), by default the last, said
    in the log when there are more."""
    path = Path(path)
    try:
        text = read_user_file(path, "trajectory", limit=None).decode("utf-8")
    except OSError as e:
        raise VioError(f"{path}: cannot read ({e.strerror})") from None
    except UnicodeDecodeError:
        raise VioError(f"{path}: not a text file") from None
    # a byte-order mark (a file saved by a Windows editor) hid the header's '#': "expected 8 values ..., got 10"
    text = text.removeprefix("\ufeff")
    lines = text.splitlines()
    t, p, q = [], [], []
    runs: list[tuple[str | None, list, list, list]] = [(None, t, p, q)]  # (its marker line, t, p, q) of each run
    for i, line in enumerate(lines, start=1):
        s = line.strip()
        if s.startswith(RUN_MARKER):
            t, p, q = [], [], []
            runs.append((s, t, p, q))
            continue
        if not s or s.startswith("#"):
            continue
        parts = s.replace(",", " ").split()
        if i == len(lines) and not text.endswith("\n"):
            # a write that stopped mid-line (a full disk, a power cut) may be cut inside a number and still parse
            # (qw 0.7071 cut to 0.: a pose turned 180 deg): a last line without its newline is left out, said
            log.warning("%s:%d: last line has no newline at the end (a write cut short?): left out, %d poses "
                        "read before it", path, i, len(t))
            break
        if len(parts) != 8:
            raise VioError(f"{path}:{i}: expected 8 values 't x y z qx qy qz qw', got {len(parts)}")
        try:
            t.append(_seconds_to_ns(parts[0]))
            vals = [float(x) for x in parts[1:]]
        except ValueError:
            raise VioError(f"{path}:{i}: not a number in {s!r}") from None
        if not -(2**63) <= t[-1] < 2**63:  # int64 nanoseconds reach the year 2262
            raise VioError(f"{path}:{i}: time stamp {parts[0]} is out of range: TUM stamps are seconds (is this "
                           "file in milliseconds or nanoseconds?)")
        if not all(map(math.isfinite, vals)):  # math, not numpy, on 7 floats: a 1M-pose file read 3x faster
            raise VioError(f"{path}:{i}: non-finite value")
        if math.hypot(*vals[3:7]) < 1e-9:
            raise VioError(f"{path}:{i}: zero quaternion")
        if math.hypot(*vals[3:7]) > 1e100:  # its square overflows: was "trajectory has an invalid quaternion", no file
            raise VioError(f"{path}:{i}: quaternion of norm {math.hypot(*vals[3:7]):.3g} (TUM's is a unit quaternion)")
        if max(map(abs, vals[0:3])) > MAX_POSITION_M:  # `vio eval` printed "ATE inf" with exit 0 (a review's note)
            raise VioError(f"{path}:{i}: position {vals[0]:.3g} {vals[1]:.3g} {vals[2]:.3g} is beyond "
                           f"{MAX_POSITION_M:.0e} m (metres are expected; no place on Earth is that far)")
        p.append(vals[0:3])
        q.append([vals[6], vals[3], vals[4], vals[5]])
        if len(t) > 1 and t[-1] <= t[-2]:
            raise VioError(f"{path}:{i}: time stamp not increasing")
    t, p, q = _one_run(path, runs, run)
    if not t:
        raise VioError(f"{path}: no poses")
    return Trajectory(np.array(t, dtype=np.int64), np.array(p), np.array(q))
