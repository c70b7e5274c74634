"""`vio eval`: compare an estimated trajectory with ground truth.

Metrics (definitions in docs/evaluation.md): absolute trajectory error (ATE) after SE(3) and after 4-DoF
(yaw + translation) alignment, relative pose error (RPE) as drift in % of distance travelled over segments
of fixed GT path length, rotation drift in deg/m, and coverage of the GT time span. numpy only, so the
estimator and benchmark code can call `evaluate()` without pulling in evo.
"""

from __future__ import annotations

import argparse
import json
import logging
import math
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from vio import VioError
from vio.argtypes import path_arg, positive_float, positive_float_up_to, positive_int
from vio.geometry import closest_yaw, inv_T, make_T, quat_wxyz_to_rot
from vio.trajectory import Trajectory, read_tum

log = logging.getLogger(__name__)

DEFAULT_RPE_LENGTHS_M: tuple[float, ...] = (1.0, 2.0, 5.0, 10.0, 20.0, 50.0)
DEFAULT_MAX_DT_MS = 20.0
DEFAULT_MAX_GAP_S = 0.5


# ------------------------------------------------------------------------------------------------ results

@dataclass
class ErrorStats:
    """Summary of a set of non-negative errors."""

    rmse: float
    mean: float
    median: float
    std: float
    max: float

    @classmethod
    def of(cls, e: np.ndarray) -> ErrorStats:
        e = np.asarray(e, dtype=float)
        if len(e) == 0:
            return cls(*(math.nan,) * 5)
        return cls(float(np.sqrt(np.mean(e ** 2))), float(np.mean(e)), float(np.median(e)), float(np.std(e)),
                   float(np.max(e)))


@dataclass
class AteResult:
    """Absolute errors after one alignment. `T_gtworld_estworld` maps estimated positions into the GT world."""

    alignment: str
    T_gtworld_estworld: np.ndarray
    trans_m: ErrorStats
    rot_deg: ErrorStats
    errors_m: np.ndarray = field(repr=False)  # (M,) per matched pose
    rotation_from: str = "positions"  # "orientations" when the path was too small to fix the rotation


@dataclass
class RpeSegment:
    """Drift over all GT segments of one path length (starting at every matched pose)."""

    length_m: float
    n_pairs: int
    trans_pct: float  # mean translation error in % of segment length
    trans_pct_median: float
    rot_deg_per_m: float  # mean rotation error per metre of segment


@dataclass
class EvalResult:
    n_est: int
    n_gt: int
    n_matched: int
    max_dt_ms: float
    interpolated: bool
    gt_span_s: float
    coverage: float  # share of the GT time span covered by matched estimates (0..1)
    longest_gap_s: float
    path_length_m: float  # GT path length over the matched poses
    ate_4dof: AteResult
    ate_se3: AteResult
    rpe: list[RpeSegment]
    rpe_trans_pct: float  # mean of the per-length means (NaN when the path is shorter than every length)
    rpe_rot_deg_per_m: float
    t_ns: np.ndarray = field(repr=False)  # (M,) matched estimate stamps
    p_gt: np.ndarray = field(repr=False)  # (M, 3) GT positions at t_ns
    p_est: np.ndarray = field(repr=False)  # (M, 3) estimated positions, unaligned
    quaternion_order: str = ""  # said when one file's orientations agree only if its quaternions are read w-first

    def to_dict(self) -> dict:
        """All summary numbers (per-pose arrays left out) as JSON-ready values."""
        d = asdict(self)
        for k in ("t_ns", "p_gt", "p_est"):
            d.pop(k)
        for a in ("ate_4dof", "ate_se3"):
            d[a].pop("errors_m")
            d[a]["T_gtworld_estworld"] = np.asarray(d[a]["T_gtworld_estworld"]).tolist()
        return _json_safe(d)

    @property
    def partial(self) -> str:
        """Said when most of the estimate has no ground truth: the figures then describe a part of the flight (a
        ground truth cut to its last 0.2 s gave an ATE over 5 of 192 poses, read as a perfect score)."""
        if self.n_matched >= 0.5 * self.n_est:
            return ""
        return (f"only {self.n_matched} of the {self.n_est} estimated poses have ground truth: the figures describe "
                f"{100 * self.n_matched / max(self.n_est, 1):.0f} % of the estimate")

    def summary(self) -> str:
        lines = [
            f"poses: {self.n_est} estimated, {self.n_gt} ground truth, {self.n_matched} matched "
            f"({'interpolated GT' if self.interpolated else 'nearest GT'} within {self.max_dt_ms:g} ms)",
            f"coverage: {100 * self.coverage:.1f} % of the {self.gt_span_s:.2f} s ground-truth span; "
            f"longest gap {self.longest_gap_s:.2f} s",
            f"path length (GT, matched poses): {self.path_length_m:.2f} m",
        ]
        if self.partial:
            lines.append(f"WARNING: {self.partial}")
        if self.quaternion_order:
            lines.append(f"WARNING: {self.quaternion_order}")
        for a in (self.ate_4dof, self.ate_se3):
            s = a.trans_m
            lines.append(f"ATE {a.alignment:<5} rmse {s.rmse:.4f} m  mean {s.mean:.4f}  median {s.median:.4f}  "
                         f"max {s.max:.4f}  | rot rmse {a.rot_deg.rmse:.3f} deg"
                         + ("  (path too small: rotation aligned on orientations)"
                            if a.rotation_from == "orientations" else ""))
        for r in self.rpe:
            lines.append(f"RPE {r.length_m:>5g} m: {r.trans_pct:6.2f} % (median {r.trans_pct_median:.2f})  "
                         f"{r.rot_deg_per_m:.4f} deg/m  ({r.n_pairs} segments)")
        if self.rpe:
            lines.append(f"RPE mean over lengths: {self.rpe_trans_pct:.2f} %  {self.rpe_rot_deg_per_m:.4f} deg/m")
        else:
            lines.append("RPE: path shorter than every segment length")
        return "\n".join(lines)


def _json_safe(x):
    """NaN/inf are not JSON; write them as null."""
    if isinstance(x, dict):
        return {k: _json_safe(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_json_safe(v) for v in x]
    if isinstance(x, (float, np.floating)):
        return float(x) if math.isfinite(x) else None
    if isinstance(x, np.integer):
        return int(x)
    return x


# ------------------------------------------------------------------------------------------------ loading

def load_trajectory(path: str | Path, run: int | None = None) -> Trajectory:
    """A TUM file, a EuRoC ground-truth csv, or a EuRoC dataset folder (its state_groundtruth_estimate0).

    A csv whose first data row starts with an integer stamp and has 8+ comma-separated values is EuRoC
    (ns, p, q_wxyz); anything else is read as TUM (seconds, p, q_xyzw): of a file `vio run` appended several runs
    to, run number `run` (default: the last; `read_tum`).
    """
    from vio.io.euroc import find_mav0, read_groundtruth_csv
    from vio.io.inputs import refuse_device

    path = Path(path)
    if not path.exists():
        raise VioError(f"{path}: file not found")
    if path.is_dir():
        return read_groundtruth_csv(find_mav0(path) / "state_groundtruth_estimate0" / "data.csv").trajectory
    refuse_device(path, "trajectory")  # /dev/zero was read for ever looking for its first line
    if _looks_like_euroc_csv(path):
        return read_groundtruth_csv(path).trajectory
    return read_tum(path, run)


def _looks_like_euroc_csv(path: Path) -> bool:
    try:
        with open(path, errors="replace") as f:
            for line in f:
                s = line.strip().lstrip("\ufeff")  # a BOM before EuRoC's '#timestamp' header: read as TUM, refused
                if s and not s.startswith("#"):
                    parts = s.split(",")
                    return len(parts) >= 8 and parts[0].strip().isdigit()
    except OSError as e:
        raise VioError(f"{path}: cannot read ({e.strerror})") from None
    return False


# ------------------------------------------------------------------------------------------------ association

def associate(est: Trajectory, gt: Trajectory, max_dt_ns: int,
              interpolate: bool = False) -> tuple[np.ndarray, Trajectory]:
    """Indices of the estimates that have a GT stamp within `max_dt_ns`, and the GT poses for them.

    With `interpolate` the GT pose is interpolated at the estimate's own stamp (same matched set), which
    removes the up to max_dt timing error of the nearest-stamp pairing.
    """
    if len(est) == 0 or len(gt) == 0:
        return np.zeros(0, np.int64), gt.subset(np.zeros(0, np.int64))
    j = np.searchsorted(gt.t_ns, est.t_ns)
    lo = np.clip(j - 1, 0, len(gt) - 1)
    hi = np.clip(j, 0, len(gt) - 1)
    d_lo = np.abs(est.t_ns - gt.t_ns[lo])
    d_hi = np.abs(gt.t_ns[hi] - est.t_ns)
    nearest = np.where(d_hi < d_lo, hi, lo)
    ok = np.minimum(d_lo, d_hi) <= max_dt_ns
    idx = np.flatnonzero(ok)
    if interpolate and len(gt) >= 2:
        inside = (est.t_ns[idx] >= gt.t_ns[0]) & (est.t_ns[idx] <= gt.t_ns[-1])
        idx = idx[inside]
        return idx, gt.interpolate(est.t_ns[idx]) if len(idx) else gt.subset(np.zeros(0, np.int64))
    return idx, gt.subset(nearest[idx])


# ------------------------------------------------------------------------------------------------ alignment

MIN_ALIGN_SPREAD_M = 0.05  # positions spread less than this (RMS) along an axis do not fix a rotation about it


def _project_so3(M: np.ndarray) -> np.ndarray:
    U, _, Vt = np.linalg.svd(M)
    return U @ np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt)) or 1.0]) @ Vt


def _spread_m(p: np.ndarray) -> np.ndarray:
    """RMS extent of the positions along their principal axes, largest first."""
    return np.linalg.svd(p - p.mean(axis=0), compute_uv=False) / math.sqrt(len(p))


def _mean_R_gt_est(R_est: np.ndarray, R_gt: np.ndarray) -> np.ndarray:
    """Chordal mean of R_gt_i R_est_i^T: the world rotation the orientations agree on."""
    return _project_so3(np.sum(R_gt @ np.swapaxes(R_est, 1, 2), axis=0))


def se3_rotation_undetermined(p_gt: np.ndarray) -> bool:
    """A path that spans less than MIN_ALIGN_SPREAD_M in two directions (hovering, a straight line) leaves
    a position fit's rotation undetermined, so a rotation error after it would be noise."""
    return bool(_spread_m(p_gt)[1] < MIN_ALIGN_SPREAD_M)


def yaw_undetermined(p_gt: np.ndarray) -> bool:
    """Less than MIN_ALIGN_SPREAD_M of horizontal spread does not fix a position fit's yaw."""
    return bool(_spread_m(p_gt[:, :2])[0] < MIN_ALIGN_SPREAD_M)


def align_se3(p_est: np.ndarray, p_gt: np.ndarray, R_est: np.ndarray | None = None,
              R_gt: np.ndarray | None = None) -> np.ndarray:
    """Rigid T (4x4) minimising sum |p_gt - T p_est|^2 (Umeyama 1991 without scale).

    With orientations given (for a path where se3_rotation_undetermined), the rotation comes from them
    instead (chordal mean) and the translation from the centroids.
    """
    mu_e, mu_g = p_est.mean(axis=0), p_gt.mean(axis=0)
    if R_est is not None and R_gt is not None:
        R = _mean_R_gt_est(R_est, R_gt)
        return make_T(R, mu_g - R @ mu_e)
    cov = (p_gt - mu_g).T @ (p_est - mu_e) / len(p_est)
    U, _, Vt = np.linalg.svd(cov)
    S = np.diag([1.0, 1.0, np.sign(np.linalg.det(U) * np.linalg.det(Vt)) or 1.0])
    R = U @ S @ Vt
    return make_T(R, mu_g - R @ mu_e)


def align_4dof(p_est: np.ndarray, p_gt: np.ndarray, R_est: np.ndarray | None = None,
               R_gt: np.ndarray | None = None) -> np.ndarray:
    """Yaw about world z + translation minimising sum |p_gt - T p_est|^2 (closed form).

    VIO observes roll and pitch through gravity, so only yaw and position are free: aligning them alone
    keeps roll/pitch errors visible instead of letting a full SE(3) fit hide them. With orientations given
    (for a path where yaw_undetermined), the yaw comes from them instead.
    """
    mu_e, mu_g = p_est.mean(axis=0), p_gt.mean(axis=0)
    e, g = p_est - mu_e, p_gt - mu_g
    if R_est is not None and R_gt is not None:
        R_m = _mean_R_gt_est(R_est, R_gt)
        yaw = closest_yaw(R_m)
    else:
        a = np.sum(e[:, 0] * g[:, 0] + e[:, 1] * g[:, 1])
        b = np.sum(e[:, 0] * g[:, 1] - e[:, 1] * g[:, 0])
        yaw = math.atan2(b, a)
    c, s = math.cos(yaw), math.sin(yaw)
    R = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    return make_T(R, mu_g - R @ mu_e)


def _angles_deg(R: np.ndarray) -> np.ndarray:
    """Rotation angles (deg) of a stack of rotation matrices (N, 3, 3)."""
    c = (np.trace(R, axis1=1, axis2=2) - 1.0) / 2.0
    return np.degrees(np.arccos(np.clip(c, -1.0, 1.0)))


def _ate(name: str, T_est: np.ndarray, T_gt: np.ndarray) -> AteResult:
    p_est, p_gt, R_est, R_gt = T_est[:, :3, 3], T_gt[:, :3, 3], T_est[:, :3, :3], T_gt[:, :3, :3]
    align, undetermined = (align_se3, se3_rotation_undetermined) if name == "SE(3)" else (align_4dof, yaw_undetermined)
    small = undetermined(p_gt)
    T_align = align(p_est, p_gt, R_est, R_gt) if small else align(p_est, p_gt)
    T = T_align @ T_est
    err = np.linalg.norm(T[:, :3, 3] - T_gt[:, :3, 3], axis=1)
    R_err = np.swapaxes(R_gt, 1, 2) @ T[:, :3, :3]
    return AteResult(name, T_align, ErrorStats.of(err), ErrorStats.of(_angles_deg(R_err)), err,
                     "orientations" if small else "positions")


W_FIRST_MIN_DEG = 90.0  # a median rotation error above this is not a drift: the quaternions' order is asked about
W_FIRST_AGREE_DEG = 20.0  # ... and one file read w-first agreeing within this says it was written so


def quaternion_order_hint(q_est: np.ndarray, q_gt: np.ndarray, T_est: np.ndarray, T_gt: np.ndarray,
                          rot_median_deg: dict[str, float]) -> str:
    """Why orientations that disagree by ~180 deg may not be the estimator's fault: a TUM file written w-first
    (qw qx qy qz, as EuRoC's csv and many tools hold them) reads as a rotation of about 180 deg from the truth,
    silently (the positions, and so the ATE, are right). Tried only when the error is beyond any drift, for each
    ATE (`rot_median_deg`: its kind -> median rotation error): on a hover the SE(3) alignment is taken from the
    orientations themselves and absorbs a w-first file's near-constant misreading, which only the 4-DoF ATE shows
    (before, its 135 deg came without this hint)."""
    for kind, median in rot_median_deg.items():
        if not median > W_FIRST_MIN_DEG:
            continue
        for name, T, q in (("estimate", T_est, q_est), ("ground truth", T_gt, q_gt)):
            T2 = T.copy()
            T2[:, :3, :3] = quat_wxyz_to_rot(q[:, [1, 2, 3, 0]])  # read as w x y z, a w-first file's are z w x y
            other = _ate(kind, *((T2, T_gt) if name == "estimate" else (T_est, T2)))
            if other.rot_deg.median < W_FIRST_AGREE_DEG:
                return (f"orientations disagree by {median:.0f} deg (median, {kind} ATE) but agree within "
                        f"{other.rot_deg.median:.1f} deg if the {name}'s quaternions are read w-first: TUM files hold "
                        "qx qy qz qw (a writer putting qw first gives this); rotation errors here are not the "
                        "estimator's")
    return ""


# ------------------------------------------------------------------------------------------------ RPE

def relative_errors(T_est: np.ndarray, T_gt: np.ndarray, length_m: float,
                    segment_id: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Translation drift [%] and rotation drift [deg/m] of every segment of GT path length >= `length_m`.

    A segment starts at each pose i and ends at the first pose j whose GT path distance from i reaches
    `length_m`; the error is E = (T_gt_i^-1 T_gt_j)^-1 (T_est_i^-1 T_est_j), divided by the actual GT path
    length d_ij of the segment. Pairs with different `segment_id` (a gap in the estimate lies between
    them) are skipped, since the estimator may have restarted there.
    """
    d = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(T_gt[:, :3, 3], axis=0), axis=1))])
    i = np.arange(len(d))
    j = np.searchsorted(d, d + length_m, side="left")
    ok = j < len(d)
    i, j = i[ok], j[ok]
    if segment_id is not None:
        same = segment_id[i] == segment_id[j]
        i, j = i[same], j[same]
    dist = d[j] - d[i]
    keep = dist > 0
    i, j, dist = i[keep], j[keep], dist[keep]
    rel_gt = inv_T(T_gt[i]) @ T_gt[j]
    rel_est = inv_T(T_est[i]) @ T_est[j]
    E = inv_T(rel_gt) @ rel_est
    return 100.0 * np.linalg.norm(E[:, :3, 3], axis=1) / dist, _angles_deg(E[:, :3, :3]) / dist


# ------------------------------------------------------------------------------------------------ evaluate

def evaluate(est: Trajectory, gt: Trajectory, *, max_dt_ms: float = DEFAULT_MAX_DT_MS, interpolate: bool = False,
             rpe_lengths_m: tuple[float, ...] = DEFAULT_RPE_LENGTHS_M,
             max_gap_s: float = DEFAULT_MAX_GAP_S, crop_gt: bool = False) -> EvalResult:
    """Compare `est` with `gt` (both T_world_body, each in its own world frame).

    `crop_gt` first cuts the ground truth to the estimate's time span (+- max_dt), so that coverage
    measures only gaps inside the run (for a run on part of a sequence). Raises VioError when fewer than
    3 estimates have ground truth within `max_dt_ms`.
    """
    if len(gt) == 0 or len(est) == 0:
        raise VioError("empty trajectory")
    if crop_gt:
        margin = int(round(max_dt_ms * 1e6))
        gt = gt.subset(np.flatnonzero((gt.t_ns >= est.t_ns[0] - margin) & (gt.t_ns <= est.t_ns[-1] + margin)))
        if len(gt) == 0:
            raise VioError(f"no ground truth within the estimate's span {est.t_s[0]:.3f}..{est.t_s[-1]:.3f} s")
    idx, gt_m = associate(est, gt, int(round(max_dt_ms * 1e6)), interpolate)
    if len(idx) < 3:
        raise VioError(
            f"only {len(idx)} estimated poses have ground truth within {max_dt_ms:g} ms (need 3): estimate "
            f"spans {est.t_s[0]:.3f}..{est.t_s[-1]:.3f} s, ground truth {gt.t_s[0]:.3f}..{gt.t_s[-1]:.3f} s")
    est_m = est.subset(idx)
    T_est, T_gt = est_m.poses(), gt_m.poses()
    p_est, p_gt = T_est[:, :3, 3], T_gt[:, :3, 3]
    ate4 = _ate("4-DoF", T_est, T_gt)
    ate6 = _ate("SE(3)", T_est, T_gt)

    t = est_m.t_ns
    dt_s = np.diff(t) * 1e-9
    gap = dt_s > max_gap_s
    segment_id = np.concatenate([[0], np.cumsum(gap)])
    span_s = (gt.t_ns[-1] - gt.t_ns[0]) * 1e-9
    covered_s = float(np.sum(dt_s[~gap]))
    edges = [max(0.0, (t[0] - gt.t_ns[0]) * 1e-9), max(0.0, (gt.t_ns[-1] - t[-1]) * 1e-9)]
    longest_gap = float(max(edges + ([float(dt_s.max())] if len(dt_s) else [])))

    rpe = []
    for L in rpe_lengths_m:
        tr, rot = relative_errors(T_est, T_gt, L, segment_id)
        if len(tr):
            rpe.append(RpeSegment(float(L), len(tr), float(np.mean(tr)), float(np.median(tr)), float(np.mean(rot))))
    result = EvalResult(
        n_est=len(est), n_gt=len(gt), n_matched=len(idx), max_dt_ms=float(max_dt_ms), interpolated=interpolate,
        gt_span_s=float(span_s), coverage=min(1.0, covered_s / span_s) if span_s > 0 else 0.0,
        longest_gap_s=longest_gap, path_length_m=gt_m.path_length_m(), ate_4dof=ate4, ate_se3=ate6, rpe=rpe,
        rpe_trans_pct=float(np.mean([r.trans_pct for r in rpe])) if rpe else math.nan,
        rpe_rot_deg_per_m=float(np.mean([r.rot_deg_per_m for r in rpe])) if rpe else math.nan,
        t_ns=t, p_gt=p_gt, p_est=p_est,
        quaternion_order=quaternion_order_hint(est_m.q_wxyz, gt_m.q_wxyz, T_est, T_gt,
                                               {"SE(3)": ate6.rot_deg.median, "4-DoF": ate4.rot_deg.median}),
    )
    log.info("eval: %d matched, ATE 4-DoF %.4f m, SE(3) %.4f m, RPE %s", len(idx), ate4.trans_m.rmse,
             ate6.trans_m.rmse, "-" if math.isnan(result.rpe_trans_pct) else f"{result.rpe_trans_pct:.2f} %")
    if result.partial:
        log.warning("eval: %s", result.partial)
    if result.quaternion_order:
        log.warning("eval: %s", result.quaternion_order)
    return result


# ------------------------------------------------------------------------------------------------ outputs

def end_drift_m(t_ns: np.ndarray, T_est: np.ndarray, gt: Trajectory) -> float:
    """Position error at the last pose, the estimate aligned on its first pose only (position and yaw): the
    drift an integrator sees at the end of a lap, which a whole-trajectory ATE alignment would spread out.
    Ground truth is taken at the nearest stamp."""
    from vio.geometry import yaw_position_alignment

    G = gt.poses()

    def at(t: int) -> np.ndarray:
        return G[int(np.argmin(np.abs(gt.t_ns - t)))]

    A = yaw_position_alignment(T_est[0], at(int(t_ns[0])))
    return float(np.linalg.norm((A @ T_est[-1])[:3, 3] - at(int(t_ns[-1]))[:3, 3]))


def plot(result: EvalResult, path: str | Path, title: str = "") -> None:
    """Top view of GT and the 4-DoF-aligned estimate, and position error over time for both alignments."""
    from vio.extras import pyplot

    plt = pyplot("plots (--plot)")

    T = result.ate_4dof.T_gtworld_estworld
    p_al = result.p_est @ T[:3, :3].T + T[:3, 3]
    t_s = (result.t_ns - result.t_ns[0]) * 1e-9
    fig, (ax0, ax1) = plt.subplots(2, 1, figsize=(8, 10), gridspec_kw={"height_ratios": [3, 1.3]})
    ax0.plot(result.p_gt[:, 0], result.p_gt[:, 1], "k-", lw=1.2, label="ground truth")
    ax0.plot(p_al[:, 0], p_al[:, 1], "-", color="tab:red", lw=1.0, label="estimate (4-DoF aligned)")
    ax0.plot(result.p_gt[0, 0], result.p_gt[0, 1], "go", label="start")
    ax0.set_xlabel("x [m]")
    ax0.set_ylabel("y [m]")
    ax0.set_aspect("equal", adjustable="datalim")
    ax0.legend(loc="best")
    ax0.set_title(title or f"ATE 4-DoF {result.ate_4dof.trans_m.rmse:.3f} m, SE(3) {result.ate_se3.trans_m.rmse:.3f} m,"
                  f" RPE {result.rpe_trans_pct:.2f} %")
    ax0.grid(True, alpha=0.3)
    ax1.plot(t_s, result.ate_4dof.errors_m, color="tab:red", lw=0.8, label="4-DoF")
    ax1.plot(t_s, result.ate_se3.errors_m, color="tab:blue", lw=0.8, label="SE(3)")
    ax1.set_xlabel("time since first matched pose [s]")
    ax1.set_ylabel("position error [m]")
    ax1.legend(loc="best")
    ax1.grid(True, alpha=0.3)
    save_figure(plt, fig, path)


def plot_format(path: str | Path) -> str:
    """The image format a plot file is written in, from its suffix (none: PNG), or a one-line VioError for a suffix
    matplotlib cannot write. Checked before the work: `--loop-plot run.txt` ended a whole replay in an internal
    error. The format is also passed to savefig, which otherwise appends '.png' to a name without a suffix: the
    plot went to another file than the one asked for (and printed), over whatever was there."""
    from matplotlib.backend_bases import FigureCanvasBase

    suffix = Path(path).suffix.lower().lstrip(".")
    if not suffix:
        return "png"
    known = FigureCanvasBase.get_supported_filetypes()
    if suffix not in known:
        raise VioError(f"{path}: a plot cannot be written as .{suffix}; name it .png, .svg or .pdf "
                       f"(or one of {', '.join(sorted(known))})")
    return suffix


def require_plot(path: str | Path, what: str) -> None:
    """What a plot to `path` needs, asked for before the work that leads to it (a replay, an evaluation, an
    analysis): the [tools] extra (`what`: the option, as the user names it) and a format matplotlib can write."""
    from vio.extras import pyplot

    pyplot(what)
    plot_format(path)


def save_figure(plt, fig, path: str | Path) -> None:
    """Lay out, write (an unwritable path is a one-line VioError) and close a matplotlib figure, under exactly
    `path`."""
    fig.tight_layout()
    try:
        fig.savefig(path, dpi=110, format=plot_format(path))
    except OSError as e:
        raise VioError(f"{path}: cannot write plot ({e.strerror})") from None
    finally:
        plt.close(fig)


def write_json(result: EvalResult, path: str | Path, **extra) -> None:
    try:
        Path(path).write_text(json.dumps({**extra, **result.to_dict()}, indent=2) + "\n")
    except OSError as e:
        raise VioError(f"{path}: cannot write ({e.strerror})") from None


# ------------------------------------------------------------------------------------------------ CLI

def _lengths(text: str) -> tuple[float, ...]:
    try:
        vals = tuple(float(x) for x in text.split(",") if x.strip())
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated metres, got {text!r}") from None
    if not vals or any(not (v > 0) for v in vals):
        raise argparse.ArgumentTypeError(f"segment lengths must be positive, got {text!r}")
    return vals


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("est", type=path_arg, help="estimated trajectory (TUM: t x y z qx qy qz qw)")
    p.add_argument("gt", type=path_arg, help="ground truth: TUM file, EuRoC ground-truth csv or EuRoC dataset folder")
    p.add_argument("--plot", type=path_arg, metavar="PNG", help="write a top view and error-over-time plot")
    p.add_argument("--json", type=path_arg, metavar="FILE", help="write all numbers as JSON")
    # at most 10 s: 1e300 paired any estimate with any ground-truth pose (a review's note)
    p.add_argument("--max-dt-ms", type=positive_float_up_to(10_000.0), default=DEFAULT_MAX_DT_MS,
                   help="largest time difference for an estimate/GT pair, at most 10000 (default %(default)s)")
    p.add_argument("--interpolate", action="store_true", help="interpolate GT at the estimate stamps")
    p.add_argument("--rpe-lengths", type=_lengths, default=DEFAULT_RPE_LENGTHS_M, metavar="M,M,...",
                   help=f"RPE segment lengths in metres (default {','.join(f'{x:g}' for x in DEFAULT_RPE_LENGTHS_M)})")
    p.add_argument("--max-gap-s", type=positive_float, default=None,
                   help=f"time between estimates above which it counts as a gap (default {DEFAULT_MAX_GAP_S:g}, or "
                   "2.5 steps of an estimate whose poses come further apart)")
    p.add_argument("--run", type=positive_int, metavar="N", help="of an estimate file `vio run` appended several "
                   "runs to (a '# kestrel-vio run started' line before each, each in its own frame): evaluate run N "
                   "(1 = the first; default: the last, said)")
    p.add_argument("--crop-gt", action="store_true",
                   help="cut the ground truth to the estimate's time span (coverage then ignores the rest)")


def run(args: argparse.Namespace) -> int:
    from vio.io.outputs import check_outputs, recording_of

    check_outputs({"the JSON": args.json, "the plot": args.plot},
                  reads={"the estimate": args.est, "the ground truth": args.gt}, recordings=(recording_of(args.gt),))
    if args.plot:  # the [tools] extra and the plot's format, asked for now, not after printing and --json
        require_plot(args.plot, "plots (--plot)")
    est = load_trajectory(args.est, args.run)
    spacing = float(np.median(np.diff(est.t_ns))) * 1e-9 if len(est) > 1 else 0.0
    max_gap_s = args.max_gap_s
    if max_gap_s is None:
        max_gap_s = DEFAULT_MAX_GAP_S
        if spacing > max_gap_s:  # keyframe poses, say: gaps are what is longer than a few of their steps
            max_gap_s = 2.5 * spacing
            log.info("eval: poses every %.3g s (median): a gap is a step over %.3g s", spacing, max_gap_s)
    elif max_gap_s < spacing:  # every step a gap: "coverage 0.0 %" and no RPE segment, on a whole flight
        raise VioError(f"--max-gap-s {max_gap_s:g} s is below the estimate's median pose spacing {spacing:.3g} s: "
                       "every step would count as a gap")
    gt = load_trajectory(args.gt)
    result = evaluate(est, gt, max_dt_ms=args.max_dt_ms, interpolate=args.interpolate,
                      rpe_lengths_m=args.rpe_lengths, max_gap_s=max_gap_s, crop_gt=args.crop_gt)
    print(f"estimate: {args.est}\nground truth: {args.gt}")
    print(result.summary())
    if args.json:
        write_json(result, args.json, est=str(args.est), gt=str(args.gt))
    if args.plot:
        plot(result, args.plot)
    return 0
