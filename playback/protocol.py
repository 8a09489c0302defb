"""USB packet format between the player and the stimulator controller (see docs/usb-protocol.md).

All multi-byte fields are little-endian. A frame packet is a 24-byte header, the 40 Hz codes,
the 320 Hz codes (uint16 per channel, in device channel order) and a CRC-32 (``zlib.crc32``)
of everything before it. The status reply (vendor control IN request) is 28 bytes.
"""
from __future__ import annotations

import struct
import zlib
from dataclasses import dataclass

import numpy as np

MAGIC_FRAME = b"HPTX"
MAGIC_STATUS = b"HPTS"
VERSION = 1
TYPE_FRAME = 0x01
FLAG_RESYNC = 0x0001  # first frame of a stream: the controller accepts any sequence number

# magic, version, type, n_channels, sequence, frame_us, ttl_us, flags, reserved
_HEADER = struct.Struct("<4sBBHIIIHH")
HEADER_SIZE = _HEADER.size  # 24
CRC_SIZE = 4

# Vendor control request for the status (bmRequestType 0xC0: IN, vendor, device).
STATUS_REQUEST_TYPE = 0xC0
STATUS_REQUEST = 0x01
# magic, version, state, n_channels, last_sequence, frames_accepted, bad_checksum,
# bad_sequence, ttl_expired, reserved
_STATUS = struct.Struct("<4sBBHIIHHHH")
STATUS_SIZE = _STATUS.size + CRC_SIZE  # 28

STATE_IDLE = 0  # no frame received since power-up
STATE_PLAYING = 1  # a valid frame is being played
STATE_EXPIRED = 2  # the last frame's time-to-live ran out: all outputs at 0
STATE_NAMES = {STATE_IDLE: "idle", STATE_PLAYING: "playing", STATE_EXPIRED: "expired"}


class ProtocolError(ValueError):
    """A packet that does not decode (bad magic, version, length or checksum)."""


def frame_size(n_channels: int) -> int:
    """Bytes in a frame packet for `n_channels` channels."""
    return HEADER_SIZE + 4 * n_channels + CRC_SIZE


@dataclass(frozen=True)
class FramePacket:
    """A decoded frame packet."""

    sequence: int
    frame_us: int
    ttl_us: int
    flags: int
    codes40: np.ndarray
    codes320: np.ndarray


@dataclass(frozen=True)
class Status:
    """A decoded status reply."""

    state: int
    n_channels: int
    last_sequence: int
    frames_accepted: int
    bad_checksum: int
    bad_sequence: int
    ttl_expired: int

    @property
    def state_name(self) -> str:
        """``idle``, ``playing`` or ``expired``."""
        return STATE_NAMES.get(self.state, f"unknown({self.state})")


def encode_frame(sequence: int, frame_us: int, ttl_us: int, codes40: np.ndarray, codes320: np.ndarray,
                 flags: int = 0) -> bytes:
    """Build a frame packet.

    Parameters
    ----------
    sequence : int
        Frame counter, uint32 (wraps).
    frame_us, ttl_us : int
        Frame duration and time-to-live in µs (uint32).
    codes40, codes320 : ndarray of uint16, shape (n_channels,)
        DAC codes per device channel.
    flags : int
        ``FLAG_RESYNC`` on the first frame of a stream.
    """
    c40 = np.asarray(codes40, dtype="<u2")
    c320 = np.asarray(codes320, dtype="<u2")
    if c40.ndim != 1 or c40.shape != c320.shape:
        raise ValueError(f"codes must be two 1-D arrays of equal length, got {c40.shape} and {c320.shape}")
    header = _HEADER.pack(MAGIC_FRAME, VERSION, TYPE_FRAME, c40.size, sequence & 0xFFFFFFFF,
                          int(frame_us), int(ttl_us), flags, 0)
    body = header + c40.tobytes() + c320.tobytes()
    return body + struct.pack("<I", zlib.crc32(body))


def decode_frame(packet: bytes | bytearray | memoryview) -> FramePacket:
    """Decode and verify a frame packet; raises :class:`ProtocolError`."""
    data = bytes(packet)
    if len(data) < HEADER_SIZE + CRC_SIZE:
        raise ProtocolError(f"packet too short ({len(data)} bytes)")
    magic, version, ptype, n, seq, frame_us, ttl_us, flags, _ = _HEADER.unpack_from(data)
    if magic != MAGIC_FRAME:
        raise ProtocolError(f"bad magic {magic!r}")
    if version != VERSION:
        raise ProtocolError(f"unsupported protocol version {version}")
    if ptype != TYPE_FRAME:
        raise ProtocolError(f"unknown packet type {ptype:#04x}")
    if len(data) != frame_size(n):
        raise ProtocolError(f"length {len(data)} does not match {n} channels ({frame_size(n)} bytes)")
    (crc,) = struct.unpack_from("<I", data, len(data) - CRC_SIZE)
    if crc != zlib.crc32(data[:-CRC_SIZE]):
        raise ProtocolError("checksum mismatch")
    codes = np.frombuffer(data, dtype="<u2", count=2 * n, offset=HEADER_SIZE)
    return FramePacket(seq, frame_us, ttl_us, flags, codes[:n].astype(np.uint16), codes[n:].astype(np.uint16))


def split_packets(stream: bytes) -> list[bytes]:
    """Split concatenated frame packets (a file sink's output) using each header's length."""
    out = []
    pos = 0
    while pos < len(stream):
        if len(stream) - pos < HEADER_SIZE:
            raise ProtocolError(f"truncated header at byte {pos}")
        n = _HEADER.unpack_from(stream, pos)[3]
        size = frame_size(n)
        if len(stream) - pos < size:
            raise ProtocolError(f"truncated packet at byte {pos}")
        out.append(stream[pos:pos + size])
        pos += size
    return out


def encode_status(status: Status) -> bytes:
    """Build a status reply (controller side; used by the emulator)."""
    body = _STATUS.pack(MAGIC_STATUS, VERSION, status.state, status.n_channels,
                        status.last_sequence & 0xFFFFFFFF, status.frames_accepted & 0xFFFFFFFF,
                        min(status.bad_checksum, 0xFFFF), min(status.bad_sequence, 0xFFFF),
                        min(status.ttl_expired, 0xFFFF), 0)
    return body + struct.pack("<I", zlib.crc32(body))


def decode_status(reply: bytes | bytearray | memoryview) -> Status:
    """Decode and verify a status reply; raises :class:`ProtocolError`."""
    data = bytes(reply)
    if len(data) != STATUS_SIZE:
        raise ProtocolError(f"status reply has {len(data)} bytes, expected {STATUS_SIZE}")
    (crc,) = struct.unpack_from("<I", data, STATUS_SIZE - CRC_SIZE)
    if crc != zlib.crc32(data[:-CRC_SIZE]):
        raise ProtocolError("status checksum mismatch")
    magic, version, state, n, last, accepted, bad_crc, bad_seq, expired, _ = _STATUS.unpack_from(data)
    if magic != MAGIC_STATUS or version != VERSION:
        raise ProtocolError(f"bad status magic/version {magic!r}/{version}")
    return Status(state, n, last, accepted, bad_crc, bad_seq, expired)
