"""Compile time of whole assets with the default scene (issues 2 and 9), against the reference renderer.

Inputs: Brownian height maps and the bundled KES samples (``samples/kes``), each compiled by the
``haptex-compile`` command in a fresh process, as users run it.

Baseline, measured in the same run: computing every table value directly with the reference
renderer (per-point cost measured on a sample of nodes, times the number of table values).

    python bench/bench_compile.py [--quick]
"""
from __future__ import annotations

import argparse
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from haptex_compile.compile import model_for, settings_for  # noqa: E402
from haptex_compile.fractal import brownian_surface  # noqa: E402
from haptex_compile.render import point_intensities, straight_path  # noqa: E402
from haptex_compile.scene import default_scene  # noqa: E402
from haptex_compile.sources import SourceOptions, load_source  # noqa: E402
from playback.asset import read_asset  # noqa: E402


def _reference_cost_s(spec: str, options: SourceOptions, n: int = 12) -> float:
    scene = default_scene()
    surface = load_source(spec, options).surface
    model, settings = model_for(scene), settings_for(scene)
    rng = np.random.default_rng(0)
    w, h = surface.extent_mm
    t0 = time.perf_counter()
    for _ in range(n):
        s = float(np.exp(rng.uniform(np.log(10), np.log(200))))
        point_intensities(surface, model, settings, straight_path(rng.uniform(0, w), rng.uniform(0, h), s, rng.uniform(0, 180)), 0.0)
    return (time.perf_counter() - t0) / n


SAMPLES = Path(__file__).resolve().parents[1] / "samples" / "kes"
KES_TARGET_S = 5.0  # issue 9: a KES file with the default scene


def _cli_compile(spec: str, out: Path, *args: str) -> tuple[float, float]:
    """Wall and CPU seconds of ``haptex-compile spec -o out`` as a user runs it (start-up included)."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    code = "import sys; from haptex_compile.cli import main; sys.argv[0] = 'haptex-compile'; main()"
    subprocess.run([sys.executable, "-c", code, spec, "-o", str(out), "-q", *args], check=True)
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    return wall, (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)


def run(quick: bool = False) -> str:
    sizes = [256, 512] if quick else [512, 1024]
    kes_files = sorted(SAMPLES.glob("*.kes.json"))[:1] if quick else sorted(SAMPLES.glob("*.kes.json"))
    rows = ["| input | surface | haptex-compile wall s | CPU s | tables (dir x speed x nodes) | measured RMS / max error "
            "| asset MB | reference per table value ms | direct-reference estimate s | speed-up |",
            "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    kes_walls = []
    with tempfile.TemporaryDirectory() as tmp:
        cases = []
        for n in sizes:
            npy = Path(tmp) / f"h{n}.npy"
            np.save(npy, brownian_surface(n, 0.5, pixel_size_um=20.0, rms_um=5.0, seed=1))
            cases.append((f"{n}x{n} Brownian H=0.5 .npy", str(npy), SourceOptions(pixel_size_um=20.0), ("--pixel-size", "20um")))
        for path in kes_files:
            cases.append((f"{path.name} (KES)", str(path), SourceOptions(), ()))
        for label, spec, options, args in cases:
            out = Path(tmp) / "out.tact.h5"
            wall, cpu = _cli_compile(spec, out, *args)
            if label.endswith("(KES)"):
                kes_walls.append(wall)
            a = read_asset(out)
            nd, ns, nj, ni = a.tables.shape
            w, h = load_source(spec, options).surface.extent_mm
            per = _reference_cost_s(spec, options, n=4 if quick else 12)
            direct = per * nd * ns * nj * ni
            rows.append(f"| {label} | {w:.1f} x {h:.1f} mm | {wall:.1f} | {cpu:.1f} | "
                        f"{nd} x {ns} x {nj}x{ni} | {a.tables.rms_rel_error:.2%} / {a.tables.max_rel_error:.2%} | "
                        f"{os.path.getsize(out) / 1e6:.2f} | {per * 1e3:.1f} | {direct:.0f} | {direct / wall:.0f}x |")
    load = os.getloadavg()[0]
    return ("\n".join(rows) + "\n\nDefault scene (24 contactors, 10-200 mm/s, all directions, tolerance 2 %, footprint 0.25 mm); "
            f"wall time of the command, Python start-up included; load average {load:.1f} on {os.cpu_count()} cores.\n"
            f"KES files: slowest {max(kes_walls):.1f} s against the issue's target {KES_TARGET_S:g} s.\n")


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--quick", action="store_true")
    print(run(parser.parse_args().quick))
