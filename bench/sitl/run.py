"""Closed-loop SITL test: ArduCopter SITL flies a mission on Kestrel's vision alone (docs/autopilot.md,
"Closed-loop SITL test").

    python -m bench.sitl.run --sitl-bin PATH/arducopter --mission box --out runs/sitl [--faults 2,10]

What runs (all on loopback):
- ArduCopter SITL (`--model quad --speedup 1`), GPS off, EKF3 on external nav (PARAMS below), its
  SERIAL0 (tcp 5760) for this script, SERIAL1 (5762) for Kestrel's autopilot link, SERIAL2 (5763) for the
  camera's truth stream;
- `vio run` (the real daemon, a subprocess) with `[source] kind = "sitl"` (cameras rendered at the SITL's
  SIM_STATE pose, drivers/sitl_camera.py) and `imu = "mavlink"` (the SITL's IMU), sending ODOMETRY back;
- this script: records truth (SIM_STATE), the autopilot's estimate (LOCAL_POSITION_NED, ATTITUDE), EKF
  status and STATUSTEXT; arms in GUIDED, takes off, streams the mission's position targets, covers the
  cameras (the blackout file) for the `--faults` durations, lands; then writes report.json and report.md
  (bench/sitl/report.py).

No SITL binary: one line saying so, exit 2 (CI has none; tests/test_sitl_harness.py tests the pieces).
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path
from types import SimpleNamespace

import numpy as np

from bench.sitl import mission as msn
from bench.sitl import report as rep

HOME = (-35.363261, 149.165230, 584.0)  # ArduPilot's CMAC default home; any place works
DEFAULT_BIN = os.environ.get("KESTREL_SITL_BIN", "/work/sitl/ardupilot/build/sitl/bin/arducopter")
PARAMS = {  # docs/autopilot.md "ArduPilot (EKF3)", plus what a GPS-less SITL needs
    "AHRS_EKF_TYPE": 3, "EK3_ENABLE": 1, "EK2_ENABLE": 0,
    "GPS_TYPE": 0, "GPS1_TYPE": 0, "SIM_GPS_DISABLE": 1, "SIM_GPS1_ENABLE": 0,  # names differ across versions
    "VISO_TYPE": 1, "VISO_DELAY_MS": 50, "VISO_POS_M_NSE": 0.1, "VISO_VEL_M_NSE": 0.1, "VISO_YAW_M_NSE": 0.2,
    "EK3_SRC1_POSXY": 6, "EK3_SRC1_VELXY": 6, "EK3_SRC1_POSZ": 1, "EK3_SRC1_VELZ": 6, "EK3_SRC1_YAW": 6,
    "COMPASS_USE": 0, "COMPASS_USE2": 0, "COMPASS_USE3": 0,
    "SERIAL1_PROTOCOL": 2, "SERIAL2_PROTOCOL": 2,
    "ARMING_CHECK": 0,  # the GPS and compass checks cannot pass without them; the EKF still gates arming
    "FS_EKF_ACTION": 1,  # land on an EKF failsafe (what the blackout test watches for)
}
RECORDED = {"SIM_STATE": 20, "LOCAL_POSITION_NED": 20, "ATTITUDE": 20, "EKF_STATUS_REPORT": 5}


class Recorder(threading.Thread):
    """Reads the script's own SITL link and keeps every message the report needs, stamped on the host clock."""

    def __init__(self, conn) -> None:
        super().__init__(name="recorder", daemon=True)
        self.conn = conn
        self.stop = threading.Event()
        self.truth: list = []  # (t_ns, n, e, d, yaw, q1..q4 = FRD body -> NED, w first)
        self.local: list = []  # (t_ns, n, e, d)
        self.att: list = []  # (t_ns, yaw)
        self.ekf: list = []  # (t_ns, flags, pos_horiz_ratio, compass(yaw)_ratio)
        self.text: list = []  # (t_ns, text)
        self.modes: list = []  # (t_ns, custom_mode)
        self.odom: list = []  # (t_ns, reset_counter): Kestrel's ODOMETRY as the autopilot routes it to this link
        self.home: list = []  # (t_ns, latitude 1e-7 deg): HOME_POSITION as answered
        self.boot_ms = 0
        self.mode = -1  # the autopilot's custom_mode and armed flag (component 1's HEARTBEAT only)
        self.armed = False

    def run(self) -> None:
        from drivers.sitl_camera import ned_from_geodetic

        while not self.stop.is_set():
            m = self.conn.recv_match(blocking=True, timeout=0.2)
            if m is None:
                continue
            t, kind = time.monotonic_ns(), m.get_type()
            if kind == "SIM_STATE":
                ned = ned_from_geodetic(HOME, m.lat_int or int(m.lat * 1e7), m.lon_int or int(m.lon * 1e7), m.alt)
                self.truth.append((t, *ned, m.yaw, m.q1, m.q2, m.q3, m.q4))
            elif kind == "LOCAL_POSITION_NED":
                self.local.append((t, m.x, m.y, m.z))
                self.boot_ms = m.time_boot_ms
            elif kind == "ATTITUDE":
                self.att.append((t, m.yaw))
            elif kind == "EKF_STATUS_REPORT":
                self.ekf.append((t, m.flags, m.pos_horiz_variance, m.compass_variance))
            elif kind == "ODOMETRY" and m.get_srcComponent() != 1:
                self.odom.append((t, m.reset_counter))
            elif kind == "HOME_POSITION":
                self.home.append((t, m.latitude))
            elif kind == "COMMAND_ACK":  # a refused arm or takeoff says why only here
                self.text.append((t, f"COMMAND_ACK {m.command} result {m.result}"))
                print(f"[sitl] COMMAND_ACK {m.command} result {m.result}", flush=True)
            elif kind == "STATUSTEXT":
                self.text.append((t, m.text))
                print(f"[sitl] {m.text}", flush=True)
            elif kind == "HEARTBEAT" and m.get_srcComponent() == 1:
                self.mode, self.armed = m.custom_mode, bool(m.base_mode & 128)  # MAV_MODE_FLAG_SAFETY_ARMED
                if not self.modes or self.modes[-1][1] != m.custom_mode:
                    self.modes.append((t, m.custom_mode))


def kestrel_config(out: Path, fps: float, width: int, height: int, land_after_loss_s: float = 0.0,
                   record: bool = False) -> Path:
    """The daemon's config. With `record` it also records the frames and IMU samples as it received them (host
    stamps, EuRoC in out/record/<start time>), so that a flight whose estimate went wrong can be replayed offline
    (`vio replay out/record/<start time>`): raw.npz holds only this script's streams, and one drifting flight
    could not be (docs/autopilot.md, "Re-checked 2026-12-07")."""
    record_line = f'record_dir = "{out / "record"}"\n' if record else ""
    cfg = f"""[source]
kind = "sitl"
imu = "mavlink"
sitl_url = "tcp:127.0.0.1:5763"
sitl_home = [{HOME[0]}, {HOME[1]}, {HOME[2]}]
sitl_blackout_file = "{out / 'blackout'}"
fps = {fps}
width = {width}
height = {height}

[mavlink]
url = "tcp:127.0.0.1:5762"
mount = "camera-forward"
origin_lat_deg = {HOME[0]}
origin_lon_deg = {HOME[1]}
origin_alt_m = {HOME[2]}
land_after_loss_s = {land_after_loss_s}

[run]
{record_line}trajectory_file = "{out / 'kestrel.tum'}"
status_file = "{out / 'status.json'}"
"""
    path = out / "kestrel.toml"
    path.write_text(cfg)
    return path


def copter_defaults(binary: str) -> Path | None:
    """ArduPilot's own SITL quad parameters (frame class, RC ranges...), next to the binary's source tree:
    build/sitl/bin/arducopter -> Tools/autotest/default_params/copter.parm."""
    p = Path(binary).resolve().parents[3] / "Tools" / "autotest" / "default_params" / "copter.parm"
    return p if p.is_file() else None


def start_sitl(binary: str, out: Path, extra: dict | None = None) -> subprocess.Popen:
    """ArduCopter SITL in `out` (its eeprom.bin and logs land there): ArduPilot's quad defaults, then PARAMS,
    then `extra` (--ap-param)."""
    parm = out / "sitl.parm"
    parm.write_text("".join(f"{k} {v}\n" for k, v in {**PARAMS, **(extra or {})}.items()))
    base = copter_defaults(binary)
    defaults = f"{base},{parm}" if base else str(parm)
    home = ",".join(str(x) for x in HOME) + ",0"
    return subprocess.Popen([binary, "--model", "quad", "--speedup", "1", "--home", home, "--defaults", defaults,
                             "-I0"], cwd=out, stdout=open(out / "sitl.log", "w"), stderr=subprocess.STDOUT)


def ensure_home(conn, rec: Recorder, timeout_s: float = 20.0) -> bool:
    """Ask for HOME_POSITION; without one, send the EKF origin and home from here (at HOME, as Kestrel's
    [mavlink] origin_* would) until the autopilot reports a home. True when the harness had to.

    Why: GUIDED's NAV_TAKEOFF converts its altitude above home to one above the EKF origin and is refused
    (COMMAND_ACK 22 result 4) while there is none. Kestrel used to send SET_GPS_GLOBAL_ORIGIN/
    SET_HOME_POSITION only 3 times right after link-up, which could be before EKF3 took them (3 of 6 runs
    refused the takeoff); it now re-sends until GPS_GLOBAL_ORIGIN comes back (drivers/mavlink_out.py). This
    stays as a second line, and the report says whether it was needed."""
    deadline = time.monotonic() + timeout_s
    by_harness = False
    lat, lon, alt_mm = int(HOME[0] * 1e7), int(HOME[1] * 1e7), int(HOME[2] * 1000)
    while not rec.home:
        if time.monotonic() > deadline:
            raise TimeoutError("the autopilot reports no HOME_POSITION, so GUIDED takeoff would be refused")
        conn.mav.command_long_send(conn.target_system, 1, 512, 0, 242, 0, 0, 0, 0, 0, 0)  # REQUEST_MESSAGE home
        time.sleep(1.0)
        if not rec.home and time.monotonic() > deadline - timeout_s + 3.0:
            if not by_harness:
                print("autopilot has no home: the harness sends SET_GPS_GLOBAL_ORIGIN and SET_HOME_POSITION",
                      flush=True)
            by_harness = True
            conn.mav.set_gps_global_origin_send(conn.target_system, lat, lon, alt_mm, 0)
            conn.mav.set_home_position_send(conn.target_system, lat, lon, alt_mm, 0, 0, 0, [1, 0, 0, 0], 0, 0, 0, 0)
    return by_harness


def fly(conn, rec: Recorder, path: msn.Path, faults: list[float], out: Path, hold_on_loss: bool = True,
        land_after_loss_s: float | None = None, restart_at_s: float | None = None,
        restart: Callable[[], None] | None = None) -> dict:
    """Wait for vision, record the ground alignment, take off, follow `path`, black out, land. Returns the events.

    With `hold_on_loss` the mission clock stops at Kestrel's "VIO tracking lost" STATUSTEXT (the target
    stays where the vehicle was, zero velocity) and runs on at "VIO tracking regained": the autopilot
    dead-reckons through a blackout and keeps flying any moving target it is given, so holding is the
    mission's job (docs/autopilot.md, "Camera blackouts"). With `land_after_loss_s` the mission lands once
    vision has been lost that long (the EKF's own failsafe comes only when its variance grows, ~8 s).
    With `restart_at_s` the harness calls `restart` (kill Kestrel, start it again, as systemd does after a crash)
    once the mission clock reaches it: a restart in flight, which then starts in the air."""
    blackout = out / "blackout"
    deadline = time.monotonic() + 120
    while not any("external nav" in s for _, s in rec.text):
        if time.monotonic() > deadline:
            raise TimeoutError("EKF3 never reported 'using external nav data' (see kestrel.log)")
        time.sleep(0.5)
    time.sleep(3.0)  # ground samples for the start alignment
    t_ground = (time.monotonic_ns() - 3_000_000_000, time.monotonic_ns())
    home_by_harness = ensure_home(conn, rec)
    msn.arm_and_takeoff(conn, rec, -path.waypoints[0, 2])
    time.sleep(8.0)
    t0 = time.monotonic_ns()
    # blackouts evenly spaced over the mission: [(start [s into the path], duration [s])]
    pending = [(path.duration_s * (k + 1) / (len(faults) + 1), d) for k, d in enumerate(faults)]
    windows: list = []  # [host ns when the cameras went black, host ns when they came back, duration]
    clock: list = []  # (host ns, mission time [s]): the mission clock stops while Kestrel reports vision lost
    end_ns = None
    t_mission, last_ns, n_text = 0.0, t0, 0
    lost = False
    lost_since = None
    restarted_ns = None
    while t_mission < path.duration_s:
        now = time.monotonic_ns()
        if hold_on_loss:  # what a companion mission should do: hold where vision was lost, resume when back
            for _t, text in rec.text[n_text:]:
                lost = True if ("VIO tracking lost" in text or "VIO not tracking" in text) \
                    else False if "VIO tracking regained" in text else lost
            n_text = len(rec.text)
        if lost and land_after_loss_s is not None and lost_since is not None \
                and now - lost_since > land_after_loss_s * 1e9:
            break  # blind too long: land where it is (below) instead of waiting for the EKF failsafe
        lost_since = (lost_since or now) if lost else None
        if not lost:
            t_mission += (now - last_ns) * 1e-9
        last_ns = now
        if restart is not None and restarted_ns is None and restart_at_s is not None and t_mission >= restart_at_s:
            restarted_ns = now
            restart()
        if end_ns is None and pending and t_mission >= pending[0][0]:
            _start_s, dur = pending.pop(0)
            blackout.touch()
            windows.append([now, None, dur])
            end_ns = now + int(dur * 1e9)
        elif end_ns is not None and now >= end_ns:
            blackout.unlink()
            windows[-1][1] = now
            end_ns = None
        p, v = path.target(t_mission)
        if rec.mode == msn.COPTER_MODES["LAND"]:
            break  # LAND from the autopilot's failsafe or Kestrel's land_after_loss_s: no more targets
        msn.send_target(conn, p, v * (not lost), rec.boot_ms)
        clock.append((now, t_mission))
        time.sleep(0.1)
    if end_ns is not None:  # landing mid-blackout: LAND now, keep the cameras black for the blackout's length
        msn.set_mode(conn, rec, "LAND")
        time.sleep(max(0.0, (end_ns - time.monotonic_ns()) * 1e-9))
        windows[-1][1] = time.monotonic_ns()
    blackout.unlink(missing_ok=True)
    msn.set_mode(conn, rec, "LAND")
    deadline = time.monotonic() + 60
    while rec.armed and time.monotonic() < deadline:
        time.sleep(1.0)
    return {"t_ground": t_ground, "t0": t0, "blackouts": windows, "clock": clock, "hold_on_loss": hold_on_loss,
            "home_set_by_harness": home_by_harness, "restarted_ns": restarted_ns}


def save_raw(rec: Recorder, ev: dict, out: Path) -> None:
    """The recorded streams and events (raw.npz, events.json), so the report can be recomputed without a
    flight (`python -m bench.sitl.run --resummarise DIR`)."""
    np.savez(out / "raw.npz", truth=np.array(rec.truth), local=np.array(rec.local), att=np.array(rec.att),
             ekf=np.array(rec.ekf) if rec.ekf else np.zeros((0, 4)),
             modes=np.array(rec.modes) if rec.modes else np.zeros((0, 2)),
             odom=np.array(rec.odom) if rec.odom else np.zeros((0, 2)))
    (out / "events.json").write_text(json.dumps({**ev, "text": rec.text}))


def load_raw(out: Path) -> tuple[SimpleNamespace, dict]:
    """What save_raw wrote: the recorder's streams (as arrays) and the flight's events."""
    raw = np.load(out / "raw.npz")
    ev = json.loads((out / "events.json").read_text())
    rec = SimpleNamespace(**{k: raw[k] for k in raw.files}, text=[tuple(x) for x in ev.pop("text")])
    return rec, ev


def summarise(rec: Recorder | SimpleNamespace, path: msn.Path, ev: dict, out: Path) -> dict:
    truth = np.asarray(rec.truth, dtype=float)
    local = np.asarray(rec.local, dtype=float)
    att = np.asarray(rec.att, dtype=float)
    g0, g1 = ev["t_ground"]
    on_ground = (local[:, 0] >= g0) & (local[:, 0] <= g1)
    tg = local[on_ground, 0]
    align = rep.start_alignment(local[on_ground, 1:4], np.interp(tg, att[:, 0], att[:, 1]),
                                rep.interp_positions(tg, truth[:, 0], truth[:, 1:4]),
                                np.interp(tg, truth[:, 0], truth[:, 4]))
    clock = np.asarray(ev.get("clock") or [(ev["t0"], 0.0), (ev["t0"] + path.duration_s * 1e9, path.duration_s)],
                       dtype=float)
    land = [t for t, m in rec.modes if int(m) == msn.COPTER_MODES["LAND"]]
    t_end = min([clock[-1, 0], *land])  # after a LAND the setpoint means nothing
    flying = (truth[:, 0] >= ev["t0"]) & (truth[:, 0] <= t_end)
    tf = truth[flying, 0]
    p_truth = truth[flying, 1:4]
    p_planned = align.apply(path.positions(np.interp(tf, clock[:, 0], clock[:, 1])))
    p_ekf = align.apply(rep.interp_positions(tf, local[:, 0], local[:, 1:4]))
    ekf = np.asarray(rec.ekf, dtype=float).reshape(-1, 4)
    ekf_fly = ekf[(ekf[:, 0] >= ev["t0"]) & (ekf[:, 0] <= t_end)] if len(ekf) else ekf
    summary = {
        "mission duration [s]": path.duration_s, "flown until LAND [s]": (t_end - ev["t0"]) * 1e-9,
        "mission held while vision lost": bool(ev.get("hold_on_loss", False)),
        "LAND after vision lost [s]: Kestrel's land_after_loss_s / the harness's": [
            ev.get("kestrel_land_after_loss_s", 0.0), ev.get("harness_land_after_loss_s")],
        "ArduPilot parameters over PARAMS (--ap-param)": ev.get("ap_params", {}),
        "home set by the harness (Kestrel's origin not taken)": bool(ev.get("home_set_by_harness", False)),
        "Kestrel killed and restarted at [s into the mission]": (round((ev["restarted_ns"] - ev["t0"]) * 1e-9, 1)
                                                                  if ev.get("restarted_ns") else None),
        "vehicle cross-track error vs mission path [m]": rep.error_stats(
            rep.distance_to_polyline(p_truth, align.apply(path.waypoints))),
        "vehicle error vs timed setpoint [m]": rep.error_stats(np.linalg.norm(p_truth - p_planned, axis=1)),
        "autopilot estimate (LOCAL_POSITION_NED) vs truth [m]": rep.error_stats(
            np.linalg.norm(p_ekf - p_truth, axis=1)),
        "EKF yaw/compass test ratio": rep.ratio_stats(ekf_fly[:, 3]) if len(ekf_fly) else {"n": 0},
        "EKF position test ratio": rep.ratio_stats(ekf_fly[:, 2]) if len(ekf_fly) else {"n": 0},
        "failsafe STATUSTEXT": [s for _, s in rep.failsafe_events(rec.text)],
        "flight modes (custom_mode) in order": [m for _, m in rec.modes],
    }
    for start, end, dur in ev["blackouts"]:
        if end is None:
            continue
        key = f"blackout {dur:g} s"
        hold = rep.blackout_hold(truth[:, 0], truth[:, 1:4], (start, end))
        summary[f"{key}: drift from the blackout-start position while blind (truth) [m]"] = hold
        failsafe_land = [t for t in land if start <= t <= end + 5e9]
        if failsafe_land:  # it should come down where the blackout began
            summary[f"{key}: LAND at [s after blackout start]"] = (failsafe_land[0] - start) * 1e-9
            summary[f"{key}: landed, horizontal offset from the blackout-start position [m]"] = rep.landed_offset(
                truth[:, 0], truth[:, 1:4], start, int(truth[-1, 0]))
        else:  # it should be back on the mission path
            m = (tf >= end + 5e9) & (tf <= end + 15e9)  # settled: 5..15 s after the cameras came back
            summary[f"{key}: max |truth - setpoint| 5-15 s after [m]"] = rep.recovery_error(
                tf[m], p_truth[m], p_planned[m], (end + 5e9, end + 15e9))
    est = out / "kestrel.tum"
    if est.exists() and est.stat().st_size:
        from drivers.sitl_camera import world_from_ned
        from vio.trajectory import read_tum

        tum = read_tum(est)
        inside = (tum.t_ns >= truth[0, 0]) & (tum.t_ns <= truth[-1, 0])
        t_est, p_est = tum.t_ns[inside], tum.p[inside]
        p_gt = np.array([world_from_ned(p) for p in rep.interp_positions(t_est, truth[:, 0], truth[:, 1:4])])
        odom = np.asarray(rec.odom).reshape(-1, 2)
        resets = odom[1:, 0][np.diff(odom[:, 1]) != 0] if len(odom) > 1 else []
        seg = rep.segment_ids(t_est, resets)
        summary["Kestrel error vs SITL truth, 4-DoF aligned per reset segment [m]"] = {
            **rep.per_segment_error(p_est, p_gt, seg), "resets seen in ODOMETRY": len(resets),
            "poses": int(len(t_est))}
    return summary


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sitl-bin", default=DEFAULT_BIN, help="ArduCopter SITL binary (env KESTREL_SITL_BIN)")
    ap.add_argument("--mission", choices=("box", "eight", "both"), default="both")
    ap.add_argument("--laps", type=int, default=2, help="laps of each pattern (2 laps of both: about 3.5 minutes)")
    ap.add_argument("--faults", default="", help="camera blackouts during the mission, seconds, e.g. 2,10")
    ap.add_argument("--fps", type=float, default=15.0)
    ap.add_argument("--width", type=int, default=320)
    ap.add_argument("--height", type=int, default=200)
    ap.add_argument("--out", default="runs/sitl")
    ap.add_argument("--no-hold", action="store_true",
                    help="keep streaming the moving mission target while Kestrel reports vision lost")
    ap.add_argument("--land-after-loss", type=float, default=None, metavar="S",
                    help="LAND once Kestrel has reported vision lost for S seconds (default: hold and leave it "
                         "to the EKF failsafe)")
    ap.add_argument("--kestrel-land-after-loss", type=float, default=0.0, metavar="S",
                    help="Kestrel's own [mavlink] land_after_loss_s: the daemon asks the autopilot to LAND once "
                         "tracking has been lost S s (the product's option; default 0 = off)")
    ap.add_argument("--restart-at", type=float, default=None, metavar="S",
                    help="kill Kestrel S seconds into the mission and start it again 1 s later (a crash and "
                         "systemd's restart, in flight)")
    ap.add_argument("--record", action="store_true",
                    help="Kestrel records the frames and IMU samples it received to OUT/record/<start time> (EuRoC, "
                         "about 2 MB/s at 320x200 and 15 Hz; more disk writes beside the real-time SITL), for "
                         "`vio replay`")
    ap.add_argument("--ap-param", action="append", default=[], metavar="NAME=VALUE",
                    help="an ArduPilot parameter over PARAMS (repeatable), e.g. FS_EKF_THRESH=0.5")
    ap.add_argument("--resummarise", action="store_true",
                    help="no flight: recompute report.json/report.md from --out's raw.npz and events.json")
    args = ap.parse_args(argv)
    parts = {"box": [msn.box(laps=args.laps)], "eight": [msn.figure_eight(laps=args.laps)],
             "both": [msn.box(laps=args.laps), msn.figure_eight(laps=args.laps)]}[args.mission]
    path = msn.chain(*parts) if len(parts) > 1 else parts[0]
    if args.resummarise:
        out = Path(args.out).resolve()
        try:
            rec, ev = load_raw(out)
        except (OSError, KeyError, ValueError) as e:
            print(f"--resummarise: cannot read the recording in {out} ({e})", file=sys.stderr)
            return 2
        return write_report(summarise(rec, path, ev, out), out)
    if not (os.path.isfile(args.sitl_bin) and os.access(args.sitl_bin, os.X_OK)):
        print(f"no SITL binary at {args.sitl_bin}: build ArduCopter SITL (docs/autopilot.md) or pass --sitl-bin",
              file=sys.stderr)
        return 2
    try:
        faults = [float(x) for x in args.faults.split(",") if x.strip()]
    except ValueError:
        print(f"--faults {args.faults!r}: expected seconds separated by commas, e.g. 2,10", file=sys.stderr)
        return 2
    ap_params = {}
    for item in args.ap_param:
        name, _, value = item.partition("=")
        try:
            ap_params[name.strip()] = float(value)
        except ValueError:
            print(f"--ap-param {item!r}: expected NAME=NUMBER, e.g. FS_EKF_THRESH=0.5", file=sys.stderr)
            return 2
    out = Path(args.out).resolve()
    shutil.rmtree(out, ignore_errors=True)
    out.mkdir(parents=True)

    os.environ["MAVLINK20"] = "1"
    from pymavlink import mavutil

    sitl = start_sitl(args.sitl_bin, out, ap_params)
    daemon = None
    try:
        conn = mavutil.mavlink_connection("tcp:127.0.0.1:5760", source_system=250, retries=30)
        conn.wait_heartbeat(timeout=60)
        for name, hz in RECORDED.items():
            msg_id = getattr(mavutil.mavlink, f"MAVLINK_MSG_ID_{name}")
            conn.mav.command_long_send(conn.target_system, 1, 511, 0, msg_id, 1e6 / hz, 0, 0, 0, 0, 0)
        rec = Recorder(conn)
        rec.start()
        cfg = kestrel_config(out, args.fps, args.width, args.height, args.kestrel_land_after_loss, args.record)
        def start_daemon(mode: str = "w") -> subprocess.Popen:
            return subprocess.Popen([sys.executable, "-m", "vio.app.cli", "run", "--config", str(cfg)],
                                    stdout=open(out / "kestrel.log", mode), stderr=subprocess.STDOUT)

        daemon = start_daemon()

        def restart() -> None:  # a crash (SIGKILL: nothing said, nothing flushed) and systemd's restart 1 s later
            nonlocal daemon
            daemon.kill()
            daemon.wait(10)
            print("[harness] Kestrel killed in flight; restarting it in 1 s", flush=True)
            time.sleep(1.0)
            daemon = start_daemon("a")

        try:
            ev = fly(conn, rec, path, faults, out, hold_on_loss=not args.no_hold,
                     land_after_loss_s=args.land_after_loss, restart_at_s=args.restart_at, restart=restart)
            ev.update(kestrel_land_after_loss_s=args.kestrel_land_after_loss, ap_params=ap_params,
                      harness_land_after_loss_s=args.land_after_loss)
        finally:
            rec.stop.set()
            rec.join(2.0)
        save_raw(rec, ev, out)
        summary = summarise(rec, path, ev, out)
    except (TimeoutError, ConnectionError, OSError, ValueError, IndexError) as e:
        print(f"closed-loop run stopped: {e}", file=sys.stderr)
        return 1
    finally:
        for p in (daemon, sitl):
            if p is not None and p.poll() is None:
                p.terminate()
                try:
                    p.wait(10)
                except subprocess.TimeoutExpired:
                    p.kill()
    write_report(summary, out)
    return 0 if not summary["failsafe STATUSTEXT"] or faults else 1


def write_report(summary: dict, out: Path) -> int:
    (out / "report.json").write_text(json.dumps(summary, indent=1, default=str))
    (out / "report.md").write_text(rep.markdown(summary))
    print(rep.markdown(summary))
    return 0


if __name__ == "__main__":
    sys.exit(main())
