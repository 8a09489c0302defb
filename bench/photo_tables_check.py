"""The tables of real fabric photographs against the reference renderer at uniform random points.

Run ``python bench/photo_tables_check.py [--points 512] [NAME ...]`` (names of files in
``../shared/fabrics``; default: all of them). For each photo, compiled as ``haptex-compile``
would with default options (the photo pipeline, then ``build_checked_tables`` on the default
scene), it prints the tables' nodes and size, the compile's rounds and time, the error the
compiler stated (its check), and the RMS relative error of table playback against the reference
renderer at `--points` points drawn uniformly: positions over the node grid, directions in
[0, 180), speeds log-uniform in 10-200 mm/s (the same points for the same tables; seed fixed).
Those points are what random strokes meet; the compiler's check instead draws families at
midpoints between nodes, a few dozen at a time. Not part of ``python -m bench`` (it needs
``../shared`` and takes about a minute per photo); to compare two versions of the code, run
it with each on ``PYTHONPATH``.
"""
from __future__ import annotations

import argparse
import functools
import logging
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np

from haptex_compile.compile import (CHECK_WORKERS, _as_player_tables, build_checked_tables, model_for,
                                    reference_amplitudes, relative_errors, settings_for)
from haptex_compile.scene import default_scene
from haptex_compile.sources import SourceOptions, load_source

FABRICS = Path(__file__).resolve().parents[1].parent / "shared" / "fabrics"


def uniform_points(grid, n: int, seed: int = 12345) -> list:
    """`n` check points (family "uniform") drawn uniformly over the grid, directions and log-speeds."""
    rng = np.random.default_rng(seed)
    points = []
    for _ in range(n):
        fi, fj = rng.uniform(0, grid.shape[1] - 1), rng.uniform(0, grid.shape[0] - 1)
        p = grid.origin_mm + fi * grid.basis_mm[0] + fj * grid.basis_mm[1]
        speed = float(np.exp(rng.uniform(np.log(10.0), np.log(200.0))))
        points.append(("uniform", p, speed, float(rng.uniform(0.0, 180.0))))
    return points


def row(path: Path, n_points: int) -> str:
    surface = load_source(str(path), SourceOptions()).surface
    scene = default_scene()
    model, settings = model_for(scene), settings_for(scene)
    t0 = time.perf_counter()
    tables, stats, _ = build_checked_tables(surface, model, settings, scene)
    seconds = time.perf_counter() - t0
    points = uniform_points(tables.grid, n_points)
    with ThreadPoolExecutor(max_workers=CHECK_WORKERS) as pool:
        refs = np.array(list(pool.map(functools.partial(reference_amplitudes, surface, model, settings), points)))
    u, v = (np.array([p[1][k] for p in points]) for k in (0, 1))
    a40, a320, _ = _as_player_tables(tables, settings.frame_ms).interpolator(
        u, v, np.array([p[2] for p in points]), np.array([p[3] for p in points]))
    e = relative_errors(model, a40, a320, refs[:, 0], refs[:, 1])
    nd, ns, nj, ni = tables.a40.shape
    return (f"| {path.name} | {nd} x {ns} x {nj} x {ni} | {tables.a40.size / 1e6:.2f} | {len(stats['refinements'])} "
            f"| {seconds:.1f} | {100 * stats['rms_rel_error']:.2f} %{'' if stats['tolerance_met'] else ' (not met)'} "
            f"| {stats['n_check_samples']} | {100 * float(np.sqrt(np.mean(e ** 2))):.2f} % "
            f"| {100 * float(np.quantile(e, 0.95)):.2f} % |")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("names", nargs="*", help="photos in ../shared/fabrics (default: all)")
    parser.add_argument("--points", type=int, default=512, help="uniform random points per photo")
    args = parser.parse_args()
    if not FABRICS.is_dir():
        print(f"skipped: {FABRICS} is absent")
        return
    logging.disable(logging.WARNING)  # the pipeline's warnings (default pixel size, relief) are known
    paths = [FABRICS / n for n in args.names] or sorted(p for p in FABRICS.iterdir() if p.suffix.lower() in (".jpg", ".bmp", ".png", ".tif"))
    print("| photo | nodes dir x speed x j x i | M values | rounds | tables s | stated RMS error | check points "
          f"| RMS error at {args.points} uniform points | their 95th percentile |")
    print("| --- | --- | --- | --- | --- | --- | --- | --- | --- |")
    for path in paths:
        print(row(path, args.points), flush=True)


if __name__ == "__main__":
    main()
