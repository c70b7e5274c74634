"""Human-readable summary of a StereoCalibration (`vio calib show`): the numbers a person checks by eye
to catch a wrong file: baseline, focal lengths, how the cameras sit on the body, time offset, IMU noise."""

from __future__ import annotations

import numpy as np

from vio.calibration import CameraCalibration, StereoCalibration, calibration_units_problem
from vio.geometry import rotation_angle_deg

_AXES = ("x", "y", "z")


def _axis_name(v: np.ndarray) -> tuple[str, float]:
    """Nearest signed body axis of unit vector v and the angle to it in degrees."""
    k = int(np.argmax(np.abs(v)))
    sign = "+" if v[k] > 0 else "-"
    ang = float(np.degrees(np.arccos(np.clip(abs(v[k]), -1.0, 1.0))))
    return f"{sign}{_AXES[k]}", ang


def camera_axes(cam: CameraCalibration) -> dict[str, tuple[str, float]]:
    """Where the optical axes (x right, y down, z forward) point in the body frame."""
    R = cam.T_body_cam[:3, :3]
    return {name: _axis_name(R[:, i]) for i, name in enumerate(("right(x)", "down(y)", "forward(z)"))}


def _camera_lines(name: str, cam: CameraCalibration) -> list[str]:
    fov_h = np.degrees(2 * np.arctan2(cam.width / 2, cam.fx))
    fov_v = np.degrees(2 * np.arctan2(cam.height / 2, cam.fy))
    t = cam.T_body_cam[:3, 3]
    axes = ", ".join(f"{k} -> body {v[0]} ({v[1]:.2f} deg off)" for k, v in camera_axes(cam).items())
    dist = ", ".join(f"{d:.6g}" for d in cam.distortion)
    return [
        f"{name}: {cam.width}x{cam.height} @ {cam.rate_hz:g} Hz",
        f"  focal length   fx={cam.fx:.3f} fy={cam.fy:.3f} px  (fx/fy={cam.fx / cam.fy:.4f}; "
        f"pinhole FOV {fov_h:.1f} x {fov_v:.1f} deg)",
        f"  principal pt   cx={cam.cx:.3f} cy={cam.cy:.3f} px  (offset from centre "
        f"{cam.cx - cam.width / 2:+.1f}, {cam.cy - cam.height / 2:+.1f} px)",
        f"  distortion     {cam.distortion_model} [{dist}]",
        f"  position in body  [{t[0]:+.4f}, {t[1]:+.4f}, {t[2]:+.4f}] m",
        f"  axes           {axes}",
        f"  rotation vs body  {rotation_angle_deg(cam.T_body_cam[:3, :3]):.3f} deg",
    ]


def format_calibration(calib: StereoCalibration, title: str = "") -> str:
    T = calib.T_cam1_cam0
    t = T[:3, 3]
    imu = calib.imu
    s = imu.discrete_sigmas()
    lines = [title] if title else []
    lines += _camera_lines("cam0", calib.cam0) + _camera_lines("cam1", calib.cam1)
    lines += [
        "stereo (T_cam1_cam0)",
        f"  baseline       {calib.baseline_m * 1000:.2f} mm  (t = [{t[0]:+.5f}, {t[1]:+.5f}, {t[2]:+.5f}] m)",
        f"  rotation angle {rotation_angle_deg(T[:3, :3]):.3f} deg between cam0 and cam1",
        f"  focal ratio    cam1/cam0 fx {calib.cam1.fx / calib.cam0.fx:.4f}",
        f"time offset      {calib.time_offset_ns / 1e6:+.3f} ms  (t_imu = t_cam + offset)",
        f"IMU noise        @ {imu.rate_hz:g} Hz",
        f"  gyro   noise density {imu.gyroscope_noise_density:.4g} rad/s/sqrt(Hz)  "
        f"random walk {imu.gyroscope_random_walk:.4g} rad/s^2/sqrt(Hz)",
        f"  accel  noise density {imu.accelerometer_noise_density:.4g} m/s^2/sqrt(Hz)  "
        f"random walk {imu.accelerometer_random_walk:.4g} m/s^3/sqrt(Hz)",
        f"  per sample     gyro {s['gyro']:.4g} rad/s, accel {s['accel']:.4g} m/s^2",
    ]
    problem = calibration_units_problem(calib)
    if problem:  # the numbers above would read as plausible millimetres: say what vio run / replay will refuse
        lines.append(f"UNITS PROBLEM    {problem} (vio run and vio replay refuse this file)")
    return "\n".join(lines)
