"""The onboard daemon: buffers, sd_notify, status file, fault recovery, and `vio run` end to end.

The in-process tests use tiny stand-ins for the source, estimator and MAVLink output so they exercise the
daemon's own logic in a couple of seconds; the subprocess tests run the real `vio run` with the fake
source, the real estimator and a fake autopilot on loopback UDP.
"""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

from vio.config import config_from_dict
from vio.sdnotify import SdNotifier, watchdog_interval_s
from vio.service import LatestState, SensorBuffer, Service, write_status_file
from vio.status import EXIT_HEALTHY, EXIT_NOT_RUNNING, EXIT_UNHEALTHY, evaluate, format_status
from vio.types import ImuSample, NavState, StereoFrame

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


def test_latest_state_keeps_only_the_newest() -> None:
    from vio.service import Output

    box = LatestState()
    for k in range(3):
        box.publish(Output(NavState(k, np.eye(4), np.zeros(3)), k, k))
    seq, out = box.wait_newer(0, 0.0)
    assert out.state.t_ns == 2
    assert box.wait_newer(seq, 0.0)[1] is None


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
    assert evaluate(_status(healthy=False, state="degraded"), 1001.0, 3.0)[0] == EXIT_UNHEALTHY
    assert evaluate(_status(), 1010.0, 3.0)[0] == EXIT_NOT_RUNNING  # stale file: daemon dead or hung
    assert evaluate(_status(state="stopped"), 1000.5, 3.0)[0] == EXIT_NOT_RUNNING


def test_status_text_names_what_a_person_needs() -> None:
    text = format_status(_status(warnings=["autopilot link down"]), "HEALTHY", 1000.5)
    for needle in ("HEALTHY", "up 1h02m05s", "camera 20.0 Hz", "IMU 200 Hz", "tracks 140", "resets 1",
                   "link up", "p50 41.0 ms", "WARNING   autopilot link down"):
        assert needle in text, needle


def test_status_cli_exit_codes(tmp_path: Path) -> None:
    from vio.cli import main

    path = tmp_path / "status.json"
    assert main(["status", "--file", str(path)]) == EXIT_NOT_RUNNING
    write_status_file(path, _status(written_unix=time.time()))
    assert main(["status", "--file", str(path)]) == EXIT_HEALTHY
    write_status_file(path, _status(written_unix=time.time(), healthy=False))
    assert main(["status", "--file", str(path)]) == EXIT_UNHEALTHY
    path.write_text("{not json")
    assert main(["status", "--file", str(path)]) == EXIT_NOT_RUNNING


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

    def calibration(self) -> str:
        return "calib"

    def health(self) -> dict:
        return {"name": "scripted", "k": self.k}

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


class ScriptedEstimator:
    """One tracked NavState per frame; raises once when told to, as a gtsam failure would."""

    def __init__(self, calib: str, explode: list) -> None:
        assert calib == "calib"
        self.explode = explode
        self.n = 0
        self.n_tracks = 99

    def feed_imu(self, s: ImuSample) -> None:
        return None

    def feed_frame(self, f: StereoFrame) -> NavState:
        if self.explode:
            self.explode.pop()
            raise RuntimeError("Indeterminant linear system")
        self.n += 1
        T = np.eye(4)
        T[0, 3] = 0.01 * self.n
        return NavState(f.t_ns, T, np.zeros(3))


@dataclass
class MavStats:
    states_sent: int = 0
    autopilot_heartbeats: int = 3


class RecordingMavlink:
    """Shaped like drivers.mavlink_out.MavlinkOutput: send_state, poll, close, link_up, stats."""

    link_up = True

    def __init__(self) -> None:
        self.states: list[NavState] = []
        self.closed = False
        self.stats = MavStats()

    def send_state(self, s: NavState) -> None:
        self.states.append(s)
        self.stats.states_sent += 1

    def poll(self) -> None:
        return None

    def close(self) -> None:
        self.closed = True


def _wait(cond, timeout_s: float) -> bool:
    t0 = time.monotonic()
    while time.monotonic() - t0 < timeout_s:
        if cond():
            return True
        time.sleep(0.02)
    return False


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
    finally:
        t0 = time.monotonic()
        svc.request_stop(signal.SIGTERM)
        runner.join(5.0)
    assert not runner.is_alive() and time.monotonic() - t0 < 2.0
    assert events.count("start") >= 3 and events[-1] == "stop"  # failed boot open, first run, reopen
    assert mavs[0].closed
    assert json.loads((tmp_path / "status.json").read_text())["state"] == "stopped"
    assert len((tmp_path / "traj.tum").read_text().splitlines()) >= 10


def _started(src: ScriptedSource) -> ScriptedSource:
    src.start()
    return src


# ------------------------------------------------------------------------------ `vio run` subprocess

def test_run_config_error_exits_3(tmp_path: Path) -> None:
    bad = tmp_path / "config.toml"
    bad.write_text('[source]\nkind = "euroc"\ndatset = "/nowhere"\n')
    r = subprocess.run([sys.executable, "-m", "vio.cli", "run", "--config", str(bad)], capture_output=True,
                       text=True, timeout=60)
    assert r.returncode == 3
    assert "configuration error" in r.stderr and "datset" in r.stderr and "Traceback" not in r.stderr
    r = subprocess.run([sys.executable, "-m", "vio.cli", "run", "--config", str(tmp_path / "absent.toml")],
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 3 and "absent.toml" in r.stderr
