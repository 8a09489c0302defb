"""Reading height maps (µm) from ``.npy`` and ``.exr`` files, with the same checks for both.

A height map is a real 2-D array of at least 8 x 8 finite values in micrometres.  The pixel
size is not stored in these files; the caller takes it from ``--pixel-size``.
"""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from haptex_compile.errors import InputError
from haptex_compile.io_exr import read_exr_channels
from haptex_compile.io_images import MIN_SIDE_PX

__all__ = ["read_height_npy", "read_height_exr", "check_height_um"]

_NPY_MAGIC = b"\x93NUMPY"
_MAX_HEADER_BYTES = 100_000


def check_height_um(height_um: np.ndarray, source: str | os.PathLike | None) -> np.ndarray:
    """Check a height map and return it as float64 µm.

    Parameters
    ----------
    height_um : numpy.ndarray
        Candidate height map, µm.
    source : str or os.PathLike or None
        Where it came from, for the error message.

    Returns
    -------
    numpy.ndarray
        float64 [ny, nx] µm, C-contiguous, a new array.

    Raises
    ------
    InputError
        If it is not a real numeric 2-D array of at least 8 x 8 finite values.
    """
    array = np.asarray(height_um)
    if array.dtype.kind not in "fiu":
        raise InputError(source, f"height map must be real numbers, got dtype {array.dtype}")
    if array.ndim != 2:
        raise InputError(source, f"height map must be 2-D, got shape {array.shape}")
    ny, nx = array.shape
    if min(ny, nx) < MIN_SIDE_PX:
        raise InputError(source, f"height map too small ({nx} x {ny}; at least {MIN_SIDE_PX} x "
                                 f"{MIN_SIDE_PX} needed)")
    # (longdouble beyond float64 becomes inf, and a signalling NaN, as in a damaged EXR's float32
    # channel, warns "invalid value encountered in cast": both counted below)
    with np.errstate(over="ignore", invalid="ignore"):
        heights = np.array(array, dtype=np.float64, order="C")
    bad = int(heights.size - np.count_nonzero(np.isfinite(heights)))
    if bad:
        n_nan = int(np.count_nonzero(np.isnan(heights)))
        raise InputError(source, f"{bad} of {heights.size} height values are not finite "
                                 f"({n_nan} NaN, {bad - n_nan} inf)")
    return heights


def read_height_npy(path: str | os.PathLike, *, max_pixels: int = 200_000_000) -> np.ndarray:
    """Read a height map in µm from a ``.npy`` file (2-D, real numbers, no pickles).

    The header is read first: dtype, shape and the data size are checked against the file
    before any data is allocated.

    Parameters
    ----------
    path : str or os.PathLike
        The ``.npy`` file (format version 1.0 or 2.0, as written by :func:`numpy.save`).
    max_pixels : int
        Largest accepted number of values.

    Returns
    -------
    numpy.ndarray
        float64 [ny, nx] µm.

    Raises
    ------
    InputError
        For a missing, empty, truncated or non-.npy file, object/structured/complex/bool data,
        not 2-D, smaller than 8 x 8, larger than `max_pixels`, or NaN/inf values (counted).
    """
    p = Path(path)
    if not p.exists():
        raise InputError(path, "no such height-map file")
    if p.is_dir():
        raise InputError(path, "is a directory, expected a .npy height map")
    try:
        size = p.stat().st_size
        if size == 0:
            raise InputError(path, "empty .npy file (0 bytes)")
        with open(p, "rb") as handle:
            if handle.read(6) != _NPY_MAGIC:
                raise InputError(path, "not a .npy file (bad magic string)")
            handle.seek(0)
            try:
                version = np.lib.format.read_magic(handle)
                if version == (1, 0):
                    shape, fortran, dtype = np.lib.format.read_array_header_1_0(
                        handle, max_header_size=_MAX_HEADER_BYTES)
                elif version == (2, 0):
                    shape, fortran, dtype = np.lib.format.read_array_header_2_0(
                        handle, max_header_size=_MAX_HEADER_BYTES)
                else:
                    raise InputError(path, f".npy format version {version[0]}.{version[1]} is "
                                           "not supported (1.0 or 2.0)")
            except InputError:
                raise
            except Exception as exc:  # numpy raises ValueError, SyntaxError, TypeError, ...
                raise InputError(path, f"corrupt .npy header ({str(exc).splitlines()[0]})") \
                    from None
            if dtype.hasobject or dtype.fields is not None or dtype.subdtype is not None \
                    or dtype.kind not in "fiu":
                raise InputError(path, f"height map must be real numbers, got dtype {dtype}")
            if len(shape) != 2:
                raise InputError(path, f"height map must be 2-D, got shape {tuple(shape)}")
            count = int(shape[0]) * int(shape[1])
            if count > max_pixels:
                raise InputError(path, f"height map claims {shape[1]} x {shape[0]} values, more "
                                       f"than the limit of {max_pixels / 1e6:.1f} M")
            need = handle.tell() + count * dtype.itemsize
            if size < need:
                raise InputError(path, f".npy file truncated ({size} of {need} bytes)")
            data = np.fromfile(handle, dtype=dtype, count=count)
    except OSError as exc:
        raise InputError(path, f"cannot read: {exc.strerror or exc}") from None
    array = data.reshape(shape, order="F" if fortran else "C")
    return check_height_um(array, path)


def read_height_exr(path: str | os.PathLike, *, max_pixels: int = 200_000_000) -> np.ndarray:
    """Read a height map in µm from an EXR file: channel ``height``, or its only channel.

    Parameters
    ----------
    path : str or os.PathLike
        The EXR file.
    max_pixels : int
        Largest accepted data window, checked from the header before reading pixels.

    Returns
    -------
    numpy.ndarray
        float64 [ny, nx] µm.

    Raises
    ------
    InputError
        For an unreadable or corrupt EXR, several channels none of which is ``height``,
        a map smaller than 8 x 8, or NaN/inf values (counted).
    """
    channels = read_exr_channels(path, max_pixels=max_pixels)
    if "height" in channels:
        values = channels["height"]
    elif len(channels) == 1:
        values = next(iter(channels.values()))
    else:
        raise InputError(path, f"no 'height' channel among {len(channels)} channels "
                               f"({', '.join(sorted(channels))})")
    return check_height_um(values, path)
