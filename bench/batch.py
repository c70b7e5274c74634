"""Speed-up of `vio batch` on this machine's cores: the same flights with 1 worker, N local workers and Ray.

    python bench/batch.py [--flights 4] [--duration 15] [--size 752x480] [--workers 2] [--ray] [--json out.json]
                          [--flights-dir DIR]

Simulates the flights once (seeds 0..F-1, survey profile, realistic variant) into a temporary folder (or
into --flights-dir, where flights simulated by an earlier run with the same settings are reused: repeated
measurements on a busy machine then cost only the batches), then
runs `run_batch` with 1 worker, with --workers local processes and (with --ray) on a local Ray instance of
--workers CPUs, and prints the wall time of each and the speed-up over one worker. Each replay is
single-threaded (vio.app.batch), so the speed-up measures the engine, not BLAS threads.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--flights", type=int, default=4)
    ap.add_argument("--duration", type=float, default=15.0)
    ap.add_argument("--size", default="752x480")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--ray", action="store_true", help="also time a local Ray instance")
    ap.add_argument("--json", help="write the figures here")
    ap.add_argument("--flights-dir", help="simulate the flights here and reuse them in later runs")
    args = ap.parse_args(argv)
    from vio.app.batch import run_batch
    from vio.sim.generate import SimConfig, simulate

    w, h = (int(x) for x in args.size.split("x"))
    load0 = os.getloadavg()
    print(f"load average before: {load0[0]:.2f} / {load0[1]:.2f} / {load0[2]:.2f}", file=sys.stderr, flush=True)
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        flights = []
        sims = Path(args.flights_dir) if args.flights_dir else root
        for seed in range(args.flights):
            f = sims / f"f{seed}_{args.duration:g}s_{args.size}"
            if not (f / "complete").is_file():  # not simulated yet, or cut short
                print(f"simulating {f.name} ...", file=sys.stderr, flush=True)
                simulate(f, SimConfig(duration_s=args.duration, width=w, height=h, seed=seed), overwrite=True)
                (f / "complete").write_text("")
            flights.append(str(f))
        out: dict = {"flights": args.flights, "duration_s": args.duration, "size": args.size,
                     "load_average_start": list(load0)}
        runs = [("1 worker", 1, None), (f"{args.workers} local workers", args.workers, None)]
        if args.ray:
            runs.append((f"ray local, {args.workers} CPUs", args.workers, "local"))
        base = None
        for name, n, ray in runs:
            t0 = time.perf_counter()
            rep = run_batch(flights, root / name.replace(" ", "_"), workers=n, ray_address=ray, progress=False)
            wall = time.perf_counter() - t0
            base = base or wall
            rtf = rep["summary"]["realtime_factor"]
            rtf_text = f"{rtf['mean']:.2f}" if rtf else "- (all failed)"
            print(f"{name:>24}: {wall:6.1f} s for {args.flights} x {args.duration:g} s flights, speed-up "
                  f"{base / wall:.2f}, per-flight real-time factor mean {rtf_text}")
            out[name] = {"wall_s": wall, "speedup": base / wall, "rtf_mean": rtf and rtf["mean"]}
    out["load_average_end"] = list(os.getloadavg())
    print(f"load average after: {out['load_average_end'][0]:.2f}", file=sys.stderr)
    if args.json:
        Path(args.json).write_text(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
