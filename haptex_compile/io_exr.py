"""OpenEXR writing and low-level reading through the ``OpenEXR`` package.

OpenCV's wheels are built without EXR support, so EXR goes through the OpenEXR library's own
Python binding.  Files are written single-part, scanline, ZIP-compressed, float32 channels,
made in memory and written atomically (:func:`playback.paths.replace_with_bytes`: a temporary
file in the target directory, then :func:`os.replace`), so a failed or interrupted write never
leaves a partial file and keeps an older one intact.  Identical
inputs give byte-identical files (EXR stores no time stamp).
"""
from __future__ import annotations

import contextlib
import io
import logging
import os
from pathlib import Path
from typing import Iterator

import numpy as np
import OpenEXR

from haptex_compile.errors import InputError
from haptex_compile.native_output import captured_native_output
from playback.file_modes import new_file_mode
from playback.paths import check_replaceable, replace_with_bytes

__all__ = ["write_exr", "exr_image", "read_exr_channels", "EXR_MAGIC"]

EXR_MAGIC = b"\x76\x2f\x31\x01"
LOG = logging.getLogger("haptex.io")

# Header attributes the library sets itself; user attributes must not override them.
_RESERVED = {"channels", "compression", "dataWindow", "displayWindow", "lineOrder",
             "pixelAspectRatio", "screenWindowCenter", "screenWindowWidth", "type", "name",
             "tiles", "version", "chunkCount", "view", "multiView", "maxSamplesPerPixel"}

_STORED_DTYPE = {"HALF": np.float16, "FLOAT": np.float32, "UINT": np.uint32}


def write_exr(path: str | os.PathLike, channels: dict[str, np.ndarray], *,
              attributes: dict[str, str] | None = None) -> None:
    """Write 2-D maps as named float32 channels of a single-part scanline EXR (ZIP), atomically.

    Parameters
    ----------
    path : str or os.PathLike
        The output file; its directory must exist.  Replaced atomically if present.
    channels, attributes
        As for :func:`exr_image`, which makes the file's bytes.

    Raises
    ------
    ValueError
        As for :func:`exr_image`.
    InputError
        If the file cannot be written (missing directory, permissions, disk full).
    """
    image = exr_image(channels, attributes=attributes, file_name=path)
    target = Path(path)
    check_replaceable(target)
    directory = target.parent if str(target.parent) else Path(".")
    if not directory.is_dir():
        raise InputError(path, "cannot write: the output directory does not exist")
    replace_with_bytes(target, image, new_file_mode())


def exr_image(channels: dict[str, np.ndarray], *, attributes: dict[str, str] | None = None,
              file_name: str | os.PathLike = "EXR") -> bytes:
    """The bytes of a single-part scanline EXR (ZIP) of 2-D maps as named float32 channels,
    made in memory (:func:`write_exr` writes them; the compiler writes them beside the asset,
    both or neither).

    Parameters
    ----------
    channels : dict of str to numpy.ndarray
        Channel name -> real 2-D array, all of the same shape [ny, nx]; stored as float32
        (e.g. ``{"height": height_um, "a40": a40_um}``).  EXR sorts channels by name.
    attributes : dict of str to str, optional
        Extra string attributes for the header (e.g. ``{"pixel_size_um": "10"}``).

    Raises
    ------
    ValueError
        For no channels, a bad channel name, arrays that are not real 2-D, differ in shape or
        have values that are not finite in float32, or bad attributes.
    InputError
        If the library fails (its message names `file_name`).
    """
    if not channels:
        raise ValueError("write_exr needs at least one channel")
    shape = None
    stored: dict[str, np.ndarray] = {}
    for name, values in channels.items():
        if not isinstance(name, str) or not name or len(name.encode("utf-8")) > 255 \
                or any(ord(c) < 32 for c in name):
            raise ValueError(f"bad EXR channel name {name!r} (1-255 printable characters)")
        array = np.asarray(values)
        if array.dtype.kind not in "fiub" or array.ndim != 2 or array.size == 0:
            raise ValueError(f"EXR channel {name!r} must be a non-empty real 2-D array, got "
                             f"{array.dtype} with shape {array.shape}")
        if shape is None:
            shape = array.shape
        elif array.shape != shape:
            raise ValueError(f"EXR channel {name!r} has shape {array.shape}, others {shape}")
        with np.errstate(over="ignore", invalid="ignore"):
            as_f32 = np.ascontiguousarray(array, dtype=np.float32)
        bad = int(np.count_nonzero(~np.isfinite(as_f32)))
        if bad:
            raise ValueError(f"EXR channel {name!r} has {bad} values that are not finite in "
                             "float32")
        stored[name] = as_f32
    header: dict[str, object] = {"compression": OpenEXR.ZIP_COMPRESSION,
                                 "type": OpenEXR.scanlineimage,
                                 "lineOrder": OpenEXR.INCREASING_Y}
    for key, text in (attributes or {}).items():
        if not isinstance(key, str) or not key or key in _RESERVED or not isinstance(text, str):
            raise ValueError(f"bad EXR attribute {key!r}: {text!r} (string name not in "
                             f"{sorted(_RESERVED)}, string value)")
        header[key] = text

    buffer = io.BytesIO()
    try:
        with _library_output(file_name):
            OpenEXR.File(header, stored).write(buffer)
    except RuntimeError as exc:  # the library's own errors
        raise InputError(file_name, f"cannot write EXR: {_first_line(exc)}") from None
    return buffer.getvalue()


@contextlib.contextmanager
def _library_output(path: str | os.PathLike) -> Iterator[None]:
    """Keep what the OpenEXR library prints itself while reading or writing `path` out of the
    tools' output: on a corrupt file it printed a "Warning: ..." line on stdout and its own error
    line on stderr before ours. Its lines are logged at debug level (``-vv``): the caller's
    one-line error says what went wrong."""
    lines: list[str] = []
    try:
        with captured_native_output() as lines:
            yield
    finally:  # (the descriptors are back: the log reaches the terminal)
        for line in lines:
            LOG.debug("%s: OpenEXR library: %s", path, line)


def _first_line(exc: BaseException) -> str:
    text = str(exc).strip()
    return text.splitlines()[0] if text else type(exc).__name__


def read_exr_channels(path: str | os.PathLike, *, max_pixels: int = 200_000_000
                      ) -> dict[str, np.ndarray]:
    """Read every channel of a single-part EXR file (scanline or tiled, full resolution).

    Parameters
    ----------
    path : str or os.PathLike
        The EXR file.
    max_pixels : int
        Largest accepted data window (width x height), checked from the header first.

    Returns
    -------
    dict of str to numpy.ndarray
        Channel name -> [ny, nx] array over the data window, as stored (float16 for HALF,
        float32 for FLOAT, uint32 for UINT); values are not checked (may be NaN or inf).

    Raises
    ------
    InputError
        For a missing, empty or non-EXR file, a corrupt or truncated one, a multi-part, deep
        or sub-sampled file, or a data window larger than `max_pixels`.
    """
    p = Path(path)
    if not p.exists():
        raise InputError(path, "no such EXR file")
    if p.is_dir():
        raise InputError(path, "is a directory, expected an EXR file")
    try:
        with open(p, "rb") as handle:
            magic = handle.read(4)
    except OSError as exc:
        raise InputError(path, f"cannot read: {exc.strerror or exc}") from None
    if not magic:
        raise InputError(path, "empty EXR file (0 bytes)")
    if magic != EXR_MAGIC:
        raise InputError(path, "not an OpenEXR file (bad magic number)")

    try:
        with _library_output(path):
            return _read_channels(p, path, max_pixels)
    except InputError:
        raise
    except MemoryError:
        raise InputError(path, "EXR file too large to read into memory") from None
    except Exception as exc:  # the binding raises RuntimeError, ValueError, TypeError, ...
        raise InputError(path, f"corrupt or unreadable EXR file ({_first_line(exc)})") from None


def _utf8_name(p: Path) -> bool:
    """`p` can be passed to the OpenEXR binding as a name: it refuses names with bytes that are
    not UTF-8 (which Python keeps as lone surrogates)."""
    try:
        str(p).encode("utf-8")
    except UnicodeEncodeError:
        return False
    return True


def _read_channels(p: Path, path: str | os.PathLike, max_pixels: int) -> dict[str, np.ndarray]:
    """:func:`read_exr_channels` past its checks of the path and the magic number."""
    # The binding reads the file by its name, or from its bytes (read once) where it cannot
    # take the name (see _utf8_name).
    data = None if _utf8_name(p) else p.read_bytes()

    def source() -> str | io.BytesIO:
        return str(p) if data is None else io.BytesIO(data)

    head = OpenEXR.File(source(), header_only=True)
    if len(head.parts) != 1:
        raise InputError(path, f"multi-part EXR ({len(head.parts)} parts) is not supported; "
                               "write a single-part file")
    header = head.header()
    storage = header.get("type", OpenEXR.scanlineimage)
    if storage not in (OpenEXR.scanlineimage, OpenEXR.tiledimage):
        raise InputError(path, f"EXR storage {storage.name} is not supported "
                               "(only flat scanline or tiled images)")
    (x0, y0), (x1, y1) = (np.asarray(c, dtype=np.int64) for c in header["dataWindow"])
    nx, ny = int(x1 - x0 + 1), int(y1 - y0 + 1)
    if nx <= 0 or ny <= 0:
        raise InputError(path, f"corrupt EXR: empty data window ({nx} x {ny})")
    if nx * ny > max_pixels:
        raise InputError(path, f"EXR claims {nx} x {ny} pixels ({nx * ny / 1e6:.1f} MP), more "
                               f"than the limit of {max_pixels / 1e6:.1f} MP")
    declared = header.get("channels", [])
    if not declared:
        raise InputError(path, "EXR file has no channels")
    for channel in declared:
        if channel.xSampling != 1 or channel.ySampling != 1:
            raise InputError(path, f"EXR channel {channel.name!r} is sub-sampled "
                                   f"({channel.xSampling} x {channel.ySampling}); not supported")
    full = OpenEXR.File(source(), separate_channels=True)
    result: dict[str, np.ndarray] = {}
    for name, channel in full.channels().items():
        pixels = channel.pixels
        if not isinstance(pixels, np.ndarray) or pixels.shape != (ny, nx):
            raise InputError(path, f"corrupt EXR: channel {name!r} does not fill the "
                                   f"{nx} x {ny} data window")
        result[str(name)] = np.array(pixels, dtype=_STORED_DTYPE.get(channel.type().name,
                                                                     pixels.dtype))
    if not result:
        raise InputError(path, "EXR file has no channels")
    return result
