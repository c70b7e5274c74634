"""Subprocess side of the benchmark suite: one `vio replay` under the thread limits the parent chose.

    python bench/child.py [--cv-threads N] [--profile OUT.pstats] [--output-json OUT.json] -- REPLAY ARGS...

Why a separate process: CPU affinity and the BLAS/OpenMP thread variables only take effect before numpy,
OpenCV and gtsam load, and a fresh process per run keeps one run's caches and memory out of the next.
OpenCV's own pool is sized with cv2.setNumThreads here, because no environment variable reaches it.

`--output-json` also times the MAVLink output stage on the replay's own trajectory: each state goes
through MavlinkOutput.send_state() (ODOMETRY built, packed and sent over UDP loopback) as `vio run` does,
with a stepped clock so that every state is due for sending.
"""

from __future__ import annotations

import argparse
import json
import socket
import sys
import time
from pathlib import Path

import numpy as np

FRAME_PERIOD_NS = 50_000_000  # 20 Hz camera: the clock step between states in the output timing


def summary_ms(values: list[float] | np.ndarray) -> dict:
    """mean/p50/p95/p99/max of a list of durations in ms (NaN-free; empty gives zeros)."""
    x = np.asarray(values, dtype=float)
    if len(x) == 0:
        return {"n": 0, "mean": 0.0, "p50": 0.0, "p95": 0.0, "p99": 0.0, "max": 0.0}
    p50, p95, p99 = np.percentile(x, [50, 95, 99])
    return {"n": int(len(x)), "mean": float(x.mean()), "p50": float(p50), "p95": float(p95), "p99": float(p99),
            "max": float(x.max())}


def time_output_stage(tum_path: Path) -> dict:
    """Per-state cost of MavlinkOutput.send_state() for the poses in `tum_path`, sent to a local UDP sink."""
    from drivers.mavlink_out import MavlinkOutput
    from vio.config import MavlinkConfig
    from vio.trajectory import read_tum
    from vio.types import NavState

    traj = read_tum(tum_path)
    sink = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sink.bind(("127.0.0.1", 0))
    clock = [0]
    try:
        cfg = MavlinkConfig(mount="rpy")
    except TypeError:  # a --compare revision from before [mavlink] mount (identity mount then)
        cfg = MavlinkConfig()
    out = MavlinkOutput(cfg, f"udpout:127.0.0.1:{sink.getsockname()[1]}", clock_ns=lambda: clock[0])
    times_ms = []
    try:
        for t_ns, T in zip(traj.t_ns, traj.poses()):
            clock[0] += FRAME_PERIOD_NS
            st = NavState(int(t_ns), T, np.zeros(3))
            t0 = time.perf_counter()
            out.send_state(st)
            times_ms.append((time.perf_counter() - t0) * 1e3)
    finally:
        out.close()
        sink.close()
    return {"output_ms": summary_ms(times_ms), "states_sent": out.stats.states_sent}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--cv-threads", type=int, help="cv2.setNumThreads(N) before the replay")
    ap.add_argument("--profile", metavar="PSTATS", help="run the replay under cProfile and dump the stats here")
    ap.add_argument("--output-json", metavar="JSON", help="time the MAVLink output stage; write the result here")
    ap.add_argument("replay_args", nargs=argparse.REMAINDER, help="-- then the arguments of `vio replay`")
    args = ap.parse_args(argv)
    rargs = args.replay_args[1:] if args.replay_args[:1] == ["--"] else args.replay_args
    import cv2

    if args.cv_threads:
        cv2.setNumThreads(args.cv_threads)
    import importlib

    import vio

    # the CLI of the imported tree: vio/app/cli.py since the app layer, vio/cli.py before (a --compare
    # revision); chosen by file, because an editable install would otherwise serve this tree's vio.app
    cli = "vio.app.cli" if (Path(vio.__file__).parent / "app" / "cli.py").is_file() else "vio.cli"
    vio_main = importlib.import_module(cli).main

    cmd = ["-q", "replay", *rargs]
    if args.profile:
        import cProfile

        prof = cProfile.Profile()
        rc = prof.runcall(vio_main, cmd)
        prof.dump_stats(args.profile)
    else:
        rc = vio_main(cmd)
    if args.output_json and rc == 0:
        tum = Path(rargs[rargs.index("--output") + 1])
        try:
            res = time_output_stage(tum)
        except ImportError as e:  # an older revision under --compare may lack the output module
            res = {"error": f"no output stage: {e}"}
        res["vio_module"] = str(Path(vio.__file__).resolve().parent)
        Path(args.output_json).write_text(json.dumps(res, indent=1) + "\n")
    return rc


if __name__ == "__main__":
    sys.exit(main())
