"""Can the SITL camera keep up? Render cost of one stereo pair by drivers/sitl_camera.py, as a real-time factor.

    python -m bench.sitl.render_rate [--width 320 --height 200 --fps 15 --frames 40]

Renders `--frames` stereo pairs along a box path in the room (the closed-loop mission's poses) and prints
ms per pair and the real-time factor (camera-seconds rendered per wall second; >= 1 keeps up, on one core,
before the estimator's own cost). Quoted in docs/autopilot.md, "Closed-loop SITL test".
"""

from __future__ import annotations

import argparse
import os
import time

import numpy as np

from bench.sitl import mission as msn
from bench.sitl.run import HOME
from drivers.sitl_camera import SitlCameraSource, T_world_body_from_sim


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--width", type=int, default=320)
    ap.add_argument("--height", type=int, default=200)
    ap.add_argument("--fps", type=float, default=15.0)
    ap.add_argument("--frames", type=int, default=40)
    args = ap.parse_args(argv)
    src = SitlCameraSource("tcp:unused", HOME, width=args.width, height=args.height, fps=args.fps)
    src._renderers()  # scene and per-pixel rays: startup cost, not per frame
    path = msn.box()
    poses = [T_world_body_from_sim([1.0, 0, 0, 0], path.target(t)[0])
             for t in np.linspace(0, path.duration_s, args.frames)]
    t0, c0 = time.perf_counter(), time.process_time()
    for k, T in enumerate(poses):
        src.render(T, k)
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    ms = wall / len(poses) * 1e3
    print(f"{args.width}x{args.height}: {ms:.1f} ms per stereo pair (CPU {cpu / len(poses) * 1e3:.1f} ms), "
          f"real-time factor at {args.fps:g} Hz: {1e3 / (ms * args.fps):.2f}; load average {os.getloadavg()[0]:.1f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
