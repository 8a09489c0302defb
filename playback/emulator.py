"""An emulated stimulator controller, reachable through pyusb as a custom backend.

:class:`ControllerEmulator` behaves as the controller described in docs/usb-protocol.md: it
decodes frame packets, rejects bad checksums and stale sequence numbers, plays each valid frame
until the next one arrives or its time-to-live runs out (then all outputs are 0), answers the
status request, and can synthesise the drive waveforms (40 Hz + 320 Hz sines per channel).

:class:`EmulatorBackend` implements ``usb.backend.IBackend`` so that ``usb.core.find`` finds the
emulated device and the player's real pyusb code path (find, set_configuration, write,
ctrl_transfer, clear_halt) is exercised in tests. Faults can be injected: write timeouts,
endpoint stalls, and unplugging.
"""
from __future__ import annotations

import errno
from collections import deque
from dataclasses import dataclass
from types import SimpleNamespace
from typing import Any

import numpy as np
import usb.backend
import usb.core

from playback import protocol
from playback.clock import MonotonicClock, VirtualClock

_NO_DEVICE = (-4, errno.ENODEV, "No such device (it may have been disconnected)")
_PIPE = (-9, errno.EPIPE, "Pipe error")
_TIMEOUT = (-7, errno.ETIMEDOUT, "Operation timed out")


@dataclass
class AcceptedFrame:
    """A frame the controller accepted, with its arrival time on the emulator's clock."""

    arrival_s: float
    sequence: int
    frame_us: int
    ttl_us: int
    codes40: np.ndarray
    codes320: np.ndarray


class ControllerEmulator:
    """The controller's behaviour, independent of USB plumbing.

    Parameters
    ----------
    n_channels : int
        Output channels.
    vendor_id, product_id : int
        Ids it enumerates with.
    clock : VirtualClock or MonotonicClock
        Timestamps arrivals (the player's clock, so TTL is judged on the same time axis).
    dac_bits, full_scale_v_rms : int, float
        DAC scaling for the synthesised waveforms (V rms at the largest code).
    interface, endpoint_out : int
        bInterfaceNumber and the bulk OUT endpoint number.
    """

    def __init__(self, n_channels: int, *, vendor_id: int = 0x1209, product_id: int = 0x0001,
                 clock: VirtualClock | MonotonicClock | None = None, dac_bits: int = 12,
                 full_scale_v_rms: float = 40.0, interface: int = 0, endpoint_out: int = 1) -> None:
        self.n_channels = n_channels
        self.vendor_id = vendor_id
        self.product_id = product_id
        self.clock = clock or MonotonicClock()
        self.volts_per_code = full_scale_v_rms / ((1 << dac_bits) - 1)
        self.interface = interface
        self.endpoint_address = endpoint_out & 0x0F  # OUT direction bit is 0
        self.plugged = True
        self.halted = False
        self.frames: list[AcceptedFrame] = []
        self.raw: list[bytes] = []  # every packet received, valid or not
        self.bad_checksum = 0
        self.bad_sequence = 0
        self.ttl_expired = 0
        self._last_seq: int | None = None
        self._faults: deque[str] = deque()
        self.writes = 0

    # -- fault injection -------------------------------------------------------------------
    def inject(self, kind: str, count: int = 1) -> None:
        """Make the next `count` bulk writes fail: ``"timeout"``, ``"stall"`` or ``"short"``."""
        if kind not in {"timeout", "stall", "short"}:
            raise ValueError(f"unknown fault {kind!r}")
        self._faults.extend([kind] * count)

    def unplug(self) -> None:
        """The cable is pulled: every later USB call fails with 'no such device'."""
        self.plugged = False

    def replug(self) -> None:
        """Plug back in (a fresh enumeration is needed, as on real hardware)."""
        self.plugged = True

    # -- controller behaviour --------------------------------------------------------------
    def receive(self, data: bytes) -> bool:
        """Process one packet as the controller firmware would; True if it was accepted."""
        now = self.clock.now()
        self.raw.append(bytes(data))
        try:
            pkt = protocol.decode_frame(data)
        except protocol.ProtocolError:
            self.bad_checksum += 1
            return False
        if pkt.codes40.size != self.n_channels:
            self.bad_checksum += 1
            return False
        if self._last_seq is not None and not pkt.flags & protocol.FLAG_RESYNC:
            step = (pkt.sequence - self._last_seq) & 0xFFFFFFFF
            if step == 0 or step >= 1 << 31:  # duplicate or older: never replay stale output
                self.bad_sequence += 1
                return False
            if step > 1:  # frames lost in between: play this one, count the gap
                self.bad_sequence += 1
        if self.frames:
            prev = self.frames[-1]
            if now > prev.arrival_s + prev.ttl_us * 1e-6:
                self.ttl_expired += 1
        self._last_seq = pkt.sequence
        self.frames.append(AcceptedFrame(now, pkt.sequence, pkt.frame_us, pkt.ttl_us, pkt.codes40, pkt.codes320))
        return True

    def state(self) -> int:
        """``STATE_IDLE``, ``STATE_PLAYING`` or ``STATE_EXPIRED`` at the current time."""
        if not self.frames:
            return protocol.STATE_IDLE
        last = self.frames[-1]
        if self.clock.now() > last.arrival_s + last.ttl_us * 1e-6:
            return protocol.STATE_EXPIRED
        return protocol.STATE_PLAYING

    def status(self) -> protocol.Status:
        """The status the controller reports now."""
        state = self.state()
        expired = self.ttl_expired + (1 if state == protocol.STATE_EXPIRED else 0)
        return protocol.Status(state, self.n_channels, self._last_seq or 0, len(self.frames),
                               self.bad_checksum, self.bad_sequence, expired)

    def codes_at(self, t_s: float) -> tuple[np.ndarray, np.ndarray]:
        """DAC codes being output at time `t_s` (zeros before the first frame or after TTL)."""
        arrivals = np.array([f.arrival_s for f in self.frames])
        k = int(np.searchsorted(arrivals, t_s, side="right")) - 1
        zeros = np.zeros(self.n_channels, np.uint16)
        if k < 0:
            return zeros, zeros
        f = self.frames[k]
        if t_s > f.arrival_s + f.ttl_us * 1e-6:
            return zeros, zeros
        return f.codes40, f.codes320

    def synthesise(self, t_start_s: float, t_end_s: float, rate_hz: float = 8000.0
                   ) -> tuple[np.ndarray, np.ndarray]:
        """Drive waveforms (V) per channel: ``sqrt2 (V40 sin 2pi40t + V320 sin 2pi320t)``.

        Each frame is played from its arrival until the next arrival or its TTL, whichever is
        first; the sines' phase runs on the absolute time axis (no clicks between frames).

        Returns
        -------
        t_s : ndarray, shape (n_samples,)
        volts : ndarray of float32, shape (n_samples, n_channels)
        """
        n = max(0, int(np.floor((t_end_s - t_start_s) * rate_hz)))
        t = t_start_s + np.arange(n) / rate_hz
        out = np.zeros((n, self.n_channels), dtype=np.float32)
        if not self.frames or n == 0:
            return t, out
        arrivals = np.array([f.arrival_s for f in self.frames])
        expiry = arrivals + np.array([f.ttl_us for f in self.frames]) * 1e-6
        k = np.searchsorted(arrivals, t, side="right") - 1
        active = (k >= 0) & (t <= expiry[np.maximum(k, 0)])
        c40 = np.stack([f.codes40 for f in self.frames]).astype(np.float64) * self.volts_per_code
        c320 = np.stack([f.codes320 for f in self.frames]).astype(np.float64) * self.volts_per_code
        kk = np.maximum(k, 0)
        s40 = np.sin(2 * np.pi * 40.0 * t)[:, None]
        s320 = np.sin(2 * np.pi * 320.0 * t)[:, None]
        wave = np.sqrt(2.0) * (c40[kk] * s40 + c320[kk] * s320)
        out[:] = np.where(active[:, None], wave, 0.0)
        return t, out

    # -- USB endpoint side -----------------------------------------------------------------
    def _raise(self, err: tuple[int, int, str], cls: type = usb.core.USBError) -> None:
        code, eno, text = err
        raise cls(text, code, eno)

    def check_plugged(self) -> None:
        """Raise 'no such device' if unplugged."""
        if not self.plugged:
            self._raise(_NO_DEVICE)

    def bulk_write(self, endpoint: int, data: bytes, timeout_ms: int) -> int:
        """What the bulk OUT endpoint does with one transfer (may raise injected faults)."""
        self.check_plugged()
        self.writes += 1
        if (endpoint & 0x7F) != self.endpoint_address:
            self._raise(_PIPE)
        if self.halted:
            self._raise(_PIPE)
        if self._faults:
            fault = self._faults.popleft()
            if fault == "timeout":
                # The host waits the whole timeout before giving up.
                if getattr(self.clock, "virtual", False):
                    self.clock.advance(timeout_ms * 1e-3)
                else:
                    self.clock.sleep_until(self.clock.now() + timeout_ms * 1e-3)
                self._raise(_TIMEOUT, usb.core.USBTimeoutError)
            if fault == "stall":
                self.halted = True
                self._raise(_PIPE)
            if fault == "short":
                n = max(0, len(data) - 8)  # the tail never arrived: the truncated packet fails its CRC
                self.receive(data[:n])
                return n
        self.receive(data)
        return len(data)


def _descriptor(**fields: Any) -> SimpleNamespace:
    return SimpleNamespace(extra_descriptors=[], **fields)


class EmulatorBackend(usb.backend.IBackend):
    """A pyusb backend whose only device is a :class:`ControllerEmulator`."""

    def __init__(self, emulator: ControllerEmulator) -> None:
        super().__init__()
        self.emulator = emulator

    def enumerate_devices(self):  # noqa: D102 (IBackend API)
        if self.emulator.plugged:
            yield self.emulator

    def get_parent(self, dev):  # noqa: D102
        return None

    def get_device_descriptor(self, dev):  # noqa: D102
        return SimpleNamespace(
            bLength=18, bDescriptorType=1, bcdUSB=0x0200, bDeviceClass=0, bDeviceSubClass=0,
            bDeviceProtocol=0, bMaxPacketSize0=64, idVendor=dev.vendor_id, idProduct=dev.product_id,
            bcdDevice=0x0100, iManufacturer=0, iProduct=0, iSerialNumber=0, bNumConfigurations=1,
            address=1, bus=1, port_number=1, port_numbers=(1,), speed=3)

    def get_configuration_descriptor(self, dev, config):  # noqa: D102
        if config != 0:
            raise IndexError("no such configuration")
        return _descriptor(bLength=9, bDescriptorType=2, wTotalLength=25, bNumInterfaces=1,
                           bConfigurationValue=1, iConfiguration=0, bmAttributes=0x80, bMaxPower=50)

    def get_interface_descriptor(self, dev, intf, alt, config):  # noqa: D102
        if intf != 0 or alt != 0 or config != 0:
            raise IndexError("no such interface")
        return _descriptor(bLength=9, bDescriptorType=4, bInterfaceNumber=dev.interface,
                           bAlternateSetting=0, bNumEndpoints=1, bInterfaceClass=0xFF,
                           bInterfaceSubClass=0, bInterfaceProtocol=0, iInterface=0)

    def get_endpoint_descriptor(self, dev, ep, intf, alt, config):  # noqa: D102
        if ep != 0 or intf != 0 or alt != 0 or config != 0:
            raise IndexError("no such endpoint")
        return _descriptor(bLength=7, bDescriptorType=5, bEndpointAddress=dev.endpoint_address,
                           bmAttributes=0x02, wMaxPacketSize=512, bInterval=0, bRefresh=0, bSynchAddress=0)

    def open_device(self, dev):  # noqa: D102
        dev.check_plugged()
        return dev

    def close_device(self, dev_handle):  # noqa: D102
        pass

    def set_configuration(self, dev_handle, config_value):  # noqa: D102
        dev_handle.check_plugged()

    def get_configuration(self, dev_handle):  # noqa: D102
        dev_handle.check_plugged()
        return 1

    def set_interface_altsetting(self, dev_handle, intf, altsetting):  # noqa: D102
        dev_handle.check_plugged()

    def claim_interface(self, dev_handle, intf):  # noqa: D102
        dev_handle.check_plugged()

    def release_interface(self, dev_handle, intf):  # noqa: D102
        dev_handle.check_plugged()

    def is_kernel_driver_active(self, dev_handle, intf):  # noqa: D102
        return False

    def bulk_write(self, dev_handle, ep, intf, data, timeout):  # noqa: D102
        return dev_handle.bulk_write(ep, bytes(data), timeout)

    def ctrl_transfer(self, dev_handle, bmRequestType, bRequest, wValue, wIndex, data, timeout):  # noqa: D102,N803
        dev_handle.check_plugged()
        if bmRequestType == protocol.STATUS_REQUEST_TYPE and bRequest == protocol.STATUS_REQUEST:
            reply = protocol.encode_status(dev_handle.status())
            n = min(len(reply), len(data))
            data[:n] = type(data)(data.typecode, reply[:n])
            return n
        dev_handle._raise(_PIPE)  # unknown request: the device stalls endpoint 0

    def clear_halt(self, dev_handle, ep):  # noqa: D102
        dev_handle.check_plugged()
        dev_handle.halted = False

    def reset_device(self, dev_handle):  # noqa: D102
        dev_handle.check_plugged()
