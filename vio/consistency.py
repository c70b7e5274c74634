"""Is the reported covariance honest? NEES of estimated poses against ground truth.

An autopilot weighs our pose by the covariance we send; one that is too small makes its EKF trust a
drifting pose over its own IMU. The normalised estimation error squared (NEES) e^T C^-1 e of a consistent
estimator averages the state dimension (6 for a pose), with the chi-square spread; much larger means the
covariance claims more than the estimator knows.

Errors are in the covariance's own coordinates: GTSAM's Pose3 perturbation T = T_est * Exp([dtheta; drho])
(body frame, rotation first). The estimator's world is tied to the truth's once, at the first estimate,
by yaw and position only (gravity fixes roll and pitch), so drift since then counts as error, as it does
for the autopilot.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.stats import chi2

from vio.geometry import so3_log, yaw_position_alignment
from vio.types import NavState

POSE_DOF = 6


@dataclass
class NeesResult:
    t_ns: np.ndarray  # (N,) state stamps with truth
    nees: np.ndarray  # (N,) pose NEES (6 DoF)
    nees_position: np.ndarray  # (N,) position-only NEES (3 DoF)
    nees_rotation: np.ndarray  # (N,) rotation-only NEES (3 DoF)
    sigma_position_m: np.ndarray  # (N,) reported position sigma (sqrt of the largest eigenvalue)
    error_position_m: np.ndarray  # (N,) position error norm

    @property
    def mean(self) -> float:
        return float(np.mean(self.nees)) if len(self.nees) else float("nan")

    def summary(self) -> dict:
        return {"states": int(len(self.nees)), "nees_mean": self.mean,
                "nees_position_mean": float(np.mean(self.nees_position)) if len(self.nees) else float("nan"),
                "nees_rotation_mean": float(np.mean(self.nees_rotation)) if len(self.nees) else float("nan"),
                "nees_median": float(np.median(self.nees)) if len(self.nees) else float("nan"),
                "error_position_max_m": float(np.max(self.error_position_m)) if len(self.nees) else float("nan"),
                "sigma_position_max_m": float(np.max(self.sigma_position_m)) if len(self.nees) else float("nan")}


def chi2_interval(dof: int, n_independent: int, confidence: float = 0.95) -> tuple[float, float]:
    """Interval of the mean of `n_independent` NEES samples of `dof` each (two-sided)."""
    n = max(int(n_independent), 1)
    a = (1.0 - confidence) / 2.0
    return float(chi2.ppf(a, dof * n) / n), float(chi2.ppf(1.0 - a, dof * n) / n)


def pose_nees(states: list[NavState], truth_t_ns: np.ndarray, truth_T: np.ndarray, *,
              max_dt_ns: int = 2_000_000, skip_s: float = 0.0, realign_on_reset: bool = True,
              align: np.ndarray | None = None) -> NeesResult:
    """NEES of each state's pose against truth at the same stamp (truth must be sampled at least as densely).

    `skip_s`: leave out states in the first seconds after the first one (the alignment makes the first
    errors zero by construction). States are taken in order; with `realign_on_reset` a reset (reset_counter
    change) re-aligns, as the autopilot re-anchors its reference there; without, the error across the reset
    counts (how well the reset bridge kept position and heading). `align`: a fixed T_gtworld_estworld instead
    (states in a frame tied to the truth's beforehand, e.g. a loaded map's): no state is spent on aligning."""
    truth_t_ns = np.asarray(truth_t_ns, dtype=np.int64)
    out = {k: [] for k in ("t", "n", "np", "nr", "s", "e")}
    fixed = align
    counter = None
    t_first = None
    for st in states:
        i = int(np.searchsorted(truth_t_ns, st.t_ns))
        cands = [j for j in (i - 1, i) if 0 <= j < len(truth_t_ns)]
        if not cands:
            continue
        j = min(cands, key=lambda k: abs(int(truth_t_ns[k]) - st.t_ns))
        if abs(int(truth_t_ns[j]) - st.t_ns) > max_dt_ns:
            continue
        T_gt = truth_T[j]
        if t_first is None and fixed is not None:
            t_first = st.t_ns
        if fixed is None and (align is None or (realign_on_reset and st.reset_counter != counter)):
            align = yaw_position_alignment(st.T_world_body, T_gt)  # T_gtworld_estworld
            counter = st.reset_counter
            if t_first is None:
                t_first = st.t_ns
            continue
        if (st.t_ns - t_first) * 1e-9 < skip_s:
            continue
        T_est = align @ st.T_world_body
        dR = T_est[:3, :3].T @ T_gt[:3, :3]
        e = np.concatenate([so3_log(dR), T_est[:3, :3].T @ (T_gt[:3, 3] - T_est[:3, 3])])
        C = 0.5 * (st.cov_pose + st.cov_pose.T)
        try:
            nees = float(e @ np.linalg.solve(C, e))
            nr = float(e[:3] @ np.linalg.solve(C[:3, :3], e[:3]))
            npos = float(e[3:] @ np.linalg.solve(C[3:, 3:], e[3:]))
        except np.linalg.LinAlgError:
            nees = nr = npos = float("inf")
        out["t"].append(st.t_ns)
        out["n"].append(nees)
        out["np"].append(npos)
        out["nr"].append(nr)
        out["s"].append(float(np.sqrt(max(np.linalg.eigvalsh(C[3:, 3:]).max(), 0.0))))
        out["e"].append(float(np.linalg.norm(e[3:])))
    return NeesResult(np.array(out["t"], np.int64), np.array(out["n"]), np.array(out["np"]), np.array(out["nr"]),
                      np.array(out["s"]), np.array(out["e"]))


@dataclass
class ReplayedStates:
    """Everything a covariance check needs from one replay: the states at both rates and their sources."""

    frame_states: list[NavState]
    imu_states: list[NavState]
    estimator: object  # vio.estimator.Estimator
    dataset: object  # vio.io.euroc.EurocDataset


def replay_states(path, cfg=None, imu_to_end: bool = False, calibration=None) -> ReplayedStates:
    """Replay a dataset through a fresh estimator, keeping every frame-rate and IMU-rate state.

    `imu_to_end`: feed the IMU after the last frame too (cameras that stop while the IMU runs on); by
    default the replay ends at the last frame, as `vio replay` does. `calibration`: instead of the
    dataset's. A dataset whose IMU looks like the wrong units is refused (VioError), as `vio replay` does."""
    from vio import VioError
    from vio.estimator import Estimator
    from vio.io.euroc import EurocDataset
    from vio.types import ImuSample

    ds = EurocDataset(path, calibration)
    if ds.units_problem:
        raise VioError(ds.units_problem)
    est = Estimator(ds.calibration, cfg)
    frames: list[NavState] = []
    imu: list[NavState] = []
    est.listeners.append(frames.append)
    for ev in ds.events(t_end_ns=None if imu_to_end else int(ds.frame_t[-1]), lazy_right=True):
        if isinstance(ev, ImuSample):
            st = est.feed_imu(ev)
            if st is not None:
                imu.append(st)
        else:
            est.feed_frame(ev)
    return ReplayedStates(frames, imu, est, ds)

