"""ROS bags and MCAP files as replay datasets, and an MCAP writer on ROS 2 schemas.

Read: a ROS 1 `.bag`, a ROS 2 bag folder (sqlite3 or MCAP storage) through `rosbags` (no ROS install), or a
bare `.mcap` file (ours, or any with ROS 2 `cdr` channels) through `mcap`; sensor_msgs/Image (mono8/16,
bgr8/rgb8/bgra8/rgba8) and sensor_msgs/CompressedImage for the cameras, sensor_msgs/Imu for the IMU. Header
stamps are used, never the bag's receive stamps. A recorder stores messages as they arrive, so a message
can come after a newer one on its topic (a driver thread, a busy recorder): one up to `MAX_LATE_S` older than
the newest before it is put in its place by stamp (all of them counted in a note); one later than that is a
clock jump, a VioError naming the topic and message, as is a repeated stamp with other data (an exact repeat
is dropped and noted). Left and right images are paired by equal stamp (1 us) with left-only frames kept
(`EurocDataset._pair`).

`BagDataset` is an `EurocDataset` for the replay loop: the IMU and all stamps are read when it is opened,
images are decoded while streaming (a second pass over the camera topics; the right image lazily).

`rosbags` and `mcap` are the [bags] extra, imported inside the functions that need them (`vio.extras`).
A bag carries no camera-IMU calibration: the caller passes one.
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import json
import logging
import os
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from types import ModuleType

import cv2
import numpy as np
import yaml

from vio import VioError
from vio.calibration import StereoCalibration, calibration_from_dict, calibration_units_problem, calibration_yaml
from vio.io.atomic import set_aside, settle_aside
from vio.io.euroc import (
    DatasetStats,
    EurocDataset,
    FlushPacer,
    ImuData,
    _step_problem,
    image_size_problem,
    imu_units_problem,
)
from vio.io.images import Uint16To8, grey
from vio.types import ImuSample, StereoFrame

log = logging.getLogger(__name__)

IMAGE = "sensor_msgs/msg/Image"
COMPRESSED = "sensor_msgs/msg/CompressedImage"
IMU = "sensor_msgs/msg/Imu"
ODOMETRY = "nav_msgs/msg/Odometry"
SCALE_SPREAD = 4  # left images besides the first, spread over a bag, on which a 16-bit scale is decided
MAX_LATE_S = 0.5  # a message at most this much older than the newest before it on its topic is put in its place


@dataclass(frozen=True)
class BagTopics:
    """The topics to read (EuRoC's names by default) and which camera messages: 'auto' (Image or
    CompressedImage; TOPIC/compressed, image_transport's name, when the bag has no TOPIC), 'raw' (Image only)
    or 'compressed' (CompressedImage only, TOPIC or TOPIC/compressed). As `[bag]` in the config."""

    left: str = "/cam0/image_raw"
    right: str = "/cam1/image_raw"
    imu: str = "/imu0"
    images: str = "auto"

    @classmethod
    def from_config(cls, bag, left: str | None = None, right: str | None = None,
                    imu: str | None = None) -> BagTopics:
        """The [bag] section (a vio.config.BagConfig), with the topics given on the command line winning."""
        return cls(left or bag.left_topic, right or bag.right_topic, imu or bag.imu_topic, bag.images)


def _need(module: str):
    from vio.extras import require

    return require(module, "bags", "reading and writing bags / MCAP")


BAG_SUFFIXES = (".bag", ".mcap", ".db3")  # ROS 1 bags, MCAP files, ROS 2 sqlite bags


def is_bag(path: str | Path) -> bool:
    p = Path(path)
    if p.is_file():
        return p.suffix in BAG_SUFFIXES
    return p.is_dir() and (p / "metadata.yaml").is_file()


def _typestore():
    ts = _need("rosbags.typesys")
    return ts.get_typestore(ts.Stores.ROS2_HUMBLE)


class _BagFile:
    """Messages of some topics in file order as (topic, msgtype, raw, kind); kind 'cdr' or 'ros1'."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.bare_mcap = path.is_file() and path.suffix == ".mcap"
        self.typestore = _typestore()
        self.topics: dict[str, tuple[str, int]] = {}  # topic -> (msgtype, message count)
        self.truncated = False  # a bare MCAP file without its summary (recorder killed): read up to the damage
        self.damaged: str | None = None  # a chunk that fails its CRC: read up to it (said, never used)
        if self.bare_mcap:
            reader = _need("mcap.reader")
            try:
                with open(path, "rb") as f:
                    summary = reader.make_reader(f).get_summary()
            except Exception:  # mcap raises EndOfFile, RecordLengthLimitExceeded... on a file cut short
                summary = None
            if summary is None:
                self.truncated = True
                for topic, ty, _raw, _r in self.messages(None):
                    old = self.topics.get(topic, (ty, 0))
                    self.topics[topic] = (ty, old[1] + 1)
                if not self.topics:  # nothing readable at all: not a recording cut short, not an MCAP
                    raise VioError(f"{path}: not a readable MCAP file (empty, another format, or damaged at its "
                                   "start)")
            else:
                counts = summary.statistics.channel_message_counts if summary.statistics else {}
                for cid, ch in summary.channels.items():
                    schema = summary.schemas.get(ch.schema_id)
                    self.topics[ch.topic] = (schema.name if schema else "?", int(counts.get(cid, 0)))
        else:
            hl = _need("rosbags.highlevel")
            try:
                with hl.AnyReader([path], default_typestore=self.typestore) as r:
                    for c in r.connections:
                        old = self.topics.get(c.topic, (c.msgtype, 0))
                        self.topics[c.topic] = (c.msgtype, old[1] + c.msgcount)
            except Exception as e:  # rosbags raises its own error types for damaged or foreign files
                inside = sorted(path.glob("*.mcap")) if path.is_dir() else []
                hint = (f"; an MCAP file inside cut short is read up to the damage when given alone: vio replay "
                        f"{inside[0]}") if inside else ""
                raise VioError(f"{path}: cannot read the bag ({type(e).__name__}: {e}){hint}") from None

    def messages(self, topics: list[str] | None) -> Iterator[tuple[str, str, bytes, object]]:
        if self.bare_mcap:
            reader = _need("mcap.reader")
            with open(self.path, "rb") as f:
                # streamed in file order with every chunk's CRC checked: a flipped bit in a chunk changed an IMU
                # sample that was then used (a review's finding)
                it = reader.NonSeekingReader(f, validate_crcs=True).iter_messages(topics=topics, log_time_order=False)
                read = 0
                while True:
                    try:
                        schema, ch, msg = next(it)
                    except StopIteration:
                        return
                    except Exception as e:  # the damaged end of a file cut short: what came before is kept
                        if self.truncated:
                            return
                        if type(e).__name__ == "CRCValidationError" or read:
                            # a chunk that fails its CRC, or that no longer decompresses (the same flipped bit
                            # under zstd): what came before it is kept, and said
                            why = "fails its CRC check" if type(e).__name__ == "CRCValidationError" else \
                                f"cannot be read ({type(e).__name__})"
                            self.damaged = self.damaged or (f"a chunk ending at byte {f.tell()} {why} (a damaged "
                                                            "file): read up to it, nothing after it")
                            return
                        raise VioError(f"{self.path}: cannot read the MCAP file ({type(e).__name__}: {e})") \
                            from None
                    read += 1
                    if schema is not None:
                        yield ch.topic, schema.name, msg.data, None
            return
        hl = _need("rosbags.highlevel")
        with hl.AnyReader([self.path], default_typestore=self.typestore) as r:
            conns = [c for c in r.connections if c.topic in topics]
            for c, _t, raw in r.messages(connections=conns):
                yield c.topic, c.msgtype, raw, r

    def deserialize(self, raw: bytes, msgtype: str, reader) -> object:
        if reader is None:
            return self.typestore.deserialize_cdr(raw, msgtype)
        return reader.deserialize(raw, msgtype)


def _check_late(name: str, k: int, t: int, newest: int | None) -> None:
    """A message older than the newest before it on its topic by more than MAX_LATE_S: a clock that jumped back,
    not a late message (sorting it in would mix two clocks)."""
    if newest is not None and newest - t > MAX_LATE_S * 1e9:
        raise VioError(f"{name}: message {k + 1}: out-of-order time stamp {t}, {(newest - t) * 1e-9:.3f} s before "
                       f"the newest before it ({newest}): more than {MAX_LATE_S:g} s late, did the clock jump back?")


def _exact_repeats(stamps: list[int], data: list, ordinals: list[int], name: str, other: str,
                   notes: list[str]) -> set[int]:
    """Positions of the messages that repeat an earlier one exactly (same stamp, same data: `data` holds what is
    compared), wherever it came in the bag, said in `notes`; the same stamp with other data is a VioError
    naming both messages (`other`: what differs, e.g. "other values")."""
    by_stamp = sorted(range(len(stamps)), key=lambda i: (stamps[i], i))  # by stamp, then as they came
    repeat: set[int] = set()
    for a, b in zip(by_stamp, by_stamp[1:]):
        if stamps[b] == stamps[a]:
            if data[b] != data[a]:
                raise VioError(f"{name}: message {ordinals[b] + 1}: duplicate time stamp with {other} than "
                               f"message {ordinals[a] + 1} {stamps[b]}")
            repeat.add(b)
    if repeat:
        notes.append(f"{name}: {len(repeat)} exact repeats (same stamp, same data) dropped")
    return repeat


def _stamp_order(stamps: list[int], ordinals: list[int], name: str, what: str, notes: list[str]) -> np.ndarray | None:
    """The stable order that sorts the stamps, or None when they are in order already; how many came late goes
    into `notes`.

    A message that came late fills a gap of its own when sorted in: the stamps on either side of it are two of
    the topic's steps apart. A clock that jumped back by less than MAX_LATE_S makes every message for that long
    "late", and they land between the ones already there, where the neighbours are one step apart: that is two
    clocks mixed, refused as a clock jump (a review's finding: 40 IMU samples 0.2 s back were sorted in)."""
    t = np.asarray(stamps, dtype=np.int64)
    if len(t) < 2 or bool(np.all(np.diff(t) >= 0)):
        return None
    newest = np.maximum.accumulate(t)
    is_late = t < newest
    order = np.argsort(t, kind="stable")
    ts = t[order]
    step = float(np.median(np.diff(ts)))
    pos = np.argsort(order)  # bag index -> place in stamp order
    for k in np.flatnonzero(is_late):
        i = int(pos[k])
        lo, hi = ts[max(i - 1, 0)], ts[min(i + 1, len(ts) - 1)]
        span = float(hi - lo) * (2 if i == 0 or i == len(ts) - 1 else 1)
        if span < 1.5 * step:
            raise VioError(f"{name}: message {ordinals[k] + 1}: out-of-order time stamp {int(t[k])}, "
                           f"{(newest[k] - t[k]) * 1e-9:.3f} s before the newest before it, lands between messages "
                           "already there instead of in a gap of its own: did the clock jump back?")
    notes.append(f"{name}: {int(np.count_nonzero(is_late))} {what} came after a newer one (at most {MAX_LATE_S:g} s "
                 "late): put in their place by stamp")
    return order


def _stamp(msg) -> int:
    s = msg.header.stamp
    return int(s.sec) * 1_000_000_000 + int(s.nanosec)


def decode_image(msg, msgtype: str, to8: Uint16To8 | None = None) -> np.ndarray | None:
    """An Image or CompressedImage message as 8-bit grey (as the EuRoC reader loads a PNG); None if broken.
    A 16-bit image is scaled by `to8`, the recording's one scale (without it: by this image alone)."""
    img = decode_grey(msg, msgtype)
    if img is not None and img.dtype == np.uint16:
        img = (to8 or Uint16To8("image")).convert(img)
    return img


def decode_grey(msg, msgtype: str) -> np.ndarray | None:
    """An Image or CompressedImage message as grey at its own depth (8 or 16 bits); None if broken."""
    if msgtype.endswith("CompressedImage"):
        img = cv2.imdecode(np.asarray(msg.data, np.uint8), cv2.IMREAD_UNCHANGED)
        if img is None:
            return None
    else:
        enc = msg.encoding.lower()
        h, w, step = int(msg.height), int(msg.width), int(msg.step)
        data = np.asarray(msg.data, np.uint8)
        if data.size < h * step:
            return None
        rows = data[: h * step].reshape(h, step)
        if enc in ("mono8", "8uc1"):
            img = rows[:, :w]
        elif enc in ("mono16", "16uc1"):
            img = rows[:, : 2 * w].copy().view(">u2" if msg.is_bigendian else "<u2").astype(np.uint16)
        elif enc in ("bgr8", "rgb8", "bgra8", "rgba8"):
            ch = 4 if enc.endswith("a8") else 3
            img = rows[:, : ch * w].reshape(h, w, ch)
            code = {"bgr8": cv2.COLOR_BGR2GRAY, "rgb8": cv2.COLOR_RGB2GRAY, "bgra8": cv2.COLOR_BGRA2GRAY,
                    "rgba8": cv2.COLOR_RGBA2GRAY}[enc]
            return cv2.cvtColor(np.ascontiguousarray(img), code)
        else:
            raise VioError(f"image encoding {msg.encoding!r} is not supported (mono8, mono16, bgr8, rgb8, ...)")
        img = np.ascontiguousarray(img)
    return grey(img)


class BagDataset(EurocDataset):
    """A bag or MCAP file opened for replay, with the EurocDataset interface `vio.app.replay` uses."""

    def __init__(self, path: str | Path, calibration: StereoCalibration | None,
                 topics: BagTopics | None = None) -> None:
        p = Path(path)
        if not p.exists():
            raise VioError(f"{p}: not found")
        if calibration is None:
            calibration = recorded_calibration(p)
        if calibration is None:
            raise VioError(f"{p}: a bag carries no camera-IMU calibration: give one with --calib (an MCAP file "
                           "recorded by vio record carries its own)")
        self.path = self.root = self.mav0 = p
        self.topics = topics or BagTopics()
        self.stats = DatasetStats()
        # (message, type) of left images spread over the bag, from the stamp pass: a 16-bit scale is decided on them
        self._scale_left: list[tuple[object, str]] = []
        self._to8 = Uint16To8(str(p), self._scale_samples, self._warn)
        self._bag = _BagFile(p)
        if self._bag.truncated:
            self.stats.notes.append(f"{p}: no MCAP summary (the recorder stopped mid-write?): read up to the "
                                    "damaged end")
        self._check_topics()
        self.calibration = calibration
        self.imu = self._read_imu()
        (self.cam0_t, self._cam0_drop), (self.cam1_t, self._cam1_drop) = self._read_cam_stamps()
        if self._bag.damaged:
            self.stats.notes.append(f"{p}: {self._bag.damaged}")
        self.cam0_files = list(range(len(self.cam0_t)))  # message ordinal after drops: never None
        self.cam1_files = list(range(len(self.cam1_t)))
        self.has_cam1 = True
        self._check_overlap()
        self.units_problem = imu_units_problem(self.imu, self.where("imu")) or calibration_units_problem(calibration)
        if self.units_problem is None:
            self.imu = self._drop_out_of_range(self.imu)
        self.groundtruth = None
        self.groundtruth_problem = None
        for n in self.stats.notes:
            log.warning(n)
        self._pair()

    def where(self, stream: str) -> str:
        topic = {"imu": self.topics.imu, "cam0": self.topics.left, "cam1": self.topics.right}[stream]
        return f"{self.path} topic {topic}"

    # -- opening -------------------------------------------------------------------------------------------
    def _camera_topic(self, topic: str) -> str:
        """The topic a camera is read from, as `images` says: TOPIC, or image_transport's TOPIC/compressed."""
        have, mode = self._bag.topics, self.topics.images
        if mode == "raw":
            return topic
        compressed = f"{topic.rstrip('/')}/compressed"
        if mode == "compressed":
            return topic if have.get(topic, ("",))[0] == COMPRESSED or compressed not in have else compressed
        return compressed if topic not in have and compressed in have else topic

    def _check_topics(self) -> None:
        have = self._bag.topics
        if self.topics.images not in ("auto", "raw", "compressed"):
            raise VioError(f"{self.path}: images = {self.topics.images!r} is not one of auto, raw, compressed")
        self.topics = dataclasses.replace(self.topics, left=self._camera_topic(self.topics.left),
                                          right=self._camera_topic(self.topics.right))
        cam_types = {"auto": (IMAGE, COMPRESSED), "raw": (IMAGE,), "compressed": (COMPRESSED,)}[self.topics.images]
        wanted = (("left", self.topics.left, cam_types), ("right", self.topics.right, cam_types),
                  ("imu", self.topics.imu, (IMU,)))
        if self.topics.left == self.topics.right:
            raise VioError(f"{self.path}: the left and right cameras are both read from {self.topics.left}: give "
                           "each its own topic (--left-topic, --right-topic or [bag])")
        missing = [f"{what} {t}" for what, t, _ in wanted if t not in have]
        if missing:
            listing = ", ".join(f"{t} ({ty}, {n} msgs)" for t, (ty, n) in sorted(have.items())) or "none"
            if self._bag.truncated:  # only the messages before the cut are known: the topics may well be right
                raise VioError(f"{self.path}: the file is cut short (no MCAP summary: the recorder stopped mid-write?) "
                               f"and no message of the {' / '.join(missing)} topic comes before the cut; read before "
                               f"it: {listing} (if the topics are named otherwise: --left-topic, --right-topic, "
                               "--imu-topic or [bag] in the config)")
            raise VioError(f"{self.path}: no {' / '.join(missing)} topic; the bag has: {listing} "
                           "(choose with --left-topic, --right-topic, --imu-topic or [bag] in the config)")
        for what, t, types in wanted:
            if have[t][0] not in types:
                why = f" ([bag] images = {self.topics.images!r})" if self.topics.images != "auto" else ""
                raise VioError(f"{self.path}: topic {t} ({what}) is {have[t][0]}, expected "
                               f"{' or '.join(types)}{why}")

    def _read_imu(self) -> ImuData:
        rows: list[tuple[int, float, float, float, float, float, float]] = []
        ordinals: list[int] = []
        newest = None
        name = self.where("imu")
        for k, (_, ty, raw, r) in enumerate(self._bag.messages([self.topics.imu])):
            m = self._bag.deserialize(raw, ty, r)
            w, a = m.angular_velocity, m.linear_acceleration
            row = (_stamp(m), float(w.x), float(w.y), float(w.z), float(a.x), float(a.y), float(a.z))
            if row[0] <= 0:
                raise VioError(f"{name}: message {k + 1}: time stamp {row[0]} is not positive")
            _check_late(name, k, row[0], newest)
            newest = row[0] if newest is None else max(newest, row[0])
            rows.append(row)
            ordinals.append(k)
        # exact repeats dropped before the order is checked
        repeat = _exact_repeats([r[0] for r in rows], rows, ordinals, name, "other values", self.stats.notes)
        if repeat:
            rows = [r for i, r in enumerate(rows) if i not in repeat]
            ordinals = [k for i, k in enumerate(ordinals) if i not in repeat]
        order = _stamp_order([r[0] for r in rows], ordinals, name, "messages", self.stats.notes)
        if order is not None:
            rows = [rows[i] for i in order]
        vals = np.array(rows, dtype=float).reshape(-1, 7)
        t = np.array([r[0] for r in rows], dtype=np.int64)
        bad = ~np.all(np.isfinite(vals[:, 1:]), axis=1)
        if bad.any():
            n_bad = int(bad.sum())
            if 2 * n_bad > len(vals):
                raise VioError(f"{name}: {n_bad} of {len(vals)} IMU messages have a non-finite value")
            self.stats.notes.append(f"{name}: {n_bad} of {len(vals)} IMU messages with a non-finite value skipped")
            self.stats.imu_rows_skipped["non-finite value"] = n_bad
            vals, t = vals[~bad], t[~bad]
        if len(t) < 2:
            raise VioError(f"{name}: fewer than 2 IMU messages")
        problem = _step_problem(name, t, "imu")
        if problem:
            raise VioError(problem)
        return ImuData(t, vals[:, 1:4].copy(), vals[:, 4:7].copy())

    def _read_cam_stamps(self):
        """Per camera topic: the stamps in stamp order and the bag ordinals of the exact repeats dropped; a
        message that came late (`MAX_LATE_S`) gets its place through `self._rank` (bag ordinal after the drops ->
        place in stamp order), which the streaming pass follows. A repeat is the same stamp with the same bytes
        (a digest, not the image, is kept), wherever it came in the bag."""
        out: dict[str, list[tuple[int, int, bytes]]] = {self.topics.left: [], self.topics.right: []}
        newest: dict[str, int] = {}
        ordinal = {self.topics.left: 0, self.topics.right: 0}
        for topic, ty, raw, r in self._bag.messages([self.topics.left, self.topics.right]):
            k = ordinal[topic]
            ordinal[topic] += 1
            msg = self._bag.deserialize(raw, ty, r)
            if topic == self.topics.left and k & (k - 1) == 0:  # the first and ordinals 1, 2, 4, 8, ...
                self._scale_left = [*self._scale_left[:1], *self._scale_left[1:][-(SCALE_SPREAD - 1):], (msg, ty)]
            t = _stamp(msg)
            _check_late(f"{self.path} topic {topic}", k, t, newest.get(topic))
            newest[topic] = max(newest.get(topic, t), t)
            out[topic].append((t, k, hashlib.blake2b(bytes(raw), digest_size=16).digest()))
        res = []
        self._rank = {}
        for topic in (self.topics.left, self.topics.right):
            name = f"{self.path} topic {topic}"
            msgs = out[topic]
            repeat = _exact_repeats([m[0] for m in msgs], [m[2] for m in msgs], [m[1] for m in msgs], name,
                                    "another image", self.stats.notes)
            dropped = {msgs[i][1] for i in repeat}
            kept = [m for i, m in enumerate(msgs) if i not in repeat]  # bag order
            stamps, ks = [m[0] for m in kept], [m[1] for m in kept]
            order = _stamp_order(stamps, ks, name, "images", self.stats.notes)
            t = np.array(stamps, dtype=np.int64)
            if order is not None:
                t = t[order]
                self._rank[topic] = np.argsort(order)
            problem = _step_problem(name, t, "camera")
            if problem:
                raise VioError(problem)
            res.append((t, dropped))
        return res

    # -- streaming -----------------------------------------------------------------------------------------
    def _scale_samples(self) -> list[np.ndarray]:
        """Left images kept from the stamp pass, from which a 16-bit depth is decided: the first and the last
        SCALE_SPREAD at power-of-two ordinals, which spread over the bag (the last in its second half) without
        knowing its length beforehand. The first alone gave a bag opening dark (auto-exposure settling, a lens
        cap) too small a scale, and every later frame was clipped to white. Those that do not decode are left out."""
        kept, self._scale_left = self._scale_left, []
        return [img for img in (decode_grey(*m) for m in kept) if img is not None]

    def _decode(self, item) -> np.ndarray | None:
        raw, ty, r = item
        img = decode_image(self._bag.deserialize(raw, ty, r), ty, self._to8)
        if img is None:
            self.stats.unreadable_images += 1
            self._warn(f"{self.path}: unreadable image; skipped")
        return img

    def _raw_frames(self) -> Iterator[tuple[int, tuple, tuple | None]]:
        """(frame index, left message, right message or None) in frame order, from one pass over the bag."""
        right_of = self._right_files  # frame index -> right ordinal (after drops) or None
        left_t, right_t = self.topics.left, self.topics.right
        pending_l: dict[int, tuple] = {}
        pending_r: dict[int, tuple] = {}
        counters = {left_t: [0, 0], right_t: [0, 0]}  # topic -> [ordinal in the bag, index after drops]
        drops = {left_t: self._cam0_drop, right_t: self._cam1_drop}
        nxt = 0
        n = len(self.frame_t)
        for topic, ty, raw, r in self._bag.messages([left_t, right_t]):
            c = counters[topic]
            k = c[0]
            c[0] += 1
            if k in drops[topic]:
                continue
            idx = c[1]
            c[1] += 1
            if topic in self._rank:  # a message that came late: its place in stamp order
                idx = int(self._rank[topic][idx])
            (pending_l if topic == left_t else pending_r)[idx] = (raw, ty, r)
            while nxt < n and nxt in pending_l and (right_of[nxt] is None or right_of[nxt] in pending_r):
                j = right_of[nxt]
                yield nxt, pending_l.pop(nxt), None if j is None else pending_r[j]
                nxt += 1
                need = next((right_of[i] for i in range(nxt, n) if right_of[i] is not None), None)
                for jj in [jj for jj in pending_r if need is None or jj < need]:
                    del pending_r[jj]
        while nxt < n:  # lefts whose right never came (cannot happen for a bag read twice the same way)
            if nxt in pending_l:
                yield nxt, pending_l.pop(nxt), None
            nxt += 1

    def frame(self, i: int, lazy_right: bool = False) -> StereoFrame | None:
        raise VioError("a bag is streamed: use events()")

    def first_image_size_problem(self) -> str | None:
        for _k, left, right in self._raw_frames():
            for cam, item, calib in (("cam0", left, self.calibration.cam0), ("cam1", right, self.calibration.cam1)):
                img = None if item is None else self._decode(item)
                if img is None:
                    continue
                problem = image_size_problem(self.where(cam), img, calib, "wrong calibration file, or another topic?")
                if problem:
                    return problem
            return None
        return None

    def events(self, t_start_ns: int | None = None, t_end_ns: int | None = None,
               lazy_right: bool = False) -> Iterator[ImuSample | StereoFrame]:
        """As EurocDataset.events: IMU first on equal stamps, frames in stamp order."""
        imu_t = self.imu.t_ns
        lo = 0 if t_start_ns is None else int(np.searchsorted(imu_t, t_start_ns))
        hi = len(imu_t) if t_end_ns is None else int(np.searchsorted(imu_t, t_end_ns, side="right"))
        ts = imu_t[lo:hi].tolist()
        gyro = self.imu.gyro[lo:hi].copy()
        accel = self.imu.accel[lo:hi].copy()
        i, n = 0, hi - lo
        frame_t = self.frame_t.tolist()
        for k, left, right in self._raw_frames():
            t = frame_t[k]
            if t_start_ns is not None and t < t_start_ns:
                continue
            if t_end_ns is not None and t > t_end_ns:
                break
            while i < n and ts[i] <= t:
                yield ImuSample(ts[i], gyro[i], accel[i])
                i += 1
            img = self._decode(left)
            if img is None:
                continue
            if right is None:
                yield StereoFrame(t, img, None, seq=k)
            elif lazy_right:
                yield StereoFrame(t, img, None, seq=k, load_right=functools.partial(self._decode, right))
            else:
                yield StereoFrame(t, img, self._decode(right), seq=k)
        while i < n:
            yield ImuSample(ts[i], gyro[i], accel[i])
            i += 1


# ------------------------------------------------------------------------------------------------- writing

def _header(ts, t_ns: int, frame_id: str):
    Header = ts.types["std_msgs/msg/Header"]
    Time = ts.types["builtin_interfaces/msg/Time"]
    return Header(stamp=Time(sec=int(t_ns // 1_000_000_000), nanosec=int(t_ns % 1_000_000_000)), frame_id=frame_id)


def image_message(ts, t_ns: int, img: np.ndarray, frame_id: str, compression: str = "raw"):
    """sensor_msgs Image (raw mono8) or CompressedImage ('png' lossless, 'jpeg')."""
    if compression == "raw":
        img = np.ascontiguousarray(img, np.uint8)
        return IMAGE, ts.types[IMAGE](header=_header(ts, t_ns, frame_id), height=img.shape[0], width=img.shape[1],
                                      encoding="mono8", is_bigendian=0, step=img.shape[1],
                                      data=img.reshape(-1))
    ext, params = {"png": (".png", []),  # OpenCV's defaults, as the EuRoC writer's imwrite: fastest here
                   "jpeg": (".jpg", [cv2.IMWRITE_JPEG_QUALITY, 90])}[compression]
    ok, buf = cv2.imencode(ext, img, params)
    if not ok:
        raise VioError(f"cannot encode an image as {compression}")
    return COMPRESSED, ts.types[COMPRESSED](header=_header(ts, t_ns, frame_id), format=compression,
                                            data=buf.reshape(-1))


def imu_message(ts, s: ImuSample, frame_id: str = "imu0"):
    V3 = ts.types["geometry_msgs/msg/Vector3"]
    Q = ts.types["geometry_msgs/msg/Quaternion"]
    cov = np.zeros(9)
    ocov = np.zeros(9)
    ocov[0] = -1.0  # no orientation (REP 145)
    g, a = s.gyro, s.accel
    return IMU, ts.types[IMU](header=_header(ts, s.t_ns, frame_id), orientation=Q(x=0.0, y=0.0, z=0.0, w=1.0),
                              orientation_covariance=ocov, angular_velocity=V3(x=float(g[0]), y=float(g[1]),
                                                                               z=float(g[2])),
                              angular_velocity_covariance=cov, linear_acceleration=V3(
                                  x=float(a[0]), y=float(a[1]), z=float(a[2])),
                              linear_acceleration_covariance=cov.copy())


def odometry_message(ts, st) -> tuple[str, object]:
    """A NavState as nav_msgs/Odometry (pose in world, twist: world-frame velocity in the linear part)."""
    from vio.geometry import rot_to_quat_wxyz

    g = ts.types
    T = st.T_world_body
    q = rot_to_quat_wxyz(T[:3, :3])
    p = T[:3, 3]
    cov6 = np.zeros((6, 6))
    if getattr(st, "cov_pose", None) is not None:  # GTSAM order (rot, pos) -> ROS order (pos, rot)
        c = np.asarray(st.cov_pose)
        cov6 = c[np.ix_([3, 4, 5, 0, 1, 2], [3, 4, 5, 0, 1, 2])]
    v = np.asarray(st.v_world) if getattr(st, "v_world", None) is not None else np.zeros(3)
    twist_cov = np.zeros((6, 6))
    if getattr(st, "cov_vel", None) is not None:
        twist_cov[:3, :3] = np.asarray(st.cov_vel)
    pose = g["geometry_msgs/msg/Pose"](position=g["geometry_msgs/msg/Point"](x=float(p[0]), y=float(p[1]),
                                                                             z=float(p[2])),
                                       orientation=g["geometry_msgs/msg/Quaternion"](
                                           x=float(q[1]), y=float(q[2]), z=float(q[3]), w=float(q[0])))
    V3 = g["geometry_msgs/msg/Vector3"]
    twist = g["geometry_msgs/msg/Twist"](linear=V3(x=float(v[0]), y=float(v[1]), z=float(v[2])),
                                         angular=V3(x=0.0, y=0.0, z=0.0))
    return ODOMETRY, g[ODOMETRY](
        header=_header(ts, st.t_ns, "world"), child_frame_id="body",
        pose=g["geometry_msgs/msg/PoseWithCovariance"](pose=pose, covariance=cov6.reshape(-1).astype(float)),
        twist=g["geometry_msgs/msg/TwistWithCovariance"](twist=twist, covariance=twist_cov.reshape(-1)))


CALIBRATION_ATTACHMENT = "kestrel-calibration.yaml"  # the recorder's calibration inside an MCAP file


def recorded_calibration(path: Path) -> StereoCalibration | None:
    """The calibration `vio record` put into a bare MCAP file (an attachment), or None (another file, a bag)."""
    if not (path.is_file() and path.suffix == ".mcap"):
        return None
    stream = _need("mcap.stream_reader")
    records = _need("mcap.records")
    try:
        with open(path, "rb") as f:
            # the recorder writes it first, before any schema, channel or data: reading stops at those (a
            # multi-GB file of someone else's would otherwise be read whole, chunks decompressed, for nothing)
            for rec in stream.StreamReader(f, emit_chunks=True).records:
                if isinstance(rec, records.Attachment) and rec.name == CALIBRATION_ATTACHMENT:
                    d = yaml.safe_load(rec.data.decode())
                    if not isinstance(d, dict):
                        raise VioError(f"{path}: its recorded calibration is not a YAML mapping")
                    log.info("%s: the calibration recorded with it is used", path)
                    return calibration_from_dict(d, where=f"{path} (recorded calibration)")
                if isinstance(rec, (records.Schema, records.Channel, records.Chunk, records.Message)):
                    return None
    except VioError:
        raise
    except Exception:  # a file cut short before the attachment, or not an MCAP at all: the caller says so
        return None
    return None


def require_mcap_writer(what: str = "reading and writing bags / MCAP") -> ModuleType:
    """mcap's writer module (1.5 or newer), with rosbags' type store that McapWriter serialises with: a
    recording command checks them before it opens a source or starts a daemon (`what`: the option, as the user
    wrote it), rather than failing once the recording begins."""
    from vio.extras import require

    writer = require("mcap.writer", "bags", what)
    require("rosbags.typesys", "bags", what)
    if not hasattr(writer.Writer, "flush"):  # mcap < 1.5 cannot finish a chunk before it is full
        raise VioError("writing MCAP needs mcap 1.5 or newer (Writer.flush, which the periodic fsync needs): "
                       "pip install -U 'kestrel-vio[bags]'")
    return writer


class McapWriter:
    """A bare MCAP file on ROS 2 schemas (`ros2msg` + `cdr`, which Foxglove and `vio replay` read as they
    are) plus JSON channels (health). Messages are logged at their sensor stamp.

    As the EuRoC writer, it flushes at least every `flush_interval_s` of sensor data time: the chunk being
    built (in memory until it reaches `chunk_size`) is finished, written and fsynced, so a killed recorder or a
    power cut loses at most that much plus what came since (a file cut there is read up to it)."""

    def __init__(self, path: str | Path, compression: str = "png", chunk_size: int = 1 << 20,
                 calibration: StereoCalibration | None = None, flush_interval_s: float = 0.5) -> None:
        writer = require_mcap_writer()
        self.ts = _typestore()
        self.path = Path(path)
        self.compression = compression
        # a file there (`vio record OUT.mcap --overwrite`) is kept beside until this one has a message (`close`): it
        # was truncated here, before any data came, so a source that failed at once left nothing of either
        self._replaced: Path | None = None
        self.messages = 0
        if self.path.is_file():
            self._replaced = set_aside(self.path)
        self._f = open(self.path, "wb")
        # PNG/JPEG are compressed already: zstd over them costs CPU for ~nothing; raw images and IMU do compress
        chunk_compression = writer.CompressionType.ZSTD if compression == "raw" else writer.CompressionType.NONE
        self._w = writer.Writer(self._f, chunk_size=chunk_size, compression=chunk_compression)
        self._w.start(profile="ros2", library="kestrel-vio")
        if calibration is not None:
            # first in the file, so that a recording cut short still carries it: an OAK's factory calibration has
            # no YAML to keep beside the file, and a replay without one could not start (a review's finding)
            self._w.add_attachment(0, 0, CALIBRATION_ATTACHMENT, "application/yaml",
                                   calibration_yaml(calibration).encode())
        self._schemas: dict[str, int] = {}
        self._channels: dict[str, int] = {}
        self.bytes_images = 0
        self._flush_pacer = FlushPacer(flush_interval_s)  # EurocWriter's pacing

    def _channel(self, topic: str, msgtype: str) -> int:
        if topic not in self._channels:
            if msgtype not in self._schemas:
                text = self.ts.generate_msgdef(msgtype, ros_version=2)[0]
                self._schemas[msgtype] = self._w.register_schema(msgtype, "ros2msg", text.encode())
            self._channels[topic] = self._w.register_channel(topic, "cdr", self._schemas[msgtype])
        return self._channels[topic]

    def write(self, topic: str, t_ns: int, msgtype: str, msg) -> None:
        data = self.ts.serialize_cdr(msg, msgtype)
        self._w.add_message(self._channel(topic, msgtype), log_time=int(t_ns), data=bytes(data),
                            publish_time=int(t_ns))
        self.messages += 1

    def write_frame(self, frame: StereoFrame, topics: BagTopics = BagTopics()) -> None:
        for topic, img, fid in ((topics.left, frame.left, "cam0"), (topics.right, frame.right_image(), "cam1")):
            if img is not None:
                ty, msg = image_message(self.ts, frame.t_ns, img, fid, self.compression)
                self.write(topic, frame.t_ns, ty, msg)
        self._flush_pacer(frame.t_ns, self.flush)

    def write_imu(self, s: ImuSample, topic: str = "/imu0") -> None:
        ty, msg = imu_message(self.ts, s)
        self.write(topic, s.t_ns, ty, msg)
        self._flush_pacer(s.t_ns, self.flush)

    def write_state(self, st, topic: str = "/vio/odometry") -> None:
        ty, msg = odometry_message(self.ts, st)
        self.write(topic, st.t_ns, ty, msg)

    def write_json(self, topic: str, t_ns: int, obj: dict) -> None:
        if topic not in self._channels:
            sid = self._w.register_schema(topic.strip("/").replace("/", "_"), "jsonschema",
                                          json.dumps({"type": "object"}).encode())
            self._channels[topic] = self._w.register_channel(topic, "json", sid)
        self._w.add_message(self._channels[topic], log_time=int(t_ns), publish_time=int(t_ns),
                            data=json.dumps(obj, default=str).encode())

    def flush(self) -> None:
        """Finish the chunk in progress and fsync: what was written so far survives a power cut."""
        self._w.flush()  # writes the open chunk and its message index, flushes the file object
        os.fsync(self._f.fileno())

    def close(self) -> None:
        if self._f.closed:
            return
        self._w.finish()
        self._f.close()
        old, self._replaced = self._replaced, None
        if old is not None and settle_aside(old, self.path, self.messages > 0):  # nothing recorded: put back
            log.warning("%s: nothing was recorded; the file that was there is kept (it is replaced only with data)",
                        self.path)

    def __enter__(self) -> McapWriter:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def export_bag(dataset: EurocDataset, out: str | Path, kind: str = "mcap", compression: str = "raw",
               topics: BagTopics = BagTopics()) -> Path:
    """Write a EuRoC dataset as a bag: kind 'ros1' (.bag), 'ros2-sqlite3' or 'ros2-mcap' (bag folders, with
    rosbags) or 'mcap' (a bare file, with the mcap library). Messages go in stamp order."""
    out = Path(out)
    events = dataset.events()
    if kind == "mcap":
        with McapWriter(out, compression) as w:
            for ev in events:
                (w.write_imu(ev, topics.imu) if isinstance(ev, ImuSample) else w.write_frame(ev, topics))
        return out
    ts = _typestore()
    if kind == "ros1":
        writer = _need("rosbags.rosbag1").Writer(out)
        ser = ts.serialize_ros1
    elif kind in ("ros2-sqlite3", "ros2-mcap"):
        rb2 = _need("rosbags.rosbag2")
        plugin = rb2.StoragePlugin.SQLITE3 if kind == "ros2-sqlite3" else rb2.StoragePlugin.MCAP
        writer = rb2.Writer(out, version=8, storage_plugin=plugin)
        ser = ts.serialize_cdr
    else:
        raise VioError(f"unknown bag kind {kind!r} (ros1, ros2-sqlite3, ros2-mcap, mcap)")
    conns: dict[str, object] = {}
    with writer:
        def put(topic: str, t_ns: int, ty: str, msg) -> None:
            if topic not in conns:
                conns[topic] = writer.add_connection(topic, ty, typestore=ts)
            writer.write(conns[topic], int(t_ns), bytes(ser(msg, ty)))

        for ev in events:
            if isinstance(ev, ImuSample):
                put(topics.imu, ev.t_ns, *imu_message(ts, ev))
            else:
                for topic, img, fid in ((topics.left, ev.left, "cam0"), (topics.right, ev.right_image(), "cam1")):
                    if img is not None:
                        put(topic, ev.t_ns, *image_message(ts, ev.t_ns, img, fid, compression))
    return out
