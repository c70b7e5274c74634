"""Affine refinement of each track against its first appearance (its anchor patch).

Frame-to-frame KLT fits a pure translation. When the view changes, a patch is also scaled, rotated and
sheared, and the best translation of a deformed patch is biased toward where its texture is strongest: on
the aggressive synthetic flight the bias grew to ~0.5 px after 15 frames and ~1 px after 40, and 12.6 % of
all observations ended > 2 px from the true projection (see docs/frontend.md). The same bias shows with KLT
from the birth image directly, so it is a property of the translational model, not of chaining.

Here each track keeps the patch around its birth position and, after KLT, the position is refined by
inverse-compositional Lucas-Kanade with an affine warp (6 parameters) against that patch, started at the
KLT position and the track's last warp. Both patches are normalised to zero mean and unit variance (gain
and exposure changes). The zero-mean NCC after convergence doubles as an appearance check: a track that
slid along an occlusion boundary or onto another surface no longer fits any affine warp of its first patch
and is dropped. When the warp has strayed far from identity (scale, shear) the anchor is renewed at the
current, refined position: the small error of that one step is all that carries over.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np


@dataclass
class Anchors:
    """Per-track anchor data, row-aligned with the tracker's arrays."""

    tpl: np.ndarray  # (N, P*P) normalised template intensities
    J: np.ndarray  # (N, 6, P*P) Gauss-Newton step per residual: H^-1 SD^T (constant in the inverse form)
    A: np.ndarray  # (N, 2, 2) current warp's linear part (template -> current image)
    std: np.ndarray  # (N,) grey-level standard deviation of the template (contrast)

    @classmethod
    def empty(cls, p2: int) -> Anchors:
        return cls(np.zeros((0, p2), np.float32), np.zeros((0, 6, p2), np.float32), np.zeros((0, 2, 2), np.float32),
                   np.zeros(0, np.float32))

    def __len__(self) -> int:
        return len(self.tpl)

    def assemble(self, rows: np.ndarray, renew: np.ndarray | None = None, renewed: Anchors | None = None,
                 new: Anchors | None = None) -> Anchors:
        """take(rows), then replace(renew, renewed) on the result, then concat(new), in one copy of each array.

        A tracker frame did all three (plus a second take for the drift check), each a full copy of the
        Jacobians (~1 MB at 200 tracks): 0.1 ms apiece on one core."""
        k, m = len(rows), 0 if new is None else len(new)

        def one(a: np.ndarray, a_renewed: np.ndarray | None, a_new: np.ndarray | None) -> np.ndarray:
            out = np.empty((k + m, *a.shape[1:]), a.dtype)
            # mode="clip" lets np.take write into `out` directly ("raise" buffers); rows are in range by construction
            np.take(a, rows, axis=0, out=out[:k], mode="clip")
            if a_renewed is not None:
                out[:k][renew] = a_renewed
            if m:
                out[k:] = a_new
            return out

        def part(x: Anchors | None, name: str) -> np.ndarray | None:
            return None if x is None else getattr(x, name)

        return Anchors(*(one(getattr(self, f), part(renewed, f), part(new, f)) for f in ("tpl", "J", "A", "std")))


def _normalise(v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rows to zero mean and unit RMS; returns them and 1/std (0 for flat rows)."""
    v = v - v.mean(axis=-1, keepdims=True)
    s = np.sqrt(np.einsum("nk,nk->n", v, v) / v.shape[-1])[:, None]
    inv = np.where(s > 1e-3, 1.0 / np.maximum(s, 1e-3), 0.0).astype(np.float32)
    return v * inv, inv


def _inv2(M: np.ndarray) -> np.ndarray:
    """Inverses of a stack of 2x2 matrices (closed form; much cheaper than np.linalg.inv for small stacks)."""
    a, b, c, d = M[:, 0, 0], M[:, 0, 1], M[:, 1, 0], M[:, 1, 1]
    det = a * d - b * c
    det = np.where(np.abs(det) < 1e-9, 1e-9, det)
    # filled in place: the nested np.stack calls were half of this function's time
    out = np.empty((len(M), 2, 2), np.result_type(M, det))
    out[:, 0, 0], out[:, 0, 1], out[:, 1, 0], out[:, 1, 1] = d, -b, -c, a
    out /= det[:, None, None]
    return out


class AnchorRefiner:
    """Builds anchor patches and refines tracked positions against them (all tracks at once, vectorised)."""

    def __init__(self, patch_px: int = 15, iterations: int = 2, min_ncc: float = 0.85, renew_deform: float = 0.4
                 ) -> None:
        half = patch_px // 2
        self.iterations = iterations
        self.min_ncc = min_ncc
        self.renew_deform = renew_deform
        r = np.arange(-half, half + 1, dtype=np.float32)
        gy, gx = np.meshgrid(r, r, indexing="ij")
        self.off = np.column_stack([gx.ravel(), gy.ravel()])  # (P*P, 2) template coordinates (x, y)
        self.off_h = np.vstack([self.off.T, np.ones(len(self.off), np.float32)])  # (3, P*P) homogeneous
        r1 = np.arange(-half - 1, half + 2, dtype=np.float32)
        gy1, gx1 = np.meshgrid(r1, r1, indexing="ij")
        self.off_border = np.column_stack([gx1.ravel(), gy1.ravel()])  # with a 1 px border for gradients
        self.p = 2 * half + 1

    @staticmethod
    def _sample(img: np.ndarray, mx: np.ndarray, my: np.ndarray) -> np.ndarray:
        """Bilinear samples of `img` at (mx, my), both (N, K) -> (N, K) float32; outside the image replicates
        the border."""
        if mx.shape[0] == 0:
            return np.zeros(mx.shape, np.float32)
        return cv2.remap(img, np.ascontiguousarray(mx, dtype=np.float32), np.ascontiguousarray(my, dtype=np.float32),
                         cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE).astype(np.float32)

    def build(self, img: np.ndarray, pts: np.ndarray) -> Anchors:
        """Anchors for raw positions pts (N, 2) in img (identity warp)."""
        n, p = len(pts), self.p
        if n == 0:
            return Anchors.empty(p * p)
        c = pts.astype(np.float32)
        big = self._sample(img, c[:, 0, None] + self.off_border[None, :, 0], c[:, 1, None] + self.off_border[None, :, 1]
                           ).reshape(n, p + 2, p + 2)
        tpl, inv_std = _normalise(big[:, 1:-1, 1:-1].reshape(n, -1))
        gx = (0.5 * (big[:, 1:-1, 2:] - big[:, 1:-1, :-2])).reshape(n, -1) * inv_std
        gy = (0.5 * (big[:, 2:, 1:-1] - big[:, :-2, 1:-1])).reshape(n, -1) * inv_std
        x, y = self.off[:, 0][None], self.off[:, 1][None]
        sd = np.stack([gx * x, gx * y, gy * x, gy * y, gx, gy], axis=1).astype(np.float64)  # (N, 6, P*P)
        H = sd @ sd.transpose(0, 2, 1)
        # a little damping of the linear part keeps weakly textured patches from wild warps
        H += np.diag([1.0, 1.0, 1.0, 1.0, 0.0, 0.0]) * (1e-2 * p * p) + np.eye(6) * 1e-6
        J = (np.linalg.inv(H) @ sd).astype(np.float32)
        return Anchors(tpl.astype(np.float32), J, np.repeat(np.eye(2, dtype=np.float32)[None], n, axis=0),
                       np.where(inv_std[:, 0] > 0, 1.0 / np.maximum(inv_std[:, 0], 1e-9), 0.0).astype(np.float32))

    def _warped(self, img: np.ndarray, A: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Normalised image samples under the warps (A, t): (N, P*P), and 1/std of the raw samples (N, 1)."""
        n = len(t)
        xy = (np.concatenate([A, t[:, :, None]], axis=2).reshape(2 * n, 3) @ self.off_h).reshape(n, 2, -1)
        return _normalise(self._sample(img, xy[:, 0], xy[:, 1]))

    def refine(self, img: np.ndarray, pos: np.ndarray, anchors: Anchors
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Refined raw positions (N, 2), their NCC with the anchor (-1 where the warp diverged) and the contrast
        ratio (patch std now / at the anchor; a blurred or washed-out patch matches after normalisation but its
        position is unreliable); updates anchors.A in place.

        Inverse compositional: the warp W(x) = A x + t maps template coordinates into the image; each step
        solves for an increment of the template's own warp and composes its inverse, A <- A M, t <- t - A M d
        with M = (I + D)^-1, so the Jacobian stays the template's, computed once in build(). The NCC is that of
        the last warp sampled (before the last, small step): one image sampling fewer per frame."""
        n = len(pos)
        if n == 0:
            return pos.copy(), np.zeros(0), np.zeros(0)
        t = pos.astype(np.float32)
        A = anchors.A.astype(np.float32)
        eye = np.eye(2, dtype=np.float32)[None]
        ncc = np.zeros(n, np.float32)
        inv_std = np.zeros((n, 1), np.float32)
        with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
            for _ in range(self.iterations):
                w, inv_std = self._warped(img, A, t)
                r = w - anchors.tpl
                ncc = 1.0 - 0.5 * np.einsum("nk,nk->n", r, r) / r.shape[1]  # both sides have unit RMS
                dp = (anchors.J @ r[:, :, None])[:, :, 0]
                A = A @ _inv2(eye + dp[:, :4].reshape(n, 2, 2))
                t = t - (A @ dp[:, 4:, None])[:, :, 0]
            det = A[:, 0, 0] * A[:, 1, 1] - A[:, 0, 1] * A[:, 1, 0]
        bad = ~(np.isfinite(t).all(axis=1) & (det > 0.1) & (det < 10.0))
        ncc[bad] = -1.0
        A[bad] = np.eye(2)
        anchors.A[:] = A
        std_now = np.where(inv_std[:, 0] > 0, 1.0 / np.maximum(inv_std[:, 0], 1e-9), 0.0)
        contrast = std_now / np.maximum(anchors.std, 1e-3)
        return t.astype(np.float64), ncc.astype(np.float64), contrast

    def needs_renewal(self, warps: np.ndarray) -> np.ndarray:
        """Rows of `warps` (N, 2, 2: anchors' A) that deform the patch by more than `renew_deform` (largest
        |singular value - 1|). Takes the warps alone: the tracker asks before it copies the other anchor rows."""
        if len(warps) == 0:
            return np.zeros(0, bool)
        # singular values of the 2x2 warps in closed form (np.linalg.svd on the stack was 0.3 ms per frame):
        # Q +- R with Q, R the norms of the warp's rotation-like and reflection-like parts
        A = warps.astype(np.float64)
        a, b, c, d = A[:, 0, 0], A[:, 0, 1], A[:, 1, 0], A[:, 1, 1]
        q, r = np.hypot(0.5 * (a + d), 0.5 * (c - b)), np.hypot(0.5 * (a - d), 0.5 * (c + b))
        return np.maximum(np.abs(q + r - 1.0), np.abs(np.abs(q - r) - 1.0)) > self.renew_deform
