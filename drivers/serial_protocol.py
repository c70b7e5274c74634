"""Kestrel serial IMU frame protocol (see docs/serial-imu.md): encoder and a resynchronising parser.

Frame (little endian)::

    0xA5 0x5A | len u8 | type u8 | seq u16 | payload (len bytes) | crc u16

`crc` is CRC-16/CCITT-FALSE (poly 0x1021, init 0xFFFF; `binascii.crc_hqx(data, 0xFFFF)`) over
len, type, seq and payload. Type 0x01 (IMU) payload, 32 bytes: t_us u64 (device clock, microseconds),
gyro x,y,z i32 [1e-6 rad/s], accel x,y,z i32 [1e-5 m/s^2] in the IMU (= body) frame.

The parser never raises on bad bytes: it counts them. A candidate frame whose CRC fails is dropped by
advancing ONE byte (not the whole claimed length), because the sync word may have been garbage and the
real next frame may start inside the bytes that the bogus length covered. Unknown frame types are
rejected like garbage (a new type needs a parser that knows its length), so a fake sync word can never
make the parser wait for a long bogus frame and delay the good ones behind it.
"""

from __future__ import annotations

import binascii
import struct
from dataclasses import dataclass

import numpy as np

SYNC = b"\xa5\x5a"
TYPE_IMU = 0x01
_HEADER = struct.Struct("<2sBBH")  # sync, len, type, seq
_IMU = struct.Struct("<Q3i3i")
HEADER_SIZE = _HEADER.size  # 6
CRC_SIZE = 2
IMU_PAYLOAD_SIZE = _IMU.size  # 32
IMU_FRAME_SIZE = HEADER_SIZE + IMU_PAYLOAD_SIZE + CRC_SIZE  # 40
GYRO_LSB_RAD_S = 1e-6
ACCEL_LSB_M_S2 = 1e-5
PAYLOAD_SIZES = {TYPE_IMU: IMU_PAYLOAD_SIZE}  # known types and their exact payload length
_I32 = (-(2**31), 2**31 - 1)


def crc16(data: bytes) -> int:
    """CRC-16/CCITT-FALSE, the checksum of the frame."""
    return binascii.crc_hqx(data, 0xFFFF)


@dataclass(frozen=True)
class RawImu:
    """One decoded IMU frame, still on the device clock."""

    seq: int
    t_us: int
    gyro: np.ndarray  # rad/s
    accel: np.ndarray  # m/s^2


def encode_imu(seq: int, t_us: int, gyro_rad_s: np.ndarray, accel_m_s2: np.ndarray) -> bytes:
    """One complete IMU frame; values beyond the int32 range saturate (as a real sensor would clip)."""
    g = np.clip(np.round(np.asarray(gyro_rad_s, float) / GYRO_LSB_RAD_S), *_I32).astype(np.int64)
    a = np.clip(np.round(np.asarray(accel_m_s2, float) / ACCEL_LSB_M_S2), *_I32).astype(np.int64)
    payload = _IMU.pack(int(t_us) & 0xFFFFFFFFFFFFFFFF, *map(int, g), *map(int, a))
    body = struct.pack("<BBH", len(payload), TYPE_IMU, seq & 0xFFFF) + payload
    return SYNC + body + struct.pack("<H", crc16(body))


@dataclass
class ParserStats:
    """Every byte the parser sees ends up either in a good frame or in one of these error classes."""

    bytes_in: int = 0
    frames_ok: int = 0
    bytes_discarded: int = 0  # garbage skipped while looking for a sync word
    crc_errors: int = 0  # candidate frames whose CRC failed (corruption, truncation, fake sync)
    bad_length: int = 0  # length byte impossible for the frame type
    unknown_type: int = 0  # sync word followed by a type byte we do not know (garbage or a newer sender)
    seq_lost: int = 0  # frames missing according to the sequence counter (lost or corrupted in transit)
    seq_resets: int = 0  # sequence went backwards by a lot (sender restarted)

    def as_dict(self) -> dict[str, int]:
        return dict(self.__dict__)


class FrameParser:
    """Incremental parser: feed() any chunk of bytes, get the complete, CRC-valid IMU frames back."""

    def __init__(self) -> None:
        self._buf = bytearray()
        self._last_seq: int | None = None
        self.stats = ParserStats()

    def feed(self, data: bytes) -> list[RawImu]:
        self.stats.bytes_in += len(data)
        self._buf += data
        out: list[RawImu] = []
        buf = self._buf
        pos = 0
        n = len(buf)
        while True:
            k = buf.find(SYNC, pos)
            if k < 0:
                # keep a trailing 0xA5: it may be the first half of a sync word split across reads
                keep = 1 if n > pos and buf[n - 1] == SYNC[0] else 0
                self.stats.bytes_discarded += n - pos - keep
                pos = n - keep
                break
            self.stats.bytes_discarded += k - pos
            pos = k
            if n - pos < HEADER_SIZE:
                break
            _, length, ftype, seq = _HEADER.unpack_from(buf, pos)
            want = PAYLOAD_SIZES.get(ftype)
            if want is None:
                # not waiting for a length we cannot check: a fake sync in garbage would stall the stream
                self.stats.unknown_type += 1
                self.stats.bytes_discarded += 1
                pos += 1
                continue
            if length != want:
                self.stats.bad_length += 1
                self.stats.bytes_discarded += 1
                pos += 1
                continue
            end = pos + HEADER_SIZE + length + CRC_SIZE
            if end > n:
                break  # incomplete: wait for more bytes
            (crc,) = struct.unpack_from("<H", buf, end - CRC_SIZE)
            if crc != crc16(bytes(buf[pos + 2:end - CRC_SIZE])):
                self.stats.crc_errors += 1
                self.stats.bytes_discarded += 1
                pos += 1
                continue
            self._count_seq(seq)
            t_us, gx, gy, gz, ax, ay, az = _IMU.unpack_from(buf, pos + HEADER_SIZE)
            out.append(RawImu(seq, t_us, np.array([gx, gy, gz]) * GYRO_LSB_RAD_S,
                              np.array([ax, ay, az]) * ACCEL_LSB_M_S2))
            self.stats.frames_ok += 1
            pos = end
        del buf[:pos]
        return out

    def _count_seq(self, seq: int) -> None:
        if self._last_seq is not None:
            gap = (seq - self._last_seq - 1) & 0xFFFF
            if gap > 0x8000:  # went backwards: sender restarted, not 60000 lost frames
                self.stats.seq_resets += 1
            else:
                self.stats.seq_lost += gap
        self._last_seq = seq
