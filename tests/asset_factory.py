"""Synthetic assets for the player's tests and benchmark, written by the compiler's one writer.

``write_test_asset`` fills the tables from a function
``f(direction_deg, speed_mm_s, u_mm, v_mm) -> (a40, a320)`` so tests know the exact values, and
writes them with :func:`haptex_compile.asset_writer.write_asset` (the format has one writer).
"""
from __future__ import annotations

import sys
from pathlib import Path
from typing import Callable

import h5py
import numpy as np


# A tiny surface and scene that compile in seconds (CLI and playback-against-reference tests).
TINY_SPEC = "brownian:H=0.5,size=64,pixel=20um,rms=5um,seed=2"
TINY_SCENE = """
[array]
grid = { rows = 2, cols = 2, pitch_mm = 1.0 }
[motion]
speeds_mm_s = [40, 80]
directions_deg = [0, 90]
tolerance = 0.5
"""

# The tools' console scripts and the modules whose main() they run.
TOOL_MODULES = {"haptex-compile": "haptex_compile.cli", "haptex-inspect": "haptex_compile.inspect_cli",
                "haptex-play": "playback.cli"}


def tool_argv(tool: str) -> list[str]:
    """The command line, before its arguments, that runs `tool` in a fresh Python as its console
    script does (the installed script need not be on PATH)."""
    return [sys.executable, "-c", f"import sys; from {TOOL_MODULES[tool]} import main; sys.argv[0] = {tool!r}; main()"]


AmplitudeFn = Callable[[np.ndarray, np.ndarray, np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]]


def haptex24_layout_mm(pitch_mm: float = 2.0) -> np.ndarray:
    """The HAPTEX array: 6 x 4 contactors at `pitch_mm`, centred on the origin, row-major."""
    x = (np.arange(6) - 2.5) * pitch_mm
    y = (np.arange(4) - 1.5) * pitch_mm
    xx, yy = np.meshgrid(x, y)
    return np.column_stack([xx.ravel(), yy.ravel()])


def smooth_field(direction_deg: np.ndarray, speed_mm_s: np.ndarray, u_mm: np.ndarray,
                 v_mm: np.ndarray, period_mm: float = 8.0) -> tuple[np.ndarray, np.ndarray]:
    """A smooth, strictly positive test field, periodic in space (period_mm) and in direction (180°)."""
    k = 2 * np.pi / period_mm
    th = np.deg2rad(direction_deg)
    a40 = (5.0 + 1.5 * np.cos(2 * th) + np.sin(k * u_mm) * np.cos(k * v_mm)) * (speed_mm_s / 80.0) ** 0.5
    a320 = (0.8 + 0.2 * np.sin(2 * th + 0.3) + 0.3 * np.cos(k * (u_mm + v_mm))) * (speed_mm_s / 80.0)
    return a40, a320


def make_table_arrays(fn: AmplitudeFn, direction_deg: np.ndarray, speed_mm_s: np.ndarray,
                      origin_mm: np.ndarray, grid_basis_mm: np.ndarray, n_j: int, n_i: int
                      ) -> tuple[np.ndarray, np.ndarray]:
    """Sample `fn` at every node; returns float32 a40, a320 [n_dir, n_speed, n_j, n_i]."""
    jj, ii = np.meshgrid(np.arange(n_j), np.arange(n_i), indexing="ij")
    u = origin_mm[0] + ii * grid_basis_mm[0, 0] + jj * grid_basis_mm[1, 0]
    v = origin_mm[1] + ii * grid_basis_mm[0, 1] + jj * grid_basis_mm[1, 1]
    d = np.asarray(direction_deg, dtype=np.float64)[:, None, None, None]
    s = np.asarray(speed_mm_s, dtype=np.float64)[None, :, None, None]
    a40, a320 = fn(d, s, u[None, None], v[None, None])
    shape = (len(direction_deg), len(speed_mm_s), n_j, n_i)
    return (np.broadcast_to(a40, shape).astype(np.float32), np.broadcast_to(a320, shape).astype(np.float32))


def write_test_asset(
    path: str | Path,
    *,
    fn: AmplitudeFn = smooth_field,
    direction_deg: np.ndarray | None = None,
    speed_mm_s: np.ndarray | None = None,
    origin_mm: tuple[float, float] = (0.0, 0.0),
    grid_basis_mm: np.ndarray | None = None,
    n_j: int = 32,
    n_i: int = 32,
    periodic: bool = True,
    contactors_mm: np.ndarray | None = None,
    frame_ms: float = 25.0,
    max_rel_error: float = 0.02,
    format_version: str = "1.0",
    height_shape: tuple[int, int] = (16, 16),
) -> Path:
    """Write a complete v1 asset whose tables sample `fn`.

    Defaults: directions every 7.5°, 21 speeds 10-320 mm/s, 32 x 32 nodes at 0.25 mm (one 8 mm
    period of :func:`smooth_field`), periodic. For that field the interpolation error stays
    below 1.5 % (the stated ``max_rel_error`` is 2 %). A `format_version` other than the
    writer's is patched in afterwards (to test the reader's refusal).
    """
    from haptex_compile.asset_writer import FORMAT_VERSION, AssetContent, write_asset
    from haptex_compile.colours import TwoColourModel
    from haptex_compile.frame_analysis import AnalysisSettings
    from haptex_compile.scene import Scene
    from haptex_compile.surface import Surface, periodic_surface_from_tile
    from haptex_compile.tables import TableGrid, Tables

    path = Path(path)
    direction = np.arange(0.0, 180.0, 7.5) if direction_deg is None else np.asarray(direction_deg, float)
    speed = np.geomspace(10.0, 320.0, 21) if speed_mm_s is None else np.asarray(speed_mm_s, float)
    basis = np.array([[0.25, 0.0], [0.0, 0.25]]) if grid_basis_mm is None else np.asarray(grid_basis_mm, float)
    origin = np.asarray(origin_mm, dtype=np.float64)
    a40, a320 = make_table_arrays(fn, direction, speed, origin, basis, n_j, n_i)
    contactors = haptex24_layout_mm() if contactors_mm is None else np.asarray(contactors_mm, float)
    height = np.zeros(height_shape)
    surface = periodic_surface_from_tile(height, 20.0) if periodic else Surface(height, 20.0, False)
    zeros = np.zeros_like(a40)
    tables = Tables(a40, a320, zeros, zeros, zeros, direction, speed, TableGrid(origin, basis, (n_j, n_i), periodic))
    content = AssetContent(surface=surface, tables=tables, model=TwoColourModel(),
                           settings=AnalysisSettings(frame_ms=frame_ms), scene=Scene(contactors_mm=contactors),
                           source_name="synthetic", source_kind="heightmap",
                           table_errors={"max_rel_error": max_rel_error, "rms_rel_error": max_rel_error / 3,
                                         "tolerance": 0.05})
    write_asset(path, content)
    if format_version != FORMAT_VERSION:
        with h5py.File(path, "r+") as f:
            f.attrs["format_version"] = format_version
    return path
