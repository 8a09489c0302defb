"""Robust reading of photographs (JPEG, PNG, BMP, TIFF) into a grey image in [0, 1].

Every file is checked before it is decoded: the format is recognised from its content (not
its suffix), the pixel dimensions are read from the header and refused above a limit, and
the file structure is walked far enough to detect truncation (JPEG end-of-image marker, PNG
chunk checksums and ``IEND``, BMP pixel-array size, TIFF strip and tile extents).  Only
then does OpenCV decode the pixels.  Every failure is an
:class:`~haptex_compile.errors.InputError` whose one-line message names the file.

The pixel size (µm per pixel) is taken from the file's resolution metadata when it is
plausible for a texture close-up (1-500 µm/px); 72 and 96 dpi, which image software writes
when it knows nothing, are ignored.
"""
from __future__ import annotations

import logging
import math
import os
import struct
import zlib
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from haptex_compile.errors import InputError
from haptex_compile.native_output import captured_native_output

LOG = logging.getLogger("haptex.io")

__all__ = ["ImageData", "SUPPORTED_IMAGE_SUFFIXES", "read_image", "MIN_SIDE_PX"]

SUPPORTED_IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png", ".bmp", ".tif", ".tiff")

#: Smallest accepted image or height-map side, in pixels.
MIN_SIDE_PX = 8

#: Plausible pixel sizes of a texture photograph, µm per pixel (inclusive).
PLAUSIBLE_PIXEL_UM = (1.0, 500.0)

#: Resolutions that image software writes by default; they say nothing about the scene.
_DEFAULT_DPI = (72.0, 96.0)

#: Rec. 601 luma weights (R, G, B): the weights of the JPEG/JFIF Y channel, so that a colour
#: JPEG decoded as grey and a colour PNG of the same pixels give the same grey image.
LUMA_WEIGHTS_RGB = (0.299, 0.587, 0.114)


@dataclass(frozen=True, eq=False)
class ImageData:
    """A photograph read for the compiler.

    Attributes
    ----------
    grey : numpy.ndarray
        float64 [ny, nx] in [0, 1]: the stored values scaled by the full scale of the bit
        depth; colour is reduced to luma with Rec. 601 weights (0.299 R + 0.587 G +
        0.114 B) on the stored, gamma-encoded values (no linearisation); alpha is dropped
        (not composited).  Colour JPEGs are decoded straight to their Y channel, which is
        the same weighting.  EXIF orientation is applied, as image viewers do.
    bit_depth : int
        8 or 16: the precision kept in `grey` (16-bit PNG/TIFF keep all 16 bits).
    channels : int
        Channels in the file: 1 grey, 2 grey + alpha, 3 colour (palette images count as 3),
        4 colour + alpha (or CMYK JPEG).
    pixel_size_um : float or None
        µm per pixel from the resolution metadata when plausible (1-500 µm/px, square pixels,
        not a 72/96 dpi software default), else None.
    metadata_note : str
        One line saying where `pixel_size_um` came from or why there is none.
    """

    grey: np.ndarray
    bit_depth: int
    channels: int
    pixel_size_um: float | None
    metadata_note: str


class _Bad(Exception):
    """A problem found while parsing; turned into an InputError naming the file."""


@dataclass
class _Header:
    """What the header parsers learn before any pixel is decoded."""

    fmt: str  # "JPEG", "PNG", "BMP", "TIFF"
    width: int
    height: int
    channels: int
    # Resolution candidates in order of preference: (x, y, unit, source); unit is
    # "inch", "cm", "m" or "" (no absolute unit).
    resolutions: list[tuple[float, float, str, str]] = field(default_factory=list)
    sample_format: int = 1  # TIFF SampleFormat: 1 uint, 2 int, 3 float
    bits: int = 8
    colour_type: int = 0  # PNG colour type
    tags: dict[int, np.ndarray] = field(default_factory=dict)  # TIFF tags for the checks


# --------------------------------------------------------------------------- file access


def read_file_bytes(path: str | os.PathLike, what: str = "file") -> bytes:
    """Read a whole input file, turning every file-system problem into an InputError.

    Parameters
    ----------
    path : str or os.PathLike
        The file.
    what : str
        What the file should be, for messages (e.g. ``"image"``).

    Returns
    -------
    bytes
        The file content; never empty.

    Raises
    ------
    InputError
        If the path is missing, a directory, unreadable or empty.
    """
    p = Path(path)
    if not p.exists():
        raise InputError(path, f"no such {what}")
    if p.is_dir():
        raise InputError(path, f"is a directory, expected a {what}")
    try:
        data = p.read_bytes()
    except OSError as exc:
        raise InputError(path, f"cannot read: {exc.strerror or exc}") from None
    if not data:
        raise InputError(path, f"empty {what} (0 bytes)")
    return data


# --------------------------------------------------------------------------- TIFF / EXIF IFD

_TIFF_TYPE_SIZE = {1: 1, 2: 1, 3: 2, 4: 4, 5: 8, 6: 1, 7: 1, 8: 2, 9: 4, 10: 8, 11: 4, 12: 8,
                   13: 4, 16: 8, 17: 8, 18: 8}
_TIFF_NUMPY = {1: "u1", 3: "u2", 4: "u4", 6: "i1", 8: "i2", 9: "i4", 11: "f4", 12: "f8",
               13: "u4", 16: "u8", 17: "i8", 18: "u8"}
# Tags we use: dimensions, sample layout, strips/tiles, resolution, orientation.
_TIFF_WANTED = {256, 257, 258, 259, 262, 273, 274, 277, 279, 282, 283, 296, 322, 323, 324,
                325, 339}


def _tiff_ifd0(data: bytes | memoryview, base: int = 0) -> dict[int, np.ndarray]:
    """Parse the first IFD of a TIFF structure starting at `base` (a TIFF file or EXIF block).

    Returns the wanted tags as float64 or integer arrays (rationals as float64).
    """
    n = len(data)
    order = bytes(data[base:base + 2])
    if order == b"II":
        e = "<"
    elif order == b"MM":
        e = ">"
    else:
        raise _Bad("bad TIFF byte-order mark")
    (magic,) = struct.unpack_from(e + "H", data, base + 2)
    if magic == 42:
        (ifd,) = struct.unpack_from(e + "I", data, base + 4)
        count_fmt, entry_size, off_fmt, inline = "H", 12, "I", 4
    elif magic == 43:  # BigTIFF
        size, zero = struct.unpack_from(e + "HH", data, base + 4)
        if size != 8 or zero != 0:
            raise _Bad("bad BigTIFF header")
        (ifd,) = struct.unpack_from(e + "Q", data, base + 8)
        count_fmt, entry_size, off_fmt, inline = "Q", 20, "Q", 8
    else:
        raise _Bad("bad TIFF magic number")
    pos = base + ifd
    if ifd < 8 or pos >= n:
        raise _Bad("TIFF directory offset outside the file (truncated?)")
    (count,) = struct.unpack_from(e + count_fmt, data, pos)
    pos += struct.calcsize(count_fmt)
    if count == 0 or pos + count * entry_size > n:
        raise _Bad("TIFF directory truncated or empty")
    tags: dict[int, np.ndarray] = {}
    for i in range(count):
        tag, typ = struct.unpack_from(e + "HH", data, pos + i * entry_size)
        if tag not in _TIFF_WANTED or typ not in _TIFF_TYPE_SIZE or typ == 2 or typ == 7:
            continue
        (cnt,) = struct.unpack_from(e + off_fmt, data, pos + i * entry_size + 4)
        nbytes = cnt * _TIFF_TYPE_SIZE[typ]
        value_pos = pos + i * entry_size + 4 + inline
        if nbytes > inline:
            (off,) = struct.unpack_from(e + off_fmt, data, value_pos)
            value_pos = base + off
        if cnt == 0 or value_pos + nbytes > n:
            raise _Bad(f"TIFF tag {tag} points outside the file (truncated?)")
        raw = data[value_pos:value_pos + nbytes]
        if typ in (5, 10):
            kind = "u4" if typ == 5 else "i4"
            pairs = np.frombuffer(raw, dtype=e + kind).astype(np.float64).reshape(-1, 2)
            with np.errstate(divide="ignore", invalid="ignore"):
                tags[tag] = pairs[:, 0] / pairs[:, 1]
        else:
            tags[tag] = np.frombuffer(raw, dtype=e + _TIFF_NUMPY[typ])
    return tags


def _tiff_resolution(tags: dict[int, np.ndarray], source: str) -> list[tuple[float, float, str, str]]:
    """Resolution candidate from XResolution/YResolution/ResolutionUnit, if present."""
    if 282 not in tags:
        return []
    x = float(tags[282][0])
    y = float(tags[283][0]) if 283 in tags else x
    unit = int(tags[296][0]) if 296 in tags else 2  # TIFF default unit: inch
    return [(x, y, {2: "inch", 3: "cm"}.get(unit, ""), source)]


# --------------------------------------------------------------------------- format parsers

_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
_PNG_DEPTHS = {0: (1, 2, 4, 8, 16), 2: (8, 16), 3: (1, 2, 4, 8), 4: (8, 16), 6: (8, 16)}
_PNG_CHANNELS = {0: 1, 2: 3, 3: 3, 4: 2, 6: 4}  # channels once decoded
_PNG_SAMPLES = {0: 1, 2: 3, 3: 1, 4: 2, 6: 4}   # samples per stored pixel


def _png_header(data: bytes) -> _Header:
    if len(data) < 33 or data[12:16] != b"IHDR":
        raise _Bad("PNG truncated or without IHDR header")
    length, = struct.unpack_from(">I", data, 8)
    width, height, depth, colour, comp, filt, interlace = struct.unpack_from(">IIBBBBB", data, 16)
    if length != 13 or width == 0 or height == 0 or width > 2**31 - 1 or height > 2**31 - 1:
        raise _Bad("corrupt PNG header (IHDR)")
    if colour not in _PNG_DEPTHS or depth not in _PNG_DEPTHS[colour] or comp or filt or interlace > 1:
        raise _Bad(f"corrupt PNG header (colour type {colour}, bit depth {depth})")
    return _Header("PNG", width, height, _PNG_CHANNELS[colour], bits=depth, colour_type=colour)


def _png_check(data: bytes, header: _Header) -> None:
    """Walk all chunks: checksums of critical chunks, an IDAT, and IEND must be present."""
    view = memoryview(data)
    n, pos, idat_bytes = len(data), 8, 0
    has_trns = False
    while True:
        if pos + 12 > n:
            raise _Bad("PNG truncated (no IEND chunk)")
        length, ctype = struct.unpack_from(">I4s", data, pos)
        end = pos + 12 + length
        if length > 2**31 - 1 or not ctype.isalpha():
            raise _Bad(f"corrupt PNG chunk at byte {pos}")
        if end > n:
            raise _Bad("PNG truncated (chunk runs past the end of the file)")
        (crc,) = struct.unpack_from(">I", data, end - 4)
        crc_ok = zlib.crc32(view[pos + 4:end - 4]) == crc
        critical = ctype[:1].isupper()
        if not crc_ok and critical:
            raise _Bad(f"corrupt PNG: checksum error in {ctype.decode('ascii')} chunk")
        if crc_ok:
            if ctype == b"IDAT":
                idat_bytes += length
            elif ctype == b"tRNS":
                has_trns = True
            elif ctype == b"pHYs" and length == 9:
                ppu_x, ppu_y, unit = struct.unpack_from(">IIB", data, pos + 8)
                header.resolutions.append(
                    (float(ppu_x), float(ppu_y), "m" if unit == 1 else "", "PNG pHYs"))
            elif ctype == b"IEND":
                break
        pos = end
    if not idat_bytes:
        raise _Bad("corrupt PNG: no image data (IDAT)")
    # Deflate expands at most 1032-fold: fewer compressed bytes than that cannot hold the
    # image, so refuse before the decoder allocates it (a cheap decompression-bomb guard).
    row_bytes = 1 + (header.width * header.bits * _PNG_SAMPLES[header.colour_type] + 7) // 8
    if idat_bytes * 1032 < row_bytes * header.height:
        raise _Bad(f"corrupt PNG: {idat_bytes} bytes of image data cannot hold "
                   f"{header.width} x {header.height} pixels")
    if has_trns and header.channels in (1, 3):
        header.channels += 1


_JPEG_SOF = {0xC0, 0xC1, 0xC2, 0xC3, 0xC5, 0xC6, 0xC7, 0xC9, 0xCA, 0xCB, 0xCD, 0xCE, 0xCF}


def _jpeg_header(data: bytes) -> tuple[_Header, int]:
    """Walk the marker segments up to the first scan; returns the header and the SOS offset."""
    n, pos = len(data), 2
    header: _Header | None = None
    jfif: list[tuple[float, float, str, str]] = []
    exif: list[tuple[float, float, str, str]] = []
    while True:
        if pos + 4 > n:
            raise _Bad("JPEG truncated before the image data")
        if data[pos] != 0xFF:
            raise _Bad(f"corrupt JPEG: no marker at byte {pos}")
        while pos + 1 < n and data[pos + 1] == 0xFF:  # fill bytes
            pos += 1
        marker = data[pos + 1]
        if marker == 0x01 or 0xD0 <= marker <= 0xD8:  # standalone markers
            pos += 2
            continue
        if marker == 0xD9:
            raise _Bad("corrupt JPEG: end-of-image marker before any image data")
        if pos + 4 > n:
            raise _Bad("JPEG truncated before the image data")
        (seglen,) = struct.unpack_from(">H", data, pos + 2)
        if seglen < 2 or pos + 2 + seglen > n:
            raise _Bad("JPEG truncated or corrupt marker segment")
        seg = data[pos + 4:pos + 2 + seglen]
        if marker == 0xDA:
            if header is None:
                raise _Bad("corrupt JPEG: image data before the frame header (SOF)")
            header.resolutions = jfif + exif
            return header, pos
        if marker in _JPEG_SOF and header is None:
            if len(seg) < 6:
                raise _Bad("corrupt JPEG frame header (SOF)")
            precision, height, width, ncomp = struct.unpack_from(">BHHB", seg, 0)
            if height == 0:
                raise _Bad("JPEG with height defined after the scan (DNL) is not supported")
            if width == 0 or ncomp not in (1, 3, 4):
                raise _Bad(f"corrupt JPEG frame header ({width} px wide, {ncomp} components)")
            if precision != 8:
                raise _Bad(f"{precision}-bit JPEG is not supported (only 8-bit)")
            header = _Header("JPEG", width, height, ncomp, bits=8)
        elif marker == 0xE0 and seg[:5] == b"JFIF\x00" and len(seg) >= 12:
            units, xd, yd = struct.unpack_from(">BHH", seg, 7)
            if units in (1, 2):
                jfif.append((float(xd), float(yd), "inch" if units == 1 else "cm", "JFIF density"))
        elif marker == 0xE1 and seg[:6] == b"Exif\x00\x00":
            try:  # EXIF is metadata only: a broken block costs the pixel size, not the image
                exif = _tiff_resolution(_tiff_ifd0(seg, 6), "EXIF resolution")
            except (_Bad, struct.error, ValueError):
                exif = []
        pos += 2 + seglen


def _jpeg_check(data: bytes, sos: int) -> None:
    # Inside entropy-coded data every 0xFF is stuffed or a restart marker, and thumbnails
    # (in APP segments) lie before the first scan: an FFD9 after it is the real EOI.
    if data.rfind(b"\xff\xd9", sos) < 0:
        raise _Bad("JPEG truncated (no end-of-image marker)")


def _bmp_header(data: bytes) -> tuple[_Header, int, int, int]:
    """Returns the header, pixel-array offset, bits per pixel and compression."""
    if len(data) < 26:
        raise _Bad("BMP truncated (header incomplete)")
    offset, dib = struct.unpack_from("<II", data, 10)
    if dib == 12:
        width, height, planes, bpp = struct.unpack_from("<HHHH", data, 18)
        compression, res = 0, []
    elif dib in (40, 52, 56, 64, 108, 124):
        if len(data) < 14 + 40:
            raise _Bad("BMP truncated (header incomplete)")
        width, height, planes, bpp, compression, _, xppm, yppm = struct.unpack_from(
            "<iiHHIIii", data, 18)
        height = abs(height)  # negative: rows stored top-down
        res = [(float(xppm), float(yppm), "m", "BMP resolution")] if xppm > 0 and yppm > 0 else []
    else:
        raise _Bad(f"unsupported BMP header size {dib}")
    if width <= 0 or height <= 0 or planes != 1 or bpp not in (1, 4, 8, 16, 24, 32):
        raise _Bad(f"corrupt BMP header ({width} x {height} px, {bpp} bits per pixel)")
    if compression not in (0, 1, 2, 3, 6):
        raise _Bad(f"unsupported BMP compression {compression}")
    channels = 4 if bpp == 32 and compression in (3, 6) else (3 if bpp > 8 else 1)
    return _Header("BMP", width, height, channels, res, bits=8), offset, bpp, compression


def _bmp_check(data: bytes, header: _Header, offset: int, bpp: int, compression: int) -> None:
    if offset >= len(data):
        raise _Bad("BMP truncated (no pixel data)")
    if compression in (0, 3, 6):  # uncompressed: the pixel array size is known exactly
        stride = ((header.width * bpp + 31) // 32) * 4
        need = offset + stride * header.height
        if need > len(data):
            raise _Bad(f"BMP truncated ({len(data)} of {need} bytes)")


def _tiff_header(data: bytes) -> _Header:
    tags = _tiff_ifd0(data, 0)
    if 256 not in tags or 257 not in tags:
        raise _Bad("corrupt TIFF: no image width/length")
    width, height = int(tags[256][0]), int(tags[257][0])
    spp = int(tags[277][0]) if 277 in tags else 1
    bits = int(tags[258][0]) if 258 in tags else 1
    photometric = int(tags[262][0]) if 262 in tags else 1
    sample_format = int(tags[339][0]) if 339 in tags else 1
    if width <= 0 or height <= 0 or not 1 <= spp <= 8:
        raise _Bad(f"corrupt TIFF header ({width} x {height} px, {spp} samples per pixel)")
    channels = 3 if photometric == 3 else min(spp, 4)
    return _Header("TIFF", width, height, channels, _tiff_resolution(tags, "TIFF resolution"),
                   sample_format=sample_format, bits=bits, tags=tags)


def _tiff_check(data: bytes, header: _Header) -> None:
    tags = header.tags
    if header.sample_format not in (1, 4) or header.bits > 16:
        kind = {2: "signed-integer ", 3: "floating-point "}.get(header.sample_format, "")
        raise _Bad(f"{header.bits}-bit {kind}TIFF is not a photograph (8 or 16 bit unsigned); "
                   "give height maps as .npy or .exr")
    for off_tag, cnt_tag, what in ((273, 279, "strip"), (324, 325, "tile")):
        if off_tag in tags:
            offsets = tags[off_tag].astype(np.uint64)
            counts = tags.get(cnt_tag)
            if counts is None or len(counts) != len(offsets):
                raise _Bad(f"corrupt TIFF: {what} offsets without matching byte counts")
            ends = offsets + counts.astype(np.uint64)
            if int(ends.max()) > len(data):
                raise _Bad(f"TIFF truncated ({what} data runs past the end of the file)")
            return
    raise _Bad("corrupt TIFF: no strip or tile data")


# --------------------------------------------------------------------------- pixel size


def _pixel_size(resolutions: list[tuple[float, float, str, str]]) -> tuple[float | None, str]:
    """The first plausible pixel size among the candidates, and a note saying why."""
    factors = {"inch": 25400.0, "cm": 1e4, "m": 1e6}
    rejected = []
    for x, y, unit, source in resolutions:
        if unit not in factors:
            rejected.append(f"{source} has no absolute unit")
            continue
        if not (math.isfinite(x) and math.isfinite(y) and x > 0 and y > 0):
            rejected.append(f"{source} is not a positive number")
            continue
        um_x, um_y = factors[unit] / x, factors[unit] / y
        dpi = 25400.0 / um_x
        text = (f"{source} {x:g} dpi" if unit == "inch"
                else f"{source} {x:g} px/{unit} ({dpi:.4g} dpi)")
        if abs(um_x - um_y) > 0.01 * max(um_x, um_y):
            rejected.append(f"{source} has non-square pixels ({um_x:.3g} x {um_y:.3g} µm)")
        elif any(abs(dpi - d) < 0.5 for d in _DEFAULT_DPI):
            rejected.append(f"{text} is a software default")
        elif not PLAUSIBLE_PIXEL_UM[0] <= um_x <= PLAUSIBLE_PIXEL_UM[1]:
            rejected.append(f"{text} gives {um_x:.4g} µm/px, outside "
                            f"{PLAUSIBLE_PIXEL_UM[0]:g}-{PLAUSIBLE_PIXEL_UM[1]:g} µm/px")
        else:
            return um_x, f"pixel size {um_x:.6g} µm from {text}"
    if rejected:
        return None, "no usable resolution metadata (" + "; ".join(rejected) + ")"
    return None, "no usable resolution metadata"


# --------------------------------------------------------------------------- public reader


def _identify(data: bytes) -> str:
    if data.startswith(_PNG_SIGNATURE):
        return "PNG"
    if data.startswith(b"\xff\xd8\xff"):
        return "JPEG"
    if data.startswith(b"BM"):
        return "BMP"
    if data[:4] in (b"II*\x00", b"MM\x00*", b"II+\x00", b"MM\x00+"):
        return "TIFF"
    raise _Bad("not a JPEG, PNG, BMP or TIFF image (unrecognised file content)")


def _decode(data: bytes, flags: int) -> tuple[np.ndarray | None, list[str]]:
    """cv2.imdecode with OpenCV's own log messages silenced (our error says it once), and the
    lines its codecs print themselves (libjpeg: "Corrupt JPEG data: ...") kept for the caller."""
    level = cv2.utils.logging.getLogLevel()
    cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_SILENT)
    try:
        with captured_native_output() as lines:
            pixels = cv2.imdecode(np.frombuffer(data, dtype=np.uint8), flags)
        return pixels, lines
    finally:
        cv2.utils.logging.setLogLevel(level)


def _warn_transparency(path: str | Path, data: bytes) -> None:
    """Warn when an image with an alpha channel has pixels that are not opaque: alpha is
    dropped, so a swatch cut out on a transparent background was compiled with its background's
    colour values as texture, without a word."""
    try:
        pixels, _ = _decode(data, cv2.IMREAD_UNCHANGED)
    except cv2.error:  # (decoded once already: the image itself is read)
        return
    if pixels is None or pixels.ndim != 3 or pixels.shape[2] not in (2, 4):
        return
    alpha = pixels[:, :, -1]
    clear = float(np.mean(alpha < np.iinfo(alpha.dtype).max))
    if clear > 0:
        LOG.warning("%s: %.3g%% of its pixels are transparent or partly so: transparency is ignored (their colour"
                    " values are compiled as texture); crop to the fabric", path, 100 * clear)


def _to_grey(pixels: np.ndarray) -> np.ndarray:
    """Decoded uint8/uint16 pixels (grey, BGR or BGRA) -> float64 luma in [0, 1]."""
    scale = 1.0 / float(np.iinfo(pixels.dtype).max)
    if pixels.ndim == 3 and pixels.shape[2] == 1:
        pixels = pixels[:, :, 0]
    if pixels.ndim == 2:
        return np.multiply(pixels, scale, dtype=np.float64)
    grey = np.empty(pixels.shape[:2])
    code = cv2.COLOR_BGRA2GRAY if pixels.shape[2] == 4 else cv2.COLOR_BGR2GRAY
    # OpenCV's float32 conversion uses exactly the Rec. 601 weights and is SIMD-fast; its
    # rounding error (< 0.02 of a 16-bit step) is far below the input's quantisation.
    # Blocks of rows bound the temporary copies.
    step = max(1, (1 << 20) // pixels.shape[1])
    for y0 in range(0, pixels.shape[0], step):
        block = cv2.cvtColor(pixels[y0:y0 + step].astype(np.float32), code)
        np.multiply(block, scale, out=grey[y0:y0 + step], dtype=np.float64)
    # Float32 weights sum to 1 + 6e-8: keep white at exactly 1.  Nothing can be negative.
    return np.minimum(grey, 1.0, out=grey)


def read_image(path: str | os.PathLike, *, max_pixels: int = 200_000_000) -> ImageData:
    """Read a photograph (JPEG, PNG, BMP or TIFF; 8 or 16 bit; grey or colour) as grey in [0, 1].

    Parameters
    ----------
    path : str or os.PathLike
        The image file; its format is recognised from its content.
    max_pixels : int
        Largest accepted width x height; checked from the header before any decoding.

    Returns
    -------
    ImageData
        The grey image (float64 [ny, nx] in [0, 1]), bit depth kept, channels in the file,
        pixel size from plausible metadata (µm/px) or None, and a note on the metadata.

    Raises
    ------
    InputError
        For a missing file, a directory, an empty, truncated, corrupt or unsupported file, an
        image larger than `max_pixels` or smaller than 8 x 8 pixels.
    """
    data = read_file_bytes(path, "image")
    try:
        fmt = _identify(data)
        try:
            if fmt == "PNG":
                header = _png_header(data)
            elif fmt == "JPEG":
                header, sos = _jpeg_header(data)
            elif fmt == "BMP":
                header, offset, bpp, compression = _bmp_header(data)
            else:
                header = _tiff_header(data)
        except (struct.error, IndexError, ValueError) as exc:
            raise _Bad(f"corrupt or truncated {fmt} header ({exc})") from None
        w, h = header.width, header.height
        if w * h > max_pixels:
            raise _Bad(f"image claims {w} x {h} pixels ({w * h / 1e6:.1f} MP), more than the "
                       f"limit of {max_pixels / 1e6:.1f} MP")
        if min(w, h) < MIN_SIDE_PX:
            raise _Bad(f"image too small ({w} x {h} pixels; at least {MIN_SIDE_PX} x "
                       f"{MIN_SIDE_PX} needed)")
        try:
            if fmt == "PNG":
                _png_check(data, header)
            elif fmt == "JPEG":
                _jpeg_check(data, sos)
            elif fmt == "BMP":
                _bmp_check(data, header, offset, bpp, compression)
            else:
                _tiff_check(data, header)
        except (struct.error, IndexError, ValueError, OverflowError) as exc:
            raise _Bad(f"corrupt {fmt} file ({exc})") from None

        # A 3-component JPEG decodes straight to its Y (Rec. 601 luma) channel: exact, faster.
        if fmt == "JPEG" and header.channels in (1, 3):
            flags = cv2.IMREAD_GRAYSCALE
        else:
            flags = cv2.IMREAD_ANYDEPTH | cv2.IMREAD_ANYCOLOR
        try:
            pixels, said = _decode(data, flags)
        except cv2.error as exc:
            raise _Bad(f"cannot decode {fmt} data ({str(exc).strip().splitlines()[-1]})") from None
        if pixels is None or pixels.size == 0:
            raise _Bad(f"cannot decode {fmt} data ({said[0] if said else 'corrupt or unsupported file'})")
        for line in dict.fromkeys(said):  # decoded, with the codec's complaints (a damaged JPEG)
            LOG.warning("%s: the %s decoder says: %s", path, fmt, line)
        if pixels.shape[:2] not in ((h, w), (w, h)):  # (w, h): EXIF orientation applied
            raise _Bad(f"decoded {pixels.shape[1]} x {pixels.shape[0]} pixels but the header "
                       f"says {w} x {h} (corrupt file)")
        if header.channels in (2, 4) and fmt != "JPEG":  # (a 4-channel JPEG is CMYK)
            _warn_transparency(path, data)
        if pixels.dtype == np.uint8:
            bit_depth = 8
        elif pixels.dtype == np.uint16:
            bit_depth = 16
        else:
            raise _Bad(f"unsupported sample type {pixels.dtype} (only 8- and 16-bit images)")
    except _Bad as exc:
        raise InputError(path, str(exc)) from None

    pixel_size_um, note = _pixel_size(header.resolutions)
    suffix = Path(path).suffix.lower()
    expected = {".jpg": "JPEG", ".jpeg": "JPEG", ".png": "PNG", ".bmp": "BMP", ".tif": "TIFF",
                ".tiff": "TIFF"}.get(suffix)
    if expected is not None and expected != fmt:
        note += f"; file content is {fmt} despite its {suffix} suffix"
    return ImageData(grey=_to_grey(pixels), bit_depth=bit_depth, channels=header.channels,
                     pixel_size_um=pixel_size_um, metadata_note=note)
