"""Rotations and rigid transforms on numpy arrays.

Quaternions are Hamilton; arrays carry their component order in the name (`q_wxyz`, `q_xyzw`).
Conversions go through scipy's Rotation so we do not hand-roll quaternion algebra; a single rotation
matrix goes through gtsam's Rot3 instead, where per-frame code converts one at a time (scipy's from_matrix
costs ~100 us a call, Rot3 ~3 us, equal to 1e-15).
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Sequence

import gtsam
import numpy as np
from scipy.spatial.transform import Rotation

GRAVITY_M_S2 = 9.81
_EYE3 = np.eye(3)


def skew(v: np.ndarray) -> np.ndarray:
    """3x3 cross-product matrix: skew(a) @ b == a x b."""
    x, y, z = v
    return np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])


def quat_wxyz_to_rot(q_wxyz: np.ndarray) -> np.ndarray:
    """Rotation matrix (..., 3, 3) from Hamilton quaternions (..., 4) in w,x,y,z order (normalised here)."""
    q = np.asarray(q_wxyz, dtype=float)
    return Rotation.from_quat(q[..., [1, 2, 3, 0]]).as_matrix()


def _single_rot3(R: np.ndarray) -> gtsam.Rot3 | None:
    """R as a gtsam Rot3 when it is one orthonormal 3x3 matrix (else None: scipy handles stacks, and finds
    the nearest rotation of a matrix that is not quite one)."""
    if R.shape != (3, 3) or not float(np.abs(R @ R.T - _EYE3).max()) <= 1e-9:  # (np.allclose: 20 us)
        return None
    return gtsam.Rot3(R)


def rot_to_quat_wxyz(R: np.ndarray) -> np.ndarray:
    """Hamilton quaternion(s) w,x,y,z with w >= 0 from rotation matrix/matrices."""
    R = np.asarray(R, dtype=float)
    r3 = _single_rot3(R)
    if r3 is not None:
        g = r3.toQuaternion()
        q = np.array([g.w(), g.x(), g.y(), g.z()])
        q /= np.linalg.norm(q)
        return -q if q[0] < 0 else q
    q = Rotation.from_matrix(R).as_quat()[..., [3, 0, 1, 2]]
    return np.where(q[..., :1] < 0, -q, q)


def so3_exp(phi: np.ndarray) -> np.ndarray:
    """Rotation matrix (..., 3, 3) of rotation vector(s) (..., 3) (axis * angle, rad)."""
    phi = np.asarray(phi, dtype=float)
    if phi.shape == (3,):
        R = _so3_exp_one(float(phi[0]), float(phi[1]), float(phi[2]))
        if R is not None:
            return R
    return Rotation.from_rotvec(phi).as_matrix()


def _so3_exp_one(x: float, y: float, z: float) -> np.ndarray | None:
    """scipy's Rotation.from_rotvec(v).as_matrix() of one finite rotation vector, the same operations in the same
    order on Python floats (libm's sin and cos, as scipy's compiled code calls them): equal to the bit (a test
    compares them on a million vectors from 1e-6 to 3 rad, both sides of the small-angle series), at 5 us instead
    of scipy's 33 us for one vector (the loop stage's edge mean asks one per verified candidate). None when the
    vector is not finite (math.sin raises where C's gives NaN: scipy's answer then)."""
    angle = math.sqrt(x * x + y * y + z * z)
    if not math.isfinite(angle):
        return None
    if angle <= 1e-3:  # scipy's Taylor series of sin(angle / 2) / angle
        a2 = angle * angle
        scale = 0.5 - a2 / 48 + a2 * a2 / 3840
    else:
        scale = math.sin(angle / 2) / angle
    qx, qy, qz, w = scale * x, scale * y, scale * z, math.cos(angle / 2)
    x2, y2, z2, w2 = qx * qx, qy * qy, qz * qz, w * w
    xy, zw, xz, yw, yz, xw = qx * qy, qz * w, qx * qz, qy * w, qy * qz, qx * w
    return np.array([[x2 - y2 - z2 + w2, 2 * (xy - zw), 2 * (xz + yw)],
                     [2 * (xy + zw), -x2 + y2 - z2 + w2, 2 * (yz - xw)],
                     [2 * (xz - yw), 2 * (yz + xw), -x2 - y2 + z2 + w2]])


def so3_log(R: np.ndarray) -> np.ndarray:
    """Rotation vector (axis * angle, rad) of a rotation matrix."""
    R = np.asarray(R, dtype=float)
    r3 = _single_rot3(R)
    return gtsam.Rot3.Logmap(r3) if r3 is not None else Rotation.from_matrix(R).as_rotvec()


def make_T(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """4x4 transform from rotation R (3x3) and translation t (3,)."""
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t
    return T


def inv_T(T: np.ndarray) -> np.ndarray:
    """Inverse of a rigid transform (or a stack of them, shape (..., 4, 4))."""
    T = np.asarray(T, dtype=float)
    if T.shape == (4, 4) and T.flags.c_contiguous:
        # one row-major transform on Python floats, 4 us instead of 15 (the loop stage inverts ~9 a searched
        # keyframe): einsum's answer to the bit, which sums a row-major T's (0 + first product) + second + third in
        # that order, so a zero translation keeps its -0.0 (a test compares the bytes). A column-major T (gtsam's
        # poses) einsum sums in another order (first + third) + second, and its answer keeps T's memory order, in
        # which numpy's products round differently: it stays on the general path below
        (a, b, c, x), (d, e, f, y), (g, h, i, z) = T[:3].tolist()
        return np.array([[a, d, g, -(0.0 + a * x + d * y + g * z)], [b, e, h, -(0.0 + b * x + e * y + h * z)],
                         [c, f, i, -(0.0 + c * x + f * y + i * z)], [0.0, 0.0, 0.0, 1.0]])
    R = T[..., :3, :3]
    t = T[..., :3, 3]
    out = np.zeros_like(T)
    Rt = np.swapaxes(R, -1, -2)
    out[..., :3, :3] = Rt
    out[..., :3, 3] = -np.einsum("...ij,...j->...i", Rt, t)
    out[..., 3, 3] = 1.0
    return out


def transform_points(T_a_b: np.ndarray, p_b: np.ndarray) -> np.ndarray:
    """p_a = T_a_b @ p_b for points p_b of shape (N, 3)."""
    return p_b @ T_a_b[:3, :3].T + T_a_b[:3, 3]


def rotation_angle_deg(R: np.ndarray) -> float:
    """Angle of a rotation matrix in degrees (robust to round-off)."""
    c = (np.trace(R) - 1.0) / 2.0
    return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))


def is_rotation(R: np.ndarray, tol: float = 1e-6) -> bool:
    """True if R is orthonormal with determinant +1 within tol."""
    R = np.asarray(R, dtype=float)
    return R.shape == (3, 3) and np.allclose(R @ R.T, np.eye(3), atol=tol) and abs(np.linalg.det(R) - 1) < tol


def is_se3(T: np.ndarray, tol: float = 1e-6) -> bool:
    """True if T is a valid 4x4 rigid transform."""
    T = np.asarray(T, dtype=float)
    return T.shape == (4, 4) and is_rotation(T[:3, :3], tol) and np.allclose(T[3], [0, 0, 0, 1], atol=tol)


def roll_pitch_yaw(R_world_body: np.ndarray) -> np.ndarray:
    """Z-Y-X Euler angles (roll, pitch, yaw) in rad of a world(z-up)<-body rotation.

    At pitch +-90 deg roll and yaw are not separable; scipy then sets one of them to zero and warns, which
    is fine for our uses (a mount looking straight up or down), so the warning is silenced."""
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message="Gimbal lock detected")
        return Rotation.from_matrix(R_world_body).as_euler("ZYX")[::-1].copy()


def yaw_of(R_world_body: np.ndarray) -> float:
    """The Z-Y-X yaw of `roll_pitch_yaw` (rad) without scipy's object per call (the loop stage's gates ask it for
    every candidate); pitch below 90 deg."""
    return float(np.arctan2(R_world_body[1, 0], R_world_body[0, 0]))


def closest_yaw(M: np.ndarray) -> float:
    """Angle (rad) of the rotation about z closest to the 3x3 matrix M (maximises trace(Rz^T M))."""
    return float(np.arctan2(M[1, 0] - M[0, 1], M[0, 0] + M[1, 1]))


def yaw_between(R_world_a: np.ndarray, R_world_b: np.ndarray) -> float:
    """The turn about world z (rad) that best takes orientation b onto a: Rz(yaw) @ R_world_b ~ R_world_a.

    Why not the difference of the two Euler yaws: those mean "heading" only for a body whose z axis is near
    vertical. EuRoC's IMU has its x axis up (Z-Y-X pitch -70 deg), where a 0.5 deg tilt difference moves
    the Euler yaw by ~1.4 deg, and a body axis exactly vertical leaves it undefined; here the two
    orientations are compared in the world frame, whatever the body's axes."""
    return closest_yaw(np.asarray(R_world_a, float) @ np.asarray(R_world_b, float).T)


def yaw_position_alignment(T_a0: np.ndarray, T_b0: np.ndarray) -> np.ndarray:
    """T_b_a from one pose pair: the turn about z and the shift that map pose T_a0 (in world a) onto T_b0 (in
    world b), roll/pitch left as they are. Aligns an estimate on its first pose, as an autopilot's frame is."""
    R = so3_exp(np.array([0.0, 0.0, yaw_between(T_b0[:3, :3], T_a0[:3, :3])]))
    return make_T(R, T_b0[:3, 3] - R @ T_a0[:3, 3])


def gravity_aligned_rotation(accel_body: np.ndarray, headings: Sequence[np.ndarray] = ()) -> np.ndarray:
    """R_world_body that makes the measured specific force point along world +z, with world +x along the
    horizontal heading of the first of body x and then `headings` (body-frame axes) that lies at least 45 deg
    off the vertical.

    A still accelerometer reads R_world_body^T @ [0, 0, g]; yaw is unobservable, so it is a convention: body x
    by default. An IMU whose x axis points up (an OAK's, EuRoC's sensor) has no heading of x, and the start yaw
    came out of the rotation's gimbal lock, 115 deg on one flight; the camera's view (its optical axis, or the
    image top for a camera looking down) is the heading an integrator expects there.
    """
    a = np.asarray(accel_body, dtype=float)
    n = np.linalg.norm(a)
    if n < 1e-6:
        raise ValueError("accelerometer reads zero: cannot find gravity")
    z_body = a / n
    R, _ = Rotation.align_vectors([[0.0, 0.0, 1.0]], [z_body])
    R_wb = R.as_matrix()
    axes = [np.array([1.0, 0.0, 0.0]), *(np.asarray(h, dtype=float) for h in headings)]
    flat = [R_wb @ (h / np.linalg.norm(h)) for h in axes]
    level = [k for k, v in enumerate(flat) if np.hypot(v[0], v[1]) >= np.sqrt(0.5)]
    k = level[0] if level else int(np.argmax([np.hypot(v[0], v[1]) for v in flat]))
    # body x: its heading is the rotation's yaw (kept as the Euler angle: the same numbers as before)
    yaw = roll_pitch_yaw(R_wb)[2] if k == 0 else float(np.arctan2(flat[k][1], flat[k][0]))
    return so3_exp(np.array([0.0, 0.0, -yaw])) @ R_wb
