"""Covariance honesty over simulated flights: pose NEES of frame-rate and IMU-rate states.

    python bench/nees.py [--duration 30] [--seeds 1 2] [--profiles survey aggressive]
                         [--variants clean realistic hard] [--blackout START:LENGTH] [--json out.json]

Each flight is replayed through the estimator; every frame-rate state and every IMU-rate state (the
ones the daemon sends between frames) is compared with the simulator's truth. `--blackout 10:2` blacks
out both cameras for 2 s from 10 s into the flight, to check that the covariance grows while vision is
missing. The 95 % chi-square interval is computed with one independent sample per second of flight
(consecutive states share most of their error).
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench.flights import FlightSpec, ensure_flight  # noqa: E402
from vio.sim.faults import blackout, copy_dataset  # noqa: E402


def run_flight(path: Path, cfg=None) -> dict:
    from vio.consistency import POSE_DOF, pose_nees, replay_states

    r = replay_states(path, cfg)
    gt = r.dataset.groundtruth.trajectory
    T_gt = gt.poses()
    out = {"dof": POSE_DOF, "resets": r.estimator.reset_counter}
    for name, states in (("frame", r.frame_states), ("imu", r.imu_states[::10])):
        r = pose_nees(states, gt.t_ns, T_gt, skip_s=1.0)
        out[name] = r.summary()
        out[name]["seconds"] = float((r.t_ns[-1] - r.t_ns[0]) * 1e-9) if len(r.t_ns) > 1 else 0.0
    return out


def main(argv: list[str] | None = None) -> int:
    from vio.consistency import POSE_DOF, chi2_interval

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--duration", type=float, default=30.0)
    p.add_argument("--seeds", type=int, nargs="+", default=[1])
    p.add_argument("--profiles", nargs="+", default=["survey", "aggressive"])
    p.add_argument("--variants", nargs="+", default=["clean", "realistic", "hard"])
    p.add_argument("--size", default="752x480")
    p.add_argument("--blackout", metavar="START:LENGTH", help="black cameras from START s for LENGTH s")
    p.add_argument("--json", metavar="FILE")
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    rows, seconds, sums = [], 0.0, []
    for profile in args.profiles:
        for variant in args.variants:
            for seed in args.seeds:
                spec = FlightSpec(profile, args.duration, seed, variant, args.size)
                path = ensure_flight(spec)
                if args.blackout:
                    a, b = (float(x) for x in args.blackout.split(":"))
                    path = copy_dataset(path, Path("/tmp/kestrel-bench/blackout") / spec.key)
                    blackout(path, a, b)
                r = run_flight(path)
                r["flight"] = spec.key + (f"-blackout{args.blackout}" if args.blackout else "")
                rows.append(r)
                seconds += r["frame"]["seconds"]
                sums.append(r["frame"]["nees_mean"] * r["frame"]["states"])
                print(f"{r['flight']:<48} resets {r['resets']}  frame NEES mean {r['frame']['nees_mean']:7.2f} "
                      f"(pos {r['frame']['nees_position_mean']:6.2f} rot {r['frame']['nees_rotation_mean']:6.2f})  "
                      f"imu-rate NEES {r['imu']['nees_mean']:7.2f}  max err {r['frame']['error_position_max_m']:.3f} m "
                      f"max sigma {r['frame']['sigma_position_max_m']:.3f} m", flush=True)
    n_states = sum(r["frame"]["states"] for r in rows)
    mean = float(np.sum(sums) / max(n_states, 1))
    lo, hi = chi2_interval(POSE_DOF, int(seconds))
    print(f"all flights: frame-rate NEES mean {mean:.2f} (dof {POSE_DOF}; 95 % interval for {int(seconds)} "
          f"independent samples [{lo:.2f}, {hi:.2f}])")
    if args.json:
        Path(args.json).write_text(json.dumps({"flights": rows, "nees_mean": mean, "interval": [lo, hi]}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
