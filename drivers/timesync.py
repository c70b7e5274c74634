"""Device clock -> host clock for sensors that stamp with their own clock (serial IMU, flight controller).

Model: arrival_host = a + (1 + drift) * t_device + delay, with delay >= 0 (USB/UART latency, OS
scheduling) and rarely near its minimum. The least-delayed samples therefore form the LOWER envelope of
(t_device, arrival - t_device); we take the minimum of each block (default 1 s) over a sliding window
(default 20 s) and fit a line through those minima. The intercept is the clock offset plus the minimum
transport latency (which cannot be separated from the offset without a round trip; it is small and
constant, and the calibration's camera-IMU time offset absorbs it). The slope is the drift.

Why not a plain average: mean(arrival - t_device) includes the mean latency, which varies with load,
so averaging moves every stamp by tens of ms whenever the host is busy.

Round trips (`roundtrip=True`, the MAVLink IMU's TIMESYNC exchange): a request leaves at host time ts1, the
device stamps its answer tc1, the answer arrives at t_recv; the device stamp then lies within rtt/2 of the
midpoint (ts1 + t_recv)/2, whatever the link's one-way delays. Each pair is that midpoint with rtt/2 as
its uncertainty, each block keeps its tightest round trip, and the line is a plain least-squares fit
through those (no envelope shift: the error is symmetric, not one-sided).

How far the stamps may be off (`uncertainty_ns`, which the daemon's output stage turns into covariance and quality,
docs/autopilot.md "IMU clock health"): the fit's misfit to its newest seconds (each block's distance from the line,
beyond a round trip's own half duration: what the line provably misses now), the move of the mapping at the last
refit (consecutive fits that disagree, or the newest block against the mapping in use before it: the stamps given
out before it were off by that much), the smallest miss of the pairs of the last LIVE_S against the mapping (between
refits), and, once no block has closed for a while (answers stopped), a growth of STALE_RATE per second of
extrapolation. On a healthy clock the first three stay within a millisecond or two; a SITL that stalled 150 ms puts
the newest blocks ~0.1 s off the 20 s line that only bends towards them, and the measure says so for as long as the
line has not caught up.

`StreamMonitor` checks any stamped stream for gaps, non-monotonic stamps and time jumps and counts them,
so data problems are reported, never silently smoothed over.
"""

from __future__ import annotations

import logging
import math
from collections import deque
from dataclasses import dataclass

import numpy as np

log = logging.getLogger(__name__)

# The clock rates the fit follows: up to 5 % off the host's (an MCU's internal RC oscillator is specified to
# about 1-2 %); a rate beyond 0.2 % is followed but said once (no crystal is that far off).
MAX_DRIFT_PPM = 50_000.0
FAST_DRIFT_PPM = 2_000.0
# Until this many blocks, the slope stays within a crystal's 0.1 % (too few points to tell a fast clock from one
# late block); from then on it is a median of the blocks' pairwise slopes, which one stalled read cannot bend.
ROBUST_BLOCKS = 5
EARLY_DRIFT_PPM = 1_000.0
# The uncertainty measure: the misfit of the newest RECENT_BLOCKS blocks counts (older ones the line has averaged
# over; a step shows in the newest), and without a new block for more than two block lengths (the autopilot stopped
# answering TIMESYNC) the extrapolated line is trusted to STALE_RATE (0.1 %: ten times a crystal's worst, about
# what a SITL that loses time under load drifts by, docs/autopilot.md) per second beyond them.
RECENT_BLOCKS = 3
STALE_RATE = 1e-3
# Between refits (a block closes once a second) the newest pairs are compared with the mapping as they come: the
# smallest miss (beyond a round trip's bound) among those of the last LIVE_S, once there are LIVE_MIN_PAIRS of them.
# The smallest, because single answers miss for reasons of their own (ArduPilot's answers stamped up to 43 ms early,
# in runs of up to 5 of its 10 a second; a late arrival); a stepped clock makes every one miss: seen within LIVE_S.
LIVE_S = 0.6
LIVE_MIN_PAIRS = 6


def _theil_sen(t: np.ndarray, d: np.ndarray) -> float:
    """Median of the pairwise slopes (Theil-Sen, the slope scipy.stats.theilslopes gives): a late block (a stalled
    reader, a burst) moves a least-squares line through ~20 block minima by tens of ms once the slope may reach per
    cents; the median does not follow it.

    Computed here rather than by scipy.stats: this runs in the sensor's reader thread, and the first call imported
    scipy.stats there (1.2 s on a loaded 2-core machine), mid-stream, 3 s after the IMU started: the MAVLink IMU
    read nothing for that long, so every ArduPilot SITL flight began with 'no estimate for 0.5 s', poses too old
    to send and a 'VIO tracking lost' STATUSTEXT on the ground (docs/autopilot.md, "Closed-loop SITL test")."""
    if not np.any(np.diff(t) > 0):
        return 0.0
    dt = t[:, None] - t
    pairs = dt > 0
    return float(np.median((d[:, None] - d)[pairs] / dt[pairs]))


@dataclass
class ClockEstimate:
    offset_ns: float  # host - device at t_ref_dev_ns
    drift_ppm: float  # (host rate / device rate - 1) * 1e6
    t_ref_dev_ns: int
    n_blocks: int


class ClockSync:
    """Running lower-envelope fit of host arrival time against device time."""

    def __init__(self, block_s: float = 1.0, window_s: float = 20.0, max_jump_s: float = 0.5,
                 max_drift_ppm: float = MAX_DRIFT_PPM, roundtrip: bool = False) -> None:
        self.roundtrip = roundtrip
        self.block_ns = int(block_s * 1e9)
        self.window_blocks = max(2, int(round(window_s / block_s)))
        self.max_jump_ns = int(max_jump_s * 1e9)
        self.max_drift = max_drift_ppm * 1e-6
        # per block its best pair: (t_dev, host - dev, uncertainty); best = least uncertain (envelope: least delayed)
        self._blocks: deque[tuple[int, int, int]] = deque()
        self._cur: tuple[int, int, int] | None = None
        self._cur_all: list[tuple[int, int, int]] = []  # round trips: every pair of the current block
        self._cur_start: int | None = None
        self._est: ClockEstimate | None = None
        self._last_dev: int | None = None
        self.resets = 0
        # why the stamps cannot be trusted (a clock rate beyond what the fit follows), None while they can: a
        # source must then hold its samples back rather than hand the estimator stamps that are off by a
        # growing amount (a line clamped at 0.1 % on a 1 % slow clock put them 185 ms early: a review's finding)
        self.problem: str | None = None
        self._fast_warned = False
        self._misfit_ns = 0.0  # the newest blocks' distance from the line (beyond their own bounds) at the last refit
        self._jump_ns = 0.0  # how far the last refit moved the mapping at its newest block
        self._cur_d_max: int | None = None  # arrivals before the first fit: the current block's largest host - device
        # the pairs of the last LIVE_S: their device times, and (t_dev, miss) with misses rising from the oldest on
        # (a sliding minimum: each add is O(1) on average and the measure a float read from another thread)
        self._live_t: deque[int] = deque()
        self._live_min: deque[tuple[int, float]] = deque()
        self._live_miss_ns = 0.0

    def reset(self) -> None:
        """Forget everything (device restarted or its clock jumped)."""
        self._blocks.clear()
        self._cur = None
        self._cur_all = []
        self._cur_start = None
        self._est = None
        self._last_dev = None
        self._misfit_ns = self._jump_ns = 0.0
        self._cur_d_max = None
        self._live_t.clear()
        self._live_min.clear()
        self._live_miss_ns = 0.0
        self.resets += 1

    def add(self, t_dev_ns: int, t_host_ns: int, uncertainty_ns: int = 0) -> None:
        """Add one (device stamp, host stamp) pair: the host arrival time, or with `roundtrip` the round
        trip's midpoint and half its duration as `uncertainty_ns`."""
        d = t_host_ns - t_dev_ns
        # arrivals far EARLIER than predicted mean the device clock jumped ahead; far later ones are only a
        # stalled reader (delay is unbounded above) and must not restart the sync. A round trip's midpoint is
        # off by at most its uncertainty either way.
        miss = 0.0 if self._est is None else self._predict_offset(t_dev_ns) - d
        if self.roundtrip:
            miss = abs(miss) - uncertainty_ns
        if self._est is not None and miss > self.max_jump_ns:
            log.warning("device clock jumped by %.3f s against the host: clock sync restarted",
                        (self._predict_offset(t_dev_ns) - d) / 1e9)
            self.reset()
        if self._last_dev is not None and t_dev_ns < self._last_dev:
            log.warning("device clock went backwards by %.3f s: clock sync restarted",
                        (self._last_dev - t_dev_ns) / 1e9)
            self.reset()
        self._last_dev = t_dev_ns
        if self._cur_start is None:
            self._cur_start = t_dev_ns
        if t_dev_ns - self._cur_start >= self.block_ns:
            if self._cur is not None:
                self._blocks.append(self._consistent_best(self._cur_all) if self.roundtrip else self._cur)
                while len(self._blocks) > self.window_blocks:
                    self._blocks.popleft()
                self._refit()
            self._cur = None
            self._cur_all = []
            self._cur_d_max = None
            self._cur_start = t_dev_ns
        self._cur_d_max = d if self._cur_d_max is None else max(self._cur_d_max, d)
        if self._est is not None:
            self._add_live(t_dev_ns, max(abs(d - self._predict_offset(t_dev_ns)) - uncertainty_ns, 0.0))
        key = uncertainty_ns if self.roundtrip else d
        if self._cur is None or key < (self._cur[2] if self.roundtrip else self._cur[1]):
            self._cur = (t_dev_ns, d, uncertainty_ns)
        if self.roundtrip:
            self._cur_all.append((t_dev_ns, d, uncertainty_ns))

    def _consistent_best(self, pairs: list[tuple[int, int, int]]) -> tuple[int, int, int]:
        """The block's tightest round trip among those that agree with all the others' bounds.

        Each answer bounds the offset to d +- its half round trip, but ArduPilot stamps an answer with its UART's
        receive-time estimate, which subtracts 10 bits at the port's baud rate for every byte still buffered behind
        the request: exact on a real UART, early on a SITL's TCP link (or a USB one), where an ODOMETRY read in the
        same chunk put 44 of 399 answers 20-43 ms early with tight round trips (a probe against the ArduCopter
        SITL, docs/autopilot.md "Re-checked 2026-12-07"), and the block kept the tightest: stamps up to 6 ms off.
        Early answers only raise d, so one whose lower bound lies above another's upper bound is that; the others
        are kept as before. Within the block the current drift is taken out (a clock up to 5 % off)."""
        slope = self._est.drift_ppm * 1e-6 if self._est is not None else 0.0
        t0 = pairs[0][0]
        dd = [d - slope * (t - t0) for t, d, _ in pairs]
        upper = min(x + u for x, (_, _, u) in zip(dd, pairs))
        return min((p for x, p in zip(dd, pairs) if x - p[2] <= upper), key=lambda p: p[2])

    def _refit(self) -> None:
        t = np.array([b[0] for b in self._blocks], dtype=np.float64)
        d = np.array([b[1] for b in self._blocks], dtype=np.float64)
        t_ref = int(t[-1])
        # round trips: each block's pair weighted by 1 / its uncertainty, floored at the blocks' median, so that
        # the blocks of an ordinary link count alike and one whose answers were all read late (a reader that
        # stalled: its midpoint is off by up to half the stall) hardly at all. Unweighted, a 1 s stall of the
        # MAVLink reader bent the line by +2.4 % and then -0.3 % for its whole 20 s window: the IMU's time base
        # off by that much, which a take-off shows as a scale the images do not share (the stereo check then
        # blamed the right camera, tests/test_mavlink_imu.py).
        u = np.array([b[2] for b in self._blocks], dtype=np.float64)
        w = 1.0 / np.maximum(u, max(float(np.median(u)), 1.0))
        if len(t) >= 3:
            # round trips scatter both ways around the truth: a (weighted) fit; arrivals: the median slope
            slope = float(np.polyfit(t - t_ref, d, 1, w=w)[0]) if self.roundtrip else _theil_sen(t, d)
            limit = self.max_drift
            if len(t) >= ROBUST_BLOCKS:
                self._check_rate(slope, len(t))
            else:
                limit = min(limit, EARLY_DRIFT_PPM * 1e-6)
            slope = float(np.clip(slope, -limit, limit))
            resid = d - slope * (t - t_ref)
            # lower envelope: shift the line down to touch the lowest residual (no point lies below it); round
            # trips scatter both ways around the truth, so their line is the plain fit
            icpt = float(np.average(resid, weights=w**2) if self.roundtrip else np.min(resid))
        else:
            # under three seconds of answers no slope yet: the newest second's (a mean over two would lag a clock
            # drifting 2 % by 10 ms more, a review's finding)
            slope, icpt = 0.0, float(self._blocks[-1][1] if self.roundtrip else np.min(d))
        before = self._predict_offset(t_ref) if self._est is not None else None
        self._est = ClockEstimate(icpt, slope * 1e6, t_ref, len(t))
        # the newest block against the mapping in use until now (how far the stamps of the last second were off,
        # beyond a round trip's own bound), or, the same in other words, how far this refit moved the mapping there
        self._jump_ns = 0.0 if before is None else max(abs(self._predict_offset(t_ref) - before),
                                                        abs(d[-1] - before) - (u[-1] if self.roundtrip else 0.0))
        # each recent block's distance from the line: a round trip's beyond its own half round trip (the truth lies
        # within it), over the last RECENT_BLOCKS; for arrivals the newest block's height above the envelope (its
        # least delayed sample came that much later than the line says: a reader stalled for the whole second, or a
        # clock that stepped; the next block tells them apart, so an older late block no longer counts)
        k = min(RECENT_BLOCKS if self.roundtrip else 1, len(t))
        miss = np.abs(d[-k:] - (icpt + slope * (t[-k:] - t_ref)))
        self._misfit_ns = float(np.max(np.maximum(miss - u[-k:], 0.0) if self.roundtrip else miss))

    def _check_rate(self, slope: float, n_blocks: int) -> None:
        """A crystal keeps a device clock within 0.01 % of the host's; an MCU on its internal RC oscillator is off
        by up to a few per cent, which the fit follows (said once), and beyond `max_drift_ppm` it does not."""
        if abs(slope) > self.max_drift:
            if self.problem is None:
                self.problem = (f"device clock runs {100 * slope:+.2f} % against the host's, beyond the "
                                f"{self.max_drift * 100:.0f} % the clock sync follows: stamps unusable")
                log.error("%s", self.problem)
        elif self.problem is not None and n_blocks >= 3:
            log.warning("device clock rate back within %.0f %% of the host's (%+.3f %%): stamps usable again",
                        self.max_drift * 100, 100 * slope)
            self.problem = None
        if abs(slope) > FAST_DRIFT_PPM * 1e-6 and n_blocks >= 10 and not self._fast_warned:
            self._fast_warned = True
            # slope = d(host - device)/d(device): positive is a device clock that falls behind (an ArduPilot SITL
            # losing simulated time under load); "+0.38 %" alone was read as a clock running fast
            log.warning("device clock runs %.3f %% %s than the host's (a crystal is within 0.01 %%): followed, but "
                        "check the device's oscillator", 100 * abs(slope), "slower" if slope > 0 else "faster")

    def _predict_offset(self, t_dev_ns: int) -> float:
        e = self._est
        assert e is not None
        return e.offset_ns + e.drift_ppm * 1e-6 * (t_dev_ns - e.t_ref_dev_ns)

    def to_host(self, t_dev_ns: int) -> int | None:
        """Host-clock stamp of a device stamp; before the first block closes, the running minimum of
        (host - device) is used; None before any sample."""
        if self._est is not None:
            return int(round(t_dev_ns + self._predict_offset(t_dev_ns)))
        if self._cur is not None:
            return int(t_dev_ns + self._cur[1])
        return None

    def uncertainty_ns(self, t_dev_ns: int) -> float:
        """How far the host stamp `to_host(t_dev_ns)` may be off the truth [ns]: the recent blocks' misfit to the
        line, the last refit's move or the newest pairs' smallest miss, whichever is largest, plus STALE_RATE per ns
        of extrapolation beyond two blocks after the newest; before the first fit the current block's own spread (its
        tightest round trip's half duration, or the arrivals' range); inf while the stamps cannot be placed
        (`problem`, no sample)."""
        if self.problem is not None:
            return math.inf
        e = self._est
        if e is None:
            # read once: the serial IMU's reader thread closes blocks (self._cur = None) while the output asks
            cur, d_max = self._cur, self._cur_d_max
            if cur is None:
                return math.inf
            if self.roundtrip:
                return float(cur[2])
            return max(float((d_max or cur[1]) - cur[1]), 0.0)  # 0 floor: a d_max read from the next block
        stale = max(0, t_dev_ns - e.t_ref_dev_ns - 2 * self.block_ns)
        return max(self._misfit_ns, self._jump_ns, self._live_miss_ns) + STALE_RATE * stale

    def _add_live(self, t_dev_ns: int, miss: float) -> None:
        """Keep the smallest miss of the pairs of the last LIVE_S against the mapping in use (0 with fewer than
        LIVE_MIN_PAIRS of them)."""
        oldest = t_dev_ns - LIVE_S * 1e9
        self._live_t.append(t_dev_ns)
        while self._live_t[0] < oldest:
            self._live_t.popleft()
        while self._live_min and self._live_min[-1][1] >= miss:
            self._live_min.pop()
        self._live_min.append((t_dev_ns, miss))
        while self._live_min[0][0] < oldest:
            self._live_min.popleft()
        self._live_miss_ns = self._live_min[0][1] if len(self._live_t) >= LIVE_MIN_PAIRS else 0.0

    @property
    def estimate(self) -> ClockEstimate | None:
        return self._est

    def as_dict(self) -> dict:
        e = self._est
        return {"mode": "roundtrip" if self.roundtrip else "arrival",
                "offset_ns": None if e is None else round(e.offset_ns),
                "drift_ppm": None if e is None else round(e.drift_ppm, 3),
                "blocks": 0 if e is None else e.n_blocks, "resets": self.resets, "problem": self.problem,
                "misfit_ms": round(self._misfit_ns / 1e6, 3), "refit_move_ms": round(self._jump_ns / 1e6, 3)}


class StreamMonitor:
    """Counts gaps, non-monotonic stamps and time jumps of one stamped stream and logs each event once."""

    def __init__(self, name: str, nominal_rate_hz: float, gap_factor: float = 2.5, jump_s: float = 1.0) -> None:
        self.name = name
        self.period_ns = int(1e9 / nominal_rate_hz)
        self.gap_ns = int(gap_factor * self.period_ns)
        self.jump_ns = int(jump_s * 1e9)
        self.last_t: int | None = None
        self.count = 0
        self.gaps = 0
        self.missing_estimate = 0  # samples that the gaps imply were lost
        self.non_monotonic = 0
        self.jumps = 0
        self.max_dt_ns = 0

    def check(self, t_ns: int) -> bool:
        """Record one stamp. False means the sample must be dropped (not after the previous one)."""
        self.count += 1
        if self.last_t is None:
            self.last_t = t_ns
            return True
        dt = t_ns - self.last_t
        if dt <= 0:
            self.non_monotonic += 1
            if self._should_log(self.non_monotonic):
                log.warning("%s: non-monotonic stamp %d after %d (dt %d ns); sample dropped",
                            self.name, t_ns, self.last_t, dt)
            return False
        if dt > self.jump_ns:
            self.jumps += 1
            log.warning("%s: time jump of %.3f s", self.name, dt / 1e9)
        elif dt > self.gap_ns:
            self.gaps += 1
            self.missing_estimate += int(round(dt / self.period_ns)) - 1
            if self._should_log(self.gaps):
                log.warning("%s: gap of %.1f ms (nominal %.1f ms)", self.name, dt / 1e6, self.period_ns / 1e6)
        self.max_dt_ns = max(self.max_dt_ns, dt)
        self.last_t = t_ns
        return True

    @staticmethod
    def _should_log(n: int) -> bool:
        """Log the first 10 events of a kind, then every 100th: a broken sensor must not flood the log."""
        return n <= 10 or n % 100 == 0

    def as_dict(self) -> dict:
        return {"count": self.count, "gaps": self.gaps, "missing_estimate": self.missing_estimate,
                "non_monotonic": self.non_monotonic, "jumps": self.jumps, "max_dt_ms": self.max_dt_ns / 1e6}
