"""Recording of a playback run to HDF5 (``--record out.h5``), written atomically.

Layout (the same for ``--mode tables`` and ``--mode direct``), n = frames sent, c = asset
contactors, m = device channels, L = packet bytes:

* ``/frames/t_s`` float64 [n]: frame centre, trajectory time (s)
* ``/frames/index`` int64 [n]: frame number k (gaps = frames skipped because the player was late)
* ``/frames/deadline_s``, ``/frames/sent_s`` float64 [n]: scheduled start and send completion on
  the player's clock, relative to the start of the run
* ``/frames/a40``, ``/frames/a320`` float32 [n, c]: amplitudes in µm before device calibration
* ``/frames/flags`` uint8 [n, c]: interpolation flags (playback.interp)
* ``/frames/codes`` uint16 [n, 2, m]: DAC codes sent (row 0: 40 Hz, row 1: 320 Hz)
* ``/frames/render_us``, ``/frames/latency_us`` float32 [n]: render time; input snapshot to
  packet accepted by the transport (end-to-end on the host, including the wait for the packet's
  due time: about ``prep``)
* ``/frames/input_age_ms`` float32 [n]: frame centre minus the newest trajectory sample used
* ``/frames/gain`` float32 [n]: fade applied for a stale live source (1 = none)
* ``/frames/late`` uint8 [n]: 1 if the transport accepted the packet after the frame's window
  started (``sent_s > deadline_s``; docs/usb-protocol.md, "Host timing")
* ``/frames/clamped``, ``/frames/nonfinite`` uint16 [n]: safety counts of the frame
* ``/frames/sequence`` uint32 [n], ``/frames/packet`` uint8 [n, L]: what went over the wire
* ``/waveforms/volts`` float32 [samples, m] and ``/waveforms/t_s`` (only with ``--waveforms``)

Root attributes describe the run (asset, mode, device, profile JSON, counters;
``frames_not_recorded``: frames sent past the record's size limit). The file is built in memory
and written, when complete, to a temporary name in the same folder and renamed.
"""
from __future__ import annotations

import json
import logging
import os
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from playback.errors import InputError
from playback.file_modes import new_file_mode
from playback.paths import check_replaceable, replace_with_bytes, temporary_beside
from playback.text_files import utf8_text

RECORD_FORMAT = "haptex-playback-record"
RECORD_VERSION = "1.0"
# A record is held in memory until it is written out (see Recorder): frames past this many bytes
# are not recorded (warned once, counted in the record). About 0.55 KB a frame with the HAPTEX
# array's 24 contactors: 13 h of playback; 17 bytes more a frame per contactor.
MAX_RECORD_BYTES = 1 << 30
LOG = logging.getLogger("haptex.play")


class Recorder:
    """Collects frames into an HDF5 file built in memory; :meth:`close` writes it to its name
    (through a temporary file and a rename), :meth:`abort` drops it. Frames past
    ``MAX_RECORD_BYTES`` are counted, not recorded (attribute ``frames_not_recorded``).

    Parameters
    ----------
    path : str or Path
        Final file name.
    n_contactors, n_channels, packet_size : int
        Array widths.
    attrs : dict
        Root attributes (JSON-encoded when not a plain number or string).
    chunk : int
        Frames buffered in memory between writes.

    Attributes
    ----------
    hold : bool
        While True (set by the player during real-time playback) :meth:`append` only buffers,
        up to ``max_pending`` frames, and the player calls :meth:`flush` when a frame has just
        been sent and the next one is far enough away: the HDF5 writes never delay a frame.
    """

    _SPEC = {
        "t_s": (np.float64, ()), "index": (np.int64, ()), "deadline_s": (np.float64, ()),
        "sent_s": (np.float64, ()), "render_us": (np.float32, ()), "latency_us": (np.float32, ()),
        "input_age_ms": (np.float32, ()), "gain": (np.float32, ()), "late": (np.uint8, ()),
        "clamped": (np.uint16, ()), "nonfinite": (np.uint16, ()), "sequence": (np.uint32, ()),
    }

    def __init__(self, path: str | Path, n_contactors: int, n_channels: int, packet_size: int,
                 attrs: dict[str, Any] | None = None, chunk: int = 256) -> None:
        self.path = Path(path)
        check_replaceable(self.path)
        try:  # a folder the record cannot be written to is found now, not after the session
            fd, probe = temporary_beside(self.path)
            os.close(fd)
            os.unlink(probe)
        except OSError as exc:
            raise InputError(self.path, f"cannot create record ({exc.strerror or exc})") from None
        spec = dict(self._SPEC)
        spec.update({"a40": (np.float32, (n_contactors,)), "a320": (np.float32, (n_contactors,)),
                     "flags": (np.uint8, (n_contactors,)), "codes": (np.uint16, (2, n_channels)),
                     "packet": (np.uint8, (packet_size,))})
        self.spec = spec
        frame_bytes = sum(np.dtype(dtype).itemsize * int(np.prod(shape)) for dtype, shape in spec.values())
        self.max_frames = max(1, MAX_RECORD_BYTES // frame_bytes)
        self.dropped = 0  # frames not recorded past max_frames
        # Built in memory and written out whole by close() (playback.paths.replace_with_bytes):
        # libhdf5 flushing into a full disk crashed the player after hundreds of lines of
        # tracebacks, and no write can now delay a frame (see MAX_RECORD_BYTES for the memory).
        self.file = h5py.File(f"haptex-record-{id(self)}", "w", driver="core", backing_store=False)
        self.frames = self.file.create_group("frames")
        for name, (dtype, shape) in spec.items():
            self.frames.create_dataset(name, shape=(0,) + shape, maxshape=(None,) + shape, dtype=dtype,
                                       chunks=(chunk,) + shape, track_times=False)
        self.chunk = chunk
        self.hold = False
        self.max_pending = 8 * chunk  # bounds the memory held while flushes are deferred
        self._buf: dict[str, list[Any]] = {k: [] for k in spec}
        self.n = 0
        self.closed = False  # renamed into place by close()
        self.set_attrs(attrs or {})
        self.file.attrs["format"] = RECORD_FORMAT
        self.file.attrs["format_version"] = RECORD_VERSION

    def set_attrs(self, attrs: dict[str, Any]) -> None:
        """Set root attributes (dicts and lists become JSON strings)."""
        for key, value in attrs.items():
            if isinstance(value, (dict, list, tuple)) or value is None:
                value = json.dumps(value, default=float)
            self.file.attrs[key] = utf8_text(value) if isinstance(value, str) else value  # (a path's name)

    @property
    def pending(self) -> int:
        """Frames buffered and not yet written."""
        return len(self._buf["t_s"])

    @property
    def flush_due(self) -> bool:
        """A chunk or more is buffered."""
        return self.pending >= self.chunk

    def append(self, **frame: Any) -> None:
        """Add one frame; every field of the layout must be given.

        The arrays are kept by reference until the next flush: pass arrays nobody modifies.
        """
        if self.n + self.pending >= self.max_frames:
            if not self.dropped:
                LOG.warning("%s: the record holds its limit of %d frames (%d MB in memory): later frames are not"
                            " recorded", self.path, self.max_frames, MAX_RECORD_BYTES >> 20)
            self.dropped += 1
            return
        for key in self.spec:
            self._buf[key].append(frame[key])
        if self.pending >= (self.max_pending if self.hold else self.chunk):
            self.flush()

    def flush(self) -> None:
        """Write buffered frames to the file."""
        m = len(self._buf["t_s"])
        if not m:
            return
        for key, (dtype, _) in self.spec.items():
            ds = self.frames[key]
            ds.resize(self.n + m, axis=0)
            ds[self.n:self.n + m] = np.asarray(self._buf[key], dtype=dtype)
            self._buf[key].clear()
        self.n += m

    def write_waveforms(self, t_s: np.ndarray, volts: np.ndarray, rate_hz: float) -> None:
        """Store synthesised drive waveforms (emulator only)."""
        g = self.file.require_group("waveforms")
        g.create_dataset("t_s", data=np.asarray(t_s, np.float64), track_times=False)
        g.create_dataset("volts", data=np.asarray(volts, np.float32), track_times=False,
                         chunks=True, compression="gzip", compression_opts=1)
        g.attrs["sample_rate_hz"] = float(rate_hz)
        g.attrs["description"] = "sqrt2 * (V40 sin(2 pi 40 t) + V320 sin(2 pi 320 t)) per device channel, volts"

    def close(self, attrs: dict[str, Any] | None = None) -> Path:
        """Flush, write the final attributes and write the file into place (a temporary file
        and a rename: an error, such as a full disk, leaves no file and raises
        :class:`InputError`)."""
        self.flush()
        if attrs:
            self.set_attrs(attrs)
        self.file.attrs["frames_not_recorded"] = self.dropped
        self.file.flush()
        image = self.file.id.get_file_image()
        self.file.close()
        replace_with_bytes(self.path, image, new_file_mode())
        self.closed = True
        return self.path

    def abort(self) -> None:
        """Drop the record (nothing was written to disk)."""
        self.file.close()

    def __enter__(self) -> "Recorder":
        return self

    def __exit__(self, *exc_info: object) -> None:
        """A record not closed by then is unfinished (the run failed before it, or was stopped
        before it began): it is dropped, and nothing is left beside the record's name."""
        if not self.closed:
            self.abort()
