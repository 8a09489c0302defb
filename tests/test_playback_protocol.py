"""Packet format: round trips, and every corruption is caught by the checksum."""
from __future__ import annotations

import struct

import numpy as np
import pytest

from playback import protocol


def test_frame_roundtrip_and_size():
    c40 = np.arange(24, dtype=np.uint16) * 170
    c320 = np.arange(24, dtype=np.uint16)[::-1] * 3
    pkt = protocol.encode_frame(0xFFFFFFFF + 5, 25000, 50000, c40, c320, protocol.FLAG_RESYNC)
    assert len(pkt) == protocol.frame_size(24) == 24 + 96 + 4
    assert pkt[:4] == b"HPTX" and pkt[4] == 1 and pkt[5] == 1
    assert struct.unpack_from("<H", pkt, 6)[0] == 24
    f = protocol.decode_frame(pkt)
    assert f.sequence == 4 and f.frame_us == 25000 and f.ttl_us == 50000 and f.flags == protocol.FLAG_RESYNC
    np.testing.assert_array_equal(f.codes40, c40)
    np.testing.assert_array_equal(f.codes320, c320)
    # Codes sit little-endian right after the header.
    assert struct.unpack_from("<H", pkt, 24 + 2)[0] == 170


def test_every_single_byte_corruption_detected():
    pkt = bytearray(protocol.encode_frame(7, 25000, 50000, np.full(4, 1000, np.uint16), np.full(4, 9, np.uint16)))
    for i in range(len(pkt)):
        bad = bytearray(pkt)
        bad[i] ^= 0x5A
        with pytest.raises(protocol.ProtocolError):
            protocol.decode_frame(bytes(bad))
    with pytest.raises(protocol.ProtocolError, match="length"):
        protocol.decode_frame(bytes(pkt) + b"\0")


def test_status_roundtrip_and_split():
    st = protocol.Status(protocol.STATE_EXPIRED, 24, 1234, 1200, 3, 2, 1)
    raw = protocol.encode_status(st)
    assert len(raw) == protocol.STATUS_SIZE == 28
    assert protocol.decode_status(raw) == st
    with pytest.raises(protocol.ProtocolError):
        protocol.decode_status(raw[:-1] + bytes([raw[-1] ^ 1]))
    pkts = [protocol.encode_frame(k, 25000, 50000, np.full(3, k, np.uint16), np.zeros(3, np.uint16)) for k in range(5)]
    assert protocol.split_packets(b"".join(pkts)) == pkts
    with pytest.raises(protocol.ProtocolError, match="truncated"):
        protocol.split_packets(b"".join(pkts)[:-3])
