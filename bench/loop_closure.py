"""Loop-closure benchmark: odometry alone vs loop-corrected, on simulated loop flights.

    python bench/loop_closure.py [--flights survey:120:4:realistic,...] [--cache DIR] [--json out.json]

For each flight (profile:duration_s:seed:variant[:aliasing period m] at 752x480, the simulator's and EuRoC's
size, or --size; simulated once into
--cache; an aliasing period repeats the room's textures, vio simulate --aliasing): replays with the
loop-closure worker beside the odometry and reports ATE (4-DoF) of both trajectories, end-of-flight position
drift (both trajectories aligned on their first pose, as an integrator sees it), loop edges accepted /
switched off / refused, false edges (error against ground truth > 0.2 m or 3 deg) left active in the final
graph, the real-time factor with and without loop closure, and the per-keyframe detection + verification
cost measured again on one core (OpenCV one thread, the keyframes re-fed sequentially). `--refeed-config X.toml`
also feeds those recorded keyframes to the loop stage with X's [loop] and reports both side by side."""

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
        self.items: list = []  # keyframes as submitted
        self.settles: list = []  # (keyframes submitted before, settled poses), in the order they came
        self.dropped, self.error = 0, None

    def submit(self, *item) -> None:
        self.items.append(item)

    def settle(self, settled) -> None:
        if settled:
            self.settles.append((len(self.items), tuple(settled)))

    def feed(self, closer, start: int = 0, each=None) -> None:
        """The recorded keyframes from `start` on and the settled poses in between into `closer`, in the order
        the worker would have had them, then its end of flight (`finish`); `each(closer)` after every keyframe."""
        s = 0
        for n in range(start, len(self.items) + 1):
            while s < len(self.settles) and self.settles[s][0] <= n:
                for t_ns, T in self.settles[s][1]:
                    closer.settle(t_ns, T)
                s += 1
            if n < len(self.items):
                closer.add_keyframe(*self.items[n])
                if each is not None:
                    each(closer)
        closer.finish()

    def close(self) -> None:
        pass


def _gt_pose(gt, t_ns: int) -> np.ndarray:
    from vio.geometry import make_T, quat_wxyz_to_rot

    k = int(np.argmin(np.abs(gt.t_ns - t_ns)))
    return make_T(quat_wxyz_to_rot(gt.q_wxyz[k]), gt.p[k])


def _edge_figures(closer, gt) -> tuple[int, int, list[float]]:
    """(false edges in all, false edges active, active edges' translation error in m) against ground truth: false is
    > 0.2 m or 3 deg off."""
    from vio.geometry import inv_T, so3_log

    kt = [k.t_ns for k in closer.keyframes]
    false_active = false_total = 0
    edge_err_m = []
    for e in closer.graph.edges:
        if e.kind != "loop":
            continue
        err = inv_T(inv_T(_gt_pose(gt, kt[e.i])) @ _gt_pose(gt, kt[e.j])) @ e.T_i_j
        bad = np.linalg.norm(err[:3, 3]) > 0.2 or np.degrees(np.linalg.norm(so3_log(err[:3, :3]))) > 3.0
        false_total += bad
        false_active += bad and e.weight >= 0.5
        if e.weight >= 0.5:
            edge_err_m.append(float(np.linalg.norm(err[:3, 3])))
    return int(false_total), int(false_active), edge_err_m


def refeed(rec: _Recorder, calib, loop_cfg, gt, t: np.ndarray, T_odom: np.ndarray, ate_odom_m: float):
    """The recorded keyframes (and settled poses) into a fresh LoopCloser with `loop_cfg`, on this thread: the
    closer, and its accuracy on the odometry `T_odom` at `t` and cost per odometry keyframe (OpenCV as the caller
    set it).
    Two configurations re-fed from one recording see exactly the same keyframes."""
    from vio.evaluation import end_drift_m, evaluate
    from vio.loop.closer import LoopCloser
    from vio.trajectory import Trajectory

    cl = LoopCloser(calib, loop_cfg)
    t0 = time.perf_counter()
    rec.feed(cl)
    per_kf_ms = (time.perf_counter() - t0) / max(len(rec.items), 1) * 1e3
    T_loop = cl.corrected_trajectory(t, T_odom)
    ate = evaluate(Trajectory.from_poses(t, T_loop), gt).ate_4dof.trans_m.rmse
    false_total, false_active, err = _edge_figures(cl, gt)
    return cl, {"ate_loop_m": ate, "ate_ratio": ate / ate_odom_m,
            "ate_loop_true_edges_m": evaluate(Trajectory.from_poses(t, _with_true_edges(cl, gt, t, T_odom)),
                                              gt).ate_4dof.trans_m.rmse,
            "loop_edge_error_median_m": float(np.median(err)) if err else None,
            "end_drift_loop_m": end_drift_m(t, T_loop, gt), "accepted": cl.stats.accepted,
            "false_edges": false_total, "false_edges_active": false_active, "ms_per_keyframe": per_kf_ms,
            # per keyframe searched: extraction + retrieval + verification, and the pose graph's upkeep
            **{k: cl.stats.to_dict()[k] for k in ("detect_ms_mean", "graph_ms_mean")}}


def _flight_data(spec: str | None, cache: Path, size: tuple[int, int], scene: str, dataset: Path | None) -> Path:
    """The flight's EuRoC folder: `dataset`, or `spec` (profile:duration_s:seed:variant[:aliasing m]) simulated
    into `cache` the first time it is asked for."""
    from vio.sim.generate import SimConfig, simulate

    if dataset is not None:
        return dataset
    profile, dur, seed, variant, *alias = spec.split(":")
    period = float(alias[0]) if alias else None
    data = cache / (f"{profile}-{variant}-seed{seed}-{dur}s-{size[0]}x{size[1]}" +
                    (f"-aliasing{alias[0]}m" if alias else "") + ("" if scene == "room" else f"-{scene}"))
    if not (data / "mav0").is_dir():
        simulate(data, SimConfig(profile=profile, duration_s=float(dur), seed=int(seed), variant=variant,
                                 width=size[0], height=size[1], aliasing_period_m=period, scene=scene),
                 overwrite=True, progress=False)
    return data


def record(spec: str | None, cache: Path, size: tuple[int, int], scene: str, dataset: Path | None,
           config: Path | None, out_dir: Path) -> Path:
    """Replay the flight once and keep what its loop stage was handed (keyframes, settled poses), with the
    calibration and [loop] configuration, in out_dir/<flight>.pkl: `--refeed-timing` feeds it again as often as
    asked, without the replay (its threads and its timing noise) and with exactly the same keyframes each time."""
    import pickle

    from vio.app.replay import replay
    from vio.config import VioConfig, load_config
    from vio.io.euroc import EurocDataset

    data = _flight_data(spec, cache, size, scene, dataset)
    cfg = load_config(config) if config is not None else VioConfig()
    rec = _Recorder()
    ds = EurocDataset(data)
    replay(ds, cfg, progress=False, loop=rec)
    out_dir.mkdir(parents=True, exist_ok=True)
    out = out_dir / f"{data.name}.pkl"
    with open(out, "wb") as f:
        pickle.dump({"flight": data.name, "items": rec.items, "settles": rec.settles,
                     "calibration": ds.calibration, "loop": cfg.loop}, f, protocol=pickle.HIGHEST_PROTOCOL)
    return out


def loop_digest(closer) -> str:
    """SHA-256 of everything the loop stage decided and keeps: each keyframe's features and bag of words, the pose
    graph's edges (poses, weights, inliers, sigma scales), odometry and estimate, and the stage's counts (not its
    timings). Two revisions of the stage fed the same recording agree on it only if their results are
    bit-identical."""
    import hashlib

    h = hashlib.sha256()

    def put(*xs) -> None:
        for x in xs:
            h.update(np.ascontiguousarray(x).tobytes() if isinstance(x, np.ndarray) else repr(x).encode())

    for kf, v in zip(closer.keyframes, closer.index.vectors):
        put(kf.t_ns, kf.session, kf.path_m, kf.feats.desc, kf.feats.uv, kf.feats.p_cam, v.words, v.weights)
    for e in closer.graph.edges:
        put(e.i, e.j, e.kind, e.weight, e.inliers, e.sigma_scale, e.T_i_j)
    put(np.array(closer.graph.odom), np.array(closer.graph.estimate))
    put({k: v for k, v in closer.stats.to_dict().items() if "_ms" not in k})
    return h.hexdigest()


def refeed_timing(paths: list[Path], runs: int) -> list[dict]:
    """Each recording (`--record`) fed to a fresh loop stage `runs` times, the recordings taking turns, OpenCV
    on one thread: per run the stage's `detect_ms` (extraction, retrieval, verification per searched keyframe)
    measured in this process's CPU time instead of the wall clock (other work on a shared machine adds to the
    wall clock, not to this), and the digest of the results (`loop_digest`), which must not change between runs."""
    import pickle
    import types

    import cv2

    import vio.loop.closer as closer_mod
    from vio.loop.closer import LoopCloser

    recs = []
    for p in paths:
        with open(p, "rb") as f:
            d = pickle.load(f)
        rec = _Recorder()
        rec.items, rec.settles = d["items"], d["settles"]
        recs.append((d, rec))
    cv2.setNumThreads(1)
    cpu_clock = types.SimpleNamespace(**{k: getattr(time, k) for k in dir(time) if not k.startswith("_")})
    cpu_clock.perf_counter = time.process_time
    rows = []
    try:
        closer_mod.time = cpu_clock
        for run in range(runs):
            for d, rec in recs:
                cl = LoopCloser(d["calibration"], d["loop"])
                rec.feed(cl)
                st = cl.stats.to_dict()
                rows.append({"flight": d["flight"], "run": run, "searched": len(cl.stats.detect_ms),
                             "detect_cpu_ms_mean": st["detect_ms_mean"], "graph_cpu_ms_mean": st["graph_ms_mean"],
                             "accepted": st["accepted"], "digest": loop_digest(cl),
                             "load": os.getloadavg()[0]})
    finally:
        closer_mod.time = time
        cv2.setNumThreads(-1)
    return rows


def run_flight(spec: str, cache: Path, size: tuple[int, int] = (752, 480), scene: str = "room",
               dataset: Path | None = None, config: Path | None = None, refeed_configs: tuple[Path, ...] = ()) -> dict:
    import cv2

    from vio.app.loop_worker import LoopWorker
    from vio.app.replay import replay
    from vio.config import VioConfig, load_config
    from vio.evaluation import end_drift_m, evaluate
    from vio.io.euroc import EurocDataset
    from vio.loop.closer import LoopCloser
    from vio.trajectory import Trajectory

    data = _flight_data(spec, cache, size, scene, dataset)
    ds = EurocDataset(data)
    gt = ds.groundtruth.trajectory
    cfg = load_config(config) if config is not None else VioConfig()
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
    false_total, false_active, edge_err_m = _edge_figures(closer, gt)
    ev_gt_edges = evaluate(Trajectory.from_poses(t, _with_true_edges(closer, gt, t, T_odom)), gt)
    # one-core cost: the same keyframes again, sequentially, OpenCV on one thread
    rec = _Recorder()
    replay(EurocDataset(data), cfg, progress=False, loop=rec)
    cv2.setNumThreads(1)
    ate_odom = ev_o.ate_4dof.trans_m.rmse
    seq, one = refeed(rec, ds.calibration, cfg.loop, gt, t, T_odom, ate_odom)
    per_kf_ms, st = one["ms_per_keyframe"], seq.stats.to_dict()
    # other loop configurations on exactly these keyframes (each beside this configuration's own re-feed)
    others = {}
    for path in refeed_configs:
        others[str(path)] = {"this": one, "other": refeed(rec, ds.calibration, load_config(path).loop, gt, t,
                                                          T_odom, ate_odom)[1]}
    cv2.setNumThreads(-1)
    return {"flight": data.name, "path_m": ev_o.path_length_m,
            "ate_odometry_m": ev_o.ate_4dof.trans_m.rmse, "ate_loop_m": ev_l.ate_4dof.trans_m.rmse,
            "ate_ratio": ev_l.ate_4dof.trans_m.rmse / ev_o.ate_4dof.trans_m.rmse,
            "ate_loop_true_edges_m": ev_gt_edges.ate_4dof.trans_m.rmse,
            "loop_edge_error_median_m": float(np.median(edge_err_m)) if edge_err_m else None,
            "end_drift_odometry_m": end_drift_m(t, T_odom, gt), "end_drift_loop_m": end_drift_m(t, T_loop, gt),
            "keyframes": st["keyframes"], "accepted": closer.stats.accepted,
            "switched_off": closer.stats.switched_off, "refused": closer.stats.refused,
            "false_edges": int(false_total), "false_edges_active": int(false_active),
            "rtf_odometry": off.realtime_factor, "rtf_with_loop": on.realtime_factor,
            "one_core_ms_per_keyframe": per_kf_ms, "one_core_detect_ms_mean": one["detect_ms_mean"],
            "one_core_graph_ms_mean": one["graph_ms_mean"],
            "one_core_optimize_ms_max": st["optimize_ms_max"],
            "memory_per_keyframe_bytes": closer.memory_per_keyframe_bytes(), "dropped": worker.dropped,
            "refeed": others}


def _with_true_edges(closer, gt, t_ns: np.ndarray, T_odom: np.ndarray) -> np.ndarray:
    """The loop-corrected trajectory the same pose graph would give if every active loop edge were exact
    (ground truth between the same keyframes): what is left is the graph's own floor (the odometry's
    short-term error, which no pose graph over keyframes removes), so ATE loop - this = the edges' share."""
    from vio.geometry import inv_T
    from vio.loop.closer import corrected_poses
    from vio.loop.posegraph import PoseGraph

    src = closer.graph
    g = PoseGraph(src.noise)
    for k, T in enumerate(src.odom):
        prev = k - 1 if k and closer.keyframes[k].session == closer.keyframes[k - 1].session else None
        seg = src.priors.get(k)
        g.add_node(T, prev, None if seg is None else seg[1:])
        if k in src.settled:  # as it is added: settling the newest node recomposes nothing after it
            g.settle(k, src.settled[k])
    kt = [k.t_ns for k in closer.keyframes]
    for e in src.edges:
        if e.kind == "loop" and e.weight >= 0.5:
            g.add_loop(e.i, e.j, inv_T(_gt_pose(gt, kt[e.i])) @ _gt_pose(gt, kt[e.j]))
    g.optimize(decide=True)
    return corrected_poses(closer, g, t_ns, T_odom)


def graph_scaling(n: int) -> dict:
    """A synthetic n-keyframe loop flight built keyframe by keyframe as the closer does it (2 m circle, 40
    keyframes a lap, odometry drifting in yaw and forward; each lap from the second on closes on the first
    with 3 consecutive true edges; 20 random false edges arrive at random times), with a re-solve after
    each closure. Returns the re-solve times (ms) of the last lap's closures, the amortised per-keyframe
    cost of adding nodes, the ATE against the truth, and the false edges left active."""
    from vio.geometry import make_T, so3_exp
    from vio.loop.posegraph import PoseGraph

    rng = np.random.default_rng(0)
    truth = [make_T(so3_exp(np.array([0, 0, 2 * np.pi * k / 40])),
                    2 * np.array([np.cos(2 * np.pi * k / 40), np.sin(2 * np.pi * k / 40), 1.0])) for k in range(n)]
    false_at = set(int(x) for x in rng.choice(np.arange(60, n), 20, replace=False))
    g, prev, T = PoseGraph(), None, truth[0].copy()
    solve_ms, decide_ms, add_s, false_edges = [], [], 0.0, []
    for k in range(n):
        if k:
            T = T @ np.linalg.inv(truth[k - 1]) @ truth[k] @ make_T(so3_exp(np.r_[0, 0, 8e-4]), np.r_[3e-3, 0, 0])
        t0 = time.perf_counter()
        prev = g.add_node(T, prev)
        add_s += time.perf_counter() - t0
        closure = False
        if k >= 40 and k % 40 in (0, 1, 2):
            g.add_loop(k % 40, k, np.linalg.inv(truth[k % 40]) @ truth[k])
            closure = k % 40 == 2
        if k in false_at:
            a = int(rng.integers(0, k - 30))
            g.add_loop(a, k, make_T(so3_exp(rng.normal(size=3) * 0.3), rng.normal(size=3)))
            false_edges.append(len(g.edges) - 1)
            closure = True
        if closure:
            t0 = time.perf_counter()
            decided = g.optimize()["decided"]
            (decide_ms if decided else solve_ms).append((time.perf_counter() - t0) * 1e3)
    t0 = time.perf_counter()
    g.optimize(decide=True)  # the GNC decision over every loop edge at the full size, forced
    forced_ms = (time.perf_counter() - t0) * 1e3
    ate = float(np.sqrt(np.mean([np.sum((e[:3, 3] - t[:3, 3]) ** 2) for e, t in zip(g.estimate, truth)])))
    return {"keyframes": n, "fast_ms_last": solve_ms[-1], "fast_ms_max_last_lap": max(solve_ms[-3:]),
            "fast_ms_mean": float(np.mean(solve_ms)), "fast_solves": len(solve_ms),
            "gnc_solves": len(decide_ms), "gnc_ms_mean": float(np.mean(decide_ms)) if decide_ms else 0.0,
            "gnc_ms_max": max(decide_ms, default=0.0), "gnc_forced_ms": forced_ms,
            "add_node_ms_per_keyframe": add_s / n * 1e3, "decision_nodes": g.last_decision_nodes,
            "ate_m": ate, "false_active": sum(g.edges[k].weight >= 0.5 for k in false_edges),
            "true_off": sum(e.weight < 0.5 for k, e in enumerate(g.edges)
                            if e.kind == "loop" and k not in false_edges)}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--graph", type=int, nargs="*", metavar="N",
                    help="only time the re-solve after a closure on synthetic N-keyframe graphs (e.g. 300 1200 2400)")
    ap.add_argument("--flights", default=DEFAULT_FLIGHTS)
    ap.add_argument("--cache", default="/tmp/kestrel-loop-bench")
    ap.add_argument("--json", help="write the results here")
    ap.add_argument("--size", default="752x480", help="image size WxH of the flights (default 752x480, as vio "
                    "simulate and EuRoC; 376x240 runs 3x faster with half the edge accuracy)")
    ap.add_argument("--config", type=Path, help="TOML configuration (odometry and [loop]) instead of the defaults")
    ap.add_argument("--refeed-config", type=Path, nargs="+", default=[], metavar="TOML",
                    help="also feed the recorded keyframes to the loop stage with each of these configurations' "
                         "[loop] (same keyframes, same odometry: an A/B of loop settings without replay noise)")
    ap.add_argument("--scene", default="room", help="simulator scene (room, hall, shelves: vio simulate --scene)")
    ap.add_argument("--datasets", nargs="+", type=Path, metavar="DIR",
                    help="recorded flights with ground truth (EuRoC ASL folders, e.g. made by `vio simulate "
                         "--imu-from`) instead of --flights")
    ap.add_argument("--record", type=Path, metavar="DIR",
                    help="only replay each flight once and keep its loop stage's keyframes in DIR/<flight>.pkl "
                         "(for --refeed-timing)")
    ap.add_argument("--refeed-timing", type=Path, nargs="+", metavar="PKL",
                    help="only feed these recordings (--record) to a fresh loop stage --runs times each, on one "
                         "thread: detection + verification per searched keyframe in CPU time, and a digest of "
                         "the results (equal digests: bit-identical loop stage)")
    ap.add_argument("--runs", type=int, default=3, help="re-feeds of each recording for --refeed-timing")
    args = ap.parse_args(argv)
    if args.refeed_timing:
        missing = [str(p) for p in args.refeed_timing if not p.is_file()]
        if missing:
            print(f"no such recording: {', '.join(missing)} (make them with --record DIR)", file=sys.stderr)
            return 2
        rows = refeed_timing(args.refeed_timing, args.runs)
        for r in rows:
            print(f"{r['flight']} run {r['run']}: detection {r['detect_cpu_ms_mean']:.3f} ms CPU per searched "
                  f"keyframe ({r['searched']} searched), pose graph {r['graph_cpu_ms_mean']:.3f}, "
                  f"{r['accepted']} edges, load {r['load']:.1f}, digest {r['digest'][:16]}", flush=True)
        for name in dict.fromkeys(r["flight"] for r in rows):
            ms = [r["detect_cpu_ms_mean"] for r in rows if r["flight"] == name]
            digests = {r["digest"] for r in rows if r["flight"] == name}
            print(f"{name}: detection mean of runs {np.mean(ms):.3f} ms (fastest {min(ms):.3f}, slowest "
                  f"{max(ms):.3f}), digest {'same in every run' if len(digests) == 1 else 'DIFFERS between runs'}",
                  flush=True)
        if args.json:
            Path(args.json).write_text(json.dumps(rows, indent=1))
        return 0
    if args.graph:
        rows = []
        for n in args.graph:
            r = graph_scaling(n)
            rows.append(r)
            print(f"pose graph {n} keyframes: re-solve after the last closure {r['fast_ms_last']:.1f} ms "
                  f"(last lap max {r['fast_ms_max_last_lap']:.1f}, mean over {r['fast_solves']} fast-path "
                  f"closures {r['fast_ms_mean']:.1f}); {r['gnc_solves']} GNC decisions mean "
                  f"{r['gnc_ms_mean']:.0f} max {r['gnc_ms_max']:.0f}, forced at the end {r['gnc_forced_ms']:.0f} ms; "
                  f"decision graph {r['decision_nodes']} nodes, adding a keyframe "
                  f"{r['add_node_ms_per_keyframe']:.2f} ms, ATE {r['ate_m']:.4f} m, "
                  f"false edges active {r['false_active']}/20, true edges off {r['true_off']}", flush=True)
        if args.json:
            Path(args.json).write_text(json.dumps(rows, indent=1))
        return 0
    rows = []
    todo = [(None, d) for d in args.datasets] if args.datasets else [(s, None) for s in args.flights.split(",")]
    for spec, dataset in todo:
        if dataset is not None and not (dataset / "mav0").is_dir():
            print(f"{dataset}: not an EuRoC ASL folder (no mav0/)", file=sys.stderr)
            return 2
        size = tuple(int(v) for v in args.size.lower().split("x"))
        if args.record:
            print(f"recorded {record(spec, Path(args.cache), size, args.scene, dataset, args.config, args.record)}",
                  flush=True)
            continue
        r = run_flight(spec, Path(args.cache), size, args.scene, dataset, args.config, tuple(args.refeed_config))
        rows.append(r)
        print(f"{r['flight']}: ATE {r['ate_odometry_m']:.4f} -> {r['ate_loop_m']:.4f} m ({r['ate_ratio']:.2f}x; "
              f"with exact loop edges {r['ate_loop_true_edges_m']:.4f} m), "
              f"end drift {r['end_drift_odometry_m']:.4f} -> {r['end_drift_loop_m']:.4f} m, "
              f"{r['accepted']} edges ({r['switched_off']} off, {r['false_edges_active']} false active), "
              f"RTF {r['rtf_odometry']:.2f} -> {r['rtf_with_loop']:.2f}, "
              f"{r['one_core_ms_per_keyframe']:.1f} ms/keyframe (one core; per keyframe searched: detection "
              f"{r['one_core_detect_ms_mean']:.1f}, pose graph {r['one_core_graph_ms_mean']:.1f}), "
              f"opt max {r['one_core_optimize_ms_max']:.0f} ms, {r['memory_per_keyframe_bytes'] / 1024:.1f} KiB/kf",
              flush=True)
        for path, ab in r["refeed"].items():
            a, o = ab["this"], ab["other"]
            print(f"  re-fed with {path}: loop ATE {a['ate_loop_m']:.4f} -> {o['ate_loop_m']:.4f} m "
                  f"(ratio {a['ate_ratio']:.3f} -> {o['ate_ratio']:.3f}; exact edges "
                  f"{a['ate_loop_true_edges_m']:.4f} -> {o['ate_loop_true_edges_m']:.4f}), "
                  f"end drift {a['end_drift_loop_m']:.4f} -> "
                  f"{o['end_drift_loop_m']:.4f} m, edges {a['accepted']} -> {o['accepted']} (false active "
                  f"{a['false_edges_active']} -> {o['false_edges_active']}), {a['ms_per_keyframe']:.2f} -> "
                  f"{o['ms_per_keyframe']:.2f} ms/keyframe", flush=True)
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
