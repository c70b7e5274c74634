"""Map file: the keyframe database and its optimised poses, for a later flight to relocalise in.

One `.npz` (numpy arrays, read with allow_pickle=False) holding a JSON header and flat arrays:

    header          JSON text: {"format": "kestrel-vio-map", "version": 1, "keyframes": N, "descriptors": M,
                    "created_utc": ..., "vocabulary": {"k", "depth", "sha256"}, "camera": {fx, fy, cx, cy,
                    width, height}, "note": ..., "parts": [{"keyframes": n, "join_edges": k or null}]}
                    parts (optional, readers of version 1 ignore it): the keyframes in order, by the flight
                    segment they came from; join_edges is the loop edges that placed a segment in the map's
                    frame (null for the first, the frame's origin)
                    checkpoint (optional, readers of version 1 ignore it): present only in a map `vio run` wrote
                    while flying ([map] checkpoint_s), absent once the run saved it at a clean stop: {"boot_id",
                    "started_utc", "pid", "loaded"} of the run that wrote it (`run_identity`); a file that still
                    has it is the map of a run that did not stop cleanly
    kf_t_ns         (N,) int64    keyframe stamps (IMU clock of the mapping flight)
    kf_T_world_body (N, 4, 4) f64 loop-corrected keyframe poses in the map's world frame (ENU/FLU, z up)
    kf_offsets      (N+1,) int64  keyframe k owns descriptor rows kf_offsets[k]:kf_offsets[k+1]
    desc            (M, 32) uint8 upright ORB descriptors
    uv              (M, 2) f32    undistorted pixels in cam0
    p_cam           (M, 3) f32    stereo points in cam0 [m], NaN without depth

A reader refuses another format name, a newer version, and a header without a version or with one below 1 (a
damaged map). Bag-of-words vectors are not stored: they are recomputed with the loading side's vocabulary, so a map
survives a vocabulary update."""

from __future__ import annotations

import datetime
import hashlib
import json
import math
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from vio import VioError
from vio.calibration import FOCAL_MAX_SIDES, MAX_IMAGE_SIDE
from vio.geometry import is_se3
from vio.io.atomic import replace_atomically
from vio.loop.features import KeyframeFeatures
from vio.loop.vocabulary import NPZ_DAMAGED, load_npz

FORMAT = "kestrel-vio-map"
VERSION = 1
# what no map holds: a keyframe this far from the map's origin (a VIO map spans kilometres), a stereo point this far
# from its camera (the front end's max_depth_m is at most 1 km)
MAX_EXTENT_M = 1e6
MAX_POINT_M = 1e4


@dataclass(frozen=True)
class MapData:
    header: dict
    t_ns: np.ndarray
    T_world_body: np.ndarray
    features: list[KeyframeFeatures]
    stamp: tuple | None = None  # file_stamp() of the file as it was read


def file_stamp(path: str | Path) -> tuple | None:
    """What tells whether a map file changed since it was read (another run saved over it): None when absent."""
    try:
        st = os.stat(path)
    except OSError:
        return None
    return os.path.realpath(path), st.st_size, st.st_mtime_ns, st.st_ino


def boot_id() -> str:
    """This boot's id (Linux: /proc/sys/kernel/random/boot_id), '' where there is none: a checkpoint written since
    this boot is this flight's (a daemon restarted by systemd), one from an earlier boot is not."""
    try:
        return Path("/proc/sys/kernel/random/boot_id").read_text().strip()
    except OSError:
        return ""


def loaded_key(loaded: str | None) -> str | None:
    """The map a run loaded (`[map] load`) as a checkpoint's header names it, and a restart compares it: its real
    path, or None."""
    return os.path.realpath(loaded) if loaded else None


def run_identity(loaded: str | None) -> dict:
    """What names the run writing a checkpoint (the header's `checkpoint`): the boot, the process and its start,
    and the map it loaded (`loaded_key`)."""
    return {"boot_id": boot_id(),
            "started_utc": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
            "pid": os.getpid(), "loaded": loaded_key(loaded)}


def vocabulary_digest(voc) -> str:
    return hashlib.sha256(voc.centres.tobytes() + voc.idf.tobytes()).hexdigest()


def save_map(path: str | Path, t_ns, T_world_body, features: list[KeyframeFeatures], vocabulary, cam,
             note: str = "", parts: list[dict] | None = None, checkpoint: dict | None = None) -> dict:
    """Write a map (format: module docstring). `checkpoint`: the writing run's `run_identity`, for a map written in
    flight that is not final yet (absent: a finished map)."""
    offsets = np.concatenate([[0], np.cumsum([len(f.desc) for f in features])]).astype(np.int64)
    header = {"format": FORMAT, "version": VERSION, "keyframes": len(features), "descriptors": int(offsets[-1]),
              "created_utc": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
              "vocabulary": {"k": vocabulary.k, "depth": vocabulary.depth, "sha256": vocabulary_digest(vocabulary)},
              "camera": {"fx": cam.fx, "fy": cam.fy, "cx": cam.cx, "cy": cam.cy, "width": cam.width,
                         "height": cam.height,
                         # the keyframes' poses are the body's (IMU's): the camera's place on it is what a later
                         # flight with another mount needs to place them by the camera (LoopCloser.load_map)
                         "T_body_cam": [[float(x) for x in row] for row in np.asarray(cam.T_body_cam)]},
              "note": note}
    if parts is not None:
        header["parts"] = parts
    if checkpoint is not None:
        header["checkpoint"] = checkpoint

    def cat(attr, shape, dtype):
        arrs = [getattr(f, attr) for f in features]
        return np.concatenate(arrs).astype(dtype) if arrs else np.zeros(shape, dtype)
    # Written beside the target and renamed over it only when complete: a map grown in place (`[map] load` and
    # `save` the same file) must not lose the old one to a full disk or a kill half-way through the write.
    # A link is written through, to the file it names: renamed over, the link itself became the new map and the
    # file it named (the map a flight loaded through it) was left as it was.
    path = Path(path)
    real = Path(os.path.realpath(path))
    if real.exists() and not real.is_file():  # renamed over, a device node (/dev/null as root) would be replaced
        raise VioError(f"{path}: is not a regular file (a device, pipe or socket): the map is not written there")

    def write(f) -> None:
        np.savez_compressed(f, header=np.array(json.dumps(header)), kf_t_ns=np.asarray(t_ns, np.int64),
                            kf_T_world_body=np.asarray(T_world_body, np.float64).reshape(-1, 4, 4),
                            kf_offsets=offsets, desc=cat("desc", (0, 32), np.uint8),
                            uv=cat("uv", (0, 2), np.float32), p_cam=cat("p_cam", (0, 3), np.float32))
    try:  # durable: a map is the work of every flight that grew it, and a drone's power is cut, not shut down
        replace_atomically(real, write, durable=True)
    except OSError as e:
        raise VioError(f"{path}: cannot write the map ({e.strerror or e}); "
                       + ("the map that was there is kept" if path.exists() else "nothing written")) from None
    return header


def _inconsistency(off: np.ndarray, desc: np.ndarray, uv: np.ndarray, p: np.ndarray, t_ns: np.ndarray,
                   T: np.ndarray) -> str | None:
    """What does not fit together in a map's arrays (a file damaged or written by something else), or None: a
    map is flown on, so one that would load with keyframes missing, empty, or at NaN poses is refused whole."""
    # as stored, before any cast: float stamps were cut to whole numbers and ones beyond int64 wrapped, unsaid;
    # one number or a column ended in a TypeError ("internal error")
    if t_ns.ndim != 1 or not np.issubdtype(t_ns.dtype, np.integer):
        return f"keyframe stamps {t_ns.shape} {t_ns.dtype}, one whole number of nanoseconds per keyframe needed"
    if t_ns.dtype.kind == "u" and t_ns.size and int(t_ns.max()) >= 2**63:
        # unsigned stamps from 2^63 on wrapped to negative ones in the int64 cast, unsaid (a review's finding)
        return f"keyframe stamp {int(t_ns.max())} ns is beyond int64 nanoseconds (2^63 - 1, the year 2262)"
    n = len(t_ns)
    if n == 0:
        return "no keyframes"
    if T.shape != (n, 4, 4) or not np.isfinite(T).all():
        return f"keyframe poses: shape {T.shape} or non-finite values for {n} keyframes"
    if not all(is_se3(Tk, tol=1e-4) for Tk in T):
        return "keyframe poses are not rigid transforms"
    if np.abs(T[:, :3, 3]).max() > MAX_EXTENT_M:
        # a keyframe 1e300 m out loaded, and a flight relocalised on it would be placed there (a review's finding)
        return (f"a keyframe {np.abs(T[:, :3, 3]).max():.3g} m from the map's origin, beyond any flight's "
                f"({MAX_EXTENT_M:.0e} m)")
    if desc.ndim != 2 or desc.shape[1] != 32 or desc.dtype != np.uint8:  # before len(desc): one number has none
        return f"descriptors {desc.shape} {desc.dtype}, ORB needs (N, 32) uint8"
    if off.ndim != 1 or not np.issubdtype(off.dtype, np.integer) or len(off) != n + 1 or off[0] != 0 \
            or np.any(np.diff(off) < 0) or off[-1] != len(desc):  # float offsets cannot slice
        return f"keyframe offsets do not split the {len(desc)} descriptors into {n} keyframes"
    if uv.shape != (len(desc), 2) or p.shape != (len(desc), 3) or not np.isfinite(uv).all():
        return "pixels or points do not match the descriptors"
    if not np.all(np.isfinite(p).all(axis=1) | np.isnan(p).all(axis=1)):
        # a point is three finite coordinates or, without stereo depth, three NaN: a row finite in x (what tells a
        # point, KeyframeFeatures.has_3d) and infinite or NaN after it was loaded and fed to the PnP
        return "stereo points neither finite nor NaN (no depth) in all three coordinates"
    if len(p) and np.nanmax(np.abs(p), initial=0.0) > MAX_POINT_M:  # 1e300 m was loaded and fed to the PnP
        return (f"a stereo point {np.nanmax(np.abs(p)):.3g} m from its camera, beyond any stereo depth "
                f"({MAX_POINT_M:.0e} m)")
    return None


def _header_problem(header: dict, n: int) -> str | None:
    """What in a map's header does not fit its keyframes, or None: the parts (each flight that made the map, in
    keyframe order) must split them exactly, and the camera must be a size; a map grown from a damaged one would
    carry the damage on."""
    parts = header.get("parts")
    if parts is not None:
        ok = isinstance(parts, list) and all(
            isinstance(q, dict) and type(q.get("keyframes")) is int and q["keyframes"] >= 1
            and (q.get("join_edges") is None or (type(q["join_edges"]) is int and q["join_edges"] >= 0))
            for q in parts)
        if not ok or sum(q["keyframes"] for q in parts) != n or (parts and parts[0].get("join_edges") is not None):
            return f"its header's parts do not split its {n} keyframes"
    cp = header.get("checkpoint")
    if cp is not None and not (isinstance(cp, dict) and isinstance(cp.get("boot_id"), str)
                               and (cp.get("loaded") is None or isinstance(cp["loaded"], str))):
        return "its header's checkpoint does not name the run that wrote it"
    cam = header.get("camera")
    if not isinstance(cam, dict) or not all(type(cam.get(k)) in (int, float) and math.isfinite(cam[k])
                                            and cam[k] > 0 for k in ("width", "height", "fx", "fy", "cx", "cy")) \
            or not all(float(cam[k]).is_integer() and cam[k] <= MAX_IMAGE_SIDE for k in ("width", "height")):
        # whole pixels: 752.5 was taken; and a camera's size: 1e300 was (map info printed 301 digits)
        # the principal point too: the loader re-expresses the map's pixels in the flight's camera with it; not
        # true/false, which Python counts as ints (`vio map info` said "camera TruexTrue")
        return (f"its header has no camera size (whole pixels, at most {MAX_IMAGE_SIDE} a side), focal lengths and "
                "principal point")
    side = max(cam["width"], cam["height"])
    if max(cam["fx"], cam["fy"]) > FOCAL_MAX_SIDES * side or cam["cx"] > cam["width"] or cam["cy"] > cam["height"]:
        # fx or cx of 1e300 was loaded and the map's pixels re-expressed with it (a review's finding): as a calibration
        return (f"its header's camera (fx {cam['fx']:.6g}, fy {cam['fy']:.6g}, cx {cam['cx']:.6g}, cy {cam['cy']:.6g} "
                f"for {cam['width']:.0f}x{cam['height']:.0f}) is no camera's")
    if "T_body_cam" in cam:  # maps before 2026-12-06 do not have it
        try:
            T = np.array(cam["T_body_cam"], dtype=float)
            ok = T.shape == (4, 4) and bool(np.isfinite(T).all()) and is_se3(T, tol=1e-4)
        except (TypeError, ValueError):
            ok = False
        if not ok:
            return "its header's camera T_body_cam is not a rigid transform"
    return None


def part_ranges(header: dict, n: int) -> list[tuple[int, int]]:
    """(first, end) keyframe index of each flight a map's header names in `parts` (checked by load_map to split
    its n keyframes); the whole map for one without parts."""
    ends = np.cumsum([0, *([int(q["keyframes"]) for q in header.get("parts") or []] or [n])])
    return [(int(a), int(b)) for a, b in zip(ends[:-1], ends[1:])]


def _stamps_problem(header: dict, t_ns: np.ndarray) -> str | None:
    """Keyframe stamps that go back within one flight of the map (a damaged or hand-made file), or None. Across
    the parts of a grown map they may: each flight has its own clock. A map without `parts` (optional in
    version 1; maps grown before 2026-12-03 have none) may hold several flights: not checked (a review's)."""
    if not header.get("parts"):
        return None
    for k, (a, b) in enumerate(part_ranges(header, len(t_ns))):
        if np.any(np.diff(t_ns[a:b]) <= 0):
            return f"keyframe stamps do not increase within flight {k + 1} of the map"
    return None


def load_map(path: str | Path) -> MapData:
    stamp = file_stamp(path)
    try:
        z = load_npz(path, "a map file")
        if not isinstance(z, np.lib.npyio.NpzFile):  # a single .npy array
            raise VioError(f"{path}: not a Kestrel VIO map (a .npy array, not an .npz archive)")
        with z:
            try:
                header = json.loads(str(z["header"]))
            except RecursionError:  # JSON nested thousands deep: no map's header is
                raise VioError(f"{path}: not a Kestrel VIO map (its header is nested too deep to be one)") from None
            if not isinstance(header, dict) or header.get("format") != FORMAT:
                got = header.get("format") if isinstance(header, dict) else type(header).__name__
                raise VioError(f"{path}: not a Kestrel VIO map (format {got!r})")
            if "version" not in header:
                raise VioError(f"{path}: damaged map (its header states no format version)")
            version = header["version"]
            if type(version) is not int:
                raise VioError(f"{path}: damaged map (its header's version {version!r} is not a whole number)")
            if version < 1:  # every map ever written says 1 or more: 0 or below was accepted as if it were 1
                raise VioError(f"{path}: damaged map (its header's version {version} is not a map format version; "
                               "the first is 1)")
            if version > VERSION:
                raise VioError(f"{path}: map format version {header['version']} is newer than this program's "
                               f"({VERSION})")
            off = z["kf_offsets"]
            for name in ("uv", "p_cam", "kf_T_world_body"):
                # complex numbers lost their imaginary part in the float cast below, unsaid (a numpy warning only)
                if z[name].dtype.kind not in "fiu":
                    raise VioError(f"{path}: damaged map ({name} stored as {z[name].dtype}, real numbers needed)")
            desc, uv, p = z["desc"], z["uv"].astype(np.float64), z["p_cam"].astype(np.float64)
            t_ns, T = z["kf_t_ns"], z["kf_T_world_body"].astype(np.float64)
            problem = _inconsistency(off, desc, uv, p, t_ns, T)
            if not problem:
                t_ns = t_ns.astype(np.int64)
                problem = _header_problem(header, len(t_ns)) or _stamps_problem(header, t_ns)
            if problem:
                raise VioError(f"{path}: damaged map ({problem})")
            feats = [KeyframeFeatures(desc[a:b], uv[a:b], p[a:b]) for a, b in zip(off[:-1], off[1:])]
            return MapData(header, t_ns, T, feats, stamp)
    except IsADirectoryError:
        raise VioError(f"{path}: is a folder, not a map file") from None
    except FileNotFoundError:
        raise VioError(f"{path}: no such map file") from None
    except OSError as e:
        raise VioError(f"{path}: cannot read the map ({e.strerror or e})") from None
    except MemoryError as e:  # an array header declaring more than the archive holds (damaged), or a map too large
        raise VioError(f"{path}: cannot load the map: its arrays need more memory than this computer has ({e}); a "
                       "damaged file can declare sizes it does not hold") from None
    except NPZ_DAMAGED:  # a damaged file, as one cut short
        raise VioError(f"{path}: not a Kestrel VIO map, or a truncated or damaged one (not a complete .npz "
                       "archive)") from None
    except (KeyError, ValueError, json.JSONDecodeError) as e:
        # numpy takes what is neither .npy nor .npz for a pickle, and suggests loading it unsafely: never
        why = "not an .npz archive" if "pickle" in str(e) else str(e)
        raise VioError(f"{path}: not a Kestrel VIO map ({why})") from None
