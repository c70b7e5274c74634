"""The onboard daemon: buffers, sd_notify, status file, fault recovery, and `vio run` end to end.

The in-process tests use tiny stand-ins for the source, estimator and MAVLink output so they exercise the
daemon's own logic in a couple of seconds; the subprocess tests run the real `vio run` with the fake
source, the real estimator and a fake autopilot on loopback UDP.
"""

from __future__ import annotations

import dataclasses
import importlib.util
import json
import logging
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import pytest

from vio.app.daemon.buffers import LatestState, SensorBuffer
from vio.app.daemon.service import Service
from vio.app.daemon.status import write_status_file
from vio.app.sdnotify import SdNotifier, watchdog_interval_s
from vio.app.status import EXIT_HEALTHY, EXIT_NOT_RUNNING, EXIT_UNHEALTHY, evaluate, format_status
from vio.config import config_from_dict
from vio.estimator import FrameTimings, ProcessedFrame
from vio.types import FeatureFrame, ImuSample, NavState, StereoFrame

REPO = Path(__file__).resolve().parents[1]


def imu(t_ns: int) -> ImuSample:
    return ImuSample(t_ns, np.zeros(3), np.array([0.0, 0.0, 9.81]))


def frame(t_ns: int, seq: int = 0) -> StereoFrame:
    img = np.zeros((8, 8), np.uint8)
    return StereoFrame(t_ns, img, img, seq=seq)


# ------------------------------------------------------------------------------------------- buffers

def test_buffer_drops_oldest_frame_and_counts() -> None:
    buf = SensorBuffer(max_frames=2, max_imu=100)
    for k in range(5):
        buf.put_frame(frame(k * 50_000_000, k), arrival_ns=k)
    assert buf.frames_in == 5 and buf.frames_dropped == 3
    seqs = []
    while True:
        _, item = buf.take(0.0)
        if item is None:
            break
        seqs.append(item[1].seq)
    assert seqs == [3, 4]  # the newest survive


def test_buffer_hands_out_imu_up_to_the_next_frame_in_order() -> None:
    buf = SensorBuffer(max_frames=4, max_imu=100)
    for t in (0, 5, 10):
        buf.put_imu(imu(t))
    buf.put_frame(frame(10), 0)
    buf.put_imu(imu(15))
    samples, item = buf.take(0.0)
    assert [s.t_ns for s in samples] == [0, 5, 10] and item[1].t_ns == 10
    samples, item = buf.take(0.0)
    assert [s.t_ns for s in samples] == [15] and item is None


def test_buffer_imu_overflow_is_counted_not_silent() -> None:
    buf = SensorBuffer(max_frames=4, max_imu=3)
    results = [buf.put_imu(imu(t)) for t in range(5)]
    assert results == [True, True, True, False, False]
    assert buf.imu_overflow == 2 and buf.imu_in == 5


def test_latest_state_gives_newest_state_and_every_frame_state() -> None:
    from vio.app.daemon.buffers import Output

    box = LatestState()
    for k in range(3):
        box.publish(Output(NavState(k, np.eye(4), np.zeros(3)), k, k))
    box.publish(Output(NavState(3, np.eye(4), np.zeros(3)), -1, 3))  # an IMU-rate state: no frame
    seq, out, frames = box.wait_newer(0, 0.0)
    assert out.state.t_ns == 3
    assert [f.state.t_ns for f in frames] == [0, 1, 2]  # every frame state reaches the TUM log
    assert box.wait_newer(seq, 0.0)[1:] == (None, [])


# ------------------------------------------------------------------------------------------ sd_notify

@pytest.fixture()
def notify_socket(tmp_path: Path):
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    path = tmp_path / "notify.sock"
    sock.bind(str(path))
    sock.settimeout(0.1)
    yield sock, str(path)
    sock.close()


def _received(sock: socket.socket) -> list[str]:
    out = []
    while True:
        try:
            out.append(sock.recv(4096).decode())
        except (TimeoutError, BlockingIOError):
            return out


def test_sdnotify_sends_datagrams_and_is_a_noop_without_socket(notify_socket) -> None:
    sock, path = notify_socket
    n = SdNotifier(path)
    assert n.ready("tracking") and n.watchdog()
    assert _received(sock) == ["READY=1\nSTATUS=tracking", "WATCHDOG=1"]
    assert not SdNotifier("").ready()
    assert not SdNotifier(str(Path(path).with_name("absent.sock"))).watchdog()  # logs once, never raises


def test_watchdog_interval_is_half_the_period_and_respects_pid(monkeypatch) -> None:
    monkeypatch.setenv("WATCHDOG_USEC", "4000000")
    monkeypatch.setenv("WATCHDOG_PID", str(os.getpid()))
    assert watchdog_interval_s() == 2.0
    monkeypatch.setenv("WATCHDOG_PID", str(os.getpid() + 1))
    assert watchdog_interval_s() is None
    monkeypatch.delenv("WATCHDOG_USEC")
    assert watchdog_interval_s() is None


# ---------------------------------------------------------------------------------------- status

def _status(**kw) -> dict:
    s = {"version": 1, "state": "running", "healthy": True, "written_unix": 1000.0, "uptime_s": 3725.0,
         "rates_hz": {"camera": 20.0, "imu": 200.0, "estimator": 20.0, "output": 30.0},
         "estimator": {"tracking": True, "quality": 87, "tracks": 140, "reset_counter": 1, "daemon_resets": 0,
                       "last_pose_age_s": 0.05, "position_m": [1.0, 2.0, 0.5]},
         "source": {"kind": "oak", "connected": True}, "mavlink": {"state": "up", "sent": 10},
         "latency_ms": {"p50": 41.0, "max": 80.0}, "warnings": []}
    s.update(kw)
    return s


def test_status_verdicts() -> None:
    assert evaluate(_status(), 1001.0, 3.0)[0] == EXIT_HEALTHY
    assert evaluate(_status(healthy=False, state="degraded"), 1001.0, 3.0) == (EXIT_UNHEALTHY, "DEGRADED")
    assert evaluate(_status(healthy=False, state="unhealthy"), 1001.0, 3.0) == (EXIT_UNHEALTHY, "UNHEALTHY")
    assert evaluate(_status(), 1010.0, 3.0)[0] == EXIT_NOT_RUNNING  # stale file: daemon dead or hung
    assert evaluate(_status(state="stopped"), 1000.5, 3.0)[0] == EXIT_NOT_RUNNING
    # written an hour "in the future" (the wall clock stepped back): cannot tell, not HEALTHY (a review's finding)
    code, verdict = evaluate(_status(written_unix=4600.0), 1000.0, 3.0)
    assert code == EXIT_NOT_RUNNING and "clock stepped back" in verdict
    # killed (SIGKILL): its last status is fresh for up to stale_s, but its pid is gone
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    code, verdict = evaluate(_status(pid=int(dead.stdout)), 1001.0, 3.0)
    assert code == EXIT_NOT_RUNNING and verdict.startswith("NOT RUNNING (pid"), verdict
    assert evaluate(_status(pid=os.getpid()), 1001.0, 3.0)[0] == EXIT_HEALTHY
    # a pid beyond any process's (a damaged file): 'internal error: OverflowError' before (a review's finding)
    code, verdict = evaluate(_status(pid=10**23), 1001.0, 3.0)
    assert code == EXIT_NOT_RUNNING and verdict.startswith("NOT RUNNING (pid"), verdict


def test_status_json_of_a_daemon_that_is_gone_says_so(tmp_path, capsys) -> None:
    """`vio status --json` after a kill -9 printed the last file as written: "degraded", tracking true, while the
    text said NOT RUNNING (a review's finding)."""
    from vio.app.cli import main

    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    path = tmp_path / "status.json"
    path.write_text(json.dumps(_status(pid=int(dead.stdout), written_unix=time.time(), state="degraded")))
    assert main(["status", "--file", str(path), "--json"]) == EXIT_NOT_RUNNING
    out = json.loads(capsys.readouterr().out)
    assert out["state"] == "not running" and out["estimator"]["tracking"] is False and not out["healthy"]
    assert out["last_written_state"] == "degraded" and out["verdict"].startswith("NOT RUNNING (pid")
    # the text said "tracking True, last pose 0.00 s ago" for the same dead daemon (a QA sweep)
    assert main(["status", "--file", str(path)]) == EXIT_NOT_RUNNING
    text = capsys.readouterr().out
    assert "tracking False" in text and "not running: the figures above are the last ones it wrote" in text
    # a NaN written_unix read HEALTHY (every comparison with it false), a null section ended in an internal error
    for bad in ({"written_unix": float("nan")}, {"written_unix": "1796566198"}):
        path.write_text(json.dumps(_status(pid=os.getpid(), **bad)))
        assert main(["status", "--file", str(path)]) == EXIT_NOT_RUNNING
        assert "UNKNOWN (its written_unix" in capsys.readouterr().out
    path.write_text(json.dumps({**_status(pid=os.getpid(), written_unix=time.time()), "rates_hz": None,
                                "estimator": None, "mavlink": [1]}))
    assert main(["status", "--file", str(path)]) == EXIT_HEALTHY
    assert "camera -" in capsys.readouterr().out


def test_status_json_without_a_status_file_prints_the_state_on_stdout(tmp_path, capsys) -> None:
    """`vio status --json` with no status file printed nothing on stdout (its line went to stderr), so a health
    check piping it to jq got nothing to read (an integrator's walk-through)."""
    from vio.app.cli import main

    assert main(["status", "--file", str(tmp_path / "status.json"), "--json"]) == EXIT_NOT_RUNNING
    cap = capsys.readouterr()
    out = json.loads(cap.out)
    assert out["state"] == "not running" and out["healthy"] is False, out
    assert out["verdict"].startswith("NOT RUNNING (") and "NOT RUNNING (" in cap.err
    assert main(["status", "--file", str(tmp_path / "status.json")]) == EXIT_NOT_RUNNING
    assert capsys.readouterr().out == ""  # the text form as before: its line on stderr only
    # a --config that cannot be read exited 1, which a script reads as "degraded": 3, as for vio run
    assert main(["status", "--config", str(tmp_path / "missing.toml"), "--json"]) == 3
    out = json.loads(capsys.readouterr().out)
    assert out["state"] == "unknown" and "missing.toml" in out["verdict"], out
    (tmp_path / "bad.json").write_text("{not json")
    assert main(["status", "--file", str(tmp_path / "bad.json"), "--json"]) == EXIT_NOT_RUNNING
    out = json.loads(capsys.readouterr().out)
    assert out["state"] == "unknown" and out["verdict"].startswith("UNKNOWN ("), out


def test_the_status_files_mavlink_section_keeps_fields_not_known_yet_as_null() -> None:
    """`origin_ours` is None until the autopilot answers (docs/autopilot.md), but the status file left every None
    out, so `vio status --json` had no such key at all (an integrator's walk-through); values no JSON reader takes
    (NaN, lists) stay out."""
    from types import SimpleNamespace

    from vio.app.daemon.status import _mavlink_health

    out = SimpleNamespace(link_up=True, health=lambda: {"origin_ours": None, "first_tilt_deg": None, "sent": 3,
                                                         "last_latency_ms": float("nan"), "ids": [1]})
    h = _mavlink_health(out)
    assert h == {"origin_ours": None, "first_tilt_deg": None, "sent": 3, "state": "up"}, h
    assert "mavlink   link up, sent 3" in format_status(_status(mavlink=h), "HEALTHY", 1000.5)


def test_status_text_names_what_a_person_needs() -> None:
    text = format_status(_status(warnings=["autopilot link down"]), "HEALTHY", 1000.5)
    for needle in ("HEALTHY", "up 1h02m05s", "camera 20.0 Hz", "IMU 200 Hz", "tracks 140", "resets 1",
                   "link up", "p50 41.0 ms", "WARNING   autopilot link down"):
        assert needle in text, needle


def test_status_text_says_when_no_pose_goes_to_an_autopilot() -> None:
    s = _status()
    s["mavlink"] = {"state": "off"}
    assert "mavlink   OFF: [mavlink] url is empty" in format_status(s, "HEALTHY", 1000.5)


def test_status_text_shows_the_loop_stage_when_it_runs() -> None:
    s = _status()
    assert "  loop " not in format_status(s, "HEALTHY", 1000.5)
    s["loop"] = {"keyframes": 80, "closures": 6, "loop_edges": 12, "switched_off": 1, "relocalised": True,
                 "map_keyframes": 92, "dropped": 0, "error": None, "placement_sigma_m": 0.0172, "output": "blend",
                 "loop_jumps": 0, "blend_remaining_m": 0.42, "blend_remaining_deg": 12.0}
    text = format_status(s, "HEALTHY", 1000.5)
    for needle in ("output blend", "edges 12 (1 switched off), in the map +-1.7 cm",
                   "blend still to go 0.42 m 12.0 deg", "map of 92 keyframes"):
        assert needle in text, text
    assert "checkpoint" not in text  # no [map] save: nothing said of checkpoints
    s["loop"].update(map_checkpoints=0, map_checkpoint_error=None, map_checkpoint_age_s=None)
    assert ", no map checkpoint yet" in format_status(s, "HEALTHY", 1000.5)
    s["loop"].update(map_checkpoints=4, map_checkpoint_age_s=12.3)
    assert ", map checkpoint 12.3 s old (4 written)" in format_status(s, "HEALTHY", 1000.5)
    s["loop"].update(map_checkpoint_error="disk full")
    assert ", map checkpoint FAILING: disk full" in format_status(s, "HEALTHY", 1000.5)


def test_status_text_shows_the_land_after_loss_failsafe_only_when_configured() -> None:
    s = _status()
    assert "failsafe" not in format_status(s, "HEALTHY", 1000.5)
    s["mavlink"] = {**s["mavlink"], "land_after_loss_s": 3.0, "land_requests": 1, "land_accepted": True}
    assert "LAND after 3.0 s of lost vision: requests 1, accepted True" in format_status(s, "HEALTHY", 1000.5)


def test_status_cli_exit_codes(tmp_path: Path) -> None:
    from vio.app.cli import main

    path = tmp_path / "status.json"
    assert main(["status", "--file", str(path)]) == EXIT_NOT_RUNNING
    write_status_file(path, _status(written_unix=time.time()))
    assert main(["status", "--file", str(path)]) == EXIT_HEALTHY
    write_status_file(path, _status(written_unix=time.time(), healthy=False))
    assert main(["status", "--file", str(path)]) == EXIT_UNHEALTHY
    path.write_text("{not json")
    assert main(["status", "--file", str(path)]) == EXIT_NOT_RUNNING


def test_status_says_why_the_status_file_is_missing(tmp_path: Path, capsys, monkeypatch) -> None:
    """A daemon running with a state folder it cannot write never writes its status, and `vio status` said "does
    not exist; is the service started?" of a running service. Three cases, each its own line (exit 4): the folder
    is missing; it is not writable (the daemon cannot write its status there: its log says why); it is fine and
    no file yet (service not started)."""
    from vio.app.cli import main

    def verdict(path: Path) -> str:
        assert main(["status", "--file", str(path)]) == EXIT_NOT_RUNNING
        out = capsys.readouterr()
        assert out.out == "" and len(out.err.strip().splitlines()) == 1, out
        return out.err.strip()

    gone = tmp_path / "gone" / "status.json"
    assert verdict(gone) == (f"kestrel-vio: NOT RUNNING ({gone.parent} does not exist, so no status file "
                             "status.json; is the service started? try: systemctl status kestrel-vio)")
    fine = tmp_path / "status.json"
    assert verdict(fine) == (f"kestrel-vio: NOT RUNNING ({fine} does not exist; is the service started? try: "
                             "systemctl status kestrel-vio)")
    locked = tmp_path / "ro"
    locked.mkdir()
    locked.chmod(0o555)
    if os.geteuid() == 0:  # root writes anywhere: os.access answers as a service user would
        real = os.access
        monkeypatch.setattr(os, "access", lambda p, mode, **kw: not (Path(p) == locked and mode & os.W_OK)
                            and real(p, mode, **kw))
    text = verdict(locked / "status.json")
    assert text.startswith(f"kestrel-vio: UNKNOWN ({locked / 'status.json'} does not exist and {locked} is not "
                           "writable by user "), text
    assert text.endswith("a daemon running as that user cannot write its status there; check its log: journalctl "
                         "-u kestrel-vio)"), text


# ---------------------------------------------------------------- in-process service with stand-ins

class ScriptedSource:
    """Live-like source: IMU at 200 Hz and frames at 20 Hz in real time on the monotonic clock. While
    `silent` is set it delivers nothing (a pulled cable); `fail_on_start` makes start() raise."""

    def __init__(self, log: list, silent: threading.Event, fail_on_start: list) -> None:
        self.log, self.silent, self.fail = log, silent, fail_on_start
        self.t_next = time.monotonic_ns()
        self.k = 0

    def start(self) -> None:
        self.log.append("start")
        if self.fail:
            self.fail.pop()
            raise OSError("no OAK device found")
        self.t_next = time.monotonic_ns()

    def stop(self) -> None:
        self.log.append("stop")

    finished = False

    def calibration(self) -> str:
        return "calib"

    def health(self) -> dict:
        return {"name": "scripted", "k": self.k}

    clock_error_s = 0.0  # what stamp_uncertainty_s() says: a test raises it to act out a sick IMU clock sync

    def stamp_uncertainty_s(self) -> float:
        return self.clock_error_s

    def poll(self) -> list:
        if self.silent.is_set():
            self.t_next = time.monotonic_ns()
            return []
        out = []
        now = time.monotonic_ns()
        while self.t_next <= now:
            out.append(imu(self.t_next))
            if self.k % 10 == 0:
                out.append(frame(self.t_next, self.k))
            self.k += 1
            self.t_next += 5_000_000
        return out


@dataclass
class Health:
    """Same fields as vio.estimator.EstimatorHealth (the daemon reads nothing else)."""

    initialized: bool = False
    tracking: bool = False
    reset_counter: int = 0
    frames_processed: int = 0
    frames_unusable: int = 0
    unusable_reasons: dict = field(default_factory=dict)
    imu_rejected: int = 0
    imu_rejected_reasons: dict = field(default_factory=dict)
    frames_dropped: int = 0
    vision_age_s: float | None = None
    last_reset_reason: str = ""
    sensor_error: str | None = None
    calibration_warning: str | None = None
    stereo_warning: str | None = None
    frame_stamps: dict | None = None
    stopped_for_run: str | None = None


class ScriptedEstimator:
    """Shaped like vio.estimator.Estimator (feed_imu, feed_frame, reset, health, last_features): one tracked
    NavState per frame; raises once when told to, as a gtsam failure would. While `blind` is set its frames
    are unusable (a lens cap): no state, tracking False, the reason counted."""

    def __init__(self, calib: str, explode: list, blind: threading.Event | None = None) -> None:
        assert calib == "calib"
        self.explode = explode
        self.blind = blind or threading.Event()
        self.n = 0
        self.resets = 0
        self.unusable = 0
        self.tracking = False
        self.last_features: FeatureFrame | None = None
        self.last_frame_stamp_ns: int | None = None
        self._done: list[ProcessedFrame] = []
        self.calibration_warning: str | None = None  # what the stereo check says once it let go
        self.frame_stamps: dict | None = None  # what the frame clock says (vio.frame_clock.FrameClockStats.as_dict)

    def feed_imu(self, s: ImuSample) -> None:
        return None

    def take_processed(self) -> list[ProcessedFrame]:
        done, self._done = self._done, []
        return done

    def feed_frame(self, f: StereoFrame) -> NavState | None:
        if self.explode:
            self.explode.pop()
            raise RuntimeError("Indeterminant linear system")
        self.n += 1
        self.last_frame_stamp_ns = f.t_ns
        if self.blind.is_set():
            self.unusable += 1
            self.tracking = False
            self._done.append(ProcessedFrame(f.t_ns, FeatureFrame.empty(f.t_ns, "image too dark"), FrameTimings(),
                                             None))
            return None
        self.tracking = True
        self.last_features = FeatureFrame(f.t_ns, np.arange(99), np.zeros((99, 2)), np.zeros((99, 2)),
                                          np.ones(99), np.ones(99, np.int64))
        T = np.eye(4)
        T[0, 3] = 0.01 * self.n
        st = NavState(f.t_ns, T, np.zeros(3), reset_counter=self.resets)
        self._done.append(ProcessedFrame(f.t_ns, self.last_features, FrameTimings(), st))
        return st

    def reset(self, reason: str, bridge: bool = True, keep_bias: bool | None = None) -> None:
        self.resets += 1

    def health(self) -> Health:
        return Health(initialized=self.n > 0, tracking=self.tracking, reset_counter=self.resets,
                      frames_processed=self.n, frames_unusable=self.unusable,
                      unusable_reasons={"image too dark": self.unusable} if self.unusable else {},
                      calibration_warning=self.calibration_warning, frame_stamps=self.frame_stamps)


@dataclass
class MavStats:
    states_sent: int = 0
    autopilot_heartbeats: int = 3
    states_withheld: int = 0
    withheld_for: str = ""


class RecordingMavlink:
    """Shaped like drivers.mavlink_out.MavlinkOutput: send_state, poll, close, link_up, stats."""

    link_up = True

    def __init__(self) -> None:
        self.states: list[NavState] = []
        self.closed = False
        self.stats = MavStats()

    @property
    def states_sent(self) -> int:
        return self.stats.states_sent

    withholding = False  # as MavlinkOutput's "withholding_old_poses"

    def health(self) -> dict:
        return {**asdict(self.stats), "withholding_old_poses": self.withholding}

    def counters(self) -> dict[str, int]:
        return {k: v for k, v in asdict(self.stats).items() if type(v) is int}

    def send_state(self, s: NavState) -> None:
        self.states.append(s)
        self.stats.states_sent += 1
        self.stats.states_withheld += self.withheld_for is not None  # as MavlinkOutput counts them

    withheld_for: str | None = None  # as MavlinkOutput.withhold() was last told

    def withhold(self, why: str | None) -> None:
        self.withheld_for = why
        if why is not None:
            self.stats.withheld_for = why

    def poll(self) -> None:
        return None

    def close(self, final: bool = True) -> None:
        self.closed = True


def _read_status(path: Path) -> dict:
    """The daemon's status file, {} while it is not there or half written."""
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):
        return {}


def _status_warns(status: Path, match) -> bool:
    """Whether the daemon's status file holds a warning `match(w)` accepts; a file being replaced (or not yet
    written) reads as not yet."""
    try:
        return any(match(w) for w in json.loads(status.read_text())["warnings"])
    except (OSError, ValueError, KeyError):
        return False


def _wait(cond, timeout_s: float) -> bool:
    t0 = time.monotonic()
    while time.monotonic() - t0 < timeout_s:
        if cond():
            return True
        time.sleep(0.02)
    return False


def fly_fake(tmp_path: Path, config_toml: str, wait_s: float, settle_s: float = 0.0) -> tuple[int, str]:
    """`vio run --config` (written from `config_toml`) as a subprocess until its fake source has finished (or
    `wait_s` passed), `settle_s` more, then SIGTERM: (exit status, log text)."""
    cfg = tmp_path / "config.toml"
    cfg.write_text(config_toml)
    log_path = tmp_path / "daemon.log"
    with open(log_path, "w") as log:
        proc = subprocess.Popen([sys.executable, "-m", "vio.app.cli", "run", "--config", str(cfg)], cwd=REPO,
                                stdout=log, stderr=subprocess.STDOUT)
    try:
        assert _wait(lambda: "source finished" in log_path.read_text() or proc.poll() is not None, wait_s), \
            log_path.read_text()[-3000:]
        time.sleep(settle_s)
    finally:
        proc.send_signal(signal.SIGTERM)
        rc = proc.wait(15)
    return rc, log_path.read_text()


def test_service_survives_source_loss_and_estimator_failure(tmp_path: Path, notify_socket) -> None:
    sock, path = notify_socket
    cfg = config_from_dict({"run": {"status_file": str(tmp_path / "status.json"), "source_timeout_s": 0.3,
                                    "reconnect_max_s": 0.2, "trajectory_file": str(tmp_path / "traj.tum")},
                            "source": {"kind": "fake"}})
    events: list = []
    silent = threading.Event()
    explode: list = []
    mavs: list[RecordingMavlink] = []

    def make_mav() -> RecordingMavlink:
        mavs.append(RecordingMavlink())
        return mavs[-1]

    svc = Service(cfg, source_factory=lambda: _started(ScriptedSource(events, silent, fail_first)),
                  estimator_factory=lambda c: ScriptedEstimator(c, explode), mavlink_factory=make_mav,
                  notifier=SdNotifier(path))
    fail_first = [True]  # first open fails like an unplugged camera at boot
    runner = threading.Thread(target=svc.run)
    runner.start()
    try:
        assert _wait(lambda: svc.ready, 5.0), "never became ready"
        assert any(m.startswith("READY=1") for m in _received(sock))
        assert _wait(lambda: len(mavs[0].states) >= 5, 3.0)
        # cable pulled: the source goes quiet, is closed and reopened; data return -> poses again
        silent.set()
        assert _wait(lambda: svc.source.disconnects == 1, 3.0)
        silent.clear()
        assert _wait(lambda: svc.source.connected, 3.0)
        n = len(mavs[0].states)
        assert _wait(lambda: len(mavs[0].states) > n + 3, 3.0)
        # poses withheld as too old (the estimator behind): degraded, not "waiting for vision", tracking false
        mavs[0].withholding = True
        assert _wait(lambda: json.loads((tmp_path / "status.json").read_text())["state"] == "degraded", 3.0)
        st = json.loads((tmp_path / "status.json").read_text())
        assert not st["estimator"]["tracking"] and any("poses withheld" in w for w in st["warnings"])
        mavs[0].withholding = False
        # estimator failure -> reset, poses keep flowing, reset_counter moves on
        explode.append(True)
        assert _wait(lambda: svc.estimator.resets >= 1, 3.0)
        n = len(mavs[0].states)
        assert _wait(lambda: len(mavs[0].states) > n + 3, 3.0)
        assert mavs[0].states[-1].reset_counter >= 1
        assert _wait(lambda: (tmp_path / "status.json").exists(), 3.0)
        status = json.loads((tmp_path / "status.json").read_text())
        assert status["mavlink"]["state"] == "up" and status["mavlink"]["autopilot_heartbeats"] == 3
        assert status["mavlink"]["sent"] > 0 and status["estimator"]["tracks"] == 99
        assert status["source"]["driver"]["name"] == "scripted"
        # as the log counts them, not lagging behind the next pose
        assert _wait(lambda: json.loads((tmp_path / "status.json").read_text())["estimator"]["resets"] >= 1, 3.0)
    finally:
        t0 = time.monotonic()
        svc.request_stop(signal.SIGTERM)
        runner.join(5.0)
    assert not runner.is_alive() and time.monotonic() - t0 < 2.0
    assert events.count("start") >= 3 and events[-1] == "stop"  # failed boot open, first run, reopen
    assert mavs[0].closed
    assert json.loads((tmp_path / "status.json").read_text())["state"] == "stopped"
    assert len((tmp_path / "traj.tum").read_text().splitlines()) >= 10


def test_a_wrong_calibration_or_uncertain_frame_stamps_show_in_the_status_as_degraded(tmp_path: Path) -> None:
    """The estimator's stereo check let go of the calibration: poses keep flowing (cam1 is refined), but the status
    file says why the daemon is not simply running (state degraded, the warning, the estimator's own field), so
    `vio status` does not call it healthy and the next flight is not flown on the same wrong file unnoticed. The
    same for a camera whose frame stamps jitter too much to restamp."""
    cfg = config_from_dict({"run": {"status_file": str(tmp_path / "status.json")}, "source": {"kind": "fake"}})
    ests: list[ScriptedEstimator] = []

    def make_est(c: str) -> ScriptedEstimator:
        ests.append(ScriptedEstimator(c, []))
        return ests[-1]

    mavs: list[RecordingMavlink] = []
    svc = Service(cfg, source_factory=lambda: _started(ScriptedSource([], threading.Event(), [])),
                  estimator_factory=make_est, mavlink_factory=lambda: mavs.append(RecordingMavlink()) or mavs[-1])
    runner = threading.Thread(target=svc.run)
    runner.start()
    status = tmp_path / "status.json"
    try:
        assert _wait(lambda: svc.ready and len(mavs[0].states) >= 5, 5.0)
        assert _wait(lambda: status.exists() and json.loads(status.read_text())["state"] == "running", 3.0)
        ests[0].calibration_warning = "the right camera disagrees with the stereo calibration (disparity bias +0.50)"
        assert _wait(lambda: json.loads(status.read_text())["state"] == "degraded", 3.0)
        st = json.loads(status.read_text())
        assert any(w.startswith("calibration: the right camera disagrees") for w in st["warnings"]), st["warnings"]
        assert st["estimator"]["calibration_warning"].startswith("the right camera") and not st["healthy"]
        # frame stamps the clock could not restamp (kept as given, 8 ms of jitter): said, as the IMU clock's are; a
        # restamped camera's line error (0.4 ms) is no warning
        ests[0].calibration_warning = None
        ests[0].frame_stamps = {"mode": "auto", "restamped": 0, "uncertain_frames": 400, "stamp_sigma_ms": 8.2}
        assert _wait(lambda: any(w.startswith("camera: frame stamps uncertain by 8.2 ms") for w in
                                 json.loads(status.read_text())["warnings"]), 3.0)
        assert json.loads(status.read_text())["state"] == "degraded"
        ests[0].frame_stamps = {"mode": "auto", "restamped": 400, "uncertain_frames": 400, "stamp_sigma_ms": 0.4}
        assert _wait(lambda: json.loads(status.read_text())["state"] == "running", 3.0)
        n = len(mavs[0].states)
        assert _wait(lambda: len(mavs[0].states) > n + 3, 3.0)  # still flying on the refined calibration
    finally:
        svc.request_stop(signal.SIGTERM)
        runner.join(5.0)
    assert not runner.is_alive()


class Moving(ScriptedEstimator):
    """ScriptedEstimator flying at 2 m/s and turning at 0.5 rad/s, with a 1 cm position sigma per axis."""

    def feed_frame(self, f: StereoFrame) -> NavState | None:
        st = super().feed_frame(f)
        if st is None:
            return None
        return NavState(st.t_ns, st.T_world_body, np.array([2.0, 0.0, 0.0]), cov_pose=np.eye(6) * 1e-4,
                        cov_vel=np.eye(3) * 1e-4, omega_body=np.array([0.0, 0.0, 0.5]), reset_counter=st.reset_counter)


def test_the_imu_clock_health_reaches_what_is_sent_and_the_status(tmp_path: Path, caplog) -> None:
    """The IMU source's own measure of how far its stamps may be off (stamp_uncertainty_s) rises mid-flight, as the
    ArduPilot SITL's did when its clock stalled 150 ms (docs/autopilot.md: stamps ~0.2 s off for ~25 s went out at
    quality 100 with a covariance that did not grow). 2 ms (a healthy fit): every state goes out as the estimator
    made it. 20 ms at 2 m/s and 0.5 rad/s: position variance + (2 m/s x 20 ms)^2 along the motion, yaw + (0.5 x
    0.02)^2, quality 67 (two thirds of the way from 5 to the 50 ms bound left), and the status says 67 and why.
    200 ms, beyond [mavlink] max_stamp_error_ms: nothing tracked goes out, one log line, status not tracking,
    quality 0, the reason. Back at 1 ms: the estimator's states again, one line. Before, nothing of it reached
    the output or the status."""
    caplog.set_level(logging.INFO)
    status = tmp_path / "status.json"
    cfg = config_from_dict({"run": {"status_file": str(status)}, "mavlink": {"max_stamp_error_ms": 50.0}})
    srcs: list[ScriptedSource] = []
    ests: list[Moving] = []
    mavs: list[RecordingMavlink] = []

    def source() -> ScriptedSource:
        srcs.append(_started(ScriptedSource([], threading.Event(), [])))
        return srcs[-1]

    svc = Service(cfg, source_factory=source, estimator_factory=lambda c: ests.append(Moving(c, [])) or ests[-1],
                  mavlink_factory=lambda: mavs.append(RecordingMavlink()) or mavs[-1], notifier=SdNotifier(""))
    made: dict[int, NavState] = {}
    feed = Moving.feed_frame

    def remember(self: Moving, f: StereoFrame) -> NavState | None:
        st = feed(self, f)
        if st is not None:
            made[st.t_ns] = st
        return st

    Moving.feed_frame = remember  # type: ignore[method-assign]
    runner = threading.Thread(target=svc.run)
    runner.start()

    def sent_after(n: int, count: int) -> list[NavState]:
        assert _wait(lambda: len(mavs) and len(mavs[0].states) >= n + count, 3.0), "no more states sent"
        return mavs[0].states[n + 2:]  # the first two may have been checked before the change

    def status_says(cond) -> dict:
        assert _wait(lambda: cond(_read_status(status)), 3.0), _read_status(status)
        return _read_status(status)

    try:
        assert _wait(lambda: srcs and svc.ready, 5.0)
        srcs[0].clock_error_s = 0.002
        healthy = sent_after(0, 6)
        assert all(s is made[s.t_ns] for s in healthy)  # untouched: same quality, same covariance
        st = status_says(lambda st: st.get("state") == "running")
        assert st["estimator"]["quality"] == 100 and st["mavlink"]["stamp_error_ms"] == 2.0

        srcs[0].clock_error_s = 0.020
        grown = sent_after(len(mavs[0].states), 6)
        for s in grown:
            m = made[s.t_ns]
            add = np.zeros((6, 6))
            add[2, 2] = (0.5 * 0.02) ** 2
            add[3, 3] = (2.0 * 0.02) ** 2  # body x = world x here: the motion is along it
            np.testing.assert_allclose(s.cov_pose, m.cov_pose + add, atol=1e-12)
            assert s.tracking and s.quality == 67 and np.array_equal(s.cov_vel, m.cov_vel)  # no acceleration
        st = status_says(lambda st: st.get("estimator", {}).get("quality") == 67)
        assert st["state"] == "degraded" and st["estimator"]["tracking"]
        assert any(w.startswith("IMU stamps uncertain by 20 ms") for w in st["warnings"]), st["warnings"]

        srcs[0].clock_error_s = 0.200
        refused = sent_after(len(mavs[0].states), 6)
        assert refused and not any(s.tracking for s in refused) and {s.quality for s in refused} == {0}
        assert mavs[0].withheld_for == "VIO: IMU clock unsure, no poses"  # not even lost_output's -1/0 poses
        st = status_says(lambda st: st.get("estimator", {}).get("tracking") is False)
        assert st["estimator"]["quality"] == 0 and st["state"] == "degraded" and not st["healthy"]
        assert st["mavlink"]["refusing_uncertain_stamps"] and st["mavlink"]["stamp_error_ms"] == 200.0
        # one count of the states held back, the output's, with its why (the gate kept a second one: N beside 0)
        st = status_says(lambda st: st.get("mavlink", {}).get("states_withheld", 0) >= len(refused))
        assert "states_refused_stamps" not in st["mavlink"], st["mavlink"]
        assert st["mavlink"]["withheld_for"] == "VIO: IMU clock unsure, no poses"
        assert f"withheld {st['mavlink']['states_withheld']} (VIO: IMU clock unsure, no poses)" in \
            format_status(st, "DEGRADED", st["written_unix"])
        assert any(w.startswith("poses not sent: IMU stamps uncertain by 200 ms, beyond [mavlink] max_stamp_error_ms "
                                "= 50") for w in st["warnings"]), st["warnings"]

        srcs[0].clock_error_s = 0.001
        back = sent_after(len(mavs[0].states), 6)
        assert all(s is made[s.t_ns] for s in back) and mavs[0].withheld_for is None
        st = status_says(lambda st: st.get("state") == "running")
        assert st["estimator"]["quality"] == 100 and st["estimator"]["tracking"]
        assert not any("stamps" in w for w in st["warnings"])
    finally:
        Moving.feed_frame = feed  # type: ignore[method-assign]
        svc.request_stop(signal.SIGTERM)
        runner.join(5.0)
    assert not runner.is_alive()
    said = [r.getMessage() for r in caplog.records if r.name == "vio.app.daemon.outputs"]
    assert len(said) == 2, said  # entering, leaving: one line each
    assert said[0].startswith("IMU stamps uncertain by 200 ms (the IMU source's clock sync), beyond [mavlink] "
                              "max_stamp_error_ms = 50: no pose is sent until they are back under 40 ms"), said
    assert said[1].startswith("IMU stamps uncertain by 1 ms again"), said


def test_the_status_quality_is_what_the_autopilot_gets_while_the_output_refuses(tmp_path: Path) -> None:
    """The MAVLink output holds back a simulated source's poses (the autopilot says it is armed): the estimator tracks
    at quality 100, nothing goes out, and the status said quality 100 beside 'poses not sent'. It says 0 now (what
    is sent), and 100 again once poses go out."""
    status = tmp_path / "status.json"
    cfg = config_from_dict({"run": {"status_file": str(status)}, "source": {"kind": "fake"}})

    class Refusing(RecordingMavlink):
        refusing: str | None = "armed"

        def health(self) -> dict:
            return {**super().health(), "withholding_replay_poses": self.refusing}

    mavs: list[Refusing] = []
    svc = Service(cfg, source_factory=lambda: _started(ScriptedSource([], threading.Event(), [])),
                  estimator_factory=lambda c: ScriptedEstimator(c, []),
                  mavlink_factory=lambda: mavs.append(Refusing()) or mavs[-1], notifier=SdNotifier(""))
    runner = threading.Thread(target=svc.run)
    runner.start()
    try:
        assert _wait(lambda: _status_warns(status, lambda w: w.startswith("poses not sent")), 5.0), \
            _read_status(status)
        st = _read_status(status)
        assert st["estimator"]["tracking"] and st["estimator"]["quality"] == 0, st["estimator"]
        mavs[0].refusing = None
        assert _wait(lambda: _read_status(status).get("state") == "running", 3.0), _read_status(status)
        assert _read_status(status)["estimator"]["quality"] == 100
    finally:
        svc.request_stop(signal.SIGTERM)
        runner.join(5.0)
    assert not runner.is_alive()


def test_a_stamp_error_grows_the_covariance_along_the_motion_in_the_frames_sent() -> None:
    """StampErrorGate.apply, the vehicle yawed 90 deg (body x = world y): 2 m/s along world x is 2 m/s along body -y,
    so 20 ms of stamp error adds (0.04 m)^2 to the body y position variance only; an acceleration of 2 m/s^2 (from
    the velocities of states 0.1 s apart) adds (0.04 m/s)^2 to the world x velocity variance; a turn about body z
    (0.5 rad/s) adds (0.01 rad)^2 to that rotation's. NaN or inf (the fit cannot place the stamps) refuses."""
    from vio.app.daemon.outputs import StampErrorGate

    err = [0.02]
    gate = StampErrorGate(lambda: err[0], 0.05, 0.05, 0.005)
    T = np.eye(4)
    T[:3, :3] = [[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]

    def state(t_s: float, vx: float) -> NavState:
        return NavState(int(t_s * 1e9), T, np.array([vx, 0.0, 0.0]), cov_pose=np.eye(6) * 1e-4,
                        cov_vel=np.eye(3) * 1e-4, omega_body=np.array([0.0, 0.0, 0.5]))

    gate.apply(state(1.0, 2.0))
    s = gate.apply(state(1.1, 2.2))
    add = np.zeros(6)
    add[2], add[4] = 0.01**2, (2.2 * 0.02) ** 2
    np.testing.assert_allclose(s.cov_pose, np.eye(6) * 1e-4 + np.diag(add), atol=1e-12)
    np.testing.assert_allclose(s.cov_vel, np.eye(3) * 1e-4 + np.diag([(2.0 * 0.02) ** 2, 0, 0]), atol=1e-12)
    assert s.tracking and s.quality == 67
    for bad in (float("nan"), float("inf")):
        err[0] = bad
        s = gate.apply(state(1.2, 2.2))
        assert not s.tracking and s.quality == 0 and gate.refusing


def test_the_stamp_tolerance_is_the_configured_one_and_the_quality_ramp_starts_there(tmp_path: Path) -> None:
    """[mavlink] stamp_tolerance_ms (it was a 5 ms constant): with 10 ms, 8 ms of stamp error changes nothing and
    20 ms caps the quality at 100 x (50 - 20) / (50 - 10) = 75 (67 with 5 ms); the daemon builds its gate from the
    config and says the tolerance in its status; a tolerance at the bound is refused (the config names the keys)."""
    from vio.app.daemon.outputs import StampErrorGate

    err = [0.008]
    gate = StampErrorGate(lambda: err[0], 0.05, None, 0.010)
    s0 = NavState(1_000_000_000, np.eye(4), np.array([2.0, 0.0, 0.0]), cov_pose=np.eye(6) * 1e-4,
                  cov_vel=np.eye(3) * 1e-4)
    assert gate.apply(s0) is s0
    err[0] = 0.020
    assert gate.apply(s0).quality == 75 and gate.grown == 1
    with pytest.raises(ValueError, match="stamp tolerance 50 ms must be below the bound 50 ms"):
        StampErrorGate(lambda: 0.0, 0.05, None, 0.05)
    cfg = config_from_dict({"run": {"status_file": str(tmp_path / "s.json")},
                            "mavlink": {"stamp_tolerance_ms": 12.5}})
    svc = Service(cfg, source_factory=lambda: ScriptedSource([], threading.Event(), []),
                  estimator_factory=lambda c: ScriptedEstimator(c, []), mavlink_factory=RecordingMavlink,
                  notifier=SdNotifier(""))
    assert svc.output.stamps.tolerance_s == 0.0125
    assert svc.snapshot()["mavlink"]["stamp_tolerance_ms"] == 12.5


def test_the_mavlink_counts_cover_the_whole_run_across_a_reopened_output() -> None:
    """The daemon reopens a MAVLink output that failed (an exception from send_state or poll): the new one starts its
    counts at 0, so `vio status` read states_withheld 0 and withheld_for "" after it, as if nothing had been held
    back (docs/autopilot.md said so), and nothing at all while no output was open. The status adds the closed
    outputs' counts now: the whole run's, between the outputs too."""
    from drivers.mavlink_out import MavlinkOutput
    from vio.app.daemon.outputs import STAMPS_WITHHELD_TEXT, OutputWorker, StampErrorGate
    from vio.config import MavlinkConfig

    sink = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)  # the autopilot's end: takes and drops what comes
    sink.bind(("127.0.0.1", 0))
    err = [1.0]  # IMU stamps 1 s off: every pose withheld
    outs: list[MavlinkOutput] = []

    def make() -> MavlinkOutput:
        outs.append(MavlinkOutput(MavlinkConfig(mount="rpy"), f"udpout:127.0.0.1:{sink.getsockname()[1]}"))
        return outs[-1]

    w = OutputWorker(threading.Event(), LatestState(), make, "", 1.0,
                     stamps=StampErrorGate(lambda: err[0], 0.05, None, 0.005))
    t0 = time.monotonic_ns()

    def offer(k: int) -> None:
        w._send(w._checked(NavState(t0 + k * 100_000_000, np.eye(4), np.zeros(3))))

    def broken(s: NavState) -> None:
        raise OSError("serial write failed")

    try:
        w._ensure_mavlink()
        for k in range(3):
            offer(k)
        assert w.link()["states_withheld"] == 3
        outs[0].send_state = broken  # type: ignore[method-assign]
        offer(3)  # the output fails: closed, reopened after a back-off
        assert w.mav is None
        h = w.link()
        assert h["state"] == "closed" and h["states_withheld"] == 3 and h["withheld_for"] == STAMPS_WITHHELD_TEXT
        w._next_open = 0.0
        w._ensure_mavlink()
        assert len(outs) == 2 and outs[1].stats.states_withheld == 0  # its own count starts at 0
        err[0] = 0.001  # the clock is healthy again: sent
        offer(4)
        h = w.link()
        assert (h["states_withheld"], h["withheld_for"], h["states_sent"], w.sent) == (3, STAMPS_WITHHELD_TEXT, 1, 1)
        err[0] = 1.0
        offer(5)
        offer(6)
        assert w.link()["states_withheld"] == 5 and w.link()["states_in"] == 6  # the failed state never got in
    finally:
        w.close()
        sink.close()


def test_states_with_no_mavlink_output_open_are_counted_and_shown() -> None:
    """Between a MAVLink output that could not be opened (or failed) and its reopening, the daemon's output thread
    dropped every state uncounted: `vio status` said "link closed" and no count. They are counted, with the
    output's own states due while its connection was closed, in mavlink.states_link_closed, and its mavlink line
    says how many."""
    from drivers.mavlink_out import MavlinkOutput
    from vio.app.daemon.outputs import OutputWorker
    from vio.config import MavlinkConfig

    probe = socket.socket()
    probe.bind(("127.0.0.1", 0))
    port = probe.getsockname()[1]
    probe.close()  # nothing listens on `port` now
    opens: list[MavlinkOutput] = []

    def make() -> MavlinkOutput:
        if not opens:
            opens.append(None)  # type: ignore[arg-type]
            raise OSError("no such device")
        opens.append(MavlinkOutput(MavlinkConfig(mount="rpy"), f"tcp:127.0.0.1:{port}"))
        return opens[-1]

    w = OutputWorker(threading.Event(), LatestState(), make, "", 1.0)
    t0 = time.monotonic_ns()

    def offer(k: int) -> None:
        w._send(w._checked(NavState(t0 + k * 100_000_000, np.eye(4), np.zeros(3))))

    try:
        w._ensure_mavlink()  # fails: none open
        for k in range(3):
            offer(k)
        h = w.link()
        assert (h["state"], h["states_link_closed"]) == ("closed", 3)
        w._next_open = 0.0
        w._ensure_mavlink()  # opened, but its connection is not: its TCP peer is not there
        assert w.mav is not None and not w.mav.connected
        for k in range(3, 5):
            offer(k)
            time.sleep(0.04)  # a send period (30 Hz) past its slot with no connection: dropped there, counted
            w._poll()
        assert w.link()["states_link_closed"] == 5
        text = format_status({"mavlink": w.link(), "written_unix": time.time()}, "DEGRADED", time.time())
        assert ", not sent with the link closed 5" in text, text
    finally:
        w.close()


def _started(src: ScriptedSource) -> ScriptedSource:
    src.start()
    return src


# ------------------------------------------------------------------------------ `vio run` subprocess

def test_run_config_error_exits_3(tmp_path: Path) -> None:
    bad = tmp_path / "config.toml"
    bad.write_text('[source]\nkind = "euroc"\ndatset = "/nowhere"\n')
    r = subprocess.run([sys.executable, "-m", "vio.app.cli", "run", "--config", str(bad)], capture_output=True,
                       text=True, timeout=60)
    assert r.returncode == 3
    assert "configuration error" in r.stderr and "datset" in r.stderr and "Traceback" not in r.stderr
    r = subprocess.run([sys.executable, "-m", "vio.app.cli", "run", "--config", str(tmp_path / "absent.toml")],
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 3 and "absent.toml" in r.stderr
    # a map that cannot be read is refused at start, not found by the estimator thread once the sensors are up;
    # a calibration in millimetres too (vio replay refused it, vio run flew it: 49 m for 4.8 m, a review's finding)
    (tmp_path / "cut.kmap").write_bytes(b"PK\x03\x04" + bytes(100))
    import dataclasses

    from vio.calibration import save_calibration
    from vio.sim import default_calibration

    c = default_calibration()
    mm = [dataclasses.replace(cam, T_body_cam=np.vstack([np.hstack([cam.T_body_cam[:3, :3],
                                                                     1000 * cam.T_body_cam[:3, 3:]]), [0, 0, 0, 1]]))
          for cam in (c.cam0, c.cam1)]
    save_calibration(dataclasses.replace(c, cam0=mm[0], cam1=mm[1]), tmp_path / "calib_mm.yaml")
    save_calibration(c, tmp_path / "calib_ok.yaml")
    for section, says in ((f'[map]\nload = "{tmp_path / "cut.kmap"}"', "truncated"),
                          (f'calibration = "{tmp_path / "calib_mm.yaml"}"', "look like millimetres"),
                          (f'[map]\nsave = "{tmp_path / "nodir" / "m.kmap"}"', "does not exist"),
                          (f'[map]\nsave = "{tmp_path}"', "is a folder"),
                          ('[loop]\noutput = "jump"', "needs the loop stage"),
                          (f'calibration = "{tmp_path / "calib_ok.yaml"}"\nwidth = 320\nheight = 200',
                           "is for 752x480 images, but the camera streams"),
                          (f'[run]\nstatus_file = "{tmp_path / "calib_mm.yaml" / "status.json"}"',
                           "is a file, not a folder")):
        bad.write_text(f'[source]\nkind = "fake"\n{section}\n')
        r = subprocess.run([sys.executable, "-m", "vio.app.cli", "run", "--config", str(bad)], capture_output=True,
                           text=True, timeout=60)
        assert r.returncode == 3 and says in r.stderr and "Traceback" not in r.stderr, r.stderr


# A `vio run` whose source can be unplugged from the test: while the file named by $KESTREL_TEST_UNPLUG
# exists, every source the daemon opens delivers nothing (as a pulled USB cable does); while the file
# $KESTREL_TEST_IMU_OFF exists, its IMU samples are dropped (a serial IMU whose cable came loose).
LAUNCHER = """
import os, sys
import drivers.source as ds
from vio.types import ImuSample
real_open = ds.open_source
flag = os.environ.get("KESTREL_TEST_UNPLUG", "/nonexistent")
imu_off = os.environ.get("KESTREL_TEST_IMU_OFF", "/nonexistent")

class Unpluggable:
    def __init__(self, inner):
        self.inner = inner
    def __getattr__(self, name):
        return getattr(self.inner, name)
    def poll(self):
        out = self.inner.poll()
        if os.path.exists(imu_off):
            out = [m for m in out if not isinstance(m, ImuSample)]
        return [] if os.path.exists(flag) else out

ds.open_source = lambda cfg, **kw: Unpluggable(real_open(cfg, **kw))
from vio.app.cli import main
sys.exit(main(sys.argv[1:]))
"""


class FakeAutopilot(threading.Thread):
    """UDP peer of `udpout:`: answers with HEARTBEATs and counts the messages it receives by name."""

    def __init__(self) -> None:
        super().__init__(daemon=True)
        from pymavlink.dialects.v20 import common as mavlink2

        self.mavlink = mavlink2
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.settimeout(0.1)
        self.port = self.sock.getsockname()[1]
        self.counts: dict[str, int] = {}
        self.odometry_quality: list[int] = []  # quality of every ODOMETRY received
        self.components: set[int] = set()
        self.armed = False  # what its HEARTBEATs say
        self.stop = threading.Event()

    def run(self) -> None:
        parser = self.mavlink.MAVLink(None)
        parser.robust_parsing = True
        encoder = self.mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
        peer = None
        next_hb = 0.0
        while not self.stop.is_set():
            try:
                data, peer = self.sock.recvfrom(65536)
                for msg in parser.parse_buffer(data) or []:
                    name = msg.get_type()
                    self.counts[name] = self.counts.get(name, 0) + 1
                    self.components.add(msg.get_srcComponent())
                    if name == "ODOMETRY":
                        self.odometry_quality.append(msg.quality)
            except TimeoutError:
                pass
            if peer is not None and time.monotonic() >= next_hb:
                hb = self.mavlink.MAVLink_heartbeat_message(
                    self.mavlink.MAV_TYPE_QUADROTOR, self.mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA,
                    self.mavlink.MAV_MODE_FLAG_SAFETY_ARMED if self.armed else 0, 0,
                    self.mavlink.MAV_STATE_ACTIVE, 3)
                self.sock.sendto(hb.pack(encoder), peer)
                next_hb = time.monotonic() + 0.5

    def poses(self) -> int:
        return self.counts.get("VISION_POSITION_ESTIMATE", 0) + self.counts.get("ODOMETRY", 0)

    def odometry_tracked(self) -> int:
        """ODOMETRY messages the autopilot would use (quality > 0; lost_output = 'quality0' sends 0)."""
        return sum(q > 0 for q in self.odometry_quality)


def _need_pipeline() -> None:
    missing = [m for m in ("drivers.fake", "drivers.mavlink_out", "vio.estimator")
               if importlib.util.find_spec(m) is None]
    if missing:
        pytest.skip(f"pipeline parts not in this tree yet: {', '.join(missing)}")


def _start_daemon(tmp_path: Path, source: str, port: int, notify_path: str) -> tuple[subprocess.Popen, Path]:
    cfg = tmp_path / "config.toml"
    cfg.write_text(f"""{source}
[mavlink]
url = "udpout:127.0.0.1:{port}"
[run]
status_file = "{tmp_path / 'status.json'}"
trajectory_file = "{tmp_path / 'traj.tum'}"
source_timeout_s = 0.5
reconnect_max_s = 0.5
""")
    env = dict(os.environ, NOTIFY_SOCKET=notify_path, WATCHDOG_USEC="2000000",
               KESTREL_TEST_UNPLUG=str(tmp_path / "unplugged"), OMP_NUM_THREADS="1", PYTHONUNBUFFERED="1")
    env.pop("WATCHDOG_PID", None)
    log = open(tmp_path / "daemon.log", "w")
    proc = subprocess.Popen([sys.executable, "-c", LAUNCHER, "run", "--config", str(cfg)], cwd=REPO, env=env,
                            stdout=log, stderr=subprocess.STDOUT)
    return proc, tmp_path / "daemon.log"


def _stop_daemon(proc: subprocess.Popen) -> tuple[int, float]:
    t0 = time.monotonic()
    proc.send_signal(signal.SIGTERM)
    try:
        rc = proc.wait(10)
    except subprocess.TimeoutExpired:
        proc.kill()
        rc = proc.wait()
    return rc, time.monotonic() - t0


def test_vio_run_end_to_end_with_fake_source(tmp_path: Path, notify_socket) -> None:
    """READY after the first pose, poses reach the autopilot, an unplugged source is survived, SIGTERM
    stops it cleanly within 2 s."""
    _need_pipeline()
    sock, notify_path = notify_socket
    ap = FakeAutopilot()
    ap.start()
    proc, log_path = _start_daemon(tmp_path, '[source]\nkind = "fake"\nwidth = 320\nheight = 200',
                                   ap.port, notify_path)
    notes: list[str] = []
    try:
        assert _wait(lambda: notes.extend(_received(sock)) or any(n.startswith("READY=1") for n in notes), 60), \
            f"no READY=1; log:\n{log_path.read_text()[-3000:]}"
        assert _wait(lambda: ap.poses() >= 20, 20), f"autopilot got {ap.counts}"
        assert 197 in ap.components  # MAV_COMP_ID_VISUAL_INERTIAL_ODOMETRY
        # a second daemon on the same configuration is refused (two sent to the autopilot as one: a review's)
        second = subprocess.run([sys.executable, "-c", LAUNCHER, "run", "--config", str(tmp_path / "config.toml")],
                                cwd=REPO, capture_output=True, text=True, timeout=60)
        assert second.returncode == 3 and f"another vio run (pid {proc.pid})" in second.stderr, second.stderr
        proc.send_signal(signal.SIGHUP)  # no reload: said and ignored (it killed the daemon without a word)
        assert _wait(lambda: "received SIGHUP: ignored" in log_path.read_text(), 10)
        assert proc.poll() is None
        text = log_path.read_text()  # the lines docs/first-flight.md tells the operator to look for
        assert "ready after" in text and text.count("first pose after") == 1, text[-3000:]
        # pull the cable for a while: the daemon logs it, keeps running, and poses resume afterwards
        (tmp_path / "unplugged").touch()
        assert _wait(lambda: "source lost" in log_path.read_text(), 10), log_path.read_text()[-3000:]
        time.sleep(1.0)
        assert proc.poll() is None
        (tmp_path / "unplugged").unlink()
        assert _wait(lambda: "again after" in log_path.read_text(), 10), log_path.read_text()[-3000:]
        n = ap.poses()
        assert _wait(lambda: ap.poses() >= n + 20, 40), f"no poses after replug; log:\n{log_path.read_text()[-3000:]}"
        notes.extend(_received(sock))
        assert "WATCHDOG=1" in notes
        status = json.loads((tmp_path / "status.json").read_text())
        assert status["source"]["disconnects"] >= 1 and status["mavlink"]["state"] == "up"
    finally:
        rc, took = _stop_daemon(proc)
        ap.stop.set()
    assert rc == 0, log_path.read_text()[-3000:]
    assert took < 2.0
    assert json.loads((tmp_path / "status.json").read_text())["state"] == "stopped"
    assert "Traceback" not in log_path.read_text()


def test_vio_run_with_a_simulated_source_sends_no_pose_to_an_armed_autopilot(tmp_path: Path, notify_socket) -> None:
    """`[source] kind = "fake"` (or "euroc") is another flight's: as `vio replay --mavlink`, the daemon sends none of
    its poses while the autopilot says it is armed (it would fly on them), says why in the log and the status, and
    sends them once it is disarmed. Before, only `vio replay` held them back."""
    _need_pipeline()
    sock, notify_path = notify_socket
    ap = FakeAutopilot()
    ap.armed = True
    ap.start()
    proc, log_path = _start_daemon(tmp_path, '[source]\nkind = "fake"\nwidth = 320\nheight = 200',
                                   ap.port, notify_path)
    status_path = tmp_path / "status.json"

    def status() -> dict:
        return _read_status(status_path)
    try:
        assert _wait(lambda: any(n.startswith("READY=1") for n in _received(sock)), 60), log_path.read_text()[-3000:]
        assert _wait(lambda: any("poses not sent" in w and "autopilot says it is armed" in w
                                 for w in status().get("warnings", [])), 40), status()
        assert ap.poses() == 0, ap.counts
        assert status()["state"] == "degraded"
        assert "the autopilot is armed: no pose of this replay is sent" in log_path.read_text()
        assert "this process has sent no pose yet" not in log_path.read_text()  # not this vehicle's loss either
        ap.armed = False
        assert _wait(lambda: ap.poses() >= 10, 40), f"autopilot got {ap.counts}"
        assert _wait(lambda: not any("poses not sent" in w for w in status().get("warnings", [])), 40), status()
    finally:
        rc, took = _stop_daemon(proc)
        ap.stop.set()
    assert rc == 0 and took < 2.0, log_path.read_text()[-3000:]


def test_vio_run_replays_euroc_as_live(tmp_path: Path, notify_socket, v101_path: Path) -> None:
    """source.kind = "euroc": the real (still) V1_01 excerpt initialises, READY comes, poses flow."""
    _need_pipeline()
    sock, notify_path = notify_socket
    ap = FakeAutopilot()
    ap.start()
    proc, log_path = _start_daemon(tmp_path, f'[source]\nkind = "euroc"\ndataset = "{v101_path}"', ap.port,
                                   notify_path)
    try:
        assert _wait(lambda: any(n.startswith("READY=1") for n in _received(sock)), 60), log_path.read_text()[-3000:]
        assert _wait(lambda: ap.poses() >= 10, 20), f"autopilot got {ap.counts}"
        # one TUM pose per processed camera frame (IMU-rate states go to MAVLink only)
        traj = tmp_path / "traj.tum"
        assert _wait(lambda: traj.exists() and len(traj.read_text().splitlines()) >= 10, 20), \
            log_path.read_text()[-3000:]
    finally:
        rc, took = _stop_daemon(proc)
        ap.stop.set()
    assert rc == 0 and took < 2.0, log_path.read_text()[-3000:]
    lines = traj.read_text().splitlines()
    assert lines[0].startswith("# kestrel-vio run started ")  # a comment (TUM readers skip them): where this run starts
    t_s = [float(line.split()[0]) for line in lines if not line.startswith("#")]
    assert all(np.diff(t_s) > 0.04)  # 20 Hz frames, not 200 Hz IMU states


def _record_fake(tmp_path: Path, until, **run) -> Service:
    """Run the daemon on a fake source with recording into tmp_path/rec until `until(svc)`, then stop it."""
    from drivers.fake import FakeSource

    cfg = config_from_dict({"run": {"status_file": "", "record_dir": str(tmp_path / "rec"), **run}})

    class AnyCalibEstimator(ScriptedEstimator):
        def __init__(self, calib) -> None:
            super().__init__("calib", [])

    svc = Service(cfg, source_factory=lambda: _started(FakeSource(width=96, height=64)),
                  estimator_factory=AnyCalibEstimator, notifier=SdNotifier(""))
    runner = threading.Thread(target=svc.run)
    runner.start()
    assert _wait(lambda: until(svc), 10)
    svc.request_stop()
    runner.join(5)
    return svc


def test_recording_is_flushed_on_stop_and_readable(tmp_path: Path) -> None:
    if importlib.util.find_spec("drivers.fake") is None:
        pytest.skip("drivers/fake.py not in this tree yet")
    from vio.io.euroc import EurocDataset

    svc = _record_fake(tmp_path, lambda svc: svc.recorder.frames >= 10)
    (dataset_dir,) = (tmp_path / "rec").iterdir()
    ds = EurocDataset(dataset_dir)
    assert len(ds) == svc.recorder.frames and len(ds.imu) == svc.recorder.imu
    assert len(ds.imu) >= 9 * len(ds)  # 200 Hz IMU vs 20 Hz frames


def test_frames_the_estimator_restamps_keep_their_pose_line_and_latency_and_are_recorded_as_given(
        tmp_path: Path) -> None:
    """An estimator that moves frame stamps (vio.frame_clock, a camera stamped on arrival): the daemon finds each
    frame's arrival (the latency, the TUM pose log) by the stamp the estimator gave it, and the recording keeps the
    stamps as the camera gave them. Found by the stamp fed instead, no restamped frame got its TUM line or its
    latency (a replay of a jittered flight logged 9 poses of 151: a review's finding)."""
    from drivers.fake import FakeSource
    from vio.io.euroc import EurocDataset

    moved_ns = 1_000_000

    class Restamping(ScriptedEstimator):
        def __init__(self, calib) -> None:
            super().__init__("calib", [])

        def feed_frame(self, f: StereoFrame) -> NavState | None:
            return super().feed_frame(dataclasses.replace(f, t_ns=f.t_ns + moved_ns))

    traj = tmp_path / "traj.tum"
    cfg = config_from_dict({"run": {"status_file": "", "record_dir": str(tmp_path / "rec"),
                                    "trajectory_file": str(traj)}})
    svc = Service(cfg, source_factory=lambda: _started(FakeSource(width=96, height=64)),
                  estimator_factory=Restamping, notifier=SdNotifier(""))
    runner = threading.Thread(target=svc.run)
    runner.start()
    try:
        assert _wait(lambda: svc.recorder.frames >= 20 and len(svc.output.latency_ms) >= 10, 10), \
            (svc.recorder.frames, len(svc.output.latency_ms))
    finally:
        svc.request_stop()
        runner.join(5)
    (dataset_dir,) = (tmp_path / "rec").iterdir()
    given = EurocDataset(dataset_dir).cam0_t
    t_tum = np.array([round(float(line.split()[0]) * 1e9) for line in traj.read_text().splitlines()
                      if not line.startswith("#")])
    assert len(t_tum) >= 10
    on_given = np.isin(np.round((t_tum - moved_ns) * 1e-6), np.round(given * 1e-6))
    assert on_given.mean() > 0.8, (t_tum[:5], given[:5])  # the estimator's stamps, one per frame recorded
    assert not np.isin(np.round(given * 1e-6), np.round(t_tum * 1e-6)).any()  # the recording: the camera's stamps


def test_mcap_recording_holds_sensors_and_health_and_replays(tmp_path: Path) -> None:
    pytest.importorskip("mcap")
    pytest.importorskip("rosbags")
    from drivers.fake import FakeSource
    from vio.io.bag import BagDataset

    svc = _record_fake(tmp_path, lambda svc: svc.recorder.frames >= 25 and bool(svc._last_status),
                       record_format="mcap", record_images="png")
    (path,) = (tmp_path / "rec").iterdir()
    assert path.suffix == ".mcap"
    ds = BagDataset(path, FakeSource(width=96, height=64).calibration())
    assert len(ds) == svc.recorder.frames and len(ds.imu) == svc.recorder.imu
    from mcap.reader import make_reader

    with open(path, "rb") as f:
        topics = {c.topic for c in make_reader(f).get_summary().channels.values()}
    assert {"/cam0/image_raw", "/cam1/image_raw", "/imu0", "/vio/health"} <= topics


def test_a_driver_that_reconnects_itself_is_not_restarted(tmp_path: Path, monkeypatch) -> None:
    """An OAK driver reports state 'disconnected' and reconnects on its own: the daemon counts the loss,
    waits for the data to return, and does not tear the driver down in the middle of its reconnect."""
    import vio.app.daemon.workers as workers

    monkeypatch.setattr(workers, "FIRST_DATA_TIMEOUT_S", 0.3)
    cfg = config_from_dict({"run": {"status_file": "", "source_timeout_s": 0.3}})
    events: list = []
    silent = threading.Event()

    class SelfHealing(ScriptedSource):
        def health(self) -> dict:
            return {"state": "disconnected" if silent.is_set() else "running", "last_error": "USB reset"}

    svc = Service(cfg, source_factory=lambda: _started(SelfHealing(events, silent, [])),
                  estimator_factory=lambda c: ScriptedEstimator(c, []), notifier=SdNotifier(""))
    runner = threading.Thread(target=svc.run)
    runner.start()
    try:
        assert _wait(lambda: svc.ready, 5.0)
        silent.set()
        assert _wait(lambda: svc.source.disconnects == 1 and svc.source.last_error.startswith("driver"), 3.0)
        time.sleep(0.5)
        silent.clear()
        assert _wait(lambda: svc.source.connected, 3.0)
    finally:
        svc.request_stop()
        runner.join(5)
    assert events == ["start", "stop"]


def test_a_serial_imu_that_cannot_open_is_named_in_the_status(tmp_path: Path, notify_socket) -> None:
    """The camera delivers, the serial IMU's port does not exist: the status says why there is no IMU (the error
    sat only in the driver's JSON, under 'sensors connected')."""
    pytest.importorskip("serial")
    _need_pipeline()
    _, notify_path = notify_socket
    ap = FakeAutopilot()
    ap.start()
    proc, log_path = _start_daemon(tmp_path, '[source]\nkind = "fake"\nwidth = 320\nheight = 200\nimu = "serial"\n'
                                   f'serial_port = "{tmp_path / "ttyNOPE0"}"', ap.port, notify_path)
    status = tmp_path / "status.json"

    try:
        assert _wait(lambda: _status_warns(status, lambda w: "cannot open serial IMU port" in w), 30), \
            log_path.read_text()[-3000:]
        assert ap.poses() == 0
        # READY names the driver's error where its first open came before the camera's first frame; under load the
        # camera can come first and READY says '(starting)' (a CI run's flake): the error is in the log either way
        log_text = log_path.read_text()
        assert "ready after" in log_text and "camera delivering, no IMU sample yet (" in log_text
        assert "cannot open serial IMU port" in log_text
    finally:
        _stop_daemon(proc)
        ap.stop.set()


@pytest.mark.parametrize("sends, says", [
    ("nothing", "is open but nothing arrives on it: is the IMU powered and sending, its TX wired to this port's RX?"),
    ("wrong baud", "bytes arrive at 921600 baud but not one valid frame: the sender at another baud rate than "
                   "[source] serial_baud, or another device on [source] serial_port?"),
])
def test_a_serial_imu_port_that_opens_but_gives_no_frame_says_why(tmp_path: Path, notify_socket, sends: str,
                                                                  says: str) -> None:
    """The serial IMU's port opens (a pty) but no frame comes: nothing at all (TX/RX swapped, the IMU unpowered), or
    bytes at a wrong baud rate. The status said only 'IMU: no samples for N s: no poses', the same for both and for
    every other reason (an integrator's walk-through); it names the link's problem now, and so does the log."""
    import pty
    import threading
    import tty

    import numpy as np

    from drivers.reference_sender import _wrong_baud_bytes

    pytest.importorskip("serial")
    _need_pipeline()
    _, notify_path = notify_socket
    master, slave = pty.openpty()
    tty.setraw(slave)
    stop = threading.Event()

    def garbage() -> None:  # what a UART reads from a sender at another baud rate, 40 kB/s
        rng = np.random.default_rng(5)
        while not stop.wait(0.02):
            os.write(master, _wrong_baud_bytes(rng, 800))

    writer = threading.Thread(target=garbage, daemon=True)
    if sends == "wrong baud":
        writer.start()
    ap = FakeAutopilot()
    ap.start()
    proc, log_path = _start_daemon(tmp_path, '[source]\nkind = "fake"\nwidth = 320\nheight = 200\nimu = "serial"\n'
                                   f'serial_port = "{os.ttyname(slave)}"', ap.port, notify_path)
    status = tmp_path / "status.json"

    try:
        assert _wait(lambda: _status_warns(status, lambda w: says in w and w.startswith("IMU: no samples")), 30), \
            log_path.read_text()[-3000:]
        assert ap.poses() == 0
        said = [line for line in log_path.read_text().splitlines() if "drivers.serial_imu" in line and says in line]
        assert len(said) == 1, said  # one log line, not one a read
    finally:
        _stop_daemon(proc)
        ap.stop.set()
        stop.set()
        if writer.is_alive():
            writer.join(2)
        os.close(master)
        os.close(slave)


def test_an_oak_that_is_not_there_is_named_in_the_status_from_the_first_second(tmp_path: Path, notify_socket) -> None:
    """`vio run` with `kind = "oak"` and no camera plugged in: the driver logged 'no OAK device found' within a second,
    but `vio status` said 'sensors not delivering (starting)' for the 10 s the source thread waits for a booting OAK
    (an integrator's walk-through). The status names the driver's error as soon as the driver has one."""
    pytest.importorskip("depthai")
    _need_pipeline()
    _, notify_path = notify_socket
    ap = FakeAutopilot()
    ap.start()
    proc, log_path = _start_daemon(tmp_path, '[source]\nkind = "oak"', ap.port, notify_path)
    status = tmp_path / "status.json"
    seen: dict = {}

    def no_device() -> bool:
        try:
            st = json.loads(status.read_text())
        except (OSError, ValueError):
            return False
        if st["source"]["driver"].get("state") != "no_device":
            return False
        seen.update(st)
        return True

    try:
        assert _wait(no_device, 30), log_path.read_text()[-3000:]
        assert seen["uptime_s"] < 8, seen["uptime_s"]  # within the source thread's wait for a first frame
        assert any(w.startswith("sensors not delivering (no OAK device found") for w in seen["warnings"]), \
            seen["warnings"]
        assert ap.poses() == 0
    finally:
        _stop_daemon(proc)
        ap.stop.set()


def test_a_calibration_file_of_another_camera_is_said(tmp_path: Path, notify_socket) -> None:
    """`[source] calibration` names a file of another camera than the one streaming (its lens 1.4x longer: another
    model, another unit's import): the daemon flew with it unsaid, every distance off by that ratio (an integrator's
    walk-through). Now, once the source reports its own calibration, an error in the log and a status warning say
    what differs (state degraded), and the estimator stops for the run: no pose computed with it is sent. A
    recalibration of this camera (a few per cent) is no other camera."""
    import dataclasses

    from drivers.fake import FakeSource
    from vio.calibration import save_calibration

    _need_pipeline()
    own = FakeSource(width=320, height=200, fps=20, imu_rate_hz=200, duration_s=1.0, realtime=False).calibration()
    longer = dataclasses.replace(own, cam0=dataclasses.replace(own.cam0, fx=own.cam0.fx * 1.4, fy=own.cam0.fy * 1.4),
                                 cam1=dataclasses.replace(own.cam1, fx=own.cam1.fx * 1.4, fy=own.cam1.fy * 1.4))
    calib = tmp_path / "other.yaml"
    save_calibration(longer, calib)
    _, notify_path = notify_socket
    ap = FakeAutopilot()
    ap.start()
    proc, log_path = _start_daemon(tmp_path, f'[source]\nkind = "fake"\nwidth = 320\nheight = 200\n'
                                   f'calibration = "{calib}"', ap.port, notify_path)
    status = tmp_path / "status.json"
    says = (f"calibration: [source] calibration = '{calib}' is not this fake source's camera: its cam0 focal length fx "
            f"is {own.cam0.fx * 1.4:.1f} px, the camera's {own.cam0.fx:.1f} px (what it reports itself)")

    try:
        assert _wait(lambda: _status_warns(status, lambda w: w.startswith(says)), 30), \
            log_path.read_text()[-3000:]
        assert json.loads(status.read_text())["state"] != "running"
        assert sum(says in line for line in log_path.read_text().splitlines() if "ERROR" in line) == 1
        # and nothing computed with it reaches the autopilot: the estimator stops for the run
        time.sleep(1.5)
        sent = ap.poses()
        time.sleep(2.0)
        assert ap.poses() == sent, (sent, ap.poses())
        st = json.loads(status.read_text())
        assert not st["estimator"]["tracking"], st
        assert any(w.startswith("sensor error: calibration of another camera") for w in st["warnings"]), st
    finally:
        _stop_daemon(proc)
        ap.stop.set()
    from vio.calibration import other_camera_problem

    assert other_camera_problem(own, own) is None  # the camera's own, or a recalibration of it, is no other camera
    assert other_camera_problem(dataclasses.replace(own, cam0=dataclasses.replace(own.cam0, fx=own.cam0.fx * 1.03)),
                                own) is None


def test_a_stopped_daemon_s_status_does_not_say_tracking(tmp_path: Path, notify_socket) -> None:
    """SIGTERM while tracking: the status written at the stop (state 'stopped') kept the estimator's 'tracking': true,
    and `vio status --json` said it of a daemon gone for half an hour (an integrator's walk-through; docs/install.md:
    tracking is true only while the last state is under 1 s old). A stopped daemon tracks nothing."""
    _need_pipeline()
    _, notify_path = notify_socket
    ap = FakeAutopilot()
    ap.start()
    proc, log_path = _start_daemon(tmp_path, '[source]\nkind = "fake"\nwidth = 320\nheight = 200', ap.port,
                                   notify_path)
    status = tmp_path / "status.json"

    def tracking() -> bool:
        try:
            return json.loads(status.read_text())["estimator"]["tracking"] is True
        except (OSError, ValueError, KeyError):
            return False

    try:
        assert _wait(tracking, 60), log_path.read_text()[-3000:]
    finally:
        rc, _ = _stop_daemon(proc)
        ap.stop.set()
    assert rc == 0
    written = json.loads(status.read_text())
    assert written["state"] == "stopped" and written["estimator"]["tracking"] is False
    r = subprocess.run([sys.executable, "-m", "vio.app.cli", "status", "--json", "--file", str(status)],
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 4 and json.loads(r.stdout)["estimator"]["tracking"] is False, r.stdout
    # a status file written as the daemon stopped before this change says it too
    written["estimator"]["tracking"] = True
    status.write_text(json.dumps(written))
    r = subprocess.run([sys.executable, "-m", "vio.app.cli", "status", "--json", "--file", str(status)],
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 4 and json.loads(r.stdout)["estimator"]["tracking"] is False, r.stdout


def test_an_autopilot_serial_port_that_goes_away_is_a_link_down(tmp_path: Path) -> None:
    """`[mavlink] url` on a serial port (a pty with a flight controller's heartbeats on it) that goes away in flight:
    the output logged 'link error ... reconnecting' and then, while the port stayed gone, its link state was never
    looked at again: `vio status` said HEALTHY, 'link up' for as long as the port was gone (an integrator's
    walk-through). The link now goes down after link_timeout_s as for any silence: 'autopilot link lost' in the log,
    state degraded, `autopilot link down` in the status."""
    import pty
    import select
    import tty

    from pymavlink.dialects.v20 import common as mavlink2

    _need_pipeline()
    master, slave = pty.openpty()
    tty.setraw(slave)
    fds = [master, slave]
    stop = threading.Event()
    odometry: list[int] = []

    def autopilot() -> None:  # heartbeats every 0.3 s, disarmed; counts the poses received
        enc = mavlink2.MAVLink(None, srcSystem=1, srcComponent=1)
        parser = mavlink2.MAVLink(None)
        parser.robust_parsing = True
        while not stop.is_set():
            hb = mavlink2.MAVLink_heartbeat_message(mavlink2.MAV_TYPE_QUADROTOR, mavlink2.MAV_AUTOPILOT_ARDUPILOTMEGA,
                                                    0, 0, mavlink2.MAV_STATE_STANDBY, 3)
            try:
                os.write(master, hb.pack(enc))
                while select.select([master], [], [], 0.3)[0]:
                    for msg in parser.parse_buffer(os.read(master, 4096)) or []:
                        if msg.get_type() == "ODOMETRY":
                            odometry.append(1)
            except OSError:
                return

    ap = threading.Thread(target=autopilot, daemon=True)
    ap.start()
    cfg = tmp_path / "c.toml"
    cfg.write_text(f'[source]\nkind = "fake"\nwidth = 320\nheight = 200\n[mavlink]\n'
                   f'url = "{os.ttyname(slave)}:921600"\ncounter_file = ""\n'
                   f'[run]\nstatus_file = "{tmp_path / "status.json"}"\n')
    log_path = tmp_path / "daemon.log"
    with open(log_path, "w") as log:
        proc = subprocess.Popen([sys.executable, "-m", "vio.app.cli", "run", "--config", str(cfg)], cwd=REPO,
                                stdout=log, stderr=subprocess.STDOUT, env={**os.environ, "PYTHONUNBUFFERED": "1"})
    status = tmp_path / "status.json"

    def read() -> dict:
        return _read_status(status)

    try:
        assert _wait(lambda: read().get("mavlink", {}).get("state") == "up" and len(odometry) > 5, 60), \
            log_path.read_text()[-3000:]
        stop.set()
        ap.join(2)
        for fd in fds:  # the port goes away (a USB flight controller unplugged)
            os.close(fd)
        fds = []
        t_gone = time.monotonic()
        assert _wait(lambda: read().get("mavlink", {}).get("state") == "down", 15), \
            (read().get("mavlink"), log_path.read_text()[-2000:])
        assert time.monotonic() - t_gone < 8  # link_timeout_s (3 s) and a status period or two
        st = read()
        assert st["state"] != "running" and "autopilot link down" in st["warnings"], st["warnings"]
        assert "autopilot link lost: no heartbeat for 3.0 s" in log_path.read_text()
    finally:
        stop.set()
        for fd in fds:
            os.close(fd)
        _stop_daemon(proc)


def test_the_instance_lock_is_one_path_whether_or_not_the_status_folder_exists(tmp_path) -> None:
    """The lock fell back to the temp folder when the status folder did not exist yet; the first daemon's status
    write then made the folder and a second daemon locked another path and ran (a review's finding)."""
    from vio import VioError
    from vio.app.daemon.service import single_instance
    from vio.config import config_from_dict

    cfg = config_from_dict({"run": {"status_file": str(tmp_path / "not-yet" / "status.json")}})
    first = single_instance(cfg)
    assert first is not None and (tmp_path / "not-yet" / "status.json.lock").read_text().strip() == str(os.getpid())
    with pytest.raises(VioError, match=rf"another vio run \(pid {os.getpid()}\)"):
        single_instance(cfg)
    first.close()  # the first one ends: the next starts
    single_instance(cfg).close()


def test_a_second_daemon_sending_to_the_same_mavlink_endpoint_is_refused(tmp_path) -> None:
    """Two `vio run` with their own configurations and status files (the status-file lock cannot see them) but one
    [mavlink] url both sent to the autopilot as component 197, their poses interleaved. The second is refused at
    start (exit 3, one line naming the first's pid), also when it names the endpoint otherwise (localhost); another
    port is another endpoint; the endpoint is free again once the first ends."""
    from vio import VioError

    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:  # a port nothing else here is told to use
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]

    def config(name: str, host: str, p: int) -> Path:
        path = tmp_path / f"{name}.toml"
        path.write_text(f'[source]\nkind = "fake"\n[mavlink]\nurl = "udpout:{host}:{p}"\n[run]\nstatus_file = '
                        f'"{tmp_path / name / "status.json"}"\n')
        return path

    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")])}
    log_path = tmp_path / "first.log"
    with open(log_path, "w") as log_file:
        first = subprocess.Popen([sys.executable, "-m", "vio.app.cli", "run", "--config",
                                  str(config("first", "127.0.0.1", port))], cwd=REPO, env=env, stdout=log_file,
                                 stderr=subprocess.STDOUT)
    try:
        assert _wait(lambda: "kestrel-vio starting" in log_path.read_text(), 60), log_path.read_text()
        second = subprocess.run([sys.executable, "-m", "vio.app.cli", "run", "--config",
                                 str(config("second", "localhost", port))], cwd=REPO, env=env, capture_output=True,
                                text=True, timeout=30)  # refused at once; without the lock it ran on
        assert second.returncode == 3, second.stdout + second.stderr
        lines = second.stderr.strip().splitlines()
        assert len(lines) == 1 and f"another vio run (pid {first.pid}) sends to the autopilot at udpout:127.0.0.1:" \
            f"{port}" in lines[0], second.stderr
        assert f"one started by hand: kill {first.pid}" in lines[0]  # not only the service's systemctl
        assert not (tmp_path / "second" / "status.json").exists()
        from vio.app.daemon.service import output_endpoint_lock
        from vio.app.endpoint_lock import output_endpoint_key

        other = output_endpoint_lock(config_from_dict({"mavlink": {"url": f"udpout:127.0.0.1:{port + 1}"}}))
        assert other is not None  # another port: another endpoint
        other.close()
    finally:
        _stop_daemon(first)
    lock = output_endpoint_lock(config_from_dict({"mavlink": {"url": f"udpout:127.0.0.1:{port}"}}))
    assert lock is not None  # the first one ended: the endpoint is free
    with pytest.raises(VioError, match=rf"another vio [a-z -]+ \(pid {os.getpid()}\)"):
        output_endpoint_lock(config_from_dict({"mavlink": {"url": f"udpout:localhost:{port}"}}))
    lock.close()
    assert output_endpoint_key(f"udp:0.0.0.0:{port}") == f"udpin:*:{port}"  # mavutil's udp: is udpin:


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="the endpoint lock is Linux's abstract sockets")
def test_a_replay_and_a_daemon_never_send_to_one_autopilot_together(tmp_path, v101_path) -> None:
    """`vio replay --mavlink` took no endpoint lock: a replay towards the autopilot of a running `vio run` sent a
    recording's poses as component 197 between the live ones. Each now refuses the other at start, one line naming
    the other's pid and command: the replay exits 1 (as its other refusals) before any output file is made, the
    daemon exits 3 (as for another daemon)."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:  # a port nothing else here is told to use
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    cfg = tmp_path / "run.toml"
    cfg.write_text(f'[source]\nkind = "fake"\n[mavlink]\nurl = "udpout:127.0.0.1:{port}"\n[run]\nstatus_file = '
                   f'"{tmp_path / "status.json"}"\n')
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")])}
    vio = [sys.executable, "-m", "vio.app.cli"]
    replay = [*vio, "replay", str(v101_path), "--no-progress", "-o", str(tmp_path / "replay.tum"), "--mavlink",
              f"udpout:localhost:{port}"]
    log_path = tmp_path / "daemon.log"
    with open(log_path, "w") as log_file:
        daemon = subprocess.Popen([*vio, "run", "--config", str(cfg)], cwd=REPO, env=env, stdout=log_file,
                                  stderr=subprocess.STDOUT)
    try:
        assert _wait(lambda: "kestrel-vio starting" in log_path.read_text(), 60), log_path.read_text()
        refused = subprocess.run(replay, cwd=REPO, env=env, capture_output=True, text=True, timeout=60)
        assert refused.returncode == 1, refused.stdout + refused.stderr
        lines = refused.stderr.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith(
            f"vio replay: error: another vio run (pid {daemon.pid}) sends to the autopilot at udpout:127.0.0.1:{port} "
            f"(--mavlink udpout:localhost:{port})"), refused.stderr
        assert not (tmp_path / "replay.tum").exists()  # refused before any output
    finally:
        _stop_daemon(daemon)
    from vio import VioError
    from vio.app.endpoint_lock import mavlink_endpoint_lock

    def replay_holds_it() -> bool:
        try:
            mavlink_endpoint_lock(f"udpout:127.0.0.1:{port}", "probe", "-").close()
        except VioError:
            return True
        return False

    first = subprocess.Popen(replay, cwd=REPO, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        assert _wait(replay_holds_it, 60)
        first.send_signal(signal.SIGSTOP)  # the replay holds the endpoint as long as the daemon takes to start
        second = subprocess.run([*vio, "run", "--config", str(cfg)], cwd=REPO, env=env, capture_output=True,
                                text=True, timeout=60)
        assert second.returncode == 3, second.stdout + second.stderr
        assert f"another vio replay --mavlink (pid {first.pid}) sends to the autopilot at udpout:127.0.0.1:{port}" \
            in second.stderr and f"kill {first.pid}" in second.stderr, second.stderr
    finally:
        first.kill()
        first.wait()


def test_output_endpoint_key_is_what_two_daemons_would_share(tmp_path) -> None:
    """The lock keyed listening URLs on their address, so udpin:0.0.0.0:14550 and udpin:127.0.0.1:14550 (both bind:
    mavutil sets SO_REUSEADDR) ran side by side, each getting some of the autopilot's packets and sending as
    component 197 (a QA walk-through). A listener is its protocol and port; a sender its peer; a serial device its
    real path, whatever the baud rate or the link that names it."""
    from vio import VioError
    from vio.app.endpoint_lock import output_endpoint_key as key
    from vio.config import config_from_dict

    assert key("udpin:0.0.0.0:14550") == key("udpin:127.0.0.1:14550") == key("udp:192.168.1.5:14550")
    assert key("tcpin:0.0.0.0:5760") == key("tcpin:127.0.0.1:5760") != key("tcpin:0.0.0.0:5761")
    assert key("udpin:0.0.0.0:14550") != key("tcpin:0.0.0.0:14550")  # another protocol, another port
    assert key("udpout:localhost:14550") == key("udpout:127.0.0.1:14550") == "udpout:127.0.0.1:14550"
    assert key("udpout:10.0.0.2:14550") != key("udpout:10.0.0.3:14550")  # two autopilots
    assert key("udpout:127.0.0.1:14550") not in (key("tcp:127.0.0.1:14550"), key("udpbcast:127.0.0.1:14550"),
                                                 key("udpin:127.0.0.1:14550"))
    assert key("tcp:[::1]:5760") == key("tcp:0:0:0:0:0:0:0:1:5760")
    dev = tmp_path / "ttyACM0"
    dev.write_text("")
    (tmp_path / "by-id").symlink_to(dev)
    assert key(f"/dev/../{dev}:921600") == key(f"/dev/../{tmp_path}/by-id:57600") == f"serial:{dev}"
    assert key("/dev/ttyAMA0") == "serial:/dev/ttyAMA0" != key("/dev/ttyAMA1:921600")
    if sys.platform.startswith("linux"):
        from vio.app.daemon.service import output_endpoint_lock

        first = output_endpoint_lock(config_from_dict({"mavlink": {"url": "udpin:0.0.0.0:14555"}}))
        try:
            with pytest.raises(VioError, match=rf"another vio [a-z -]+ \(pid {os.getpid()}\) sends to the autopilot at "
                               "udpin:\\*:14555"):
                output_endpoint_lock(config_from_dict({"mavlink": {"url": "udpin:127.0.0.1:14555"}}))
        finally:
            first.close()


def test_vio_run_flies_without_an_output_folder_it_cannot_write(tmp_path, monkeypatch) -> None:
    """A state folder gone read-only made the watchdog's restart exit 3 (configuration error), which systemd never
    restarts (a review's finding): `vio run` says it and runs without that output; `vio config check` still
    fails on it."""
    import vio.app.daemon.service as svc_mod
    from vio import VioError
    from vio.config import config_from_dict

    cfg = config_from_dict({"run": {"trajectory_file": str(tmp_path / "t.tum")}})
    monkeypatch.setattr(svc_mod.os, "access", lambda path, mode: False)
    said: list[str] = []
    svc_mod.check_run_config(cfg, warn=said.append)
    assert said and "is not writable: running without it" in said[0]
    with pytest.raises(VioError, match="is not writable"):
        svc_mod.check_run_config(cfg)


def test_an_output_name_over_the_file_systems_limit_is_a_configuration_error(tmp_path) -> None:
    """A [run] path with a name over 255 bytes: a record_dir's was an internal error (Path.exists raised
    ENAMETOOLONG), a status file's passed the check and failed at every write in flight."""
    from vio import VioError
    from vio.app.daemon.service import check_run_config
    from vio.config import config_from_dict

    long = "x" * 300
    for key, value in (("record_dir", tmp_path / long), ("status_file", tmp_path / long),
                       ("trajectory_file", tmp_path / long / "t.tum")):
        cfg = config_from_dict({"run": {key: str(value)}})
        with pytest.raises(VioError, match=rf"\[run\] {key}: the name 'x{{24}}'... is 300 bytes long, over the 255"):
            check_run_config(cfg, warn=lambda _m: None)


def test_vio_run_reads_the_loop_vocabulary_once(tmp_path, monkeypatch) -> None:
    """`vio run` read a [loop] vocabulary file twice at start: in its configuration check, and again when the loop
    stage started. The check's vocabulary is now the one the loop stage uses."""
    import shutil

    import vio.app.daemon.service as svc_mod
    from drivers.fake import FakeSource
    from vio.app.cli import main
    from vio.loop.vocabulary import DEFAULT_PATH, Vocabulary

    voc = tmp_path / "voc.npz"
    shutil.copyfile(DEFAULT_PATH, voc)
    cfg = tmp_path / "c.toml"
    cfg.write_text(f'[source]\nkind = "fake"\n[run]\nstatus_file = ""\n[mavlink]\nurl = ""\n'
                   f'[loop]\nenabled = true\nvocabulary = "{voc}"\n')
    loaded: list = []
    real_load = Vocabulary.load

    def load(path=None):
        loaded.append(real_load(path))
        return loaded[-1]

    used: list = []

    def run(self) -> int:  # the daemon's start, up to the loop stage (which starts with the calibration)
        self._start_loop(FakeSource(width=96, height=64).calibration())
        used.append(self.loop.closer.vocab)
        self.loop.close()
        return 0

    monkeypatch.setattr(Vocabulary, "load", staticmethod(load))
    monkeypatch.setattr(svc_mod.Service, "run", run)
    monkeypatch.setattr(svc_mod.signal, "signal", lambda *a: None)  # run() installs handlers: not in pytest
    assert main(["run", "--config", str(cfg)]) == 0
    assert len(loaded) == 1 and used == [loaded[0]] and used[0] is loaded[0]


def test_a_stop_signal_never_waits_for_the_lock_the_main_loop_holds() -> None:
    """`vio run` hung for 10 s after SIGTERM once (killed, no status written): the handler, running in the main thread,
    called stop.set() while that thread was inside stop.wait() holding the Event's lock. The handler now hands the
    stop to a thread of its own; here it is called with the lock held, as the signal would find it."""
    from drivers.signals import stop_on_signal

    stop = threading.Event()
    got = []
    handler = stop_on_signal(lambda signum: (got.append(signum), stop.set()))
    done = threading.Event()
    with stop._cond:  # what stop.wait() holds around its wait
        threading.Thread(target=lambda: (handler(signal.SIGTERM, None), done.set()), daemon=True).start()
        assert done.wait(2.0), "the handler blocked on the Event's lock"
    assert stop.wait(2.0) and got == [signal.SIGTERM]


def test_a_recording_name_taken_by_an_earlier_mcap_is_not_reused(tmp_path: Path, monkeypatch) -> None:
    """A board without a real-time clock restarts at the same UTC second after a power cut: the new MCAP replaced
    the last flight's <time>.mcap, because only a folder of that name was looked for (a QA sweep)."""
    import time as _time

    from vio.app.daemon.outputs import _fresh_record_dir

    monkeypatch.setattr(_time, "gmtime", lambda *a: _time.struct_time((2026, 12, 6, 14, 7, 45, 6, 340, 0)))
    first = _fresh_record_dir(str(tmp_path))
    first.with_suffix(".mcap").write_bytes(b"an earlier flight")
    second = _fresh_record_dir(str(tmp_path))
    assert second != first and not second.with_suffix(".mcap").exists() and not second.exists()
    first.mkdir()  # a EuRoC folder of that name: the same rule
    assert _fresh_record_dir(str(tmp_path)) == second


def test_config_check_refuses_daemon_outputs_over_what_it_reads_or_into_the_recording(tmp_path, capsys):
    """`[run] trajectory_file` over `[source] calibration`, or inside the EuRoC recording the daemon replays (a
    csv of its mav0/), passed `vio config check`: the pose log would have replaced the calibration or the
    recording's data (a QA sweep's finding). The same for the status file, the reset counter file and the
    recording folder."""
    from vio.app.cli import main
    from vio.calibration import save_calibration
    from vio.io.euroc import EurocDataset
    from vio.sim.generate import SimConfig, simulate

    data = tmp_path / "flight"
    simulate(data, SimConfig(duration_s=1.0, width=376, height=240, variant="clean"), progress=False)
    rig = tmp_path / "rig.yaml"
    save_calibration(EurocDataset(data).calibration, rig)
    src = f"[source]\nkind = 'euroc'\ndataset = '{data}'\ncalibration = '{rig}'\n"
    cam_csv = data / "mav0" / "cam0" / "data.csv"
    over_rig = "[run] trajectory_file would be written over [source] calibration"
    for run, says in ((f"trajectory_file = '{rig}'", over_rig),
                      (f"trajectory_file = '{cam_csv}'", "[run] trajectory_file would be written into the recording"),
                      (f"status_file = '{data / 'mav0' / 'status.json'}'", "into the recording"),
                      (f"record_dir = '{data / 'mav0' / 'rec'}'", "[run] record_dir would be written into")):
        cfg = tmp_path / "c.toml"
        cfg.write_text(f"{src}[run]\n{run}\n")
        assert main(["config", "check", str(cfg)]) == 3, run
        assert says in capsys.readouterr().err, run
    before = (rig.read_bytes(), cam_csv.read_bytes())
    cfg.write_text(f"{src}[run]\ntrajectory_file = '{tmp_path / 'poses.tum'}'\nstatus_file = '{tmp_path / 's.json'}'\n")
    assert main(["-q", "config", "check", str(cfg)]) == 0, capsys.readouterr().err
    assert (rig.read_bytes(), cam_csv.read_bytes()) == before


def test_the_warning_for_held_back_simulated_poses_reads_as_a_sentence() -> None:
    """`vio run` with `[source] kind = "fake"` and no autopilot heard: the status said "... is another flight's and
    the no autopilot heartbeat says it is disarmed" (a first-time user's walk-through of docs/first-flight.md)."""
    from vio.app.daemon.service import replay_refusal_warning

    assert replay_refusal_warning("fake", "unheard") == (
        "poses not sent: [source] kind = 'fake' is another flight's and no autopilot heartbeat says it is disarmed")
    assert replay_refusal_warning("euroc", "armed") == (
        "poses not sent: [source] kind = 'euroc' is another flight's and the autopilot says it is armed")


def test_a_status_or_pose_log_path_that_is_a_folder_is_refused_and_an_empty_one_said(tmp_path: Path, capsys) -> None:
    """`[run] status_file` naming a folder passed `vio config check` and `vio run`: the status was never written
    ('Is a directory', logged once), its lock went beside it as FOLDER.lock, and `vio status` said only 'cannot read
    status: Is a directory'. An empty status_file (no status written) made `vio status --config` read '.'."""
    from vio.app.cli import main

    (tmp_path / "state").mkdir()
    for key in ("status_file", "trajectory_file"):
        cfg = tmp_path / f"{key}.toml"
        cfg.write_text(f'[source]\nkind = "fake"\n[run]\n{key} = "{tmp_path / "state"}"\n')
        capsys.readouterr()
        assert main(["config", "check", str(cfg)]) == 3
        err = capsys.readouterr().err
        assert f"[run] {key} = '{tmp_path / 'state'}': is a folder; give a file name in it" in err, err
    cfg = tmp_path / "none.toml"
    cfg.write_text('[run]\nstatus_file = ""\n')
    assert main(["status", "--config", str(cfg)]) == 4
    assert f"UNKNOWN ([run] status_file is empty in {cfg}: a daemon with this configuration writes no status" in \
        capsys.readouterr().err


def test_a_counter_file_that_is_a_folder_is_refused_at_start(tmp_path: Path, capsys) -> None:
    """`[mavlink] counter_file` naming a folder passed `vio config check` and `vio run`: the reset_counter was never
    kept, each start took a random one and said so only as a warning. Refused as `[run] status_file` is; an empty
    counter_file (a random start, by choice) still passes."""
    from vio.app.cli import main

    (tmp_path / "state").mkdir()
    cfg = tmp_path / "c.toml"
    cfg.write_text(f'[source]\nkind = "fake"\n[run]\nstatus_file = ""\n'
                   f'[mavlink]\ncounter_file = "{tmp_path / "state"}"\n')
    said = f"[mavlink] counter_file = '{tmp_path / 'state'}': is a folder; give a file name in it"
    assert main(["config", "check", str(cfg)]) == 3
    assert said in capsys.readouterr().err
    assert main(["run", "--config", str(cfg)]) == 3  # refused before any sensor starts
    assert said in capsys.readouterr().err
    cfg.write_text('[source]\nkind = "fake"\n[run]\nstatus_file = ""\n[mavlink]\ncounter_file = ""\n')
    assert main(["config", "check", str(cfg)]) == 0


def test_the_reason_for_no_pose_before_the_start_fits_a_start_in_flight_too() -> None:
    """Before its first pose the status said "keep the camera still", which a daemon restarted in flight (it starts
    moving within about a second, docs/autopilot.md "A restart in flight") cannot do."""
    from vio.app.daemon.status import _not_tracking_reason
    from vio.backend.synthetic import synthetic_calibration
    from vio.estimator import Estimator

    h = Estimator(synthetic_calibration()).health()
    assert not h.initialized
    reason = _not_tracking_reason(h, camera_ok=True)
    assert reason.startswith("not initialised yet") and "still" in reason and "motion" in reason, reason



def test_the_mavlink_counts_are_not_doubled_by_a_close_during_a_status_read(monkeypatch) -> None:
    """`vio status` reads the output thread's counts from the main thread (OutputWorker.link(), .sent) while the
    output thread may close a failed output and add its counts to the closed ones. Read in between (the open output
    taken, then its counts added to the closed ones before these were summed), its counts came twice: 2 poses sent
    read 4. The close and the read are one step each now."""
    from drivers.mavlink_out import MavlinkOutput
    from vio.app.daemon import outputs
    from vio.app.daemon.outputs import OutputWorker
    from vio.config import MavlinkConfig

    sink = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sink.bind(("127.0.0.1", 0))
    w = OutputWorker(threading.Event(), LatestState(), lambda: MavlinkOutput(
        MavlinkConfig(mount="rpy"), f"udpout:127.0.0.1:{sink.getsockname()[1]}"), "", 1.0)
    t0 = time.monotonic_ns()
    health = outputs._mavlink_health

    def closed_meanwhile(mav):  # the output thread closes the output while the status thread reads it
        h = health(mav)
        closer = threading.Thread(target=w._close_mav, kwargs={"final": False})
        closer.start()
        closer.join(2.0)
        return h

    try:
        w._ensure_mavlink()
        for k in range(2):
            w._send(w._checked(NavState(t0 + k * 100_000_000, np.eye(4), np.zeros(3))))
        assert w.link()["states_in"] == 2
        monkeypatch.setattr(outputs, "_mavlink_health", closed_meanwhile)
        h = w.link()
        assert h["states_in"] == 2, h
        assert w.mav is None and w.link()["states_in"] == 2  # closed: its counts once, among the closed ones
    finally:
        w.close()
        sink.close()


@pytest.mark.parametrize(("bad", "says"), [(np.nan, "NaN"), (1e31, "beyond 1e30"), ("stamp", "time stamp")])
def test_a_not_finite_estimate_shows_in_the_status_as_no_pose_sent(tmp_path: Path, bad: float | str,
                                                                   says: str) -> None:
    """The estimator tracks but its covariance is NaN (or finite beyond 1e30, which float32 fields cannot carry):
    the MAVLink output sends nothing (a loss of tracking, one error line), while the status read 'running', quality
    100, nothing said. It says why now, quality 0 (what the autopilot gets), and running again once the estimate is
    whole. The status named only a NaN, an infinite value or a negative variance for a 1e31 one; a stamp before 0
    (time_usec is unsigned) failed to pack, dropped as a send error with nothing in the status."""
    from drivers.mavlink_out import MavlinkOutput

    status = tmp_path / "status.json"
    cfg = config_from_dict({"run": {"status_file": str(status)}, "source": {"kind": "fake"},
                            "mavlink": {"mount": "rpy"}})
    sick = threading.Event()
    sick.set()

    class NotFinite(ScriptedEstimator):
        def feed_frame(self, f: StereoFrame) -> NavState | None:
            st = super().feed_frame(f)
            if st is not None and sick.is_set():
                # a stamp before the clock's zero: time_usec is unsigned (it failed to pack, the status said nothing)
                st = dataclasses.replace(st, t_ns=-st.t_ns) if bad == "stamp" else \
                    dataclasses.replace(st, cov_pose=np.full((6, 6), bad))
            return st

    ap = FakeAutopilot()
    ap.start()
    url = f"udpout:127.0.0.1:{ap.port}"
    svc = Service(cfg, source_factory=lambda: _started(ScriptedSource([], threading.Event(), [])),
                  estimator_factory=lambda c: NotFinite(c, []),
                  mavlink_factory=lambda: MavlinkOutput(cfg.mavlink, url).start(), notifier=SdNotifier(""))
    runner = threading.Thread(target=svc.run)
    runner.start()
    try:
        assert _wait(lambda: _status_warns(status, lambda w: "poses not sent" in w), 5.0), \
            {k: _read_status(status).get(k) for k in ("state", "warnings", "estimator")}
        st = _read_status(status)
        assert any(says in w for w in st["warnings"]), st["warnings"]
        assert st["state"] != "running" and st["estimator"]["quality"] == 0, (st["state"], st["estimator"])
        assert st["mavlink"]["states_not_finite"] > 0 and ap.poses() == 0
        sick.clear()
        assert _wait(lambda: _read_status(status).get("state") == "running", 3.0), _read_status(status)
        assert _read_status(status)["estimator"]["quality"] == 100 and ap.poses() > 0
    finally:
        svc.request_stop(signal.SIGTERM)
        runner.join(5.0)
        ap.stop.set()
    assert not runner.is_alive()


def test_the_loop_output_takes_the_mavlink_outputs_turn_of_a_start_in_flight() -> None:
    """The loop output takes the MAVLink output's turn and shift of a start in flight out of a correction into a
    map's frame (tests/test_mavlink.py::test_a_start_in_flight_relocalised_in_the_map_sends_the_maps_frame_not_
    turned_twice): the daemon wires the one to the other."""
    cfg = config_from_dict({"source": {"kind": "fake"}, "loop": {"enabled": True, "output": "jump"}})
    svc = Service(cfg, source_factory=lambda: ScriptedSource([], threading.Event(), []),
                  estimator_factory=lambda c: ScriptedEstimator(c, []), mavlink_factory=RecordingMavlink,
                  notifier=SdNotifier(""))
    assert svc._loop_output is not None and svc._loop_output.frame_turn == svc.output.frame_turn
    assert svc._loop_output.frame_pending == svc.output.frame_pending
    assert svc.output.frame_turn() is None  # no output open, or one without a turn

    class Turned(RecordingMavlink):
        def world_frame_turn(self) -> np.ndarray:
            return np.diag([-1.0, -1.0, 1.0, 1.0])

    svc.output.mav = Turned()
    np.testing.assert_array_equal(svc._loop_output.frame_turn(), np.diag([-1.0, -1.0, 1.0, 1.0]))


def test_the_map_checkpoint_is_saved_with_the_mavlink_outputs_turn_of_a_start_in_flight(tmp_path: Path) -> None:
    """The daemon hands the MAVLink output's turn of a start in flight to the map save (LoopCloser.save_map's
    world_turn: tests/test_loop.py::test_a_map_of_a_start_in_flight_is_saved_in_the_autopilots_frame): a checkpoint
    in the process's own frame put the next restart's relocalised poses off by this one's turn."""
    cfg = config_from_dict({"source": {"kind": "fake"}, "loop": {"enabled": True, "output": "jump"},
                            "map": {"save": str(tmp_path / "m.npz")}})
    svc = Service(cfg, source_factory=lambda: ScriptedSource([], threading.Event(), []),
                  estimator_factory=lambda c: ScriptedEstimator(c, []), mavlink_factory=RecordingMavlink,
                  notifier=SdNotifier(""))
    turn = np.diag([-1.0, -1.0, 1.0, 1.0])

    class Turned(RecordingMavlink):
        def world_frame_turn(self) -> np.ndarray:
            return turn

    got: dict = {}

    class Closer:
        def save_map(self, path, prune_m=0.0, prune_deg=0.0, checkpoint=None, **kw):
            got.update(kw)
            return {"path": str(path), "keyframes": 1}

    svc.output.mav = Turned()
    svc._save_checkpoint(Closer())
    np.testing.assert_array_equal(got.get("world_turn"), turn)


def test_no_map_checkpoint_is_written_while_a_start_in_flights_frame_is_to_be_chosen(tmp_path: Path) -> None:
    """Started in flight, the MAVLink output chooses its frame (the turn and shift into the autopilot's) at its first
    tracked pose; before that its world_frame_turn is None, and a checkpoint written then was in the flight's own
    frame while every later save is in the autopilot's: a restart in flight loading it (the autopilot's frame by
    assumption) sent poses off by the turn. No checkpoint is written until the frame is chosen (one of a loaded map
    is in that map's frame: written), and the loop stage tries again at the next interval."""
    cfg = config_from_dict({"source": {"kind": "fake"}, "loop": {"enabled": True, "output": "jump"},
                            "map": {"save": str(tmp_path / "m.npz")}})
    svc = Service(cfg, source_factory=lambda: ScriptedSource([], threading.Event(), []),
                  estimator_factory=lambda c: ScriptedEstimator(c, []), mavlink_factory=RecordingMavlink,
                  notifier=SdNotifier(""))

    class Pending(RecordingMavlink):
        def world_frame_turn(self) -> None:
            return None

        def frame_pending(self) -> bool:
            return True

    saved: list = []

    class Closer:
        map_keyframes = 0

        def save_map(self, path, prune_m=0.0, prune_deg=0.0, checkpoint=None, **kw):
            saved.append(kw)
            return {"path": str(path), "keyframes": 1}

    svc.output.mav = Pending()
    assert svc._save_checkpoint(Closer()) is False and not saved
    loaded = Closer()
    loaded.map_keyframes = 5
    svc._save_checkpoint(loaded)
    assert len(saved) == 1 and saved[0]["world_turn"] is None
    svc.output.mav = None  # closed after a failure: the frame it kept is still to be chosen
    svc.output._frame = (None, True)
    assert svc._save_checkpoint(Closer()) is False and len(saved) == 1


def test_a_checkpoint_not_written_is_tried_again_at_the_next_interval() -> None:
    """A checkpoint callback that wrote nothing (returns False: the frame is to be chosen) leaves the map to
    checkpoint: the next interval tries again, without waiting for a new keyframe (a hovering vehicle makes none)."""
    from vio.app.loop_worker import LoopWorker

    calls: list[int] = []

    def checkpoint(closer) -> bool | None:
        calls.append(1)
        return False if len(calls) < 3 else None

    closer = type("C", (), {"map_keyframes": 0, "finish": lambda self: None})()
    w = LoopWorker(closer, checkpoint=checkpoint, checkpoint_s=0.05)
    try:
        w._processed = 1  # one keyframe processed since the start
        assert _wait(lambda: w.checkpoints == 1, 2.0), (len(calls), w.checkpoints)
        time.sleep(0.2)
        assert len(calls) == 3 and w.checkpoints == 1
    finally:
        w.close(wait=True, timeout_s=1.0)


def test_config_check_refuses_an_output_folder_in_a_pseudo_file_system(tmp_path, capsys) -> None:
    """`[run] record_dir = "/proc/kestrel"` passed `vio config check` as root (os.access says yes to root in /proc and
    in read-only folders), and the recorder failed once the sensors were up. The folder is tried with a file made
    and removed there, as `vio record` does."""
    from vio.app.cli import main

    if not Path("/proc/self").is_dir():
        pytest.skip("no /proc here")
    for key, value in (("record_dir", "/proc/kestrel"), ("trajectory_file", "/proc/kestrel.tum")):
        cfg = tmp_path / f"{key}.toml"
        cfg.write_text(f'[source]\nkind = "fake"\n[run]\n{key} = "{value}"\nstatus_file = "{tmp_path / "s.json"}"\n')
        assert main(["config", "check", str(cfg)]) == 3, key
        err = capsys.readouterr().err
        assert f"[run] {key} = '{value}': folder /proc cannot be written" in err, err
