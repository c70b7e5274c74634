"""How close the in-flight IMU-against-camera checks come to a verdict on flights whose IMU is right.

    nice python bench/imu_checks.py [--only NAME ...] [--duration 60] [--cache DIR]

The checks (vio/sanity.py GyroScaleCheck: units and scale; vio/backend/time_offset.py `_check_mount`: the
camera-IMU rotation) stop the estimator for the rest of a run: a verdict on a right IMU would take a good flight's
poses away in the air. This replays the accuracy matrix's flights (bench/accuracy_matrix.py, real EuRoC IMUs among
them where ../shared/data is) and reports, per flight, the scale check's worst share of "too much" / "too little"
pairs over any window it decides on (a verdict needs 0.75) and the largest rotation any mount fit read against the
calibration (the limits: 4 deg over turns about two axes, 15 about one), with the replay's resets and ATE. Flights
are generated once into the bench cache (bench/flights.py); replays run one after the other in this process.
"""

from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import argparse  # noqa: E402
import sys  # noqa: E402
from pathlib import Path  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

import vio.backend.time_offset as time_offset  # noqa: E402
from bench.accuracy_matrix import cases, replay_case  # noqa: E402
from bench.flights import DEFAULT_CACHE, ensure_flight  # noqa: E402
from vio import sanity  # noqa: E402


class Recorder:
    """Wraps the checks' inputs for one replay: every pair the scale check is given, every mount fit's reading."""

    def __init__(self) -> None:
        self.pairs: list[tuple[float, float, float]] = []
        self.fits: list[tuple[float, float, bool]] = []  # (deg, sigma deg, about one axis only)
        self._add = sanity.GyroScaleCheck.add
        self._disagreement = time_offset.rotation_disagreement

    def __enter__(self) -> Recorder:
        rec, add, disagreement = self, self._add, self._disagreement

        def recorded_add(check, camera_rad, gyro_rad, span_s):
            rec.pairs.append((camera_rad, gyro_rad, span_s))
            return add(check, camera_rad, gyro_rad, span_s)

        def recorded_disagreement(fit, R_body_cam):
            seen = disagreement(fit, R_body_cam)
            if seen is not None:
                rec.fits.append((seen[0], seen[1], fit.axis_rates[1] < time_offset.MIN_AXIS_RATE_RAD_S))
            return seen

        sanity.GyroScaleCheck.add = recorded_add
        time_offset.rotation_disagreement = recorded_disagreement
        return self

    def __exit__(self, *exc) -> None:
        sanity.GyroScaleCheck.add = self._add
        time_offset.rotation_disagreement = self._disagreement

    def worst_shares(self) -> tuple[float, float]:
        """The largest share of "too much" and of "too little" pairs in any window the scale check decides on."""
        check = sanity.GyroScaleCheck()
        worst = [0.0, 0.0]
        for c, g, span in self.pairs:
            self._add(check, c, g, span)
            for k, side in enumerate((check.high, check.low)):
                recent = side[-3 * sanity.SCALE_PAIRS:]
                if len(recent) >= sanity.SCALE_PAIRS:
                    worst[k] = max(worst[k], sum(p[0] for p in recent) / len(recent))
        return worst[0], worst[1]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--only", nargs="*", default=None, help="case names to run")
    ap.add_argument("--duration", type=float, default=60.0, help="flight length [s]")
    ap.add_argument("--cache", type=Path, default=DEFAULT_CACHE, help="flight cache folder")
    args = ap.parse_args(argv)
    print("| flight | scale pairs | worst share too much / too little | mount fits | largest reading, two axes / one "
          "axis [deg] | resets | ATE SE(3) [mm] |")
    print("| --- | --- | --- | --- | --- | --- | --- |")
    for case in cases(args.duration):
        if args.only and case.name not in args.only:
            continue
        path = ensure_flight(case.flight, args.cache)
        with Recorder() as rec:
            row = replay_case(case, path, None)
        hi, lo = rec.worst_shares()
        two = max((a for a, _, one in rec.fits if not one), default=float("nan"))
        one = max((a for a, _, one in rec.fits if one), default=float("nan"))
        print(f"| {case.name} | {len(rec.pairs)} | {hi:.2f} / {lo:.2f} | {len(rec.fits)} | {two:.2f} / {one:.2f} | "
              f"{row.get('resets')} | {row.get('ate_se3_m', float('nan')) * 1e3:.1f} |", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
