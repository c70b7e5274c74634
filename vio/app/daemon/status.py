"""The daemon's status: the fields of the status snapshot and the status file that `vio status` reads."""

from __future__ import annotations

import json
import logging
import math
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from vio.io.atomic import replace_atomically

if TYPE_CHECKING:
    from vio.app.daemon.protocols import PoseOutput, Source
    from vio.estimator import EstimatorHealth

log = logging.getLogger(__name__)

STATUS_VERSION = 1


def _source_health(source: Source | None) -> dict:
    try:
        h = source.health() if source is not None else {}
    except Exception as e:  # health is for display only; never let it break the status loop
        h = {"error": str(e)}
    return json.loads(json.dumps(h, default=_json_default))


def _mavlink_health(mav: PoseOutput) -> dict:
    """Link state and the scalar counters of the MAVLink output (its health())."""
    try:
        h = mav.health()
    except Exception as e:  # display only
        h = {"health_error": str(e)}
    # None kept (null: "not known yet", e.g. origin_ours before the autopilot answers, as docs/autopilot.md says);
    # left out, a script could not tell a field not known yet from one this version does not have
    out = {k: v for k, v in h.items()
           if v is None or isinstance(v, (int, str, bool)) or (isinstance(v, float) and math.isfinite(v))}
    out["state"] = "up" if mav.link_up else "down"
    return out


def _round(v: float | None, nd: int = 2) -> float | None:
    return None if v is None else round(v, nd)


def _health_fields(h: EstimatorHealth) -> dict:
    """The estimator's own account (vio.estimator.EstimatorHealth) for the status file."""
    return {"vision_age_s": _round(h.vision_age_s), "frames_processed": h.frames_processed,
            "frames_unusable": h.frames_unusable, "unusable_reasons": dict(h.unusable_reasons),
            "frames_dropped": h.frames_dropped, "imu_rejected": h.imu_rejected,
            "imu_rejected_reasons": dict(h.imu_rejected_reasons), "last_reset_reason": h.last_reset_reason,
            "sensor_error": h.sensor_error, "calibration_warning": h.calibration_warning,
            "stereo_warning": h.stereo_warning, "frame_stamps": h.frame_stamps}


def _not_tracking_reason(h: EstimatorHealth | None, camera_ok: bool, imu_ok: bool = True) -> str:
    """Why there is no pose, in the words a person at the drone needs."""
    if not camera_ok:
        return "no camera frames"
    if not imu_ok:
        return "no IMU samples (camera frames cannot be used without them)"
    if h is None:
        return "estimator starting"
    if h.sensor_error:
        return h.sensor_error
    top = sorted(h.unusable_reasons.items(), key=lambda kv: -kv[1])[:2]
    unusable = f"; unusable frames: {', '.join(f'{k} x{n}' for k, n in top)}" if top else ""
    if not h.initialized:
        # a restart in flight waits here too: "keep still" alone is no advice to a flying vehicle
        return (f"not initialised yet (it starts when still, or after about a second of motion, facing a textured, "
                f"lit scene){unusable}")
    if h.vision_age_s is None:
        return f"no usable camera frame yet{unusable}"
    return f"last usable camera frame {h.vision_age_s:.1f} s ago (IMU time){unusable}"


def _dash(v: Any) -> str:
    return "-" if v is None else str(v)


def write_status_file(path: Path, snap: dict) -> None:
    """Atomic replace: a reader never sees half a file (temp file in the same folder, then rename). Not synced: it
    is rewritten every second and says what a running process does (after a power cut it is stale anyway)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    text = json.dumps(snap, indent=1, default=_json_default) + "\n"
    replace_atomically(path, lambda f: f.write(text.encode()), durable=False)


def _json_default(o: Any) -> Any:
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    return str(o)
