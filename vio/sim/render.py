"""Lens-distorted grayscale images and depth maps of a Scene, plus camera effects.

Every pixel's viewing ray is computed once per camera by undistorting the pixel grid with the calibration,
so rendered images carry exactly the calibrated lens distortion, and a scene point projected with
`CameraCalibration.project` lands where it was drawn. Per frame, the rays are rotated into the world
(float32, three multiply-adds per component), cast against the scene's boxes (crates are culled by their
image footprint) and shaded by one `cv2.remap` per texture level.

Camera effects, applied by `Photometric`: motion blur (averaging the image shifted along the per-pixel
optical flow of the camera motion during the exposure), gain/exposure drift and jumps, sensor noise.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from vio.calibration import CameraCalibration
from vio.geometry import inv_T
from vio.sim.scene import MIP_FACTOR, Scene

_NEAR_M = 0.05  # crate corners closer than this to the image plane disable footprint culling


class CameraRenderer:
    """Renders one calibrated camera. Construction does the expensive per-pixel undistortion once."""

    def __init__(self, cam: CameraCalibration, scene: Scene):
        self.cam = cam
        self.scene = scene
        h, w = cam.height, cam.width
        u, v = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
        xy = cam.undistort_normalized(np.stack([u.ravel(), v.ravel()], axis=1)).reshape(h, w, 2)
        self.x = np.ascontiguousarray(xy[..., 0], dtype=np.float32)  # ray direction (x, y, 1) in the camera
        self.y = np.ascontiguousarray(xy[..., 1], dtype=np.float32)
        self.norm = np.sqrt(1.0 + self.x**2 + self.y**2)  # |ray|
        # conservative culling: column u can show normalised x only within [min, max] over its rows
        self._col_lo, self._col_hi = self.x.min(axis=0), self.x.max(axis=0)
        self._row_lo, self._row_hi = self.y.min(axis=1), self.y.max(axis=1)
        self.grid_u, self.grid_v = u.astype(np.float32), v.astype(np.float32)
        self._texels_per_px = np.float32(scene.ppm / np.sqrt(cam.fx * cam.fy))

    def _windows(self, T_cam_world: np.ndarray) -> list:
        """Per crate, the pixel rectangle that can show it (None: behind the camera)."""
        out = []
        for b in range(1, len(self.scene.boxes)):
            lo, hi = self.scene.lo[b], self.scene.hi[b]
            corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
            pc = corners @ T_cam_world[:3, :3].T + T_cam_world[:3, 3]
            if np.all(pc[:, 2] <= _NEAR_M):
                out.append(None)
                continue
            if np.any(pc[:, 2] <= _NEAR_M):
                out.append((slice(None), slice(None)))
                continue
            xn, yn = pc[:, 0] / pc[:, 2], pc[:, 1] / pc[:, 2]
            c0 = int(np.searchsorted(self._col_hi, xn.min()))  # first column whose max reaches xn.min
            c1 = int(np.searchsorted(self._col_lo, xn.max(), side="right"))
            r0 = int(np.searchsorted(self._row_hi, yn.min()))
            r1 = int(np.searchsorted(self._row_lo, yn.max(), side="right"))
            out.append(None if c0 >= c1 or r0 >= r1 else (slice(r0, r1), slice(c0, c1)))
        return out

    def render(self, T_world_cam: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(image float32 0..255, depth along the optical axis [m], face index) seen from T_world_cam."""
        R = T_world_cam[:3, :3].astype(np.float32)
        o = T_world_cam[:3, 3]
        d = tuple(R[k, 0] * self.x + R[k, 1] * self.y + R[k, 2] for k in range(3))
        depth, face = self.scene.cast(o, d, self._windows(inv_T(T_world_cam)))
        mx, my = self.scene.texture_coords(o, d, depth, face)
        sharp = cv2.remap(self.scene.atlas, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        # texels per pixel, widened on oblique surfaces: blend in the smaller atlas level against aliasing.
        # It varies slowly, so it is evaluated on every 4th pixel and interpolated.
        sub = (slice(None, None, 4), slice(None, None, 4))
        axis = self.scene.face_axis[face[sub]]
        dn = np.abs(np.where(axis == 0, d[0][sub], np.where(axis == 1, d[1][sub], d[2][sub])))
        norm = self.norm[sub]
        footprint = depth[sub] * self._texels_per_px * norm * np.sqrt(norm / np.maximum(dn, 1e-3))
        w = np.clip((footprint - 1.0) * (1.0 / (MIP_FACTOR - 1)), 0.0, 1.0).astype(np.float32)
        if w.max() > 0:
            w = cv2.resize(w, (self.cam.width, self.cam.height), interpolation=cv2.INTER_LINEAR)
            k = np.float32(1.0 / MIP_FACTOR)
            off = np.float32(0.5 / MIP_FACTOR - 0.5)
            small = cv2.remap(self.scene.atlas_small, mx * k + off, my * k + off, cv2.INTER_LINEAR,
                              borderMode=cv2.BORDER_REPLICATE)
            sharp += w * (small - sharp)
        return sharp, depth, face

    def pixel_flow(self, depth: np.ndarray, v_cam: np.ndarray, w_cam: np.ndarray, step: int = 8) -> np.ndarray:
        """Image motion (du/dt, dv/dt) in px/s of every pixel for camera velocity v_cam [m/s] and angular
        rate w_cam [rad/s] (both in the camera frame). Classic interaction matrix of a point at the pixel's
        depth, evaluated every `step` pixels and resized (blur needs no more); lens distortion ignored."""
        x, y, z = self.x[::step, ::step], self.y[::step, ::step], np.maximum(depth[::step, ::step], 0.05)
        vx, vy, vz = v_cam
        wx, wy, wz = w_cam
        dx = (-vx + x * vz) / z + x * y * wx - (1 + x * x) * wy + y * wz
        dy = (-vy + y * vz) / z + (1 + y * y) * wx - x * y * wy - x * wz
        size = (self.cam.width, self.cam.height)
        fu = cv2.resize((dx * self.cam.fx).astype(np.float32), size, interpolation=cv2.INTER_LINEAR)
        fv = cv2.resize((dy * self.cam.fy).astype(np.float32), size, interpolation=cv2.INTER_LINEAR)
        return np.stack([fu, fv])

    def motion_blur(self, img: np.ndarray, flow: np.ndarray, exposure_s: float) -> np.ndarray:
        """Average of the image sampled along the flow over the exposure (centred on the frame time)."""
        length = float(np.abs(flow).max()) * exposure_s
        if length < 0.7:
            return img
        n = int(min(9, max(3, np.ceil(length))))
        acc = np.zeros_like(img)
        for s in np.linspace(-0.5, 0.5, n):
            k = np.float32(s * exposure_s)
            acc += cv2.remap(img, self.grid_u + k * flow[0], self.grid_v + k * flow[1], cv2.INTER_LINEAR,
                             borderMode=cv2.BORDER_REPLICATE)
        return acc * np.float32(1.0 / n)


@dataclass
class Photometric:
    """Gain (exposure) schedule and sensor noise of one camera; deterministic from its rng.

    log-gain(t) = offset + drift * sin(2 pi t / period + phase) + the level of the last jump; jumps (auto-
    exposure corrections) come as a Poisson process of `jump_rate_hz` and draw a new level in +-jump_size.
    """

    rng: np.random.Generator
    duration_s: float
    drift: float = 0.0
    jump_rate_hz: float = 0.0
    jump_size: float = 0.35
    noise_sigma: float = 0.0
    offset: float = 0.0

    def __post_init__(self) -> None:
        self._noise_bank: np.ndarray | None = None
        self._phase = self.rng.uniform(0, 2 * np.pi)
        self._period = self.rng.uniform(8.0, 20.0)
        n = self.rng.poisson(self.jump_rate_hz * self.duration_s) if self.jump_rate_hz > 0 else 0
        self._jump_t = np.sort(self.rng.uniform(0, self.duration_s, n))
        self._jump_level = np.concatenate([[0.0], self.rng.uniform(-self.jump_size, self.jump_size, n)])

    def gain(self, t_s: float) -> float:
        level = self._jump_level[np.searchsorted(self._jump_t, t_s, side="right")]
        return float(np.exp(self.offset + self.drift * np.sin(2 * np.pi * t_s / self._period + self._phase) + level))

    def apply(self, img: np.ndarray, t_s: float) -> np.ndarray:
        """8-bit image: gain, additive Gaussian noise, rounding and saturation."""
        out = img * np.float32(self.gain(t_s))
        if self.noise_sigma > 0:
            # a random window of a twice-as-large noise field: drawing fresh normals per frame costs more
            # than the rendering of the frame; windows at random offsets are uncorrelated in practice
            h, w = out.shape
            if self._noise_bank is None or self._noise_bank.shape != (2 * h, 2 * w):
                self._noise_bank = self.rng.standard_normal((2 * h, 2 * w), dtype=np.float32) * \
                    np.float32(self.noise_sigma)
            y0, x0 = int(self.rng.integers(h)), int(self.rng.integers(w))
            out += self._noise_bank[y0:y0 + h, x0:x0 + w]
        return np.clip(out + 0.5, 0, 255).astype(np.uint8)
