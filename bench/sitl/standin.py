"""A stand-in for the SITL's streams, to check the harness's conventions before a SITL exists: NOT a flight test.

    python -m bench.sitl.standin --seconds 40 --out runs/standin

It plays one of the project's own simulated flights (vio/sim, 'survey', clean IMU) as an ArduPilot SITL would
show it: HEARTBEAT and HIGHRES_IMU (FRD body, 200 Hz, time_usec on its own boot clock) plus TIMESYNC answers
on tcp 5762 (Kestrel's autopilot link), SIM_STATE (FRD body in NED, lat/lon 1e-7 deg) on tcp 5763 (the
camera's truth link). It starts `vio run` with the harness's own config (bench/sitl/run.py) and at the end
compares Kestrel's trajectory with the flight's truth. The vehicle does not react to anything (open loop):
what it checks is that the camera source's pose conversion, the IMU source's FRD axes and units, both
stamp paths and the daemon fit together, so that the estimator tracks. A sign error in any of them shows
as a failed or drifting estimate here instead of a crash in the SITL.
"""

from __future__ import annotations

import argparse
import math
import os
import shutil
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np

from bench.sitl.run import HOME, kestrel_config
from drivers.sitl_camera import EARTH_RADIUS_M, HOME_WORLD_M, R_FRD_FLU, R_WORLD_NED
from vio.geometry import rot_to_quat_wxyz


def _serve(port: str):
    from pymavlink import mavutil

    return mavutil.mavlink_connection(f"tcpin:127.0.0.1:{port}", source_system=1, source_component=1,
                                      dialect="ardupilotmega")


def play(seconds: float, stop: threading.Event) -> tuple[np.ndarray, np.ndarray]:
    """Serve the streams in real time until `seconds` or `stop`; returns (host stamps of truth, T_world_body)."""
    from vio.sim.generate import SimConfig, build

    sim = build(SimConfig(profile="survey", duration_s=seconds + 5, variant="clean", imu_rate_hz=200.0,
                          width=64, height=48))
    imu_link, truth_link = _serve("5762"), _serve("5763")
    t0 = time.monotonic_ns()
    boot_us0 = 12_345_678  # the autopilot's clock: its own origin, not the host's
    k_imu = 0
    next_truth, next_hb = 0.0, 0.0
    host_t, poses = [], []
    cos_lat = math.cos(math.radians(HOME[0]))
    while not stop.is_set():
        t = (time.monotonic_ns() - t0) * 1e-9
        if t > seconds:
            break
        while k_imu < len(sim.imu.t_s) and sim.imu.t_s[k_imu] <= t:
            g = R_FRD_FLU @ sim.imu.gyro[k_imu]
            a = R_FRD_FLU @ sim.imu.accel[k_imu]
            imu_link.mav.highres_imu_send(boot_us0 + int(sim.imu.t_s[k_imu] * 1e6), *a, *g, 0, 0, 0, 1013.0, 0, 0,
                                          20.0, 0x3F)
            k_imu += 1
        if t >= next_hb:
            for link in (imu_link, truth_link):
                link.mav.heartbeat_send(2, 3, 0, 0, 3)  # quadrotor, ArduPilot
            next_hb += 1.0
        if t >= next_truth:
            T = sim.motion.pose(np.array([t]))[0]
            R_ned_frd = R_WORLD_NED @ T[:3, :3] @ R_FRD_FLU
            ned = R_WORLD_NED @ (T[:3, 3] - HOME_WORLD_M)
            lat = HOME[0] + math.degrees(ned[0] / EARTH_RADIUS_M)
            lon = HOME[1] + math.degrees(ned[1] / (EARTH_RADIUS_M * cos_lat))
            truth_link.mav.sim_state_send(*rot_to_quat_wxyz(R_ned_frd), 0, 0, 0, 0, 0, 0, 0, 0, 0, lat, lon,
                                          HOME[2] - ned[2], 0, 0, 0, 0, 0, int(round(lat * 1e7)), int(round(lon * 1e7)))
            host_t.append(time.monotonic_ns())
            poses.append(T @ np.diag([1.0, -1.0, -1.0, 1.0]))  # FLU body -> the FRD body the estimator uses
            next_truth += 1 / 30
        while (m := imu_link.recv_match(type="TIMESYNC", blocking=False)) is not None:
            if m.tc1 == 0:
                imu_link.mav.timesync_send((boot_us0 + int(t * 1e6)) * 1000, m.ts1)
        for link in (imu_link, truth_link):
            link.recv_match(blocking=False)  # drain (requests are not needed: the streams are always on)
        time.sleep(0.002)
    return np.array(host_t), np.array(poses)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=40.0)
    ap.add_argument("--out", default="runs/standin")
    ap.add_argument("--fps", type=float, default=15.0)
    args = ap.parse_args(argv)
    os.environ["MAVLINK20"] = "1"
    out = Path(args.out).resolve()
    shutil.rmtree(out, ignore_errors=True)
    out.mkdir(parents=True)
    cfg = kestrel_config(out, args.fps, 320, 200)
    stop = threading.Event()
    result: dict = {}
    player = threading.Thread(target=lambda: result.update(zip(("t", "T"), play(args.seconds, stop))), daemon=True)
    player.start()
    time.sleep(1.0)
    daemon = subprocess.Popen([sys.executable, "-m", "vio.app.cli", "run", "--config", str(cfg)],
                              stdout=open(out / "kestrel.log", "w"), stderr=subprocess.STDOUT)
    player.join(args.seconds + 60)
    stop.set()
    daemon.terminate()
    daemon.wait(10)
    from vio.evaluation import evaluate
    from vio.trajectory import Trajectory, read_tum

    est = out / "kestrel.tum"
    if not est.exists() or est.stat().st_size == 0:
        print(f"no estimate: see {out / 'kestrel.log'}", file=sys.stderr)
        return 1
    res = evaluate(read_tum(est), Trajectory.from_poses(result["t"], result["T"]), interpolate=True, crop_gt=True)
    print(f"stand-in check: {res.n_matched} poses, coverage {res.coverage:.2f}, ATE 4-DoF "
          f"{res.ate_4dof.trans_m.rmse:.3f} m RMS (max {res.ate_4dof.trans_m.max:.3f}), path {res.path_length_m:.1f} m")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
