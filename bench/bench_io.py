"""Benchmark: reading large photographs with ``read_image`` against OpenCV's decode alone.

The floor is ``cv2.imread`` with the flags ``read_image`` decodes with (grey for a colour
JPEG, any depth/colour for PNG); ``read_image`` adds the header and structure checks (PNG
chunk checksums, JPEG end marker), the metadata parse and the float64 grey conversion.
Run: ``python bench/bench_io.py [--quick]``.
"""
from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

from haptex_compile.io_images import read_image

SHARED_PHOTO = Path(__file__).resolve().parents[1].parent / "shared" / "fabrics" / "phone-4330px.jpg"


def _fabric_like(side: int, colour: bool, seed: int = 0) -> np.ndarray:
    """A woven-looking 8-bit test image: two crossing thread waves, shading and sensor noise."""
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:side, 0:side].astype(np.float32)
    period = 23.0  # px per thread
    weave = np.sin(2 * np.pi * x / period) * np.sin(2 * np.pi * y / period)
    shading = 0.3 * x / side
    grey = 120 + 60 * weave + 40 * shading + rng.normal(0, 4, (side, side)).astype(np.float32)
    grey = np.clip(grey, 0, 255).astype(np.uint8)
    if not colour:
        return grey
    return np.stack([grey, np.clip(grey * 0.9, 0, 255).astype(np.uint8),
                     np.clip(grey * 1.1, 0, 255).astype(np.uint8)], axis=2)


def _interleaved_ms(functions: list, repeats: int) -> list[float]:
    """Median wall time (ms) of each function, timed in turn so that load from other
    processes falls on all of them alike."""
    for function in functions:
        function()  # warm caches (page cache, allocator)
    times: list[list[float]] = [[] for _ in functions]
    for _ in range(repeats):
        for function, bucket in zip(functions, times):
            start = time.perf_counter()
            function()
            bucket.append(time.perf_counter() - start)
    return [1e3 * statistics.median(bucket) for bucket in times]


def run(quick: bool = False) -> str:
    """Time read_image against cv2.imread on 4000 x 4000 8-bit JPEG and PNG files.

    Parameters
    ----------
    quick : bool
        Fewer repetitions (the image size stays 4000 x 4000).

    Returns
    -------
    str
        A markdown table: per file, the cv2.imread floor, read_image, and their ratio.
    """
    side, repeats = 4000, (2 if quick else 9)
    rows = []
    with tempfile.TemporaryDirectory(prefix="haptex_bench_io_") as tmp:
        files = []
        for colour in (False, True):
            pixels = _fabric_like(side, colour)
            kind = "colour" if colour else "grey"
            for ext, params in ((".jpg", [cv2.IMWRITE_JPEG_QUALITY, 92]), (".png", [])):
                path = Path(tmp) / f"fabric_{kind}{ext}"
                cv2.imwrite(str(path), pixels, params)
                files.append((f"{side}x{side} 8-bit {kind} {ext[1:].upper()}", path, ext, colour))
        if SHARED_PHOTO.is_file():
            files.append(("phone-4330px.jpg (real, colour)", SHARED_PHOTO, ".jpg", True))
        for label, path, ext, colour in files:
            # The flags read_image decodes with: the floor for the same decoded pixels.
            flags = cv2.IMREAD_GRAYSCALE if ext == ".jpg" else cv2.IMREAD_ANYDEPTH | cv2.IMREAD_ANYCOLOR
            floor, naive, ours = _interleaved_ms([
                lambda: cv2.imread(str(path), flags),
                lambda: cv2.cvtColor(cv2.imread(str(path)), cv2.COLOR_BGR2GRAY)
                .astype(np.float64) / 255.0,
                lambda: read_image(path)], repeats)
            size_mb = path.stat().st_size / 1e6
            rows.append(f"| {label} | {size_mb:.1f} | {floor:.0f} | {naive:.0f} | {ours:.0f} | "
                        f"{ours / floor:.2f} |")
    header = ["| file | MB | cv2.imread floor (ms) | imread colour + cvtColor + float (ms) | "
              "read_image (ms) | read_image / floor |",
              "| --- | ---: | ---: | ---: | ---: | ---: |"]
    note = (f"\nMedian of {repeats} interleaved runs after one warm-up; files in the page "
            "cache; machine load at the time affects all columns alike. Floor: "
            "cv2.imread with the decode flags read_image uses (grey for JPEG, any depth/colour "
            "for PNG).\n")
    return "\n".join(header + rows) + "\n" + note


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="fewer repetitions (< 60 s)")
    args = parser.parse_args(argv)
    sys.stdout.write(run(quick=args.quick))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
