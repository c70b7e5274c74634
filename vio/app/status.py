"""`vio status`: the daemon's health for a person on the drone's shell (or a script: see the exit codes).

Reads the JSON status file that `vio run` rewrites every second. Exit codes: 0 healthy; 1 running but not
giving poses or not well (starting, waiting for vision, degraded, unhealthy); 4 not running: the file is
missing, unreadable, stale (not rewritten for `--stale-s` seconds) or written by a stopped daemon.

States: `starting` (sensors not delivering yet), `waiting for vision` (sensors deliver, no tracked pose:
not initialised, dark, lens cap, camera frames stopped; nothing goes to the autopilot), `running`
(healthy: a fresh tracked pose, every thread alive, no warnings), `degraded` (running with warnings:
autopilot link down, frames dropped, recording or trajectory file failed, IMU missing), `unhealthy` (a
thread died or is stuck; the systemd watchdog is no longer fed), `stopped`.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import os
import stat
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from vio.argtypes import path_arg, positive_float_up_to
from vio.io.inputs import is_device

EXIT_HEALTHY = 0
EXIT_UNHEALTHY = 1
EXIT_NOT_RUNNING = 4
DEFAULT_STATUS_FILE = "/run/kestrel-vio/status.json"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--file", type=path_arg,
                   help=f"status file (default: [run] status_file of --config, else {DEFAULT_STATUS_FILE})")
    p.add_argument("--config", help="take the status file path from this TOML config")
    # a number > 0: with nan or inf a hung daemon's last status never went stale and read HEALTHY (a QA walk-through)
    # and at most an hour: 1e300 did the same (a review's finding)
    p.add_argument("--stale-s", type=positive_float_up_to(3600.0), default=3.0,
                   help="older than this = daemon not running (default 3)")
    p.add_argument("--json", action="store_true", help="print the raw status JSON")


def read_status(path: Path) -> dict[str, Any]:
    """Parse the status file; OSError / ValueError mean 'not running' to the caller."""
    if is_device(path):  # /dev/zero was read for ever (a review's finding)
        raise ValueError("is a device, not a status file")
    with contextlib.suppress(OSError):  # the daemon writes a regular file: opening a pipe waited for a writer for ever
        if stat.S_ISFIFO(os.stat(path).st_mode):
            raise ValueError("is a pipe, not a status file")
    try:
        data = json.loads(path.read_text())
    except RecursionError:  # nested thousands deep: was an internal error (a review's finding)
        raise ValueError("nested too deep to be a status file") from None
    if not isinstance(data, dict) or "state" not in data:
        raise ValueError("not a kestrel-vio status file")
    return data


def _pid_gone(pid: Any) -> bool:
    """The daemon that wrote the status is no longer a process (killed: its last status is still fresh)."""
    if not isinstance(pid, int) or pid <= 0:
        return False
    try:
        os.kill(pid, 0)
    except (ProcessLookupError, OverflowError):  # OverflowError: no process has it (was an internal error)
        return True
    except OSError:  # another user's process (EPERM): it exists
        return False
    return False


def _written_unix(status: dict[str, Any]) -> float | None:
    """When the status was written [unix s], or None when its written_unix is no finite number."""
    w = status.get("written_unix")
    if isinstance(w, bool) or not isinstance(w, (int, float)) or not math.isfinite(w):
        return None
    return float(w)


def evaluate(status: dict[str, Any], now_unix: float, stale_s: float,
             pid_gone: Callable[[Any], bool] = _pid_gone) -> tuple[int, str]:
    """Exit code and a one-word verdict for a parsed status."""
    written = _written_unix(status)
    if written is None:  # NaN read HEALTHY: every comparison with it is false (a QA sweep)
        return EXIT_NOT_RUNNING, (f"UNKNOWN (its written_unix {status.get('written_unix')!r} is no time: not a status "
                                  "this daemon wrote)")
    age = now_unix - written
    if status.get("state") == "stopped":
        return EXIT_NOT_RUNNING, "STOPPED"
    if pid_gone(status.get("pid")):
        return EXIT_NOT_RUNNING, f"NOT RUNNING (pid {status.get('pid')} is gone: killed or crashed)"
    if age > stale_s:
        return EXIT_NOT_RUNNING, (f"STALE ({age:.0f} s old: daemon not running or hung, or its status file can no "
                                  "longer be written: a full or read-only disk; its log says which)")
    if age < -stale_s:
        # written "in the future": the wall clock stepped back since, and its age says nothing (a hung daemon read
        # HEALTHY, "-3586 s old": a review's finding)
        return EXIT_NOT_RUNNING, f"STALE (written {-age:.0f} s in the future: the clock stepped back; cannot tell)"
    if status.get("healthy"):
        return EXIT_HEALTHY, "HEALTHY"
    state = str(status.get("state", "unhealthy")).upper()
    return EXIT_UNHEALTHY, state if state in ("STARTING", "WAITING FOR VISION", "DEGRADED") else "UNHEALTHY"


def _fmt(v: Any, unit: str = "", nd: int = 1) -> str:
    if v is None:
        return "-"
    if isinstance(v, float):
        return f"{v:.{nd}f}{unit}"
    return f"{v}{unit}"


def _checkpoint_text(lp: dict[str, Any]) -> str:
    """The map checkpoints of a daemon with `[map] save` (nothing from one without, or an older daemon)."""
    if "map_checkpoints" not in lp:
        return ""
    if lp.get("map_checkpoint_error"):
        return f", map checkpoint FAILING: {lp['map_checkpoint_error']}"
    if not lp.get("map_checkpoints"):
        return ", no map checkpoint yet"
    return f", map checkpoint {_fmt(lp.get('map_checkpoint_age_s'), ' s')} old ({lp['map_checkpoints']} written)"


def _withheld_text(mav: dict[str, Any]) -> str:
    """The states the MAVLink output held back on the daemon's word and why (the IMU clock; nothing before any)."""
    n = mav.get("states_withheld")
    if not n:
        return ""
    return f", withheld {n} ({mav.get('withholding_for') or mav.get('withheld_for') or 'no reason given'})"


def _link_closed_text(mav: dict[str, Any]) -> str:
    """The states that found no connection to the autopilot (nothing when none did, or an older daemon)."""
    n = mav.get("states_link_closed")
    return f", not sent with the link closed {n}" if n else ""


def format_status(s: dict[str, Any], verdict: str, now_unix: float) -> str:
    """Readable multi-line report; every field tolerates absence (an older daemon, a starting one)."""
    def section(key: str) -> dict:  # absent, null or of another type: an older, starting or foreign daemon
        v = s.get(key)
        return v if isinstance(v, dict) else {}

    r, e, src, mav, lat = (section(k) for k in ("rates_hz", "estimator", "source", "mavlink", "latency_ms"))
    up = float(s.get("uptime_s") or 0)
    written = _written_unix(s)
    written = now_unix if written is None else written
    lines = [
        f"kestrel-vio: {verdict}   state {s.get('state')}   pid {s.get('pid')}   "
        f"up {int(up // 3600)}h{int(up % 3600 // 60):02d}m{int(up % 60):02d}s   "
        f"(status {now_unix - float(written):.1f} s old)",
        f"  sensors   {src.get('kind', '-')}: {'connected' if src.get('connected') else 'NOT DELIVERING'}, "
        f"camera {_fmt(r.get('camera'), ' Hz')}, IMU {_fmt(r.get('imu'), ' Hz', 0)}, "
        f"disconnects {_fmt(src.get('disconnects'))}, frames dropped {_fmt(src.get('frames_dropped'))}, "
        f"IMU lost {_fmt(src.get('imu_overflow'))}",
        f"  estimator {_fmt(r.get('estimator'), ' Hz')}, tracking {_fmt(e.get('tracking'))}"
        f"{'' if e.get('initialized') in (None, True) else ' (not initialised)'}, "
        f"quality {_fmt(e.get('quality'))}, tracks {_fmt(e.get('tracks'))}, "
        f"resets {_fmt(e.get('resets', e.get('reset_counter')))} (daemon-forced {_fmt(e.get('daemon_resets'))}), "
        f"last pose {_fmt(e.get('last_pose_age_s'), ' s ago', 2)}",
        f"  position  {e.get('position_m') or '-'} m (world, z up)   "
        f"latency frame->output p50 {_fmt(lat.get('p50'), ' ms')} max {_fmt(lat.get('max'), ' ms')}",
        f"  mavlink   link {mav.get('state', '-')}, sent {_fmt(mav.get('sent'))}, "
        f"output {_fmt(r.get('output'), ' Hz')}, errors {_fmt(mav.get('errors'))}{_withheld_text(mav)}"
        f"{_link_closed_text(mav)}"
        if mav.get("state") != "off" else
        "  mavlink   OFF: [mavlink] url is empty, no pose goes to an autopilot",
    ]
    if mav.get("land_after_loss_s"):
        lines.append(f"  failsafe  LAND after {_fmt(mav.get('land_after_loss_s'), ' s')} of lost vision: "
                     f"requests {_fmt(mav.get('land_requests'))}, accepted {_fmt(mav.get('land_accepted'))}")
    unusable = e.get("unusable_reasons") or {}
    if e.get("frames_unusable") or e.get("imu_rejected"):
        reasons = ", ".join(f"{k} x{n}" for k, n in sorted(unusable.items(), key=lambda kv: -kv[1])[:3])
        reasons = f" ({reasons})" if reasons else ""
        lines.append(f"  inputs    unusable frames {_fmt(e.get('frames_unusable'))}{reasons}, "
                     f"IMU samples rejected {_fmt(e.get('imu_rejected'))}, frames dropped by the estimator "
                     f"{_fmt(e.get('frames_dropped'))}")
    lp = s.get("loop")
    if lp:
        where = {True: ", in the map", False: ", NOT in the map yet"}.get(lp.get("relocalised"), "")
        if lp.get("placement_sigma_m") is not None:
            where += f" +-{100 * float(lp['placement_sigma_m']):.1f} cm"
        walk = ""
        if lp.get("blend_remaining_m") is not None:
            walk = (f", blend still to go {_fmt(lp.get('blend_remaining_m'), ' m', 2)} "
                    f"{_fmt(lp.get('blend_remaining_deg'), ' deg')}")
        lines.append(f"  loop      output {lp.get('output', '-')}, keyframes {_fmt(lp.get('keyframes'))}, edges "
                     f"{_fmt(lp.get('loop_edges'))} ({_fmt(lp.get('switched_off'))} switched off){where}, "
                     f"jumps {_fmt(lp.get('loop_jumps'))}{walk}"
                     + (f", map of {lp['map_keyframes']} keyframes" if lp.get("map_keyframes") else "")
                     + _checkpoint_text(lp)
                     + (f", STOPPED: {lp['error']}" if lp.get("error") else ""))
    rec = s.get("recording")
    if rec:
        failed = f": {rec.get('error')}" if rec.get("error") else ""
        lines.append(f"  recording {rec.get('state', 'recording')}{failed}, {rec.get('dir')}: {rec.get('frames')} "
                     f"frames, {rec.get('imu')} IMU, {rec.get('frames_dropped')} frames dropped")
    traj = s.get("trajectory_file")
    if traj:
        failed = f": {traj.get('error')}" if traj.get("error") else ""
        lines.append(f"  poses log {traj.get('state')}{failed}, {traj.get('path')}: {traj.get('poses')} poses")
    wd = s.get("watchdog") or {}
    lines.append(f"  watchdog  {'on' if wd.get('enabled') else 'off (not under systemd)'}"
                 f"{', fed' if wd.get('fed') else ', NOT fed' if wd.get('enabled') else ''}")
    for w in s.get("warnings") or []:
        lines.append(f"  WARNING   {w}")
    if s.get("state") == "stopped":
        lines.append("  (stopped: the figures above are the last ones before the stop, not the vehicle's now)")
    elif s.get("state") == "not running":
        lines.append(f"  (not running: the figures above are the last ones it wrote, in state "
                     f"{s.get('last_written_state')!r}, not the vehicle's now)")
    return "\n".join(lines)


def _status_path(args: argparse.Namespace) -> Path | None:
    """The status file to read; None when --config names a configuration that writes none ([run] status_file
    empty)."""
    if args.file:
        return Path(args.file)
    if args.config:
        from vio.config import load_config

        status_file = load_config(args.config).run.status_file
        return Path(status_file) if status_file else None
    return Path(DEFAULT_STATUS_FILE)


def _user() -> str:
    """This process's user name (the one os.access checked for), or its uid."""
    try:
        import pwd

        return pwd.getpwuid(os.geteuid()).pw_name
    except (ImportError, KeyError):
        return str(os.geteuid())


def missing_file_text(path: Path) -> str:
    """The verdict line for a missing status file: its folder is missing (service not started), or cannot be
    written (a running daemon never writes its status there: "is the service started?" sent people looking at a
    service that was running), or the service has not written it yet."""
    folder = path.parent
    if not folder.is_dir():
        return (f"NOT RUNNING ({folder} does not exist, so no status file {path.name}; is the service started? "
                "try: systemctl status kestrel-vio)")
    if not os.access(folder, os.W_OK):
        return (f"UNKNOWN ({path} does not exist and {folder} is not writable by user {_user()}: a daemon running "
                "as that user cannot write its status there; check its log: journalctl -u kestrel-vio)")
    return f"NOT RUNNING ({path} does not exist; is the service started? try: systemctl status kestrel-vio)"


def _no_status(args: argparse.Namespace, state: str, text: str, code: int = EXIT_NOT_RUNNING) -> int:
    """No status to show: the line on stderr, and with --json an object on stdout too, so that a script reading
    `vio status --json` (a health check piping it to jq) gets the state rather than nothing."""
    print(f"kestrel-vio: {text}", file=sys.stderr)
    if args.json:
        print(json.dumps({"state": state, "healthy": False, "verdict": text}, indent=1))
    return code


def run(args: argparse.Namespace) -> int:
    from vio import VioError
    from vio.app.cli import EXIT_CONFIG

    try:
        path = _status_path(args)
    except VioError as e:
        # exit 1 (the CLI's for any error) read as "degraded" to a script watching the exit code (an integrator's
        # walk-through): a configuration that cannot be read is EXIT_CONFIG, as for vio run and vio config check
        return _no_status(args, "unknown", f"UNKNOWN (--config: {e})", EXIT_CONFIG)
    if path is None:  # read as '.': "cannot read status: Is a directory"
        return _no_status(args, "unknown", f"UNKNOWN ([run] status_file is empty in {args.config}: a daemon with "
                          "this configuration writes no status file; set one to use vio status)")
    try:
        status = read_status(path)
    except FileNotFoundError:
        text = missing_file_text(path)
        return _no_status(args, "not running" if text.startswith("NOT RUNNING") else "unknown", text)
    except (OSError, ValueError) as e:
        return _no_status(args, "unknown", f"UNKNOWN ({path}: cannot read status: {e})")
    now = time.time()
    code, verdict = evaluate(status, now, args.stale_s)
    gone = code == EXIT_NOT_RUNNING and status.get("state") != "stopped"
    if status.get("state") == "stopped" and isinstance(status.get("estimator"), dict):
        status = {**status, "estimator": {**status["estimator"], "tracking": False}}  # one written before 2026-12-07
    if args.json:
        print(json.dumps(_not_running(status, verdict) if gone else status, indent=1))
    else:
        try:
            text = format_status(_not_running(status, verdict) if gone else status, verdict, now)
        except (TypeError, ValueError, AttributeError) as e:  # a field of another type: a file not ours
            print(f"kestrel-vio: UNKNOWN ({path}: cannot read status: {type(e).__name__}: {e})", file=sys.stderr)
            return EXIT_NOT_RUNNING
        print(text)
    return code


def _not_running(status: dict[str, Any], verdict: str) -> dict[str, Any]:
    """The daemon's last word, from a process that is gone or hung: its "tracking" and state are no longer true (a
    review's finding: --json said degraded and tracking after a kill -9, and the text said so too: a QA sweep);
    the rest is kept."""
    return {**status, "state": "not running", "healthy": False, "verdict": verdict,
            "last_written_state": status.get("state"),
            "estimator": {**(status.get("estimator") if isinstance(status.get("estimator"), dict) else {}),
                          "tracking": False}}
