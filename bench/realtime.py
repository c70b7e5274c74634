"""Real-time benchmark of the whole pipeline on one core.

    python bench/realtime.py DATASET [--json out.json] [--config FILE] [--all-cores | --cpu N]

Pins the process to CPU 0 (or N) and limits OpenMP/BLAS/OpenCV to one thread (as `taskset -c 0` with
OMP/OPENBLAS/MKL_NUM_THREADS=1 would), replays the dataset as fast as possible and prints the real-time
factor (data seconds / wall seconds), per-frame front-end/back-end/total times (mean, p50/p95/p99, max; `--json`
also keeps every frame's) and the back-end time per
10 s segment, which must stay flat over a long flight (fixed-lag smoother). On a machine that other work
shares, the CPU-time factor (data seconds / process CPU seconds) is the steadier figure of the two.
"""

from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import argparse  # noqa: E402
import json  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("dataset")
    ap.add_argument("--json", help="write the summary here")
    ap.add_argument("--config", help="TOML configuration")
    ap.add_argument("--all-cores", action="store_true", help="do not pin to a CPU")
    ap.add_argument("--cpu", type=int, default=0, help="the CPU to pin to (default 0)")
    args = ap.parse_args(argv)
    if not args.all_cores and hasattr(os, "sched_setaffinity"):
        os.sched_setaffinity(0, {args.cpu})
    import cv2

    cv2.setNumThreads(1)
    from vio import VioError
    from vio.app.replay import replay
    from vio.config import load_config
    from vio.io.euroc import EurocDataset

    try:
        ds = EurocDataset(args.dataset)
        cfg = load_config(args.config)
        cpu0 = time.process_time()
        res = replay(ds, cfg, progress=False)
        cpu_s = time.process_time() - cpu0
    except VioError as e:
        print(f"realtime: {e}", file=sys.stderr)
        return 1
    d = res.stats_dict()
    per = d.pop("per_frame")
    t = np.array([f["t_ns"] for f in per], dtype=np.int64)
    seg = ((t - t[0]) // 10_000_000_000) if len(t) else np.zeros(0, np.int64)
    d["backend_ms_per_10s"] = [float(np.mean([f["backend_ms"] for f, s in zip(per, seg) if s == k]))
                               for k in range(int(seg.max()) + 1)] if len(seg) else []
    d["dataset"] = str(args.dataset)
    d["cpu"] = "all" if args.all_cores else f"cpu{args.cpu}"
    d["cpu_s"] = cpu_s
    d["realtime_factor_cpu"] = d["data_s"] / max(cpu_s, 1e-9)
    print(f"{args.dataset}: {d['frames']} frames, {d['data_s']:.1f} s data in {d['wall_s']:.1f} s -> "
          f"real-time factor {d['realtime_factor']:.2f} (CPU time {cpu_s:.1f} s: {d['realtime_factor_cpu']:.2f}); "
          f"resets {d['resets']}, keyframes {d['keyframes']}")
    for k, v in d["timing_ms"].items():
        print(f"  {k:<12} mean {v['mean']:6.1f}  p50 {v['p50']:6.1f}  p95 {v['p95']:6.1f}  p99 {v['p99']:6.1f}  "
              f"max {v['max']:6.1f}")
    print("  back end per 10 s [ms]: " + " ".join(f"{x:.1f}" for x in d["backend_ms_per_10s"]))
    if args.json:
        with open(args.json, "w") as f:
            json.dump({**d, "per_frame": per}, f, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
