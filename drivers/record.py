"""`vio record OUT [--format mcap]`: record live sensors to a EuRoC ASL dataset (or one MCAP file) that
`vio replay` reads back.

Images are lossless PNG, IMU rows are written with 17 significant digits (float64 round-trips exactly),
and the calibration the source reports (device EEPROM, or the config's calibration file) goes into the
sensor.yaml files. The writer fsyncs every `FLUSH_INTERVAL_S` of data and the loop also flushes on the
wall clock, so a power cut or SIGKILL loses at most about one second; SIGTERM/SIGINT/SIGHUP stop cleanly
(flush, close, exit 0).
"""

from __future__ import annotations

import argparse
import logging
import signal
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from drivers.base import SensorSource
from drivers.signals import stop_on_signal
from vio import VioError
from vio.argtypes import MAX_SECONDS, path_arg, positive_float_up_to
from vio.calibration import StereoCalibration
from vio.types import ImuSample, StereoFrame

log = logging.getLogger(__name__)

FLUSH_INTERVAL_S = 0.5
# a stream silent this long while the other one went on stopped (a pulled cable), or had a gap the closing lines say:
# an OAK's frames trail its IMU by tens of ms, a stream's period is 50 ms at most
STREAM_STOPPED_S = 1.0


@dataclass
class RecordStats:
    frames: int = 0
    imu: int = 0
    dropped_out_of_order: int = 0
    source_health: dict = field(default_factory=dict)
    first_frame_t_ns: int | None = None
    first_imu_t_ns: int | None = None
    last_frame_t_ns: int | None = None
    last_imu_t_ns: int | None = None
    # per stream ("IMU", "stereo frames"): its longest silence between two of its stamps, (length ns, end stamp)
    longest_gap: dict = field(default_factory=dict)

    @property
    def start_t_ns(self) -> int | None:
        """Where the recording holds both streams: the first stamp of the stream that started last (a camera boots
        after its IMU, a serial IMU opens before the camera: seconds apart), or of the only one. `--duration`
        counts from here."""
        starts = [t for t in (self.first_frame_t_ns, self.first_imu_t_ns) if t is not None]
        return max(starts) if starts else None

    @property
    def last_t_ns(self) -> int | None:
        """The newest stamp recorded, of either stream."""
        ends = [t for t in (self.last_frame_t_ns, self.last_imu_t_ns) if t is not None]
        return max(ends) if ends else None

    @property
    def span_s(self) -> float:
        """Seconds from `start_t_ns` to the last stamp: what `--duration` asked for. Counted from the first stamp
        of either stream, `--duration 10` with a serial IMU read 'over 12.21 s' (the IMU's lead counted)."""
        if self.start_t_ns is None or self.last_t_ns is None:
            return 0.0
        return (self.last_t_ns - self.start_t_ns) / 1e9

    @property
    def lead_s(self) -> float:
        """Seconds one stream was recorded alone before the other started (0 with one stream). From the streams'
        first stamps, not from the first one received: a source may hand over a later IMU sample before an earlier
        frame, and the lead was then 0 (not said) or short."""
        if self.first_frame_t_ns is None or self.first_imu_t_ns is None:
            return 0.0
        return abs(self.first_frame_t_ns - self.first_imu_t_ns) / 1e9

    @property
    def stopped_stream(self) -> tuple[str, float] | None:
        """("IMU" or "stereo frames", seconds) when one stream ended more than STREAM_STOPPED_S before the other: a
        serial IMU unplugged in the recording left its frames without IMU and `vio record` said "recorded ... over
        8.00 s", exit 0 (an integrator's walk-through). None when both went on to the end (or only one was there)."""
        if self.last_frame_t_ns is None or self.last_imu_t_ns is None:
            return None
        early = (self.last_frame_t_ns - self.last_imu_t_ns) / 1e9
        if abs(early) <= STREAM_STOPPED_S:
            return None
        return ("IMU", early) if early > 0 else ("stereo frames", -early)

    def note_gap(self, stream: str, t_ns: int, previous_ns: int) -> None:
        """Keep `stream`'s longest silence (from its previous stamp to `t_ns`)."""
        gap = t_ns - previous_ns
        if gap > self.longest_gap.get(stream, (0, 0))[0]:
            self.longest_gap[stream] = (gap, t_ns)

    @property
    def leading_stream(self) -> str | None:
        """"IMU" or "stereo frames": the stream that started first (None when lead_s is 0)."""
        if not self.lead_s:
            return None
        return "IMU" if self.first_imu_t_ns < self.first_frame_t_ns else "stereo frames"  # type: ignore[operator]


class RecordingWriteError(VioError):
    """The writer could not write an image (cv2.imwrite says only that it failed): said with what most likely
    happened (a full disk, the folder removed), as `vio run`'s recorder says it."""


def _wait_calibration(source: SensorSource, timeout_s: float, stop: threading.Event) -> StereoCalibration:
    deadline = time.monotonic() + timeout_s
    while not stop.is_set():
        calib = source.calibration()
        if calib is not None:
            return calib
        if time.monotonic() > deadline:
            raise VioError(f"no calibration from the {source.name} source within {timeout_s:.0f} s "
                           f"(device state: {source.health().get('state', '?')}, "
                           f"last error: {source.health().get('last_error', '') or 'none'})")
        stop.wait(0.05)
    raise VioError("stopped before the source delivered its calibration")


def record(source: SensorSource, out: str | Path, *, duration_s: float | None = None,
           stop: threading.Event | None = None, calibration: StereoCalibration | None = None,
           overwrite: bool = False, calib_timeout_s: float = 30.0, fmt: str = "euroc",
           images: str = "png", png_level: int = 0) -> RecordStats:
    """Record `source` into the EuRoC folder `out` until `duration_s` of data, `stop`, or the source ends.

    The duration counts data time (sensor stamps), so a finite fake source records the same span however
    fast it is read; a wall-clock guard ends the recording if the source stops delivering."""
    stop = stop or threading.Event()
    stats = RecordStats()
    source.start()
    try:
        calib = calibration or _wait_calibration(source, calib_timeout_s, stop)
        end_ns: int | None = None
        last = {"imu": -1, "frame": -1}
        wall_start = time.monotonic()
        with _open_writer(out, calib, fmt, images, overwrite, png_level) as writer:
            next_flush = time.monotonic() + FLUSH_INTERVAL_S
            done = False
            compared = calibration is None
            while not stop.is_set() and not done:
                msgs = source.poll()
                if not compared and msgs:
                    compared = _other_camera(calibration, source)
                for m in msgs:
                    key = "imu" if isinstance(m, ImuSample) else "frame"
                    if duration_s is not None and last[key] < 0 and (end_ns is None or m.t_ns < end_ns):
                        # the span counts from the later of the two streams' starts (a camera that boots after the
                        # IMU would otherwise get less than asked); a source with one stream counts from it
                        end_ns = max(end_ns or 0, m.t_ns + int(duration_s * 1e9))
                    if end_ns is not None and m.t_ns > end_ns:
                        done = True
                        continue
                    if m.t_ns <= last[key]:  # EuRoC needs strictly increasing stamps per file
                        stats.dropped_out_of_order += 1
                        continue
                    if last[key] >= 0:
                        stats.note_gap("IMU" if key == "imu" else "stereo frames", m.t_ns, last[key])
                    last[key] = m.t_ns
                    if isinstance(m, ImuSample):
                        writer.write_imu(m)
                        stats.imu += 1
                        stats.last_imu_t_ns = m.t_ns
                        if stats.first_imu_t_ns is None:
                            stats.first_imu_t_ns = m.t_ns
                    elif isinstance(m, StereoFrame):
                        try:
                            writer.write_frame(m)
                        except VioError as e:  # an image cv2 could not write
                            raise RecordingWriteError(str(e)) from None
                        stats.frames += 1
                        stats.last_frame_t_ns = m.t_ns
                        if stats.first_frame_t_ns is None:
                            stats.first_frame_t_ns = m.t_ns
                now = time.monotonic()
                if now >= next_flush:  # data may stop arriving: flush on the wall clock too
                    writer.flush()
                    next_flush = now + FLUSH_INTERVAL_S
                if source.finished and not msgs:
                    break
                if duration_s is not None and now - wall_start > duration_s + 10.0:
                    log.warning("source delivered less than %.1f s of data in %.1f s of wall time; stopping",
                                duration_s, now - wall_start)
                    break
                if not msgs:
                    stop.wait(0.005)
    finally:
        stats.source_health = source.health()
        source.stop()
    return stats


def _other_camera(given: StereoCalibration, source: SensorSource) -> bool:
    """Compare the calibration file with the one the source reports itself, once it does (True then): a file of
    another camera went into the recording unsaid, every distance of its replays off by that ratio (as `vio run`
    says it: vio/app/daemon/service.py)."""
    from vio.calibration import other_camera_problem

    own = source.calibration()
    if own is None:
        return False
    problem = other_camera_problem(given, own)
    if problem:
        log.error("calibration: [source] calibration is not this %s source's camera: %s (what it reports itself); "
                  "it goes into the recording all the same: replays of it are off by that ratio unless its sensor.yaml "
                  "files are replaced with this camera's calibration", source.name, problem)
    return True


def refuse_recorded(out: str | Path, fmt: str, overwrite: bool) -> None:
    """VioError when OUT already holds recorded data (an MCAP file, a EuRoC folder's mav0/) and --overwrite is not
    given: said before the source is opened (an OAK takes seconds to start), as the writer would say after it."""
    path = Path(out)
    mav0 = path / "mav0"
    held = path.exists() if fmt == "mcap" else mav0.is_dir() and any(mav0.iterdir())
    if held and not overwrite:
        what = "exists" if fmt == "mcap" else "holds a dataset"
        raise VioError(f"{path}: already {what}; refusing to overwrite recorded data")


def refuse_unwritable(out: str | Path, fmt: str) -> None:
    """VioError when OUT cannot be written (a read-only card, a folder of another user's, a path through a file; an
    MCAP file's folder missing: its writer makes no folder), said before the source is opened: the writer failed
    once the sensors were up, saying that what was written before stays readable where nothing was."""
    from vio.io.outputs import folder_problem

    path = Path(out)
    problem = folder_problem(path.parent if fmt == "mcap" else path, made=fmt != "mcap")
    if problem:
        raise VioError(f"{out}: cannot record there: {problem}")


def _open_writer(out: str | Path, calib: StereoCalibration, fmt: str, images: str, overwrite: bool,
                 png_level: int = 0):
    """EurocWriter (a folder) or McapWriter (one file; sensors on ROS 2 schemas, `images` png/jpeg/raw)."""
    if fmt == "mcap":
        from vio.io.bag import McapWriter

        refuse_recorded(out, fmt, overwrite)
        return McapWriter(Path(out), images, calibration=calib)
    from vio.io.euroc import EurocWriter

    return EurocWriter(out, calib, flush_interval_s=FLUSH_INTERVAL_S, overwrite=overwrite, png_level=png_level)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("out", type=path_arg, help="output folder (EuRoC ASL layout: OUT/mav0/...), or with --format "
                        "mcap the MCAP file")
    parser.add_argument("--source", choices=("oak", "fake", "euroc"), help="overrides [source] kind of the config")
    parser.add_argument("--duration", type=positive_float_up_to(MAX_SECONDS), metavar="S",
                        help="seconds of data to record (default: until Ctrl-C / SIGTERM)")
    parser.add_argument("--config", metavar="FILE", help="TOML configuration ([source] section)")
    parser.add_argument("--overwrite", action="store_true", help="replace a dataset already in OUT")
    parser.add_argument("--format", choices=("euroc", "mcap"), default=None,
                        help="euroc: a folder of PNGs (default); mcap: one file OUT on ROS 2 schemas (Foxglove, "
                        "`vio replay OUT` reads it back with its calibration); default from [run] record_format")
    parser.add_argument("--images", choices=("png", "jpeg", "raw"), default=None,
                        help="mcap images: png lossless, jpeg, raw; default from [run] record_images")


def run(args: argparse.Namespace) -> int:
    import dataclasses

    from drivers.source import open_source
    from vio.calibration import load_calibration
    from vio.config import load_config

    cfg = load_config(args.config)
    src_cfg = cfg.source if args.source is None else dataclasses.replace(cfg.source, kind=args.source)
    calibration = load_calibration(src_cfg.calibration) if src_cfg.calibration else None
    if calibration is not None and src_cfg.kind in ("fake", "oak"):
        from vio.calibration import streamed_size_problem

        # the recording's sensor.yaml said 1280x800 of 320x200 images: exit 0, and `vio replay` refused it
        problem = streamed_size_problem(calibration, src_cfg.width, src_cfg.height, src_cfg.calibration)
        if problem:
            raise VioError(f"{args.config}: {problem}")
    fmt = args.format or cfg.run.record_format
    if src_cfg.kind == "euroc" and src_cfg.dataset:
        from vio.io.outputs import check_outputs

        # `vio record DATASET --overwrite` of the dataset the euroc source replays deleted its images as it read them
        # (a review's finding): never into the recording read, --overwrite or not, as `vio run`'s record_dir
        check_outputs({}, recordings=(src_cfg.dataset,),
                      folders={"the recording": str(Path(args.out) / "mav0") if fmt == "euroc" else args.out})
    try:
        if fmt == "euroc" and Path(args.out).exists() and not Path(args.out).is_dir():
            raise VioError(f"{args.out}: is a file; vio record writes a folder (EuRoC layout: OUT/mav0/...)")
        refuse_recorded(args.out, fmt, args.overwrite)
    except OSError as e:  # a name over the file system's limits: was 'internal error: OSError: File name too long'
        raise VioError(f"{args.out}: cannot record there: {e.strerror or e}") from None
    refuse_unwritable(args.out, fmt)
    if src_cfg.imu == "serial":  # else the port was retried for the whole --duration, the cameras recorded alone
        from vio.extras import require

        require("serial", "serial", '[source] imu = "serial"')
    source: Any = open_source(src_cfg)
    stop = threading.Event()

    def on_signal(signum: int) -> None:  # in a thread of its own (drivers.signals: a handler must not set stop)
        log.info("%s received: finishing the recording", signal.Signals(signum).name)
        stop.set()

    # SIGHUP too: `vio record` over ssh whose session ends was killed by it, the data since the last flush (0.56 s) lost
    # and the csv cut mid-row; it ends the recording as SIGTERM does (the daemon ignores it: it has no terminal)
    old = {s: signal.signal(s, stop_on_signal(on_signal)) for s in (signal.SIGTERM, signal.SIGINT, signal.SIGHUP)}
    try:
        log.info("recording %s source to %s%s", src_cfg.kind, args.out,
                 f" for {args.duration:g} s" if args.duration else " until SIGINT/SIGTERM")
        try:
            stats = record(source, args.out, duration_s=args.duration, stop=stop, calibration=calibration,
                           overwrite=args.overwrite, fmt=args.format or cfg.run.record_format,
                           images=args.images or cfg.run.record_images, png_level=cfg.run.record_png_level)
        except OSError as e:  # a full disk or a file size limit in the MCAP writer: an "internal error" before
            raise VioError(f"{args.out}: cannot write the recording ({e.strerror or e}): stopped; what was written "
                           "before stays readable") from None
        except RecordingWriteError as e:  # a full disk for a EuRoC folder's images: it said only 'cannot write image'
            from vio.io.outputs import storage_diagnosis

            raise VioError(f"{args.out}: cannot write the recording ({e}{storage_diagnosis(Path(args.out), str(e))}): "
                           "stopped; what was written before stays readable") from None
    finally:
        for s, h in old.items():
            signal.signal(s, h)
    lead = ""
    first = stats.leading_stream
    if first is not None:
        later = "stereo frame" if first == "IMU" else "IMU sample"
        lead = f" (from the first {later}; {first} from {stats.lead_s:.2f} s before it)"
    log.info("recorded %d stereo frames and %d IMU samples over %.2f s%s to %s (dropped: %d out of order)",
             stats.frames, stats.imu, stats.span_s, lead, args.out, stats.dropped_out_of_order)
    log.info("source health at the end: %s", stats.source_health)
    if stats.frames == 0 and stats.imu == 0:
        log.error("nothing was recorded; source health: %s", stats.source_health)
        return 1
    if stats.frames == 0 or (stats.imu == 0 and src_cfg.imu != "none"):
        # what was recorded stays on disk, but a replay needs both streams
        log.error("no %s was recorded (the %s delivered nothing): %s cannot be replayed; source health: %s",
                  "camera frame" if stats.frames == 0 else "IMU sample", "camera" if stats.frames == 0 else "IMU",
                  args.out, stats.source_health)
        return 1
    return _stream_stops(stats, args.out)


def _driver_error(health: dict, stream: str) -> str:
    """The last error the driver of `stream` reported (a combined source's camera or IMU part, else the source's)."""
    part = health.get("imu" if stream == "IMU" else "camera")
    err = (part if isinstance(part, dict) else health).get("last_error") or ""
    return f" ({err})" if err else ""


def _stream_stops(stats: RecordStats, out: str) -> int:
    """Say a stream that stopped before the end (exit 1: the recording is not what was asked, though what it holds
    is kept and replays up to there) or went silent for a while and came back (a warning: a replay resets there)."""
    stopped = stats.stopped_stream
    if stopped is not None:
        stream, early_s = stopped
        other = "stereo frames" if stream == "IMU" else "IMU"
        why = _driver_error(stats.source_health, stream)
        log.error("the %s stopped %.2f s before the end of the recording%s: the last %.2f s of %s have no %s; "
                  "what was recorded is kept, and a replay of %s uses it up to there", stream, early_s, why, early_s,
                  other, stream, out)
        return 1
    for stream, (gap_ns, t_ns) in stats.longest_gap.items():
        if gap_ns > STREAM_STOPPED_S * 1e9 and stats.start_t_ns is not None:
            log.warning("the %s had a gap of %.2f s (ending %.2f s into the recording): a replay resets there",
                        stream, gap_ns / 1e9, (t_ns - stats.start_t_ns) / 1e9)
    return 0
