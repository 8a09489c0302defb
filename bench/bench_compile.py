"""Compile time of whole assets with the default scene (issue 2), against the reference renderer.

Baseline, measured in the same run: computing every table value directly with the reference
renderer (per-point cost measured on a sample of nodes, times the number of table values).

    python bench/bench_compile.py [--quick]
"""
from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from haptex_compile.compile import compile_source, model_for, settings_for  # noqa: E402
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


def run(quick: bool = False) -> str:
    sizes = [256, 512] if quick else [512, 1024]
    rows = ["| input | surface | compile s | tables (dir x speed x nodes) | measured RMS / max error | asset MB | reference per table value ms | direct-reference estimate s | speed-up |",
            "| --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    with tempfile.TemporaryDirectory() as tmp:
        for n in sizes:
            npy = Path(tmp) / f"h{n}.npy"
            np.save(npy, brownian_surface(n, 0.5, pixel_size_um=20.0, rms_um=5.0, seed=1))
            options = SourceOptions(pixel_size_um=20.0)
            out = Path(tmp) / f"h{n}.tact.h5"
            t0 = time.perf_counter()
            compile_source(str(npy), out, default_scene(), options)
            dt = time.perf_counter() - t0
            a = read_asset(out)
            nd, ns, nj, ni = a.tables.shape
            per = _reference_cost_s(str(npy), options, n=4 if quick else 12)
            direct = per * nd * ns * nj * ni
            rows.append(f"| {n}x{n} Brownian H=0.5 .npy | {n * 0.02:.1f} x {n * 0.02:.1f} mm at 20 um | {dt:.1f} | "
                        f"{nd} x {ns} x {nj}x{ni} | {a.tables.rms_rel_error:.2%} / {a.tables.max_rel_error:.2%} | "
                        f"{os.path.getsize(out) / 1e6:.2f} | {per * 1e3:.1f} | {direct:.0f} | {direct / dt:.0f}x |")
    load = os.getloadavg()[0]
    return "\n".join(rows) + f"\n\nDefault scene (24 contactors, 10-200 mm/s, all directions, tolerance 2 %, footprint 0.25 mm); load average {load:.1f} on {os.cpu_count()} cores.\n"


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--quick", action="store_true")
    print(run(parser.parse_args().quick))
