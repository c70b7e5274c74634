"""What the live view costs the frame loop: a replay without a view, with a view saved to .rrd, with a
viewer that is slow (50 ms per frame) and with `serve` and no viewer connected.

    python bench/view.py [DATASET] [--json out.json]

Prints the replay's mean per-frame time and real-time factor for each, and the time `LiveView.submit()`
took in the frame loop (mean, p99, max), with how many view frames were dropped. Default dataset: a simulated
752x480 survey flight of 15 s (realistic variant). OpenCV/BLAS limited to one thread.
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
    ap.add_argument("--json")
    args = ap.parse_args(argv)
    import cv2

    cv2.setNumThreads(1)
    from vio.app.replay import replay
    from vio.app.view import LiveView
    from vio.io.euroc import EurocDataset

    tmp = Path(tempfile.mkdtemp())
    out: dict = {}
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

        cases = {"no view": lambda: None, "rrd": lambda: LiveView(str(tmp / "a.rrd"), None),
                 "slow viewer (50 ms/frame)": lambda: slow(str(tmp / "b.rrd")),
                 "serve, no viewer": lambda: LiveView("serve", None, web_port=9091)}
        for name, make in cases.items():
            ds = EurocDataset(src)
            view = make()
            res = replay(ds, None, progress=False, view=view)
            if view is not None:
                view.close()
            st = res.stats_dict()["timing_ms"]["total_ms"]
            line = f"{name:>26}: per frame mean {st['mean']:.2f} ms, real-time factor {res.realtime_factor:.2f}"
            out[name] = {"frame_ms_mean": st["mean"], "rtf": res.realtime_factor}
            if view is not None:
                vs = view.stats()
                line += (f"; submit() mean {vs['submit_ms']['mean']:.3f} ms, p99 {vs['submit_ms']['p99']:.3f}, "
                         f"max {vs['submit_ms']['max']:.3f}; {vs['logged']} logged, {vs['dropped']} dropped")
                out[name]["view"] = vs
            print(line)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    if args.json:
        Path(args.json).write_text(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
