"""Measure the MAVLink IMU source on UDP loopback: rate, stamp jitter, latency, TIMESYNC round trip and how
far each host stamp lies from the instant the sample was made.

    python bench/mavlink_imu.py [--seconds 10] [--rate 200] [--ppm 50] [--offset-s 5]

The flight controller is the fake one of tests/test_mavlink_imu.py (HIGHRES_IMU packed by pymavlink,
TIMESYNC answered on a clock `--ppm` fast and `--offset-s` ahead). Results are quoted in docs/autopilot.md.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
import test_mavlink_imu as t  # noqa: E402  (its FakeFC and stream(): one fake flight controller, not two)

from drivers.mavlink_imu import MavlinkImuSource  # noqa: E402
from drivers.mavlink_link import MavlinkLink  # noqa: E402


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seconds", type=float, default=10.0)
    p.add_argument("--rate", type=float, default=200.0)
    p.add_argument("--ppm", type=float, default=50.0)
    p.add_argument("--offset-s", type=float, default=5.0)
    args = p.parse_args()
    t.PERIOD_NS = int(round(1e9 / args.rate))
    fc_clock = lambda h: int(args.offset_s * 1e9 + h * (1 + args.ppm * 1e-6))  # noqa: E731
    n = int(args.seconds * args.rate)
    fc = t.FakeFC(t.stream(fc_clock, n), fc_clock)
    fc.start()
    src = MavlinkImuSource(MavlinkLink(f"udpout:127.0.0.1:{fc.port}"), rate_hz=args.rate, owns_link=True)
    cpu0 = time.process_time()
    src.start()
    try:
        samples = t.collect(src, args.seconds + 0.5)
        h = src.health()
    finally:
        src.stop()
        fc.close()
    cpu = time.process_time() - cpu0
    ks = np.array([int(round(s.gyro[0] * 1e3)) for s in samples])
    err = (np.array([s.t_ns for s in samples]) - (fc.start_ns + ks * t.PERIOD_NS)) / 1e6
    settled = np.abs(err[ks >= args.rate])  # after the first second
    print(f"samples {len(samples)} of {n}; rate {h['rate_hz']} Hz; stamp jitter {h['stamp_jitter_us']} us; "
          f"gaps {h['stream']['gaps']}")
    print(f"latency (arrival - mapped stamp) median {h['latency_ms_median']} ms, p99 {h['latency_ms_p99']} ms; "
          f"TIMESYNC rtt median {h['timesync_rtt_ms_median']} ms; drift found {h['clock']['drift_ppm']} ppm "
          f"(true {-args.ppm / (1 + args.ppm * 1e-6):.1f})")
    print(f"host stamp error after 1 s: median {np.median(settled):.3f} ms, p99 {np.percentile(settled, 99):.3f} ms, "
          f"max {settled.max():.3f} ms; process CPU {cpu / args.seconds * 100:.1f} % of one core "
          "(source + fake FC)")


if __name__ == "__main__":
    main()
