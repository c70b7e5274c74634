"""Real-time benchmark of the whole pipeline on one core.

    python bench/realtime.py DATASET [--json out.json] [--config FILE] [--all-cores | --cpu N]
                             [--png as-is|stored|euroc]

Pins the process to CPU 0 (or N) and limits OpenMP/BLAS/OpenCV to one thread (as `taskset -c 0` with
OMP/OPENBLAS/MKL_NUM_THREADS=1 would), replays the dataset as fast as possible and prints the real-time
factor (data seconds / wall seconds), per-frame front-end/back-end/total times (mean, p50/p95/p99, max; `--json`
also keeps every frame's) and the back-end time per
10 s segment, which must stay flat over a long flight (fixed-lag smoother). On a machine that other work
shares, the CPU-time factor (data seconds / process CPU seconds) is the steadier figure of the two.

PNG decoding is part of the replay, and its cost depends on how the files were written: `--png stored`
replays a copy with the images re-written as Kestrel's recorder and simulator write them (no deflate, no row
filters: 0.2 ms per 752x480 image here), `--png euroc` as EuRoC's own files are (stored deflate blocks with
filtered rows: 1.3-1.4 ms, the same as the V1_01 excerpt's files), `as-is` (default) reads DATASET's files.

The image files are read once before the timed replay (`--cold` leaves that out): a flight whose files are not in
the page cache replays ~8 % slower here (aggressive-realistic-seed1-30s after dropping the caches: 4.60 against
5.00 / 5.01 on the next two runs), which made the first of two configurations timed on a flight look slower.
With the files read first: 4.97 and 4.93 right after dropping the caches, 4.84-5.24 on warm runs.
"""

from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import argparse  # noqa: E402
import contextlib  # noqa: E402
import json  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

PNG_CHOICES = ("stored", "euroc")


def reencoded_copy(dataset: str, how: str, out: Path) -> Path:
    """A copy of DATASET under `out` with every camera image re-written as `how` (lossless: same pixels)."""
    import shutil

    import cv2

    from vio.io.euroc import png_write_params

    # euroc: level 0 keeps deflate out, OpenCV's default row filters stay in (EuRoC's are Paeth and Average)
    params = png_write_params(0) if how == "stored" else [cv2.IMWRITE_PNG_COMPRESSION, 0]
    src = Path(dataset)
    for f in src.rglob("*"):
        dst = out / f.relative_to(src)
        if f.is_dir():
            dst.mkdir(parents=True, exist_ok=True)
        elif f.suffix.lower() == ".png" and f.parent.name == "data":
            dst.parent.mkdir(parents=True, exist_ok=True)
            if not cv2.imwrite(str(dst), cv2.imread(str(f), cv2.IMREAD_UNCHANGED), params):
                raise OSError(f"{dst}: cannot write")
        else:
            dst.parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(f, dst)
    return out


def _warm_page_cache(dataset: Path) -> None:
    """Read every file under the cameras' data folders once, so that the timed replay measures decoding and
    estimation, not the disk."""
    for cam in sorted((dataset / "mav0").glob("cam*/data")):
        for f in cam.iterdir():
            with contextlib.suppress(OSError):  # an unreadable image is the replay's to report
                f.read_bytes()


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("dataset")
    ap.add_argument("--json", help="write the summary here")
    ap.add_argument("--config", help="TOML configuration")
    ap.add_argument("--all-cores", action="store_true", help="do not pin to a CPU")
    ap.add_argument("--cpu", type=int, default=0, help="the CPU to pin to (default 0)")
    ap.add_argument("--cold", action="store_true", help="do not read the image files once before timing (the page "
                    "cache then decides part of the figure)")
    ap.add_argument("--png", choices=("as-is", *PNG_CHOICES), default="as-is",
                    help="replay a copy with the images re-written: stored (Kestrel's recorder) or euroc (as EuRoC's)")
    args = ap.parse_args(argv)
    if args.png != "as-is":
        import tempfile

        tmp = tempfile.TemporaryDirectory(prefix="kestrel-realtime-")
        print(f"re-writing the images of {args.dataset} as {args.png} PNGs ...", flush=True)
        dataset = str(reencoded_copy(args.dataset, args.png, Path(tmp.name) / "ds"))
    else:
        dataset = args.dataset
    if not args.all_cores and hasattr(os, "sched_setaffinity"):
        os.sched_setaffinity(0, {args.cpu})
    import cv2

    cv2.setNumThreads(1)
    from vio import VioError
    from vio.app.replay import replay
    from vio.config import load_config
    from vio.io.euroc import EurocDataset

    if not args.cold:
        _warm_page_cache(Path(dataset))
    try:
        ds = EurocDataset(dataset)
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
    d["png"] = args.png
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
