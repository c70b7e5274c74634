"""MAVLink output: frame conversions against hand-derived truth, every sent message decoded by pymavlink
from a fake autopilot on UDP loopback, scheduling with a fake clock, and one real-time run for the rate,
heartbeat and link-loss contracts."""

from __future__ import annotations

import dataclasses
import logging
import math
import socket
import threading
import time

import numpy as np
import pytest

from drivers.mavlink_frames import (
    R_NED_WORLD,
    _axis_rotations,
    mount_rotation,
    mount_rpy_deg_from_matrix,
    mount_transform,
    to_vehicle_odometry,
    upper_triangle,
)
from drivers.mavlink_out import ORIGIN_MAX_SENDS, MavlinkOutput, mavlink, mavutil, restamp_to_host_clock
from vio import VioError
from vio.config import MavlinkConfig
from vio.geometry import make_T, so3_exp
from vio.types import NavState, covariance_quality

# A level vehicle whose FRD body looks along world x: body x = world x, y = -world y, z = -world z.
R_LEVEL = np.diag([1.0, -1.0, -1.0])
R_CAM_FWD = np.array([[0.0, 0, 1], [1, 0, 0], [0, 1, 0]])  # optical axes (right, down, forward) in FRD
R_CAM_DOWN = np.array([[0.0, -1, 0], [1, 0, 0], [0, 0, 1]])  # optical axes, image top towards the nose


def rot(axis: str, deg: float) -> np.ndarray:
    v = {"x": [1.0, 0, 0], "y": [0, 1.0, 0], "z": [0, 0, 1.0]}[axis]
    return so3_exp(np.radians(deg) * np.array(v))


def odom(R_wb: np.ndarray, p=(0, 0, 0), v=(0, 0, 0), w=(0, 0, 0), rpy=(0, 0, 0), off=(0, 0, 0),
         cov_pose=None, cov_vel=None):
    return to_vehicle_odometry(0, make_T(R_wb, np.array(p, float)), np.array(v, float), np.array(w, float),
                               np.eye(6) * 1e-2 if cov_pose is None else cov_pose,
                               np.eye(3) * 1e-2 if cov_vel is None else cov_vel, mount_transform(rpy, off))


def random_spd(n: int, seed: int) -> np.ndarray:
    A = np.random.default_rng(seed).normal(size=(n, n))
    return A @ A.T * 1e-3 + np.eye(n) * 1e-4


# ------------------------------------------------------------------ frames


def test_position_velocity_attitude_in_ned_for_known_orientations():
    o = odom(R_LEVEL, p=(1, 2, 3), v=(0.5, -1, 2))
    np.testing.assert_allclose(o.p_ned, [1, -2, -3])
    np.testing.assert_allclose(o.v_ned, [0.5, 1, -2])
    np.testing.assert_allclose(o.v_frd, [0.5, 1, -2])  # level, nose along world x: FRD == local NED axes
    np.testing.assert_allclose(o.rpy, [0, 0, 0], atol=1e-12)
    np.testing.assert_allclose(o.q_ned_frd_wxyz, [1, 0, 0, 0], atol=1e-12)
    # Turned left by 90 deg (counter-clockwise seen from above, world z up): yaw -90 deg in NED.
    o = odom(rot("z", 90) @ R_LEVEL, v=(0, 1, 0))
    np.testing.assert_allclose(np.degrees(o.rpy), [0, 0, -90], atol=1e-9)
    np.testing.assert_allclose(o.v_frd, [1, 0, 0], atol=1e-12)  # moving along its nose
    # Nose up 10 deg: a rotation about world -y (= FRD +y) -> pitch +10.
    np.testing.assert_allclose(np.degrees(odom(rot("y", -10) @ R_LEVEL).rpy), [0, 10, 0], atol=1e-9)
    # Right wing (world -y) down 20 deg: rotation about the nose (world +x) by +20 deg -> roll +20.
    np.testing.assert_allclose(np.degrees(odom(rot("x", 20) @ R_LEVEL).rpy), [20, 0, 0], atol=1e-9)


def test_lever_arm_moves_position_and_adds_rotation_velocity():
    # IMU 0.1 m in front of the reference point, vehicle level at the origin, yawing right at 1 rad/s.
    o = odom(R_LEVEL, w=(0, 0, 1), off=(0.1, 0, 0))
    np.testing.assert_allclose(o.p_ned, [-0.1, 0, 0], atol=1e-12)
    np.testing.assert_allclose(o.omega_frd, [0, 0, 1])
    np.testing.assert_allclose(o.v_frd, [0, -0.1, 0], atol=1e-12)  # the tail swings left in a right turn
    np.testing.assert_allclose(o.v_ned, [0, -0.1, 0], atol=1e-12)


@pytest.mark.parametrize("R_frd_body,rpy_deg", [
    (np.eye(3), [0, 0, 0]),
    (np.diag([1.0, -1.0, -1.0]), [180, 0, 0]),  # FLU IMU
    (R_CAM_FWD, [90, 0, 90]),
    (R_CAM_DOWN, [0, 0, 90]),
    (rot("y", -30) @ R_CAM_FWD, [60, 0, 90]),  # forward camera tilted 30 deg down
])
def test_documented_mounts_give_a_level_vehicle(R_frd_body, rpy_deg):
    np.testing.assert_allclose(mount_rpy_deg_from_matrix(R_frd_body), rpy_deg, atol=1e-9)
    np.testing.assert_allclose(mount_transform(rpy_deg, [0, 0, 0])[:3, :3], R_frd_body, atol=1e-12)
    # The IMU's attitude on a level vehicle is R_world_frd @ R_frd_body; the output must then be level.
    o = odom(R_LEVEL @ R_frd_body, rpy=rpy_deg, w=R_frd_body.T @ np.array([0.1, 0.2, 0.3]))
    np.testing.assert_allclose(o.rpy, [0, 0, 0], atol=1e-9)
    np.testing.assert_allclose(o.omega_frd, [0.1, 0.2, 0.3], atol=1e-12)


def test_upper_triangle_order_matches_mavlink():
    M = np.arange(36.0).reshape(6, 6)
    ut = upper_triangle(M)
    assert len(ut) == 21
    assert [ut[i] for i in (0, 6, 11, 15, 18, 20)] == [M[i, i] for i in range(6)]  # the diagonal
    assert ut[1] == M[0, 1] and ut[5] == M[0, 5] and ut[7] == M[1, 2]


def test_pose_covariance_level_vehicle_is_the_block_swap():
    cov = random_spd(6, 0)  # GTSAM order: rotation (body) then translation (body)
    o = odom(R_LEVEL, cov_pose=cov)
    expect = np.block([[cov[3:, 3:], cov[3:, :3]], [cov[:3, 3:], cov[:3, :3]]])
    np.testing.assert_allclose(o.cov_pose_ned, expect, atol=1e-12)
    # Yawed 90 deg: north/east variances swap.
    o = odom(rot("z", 90) @ R_LEVEL, cov_pose=np.diag([1e-4, 2e-4, 3e-4, 1.0, 4.0, 9.0]))
    np.testing.assert_allclose(np.diag(o.cov_pose_ned)[:3], [4.0, 1.0, 9.0], atol=1e-9)


def test_pose_covariance_matches_finite_difference_jacobian():
    """Generic attitude, mount and lever arm: J from perturbing T_world_body by Exp(xi) on the right."""
    R_wb = so3_exp([0.3, -0.2, 1.1])
    T = make_T(R_wb, np.array([1.0, -2.0, 0.5]))
    rpy_m, off = [10.0, -5.0, 30.0], [0.05, -0.02, 0.1]
    T_fb = mount_transform(rpy_m, off)

    def f(xi: np.ndarray) -> np.ndarray:
        Tp = T @ make_T(so3_exp(xi[:3]), xi[3:])
        o = to_vehicle_odometry(0, Tp, np.zeros(3), np.zeros(3), np.eye(6), np.eye(3), T_fb)
        return np.concatenate([o.p_ned, o.rpy])

    h, J = 1e-6, np.zeros((6, 6))
    for k in range(6):
        e = np.zeros(6)
        e[k] = h
        J[:, k] = (f(e) - f(-e)) / (2 * h)
    cov = random_spd(6, 1)
    o = to_vehicle_odometry(0, T, np.zeros(3), np.zeros(3), cov, np.eye(3), T_fb)
    np.testing.assert_allclose(o.cov_pose_ned, J @ cov @ J.T, rtol=1e-5, atol=1e-10)


def test_velocity_covariance_rotates_into_ned():
    cv = random_spd(3, 2)
    o = odom(R_LEVEL, cov_vel=cv)
    np.testing.assert_allclose(o.cov_v_ned, R_NED_WORLD @ cv @ R_NED_WORLD.T)
    np.testing.assert_allclose(o.cov_v_frd, o.cov_v_ned)  # at rest and level the two frames coincide


# ------------------------------------------------------------------ fake autopilot


class FakeAutopilot:
    """A MAVLink endpoint on UDP loopback playing the flight controller: it decodes everything it gets."""

    def __init__(self, sysid: int = 7) -> None:
        self.conn = mavutil.mavlink_connection("udpin:127.0.0.1:0", source_system=sysid, source_component=1,
                                               dialect="ardupilotmega")
        self.port = self.conn.port.getsockname()[1]
        self.received: list = []

    def drain(self, wait_s: float = 0.05) -> list:
        end = time.monotonic() + wait_s
        got = []
        while True:
            m = self.conn.recv_match(blocking=False)
            if m is not None:
                got.append(m)
            elif time.monotonic() > end:
                break
            else:
                time.sleep(0.002)
        self.received += got
        return got

    def heartbeat(self, system_status: int = mavlink.MAV_STATE_STANDBY, base_mode: int = 0) -> None:
        self.conn.mav.heartbeat_send(mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA, base_mode, 0,
                                     system_status)

    def of(self, kind: str, msgs: list | None = None) -> list:
        return [m for m in (self.received if msgs is None else msgs) if m.get_type() == kind]


class FakeClock:
    def __init__(self) -> None:
        self.t = 10_000_000_000

    def __call__(self) -> int:
        return self.t

    def advance(self, s: float) -> None:
        self.t += int(s * 1e9)


def state(t_ns: int, **kw) -> NavState:
    base = dict(T_world_body=make_T(R_LEVEL, np.array([1.0, 2.0, 3.0])), v_world=np.array([0.5, -1.0, 2.0]),
                omega_body=np.array([0.0, 0.0, 0.0]), cov_pose=np.diag([1e-4, 2e-4, 3e-4, 0.01, 0.02, 0.03]),
                cov_vel=np.diag([0.001, 0.002, 0.003]), quality=80)
    base.update(kw)
    return NavState(t_ns=t_ns, **base)


@pytest.fixture
def ap():
    a = FakeAutopilot()
    yield a
    a.conn.close()


def make_out(ap: FakeAutopilot, clock=None, **cfg) -> MavlinkOutput:
    c = MavlinkConfig(**{"mount": "rpy", **cfg})
    return MavlinkOutput(c, f"udpout:127.0.0.1:{ap.port}", **({"clock_ns": clock} if clock else {}))


def test_every_message_decodes_with_the_expected_fields(ap):
    s = state(123_456_789_000, reset_counter=2)
    got = []
    # one output per kind: ODOMETRY and VISION_* together are refused (ArduPilot would fuse the estimate twice)
    for kinds in (["VISION_POSITION_ESTIMATE", "VISION_SPEED_ESTIMATE"], ["ODOMETRY"]):
        clock = FakeClock()
        out = make_out(ap, clock, messages=kinds)
        out.poll()  # our first heartbeat tells the udpin fake where we are
        ap.drain()
        ap.heartbeat()
        time.sleep(0.02)
        clock.advance(0.1)
        out.poll()
        assert out.link_up and out.target_system == 7
        out.send_state(s)
        got += ap.drain()
        if kinds != ["ODOMETRY"]:
            out.close()
    expect = odom(R_LEVEL, p=(1, 2, 3), v=(0.5, -1, 2), cov_pose=s.cov_pose, cov_vel=s.cov_vel)
    (vpe,), (vse,), (odo,) = ap.of("VISION_POSITION_ESTIMATE", got), ap.of("VISION_SPEED_ESTIMATE", got), \
        ap.of("ODOMETRY", got)
    for m in (vpe, vse, odo):
        assert (m.get_srcSystem(), m.get_srcComponent()) == (7, 197)  # autopilot's system id, VIO component
        assert m.reset_counter == 2
    assert vpe.usec == vse.usec == odo.time_usec == 123_456_789
    np.testing.assert_allclose([vpe.x, vpe.y, vpe.z], [1, -2, -3], rtol=1e-6)
    np.testing.assert_allclose([vpe.roll, vpe.pitch, vpe.yaw], [0, 0, 0], atol=1e-6)
    np.testing.assert_allclose(vpe.covariance, upper_triangle(expect.cov_pose_ned), rtol=1e-6)
    np.testing.assert_allclose([vpe.covariance[i] for i in (0, 6, 11, 15, 18, 20)],
                               [0.01, 0.02, 0.03, 1e-4, 2e-4, 3e-4], rtol=1e-6)
    np.testing.assert_allclose([vse.x, vse.y, vse.z], [0.5, 1, -2], rtol=1e-6)
    np.testing.assert_allclose(vse.covariance, [0.001, 0, 0, 0, 0.002, 0, 0, 0, 0.003], rtol=1e-6)
    assert (odo.frame_id, odo.child_frame_id) == (mavlink.MAV_FRAME_LOCAL_FRD, mavlink.MAV_FRAME_BODY_FRD)
    assert odo.estimator_type == mavlink.MAV_ESTIMATOR_TYPE_VIO and odo.quality == 80
    np.testing.assert_allclose(odo.q, [1, 0, 0, 0], atol=1e-6)
    np.testing.assert_allclose([odo.x, odo.y, odo.z, odo.vx, odo.vy, odo.vz], [1, -2, -3, 0.5, 1, -2], rtol=1e-6)
    np.testing.assert_allclose(odo.pose_covariance, vpe.covariance)
    # body-frame velocity: the world covariance rotated, plus the attitude uncertainty of a moving body
    np.testing.assert_allclose([odo.velocity_covariance[i] for i in (0, 1, 2, 6, 7, 11)],
                               upper_triangle(expect.cov_v_frd), rtol=1e-6)
    assert all(np.isnan([odo.velocity_covariance[i] for i in (15, 18, 20)]))  # rate variance unknown
    hb = ap.of("HEARTBEAT")
    assert hb and hb[-1].type == mavlink.MAV_TYPE_ONBOARD_CONTROLLER
    assert hb[-1].autopilot == mavlink.MAV_AUTOPILOT_INVALID
    out.close()


def test_reset_counter_follows_estimator_wraps_and_can_be_forced(ap):
    clock = FakeClock()
    out = make_out(ap, clock, messages=["ODOMETRY"])
    counters = []
    for i, rc in enumerate([0, 1, 1, 255, 256]):
        clock.advance(0.1)
        out.send_state(state(1_000_000_000 * (i + 1), reset_counter=rc, cov_pose=np.eye(6) * (1 + rc)))
        counters += [m.reset_counter for m in ap.of("ODOMETRY", ap.drain())]
    out.force_reset()
    clock.advance(0.1)
    out.send_state(state(9_000_000_000, reset_counter=256))
    counters += [m.reset_counter for m in ap.of("ODOMETRY", ap.drain())]
    assert counters == [0, 1, 1, 255, 0, 1]
    assert "STATUSTEXT" in out.stats.sent  # the resets were announced
    out.close()


def test_a_loop_correction_step_is_announced_as_such_not_as_an_estimator_reset(ap):
    """[loop] output = jump steps the pose with reset_counter + 1 (the autopilot must re-reference), but the ground
    station should not read every loop closure as the estimator failing."""
    clock = FakeClock()
    out = make_out(ap, clock, messages=["ODOMETRY"])
    texts = []
    for i, (rc, jumps) in enumerate([(0, 0), (1, 1), (1, 1), (2, 1), (3, 2)]):
        clock.advance(0.1)
        out.send_state(state(1_000_000_000 * (i + 1), reset_counter=rc, loop_jumps=jumps))
        texts += [m.text for m in ap.of("STATUSTEXT", ap.drain())]
    assert texts == ["VIO loop correction", "VIO reset", "VIO loop correction"]
    out.close()


def test_a_first_pose_far_from_level_warns_about_the_mount_once(ap, caplog):
    """camera-down rig set up as camera-forward: the standing vehicle comes out 90 deg from level. Poses still go
    out (it may really lean), but the log and the ground station say to check the mount; a level start says
    nothing."""
    clock = FakeClock()
    out = make_out(ap, clock, messages=["ODOMETRY"])
    with caplog.at_level(logging.WARNING, logger="drivers.mavlink_out"):
        for _ in range(3):
            clock.advance(0.1)
            out.send_state(state(clock.t, T_world_body=make_T(rot("y", -90) @ R_LEVEL, np.zeros(3))))
    got = ap.drain()
    assert [m.text for m in ap.of("STATUSTEXT", got)] == ["VIO: 90 deg tilt at start: check mount"]
    assert len(ap.of("ODOMETRY", got)) == 3
    assert sum("[mavlink] mount" in r.getMessage() for r in caplog.records) == 1
    assert out.health()["first_tilt_deg"] == pytest.approx(90.0)
    out.close()
    out = make_out(ap, clock, messages=["ODOMETRY"])
    clock.advance(0.1)
    out.send_state(state(clock.t, T_world_body=make_T(rot("x", 10) @ R_LEVEL, np.zeros(3))))
    assert not ap.of("STATUSTEXT", ap.drain())
    assert out.health()["first_tilt_deg"] == pytest.approx(10.0)
    out.close()
    # a camera tilt left out of the config (22 deg on the EuRoC bench set-up): the log says so, no STATUSTEXT
    caplog.clear()
    out = make_out(ap, clock, messages=["ODOMETRY"])
    with caplog.at_level(logging.WARNING, logger="drivers.mavlink_out"):
        clock.advance(0.1)
        out.send_state(state(clock.t, T_world_body=make_T(rot("y", -22) @ R_LEVEL, np.zeros(3))))
    assert not ap.of("STATUSTEXT", ap.drain()) and "set [mavlink] camera_tilt_deg" in caplog.text
    out.close()


@pytest.mark.parametrize("cfg, says", [
    (dict(origin_lat_deg=473977418, origin_lon_deg=85455939), "latitude within [+]-90"),
    (dict(origin_lat_deg=95.0, origin_lon_deg=400.0), "latitude within [+]-90"),
    (dict(origin_lat_deg=47.3), "both or neither"),
    (dict(origin_lat_deg=47.3, origin_lon_deg=8.5, origin_alt_m=1e6), "origin_alt_m"),
    (dict(mount_offset_m=[100.0, 0.0, 50.0]), "lever arm over 2.0 m"),
    (dict(messages=["ODOMETRY", "VISION_POSITION_ESTIMATE"]), "fuse twice"),
])
def test_settings_that_would_send_nonsense_are_refused_at_start(cfg, says):
    """An origin in a ground station's 1e7 integers was accepted and broke the link every second (the packer's
    struct.error taken for a link failure); latitude 95 would have been sent as an origin; a lever arm in cm read
    as metres; ODOMETRY with VISION_* (the estimate fused twice) was only a warning: a review's findings."""
    from drivers.mavlink_out import check_mavlink_config

    with pytest.raises(VioError, match=says):
        check_mavlink_config(MavlinkConfig(**{"mount": "rpy", "url": "udpout:127.0.0.1:14550", **cfg}))


def test_a_message_that_cannot_be_packed_is_dropped_and_the_link_stays(ap, caplog):
    clock = FakeClock()
    out = make_out(ap, clock, messages=["ODOMETRY"])
    out.send_state(state(clock.t))
    assert len(ap.of("ODOMETRY", ap.drain())) == 1
    bad = mavlink.MAVLink_set_gps_global_origin_message(1, 473977418 * 10**7, 0, 0, 0)  # beyond int32
    with caplog.at_level("ERROR", logger="drivers.mavlink_link"):
        assert not out._send(bad, "SET_GPS_GLOBAL_ORIGIN")
        assert not out._send(bad, "SET_GPS_GLOBAL_ORIGIN")
    assert caplog.text.count("cannot be packed") == 1 and out.connected and out.stats.io_errors == 0
    clock.advance(0.1)
    out.send_state(state(clock.t))
    assert len(ap.of("ODOMETRY", ap.drain())) == 1
    out.close()


def test_a_connection_string_without_a_port_is_refused_when_given_as_an_argument():
    with pytest.raises(VioError, match="PORT"):
        MavlinkOutput(MavlinkConfig(mount="rpy"), "udpout:127.0.0.1")


def test_lost_tracking_sends_nothing_and_cancels_the_pending_state(ap):
    clock = FakeClock()
    out = make_out(ap, clock, messages=["ODOMETRY"])
    out.send_state(state(1_000_000_000))
    assert len(ap.of("ODOMETRY", ap.drain())) == 1
    clock.advance(0.01)  # inside the 33 ms slot: this one waits...
    out.send_state(state(1_010_000_000))
    out.send_state(state(1_020_000_000, tracking=False, quality=0))  # ...and is cancelled by the loss
    for _ in range(10):
        clock.advance(0.05)
        out.send_state(state(clock.t, tracking=False, quality=0))
    got = ap.drain()
    assert not [m for m in got if m.get_type() in ("ODOMETRY", "VISION_POSITION_ESTIMATE",
                                                   "VISION_SPEED_ESTIMATE")]
    assert [m.text for m in ap.of("STATUSTEXT", got)] == ["VIO tracking lost"]
    clock.advance(0.05)
    out.send_state(state(clock.t))
    got = ap.drain()
    assert len(ap.of("ODOMETRY", got)) == 1 and ap.of("STATUSTEXT", got)[0].text == "VIO tracking regained"
    out.close()


@pytest.mark.parametrize("lost_output", ["none", "quality0"])
def test_a_state_with_a_nan_covariance_is_never_sent_and_counts_as_lost_tracking(ap, lost_output, caplog):
    """NaN compares false both ways: covariance_quality read a NaN covariance as quality 100 and the pose messages
    carried the NaN (a review's finding). Such a state is a loss of tracking, sent as nothing, not even quality 0;
    so is one with a number beyond the messages' float32 fields."""
    assert covariance_quality(np.full((6, 6), np.nan), 0.05) == 0.0
    clock = FakeClock()
    out = make_out(ap, clock, messages=["ODOMETRY"], **({"lost_output": lost_output} if lost_output != "none"
                                                         else {}))
    out.send_state(state(clock.t))
    assert len(ap.of("ODOMETRY", ap.drain())) == 1
    bad = [dict(cov_pose=np.full((6, 6), np.nan)), dict(v_world=np.array([np.inf, 0, 0])),
           dict(cov_pose=np.diag([1e-4] * 3 + [-0.5] * 3)), dict(cov_vel=np.diag([-1.0, 1, 1])),
           dict(cov_pose=np.full((6, 6), np.nan)),
           # finite, but beyond the float32 fields: failed to pack, dropped as a send error, the status running
           dict(v_world=np.array([1e35, 0, 0])), dict(cov_pose=np.eye(6) * 1e36)]
    for kw in bad:
        clock.advance(0.05)
        out.send_state(state(clock.t, **kw))
    got = ap.drain()
    assert not [m for m in got if m.get_type() in ("ODOMETRY", "VISION_POSITION_ESTIMATE")]
    assert [m.text for m in ap.of("STATUSTEXT", got)] == ["VIO tracking lost"]
    assert out.health()["states_not_finite"] == 7 and "NaN or infinite" in caplog.text
    assert covariance_quality(np.diag([1e-4] * 3 + [-0.5] * 3), 0.05) == 0.0  # it read 1: a review's finding
    clock.advance(0.05)
    out.send_state(state(clock.t))
    assert len(ap.of("ODOMETRY", ap.drain())) == 1
    out.close()


@pytest.mark.parametrize("t_ns", [-5_000_000_000, -1, 2 ** 64 * 1000])
def test_a_pose_stamped_outside_time_usec_is_withheld_and_said(ap, caplog, t_ns):
    """ODOMETRY's and VISION_*'s time_usec is unsigned 64-bit: a state stamped before 0 (or past 2^64 us) failed to
    pack and was dropped as a send error ('ODOMETRY not sent: a field cannot be packed'), the status saying nothing
    of it. It is withheld as a NaN one is: a loss of tracking, one error line naming the stamp, the status's flag."""
    clock = FakeClock()
    out = make_out(ap, clock, messages=["ODOMETRY"])
    try:
        with caplog.at_level("INFO", logger="drivers.mavlink_out"):
            out.send_state(state(t_ns))
            clock.advance(0.05)
            out.send_state(state(t_ns + (50_000_000 if t_ns > 0 else -50_000_000)))
        got = ap.drain()
        assert not ap.of("ODOMETRY", got)
        assert "cannot be packed" not in caplog.text
        assert "time stamp" in caplog.text and str(t_ns) in caplog.text, caplog.text
        h = out.health()
        assert h["withholding_not_finite"] and "time stamp" in h["withholding_not_sendable"], h
        assert h["states_not_finite"] == 2 and h["states_sent"] == 0
        clock.advance(0.05)
        out.send_state(state(clock.t))
        assert len(ap.of("ODOMETRY", ap.drain())) == 1
        assert not out.health()["withholding_not_finite"] and out.health()["withholding_not_sendable"] is None
    finally:
        out.close()


def test_a_pending_state_is_never_replaced_by_an_older_one(ap):
    clock = FakeClock()
    out = make_out(ap, clock, messages=["ODOMETRY"])
    out.send_state(state(1_000_000_000))
    ap.drain()
    clock.advance(0.01)  # inside the slot: these wait
    assert out.send_state(state(1_020_000_000))
    assert not out.send_state(state(1_015_000_000))  # an older one (a frame state behind an IMU-rate one)
    clock.advance(0.05)
    out.poll()
    assert [m.time_usec for m in ap.of("ODOMETRY", ap.drain())] == [1_020_000]
    out.close()


def _counted(ap: FakeAutopilot, clock, path) -> MavlinkOutput:
    return MavlinkOutput(MavlinkConfig(mount="rpy", messages=["ODOMETRY"]), f"udpout:127.0.0.1:{ap.port}",
                         clock_ns=clock, counter_file=str(path))


def test_a_restarted_output_moves_reset_counter_on_from_the_last_one_sent(ap, tmp_path, caplog, monkeypatch):
    """A daemon restarted in flight (systemd after a crash or the watchdog) starts a new origin; with the counter
    at 0 again, as the flight before had sent, the autopilot fused the jump as a measurement (a review's finding).
    The counter sent is kept in [mavlink] counter_file and the next process starts one past it; with none kept,
    at a random value."""
    path = tmp_path / "reset_counter"
    starts = []
    for _ in range(3):
        clock = FakeClock()
        out = _counted(ap, clock, path)
        out.send_state(state(clock.t, reset_counter=2))  # the estimator reset twice in this flight
        starts.append(ap.of("ODOMETRY", ap.drain())[-1].reset_counter)
        out.close()
        assert int(path.read_text()) == starts[-1]
    assert starts[1] == (starts[0] + 3) % 256 and starts[2] == (starts[1] + 3) % 256
    path.write_text("not a number")
    with caplog.at_level("INFO", logger="drivers.mavlink_out"):
        out = _counted(ap, FakeClock(), path)
    assert "a random value" in caplog.text and "cannot read it" in caplog.text
    out.close()
    missing = tmp_path / "no-such-folder" / "reset_counter"
    with caplog.at_level("WARNING", logger="drivers.mavlink_out"):
        out = _counted(ap, FakeClock(), missing)
        out.send_state(state(1_000_000_000))
        ap.drain()
    assert "cannot keep the reset_counter" in caplog.text
    out.close()
    # `counter_file = ""` in `vio run`: every start sent 0, so a restart in flight re-sent the last run's counter (a
    # QA sweep); the daemon's output starts at a random value, said, and a replay's (no counter kept) still at 0
    import secrets

    monkeypatch.setattr(secrets, "randbelow", lambda n: 173)
    for random_first, first in ((True, 173), (False, 0)):
        caplog.clear()
        with caplog.at_level("INFO", logger="drivers.mavlink_out"):
            out = MavlinkOutput(MavlinkConfig(mount="rpy", messages=["ODOMETRY"]), f"udpout:127.0.0.1:{ap.port}",
                                clock_ns=FakeClock(), counter_file="", random_first_counter=random_first)
            out.send_state(state(1_000_000_000))
        assert ap.of("ODOMETRY", ap.drain())[-1].reset_counter == first
        assert ("counter_file is empty" in caplog.text) == random_first
        out.close()


def test_a_counter_file_that_cannot_be_written_is_never_trusted(ap, tmp_path, monkeypatch, caplog):
    """A full or read-only disk: the write failed, the old file stayed, and the restart started one past that
    stale value, the very counter the autopilot last got with a new origin (a review's finding)."""
    import os

    path = tmp_path / "reset_counter"
    out = _counted(ap, FakeClock(), path)
    clock = FakeClock()
    out._clock = clock
    out.send_state(state(clock.t))
    first = ap.of("ODOMETRY", ap.drain())[-1].reset_counter
    real_replace = os.replace

    def full(*a, **kw):
        raise OSError(28, "No space left on device")
    monkeypatch.setattr(os, "replace", full)
    clock.advance(0.1)
    out.send_state(state(clock.t, reset_counter=1))  # a reset: the new counter cannot be kept
    ap.drain()
    out.close()
    assert not path.exists()  # the stale value is gone (a full disk still lets a file be removed)
    monkeypatch.setattr(os, "replace", real_replace)
    path.write_text(f"{first}\n")  # a read-only disk keeps it: the restart cannot write it back either
    monkeypatch.setattr(os, "replace", full)
    with caplog.at_level("INFO", logger="drivers.mavlink_out"):
        out = _counted(ap, FakeClock(), path)
    assert "a random value" in caplog.text and "may be stale" in caplog.text
    out.close()


def test_flapping_tracking_gives_one_unstable_message_then_the_final_state(ap):
    """Frames in bursts (an overloaded board) flip tracking every 0.2 s: the ground station gets "lost",
    "regained", "lost", then one "unstable", and the state it settled in once it held for 3 s."""
    clock = FakeClock()
    out = make_out(ap, clock)
    out.send_state(state(clock.t))
    for k in range(20):
        clock.advance(0.2)
        out.send_state(state(clock.t, tracking=k % 2 == 1))
    texts = [m.text for m in ap.of("STATUSTEXT", ap.drain())]
    assert texts == ["VIO tracking lost", "VIO tracking regained", "VIO tracking lost", "VIO tracking unstable"]
    for _ in range(40):  # tracking holds (the last state was tracking) for 4 s
        clock.advance(0.1)
        out.send_state(state(clock.t))
    texts = [m.text for m in ap.of("STATUSTEXT", ap.drain())]
    assert texts == ["VIO tracking regained"]
    out.close()


@pytest.mark.parametrize("lost_output, sent", [("failed", -1), ("quality0", 0)])
def test_lost_output_quality0_sends_odometry_marked_invalid(ap, lost_output, sent, caplog):
    """lost_output = failed: the autopilot still hears us while lost, with quality -1 (MAVLink's "failed", which
    ArduPilot's VISO_QUAL_MIN and PX4's EKF2_EV_QMIN reject at their default 0); quality0 sends 0 ("unknown",
    fused at those defaults: a review's finding), with a warning at start."""
    clock = FakeClock()
    with caplog.at_level("WARNING", logger="drivers.mavlink_out"):
        out = make_out(ap, clock, messages=["ODOMETRY"], lost_output=lost_output)
    assert ("fuse at their default 0" in caplog.text) == (lost_output == "quality0")
    # an estimator that never tracked (started from the IMU alone, cameras black from boot), and one reset into a
    # new frame: nothing, not lost_output's pose with its prior's 1 mm covariance (a QA sweep)
    out.send_state(state(900_000_000, tracking=False, quality=0))
    clock.advance(0.05)
    assert not ap.of("ODOMETRY", ap.drain())
    out.send_state(state(1_000_000_000, quality=80))
    clock.advance(0.05)
    out.send_state(state(clock.t, tracking=False, quality=0))
    got = ap.of("ODOMETRY", ap.drain())
    assert [m.quality for m in got] == [80, sent]
    clock.advance(0.05)
    out.send_state(state(clock.t, tracking=False, quality=0, reset_counter=1))
    clock.advance(0.05)
    assert not ap.of("ODOMETRY", ap.drain())
    out.close()
    with pytest.raises(VioError, match="quality0"):
        MavlinkOutput(MavlinkConfig(mount="rpy", lost_output="quality0", messages=["VISION_POSITION_ESTIMATE"]),
                      "udpout:127.0.0.1:14550")


@pytest.mark.parametrize("tilt_deg", [0.0, 30.0, -15.0])
def test_camera_mount_is_derived_for_every_imu_orientation(tilt_deg):
    """mount = camera-forward with the stated tilt: whichever way the IMU sits (square to the frame, or tilted
    inside the camera), a level vehicle reports roll = pitch = yaw = 0."""
    R_frd_cam = rot("y", -tilt_deg) @ R_CAM_FWD  # forward camera, tilted down by tilt_deg
    for R_frd_body in _axis_rotations():  # IMU square to the airframe
        R_body_cam = R_frd_body.T @ R_frd_cam
        m = mount_rotation("camera-forward", None, R_body_cam, camera_tilt_deg=tilt_deg)
        np.testing.assert_allclose(m.R_frd_body, R_frd_body, atol=1e-12)
        assert m.off_axis_deg < 1e-6
        # the same IMU inside the camera (tilted with it): the exact rotation, reported as off-axis
        R_frd_imu = rot("y", -tilt_deg) @ R_frd_body
        m = mount_rotation("camera-forward", None, R_frd_imu.T @ R_frd_cam, camera_tilt_deg=tilt_deg)
        np.testing.assert_allclose(m.R_frd_body, R_frd_imu, atol=1e-12)
    R_frd_body = np.diag([1.0, -1.0, -1.0])
    np.testing.assert_allclose(mount_rotation("camera-down", None, R_frd_body.T @ R_CAM_DOWN).R_frd_body,
                               R_frd_body, atol=1e-12)


def test_unstated_camera_tilt_is_warned_about(caplog):
    """A square IMU with a camera tilted 25 deg that nobody stated: the mount is kept exact and a warning
    says how to fix it, instead of a silently snapped attitude."""
    R_body_cam = rot("y", -25.0) @ R_CAM_FWD  # FRD IMU, camera pitched 25 deg down
    caplog.set_level(logging.WARNING, logger="drivers.mavlink_out")
    out = MavlinkOutput(MavlinkConfig(), "udpout:127.0.0.1:14550", T_body_cam0=make_T(R_body_cam, np.zeros(3)))
    out.close()
    assert any("camera_tilt_deg" in r.message and "25.0 deg" in r.message for r in caplog.records)


def test_default_mount_from_the_calibration_is_not_upside_down(ap, caplog):
    """No config file: the simulator's FLU IMU and forward camera give a level, upright vehicle (roll 0, not 180).
    The daemon hands the mount over again once the output is up: logged once, not twice."""
    import logging

    from vio.sim import default_calibration

    calib = default_calibration()
    clock = FakeClock()
    out = MavlinkOutput(MavlinkConfig(), f"udpout:127.0.0.1:{ap.port}", clock_ns=clock,
                        T_body_cam0=calib.cam0.T_body_cam)
    out.send_state(state(1_000_000_000, T_world_body=np.eye(4)))  # level, nose along world x
    att = ap.of("ODOMETRY", ap.drain())
    out.close()
    lazy = MavlinkOutput(MavlinkConfig(), f"udpout:127.0.0.1:{ap.port}", clock_ns=clock)
    assert lazy.T_frd_body is None and not lazy.send_state(state(2_000_000_000))  # no mount yet: nothing sent
    with caplog.at_level(logging.INFO, logger="drivers.mavlink_out"):
        lazy.set_camera_mount(calib.cam0.T_body_cam)
        lazy.set_camera_mount(calib.cam0.T_body_cam)
    assert sum("IMU mount from the calibration" in r.getMessage() for r in caplog.records) == 1
    np.testing.assert_allclose(lazy.T_frd_body[:3, :3], np.diag([1.0, -1.0, -1.0]), atol=1e-9)
    lazy.close()
    assert att, "no pose message"
    q = att[0].q
    np.testing.assert_allclose(np.abs(q[0]), 1.0, atol=1e-6)  # identity attitude in NED/FRD


def test_rate_limit_sends_newest_state_once(ap):
    clock = FakeClock()
    out = make_out(ap, clock, rate_hz=30.0, messages=["VISION_POSITION_ESTIMATE"])
    for _ in range(400):  # 2 s of a 200 Hz estimator
        clock.advance(0.005)
        out.send_state(state(clock.t, T_world_body=make_T(R_LEVEL, np.array([clock.t * 1e-9, 0, 0]))))
    for _ in range(20):  # nothing new: polling must not resend the last one
        clock.advance(0.05)
        out.poll()
    msgs = ap.of("VISION_POSITION_ESTIMATE", ap.drain(0.2))
    assert len(msgs) == 61  # the first state at once, then 30 Hz for 1.995 s: the slots follow a fixed grid
    stamps = [m.usec for m in msgs]
    assert stamps == sorted(set(stamps))
    # each message carries the newest state of its slot (at most one 5 ms input period old)
    np.testing.assert_allclose([m.x - msgs[0].x for m in msgs], np.arange(61) / 30.0, atol=0.0051)
    # a slower estimator (20 Hz) is forwarded completely, each state once
    n0 = len(msgs)
    for _ in range(20):
        clock.advance(0.05)
        out.send_state(state(clock.t))
    assert len(ap.of("VISION_POSITION_ESTIMATE", ap.drain())) == 20 and n0 == 61
    out.close()


def test_timesync_request_is_answered_with_our_monotonic_clock(ap):
    out = make_out(ap, FakeClock())
    out.poll()
    ap.drain()
    ap.conn.mav.timesync_send(0, 987_654_321)
    ap.conn.mav.timesync_send(5, 42)  # an answer to someone else's request: not ours to answer
    time.sleep(0.02)
    before = time.monotonic_ns()
    out.poll()
    replies = ap.of("TIMESYNC", ap.drain())
    assert len(replies) == 1 and replies[0].ts1 == 987_654_321
    assert before <= replies[0].tc1 <= time.monotonic_ns()
    # locked on an autopilot (system 7), another system's request is not ours to answer: a second answer on the
    # link would spoil its round trip (a review's finding)
    ap.heartbeat()
    time.sleep(0.02)
    out.poll()
    ap.drain()
    ap.conn.mav.srcSystem = 9
    ap.conn.mav.timesync_send(0, 111)
    ap.conn.mav.srcSystem = 7
    ap.conn.mav.timesync_send(0, 222)
    time.sleep(0.02)
    out.poll()
    assert [m.ts1 for m in ap.of("TIMESYNC", ap.drain())] == [222]
    out.close()


def test_origin_is_repeated_after_link_up_until_the_autopilot_confirms_it(ap):
    """An autopilot still booting drops SET_GPS_GLOBAL_ORIGIN (and then refuses a GUIDED take-off): the
    origin and home go out every second, each with a request for GPS_GLOBAL_ORIGIN, until the autopilot
    reports one; then they stop."""
    clock = FakeClock()
    out = make_out(ap, clock, origin_lat_deg=47.3977419, origin_lon_deg=8.5455938, origin_alt_m=488.0)
    out.poll()
    ap.drain()
    assert not ap.of("SET_GPS_GLOBAL_ORIGIN")  # not before the autopilot is there
    ap.heartbeat()
    time.sleep(0.02)
    for _ in range(10):
        out.poll()
        clock.advance(0.6)
    got = ap.drain()
    origins = ap.of("SET_GPS_GLOBAL_ORIGIN", got)
    assert len(origins) == 5 and len(ap.of("SET_HOME_POSITION", got)) == 5  # polls 0.6 s apart, 1 s period
    asks = [m for m in ap.of("COMMAND_LONG", got) if m.command == mavlink.MAV_CMD_REQUEST_MESSAGE]
    assert len(asks) == 5 and asks[0].param1 == mavlink.MAVLINK_MSG_ID_GPS_GLOBAL_ORIGIN
    o = origins[0]
    assert (o.target_system, o.latitude, o.longitude, o.altitude) == (7, 473977419, 85455938, 488000)
    assert not out.stats.origin_confirmed and out.health()["origin_ours"] is None
    # another component of the autopilot's system (a companion program repeating what it heard) is not the autopilot
    # confirming its EKF origin: the repeats stopped on it (outfix's note)
    ap.conn.mav.srcComponent = 191
    ap.conn.mav.gps_global_origin_send(473977419, 85455938, 488000)
    ap.conn.mav.srcComponent = 1
    time.sleep(0.02)
    out.poll()
    assert not out.stats.origin_confirmed
    ap.conn.mav.gps_global_origin_send(473977419, 85455938, 488000)
    time.sleep(0.02)
    for _ in range(10):
        out.poll()
        clock.advance(0.6)
    assert out.stats.origin_confirmed and out.health()["origin_ours"] is True
    assert len(ap.of("SET_GPS_GLOBAL_ORIGIN", ap.drain())) <= 1  # at most the one already due
    out.close()


def test_an_origin_the_autopilot_drops_after_confirming_it_is_set_again(ap, caplog):
    """ArduCopter SITL confirmed the origin set while it booted (GPS_GLOBAL_ORIGIN), then its EKF3 initialised and
    dropped it (NavEKF3::InitialiseFilter clears the shared origin): no origin, no home, GUIDED take-off refused
    (1 of 6 flights; the bench's harness set it). While disarmed the confirmed origin is asked for every 5 s; an
    autopilot that answers gets nothing else, one that stops answering for 3 s gets the origin again. Armed, no
    check (an answer missed then is no loss)."""
    clock = FakeClock()
    out = make_out(ap, clock, origin_lat_deg=47.3977419, origin_lon_deg=8.5455938, origin_alt_m=488.0)
    has_origin = True

    def run(seconds: float, base_mode: int = 0) -> list:
        """polls 0.5 s apart, the autopilot's heartbeat before each; it answers origin requests while it has one"""
        got = []
        for _ in range(int(seconds / 0.5)):
            ap.heartbeat(base_mode=base_mode)
            time.sleep(0.01)
            out.poll()
            clock.advance(0.5)
            new = ap.drain(0.02)
            got += new
            asked = [m for m in ap.of("COMMAND_LONG", new) if m.command == mavlink.MAV_CMD_REQUEST_MESSAGE
                     and m.param1 == mavlink.MAVLINK_MSG_ID_GPS_GLOBAL_ORIGIN]
            if asked and has_origin:
                ap.conn.mav.gps_global_origin_send(473977419, 85455938, 488000)
        return got

    def asks(msgs: list) -> int:
        return len([m for m in ap.of("COMMAND_LONG", msgs) if m.command == mavlink.MAV_CMD_REQUEST_MESSAGE])

    out.poll()
    ap.drain()
    got = run(2.0)
    assert out.stats.origin_confirmed and len(ap.of("SET_GPS_GLOBAL_ORIGIN", got)) == 1
    got = run(20.0)  # answered: asked again every 5 s, nothing set
    assert not ap.of("SET_GPS_GLOBAL_ORIGIN", got) and 3 <= asks(got) <= 5 and out.stats.origin_lost == 0
    has_origin = False  # its EKF initialised: the origin is gone, and it says nothing
    with caplog.at_level(logging.WARNING, logger="drivers.mavlink_out"):
        got = run(10.0)
    assert ap.of("SET_GPS_GLOBAL_ORIGIN", got) and ap.of("SET_HOME_POSITION", got)
    assert out.stats.origin_lost == 1 and not out.stats.origin_confirmed
    assert "no longer reports the EKF origin it confirmed" in caplog.text
    has_origin = True
    run(2.0)
    assert out.stats.origin_confirmed and out.health()["origin_lost"] == 1
    armed = mavlink.MAV_MODE_FLAG_SAFETY_ARMED
    has_origin = False
    got = run(20.0, base_mode=armed)  # armed: not asked, nothing set
    assert asks(got) == 0 and not ap.of("SET_GPS_GLOBAL_ORIGIN", got) and out.stats.origin_lost == 1
    out.close()


def test_a_replay_sets_no_origin_on_an_armed_autopilot(ap):
    """A replay's configured origin (its flight's config) is another flight's business: not sent to an autopilot
    that says it is armed; once it says disarmed, as for `vio run`."""
    clock = FakeClock()
    c = MavlinkConfig(mount="rpy", origin_lat_deg=47.3977419, origin_lon_deg=8.5455938, origin_alt_m=488.0)
    out = MavlinkOutput(c, f"udpout:127.0.0.1:{ap.port}", clock_ns=clock, poses_to_armed=False)
    out.poll()
    ap.drain()  # its first heartbeat: the autopilot's side learns where to answer
    for armed in (True, False):
        for _ in range(4):
            ap.heartbeat(mavlink.MAV_STATE_ACTIVE, mavlink.MAV_MODE_FLAG_SAFETY_ARMED if armed else 0)
            time.sleep(0.02)
            out.poll()
            clock.advance(0.6)
        assert bool(ap.of("SET_GPS_GLOBAL_ORIGIN", ap.drain())) is not armed, armed
    out.close()


def test_a_replay_sets_no_origin_on_an_autopilot_it_no_longer_hears(ap):
    """A replay's origin went on being sent (up to ORIGIN_MAX_SENDS, 1 s apart, until confirmed) after the autopilot
    fell silent past link_timeout_s, though it may have armed meanwhile (its poses were held back then). Held back
    too until a heartbeat says disarmed again."""
    clock = FakeClock()
    c = MavlinkConfig(mount="rpy", origin_lat_deg=47.3977419, origin_lon_deg=8.5455938, origin_alt_m=488.0)
    out = MavlinkOutput(c, f"udpout:127.0.0.1:{ap.port}", clock_ns=clock, poses_to_armed=False)
    out.poll()
    ap.drain()  # its first heartbeat: the autopilot's side learns where to answer

    def step(n: int, beat: bool) -> list:
        for _ in range(n):
            if beat:
                ap.heartbeat(mavlink.MAV_STATE_ACTIVE, 0)
                time.sleep(0.02)
            out.poll()
            clock.advance(0.6)
        return ap.of("SET_GPS_GLOBAL_ORIGIN", ap.drain())

    assert step(3, beat=True)  # heard disarmed: sent (not confirmed: tried again)
    step(int(c.link_timeout_s / 0.6) + 1, beat=False)  # silent past the timeout
    assert not out.link_up and not step(4, beat=False)
    assert step(3, beat=True)  # heard disarmed again
    out.close()


def test_an_autopilot_restart_inside_the_link_timeout_gets_the_origin_again(ap, caplog):
    """ArduCopter SITL rebooted with 2.3 s of silent heartbeats, inside link_timeout_s (3 s): the link never
    went down, so the origin it had confirmed was never sent again and the rebooted EKF had none (GUIDED
    refused; an in-flight watchdog recovery would have lost its position). A booting heartbeat after a running
    one, or its TIMESYNC clock (time since boot) going back, is a restart: the origin goes out again until
    confirmed, once per restart."""
    clock = FakeClock()
    out = make_out(ap, clock, origin_lat_deg=47.3977419, origin_lon_deg=8.5455938, origin_alt_m=488.0)

    def step(n: int = 3, status: int = mavlink.MAV_STATE_STANDBY) -> list:
        """n polls 0.6 s apart, the autopilot's heartbeat in `status` before each"""
        for _ in range(n):
            ap.heartbeat(status)
            time.sleep(0.01)
            out.poll()
            clock.advance(0.6)
        return ap.drain()

    def confirm() -> None:
        ap.conn.mav.gps_global_origin_send(473977419, 85455938, 488000)
        step()
        assert out.stats.origin_confirmed
        assert not ap.of("SET_GPS_GLOBAL_ORIGIN", step())

    out.poll()
    ap.drain()  # our first heartbeat tells the fake where we are
    assert ap.of("SET_GPS_GLOBAL_ORIGIN", step(status=mavlink.MAV_STATE_BOOT))  # first seen booting: no restart
    ap.conn.mav.timesync_send(0, 20_000_000_000)  # its clock: 20 s since boot
    confirm()
    assert out.stats.autopilot_restarts == 0 and out.health()["autopilot_restarts"] == 0

    with caplog.at_level(logging.WARNING, logger="drivers.mavlink_out"):
        got = step(status=mavlink.MAV_STATE_BOOT)  # rebooted: its heartbeats kept coming within the timeout
    assert out.stats.autopilot_restarts == 1 and not out.stats.origin_confirmed and out.link_up
    assert ap.of("SET_GPS_GLOBAL_ORIGIN", got) and "the autopilot restarted" in caplog.text
    ap.conn.mav.timesync_send(0, 1_500_000_000)  # the same restart's clock, seen afterwards: not a second one
    confirm()
    assert out.stats.autopilot_restarts == 1 and out.stats.link_losses == 0

    # a companion program on the same system (MAVROS, MAVSDK through a router) asks with wall-clock ts1 between
    # the autopilot's requests: not a restart each time the autopilot's small ts1 follows (a review's finding:
    # each false restart re-sent LAND), and not ours to answer
    ap.conn.mav.srcComponent = 191
    ap.conn.mav.timesync_send(0, 1_700_000_000_000_000_000)
    ap.conn.mav.srcComponent = 1
    got = step(1)
    assert not [m for m in ap.of("TIMESYNC", got) if m.ts1 == 1_700_000_000_000_000_000]
    ap.conn.mav.timesync_send(0, 9_000_000_000)
    step(1)
    assert out.stats.autopilot_restarts == 1
    step(1, mavlink.MAV_STATE_UNINIT)  # PX4 sends UNINIT for states it does not map (a failed preflight check)
    assert out.stats.autopilot_restarts == 1
    ap.conn.mav.timesync_send(0, 2_000_000_000)  # its clock tells first (PX4 asks every few hundred ms) ...
    got = step(status=mavlink.MAV_STATE_BOOT)  # ... then its booting heartbeats: one restart
    assert out.stats.autopilot_restarts == 2 and ap.of("SET_GPS_GLOBAL_ORIGIN", got)
    ap.conn.mav.timesync_send(0, 5_000_000_000)
    step(1, mavlink.MAV_STATE_BOOT)
    ap.conn.mav.timesync_send(0, 4_000_000_000)  # 1 s back is a restart; a late or reordered request is not
    ap.conn.mav.timesync_send(0, 3_800_000_000)
    step()
    assert out.stats.autopilot_restarts == 3
    out.close()


def test_replayed_states_are_restamped_onto_the_host_clock_keeping_their_spacing():
    got: list[NavState] = []
    push = restamp_to_host_clock(got.append)
    t_data = 1_403_715_273_262_142_976  # EuRoC (Unix epoch) stamp
    before = time.monotonic_ns()
    push(state(t_data))
    push(state(t_data + 50_000_000))
    assert before <= got[0].t_ns <= time.monotonic_ns()
    assert got[1].t_ns - got[0].t_ns == 50_000_000


def test_bad_configuration_names_the_key():
    with pytest.raises(VioError, match="messages"):
        MavlinkOutput(MavlinkConfig(messages=["ODOMETRY", "ATTITUDE"]), "udpout:127.0.0.1:14550")
    with pytest.raises(VioError, match="mount_rpy_deg"):
        MavlinkOutput(MavlinkConfig(mount_rpy_deg=[0.0, 0.0]), "udpout:127.0.0.1:14550")
    with pytest.raises(VioError, match="url"):
        MavlinkOutput(MavlinkConfig(), "")
    with pytest.raises(VioError, match="baud"):
        MavlinkOutput(MavlinkConfig(), "/dev/ttyAMA0:fast")
    with pytest.raises(VioError, match="expected"):
        MavlinkOutput(MavlinkConfig(), "ttyAMA0")


def test_unreachable_tcp_peer_retries_quietly_then_connects(caplog):
    clock = FakeClock()
    probe = socket.socket()
    probe.bind(("127.0.0.1", 0))
    port = probe.getsockname()[1]
    probe.close()  # nothing listens on `port` now
    caplog.set_level(logging.DEBUG, logger="drivers.mavlink_out")
    out = MavlinkOutput(MavlinkConfig(mount="rpy"), f"tcp:127.0.0.1:{port}", clock_ns=clock)
    for _ in range(20):
        clock.advance(1.0)
        out.send_state(state(clock.t))
    assert not out.connected
    assert len([r for r in caplog.records if r.levelno >= logging.WARNING]) == 1
    server = socket.socket()
    server.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    server.bind(("127.0.0.1", port))
    server.listen(1)
    clock.advance(6.0)
    out.send_state(state(clock.t))
    assert out.connected and out.stats.reconnects == 1
    peer, _ = server.accept()
    peer.settimeout(2.0)
    parser = mavlink.MAVLink(None)
    msgs = parser.parse_buffer(peer.recv(4096)) or []
    assert {m.get_type() for m in msgs} >= {"HEARTBEAT", "ODOMETRY"}
    peer.close()  # the autopilot side goes away: one warning, no busy loop of empty reads, then retries
    server.close()
    for _ in range(20):  # estimates keep coming (without them, 0.5 s on is a loss of tracking and says so)
        clock.advance(0.5)
        out.send_state(state(clock.t))
    assert not out.connected and out.stats.io_errors >= 1
    assert len([r for r in caplog.records if r.levelno >= logging.WARNING]) == 2
    out.close()


def test_states_due_while_the_link_is_closed_are_counted_and_said(caplog):
    """A state whose send slot came while the connection was closed (a serial port unplugged, a TCP peer gone) was
    counted nowhere as such: it waited, and the next one counted it as superseded (the normal rate limit). It is
    dropped at its slot and counted in states_link_closed, once (not also superseded), and the replay's summary
    says how many; the link back, poses go out again."""
    clock = FakeClock()
    probe = socket.socket()
    probe.bind(("127.0.0.1", 0))
    port = probe.getsockname()[1]
    probe.close()  # nothing listens on `port` now
    url = f"tcp:127.0.0.1:{port}"
    out = MavlinkOutput(MavlinkConfig(mount="rpy"), url, clock_ns=clock)
    for _ in range(5):
        clock.advance(0.2)
        out.send_state(state(clock.t))
    h = out.health()
    assert not out.connected  # the newest waits for the link's return (a period at most, below): not counted yet
    assert (h["states_link_closed"], h["states_superseded"], h["states_sent"]) == (4, 0, 0)
    server = socket.socket()
    server.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    server.bind(("127.0.0.1", port))
    server.listen(1)
    try:
        clock.advance(6.0)
        out.send_state(state(clock.t))
        assert out.connected and out.states_sent == 1 and out.health()["states_link_closed"] == 5
        from vio.app.replay import mavlink_summary

        extra, line = mavlink_summary(out.stats, url)
        assert extra["states_link_closed"] == 5
        assert line == f"mavlink: 1 poses sent to {url}; 5 not sent: no connection (the link was closed)"
    finally:
        out.close()
        server.close()


class _SharedLink:
    """A drivers.mavlink_link.MavlinkLink stand-in: sends while `connected` (its reader thread reopens it)."""

    url = "udpout:127.0.0.1:9"

    def __init__(self) -> None:
        self.connected, self.sent = True, []

    def send(self, msg) -> bool:
        if self.connected:
            self.sent.append(msg.get_type())
        return self.connected

    def subscribe(self, *a) -> None: ...
    def unsubscribe(self, *a) -> None: ...
    def acquire(self) -> None: ...
    def release(self) -> None: ...
    def set_source_system(self, sysid: int) -> None: ...


def test_a_state_in_the_gap_of_a_link_that_reconnects_at_once_goes_out_when_it_is_back():
    """A shared link's reader reopens it within ms of an error. A state that came in that gap was dropped at once
    (its slot had come with no connection, 1c97837), fresh as it was: the autopilot's poses came a state period apart
    twice (A at 0, C at 100 ms: B at 50 ms, the link back at 52, went nowhere). It waits for the link's return now,
    and only one that waited a whole period more with none is dropped, counted in states_link_closed."""
    clock, link = FakeClock(), _SharedLink()
    out = MavlinkOutput(MavlinkConfig(mount="rpy", messages=["ODOMETRY"]), link=link, clock_ns=clock,
                        max_state_age_ms=500)
    try:
        out.send_state(state(clock.t))  # A
        clock.advance(0.040)
        link.connected = False  # a link error; its reader reopens it at once
        clock.advance(0.010)
        out.send_state(state(clock.t))  # B, polled at once: no connection
        clock.advance(0.002)
        link.connected = True
        clock.advance(0.008)
        out.poll()  # the output thread's next look (every 10 ms at most)
        assert (out.states_sent, out.stats.states_link_closed) == (2, 0)  # B, 10 ms old
        link.connected = False  # now gone for longer: C waits a period, then is dropped and counted
        clock.advance(0.040)
        out.send_state(state(clock.t))
        for _ in range(4):
            clock.advance(0.010)
            out.poll()
        assert (out.states_sent, out.stats.states_link_closed, out.stats.states_superseded) == (2, 1, 0)
        assert link.sent.count("ODOMETRY") == 2
    finally:
        out.close()


# ------------------------------------------------------------------ real time


def test_real_time_rate_heartbeat_and_link_loss(ap, caplog):
    """Background thread at 30 Hz fed at 100 Hz; the autopilot goes silent for 1.2 s and comes back."""
    caplog.set_level(logging.INFO, logger="drivers.mavlink_out")
    out = MavlinkOutput(MavlinkConfig(rate_hz=30.0, link_timeout_s=0.5, messages=["ODOMETRY"], mount="rpy"),
                        f"udpout:127.0.0.1:{ap.port}").start()
    stop = threading.Event()

    def feed() -> None:
        while not stop.is_set():
            out.send_state(state(time.monotonic_ns()))
            time.sleep(0.01)

    feeder = threading.Thread(target=feed, daemon=True)
    feeder.start()
    counts: list[tuple[float, int, int]] = []  # (time, odometry so far, heartbeats so far)
    silent = (4.0, 5.2)
    t_start = time.monotonic()
    next_hb = t_start
    while (t := time.monotonic() - t_start) < 6.5:
        if time.monotonic() >= next_hb:
            next_hb += 0.25
            if not silent[0] <= t < silent[1]:
                ap.heartbeat()
            if ap.of("TIMESYNC") == [] and t > 1.0:
                ap.conn.mav.timesync_send(0, 1)
        ap.drain(0.01)
        counts.append((time.monotonic() - t_start, len(ap.of("ODOMETRY")), len(ap.of("HEARTBEAT"))))
    stop.set()
    feeder.join()
    out.close()

    def at(t: float) -> tuple[float, int, int]:
        return min(counts, key=lambda c: abs(c[0] - t))

    (ta, na, ha), (tb, nb, hb) = at(0.5), at(3.5)
    rate = (nb - na) / (tb - ta)
    assert abs(rate - 30.0) <= 1.5, f"output rate {rate:.2f} Hz over {tb - ta:.2f} s"
    assert 2 <= hb - ha <= 4  # our heartbeat at 1 Hz over 3 s
    assert out.stats.link_losses == 1
    assert out.stats.timesync_answered >= 1 and ap.of("TIMESYNC")
    lost = [r for r in caplog.records if "link lost" in r.getMessage()]
    up = [r for r in caplog.records if "link up" in r.getMessage()]
    assert len(lost) == 1 and len(up) == 2  # one line per transition, no flood
    assert len(caplog.records) < 10
    (tc, nc, _), (td, nd, _) = at(silent[1] + 0.3), at(6.4)
    assert nd - nc >= 0.8 * 30 * (td - tc)  # output went on through and after the silence



def test_only_the_autopilots_own_heartbeat_is_trusted(ap):
    """ArduPilot forwards every heartbeat on every link: Kestrel's own coming back (component 197), a
    peripheral claiming a vehicle type, and a second vehicle must neither bring the link up nor move
    target_system; only system 7 component 1 does."""
    clock = FakeClock()
    out = make_out(ap, clock)
    out.poll()
    ap.drain()

    def hb(sysid: int, comp: int, kind: int, autopilot: int) -> None:
        ap.conn.mav.srcSystem, ap.conn.mav.srcComponent = sysid, comp
        ap.conn.mav.heartbeat_send(kind, autopilot, 0, 0, mavlink.MAV_STATE_ACTIVE)
        time.sleep(0.02)
        clock.advance(0.1)
        out.poll()

    hb(7, 197, mavlink.MAV_TYPE_ONBOARD_CONTROLLER, mavlink.MAV_AUTOPILOT_INVALID)  # our own, echoed
    hb(7, 197, mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA)  # our component, whatever it says
    hb(7, mavlink.MAV_COMP_ID_PERIPHERAL, mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA)
    assert not out.link_up and out.health()["other_heartbeats"] == 3
    hb(7, 1, mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA)
    assert out.link_up and out.target_system == 7
    hb(9, 1, mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA)  # another vehicle on the radio
    assert out.target_system == 7 and out.system_id == 7 and out.health()["other_heartbeats"] == 4
    out.close()


def test_land_after_loss_asks_an_armed_autopilot_to_land_once_per_loss(ap):
    """land_after_loss_s: a loss shorter than S sends no LAND; a longer one while armed sends
    MAV_CMD_NAV_LAND (repeated 1 s apart until acknowledged), one STATUSTEXT, and the status says so."""
    clock = FakeClock()
    out = make_out(ap, clock, land_after_loss_s=3.0)

    def armed_heartbeat(armed: bool = True) -> None:
        ap.conn.mav.heartbeat_send(mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA,
                                   mavlink.MAV_MODE_FLAG_SAFETY_ARMED if armed else 0, 4, mavlink.MAV_STATE_ACTIVE)
        time.sleep(0.02)

    def lose_for(s: float) -> list:
        got = []
        for _ in range(int(round(s / 0.5))):
            clock.advance(0.5)
            armed_heartbeat()
            out.send_state(state(clock.t, tracking=False, quality=0))
            got += ap.drain(0.01)
        return got

    def lands(msgs: list) -> list:
        return [m for m in ap.of("COMMAND_LONG", msgs) if m.command == mavlink.MAV_CMD_NAV_LAND]

    armed_heartbeat()
    out.send_state(state(clock.t))
    got = lose_for(2.5)  # a 2.5 s loss, then vision back: no LAND
    clock.advance(0.1)
    out.send_state(state(clock.t))
    assert not lands(got + ap.drain()) and out.stats.land_requests == 0
    got = lose_for(4.5)  # LAND once the loss has lasted 3 s, again at 4 s while unacknowledged
    assert len(lands(got)) == 2 and lands(got)[0].target_system == 7
    assert "VIO lost: LAND requested" in [m.text for m in ap.of("STATUSTEXT", got)]
    assert not out.health()["land_accepted"]
    ap.conn.mav.command_ack_send(mavlink.MAV_CMD_NAV_LAND, mavlink.MAV_RESULT_ACCEPTED)
    time.sleep(0.02)
    got = lose_for(3.0)
    assert not lands(got)  # acknowledged: no more requests during this loss
    h = out.health()
    assert h["land_accepted"] and h["land_requests"] == 2 and h["land_after_loss_s"] == 3.0
    out.close()


def test_a_replay_sends_no_pose_to_an_armed_autopilot(ap, caplog):
    """`vio replay --mavlink` sends a recording's poses, another flight's: an autopilot that says it is armed would
    fly on them. None goes out while it says so (said once: log and STATUSTEXT); disarmed, they go out again. `vio
    run` (the default) sends to an armed autopilot, which is what it is for."""
    import logging

    clock = FakeClock()
    c = MavlinkConfig(mount="rpy", messages=["VISION_POSITION_ESTIMATE"])
    replay_out = MavlinkOutput(c, f"udpout:127.0.0.1:{ap.port}", clock_ns=clock, poses_to_armed=False)

    def heartbeat(armed: bool) -> None:
        ap.heartbeat(mavlink.MAV_STATE_ACTIVE, mavlink.MAV_MODE_FLAG_SAFETY_ARMED if armed else 0)
        time.sleep(0.02)

    def fly(out: MavlinkOutput, armed: bool, n: int = 4) -> list:
        got = []
        for _ in range(n):
            heartbeat(armed)
            clock.advance(0.1)
            out.send_state(state(clock.t))
            got += ap.drain(0.01)
        return got

    assert ap.of("VISION_POSITION_ESTIMATE", fly(replay_out, armed=False))
    with caplog.at_level(logging.ERROR, logger="drivers.mavlink_out"):
        got = fly(replay_out, armed=True) + fly(replay_out, armed=True)
    assert not ap.of("VISION_POSITION_ESTIMATE", got) and replay_out.stats.states_refused_armed >= 6
    assert [m.text for m in ap.of("STATUSTEXT", got)].count("VIO replay: armed, poses not sent") == 1
    assert sum("the autopilot is armed: no pose of this replay is sent" in r.getMessage()
               for r in caplog.records) == 1
    assert ap.of("VISION_POSITION_ESTIMATE", fly(replay_out, armed=False))  # disarmed again: sent
    replay_out.close()
    run_out = MavlinkOutput(c, f"udpout:127.0.0.1:{ap.port}", clock_ns=clock)
    assert ap.of("VISION_POSITION_ESTIMATE", fly(run_out, armed=True)) and run_out.stats.states_refused_armed == 0
    run_out.close()


def test_a_replay_sends_no_pose_before_an_autopilot_heartbeat_says_disarmed(ap):
    """A replay's first states came before the autopilot's first heartbeat (1 Hz) and went out though it might be
    armed; and one silent past link_timeout_s may have armed since. None goes out until a heartbeat says disarmed,
    nor once heartbeats stop for link_timeout_s."""
    clock = FakeClock()
    c = MavlinkConfig(mount="rpy", messages=["VISION_POSITION_ESTIMATE"])
    out = MavlinkOutput(c, f"udpout:127.0.0.1:{ap.port}", clock_ns=clock, poses_to_armed=False)

    def fly(n: int = 4, beat: bool = True) -> list:
        got = []
        for _ in range(n):
            if beat:
                ap.heartbeat(mavlink.MAV_STATE_ACTIVE, 0)
                time.sleep(0.02)
            clock.advance(0.1)
            out.send_state(state(clock.t))
            got += ap.drain(0.01)
        return got

    assert not ap.of("VISION_POSITION_ESTIMATE", fly(beat=False)) and out.stats.states_refused_unheard >= 3
    assert ap.of("VISION_POSITION_ESTIMATE", fly())  # disarmed, heard: sent
    clock.advance(c.link_timeout_s + 0.5)
    n = out.stats.states_refused_unheard
    assert not ap.of("VISION_POSITION_ESTIMATE", fly(beat=False)) and out.stats.states_refused_unheard > n
    assert out.stats.states_refused_armed == 0
    out.close()


def test_a_replay_says_nothing_of_its_tracking_to_an_armed_autopilot(ap):
    """A replay towards an armed autopilot sent no pose, but its recording's losses and regains went out as
    STATUSTEXT 'VIO tracking lost' / 'regained' to the ground station of a vehicle flying on something else
    (spoken aloud by QGC and Mission Planner). Only the one 'VIO replay: armed, poses not sent' goes out; disarmed,
    they are said as for vio run."""
    clock = FakeClock()
    c = MavlinkConfig(mount="rpy", messages=["VISION_POSITION_ESTIMATE"])

    def fly(armed: bool) -> list:
        out = MavlinkOutput(c, f"udpout:127.0.0.1:{ap.port}", clock_ns=clock, poses_to_armed=False)
        out.poll()
        ap.drain()  # its first heartbeat: the autopilot's side learns where to answer
        got = []
        for tracking in (True, True, False, False, True, True):
            ap.heartbeat(mavlink.MAV_STATE_ACTIVE, mavlink.MAV_MODE_FLAG_SAFETY_ARMED if armed else 0)
            time.sleep(0.02)
            clock.advance(0.5)
            out.poll()
            out.send_state(state(clock.t, tracking=tracking, quality=100 if tracking else 0))
            out.poll()
            got += ap.drain(0.01)
        out.close()
        return [m.text for m in ap.of("STATUSTEXT", got)]

    texts = fly(armed=True)
    assert texts == ["VIO replay: armed, poses not sent"], texts
    texts = fly(armed=False)
    assert "VIO tracking lost" in texts and "VIO replay: armed, poses not sent" not in texts, texts


def test_a_replay_never_asks_an_armed_autopilot_to_land(ap):
    """`vio replay --mavlink --config FLIGHT.toml` with land_after_loss_s: the recording's loss of tracking (or its
    end: no more estimates) asked the armed autopilot to LAND, a vehicle flying on something else. Only `vio run`
    (poses_to_armed) asks."""
    clock = FakeClock()
    c = MavlinkConfig(mount="rpy", messages=["VISION_POSITION_ESTIMATE"], land_after_loss_s=1.0)
    out = MavlinkOutput(c, f"udpout:127.0.0.1:{ap.port}", clock_ns=clock, poses_to_armed=False)

    def heartbeat(armed: bool) -> None:
        ap.heartbeat(mavlink.MAV_STATE_ACTIVE, mavlink.MAV_MODE_FLAG_SAFETY_ARMED if armed else 0)
        time.sleep(0.02)

    got = []
    for armed, tracking in [(False, True)] * 3 + [(True, False)] * 8:
        heartbeat(armed)
        clock.advance(0.5)
        out.send_state(state(clock.t, tracking=tracking, quality=100 if tracking else 0))
        got += ap.drain(0.01)
    assert ap.of("VISION_POSITION_ESTIMATE", got)  # sent while disarmed
    assert not [m for m in ap.of("COMMAND_LONG", got) if m.command == mavlink.MAV_CMD_NAV_LAND], got
    assert out.stats.land_requests == 0
    out.close()


def test_no_estimate_at_all_is_a_loss_too_and_lands_an_armed_vehicle(ap):
    """Camera and IMU gone together (an OAK's one cable): no state says tracking = false, and the autopilot heard
    nothing, neither a STATUSTEXT nor, with land_after_loss_s, a LAND (a review's finding). No estimate for 0.5 s
    is a loss; land_after_loss_s counts from the last estimate; estimates back: regained."""
    clock = FakeClock()
    out = make_out(ap, clock, land_after_loss_s=3.0)

    def armed_heartbeat() -> None:
        ap.conn.mav.heartbeat_send(mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA,
                                   mavlink.MAV_MODE_FLAG_SAFETY_ARMED, 4, mavlink.MAV_STATE_ACTIVE)
        time.sleep(0.02)

    armed_heartbeat()
    for _ in range(5):
        clock.advance(0.05)
        out.send_state(state(clock.t))
    got = []
    for _ in range(3):  # 0.3 s of silence: not yet
        clock.advance(0.1)
        out.poll()
        got += ap.drain(0.01)
    assert "VIO tracking lost" not in [m.text for m in ap.of("STATUSTEXT", got)]
    for _ in range(30):  # to 3.3 s without an estimate
        clock.advance(0.1)
        armed_heartbeat()
        out.poll()
        got += ap.drain(0.01)
    texts = [m.text for m in ap.of("STATUSTEXT", got)]
    lands = [m for m in ap.of("COMMAND_LONG", got) if m.command == mavlink.MAV_CMD_NAV_LAND]
    assert "VIO tracking lost" in texts and "VIO lost: LAND requested" in texts and len(lands) == 1
    clock.advance(0.1)
    out.send_state(state(clock.t))
    assert "VIO tracking regained" in [m.text for m in ap.of("STATUSTEXT", ap.drain())]
    out.close()


def test_a_process_started_in_flight_that_never_tracks_counts_as_a_loss(ap):
    """A daemon restarted by systemd in flight that cannot initialise sent nothing: the loss clock only started on a
    change from tracking to lost, so the ground station heard nothing while the autopilot dead-reckoned (a QA
    sweep). An autopilot armed when first heard, before any pose, is said; no LAND for it, since a vehicle flown
    without our poses (on GPS, by hand) looks the same (a review's finding); a loss after tracking lands as ever."""
    clock = FakeClock()
    out = make_out(ap, clock, land_after_loss_s=2.0)

    def step(tracking: bool | None) -> list:
        clock.advance(0.25)
        ap.conn.mav.heartbeat_send(mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA,
                                   mavlink.MAV_MODE_FLAG_SAFETY_ARMED, 4, mavlink.MAV_STATE_ACTIVE)
        time.sleep(0.02)
        if tracking is None:
            out.poll()
        else:
            out.send_state(state(clock.t, tracking=tracking, quality=80 if tracking else 0))
        return ap.drain(0.01)

    got = sum((step(None if k < 3 else False) for k in range(10)), [])  # 2.5 s: no estimate, then never tracking
    texts = [m.text for m in ap.of("STATUSTEXT", got)]
    lands = [m for m in ap.of("COMMAND_LONG", got) if m.command == mavlink.MAV_CMD_NAV_LAND]
    assert "VIO not tracking (restarted?)" in texts and "VIO lost: LAND requested" not in texts and not lands
    assert not ap.of("ODOMETRY", got)
    assert "VIO tracking regained" in [m.text for m in ap.of("STATUSTEXT", step(True))]
    got = sum((step(False) for _ in range(10)), [])  # lost after it tracked: the failsafe as configured
    assert len([m for m in ap.of("COMMAND_LONG", got) if m.command == mavlink.MAV_CMD_NAV_LAND]) == 1
    out.close()


def test_no_land_request_once_tracking_is_back_and_the_next_loss_gets_its_own(ap):
    """A LAND not acknowledged (the command or its ACK lost on the radio) was sent again and again after vision came
    back, beside good poses; and the LAND decision raced tracking's return (a loss marked done while tracking,
    leaving the next loss without a LAND): both reviews' findings. The decision is now made under the lock
    send_state() takes."""
    clock = FakeClock()
    out = make_out(ap, clock, land_after_loss_s=3.0)

    def step(dt: float, tracking: bool) -> list:
        clock.advance(dt)
        ap.conn.mav.heartbeat_send(mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA,
                                   mavlink.MAV_MODE_FLAG_SAFETY_ARMED, 4, mavlink.MAV_STATE_ACTIVE)
        time.sleep(0.02)
        out.send_state(state(clock.t, tracking=tracking, quality=80 if tracking else 0))
        return ap.drain(0.01)

    def lands(msgs: list) -> list:
        return [m for m in ap.of("COMMAND_LONG", msgs) if m.command == mavlink.MAV_CMD_NAV_LAND]

    step(0.0, True)
    got = sum((step(0.5, False) for _ in range(7)), [])  # 3.5 s lost: one LAND, unacknowledged
    assert len(lands(got)) == 1
    after = sum((step(0.1, True) for _ in range(40)), [])  # 4 s of good tracking
    assert not lands(after) and len(ap.of("ODOMETRY", after)) >= 30
    got = sum((step(0.5, False) for _ in range(8)), [])  # the next loss: its own LAND
    assert len(lands(got)) >= 1
    out.close()


def test_land_after_loss_is_off_by_default_and_never_sent_while_disarmed(ap):
    clock = FakeClock()
    for cfg in ({}, {"land_after_loss_s": 1.0}):
        out = make_out(ap, clock, **cfg)
        ap.conn.mav.heartbeat_send(mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA,
                                   mavlink.MAV_MODE_FLAG_SAFETY_ARMED if not cfg else 0, 4,
                                   mavlink.MAV_STATE_ACTIVE)
        time.sleep(0.02)
        out.send_state(state(clock.t))
        for _ in range(10):
            clock.advance(0.5)
            out.send_state(state(clock.t, tracking=False, quality=0))
        got = ap.drain()
        assert not [m for m in ap.of("COMMAND_LONG", got) if m.command == mavlink.MAV_CMD_NAV_LAND]
        assert out.stats.land_requests == 0
        out.close()


def test_a_pose_older_than_max_state_age_is_not_sent_and_counts_as_lost(ap, caplog):
    """Nothing limited a pose's age: after a 3 s stall, or under CPU starvation, poses 0.5-2.9 s old went out at
    quality 100 (a review's finding). Beyond max_state_age_ms a state is not sent and counts as a loss of tracking
    (STATUSTEXT, land_after_loss_s); fresh ones resume it."""
    clock = FakeClock()
    out = MavlinkOutput(MavlinkConfig(mount="rpy", messages=["ODOMETRY"]), f"udpout:127.0.0.1:{ap.port}",
                        clock_ns=clock, max_state_age_ms=500)
    out.send_state(state(clock.t - 50_000_000))  # 50 ms old: sent
    assert len(ap.of("ODOMETRY", ap.drain())) == 1
    with caplog.at_level("WARNING", logger="drivers.mavlink_out"):
        for _ in range(5):
            clock.advance(0.1)
            out.send_state(state(clock.t - 900_000_000))  # 0.9 s old
    got = ap.drain()
    assert not ap.of("ODOMETRY", got) and [m.text for m in ap.of("STATUSTEXT", got)] == ["VIO tracking lost"]
    assert out.health()["states_too_old"] == 5 and caplog.text.count("not sent (beyond") == 1
    assert out.health()["withholding_old_poses"]
    clock.advance(0.1)
    out.send_state(state(clock.t - 30_000_000, tracking=False))  # fresh, not tracking: the spell is over
    assert not out.health()["withholding_old_poses"]
    clock.advance(0.1)
    out.send_state(state(clock.t - 30_000_000))
    got = ap.drain()
    assert len(ap.of("ODOMETRY", got)) == 1 and ap.of("STATUSTEXT", got)[0].text == "VIO tracking regained"
    out.close(final=False)  # a reconnect: the autopilot is not told VIO stopped
    assert not ap.of("STATUSTEXT", ap.drain())
    # a pose that aged waiting for its send slot (this thread stalled) is dropped there
    clock = FakeClock()
    out = MavlinkOutput(MavlinkConfig(mount="rpy", messages=["ODOMETRY"]), f"udpout:127.0.0.1:{ap.port}",
                        clock_ns=clock, max_state_age_ms=200)
    out.send_state(state(clock.t))
    clock.advance(0.01)
    out.send_state(state(clock.t))  # inside the slot: waits
    clock.advance(0.3)
    out.poll()
    assert len(ap.of("ODOMETRY", ap.drain())) == 1 and out.health()["states_too_old"] == 1
    out.close()
    # stamps seconds ahead of the host clock are on another clock: the check is said to be off, poses go out
    clock = FakeClock()
    out = MavlinkOutput(MavlinkConfig(mount="rpy", messages=["ODOMETRY"]), f"udpout:127.0.0.1:{ap.port}",
                        clock_ns=clock, max_state_age_ms=500)
    with caplog.at_level("WARNING", logger="drivers.mavlink_out"):
        out.send_state(state(clock.t + 10**12))
    assert "ahead of this host's clock" in caplog.text and len(ap.of("ODOMETRY", ap.drain())) == 1
    out.close()


def test_poses_withheld_for_an_unsure_imu_clock_send_nothing_not_even_a_failed_pose(ap):
    """The daemon's output stage withholds every pose while the IMU source's stamps are too uncertain ([mavlink]
    max_stamp_error_ms): nothing goes out, not even lost_output = 'failed's quality -1 ODOMETRY (PX4 fuses it at
    EKF2_EV_QMIN 0), a pose taken before it does not go out in its slot, the ground station hears why once and
    the loss of tracking as ever; withhold(None) resumes."""
    clock = FakeClock()
    out = make_out(ap, clock, messages=["ODOMETRY"], lost_output="failed")
    out.send_state(state(clock.t))
    clock.advance(0.01)
    out.send_state(state(clock.t))  # inside the slot: pending
    assert [m.quality for m in ap.of("ODOMETRY", ap.drain())] == [80]
    out.withhold("VIO: IMU clock unsure, no poses")
    clock.advance(0.05)
    out.poll()
    not_tracking = out.stats.states_not_tracking
    for k in range(5):
        out.withhold("VIO: IMU clock unsure, no poses")  # before every state: said once
        # the daemon's StampErrorGate hands the states of a spell on as lost already: each one is withheld all the
        # same (the status read states_withheld 0 beside the gate's own count of the states it held back)
        out.send_state(state(clock.t) if k < 3 else state(clock.t, tracking=False, quality=0))
        clock.advance(0.05)
    got = ap.drain()
    assert not ap.of("ODOMETRY", got), [m.quality for m in ap.of("ODOMETRY", got)]
    assert [m.text for m in ap.of("STATUSTEXT", got)] == ["VIO: IMU clock unsure, no poses", "VIO tracking lost"]
    h = out.health()
    assert h["states_withheld"] == 5 and h["withholding_for"] == h["withheld_for"] == "VIO: IMU clock unsure, no poses"
    assert out.stats.states_not_tracking == not_tracking  # one reason a state: withheld, not also 'not tracking'
    out.withhold(None)
    out.send_state(state(clock.t))
    got = ap.drain()
    assert [m.quality for m in ap.of("ODOMETRY", got)] == [80]
    assert [m.text for m in ap.of("STATUSTEXT", got)] == ["VIO tracking regained"]
    h = out.health()  # the count and its why outlive the spell
    assert h["states_withheld"] == 5 and h["withholding_for"] is None and h["withheld_for"].startswith("VIO: IMU")
    out.close()


def test_a_state_both_withheld_and_too_old_counts_once_as_withheld(ap):
    """A state of a withholding spell (the IMU clock unsure) that is also older than max_state_age_ms counted in both
    states_withheld and states_too_old: the status added up to more states held back than there were. It counts
    once, as withheld (the daemon's gate stopped it before the output saw its age); an old state outside a spell
    counts as too old, and the old-pose spell is still said."""
    clock = FakeClock()
    out = MavlinkOutput(MavlinkConfig(mount="rpy", messages=["ODOMETRY"]), f"udpout:127.0.0.1:{ap.port}",
                        clock_ns=clock, max_state_age_ms=500)
    out.send_state(state(clock.t - 50_000_000))  # fresh: sent
    for _ in range(4):
        clock.advance(0.1)
        out.withhold("VIO: IMU clock unsure, no poses")
        out.send_state(state(clock.t - 900_000_000))  # withheld and 0.9 s old
    h = out.health()
    assert (h["states_withheld"], h["states_too_old"]) == (4, 0) and h["withholding_old_poses"]
    out.withhold(None)
    clock.advance(0.1)
    out.send_state(state(clock.t - 900_000_000))  # old, not withheld
    h = out.health()
    assert (h["states_withheld"], h["states_too_old"]) == (4, 1)
    assert len(ap.of("ODOMETRY", ap.drain())) == 1  # only the first
    out.close()


def test_a_state_too_old_or_not_finite_is_not_also_counted_not_tracking(ap, caplog):
    """One reason a state (as 25994b8 made it for withheld and too old): a tracked state older than max_state_age_ms,
    or holding a NaN, is sent as a loss of tracking, and counted in states_not_tracking as well as in its own count
    (4 states in, 1 sent, 5 reasons); a withheld NaN state counted as withheld and not finite. Each counts once now,
    the reason that stopped it first (withheld, too old, not finite, then the estimator's own loss), and the NaN
    error line is still said once."""
    clock = FakeClock()
    out = MavlinkOutput(MavlinkConfig(mount="rpy", messages=["ODOMETRY"]), f"udpout:127.0.0.1:{ap.port}",
                        clock_ns=clock, max_state_age_ms=500)
    nan_cov = np.full((6, 6), np.nan)
    try:
        out.send_state(state(clock.t))  # fresh, tracked: sent
        clock.advance(0.1)
        out.send_state(state(clock.t - 900_000_000))  # tracked, 0.9 s old
        clock.advance(0.1)
        out.send_state(state(clock.t, cov_pose=nan_cov))  # tracked, a NaN covariance
        clock.advance(0.1)
        out.send_state(state(clock.t, tracking=False))  # the estimator's own loss
        clock.advance(0.1)
        out.withhold("VIO: IMU clock unsure, no poses")
        out.send_state(state(clock.t, cov_pose=nan_cov))  # withheld, with a NaN
        st = out.stats
        got = (st.states_sent, st.states_too_old, st.states_not_finite, st.states_not_tracking, st.states_withheld)
        assert got == (1, 1, 1, 1, 1) and st.states_in == sum(got)
        assert caplog.text.count("estimate holds a NaN") == 1
    finally:
        out.close()


def test_a_serial_link_is_held_exclusively(caplog):
    """Two daemons on one flight controller's UART both opened it and interleaved their poses and reset counters
    (a QA sweep): the device is held with flock, and the second output cannot open it, says why and retries."""
    import errno
    import os
    import pty
    import termios

    from drivers.mavlink_link import open_connection

    master, slave = pty.openpty()
    dev = os.ttyname(slave)
    first = open_connection(f"{dev}:115200", 1)
    speed = termios.tcgetattr(slave)[4:6]
    with pytest.raises(OSError) as e:
        open_connection(f"{dev}:57600", 2)
    assert e.value.errno == errno.EBUSY and "held by another connection" in str(e.value)
    # refused before it was opened: the flying link's speed is as it was (a lock taken after mavutil's open let
    # the refused one set it first: a review's finding)
    assert termios.tcgetattr(slave)[4:6] == speed
    with caplog.at_level("WARNING", logger="drivers.mavlink_out"):
        out = MavlinkOutput(MavlinkConfig(mount="rpy", messages=["ODOMETRY"]), f"{dev}:115200", clock_ns=FakeClock())
    assert "held by another connection" in caplog.text
    out.close()
    first.close()  # released: the next process (a restart) gets it
    open_connection(f"{dev}:115200", 2).close()
    os.close(master)
    os.close(slave)


def test_a_replays_refusal_is_not_said_after_the_autopilot_disarms_with_no_pose_to_send(ap):
    """The status's "poses not sent: ... the autopilot says it is armed" (health's withholding_replay_poses) was
    cleared only by the next pose sent: a recording that ended, or a loss of tracking, while the autopilot was armed
    kept saying it was armed after it disarmed. It now follows the autopilot while no pose is pending."""
    clock = FakeClock()
    c = MavlinkConfig(mount="rpy", messages=["VISION_POSITION_ESTIMATE"])
    out = MavlinkOutput(c, f"udpout:127.0.0.1:{ap.port}", clock_ns=clock, poses_to_armed=False)

    def beat(armed: bool, pose: bool) -> None:
        for _ in range(3):
            ap.heartbeat(mavlink.MAV_STATE_ACTIVE, mavlink.MAV_MODE_FLAG_SAFETY_ARMED if armed else 0)
            time.sleep(0.02)
            clock.advance(0.1)
            if pose:
                out.send_state(state(clock.t))
            out.poll()

    out.poll()
    ap.drain()  # our first heartbeat: the autopilot's side learns where to answer
    beat(armed=True, pose=True)
    assert out.health()["withholding_replay_poses"] == "armed" and out.stats.states_refused_armed
    beat(armed=False, pose=False)  # the recording ended: no more poses
    assert out.health()["withholding_replay_poses"] is None
    beat(armed=False, pose=True)
    assert out.health()["withholding_replay_poses"] is None and out.stats.states_sent
    out.close()


def test_a_process_started_in_flight_continues_in_the_autopilots_frame(ap, caplog):
    """A daemon restarted in flight starts its world where the vehicle is; EKF3 resets its position to the external
    nav's at the new reset_counter, so the autopilot's position moved by all the vehicle had flown (1.3 m on the
    SITL, docs/autopilot.md). Heard armed before its first pose, the output asks for the autopilot's own estimate and
    places its first tracked pose there, then turns and shifts every later pose the same way."""
    clock = FakeClock()
    out = make_out(ap, clock, messages=["ODOMETRY"])
    out.poll()  # our first heartbeat: the UDP autopilot learns where to answer
    ap.drain()
    armed = mavlink.MAV_MODE_FLAG_SAFETY_ARMED
    ap.conn.mav.heartbeat_send(mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA, armed, 4,
                               mavlink.MAV_STATE_ACTIVE)
    time.sleep(0.02)
    out.poll()
    asked = [m.param1 for m in ap.of("COMMAND_LONG", ap.drain())
             if m.command == mavlink.MAV_CMD_SET_MESSAGE_INTERVAL]
    assert sorted(asked) == sorted([mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED, mavlink.MAVLINK_MSG_ID_ATTITUDE])
    yaw_ap = math.radians(120.0)
    ap.conn.mav.local_position_ned_send(1000, 4.0, -3.0, -1.5, 0.0, 0.0, 0.0)
    ap.conn.mav.attitude_send(1000, 0.0, 0.0, yaw_ap, 0.0, 0.0, 0.0)
    time.sleep(0.02)
    clock.advance(0.1)
    out.poll()
    first = state(clock.t)  # at (1, 2, 3) in our world, level, its own yaw
    with caplog.at_level("INFO", logger="drivers.mavlink_out"):
        out.send_state(first)
        got = ap.drain()
    od0 = ap.of("ODOMETRY", got)[-1]
    # read once: their rate goes back to the autopilot's default (0), not 10 Hz on the link for the rest of the flight
    back = [(m.param1, m.param2) for m in ap.of("COMMAND_LONG", got)
            if m.command == mavlink.MAV_CMD_SET_MESSAGE_INTERVAL]
    assert sorted(back) == sorted([(mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED, 0.0),
                                   (mavlink.MAVLINK_MSG_ID_ATTITUDE, 0.0)])
    w, x, y, z = od0.q
    np.testing.assert_allclose([od0.x, od0.y, od0.z], [4.0, -3.0, -1.5], atol=1e-5)
    assert math.atan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z)) == pytest.approx(yaw_ap, abs=1e-5)
    assert "continue in the autopilot's frame" in caplog.text
    # 1 m along our world x later: the autopilot sees it 1 m along its heading turned by the same yaw
    ours = to_vehicle_odometry(first.t_ns, first.T_world_body, first.v_world, first.omega_body, first.cov_pose,
                               first.cov_vel, out.T_frd_body)
    clock.advance(0.1)
    T = first.T_world_body.copy()
    T[0, 3] += 1.0
    out.send_state(state(clock.t, T_world_body=T))
    od1 = ap.of("ODOMETRY", ap.drain())[-1]
    step = np.array([od1.x - od0.x, od1.y - od0.y, od1.z - od0.z])
    dyaw = yaw_ap - ours.rpy[2]
    expect = np.array([math.cos(dyaw), math.sin(dyaw), 0.0])  # our world x is NED x before the turn
    np.testing.assert_allclose(step, expect, atol=1e-5)
    out.close()


def _heard_armed(ap, clock) -> MavlinkOutput:
    """An ODOMETRY output that has heard the autopilot armed in GUIDED (a process starting in flight), the messages
    of its link-up drained."""
    out = make_out(ap, clock, messages=["ODOMETRY"])
    out.poll()
    ap.drain()
    ap.conn.mav.heartbeat_send(mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA,
                               mavlink.MAV_MODE_FLAG_SAFETY_ARMED, 4, mavlink.MAV_STATE_ACTIVE)
    time.sleep(0.02)
    out.poll()
    ap.drain()
    return out


def test_a_start_in_flight_carries_the_autopilots_estimate_to_our_first_poses_stamp(ap, caplog):
    """The autopilot's LOCAL_POSITION_NED and ATTITUDE are up to AP_POSE_MAX_AGE_NS older than our first tracked pose;
    taken as they were, a vehicle at 5 m/s put the whole frame 1 m off for the rest of the flight (0.2 s here).
    They are carried to our pose's stamp along the autopilot's own velocity and yaw rate."""
    clock = FakeClock()
    out = _heard_armed(ap, clock)
    yaw_ap = math.radians(120.0)
    ap.conn.mav.local_position_ned_send(1000, 4.0, -3.0, -1.5, 5.0, -1.0, 0.5)  # moving at 5.1 m/s
    # a 30 deg banked turn at 0.4 rad/s about the vertical: body rates q = 0.4 sin 30, r = 0.4 cos 30 (yawspeed alone
    # read 0.35 rad/s)
    roll = math.radians(30.0)
    ap.conn.mav.attitude_send(1000, roll, 0.0, yaw_ap, 0.0, 0.4 * math.sin(roll), 0.4 * math.cos(roll))
    time.sleep(0.02)
    clock.advance(0.1)
    out.poll()  # read: their arrival
    clock.advance(0.2)
    with caplog.at_level("INFO", logger="drivers.mavlink_out"):
        out.send_state(state(clock.t))  # our first tracked pose, 0.2 s after the autopilot's
        od = ap.of("ODOMETRY", ap.drain())[-1]
    np.testing.assert_allclose([od.x, od.y, od.z], [4.0 + 5.0 * 0.2, -3.0 - 1.0 * 0.2, -1.5 + 0.5 * 0.2], atol=1e-5)
    w, x, y, z = od.q
    assert math.atan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z)) == pytest.approx(yaw_ap + 0.4 * 0.2, abs=1e-5)
    assert "carried 200 ms to our pose" in caplog.text
    out.close()


def test_a_process_started_on_the_ground_keeps_its_own_frame(ap):
    """Disarmed when first heard (the normal start): nothing is asked and nothing turned."""
    clock = FakeClock()
    out = make_out(ap, clock, messages=["ODOMETRY"])
    out.poll()
    ap.drain()
    ap.heartbeat()
    time.sleep(0.02)
    out.poll()
    ap.conn.mav.local_position_ned_send(1000, 4.0, -3.0, -1.5, 0.0, 0.0, 0.0)
    ap.conn.mav.attitude_send(1000, 0.0, 0.0, 2.0, 0.0, 0.0, 0.0)
    time.sleep(0.02)
    clock.advance(0.1)
    out.poll()
    s = state(clock.t)
    out.send_state(s)
    got = ap.drain()
    assert not [m for m in ap.of("COMMAND_LONG", got) if m.command == mavlink.MAV_CMD_SET_MESSAGE_INTERVAL]
    od = ap.of("ODOMETRY", got)[-1]
    ours = to_vehicle_odometry(s.t_ns, s.T_world_body, s.v_world, s.omega_body, s.cov_pose, s.cov_vel,
                               out.T_frd_body)
    np.testing.assert_allclose([od.x, od.y, od.z], ours.p_ned, atol=1e-5)
    out.close()


class _KeepingLink(_SharedLink):
    """_SharedLink that keeps the messages it sends, and hands the output the autopilot's messages (its reader)."""

    def __init__(self) -> None:
        super().__init__()
        self.msgs: list = []
        self._enc = mavlink.MAVLink(None, srcSystem=7, srcComponent=1)
        self._dec = mavlink.MAVLink(None)
        self.handler = None

    def send(self, msg) -> bool:
        if self.connected:
            self.msgs.append(msg)
        return super().send(msg)

    def subscribe(self, names, handler) -> None:
        self.handler = handler

    def from_autopilot(self, msg) -> None:
        self.handler(self._dec.parse_char(msg.pack(self._enc)), 0)


def test_a_lost_pose_does_not_go_out_before_a_start_in_flight_has_chosen_its_frame():
    """Started in flight (heard armed first), lost_output = 'failed': the first tracked pose did not go out (the link
    was closed at its slot), and the lost pose after it went out in this process's own frame, the next tracked one in
    the autopilot's, with one reset_counter: PX4 fuses any quality at EKF2_EV_QMIN 0, so it took a 3.6 m jump as a
    measurement. Until the frame is chosen (at the first tracked pose sent) no lost pose goes out."""
    clock, link = FakeClock(), _KeepingLink()
    out = MavlinkOutput(MavlinkConfig(mount="rpy", messages=["ODOMETRY"], lost_output="failed"), link=link,
                        clock_ns=clock, max_state_age_ms=500)
    try:
        link.from_autopilot(mavlink.MAVLink_heartbeat_message(
            mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA, mavlink.MAV_MODE_FLAG_SAFETY_ARMED, 4,
            mavlink.MAV_STATE_ACTIVE, 3))
        out.poll()
        link.from_autopilot(mavlink.MAVLink_local_position_ned_message(1000, 4.0, -3.0, -1.5, 0.0, 0.0, 0.0))
        link.from_autopilot(mavlink.MAVLink_attitude_message(1000, 0.0, 0.0, math.radians(120.0), 0.0, 0.0, 0.0))
        clock.advance(0.01)
        out.poll()
        link.connected = False
        out.send_state(state(clock.t))  # tracked, its slot comes with no connection
        for _ in range(5):
            clock.advance(0.01)
            out.poll()
        assert out.stats.states_link_closed == 1
        link.connected = True
        for _ in range(3):  # lost: the camera went dark
            clock.advance(0.04)
            out.send_state(state(clock.t, tracking=False, quality=0))
        clock.advance(0.04)
        out.send_state(state(clock.t))  # tracked again
        sent = [m for m in link.msgs if m.get_type() == "ODOMETRY"]
        assert sent and all(abs(m.x - 4.0) < 0.01 and abs(m.y + 3.0) < 0.01 for m in sent), \
            [(m.x, m.y, m.quality, m.reset_counter) for m in sent]
    finally:
        out.close()


def test_the_health_says_the_reset_counter_the_autopilot_got(ap, tmp_path):
    """`vio status` gave the estimator's reset_counter 'as the autopilot got it' (0) while the autopilot got it past
    where this process started (counter_file, or a random start): 108 in a `vio run` on V1_01. The output's health
    has the one it sent (none before the first pose)."""
    path = tmp_path / "reset_counter"
    path.write_text("41\n")
    clock = FakeClock()
    out = _counted(ap, clock, path)
    try:
        assert "reset_counter" not in out.health()
        out.send_state(state(clock.t, reset_counter=2))
        sent = ap.of("ODOMETRY", ap.drain())[-1].reset_counter
        assert sent == 44 and out.health()["reset_counter"] == sent
    finally:
        out.close()


def _worker_started_in_flight(send_pose: bool = True, **cfg):
    """An OutputWorker (over a _KeepingLink) whose output heard the autopilot armed, read its estimate (4, -3, -1.5 m
    NED, yaw 120 deg) and sent one tracked pose, so that it continues in the autopilot's frame (without `send_pose`
    the frame's choice is still to come); the link, and the outputs it has made. `cfg`: more [mavlink] keys."""
    from vio.app.daemon.buffers import LatestState
    from vio.app.daemon.outputs import OutputWorker

    link = _KeepingLink()
    outs: list[MavlinkOutput] = []

    def make() -> MavlinkOutput:
        outs.append(MavlinkOutput(MavlinkConfig(mount="rpy", messages=["ODOMETRY"], **cfg), link=link,
                                  random_first_counter=True))
        return outs[-1]

    w = OutputWorker(threading.Event(), LatestState(), make, "", 1.0)
    try:
        w._ensure_mavlink()
        link.from_autopilot(mavlink.MAVLink_heartbeat_message(
            mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA, mavlink.MAV_MODE_FLAG_SAFETY_ARMED, 4,
            mavlink.MAV_STATE_ACTIVE, 3))
        w.mav.poll()
        link.from_autopilot(mavlink.MAVLink_local_position_ned_message(1000, 4.0, -3.0, -1.5, 0.0, 0.0, 0.0))
        link.from_autopilot(mavlink.MAVLink_attitude_message(1000, 0.0, 0.0, math.radians(120.0), 0.0, 0.0, 0.0))
        w.mav.poll()
        if send_pose:
            w._send(state(time.monotonic_ns()))
    except BaseException:
        w.close()
        raise
    return w, link, outs


def _fail_the_output(w) -> None:
    """Make the worker's output raise at its next pose (a bug) and send one: the worker drops it to reopen later."""
    def broken(s: NavState) -> None:
        raise OSError("a bug")

    w.mav.send_state = broken  # type: ignore[method-assign]
    w._send(state(time.monotonic_ns()))
    assert w.mav is None


def test_a_reopened_output_keeps_the_autopilots_frame_of_a_start_in_flight():
    """The daemon reopens a MAVLink output that failed (an exception from send_state or poll). The new one, fed a
    tracked pose before the autopilot's next heartbeat, sent in the estimator's own frame at its new reset_counter:
    EKF3 resets to the external nav's position there, and a process started in flight had its autopilot's position
    jump by all the vehicle had flown before the start (3.6 m here), what the frame turn is for. It keeps the frame
    of the output before it now."""
    w, link, outs = _worker_started_in_flight()
    try:
        first = [m for m in link.msgs if m.get_type() == "ODOMETRY"]
        assert [(round(m.x, 3), round(m.y, 3)) for m in first] == [(4.0, -3.0)]
        _fail_the_output(w)
        w._next_open = 0.0
        w._ensure_mavlink()
        assert len(outs) == 2
        time.sleep(0.04)  # past the new output's first send slot
        w._send(state(time.monotonic_ns()))  # the same pose: the vehicle hovers
        last = [m for m in link.msgs if m.get_type() == "ODOMETRY"][-1]
        assert (round(last.x, 3), round(last.y, 3)) == (4.0, -3.0), (last.x, last.y, last.reset_counter)
    finally:
        w.close()


def test_no_home_is_set_on_an_armed_autopilot(ap):
    """The origin and home go out at each link-up. An armed autopilot has set its home where it armed (ArduCopter
    moves an unlocked home to the vehicle at arming) and RTL flies there: a link lost and back in flight (or a
    restart in flight) moved it to the configured origin, which is only where this process's frame began (a second
    take-off elsewhere, a start in flight). Nor the origin: EKF3 on external nav takes a new one in flight, which
    moves every global position it holds where it had another (a GPS start); it is only asked for while armed.
    Origin and home again once it is disarmed."""
    clock = FakeClock()
    out = make_out(ap, clock, origin_lat_deg=47.3977419, origin_lon_deg=8.5455938, origin_alt_m=488.0)
    out.poll()
    ap.drain()
    armed = mavlink.MAV_MODE_FLAG_SAFETY_ARMED
    for _ in range(4):
        ap.heartbeat(mavlink.MAV_STATE_ACTIVE, armed)
        time.sleep(0.01)
        out.poll()
        clock.advance(0.6)
    got = ap.drain()
    assert not ap.of("SET_GPS_GLOBAL_ORIGIN", got) and not ap.of("SET_HOME_POSITION", got)
    assert [m for m in ap.of("COMMAND_LONG", got) if m.command == mavlink.MAV_CMD_REQUEST_MESSAGE
            and int(m.param1) == mavlink.MAVLINK_MSG_ID_GPS_GLOBAL_ORIGIN]
    for _ in range(4):
        ap.heartbeat(mavlink.MAV_STATE_STANDBY, 0)
        time.sleep(0.01)
        out.poll()
        clock.advance(0.6)
    got = ap.drain()
    assert ap.of("SET_HOME_POSITION", got) and ap.of("SET_GPS_GLOBAL_ORIGIN", got)
    out.close()


def test_an_armed_autopilots_other_origin_is_kept_and_said(ap, caplog):
    """An autopilot heard armed at link-up that holds another EKF origin (a GPS start, a ground station's) keeps it:
    no SET_GPS_GLOBAL_ORIGIN goes out, and the log says the two differ."""
    clock = FakeClock()
    out = make_out(ap, clock, origin_lat_deg=47.3977419, origin_lon_deg=8.5455938, origin_alt_m=488.0)
    out.poll()
    ap.drain()
    with caplog.at_level("INFO", logger="drivers.mavlink_out"):
        for _ in range(3):
            ap.heartbeat(mavlink.MAV_STATE_ACTIVE, mavlink.MAV_MODE_FLAG_SAFETY_ARMED)
            time.sleep(0.01)
            out.poll()
            clock.advance(0.6)
        ap.conn.mav.gps_global_origin_send(473980000, 85460000, 500000)
        time.sleep(0.02)
        for _ in range(4):
            ap.heartbeat(mavlink.MAV_STATE_ACTIVE, mavlink.MAV_MODE_FLAG_SAFETY_ARMED)
            time.sleep(0.01)
            out.poll()
            clock.advance(0.6)
    assert not ap.of("SET_GPS_GLOBAL_ORIGIN", ap.drain())
    assert "is not [mavlink] origin" in caplog.text and "kept, it is armed" in caplog.text
    # the status says whose it is: confirmed alone read as ours
    assert out.health()["origin_confirmed"] is True and out.health()["origin_ours"] is False
    out.close()


@pytest.mark.parametrize("mode", ["jump", "blend"])
def test_a_start_in_flight_relocalised_in_the_map_sends_the_maps_frame_not_turned_twice(mode):
    """A daemon restarted in flight with its map ([map] save's checkpoint, or [map] load) and [loop] output = jump or
    blend: its poses continue in the autopilot's frame (the turn and shift of a start in flight), and the autopilot's
    frame is the map's (the process before sent it). Relocalised, the loop output maps the odometry into the map's
    frame, and the output turned and shifted that once more: 3.2 m and 240 deg of yaw off at the jump's new
    reset_counter (jump), or walked there at the blend rate. The map's frame goes out as it is now."""
    from vio.loop.output import CorrectedOutput, CorrectionUncertainty

    clock, link = FakeClock(), _KeepingLink()
    out = MavlinkOutput(MavlinkConfig(mount="rpy", messages=["ODOMETRY"]), link=link, clock_ns=clock)
    loop = CorrectedOutput(mode)
    loop.frame_turn = out.world_frame_turn
    try:
        link.from_autopilot(mavlink.MAVLink_heartbeat_message(
            mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA, mavlink.MAV_MODE_FLAG_SAFETY_ARMED, 4,
            mavlink.MAV_STATE_ACTIVE, 3))
        out.poll()
        link.from_autopilot(mavlink.MAVLink_local_position_ned_message(1000, 4.0, -3.0, -1.5, 0.0, 0.0, 0.0))
        link.from_autopilot(mavlink.MAVLink_attitude_message(1000, 0.0, 0.0, math.radians(120.0), 0.0, 0.0, 0.0))
        clock.advance(0.01)
        out.poll()
        odo = state(clock.t)  # the odometry at (1, 2, 3), level, yaw 0: the vehicle hovers there
        out.send_state(loop.apply(odo, np.eye(4), 0))
        # the map's frame is the autopilot's: there the vehicle is at NED (4.05, -3, -1.5) (5 cm from where the
        # autopilot had it), yaw 120 deg, i.e. world (4.05, 3, 1.5) at yaw -120 deg
        Rz = so3_exp(np.array([0.0, 0.0, math.radians(-120.0)]))
        C = make_T(Rz, np.array([4.05, 3.0, 1.5]) - Rz @ odo.T_world_body[:3, 3])
        unc = CorrectionUncertainty(np.diag([1e-4, 1e-4, 1e-4, 1e-4]), np.array([4.0, 3.0, 1.5]))
        for _ in range(20):
            clock.advance(0.1)
            out.send_state(loop.apply(dataclasses.replace(odo, t_ns=clock.t), C, 1, unc, segment=1, own_frame=False,
                                      in_map=True))
        sent = [m for m in link.msgs if m.get_type() == "ODOMETRY"]
        for m in sent:
            w, x, y, z = m.q
            yaw = math.degrees(math.atan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z)))
            assert 4.0 - 1e-3 < m.x < 4.05 + 1e-3 and abs(m.y + 3.0) < 1e-3 and abs(m.z + 1.5) < 1e-3, (m.x, m.y, m.z)
            assert yaw == pytest.approx(120.0, abs=1e-3)
        assert sent[-1].x == pytest.approx(4.05, abs=1e-4)
        assert sent[-1].reset_counter == (1 if mode == "jump" else 0)
    finally:
        out.close()


@pytest.mark.parametrize("mode", ["jump", "blend"])
def test_a_start_in_flight_rejoined_after_a_reset_stays_in_the_autopilots_frame(mode):
    """No map: an estimator reset's segment joined back to the flight's first one comes through loop edges (with an
    uncertainty) into this process's own frame, the one the output turns into the autopilot's: it stays turned (only
    a loaded map's frame is the autopilot's already)."""
    from vio.loop.output import CorrectedOutput, CorrectionUncertainty

    clock, link = FakeClock(), _KeepingLink()
    out = MavlinkOutput(MavlinkConfig(mount="rpy", messages=["ODOMETRY"]), link=link, clock_ns=clock)
    loop = CorrectedOutput(mode)
    loop.frame_turn = out.world_frame_turn
    try:
        link.from_autopilot(mavlink.MAVLink_heartbeat_message(
            mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA, mavlink.MAV_MODE_FLAG_SAFETY_ARMED, 4,
            mavlink.MAV_STATE_ACTIVE, 3))
        out.poll()
        link.from_autopilot(mavlink.MAVLink_local_position_ned_message(1000, 4.0, -3.0, -1.5, 0.0, 0.0, 0.0))
        link.from_autopilot(mavlink.MAVLink_attitude_message(1000, 0.0, 0.0, math.radians(120.0), 0.0, 0.0, 0.0))
        clock.advance(0.01)
        out.poll()
        odo = state(clock.t)
        out.send_state(loop.apply(odo, np.eye(4), 0))
        C = make_T(np.eye(3), np.array([0.05, 0.0, 0.0]))  # 5 cm of drift taken out
        unc = CorrectionUncertainty(np.diag([1e-4, 1e-4, 1e-4, 1e-4]), np.array([1.0, 2.0, 3.0]))
        for _ in range(10):
            clock.advance(0.1)
            out.send_state(loop.apply(dataclasses.replace(odo, t_ns=clock.t), C, 1, unc, segment=1, own_frame=False,
                                      in_map=False))
        last = [m for m in link.msgs if m.get_type() == "ODOMETRY"][-1]
        assert np.hypot(last.x - 4.0, last.y + 3.0) == pytest.approx(0.05, abs=1e-4) and abs(last.z + 1.5) < 1e-4
    finally:
        out.close()


@pytest.mark.parametrize("off_s", [1000.0, -5.0])
def test_a_start_in_flight_with_pose_stamps_on_another_clock_carries_the_estimate_to_now(ap, caplog, off_s):
    """Pose stamps not on this host's clock (a sensor's own clock, max_state_age_ms off) say nothing about the
    autopilot's estimate's age: their difference was clamped to 0.5 s and the estimate carried 2.5 m along a 5 m/s
    velocity (a review's finding). It is carried to the output's clock now, where the pose is being sent."""
    clock = FakeClock()
    out = _heard_armed(ap, clock)
    ap.conn.mav.local_position_ned_send(1000, 4.0, -3.0, -1.5, 5.0, 0.0, 0.0)
    ap.conn.mav.attitude_send(1000, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
    time.sleep(0.02)
    clock.advance(0.1)
    out.poll()  # read: their arrival
    clock.advance(0.1)
    with caplog.at_level("INFO", logger="drivers.mavlink_out"):
        out.send_state(state(clock.t + int(off_s * 1e9)))
        od = ap.of("ODOMETRY", ap.drain())[-1]
    np.testing.assert_allclose([od.x, od.y, od.z], [4.0 + 5.0 * 0.1, -3.0, -1.5], atol=1e-5)
    assert "carried 100 ms to our pose" in caplog.text
    out.close()


def test_an_origin_only_asked_for_through_a_long_flight_is_set_once_disarmed(ap):
    """Heard armed, the origin is only asked for, ORIGIN_MAX_SENDS times; a flight longer than that (a minute) spent
    them all, and once disarmed nothing set it: no origin and no home for the next take-off (a review's finding)."""
    clock = FakeClock()
    out = make_out(ap, clock, origin_lat_deg=47.3977419, origin_lon_deg=8.5455938, origin_alt_m=488.0)
    out.poll()
    ap.drain()
    for _ in range(ORIGIN_MAX_SENDS + 5):
        ap.heartbeat(mavlink.MAV_STATE_ACTIVE, mavlink.MAV_MODE_FLAG_SAFETY_ARMED)
        time.sleep(0.005)
        out.poll()
        clock.advance(1.0)
    got = ap.drain()
    assert not ap.of("SET_GPS_GLOBAL_ORIGIN", got)
    for _ in range(4):
        ap.heartbeat(mavlink.MAV_STATE_STANDBY, 0)
        time.sleep(0.01)
        out.poll()
        clock.advance(0.6)
    got = ap.drain()
    assert ap.of("SET_GPS_GLOBAL_ORIGIN", got) and ap.of("SET_HOME_POSITION", got)
    out.close()


def test_the_loop_output_gets_the_turn_of_a_start_in_flight_while_the_output_is_reopened():
    """OutputWorker.frame_turn (read by the loop output at each new correction) said None while a failed output
    waited to be reopened (up to reconnect_max_s): a correction into a loaded map's frame taken then kept the turn,
    and the reopened output, which keeps the frame, turned its poses twice until the next solve."""
    w, _, _ = _worker_started_in_flight()
    try:
        turn = w.frame_turn()
        assert turn is not None
        _fail_the_output(w)
        got = w.frame_turn()
        assert got is not None, "no turn while the output is reopened"
        np.testing.assert_allclose(got, turn)
        w._next_open = 0.0
        w._ensure_mavlink()
        np.testing.assert_allclose(w.frame_turn(), turn)
    finally:
        w.close()


def _armed_beat(link) -> None:
    link.from_autopilot(mavlink.MAVLink_heartbeat_message(
        mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA, mavlink.MAV_MODE_FLAG_SAFETY_ARMED, 4,
        mavlink.MAV_STATE_ACTIVE, 3))


def _reopen(w) -> None:
    w._next_open = 0.0
    w._ensure_mavlink()
    assert w.mav is not None


def _lands(link) -> list:
    return [m for m in link.msgs if m.get_type() == "COMMAND_LONG" and m.command == mavlink.MAV_CMD_NAV_LAND]


def _texts(link) -> list[str]:
    return [m.text if isinstance(m.text, str) else m.text.decode() for m in link.msgs
            if m.get_type() == "STATUSTEXT"]


@pytest.mark.parametrize("lost_before_failure", [True, False])
def test_a_reopened_output_keeps_the_loss_clock_of_a_loss_of_tracking(lost_before_failure):
    """The daemon reopens a MAVLink output that failed (an exception from it). One reopened during a loss of tracking
    began with no tracking state of its own: the lost states it got were no change, so the loss had no clock, no
    land_after_loss_s LAND and (a loss that began while none was open) no 'VIO tracking lost'. It goes on from the
    closed one's tracking state and loss clock."""
    w, link, outs = _worker_started_in_flight(land_after_loss_s=0.2)
    try:
        if lost_before_failure:
            w._send(state(time.monotonic_ns(), tracking=False, quality=0))
            assert _texts(link).count("VIO tracking lost") == 1
        _fail_the_output(w)
        _reopen(w)
        _armed_beat(link)
        w.mav.poll()
        for _ in range(4):
            time.sleep(0.08)
            w._send(state(time.monotonic_ns(), tracking=False, quality=0))
            w.mav.poll()
        assert _texts(link).count("VIO tracking lost") == 1, _texts(link)
        assert _lands(link), _texts(link)
    finally:
        w.close()


def test_a_reopened_output_moves_reset_counter_only_with_the_estimator(monkeypatch):
    """A reopened output drew a new random first counter (counter_file empty): after an estimator reset while none
    was open its pose, a step, could go out at the very counter the autopilot last got (1 in 256), fused as a
    measurement; and without a reset the counter moved for nothing. It goes on from the closed one's counter."""
    draws = iter([5, 4])  # the second output's random start meets the first's: rc 1 + 4 == rc 0 + 5
    monkeypatch.setattr("drivers.mavlink_out.secrets.randbelow", lambda n: next(draws))
    w, link, outs = _worker_started_in_flight()
    try:
        first = [m.reset_counter for m in link.msgs if m.get_type() == "ODOMETRY"]
        assert first == [5]
        _fail_the_output(w)
        _reopen(w)
        time.sleep(0.04)
        w._send(state(time.monotonic_ns(), reset_counter=1))  # the estimator reset meanwhile: a step
        sent = [m.reset_counter for m in link.msgs if m.get_type() == "ODOMETRY"]
        assert sent == [5, 6], sent
        assert "VIO reset" in _texts(link)
    finally:
        w.close()


def test_a_reopened_output_with_the_frame_still_to_choose_keeps_its_loss():
    """Started in flight (heard armed before any pose: not tracking, 'VIO not tracking (restarted?)'), the output
    failed before its first tracked pose chose the frame. The reopened one kept the frame's choice still to come but
    skipped the loss: no tracking state, so its first tracked pose was no 'VIO tracking regained' either, and a
    loss after it none of its own until a second change. It goes on from the closed one's loss."""
    w, link, outs = _worker_started_in_flight(send_pose=False, land_after_loss_s=0.2)
    try:
        assert "VIO not tracking (restarted?)" in _texts(link)
        _fail_the_output(w)
        _reopen(w)
        _armed_beat(link)
        w.mav.poll()
        w._send(state(time.monotonic_ns(), tracking=False, quality=0))
        time.sleep(0.3)
        w.mav.poll()
        assert not _lands(link)  # a start in flight's own loss asks no LAND (nothing says we flew it)
        time.sleep(0.04)
        w._send(state(time.monotonic_ns()))
        sent = [m for m in link.msgs if m.get_type() == "ODOMETRY"]
        assert [(round(m.x, 3), round(m.y, 3)) for m in sent] == [(4.0, -3.0)]
        assert "VIO tracking regained" in _texts(link), _texts(link)
        for _ in range(4):
            time.sleep(0.08)
            w._send(state(time.monotonic_ns(), tracking=False, quality=0))
            w.mav.poll()
        assert "VIO tracking lost" in _texts(link) and _lands(link), _texts(link)
    finally:
        w.close()


def _loop_in_flight(mode: str):
    """A MavlinkOutput (over a _KeepingLink, fake clock) that heard the autopilot armed and read its estimate (4, -3,
    -1.5 m NED, yaw 120 deg), and a CorrectedOutput in `mode`; the map's frame (the autopilot's) has the vehicle at
    NED (4.05, -3, -1.5), yaw 120 deg. Returns (clock, link, out, loop, odo, C, unc)."""
    from vio.loop.output import CorrectedOutput, CorrectionUncertainty

    clock, link = FakeClock(), _KeepingLink()
    out = MavlinkOutput(MavlinkConfig(mount="rpy", messages=["ODOMETRY"]), link=link, clock_ns=clock)
    loop = CorrectedOutput(mode)
    _armed_beat(link)
    out.poll()
    link.from_autopilot(mavlink.MAVLink_local_position_ned_message(1000, 4.0, -3.0, -1.5, 0.0, 0.0, 0.0))
    link.from_autopilot(mavlink.MAVLink_attitude_message(1000, 0.0, 0.0, math.radians(120.0), 0.0, 0.0, 0.0))
    clock.advance(0.01)
    out.poll()
    odo = state(clock.t)  # the odometry at (1, 2, 3), level, yaw 0: the vehicle hovers there
    Rz = so3_exp(np.array([0.0, 0.0, math.radians(-120.0)]))
    C = make_T(Rz, np.array([4.05, 3.0, 1.5]) - Rz @ odo.T_world_body[:3, 3])
    unc = CorrectionUncertainty(np.diag([1e-4, 1e-4, 1e-4, 1e-4]), np.array([4.0, 3.0, 1.5]))
    return clock, link, out, loop, odo, C, unc


def _check_in_the_maps_frame(link, mode: str) -> None:
    sent = [m for m in link.msgs if m.get_type() == "ODOMETRY"]
    for m in sent:
        w, x, y, z = m.q
        yaw = math.degrees(math.atan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z)))
        assert 4.0 - 1e-3 < m.x < 4.05 + 1e-3 and abs(m.y + 3.0) < 1e-3 and abs(m.z + 1.5) < 1e-3, \
            [(round(m.x, 3), round(m.y, 3), m.reset_counter) for m in sent]
        assert yaw == pytest.approx(120.0, abs=1e-3)
    assert sent[-1].x == pytest.approx(4.05, abs=1e-4), [(round(m.x, 3), m.reset_counter) for m in sent]
    steps = [(a.reset_counter, b.reset_counter) for a, b in zip(sent, sent[1:]) if abs(a.x - b.x) > 1e-3]
    if mode == "jump":  # the 5 cm step comes with a new reset_counter, never without one
        assert steps and all(a != b for a, b in steps), steps


@pytest.mark.parametrize("mode", ["jump", "blend"])
def test_a_map_correction_taken_before_the_start_in_flights_turn_is_chosen_is_not_turned_twice(mode):
    """Started in flight with a map: the loop output took a correction into the map's frame (the autopilot's) while
    the MAVLink output's turn was still to be chosen (frame_turn None: nothing taken out), and the output then chose
    it at an earlier state of the odometry's own frame, still waiting to be sent: every pose after it went out
    turned twice, 3.2 m and 240 deg of yaw off (jump) until the next solve. A correction into a map's frame is taken
    once the turn is chosen."""
    clock, link, out, loop, odo, C, unc = _loop_in_flight(mode)
    loop.frame_turn, loop.frame_pending = out.world_frame_turn, out.frame_pending
    try:
        first = loop.apply(odo, np.eye(4), 0)  # handed to the output, not sent yet
        clock.advance(0.005)
        nxt = loop.apply(dataclasses.replace(odo, t_ns=clock.t), C, 1, unc, segment=1, own_frame=False, in_map=True)
        out.send_state(first)  # its first tracked pose: the turn is chosen from it
        clock.advance(0.1)
        out.send_state(nxt)
        for _ in range(20):
            clock.advance(0.1)
            out.send_state(loop.apply(dataclasses.replace(odo, t_ns=clock.t), C, 1, unc, segment=1,
                                      own_frame=False, in_map=True))
        _check_in_the_maps_frame(link, mode)
    finally:
        out.close()


@pytest.mark.parametrize("mode", ["jump", "blend"])
def test_a_map_correction_taken_with_no_output_open_gets_the_turn_chosen_later(mode):
    """A correction into the map's frame taken while no MAVLink output was open (none opened yet: no turn, none
    pending) kept the turn the output chose later in (never taken out) until the next solve: its poses went in the
    autopilot's estimate's frame, not the map's, and the next solve stepped (blend: walked) to the map's. The held
    correction takes the turn out once there is one."""
    clock, link, out, loop, odo, C, unc = _loop_in_flight(mode)
    loop.frame_turn, loop.frame_pending = (lambda: None), (lambda: False)  # no output open
    try:
        clock.advance(0.005)
        s1 = loop.apply(dataclasses.replace(odo, t_ns=clock.t), C, 1, unc, segment=1, own_frame=False, in_map=True)
        loop.frame_turn, loop.frame_pending = out.world_frame_turn, out.frame_pending  # the output is open
        out.send_state(s1)  # the turn is chosen from the map's pose: ~5 cm from the autopilot's estimate
        for _ in range(20):
            clock.advance(0.1)
            out.send_state(loop.apply(dataclasses.replace(odo, t_ns=clock.t), C, 1, unc, segment=1,
                                      own_frame=False, in_map=True))
        _check_in_the_maps_frame(link, mode)
    finally:
        out.close()


def test_a_reopened_output_hearing_the_autopilot_armed_before_the_hand_over_keeps_the_processs_frame():
    """The daemon's factory starts the reopened output's thread before the worker hands it the closed one's frame and
    counter: a first heartbeat read in between, armed, made it a start in flight (its own output had sent nothing),
    and its first tracked pose chose a turn into the autopilot's frame at the reset_counter the process had sent its
    own frame's poses with: a step the autopilot fused as a measurement. The hand-over undoes that choice when the
    closed one had sent poses (in the process's own frame)."""
    from vio.app.daemon.buffers import LatestState
    from vio.app.daemon.outputs import OutputWorker

    link = _KeepingLink()
    outs: list[MavlinkOutput] = []

    def make() -> MavlinkOutput:
        outs.append(MavlinkOutput(MavlinkConfig(mount="rpy", messages=["ODOMETRY"]), link=link,
                                  random_first_counter=True))
        if len(outs) == 2:  # its thread reads the autopilot before the hand-over
            _armed_beat(link)
            link.from_autopilot(mavlink.MAVLink_local_position_ned_message(1000, 4.0, -3.0, -1.5, 0.0, 0.0, 0.0))
            link.from_autopilot(mavlink.MAVLink_attitude_message(1000, 0.0, 0.0, math.radians(120.0), 0.0, 0.0,
                                                                 0.0))
            outs[-1].poll()
        return outs[-1]

    w = OutputWorker(threading.Event(), LatestState(), make, "", 1.0)
    try:
        w._ensure_mavlink()
        w._send(state(time.monotonic_ns()))  # the autopilot not heard yet: the process's own frame
        _fail_the_output(w)
        _reopen(w)
        time.sleep(0.04)
        w._send(state(time.monotonic_ns()))
        sent = [m for m in link.msgs if m.get_type() == "ODOMETRY"]
        assert len(sent) == 2 and len({m.reset_counter for m in sent}) == 1
        assert [(round(m.x, 3), round(m.y, 3)) for m in sent] == [(1.0, -2.0)] * 2, \
            [(m.x, m.y, m.reset_counter) for m in sent]
    finally:
        w.close()


def test_a_start_in_flight_takes_the_autopilots_own_estimate_not_another_components():
    """A start in flight places its first pose where the autopilot's own estimate (LOCAL_POSITION_NED, ATTITUDE) has
    the vehicle. They were taken from any component of the autopilot's system: another onboard component's (a second
    estimator, a companion program, with the vehicle's system id) put every pose of the process in its frame, 50 m
    off here. Only the autopilot's (component 1) are read, as for its heartbeat and TIMESYNC."""
    clock, link = FakeClock(), _KeepingLink()
    out = MavlinkOutput(MavlinkConfig(mount="rpy", messages=["ODOMETRY"]), link=link, clock_ns=clock)
    other = mavlink.MAVLink(None, srcSystem=7, srcComponent=191)
    dec = mavlink.MAVLink(None)
    try:
        _armed_beat(link)
        out.poll()
        link.from_autopilot(mavlink.MAVLink_local_position_ned_message(1000, 4.0, -3.0, -1.5, 0.0, 0.0, 0.0))
        link.from_autopilot(mavlink.MAVLink_attitude_message(1000, 0.0, 0.0, math.radians(120.0), 0.0, 0.0, 0.0))
        for m in (mavlink.MAVLink_local_position_ned_message(1000, 40.0, 30.0, -1.5, 0.0, 0.0, 0.0),
                  mavlink.MAVLink_attitude_message(1000, 0.0, 0.0, math.radians(-60.0), 0.0, 0.0, 0.0)):
            link.handler(dec.parse_char(m.pack(other)), 0)
        clock.advance(0.01)
        out.poll()
        out.send_state(state(clock.t))
        sent = [m for m in link.msgs if m.get_type() == "ODOMETRY"]
        assert [(round(m.x, 3), round(m.y, 3)) for m in sent] == [(4.0, -3.0)]
    finally:
        out.close()


def test_only_the_autopilots_own_ack_stops_the_land_requests():
    """MAV_CMD_NAV_LAND is repeated until the autopilot accepts it (COMMAND_ACK). An ACK from another component of its
    system (a companion program answering commands it sees on the link) counted as the autopilot's: the repeats
    stopped and the status said land_accepted, while the autopilot may never have had the command."""
    clock, link = FakeClock(), _KeepingLink()
    out = MavlinkOutput(MavlinkConfig(mount="rpy", messages=["ODOMETRY"], land_after_loss_s=1.0), link=link,
                        clock_ns=clock)
    other = mavlink.MAVLink(None, srcSystem=7, srcComponent=191)
    dec = mavlink.MAVLink(None)
    try:
        out.send_state(state(clock.t))  # tracked: a pose before the autopilot is heard, no start in flight
        _armed_beat(link)
        out.poll()
        clock.advance(0.1)
        out.send_state(state(clock.t, tracking=False, quality=0))
        for _ in range(3):
            clock.advance(0.6)
            _armed_beat(link)
            out.poll()
        assert len(_lands(link)) == 1
        ack = mavlink.MAVLink_command_ack_message(mavlink.MAV_CMD_NAV_LAND, mavlink.MAV_RESULT_ACCEPTED)
        link.handler(dec.parse_char(ack.pack(other)), 0)
        for _ in range(10):
            clock.advance(0.6)
            _armed_beat(link)
            out.poll()
        assert not out.stats.land_accepted and len(_lands(link)) == 5
    finally:
        out.close()
