"""What the live view costs the frame loop: a replay without a view, with a view saved to .rrd, with a
viewer that is slow (50 ms per frame) and with `serve` and no viewer connected.

    taskset -c 1 python bench/view.py [DATASET] [--repeat 3] [--json out.json]

For each case, --repeat replays (the cases interleaved, so that a change in the machine's load hits all of
them alike), and per case the median of: the replay's mean wall time per frame, and the process CPU time
per frame (all threads, Rerun's own included), split into the frame loop's thread and the threads beside
it (the view thread and Rerun's: process CPU minus the main thread's, exited threads included). On one
core (taskset) the CPU of the threads beside the frame loop is what the frame loop loses to the view; it
is the robust figure on a shared machine, where wall time and even the main thread's CPU time move by a
few ms per frame with other users' load (cache, memory bandwidth). The view logs at bounded wall-clock
rates, so its CPU is per second, not per frame: it is also given per second and per frame of a live 20 Hz
camera (a replay runs at whatever speed the machine allows). A warm-up replay goes first, not
counted. Also the time `LiveView.submit()` took in the frame
loop (mean, p99, max) and how many view frames were logged, thinned (to [view] rate_hz / image_hz) and
dropped. Default dataset: a simulated 752x480 survey flight of 15 s (realistic variant).
OpenCV/BLAS limited to one thread.
"""

from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import argparse  # noqa: E402
import json  # noqa: E402
import shutil  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("dataset", nargs="?")
    ap.add_argument("--repeat", type=int, default=3, help="replays per case (interleaved)")
    ap.add_argument("--json")
    args = ap.parse_args(argv)
    import cv2
    import numpy as np

    cv2.setNumThreads(1)
    from vio.app.replay import replay
    from vio.app.view import LiveView
    from vio.config import ViewConfig
    from vio.io.euroc import EurocDataset

    load0 = os.getloadavg()[0]
    tmp = Path(tempfile.mkdtemp())
    runs: dict[str, list[dict]] = {}
    try:
        src = args.dataset
        if src is None:
            from vio.sim.generate import SimConfig, simulate

            src = tmp / "sim"
            simulate(src, SimConfig(duration_s=15, variant="realistic"))

        def slow(target):
            v = LiveView(target, None)
            fast = v._log
            v._log = lambda *a: (time.sleep(0.05), fast(*a))
            return v

        ports = iter(range(9091, 9191))  # a web viewer's port stays bound until the process ends
        cases = {"no view": lambda: None, "rrd": lambda: LiveView(str(tmp / "a.rrd"), None),
                 "slow viewer (50 ms/frame)": lambda: slow(str(tmp / "b.rrd")),
                 "serve, no viewer": lambda: LiveView("serve", None, ViewConfig(web_port=next(ports)))}
        print(f"cores: {sorted(os.sched_getaffinity(0))}, load average {os.getloadavg()[0]:.2f}", flush=True)
        replay(EurocDataset(src), None, progress=False)  # warm-up (imports, first-call costs), not counted
        for rep in range(args.repeat):
            for name, make in cases.items():
                ds = EurocDataset(src)
                view = make()
                cpu0, main0, wall0 = time.process_time(), time.thread_time(), time.perf_counter()
                res = replay(ds, None, progress=False, view=view)
                if view is not None:
                    view.close()
                wall_s = time.perf_counter() - wall0
                n = max(1, res.frames)
                cpu_ms = (time.process_time() - cpu0) * 1e3 / n
                main_ms = (time.thread_time() - main0) * 1e3 / n
                st = res.stats_dict()["timing_ms"]["total_ms"]
                run = {"frame_ms_mean": st["mean"], "cpu_ms_per_frame": cpu_ms, "main_cpu_ms_per_frame": main_ms,
                       "other_threads_cpu_ms_per_frame": cpu_ms - main_ms,
                       "other_threads_cpu_ms_per_s": (cpu_ms - main_ms) * n / wall_s, "rtf": res.realtime_factor}
                if view is not None:
                    run["view"] = view.stats()
                runs.setdefault(name, []).append(run)
                print(f"  run {rep + 1} {name}: frame {st['mean']:.2f} ms, CPU {cpu_ms:.2f} ms/frame (frame loop "
                      f"{main_ms:.2f}, other threads {cpu_ms - main_ms:.2f})", flush=True)
        cores = sorted(os.sched_getaffinity(0))
        out: dict = {"command": f"taskset -c {','.join(map(str, cores))} python bench/view.py "
                                + " ".join(argv if argv is not None else sys.argv[1:]),
                     "load_average_start": load0, "load_average_end": os.getloadavg()[0], "cores": cores}
        base = None
        for name, rs in runs.items():
            frame = float(np.median([r["frame_ms_mean"] for r in rs]))
            cpu = float(np.median([r["cpu_ms_per_frame"] for r in rs]))
            other = float(np.median([r["other_threads_cpu_ms_per_frame"] for r in rs]))
            per_s = float(np.median([r["other_threads_cpu_ms_per_s"] for r in rs]))
            base = base or {"frame": frame, "cpu": cpu, "other": other}
            line = (f"{name:>26}: per frame mean {frame:.2f} ms (+{frame - base['frame']:.2f}), CPU {cpu:.2f} ms "
                    f"(+{cpu - base['cpu']:.2f}), threads beside the frame loop {other:.3f} ms "
                    f"(+{other - base['other']:.3f}; {per_s:.1f} ms per s, {per_s / 20:.2f} ms per frame of a 20 Hz "
                    f"camera), real-time factor {np.median([r['rtf'] for r in rs]):.2f}")
            out[name] = {"frame_ms_mean": frame, "cpu_ms_per_frame": cpu, "extra_frame_ms": frame - base["frame"],
                         "extra_cpu_ms": cpu - base["cpu"], "other_threads_cpu_ms": other,
                         "extra_other_threads_cpu_ms": other - base["other"], "other_threads_cpu_ms_per_s": per_s,
                         "runs": rs}
            if "view" in rs[0]:
                vs = rs[-1]["view"]
                sub = max(r["view"]["submit_ms"]["max"] for r in rs)
                line += (f"; submit() mean {vs['submit_ms']['mean']:.3f} ms, p99 {vs['submit_ms']['p99']:.3f}, max "
                         f"(all runs) {sub:.3f}; last run {vs['logged']} logged ({vs['images']} images), "
                         f"{vs['thinned']} thinned, {vs['dropped']} dropped")
            print(line)
        print(f"load average at the end {out['load_average_end']:.2f}")
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    if args.json:
        Path(args.json).write_text(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
