"""Runs the loop-closure stage (vio.loop.LoopCloser) in its own thread beside the odometry.

The frame loop only hands a keyframe over (`submit`: a non-blocking put into a bounded queue; a full queue
drops the keyframe and counts it) and reads the newest correction (`correction`, under a lock). It never
waits for retrieval, verification or the pose-graph solve. A live view that asks for them (`keep_snapshot`)
reads the corrected keyframe poses and loop edges as a `LoopSnapshot`, built in this thread after each
keyframe so that the view never reads the pose graph while it is being solved. A map checkpoint (`vio run`'s
`[map] checkpoint_s`) is written by this thread too, between keyframes: the frame loop never waits for it."""

from __future__ import annotations

import contextlib
import logging
import queue
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from vio.loop.output import CorrectionUncertainty

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class LoopSnapshot:
    """The pose graph as of one keyframe, for the view: corrected positions in the world (a loaded map's
    keyframes first, in the map's frame), the odometry segment of each (a reset starts a new one) and the
    loop edges as (i, j, GNC weight; below 0.5: rejected)."""

    version: int  # keyframes processed when it was taken
    closures: int
    positions: np.ndarray  # (N, 3)
    sessions: np.ndarray  # (N,)
    loop_edges: tuple[tuple[int, int, float], ...]


@dataclass(frozen=True)
class _Settled:
    poses: tuple  # ((stamp ns, T_world_body), ...) from ProcessedFrame.settled


class LoopWorker:
    def __init__(self, closer, max_queue: int = 64, keep_snapshot: bool = False,
                 checkpoint: Callable[[object], bool | None] | None = None, checkpoint_s: float = 0.0) -> None:
        """`checkpoint(closer)`: called in this thread every `checkpoint_s` while keyframes came since the last
        call (and not after close()); what it raises is logged, the stage goes on; False: nothing written yet, tried
        again at the next interval."""
        self.closer = closer
        self._checkpoint = checkpoint if checkpoint_s > 0 else None
        self._checkpoint_s = checkpoint_s
        self._next_checkpoint = time.monotonic() + checkpoint_s
        self._checkpointed = 0  # keyframes processed as of the last checkpoint
        self._checkpoint_error: str | None = None
        self._checkpoint_at: float | None = None  # monotonic time of the last checkpoint written
        self.checkpoints = 0
        self._q: queue.Queue = queue.Queue(maxsize=max_queue)
        self._lock = threading.Lock()
        self._correction = np.eye(4)
        self._uncertainty: CorrectionUncertainty | None = None
        self._segment: tuple[int, bool] = (0, True)  # the correction's odometry segment, and is it its own frame
        # reset_counter of the newest keyframe the correction was taken at (CorrectedOutput.restart)
        self._counter: int | None = None
        # is the correction's frame a loaded map's (the flight relocalised in it), not the flight's own first segment's
        self._in_map = False
        self.closures = 0  # accepted closures so far
        # the pose graph's estimate version behind the correction: +1 at each solve (a closure, or loop edges the
        # graph deferred brought in later), not when only a new odometry segment begins
        self._version = 0
        self.dropped = 0
        self.error: str | None = None
        self.keep_snapshot = keep_snapshot
        self._snapshot: LoopSnapshot | None = None
        self._processed = 0
        # the closer's counts as of the last keyframe processed, for `status` (read from other threads)
        self._counts = {"loop_edges": 0, "switched_off": 0, "relocalised": False if closer.map_keyframes else None,
                        "confirmed": False if closer.map_keyframes else None}
        if closer.map_keyframes:
            log.info("loop closure: map of %d keyframes loaded; poses are in this flight's own frame until it "
                     "relocalises", closer.map_keyframes)
        self._abandon = threading.Event()  # close() ran out of time: skip what is still queued
        self._closing = threading.Event()  # close() was called: no more checkpoints
        self._thread = threading.Thread(target=self._run, name="loop-closure", daemon=True)
        self._thread.start()

    def submit(self, t_ns: int, T_world_body: np.ndarray, image: np.ndarray, ff, reset_counter: int) -> bool:
        try:
            self._q.put_nowait((t_ns, np.array(T_world_body), image, ff, reset_counter))
            return True
        except queue.Full:
            self.dropped += 1
            return False

    def settle(self, settled) -> None:
        """Hand over the odometry's smoothed poses of keyframes that left its window (`ProcessedFrame.settled`),
        behind the keyframes already queued. A full queue drops them: those edges keep the first estimates."""
        if settled:
            with contextlib.suppress(queue.Full):
                self._q.put_nowait(_Settled(tuple(settled)))

    def correction(self) -> tuple[np.ndarray, int, CorrectionUncertainty | None, int, bool, int | None, bool]:
        """(T_world_odom, its version: the pose graph's solves behind it, its uncertainty where the frame came
        through loop edges, the odometry segment it is for, is that segment in a frame of its own, the reset_counter
        of the newest keyframe it was taken at, is its frame a loaded map's) as of the last keyframe processed; the
        arguments of CorrectedOutput.apply."""
        with self._lock:
            return (self._correction.copy(), self._version, self._uncertainty, *self._segment, self._counter,
                    self._in_map)

    def _set_correction(self, counter: int | None = None) -> None:
        """The closer's newest correction, versioned by the pose graph's solves: a new odometry segment (an
        estimator reset) changes the correction without one, and `jump` keeps what it has until a closure."""
        if self.closer.placement_unconfirmed():
            # joined to another frame by too few edges to rule out a look-alike place: the output keeps the
            # correction it has (this segment's own frame) until the join is confirmed. Its reset_counter stays the
            # one it was solved with: labelled with this keyframe's, an old estimator's correction not applied yet
            # passed CorrectedOutput.restart's check and was applied to the new estimator's odometry (a review's)
            return
        T, version = self.closer.correction(), self.closer.graph.estimate_version
        unc, seg = self.closer.correction_uncertainty(), self.closer.correction_segment()
        in_map = self.closer.relocalised
        with self._lock:
            self._correction, self._version, self._uncertainty, self._segment = T, version, unc, seg
            self._in_map = in_map
            if counter is not None:
                self._counter = counter

    def status(self) -> dict:
        """Counts for the daemon's status file and health line (thread-safe copy)."""
        with self._lock:
            u = self._uncertainty
            at = self._checkpoint_at
            out = {"keyframes": self._processed, "closures": self.closures, **self._counts,
                   "map_keyframes": self.closer.map_keyframes, "dropped": self.dropped, "error": self.error,
                   # how well the loop edges place the flight in the frame they brought (None in its own frame)
                   "placement_sigma_m": None if u is None else round(u.position_sigma_m, 4)}
        if self._checkpoint is not None:  # what a kill now would keep of the map ([map] checkpoint_s)
            out.update(map_checkpoints=self.checkpoints, map_checkpoint_error=self._checkpoint_error,
                       map_checkpoint_age_s=None if at is None else round(time.monotonic() - at, 1))
        return out

    def _note_events(self, closed: bool) -> None:
        """One log line per event an operator cares about: the first closure, the flight placed in a loaded map,
        loop edges switched off after the fact. (Every closure would be several lines a second in a lap.)"""
        c = self.closer
        new = {"loop_edges": c.stats.accepted, "switched_off": c.stats.switched_off,
               "relocalised": bool(c.relocalised) if c.map_keyframes else None,
               "confirmed": bool(c.relocalised) and not c.placement_unconfirmed() if c.map_keyframes else None}
        old = self._counts
        if closed and self.closures == 1:
            log.info("loop closure: first closure at keyframe %d (%d loop edges)", self._processed, new["loop_edges"])
        if new["relocalised"] and not old["relocalised"]:
            n = c.cfg.output_join_edges
            log.info("loop closure: relocalised in the map (%d keyframes)%s", c.map_keyframes,
                     f"; corrected poses are in the map's frame once {n} loop edges confirm the place" if n else "")
        if new["confirmed"] and not old.get("confirmed"):
            log.info("loop closure: placement in the map confirmed: corrected poses are in the map's frame")
        if old["relocalised"] and new["relocalised"] is False:
            log.warning("loop closure: no longer placed in the map (an estimator reset, or the edges that placed it "
                        "switched off): poses are in a frame of their own until it relocalises again")
        if new["switched_off"] > old["switched_off"]:
            log.warning("loop closure: %d loop edge(s) switched off by GNC (inconsistent with the others)",
                        new["switched_off"] - old["switched_off"])
        with self._lock:
            self._counts = new

    def snapshot(self) -> LoopSnapshot | None:
        """The newest LoopSnapshot (None before the first keyframe, or without keep_snapshot)."""
        with self._lock:
            return self._snapshot

    def _take_snapshot(self) -> LoopSnapshot:
        c = self.closer
        return LoopSnapshot(self._processed, self.closures, np.array([T[:3, 3] for T in c.graph.estimate]),
                            np.array([k.session for k in c.keyframes]),
                            tuple((e.i, e.j, e.weight) for e in c.graph.edges if e.kind == "loop"))

    def _next(self):
        """The next queued item; in between, a checkpoint when one is due and keyframes came since the last."""
        while self._checkpoint is not None:
            dirty = self._processed > self._checkpointed and self.error is None and not self._closing.is_set() \
                and not self._abandon.is_set()  # closing: the final save follows, within the shutdown budget
            wait = self._next_checkpoint - time.monotonic()
            if dirty and wait <= 0:
                self._write_checkpoint()
                continue
            try:
                return self._q.get(timeout=wait if dirty else self._checkpoint_s)
            except queue.Empty:
                continue
        return self._q.get()

    def _write_checkpoint(self) -> None:
        self._next_checkpoint = time.monotonic() + self._checkpoint_s
        before, self._checkpointed = self._checkpointed, self._processed
        try:
            if self._checkpoint(self.closer) is False:  # not written yet (the frame to save in is to be chosen)
                self._checkpointed = before
                return
            self.checkpoints += 1
            self._checkpoint_at = time.monotonic()
            if self._checkpoint_error is not None:
                log.info("map checkpoint written again")
            self._checkpoint_error = None
        except Exception as e:  # noqa: BLE001 - a failed checkpoint must not stop loop closure
            msg = str(e) or type(e).__name__
            if msg != self._checkpoint_error:  # one line per event, not one per checkpoint
                log.error("map checkpoint not written: %s", msg)
            self._checkpoint_error = msg

    def _run(self) -> None:
        while True:
            item = self._next()
            try:
                if item is None:
                    if self.error is None and not self._abandon.is_set():
                        try:  # the thread stops whatever finish() does (close() waits for it)
                            self.closer.finish()
                            self._set_correction()
                        except Exception as e:
                            self.error = f"{type(e).__name__}: {e}"
                            log.error("loop closure: the end-of-flight update failed: %s", self.error)
                    return
                if isinstance(item, _Settled):
                    if self.error is None and not self._abandon.is_set():
                        for t_ns, T in item.poses:
                            self.closer.settle(t_ns, T)
                elif self._abandon.is_set():
                    self.dropped += 1
                elif self.error is None:
                    closed = self.closer.add_keyframe(*item)
                    self._set_correction(int(item[4]))
                    with self._lock:
                        self.closures += int(closed)
                        self._processed += 1
                    self._note_events(closed)
                    if self.keep_snapshot:
                        snap = self._take_snapshot()
                        with self._lock:
                            self._snapshot = snap
            except Exception as e:  # the odometry goes on without loop closure
                self.error = f"{type(e).__name__}: {e}"
                log.error("loop closure stopped: %s", self.error)
            finally:
                self._q.task_done()

    def close(self, wait: bool = True, timeout_s: float | None = None, grace_s: float = 5.0) -> bool:
        """Stop the thread. `wait`: after it has processed what is queued (a map saved afterwards holds every
        keyframe), within `timeout_s` if given; else what is queued is dropped (counted). Returns True when
        the thread has stopped (the keyframe in hand gets `grace_s` more), so that its state (the map) can be
        read without it changing underneath."""
        self._closing.set()
        if not wait:
            with contextlib.suppress(queue.Empty):
                while True:
                    item = self._q.get_nowait()
                    if item is not None and not isinstance(item, _Settled):
                        self.dropped += 1
                    self._q.task_done()
        with contextlib.suppress(queue.Full):
            self._q.put(None, timeout=timeout_s)  # behind what is queued: the thread drains, then stops
        self._thread.join(timeout=timeout_s if wait else grace_s)
        if self._thread.is_alive():
            self._abandon.set()  # the rest is dropped; the keyframe in hand is finished
            log.warning("loop closure: %d keyframes still queued at close, dropped", self._q.qsize())
            self._thread.join(timeout=grace_s)
        return not self._thread.is_alive()
