"""The closed-loop report's maths: vehicle tracking error, Kestrel's error, EKF events, blackout recovery.

Inputs are plain arrays recorded by bench/sitl/run.py (host stamps in ns, positions in the autopilot's local
NED frame or the SITL's truth NED); nothing here talks to a SITL, so every figure is unit-tested.

Frames: the mission is flown in the autopilot's local frame, which with vision position and yaw is
Kestrel's frame (docs/autopilot.md "Frames"). Its relation to the SITL's truth NED is fixed at the start:
`start_alignment` takes the yaw and offset between the autopilot's estimate and the truth while the vehicle
sits on the ground, and every later comparison uses that one transform. Drift of Kestrel therefore shows as
tracking error, as it would on a real vehicle; nothing is re-fitted afterwards. Kestrel's own trajectory
is the exception: each estimator reset starts a new Kestrel frame, so it is aligned once per reset segment
(`per_segment_error`). Blackouts are judged against where the vehicle was when the cameras went black
(`blackout_hold`, `landed_offset`), not against the mission setpoint that keeps moving meanwhile.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

YAW_GATE = 1.0  # EKF innovation test ratios: <= 1 is inside the gate


def wrap_pi(a: np.ndarray | float) -> np.ndarray:
    return (np.asarray(a, dtype=float) + np.pi) % (2 * np.pi) - np.pi


@dataclass(frozen=True)
class Alignment:
    """p_truth = R(yaw) p_local + t, both NED (yaw about down)."""

    yaw: float
    t: np.ndarray

    def apply(self, p_local: np.ndarray) -> np.ndarray:
        c, s = math.cos(self.yaw), math.sin(self.yaw)
        R = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        return np.asarray(p_local, dtype=float) @ R.T + self.t


def start_alignment(p_local: np.ndarray, yaw_local: np.ndarray, p_truth: np.ndarray,
                    yaw_truth: np.ndarray) -> Alignment:
    """The local->truth transform from simultaneous samples on the ground (mean yaw difference, then offset)."""
    dyaw = wrap_pi(np.asarray(yaw_truth) - np.asarray(yaw_local))
    yaw = float(math.atan2(np.mean(np.sin(dyaw)), np.mean(np.cos(dyaw))))
    a = Alignment(yaw, np.zeros(3))
    return Alignment(yaw, np.mean(np.asarray(p_truth, float) - a.apply(p_local), axis=0))


def interp_positions(t_query_ns: np.ndarray, t_ns: np.ndarray, p: np.ndarray) -> np.ndarray:
    """Linear interpolation of (N, 3) positions at t_query_ns (clamped at the ends)."""
    tq = np.asarray(t_query_ns, dtype=np.int64)
    t = np.asarray(t_ns, dtype=np.int64)
    return np.stack([np.interp(tq - t[0], t - t[0], np.asarray(p, float)[:, k]) for k in range(3)], axis=1)


def distance_to_polyline(points: np.ndarray, polyline: np.ndarray) -> np.ndarray:
    """Each point's distance to the nearest point of the polyline (segments between consecutive vertices)."""
    P = np.asarray(points, dtype=float).reshape(-1, 1, 3)
    A, B = np.asarray(polyline, float)[:-1], np.asarray(polyline, float)[1:]
    AB = B - A
    L2 = np.maximum(np.sum(AB * AB, axis=1), 1e-12)
    s = np.clip(np.sum((P - A) * AB, axis=2) / L2, 0.0, 1.0)
    nearest = A + s[..., None] * AB
    return np.min(np.linalg.norm(P - nearest, axis=2), axis=1)


def error_stats(e: np.ndarray) -> dict:
    e = np.asarray(e, dtype=float)
    if len(e) == 0:
        return {"n": 0}
    return {"n": int(len(e)), "rms": float(np.sqrt(np.mean(e**2))), "median": float(np.median(e)),
            "p95": float(np.percentile(e, 95)), "max": float(np.max(e))}


def ratio_stats(r: np.ndarray, gate: float = YAW_GATE) -> dict:
    """Innovation test ratios: how many samples lay outside the gate, and how far."""
    r = np.asarray(r, dtype=float)
    r = r[np.isfinite(r)]
    if len(r) == 0:
        return {"n": 0}
    return {"n": int(len(r)), "max": float(r.max()), "p95": float(np.percentile(r, 95)),
            "outside_gate": int(np.sum(r > gate)), "outside_fraction": float(np.mean(r > gate))}


FAILSAFE_WORDS = ("EKF Failsafe", "EKF variance", "failsafe", "Failsafe")


def failsafe_events(statustexts: list[tuple[int, str]]) -> list[tuple[int, str]]:
    """STATUSTEXTs (t_ns, text) that announce an autopilot failsafe."""
    return [(t, s) for t, s in statustexts if any(w in s for w in FAILSAFE_WORDS)]


def recovery_error(t_ns: np.ndarray, p_truth: np.ndarray, p_expected: np.ndarray, window_ns: tuple[int, int]) -> float:
    """Largest |truth - expected| within [start, end] ns: after a blackout, is the vehicle where it should be?"""
    t = np.asarray(t_ns)
    m = (t >= window_ns[0]) & (t <= window_ns[1])
    if not np.any(m):
        return float("nan")
    return float(np.max(np.linalg.norm(np.asarray(p_truth)[m] - np.asarray(p_expected)[m], axis=1)))


def blackout_hold(t_ns: np.ndarray, p_truth: np.ndarray, window_ns: tuple[int, int]) -> dict:
    """How far the vehicle moved while blind, against where it was when the cameras went black.

    Why not the setpoint: the harness's setpoint keeps moving along the mission during a blackout, but a
    vehicle that has lost vision should hold (or land) where it is, not chase it; the failure to catch is
    a fly-away, i.e. motion away from the blackout-start position. Horizontal and vertical are separate
    because a LAND failsafe descends on purpose."""
    t = np.asarray(t_ns)
    p = np.asarray(p_truth, dtype=float)
    m = (t >= window_ns[0]) & (t <= window_ns[1])
    if not np.any(m):
        return {"n": 0}
    p0 = p[int(np.argmax(m))]
    d = p[m] - p0
    return {"n": int(np.sum(m)), "horizontal_max_m": float(np.max(np.linalg.norm(d[:, :2], axis=1))),
            "horizontal_end_m": float(np.linalg.norm(d[-1, :2])), "down_end_m": float(d[-1, 2])}


def landed_offset(t_ns: np.ndarray, p_truth: np.ndarray, t_blackout_ns: int, t_landed_ns: int) -> float:
    """Horizontal distance between where the vehicle touched down and where it was when the blackout began:
    a failsafe LAND should come down under the blackout-start position."""
    t = np.asarray(t_ns)
    p = np.asarray(p_truth, dtype=float)
    i0 = int(np.searchsorted(t, t_blackout_ns))
    i1 = min(int(np.searchsorted(t, t_landed_ns)), len(t) - 1)
    if i0 >= len(t):
        return float("nan")
    return float(np.linalg.norm(p[i1, :2] - p[i0, :2]))


def segment_ids(t_ns: np.ndarray, reset_ns: list[int] | np.ndarray = (), max_gap_ns: int = 500_000_000) -> np.ndarray:
    """Segment index of each estimate stamp: a new segment at every estimator reset and at every gap in the
    estimate longer than `max_gap_ns` (a reset always follows a loss of tracking, and while lost the daemon
    writes no pose, so the gap marks it even when the reset time itself was not recorded)."""
    t = np.asarray(t_ns, dtype=np.int64)
    if len(t) == 0:
        return np.zeros(0, dtype=int)
    new = np.zeros(len(t), dtype=bool)
    new[1:] = np.diff(t) > max_gap_ns
    for r in reset_ns:
        k = int(np.searchsorted(t, int(r)))
        if 0 < k < len(t):
            new[k] = True
    return np.cumsum(new)


def per_segment_error(p_est: np.ndarray, p_gt: np.ndarray, seg: np.ndarray, min_poses: int = 10) -> dict:
    """Kestrel vs truth with one 4-DoF (yaw + translation) alignment per reset segment.

    Why per segment: each estimator reset starts a new world frame (origin and yaw of its own), which the
    autopilot absorbs through reset_counter; one alignment across a reset would charge the frame change as
    error. Segments shorter than `min_poses` are counted but not scored (an alignment of a few poses fits
    anything)."""
    from vio.evaluation import align_4dof

    p_est, p_gt, seg = np.asarray(p_est, float), np.asarray(p_gt, float), np.asarray(seg)
    errs, parts = [], []
    for s in np.unique(seg):
        m = seg == s
        if np.sum(m) < min_poses:
            parts.append({"poses": int(np.sum(m)), "rmse": None})
            continue
        T = align_4dof(p_est[m], p_gt[m])
        e = np.linalg.norm(p_est[m] @ T[:3, :3].T + T[:3, 3] - p_gt[m], axis=1)
        errs.append(e)
        parts.append({"poses": int(np.sum(m)), "rmse": float(np.sqrt(np.mean(e**2))), "max": float(e.max())})
    e = np.concatenate(errs) if errs else np.zeros(0)
    return {"segments": len(parts), "rmse": float(np.sqrt(np.mean(e**2))) if len(e) else float("nan"),
            "max": float(e.max()) if len(e) else float("nan"), "per_segment": parts}


def markdown(summary: dict) -> str:
    """The report as a markdown table (the figures quoted in docs/autopilot.md come from this)."""
    lines = ["| figure | value |", "|---|---|"]

    def fmt(v) -> str:
        if isinstance(v, float):
            return f"{v:.3f}"
        if isinstance(v, dict):
            return ", ".join(f"{k} {fmt(x)}" for k, x in v.items())
        if isinstance(v, list):
            return "; ".join(fmt(x) for x in v) or "none"
        return str(v)

    for k, v in summary.items():
        lines.append(f"| {k} | {fmt(v)} |")
    return "\n".join(lines) + "\n"
