"""`vio demo`: simulate a short survey flight, replay it through the estimator, print accuracy and speed.

The first command of the README: it needs nothing but the installed package (no data, no camera).
"""

from __future__ import annotations

import argparse
import os
import tempfile
from pathlib import Path

from vio.argtypes import int_at_least
from vio.sim.motion import PROFILES


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--duration", type=float, default=20.0, help="flight length in seconds (default 20)")
    p.add_argument("--profile", choices=PROFILES, default="survey", help="simulated motion profile (default survey)")
    # numpy takes no negative seed: -1 was an error after the temporary folder was made and the scene built
    p.add_argument("--seed", type=int_at_least(0), default=1, help="random seed of the flight")
    p.add_argument("--keep", metavar="DIR", help="write the dataset and trajectory here instead of a temp folder")
    # `vio -q demo` sets it too (cli.main): -q drew both progress bars, as demo had no way to turn them off
    p.add_argument("--no-progress", action="store_true", help="no progress bars")


def run(args: argparse.Namespace) -> int:
    from vio import UsageError, VioError
    from vio.app.replay import TumSink, replay
    from vio.evaluation import evaluate
    from vio.io.euroc import EurocDataset
    from vio.sim.generate import SimConfig, simulate

    if not 5 <= args.duration <= 3600:  # nan and 1e9 passed and failed after the temp folder: exit 1, not 2
        raise UsageError(f"--duration {args.duration}: 5 to 3600 s (the flight starts with 2 s standing still)")
    if args.keep:  # made (and known writable) before the flight is simulated, not after
        if Path(args.keep).exists() and not Path(args.keep).is_dir():
            raise VioError(f"--keep {args.keep}: is a file, not a folder")
        try:
            Path(args.keep).mkdir(parents=True, exist_ok=True)
        except OSError as e:
            raise VioError(f"--keep {args.keep}: cannot make the folder ({e.strerror or e})") from None
        if not os.access(args.keep, os.W_OK):
            raise VioError(f"--keep {args.keep}: the folder is not writable")
    with tempfile.TemporaryDirectory(prefix="kestrel-demo-") as tmp:
        root = Path(args.keep) if args.keep else Path(tmp)
        data = root / "flight"
        print(f"demo: simulating a {args.duration:g} s {args.profile} flight (seed {args.seed}) into {data}")
        simulate(data, SimConfig(profile=args.profile, duration_s=args.duration, seed=args.seed),
                 overwrite=True, progress=not args.no_progress)
        dataset = EurocDataset(data)
        tum = TumSink(root / "trajectory.tum")
        try:
            res = replay(dataset, sinks=[tum], progress=not args.no_progress)
        finally:
            tum.close()
        ev = evaluate(res.trajectory(), dataset.groundtruth.trajectory)
        timing = res.stats_dict()["timing_ms"]
        print(ev.summary())
        print(f"speed: {res.frames} frames in {res.wall_s:.1f} s = real-time factor {res.realtime_factor:.2f} "
              f"(front end {timing['frontend_ms']['mean']:.1f} ms, back end {timing['backend_ms']['mean']:.1f} ms "
              f"per frame); resets: {res.resets}")
        if args.keep:
            print(f"demo: dataset in {data}, trajectory in {root / 'trajectory.tum'}")
    return 0
