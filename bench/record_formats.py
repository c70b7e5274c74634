"""Bytes per second and CPU per second of data of the recorders, on one core: EuRoC PNG vs MCAP (png/jpeg/raw).

    python bench/record_formats.py [DATASET] [--seconds 10] [--json out.json]

Reads the frames and IMU of DATASET (default: a simulated 752x480 survey flight, realistic variant) into
memory first, then writes them with each writer on one thread (OpenCV limited to one thread, the process
pinned to CPU 0 where the OS allows it) and reports the output size and the process CPU time, both per second
of recorded data. The daemon's recorder does the same work on its own thread.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path


def _size(path: Path) -> int:
    if path.is_file():
        return path.stat().st_size
    return sum(p.stat().st_size for p in path.rglob("*") if p.is_file())


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("dataset", nargs="?")
    ap.add_argument("--seconds", type=float, default=10.0)
    ap.add_argument("--json")
    args = ap.parse_args(argv)
    import cv2

    cv2.setNumThreads(1)
    if hasattr(os, "sched_setaffinity"):
        os.sched_setaffinity(0, {0})
    from vio.io.bag import McapWriter
    from vio.io.euroc import EurocDataset, EurocWriter
    from vio.types import ImuSample, StereoFrame

    tmp = Path(tempfile.mkdtemp())
    try:
        src = args.dataset
        if src is None:
            from vio.sim.generate import SimConfig, simulate

            src = tmp / "sim"
            simulate(src, SimConfig(duration_s=args.seconds + 1, variant="realistic"))
        ds = EurocDataset(src)
        t0 = int(ds.frame_t[0])
        events = []
        for ev in ds.events(t_end_ns=t0 + int(args.seconds * 1e9)):
            if isinstance(ev, StereoFrame):
                ev = StereoFrame(ev.t_ns, ev.left, ev.right_image(), seq=ev.seq)
            events.append(ev)
        ts = [e.t_ns for e in events]
        data_s = (max(ts) - min(ts)) * 1e-9
        w, h = ds.calibration.cam0.width, ds.calibration.cam0.height
        print(f"{sum(isinstance(e, StereoFrame) for e in events)} stereo frames {w}x{h}, "
              f"{sum(isinstance(e, ImuSample) for e in events)} IMU samples, {data_s:.1f} s of data")
        out = {"data_s": data_s, "size": f"{w}x{h}"}
        writers = {"euroc png": lambda p: EurocWriter(p, ds.calibration, flush_interval_s=0.5),
                   "euroc png level 1": lambda p: EurocWriter(p, ds.calibration, flush_interval_s=0.5, png_level=1),
                   "mcap png": lambda p: McapWriter(p.with_suffix(".mcap"), "png"),
                   "mcap jpeg": lambda p: McapWriter(p.with_suffix(".mcap"), "jpeg"),
                   "mcap raw": lambda p: McapWriter(p.with_suffix(".mcap"), "raw")}
        for name, make in writers.items():
            path = tmp / name.replace(" ", "_")
            c0, w0 = time.process_time(), time.perf_counter()
            with make(path) as wr:
                for e in events:
                    (wr.write_imu(e) if isinstance(e, ImuSample) else wr.write_frame(e))
            cpu, wall = time.process_time() - c0, time.perf_counter() - w0
            target = path if path.exists() else path.with_suffix(".mcap")
            size = _size(target)
            print(f"{name:>17}: {size / data_s / 1e6:6.2f} MB/s, CPU {cpu / data_s:5.3f} s per s of data "
                  f"({100 * cpu / data_s:.0f} % of one core), wall {wall:.1f} s")
            out[name] = {"MB_per_s": size / data_s / 1e6, "cpu_s_per_s": cpu / data_s, "wall_s": wall}
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    if args.json:
        Path(args.json).write_text(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
