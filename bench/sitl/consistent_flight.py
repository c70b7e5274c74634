"""A recorded SITL flight taken apart: its images and IMU replaced, one at a time, by ones consistent with its truth.

Why: the stereo check let go of the SITL's exact calibration (docs/estimator.md, "Why the check reads a bias on
the SITL flights"), and a recording mixes everything the SITL does (its IMU, its frame stamps taken on arrival,
its 1e-7 deg SIM_STATE positions, its motion). This writes a EuRoC folder along the harness's SIM_STATE truth
(raw.npz of `python -m bench.sitl.run ... --record`) in which each part is either the recording's or made
consistent with that truth, so a replay (`vio -v replay OUT`, "stereo check t=" lines) shows which part the
reading follows:

- motion: a smoothing spline through the truth positions (`--lam`; None = generalised cross-validation, which
  keeps ~0.3 m/s^2 of wiggle from the 1 cm position steps; 0.1 is as smooth as the SITL's own accelerometer)
  and a rotation spline through its attitudes;
- images: rendered by the SITL camera's own renderer (drivers/sitl_camera.py, same room, same rig) at the spline
  (default), at the raw truth interpolated at each stamp (`--render-truth`: as the SITL camera saw it), or at
  the spline's positions rounded to SIM_STATE's 1e-7 deg grid (`--quantise`); any size (`--size`);
- frame stamps: the recording's (taken on arrival, ~10 ms jitter) or an exact grid (`--grid-hz`);
- IMU: differentiated from the splines (noise-free, bias-free; `--imu-lag-ms` makes it lag the images as the
  SITL's does, ~15 ms), the recording's (`--imu recorded`), or the recording's accelerometer with the spline's
  gyro (`--imu recorded-accel`).

Nothing here talks to a SITL. Writes OUT/mav0 (cam0, cam1, imu0) and OUT/truth.tum (body poses at the frames).
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import numpy as np
from scipy.interpolate import make_smoothing_spline
from scipy.spatial.transform import Rotation, RotationSpline, Slerp

from drivers.sitl_camera import EARTH_RADIUS_M, R_WORLD_NED, SitlCameraSource, frd_calibration, world_from_ned
from vio import VioError
from vio.geometry import make_T
from vio.io.euroc import EurocWriter
from vio.sim.motion import GRAVITY_M_S2
from vio.types import ImuSample


class TruthSplines:
    """Position and attitude splines through the harness's SIM_STATE truth (world z up, FRD body)."""

    def __init__(self, raw_npz: Path, lam: float | None) -> None:
        tr = np.load(raw_npz)["truth"]  # t_ns, n, e, d, yaw, q1..q4 (FRD -> NED, w first)
        self.t0_ns = int(tr[0, 0])
        t = (tr[:, 0] - self.t0_ns) * 1e-9
        keep = np.r_[True, np.diff(t) > 1e-4]  # two messages read in one go share a stamp
        self.t, tr = t[keep], tr[keep]
        self.p = world_from_ned(tr[:, 1:4])
        q = tr[:, 5:9]
        self.R = Rotation.from_matrix(R_WORLD_NED @ Rotation.from_quat(np.c_[q[:, 1:4], q[:, 0]]).as_matrix())
        self._pos = [make_smoothing_spline(self.t, self.p[:, i], lam=lam) for i in range(3)]
        self._rot = RotationSpline(self.t, self.R)

    def seconds(self, t_ns: np.ndarray) -> np.ndarray:
        return (np.asarray(t_ns, dtype=np.int64) - self.t0_ns) * 1e-9

    def pose(self, t_s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return self._rot(t_s).as_matrix(), np.stack([s(t_s) for s in self._pos], -1)

    def raw_pose(self, t_s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The truth as the SITL camera used it: positions interpolated linearly, attitudes by slerp."""
        return Slerp(self.t, self.R)(t_s).as_matrix(), np.stack([np.interp(t_s, self.t, self.p[:, i])
                                                                  for i in range(3)], -1)

    def imu(self, t_s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(gyro, accel) a perfect IMU on the FRD body reads at t_s."""
        R = self._rot(t_s).as_matrix()
        acc = np.stack([s(t_s, 2) for s in self._pos], -1) + np.array([0.0, 0.0, GRAVITY_M_S2])
        h = 1e-4
        Ra, Rb = self._rot(t_s - h).as_matrix(), self._rot(t_s + h).as_matrix()
        gyro = Rotation.from_matrix(np.einsum("nji,njk->nik", Ra, Rb)).as_rotvec() / (2 * h)
        return gyro, np.einsum("nji,nj->ni", R, acc)


def quantised(p_world: np.ndarray, home_lat_deg: float) -> np.ndarray:
    """World positions rounded to SIM_STATE's 1e-7 deg latitude/longitude grid (1.1 cm north, 0.9 cm east here)."""
    step_n = math.radians(1e-7) * EARTH_RADIUS_M
    step_e = step_n * math.cos(math.radians(home_lat_deg))
    out = np.array(p_world, dtype=float)
    out[:, 0] = np.round(out[:, 0] / step_n) * step_n  # world x = north
    out[:, 1] = -np.round(-out[:, 1] / step_e) * step_e  # world y = -east
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("recording", type=Path, help="the SITL recording (EuRoC folder with mav0/)")
    ap.add_argument("raw", type=Path, help="the harness's raw.npz (SIM_STATE truth on the host clock)")
    ap.add_argument("out", type=Path)
    ap.add_argument("--lam", type=float, default=None, help="smoothing of the position spline (default: GCV)")
    ap.add_argument("--imu", choices=("synthetic", "recorded", "recorded-accel"), default="synthetic")
    ap.add_argument("--imu-lag-ms", type=float, default=0.0, help="the synthetic IMU reads the motion this late")
    ap.add_argument("--render-truth", action="store_true", help="images at the raw truth, not the spline")
    ap.add_argument("--quantise", action="store_true", help="images at the spline rounded to 1e-7 deg")
    ap.add_argument("--grid-hz", type=float, default=0.0, help="frames on an exact grid at this rate")
    ap.add_argument("--size", default="320x200")
    ap.add_argument("--max-frames", type=int, default=0, help="the first N frames only (0: all)")
    ap.add_argument("--home-lat", type=float, default=-35.363261)
    a = ap.parse_args(argv)
    src = a.recording / "mav0"
    if not (src / "cam0" / "data.csv").is_file() or not (src / "imu0" / "data.csv").is_file():
        print(f"consistent_flight: {a.recording} has no mav0/cam0/data.csv and mav0/imu0/data.csv", file=sys.stderr)
        return 2
    if not a.raw.is_file():
        print(f"consistent_flight: {a.raw} does not exist (the harness's raw.npz of the same flight)", file=sys.stderr)
        return 2
    try:
        w, h = (int(x) for x in a.size.lower().split("x"))
    except ValueError:
        print(f"consistent_flight: --size {a.size!r} is not WIDTHxHEIGHT", file=sys.stderr)
        return 2
    truth = TruthSplines(a.raw, a.lam)
    stamps = np.loadtxt(src / "cam0" / "data.csv", delimiter=",", usecols=0, dtype=np.int64, ndmin=1)
    if a.max_frames:
        stamps = stamps[: a.max_frames]
    if a.grid_hz > 0:
        stamps = stamps[0] + np.round(np.arange(len(stamps)) * 1e9 / a.grid_hz).astype(np.int64)
    inside = (truth.seconds(stamps) > truth.t[0] + 0.1) & (truth.seconds(stamps) < truth.t[-1] - 0.1)
    stamps = stamps[inside]
    imu = np.loadtxt(src / "imu0" / "data.csv", delimiter=",", ndmin=2)
    imu_ns = imu[:, 0].astype(np.int64)
    sel = (imu_ns >= stamps[0] - 100_000_000) & (imu_ns <= stamps[-1] + 100_000_000)
    imu, imu_ns = imu[sel], imu_ns[sel]
    if a.imu != "recorded":
        gyro, accel = truth.imu(truth.seconds(imu_ns) - a.imu_lag_ms * 1e-3)
        imu[:, 1:4] = gyro
        if a.imu == "synthetic":
            imu[:, 4:7] = accel

    t_s = truth.seconds(stamps)
    R_wb, p_wb = truth.raw_pose(t_s) if a.render_truth else truth.pose(t_s)
    if a.quantise:
        p_wb = quantised(p_wb, a.home_lat)
    camera = SitlCameraSource("offline", (a.home_lat, 0.0, 0.0), width=w, height=h, fps=15.0)
    try:  # the SITL camera's own calibration at this size (its IMU noise is what the recording states)
        writer = EurocWriter(a.out, frd_calibration(w, h, 15.0))
    except VioError as e:
        print(f"consistent_flight: {e}", file=sys.stderr)
        return 2
    for r in imu:
        writer.write_imu(ImuSample(int(r[0]), r[1:4], r[4:7]))
    for s, R, p in zip(stamps, R_wb, p_wb):
        writer.write_frame(camera.render(make_T(R, p), int(s)))
    writer.close()
    q = Rotation.from_matrix(R_wb).as_quat()
    np.savetxt(a.out / "truth.tum", np.c_[stamps * 1e-9, p_wb, q], fmt="%.9f")
    print(f"{a.out}: {len(stamps)} frames at {w}x{h}, {len(imu)} IMU samples ({a.imu}); images at the "
          f"{'raw truth' if a.render_truth else 'spline'}{' on the 1e-7 deg grid' if a.quantise else ''}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
