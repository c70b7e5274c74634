"""Frame stamps on the camera's own clock, for cameras stamped on arrival at the host.

A camera exposes on its own crystal, one frame every period; a driver that stamps each frame when it reaches
the host (a USB camera read through V4L2 or GStreamer, a recording made that way) adds the transfer's varying
delay to every stamp. The estimator integrates the IMU between frame stamps, so a few milliseconds of that
delay move each keyframe along the path by the vehicle's speed times it: on a simulated aggressive flight 3 ms
of jitter took the ATE from 15 to 57 mm (docs/estimator.md "Frame stamps"). Frames taken at irregular times
and stamped with them (an external trigger with hardware stamps) are not its case: moved onto a line, they
leave the times they show (`frame_stamps = "raw"`). The SITL camera of bench/sitl is its case: it renders the
SIM_STATE the autopilot's simulator sends at the camera rate, stamped on arrival.

`FrameClock` fits the camera's clock, stamp = offset + period x frame number, to the last
`frame_stamp_window_s` of stamps (least squares, then again without the stamps far off that line: a frame
held up for long), numbering frames by the fitted period so that dropped frames keep their place, and stamps
each frame with the line's value. The line keeps the stamps' mean, so a constant latency stays where the
calibration's time offset has it. It only steps in where it helps: with `frame_stamps = "auto"` the stamps
are kept as given while they jitter (change from one frame to the next around the line) by less than `ON_MS`
(a camera stamped on the device, as an OAK, or a dataset such as EuRoC, whose stamps fit to well under a
microsecond: byte for byte the same replay; and a smoothly drifting offset, which the time offset state
follows), and it never restamps where the spread is too large to number frames reliably, where a stamp
leaves the line for good (a camera restarted, its rate changed: the fit starts again), or across a gap.
"""

from __future__ import annotations

import logging
from collections import deque
from dataclasses import dataclass, field

import numpy as np

from vio.frontend.median import median

log = logging.getLogger(__name__)

MODES = ("auto", "raw", "regular")
MIN_FRAMES = 20  # frames in the fit before a stamp is moved: a line from fewer moves them by its own error
ON_MS = 0.25  # auto: restamp from this jitter (1 sigma, robust) of the stamps from frame to frame...
OFF_MS = 0.1  # ...until it falls below this one (hysteresis: no switching back and forth near one threshold)
MAX_SPREAD_PERIODS = 0.125  # above this spread (in periods) frame numbers could be mistaken: stamps kept...
START_SPREAD_PERIODS = 0.1  # ...and restamping starts only below this one (no switching near the bound)
OFF_LINE_PERIODS = 0.25  # a stamp this far from the line (and 8 sigma) is off it...
EARLY_SIGMAS, EARLY_MIN_NS = 5.0, 1e6  # ...and one this far before it (and 1 ms): a delay never stamps a frame
# early, a frame held up past the next one's time and numbered as it does (put on the line a period late, it
# left the next frame out of order for the estimator to drop: a review's finding). Only from EARLY_MIN_FRAMES in
# the fit: the spread of the first 20 frames came out 0.7 ms for 3 ms, and the clock started again
EARLY_MIN_FRAMES = 50
OFF_LINE_OF_RECENT = (3, 6)  # ...and this many of the last frames mean the camera's clock changed: the fit starts
# again. Not "in a row": a camera gone from 20 to 30 Hz puts every third frame on the old line and was never
# refitted, every third frame moved 17 ms (a review's finding)
BURST_STEP_PERIODS = 0.25  # two frames closer than this were held up and delivered together (a burst: `restamp`)
QUIET_JITTER_MS = 0.05  # stamps kept as given jittering below this (a fifth of ON_MS)...
QUIET_FIT_EVERY = 10  # ...are refitted every this many frames, not every frame
WARMUP_SIGMA_FRAMES = 8  # stamps before a first fit that say how much they jitter (`_given_sigma`)
SIGMA_RECENT = 20  # frames whose sigmas' median the stats and the status report
SIGMAS_KEPT = 256  # stamps handed out whose sigma the estimator can ask for (frames it has not solved yet; at least
# the frames it may queue: the estimator passes its max_pending_frames)
MAX_GAP_S = 1.0  # a longer pause between frames starts the fit again (a camera restarted, a recording cut)
# ...so no burst frame is later than that on its place: the cap of its sigma. Measured from a fit that starved (a
# host reading a camera in pairs: every frame a burst's or its first, none taken into the warm-up) it grew with the
# run, 60 s after a minute
MAX_LATE_NS = MAX_GAP_S * 1e9


@dataclass
class FrameClockStats:
    """What the clock did over a run, for the replay's statistics and the daemon's status."""

    mode: str
    frames: int = 0
    restamped: int = 0
    largest_move_ns: int = 0
    spread_ns: float | None = None  # the stamps' latest spread around the fitted line (robust 1 sigma; kept as given
    # for a spread too large to number frames: their standard deviation from frame to frame)
    jitter_ns: float | None = None  # the part of it that changes from frame to frame (what auto goes by; kept as given
    # for a spread too large to number frames: the same as spread_ns)
    period_ns: float | None = None  # the fitted frame period (the median step where the spread is too large)
    restarts: int = 0  # fits started again (gaps, a clock that changed)
    uncertain: int = 0  # frames handed out with a stamp sigma (stamp_sigma_ns > 0: the estimator's stamp link)
    bursts: int = 0  # frames held up and delivered together (a USB stall): bursts seen...
    burst_frames: int = 0  # ...and their frames, the first of each included
    keyframes_skipped: int = 0  # frames too uncertain for a keyframe ([backend] keyframe_max_stamp_sigma_ms; the
    # estimator counts them)
    # the last SIGMA_RECENT sigmas handed out, whose median is `sigma_ns` (taken when read, not on every frame)
    recent_sigmas: deque = field(default_factory=lambda: deque(maxlen=SIGMA_RECENT))
    sigma_max_ns: float = 0.0  # the largest handed out
    stamp_link: bool = True  # whether the estimator uses the sigmas ([backend] frame_stamp_link), for what is said

    @property
    def sigma_ns(self) -> float:
        """The stamps' sigma now: the median of the last SIGMA_RECENT handed out (one frame held up far off the line,
        33 ms on a SITL flight, is not what the camera's stamps are; the status warns on this)."""
        return float(median(np.asarray(self.recent_sigmas))) if self.recent_sigmas else 0.0

    def as_dict(self) -> dict:
        """Plain Python numbers only (the fits hand numpy scalars in; a status reader or log gets `1.2`, not
        `np.float64(1.2)`)."""
        def ms(ns: float | None, digits: int = 3) -> float | None:
            return None if ns is None else round(float(ns) * 1e-6, digits)
        return {"mode": self.mode, "frames": int(self.frames), "restamped": int(self.restamped),
                "largest_move_ms": ms(self.largest_move_ns), "spread_ms": ms(self.spread_ns),
                "jitter_ms": ms(self.jitter_ns), "period_ms": ms(self.period_ns, 4),
                "restarts": int(self.restarts), "uncertain_frames": int(self.uncertain), "bursts": int(self.bursts),
                "burst_frames": int(self.burst_frames), "keyframes_skipped": int(self.keyframes_skipped),
                "stamp_sigma_ms": ms(self.sigma_ns),
                "stamp_sigma_max_ms": ms(self.sigma_max_ns), "stamp_link": bool(self.stamp_link)}


class FrameClock:
    """Restamps frames on a line fitted to their recent stamps (see the module's docstring)."""

    def __init__(self, mode: str = "auto", window_s: float = 10.0, sigmas_kept: int = SIGMAS_KEPT) -> None:
        if mode not in MODES:
            raise ValueError(f"frame stamps mode {mode!r} is not one of {list(MODES)}")
        self.mode = mode
        self.window_ns = int(window_s * 1e9)
        self.stats = FrameClockStats(mode)
        self._ref_ns = 0  # stamps are kept relative to the run's first one (float64 keeps them exact)
        self._n: deque[int] = deque()
        self._a: deque[float] = deque()
        self._line: tuple[float, float] | None = None  # (value at frame 0, period) in ns relative to _ref_ns
        self._spread = 0.0
        self._jitter = 0.0
        self._since_fit = 0  # frames since the last fit
        self._on = False
        self._off_line: deque[bool] = deque(maxlen=OFF_LINE_OF_RECENT[1])  # the last frames: off the line or not
        self._burst = 0  # frames of the burst being delivered (a USB stall's; 0: none), its first counted
        self._burst_step = 0.0  # the frame period that burst was told by (`restamp`)
        self._warned = False  # the spread-too-large warning, once per fit
        self._last_in = None
        self._last_out = None
        self._fit_n = (0.0, 1.0, 1)  # the last fit's mean frame number, sum of squared deviations, stamps kept
        # the last fit's standard deviations (not robust: a sigma handed out is taken as Gaussian) of the stamps it
        # kept around its line (`_line_sigma`) and of a stamp from frame to frame (`_given_sigma`)
        self._rms_ns = 0.0
        self._step_rms_ns: float | None = 0.0  # None: not computed yet from `_step_a`, the last fit's stamps
        self._step_a: np.ndarray | None = None
        # stamp handed out -> its sigma [ns], the newest `sigmas_kept` in the order handed out. Keyed, not searched
        # back until an older stamp: a clock reset hands out earlier stamps, and the frames still queued from before
        # it were then taken as exact
        self._sigmas: dict[int, float] = {}
        self._sigmas_kept = max(int(sigmas_kept), 1)
        self._late: dict[int, float] = {}  # stamp handed out -> `stamp_late_ns` (only those numbered past the next)
        self._late_now = 0.0  # that of the frame being restamped

    def restamp(self, t_ns: int) -> int:
        """The stamp to use for a frame stamped `t_ns` (stamps must come in order; one not after the last by less
        than MAX_GAP_S comes out not after the last one handed out, one that goes back further starts the fit
        again: a clock reset)."""
        t_ns = int(t_ns)
        self.stats.frames += 1
        if self.mode == "raw":
            return t_ns
        last_in = self._last_in
        if last_in is not None and last_in - MAX_GAP_S * 1e9 < t_ns <= last_in:
            # a stamp repeated, or a little out of order: the fit kept, and not after the last stamp handed out, so
            # that the estimator drops the frame as it would the stamp as given (a repeat of a frame moved earlier
            # would otherwise come after it). Starting the fit again on each threw away 10 s of fit, kept the next
            # 20 frames as given and logged twice (a driver repeating a stamp every 30 s: 4 restarts in 2 minutes,
            # a review's finding)
            return t_ns if self._last_out is None else min(t_ns, self._last_out)  # dropped, so no sigma for it
        self._last_in = t_ns
        if last_in is None or t_ns <= last_in or t_ns - last_in > MAX_GAP_S * 1e9:
            if last_in is not None:
                gap = f"a gap of {(t_ns - last_in) * 1e-9:.2f} s" if t_ns > last_in else \
                    f"a stamp {(last_in - t_ns) * 1e-9:.2f} s back (a clock reset)"
                self._restart(gap)
            self._start(t_ns)
            return self._out(t_ns, t_ns, self._given_sigma())
        a = float(t_ns - self._ref_ns)
        step = self._period_so_far()
        if step is None and self._burst:
            # a burst whose head was the warm-up's fourth stamp: taken back out, it left three, too few for a median
            # step, and the burst's next frame went out as an ordinary one (32 ms late with sigma 0, into the first
            # fit: a review's finding). The burst goes on by the step it started with
            step = self._burst_step
        if step is not None and t_ns - last_in < BURST_STEP_PERIODS * step:
            # Two frames this close: the camera did not expose them so; they were held up and delivered together (a
            # USB stall's burst). Out of the fit (numbered by its arrival, a burst frame sat within `far` of a wrong
            # place and bent the line: with stalls every 2 s the clock restamped a third of the frames and handed
            # 5 % out with a sigma under half their error), and so is the frame before it, the burst's first, if
            # the fit took it; not counted as off the line either (a 120 ms stall's three frames started the fit
            # again: 5 of 11 stalls, 20 frames kept as given after each). Kept as given, its sigma how late it is
            # if nothing was dropped since the fit's last (an upper bound: a drop puts its place later). Only a frame
            # late on that place: a camera gone faster (100 Hz frames 10 ms apart) comes early on it, and is a
            # changed clock, to fit again (a review's case). Before a first fit (a run's first second, or after a
            # restart) the same by the median step so far: stalled frames went out up to 250 ms late as exact
            head_in = self._a[-1] == float(last_in - self._ref_ns) and \
                len(self._a) > (MIN_FRAMES if self._line is not None else 1)  # the fit (or the warm-up) took it
            i = -2 if head_in else -1
            before = (self._n[i], self._a[i])  # the fit's last frame before the burst: its number and stamp
            k = max(self._burst, 1) + 1  # this frame is the burst's k-th after it (its first: 1)
            place = self._ref_ns + int(round(self._place_after(before, k, step)))  # its place if nothing was dropped
            if t_ns >= place - max(3 * self._spread, EARLY_MIN_NS):
                if head_in:
                    self._n.pop()
                    self._a.pop()
                if self._burst == 0:
                    # the burst's first went out already (on a place it may not have, with the line's sigma): its
                    # sigma, which the estimator reads when it solves that frame (later), says now how far it may be
                    # off from the first place after the fit's last
                    head = self._last_out
                    late = float(min(abs(head - self._ref_ns - int(round(self._place_after(before, 1, step)))),
                                     MAX_LATE_NS))
                    if head in self._sigmas and late > self._sigmas[head]:
                        self.stats.uncertain += int(self._sigmas[head] == 0)
                        self._sigmas[head] = late
                        self.stats.sigma_max_ns = max(self.stats.sigma_max_ns, self._sigmas[head])
                    self.stats.bursts += 1
                    self.stats.burst_frames += 1
                self.stats.burst_frames += 1
                self._burst, self._burst_step = k, step
                return self._out(t_ns, t_ns, max(float(min(abs(t_ns - place), MAX_LATE_NS)), self._given_sigma()))
        behind, self._burst = self._burst + 1, 0  # this frame's place after the fit's last (a burst's frames between)
        n = self._number(a)
        if self.stats.bursts and n > self._n[-1] + behind and step is not None:
            # numbered past the next place: frames dropped, or the head of a burst still to come (a camera that
            # stalled before stalls again), late by this if nothing was dropped (`stamp_late_ns`)
            self._late_now = a - self._place_after((self._n[-1], self._a[-1]), behind, step)
        if self._line is not None:
            off = a - self._place(n)
            far = max(OFF_LINE_PERIODS * self._line[1], 8 * self._spread)
            early = far if len(self._n) < EARLY_MIN_FRAMES else min(far, max(EARLY_SIGMAS * self._spread, EARLY_MIN_NS))
            if off > far or off < -early:
                alone = not any(self._off_line)
                self._off_line.append(True)
                if sum(self._off_line) >= OFF_LINE_OF_RECENT[0]:
                    self._restart(f"{OFF_LINE_OF_RECENT[0]} of the last {len(self._off_line)} frames off the camera "
                                  f"clock's line (the last by {off * 1e-6:.1f} ms)")
                    self._start(t_ns)
                    return self._out(t_ns, t_ns, max(abs(off), self._given_sigma()))  # off the line itself
                # a frame held up: the line has it; one early, or late after others off the line: the clock may
                # have changed
                late = off > 0 and self._on and alone
                # past the next place, early on it as well as late: a stall's first frame 80-100 ms late numbered
                # two places on sat 18 ms early there and was given 18 ms for 82 (14 of 20 stalls of 120 ms; a
                # review's finding)
                skipped = n > self._n[-1] + 1
                if late and not skipped:  # out of the fit either way
                    return self._out(t_ns, self._on_line(n), self._line_sigma(n))
                if skipped:
                    # Late on a place past the next one: frames dropped, or the next frames held up together (a
                    # USB stall delivers them in a burst; 120 ms every 10 s at 20 Hz put 11 frames 100 ms off with
                    # the line's sub-ms sigma, and the burst's next ones given 21 ms for 71). Kept as given, its
                    # sigma how late it is if nothing was dropped.
                    off = max(abs(off), a - self._place(self._n[-1] + 1))
                return self._out(t_ns, t_ns, max(abs(off), self._given_sigma()))
            if self._on and off < 0 and n > self._n[-1] + 1:
                # Numbered past the next frame's place (a drop), yet early on its own: it may as well be the next
                # frame held up. Unless it sits on its place (within 3 spreads: a delay is never much early) and is
                # too late to be held up within the fit (`far`), neither number is safe: put on either, a wrong one
                # is a whole period off with the line's sub-ms sigma (exponential delays of 5 / 6 / 7 ms at 20 Hz:
                # 14 / 63 / 192 of 24,000 frames 50 ms off; 2 / 17 / 42 with this, those left delayed by about a
                # period, which no stamp tells from a drop). Kept as given, its sigma covering both. (Stamps kept as
                # given anyway need no number.)
                late = a - self._place(self._n[-1] + 1)
                if late <= far or -off > max(3 * self._spread, EARLY_MIN_NS):
                    self._off_line.append(True)  # not on the line for sure either: counts towards a changed clock
                    return self._out(t_ns, t_ns, max(late, -off, self._given_sigma()))
        self._off_line.append(False)
        self._n.append(n)
        self._a.append(a)
        # the window, but never fewer than MIN_FRAMES: a short window at a low rate (1 s at 15 Hz, which the
        # config allows) never held them, and the clock never restamped a frame, silently (a review's finding)
        while len(self._a) > MIN_FRAMES and a - self._a[0] > self.window_ns:
            self._n.popleft()
            self._a.popleft()
        if len(self._n) >= MIN_FRAMES:
            if self._line is None:
                self._renumber()
                n = self._n[-1]
            self._since_fit += 1
            # a fit costs ~0.1 ms; stamps kept as given whose jitter is far below ON_MS (a device's, a dataset's: the
            # common case) are refitted every QUIET_FIT_EVERY frames only: they are handed out as given whatever the
            # line, which then only numbers frames and notices jitter starting (that many frames later at most)
            if self._on or self._jitter >= QUIET_JITTER_MS * 1e6 or self._since_fit >= QUIET_FIT_EVERY \
                    or len(self._n) < 2 * MIN_FRAMES:
                self._fit()
                self._since_fit = 0
        if not self._on or self._line is None:
            return self._out(t_ns, t_ns, self._given_sigma())
        return self._out(t_ns, self._on_line(n), self._line_sigma(n))

    def stamp_sigma_ns(self, t_ns: int) -> float:
        """How far the stamp `t_ns` handed out (one of the last SIGMAS_KEPT) may be off its frame's exposure, beyond
        a constant latency (1 sigma, ns): the line's own error for a restamped frame (`_line_sigma`); the stamps'
        standard deviation from frame to frame for one kept as given while they jitter (`_given_sigma`: ON_MS or more
        from frame to frame, a jitter the clock could not take out, too large to number the frames, or before a fit
        holds MIN_FRAMES; a frame off the line and kept: its distance from it, if more); 0 for
        stamps that keep to their line (a device's, a dataset's), for `raw` (taken as exact), and for a stamp
        it does not know. The estimator lets each keyframe's camera pose move along its motion by it (the smoother's
        stamp link), so that neither the poses nor the covariance sent take such a stamp as exact."""
        return self._sigmas.get(int(t_ns), 0.0)

    def _given_sigma(self) -> float:
        """The error of a stamp kept as given: the standard deviation of the last fit's stamps from frame to frame
        (`_step_sigma`; kept across a restart: the same camera, most likely) while they jitter, else 0. Before the
        run's first fit (MIN_FRAMES), the same from the stamps so far once there are WARMUP_SIGMA_FRAMES: the first
        second of a run (a service restarted in flight) took 8 ms of jitter as exact."""
        if self.stats.spread_ns is None:
            if len(self._a) < WARMUP_SIGMA_FRAMES:
                return 0.0
            robust, rms = self._step_sigma(np.asarray(self._a))
            return rms if robust >= ON_MS * 1e6 else 0.0
        if self._jitter < ON_MS * 1e6:
            return 0.0
        if self._step_rms_ns is None:  # the last fit's, taken when first asked for (restamped: seldom or never)
            self._step_rms_ns = self._step_sigma(self._step_a)[1]
        return self._step_rms_ns

    def _line_sigma(self, n: int) -> float:
        """The error of frame n's stamp on the fitted line (least squares: s x sqrt(1/k + (n - mean)^2 / Sxx), s the
        standard deviation of the stamps within 6 robust sigmas of it; ~2 s / sqrt(k) at the newest frame, 0.4 ms for
        3 ms of jitter over a 10 s window at 20 Hz). Not the robust spread: for the one-sided delays of a stamp on
        arrival that is 0.7 of the standard deviation: the newest restamped stamps of 120 simulated flights (3 ms
        exponential delays, one frame per 10 s window) came out 1.33 of their sigma off (rms) with it, 1.18 with the
        standard deviation of the stamps the fit kept (4 robust sigmas: the tail of the delays cut off), 1.00 with
        this (Gaussian jitter: 1.00 either way; a frame held up, far beyond 6 sigmas, stays out)."""
        nm, sxx, k = self._fit_n
        return self._rms_ns * float(np.sqrt(1.0 / k + (n - nm) ** 2 / sxx))

    @staticmethod
    def _step_sigma(a: np.ndarray) -> tuple[float, float]:
        """A stamp's robust sigma and standard deviation from frame to frame, from consecutive stamps `a` alone: each
        step off the median step's nearest multiple (a dropped frame is whole periods), over sqrt(2) (two stamps'
        errors per step). Not from the residuals of the line: where the stamps spread too much to number the frames,
        frames numbered wrongly bend the line and the residuals ran to 16 ms for 7 ms of jitter (8 ms arrival
        delays, 20 Hz). The standard deviation is the sigma handed out (a one-sided delay's robust sigma is 0.7 of
        it), without the steps off by more than 6 robust sigmas (a frame held up)."""
        if len(a) < 3:
            return 0.0, 0.0
        steps = np.diff(a)
        period = float(median(steps))
        if period <= 0:
            return 0.0, 0.0
        dev = steps - period * np.maximum(1.0, np.round(steps / period))
        dev = dev - float(median(dev))
        robust = 1.4826 * float(median(np.abs(dev)))
        kept = dev[np.abs(dev) <= max(6.0 * robust, 1e3)]
        return robust / np.sqrt(2.0), float(np.sqrt(np.mean(kept ** 2) / 2.0)) if len(kept) else 0.0

    def _period_so_far(self) -> float | None:
        """The frame period the burst test goes by: the line's, or before a first fit the median step of the frames
        so far (from three steps: one stall among them does not move it); None before that."""
        if self._line is not None:
            return self._line[1]
        if len(self._a) < 4:
            return None
        step = float(median(np.diff(np.asarray(self._a))))
        return step if step > 0 else None

    def _place_after(self, before: tuple[int, float], k: int, step: float) -> float:
        """Place of the k-th frame after the fit's frame `before` (its number and stamp) if none was dropped, relative
        to the run's first stamp (as `_place`): on the line, or before a first fit that frame's own stamp plus k
        steps."""
        if self._line is not None:
            return self._place(before[0] + k)
        return before[1] + k * step

    def _place(self, n: int) -> float:
        """Frame n's place on the fitted line, relative to the run's first stamp (ns, as `a` in `restamp`)."""
        return self._line[0] + self._line[1] * n

    def _on_line(self, n: int) -> int:
        """Frame n's stamp on the fitted camera clock (host ns)."""
        return self._ref_ns + int(round(self._place(n)))

    def _start(self, t_ns: int) -> None:
        self._ref_ns = t_ns
        self._n.clear()
        self._a.clear()
        self._n.append(0)
        self._a.append(0.0)
        self._line = None
        self._since_fit = 0
        self._off_line.clear()
        self._burst = 0
        self._warned = False
        self._on = False  # kept as given until the new fit has MIN_FRAMES (the restart's line says so)

    def _restart(self, why: str) -> None:
        self.stats.restarts += 1
        log.info("frame clock: %s: fitting the camera's clock again (stamps kept as given meanwhile)", why)

    def _number(self, a: float) -> int:
        """This frame's number: the last one's plus the fitted periods since it (a dropped frame is skipped)."""
        n_last, a_last = self._n[-1], self._a[-1]
        if self._line is not None:
            c, period = self._line
            return n_last + max(1, int(round((a - (c + period * n_last)) / period)))
        steps = np.diff(np.asarray(self._a)) if len(self._a) > 1 else None
        period = float(median(steps)) if steps is not None else a - a_last  # warming up: the typical step
        return n_last + max(1, int(round((a - a_last) / period)))

    def _renumber(self) -> None:
        """The first fit's frames numbered again by the median step of them all. Numbered one by one from the steps
        so far, a first frame delivered just before the second (1 ms) made the typical step 1 ms: the fit found a
        10.5 ms period for a 20 Hz camera, said the stamps spread 236 ms, and no frame of the flight was restamped
        (a review's finding)."""
        steps = np.diff(np.asarray(self._a))
        numbers = np.concatenate([[0], np.cumsum(np.maximum(1, np.round(steps / float(median(steps)))))])
        self._n = deque(int(k) for k in numbers)

    def _fit(self) -> None:
        n = np.asarray(self._n, dtype=float)
        a = np.asarray(self._a)
        # a robust start, the median step per frame and the median offset, whose far-off stamps the least squares
        # leave out: one least-squares pass over all of them let 4 frames buffered at the start and delivered
        # together tilt the line so far that no stamp of the flight was restamped (a review's finding)
        r = a - float(median(np.diff(a) / np.diff(n))) * n
        r = np.abs(r - median(r))
        keep = r <= max(4 * 1.4826 * float(median(r)), 1e3)
        for _ in range(2):  # least squares, then again without the stamps far above or below it
            nm, am = n[keep].mean(), a[keep].mean()
            dn = n[keep] - nm
            period = float(dn @ (a[keep] - am) / (dn @ dn))
            r = a - (am + period * (n - nm))
            med = float(median(r[keep]))
            spread = 1.4826 * float(median(np.abs(r[keep] - med)))
            keep = np.abs(r - med) <= max(4 * spread, 1e3)
        if period <= 0:
            return
        # the jitter is what changes from one frame to the next: a stamp offset that drifts smoothly (a camera
        # clock against the IMU's, which the time offset state follows) leaves the line as well, but not that
        step = np.diff(r[keep])
        jitter = 1.4826 * float(median(np.abs(step - median(step)))) / float(np.sqrt(2.0))
        self._line = (am - period * nm, period)
        self._spread, self._jitter = spread, jitter
        self._fit_n = (float(nm), max(float(dn @ dn), 1.0), len(dn))
        self._step_rms_ns, self._step_a = None, a  # `_given_sigma` reads them from these stamps when it needs them
        self.stats.spread_ns, self.stats.jitter_ns, self.stats.period_ns = spread, jitter, period
        if spread > MAX_SPREAD_PERIODS * period:
            # Said from the stamps themselves (the median step: a few dropped frames do not move it, and folding
            # them would fold jitter too; the standard deviation from frame to frame, which `_given_sigma` hands
            # out), not from this line: frames numbered wrongly bend it, and 8 ms of delays at 20 Hz read a 45.2 ms
            # period and a 16 ms spread, which an operator takes for the camera's
            step = float(median(np.diff(a)))
            if step > 0:
                self.stats.period_ns = step
                # the jitter too, the same figure (all of it changes from frame to frame, and it is what each stamp's
                # sigma is): the bent line's said 5.4 ms for 3 ms after a camera went from 25 to 20 Hz (a review's
                # finding)
                self.stats.spread_ns = self.stats.jitter_ns = self._step_rms_ns = self._step_sigma(a)[1]
            self._set_on(False, f"the stamps jitter {self.stats.spread_ns * 1e-6:.1f} ms (1 sigma) from frame to "
                                f"frame around a {self.stats.period_ns * 1e-6:.2f} ms frame period: too much to number "
                                "the frames, stamps kept as given")
        elif self._on:
            if self.mode == "auto" and jitter < OFF_MS * 1e6:
                self._set_on(False, None)
        elif spread <= START_SPREAD_PERIODS * period and (self.mode == "regular" or jitter >= ON_MS * 1e6):
            self._set_on(True, None)
        if self._on:  # the line's sigma, which only a restamped frame reads (`_on` changes only here and in `_start`)
            near = np.abs(r - med) <= max(6 * spread, 1e3)
            kept = r[near] - float(np.mean(r[near]))
            self._rms_ns = float(np.sqrt(np.mean(kept ** 2)))

    def _set_on(self, on: bool, why: str | None) -> None:
        if on and not self._on:
            log.info("frame stamps jitter by %.2f ms (1 sigma) around a %.3f ms frame clock: frames stamped on that "
                     "clock from now on (frame_stamps = %s)", self._jitter * 1e-6, self._line[1] * 1e-6, self.mode)
        elif self._on and not on:
            log.info("frame stamps: %s", why or f"the stamps jitter by {self._jitter * 1e-6:.2f} ms now: kept as "
                                                 "given")
        elif why and not self._warned:
            log.warning("frame stamps: %s", why)
        self._warned = self._warned or why is not None
        self._on = on

    def stamp_late_ns(self, t_ns: int) -> float:
        """How late the stamp `t_ns` handed out may be if the frames its numbering skipped were not dropped but held
        up behind it (ns; 0 for a frame numbered next, or before the camera stalled once). The head of a USB stall's
        burst is told only by the burst's next frame, which raises its sigma (`restamp`): a frame processed before
        that arrives (the IMU past its stamp first) went out with its sigma from before, as a keyframe 100 ms off
        with 0.2-2.6 ms. The estimator's keyframe rule reads this too."""
        return self._late.get(int(t_ns), 0.0)

    def _out(self, t_in: int, t_out: int, sigma: float) -> int:
        if self._last_out is not None and t_out <= self._last_out:
            # not out of order where the stamp as given is not (the estimator would drop the frame); it can be
            # where a frame held up to within a millisecond or so of the next one's time was put on that time
            t_out, sigma = t_in, max(sigma, self._given_sigma(), float(abs(t_out - t_in)))
        self._last_out = t_out
        if t_out not in self._sigmas:  # a stamp handed out again: the estimator drops that frame, not the first
            self._sigmas[t_out] = sigma
            if len(self._sigmas) > self._sigmas_kept:
                self._late.pop(next(iter(self._sigmas)), None)
                del self._sigmas[next(iter(self._sigmas))]
            if self._late_now > 0:
                self._late[t_out] = self._late_now
        self._late_now = 0.0
        self.stats.recent_sigmas.append(sigma)
        if sigma > 0:
            self.stats.uncertain += 1
            self.stats.sigma_max_ns = max(self.stats.sigma_max_ns, sigma)
        if t_out != t_in:
            self.stats.restamped += 1
            self.stats.largest_move_ns = max(self.stats.largest_move_ns, abs(t_out - t_in))
        return t_out


def frame_stamps_line(stats: dict | None) -> str | None:
    """One line for a replay whose frames were restamped or whose stamps were uncertain (None where every stamp was
    kept as given and exact)."""
    if not stats or not (stats["restamped"] or stats.get("uncertain_frames")):
        return None
    line = f"frame stamps: {stats['restamped']} of {stats['frames']} frames restamped on the camera's clock"
    if stats["period_ms"] is not None:
        line += (f" ({stats['period_ms']:.3f} ms period; the stamps spread {stats['spread_ms']:.2f} ms around it, "
                 f"largest move {stats['largest_move_ms']:.1f} ms; {stats['restarts']} restarts)")
    if stats.get("bursts"):
        line += (f"; {stats['burst_frames']} frames in {stats['bursts']} bursts (held up and delivered together: "
                 "a USB stall? kept as given, their sigma how late they may be)")
    if stats.get("keyframes_skipped"):
        line += (f"; {stats['keyframes_skipped']} frames too uncertain to be keyframes ([backend] "
                 "keyframe_max_stamp_sigma_ms)")
    if stats.get("uncertain_frames"):
        line += (f"; {stats['uncertain_frames']} stamps uncertain by up to {stats['stamp_sigma_max_ms']:.2f} ms "
                 "(1 sigma), " + ("their camera poses free to move along the motion by it"
                                  if stats.get("stamp_link", True) else "taken as exact ([backend] frame_stamp_link "
                                                                       "is off)"))
    return line
