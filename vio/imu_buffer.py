"""The estimator's one IMU buffer: pre-integration, the front end's gyro prior, the initialisers and the
in-flight time-offset solver all read the same samples (each sample stored once, trimmed by its owner to
the longest history a reader needs)."""

from __future__ import annotations

import bisect
import logging

import gtsam
import numpy as np

from vio.types import ImuSample

log = logging.getLogger(__name__)

TRIM_CHUNK = 64  # samples dropped at a time at the least
MOTION_UNKNOWN_GAP_NS = 100_000_000  # an IMU gap this long: the motion in it is unknown (interpolation is a guess)


class ImuBuffer:
    """Time-ordered IMU samples with interpolation; old samples are trimmed explicitly by the owner."""

    def __init__(self) -> None:
        self.t: list[int] = []
        self.gyro: list[np.ndarray] = []
        self.accel: list[np.ndarray] = []

    def __len__(self) -> int:
        return len(self.t)

    def add(self, s: ImuSample) -> bool:
        """Append a sample; out-of-order or duplicate stamps are dropped (returns False)."""
        if self.t and s.t_ns <= self.t[-1]:
            log.debug("IMU sample at %d not after %d: dropped", s.t_ns, self.t[-1])
            return False
        self.t.append(int(s.t_ns))
        self.gyro.append(np.asarray(s.gyro, dtype=float))
        self.accel.append(np.asarray(s.accel, dtype=float))
        return True

    @property
    def last_t_ns(self) -> int | None:
        return self.t[-1] if self.t else None

    def trim_before(self, t_ns: int, min_keep: int = 0) -> None:
        """Drop samples strictly older than the last sample at or before t_ns (keep one for interpolation),
        but keep at least the newest `min_keep` samples (a reader that needs a longer history)."""
        i = min(bisect.bisect_right(self.t, t_ns) - 1, len(self.t) - min_keep)
        # in chunks: deleting the head of a 10 000-sample list for every sample was a visible cost, and a
        # few older samples more change nothing (every reader asks by time, or for the newest n)
        if i >= TRIM_CHUNK or (i > 0 and len(self.t) <= TRIM_CHUNK):
            del self.t[:i], self.gyro[:i], self.accel[:i]

    def tail(self, n: int) -> tuple[np.ndarray, np.ndarray]:
        """The newest n samples as arrays (t_ns, gyro)."""
        return np.array(self.t[-n:], dtype=np.int64), np.array(self.gyro[-n:])

    def at(self, t_ns: int) -> tuple[np.ndarray, np.ndarray]:
        """Linearly interpolated (gyro, accel) at t_ns; clamped to the ends of the buffer."""
        i = bisect.bisect_left(self.t, t_ns)
        if i <= 0:
            return self.gyro[0], self.accel[0]
        if i >= len(self.t):
            return self.gyro[-1], self.accel[-1]
        t0, t1 = self.t[i - 1], self.t[i]
        a = (t_ns - t0) / (t1 - t0)
        return ((1 - a) * self.gyro[i - 1] + a * self.gyro[i]), ((1 - a) * self.accel[i - 1] + a * self.accel[i])

    def largest_gap_ns(self, t0_ns: int, t1_ns: int) -> int:
        """The longest spacing between the samples `integrate` reads for [t0, t1] (those inside and the two that
        bracket it): what it bridges by interpolating. Beyond the buffer's ends it holds the end sample: the
        stretch to t0 or t1 counts as a gap."""
        i = max(bisect.bisect_right(self.t, t0_ns) - 1, 0)
        j = bisect.bisect_left(self.t, t1_ns) + 1
        knots = self.t[i:j]
        if not knots:
            return t1_ns - t0_ns
        knots = [min(t0_ns, knots[0]), *knots, max(t1_ns, knots[-1])]
        return max(b - a for a, b in zip(knots[:-1], knots[1:]))

    def window(self, t0_ns: int, t1_ns: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Samples with t0 <= t <= t1 as arrays (t_ns, gyro, accel)."""
        i = bisect.bisect_left(self.t, t0_ns)
        j = bisect.bisect_right(self.t, t1_ns)
        if j <= i:
            return np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros((0, 3))
        return np.array(self.t[i:j]), np.array(self.gyro[i:j]), np.array(self.accel[i:j])

    def integrate(self, pim: gtsam.PreintegratedCombinedMeasurements, t0_ns: int, t1_ns: int) -> int:
        """Integrate the IMU over [t0, t1] into `pim`; returns the number of pieces integrated."""
        if t1_ns <= t0_ns or not self.t:
            return 0
        knots = [t0_ns] + [t for t in self.t[bisect.bisect_right(self.t, t0_ns):bisect.bisect_left(self.t, t1_ns)]]
        knots.append(t1_ns)
        g_prev, a_prev = self.at(knots[0])
        n = 0
        for ta, tb in zip(knots[:-1], knots[1:]):
            g_next, a_next = self.at(tb)
            dt = (tb - ta) * 1e-9
            if dt > 0:
                pim.integrateMeasurement(0.5 * (a_prev + a_next), 0.5 * (g_prev + g_next), dt)
                n += 1
            g_prev, a_prev = g_next, a_next
        return n
