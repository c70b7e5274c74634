"""Reference sender and link simulator for the serial IMU protocol.

* `imu_frames()`: a deterministic IMU signal as protocol frames (what a correct firmware sends).
* `corrupt_link()`: the same frames as a faulty link delivers them: garbage bursts, truncated frames,
  flipped bits, bursts of bytes received at the wrong baud rate. It returns which sequence numbers
  arrive intact, so tests can check that the parser recovers exactly those.
* `python -m drivers.reference_sender (--port DEV | --pty) [--rate 400] [--faults]`: streams frames in
  real time to a serial port or to a new pseudo-terminal (its path is printed), for bench tests with
  `vio record` and `[source] imu = "serial"`.

The C version for microcontroller firmware is tools/serial_imu_sender.c (byte-identical frames).
"""

from __future__ import annotations

import argparse
import contextlib
import itertools
import os
import sys
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass

import numpy as np

from drivers.fake import imu_signal
from drivers.serial_protocol import encode_imu


@dataclass(frozen=True)
class SentFrame:
    seq: int
    t_us: int
    gyro: np.ndarray
    accel: np.ndarray
    data: bytes


def imu_frames(n: int, rate_hz: float = 400.0, t0_us: int = 1_000_000, seq0: int = 0) -> Iterator[SentFrame]:
    period_us = 1e6 / rate_hz
    for k in range(n):
        gyro, accel = imu_signal(k, rate_hz)
        t_us = t0_us + int(round(k * period_us))
        seq = (seq0 + k) & 0xFFFF
        yield SentFrame(seq, t_us, gyro, accel, encode_imu(seq, t_us, gyro, accel))


@dataclass
class LinkFaults:
    """Per-frame probabilities of each fault class (independent, seeded)."""

    garbage: float = 0.05  # random bytes inserted before the frame
    truncate: float = 0.02  # frame cut short (bytes lost), the next frame follows directly
    bitflip: float = 0.02  # one bit of the frame flipped
    baud_burst: float = 0.01  # a burst of bytes as seen at a wrong baud rate (mostly 0x00/0x80/0xF8/0xFE...)


def _wrong_baud_bytes(rng: np.random.Generator, n: int) -> bytes:
    # A UART sampling at the wrong rate mostly sees framing errors that read as a few recurring patterns.
    pool = np.array([0x00, 0x80, 0xF8, 0xFE, 0xE0, 0x78, 0x1E, 0xFF, 0xA5, 0x5A], dtype=np.uint8)
    return bytes(rng.choice(pool, size=n))


def corrupt_link(frames: list[SentFrame], faults: LinkFaults, seed: int = 0) -> tuple[bytes, list[int], int]:
    """Bytes a faulty link delivers. Returns (stream, intact frame indices, number of damaged frames)."""
    rng = np.random.default_rng(seed)
    out = bytearray()
    intact: list[int] = []
    damaged = 0
    for i, f in enumerate(frames):
        if rng.random() < faults.garbage:
            out += bytes(rng.integers(0, 256, size=int(rng.integers(1, 60)), dtype=np.uint8))
        if rng.random() < faults.baud_burst:
            out += _wrong_baud_bytes(rng, int(rng.integers(5, 200)))
        data = bytearray(f.data)
        r = rng.random()
        if r < faults.truncate:
            data = data[: int(rng.integers(1, len(data)))]
            damaged += 1
        elif r < faults.truncate + faults.bitflip:
            bit = int(rng.integers(0, len(data) * 8))
            data[bit // 8] ^= 1 << (bit % 8)
            damaged += 1
        else:
            intact.append(i)
        out += data
    return bytes(out), intact, damaged


def stream_realtime(fd: int, rate_hz: float, seconds: float, faults: LinkFaults | None = None,
                    chunk_frames: int = 4, seed: int = 0, listened: Callable[[], bool] | None = None) -> int:
    """Write frames to `fd` paced in real time (chunks of `chunk_frames`, as a UART FIFO would); the
    device stamps are microseconds of time.monotonic, i.e. a device clock with zero drift. With `listened`, a chunk
    is sent only while it says a reader is there: the others are lost, as on a UART nobody reads (a pty buffered
    them, and the reader that opened it later got seconds-old frames in one burst)."""
    n = int(seconds * rate_hz)
    t_start = time.monotonic()
    t0_us = int(t_start * 1e6)
    # made as they are sent: building the default hour's 1.44 M frames first took longer than the stamps
    # allowed, sent nothing for seconds and then a burst of late frames (a QA sweep)
    frames = imu_frames(n, rate_hz, t0_us=t0_us)
    sent = 0
    for j in range(0, n, chunk_frames):
        chunk = list(itertools.islice(frames, chunk_frames))
        due = t_start + (j + len(chunk)) / rate_hz
        delay = due - time.monotonic()
        if delay > 0:
            time.sleep(delay)
        if listened is not None and not listened():
            continue
        data = corrupt_link(chunk, faults, seed + j)[0] if faults else b"".join(f.data for f in chunk)
        os.write(fd, data)
        sent += len(chunk)
    return sent


def pty_listened(master: int) -> Callable[[], bool]:
    """Whether a process has the slave side of the pty `master` open (Linux: the master polls POLLHUP while none
    has)."""
    import select

    poller = select.poll()
    poller.register(master, select.POLLHUP)

    def listened() -> bool:
        return not any(ev & select.POLLHUP for _, ev in poller.poll(0))
    return listened


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m drivers.reference_sender", description=__doc__.splitlines()[0])
    where = p.add_mutually_exclusive_group(required=True)
    where.add_argument("--port", help="serial device to write to")
    where.add_argument("--pty", action="store_true", help="create a pseudo-terminal and print its path")
    p.add_argument("--baud", type=int, default=921600)
    p.add_argument("--rate", type=float, default=400.0, help="IMU rate [Hz]")
    p.add_argument("--seconds", type=float, default=3600.0)
    p.add_argument("--faults", action="store_true", help="inject garbage, truncation, bit flips")
    args = p.parse_args(argv)
    if args.pty:
        import tty

        master, slave = os.openpty()
        tty.setraw(slave)
        print(os.ttyname(slave), flush=True)
        os.close(slave)  # only a reader holds it open: the frames go out while one does (pty_listened)
        fd = master
        listened = pty_listened(master)
    else:
        from vio.extras import require

        serial = require("serial", "serial", "the reference sender on a serial port")
        ser = serial.Serial(args.port, args.baud)
        fd = ser.fileno()
        listened = None
    with contextlib.suppress(KeyboardInterrupt):
        stream_realtime(fd, args.rate, args.seconds, LinkFaults() if args.faults else None, listened=listened)
    return 0


if __name__ == "__main__":
    sys.exit(main())
