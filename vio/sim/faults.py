"""Faults applied to a written dataset: what real flights do to a camera that a clean render does not.

Applied after rendering, to a copy, so that the same flight can be replayed with and without the fault and
the truth stays exact: both cameras black for a while (lens covered, exposure lost, a cable), or the
images stopping while the IMU runs on (a camera that died in flight).
"""

from __future__ import annotations

import shutil
from pathlib import Path

import cv2
import numpy as np


def _camera_rows(mav0: Path, cam: str) -> tuple[str, list[tuple[int, str]]]:
    lines = (mav0 / cam / "data.csv").read_text().splitlines()
    header = "\n".join(x for x in lines if x.startswith("#"))
    rows = [(int(a), b.strip()) for a, b in (x.split(",") for x in lines if x and not x.startswith("#"))]
    return header, rows


def copy_dataset(src: str | Path, dst: str | Path) -> Path:
    dst = Path(dst)
    shutil.rmtree(dst, ignore_errors=True)
    shutil.copytree(src, dst)
    return dst


def blackout(dataset: str | Path, start_s: float, length_s: float) -> int:
    """Black both cameras' images from `start_s` (after the first frame) for `length_s`; returns the count."""
    mav0 = Path(dataset) / "mav0"
    n = 0
    for cam in ("cam0", "cam1"):
        _, rows = _camera_rows(mav0, cam)
        t0 = rows[0][0]
        for t, name in rows:
            if start_s <= (t - t0) * 1e-9 < start_s + length_s:
                p = mav0 / cam / "data" / name
                img = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
                cv2.imwrite(str(p), np.zeros_like(img))
                n += 1
    return n


def cameras_stop(dataset: str | Path, after_s: float) -> int:
    """End both cameras' streams `after_s` after the first frame (the IMU runs on); returns frames removed."""
    mav0 = Path(dataset) / "mav0"
    n = 0
    for cam in ("cam0", "cam1"):
        header, rows = _camera_rows(mav0, cam)
        t0 = rows[0][0]
        keep = [(t, name) for t, name in rows if (t - t0) * 1e-9 <= after_s]
        n += len(rows) - len(keep)
        (mav0 / cam / "data.csv").write_text(header + "\n" + "".join(f"{t},{name}\n" for t, name in keep))
    return n
