"""Tests of the input readers (photographs, .npy/.exr height maps) and the EXR writer.

Files are crafted byte by byte where the point is the file structure (PNG chunks, TIFF tags,
a header claiming 100 000 x 100 000 pixels), so each test knows the exact expected answer.
The fuzz tests feed random bytes and damaged valid files of every format to every reader and
require either valid data or an InputError; the number of inputs tried is printed at the end
of the module (set HAPTEX_FUZZ_EXAMPLES to run more, HAPTEX_FUZZ_RANDOM=1 for new inputs).
"""
from __future__ import annotations

import collections
import io
import os
import struct
import time
import zlib
from pathlib import Path

import cv2
import numpy as np
import OpenEXR
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from haptex_compile import io_exr
from haptex_compile.errors import InputError
from haptex_compile.io_exr import read_exr_channels, write_exr
from haptex_compile.io_heightmaps import read_height_exr, read_height_npy
from haptex_compile.io_images import SUPPORTED_IMAGE_SUFFIXES, ImageData, read_image

# --------------------------------------------------------------------------- file crafting


def _chunk(ctype: bytes, payload: bytes) -> bytes:
    return struct.pack(">I", len(payload)) + ctype + payload + struct.pack(
        ">I", zlib.crc32(ctype + payload))


def png_bytes(pixels: np.ndarray, colour_type: int, depth: int = 8, *, extra: bytes = b"",
              plte: bytes = b"", ihdr_size: tuple[int, int] | None = None) -> bytes:
    """A PNG written from the specification (filter 0 on every row, one IDAT).

    `pixels` is [ny, nx] or [ny, nx, c] in file channel order (RGB, not BGR).
    """
    ny, nx = pixels.shape[:2]
    width, height = ihdr_size or (nx, ny)
    if depth == 16:
        rows = pixels.astype(">u2").reshape(ny, -1).view(np.uint8)
    else:
        rows = pixels.astype(np.uint8).reshape(ny, -1)
    raw = np.concatenate([np.zeros((ny, 1), np.uint8), rows], axis=1).tobytes()
    ihdr = struct.pack(">IIBBBBB", width, height, depth, colour_type, 0, 0, 0)
    return (b"\x89PNG\r\n\x1a\n" + _chunk(b"IHDR", ihdr) + extra
            + (_chunk(b"PLTE", plte) if plte else b"")
            + _chunk(b"IDAT", zlib.compress(raw, 6)) + _chunk(b"IEND", b""))


def phys_chunk(px_per_m_x: int, px_per_m_y: int, unit: int = 1) -> bytes:
    return _chunk(b"pHYs", struct.pack(">IIB", px_per_m_x, px_per_m_y, unit))


def tiff_bytes(pixels: np.ndarray, *, resolution: tuple[int, int] | None = None,
               unit: int = 2, size: tuple[int, int] | None = None) -> bytes:
    """An uncompressed little-endian TIFF (one strip) written from the specification."""
    ny, nx = pixels.shape[:2]
    spp = 1 if pixels.ndim == 2 else pixels.shape[2]
    bits = 16 if pixels.dtype == np.uint16 else 8
    data = pixels.astype("<u2" if bits == 16 else np.uint8).tobytes()
    width, height = size or (nx, ny)
    entries = [(256, 4, 1, width), (257, 4, 1, height), (258, 3, 1, bits), (259, 3, 1, 1),
               (262, 3, 1, 2 if spp == 3 else 1), (273, 4, 1, 0), (277, 3, 1, spp),
               (278, 4, 1, ny), (279, 4, 1, len(data))]
    if resolution is not None:
        entries += [(282, 5, 1, 0), (283, 5, 1, 0), (296, 3, 1, unit)]
    if spp == 3:
        entries[2] = (258, 3, 1, bits)  # libtiff accepts a single BitsPerSample value
    ifd_size = 2 + 12 * len(entries) + 4
    rational_at = 8 + ifd_size
    data_at = rational_at + 16
    out = bytearray(b"II*\x00" + struct.pack("<I", 8) + struct.pack("<H", len(entries)))
    for tag, typ, count, value in sorted(entries):
        if tag == 273:
            value = data_at
        elif tag in (282, 283):
            value = rational_at + (0 if tag == 282 else 8)
        fmt = "<HHIH2x" if typ == 3 else "<HHII"
        out += struct.pack(fmt, tag, typ, count, value)
    out += struct.pack("<I", 0)
    num, den = resolution if resolution is not None else (0, 1)
    out += struct.pack("<IIII", num, den, num, den)
    return bytes(out) + data


def jpeg_bytes(pixels: np.ndarray, **params: int) -> bytes:
    flags = []
    for key, value in params.items():
        flags += [getattr(cv2, key), value]
    ok, buf = cv2.imencode(".jpg", pixels, flags)
    assert ok
    return buf.tobytes()


def jpeg_with_app(jpeg: bytes, marker: int, payload: bytes) -> bytes:
    """Insert an APPn segment right after SOI."""
    return jpeg[:2] + bytes([0xFF, marker]) + struct.pack(">H", len(payload) + 2) + payload + jpeg[2:]


def exif_payload(orientation: int = 1, xres: tuple[int, int] | None = None) -> bytes:
    """An EXIF APP1 payload with a big-endian IFD0 holding Orientation and resolution."""
    entries = [(274, 3, 1, orientation)]
    if xres is not None:
        entries += [(282, 5, 1, 0), (283, 5, 1, 0), (296, 3, 1, 2)]
    ifd = struct.pack(">H", len(entries))
    rational_at = 8 + 2 + 12 * len(entries) + 4
    for tag, typ, count, value in entries:
        if typ == 3:
            ifd += struct.pack(">HHIH2x", tag, typ, count, value)
        else:
            ifd += struct.pack(">HHII", tag, typ, count, rational_at + (0 if tag == 282 else 8))
    ifd += struct.pack(">I", 0)
    rationals = struct.pack(">IIII", *(xres + xres)) if xres else b""
    return b"Exif\x00\x00" + b"MM\x00*" + struct.pack(">I", 8) + ifd + rationals


def patch_jpeg_size(jpeg: bytes, width: int, height: int) -> bytes:
    pos = jpeg.find(b"\xff\xc0")
    assert pos > 0
    return jpeg[:pos + 5] + struct.pack(">HH", height, width) + jpeg[pos + 9:]


def encode(ext: str, pixels: np.ndarray, *params: int) -> bytes:
    ok, buf = cv2.imencode(ext, pixels, list(params))
    assert ok
    return buf.tobytes()


def texture(ny: int, nx: int, seed: int = 0) -> np.ndarray:
    """A smooth random texture in [0, 1] (so that JPEG keeps it well)."""
    rng = np.random.default_rng(seed)
    noise = rng.standard_normal((ny, nx))
    smooth = cv2.GaussianBlur(noise, (0, 0), 2.0)
    return (smooth - smooth.min()) / (smooth.max() - smooth.min())


def write(tmp_path: Path, name: str, data: bytes) -> Path:
    path = tmp_path / name
    path.write_bytes(data)
    return path


# --------------------------------------------------------------------------- photographs


def test_16bit_png_and_tiff_keep_all_16_bits(tmp_path):
    # Values that are not multiples of 257 cannot survive a round trip through 8 bits.
    values = (np.arange(40 * 30).reshape(30, 40) * 53 + 7) % 65536
    values = values.astype(np.uint16)
    for name, data in (("g16.png", png_bytes(values, 0, 16)),
                       ("g16.tif", tiff_bytes(values)),
                       ("g16cv.png", encode(".png", values)),
                       ("g16cv.tif", encode(".tif", values))):
        image = read_image(write(tmp_path, name, data))
        assert image.bit_depth == 16 and image.channels == 1, name
        np.testing.assert_array_equal(np.rint(image.grey * 65535).astype(np.int64), values)


def test_colour_becomes_rec601_luma_and_alpha_is_dropped(tmp_path):
    rng = np.random.default_rng(1)
    rgb = rng.integers(0, 65536, size=(20, 24, 3), dtype=np.uint16)
    expected = (0.299 * rgb[..., 0] + 0.587 * rgb[..., 1] + 0.114 * rgb[..., 2]) / 65535
    alpha = rng.integers(0, 65536, size=(20, 24, 1), dtype=np.uint16)
    for name, data, channels in (
            ("rgb16.png", png_bytes(rgb, 2, 16), 3),
            ("rgba16.png", png_bytes(np.concatenate([rgb, alpha], axis=2), 6, 16), 4),
            ("rgb16.tif", tiff_bytes(rgb), 3)):
        image = read_image(write(tmp_path, name, data))
        assert image.channels == channels and image.bit_depth == 16, name
        # Within 5 % of one 16-bit step: the 16 bits survive the colour conversion.
        np.testing.assert_allclose(image.grey, expected, rtol=0, atol=0.05 / 65535, err_msg=name)


def test_pure_primaries_give_their_luma_weights_in_every_format(tmp_path):
    for weight, bgr in ((0.299, (0, 0, 255)), (0.587, (0, 255, 0)), (0.114, (255, 0, 0))):
        pixels = np.zeros((16, 16, 3), np.uint8)
        pixels[:] = bgr
        for ext, tol in ((".png", 1e-6), (".bmp", 1e-6), (".tif", 1e-6), (".jpg", 1.5 / 255)):
            image = read_image(write(tmp_path, "p" + ext, encode(ext, pixels)))
            assert abs(image.grey.mean() - weight) <= tol, (ext, weight)


def test_palette_and_grey_alpha_png(tmp_path):
    index = (np.arange(16 * 16).reshape(16, 16) % 3).astype(np.uint8)
    palette = bytes([255, 0, 0, 0, 255, 0, 0, 0, 255])
    image = read_image(write(tmp_path, "pal.png", png_bytes(index, 3, plte=palette)))
    expected = np.array([0.299, 0.587, 0.114])[index]
    assert image.channels == 3
    np.testing.assert_allclose(image.grey, expected, atol=1e-6)
    grey_alpha = np.stack([index * 100, 255 - index * 100], axis=2)
    image = read_image(write(tmp_path, "la.png", png_bytes(grey_alpha, 4)))
    assert image.channels == 2
    np.testing.assert_allclose(image.grey, index * 100 / 255, atol=1e-12)


def test_jpeg_grey_matches_the_texture(tmp_path):
    grey = texture(64, 96)
    pixels = np.rint(grey * 255).astype(np.uint8)
    colour = np.repeat(pixels[:, :, None], 3, axis=2)
    for name, data in (("g.jpg", jpeg_bytes(pixels, IMWRITE_JPEG_QUALITY=95)),
                       ("c.jpg", jpeg_bytes(colour, IMWRITE_JPEG_QUALITY=95)),
                       ("p.jpg", jpeg_bytes(colour, IMWRITE_JPEG_PROGRESSIVE=1))):
        image = read_image(write(tmp_path, name, data))
        assert image.grey.shape == (64, 96) and image.bit_depth == 8
        # Quality 95 on a smooth texture: a couple of grey levels at most.
        assert np.abs(image.grey - pixels / 255).max() < 4 / 255, name


@pytest.mark.parametrize("make, expected_um, why", [
    (lambda p: png_bytes(p, 0, extra=phys_chunk(100_000, 100_000)), 10.0, "PNG pHYs"),
    (lambda p: png_bytes(p, 0, extra=phys_chunk(40_000, 40_000)), 25.0, "PNG pHYs"),
    (lambda p: tiff_bytes(p, resolution=(2540, 1)), 10.0, "TIFF resolution 2540 dpi"),
    (lambda p: tiff_bytes(p, resolution=(5000, 3), unit=3), 6.0, "TIFF resolution"),
    (lambda p: encode(".tif", p, cv2.IMWRITE_TIFF_XDPI, 1270, cv2.IMWRITE_TIFF_YDPI, 1270,
                      cv2.IMWRITE_TIFF_RESUNIT, 2), 20.0, "TIFF resolution 1270 dpi"),
    (lambda p: jpeg_with_app(jpeg_bytes(p), 0xE1, exif_payload(1, (2540, 1))), 10.0, "EXIF"),
    (lambda p: jpeg_with_app(jpeg_bytes(p), 0xE0, b"JFIF\x00\x01\x02\x02" + struct.pack(">HH", 400, 400)
                             + b"\x00\x00"), 25.0, "JFIF density 400 per cm"),
])
def test_pixel_size_from_metadata(tmp_path, make, expected_um, why):
    pixels = np.rint(texture(16, 16) * 255).astype(np.uint8)
    image = read_image(write(tmp_path, "m.img", make(pixels)))
    assert image.pixel_size_um == pytest.approx(expected_um, rel=1e-9)
    assert why.split()[0] in image.metadata_note and "µm" in image.metadata_note


def test_bmp_pixel_size_from_pels_per_metre(tmp_path):
    data = bytearray(encode(".bmp", np.full((16, 16), 100, np.uint8)))
    data[38:46] = struct.pack("<ii", 50_000, 50_000)  # 20 µm per pixel
    image = read_image(write(tmp_path, "r.bmp", bytes(data)))
    assert image.pixel_size_um == pytest.approx(20.0)


@pytest.mark.parametrize("chunk, reason", [
    (phys_chunk(2835, 2835), "software default"),          # 72 dpi
    (phys_chunk(3780, 3780), "software default"),          # 96 dpi
    (phys_chunk(2_000_000, 2_000_000), "outside"),         # 0.5 µm/px
    (phys_chunk(1000, 1000), "outside"),                   # 1 mm/px
    (phys_chunk(100_000, 50_000), "non-square"),
    (phys_chunk(100_000, 100_000, unit=0), "no absolute unit"),
    (phys_chunk(0, 0), "not a positive"),
    (b"", "no usable"),
])
def test_implausible_pixel_size_is_ignored_with_a_reason(tmp_path, chunk, reason):
    pixels = np.zeros((16, 16), np.uint8)
    image = read_image(write(tmp_path, "x.png", png_bytes(pixels, 0, extra=chunk)))
    assert image.pixel_size_um is None
    assert reason in image.metadata_note and "no usable" in image.metadata_note


def test_pixel_size_from_a_corrupt_ancillary_chunk_is_not_trusted(tmp_path):
    chunk = bytearray(phys_chunk(100_000, 100_000))
    chunk[-1] ^= 0xFF  # bad checksum: libpng would skip the chunk, so do we
    image = read_image(write(tmp_path, "c.png", png_bytes(np.zeros((16, 16)), 0, extra=bytes(chunk))))
    assert image.pixel_size_um is None


def test_exif_orientation_is_applied(tmp_path):
    pixels = np.zeros((16, 32), np.uint8)
    pixels[:, :8] = 255  # a bright band on the left
    data = jpeg_with_app(jpeg_bytes(pixels, IMWRITE_JPEG_QUALITY=100), 0xE1, exif_payload(6))
    image = read_image(write(tmp_path, "o.jpg", data))
    # Orientation 6: the viewer rotates 90° clockwise, so the left band ends up on top.
    assert image.grey.shape == (32, 16)
    assert image.grey[:8].mean() > 0.9 and image.grey[8:].mean() < 0.1


def test_constant_and_minimum_size_images_are_read(tmp_path):
    for ext in (".png", ".jpg", ".bmp", ".tif"):
        image = read_image(write(tmp_path, "k" + ext, encode(ext, np.full((8, 8), 77, np.uint8))))
        assert image.grey.shape == (8, 8)
        assert np.ptp(image.grey) == 0 and abs(image.grey[0, 0] - 77 / 255) < 1.5 / 255


@pytest.mark.parametrize("ext", [".png", ".jpg", ".bmp", ".tif"])
@pytest.mark.parametrize("shape", [(1, 1), (7, 7), (100, 7), (1, 50)])
def test_too_small_images_are_refused(tmp_path, ext, shape):
    path = write(tmp_path, "s" + ext, encode(ext, np.full(shape, 9, np.uint8)))
    with pytest.raises(InputError, match="too small"):
        read_image(path)


def _huge_files() -> dict[str, bytes]:
    small = np.full((16, 16), 50, np.uint8)
    bmp = bytearray(encode(".bmp", small))
    bmp[18:26] = struct.pack("<ii", 100_000, 100_000)
    return {
        "png": png_bytes(small, 0, ihdr_size=(100_000, 100_000)),  # valid checksum
        # JPEG sizes are 16-bit: 65 000 x 65 000 is the largest claim it can make.
        "jpg": patch_jpeg_size(jpeg_bytes(small), 65_000, 65_000),
        "bmp": bytes(bmp),
        "tif": tiff_bytes(small, size=(100_000, 100_000)),
    }


@pytest.mark.parametrize("ext", ["png", "jpg", "bmp", "tif"])
def test_header_claiming_100000_squared_pixels_is_refused_before_decoding(tmp_path, ext):
    path = write(tmp_path, "huge." + ext, _huge_files()[ext])
    side = 65000 if ext == "jpg" else 100000
    start = time.perf_counter()
    with pytest.raises(InputError, match=f"{side} x {side} pixels") as info:
        read_image(path)
    assert time.perf_counter() - start < 0.5  # nothing was decoded or allocated
    assert str(path) in str(info.value) and "\n" not in str(info.value)
    # The limit is a parameter: a 16 x 16 file is refused below 256 pixels, read at 256.
    small = write(tmp_path, "small." + ext, encode("." + ext, np.full((16, 16), 3, np.uint8)))
    with pytest.raises(InputError, match="16 x 16"):
        read_image(small, max_pixels=255)
    assert read_image(small, max_pixels=256).grey.shape == (16, 16)


def test_png_within_the_limit_but_with_too_little_data_is_refused_before_decoding(tmp_path):
    # 10 000 x 10 000 is under the default limit, but 16 x 16 pixels of deflate data cannot
    # expand (at most 1032-fold) to 100 MB: refused without allocating the image.
    data = png_bytes(np.full((16, 16), 5, np.uint8), 0, ihdr_size=(10_000, 10_000))
    start = time.perf_counter()
    with pytest.raises(InputError, match="cannot hold 10000 x 10000 pixels"):
        read_image(write(tmp_path, "bomb.png", data))
    assert time.perf_counter() - start < 0.5
    # The bound is not too tight: the most compressible real image (constant) still reads.
    constant = encode(".png", np.zeros((2000, 3000), np.uint8))
    assert read_image(write(tmp_path, "zero.png", constant)).grey.shape == (2000, 3000)


def _valid_files() -> dict[str, bytes]:
    grey = np.rint(texture(40, 48, seed=2) * 255).astype(np.uint8)
    colour = np.stack([grey, grey[::-1], grey[:, ::-1]], axis=2)
    return {
        "grey.png": encode(".png", grey),
        "colour16.png": encode(".png", colour.astype(np.uint16) * 257),
        "grey.jpg": jpeg_bytes(grey),
        "colour.jpg": jpeg_bytes(colour),
        "progressive.jpg": jpeg_bytes(colour, IMWRITE_JPEG_PROGRESSIVE=1),
        "grey.bmp": encode(".bmp", grey),
        "colour.bmp": encode(".bmp", colour),
        "grey.tif": tiff_bytes(grey),
        "colour16lzw.tif": encode(".tif", colour.astype(np.uint16) * 257),
    }


@pytest.mark.parametrize("name", sorted(_valid_files()))
def test_truncated_images_are_refused_at_every_cut(tmp_path, name):
    data = _valid_files()[name]
    assert read_image(write(tmp_path, name, data)).grey.shape == (40, 48)
    # Every cut from 1 byte to the last byte (stride keeps the test quick, ends dense).
    cuts = sorted(set(range(1, len(data), max(1, len(data) // 97))) | set(range(len(data) - 24, len(data))))
    for cut in cuts:
        path = write(tmp_path, name, data[:cut])
        with pytest.raises(InputError):
            read_image(path)


def test_missing_empty_directory_and_foreign_files(tmp_path):
    cases = {
        "missing": (tmp_path / "nope.png", "no such image"),
        "directory": (tmp_path, "is a directory"),
        "empty": (write(tmp_path, "empty.jpg", b""), "empty image"),
        "text": (write(tmp_path, "t.png", b"this is not an image\n" * 5), "not a JPEG, PNG"),
        "gif": (write(tmp_path, "g.png", b"GIF89a" + bytes(100)), "not a JPEG, PNG"),
        "float tiff": (write(tmp_path, "f.tif", encode(".tif", np.ones((16, 16), np.float32))),
                       "floating-point"),
    }
    for label, (path, message) in cases.items():
        with pytest.raises(InputError, match=message) as info:
            read_image(path)
        assert str(path) in str(info.value), label
        assert "\n" not in str(info.value), label


def test_format_comes_from_content_and_a_wrong_suffix_is_noted(tmp_path):
    image = read_image(write(tmp_path, "really_png.jpg", encode(".png", np.zeros((9, 9), np.uint8))))
    assert image.grey.shape == (9, 9) and "PNG despite its .jpg suffix" in image.metadata_note
    assert set(SUPPORTED_IMAGE_SUFFIXES) == {".jpg", ".jpeg", ".png", ".bmp", ".tif", ".tiff"}


def test_png_critical_chunk_corruption_is_refused(tmp_path):
    data = bytearray(encode(".png", np.rint(texture(20, 20) * 255).astype(np.uint8)))
    idat = data.find(b"IDAT")
    data[idat + 10] ^= 0x01  # one bit inside the compressed pixels
    with pytest.raises(InputError, match="checksum error in IDAT"):
        read_image(write(tmp_path, "bit.png", bytes(data)))


@pytest.mark.shared
def test_real_fabric_photographs(shared_fabrics):
    for path in sorted(shared_fabrics.iterdir()):
        if path.suffix.lower() not in SUPPORTED_IMAGE_SUFFIXES:
            continue
        image = read_image(path)
        reference = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
        assert image.grey.shape == reference.shape, path.name
        assert np.isfinite(image.grey).all() and image.grey.std() > 0.02, path.name
        # OpenCV's own grey conversion rounds to 8 bits: within one level of ours.
        assert np.abs(image.grey * 255 - reference).max() <= 1.0 + 1e-9, path.name


# --------------------------------------------------------------------------- height maps


def _npy(array: np.ndarray, **kwargs) -> bytes:
    buffer = io.BytesIO()
    np.save(buffer, array, **kwargs)
    return buffer.getvalue()


def test_npy_heights_come_back_exactly_in_float64(tmp_path):
    rng = np.random.default_rng(3)
    base = rng.normal(0, 5, size=(12, 10))
    for array in (base, base.astype(np.float32), np.asfortranarray(base), base.astype(">f8"),
                  np.rint(base * 100).astype(np.int16)):
        heights = read_height_npy(write(tmp_path, "h.npy", _npy(array)))
        assert heights.dtype == np.float64 and heights.shape == (12, 10)
        np.testing.assert_array_equal(heights, array.astype(np.float64))


@pytest.mark.parametrize("array, message", [
    (np.zeros((8, 8, 2)), "must be 2-D"),
    (np.zeros(64), "must be 2-D"),
    (np.zeros((7, 100)), "too small"),
    (np.zeros((1, 1)), "too small"),
    (np.zeros((0, 9)), "too small"),
    (np.zeros((8, 8), complex), "real numbers"),
    (np.zeros((8, 8), bool), "real numbers"),
    (np.zeros((8, 8), "U3"), "real numbers"),
    (np.zeros((8, 8), [("a", "f4"), ("b", "f4")]), "real numbers"),
])
def test_npy_bad_arrays_are_refused(tmp_path, array, message):
    with pytest.raises(InputError, match=message):
        read_height_npy(write(tmp_path, "bad.npy", _npy(array)))


def test_npy_object_array_is_refused_without_unpickling(tmp_path):
    sentinel = tmp_path / "pickle_ran"

    class Evil:
        def __reduce__(self):
            return (Path.touch, (sentinel,))

    array = np.empty((8, 8), dtype=object)
    array[0, 0] = Evil()
    with pytest.raises(InputError, match="real numbers"):
        read_height_npy(write(tmp_path, "obj.npy", _npy(array, allow_pickle=True)))
    assert not sentinel.exists()


@pytest.mark.parametrize("reader_ext", ["npy", "exr"])
def test_non_finite_heights_are_counted(tmp_path, reader_ext):
    heights = np.zeros((16, 16))
    heights[1, 2] = heights[3, 4] = np.nan
    heights[5, 6] = np.inf
    heights[7, 7] = -np.inf
    path = tmp_path / f"nan.{reader_ext}"
    if reader_ext == "npy":
        path.write_bytes(_npy(heights))
        reader = read_height_npy
    else:
        OpenEXR.File({"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage},
                     {"height": heights.astype(np.float32)}).write(str(path))
        reader = read_height_exr
    with pytest.raises(InputError, match=r"4 of 256 height values are not finite \(2 NaN, 2 inf\)"):
        reader(path)


def test_npy_damaged_files(tmp_path):
    good = _npy(np.ones((20, 20)))
    header_end = good.index(b"\n") + 1
    claim = io.BytesIO()
    np.lib.format.write_array_header_1_0(
        claim, {"descr": "<f8", "fortran_order": False, "shape": (100_000, 100_000)})
    huge = claim.getvalue() + bytes(800)
    cases = {
        "truncated": (good[:header_end + 100], "truncated"),
        "header only": (good[:header_end], "truncated"),
        "cut header": (good[:20], "corrupt .npy header"),
        "empty": (b"", "empty"),
        "not npy": (b"PK\x03\x04" + bytes(100), "not a .npy file"),
        "huge claim": (huge, "100000 x 100000"),
    }
    for label, (data, message) in cases.items():
        with pytest.raises(InputError, match=message):
            read_height_npy(write(tmp_path, "d.npy", data))
    with pytest.raises(InputError, match="not a .npy"):  # an .npz archive is not a .npy
        buffer = io.BytesIO()
        np.savez(buffer, height=np.ones((9, 9)))
        read_height_npy(write(tmp_path, "z.npy", buffer.getvalue()))
    with pytest.raises(InputError, match="no such"):
        read_height_npy(tmp_path / "missing.npy")
    with pytest.raises(InputError, match="directory"):
        read_height_npy(tmp_path)


def test_exr_height_channel_choice(tmp_path):
    rng = np.random.default_rng(4)
    height = rng.normal(0, 3, size=(9, 11))
    write_exr(tmp_path / "h.exr", {"a40": height * 2, "height": height, "a320": height * 0})
    np.testing.assert_array_equal(read_height_exr(tmp_path / "h.exr"), height.astype(np.float32))
    write_exr(tmp_path / "z.exr", {"Z": height})
    np.testing.assert_array_equal(read_height_exr(tmp_path / "z.exr"), height.astype(np.float32))
    write_exr(tmp_path / "rgb.exr", {"R": height, "G": height})
    with pytest.raises(InputError, match=r"no 'height' channel among 2 channels \(G, R\)"):
        read_height_exr(tmp_path / "rgb.exr")
    write_exr(tmp_path / "small.exr", {"height": np.ones((7, 30))})
    with pytest.raises(InputError, match="too small"):
        read_height_exr(tmp_path / "small.exr")


def test_exr_half_channels_and_offset_data_window_are_read(tmp_path):
    values = (np.arange(12 * 10).reshape(12, 10) / 8.0).astype(np.float16)  # exact in half
    path = str(tmp_path / "half.exr")
    header = {"compression": OpenEXR.PIZ_COMPRESSION, "type": OpenEXR.scanlineimage}
    OpenEXR.File(header, {"height": values}).write(path)
    np.testing.assert_array_equal(read_height_exr(path), values.astype(np.float64))
    assert read_exr_channels(path)["height"].dtype == np.float16


def test_exr_refusals(tmp_path):
    height = np.ones((10, 10), np.float32)
    multi = str(tmp_path / "multi.exr")
    OpenEXR.File([OpenEXR.Part({}, {"height": height}, "a"),
                  OpenEXR.Part({}, {"height": height}, "b")]).write(multi)
    cases = {
        multi: "multi-part",
        write(tmp_path, "e.exr", b""): "empty",
        write(tmp_path, "n.exr", b"\x89PNG" + bytes(64)): "not an OpenEXR",
        tmp_path / "missing.exr": "no such",
        tmp_path: "directory",
    }
    good = tmp_path / "good.exr"
    write_exr(good, {"height": np.ones((20, 20))})
    data = good.read_bytes()
    cases[write(tmp_path, "cut.exr", data[: len(data) - 30])] = "corrupt or unreadable"
    for path, message in cases.items():
        with pytest.raises(InputError, match=message):
            read_height_exr(path)
    with pytest.raises(InputError, match="20 x 20 pixels"):
        read_exr_channels(good, max_pixels=399)


# --------------------------------------------------------------------------- EXR writer


def _decode_exr_from_spec(data: bytes) -> tuple[dict, dict[str, np.ndarray], int]:
    """Decode a single-part scanline ZIP EXR of float32 channels, independent of OpenEXR.

    Follows the file-layout specification: magic, version, attributes, offset table, then
    chunks of 16 scanlines that are zlib-compressed after byte splitting and a delta predictor.
    """
    assert data[:4] == b"\x76\x2f\x31\x01"
    version, flags = data[4], int.from_bytes(data[5:8], "little")
    assert version == 2 and flags & 0x02 == 0 and flags & 0x10 == 0  # scanline, single part
    pos, attributes = 8, {}
    while data[pos] != 0:
        name_end = data.index(b"\x00", pos)
        type_end = data.index(b"\x00", name_end + 1)
        name = data[pos:name_end].decode()
        (size,) = struct.unpack_from("<i", data, type_end + 1)
        attributes[name] = (data[name_end + 1:type_end].decode(), data[type_end + 5:type_end + 5 + size])
        pos = type_end + 5 + size
    pos += 1
    assert attributes["compression"] == ("compression", b"\x03")  # ZIP_COMPRESSION, 16 lines per chunk
    x0, y0, x1, y1 = struct.unpack("<iiii", attributes["dataWindow"][1])
    nx, ny = x1 - x0 + 1, y1 - y0 + 1
    names, chlist = [], attributes["channels"][1]
    cpos = 0
    while chlist[cpos] != 0:
        end = chlist.index(b"\x00", cpos)
        pixel_type, _, xs, ys = struct.unpack_from("<iB3xii", chlist, end + 1)
        assert pixel_type == 2 and xs == ys == 1  # FLOAT, not sub-sampled
        names.append(chlist[cpos:end].decode())
        cpos = end + 1 + 16
    n_chunks = -(-ny // 16)
    offsets = struct.unpack_from(f"<{n_chunks}Q", data, pos)
    planes = {name: np.empty((ny, nx), np.float32) for name in names}
    compressed = 0
    for offset in offsets:
        y, size = struct.unpack_from("<ii", data, offset)
        lines = min(16, y1 - y + 1)
        raw_size = lines * len(names) * nx * 4
        block = data[offset + 8:offset + 8 + size]
        if size < raw_size:  # otherwise the chunk was stored uncompressed
            compressed += 1
            d = np.frombuffer(zlib.decompress(block), np.uint8).astype(np.int64)
            # Undo the predictor d[i] = t[i] - t[i-1] + 128 (mod 256) ...
            t = (np.cumsum(np.concatenate([d[:1], d[1:] - 128])) & 0xFF).astype(np.uint8)
            # ... and the byte split (even-indexed bytes first, then odd-indexed ones).
            half = (len(t) + 1) // 2
            raw = np.empty(len(t), np.uint8)
            raw[0::2], raw[1::2] = t[:half], t[half:]
            block = raw.tobytes()
        rows = np.frombuffer(block, "<f4").reshape(lines, len(names), nx)
        for index, name in enumerate(names):
            planes[name][y - y0:y - y0 + lines] = rows[:, index]
    return attributes, planes, compressed


def test_write_exr_is_standard_zip_scanline_float32(tmp_path):
    rng = np.random.default_rng(5)
    maps = {"height": rng.normal(0, 10, (37, 23)), "a40": rng.random((37, 23)),
            "a320": np.zeros((37, 23))}
    path = tmp_path / "out.exr"
    write_exr(path, maps, attributes={"pixel_size_um": "12.5", "speed_mm_s": "80"})
    attributes, planes, compressed = _decode_exr_from_spec(path.read_bytes())
    assert compressed >= 1  # the zlib path of the decoder was exercised
    assert sorted(planes) == ["a320", "a40", "height"]
    for name, values in maps.items():
        np.testing.assert_array_equal(planes[name], values.astype(np.float32))
    assert attributes["pixel_size_um"] == ("string", b"12.5")
    assert attributes["speed_mm_s"] == ("string", b"80")
    # And the OpenEXR library agrees.
    back = read_exr_channels(path)
    for name, values in maps.items():
        np.testing.assert_array_equal(back[name], values.astype(np.float32))


def test_write_exr_is_byte_identical_for_identical_input(tmp_path):
    maps = {"height": texture(200, 150, seed=6) * 40.0}
    write_exr(tmp_path / "a.exr", maps, attributes={"generator": "haptex"})
    write_exr(tmp_path / "b.exr", dict(maps), attributes={"generator": "haptex"})
    assert (tmp_path / "a.exr").read_bytes() == (tmp_path / "b.exr").read_bytes()


@pytest.mark.parametrize("failure", [RuntimeError("disk full"), KeyboardInterrupt()])
def test_write_exr_failure_keeps_the_old_file_and_leaves_no_temporary(tmp_path, monkeypatch, failure):
    path = tmp_path / "keep.exr"
    write_exr(path, {"height": np.ones((10, 10))})
    before = path.read_bytes()
    real_file = OpenEXR.File

    class Failing:
        def __init__(self, *args, **kwargs):
            self._file = real_file(*args, **kwargs)

        def write(self, target):
            self._file.write(target)  # the file's bytes are complete ...
            if isinstance(target, (str, Path)):
                with open(target, "r+b") as handle:
                    handle.truncate(100)  # ... then damaged, and the run dies
            else:  # (made in memory)
                target.truncate(100)
            raise failure

    monkeypatch.setattr(io_exr.OpenEXR, "File", Failing)
    with pytest.raises(type(failure) if isinstance(failure, KeyboardInterrupt) else InputError):
        write_exr(path, {"height": np.zeros((10, 10))})
    monkeypatch.undo()
    assert path.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["keep.exr"]


def test_write_exr_refuses_bad_channels(tmp_path):
    good = np.ones((8, 8))
    bad_cases = [
        ({}, "at least one channel"),
        ({"h": np.ones((8, 8, 2))}, "2-D"),
        ({"h": good, "g": np.ones((8, 9))}, "shape"),
        ({"h": np.array([[np.nan] * 8] * 8)}, "64 values that are not finite"),
        ({"h": good * 1e39}, "not finite in float32"),
        ({"": good}, "channel name"),
        ({"h": good.astype(complex)}, "real 2-D"),
    ]
    for channels, message in bad_cases:
        with pytest.raises(ValueError, match=message):
            write_exr(tmp_path / "x.exr", channels)
    with pytest.raises(ValueError, match="attribute"):
        write_exr(tmp_path / "x.exr", {"h": good}, attributes={"compression": "none"})
    with pytest.raises(InputError, match="directory does not exist"):
        write_exr(tmp_path / "no" / "x.exr", {"h": good})
    assert list(tmp_path.iterdir()) == []


# --------------------------------------------------------------------------- fuzzing

FUZZ_EXAMPLES = int(os.environ.get("HAPTEX_FUZZ_EXAMPLES", "250"))
FUZZ = settings(max_examples=FUZZ_EXAMPLES, deadline=None, database=None,
                derandomize=os.environ.get("HAPTEX_FUZZ_RANDOM") != "1",
                suppress_health_check=list(HealthCheck))
FUZZ_COUNTS: collections.Counter[str] = collections.Counter()


@pytest.fixture(scope="module", autouse=True)
def _report_fuzz_counts(request):
    yield
    if FUZZ_COUNTS:
        reporter = request.config.pluginmanager.get_plugin("terminalreporter")
        readers = sorted({key.split(":")[0] for key in FUZZ_COUNTS})
        parts = [f"{r}: {FUZZ_COUNTS[r + ':tried']} tried, {FUZZ_COUNTS[r + ':read']} read, "
                 f"{FUZZ_COUNTS[r + ':refused']} refused" for r in readers]
        total = sum(v for k, v in FUZZ_COUNTS.items() if k.endswith(":tried"))
        line = f"fuzzed readers with {total} inputs, none crashed ({'; '.join(parts)})"
        capture = request.config.pluginmanager.getplugin("capturemanager")
        if reporter is not None and capture is not None:
            with capture.global_and_fixture_disabled():  # shown even when output is captured
                reporter.write_line("\n" + line)
        else:  # pragma: no cover
            print(line)


def _check_image(result) -> None:
    assert isinstance(result, ImageData)
    grey = result.grey
    assert grey.dtype == np.float64 and grey.ndim == 2 and min(grey.shape) >= 8
    assert np.isfinite(grey).all() and grey.min() >= 0.0 and grey.max() <= 1.0
    assert result.bit_depth in (8, 16) and result.channels in (1, 2, 3, 4)
    assert result.pixel_size_um is None or 1.0 <= result.pixel_size_um <= 500.0
    assert isinstance(result.metadata_note, str) and "\n" not in result.metadata_note


def _check_heights(result) -> None:
    assert isinstance(result, np.ndarray) and result.dtype == np.float64
    assert result.ndim == 2 and min(result.shape) >= 8 and np.isfinite(result).all()


def _check_channels(result) -> None:
    assert isinstance(result, dict) and result
    shapes = {array.shape for array in result.values()}
    assert len(shapes) == 1 and len(next(iter(shapes))) == 2


READERS = {"read_image": (read_image, _check_image),
           "read_height_npy": (read_height_npy, _check_heights),
           "read_height_exr": (read_height_exr, _check_heights),
           "read_exr_channels": (read_exr_channels, _check_channels)}


def _try(reader_name: str, path: Path, data: bytes) -> None:
    reader, check = READERS[reader_name]
    path.write_bytes(data)
    FUZZ_COUNTS[reader_name + ":tried"] += 1
    try:
        result = reader(path)
    except InputError as exc:
        assert str(path) in str(exc) and "\n" not in str(exc)
        FUZZ_COUNTS[reader_name + ":refused"] += 1
        return
    check(result)
    FUZZ_COUNTS[reader_name + ":read"] += 1


def _fuzz_seeds() -> dict[str, tuple[str, bytes]]:
    grey = np.rint(texture(12, 16, seed=7) * 255).astype(np.uint8)
    colour = np.stack([grey, grey.T[:12, :12].repeat(2, axis=1)[:, :16], 255 - grey], axis=2)
    seeds = {name: ("read_image", data) for name, data in {
        "png8": encode(".png", grey),
        "png16rgb": png_bytes(colour.astype(np.uint16) * 257, 2, 16, extra=phys_chunk(100_000, 100_000)),
        "png-palette": png_bytes(grey % 3, 3, plte=bytes(range(9))),
        "jpeg": jpeg_with_app(jpeg_bytes(colour), 0xE1, exif_payload(6, (2540, 1))),
        "jpeg-progressive": jpeg_bytes(grey, IMWRITE_JPEG_PROGRESSIVE=1),
        "bmp8": encode(".bmp", grey),
        "bmp24": encode(".bmp", colour),
        "tiff8": tiff_bytes(grey, resolution=(2540, 1)),
        "tiff16-lzw": encode(".tif", colour.astype(np.uint16) * 300),
    }.items()}
    seeds["npy-f8"] = ("read_height_npy", _npy(grey / 7.0))
    seeds["npy-f4-fortran"] = ("read_height_npy", _npy(np.asfortranarray(grey.astype(np.float32))))
    exr_path = Path(os.environ.get("TMPDIR", "/tmp")) / f"haptex_fuzz_seed_{os.getpid()}.exr"
    write_exr(exr_path, {"height": grey / 3.0, "a40": grey / 5.0}, attributes={"k": "v"})
    seeds["exr"] = ("read_height_exr", exr_path.read_bytes())
    seeds["exr-channels"] = ("read_exr_channels", seeds["exr"][1])
    exr_path.unlink()
    return seeds


FUZZ_SEEDS = _fuzz_seeds()


@st.composite
def damaged(draw, data: bytes) -> bytes:
    """A valid file with random byte changes, then perhaps truncated or extended."""
    out = bytearray(data)
    for _ in range(draw(st.integers(0, 6))):
        # Headers matter most: half the changes fall in the first 64 bytes.
        limit = min(len(out), 64) if draw(st.booleans()) else len(out)
        out[draw(st.integers(0, limit - 1))] = draw(st.integers(0, 255))
    choice = draw(st.integers(0, 3))
    if choice == 1:
        out = out[:draw(st.integers(0, len(out)))]
    elif choice == 2:
        out += draw(st.binary(max_size=64))
    elif choice == 3:  # a run of bytes set to one value (zeroed or 0xFF-filled regions)
        start = draw(st.integers(0, len(out) - 1))
        out[start:start + draw(st.integers(1, 32))] = bytes([draw(st.sampled_from([0, 255]))]) * 32
    return bytes(out)


@pytest.mark.parametrize("seed_name", sorted(FUZZ_SEEDS))
def test_fuzz_damaged_valid_files(tmp_path, seed_name):
    reader_name, data = FUZZ_SEEDS[seed_name]
    _try(reader_name, tmp_path / "seed", data)  # the undamaged seed itself must be read
    assert FUZZ_COUNTS[reader_name + ":read"] >= 1

    @FUZZ
    @given(damaged(data))
    def run(sample: bytes) -> None:
        _try(reader_name, tmp_path / "fuzz", sample)

    run()


MAGICS = {"none": b"", "png": b"\x89PNG\r\n\x1a\n", "png-ihdr": b"\x89PNG\r\n\x1a\n\x00\x00\x00\x0dIHDR",
          "jpeg": b"\xff\xd8\xff", "bmp": b"BM", "tiff-le": b"II*\x00", "tiff-be": b"MM\x00*",
          "bigtiff": b"II+\x00\x08\x00\x00\x00", "npy": b"\x93NUMPY\x01\x00", "exr": b"\x76\x2f\x31\x01\x02\x00\x00\x00"}


@pytest.mark.parametrize("reader_name", sorted(READERS))
def test_fuzz_random_bytes_behind_every_magic(tmp_path, reader_name):
    @FUZZ
    @given(st.sampled_from(sorted(MAGICS)), st.binary(max_size=600))
    def run(magic: str, tail: bytes) -> None:
        _try(reader_name, tmp_path / "random", MAGICS[magic] + tail)

    run()


def test_a_damaged_jpeg_is_reported_once_in_our_words(tmp_path, capfd, caplog, monkeypatch):
    # libjpeg prints "Corrupt JPEG data: ..." on stderr itself (80 of 150 damaged JPEGs in a
    # fuzz). A JPEG that still decodes gives one warning naming the file; one that does not
    # gives the decoder's words as the error's reason; nothing raw reaches stdout or stderr.
    import logging

    monkeypatch.setattr(logging.getLogger("haptex"), "propagate", True)  # the CLI tests turn it off
    pixels = (np.random.default_rng(0).random((48, 64)) * 255).astype(np.uint8)
    ok, encoded = cv2.imencode(".jpg", pixels)
    data = encoded.tobytes()
    padded = tmp_path / "padded.jpg"
    padded.write_bytes(data[:-2] + b"\0" * 100 + data[-2:])  # 100 bytes of junk before the end marker
    with caplog.at_level(logging.WARNING, logger="haptex"):
        image = read_image(padded)
    assert image.grey.shape == (48, 64)
    said = [r.getMessage() for r in caplog.records if "decoder says" in r.getMessage()]
    assert len(said) == 1 and said[0].startswith(f"{padded}: the JPEG decoder says: Corrupt JPEG data: ")
    assert said[0].endswith("extraneous bytes before marker 0xd9")
    out, err = capfd.readouterr()
    assert "Corrupt JPEG" not in out + err


def test_a_signalling_nan_is_refused_without_a_numpy_warning():
    # A damaged EXR's float32 channel held a signalling NaN (seeds 217, 220, 272 of
    # bench_robustness): its cast to float64 printed numpy's "invalid value encountered in
    # cast" warning before the one-line refusal.
    import warnings

    from haptex_compile.io_heightmaps import check_height_um

    heights = np.zeros((8, 8), np.float32)
    heights.view(np.uint32)[3, 4] = 0x7F800001  # a signalling NaN
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with pytest.raises(InputError, match="1 of 64 height values are not finite"):
            check_height_um(heights, "x.exr")


def _text_readers():
    """(name, reader, what its errors call the file, a valid text of it)."""
    from haptex_compile.io_scene import read_scene
    from haptex_compile.io_thresholds import read_thresholds_csv
    from haptex_compile.kes_io import read_kes
    from playback.device import load_profile
    from playback.trajectory import read_csv_trajectory

    samples = Path(__file__).resolve().parents[1] / "samples"
    kes, profile = samples / "kes" / "cotton_poplin.kes.json", samples / "devices" / "haptex24.toml"
    return [
        ("scene.toml", read_scene, "scene file", "[motion]\ntolerance = 0.05\n"),
        ("th.csv", read_thresholds_csv, "threshold CSV",
         "frequency_hz,threshold_p_um,threshold_np_um\n10,30,20\n100,1,15\n300,0.2,40\n800,1,90\n"),
        ("x.kes.json", read_kes, "Kawabata file", kes.read_text(encoding="utf-8")),
        ("profile.toml", load_profile, "device profile", profile.read_text(encoding="utf-8")),
        ("t.csv", read_csv_trajectory, "trajectory CSV", "t_s,u_mm,v_mm,phi_deg\n0,0,0,0\n1,10,0,0\n"),
    ]


@pytest.mark.parametrize("name, reader, what, valid", _text_readers(), ids=[r[0] for r in _text_readers()])
def test_text_inputs_that_cannot_be_read_are_one_line_in_one_wording(tmp_path, name, reader, what, valid):
    # Each reader had its own wording: "cannot read scene (FileNotFoundError)", "file not found",
    # "[Errno 2] No such file or directory: '...'" (no file named first), "not a text TOML file".
    path = tmp_path / name
    cases = {"missing": f"no such {what}", "directory": f"is a directory, not a {what}",
             "binary": f"not UTF-8 text (byte 1): expected a {what}"}
    for case, problem in cases.items():
        if case == "directory":
            path.mkdir()
        elif case == "binary":
            path.rmdir()
            path.write_bytes(b"a\xff\xfe\x00")
        with pytest.raises(InputError) as info:
            reader(path)
        assert str(info.value) == f"{path}: {problem}", case
    # UTF-8 with a byte-order mark (as some spreadsheet exports write) is read.
    path.write_bytes(b"\xef\xbb\xbf" + valid.encode())
    reader(path)


def test_transparent_pixels_are_warned_of(tmp_path, monkeypatch, caplog):
    # Alpha is dropped: a swatch cut out on a transparent background was compiled with the
    # background's colour values as texture, without a word.
    import logging

    monkeypatch.setattr(logging.getLogger("haptex"), "propagate", True)  # the CLI tests turn it off
    grey = (np.random.default_rng(0).random((40, 50)) * 255).astype(np.uint8)
    bgra = cv2.cvtColor(grey, cv2.COLOR_GRAY2BGRA)
    for name, clear_rows in (("opaque.png", 0), ("cut.png", 10)):
        bgra[:, :, 3] = 255
        bgra[:clear_rows, :, 3] = 0
        bgra[clear_rows:clear_rows + 1, 0, 3] = 128 if clear_rows else 255  # one pixel partly transparent
        cv2.imwrite(str(tmp_path / name), bgra)
        caplog.clear()
        with caplog.at_level(logging.WARNING, logger="haptex"):
            image = read_image(tmp_path / name)
        assert image.channels == 4
        np.testing.assert_allclose(image.grey, grey / 255.0, atol=1e-12)  # the colour values, as before
        said = [r.getMessage() for r in caplog.records]
        if clear_rows:
            share = 100 * (clear_rows * 50 + 1) / (40 * 50)
            assert said == [f"{tmp_path / name}: {share:.3g}% of its pixels are transparent or partly so: transparency"
                            " is ignored (their colour values are compiled as texture); crop to the fabric"]
        else:
            assert said == []
