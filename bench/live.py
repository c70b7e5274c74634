"""Latency and memory of the onboard daemon: `vio run` plays a dataset as a live source (EuRoC playback
on the host clock) and sends ODOMETRY to a loopback "autopilot" in this process, while this process
samples the daemon's resident memory.

Why the daemon and not `vio replay`: the replay keeps every state for its evaluation, so its memory grows
by design; the daemon keeps nothing, and its path (source thread, bounded queues, estimator thread, output
thread at `mavlink.rate_hz`) is the one whose frame-to-autopilot latency matters. The EuRoC source stamps
each sample with the host CLOCK_MONOTONIC instant at which it is released, and ODOMETRY.time_usec carries
the frame's stamp, so arrival time minus time_usec is the latency from "frame available" to "message
received", on one clock.
"""

from __future__ import annotations

import json
import logging
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np

from bench.child import summary_ms
from vio import VioError

log = logging.getLogger(__name__)

RSS_PERIOD_S = 0.5
SETTLE_S = 1.0  # after the data ends: let the last frames drain before SIGTERM
SOURCE_ENDED = "source ended"  # the daemon's warning (vio.app.daemon) when the EuRoC playback is over
STARTUP_LIMIT_S = 60.0  # the daemon must have played the data by duration + this


class AutopilotStub:
    """Loopback MAVLink peer: heartbeats once a second, records (arrival_ns, time_usec) of every ODOMETRY."""

    def __init__(self) -> None:
        os.environ["MAVLINK20"] = "1"
        from pymavlink import mavutil

        self._mavutil = mavutil
        # component 1 as a flight controller's: `vio run` on a recording (kind = "euroc") sends no pose until an
        # autopilot heartbeat (drivers.mavlink_link.is_autopilot_heartbeat) says it is disarmed
        self.conn = mavutil.mavlink_connection("udpin:127.0.0.1:0", source_system=1, source_component=1,
                                               dialect="ardupilotmega")
        self.port = self.conn.port.getsockname()[1]
        self.records: list[tuple[int, int]] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="autopilot-stub", daemon=True)

    def start(self) -> AutopilotStub:
        self._thread.start()
        return self

    def _run(self) -> None:
        mav = self._mavutil.mavlink
        next_hb = 0.0
        while not self._stop.is_set():
            if time.monotonic() >= next_hb:  # dropped by mavutil until the daemon's first packet names it
                self.conn.mav.heartbeat_send(mav.MAV_TYPE_QUADROTOR, mav.MAV_AUTOPILOT_ARDUPILOTMEGA, 0, 0, 3)
                next_hb = time.monotonic() + 1.0
            m = self.conn.recv_match(type="ODOMETRY", blocking=True, timeout=0.05)
            if m is not None:
                self.records.append((time.monotonic_ns(), int(m.time_usec)))

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2.0)
        self.conn.close()

    def latencies_ms(self) -> np.ndarray:
        r = np.array(self.records, dtype=np.int64).reshape(-1, 2)
        return (r[:, 0] - r[:, 1] * 1000) / 1e6


def _rss_kb(pid: int) -> tuple[int, int] | None:
    """(VmRSS, VmHWM) of a process in kB, None once it is gone."""
    try:
        text = Path(f"/proc/{pid}/status").read_text()
    except OSError:
        return None
    vals = {}
    for line in text.splitlines():
        if line.startswith(("VmRSS:", "VmHWM:")):
            vals[line.split(":")[0]] = int(line.split()[1])
    return (vals.get("VmRSS", 0), vals.get("VmHWM", 0)) if vals else None


def _read_status(path: Path) -> dict | None:
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):  # not written yet, or caught mid-write
        return None


def memory_growth(t_s: np.ndarray, rss_mb: np.ndarray, t_start_s: float, t_end_s: float) -> dict:
    """Growth = median RSS of the late plateau (last 10 % of [t_start, t_end]) minus the early plateau
    (10-20 % into it). Medians of windows, not single samples, so one transient allocation does not count,
    and the start-up ramp (imports, first keyframes filling the window) is left out."""
    span = t_end_s - t_start_s
    if span <= 0:
        raise VioError(f"memory: no time span to measure growth over ({t_start_s:.1f}..{t_end_s:.1f} s)")
    early = (t_s >= t_start_s + 0.1 * span) & (t_s <= t_start_s + 0.2 * span)
    late = (t_s >= t_start_s + 0.9 * span) & (t_s <= t_end_s)
    if not early.any() or not late.any():
        raise VioError(f"memory: too few RSS samples in {span:.1f} s for the early/late plateaus")
    e, la = float(np.median(rss_mb[early])), float(np.median(rss_mb[late]))
    # a one-time step (a cache or pool filling up) and a steady leak give the same growth; the slope of the
    # second half tells them apart
    half = (t_s >= t_start_s + 0.5 * span) & (t_s <= t_end_s)
    slope = float(np.polyfit(t_s[half], rss_mb[half], 1)[0]) * 600.0 if half.sum() >= 2 else float("nan")
    return {"early_mb": e, "late_mb": la, "growth_mb": la - e, "second_half_mb_per_10min": slope,
            "early_window_s": [t_start_s + 0.1 * span, t_start_s + 0.2 * span],
            "late_window_s": [t_start_s + 0.9 * span, t_end_s]}


def run_live(dataset: Path, duration_s: float, workdir: Path, env: dict, cpus: set[int] | None,
             python: str = sys.executable) -> dict:
    """Run `vio run` on `dataset` in real time for `duration_s` seconds of data; latency and memory figures."""
    workdir.mkdir(parents=True, exist_ok=True)
    ap = AutopilotStub().start()
    cfg = workdir / "live.toml"
    cfg.write_text(f'[source]\nkind = "euroc"\ndataset = "{dataset}"\nrealtime = true\n'
                   f'[mavlink]\nurl = "udpout:127.0.0.1:{ap.port}"\n'
                   f'[run]\nstatus_file = "{workdir / "status.json"}"\nlog_level = "WARNING"\n')
    log_path = workdir / "daemon.log"
    samples: list[tuple[float, int, int]] = []
    status = None
    with open(log_path, "w") as logf:
        proc = subprocess.Popen([python, "-m", "vio.app.cli", "run", "--config", str(cfg)], stdout=logf,
                                stderr=subprocess.STDOUT, env=env, cwd=workdir,
                                preexec_fn=(lambda: os.sched_setaffinity(0, cpus)) if cpus else None)
        t0 = time.monotonic()
        t_done = None  # when the daemon reported the dataset played out
        try:
            while proc.poll() is None and time.monotonic() - t0 < duration_s + STARTUP_LIMIT_S:
                r = _rss_kb(proc.pid)
                if r is not None:
                    samples.append((time.monotonic() - t0, *r))
                status = _read_status(workdir / "status.json") or status
                # the daemon reopens an ended source (and would play it again): stop at the first end
                if t_done is None and SOURCE_ENDED in log_path.read_text():
                    t_done = time.monotonic() - t0
                if t_done is not None and time.monotonic() - t0 > t_done + SETTLE_S:
                    break
                time.sleep(RSS_PERIOD_S)
        finally:
            if proc.poll() is None:
                proc.send_signal(signal.SIGTERM)
                try:
                    proc.wait(10)
                except subprocess.TimeoutExpired:
                    proc.kill()
                    proc.wait()
            ap.close()
    if not samples or not ap.records:
        raise VioError(f"vio run sent no ODOMETRY on {dataset} (exit {proc.returncode}); "
                       f"log {log_path}: {log_path.read_text()[-800:]}")
    arr = np.array(samples)
    t_s, rss_mb = arr[:, 0], arr[:, 1] / 1024
    lat = ap.latencies_ms()
    # plateaus from the first pose (initialised, window filling) to the end of the data
    t_first_pose = ap.records[0][0] * 1e-9 - t0
    t_end = t_done if t_done is not None else float(t_s[-1])
    mem = memory_growth(t_s, rss_mb, t_first_pose, t_end)
    return {
        "dataset": str(dataset), "duration_s": duration_s, "cpus": sorted(cpus) if cpus else "all",
        "latency_ms": summary_ms(lat), "odometry_received": len(lat),
        "odometry_rate_hz": len(lat) / max(1e-9, (ap.records[-1][0] - ap.records[0][0]) * 1e-9),
        "daemon_status": {k: status.get(k) for k in ("latency_ms", "source", "estimator", "mavlink")}
        if status else None,
        "memory": {"peak_rss_mb": float(arr[:, 2].max() / 1024), "first_pose_s": t_first_pose, **mem},
        "rss_trace": {"t_s": [round(float(x), 2) for x in t_s], "rss_mb": [round(float(x), 2) for x in rss_mb]},
        "exit_code": proc.returncode,
    }
