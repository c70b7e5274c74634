"""Is the covariance sent with a loop-corrected pose honest? Pose NEES of `[loop] output = "jump"` in a loaded map.

    python bench/loop_output_nees.py [--second-seeds 12 13 14] [--cache DIR] [--json out.json]

A map flight (mapping profile, 60 s, seed 2, 376x240 or --size, realistic) is simulated, replayed with loop closure
and saved as a map; each second flight (survey, 30 s, scene seed 2: the same room, another path and start) is
replayed with the map loaded, and every state the autopilot would get in jump mode is kept twice: with the
correction's uncertainty added (CorrectionUncertainty, the default) and without it (the odometry's covariance
alone, as before 2026-12-06). Their pose NEES (6 DoF, vio.consistency) is taken in the map's frame from 0.5 s after
the flight relocalised, with flight 1's alignment of its loop-corrected keyframes to the truth (no alignment of the
second flight's own). For reference: each flight's odometry NEES in its own frame (aligned on its first pose), and
the map flight's own jump-mode output (no uncertainty is added in a flight's own frame).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def _simulate(path: Path, **kw) -> Path:
    from vio.sim.generate import SimConfig, simulate

    if not (path / "mav0").is_dir():
        simulate(path, SimConfig(variant="realistic", **kw), overwrite=True, progress=False)
    return path


def _replay(path: Path, closer, cfg) -> tuple[list, list, list]:
    """(odometry states, jump output with the uncertainty, jump output without), one replay."""
    from vio.app.loop_worker import LoopWorker
    from vio.app.replay import replay
    from vio.io.euroc import EurocDataset
    from vio.loop.output import CorrectedOutput

    loop = LoopWorker(closer, max_queue=100000)
    with_u, without = CorrectedOutput.from_config(cfg), CorrectedOutput.from_config(cfg)
    odo, a, b = [], [], []

    def sink(st) -> None:
        T, version, unc, *segment = loop.correction()  # segment, own frame, reset counter
        odo.append(st)
        a.append(with_u.apply(st, T, version, unc, *segment))
        b.append(without.apply(st, T, version, None, *segment))

    replay(EurocDataset(path), cfg, [sink], progress=False, loop=loop)
    return odo, a, b


def _summary(r) -> dict:
    q = r.error_position_m / np.maximum(r.sigma_position_m, 1e-12)
    return {**r.summary(), "nees_p95": float(np.percentile(r.nees, 95)) if len(r.nees) else None,
            "error_position_median_m": float(np.median(r.error_position_m)) if len(r.nees) else None,
            "sigma_position_median_m": float(np.median(r.sigma_position_m)) if len(r.nees) else None,
            "error_over_sigma_p95": float(np.percentile(q, 95)) if len(r.nees) else None}


def main(argv: list[str]) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--second-seeds", type=int, nargs="+", default=[12, 13, 14])
    ap.add_argument("--map-duration", type=float, default=60.0)
    ap.add_argument("--size", default="376x240")
    ap.add_argument("--cache", type=Path, default=Path("/tmp/kestrel-bench/loop_output_nees"))
    ap.add_argument("--json", type=Path)
    args = ap.parse_args(argv)
    from vio.config import VioConfig
    from vio.consistency import pose_nees
    from vio.evaluation import evaluate
    from vio.io.euroc import EurocDataset
    from vio.loop.closer import LoopCloser
    from vio.loop.mapfile import load_map
    from vio.trajectory import Trajectory

    w, h = (int(x) for x in args.size.split("x"))
    cfg = VioConfig()
    cfg = dataclasses.replace(cfg, loop=dataclasses.replace(cfg.loop, enabled=True, output="jump"))
    d1 = _simulate(args.cache / f"map-mapping-seed2-{args.map_duration:g}s-{args.size}", profile="mapping",
                   duration_s=args.map_duration, seed=2, width=w, height=h)
    ds1 = EurocDataset(d1)
    gt1 = ds1.groundtruth.trajectory
    mapper = LoopCloser(ds1.calibration, cfg.loop)
    odo1, jump1, _ = _replay(d1, mapper, cfg)
    kt = np.array([k.t_ns for k in mapper.keyframes])
    A = evaluate(Trajectory.from_poses(kt, np.array(mapper.graph.estimate)), gt1).ate_4dof.T_gtworld_estworld
    mapper.save_map(args.cache / "map.npz")
    out = {"map_flight": {"keyframes": len(mapper.keyframes),
                          "odometry_own_frame": _summary(pose_nees(odo1, gt1.t_ns, gt1.poses(), skip_s=1.0)),
                          "jump_own_frame": _summary(pose_nees(jump1, gt1.t_ns, gt1.poses(), skip_s=1.0,
                                                               realign_on_reset=False))},
           "second_flights": []}
    print(f"map flight: odometry NEES {out['map_flight']['odometry_own_frame']['nees_mean']:.2f}, its jump output "
          f"{out['map_flight']['jump_own_frame']['nees_mean']:.2f} (own frame)", flush=True)
    for seed in args.second_seeds:
        d2 = _simulate(args.cache / f"survey-seed{seed}-scene2-30s-{args.size}", profile="survey", duration_s=30.0,
                       seed=seed, scene_seed=2, width=w, height=h)
        gt = EurocDataset(d2).groundtruth.trajectory
        cl = LoopCloser(ds1.calibration, cfg.loop)
        cl.load_map(load_map(args.cache / "map.npz"))
        odo, with_u, without = _replay(d2, cl, cfg)
        row = {"seed": seed, "odometry_own_frame": _summary(pose_nees(odo, gt.t_ns, gt.poses(), skip_s=1.0)),
               "relocalised_after_s": None}
        if cl.relocalised_t_ns is not None:
            row["relocalised_after_s"] = (cl.relocalised_t_ns - odo[0].t_ns) * 1e-9
            t0 = cl.relocalised_t_ns + 500_000_000
            for name, states in (("jump_map_frame", with_u), ("jump_map_frame_without_uncertainty", without)):
                row[name] = _summary(pose_nees([s for s in states if s.t_ns >= t0], gt.t_ns, gt.poses(), align=A))
            j, n = row["jump_map_frame"], row["jump_map_frame_without_uncertainty"]
            print(f"seed {seed}: relocalised after {row['relocalised_after_s']:.1f} s; map-frame pose NEES "
                  f"{j['nees_mean']:.2f} (p95 {j['nees_p95']:.1f}; without the correction's uncertainty "
                  f"{n['nees_mean']:.2f}, p95 {n['nees_p95']:.1f}); position error median "
                  f"{j['error_position_median_m'] * 1e3:.1f} mm, sigma {j['sigma_position_median_m'] * 1e3:.1f} mm "
                  f"({n['sigma_position_median_m'] * 1e3:.1f}); odometry NEES in its own frame "
                  f"{row['odometry_own_frame']['nees_mean']:.2f}", flush=True)
        else:
            print(f"seed {seed}: never relocalised", flush=True)
        out["second_flights"].append(row)
    if args.json:
        args.json.write_text(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
