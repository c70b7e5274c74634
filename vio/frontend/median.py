"""The median of a short float vector, as np.median gives it, without np.median's generic machinery.

np.median handles axes, `out`, keepdims and NaN through several Python layers: ~15-25 us a call on this
project's machines, for vectors of 3-200 numbers. The per-frame code asks for ~5 medians a frame (parallax,
image flow, the stereo search's local depths), so that overhead alone was ~1 % of a replay. The partition and
the mean of the middle pair are np.median's own steps, so the result is the same float.
"""

from __future__ import annotations

import numpy as np


def median(x: np.ndarray) -> float:
    """np.median(x) of a non-empty 1-D float array (NaN if it holds one, as np.median)."""
    n = len(x)
    k = n // 2
    # kth -1 puts a NaN, which sorts last, where the check below sees it (np.median does the same)
    p = np.partition(x, (k, -1) if n % 2 else (k - 1, k, -1))
    if np.isnan(p[-1]):
        return float("nan")
    # np.median takes the mean of the middle element(s): a / 1, or (a + b) / 2 in float64
    return float(p[k]) if n % 2 else float((p[k - 1] + p[k]) / 2.0)
