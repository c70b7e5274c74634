"""16-bit camera images to the 8-bit grey the front end tracks on, one scale for a whole recording.

A 16-bit PNG or mono16 message may hold 16-bit values, or 10/12/14-bit values in the low bits (many machine
vision cameras), or such values shifted up into the high bits (MSB-aligned, the low bits always 0). A fixed
`>> 8` turned 12-bit values (0..4095) into a near-black image that every frame refused as too dark. The shift
is decided once, from the recording's first image: a shift chosen per frame would change the brightness from
frame to frame and break the KLT tracking, which assumes a constant brightness. A later frame brighter than the
range decided is clipped to white (never wrapped to black), with one warning.
"""

from __future__ import annotations

import logging
from collections.abc import Callable

import numpy as np

log = logging.getLogger(__name__)

BIT_DEPTHS = (8, 10, 12, 14, 16)  # the depths cameras write; the range decided is the smallest that holds the peak


def uint16_shift(img: np.ndarray) -> tuple[int, str] | None:
    """The right shift that makes a 16-bit image's values 8-bit, and why (for the log); None for an all-zero
    image, which says nothing about the depth (and is 0 under any shift)."""
    peak = int(img.max())
    if peak == 0:
        return None
    used = int(np.bitwise_or.reduce(img, axis=None))
    low_zero = (used & -used).bit_length() - 1  # low bits that no pixel sets
    if low_zero >= 2:  # MSB-aligned 10/12/14-bit values (noise sets the low bits of data aligned otherwise)
        return 8, f"MSB-aligned values (the low {low_zero} bits always 0, max {peak})"
    bits = next(b for b in BIT_DEPTHS if peak < 1 << b)
    return bits - 8, f"{bits}-bit values (max {peak})"


class Uint16To8:
    """Converts a recording's 16-bit images to 8 bits with one shift, decided on the first image converted.

    `first` returns the recording's first image (or None), so that the shift does not depend on which frame a
    caller happens to load first (a replay's --start, a calibration check's sample); `warn` records the one
    clipping warning (a reader's counted warnings)."""

    def __init__(self, where: str, first: Callable[[], np.ndarray | None] | None = None,
                 warn: Callable[[str], None] = log.warning) -> None:
        self.where = where
        self.shift: int | None = None
        self._first = first
        self._warn = warn
        self._clip_warned = False

    def _decide(self, img: np.ndarray) -> None:
        first = self._first() if self._first is not None else None
        self._first = None  # asked once: an unreadable or all-zero first image leaves the decision to `img`
        for sample in (first, img):
            decided = uint16_shift(sample) if sample is not None and sample.dtype == np.uint16 else None
            if decided is not None:
                self.shift, why = decided
                log.info("%s: 16-bit images with %s: scaled to 8 bits by >> %d for the whole recording",
                         self.where, why, self.shift)
                return

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
                           "decided from the recording's first image: its brightest parts are clipped to white "
                           "(said once)")
        return out.astype(np.uint8)
