"""Relocalisation accuracy in the map's frame.

    vio replay FLIGHT1 --save-map map.npz --loop-output f1_loop.tum --stats f1.json
    vio replay FLIGHT2 --load-map map.npz --loop-output f2_loop.tum --stats f2.json
    python bench/loop_reloc.py f1.json f2_loop.tum f2.json FLIGHT2

Applies flight 1's ground-truth alignment (the map's frame -> the simulator's world) to flight 2's
loop-corrected poses after it relocalised, and compares them with flight 2's ground truth: a flight that
relocalised correctly comes out in the map's frame without an alignment of its own."""

from __future__ import annotations

import json
import sys

import numpy as np


def main(argv: list[str]) -> int:
    from vio.evaluation import load_trajectory
    from vio.io.euroc import EurocDataset

    map_stats, est2, stats2, ds2 = argv
    A = np.array(json.load(open(map_stats))["loop"]["evaluation"]["ate_4dof"]["T_gtworld_estworld"])
    s2 = json.load(open(stats2))
    delay = s2["loop"]["relocalisation"]["delay_s"]
    if delay is None:
        print("flight 2 did not relocalise")
        return 1
    gt = EurocDataset(ds2).groundtruth.trajectory
    tr = load_trajectory(est2)
    k = tr.t_ns >= tr.t_ns[0] + int((delay + 0.5) * 1e9)  # after the relocalising keyframe (+ margin)
    p = (A[:3, :3] @ tr.p[k].T).T + A[:3, 3]
    g = np.array([gt.p[np.argmin(np.abs(gt.t_ns - t))] for t in tr.t_ns[k]])
    print(f"relocalised after {delay:.1f} s; ATE in the map's frame {np.sqrt(np.mean(np.sum((p - g) ** 2, 1))):.4f} m "
          f"over {int(k.sum())} poses; odometry ATE (own alignment) "
          f"{s2['evaluation']['ate_4dof']['trans_m']['rmse']:.4f} m")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
