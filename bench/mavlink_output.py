"""Measure the MAVLink output on UDP loopback: send rate vs rate_hz, stamp age at receipt, TIMESYNC round trip.

    python bench/mavlink_output.py [--seconds 10] [--rate 30]

A 200 Hz feeder thread plays the estimator; a local mavutil endpoint plays the autopilot (HEARTBEAT and a
TIMESYNC request every 0.2 s). Results are quoted in docs/autopilot.md.
"""

from __future__ import annotations

import argparse
import os
import threading
import time

import numpy as np

os.environ["MAVLINK20"] = "1"
from pymavlink import mavutil  # noqa: E402

from drivers.mavlink_out import MavlinkOutput  # noqa: E402
from vio.config import MavlinkConfig  # noqa: E402
from vio.types import NavState  # noqa: E402


def main() -> None:
    ap_args = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap_args.add_argument("--seconds", type=float, default=10.0)
    ap_args.add_argument("--rate", type=float, default=30.0)
    args = ap_args.parse_args()
    ap = mavutil.mavlink_connection("udpin:127.0.0.1:0", source_system=1, dialect="ardupilotmega")
    out = MavlinkOutput(MavlinkConfig(rate_hz=args.rate, mount="rpy"),
                        f"udpout:127.0.0.1:{ap.port.getsockname()[1]}").start()

    st = NavState(0, np.eye(4), np.zeros(3))
    t0, n = time.perf_counter(), 2000
    for _ in range(n):
        out.build_messages(st)
    print(f"build_messages (ODOMETRY): {(time.perf_counter() - t0) / n * 1e3:.3f} ms per state")

    stop = threading.Event()

    def feed() -> None:
        while not stop.is_set():
            out.send_state(NavState(time.monotonic_ns(), np.eye(4), np.zeros(3)))
            time.sleep(0.005)

    threading.Thread(target=feed, daemon=True).start()
    ages_ms, rtt_ms, n_odo = [], [], 0
    t_start, next_req, asked = time.monotonic(), 0.0, set()
    while time.monotonic() - t_start < args.seconds:
        if time.monotonic() > next_req:
            next_req = time.monotonic() + 0.2
            ap.mav.heartbeat_send(mavutil.mavlink.MAV_TYPE_QUADROTOR, mavutil.mavlink.MAV_AUTOPILOT_PX4, 0, 0, 3)
            ts = time.monotonic_ns()
            asked.add(ts)
            ap.mav.timesync_send(0, ts)
        m = ap.recv_match(blocking=True, timeout=0.01)
        if m is None:
            continue
        if m.get_type() == "ODOMETRY":
            n_odo += 1
            ages_ms.append(time.monotonic_ns() / 1e6 - m.time_usec / 1e3)
        elif m.get_type() == "TIMESYNC" and m.ts1 in asked:
            rtt_ms.append((time.monotonic_ns() - m.ts1) / 1e6)
    stop.set()
    out.close()
    print(f"ODOMETRY: {n_odo} in {args.seconds:.1f} s = {n_odo / args.seconds:.2f} Hz (rate_hz {args.rate:g})")
    print(f"stamp age at receipt: median {np.median(ages_ms):.2f} ms, p99 {np.percentile(ages_ms, 99):.2f} ms")
    print(f"TIMESYNC round trip: median {np.median(rtt_ms):.2f} ms, max {np.max(rtt_ms):.2f} ms (n={len(rtt_ms)})")


if __name__ == "__main__":
    main()
