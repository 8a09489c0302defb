"""Where frame packets go: a USB device through pyusb (real or emulated), a file, or nowhere.

Every transport has the same small interface (``open``, ``send``, ``status``, ``close``) and one
conformance test suite runs against all of them. USB faults map to :class:`DeviceError` with one
line: device absent (listing the devices found), unplugged, and timeouts or stalls that persist
past the bounded retries.
"""
from __future__ import annotations

import errno
import logging
from pathlib import Path
from typing import Any

from playback import protocol
from playback.errors import DeviceError

LOG = logging.getLogger("haptex.play.transport")


class Transport:
    """Base class: a sink for frame packets.

    Attributes
    ----------
    packets_sent : int
        Packets accepted by the transport.
    retries : int
        Write attempts repeated after a timeout, stall or short write (USB only).
    """

    name = "transport"

    def __init__(self) -> None:
        self.packets_sent = 0
        self.retries = 0
        self.is_open = False

    def open(self) -> None:
        """Connect; raises :class:`DeviceError`."""
        self.is_open = True

    def send(self, packet: bytes) -> None:
        """Deliver one packet or raise :class:`DeviceError`."""
        raise NotImplementedError

    def status(self) -> protocol.Status | None:
        """The controller's status, or ``None`` for sinks without a controller."""
        return None

    def close(self) -> None:
        """Release resources; safe to call twice and after errors."""
        self.is_open = False

    def __enter__(self) -> "Transport":
        self.open()
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()


class NullSink(Transport):
    """Accepts and drops every packet (dry runs, benchmarks)."""

    name = "null"

    def send(self, packet: bytes) -> None:  # noqa: D102
        if not self.is_open:
            raise DeviceError("null sink is not open")
        self.packets_sent += 1


class FileSink(Transport):
    """Appends the raw packets, back to back, to a file (decode with ``protocol.split_packets``)."""

    def __init__(self, path: str | Path) -> None:
        super().__init__()
        self.path = Path(path)
        self.name = f"file:{self.path}"
        self._fh = None

    def open(self) -> None:  # noqa: D102
        try:
            self._fh = open(self.path, "wb")
        except OSError as exc:
            raise DeviceError(f"{self.path}: cannot open file sink ({exc.strerror or exc})") from None
        super().open()

    def send(self, packet: bytes) -> None:  # noqa: D102
        if self._fh is None:
            raise DeviceError(f"{self.path}: file sink is not open")
        try:
            self._fh.write(packet)
        except OSError as exc:
            raise DeviceError(f"{self.path}: write failed ({exc.strerror or exc})") from None
        self.packets_sent += 1

    def close(self) -> None:  # noqa: D102
        if self._fh is not None:
            try:
                self._fh.close()
            finally:
                self._fh = None
        super().close()


def default_usb_backend() -> Any:
    """libusb-1.0 from the ``libusb-package`` wheel if installed, else pyusb's own search.

    Raises
    ------
    DeviceError
        No libusb is available.
    """
    try:
        import libusb_package  # optional: ships a libusb binary

        backend = libusb_package.get_libusb1_backend()
        if backend is not None:
            return backend
    except ImportError:
        pass
    import usb.backend.libusb1

    backend = usb.backend.libusb1.get_backend()
    if backend is None:
        raise DeviceError("libusb is not available: install libusb-1.0 or the libusb-package wheel (pip install haptex[usb])")
    return backend


def _is_no_device(exc: Exception) -> bool:
    return getattr(exc, "errno", None) == errno.ENODEV or getattr(exc, "backend_error_code", None) == -4


class UsbTransport(Transport):
    """Bulk OUT frames and vendor-request status reads through pyusb.

    Parameters
    ----------
    vendor_id, product_id : int
        Device to open.
    interface, endpoint_out : int
        Interface number and bulk OUT endpoint number (address = number, direction bit 0).
    timeout_ms : int
        Per write attempt.
    retries : int
        Extra attempts after a timeout, stall (the halt is cleared first) or short write;
        then :class:`DeviceError` and the player stops.
    backend : usb.backend.IBackend, optional
        ``None`` uses :func:`default_usb_backend`; the emulator passes its own.
    name : str
        For messages (``"usb"`` or ``"sim"``).
    """

    def __init__(self, vendor_id: int, product_id: int, *, interface: int = 0, endpoint_out: int = 1,
                 timeout_ms: int = 10, retries: int = 2, backend: Any = None, name: str = "usb") -> None:
        super().__init__()
        self.vendor_id = vendor_id
        self.product_id = product_id
        self.interface = interface
        self.endpoint = endpoint_out & 0x0F
        self.timeout_ms = timeout_ms
        self.max_retries = retries
        self.backend = backend
        self.name = name
        self.dev: Any = None

    @property
    def ident(self) -> str:
        """``vvvv:pppp``."""
        return f"{self.vendor_id:04x}:{self.product_id:04x}"

    def open(self) -> None:  # noqa: D102
        import usb.core
        import usb.util

        backend = self.backend if self.backend is not None else default_usb_backend()
        try:
            dev = usb.core.find(idVendor=self.vendor_id, idProduct=self.product_id, backend=backend)
            if dev is None:
                found = sorted({f"{d.idVendor:04x}:{d.idProduct:04x}"
                                for d in usb.core.find(find_all=True, backend=backend)})
                listing = f"devices present: {', '.join(found)}" if found else "no USB devices found at all"
                raise DeviceError(f"stimulator {self.ident} not found ({listing}); check the cable, "
                                  "the profile's vendor_id/product_id, and permissions (udev rule)")
            dev.set_configuration()
            usb.util.claim_interface(dev, self.interface)
        except usb.core.NoBackendError:
            raise DeviceError("libusb is not available: install libusb-1.0 or libusb-package") from None
        except usb.core.USBError as exc:
            raise DeviceError(f"stimulator {self.ident}: cannot open ({exc}); check permissions (udev rule)") from None
        self.dev = dev
        super().open()

    def send(self, packet: bytes) -> None:
        """Write one packet; retry a bounded number of times, then raise :class:`DeviceError`."""
        import usb.core

        if self.dev is None:
            raise DeviceError(f"stimulator {self.ident} is not open")
        last = ""
        for attempt in range(self.max_retries + 1):
            if attempt:
                self.retries += 1
            try:
                n = self.dev.write(self.endpoint, packet, self.timeout_ms)
            except usb.core.USBTimeoutError:
                last = f"write timed out after {self.timeout_ms} ms"
                continue
            except usb.core.USBError as exc:
                if _is_no_device(exc):
                    raise DeviceError(f"stimulator {self.ident} disconnected (unplugged?) after {self.packets_sent} frames") from None
                if getattr(exc, "errno", None) == errno.EPIPE:
                    last = "endpoint stalled"
                    try:
                        self.dev.clear_halt(self.endpoint)
                    except usb.core.USBError as exc2:
                        if _is_no_device(exc2):
                            raise DeviceError(f"stimulator {self.ident} disconnected (unplugged?) after {self.packets_sent} frames") from None
                    continue
                last = str(exc)
                continue
            if n == len(packet):
                self.packets_sent += 1
                return
            last = f"short write ({n} of {len(packet)} bytes)"
        raise DeviceError(f"stimulator {self.ident}: {last}; gave up after {self.max_retries + 1} attempts")

    def status(self) -> protocol.Status | None:
        """Read the controller status (vendor IN request); :class:`DeviceError` if it fails."""
        import usb.core

        if self.dev is None:
            raise DeviceError(f"stimulator {self.ident} is not open")
        try:
            reply = self.dev.ctrl_transfer(protocol.STATUS_REQUEST_TYPE, protocol.STATUS_REQUEST, 0,
                                           self.interface, protocol.STATUS_SIZE, max(self.timeout_ms, 50))
            return protocol.decode_status(bytes(reply))
        except usb.core.USBError as exc:
            if _is_no_device(exc):
                raise DeviceError(f"stimulator {self.ident} disconnected (unplugged?)") from None
            raise DeviceError(f"stimulator {self.ident}: status read failed ({exc})") from None
        except protocol.ProtocolError as exc:
            raise DeviceError(f"stimulator {self.ident}: bad status reply ({exc})") from None

    def close(self) -> None:  # noqa: D102
        import usb.core
        import usb.util

        if self.dev is not None:
            try:
                usb.util.release_interface(self.dev, self.interface)
            except (usb.core.USBError, ValueError):
                pass  # unplugged: nothing to release
            try:
                usb.util.dispose_resources(self.dev)
            except usb.core.USBError:
                pass
            self.dev = None
        super().close()


def make_transport(spec: str, profile: Any, clock: Any = None) -> tuple[Transport, Any]:
    """Build the transport named on the command line.

    Parameters
    ----------
    spec : str
        ``sim`` (emulated controller through pyusb), ``usb``, ``null`` or ``file:PATH``.
    profile : DeviceProfile
        USB ids, endpoint, timeouts, channel count and DAC scaling.
    clock : clock, optional
        The player's clock (the emulator timestamps arrivals with it).

    Returns
    -------
    transport : Transport
    emulator : ControllerEmulator or None
        The emulator behind ``sim`` (for waveforms and status), else ``None``.
    """
    if spec == "null":
        return NullSink(), None
    if spec.startswith("file:"):
        path = spec[len("file:"):]
        if not path:
            raise DeviceError("--device file:PATH needs a path")
        return FileSink(path), None
    usb_args = dict(interface=profile.interface, endpoint_out=profile.endpoint_out,
                    timeout_ms=profile.timeout_ms, retries=profile.retries)
    if spec == "usb":
        return UsbTransport(profile.vendor_id, profile.product_id, **usb_args), None
    if spec == "sim":
        from playback.emulator import ControllerEmulator, EmulatorBackend

        emu = ControllerEmulator(profile.n_channels, vendor_id=profile.vendor_id, product_id=profile.product_id,
                                 clock=clock, dac_bits=profile.dac_bits, full_scale_v_rms=profile.full_scale_v_rms,
                                 interface=profile.interface, endpoint_out=profile.endpoint_out)
        return UsbTransport(profile.vendor_id, profile.product_id, backend=EmulatorBackend(emu),
                            name="sim", **usb_args), emu
    raise DeviceError(f"unknown device {spec!r} (use sim, usb, null or file:PATH)")
