"""Frame conversions at the MAVLink edge: estimator world (z up) / body (IMU) -> local NED / vehicle FRD.

The estimator's world frame is gravity-aligned with z up and an arbitrary yaw fixed at initialisation.
We map it to the autopilot's local frame by a half turn about x (x stays, y and z flip), so world x is
the local frame's x ("forward at start" when the estimator starts with the vehicle's nose along world x)
and the result is a right-handed z-down frame with consistent yaw: exactly what a MAV_FRAME_LOCAL_FRD /
external-navigation source must provide. Nothing here knows north; call it NED only because the
autopilot treats it so. The IMU (body) is tied to the vehicle FRD frame by the configured mounting
rotation and lever arm, and every reported quantity is of the vehicle's reference point.

Numpy only (no pymavlink) so the math is testable on its own; see docs/autopilot.md for the tables.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from vio.geometry import make_T, roll_pitch_yaw, rot_to_quat_wxyz, skew

# p_ned = R_NED_WORLD @ p_world: a half turn about x (proper rotation, det +1).
R_NED_WORLD = np.diag([1.0, -1.0, -1.0])


def mount_transform(mount_rpy_deg: np.ndarray | list, mount_offset_m: np.ndarray | list) -> np.ndarray:
    """T_frd_body from the mounting: R_frd_body = Rz(yaw) Ry(pitch) Rx(roll), p_frd_body = offset.

    `mount_rpy_deg` is the IMU's orientation in the vehicle FRD frame (its axes' directions), and
    `mount_offset_m` the IMU's position in that frame relative to the vehicle's reference point.
    """
    rpy = np.radians(np.asarray(mount_rpy_deg, dtype=float))
    R = Rotation.from_euler("ZYX", rpy[::-1]).as_matrix()
    return make_T(R, np.asarray(mount_offset_m, dtype=float))


# Vehicle FRD axes in cam0's optical frame (x right, y down, z out of the lens), for the `mount` choices.
R_FRD_CAM0 = {
    "camera-forward": np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]]),  # nose = lens axis
    "camera-down": np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]),  # nose = image top
}
SNAP_DEG = 3.0  # a derived mount this close to an axis-aligned one is taken as square (calibration noise)


def _axis_rotations() -> list[np.ndarray]:
    """The 24 proper rotations that map axes onto axes (signed permutation matrices with det +1)."""
    import itertools

    out = []
    for perm in itertools.permutations(range(3)):
        for signs in itertools.product((1.0, -1.0), repeat=3):
            M = np.zeros((3, 3))
            for row, (col, sgn) in enumerate(zip(perm, signs)):
                M[row, col] = sgn
            if np.linalg.det(M) > 0:
                out.append(M)
    return out


def _angle_deg(R: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0))))


@dataclass(frozen=True)
class Mount:
    """R_frd_body and how it was found (for the start-up log line)."""

    R_frd_body: np.ndarray
    note: str
    off_axis_deg: float  # angle between the IMU's axes and the nearest vehicle axes


def mount_rotation(mount: str, mount_rpy_deg, R_body_cam0: np.ndarray | None, camera_tilt_deg: float = 0.0) -> Mount:
    """R_frd_body for the configured `mount`.

    'rpy' takes `mount_rpy_deg`. 'camera-forward' / 'camera-down' place the camera in the airframe (looking
    along the nose, pitched down by `camera_tilt_deg`; or looking down, image top to the nose) and carry
    the IMU along with the calibration's exact `R_body_cam0`: right whether the IMU sits in the camera (an
    OAK, tilted with it) or square on the frame, as long as the tilt is stated. A result within SNAP_DEG of
    an axis-aligned mount is snapped to it (calibration noise); one further off is kept and reported, since
    an unstated camera tilt on an IMU that is square to the frame would show as exactly that angle."""
    from vio import VioError

    if mount == "rpy":
        R = mount_transform(mount_rpy_deg, np.zeros(3))[:3, :3]
        return Mount(R, "mount_rpy_deg", 0.0)
    if mount not in R_FRD_CAM0:
        raise VioError(f"[mavlink] mount = {mount!r}: expected one of {['rpy', *R_FRD_CAM0]}")
    if R_body_cam0 is None:
        raise VioError(f"[mavlink] mount = {mount!r} needs the calibration's T_body_cam0")
    tilt = np.radians(camera_tilt_deg)
    # pitching the nose-mounted camera down by `tilt` about the vehicle's right axis (FRD y)
    R_tilt = np.array([[np.cos(tilt), 0.0, -np.sin(tilt)], [0.0, 1.0, 0.0], [np.sin(tilt), 0.0, np.cos(tilt)]])
    R_frd_cam = (R_tilt if mount == "camera-forward" else np.eye(3)) @ R_FRD_CAM0[mount]
    R = R_frd_cam @ np.asarray(R_body_cam0, dtype=float).T
    best = min(_axis_rotations(), key=lambda M: _angle_deg(M.T @ R))
    off = _angle_deg(best.T @ R)
    if off <= SNAP_DEG:
        return Mount(best, f"{mount}, camera tilt {camera_tilt_deg:g} deg, IMU square to the airframe", off)
    return Mount(R, f"{mount}, camera tilt {camera_tilt_deg:g} deg, IMU {off:.1f} deg from the airframe axes "
                 "(tilted with the camera, as in an OAK)", off)


def mount_rpy_deg_from_matrix(R_frd_body: np.ndarray) -> np.ndarray:
    """Inverse of the rotation part of `mount_transform`: the mount_rpy_deg that gives R_frd_body.

    Write R_frd_body's columns as the body (IMU) axes expressed in vehicle FRD, then call this.
    """
    return np.degrees(roll_pitch_yaw(np.asarray(R_frd_body, dtype=float)))


def euler_rate_matrix(roll: float, pitch: float) -> np.ndarray:
    """E with d(roll, pitch, yaw) = E @ dtheta_frd for a small body-frame (FRD) rotation dtheta_frd.

    Singular at pitch = +-90 deg; cos(pitch) is kept away from zero so the covariance stays finite
    (and large) there instead of becoming inf/NaN.
    """
    sr, cr = np.sin(roll), np.cos(roll)
    cp = np.cos(pitch)
    cp = np.copysign(max(abs(cp), 1e-3), cp)
    tp = np.sin(pitch) / cp
    return np.array([[1.0, sr * tp, cr * tp],
                     [0.0, cr, -sr],
                     [0.0, sr / cp, cr / cp]])


def upper_triangle(M: np.ndarray) -> list[float]:
    """Row-major upper triangle (diagonal included) of a square matrix: 21 values for 6x6, MAVLink order."""
    M = np.asarray(M, dtype=float)
    return [float(x) for x in M[np.triu_indices(M.shape[0])]]


@dataclass(frozen=True)
class VehicleOdometry:
    """One NavState expressed for the autopilot: the vehicle reference point in local NED, attitude of FRD.

    `cov_pose_ned` is 6x6 over (x, y, z [m] in NED, roll, pitch, yaw [rad]): the state order of MAVLink's
    pose covariances. Velocity covariances are 3x3 in NED (`cov_v_ned`) and in FRD (`cov_v_frd`).
    """

    t_ns: int
    p_ned: np.ndarray
    R_ned_frd: np.ndarray
    rpy: np.ndarray  # roll, pitch, yaw [rad] of FRD in NED (Z-Y-X)
    q_ned_frd_wxyz: np.ndarray
    v_ned: np.ndarray
    v_frd: np.ndarray
    omega_frd: np.ndarray
    cov_pose_ned: np.ndarray
    cov_v_ned: np.ndarray
    cov_v_frd: np.ndarray


def to_vehicle_odometry(t_ns: int, T_world_body: np.ndarray, v_world: np.ndarray, omega_body: np.ndarray,
                        cov_pose: np.ndarray, cov_vel: np.ndarray, T_frd_body: np.ndarray) -> VehicleOdometry:
    """Convert an estimator state (IMU pose/velocity in world, covariances as in NavState) for the autopilot.

    Pose covariance: GTSAM's Pose3 perturbation T = T_hat * Exp([dtheta; drho]) (body frame, rotation
    first) is mapped to (dp_ned, d_rpy) by its first-order Jacobian, including the lever arm, because the
    autopilot reads variances in its own axes and Euler angles. Velocity covariance adds the attitude
    term for the body-frame velocity (blocks are assumed uncorrelated: NavState carries no cross terms).
    """
    R_wb = np.asarray(T_world_body, dtype=float)[:3, :3]
    p_wb = np.asarray(T_world_body, dtype=float)[:3, 3]
    R_fb = T_frd_body[:3, :3]
    p_body_ref = -R_fb.T @ T_frd_body[:3, 3]  # vehicle reference point in the body (IMU) frame
    omega_body = np.asarray(omega_body, dtype=float)

    R_nb = R_NED_WORLD @ R_wb
    R_ned_frd = R_nb @ R_fb.T
    p_ned = R_NED_WORLD @ (p_wb + R_wb @ p_body_ref)
    v_ref_world = np.asarray(v_world, dtype=float) + R_wb @ np.cross(omega_body, p_body_ref)
    v_ned = R_NED_WORLD @ v_ref_world
    v_body = R_wb.T @ v_ref_world
    rpy = roll_pitch_yaw(R_ned_frd)

    J = np.zeros((6, 6))  # rows (dp_ned, d_rpy), columns (dtheta_body, drho_body)
    J[:3, :3] = -R_nb @ skew(p_body_ref)
    J[:3, 3:] = R_nb
    J[3:, :3] = euler_rate_matrix(rpy[0], rpy[1]) @ R_fb
    cov_pose_ned = J @ np.asarray(cov_pose, dtype=float) @ J.T

    cov_vel = np.asarray(cov_vel, dtype=float)
    cov_v_ned = R_NED_WORLD @ cov_vel @ R_NED_WORLD.T
    A = R_fb @ skew(v_body)  # d v_frd / d dtheta_body
    cov_v_frd = R_fb @ R_wb.T @ cov_vel @ R_wb @ R_fb.T + A @ np.asarray(cov_pose, dtype=float)[:3, :3] @ A.T

    return VehicleOdometry(
        t_ns=int(t_ns), p_ned=p_ned, R_ned_frd=R_ned_frd, rpy=rpy, q_ned_frd_wxyz=rot_to_quat_wxyz(R_ned_frd),
        v_ned=v_ned, v_frd=R_fb @ v_body, omega_frd=R_fb @ omega_body,
        cov_pose_ned=0.5 * (cov_pose_ned + cov_pose_ned.T), cov_v_ned=cov_v_ned,
        cov_v_frd=0.5 * (cov_v_frd + cov_v_frd.T))
