#!/usr/bin/env python3
"""Front-end benchmark: per-stage timings on one core, feature/track statistics, and (for a `vio simulate`
dataset) depth and outlier errors against the exact truth.

    taskset -c 0 python bench/frontend.py /work/shared/data/euroc/V1_01_easy_excerpt --json out.json

Prints a table and writes the figures as JSON. Threads are limited to one before numpy/OpenCV load, as on
the target computer's dedicated core.
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[_var] = "1"

import argparse  # noqa: E402
import json  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import cv2  # noqa: E402
import numpy as np  # noqa: E402

from vio import VioError  # noqa: E402
from vio.config import load_config  # noqa: E402
from vio.frontend.debug_view import TrackImageWriter  # noqa: E402
from vio.frontend.evaluate import SimTruth, stage_timings, track_stats, truth_errors  # noqa: E402
from vio.frontend.runner import run_frontend  # noqa: E402
from vio.frontend.tracker import StereoTracker  # noqa: E402
from vio.io.euroc import EurocDataset  # noqa: E402


def _time_cpu(tracker: StereoTracker) -> list[float]:
    """Wrap tracker.process to record its thread CPU time [ms] per call into the returned list."""
    out: list[float] = []
    process = tracker.process

    def timed(frame, R=None):
        t = time.thread_time()
        ff = process(frame, R)
        out.append((time.thread_time() - t) * 1e3)
        return ff

    tracker.process = timed
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("dataset", help="EuRoC dataset folder")
    ap.add_argument("--config", help="TOML config ([frontend] section is used)")
    ap.add_argument("--json", help="write the results here (default: frontend_bench_<dataset>.json)")
    ap.add_argument("--max-frames", type=int)
    ap.add_argument("--no-gyro", action="store_true", help="track without the gyro rotation prior")
    ap.add_argument("--keyframe-every", type=int, default=5, help="stand-in for the back end's keyframes")
    ap.add_argument("--show-tracks", metavar="DIR", help="write track images here")
    ap.add_argument("--no-truth", action="store_true", help="skip the simulation-truth evaluation")
    args = ap.parse_args(argv)
    cv2.setNumThreads(1)
    try:
        cfg = load_config(args.config).frontend
        ds = EurocDataset(args.dataset)
        writer = TrackImageWriter(args.show_tracks, ds.calibration) if args.show_tracks else None
        frames = []
        tracker = StereoTracker(ds.calibration, cfg)
        cpu_ms = _time_cpu(tracker)
        load = os.getloadavg()[0]
        t0 = time.perf_counter()
        for frame, ff in run_frontend(ds, cfg, args.max_frames, tracker=tracker, use_gyro=not args.no_gyro,
                                      keyframe_every=args.keyframe_every):
            frames.append(ff)
            if writer:
                writer.write(frame, ff)
        wall = time.perf_counter() - t0
        tracked = [f for f in frames[1:] if f.tracking_ok]  # frame 0 only detects
        result = {
            "dataset": str(Path(args.dataset).resolve()), "cpu_affinity": sorted(os.sched_getaffinity(0)),
            "opencv": cv2.__version__, "gyro_prior": not args.no_gyro, "wall_s": wall,
            "timings_ms": stage_timings(tracked),
            # thread CPU time of process(): on a shared machine wall time also counts waiting for the core
            "cpu_ms_per_frame_mean": float(np.mean(cpu_ms[1:])) if len(cpu_ms) > 1 else float("nan"),
            "load_average_1min": [load, os.getloadavg()[0]], **track_stats(frames),
        }
        sim_yaml = Path(args.dataset) / "simulation.yaml"
        if sim_yaml.is_file() and not args.no_truth:
            result["truth"] = truth_errors(frames, SimTruth(args.dataset, ds.calibration))
    except VioError as e:
        print(f"bench/frontend.py: error: {e}", file=sys.stderr)
        return 1
    print(f"{len(frames)} frames of {result['dataset']} on CPUs {result['cpu_affinity']}, load average "
          f"{result['load_average_1min'][0]:.1f} -> {result['load_average_1min'][1]:.1f}")
    print(f"{'stage':<12}{'mean':>8}{'p50':>8}{'p99':>8}  [ms]")
    for k, v in result["timings_ms"].items():
        print(f"{k:<12}{v['mean']:8.2f}{v['p50']:8.2f}{v['p99']:8.2f}")
    for k, v in result.items():
        if k not in ("timings_ms", "truth", "dataset", "cpu_affinity", "load_average_1min"):
            print(f"{k:<28} {v:.3f}" if isinstance(v, float) else f"{k:<28} {v}")
    for k, v in result.get("truth", {}).items():
        print(f"truth.{k:<34} {v:.4f}" if isinstance(v, float) else f"truth.{k:<34} {v}")
    out = Path(args.json or f"frontend_bench_{Path(args.dataset).resolve().name}.json")
    out.write_text(json.dumps(result, indent=2) + "\n")
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
