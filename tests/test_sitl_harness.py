"""The closed-loop SITL harness's pieces (bench/sitl/, drivers/sitl_camera.py), without a SITL.

The one test that needs an ArduCopter SITL binary skips when there is none (CI has none)."""

from __future__ import annotations

import logging
import math
import os
import threading
import time

import numpy as np
import pytest

os.environ["MAVLINK20"] = "1"
from pymavlink.dialects.v20 import ardupilotmega as mav  # noqa: E402

from bench.sitl import mission as msn  # noqa: E402
from bench.sitl import report as rep  # noqa: E402
from bench.sitl.run import DEFAULT_BIN, HOME, main  # noqa: E402
from drivers.sitl_camera import (  # noqa: E402
    EARTH_RADIUS_M,
    HOME_WORLD_M,
    SitlCameraSource,
    T_world_body_from_sim,
    frd_calibration,
    ned_from_geodetic,
    world_from_ned,
)
from vio import VioError  # noqa: E402
from vio.config import config_from_dict  # noqa: E402
from vio.geometry import make_T, rot_to_quat_wxyz  # noqa: E402
from vio.sim.scene import default_scene  # noqa: E402


def _rz(yaw: float) -> np.ndarray:
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _sim_state(q_wxyz, ned) -> mav.MAVLink_sim_state_message:
    """A SIM_STATE as ArduPilot's SITL sends it for an NED offset from HOME (inverse of the flat-earth map)."""
    lat = HOME[0] + math.degrees(ned[0] / EARTH_RADIUS_M)
    lon = HOME[1] + math.degrees(ned[1] / (EARTH_RADIUS_M * math.cos(math.radians(HOME[0]))))
    return mav.MAVLink_sim_state_message(*q_wxyz, 0, 0, 0, 0, 0, -9.81, 0, 0, 0, lat, lon, HOME[2] - ned[2], 0, 0,
                                         0, 0, 0, int(round(lat * 1e7)), int(round(lon * 1e7)))


def test_geodetic_offsets_and_world_axes():
    lat, lon, alt = HOME
    ned = ned_from_geodetic(HOME, int(round((lat + 1e-5) * 1e7)), int(round((lon + 2e-5) * 1e7)), alt + 1.5)
    assert ned[0] == pytest.approx(math.radians(1e-5) * EARTH_RADIUS_M, abs=0.01)  # ~1.11 m north
    assert ned[1] == pytest.approx(math.radians(2e-5) * EARTH_RADIUS_M * math.cos(math.radians(lat)), abs=0.01)
    assert ned[2] == pytest.approx(-1.5)
    np.testing.assert_allclose(world_from_ned([0, 0, 0]), HOME_WORLD_M)
    # north = world x, east = world -y, down = world -z
    np.testing.assert_allclose(world_from_ned([1.0, 2.0, -3.0]) - HOME_WORLD_M, [1.0, -2.0, 3.0])


def test_attitude_frd_in_world():
    # level, nose north: FRD x along world x, FRD y (right = east) along world -y, FRD z (down) along world -z
    T = T_world_body_from_sim([1.0, 0, 0, 0], np.zeros(3))
    np.testing.assert_allclose(T[:3, :3], np.diag([1.0, -1.0, -1.0]), atol=1e-12)
    # nose east (yaw +90 deg about down): forward is world -y
    q_east = rot_to_quat_wxyz(_rz(math.pi / 2))
    T = T_world_body_from_sim(q_east, np.array([0.0, 0.0, -1.0]))
    np.testing.assert_allclose(T[:3, 0], [0.0, -1.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(T[:3, 3], HOME_WORLD_M + [0, 0, 1.0])


def test_camera_extrinsics_on_frd_body():
    cal = frd_calibration(320, 200, 15.0)
    for cam in (cal.cam0, cal.cam1):
        R = cam.T_body_cam[:3, :3]  # columns: camera x (image right), y (image down), z (optical axis) in FRD
        assert R[:, 2] @ [1, 0, 0] > math.cos(math.radians(3))  # looks forward
        assert R[:, 0] @ [0, 1, 0] > math.cos(math.radians(3))  # image right = vehicle right
        assert R[:, 1] @ [0, 0, 1] > math.cos(math.radians(3))  # image down = vehicle down
    assert cal.baseline_m == pytest.approx(0.11, abs=0.005)
    assert cal.cam0.width == 320 and cal.cam0.height == 200


def test_rendered_frame_shows_the_scene_where_the_calibration_projects_it():
    """A point on the wall ahead of the vehicle, projected with the calibration, has the depth of that wall:
    pose, extrinsics and renderer agree (a wrong FRD/FLU or NED/ENU step would look at the floor or ceiling)."""
    src = SitlCameraSource("tcp:unused", HOME, width=160, height=100, fps=15.0)
    T_wb = T_world_body_from_sim([1.0, 0, 0, 0], np.array([0.0, 0.0, -1.5]))  # 1.5 m up, nose north (+x)
    cam = src.calibration().cam0
    T_wc = T_wb @ cam.T_body_cam
    renderer = src._renderers()[0][0]
    _, depth, _ = renderer.render(T_wc)
    # the room's +x wall is at x = 5; the optical axis points along +x from x ~ 0
    centre = depth[50, 80]
    assert 4.0 < centre < 5.2
    frame = src.render(T_wb, 123)
    assert frame.left.dtype == np.uint8 and frame.left.std() > 5 and frame.t_ns == 123
    scene = default_scene()
    assert scene.contains(T_wb[:3, 3][None], margin=0.5)[0]


def test_frames_follow_the_camera_rate_and_blackout(tmp_path):
    flag = tmp_path / "blackout"
    src = SitlCameraSource("tcp:unused", HOME, width=96, height=64, fps=10.0, blackout_file=str(flag))
    msg = _sim_state([1.0, 0, 0, 0], [0.5, -0.3, -1.2])
    frames = [f for k in range(50) if (f := src.on_sim_state(msg, 1_000_000_000 + k * 20_000_000)) is not None]
    assert len(frames) in (10, 11)  # 1 s of 50 Hz SIM_STATE -> 10 frames at 10 Hz (a state a quarter period early)
    assert np.diff([f.t_ns for f in frames]).min() >= 75_000_000
    # a stream at the camera rate, its states a few ms early or late: every one a frame
    steady = SitlCameraSource("tcp:unused", HOME, width=32, height=24, fps=10.0)
    arrivals = 5_000_000_000 + np.arange(30) * 100_000_000 + np.random.default_rng(1).integers(-8, 8, 30) * 1_000_000
    assert sum(steady.on_sim_state(msg, int(t)) is not None for t in arrivals) == 30
    np.testing.assert_allclose(src.last_T_world_body[:3, 3], world_from_ned([0.5, -0.3, -1.2]), atol=0.02)
    assert frames[-1].left.mean() > 20
    flag.touch()
    black = src.on_sim_state(msg, 3_000_000_000)
    assert black is not None and black.left.max() == 0 and black.right.max() == 0
    assert src.health()["frames_black"] == 1 and src.health()["blackout"]
    flag.unlink()
    assert src.on_sim_state(msg, 3_200_000_000).left.max() > 0


def test_bad_home_is_a_clear_error():
    with pytest.raises(VioError, match="sitl_home"):
        SitlCameraSource("tcp:x", (float("nan"), 0.0, 0.0))


def test_config_refuses_a_sitl_home_that_is_no_place():
    """['a', 0, 0] passed `vio config check` and stopped the source at its start (float('a')); a latitude of 1e300
    or 91 deg passed unsaid (a review's finding)."""
    base = {"kind": "sitl", "imu": "mavlink", "sitl_url": "tcp:127.0.0.1:5763"}
    for home in (["a", 0, 0], [1e300, 0, 0], [91.0, 0, 0], [0, 181.0, 0], [0, 0, 1e6], [True, 0, 0]):
        with pytest.raises(VioError, match=r"sitl_home must be \[lat_deg, lon_deg, alt_m\] \(latitude within"):
            config_from_dict({"source": {**base, "sitl_home": home}, "mavlink": {"url": "tcp:127.0.0.1:5762"}})


def test_config_sitl_needs_the_autopilot_imu():
    with pytest.raises(VioError, match="imu = 'mavlink'"):
        config_from_dict({"source": {"kind": "sitl", "imu": "oak"}})
    cfg = config_from_dict({"source": {"kind": "sitl", "imu": "mavlink", "sitl_url": "tcp:127.0.0.1:5763"},
                           "mavlink": {"url": "tcp:127.0.0.1:5762"}})
    assert cfg.source.kind == "sitl"


def test_path_timing():
    p = msn.Path(np.array([[0.0, 0, -1], [2.0, 0, -1], [2.0, 1.0, -1]]), speed_m_s=0.5, dwell_s=1.0)
    assert p.duration_s == pytest.approx(1 + 4 + 1 + 2 + 1)
    pos, vel = p.target(0.5)
    np.testing.assert_allclose(pos, [0, 0, -1])
    np.testing.assert_allclose(vel, 0)
    pos, vel = p.target(3.0)  # half way along the first leg
    np.testing.assert_allclose(pos, [1.0, 0, -1])
    np.testing.assert_allclose(vel, [0.5, 0, 0])
    np.testing.assert_allclose(p.target(100.0)[0], [2.0, 1.0, -1])


def test_missions_stay_in_the_room_and_last_about_three_minutes():
    path = msn.chain(msn.box(laps=2), msn.figure_eight(laps=2))
    assert 180 < path.duration_s < 300
    scene = default_scene()
    world = world_from_ned(path.positions(np.linspace(0, path.duration_s, 400)))
    assert scene.contains(world, margin=0.8).all()
    np.testing.assert_allclose(path.waypoints[0], path.waypoints[-1], atol=1e-9)  # ends over the take-off point


def test_distance_to_polyline():
    line = np.array([[0.0, 0, 0], [2.0, 0, 0], [2.0, 2.0, 0]])
    pts = np.array([[1.0, 0.5, 0], [3.0, 1.0, 0], [-1.0, 0, 0], [2.0, 2.0, 1.0]])
    np.testing.assert_allclose(rep.distance_to_polyline(pts, line), [0.5, 1.0, 1.0, 1.0])


def test_start_alignment_recovers_yaw_and_offset():
    rng = np.random.default_rng(0)
    p_local = rng.normal(size=(50, 3)) * 0.01
    yaw_local = rng.normal(size=50) * 0.01 + 3.1  # near the +-pi wrap
    true = rep.Alignment(0.3, np.array([1.0, -2.0, 0.5]))
    a = rep.start_alignment(p_local, yaw_local, true.apply(p_local), rep.wrap_pi(yaw_local + 0.3))
    assert a.yaw == pytest.approx(0.3, abs=1e-9)
    np.testing.assert_allclose(a.t, true.t, atol=1e-9)


def test_recovery_and_ratio_stats_and_failsafes():
    t = np.arange(10) * 1_000_000_000
    truth = np.zeros((10, 3))
    truth[7] = [0.0, 1.2, 0.0]
    expected = np.zeros((10, 3))
    assert rep.recovery_error(t, truth, expected, (0, 5_000_000_000)) == 0.0
    assert rep.recovery_error(t, truth, expected, (6_000_000_000, 9_000_000_000)) == pytest.approx(1.2)
    assert math.isnan(rep.recovery_error(t, truth, expected, (20_000_000_000, 30_000_000_000)))
    r = rep.ratio_stats(np.array([0.1, 0.5, 1.5, np.nan]))
    assert r["n"] == 3 and r["outside_gate"] == 1 and r["max"] == 1.5
    ev = rep.failsafe_events([(1, "EKF3 IMU0 is using external nav data"), (2, "EKF Failsafe: changed to LAND Mode")])
    assert ev == [(2, "EKF Failsafe: changed to LAND Mode")]
    md = rep.markdown({"a": 1.23456, "b": {"rms": 0.5}, "c": []})
    assert "| a | 1.235 |" in md and "rms 0.500" in md and "| c | none |" in md


def test_blackout_hold_is_measured_from_where_the_blackout_began():
    t = np.arange(20) * 500_000_000
    p = np.zeros((20, 3))
    p[4:, 0] = 5.0  # somewhere else before the blackout: must not count
    p[8:, 1] = np.minimum(np.arange(12) * 0.1, 0.6)  # drifts 0.6 m east while blind, descends 1 m
    p[8:, 2] = np.linspace(0.0, 1.0, 12)
    h = rep.blackout_hold(t, p, (t[8], t[15]))
    assert h["n"] == 8 and h["horizontal_max_m"] == pytest.approx(0.6) and h["down_end_m"] == pytest.approx(7 / 11)
    assert rep.landed_offset(t, p, t[8], t[-1]) == pytest.approx(0.6)
    assert rep.blackout_hold(t, p, (t[-1] + 1, t[-1] + 2)) == {"n": 0}


def test_kestrel_is_aligned_once_per_reset_segment():
    """Two segments of one flight, the second in a new Kestrel frame (a reset: turned 90 deg, shifted 3 m):
    one alignment per segment gives ~0 error, one alignment across the reset does not."""
    from vio.evaluation import align_4dof

    t = np.arange(200) * 50_000_000
    gt = np.stack([np.cos(t * 1e-9), np.sin(2 * t * 1e-9), 0.1 * t * 1e-9], axis=1)
    est = gt.copy()
    est[100:] = est[100:] @ _rz(math.pi / 2).T + [3.0, 0.0, 0.0]
    seg = rep.segment_ids(t, [t[100] - 1])
    assert list(np.unique(seg, return_counts=True)[1]) == [100, 100]
    r = rep.per_segment_error(est, gt, seg)
    assert r["segments"] == 2 and r["rmse"] < 1e-9
    T = align_4dof(est, gt)
    assert np.sqrt(np.mean(np.sum((est @ T[:3, :3].T + T[:3, 3] - gt) ** 2, axis=1))) > 0.5
    # a gap in the estimate (no poses while lost) also splits, without a recorded reset
    t_gap = np.concatenate([t[:100], t[100:] + 2_000_000_000])
    assert list(np.unique(rep.segment_ids(t_gap), return_counts=True)[1]) == [100, 100]
    short = rep.per_segment_error(est, gt, rep.segment_ids(t, [t[195]]))
    assert short["per_segment"][-1] == {"poses": 5, "rmse": None}


def test_run_without_a_sitl_binary_says_so(tmp_path, capsys):
    assert main(["--sitl-bin", str(tmp_path / "nope"), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "no SITL binary" in err[0]


def test_kestrel_land_after_loss_reaches_the_daemon_config(tmp_path):
    from bench.sitl.run import kestrel_config
    from vio.config import load_config

    assert load_config(kestrel_config(tmp_path, 15.0, 320, 200)).mavlink.land_after_loss_s == 0.0
    assert load_config(kestrel_config(tmp_path, 15.0, 320, 200, 3.0)).mavlink.land_after_loss_s == 3.0


def test_record_makes_the_daemon_record_what_it_received(tmp_path):
    """raw.npz holds only the harness's streams: a drifting flight could not be replayed. --record has the daemon
    record its frames and IMU (EuRoC) in the run folder; off by default (disk writes beside a real-time SITL)."""
    from bench.sitl.run import kestrel_config
    from vio.config import load_config

    assert load_config(kestrel_config(tmp_path, 15.0, 320, 200)).run.record_dir == ""
    cfg = load_config(kestrel_config(tmp_path, 15.0, 320, 200, record=True))
    assert cfg.run.record_dir == str(tmp_path / "record") and cfg.run.record_format == "euroc"


def test_bad_ap_param_is_a_one_line_error(tmp_path, capsys):
    assert main(["--sitl-bin", "/bin/true", "--ap-param", "FS_EKF_THRESH", "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "NAME=NUMBER" in err[0]


@pytest.mark.skipif(not os.environ.get("KESTREL_SITL_BIN") or not os.access(DEFAULT_BIN, os.X_OK),
                    reason="opt-in: set KESTREL_SITL_BIN to an ArduCopter SITL binary (it takes the fixed "
                           "ports 5760-5763, so it is never run by default)")
def test_sitl_boots_and_streams_truth(tmp_path):
    """With a SITL binary: it boots with the harness's parameters and SIM_STATE reaches the camera source."""
    from bench.sitl.run import start_sitl

    proc = start_sitl(DEFAULT_BIN, tmp_path)
    try:
        from pymavlink import mavutil

        gcs = mavutil.mavlink_connection("tcp:127.0.0.1:5760", source_system=250, retries=30)
        assert gcs.wait_heartbeat(timeout=60) is not None
        src = SitlCameraSource("tcp:127.0.0.1:5763", HOME, width=96, height=64, fps=5.0)
        src.start()
        deadline = time.monotonic() + 30
        while src.states == 0 and time.monotonic() < deadline:
            time.sleep(0.5)
        src.stop()
        assert src.states > 0
        np.testing.assert_allclose(src.last_T_world_body[:3, 3], HOME_WORLD_M, atol=0.5)
    finally:
        proc.terminate()
        proc.wait(10)


def _free_udp_port() -> int:
    import socket

    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_source_reads_a_sim_state_stream_over_mavlink():
    """The threaded path: the source asks for SIM_STATE (MAV_CMD_SET_MESSAGE_INTERVAL 108) and turns a 40 Hz
    stream from a stand-in autopilot (pymavlink over UDP loopback) into frames at its 10 Hz camera rate."""
    from pymavlink import mavutil

    port = _free_udp_port()
    src = SitlCameraSource(f"udpin:127.0.0.1:{port}", HOME, width=64, height=48, fps=10.0)
    src.start()
    fc = mavutil.mavlink_connection(f"udpout:127.0.0.1:{port}", source_system=1, source_component=1)
    try:
        requested, frames = [], []
        deadline = time.monotonic() + 20
        t_first = None
        while time.monotonic() < deadline and (t_first is None or time.monotonic() - t_first < 1.5):
            q = rot_to_quat_wxyz(_rz(0.2))
            fc.mav.send(_sim_state(q, [1.0, 0.5, -1.0]))
            while (m := fc.recv_match(type="COMMAND_LONG", blocking=False)) is not None:
                requested.append((m.command, m.param1, m.param2))
            frames += src.poll()
            if frames and t_first is None:
                t_first = time.monotonic()
            time.sleep(0.025)
        frames += src.poll()
    finally:
        src.stop()
        fc.close()
    assert (511, 108.0, pytest.approx(100_000.0)) in [(c, p1, p2) for c, p1, p2 in requested]
    assert 8 <= len(frames) <= 20  # ~1.5 s at 10 Hz (SIM_STATE at 40 Hz, thinned)
    assert src.health()["sim_states"] > len(frames)
    np.testing.assert_allclose(src.last_T_world_body[:3, 3], world_from_ned([1.0, 0.5, -1.0]), atol=0.02)


def test_open_source_combines_the_sitl_camera_with_the_autopilot_imu():
    from drivers.base import CombinedSource
    from drivers.mavlink_imu import MavlinkImuSource
    from drivers.mavlink_link import MavlinkLink
    from drivers.source import open_source

    cfg = config_from_dict({"source": {"kind": "sitl", "imu": "mavlink", "width": 96, "height": 64},
                            "mavlink": {"url": "tcp:127.0.0.1:5762"}})
    src = open_source(cfg.source, mavlink_link=MavlinkLink("tcp:127.0.0.1:5762"))  # nothing is opened yet
    assert isinstance(src, CombinedSource)
    assert isinstance(src.camera, SitlCameraSource) and isinstance(src.imu, MavlinkImuSource)
    assert src.calibration().cam0.width == 96


def test_summary_of_a_perfect_synthetic_flight(tmp_path):
    """run.summarise on recorded streams made up from a vehicle that flies the path exactly, in an autopilot
    frame turned 30 deg and shifted from the truth NED: every error is ~0, the blackout recovers, Kestrel's
    trajectory (truth in its own yawed world) has ~0 ATE. A wrong alignment or stamp pairing shows here."""
    from types import SimpleNamespace

    from bench.sitl.run import summarise
    from vio.trajectory import Trajectory, write_tum

    path = msn.box(laps=1, speed_m_s=1.0, dwell_s=1.0)
    a = rep.Alignment(math.radians(30), np.array([0.4, -0.3, 0.0]))  # autopilot frame -> truth
    t0 = 10_000_000_000
    t_ns = np.arange(0, int((path.duration_s + 20) * 1e9), 50_000_000) + 5_000_000_000  # ground from 5 s
    local_p = np.array([path.target(max(0.0, (t - t0) * 1e-9))[0] if t >= t0 else [0.0, 0.0, 0.0] for t in t_ns])
    truth_p = a.apply(local_p)
    yaw_local = np.full(len(t_ns), 0.1)
    q = [rot_to_quat_wxyz(_rz(a.yaw + 0.1))] * len(t_ns)
    rec = SimpleNamespace(
        truth=[(t, *p, a.yaw + 0.1, *qq) for t, p, qq in zip(t_ns, truth_p, q)],
        local=[(t, *p) for t, p in zip(t_ns, local_p)], att=[(t, y) for t, y in zip(t_ns, yaw_local)],
        ekf=[(t, 0, 0.2, 0.3) for t in t_ns], text=[(t0, "EKF3 IMU0 is using external nav data")], modes=[(t0, 4)],
        odom=[])
    ev = {"t_ground": (5_000_000_000, 9_000_000_000), "t0": t0,
          "blackouts": [[t0 + 2_000_000_000, t0 + 4_000_000_000, 2.0]]}
    T_est = np.array([make_T(_rz(0.7) @ T[:3, :3], _rz(0.7) @ T[:3, 3] + [1, 2, 0])
                      for T in (T_world_body_from_sim(r[5:9], r[1:4]) for r in rec.truth)])
    write_tum(Trajectory.from_poses(t_ns, T_est), tmp_path / "kestrel.tum")
    s = summarise(rec, path, ev, tmp_path)
    assert s["vehicle cross-track error vs mission path [m]"]["max"] < 1e-6
    assert s["vehicle error vs timed setpoint [m]"]["max"] < 0.06  # 50 ms sampling of a 1 m/s path
    assert s["autopilot estimate (LOCAL_POSITION_NED) vs truth [m]"]["max"] < 1e-6
    assert s["EKF yaw/compass test ratio"]["outside_gate"] == 0
    assert s["failsafe STATUSTEXT"] == []
    assert s["blackout 2 s: max |truth - setpoint| 5-15 s after [m]"] < 0.06
    hold = s["blackout 2 s: drift from the blackout-start position while blind (truth) [m]"]
    moved = path.positions(np.array([2.0, 4.0]))
    # this synthetic vehicle flew on with the path during the blackout: it did not hold
    assert hold["horizontal_max_m"] == pytest.approx(np.linalg.norm(moved[1, :2] - moved[0, :2]), abs=0.06)
    k = s["Kestrel error vs SITL truth, 4-DoF aligned per reset segment [m]"]
    assert k["segments"] == 1 and k["rmse"] < 1e-3


def _truth_npz(path, t_s: np.ndarray, ned: np.ndarray, yaw: np.ndarray) -> None:
    """A raw.npz `truth` array as bench/sitl/run.py records it: t_ns, n, e, d, yaw, q1..q4 (FRD -> NED, w first)."""
    q = np.array([rot_to_quat_wxyz(_rz(y)) for y in yaw])  # a yaw about NED's down axis: FRD -> NED
    np.savez(path, truth=np.c_[(1_000_000_000 + t_s * 1e9).round(), ned, yaw, q])


def test_consistent_flight_imu_is_what_a_perfect_imu_reads_along_the_truth(tmp_path):
    """The perfect IMU bench/sitl/consistent_flight.py writes must be that of the truth it renders: a level
    vehicle accelerating north at 0.4 m/s^2 while yawing at 0.3 rad/s reads gyro (0, 0, 0.3) on its FRD body,
    and (R^T (a - g)) in its accelerometer: gravity on -z (FRD) and the acceleration turned into the body."""
    from bench.sitl.consistent_flight import TruthSplines

    t = np.arange(0.0, 6.0, 0.05)
    ned = np.c_[0.2 * t**2, np.zeros_like(t), np.full_like(t, -1.5)]
    _truth_npz(tmp_path / "raw.npz", t, ned, 0.3 * t)
    truth = TruthSplines(tmp_path / "raw.npz", lam=None)
    ts = np.array([2.0, 3.0, 4.0])
    gyro, accel = truth.imu(ts)
    assert np.allclose(gyro, [[0.0, 0.0, 0.3]] * 3, atol=2e-3)
    # north acceleration 0.4 m/s^2 in the FRD body yawed by 0.3 t: x = 0.4 cos, y = -0.4 sin; gravity reads -g on z
    expect = np.c_[0.4 * np.cos(0.3 * ts), -0.4 * np.sin(0.3 * ts), np.full(3, -9.80665)]
    assert np.allclose(accel, expect, atol=0.02), accel


def test_consistent_flight_quantises_to_sim_states_latitude_longitude_grid():
    """SIM_STATE's lat_int/lon_int are 1e-7 deg: 1.11 cm north, cos(lat) of that east; the tool's --quantise
    must land where a SIM_STATE position does after drivers/sitl_camera.py reads it back."""
    from bench.sitl.consistent_flight import quantised

    rng = np.random.default_rng(3)
    ned = np.c_[rng.uniform(-3, 3, 50), rng.uniform(-3, 3, 50), np.full(50, -1.2)]
    back = np.array([ned_from_geodetic(HOME, int(round((HOME[0] + math.degrees(n / EARTH_RADIUS_M)) * 1e7)),
                                       int(round((HOME[1] + math.degrees(e / (EARTH_RADIUS_M *
                                                                              math.cos(math.radians(HOME[0])))))
                                                 * 1e7)), HOME[2] - d) for n, e, d in ned])
    q = quantised(world_from_ned(ned), HOME[0])
    assert np.abs(q - world_from_ned(back))[:, :2].max() < 1e-6
    assert 0.004 < np.abs(q - world_from_ned(ned))[:, 0].max() <= 0.0056  # half a 1.11 cm step at most


def test_a_reader_error_that_is_not_an_oserror_reconnects_backed_off(monkeypatch, caplog):
    """The SIM_STATE reader thread caught OSError only: another error (pymavlink's ValueError on a bad packet, a bug)
    ended it with a thread traceback, the renderer saw it dead and reopened the link at once, over and over (17,572
    opens in 3 s, state 'running'). It is a lost link now: said, 'connecting', and backed off as a failed open is."""
    opens: list[int] = []
    died: list[object] = []
    monkeypatch.setattr(threading, "excepthook", died.append)

    class Conn:
        class mav:
            @staticmethod
            def command_long_send(*a) -> None: ...

        def recv_match(self, **kw):
            raise ValueError("bad packet length")

        def close(self) -> None: ...

    def connect(url: str) -> Conn:
        opens.append(1)
        return Conn()

    src = SitlCameraSource("tcp:unused", HOME, width=32, height=24, fps=10.0, connect=connect)
    monkeypatch.setattr(src, "_renderers", lambda: [])  # no scene needed: no state ever arrives
    with caplog.at_level(logging.WARNING, logger="drivers.sitl_camera"):
        src.start()
        time.sleep(1.0)
        state = src.state
        src.stop()
    assert died == [] and 1 <= len(opens) <= 3, (len(opens), died[:1])
    assert state == "connecting"
    assert "link to tcp:unused lost (ValueError: bad packet length); reconnecting in 0.5 s" in caplog.text
