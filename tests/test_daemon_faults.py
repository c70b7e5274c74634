"""Issue 14, the daemon's side: faults of its outputs and inputs, seen from outside.

In process (stand-ins, about a second each): a recording folder and a trajectory folder removed mid-flight,
a camera that sees nothing usable (READY anyway, `waiting for vision`, watchdog still fed), camera frames
that stop, a wedged estimator loop (the watchdog stops). As subprocesses (the real `vio run`): a file-size
limit and a full disk under the recorder and the trajectory file, then an IMU that stops; and the EuRoC
excerpt whose images end while its IMU runs on (camera loss).
"""

from __future__ import annotations

import contextlib
import io
import json
import logging
import os
import resource
import shutil
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from test_service import (
    LAUNCHER,
    REPO,
    FakeAutopilot,
    RecordingMavlink,
    ScriptedEstimator,
    ScriptedSource,
    _need_pipeline,
    _received,
    _started,
    _wait,
    fly_fake,
    notify_socket,
)

import vio.app.daemon.service as service
from vio.app.daemon.service import Service
from vio.app.sdnotify import SdNotifier
from vio.app.status import EXIT_UNHEALTHY
from vio.config import config_from_dict
from vio.io.euroc import EurocDataset
from vio.types import NavState

__all__ = ["notify_socket"]  # the fixture, imported for the tests below


class CalibratedSource(ScriptedSource):
    """ScriptedSource with a real calibration (the recorder writes it into sensor.yaml)."""

    def calibration(self):
        from vio.sim import default_calibration

        return default_calibration(width=8, height=8)


def _service(tmp_path: Path, *, run: dict | None = None, blind: threading.Event | None = None,
             silent: threading.Event | None = None, notifier: SdNotifier | None = None,
             estimator=None) -> tuple[Service, list[RecordingMavlink]]:
    cfg = config_from_dict({"run": {"status_file": str(tmp_path / "status.json"), **(run or {})}})
    mavs: list[RecordingMavlink] = []

    def make_mav() -> RecordingMavlink:
        mavs.append(RecordingMavlink())
        return mavs[-1]

    silent = silent or threading.Event()
    svc = Service(cfg, source_factory=lambda: _started(CalibratedSource([], silent, [])),
                  estimator_factory=estimator or (lambda c: ScriptedEstimator("calib", [], blind)),
                  mavlink_factory=make_mav, notifier=notifier or SdNotifier(""))
    return svc, mavs


def _run(svc: Service) -> threading.Thread:
    t = threading.Thread(target=svc.run)
    t.start()
    return t


def _stop(svc: Service, runner: threading.Thread) -> None:
    svc.request_stop()
    runner.join(5)
    assert not runner.is_alive()


def _tracked(mavs: list[RecordingMavlink]) -> int:
    return sum(s.tracking for m in mavs for s in m.states)


# ------------------------------------------------------------------------------------------ in process

def test_removed_output_folders_stop_those_outputs_only(tmp_path: Path, caplog) -> None:
    svc, mavs = _service(tmp_path, run={"record_dir": str(tmp_path / "rec"),
                                        "trajectory_file": str(tmp_path / "poses" / "traj.tum")})
    runner = _run(svc)
    try:
        assert _wait(lambda: svc.recorder.frames >= 5 and svc.output.trajectory.poses >= 5, 5)
        shutil.rmtree(tmp_path / "rec")
        shutil.rmtree(tmp_path / "poses")  # writes to the open file still succeed: the daemon must notice
        assert _wait(lambda: svc.recorder.state == "failed", 3), svc.recorder.state
        assert _wait(lambda: svc.output.trajectory.state == "failed", 3)
        n = _tracked(mavs)
        assert _wait(lambda: _tracked(mavs) > n + 10, 3), "pose output stopped with the recorder"
        assert svc.healthy() == (True, [])  # nothing for the watchdog to act on
        snap = svc.snapshot()
        assert snap["recording"]["state"] == "failed" and "folder was removed" in snap["recording"]["error"]
        assert snap["trajectory_file"]["state"] == "failed" and "removed" in snap["trajectory_file"]["error"]
        assert any(w.startswith("recording failed") for w in snap["warnings"])
        assert snap["state"] == "degraded"
        time.sleep(0.5)
    finally:
        _stop(svc, runner)
    warnings = [r.getMessage() for r in caplog.records if r.levelname == "WARNING"]
    assert sum(w.startswith("recording stopped") for w in warnings) == 1, warnings
    assert sum(w.startswith("trajectory file") for w in warnings) == 1, warnings
    assert not svc.rec_buf._frames and svc.rec_buf.closed  # nothing piles up behind a failed recorder


def test_an_estimator_stopped_for_the_run_reads_degraded_not_waiting_for_vision(tmp_path: Path) -> None:
    """The IMU against the camera (a deg/s gyro, an IMU mounted 90 deg off) stops the estimator for the run: the
    daemon said "waiting for vision", as if the camera only had to see something; it is degraded, saying why."""
    import dataclasses

    class Stopped(ScriptedEstimator):
        def health(self):
            why = "the gyro turns 56x what the camera sees (...): deg/s instead of rad/s (57.3x)?"
            return dataclasses.replace(super().health(), initialized=False, tracking=False, sensor_error=why,
                                       stopped_for_run=why)

    blind = threading.Event()
    blind.set()
    svc, mavs = _service(tmp_path, estimator=lambda c: Stopped("calib", [], blind))
    runner = _run(svc)
    try:
        assert _wait(lambda: svc.ready, 3)
        assert _wait(lambda: svc.snapshot()["state"] == "degraded", 3), svc.snapshot()["state"]
        assert any("sensor error: the gyro turns 56x" in w for w in svc.snapshot()["warnings"])
        assert _tracked(mavs) == 0
    finally:
        _stop(svc, runner)


def test_blind_camera_is_ready_waiting_for_vision_and_keeps_the_watchdog(tmp_path: Path, notify_socket,
                                                                          monkeypatch, caplog) -> None:
    """Lens cap on at boot: READY once the sensors deliver, state 'waiting for vision', watchdog fed, one
    warning after stall_timeout_s naming why; the cap comes off -> running."""
    sock, path = notify_socket
    monkeypatch.setenv("WATCHDOG_USEC", "200000")
    monkeypatch.setenv("WATCHDOG_PID", str(os.getpid()))
    blind = threading.Event()
    blind.set()
    svc, mavs = _service(tmp_path, run={"stall_timeout_s": 1.0}, blind=blind, notifier=SdNotifier(path))
    runner = _run(svc)
    notes: list[str] = []
    try:
        assert _wait(lambda: svc.ready, 3)
        assert _wait(lambda: (tmp_path / "status.json").exists(), 3)
        time.sleep(1.5)
        notes += _received(sock)
        assert any(n.startswith("READY=1") for n in notes) and notes.count("WATCHDOG=1") >= 3
        snap = svc.snapshot()
        assert snap["state"] == "waiting for vision" and snap["estimator"]["tracking"] is False
        assert "image too dark" in " ".join(snap["warnings"])
        assert _tracked(mavs) == 0
        blind.clear()
        assert _wait(lambda: svc.snapshot()["state"] == "running", 3)
    finally:
        _stop(svc, runner)
    # the warning, not the periodic health lines (INFO, which start with the state and come more often than once
    # in the test when the machine is loaded)
    stall = [r.getMessage() for r in caplog.records
             if r.levelno >= logging.WARNING and "waiting for vision" in r.getMessage()]
    assert len(stall) == 1 and "image too dark" in stall[0], stall


def test_camera_frames_stop_status_and_output_say_not_tracking(tmp_path: Path) -> None:
    """The estimator stand-in keeps saying 'tracking' from IMU-rate states; the daemon's own check of the
    camera frames overrides it within about a second: status tracking False, nothing tracked goes out."""

    class ImuOnly(ScriptedSource):
        def poll(self) -> list:
            return [m for m in super().poll() if not (cam_off.is_set() and hasattr(m, "left"))]

    class Propagating(ScriptedEstimator):
        def feed_imu(self, s):  # IMU-rate states claiming tracking, as a pure dead-reckoning estimator would
            return NavState(s.t_ns, np.eye(4), np.zeros(3)) if self.n else None

    cam_off = threading.Event()
    cfg = config_from_dict({"run": {"status_file": ""}})
    mavs: list[RecordingMavlink] = []
    svc = Service(cfg, source_factory=lambda: _started(ImuOnly([], threading.Event(), [])),
                  estimator_factory=lambda c: Propagating(c, []),
                  mavlink_factory=lambda: mavs.append(RecordingMavlink()) or mavs[-1], notifier=SdNotifier(""))
    runner = _run(svc)
    try:
        assert _wait(lambda: svc.snapshot()["estimator"]["tracking"] is True, 3)
        cam_off.set()
        t0 = time.monotonic()
        assert _wait(lambda: svc.snapshot()["estimator"]["tracking"] is False, 3)
        assert time.monotonic() - t0 < 1.6
        time.sleep(0.2)
        n = _tracked(mavs)
        time.sleep(0.5)
        assert _tracked(mavs) == n and svc.output.withheld > 0
        snap = svc.snapshot()
        assert snap["estimator"]["quality"] == 0 and snap["state"] == "waiting for vision"
        assert any(w.startswith("camera: no frames") for w in snap["warnings"])
    finally:
        _stop(svc, runner)


def test_wedged_estimator_loop_stops_the_watchdog(tmp_path: Path, monkeypatch, caplog) -> None:
    monkeypatch.setattr(service, "STUCK_S", 0.5)
    monkeypatch.setenv("WATCHDOG_USEC", "200000")
    monkeypatch.setenv("WATCHDOG_PID", str(os.getpid()))
    wedge = threading.Event()

    class Wedging(ScriptedEstimator):
        def feed_frame(self, f):
            while wedge.is_set():
                time.sleep(0.05)
            return super().feed_frame(f)

    svc, _ = _service(tmp_path, estimator=lambda c: Wedging("calib", []))
    runner = _run(svc)
    try:
        assert _wait(lambda: svc.ready and svc._last_watchdog > 0, 3)
        wedge.set()
        assert _wait(lambda: svc._last_watchdog < 0, 3)
        assert svc.snapshot()["state"] == "unhealthy"
    finally:
        wedge.clear()
        _stop(svc, runner)
    assert any("not feeding the systemd watchdog: estimator loop stuck" in r.getMessage() for r in caplog.records)


# ------------------------------------------------------------------------------------------ subprocesses

class Daemon:
    """`vio run` as a subprocess; its log read through a pipe (a file would be under the size limit too)."""

    def __init__(self, tmp_path: Path, config: str, notify_path: str, fsize_limit: int | None = None) -> None:
        self.tmp = tmp_path
        cfg = tmp_path / "config.toml"
        cfg.write_text(config)
        env = dict(os.environ, NOTIFY_SOCKET=notify_path, WATCHDOG_USEC="2000000", OMP_NUM_THREADS="1",
                   PYTHONUNBUFFERED="1", KESTREL_TEST_IMU_OFF=str(tmp_path / "imu_off"))
        env.pop("WATCHDOG_PID", None)

        def limits() -> None:  # in the child: writes past the limit fail with EFBIG (Python ignores SIGXFSZ)
            if fsize_limit is not None:
                resource.setrlimit(resource.RLIMIT_FSIZE, (fsize_limit, fsize_limit))
            signal.signal(signal.SIGXFSZ, signal.SIG_IGN)

        self.lines: list[str] = []
        self.proc = subprocess.Popen([sys.executable, "-c", LAUNCHER, "run", "--config", str(cfg)], cwd=REPO,
                                     env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                                     preexec_fn=limits)
        self._reader = threading.Thread(target=lambda: self.lines.extend(iter(self.proc.stdout.readline, "")),
                                        daemon=True)
        self._reader.start()

    @property
    def log(self) -> str:
        return "".join(self.lines)

    def status(self) -> dict:
        return json.loads((self.tmp / "status.json").read_text())

    def stop(self) -> tuple[int, float]:
        t0 = time.monotonic()
        self.proc.send_signal(signal.SIGTERM)
        try:
            rc = self.proc.wait(10)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            rc = self.proc.wait()
        took = time.monotonic() - t0
        self._reader.join(5)
        return rc, took

    def rss_mb(self) -> float:
        for line in Path(f"/proc/{self.proc.pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
        return float("nan")


def _status_ok(d: Daemon, cond) -> bool:
    try:
        return bool(cond(d.status()))
    except (OSError, ValueError, KeyError, TypeError):
        return False


def test_vio_run_full_disk_and_file_size_limit_then_imu_loss(tmp_path: Path, notify_socket) -> None:
    """RLIMIT_FSIZE (64 kB: EFBIG after ~2 s of IMU rows) under the recorder, /dev/full (ENOSPC) under the
    trajectory file: one warning each, status entries, the recording stays a readable dataset, ODOMETRY and
    the watchdog go on. Then the IMU stops: no poses, a warning, memory does not grow. SIGTERM: exit 0."""
    _need_pipeline()
    sock, notify_path = notify_socket
    (tmp_path / "traj.tum").symlink_to("/dev/full")
    ap = FakeAutopilot()
    ap.start()
    d = Daemon(tmp_path, f"""[source]
kind = "fake"
width = 320
height = 200
[mavlink]
url = "udpout:127.0.0.1:{ap.port}"
[run]
status_file = "{tmp_path / 'status.json'}"
trajectory_file = "{tmp_path / 'traj.tum'}"
record_dir = "{tmp_path / 'rec'}"
""", notify_path, fsize_limit=64 * 1024)
    notes: list[str] = []
    try:
        assert _wait(lambda: "recording stopped" in d.log, 40), d.log[-3000:]
        assert _wait(lambda: ap.poses() >= 20, 20), f"autopilot got {ap.counts}; log:\n{d.log[-3000:]}"
        assert _wait(lambda: _status_ok(d, lambda s: s["recording"]["state"] == "failed"
                                        and s["trajectory_file"]["state"] == "failed"), 5), d.log[-3000:]
        s = d.status()
        assert "File too large" in s["recording"]["error"] and "No space left" in s["trajectory_file"]["error"]
        n = ap.poses()
        notes += _received(sock)
        time.sleep(1.5)
        notes += _received(sock)
        assert ap.poses() > n + 20 and d.proc.poll() is None
        assert "WATCHDOG=1" in notes[-3:], notes[-5:]
        # the IMU stops while the camera runs
        (tmp_path / "imu_off").touch()
        assert _wait(lambda: _status_ok(d, lambda s: s["estimator"]["tracking"] is False), 5), d.log[-3000:]
        time.sleep(0.5)
        n, rss0 = ap.odometry_tracked(), d.rss_mb()
        time.sleep(3.0)
        assert ap.odometry_tracked() == n, "poses went out without IMU"
        growth = d.rss_mb() - rss0
        s = d.status()
        assert any(w.startswith("IMU: no samples") for w in s["warnings"]), s["warnings"]
        assert growth < 5, f"RSS grew {growth:.1f} MB in 3 s without IMU"  # holding frames: ~8 MB (60 pairs)
        notes += _received(sock)
        assert "WATCHDOG=1" in notes[-2:]
    finally:
        rc, took = d.stop()
        ap.stop.set()
    log = d.log
    assert rc == 0 and took < 2.0, log[-3000:]
    warned = [line for line in d.lines if "WARNING" in line]
    assert sum("recording stopped" in w for w in warned) == 1, warned
    assert sum("vio.app.daemon.outputs: trajectory file" in w for w in warned) == 1, warned
    assert "Traceback" not in log and "thread died" not in log
    (rec,) = (tmp_path / "rec").iterdir()
    ds = EurocDataset(rec)
    assert len(ds.imu) > 200 and len(ds) > 5 and len(list(ds.frames())) == len(ds)
    # what the log and the status say was kept is what is on disk (it counted the writer's lost buffer too)
    assert f"{len(ds)} frames and {len(ds.imu)} IMU samples before the error" in log, log[-3000:]
    print(f"\nIMU loss: RSS growth {growth:.1f} MB in 3 s; recording kept {len(ds)} frames, {len(ds.imu)} IMU")


def test_vio_run_camera_loss_euroc(tmp_path: Path, notify_socket, v101_path: Path) -> None:
    """V1_01 excerpt live: 4.7 s of images, then IMU only. After the images end nothing tracked goes to
    the autopilot, status says waiting for vision (exit 1), the daemon is neither dead nor restarted."""
    _need_pipeline()
    from vio.app.cli import main

    sock, notify_path = notify_socket
    ap = FakeAutopilot()
    ap.start()
    d = Daemon(tmp_path, f"""[source]
kind = "euroc"
dataset = "{v101_path}"
[mavlink]
url = "udpout:127.0.0.1:{ap.port}"
[run]
status_file = "{tmp_path / 'status.json'}"
""", notify_path)
    notes: list[str] = []
    try:
        assert _wait(lambda: notes.extend(_received(sock)) or any(n.startswith("READY=1") for n in notes), 60), \
            d.log[-3000:]
        assert _wait(lambda: ap.odometry_tracked() >= 10, 20), f"autopilot got {ap.counts}; log:\n{d.log[-3000:]}"
        assert _wait(lambda: _status_ok(d, lambda s: s["state"] == "waiting for vision" and any(
            w.startswith("camera: no frames") for w in s["warnings"])), 15), d.log[-3000:]
        s = d.status()
        assert s["estimator"]["tracking"] is False and s["estimator"]["quality"] == 0
        # the EuRoC source's stamps are the recording's (to 0.1 us on a 50 ms clock): none restamped
        fs = s["estimator"]["frame_stamps"]
        assert fs["mode"] == "auto" and fs["frames"] > 50 and fs["restamped"] == 0, fs
        time.sleep(0.5)
        n = ap.odometry_tracked()
        time.sleep(2.0)
        assert ap.odometry_tracked() == n, "tracked ODOMETRY after the camera stopped"
        assert main(["status", "--file", str(tmp_path / "status.json")]) == EXIT_UNHEALTHY
        notes += _received(sock)
        assert "WATCHDOG=1" in notes[-3:] and d.proc.poll() is None
    finally:
        rc, took = d.stop()
        ap.stop.set()
    assert rc == 0 and took < 2.0, d.log[-3000:]
    assert "Traceback" not in d.log and "not feeding the systemd watchdog" not in d.log



def _jittered_flight_daemon(tmp_path: Path, notify_socket, duration_s: float, seed: int, jitter_ms: float,
                            extra_run: str = "") -> tuple[Daemon, Path, Path]:
    """`vio run` (started) on a simulated aggressive 376x240 flight whose frames are stamped on arrival with
    `jitter_ms` of jitter, played as a EuRoC source, logging its poses: (daemon, flight, TUM file)."""
    _need_pipeline()
    from vio.app.cli import main

    flight = tmp_path / "jittered"
    assert main(["simulate", str(flight), "--profile", "aggressive", "--duration", str(duration_s), "--seed",
                 str(seed), "--size", "376x240", "--stamp-jitter-ms", str(jitter_ms), "--no-progress"]) == 0
    _, notify_path = notify_socket
    tum = tmp_path / "out.tum"
    d = Daemon(tmp_path, f"""[source]
kind = "euroc"
dataset = "{flight}"
[run]
status_file = "{tmp_path / 'status.json'}"
trajectory_file = "{tum}"
{extra_run}""", notify_path)
    return d, flight, tum


def _tum_poses(tum: Path) -> list[str]:
    return [ln for ln in tum.read_text().splitlines() if ln and not ln.startswith("#")]


def test_vio_run_on_frames_stamped_on_arrival_logs_and_records_every_frame(tmp_path: Path, notify_socket) -> None:
    """`vio run` on a camera whose stamps jitter (a EuRoC flight simulated with --stamp-jitter-ms, played live):
    the estimator restamps the frames, and the daemon still finds each frame's arrival and image by the stamp the
    source gave it: a TUM line per tracked frame (the first SITL flight with regular frames logged 25 of 3181)
    and the recording keeps the stamps as given (the same fault as the in-process test in test_service.py, here
    through `vio run` as users start it)."""
    rec = tmp_path / "rec"
    d, flight, tum = _jittered_flight_daemon(tmp_path, notify_socket, duration_s=6, seed=1, jitter_ms=4,
                                             extra_run=f'record_dir = "{rec}"\n')
    try:
        assert _wait(lambda: _status_ok(d, lambda s: s["source"]["finished"]), 40), d.log[-3000:]
        time.sleep(0.5)
        fs = d.status()["estimator"]["frame_stamps"]
    finally:
        rc, _ = d.stop()
    assert rc == 0, d.log[-3000:]
    assert fs["restamped"] > 60, fs
    assert len(_tum_poses(tum)) > 0.8 * fs["frames"], (len(_tum_poses(tum)), fs)
    given = EurocDataset(flight).cam0_t
    recorded = EurocDataset(next(rec.iterdir())).cam0_t
    assert len(recorded) > 0.9 * len(given)
    steps = np.diff(recorded)  # the source's stamps moved onto the host clock whole: the jitter is still there
    np.testing.assert_array_equal(steps, np.diff(given)[:len(steps)])


def test_vio_run_on_frames_jittering_too_much_to_restamp_says_so_and_keeps_flying(tmp_path: Path,
                                                                                  notify_socket) -> None:
    """`vio run` on a camera whose stamps jitter more than the frame clock can restamp (9 ms at 20 Hz, kept as
    given): the status says so (the frame stamps' sigma, a warning naming it, state degraded, not HEALTHY) while the
    poses keep coming, which the stamp link keeps near the truth (docs/estimator.md "Stamps that are not exact")."""
    d, _, tum = _jittered_flight_daemon(tmp_path, notify_socket, duration_s=8, seed=2, jitter_ms=9)
    warned = []
    try:
        def check(s: dict) -> bool:
            warned.extend(w for w in s["warnings"] if w.startswith("camera: frame stamps uncertain by"))
            return bool(s["source"]["finished"])
        assert _wait(lambda: _status_ok(d, check), 60), d.log[-3000:]
        fs = d.status()["estimator"]["frame_stamps"]
    finally:
        rc, _ = d.stop()
    assert rc == 0, d.log[-3000:]
    assert fs["restamped"] < 0.2 * fs["frames"] and fs["uncertain_frames"] > 0.8 * fs["frames"], fs
    assert fs["stamp_sigma_ms"] > 2.0 and fs["stamp_link"] is True, fs
    assert warned, "no status warning for frame stamps uncertain by several ms"
    assert len(_tum_poses(tum)) > 0.7 * fs["frames"], (len(_tum_poses(tum)), fs)
    assert "Traceback" not in d.log


def test_an_image_write_that_fails_with_a_few_kib_left_is_called_a_full_disk(tmp_path, monkeypatch):
    """44 KiB left, less than one PNG: the file system reports itself nearly, not exactly, full (a review found
    'cannot write image' with no diagnosis)."""
    import shutil
    from collections import namedtuple

    from vio.app.daemon import outputs

    usage = namedtuple("usage", "total used free")
    monkeypatch.setattr(shutil, "disk_usage", lambda p: usage(4 << 20, (4 << 20) - 45056, 45056))
    assert "disk full: 44 KiB left" in outputs._storage_diagnosis(tmp_path)
    monkeypatch.setattr(shutil, "disk_usage", lambda p: usage(1 << 40, 1 << 39, 1 << 39))
    assert outputs._storage_diagnosis(tmp_path) == ""


def test_a_recreated_estimator_is_a_new_segment_for_the_loop_stage_and_drops_the_held_correction() -> None:
    """When reset() fails the daemon makes a new estimator, whose reset_counter starts at 0 again: the loop stage
    was handed that 0 and chained the new frame to the old one as one flight (its keyframes saved into the map
    metres off, with the old placement's small sigma), and the output kept mapping the new frame with the old
    correction (a review's finding)."""
    from vio.app.daemon.buffers import LatestState
    from vio.app.daemon.workers import EstimatorWorker
    from vio.estimator import ProcessedFrame, SolvedKeyframe
    from vio.geometry import make_T
    from vio.loop.output import CorrectedOutput, CorrectionUncertainty

    class FakeEstimator:
        last_features = None

        def __init__(self) -> None:
            self.done: list = []

        def reset(self, reason: str, bridge: bool = True, keep_bias: bool | None = None) -> None:
            raise RuntimeError("smoother in a bad state")

        def take_processed(self) -> list:
            done, self.done = self.done, []
            return done

    class FakeLoop:
        def __init__(self) -> None:
            self.counters: list[int] = []

        def submit(self, t_ns, T, image, ff, reset_counter) -> bool:
            self.counters.append(reset_counter)
            return True

        def settle(self, settled) -> None:
            pass

        def correction(self):
            unc = CorrectionUncertainty(np.eye(4) * 1e-2, np.zeros(3))
            return make_T(np.eye(3), [5.0, 0, 0]), 3, unc, 1, False, 0

    made: list[FakeEstimator] = []

    def make() -> FakeEstimator:
        made.append(FakeEstimator())
        return made[-1]

    loop, output = FakeLoop(), CorrectedOutput("jump")
    w = EstimatorWorker(threading.Event(), make, None, LatestState(), 0.5, loop=loop, loop_output=output)
    w.estimator = make()

    def frame(t_ns: int) -> None:
        st = NavState(t_ns, np.eye(4), np.zeros(3), cov_pose=np.eye(6) * 1e-6)
        w._left.append((t_ns, np.zeros((4, 4), np.uint8)))
        w.estimator.done.append(ProcessedFrame(t_ns, None, None, st, SolvedKeyframe(t_ns, None, st)))
        w._emit(st)

    frame(10**9)
    assert w.last_state.T_world_body[0, 3] == pytest.approx(5.0)  # the map's correction applied
    w._reset("test")
    assert len(made) == 2
    frame(2 * 10**9)
    assert loop.counters[0] != loop.counters[1]  # a new odometry segment for the loop stage
    assert w.last_state.T_world_body[0, 3] == pytest.approx(0.0)  # no correction of the old frame
    assert w.last_state.cov_pose[3, 3] == pytest.approx(1e-6)
    assert w.last_state.reset_counter > 0


def test_a_recreated_estimators_step_comes_with_a_new_reset_counter_after_any_number_of_loop_jumps() -> None:
    """An estimator re-created after its reset() raised starts at its own origin: a step, allowed only with a new
    reset_counter. Its base was the last published counter + 1, which holds the loop output's jumps already, and the
    loop output added them again: the counter moved by jumps + 1, the same counter mod 256 after 255 jumps (a
    long flight's loop closures in [loop] output = jump), so the step went out as a measurement."""
    from vio.app.daemon.buffers import LatestState
    from vio.app.daemon.workers import EstimatorWorker
    from vio.geometry import make_T
    from vio.loop.output import CorrectedOutput

    class FakeEstimator:
        last_features = None

        def reset(self, reason: str, bridge: bool = True, keep_bias: bool | None = None) -> None:
            raise RuntimeError("smoother in a bad state")

        def take_processed(self) -> list:
            return []

    class FakeLoop:
        version = 0

        def submit(self, *a) -> bool:
            return True

        def settle(self, settled) -> None:
            pass

        def correction(self):  # every solve moves the correction 1 cm: a jump each
            return make_T(np.eye(3), [0.01 * (self.version % 2), 0, 0]), self.version, None, 0, False, 0

    loop, output = FakeLoop(), CorrectedOutput("jump")
    w = EstimatorWorker(threading.Event(), FakeEstimator, None, LatestState(), 0.5, loop=loop, loop_output=output)
    w.estimator = FakeEstimator()
    t = 10**9
    for _ in range(255):
        loop.version += 1
        t += 10**7
        w._emit(NavState(t, make_T(np.eye(3), [30.0, 0, 0]), np.zeros(3), cov_pose=np.eye(6) * 1e-6))
    before = w.last_state.reset_counter
    assert output.jumps == 255 and before == 255
    w._reset("test")
    w._emit(NavState(t + 10**7, np.eye(4), np.zeros(3), cov_pose=np.eye(6) * 1e-6))  # at the new origin: a step
    after = w.last_state.reset_counter
    assert after % 256 != before % 256, (before, after)
    assert after == before + 1
    assert w.last_state.loop_jumps == 255  # the status's count of the run's loop jumps goes on


def test_a_recreated_estimator_continues_from_the_last_tracked_odometry_pose() -> None:
    """A new estimator (the old one's reset() raised) started at its own origin: the autopilot got, at the new
    reset_counter, a position of all that was flown since the start (EKF3 resets to it there: the start in flight's
    problem, 30 m here). It continues from the old one's last tracked odometry pose (not the loop-corrected one: the
    output's correction is dropped at the re-creation), as an estimator reset does."""
    from vio.app.daemon.buffers import LatestState
    from vio.app.daemon.workers import EstimatorWorker
    from vio.geometry import make_T
    from vio.loop.output import CorrectedOutput

    class FakeEstimator:
        last_features = None

        def __init__(self) -> None:
            self.anchor = None

        def reset(self, reason: str, bridge: bool = True, keep_bias: bool | None = None) -> None:
            raise RuntimeError("smoother in a bad state")

        def take_processed(self) -> list:
            return []

        def continue_from(self, T) -> None:
            self.anchor = np.array(T)

    class FakeLoop:
        def submit(self, *a) -> bool:
            return True

        def settle(self, settled) -> None:
            pass

        def correction(self):
            return make_T(np.eye(3), [0.5, 0, 0]), 1, None, 0, False, 0

    made: list = []

    def make():
        made.append(FakeEstimator())
        return made[-1]

    w = EstimatorWorker(threading.Event(), make, None, LatestState(), 0.5, loop=FakeLoop(),
                        loop_output=CorrectedOutput("jump"))
    w.estimator = make()
    w._emit(NavState(10**9, make_T(np.eye(3), [30.0, 0, 0]), np.zeros(3), cov_pose=np.eye(6) * 1e-6))
    w._emit(NavState(2 * 10**9, make_T(np.eye(3), [31.0, 0, 0]), np.zeros(3), tracking=False))  # lost: not it
    w._reset("test")
    assert len(made) == 2 and made[1].anchor is not None
    np.testing.assert_allclose(made[1].anchor[:3, 3], [30.0, 0, 0])


def test_frames_never_processed_neither_pile_up_nor_shift_the_latency_of_later_ones() -> None:
    """Arrival times were a queue popped once per processed frame: a frame the estimator dropped (or a reset
    cleared) gave every later frame an older one's arrival (100 ms too much after a 1.6 s IMU outage, for good,
    in the latency VISO_DELAY_MS is set from); and with the live view on, every left image fed while the IMU was
    silent stayed in memory (300 MB a minute): a review's findings."""
    from vio.app.daemon.buffers import LatestState
    from vio.app.daemon.workers import PENDING_FRAMES, EstimatorWorker, _remember
    from vio.estimator import ProcessedFrame

    w = EstimatorWorker(threading.Event(), lambda: None, None, LatestState(), 0.5)
    for k in range(10):  # frames 0-9 fed at 50 ms, arriving 20 ms after their stamps
        _remember(w._arrivals, k * 50_000_000, k * 50_000_000 + 20_000_000)

    def done(*ks: int) -> list:
        return [ProcessedFrame(k * 50_000_000, None, None, None) for k in ks]

    assert w._frame_arrival(done(0, 1)) == 70_000_000
    assert w._frame_arrival(done(5)) == 270_000_000  # 2-4 dropped by the estimator: not 2's arrival
    assert sorted(w._arrivals) == [k * 50_000_000 for k in range(6, 10)]
    pending: dict = {}
    for k in range(1000):  # the IMU silent: frames fed, none processed
        _remember(pending, k, np.zeros((400, 640), np.uint8))
    assert len(pending) == PENDING_FRAMES and min(pending) == 1000 - PENDING_FRAMES


def test_a_recreated_estimator_keeps_the_runs_verdict_on_the_imu(tmp_path: Path) -> None:
    """The IMU measured against the camera (a deg/s gyro, an IMU mounted 90 deg off) stops the estimator for the run
    (`stopped_for_run`). When the daemon then had to re-create its estimator (reset() raised), the new one knew
    nothing of it: it started again on the same wrong IMU, and the status went back from "degraded". The verdict
    is carried over now: the new estimator stays stopped, saying the same."""
    from vio.app.daemon.buffers import LatestState
    from vio.app.daemon.workers import EstimatorWorker
    from vio.config import VioConfig
    from vio.estimator import Estimator
    from vio.sim.generate import SimConfig, simulate
    from vio.types import ImuSample

    simulate(tmp_path / "f", SimConfig(duration_s=3.0, width=320, height=200, variant="clean", still_start_s=1.0),
             progress=False)
    ds = EurocDataset(tmp_path / "f")
    made: list[Estimator] = []

    def make() -> Estimator:
        made.append(Estimator(ds.calibration, VioConfig().estimator))
        return made[-1]

    w = EstimatorWorker(threading.Event(), make, None, LatestState(), 0.5)
    w.estimator = make()
    why = "the gyro turns 56x what the camera sees (...): deg/s instead of rad/s (57.3x)?"
    w.estimator._imu_disagrees(why, "IMU units", "fix the IMU's units or scale")

    def broken(*a, **k) -> None:
        raise RuntimeError("smoother in a bad state")

    w.estimator.reset = broken
    w._reset("estimator failed: RuntimeError: smoother in a bad state")
    assert len(made) == 2 and w.estimator is made[1]
    h = w.estimator.health()
    assert h.stopped_for_run == why and h.sensor_error == why
    states = []
    for ev in ds.events():  # the flight a fresh estimator starts on (below): this one does not
        r = w.estimator.feed_imu(ev) if isinstance(ev, ImuSample) else w.estimator.feed_frame(ev)
        states += [r] if r is not None else []
    assert not w.estimator.health().initialized and not any(s.tracking for s in states)
    fresh = Estimator(ds.calibration, VioConfig().estimator)
    for ev in ds.events():
        fresh.feed_imu(ev) if isinstance(ev, ImuSample) else fresh.feed_frame(ev)
    assert fresh.health().initialized


def test_an_output_failure_reads_as_a_sentence_not_a_python_type():
    """`vio status` and the journal said "recording failed: VioError: ...png: cannot write image (disk full ...)" (a
    QA walk-through on a 3 MB tmpfs): a VioError's message is the sentence; an OSError its strerror and errno name;
    anything else (a bug) keeps its type."""
    import errno

    from vio import VioError
    from vio.app.daemon.outputs import _os_error_text

    assert _os_error_text(VioError("x.png: cannot write image (disk full: 56 KiB left)")) == \
        "x.png: cannot write image (disk full: 56 KiB left)"
    assert _os_error_text(OSError(errno.ENOSPC, "No space left on device")) == "No space left on device (ENOSPC)"
    assert _os_error_text(KeyError("k")) == "KeyError: 'k'"


def _map_info(path: Path) -> tuple[dict, str]:
    """`vio map info FILE --json` and its text: (header and figures, text)."""
    args = [sys.executable, "-m", "vio.app.cli", "map", "info", str(path)]
    js = subprocess.run([*args, "--json"], cwd=REPO, capture_output=True, text=True, timeout=60)
    text = subprocess.run(args, cwd=REPO, capture_output=True, text=True, timeout=60)
    assert js.returncode == 0 and text.returncode == 0, js.stderr[-2000:] + text.stderr[-2000:]
    return json.loads(js.stdout), text.stdout


def test_a_daemon_killed_mid_flight_keeps_its_map_and_its_restart_grows_it(tmp_path: Path) -> None:
    """`[map] save` with checkpoints: `vio run` killed with SIGKILL mid-flight (as systemd's watchdog, the OOM killer
    or a power cut would) leaves its map so far, marked as a checkpoint; restarted on the same boot it loads it,
    relocalises in it, and its clean stop saves one final map holding both runs' keyframes. Before checkpoints the
    killed run left nothing and the restart saved only its own keyframes."""
    _need_pipeline()
    map_path = tmp_path / "warehouse.map.npz"
    cfg = tmp_path / "config.toml"
    cfg.write_text(f"""[source]
kind = "fake"
realtime = false
fake_duration_s = 8.0
width = 320
height = 200
[run]
status_file = "{tmp_path / 'status.json'}"
[loop]
enabled = true
output_join_edges = 3
[map]
save = "{map_path}"
checkpoint_s = 1.0
""")
    log1 = tmp_path / "first.log"
    with open(log1, "w") as out:
        proc = subprocess.Popen([sys.executable, "-m", "vio.app.cli", "run", "--config", str(cfg)], cwd=REPO,
                                stdout=out, stderr=subprocess.STDOUT)
    try:
        assert _wait(lambda: map_path.exists() and "source finished" not in log1.read_text()
                     and log1.read_text().count("map checkpoint") >= 1 and time.sleep(2.0) is None, 40), \
            log1.read_text()[-3000:]
        loop = json.loads((tmp_path / "status.json").read_text())["loop"]  # what a kill now would keep, shown
        assert loop["map_checkpoints"] >= 1 and loop["map_checkpoint_error"] is None, loop
        assert 0 <= loop["map_checkpoint_age_s"] < 5, loop
    finally:
        proc.kill()  # no clean stop: no final save
        proc.wait(15)
    assert "map saved to" not in log1.read_text(), log1.read_text()[-3000:]
    first, text = _map_info(map_path)
    assert first["checkpoint"]["pid"] == proc.pid and first["checkpoint"]["loaded"] is None, first
    assert "checkpoint of a run that did not stop cleanly" in text, text
    n1 = first["keyframes"]
    assert n1 >= 2 and len(first.get("parts") or [1]) == 1, first

    rc, text2 = fly_fake(tmp_path, cfg.read_text(), 40)
    assert rc == 0 and "Traceback" not in text2, text2[-3000:]
    assert f"its {n1} keyframes are loaded and this run grows them" in text2, text2[-3000:]
    assert "relocalised in the map" in text2 and "map saved to" in text2, text2[-3000:]
    final, text = _map_info(map_path)
    assert "checkpoint" not in final and "did not stop cleanly" not in text, final
    parts = final["parts"]
    assert len(parts) == 2 and parts[0]["keyframes"] == n1 and parts[1]["keyframes"] > 0, parts
    assert final["keyframes"] == n1 + parts[1]["keyframes"], final
    assert "part 2:" in text and "joined by" in text, text


def test_a_checkpoint_from_another_boot_is_moved_aside_not_grown_nor_written_over(tmp_path: Path, caplog) -> None:
    """A checkpoint at `[map] save` left by a run on an earlier boot (a power cut) is another flight's: it is moved
    to NAME.checkpoint-TIME.npz and said, and this run starts without it; one of this boot is grown."""
    from types import SimpleNamespace

    from vio.loop.features import KeyframeFeatures
    from vio.loop.mapfile import boot_id, load_map, run_identity, save_map

    voc = SimpleNamespace(k=2, depth=1, centres=np.zeros((2, 32), np.uint8), idf=np.ones(2))
    cam = SimpleNamespace(fx=200.0, fy=200.0, cx=160.0, cy=100.0, width=320, height=200, T_body_cam=np.eye(4))
    feats = [KeyframeFeatures(np.zeros((3, 32), np.uint8), np.ones((3, 2), np.float32),
                              np.ones((3, 3), np.float32)) for _ in range(2)]
    path = tmp_path / "m.npz"
    cfg = config_from_dict({"map": {"save": str(path)}})

    def write(boot: str) -> None:
        save_map(path, [1, 2], np.stack([np.eye(4)] * 2), feats, voc, cam,
                 checkpoint={**run_identity(None), "boot_id": boot})

    write(boot_id())
    grown = service.map_to_grow(cfg, None)
    assert grown is not None and len(grown.t_ns) == 2 and path.exists()
    write("an-earlier-boot")
    # `vio config check` says what `vio run` would do with it, and does nothing
    from vio.app.cli import main

    toml = tmp_path / "c.toml"
    toml.write_text(f'[map]\nsave = "{path}"\n')
    with contextlib.redirect_stdout(io.StringIO()) as out:
        assert main(["-q", "config", "check", str(toml)]) == 0
    assert f"note: map: {path} is the checkpoint of a run on another boot" in out.getvalue(), out.getvalue()
    assert "vio run moves it to" in out.getvalue() and path.exists()
    with caplog.at_level(logging.WARNING):
        assert service.map_to_grow(cfg, None) is None
    aside = [p for p in tmp_path.iterdir() if p.name.startswith("m.checkpoint-")]
    assert not path.exists() and len(aside) == 1 and "moved to" in caplog.text, caplog.text
    assert load_map(aside[0]).header["checkpoint"]["boot_id"] == "an-earlier-boot"
    # a finished map of another run ([map] save left set after the mapping flight) was written over by this run's
    # first checkpoint (an integrator's walk-through): kept as m.previous.npz, one generation, said
    save_map(path, [1, 2], np.stack([np.eye(4)] * 2), feats, voc, cam)
    with contextlib.redirect_stdout(io.StringIO()) as out:
        assert main(["-q", "config", "check", str(toml)]) == 0
    assert f"note: map: {path} holds the finished map of" in out.getvalue() and path.exists(), out.getvalue()
    caplog.clear()
    with caplog.at_level(logging.WARNING):
        assert service.map_to_grow(cfg, None) is None
    previous = tmp_path / "m.previous.npz"
    assert not path.exists() and len(load_map(previous).t_ns) == 2, caplog.text
    assert f"moved to {previous}, kept" in caplog.text and "replacing" not in caplog.text, caplog.text
    save_map(path, [1, 2, 3], np.stack([np.eye(4)] * 3), feats + feats[:1], voc, cam)
    caplog.clear()
    with caplog.at_level(logging.WARNING):
        assert service.map_to_grow(cfg, None) is None
    assert len(load_map(previous).t_ns) == 3 and "(replacing the older one there)" in caplog.text, caplog.text
    save_map(path, [1, 2], np.stack([np.eye(4)] * 2), feats, voc, cam)
    # [map] save a hard link of [map] load: the map grown in place (as check_run_config sees it), not another
    # run's checkpoint to move aside (they were compared by real path)
    write("an-earlier-boot")
    os.link(path, tmp_path / "hard.npz")
    linked = config_from_dict({"map": {"load": str(path), "save": str(tmp_path / "hard.npz")}})
    plan = service.checkpoint_plan(linked, load_map(path))
    assert plan.action == "grow" and plan.map is not None, plan


def test_a_map_write_cut_short_leaves_its_temporary_only_until_the_next_start(tmp_path: Path, caplog) -> None:
    """A checkpoint being written when the stop's budget ran out (or SIGKILL, a power cut) left its temporary file,
    as large as the map, beside `[map] save`: one more at every such restart. The next start removes those whose
    writer no longer runs (one log line), beside the real file when `[map] save` is a link; not a running
    process's (a replay saving the same map now), nor one written in the last STALE_AFTER_S (a writer in another
    container, whose pid this process cannot see), nor any other name."""
    from vio.io.atomic import STALE_AFTER_S, temporary_path

    (tmp_path / "state").mkdir()
    real = tmp_path / "state" / "m.npz"
    (tmp_path / "m.npz").symlink_to(real)  # [map] save through a link: the map (and its temporary) is beside real
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    stale = temporary_path(real, dead.pid)
    stale.write_bytes(bytes(4096))  # half a map
    running = temporary_path(real)  # this process's: a write in progress
    running.write_bytes(b"x")
    others = [real.with_name(".m.npz.tmp"), real.with_name(f".other.npz.{dead.pid}.tmp"),
              real.with_name(f"m.npz.{dead.pid}.tmp"), tmp_path / f".m.npz.{dead.pid}.tmp"]
    old = time.time() - STALE_AFTER_S - 5  # all of these last written before the guard's span
    for p in others:
        p.write_bytes(b"y")
    for p in [stale, running, *others]:
        os.utime(p, (old, old))
    others.append(running)
    gone = subprocess.Popen([sys.executable, "-c", "pass"])
    gone.wait()
    unseen = temporary_path(real, gone.pid)
    unseen.write_bytes(b"z")  # no process here has this pid, but it is being written now (another container)
    others.append(unseen)
    cfg = config_from_dict({"map": {"save": str(tmp_path / "m.npz")}})
    with caplog.at_level(logging.INFO, logger="vio.app.daemon.service"):
        assert service.map_to_grow(cfg, None) is None
    assert not stale.exists() and running.exists() and all(p.exists() for p in others)
    said = [r.getMessage() for r in caplog.records if "temporary file" in r.getMessage()]
    assert len(said) == 1 and "removed 1 temporary file(s) of [map] save" in said[0] and str(stale) in said[0], said
    caplog.clear()
    service.map_to_grow(cfg, None)  # nothing left to remove: nothing said
    assert not [r for r in caplog.records if "temporary file" in r.getMessage()]


def _stub_service(monkeypatch) -> list:
    """service.Service replaced by one that only records the config `vio run` started it with (returned list) and
    returns at once, and no signal handler installed: what `service.run` decides at start, without a daemon."""
    started = []

    class Started:
        watchdog_s = 0.0

        def __init__(self, cfg, map_data=None, vocabulary=None) -> None:
            started.append(cfg)

        def request_stop(self) -> None:
            pass

        def run(self) -> int:
            return 0

    monkeypatch.setattr(service, "Service", Started)
    monkeypatch.setattr(signal, "signal", lambda *_a: None)
    return started


@pytest.mark.parametrize("kind", ["text", "newer_map"])
def test_vio_run_never_writes_its_map_over_a_file_at_map_save_that_is_not_a_map_it_reads(tmp_path: Path, monkeypatch,
                                                                                       caplog, kind) -> None:
    """`[map] save` naming a file that is not a map (a typo for the calibration, a user's notes) or a map of a newer
    format: `vio config check` said OK and `vio run`'s first checkpoint (30 s in) renamed its map over it, unsaid (a
    review's finding: "map checkpoint written to precious.txt"). `vio config check` now refuses it, and `vio run`
    flies without saving the map (exit 3 is never restarted), the file kept as it was."""
    from argparse import Namespace
    from types import SimpleNamespace

    from vio.app.cli import main
    from vio.loop.features import KeyframeFeatures
    from vio.loop.mapfile import save_map

    path = tmp_path / "precious.npz"
    if kind == "text":
        path.write_text("calibration notes, not a map\n")
        says = "not a Kestrel VIO map"
    else:
        voc = SimpleNamespace(k=2, depth=1, centres=np.zeros((2, 32), np.uint8), idf=np.ones(2))
        cam = SimpleNamespace(fx=200.0, fy=200.0, cx=160.0, cy=100.0, width=320, height=200, T_body_cam=np.eye(4))
        feats = [KeyframeFeatures(np.zeros((3, 32), np.uint8), np.ones((3, 2), np.float32),
                                  np.ones((3, 3), np.float32)) for _ in range(2)]
        save_map(path, [1, 2], np.stack([np.eye(4)] * 2), feats, voc, cam)
        z = dict(np.load(path))
        header = json.loads(str(z["header"]))
        np.savez(path, **{**z, "header": np.array(json.dumps({**header, "version": 2}))})
        says = "newer than this program's"
    before = path.read_bytes()
    toml = tmp_path / "c.toml"
    toml.write_text(f'[map]\nsave = "{path}"\n')
    with contextlib.redirect_stderr(io.StringIO()) as err:
        assert main(["-q", "config", "check", str(toml)]) == 3
    assert "[map] save:" in err.getvalue() and says in err.getvalue() and "would write over it" in err.getvalue(), \
        err.getvalue()
    started = _stub_service(monkeypatch)
    with caplog.at_level(logging.ERROR):
        assert service.run(Namespace(config=str(toml))) == 0
    assert len(started) == 1 and started[0].map.save == "", started
    assert says in caplog.text and "will not be saved" in caplog.text, caplog.text
    assert path.read_bytes() == before


def test_a_checkpoint_that_cannot_be_moved_aside_does_not_keep_vio_run_from_flying(tmp_path: Path, monkeypatch,
                                                                                    caplog) -> None:
    """A power cut leaves a checkpoint (another boot's) and the state folder remounted read-only: the move aside
    failed and `vio run` exited 3, which systemd never restarts: no VIO at all. It flies without saving the map
    (a save would write over the checkpoint), as with a map folder not writable, and the checkpoint is kept."""
    import errno
    from argparse import Namespace
    from types import SimpleNamespace

    from vio.loop.features import KeyframeFeatures
    from vio.loop.mapfile import run_identity, save_map

    voc = SimpleNamespace(k=2, depth=1, centres=np.zeros((2, 32), np.uint8), idf=np.ones(2))
    cam = SimpleNamespace(fx=200.0, fy=200.0, cx=160.0, cy=100.0, width=320, height=200, T_body_cam=np.eye(4))
    feats = [KeyframeFeatures(np.zeros((3, 32), np.uint8), np.ones((3, 2), np.float32),
                              np.ones((3, 3), np.float32)) for _ in range(2)]
    path = tmp_path / "m.npz"
    save_map(path, [1, 2], np.stack([np.eye(4)] * 2), feats, voc, cam,
             checkpoint={**run_identity(None), "boot_id": "an-earlier-boot"})
    toml = tmp_path / "c.toml"
    toml.write_text(f'[map]\nsave = "{path}"\n')
    def read_only(*_a) -> None:
        raise OSError(errno.EROFS, "Read-only file system")

    started = _stub_service(monkeypatch)
    monkeypatch.setattr(os, "rename", read_only)
    with caplog.at_level(logging.ERROR):
        assert service.run(Namespace(config=str(toml))) == 0
    assert len(started) == 1 and started[0].map.save == "", started
    assert path.exists() and "cannot be moved aside" in caplog.text and "will not be saved" in caplog.text
