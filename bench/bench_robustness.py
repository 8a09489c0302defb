"""Benchmark: damaged files against the readers, ours and the libraries' alone.

Every kind of file the tools read (a tactile asset, a playback record, PNG 8 and 16 bit, TIFF,
JPEG, BMP, an EXR height map, an NPY height map) is damaged many times over (1-20 random bytes
overwritten, or one cut short in five), seeded, and read in a forked child with its file
descriptors 1 and 2 on a temporary file: by our reader (what the tools call) and by the library
alone (baseline: h5py reading every attribute and dataset, ``cv2.imdecode``, the OpenEXR
binding, ``np.load``). Counted per reader: files read, refused in one line (our errors),
other exceptions (a traceback in a tool), crashes (the child killed by a signal), files after
which raw lines reached stdout or stderr, and the mean milliseconds per file (the read alone).
Run: ``python bench/bench_robustness.py [--quick]``.
"""
from __future__ import annotations

import argparse
import logging
import os
import random
import struct
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np
import OpenEXR

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # the repo root, for tests.asset_factory

from haptex_compile.asset_validate import validate_asset  # noqa: E402
from haptex_compile.inspect_cli import record_summary  # noqa: E402
from haptex_compile.io_exr import write_exr  # noqa: E402
from haptex_compile.io_heightmaps import read_height_exr, read_height_npy  # noqa: E402
from haptex_compile.io_images import read_image  # noqa: E402
from playback import protocol  # noqa: E402
from playback.asset import read_asset, read_everything  # noqa: E402
from playback.clock import VirtualClock  # noqa: E402
from playback.device import DEFAULT_PROFILE, profile_from_dict  # noqa: E402
from playback.errors import HaptexError  # noqa: E402
from playback.player import Player  # noqa: E402
from playback.record import Recorder  # noqa: E402
from playback.trajectory import sweep_trajectory  # noqa: E402
from playback.transport import make_transport  # noqa: E402
from tests.asset_factory import write_test_asset  # noqa: E402

OUTCOMES = ("read", "refused", "exception", "crash")


def _valid_files(folder: Path) -> dict[str, Path]:
    """One valid file of each kind, made here."""
    rng = np.random.default_rng(0)
    grey8 = (rng.random((48, 64)) * 255).astype(np.uint8)
    grey16 = (rng.random((48, 64)) * 65535).astype(np.uint16)
    files = {"tactile asset": write_test_asset(folder / "a.tact.h5")}
    asset = read_asset(files["tactile asset"])
    profile = profile_from_dict(DEFAULT_PROFILE)
    clock = VirtualClock(10.0)
    transport, emulator = make_transport("sim", profile, clock)
    files["playback record"] = folder / "r.h5"
    recorder = Recorder(files["playback record"], asset.n_contactors, profile.n_channels,
                        protocol.frame_size(profile.n_channels))
    Player(asset, profile, transport, sweep_trajectory(80.0, 0.0, 0.5), clock=clock, recorder=recorder,
           emulator=emulator).run()
    for name, pixels, suffix in (("PNG 8 bit", grey8, ".png"), ("PNG 16 bit", grey16, ".png"),
                                 ("TIFF 16 bit", grey16, ".tif"), ("JPEG", grey8, ".jpg"), ("BMP", grey8, ".bmp")):
        files[name] = folder / f"{name.replace(' ', '_')}{suffix}"
        cv2.imwrite(str(files[name]), pixels)
    files["EXR height map"] = folder / "h.exr"
    write_exr(files["EXR height map"], {"height": rng.standard_normal((48, 64)).astype(np.float32)})
    files["NPY height map"] = folder / "h.npy"
    np.save(files["NPY height map"], rng.standard_normal((48, 64)))
    return files


def _exr_alone(path: Path) -> None:
    for channel in OpenEXR.File(str(path), separate_channels=True).channels().values():
        np.asarray(channel.pixels)


# kind -> (our reader, the library alone)
READERS = {
    "tactile asset": (validate_asset, read_everything),
    "playback record": (record_summary, read_everything),
    "EXR height map": (read_height_exr, _exr_alone),
    "NPY height map": (read_height_npy, lambda p: np.load(p, allow_pickle=False)),
}
_IMAGE = (read_image, lambda p: cv2.imdecode(np.fromfile(p, np.uint8), cv2.IMREAD_ANYDEPTH | cv2.IMREAD_ANYCOLOR))


def _damage(data: bytes, seed: int) -> bytes:
    """`data` with 1-20 random bytes overwritten, or (one in five) cut short; seeded."""
    rng = random.Random(seed)
    if rng.random() < 0.2:
        return data[:rng.randrange(len(data))]
    damaged = bytearray(data)
    for _ in range(rng.randint(1, 20)):
        damaged[rng.randrange(len(damaged))] = rng.randrange(256)
    return bytes(damaged)


def _in_child(fn, path: Path, sink: Path) -> tuple[str, bool, float]:
    """(outcome, whether raw lines reached fds 1 or 2, seconds) of ``fn(path)`` in a forked
    child with fds 1 and 2 on `sink`."""
    read_end, write_end = os.pipe()
    pid = os.fork()
    if pid == 0:  # the child: no exit handlers, no flushing of the parent's buffers
        os.close(read_end)
        fd = os.open(sink, os.O_WRONLY | os.O_CREAT | os.O_TRUNC)
        os.dup2(fd, 1)
        os.dup2(fd, 2)
        outcome, t0 = "read", time.perf_counter()
        try:
            result = fn(path)
            if isinstance(result, list) and result:  # the validator's problems: refused
                outcome = "refused"
        except HaptexError:
            outcome = "refused"
        except BaseException:  # noqa: BLE001 - what is counted
            outcome = "exception"
        seconds = time.perf_counter() - t0
        os.write(write_end, struct.pack("<d", seconds) + outcome.encode())
        os._exit(0)
    os.close(write_end)
    _, status = os.waitpid(pid, 0)
    message = os.read(read_end, 64)
    os.close(read_end)
    raw = sink.stat().st_size > 0
    if os.WIFSIGNALED(status) or len(message) < 8:
        return "crash", raw, float("nan")
    return message[8:].decode(), raw, struct.unpack("<d", message[:8])[0]


def run(quick: bool = False) -> str:
    n = 40 if quick else 300
    # Our readers' warnings (a JPEG's decoder complaints, relayed once in our words) go through
    # logging, which the tools format; here they are dropped, so "raw output" counts only what
    # reached the descriptors around them.
    logger = logging.getLogger("haptex")
    logger.addHandler(logging.NullHandler())
    logger.propagate = False
    lines = [f"{n} damaged copies of each kind (1-20 random bytes overwritten, or one in five cut short;"
             " seeds 0 to n - 1), each read in a forked child by our reader (what the tools call: the"
             " validator for assets, the summary for records) and by the library alone (baseline:"
             " h5py reading every attribute and dataset, `cv2.imdecode`, the OpenEXR binding,"
             " `np.load`). read / refused in one line / other exception (a traceback in a tool) /"
             " crash (killed by a signal) / files after which raw lines reached stdout or stderr;"
             " mean ms per file (the read alone, crashes left out):", "",
             "| kind | reader | read | refused | exception | crash | raw output | ms per file |",
             "| --- | --- | --- | --- | --- | --- | --- | --- |"]
    worst = {"exception": 0, "crash": 0, "raw": 0}
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        sink = folder / "sink.txt"
        for kind, good in _valid_files(folder).items():
            ours, alone = READERS.get(kind, _IMAGE)
            data = good.read_bytes()
            for label, fn in (("ours", ours), ("library alone", alone)):
                counts = dict.fromkeys(OUTCOMES, 0)
                raw, seconds = 0, []
                for seed in range(n):
                    path = folder / f"damaged{good.suffix}"
                    path.write_bytes(_damage(data, seed))
                    outcome, printed, t = _in_child(fn, path, sink)
                    counts[outcome] += 1
                    raw += printed
                    if np.isfinite(t):
                        seconds.append(t)
                if label == "ours":
                    worst["exception"] += counts["exception"]
                    worst["crash"] += counts["crash"]
                    worst["raw"] += raw
                ms = 1e3 * float(np.mean(seconds)) if seconds else float("nan")
                lines.append(f"| {kind} | {label} | " + " | ".join(str(counts[o]) for o in OUTCOMES)
                             + f" | {raw} | {ms:.2f} |")
    lines += ["", f"Our readers over all kinds: {worst['exception']} other exceptions, {worst['crash']} crashes,"
              f" {worst['raw']} files with raw output."]
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="40 damaged copies of each kind, not 300")
    print(run(quick=parser.parse_args().quick))


if __name__ == "__main__":
    main()
