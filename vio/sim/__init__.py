"""Synthetic stereo + IMU flights with exactly known truth (`vio simulate`).

Modules: `motion` (analytic trajectories), `scene` (textured room, ray casting), `render` (lens-distorted
stereo images, blur, exposure, noise), `imu` (IMU samples from the trajectory), `observe` (perfect feature
observations), `generate` (SimConfig, variants, `simulate()` writing a EuRoC dataset), `cli`.
See docs/simulator.md.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from vio import VioError
from vio.calibration import CameraCalibration, ImuNoise, StereoCalibration
from vio.geometry import make_T

# EuRoC's body frame has x up, y right, z forward; ours is FLU (x forward, y left, z up).
_R_FLU_EUROC = np.array([[0.0, 0.0, 1.0], [0.0, -1.0, 0.0], [1.0, 0.0, 0.0]])

# How the IMU (the estimator's body frame) sits in the vehicle's FLU frame (columns: the IMU's axes in FLU).
# "flu": square with the vehicle; "oak": a Luxonis OAK looking forward, whose IMU has x up, y left and z
# backwards (tests/data/depthai_calib.json: camera forward = IMU -z, camera down = IMU -x). An axis straight
# up is what Euler-angle headings get wrong, so flights with it exercise that path end to end.
IMU_MOUNTS = {"flu": np.eye(3), "oak": np.array([[0.0, 0.0, -1.0], [0.0, 1.0, 0.0], [1.0, 0.0, 0.0]])}

# EuRoC V1 cam0/cam1 (MT9M034 on the VI-sensor): intrinsics, radtan distortion and T_BS (body <- cam),
# numbers from the dataset's sensor.yaml files. Keeping EuRoC's small misalignments makes the simulated
# cameras as unrectified as real ones.
_EUROC_CAMS = (
    dict(K=(458.654, 457.296, 367.215, 248.375), dist=(-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05),
         T=((0.0148655429818, -0.999880929698, 0.00414029679422, -0.0216401454975),
            (0.999557249008, 0.0149672133247, 0.025715529948, -0.064676986768),
            (-0.0257744366974, 0.00375618835797, 0.999660727178, 0.00981073058949))),
    dict(K=(457.587, 456.134, 379.999, 255.238), dist=(-0.28368365, 0.07451284, -0.00010473, -3.55590700e-05),
         T=((0.0125552670891, -0.999755099723, 0.0182237714554, -0.0198435579556),
            (0.999598781151, 0.0130119051815, 0.0251588363115, 0.0453689425024),
            (-0.0253898008918, 0.0179005838253, 0.999517347078, 0.00786212447038))),
)
# A mild wide-angle lens for the equidistant (Kannala-Brandt k1..k4) option.
_EQUIDISTANT_DIST = ((0.012, -0.006, 0.003, -0.0008), (0.010, -0.005, 0.0025, -0.0007))


def default_calibration(model: str = "radtan", width: int = 752, height: int = 480, rate_hz: float = 20.0,
                        imu: ImuNoise | None = None, time_offset_ns: int = 0) -> StereoCalibration:
    """EuRoC-like stereo head looking forward along body x: 752x480, fx ~ 458, 0.11 m baseline.

    `width`/`height` other than 752x480 scale the intrinsics (small images make fast tests); `model` is
    'radtan' (EuRoC's coefficients) or 'equidistant' (a mild fisheye with the same K)."""
    if model not in ("radtan", "equidistant"):
        raise VioError(f"unknown camera model {model!r}; expected 'radtan' or 'equidistant'")
    sx, sy = width / 752.0, height / 480.0
    cams = []
    for i, c in enumerate(_EUROC_CAMS):
        fx, fy, cx, cy = c["K"]
        T_euroc = make_T(np.array(c["T"])[:, :3], np.array(c["T"])[:, 3])
        T_body_cam = make_T(_R_FLU_EUROC, np.zeros(3)) @ T_euroc
        dist = c["dist"] if model == "radtan" else _EQUIDISTANT_DIST[i]
        cams.append(CameraCalibration(fx=fx * sx, fy=fy * sy, cx=(cx + 0.5) * sx - 0.5, cy=(cy + 0.5) * sy - 0.5,
                                      width=int(width), height=int(height), distortion_model=model,
                                      distortion=dist, T_body_cam=T_body_cam, rate_hz=float(rate_hz)))
    return StereoCalibration(cams[0], cams[1], imu or ImuNoise(), time_offset_ns=int(time_offset_ns))


# A typical Kalibr error (issue 17): 0.05-0.1 deg and 1-2.5 mm in the camera-IMU extrinsics, up to 0.5 px
# in the intrinsics. `perturbed_calibration` applies these magnitudes times a scale.
CALIB_ERROR_ROT_DEG = 0.1
CALIB_ERROR_TRANS_M = 0.002
CALIB_ERROR_PX = 0.5


def perturbed_calibration(calib: StereoCalibration, scale: float, rng: np.random.Generator) -> StereoCalibration:
    """The calibration a slightly wrong calibration file states: the stereo rig's pose on the body turned
    by exactly scale * 0.1 deg about a random axis and moved by scale * 2 mm in a random direction, and
    fx, fy, cx, cy off by scale * 0.5 px (random signs).

    The error is the rig's (the same for both cameras, T_cam1_cam0 kept), as a Kalibr calibration's is: its
    stereo extrinsic and intrinsics come from one joint fit on the same images, so their errors agree.
    Independent errors of this size would be a broken stereo calibration instead: 0.14 deg between the
    cameras is ~1 px of disparity, 11 % of the depth at 5 m (a 40 s survey flight: ATE 0.23 m, not 0.005).
    Exact magnitudes make flights of different seeds equally wrong, the random directions differently."""
    from vio.geometry import so3_exp

    def unit(v: np.ndarray) -> np.ndarray:
        return v / np.linalg.norm(v)

    dR = so3_exp(unit(rng.standard_normal(3)) * np.deg2rad(CALIB_ERROR_ROT_DEG * scale))
    D = make_T(dR, unit(rng.standard_normal(3)) * CALIB_ERROR_TRANS_M * scale)  # body <- wrongly placed body
    dk = rng.choice([-1.0, 1.0], 4) * CALIB_ERROR_PX * scale
    cams = [replace(cam, fx=cam.fx + dk[0], fy=cam.fy + dk[1], cx=cam.cx + dk[2], cy=cam.cy + dk[3],
                    T_body_cam=D @ cam.T_body_cam) for cam in (calib.cam0, calib.cam1)]
    return replace(calib, cam0=cams[0], cam1=cams[1])


__all__ = ["IMU_MOUNTS", "default_calibration", "perturbed_calibration"]
