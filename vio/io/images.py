"""16-bit camera images to the 8-bit grey the front end tracks on, one scale for a whole recording.

A 16-bit PNG or mono16 message may hold 16-bit values, or 10/12/14-bit values in the low bits (many machine
vision cameras), or such values shifted up into the high bits (MSB-aligned, the low bits always 0). A fixed
`>> 8` turned 12-bit values (0..4095) into a near-black image that every frame refused as too dark. The shift
is decided once per recording, on its first image and four spread over it (a EuRoC folder's by file, a bag's
at power-of-two message ordinals): a shift chosen per frame would change the brightness from frame to frame and
break the KLT tracking, which assumes a constant brightness. A frame brighter than the range decided is clipped to
white (never wrapped to black), with one warning.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Sequence

import cv2
import numpy as np

log = logging.getLogger(__name__)

BIT_DEPTHS = (8, 10, 12, 14, 16)  # the depths cameras write; the range decided is the smallest that holds the peak
MSB_MIN_PEAK = 1 << 10  # a peak under this (4 % of 16 bits) cannot tell MSB-aligned data


def grey(img: np.ndarray) -> np.ndarray:
    """An image as decoded with IMREAD_UNCHANGED (a file's or a message's own channels and depth) as one grey channel
    at its own depth: colour and colour with alpha converted as IMREAD_GRAYSCALE would."""
    if img.ndim == 3:
        return cv2.cvtColor(img, cv2.COLOR_BGRA2GRAY if img.shape[2] == 4 else cv2.COLOR_BGR2GRAY)
    return img


def uint16_shift(images: Sequence[np.ndarray]) -> tuple[int, str] | None:
    """The right shift that makes a recording's 16-bit images 8-bit, judged on the images given, and why (for the
    log); None when all are zero, which says nothing about the depth (and is 0 under any shift)."""
    peak = max((int(i.max()) for i in images), default=0)
    if peak == 0:
        return None
    used = 0
    for i in images:
        used |= int(np.bitwise_or.reduce(i, axis=None))
    low_zero = (used & -used).bit_length() - 1  # low bits that no pixel sets
    # MSB-aligned 10/12/14-bit values (noise sets the low bits of data aligned otherwise); a near-black image's few
    # small values (0, 4, 8) say nothing about alignment, so it takes some light to call it
    if low_zero >= 2 and peak >= MSB_MIN_PEAK:
        return 8, f"MSB-aligned values (the low {low_zero} bits always 0, max {peak})"
    bits = next(b for b in BIT_DEPTHS if peak < 1 << b)
    return bits - 8, f"{bits}-bit values (max {peak})"


class Uint16To8:
    """Converts a recording's 16-bit images to 8 bits with one shift, decided on the first image converted.

    `first` returns images the recording opens with or spreads over (a list, maybe empty), so that the shift
    does not depend on which frame a caller happens to load first (a replay's --start, a calibration check's
    sample), nor on a dark first frame alone (auto-exposure settling, a lens cap: a 16-bit camera whose first
    image peaked at 200 was given no shift and later frames clipped to white, a review's finding); `warn` records
    the one clipping warning (a reader's counted warnings)."""

    def __init__(self, where: str, first: Callable[[], Sequence[np.ndarray]] | None = None,
                 warn: Callable[[str], None] = log.warning) -> None:
        self.where = where
        self.shift: int | None = None
        self._first = first
        self._warn = warn
        self._clip_warned = False

    def _decide(self, img: np.ndarray) -> None:
        samples = self._first() if self._first is not None else []
        self._first = None  # asked once: unreadable or all-zero samples leave the decision to the images converted
        decided = uint16_shift([i for i in samples if i.dtype == np.uint16] + [img])
        if decided is not None:
            self.shift, why = decided
            log.info("%s: 16-bit images with %s: scaled to 8 bits by >> %d for the whole recording", self.where,
                     why, self.shift)

    def convert(self, img: np.ndarray) -> np.ndarray:
        """A 16-bit image as 8 bits; values above the decided range are clipped to 255."""
        if self.shift is None:
            self._decide(img)
            if self.shift is None:  # all zero so far: black under any shift
                return np.zeros(img.shape, np.uint8)
        if self.shift == 8:  # cannot exceed 255: the former conversion, byte for byte
            return (img >> 8).astype(np.uint8)
        out = img >> self.shift
        limit = 255 << self.shift | ((1 << self.shift) - 1)
        peak = int(img.max())
        if peak > limit:
            np.minimum(out, 255, out=out)
            if not self._clip_warned:
                self._clip_warned = True
                self._warn(f"{self.where}: an image has values up to {peak}, above the {self.shift + 8}-bit range "
                           "decided on the recording's first and spread-out images: its brightest parts are clipped "
                           "to white (said once)")
        return out.astype(np.uint8)
