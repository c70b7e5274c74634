"""Cheap image statistics that tell a usable frame from a black, saturated or smeared one.

KLT on such a frame does not fail loudly: it returns plausible-looking but wrong flow. Checking the image
first (about 0.3 ms at 752x480) lets the tracker report a bad frame and re-detect on the next good one.
"""

from __future__ import annotations

import cv2
import numpy as np

from vio.config import FrontendConfig


def image_problem(img: np.ndarray, cfg: FrontendConfig, mean: float | None = None) -> str:
    """Why `img` (8-bit grey) is unusable, or "" when it looks fine. `mean`: the image's mean grey level when the
    caller has it already (the tracker's gain compensation needs it too: one pass over the image fewer)."""
    mean = float(cv2.mean(img)[0]) if mean is None else mean
    if mean < cfg.min_mean_intensity:
        return f"image too dark (mean grey {mean:.1f} < {cfg.min_mean_intensity:g})"
    saturated = float(np.count_nonzero(img >= 250)) / img.size
    if saturated > cfg.max_saturated_fraction:
        return f"image saturated ({100 * saturated:.0f}% of pixels >= 250)"
    energy = gradient_energy(img)
    if energy < cfg.min_gradient_energy:
        return f"image blurred or textureless (gradient energy {energy:.2f} < {cfg.min_gradient_energy:g})"
    return ""


def gradient_energy(img: np.ndarray) -> float:
    """Mean absolute gradient [grey levels / px] at half resolution.

    Half resolution makes it cheap and insensitive to pixel noise, while a defocused or motion-smeared image
    (blur of several pixels) still loses most of its gradient.
    """
    small = cv2.resize(img, (img.shape[1] // 2, img.shape[0] // 2), interpolation=cv2.INTER_AREA)
    gx = cv2.Sobel(small, cv2.CV_16S, 1, 0, ksize=3)
    gy = cv2.Sobel(small, cv2.CV_16S, 0, 1, ksize=3)
    # Sobel 3x3 weights sum to 4 per side: /8 turns it into grey levels per pixel of the half image
    return (float(cv2.mean(cv2.convertScaleAbs(gx))[0]) + float(cv2.mean(cv2.convertScaleAbs(gy))[0])) / 8.0
