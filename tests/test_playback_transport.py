"""One conformance suite for every transport, plus the USB faults (emulator through pyusb)."""
from __future__ import annotations

import numpy as np
import pytest

from playback import protocol
from playback.clock import VirtualClock
from playback.device import load_profile
from playback.emulator import ControllerEmulator, EmulatorBackend
from playback.errors import DeviceError
from playback.transport import FileSink, NullSink, UsbTransport, make_transport

PROFILE = load_profile(None)


def frames(n, start=0):
    return [protocol.encode_frame(start + k, 25000, 50000, np.full(24, k, np.uint16), np.full(24, 2 * k, np.uint16),
                                  protocol.FLAG_RESYNC if start + k == 0 else 0) for k in range(n)]


@pytest.fixture(params=["null", "file", "sim"])
def transport_case(request, tmp_path):
    """(transport, function returning the packets that reached the far side or None, clock)."""
    clock = VirtualClock()
    if request.param == "null":
        return NullSink(), lambda: None, clock
    if request.param == "file":
        path = tmp_path / "packets.bin"
        return FileSink(path), lambda: protocol.split_packets(path.read_bytes()), clock
    tr, emu = make_transport("sim", PROFILE, clock)
    return tr, lambda: emu.raw, clock


def test_conformance_send_in_order(transport_case):
    tr, received, clock = transport_case
    pkts = frames(10)
    with tr:
        for p in pkts:
            tr.send(p)
            clock.advance(0.025)
        assert tr.packets_sent == 10
        st = tr.status()
        if st is not None:  # a controller answers with what it accepted
            assert st.frames_accepted == 10 and st.last_sequence == 9 and st.bad_checksum == 0
            assert st.state_name == "playing"
    got = received()
    if got is not None:
        assert got == pkts
    assert not tr.is_open


def test_conformance_send_before_open_and_close_twice(transport_case):
    tr, _, _ = transport_case
    with pytest.raises(DeviceError):
        tr.send(frames(1)[0])
    tr.open()
    tr.close()
    tr.close()


def sim(clock=None, retries=2, timeout_ms=10):
    clock = clock or VirtualClock()
    emu = ControllerEmulator(24, clock=clock)
    tr = UsbTransport(0x1209, 0x0001, backend=EmulatorBackend(emu), retries=retries, timeout_ms=timeout_ms, name="sim")
    return tr, emu, clock


def test_device_absent_lists_found_devices():
    tr, emu, _ = sim()
    tr.vendor_id = 0x1234  # the emulator enumerates as 1209:0001
    with pytest.raises(DeviceError) as info:
        tr.open()
    assert "1234:0001 not found" in str(info.value) and "1209:0001" in str(info.value)
    emu.unplug()
    with pytest.raises(DeviceError, match="no USB devices found"):
        tr.open()


def test_real_usb_absent_is_clear():
    # No stimulator on a test machine: real libusb (or its absence) must give one clear line.
    tr = UsbTransport(0x1209, 0x0001)
    with pytest.raises(DeviceError) as info:
        tr.open()
    msg = str(info.value)
    assert ("not found" in msg or "libusb is not available" in msg) and "\n" not in msg


def test_unplugged_mid_stream():
    tr, emu, _ = sim()
    tr.open()
    for p in frames(3):
        tr.send(p)
    emu.unplug()
    with pytest.raises(DeviceError, match="disconnected .* after 3 frames"):
        tr.send(frames(1, 3)[0])
    tr.close()  # must not raise on a vanished device


def test_timeouts_retry_bounded_then_stop():
    tr, emu, clock = sim(retries=2, timeout_ms=10)
    tr.open()
    emu.inject("timeout", 2)  # two timeouts, the third attempt gets through
    tr.send(frames(1)[0])
    assert tr.retries == 2 and len(emu.frames) == 1
    assert clock.now() == pytest.approx(0.020)  # the host waited two timeouts
    emu.inject("timeout", 3)  # more than the retries allow
    with pytest.raises(DeviceError, match="timed out .* gave up after 3 attempts"):
        tr.send(frames(1, 1)[0])
    assert clock.now() == pytest.approx(0.050)  # bounded: 3 x 10 ms, then stop


def test_stall_is_cleared_and_retried():
    tr, emu, _ = sim()
    tr.open()
    emu.inject("stall", 1)
    tr.send(frames(1)[0])
    assert not emu.halted and len(emu.frames) == 1 and tr.retries == 1
    emu.inject("stall", 5)
    with pytest.raises(DeviceError, match="stalled"):
        tr.send(frames(1, 1)[0])


def test_short_write_retried():
    tr, emu, _ = sim()
    tr.open()
    emu.inject("short", 1)
    tr.send(frames(1)[0])
    assert emu.bad_checksum == 1 and len(emu.frames) == 1


def test_emulator_sequence_checksum_ttl():
    clock = VirtualClock()
    emu = ControllerEmulator(24, clock=clock)
    p = frames(4)
    assert emu.receive(p[0]) and emu.receive(p[1])
    assert not emu.receive(p[1])          # duplicate: rejected
    old = protocol.encode_frame(0, 25000, 50000, np.zeros(24, np.uint16), np.zeros(24, np.uint16))
    assert not emu.receive(old)           # older (no resync flag): rejected
    assert emu.receive(p[3])              # gap: played, counted
    bad = bytearray(p[2])
    bad[30] ^= 1
    assert not emu.receive(bytes(bad))
    st = emu.status()
    assert (st.bad_sequence, st.bad_checksum, st.frames_accepted) == (3, 1, 3)
    # TTL: 50 ms after the last frame everything is off.
    clock.advance(0.049)
    assert emu.status().state_name == "playing" and emu.codes_at(clock.now())[0][5] == 3
    clock.advance(0.002)
    assert emu.status().state_name == "expired" and not emu.codes_at(clock.now())[0].any()


def test_emulator_waveform_amplitudes():
    clock = VirtualClock()
    emu = ControllerEmulator(2, clock=clock, dac_bits=12, full_scale_v_rms=40.0)
    code40, code320 = 1024, 512
    emu.receive(protocol.encode_frame(0, 25000, 50000, np.array([code40, 0], np.uint16),
                                      np.array([0, code320], np.uint16), protocol.FLAG_RESYNC))
    t, volts = emu.synthesise(0.0, 0.1, 8000.0)
    v_code = 40.0 / 4095
    on = t < 0.05  # TTL 50 ms, no further frame
    # Channel 0: pure 40 Hz at V rms = code * v_code over the 50 ms it plays (2 periods).
    rms0 = np.sqrt(np.mean(volts[on, 0].astype(np.float64) ** 2))
    assert rms0 == pytest.approx(code40 * v_code, rel=1e-3)
    spec = np.abs(np.fft.rfft(volts[on, 1]))
    freqs = np.fft.rfftfreq(int(on.sum()), 1 / 8000.0)
    assert freqs[np.argmax(spec)] == pytest.approx(320.0)
    assert not volts[~on].any()  # silent after the time-to-live
