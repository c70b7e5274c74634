"""`vio run`: the onboard daemon. Sensors -> estimator -> MAVLink, supervised for systemd.

Threads and the bounded buffers between them:

    source thread --(SensorBuffer: frames drop-oldest, IMU large + counted overflow)--> estimator thread
          \\--(SensorBuffer for the recorder, same policy)--> recorder thread (EurocWriter)
    estimator thread --(LatestState: newest NavState only)--> output thread (MAVLink, TUM log)
    main thread: signals, status line + status file once a second, sd_notify READY/WATCHDOG/STATUS

Why drop the oldest frame: an autopilot needs the current pose; a pose for a frame that waited behind
others is stale on arrival. IMU samples are never dropped silently, because pre-integration needs every one;
the IMU buffer holds many seconds, and if it still overflows the estimator is far behind: the overflow is
counted, logged and the estimator is reset (its IMU chain is broken anyway).

Faults are survived, not fatal: a source that raises or goes quiet for `run.source_timeout_s` is closed
and reopened with backoff (a finite source that has ended is not reopened); an estimator exception resets
the estimator; a MAVLink error reopens the link; a recorder or trajectory-file error (disk full, file-size
limit, read-only or removed folder) stops that output with one warning and leaves the rest running.
Only an invalid configuration ends the process (exit code 3, `vio.app.cli.EXIT_CONFIG`).

Readiness and supervision: READY=1 goes to systemd once the threads run and the sensors deliver data (or
after `run.ready_timeout_s` without data: the daemon keeps reopening the sensors). Tracking is not needed:
a drone that cannot initialise (dark hangar, lens cap) reports `waiting for vision` and is not restarted.
The watchdog is fed while every loop beats; a wedged loop (no heartbeat for 5 s) stops it.

What reaches the autopilot is never more than the estimator knows: a state goes out as tracking only while
camera frames arrive (the daemon's own check, `VISION_STALE_S`) and the estimator says it is tracking.

The daemon is part of the application layer (`vio.app`), the only code in `vio` that imports `drivers`
(inside functions, so the other commands stay usable without them).
"""

from __future__ import annotations

import argparse
import dataclasses
import logging
import os
import signal
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from vio import VioError
from vio.app.daemon.buffers import LatestState, RateWindow, SensorBuffer
from vio.app.daemon.outputs import (
    OutputWorker,
    RecorderWorker,
    StampErrorGate,
    stamp_error_text,
)
from vio.app.daemon.protocols import EstimatorApi, PoseOutput, Source
from vio.app.daemon.status import (
    STATUS_VERSION,
    _dash,
    _health_fields,
    _not_tracking_reason,
    _round,
    _source_health,
    write_status_file,
)
from vio.app.daemon.workers import EstimatorWorker, SourceWorker, Worker
from vio.app.endpoint_lock import mavlink_endpoint_lock
from vio.app.sdnotify import SdNotifier, watchdog_interval_s
from vio.config import VioConfig, load_config

if TYPE_CHECKING:
    from vio.calibration import StereoCalibration

log = logging.getLogger(__name__)

JOIN_BUDGET_S = 1.6  # shutdown must finish within 2 s of SIGTERM; keep a margin for the final status write
STUCK_S = 5.0  # a loop without a heartbeat this long is wedged: the watchdog stops being fed
VISION_STALE_S = 1.0  # no camera frame for this long: not tracking, whatever the last state said
FRAME_STAMP_WARN_MS = 2.0  # a frame stamp uncertain by this much (1 sigma) is a warning: a restamped camera's line
# error is 0.2-1 ms (3 ms of jitter), a camera kept as given for jittering too much reads 5 ms and more
# sources whose poses are another flight's (a recording, a simulation): never flown on (MavlinkOutput poses_to_armed)
NOT_THIS_VEHICLE = ("euroc", "fake")


def open_source(cfg: VioConfig, mavlink_link: Any = None) -> Source:
    """The configured sensor source, started (`mavlink_link`: the connection shared with the output)."""
    from drivers.source import open_source as driver_open_source

    src = driver_open_source(cfg.source, mavlink_link=mavlink_link)
    src.start()
    return src


def load_run_calibration(cfg: VioConfig, source_calibration: Any) -> Any:
    """The calibration file named in the config wins over what the device or dataset reports."""
    if cfg.source.calibration:
        from vio.calibration import load_calibration

        return load_calibration(cfg.source.calibration)
    return source_calibration


# ------------------------------------------------------------------------------------------------ service


def replay_refusal_warning(kind: str, refusing: str) -> str:
    """The status warning while the MAVLink output holds back a simulated or recorded source's poses (`refusing`:
    "armed", or why no disarmed heartbeat came). Before, the second case read "... another flight's and the no
    autopilot heartbeat says it is disarmed"."""
    why = "the autopilot says it is armed" if refusing == "armed" else "no autopilot heartbeat says it is disarmed"
    return f"poses not sent: [source] kind = {kind!r} is another flight's and {why}"

class Service:
    """Builds the pipeline, supervises it and reports its health; `run()` returns on SIGTERM/SIGINT."""

    def __init__(self, cfg: VioConfig, *, source_factory: Callable[[], Source] | None = None,
                 estimator_factory: Callable[[StereoCalibration], EstimatorApi] | None = None,
                 mavlink_factory: Callable[[], PoseOutput] | None = None, notifier: SdNotifier | None = None,
                 map_data: Any = None, vocabulary: Any = None) -> None:
        """`map_data`, `vocabulary`: `[map] load` and `[loop] vocabulary` as `vio run` already read and checked
        them at start (`CheckedInputs`; read here when None)."""
        self.cfg = cfg
        self.instance_lock: Any = None  # the open lock file (single_instance), held for the life of the process
        self.output_lock: Any = None  # the MAVLink output's endpoint (output_endpoint_lock), held likewise
        self._map_data = map_data
        self._vocabulary = vocabulary
        from vio.loop.mapfile import run_identity

        self._run_identity = run_identity(cfg.map.load)  # in the checkpoints' headers
        self.stop = threading.Event()
        self.notifier = notifier or SdNotifier()
        rc = cfg.run
        self.est_buf = SensorBuffer(rc.queue_frames, rc.queue_imu)
        self.rec_buf = SensorBuffer(rc.queue_frames * 4, rc.queue_imu) if rc.record_dir else None
        self.latest = LatestState()
        paced = cfg.source.kind in ("fake", "euroc") and not cfg.source.realtime
        # IMU from the autopilot on the output's connection: one link, one reader (a serial port opens once)
        self.mavlink_link = shared_mavlink_link(cfg) if source_factory is None else None
        self.source = SourceWorker(self.stop, source_factory or (lambda: open_source(cfg, self.mavlink_link)),
                                   [b for b in (self.est_buf, self.rec_buf) if b is not None],
                                   rc.source_timeout_s, rc.reconnect_max_s, paced=paced)
        self._estimator_factory = estimator_factory or _default_estimator_factory(cfg)
        self.loop = None  # loop closure beside the odometry ([loop] enabled), built once the calibration is known
        self._loop_output = None
        if cfg.loop.enabled or cfg.map.load or cfg.map.save:
            from vio.loop.output import CorrectedOutput

            self._loop_output = CorrectedOutput.from_config(cfg) if cfg.loop.output != "off" else None
        self.view = None
        if cfg.view.enabled:
            from vio.app.view import LiveView

            self.view = LiveView(cfg.view.target, self._calibration_now, cfg.view)
        self.estimator = EstimatorWorker(self.stop, self._make_estimator, self.est_buf, self.latest,
                                         rc.max_imu_gap_s, view=self.view)
        mount = None
        if mavlink_factory is None and cfg.mavlink.url:
            mavlink_factory = _default_mavlink_factory(cfg, self._calibration_now, self.mavlink_link)
            mount = self._set_mount
        stamps = StampErrorGate(self.source.stamp_uncertainty_s, cfg.mavlink.max_stamp_error_ms / 1e3,
                                cfg.backend.quality_sigma_m, cfg.mavlink.stamp_tolerance_ms / 1e3)
        self.output = OutputWorker(self.stop, self.latest, mavlink_factory, rc.trajectory_file, rc.reconnect_max_s,
                                   vision_ok=self.camera_fresh, mount=mount, stamps=stamps)
        if self._loop_output is not None:  # a map's frame is not turned into the autopilot's a second time
            self._loop_output.frame_turn = self.output.frame_turn
            self._loop_output.frame_pending = self.output.frame_pending  # a map's correction waits for the turn
        self.recorder = (RecorderWorker(self.stop, self.rec_buf, rc.record_dir, self._calibration_now,
                                        rc.record_format, rc.record_images, self.latest, lambda: self._last_status,
                                        rc.record_png_level)
                         if self.rec_buf is not None else None)
        self.started = time.time()
        self.started_mono = time.monotonic()
        self.ready = False
        self.rates = RateWindow()
        self.watchdog_s = watchdog_interval_s()
        self._last_watchdog = 0.0
        self._last_status: dict = {}
        self._logged_overflow = 0
        self._logged_drops = 0
        self._stall_warned = False
        self._other_camera_said: str | None = None  # the file calibration against the source's own, once compared

    # -- wiring ---------------------------------------------------------------------------------------
    def _calibration_now(self) -> Any:
        if not self.source.calibration_ready.is_set() and not self.cfg.source.calibration:
            return None
        return load_run_calibration(self.cfg, self.source.calibration)

    def _other_camera(self) -> str:
        """Once the source has reported its own calibration: '' when [source] calibration agrees with it, else why
        the file looks like another camera's (logged once). A file of another camera model (an OAK-D Long Range's
        150 mm baseline on an OAK-D's 75 mm) was used unsaid, every distance sent to the autopilot off by that ratio.
        Such a file is no recalibration (other_camera_problem): the estimator stops for the run, no pose is sent."""
        if self._other_camera_said is None and self.cfg.source.calibration and self.source.calibration is not None:
            from vio.calibration import other_camera_problem

            problem = other_camera_problem(load_run_calibration(self.cfg, None), self.source.calibration)
            self._other_camera_said = "" if problem is None else (
                f"[source] calibration = {self.cfg.source.calibration!r} is not this {self.cfg.source.kind} source's "
                f"camera: {problem} (what it reports itself); distances are off by that ratio: give this camera's "
                "calibration, or leave [source] calibration empty for its own")
            if problem:
                log.error("calibration: %s; no pose is estimated for the rest of this run", self._other_camera_said)
                self.estimator.stop_for_run(f"calibration of another camera: {problem}")
        return self._other_camera_said or ""

    def _set_mount(self, mav: Any) -> bool:
        """Give the MAVLink output the camera mount from the calibration once it is known (an OAK reports
        it only after boot); True when done."""
        calib = self._calibration_now()
        if calib is None:
            return False
        try:
            mav.set_camera_mount(calib.cam0.T_body_cam)
        except VioError as e:  # the calibration does not decide the mount: the output says so, once
            log.error("camera mount: %s; set [mavlink] mount = 'rpy' and mount_rpy_deg", e)
        return True

    def camera_fresh(self) -> bool:
        """The daemon's own fact: camera frames arrived within VISION_STALE_S (host time)."""
        last = self.source.last_frame
        return last > 0 and time.monotonic() - last <= VISION_STALE_S

    def _make_estimator(self) -> EstimatorApi | None:
        # the estimator needs the calibration, which an OAK only reports once it is open
        while not self.stop.is_set():
            calib = self._calibration_now()
            if calib is not None:
                if (self.cfg.loop.enabled or self.cfg.map.load or self.cfg.map.save) and self.loop is None:
                    self._start_loop(calib)
                try:
                    return self._estimator_factory(calib)
                except VioError as e:  # a calibration the estimator refuses (the device's own, in wrong units)
                    log.error("estimator not started: %s", e)
                    self.estimator.crashed = f"estimator not started: {e}"
                    return None
            self.estimator.beat()
            self.source.calibration_ready.wait(0.1)
        return None  # stopping before the sensors ever came up

    def _start_loop(self, calib: Any) -> None:
        from vio.app.loop_worker import LoopWorker
        from vio.loop.closer import LoopCloser

        closer = LoopCloser(calib, self.cfg.loop, self._vocabulary)
        if self.cfg.map.load and self._map_data is None:
            from vio.loop.mapfile import load_map

            self._map_data = load_map(self.cfg.map.load)
        if self._map_data is not None:  # [map] load, or this boot's checkpoint of [map] save (map_to_grow)
            closer.load_map(self._map_data)
        every = self.cfg.map.checkpoint_s if self.cfg.map.save else 0.0
        # full: the keyframe is dropped, the odometry never waits (nor for a checkpoint: written in that thread)
        self.loop = LoopWorker(closer, max_queue=16, checkpoint=self._save_checkpoint, checkpoint_s=every)
        self.estimator.loop_worker = self.loop
        if self.view is not None:  # the view shows the loop-corrected keyframes
            self.loop.keep_snapshot = True
            self.view.loop = self.loop
        self.estimator.loop_output = self._loop_output

    def _save_checkpoint(self, closer: Any) -> bool:
        """The map so far, marked as a checkpoint of this run ([map] checkpoint_s; in the loop-closure thread). Not
        while a start in flight's frame is still to be chosen (False: tried again at the next interval): the map of
        this flight's own frame is saved turned into the autopilot's, and a checkpoint written before the turn was
        known was in the flight's own frame while later saves were not (a review's note); a loaded map's frame is its
        own either way."""
        if not getattr(closer, "map_keyframes", 0) and self.output.frame_pending():
            log.debug("map checkpoint deferred: the frame of the start in flight is not chosen yet")
            return False
        h = closer.save_map(self.cfg.map.save, self.cfg.map.prune_m, self.cfg.map.prune_deg,
                            checkpoint=self._run_identity, world_turn=self.output.frame_turn())
        (log.info if not self.loop or not self.loop.checkpoints else log.debug)(
            "map checkpoint written to %s: %d keyframes (every %.0f s until the map is saved at stop)",
            h["path"], h["keyframes"], self.cfg.map.checkpoint_s)
        return True

    @property
    def workers(self) -> list[Worker]:
        return [w for w in (self.source, self.estimator, self.output, self.recorder) if w is not None]

    # -- main loop ------------------------------------------------------------------------------------
    def run(self) -> int:
        self.notifier.status("starting: opening sensors")
        for w in self.workers:
            w.start()
        next_status = time.monotonic() + 1.0
        while not self.stop.is_set():
            self.stop.wait(0.05)
            self._check_ready()
            self._feed_watchdog()
            if time.monotonic() >= next_status:
                next_status += 1.0
                self.report()
        return self.shutdown()

    def request_stop(self, signum: int | None = None, _frame: Any = None) -> None:
        if signum is not None and not self.stop.is_set():
            log.info("received %s: stopping", signal.Signals(signum).name)
        self.stop.set()
        self.est_buf.wake()
        if self.rec_buf is not None:
            self.rec_buf.wake()
        self.latest.wake()

    def shutdown(self) -> int:
        t0 = time.monotonic()
        self.notifier.stopping()
        self.stop.set()
        deadline = t0 + JOIN_BUDGET_S
        stuck = []
        for w in self.workers:  # source first: no new data; recorder last: it flushes what was queued
            w.join(max(0.0, deadline - time.monotonic()))
            if w.is_alive():
                stuck.append(w.name)
        if self.loop is not None:
            # the keyframes queued for loop closure belong in the saved map: drain them within the budget
            stopped = self.loop.close(wait=True, timeout_s=max(0.2, deadline - time.monotonic()), grace_s=0.2)
            if self.cfg.map.save and not stopped:
                log.error("map not saved: loop closure still busy after the shutdown budget")
            elif self.cfg.map.save:
                try:
                    h = self.loop.closer.save_map(self.cfg.map.save, self.cfg.map.prune_m, self.cfg.map.prune_deg,
                                                  world_turn=self.output.frame_turn())
                    log.info("map saved to %s: %d keyframes%s%s", h["path"], h["keyframes"],
                             f", {h['pruned_keyframes']} of this flight's pruned" if h["pruned_keyframes"] else "",
                             f" ({h['note']})" if h["left_out_keyframes"] else "")
                except Exception as e:  # noqa: BLE001 - a failed save must not hide the shutdown
                    log.error("map not saved: %s", e)
        if self.view is not None:
            self.view.close(timeout_s=max(0.2, deadline - time.monotonic()))
        status = self.snapshot()
        status["state"] = "stopped"
        # the last word of a daemon that no longer estimates: the snapshot taken as it stopped said tracking true, and
        # `vio status --json` kept saying so of a daemon gone for hours (docs/install.md: true only while fresh)
        status["estimator"]["tracking"] = False
        self._write_status(status)
        if stuck:
            log.warning("stopped with %s still busy after %.1f s (abandoned)", ", ".join(stuck), JOIN_BUDGET_S)
        log.info("stopped in %.2f s: %s", time.monotonic() - t0, self._summary(status))
        self.notifier.close()
        return 0

    def _check_ready(self) -> None:
        """READY=1 once the pipeline is up: threads started and sensor data flowing, or after
        `run.ready_timeout_s` without data (systemd would otherwise kill and restart a daemon whose camera
        is unplugged at boot; the daemon keeps reopening it by itself). A first pose is not needed."""
        if self.ready:
            return
        up = time.monotonic() - self.started_mono
        if self.source.connected:
            # READY means the pipeline runs; a silent IMU is said here too (and in the status), not hidden
            why = "sensors delivering" if self.source.last_imu else \
                f"camera delivering, no IMU sample yet ({_driver_error(self.source.source, 'imu') or 'starting'})"
        elif up >= self.cfg.run.ready_timeout_s:
            why = f"no sensor data after {up:.0f} s ({_silent_source_why(self.source)}); still trying"
        else:
            return
        self.ready = True
        log.info("ready after %.1f s: %s", up, why)
        self.notifier.ready(why)

    def _warn_stall(self, tracking: bool, sensors_ok: bool) -> None:
        """Sensors deliver but no pose for `run.stall_timeout_s`: one warning naming why (lens cap, darkness,
        a sensor error). The watchdog is NOT stopped for it: a restart would not bring the pose back."""
        if tracking:
            self._stall_warned = False
            return
        since = time.monotonic() - (self.estimator.last_state_time or self.started_mono)
        if self._stall_warned or not sensors_ok or since < self.cfg.run.stall_timeout_s:
            return
        self._stall_warned = True
        log.warning("waiting for vision: sensors deliver but no tracked pose for %.0f s (%s)", since,
                    _not_tracking_reason(self.estimator.health, self.camera_fresh()))

    def healthy(self) -> tuple[bool, list[str]]:
        """Alive = every loop beat recently and no thread died. No pose is not a reason: see _warn_stall."""
        problems = []
        for w in self.workers:
            if w.crashed:
                problems.append(f"{w.name} thread died ({w.crashed})")
            elif not w.is_alive() and not self.stop.is_set():
                problems.append(f"{w.name} thread ended")
            elif w.beat_age_s() > STUCK_S:
                problems.append(f"{w.name} loop stuck for {w.beat_age_s():.0f} s")
        return not problems, problems

    def _feed_watchdog(self) -> None:
        if self.watchdog_s is None or time.monotonic() - self._last_watchdog < self.watchdog_s:
            return
        ok, problems = self.healthy()
        if ok:
            self.notifier.watchdog()
            self._last_watchdog = time.monotonic()
        elif self._last_watchdog >= 0:
            log.error("not feeding the systemd watchdog: %s", "; ".join(problems))
            self._last_watchdog = -1.0  # log once; systemd will restart us

    # -- status ---------------------------------------------------------------------------------------
    def snapshot(self) -> dict:
        now = time.monotonic()
        src, est, out = self.source, self.estimator, self.output
        counters = {
            "camera": self.est_buf.frames_in, "imu": self.est_buf.imu_in, "estimator": est.frames,
            "output": out.sent, "poses": est.good_states,
        }
        rates = {k: round(v, 1) for k, v in self.rates.rates(counters).items()}
        ok, problems = self.healthy()
        warnings = list(problems)
        frame_age = now - src.last_frame if src.last_frame else None
        imu_age = now - src.last_imu if src.last_imu else None
        camera_ok = self.camera_fresh()
        imu_ok = imu_age is not None and imu_age <= VISION_STALE_S
        if not src.connected:
            warnings.append(f"sensors not delivering ({_silent_source_why(src)})")
        else:
            if not camera_ok:
                warnings.append("camera: no frames" + (f" for {frame_age:.1f} s" if frame_age is not None else ""))
            if not imu_ok:
                why = _driver_error(src.source, "imu")
                warnings.append("IMU: no samples" + (f" for {imu_age:.1f} s" if imu_age is not None else "")
                                + ": no poses" + (f" ({why})" if why else ""))
        if self.est_buf.frames_dropped > self._logged_drops:
            warnings.append(f"{self.est_buf.frames_dropped - self._logged_drops} frames dropped (estimator behind)")
            self._logged_drops = self.est_buf.frames_dropped
        if self.est_buf.imu_overflow > self._logged_overflow:
            warnings.append(f"IMU buffer overflow: {self.est_buf.imu_overflow - self._logged_overflow} samples lost")
            self._logged_overflow = self.est_buf.imu_overflow
        state, h = est.last_state, est.health
        pose_age = now - est.last_state_time if est.last_state_time else None
        # the truth about tracking: the last state said so, it is fresh, camera frames arrive, and the
        # estimator (which knows whether a usable frame reached its back end) agrees
        tracking = bool(state is not None and state.tracking and pose_age is not None and pose_age <= VISION_STALE_S
                        and camera_ok and (h is None or h.tracking))
        if h is not None and h.sensor_error:
            warnings.append(f"sensor error: {h.sensor_error}")
        other = self._other_camera()
        if other:
            warnings.append(f"calibration: {other}")
        if h is not None and h.calibration_warning:
            warnings.append(f"calibration: {h.calibration_warning}")
        if h is not None and h.stereo_warning:
            warnings.append(f"stereo: {h.stereo_warning}")
        frame_stamps = getattr(h, "frame_stamps", None) or {}
        sigma_ms = frame_stamps.get("stamp_sigma_ms") or 0.0
        if sigma_ms >= FRAME_STAMP_WARN_MS:
            warnings.append(f"camera: frame stamps uncertain by {sigma_ms:.1f} ms (1 sigma: arrival jitter the frame "
                            "clock cannot take out, estimator.frame_stamps); the poses and the covariance sent allow "
                            "for it, the accuracy suffers: stamp the frames nearer their exposure")
        if self.ready and not tracking:
            warnings.append(f"not tracking: {_not_tracking_reason(h, camera_ok, imu_ok)}")
        self._warn_stall(tracking, src.connected and imu_ok)
        link = out.link()
        if link["state"] in ("down", "closed"):
            warnings.append(f"autopilot link {link['state']}")
        withheld = bool(link.get("withholding_old_poses"))
        if withheld:
            # the autopilot gets nothing while the status would otherwise read running, quality 100
            warnings.append("poses withheld: older than [mavlink] max_state_age_ms "
                            f"({self.cfg.mavlink.max_state_age_ms:.0f} ms; the estimator is behind its sensors)")
            tracking = False
        not_finite = bool(link.get("withholding_not_finite"))
        if not_finite:
            # the output refuses a NaN / infinite estimate (a loss of tracking): the status read running, quality 100
            # the output's own words (drivers.mavlink_out._unsendable: the values, or the stamp), not a second copy
            why = link.get("withholding_not_sendable") or "the estimate cannot be carried by the pose messages"
            warnings.append(f"poses not sent: {why} (mavlink.states_not_finite)")
            tracking = False
        refusing = link.get("withholding_replay_poses")
        if refusing:
            # a recorded or simulated source (NOT_THIS_VEHICLE) and an autopilot that is armed or not heard disarmed
            warnings.append(replay_refusal_warning(self.cfg.source.kind, refusing))
        stamps = out.stamps
        clock_refused = stamps is not None and stamps.refusing
        if clock_refused:
            # the autopilot gets nothing: not tracking, as for poses too old (the status said quality 100 meanwhile)
            warnings.append(f"poses not sent: IMU stamps uncertain by {stamp_error_text(stamps.error_s)}, beyond "
                            f"[mavlink] max_stamp_error_ms = {stamps.max_error_s * 1e3:.0f} (the IMU source's clock "
                            "sync: source.driver clock in vio status --json)")
            tracking = False
        elif stamps is not None and stamps.error_s > stamps.tolerance_s and imu_ok:
            warnings.append(f"IMU stamps uncertain by {stamp_error_text(stamps.error_s)} (the IMU source's clock "
                            "sync): the covariance sent grows by the motion over that time and the quality falls")
        recording = self.recorder.status() if self.recorder is not None else None
        if recording is not None and recording["state"] == "failed":
            warnings.append(f"recording failed: {recording['error']}")
        trajectory = out.trajectory.status()
        if trajectory is not None and trajectory["state"] == "failed":
            warnings.append(f"trajectory file failed: {trajectory['error']}")
        lat = sorted(out.latency_ms)
        if not self.ready:
            mode = "starting"
        elif not ok:
            mode = "unhealthy"
        elif not tracking and not withheld and not clock_refused and not not_finite and not refusing and \
                src.connected and imu_ok and not getattr(h, "stopped_for_run", None):
            # the pipeline runs; no pose until the camera sees something usable. Not while a recorded or simulated
            # source's poses are refused to an armed autopilot: that, not vision, keeps them from it (degraded; it
            # read "waiting for vision" whenever the status came before the estimator's start, a flaky test here)
            mode = "waiting for vision"
        elif warnings or not tracking:
            mode = "degraded"
        else:
            mode = "running"
        snap = {
            "version": STATUS_VERSION,
            "pid": os.getpid(),
            "state": mode,
            "healthy": mode == "running",  # `vio status` exits 0 only then
            "written_unix": time.time(),
            "started_unix": self.started,
            "uptime_s": round(now - self.started_mono, 1),
            "rates_hz": rates,
            "source": {"kind": self.cfg.source.kind, "connected": src.connected, "finished": src.finished,
                       "disconnects": src.disconnects, "last_error": src.last_error,
                       "last_frame_age_s": _round(frame_age), "last_imu_age_s": _round(imu_age),
                       "frames_dropped": self.est_buf.frames_dropped, "imu_overflow": self.est_buf.imu_overflow,
                       "driver": _source_health(src.source)},
            "estimator": {
                "tracking": tracking,
                # what the autopilot gets (the output's checks applied): 0 while nothing tracked goes out
                "quality": _quality_sent(state, tracking and not refusing, out.quality_out),
                "initialized": h.initialized if h is not None else None,
                # the estimator's; the autopilot gets it past where this process started: mavlink.reset_counter
                "reset_counter": state.reset_counter if state is not None else None,
                # estimator resets so far, as the log counts them: the counter above moves with the next pose only
                "resets": (h.reset_counter + est.resets_before) if h is not None else None,
                "daemon_resets": est.resets,
                "errors": est.errors,
                "tracks": est.tracks,
                "last_pose_age_s": _round(pose_age),
                "position_m": [round(float(x), 3) for x in state.T_world_body[:3, 3]] if state is not None else None,
                **(_health_fields(h) if h is not None else {}),
            },
            "loop": None if self.loop is None else {
                **self.loop.status(), "output": self.cfg.loop.output,
                # reset_counter increments that were loop-correction steps, not estimator resets
                "loop_jumps": state.loop_jumps if state is not None else 0,
                # blend: metres the sent position still has to walk to the newest correction (it is that far off the
                # loop-corrected pose on purpose, and the vehicle will move by it)
                **({"blend_remaining_m": round(self._loop_output.remaining_m, 3),
                    "blend_remaining_deg": round(self._loop_output.remaining_deg, 2)}
                   if self._loop_output is not None and self.cfg.loop.output == "blend" else
                   {"blend_remaining_m": None, "blend_remaining_deg": None})},
            "latency_ms": {"p50": round(lat[len(lat) // 2], 1), "max": round(lat[-1], 1)} if lat else None,
            "mavlink": {**link, "sent": out.sent, "errors": out.errors, "withheld_no_camera": out.withheld,
                        **(out.stamps.status() if out.stamps is not None else {})},
            "recording": recording,
            "trajectory_file": trajectory,
            "watchdog": {"enabled": self.watchdog_s is not None, "fed": self._last_watchdog > 0},
            "warnings": warnings,
        }
        return snap

    def report(self) -> None:
        snap = self.snapshot()
        self._last_status = snap
        line = self._summary(snap)
        log.info("%s", line)
        self.notifier.status(line)
        self._write_status(snap)

    @staticmethod
    def _summary(s: dict) -> str:
        r, e, lp = s["rates_hz"], s["estimator"], s.get("loop")
        lat = s["latency_ms"]
        parts = [
            s["state"],
            f"cam {r['camera']:.1f} Hz imu {r['imu']:.0f} Hz out {r['output']:.1f} Hz",
            f"tracks {_dash(e['tracks'])} q {_dash(e['quality'])}",
            f"resets {_resets(e, lp)}",
            f"latency {lat['p50']:.0f}/{lat['max']:.0f} ms" if lat else "latency -",
            f"mav {s['mavlink']['state']}",
        ]
        if lp:
            where = {None: "", True: ", in the map", False: ", not in the map yet"}[lp["relocalised"]]
            if lp["relocalised"] and lp.get("confirmed") is False:
                where += " (confirming: not sent in its frame yet)"
            if lp.get("placement_sigma_m") is not None:
                where += f" +-{lp['placement_sigma_m'] * 100:.1f} cm"
            parts.insert(4, f"loop {lp['loop_edges']} edges{where}"
                         + (f", {lp['loop_jumps']} jumps" if lp["loop_jumps"] else "")
                         + _blend_to_go(lp))
        if s["warnings"]:
            parts.append("WARN " + "; ".join(s["warnings"]))
        return " | ".join(parts)

    def _write_status(self, snap: dict) -> None:
        path = self.cfg.run.status_file
        if not path:
            return
        try:
            write_status_file(Path(path), snap)
        except OSError as e:
            if not getattr(self, "_status_warned", False):
                log.warning("cannot write status file %s: %s", path, e.strerror)
                self._status_warned = True


def _quality_sent(state: Any, sending: bool, quality_out: int | None) -> int | None:
    """The quality the autopilot gets: the output's (after its vision and clock checks), 0 while no tracked pose goes
    out (lost, too old, refused), None before any state. The estimator's own said 100 while the output refused."""
    if state is None:
        return None
    if not sending:
        return 0
    return state.quality if quality_out is None else quality_out


def _silent_source_why(worker: Any) -> str:
    """Why the source delivers nothing: the source thread's own reason, else what its driver last said (an OAK's
    'no OAK device found' from its first second: the status said '(starting)' for the 10 s the thread waits before
    it calls an unbooted device lost, an integrator's walk-through), else 'starting'."""
    if worker.last_error:
        return worker.last_error
    try:
        health = worker.source.health() if worker.source is not None else {}
    except Exception:  # display only
        health = {}
    for part in (health.get("camera"), health.get("imu"), health):  # a combined source's parts, or the source
        if isinstance(part, dict) and part.get("last_error"):
            return str(part["last_error"])
    return "starting"


def _driver_error(source: Any, part: str) -> str:
    """The last error of one part ("camera", "imu") of a combined source, for the status line that says the part
    is silent (the serial IMU's 'cannot open /dev/ttyUSB0' sat only in the driver's JSON)."""
    try:
        sub = source.health().get(part) if source is not None else None
    except Exception:  # display only
        return ""
    return str(sub.get("last_error") or "") if isinstance(sub, dict) else ""


def _default_estimator_factory(cfg: VioConfig) -> Callable[[Any], Any]:
    def make(calib: Any) -> Any:
        from vio.estimator import Estimator as VioEstimator

        return VioEstimator(calib, cfg.estimator)
    return make


def shared_mavlink_link(cfg: VioConfig) -> Any:
    """The MavlinkLink that `imu = "mavlink"` shares with the pose output (mavlink_imu_url empty or equal
    to the [mavlink] url), else None."""
    src = cfg.source
    if src.imu != "mavlink" or not cfg.mavlink.url or src.mavlink_imu_url not in ("", cfg.mavlink.url):
        return None
    from drivers.mavlink_link import MavlinkLink

    return MavlinkLink(cfg.mavlink.url, source_system=cfg.mavlink.system_id or cfg.mavlink.target_system)


def _blend_to_go(lp: dict) -> str:
    """', blending 0.42 m, 12.0 deg to go' while a blend correction still walks (both parts are what the vehicle
    will still be moved and turned by), else ''."""
    m, deg = lp.get("blend_remaining_m") or 0.0, lp.get("blend_remaining_deg") or 0.0
    if m < 0.01 and deg < 0.1:
        return ""
    return f", blending {m:.2f} m, {deg:.1f} deg to go"


def _resets(e: dict, lp: dict | None) -> int:
    """Estimator resets for the health line: as the log counts them (the estimator's own count), else from the
    reset_counter sent, less the loop-correction steps in it."""
    if e.get("resets") is not None:
        return int(e["resets"])
    return (e["reset_counter"] or 0) - (lp["loop_jumps"] if lp else 0)


def _default_mavlink_factory(cfg: VioConfig, calibration: Callable[[], StereoCalibration | None],
                             link: Any = None) -> Callable[[], Any]:
    def make() -> Any:
        from drivers.mavlink_out import MavlinkOutput

        calib = calibration()  # the camera mount comes from it; unknown yet: Service._set_mount later
        # its own thread answers TIMESYNC within milliseconds (PX4 rejects slow round trips). A recorded or
        # simulated source ("euroc", "fake") is another flight's: as with `vio replay --mavlink`, no pose of it
        # goes to an autopilot that is armed or unheard, and its losses ask no LAND
        return MavlinkOutput(cfg.mavlink, cfg.mavlink.url, link=link, counter_file=cfg.mavlink.counter_file,
                             max_state_age_ms=cfg.mavlink.max_state_age_ms, random_first_counter=True,
                             T_body_cam0=calib.cam0.T_body_cam if calib is not None else None,
                             poses_to_armed=cfg.source.kind not in NOT_THIS_VEHICLE).start()
    return make


# ---------------------------------------------------------------------------------------------- CLI glue

def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--config", required=True, help="TOML configuration (e.g. /etc/kestrel-vio/config.toml)")


def run(args: argparse.Namespace) -> int:
    from vio.app.cli import EXIT_CONFIG

    try:
        cfg = load_config(args.config)
        checked = check_run_config(cfg, warn=log.warning)
    except VioError as e:
        print(f"vio run: configuration error: {e}", file=sys.stderr)
        return EXIT_CONFIG
    try:
        lock = single_instance(cfg)  # held (open) for the life of the process
        output_lock = output_endpoint_lock(cfg)  # likewise
    except VioError as e:
        print(f"vio run: {e}", file=sys.stderr)
        return EXIT_CONFIG
    if not (getattr(args, "verbose", False) or getattr(args, "quiet", False)):
        logging.getLogger().setLevel(cfg.run.log_level)
    try:
        map_data = map_to_grow(cfg, checked.map_data)
    except VioError as e:
        # a checkpoint that cannot be moved aside (the state folder remounted read-only after the power cut that
        # left it), or a file at [map] save that is not a map this program reads: exit 3 is never restarted and the
        # vehicle had no VIO at all; as check_run_config does for a map folder not writable, fly without saving the
        # map (which would write over that file)
        log.error("%s: running, the map will not be saved", e)
        cfg = dataclasses.replace(cfg, map=dataclasses.replace(cfg.map, save=""))
        map_data = checked.map_data
    service = Service(cfg, map_data=map_data, vocabulary=checked.vocabulary)
    service.instance_lock, service.output_lock = lock, output_lock
    from drivers.signals import stop_on_signal

    # not service.request_stop itself: Event.set() in a handler can deadlock the main loop's stop.wait()
    signal.signal(signal.SIGTERM, stop_on_signal(service.request_stop))
    signal.signal(signal.SIGINT, stop_on_signal(service.request_stop))
    # SIGHUP killed the daemon without a word, and systemd takes that for a clean exit (no restart): an ssh
    # session ending under one started by hand, or `systemctl kill -s HUP` (a review's finding). There is no
    # reload: said, and ignored.
    signal.signal(signal.SIGHUP, lambda signum, _frame: log.warning(
        "received SIGHUP: ignored (vio run does not reload its configuration; restart it to apply a new one)"))
    log.info("kestrel-vio starting: source %s, MAVLink %s, recording %s, watchdog %s", cfg.source.kind,
             cfg.mavlink.url or "off", cfg.run.record_dir or "off",
             f"{service.watchdog_s:.1f} s" if service.watchdog_s else "off")
    return service.run()


def output_endpoint_lock(cfg: VioConfig) -> Any:
    """The [mavlink] url's endpoint lock (vio.app.endpoint_lock.mavlink_endpoint_lock, which `vio replay
    --mavlink` takes too), held for the life of the process, or None (no [mavlink] url, not Linux, no lock to be
    had: said). A second vio run, or a replay, sending to the same autopilot is refused, naming the holder's pid."""
    if not cfg.mavlink.url:
        return None
    return mavlink_endpoint_lock(cfg.mavlink.url, f"[mavlink] url = {cfg.mavlink.url!r}",
                                 "give this one another [mavlink] url")


def single_instance(cfg: VioConfig) -> Any:
    """The open lock file (`[run] status_file` + ".lock") this process holds, or None without a status file or
    where no lock can be had (said: no lock is no reason not to fly).

    Two daemons on one configuration (the service, and one started by hand on the bench) both sent to the
    autopilot as component 197, their poses interleaved with time going backwards, and wrote one status and
    trajectory file in turn (a review's finding). The second is refused, naming the first's pid; the lock goes
    with the process, however it ends. The status folder is made first (the status writer makes it anyway), so
    that every daemon locks the same path; a lock file another user made is locked read-only."""
    import errno
    import fcntl

    if not cfg.run.status_file:
        return None
    path = Path(cfg.run.status_file + ".lock")

    def no_lock(e: OSError) -> None:
        log.warning("no instance lock (%s: %s): a second vio run on this configuration would not be refused", path,
                    e.strerror or e)

    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        f = open(path, "a+")
    except PermissionError:
        try:
            f = open(path)  # flock needs no write access: another user's lock file still locks
        except OSError as e:
            return no_lock(e)
    except OSError as e:
        return no_lock(e)
    try:
        fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError as e:
        if e.errno not in (errno.EWOULDBLOCK, errno.EAGAIN, errno.EACCES):
            # a file system without locks (some network or overlay mounts): said, and the daemon runs
            f.close()
            return no_lock(e)
        f.seek(0)
        pid = f.read().strip() or "?"
        f.close()
        raise VioError(f"another vio run (pid {pid}) is running with this configuration's status file "
                       f"({cfg.run.status_file}): two daemons would send to the autopilot as one; stop it first "
                       f"(the service: systemctl stop kestrel-vio; one started by hand: kill {pid})") from None
    if f.writable():
        f.seek(0)
        f.truncate()
        f.write(f"{os.getpid()}\n")
        f.flush()
    return f


@dataclass(frozen=True)
class CheckpointPlan:
    """What a `vio run` starting now does with a checkpoint at `[map] save` (checkpoint_plan): `grow` it (`map`),
    move it `aside` to `aside`, or nothing (`action` None: no checkpoint there); `said` is its log line, `ahead` the
    same said before it is done (`vio config check`)."""

    action: str | None = None
    map: Any = None
    aside: Path | None = None
    said: str = ""
    ahead: str = ""


def checkpoint_plan(cfg: VioConfig, map_data: Any) -> CheckpointPlan:
    """Decided, not done: map_to_grow does it at start, `vio config check` says it (a checkpoint waiting at
    `[map] save` was not said before the daemon started). `map_data` is `[map] load`'s map as read. VioError for a
    file at `[map] save` that is not a map this program reads: no save may write over it."""
    from vio.io.outputs import same_file
    from vio.loop.mapfile import boot_id, load_map, loaded_key

    save = cfg.map.save
    if not save or not os.path.isfile(save):
        return CheckpointPlan()
    # one file as check_run_config sees it (a hard link too): the map grown in place
    if cfg.map.load and same_file(cfg.map.load, save):
        cp = (map_data.header.get("checkpoint") if map_data is not None else None) or {}
        if not cp:
            return CheckpointPlan()
        # the map grown in place: loaded as configured, whichever run's checkpoint it is
        said = (f"map: {save} is a checkpoint of a run (pid {cp.get('pid')}, started {cp.get('started_utc')}) that "
                "did not stop cleanly: loaded as [map] load, this run grows it")
        return CheckpointPlan("grow", map_data, None, said, said.replace("this run", "vio run"))
    try:
        m = load_map(save)
    except VioError as e:
        # not a map this program reads (a user's file, a map of a newer format, a damaged one): the first checkpoint
        # renamed this run's map over it, unsaid (a review's finding); vio run flies without saving the map instead
        raise VioError(f"[map] save: {e}; vio run would write over it: move it away or set another [map] save") \
            from None
    cp = m.header.get("checkpoint")
    if not cp:
        # a finished map of another run ([map] save left set after the mapping flight): this run's first checkpoint
        # wrote over it, and a 21-keyframe map became this flight's 7 (an integrator's walk-through). It is kept as
        # NAME.previous.npz, one generation (an older one there is replaced: a daemon saving at every boot must not
        # fill the disk), said
        p = Path(os.path.realpath(save))
        aside = p.with_name(f"{p.stem}.previous{p.suffix}")
        made = m.header.get("created_utc") or "an earlier run"
        older = " (replacing the older one there)" if aside.exists() else ""
        return CheckpointPlan("aside", None, aside, (
            f"map: {save} held the finished map of {made} ({len(m.t_ns)} keyframes), which this run's map would "
            f"write over: moved to {aside}{older}, kept (load it with [map] load to fly in it)"), (
            f"map: {save} holds the finished map of {made} ({len(m.t_ns)} keyframes): vio run moves it to {aside}"
            f"{older} and saves a map of its own there; to grow it instead, set [map] load to the same file"))
    loaded = loaded_key(cfg.map.load)  # as the run that wrote the checkpoint named its own
    if cp.get("boot_id") and cp["boot_id"] == boot_id() and cp.get("loaded") == loaded:
        said = (f"map: {save} is the checkpoint of this daemon's run started {cp.get('started_utc')} (pid "
                f"{cp.get('pid')}) on this boot, which did not stop cleanly: its {len(m.t_ns)} keyframes are loaded"
                + (f" in place of [map] load (they hold {cfg.map.load})" if loaded else "")
                + " and this run grows them")
        return CheckpointPlan("grow", m, None, said, said.replace("this run", "vio run"))
    p = Path(os.path.realpath(save))  # beside the file itself: renamed from a link's folder it may cross devices
    stamp = str(m.header.get("created_utc") or "").replace("-", "").replace(":", "")[:15] or \
        time.strftime("%Y%m%dT%H%M%S")
    aside = p.with_name(f"{p.stem}.checkpoint-{stamp}{p.suffix}")
    k = 1
    while aside.exists():
        aside, k = p.with_name(f"{p.stem}.checkpoint-{stamp}-{k}{p.suffix}"), k + 1
    why = "another boot" if cp.get("boot_id") != boot_id() else f"this boot that loaded {cp.get('loaded')}"
    run = f"a run on {why} (pid {cp.get('pid')}, started {cp.get('started_utc')}) that did not stop cleanly"
    return CheckpointPlan("aside", None, aside, (
        f"map: {save} was the checkpoint of {run}: moved to {aside}, kept (load it with [map] load to grow it); this "
        "run saves a map of its own"), (
        f"map: {save} is the checkpoint of {run}: vio run moves it to {aside} and keeps it (load it with [map] load to "
        "grow it), and saves a map of its own"))


def map_to_grow(cfg: VioConfig, map_data: Any) -> Any:
    """The map this run starts from: `map_data` (`[map] load`, read by check_run_config), or the checkpoint a run of
    this configuration on this boot left at `[map] save` when it did not stop cleanly (killed by the watchdog, the
    OOM killer, a crash: systemd restarts it), which holds the loaded map and that run's flight so far. A checkpoint
    from another boot, or of a run that loaded another map, is moved aside to NAME.checkpoint-TIME.npz (kept, said)
    rather than grown: this flight may be elsewhere, and its keyframes are saved only once it relocalises in what
    it loaded. Temporary files of `[map] save` whose writer no longer runs (a write cut short) are removed first:
    each is as large as the map, one more at every such restart. Called once at start, after the instance lock (no
    other daemon of this configuration runs)."""
    if cfg.map.save:  # a checkpoint's write cut short (the stop's budget ran out, SIGKILL, a power cut)
        from vio.io.atomic import remove_stale_temporaries

        removed = remove_stale_temporaries(Path(os.path.realpath(cfg.map.save)))
        if removed:
            log.warning("map: removed %d temporary file(s) of [map] save left by a run stopped while it wrote the map "
                        "(%s)", len(removed), ", ".join(str(p) for p in removed))
    plan = checkpoint_plan(cfg, map_data)
    if plan.action == "grow":
        log.info("%s", plan.said)
        return plan.map
    if plan.action == "aside":
        try:
            os.rename(os.path.realpath(cfg.map.save), plan.aside)
        except OSError as e:
            raise VioError(f"[map] save: {cfg.map.save} is the map of another run, and it cannot be moved aside to "
                           f"{plan.aside} ({e.strerror or e}); it is kept: move it, or load it with [map] load") \
                from None
        log.warning("%s", plan.said)
    return map_data


@dataclass(frozen=True)
class CheckedInputs:
    """Files check_run_config read to check them, for the service to use rather than read again (None: not read)."""

    map_data: Any = None  # [map] load
    vocabulary: Any = None  # [loop] vocabulary (a custom one; the packaged default is read by the loop stage)


def check_run_config(cfg: VioConfig, warn: Callable[[str], None] | None = None) -> CheckedInputs:
    """Problems the daemon cannot recover from by retrying: report them now, with the key to fix. Returns the
    `[map] load` map and `[loop] vocabulary` it read (`CheckedInputs`), for the service to use rather than read
    them again. With `warn`
    (`vio run`), an output folder that cannot be written is said there and the daemon runs without that output;
    without it (`vio config check`) it is an error."""
    src = cfg.source
    # an extra that is not installed: the source would be retried forever, "degraded", unseen by systemd
    from vio.extras import require

    if src.kind == "oak":
        require("depthai", "oak", '[source] kind = "oak"')
    if src.imu == "serial":
        require("serial", "serial", '[source] imu = "serial"')
    if cfg.view.enabled:  # the Service would stop in its constructor: exit 1, which systemd restarts for ever
        require("rerun", "view", "[view] enabled = true")
    if cfg.run.record_dir and cfg.run.record_format == "mcap":  # no record_dir: no recording, nothing needed
        # the recorder thread would fail at once, leaving a daemon that flies without the recording it was told to make
        from vio.io.bag import require_mcap_writer

        require_mcap_writer('[run] record_format = "mcap"')
    if src.kind == "euroc" and not src.dataset:
        raise VioError("[source] kind = 'euroc' needs 'dataset' (path of a EuRoC folder)")
    if src.kind == "euroc" and not Path(src.dataset).exists():
        raise VioError(f"[source] dataset = {src.dataset!r}: folder not found")
    calib = None
    if src.calibration:
        from vio.calibration import calibration_units_problem, load_calibration

        calib = load_calibration(src.calibration)  # VioError naming the file and key
        problem = calibration_units_problem(calib)
        if problem:
            raise VioError(f"[source] calibration = {src.calibration!r}: {problem}")
    if src.kind == "euroc":
        # what `vio replay` refuses at start (a missing IMU file, its units, images of another size than the
        # calibration's) the daemon would retry forever, "waiting for vision" (a review's finding)
        from vio.app.replay import preflight
        from vio.io.euroc import EurocDataset

        try:
            preflight(EurocDataset(src.dataset, calibration=calib))
        except VioError as e:
            raise VioError(f"[source] dataset = {src.dataset!r}: {e}") from None
    if calib is not None and src.kind in ("fake", "sitl", "oak"):
        from vio.calibration import streamed_size_problem

        problem = streamed_size_problem(calib, src.width, src.height, src.calibration)
        if problem:
            raise VioError(problem)
    if src.imu == "mavlink" and src.mavlink_imu_url:
        from drivers.mavlink_link import check_url

        check_url(src.mavlink_imu_url, "[source] mavlink_imu_url")
        from vio.serial_url import split_serial_url

        dev = [split_serial_url(u)[0] for u in (src.mavlink_imu_url, cfg.mavlink.url) if u and u.startswith("/dev/")]
        if len(dev) == 2 and os.path.realpath(dev[0]) == os.path.realpath(dev[1]) and \
                src.mavlink_imu_url != cfg.mavlink.url:
            # two links on one serial device: the second cannot open it (held exclusively), and was retried for ever
            raise VioError(f"[source] mavlink_imu_url = {src.mavlink_imu_url!r} and [mavlink] url = "
                           f"{cfg.mavlink.url!r} are one serial device: leave mavlink_imu_url empty to share the link")
    if src.imu == "serial" and cfg.mavlink.url.startswith("/dev/"):
        from vio.serial_url import split_serial_url

        if os.path.realpath(split_serial_url(cfg.mavlink.url)[0]) == os.path.realpath(src.serial_port):
            # the two readers took each other's bytes: frames lost to the MAVLink parser and MAVLink to the IMU's
            raise VioError(f"[source] serial_port = {src.serial_port!r} is the autopilot's port ([mavlink] url = "
                           f"{cfg.mavlink.url!r}): a serial IMU needs a port of its own; for the flight controller's "
                           "IMU set [source] imu = 'mavlink'")
    if cfg.mavlink.url:  # a connection string that can never open would be retried forever, unseen by systemd
        from drivers.mavlink_out import check_mavlink_config

        check_mavlink_config(cfg.mavlink)
    map_data = vocabulary = None
    if cfg.map.load:  # a map that cannot be read would only kill the estimator thread once the sensors are up
        from vio.loop.mapfile import load_map

        try:
            map_data = load_map(cfg.map.load)
        except VioError as e:
            raise VioError(f"[map] load: {e}") from None
    if (cfg.loop.enabled or cfg.map.load or cfg.map.save) and cfg.loop.vocabulary:
        # as [map] load: a vocabulary that cannot be read would only kill the estimator thread once the sensors
        # are up, and leave the daemon unhealthy (restarted for ever under systemd) instead of saying why at start
        from vio.loop.vocabulary import Vocabulary

        try:
            vocabulary = Vocabulary.load(cfg.loop.vocabulary)
        except VioError as e:
            raise VioError(f"[loop] vocabulary: {e}") from None
    from vio.io.outputs import NotWritable, check_not_reads, check_outputs, folder_problem

    recording = src.dataset if src.kind == "euroc" else None
    reads = {"[source] calibration": src.calibration, "[loop] vocabulary": cfg.loop.vocabulary,
             "[map] load": cfg.map.load, "[source] dataset": recording}
    if cfg.map.save:
        try:  # its folder (over what the daemon reads, or into the recording: with the other outputs, below)
            check_outputs({"the map": cfg.map.save}, renamed=("the map",))
        except VioError as e:
            if warn is None or not isinstance(e, NotWritable):
                raise VioError(f"[map] save: {e}") from None
            # a state folder gone read-only: fly without saving rather than not at all (exit 3 is never restarted)
            warn(f"[map] save: {e}: running, the map will not be saved")
    files = {f"[run] {k}": getattr(cfg.run, k) for k in ("trajectory_file", "status_file")}
    files["[map] save"], files["[mavlink] counter_file"] = cfg.map.save, cfg.mavlink.counter_file
    # one file for two outputs: each wrote over the other (the pose log died); the pose log over the calibration,
    # or into the recording replayed, passed the check (a QA sweep's finding); the map was written over the
    # calibration at shutdown: never over what the daemon reads, bar the map it grows
    check_not_reads(files, reads, grows={"[map] save": "[map] load"})
    check_outputs({}, recordings=(recording,), folders={**files, "[run] record_dir": cfg.run.record_dir})
    for key in ("record_dir", "trajectory_file", "status_file"):
        value = getattr(cfg.run, key)
        if not value:
            continue
        parent = Path(value) if key == "record_dir" else Path(value).parent
        # a name over the file system's limit (255 bytes): exists() raised (an internal error), and a status file's
        # own name passed and failed at every write in flight
        too_long = next((part for part in Path(value).parts if len(os.fsencode(part)) > 255), None)
        if too_long is not None:
            raise VioError(f"[run] {key}: the name {too_long[:24]!r}... is {len(os.fsencode(too_long))} bytes long, "
                           "over the 255 a file system allows")
        try:
            existing = next((p for p in (parent, *parent.parents) if p.exists()), None)
        except OSError as e:  # the whole path over PATH_MAX, say
            raise VioError(f"[run] {key} = {value!r}: {e.strerror or e}") from None
        if existing is not None and not existing.is_dir():
            raise VioError(f"[run] {key} = {value!r}: {existing} is a file, not a folder")
        # tried, not only asked: os.access says yes to root in /proc and in a read-only folder
        unwritable = existing is not None and (not os.access(existing, os.W_OK) and f"{existing} is not writable"
                                               or folder_problem(existing, made=False))
        if unwritable:
            problem = f"[run] {key} = {value!r}: {unwritable}"
            if warn is None:
                raise VioError(problem)
            # `vio run` flies without that output rather than not at all: a disk gone read-only or full in flight
            # made the watchdog's restart exit 3, which systemd never restarts (a review's finding)
            warn(f"{problem}: running without it")
    for what, value in files.items():
        if what == "[map] save" or not value:  # the map: check_outputs above
            continue
        try:
            is_folder = Path(value).is_dir()
        except OSError:  # a counter_file name over the file system's limits: not kept, a random start (the daemon)
            is_folder = False
        if is_folder:
            # a status file there was never written ('Is a directory', logged once) and `vio status` could not read
            # it; the lock went beside it as FOLDER.lock; a reset_counter was never kept (a random start each time,
            # said only as a warning)
            raise VioError(f"{what} = {value!r}: is a folder; give a file name in it")
    return CheckedInputs(map_data, vocabulary)
