"""Loop-closure benchmark: odometry alone vs loop-corrected, on simulated loop flights.

    python bench/loop_closure.py [--flights survey:120:4:realistic,...] [--cache DIR] [--json out.json]

For each flight (profile:duration_s:seed:variant[:aliasing period m] at 376x240; simulated once into
--cache; an aliasing period repeats the room's textures, vio simulate --aliasing): replays with the
loop-closure worker beside the odometry and reports ATE (4-DoF) of both trajectories, end-of-flight position
drift (both trajectories aligned on their first pose, as an integrator sees it), loop edges accepted /
switched off / refused, false edges (error against ground truth > 0.2 m or 3 deg) left active in the final
graph, the real-time factor with and without loop closure, and the per-keyframe detection + verification
cost measured again on one core (OpenCV one thread, the keyframes re-fed sequentially)."""

from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import argparse  # noqa: E402
import json  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

DEFAULT_FLIGHTS = "survey:120:4:realistic,aggressive:90:3:realistic,survey:90:6:clean,aggressive:60:5:clean"


class _Recorder:
    """Stands in for the worker: keeps the keyframes (the one-core cost is measured on them afterwards)."""

    def __init__(self) -> None:
        self.items: list = []
        self.dropped, self.error = 0, None

    def submit(self, *item) -> None:
        self.items.append(item)

    def close(self) -> None:
        pass


def _gt_pose(gt, t_ns: int) -> np.ndarray:
    from vio.geometry import make_T, quat_wxyz_to_rot

    k = int(np.argmin(np.abs(gt.t_ns - t_ns)))
    return make_T(quat_wxyz_to_rot(gt.q_wxyz[k]), gt.p[k])


def _end_drift(t: np.ndarray, T: np.ndarray, gt) -> float:
    """Position error at the end, the estimate aligned on its first pose (position and yaw)."""
    from vio.geometry import make_T, roll_pitch_yaw, so3_exp

    G0, E0 = _gt_pose(gt, int(t[0])), T[0]
    dyaw = roll_pitch_yaw(G0[:3, :3])[2] - roll_pitch_yaw(E0[:3, :3])[2]
    A = make_T(so3_exp(np.array([0, 0, dyaw])), np.zeros(3))
    A[:3, 3] = G0[:3, 3] - A[:3, :3] @ E0[:3, 3]
    return float(np.linalg.norm((A @ T[-1])[:3, 3] - _gt_pose(gt, int(t[-1]))[:3, 3]))


def run_flight(spec: str, cache: Path) -> dict:
    import cv2

    from vio.app.loop_worker import LoopWorker
    from vio.app.replay import replay
    from vio.config import VioConfig
    from vio.evaluation import evaluate
    from vio.geometry import inv_T, so3_log
    from vio.io.euroc import EurocDataset
    from vio.loop.closer import LoopCloser
    from vio.sim.generate import SimConfig, simulate
    from vio.trajectory import Trajectory

    profile, dur, seed, variant, *alias = spec.split(":")
    period = float(alias[0]) if alias else None
    data = cache / (f"{profile}-{variant}-seed{seed}-{dur}s-376x240" + (f"-aliasing{alias[0]}m" if alias else ""))
    if not (data / "mav0").is_dir():
        simulate(data, SimConfig(profile=profile, duration_s=float(dur), seed=int(seed), variant=variant,
                                 width=376, height=240, aliasing_period_m=period), overwrite=True, progress=False)
    ds = EurocDataset(data)
    gt = ds.groundtruth.trajectory
    cfg = VioConfig()
    off = replay(ds, cfg, progress=False)
    ds = EurocDataset(data)
    closer = LoopCloser(ds.calibration, cfg.loop)
    worker = LoopWorker(closer, max_queue=100000)
    on = replay(ds, cfg, progress=False, loop=worker)
    t = np.array([s.t_ns for s in on.states])
    T_odom = np.array([s.T_world_body for s in on.states])
    T_loop = closer.corrected_trajectory(t, T_odom)
    ev_o = evaluate(Trajectory.from_poses(t, T_odom), gt)
    ev_l = evaluate(Trajectory.from_poses(t, T_loop), gt)
    kt = [k.t_ns for k in closer.keyframes]
    false_active = false_total = 0
    for e in closer.graph.edges:
        if e.kind != "loop":
            continue
        err = inv_T(inv_T(_gt_pose(gt, kt[e.i])) @ _gt_pose(gt, kt[e.j])) @ e.T_i_j
        bad = np.linalg.norm(err[:3, 3]) > 0.2 or np.degrees(np.linalg.norm(so3_log(err[:3, :3]))) > 3.0
        false_total += bad
        false_active += bad and e.weight >= 0.5
    # one-core cost: the same keyframes again, sequentially, OpenCV on one thread
    rec = _Recorder()
    replay(EurocDataset(data), cfg, progress=False, loop=rec)
    cv2.setNumThreads(1)
    seq = LoopCloser(ds.calibration, cfg.loop)
    t0 = time.perf_counter()
    for item in rec.items:
        seq.add_keyframe(*item)
    per_kf_ms = (time.perf_counter() - t0) / max(len(rec.items), 1) * 1e3
    cv2.setNumThreads(-1)
    st = seq.stats.to_dict()
    return {"flight": data.name, "path_m": ev_o.path_length_m,
            "ate_odometry_m": ev_o.ate_4dof.trans_m.rmse, "ate_loop_m": ev_l.ate_4dof.trans_m.rmse,
            "ate_ratio": ev_l.ate_4dof.trans_m.rmse / ev_o.ate_4dof.trans_m.rmse,
            "end_drift_odometry_m": _end_drift(t, T_odom, gt), "end_drift_loop_m": _end_drift(t, T_loop, gt),
            "keyframes": st["keyframes"], "accepted": closer.stats.accepted,
            "switched_off": closer.stats.switched_off, "refused": closer.stats.refused,
            "false_edges": int(false_total), "false_edges_active": int(false_active),
            "rtf_odometry": off.realtime_factor, "rtf_with_loop": on.realtime_factor,
            "one_core_ms_per_keyframe": per_kf_ms, "one_core_detect_ms_mean": st["detect_ms_mean"],
            "one_core_optimize_ms_max": st["optimize_ms_max"],
            "memory_per_keyframe_bytes": closer.memory_per_keyframe_bytes(), "dropped": worker.dropped}


def graph_scaling(n: int) -> float:
    """Seconds for one GNC solve of a synthetic n-keyframe loop graph (2 m circle, 40 keyframes a lap, a
    true closure each lap, 20 random false ones)."""
    from vio.geometry import make_T, so3_exp
    from vio.loop.posegraph import PoseGraph

    rng = np.random.default_rng(0)
    truth = [make_T(so3_exp(np.array([0, 0, 2 * np.pi * k / 40])),
                    2 * np.array([np.cos(2 * np.pi * k / 40), np.sin(2 * np.pi * k / 40), 1.0])) for k in range(n)]
    g, prev, T = PoseGraph(), None, truth[0].copy()
    for k in range(n):
        if k:
            T = T @ np.linalg.inv(truth[k - 1]) @ truth[k] @ make_T(so3_exp(np.r_[0, 0, 8e-4]), np.r_[3e-3, 0, 0])
        prev = g.add_node(T, prev)
    for k in range(40, n, 40):
        g.add_loop(0, k, np.linalg.inv(truth[0]) @ truth[k])
    for _ in range(20):
        a, b = (int(x) for x in rng.integers(0, n, 2))
        g.add_loop(a, b, make_T(so3_exp(rng.normal(size=3) * 0.3), rng.normal(size=3)))
    t0 = time.perf_counter()
    g.optimize()
    return time.perf_counter() - t0


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--graph", type=int, nargs="*", metavar="N",
                    help="only time the GNC solve of synthetic N-keyframe graphs (e.g. 300 1200 2400)")
    ap.add_argument("--flights", default=DEFAULT_FLIGHTS)
    ap.add_argument("--cache", default="/tmp/kestrel-loop-bench")
    ap.add_argument("--json", help="write the results here")
    args = ap.parse_args(argv)
    if args.graph:
        for n in args.graph:
            print(f"pose graph {n} keyframes: GNC solve {graph_scaling(n) * 1e3:.0f} ms", flush=True)
        return 0
    rows = []
    for spec in args.flights.split(","):
        r = run_flight(spec, Path(args.cache))
        rows.append(r)
        print(f"{r['flight']}: ATE {r['ate_odometry_m']:.4f} -> {r['ate_loop_m']:.4f} m ({r['ate_ratio']:.2f}x), "
              f"end drift {r['end_drift_odometry_m']:.4f} -> {r['end_drift_loop_m']:.4f} m, "
              f"{r['accepted']} edges ({r['switched_off']} off, {r['false_edges_active']} false active), "
              f"RTF {r['rtf_odometry']:.2f} -> {r['rtf_with_loop']:.2f}, "
              f"{r['one_core_ms_per_keyframe']:.1f} ms/keyframe (one core), "
              f"opt max {r['one_core_optimize_ms_max']:.0f} ms, {r['memory_per_keyframe_bytes'] / 1024:.1f} KiB/kf",
              flush=True)
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
