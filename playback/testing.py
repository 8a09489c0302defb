"""Synthetic assets for tests and benchmarks (until the compiler's writer is used everywhere).

``write_test_asset`` writes the v1 layout with h5py from tables given as a function
``f(direction_deg, speed_mm_s, u_mm, v_mm) -> (a40, a320)``; tests then know the exact values.
"""
from __future__ import annotations

import json
from pathlib import Path
from typing import Callable

import h5py
import numpy as np

from playback.asset import FORMAT_NAME

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
    below 1.5 % (the stated ``max_rel_error`` is 2 %).
    """
    path = Path(path)
    direction = np.arange(0.0, 180.0, 7.5) if direction_deg is None else np.asarray(direction_deg, float)
    speed = np.geomspace(10.0, 320.0, 21) if speed_mm_s is None else np.asarray(speed_mm_s, float)
    basis = np.array([[0.25, 0.0], [0.0, 0.25]]) if grid_basis_mm is None else np.asarray(grid_basis_mm, float)
    origin = np.asarray(origin_mm, dtype=np.float64)
    a40, a320 = make_table_arrays(fn, direction, speed, origin, basis, n_j, n_i)
    contactors = haptex24_layout_mm() if contactors_mm is None else np.asarray(contactors_mm, float)
    with h5py.File(path, "w") as f:
        f.attrs["format"] = FORMAT_NAME
        f.attrs["format_version"] = format_version
        f.attrs["generator"] = "playback.testing"
        f.attrs["source_name"] = "synthetic"
        f.attrs["source_kind"] = "synthetic"
        s = f.create_group("surface")
        s.create_dataset("height", data=np.zeros(height_shape, np.float32))
        s.attrs["pixel_size_um"] = 20.0
        s.attrs["periodic"] = periodic
        if periodic:  # the height array is one period
            s.attrs["period_t1_px"] = np.array([height_shape[1], 0.0])
            s.attrs["period_t2_px"] = np.array([0.0, height_shape[0]])
            s.attrs["cell_origin_px"] = np.zeros(2)
        p = f.create_group("perception")
        fr = np.array([10.0, 40.0, 320.0, 500.0])
        p.create_dataset("frequency_hz", data=fr)
        p.create_dataset("threshold_p_um", data=np.array([30.0, 5.0, 0.12, 0.2]))
        p.create_dataset("threshold_np_um", data=np.array([2.5, 2.5, 20.0, 30.0]))
        p.attrs["base_frequencies_hz"] = np.array([40.0, 320.0])
        p.attrs["summation_exponent"] = 1.23
        p.attrs["footprint_mm"] = 0.25
        t = f.create_group("tables")
        t.create_dataset("a40", data=a40)
        t.create_dataset("a320", data=a320)
        t.create_dataset("direction_deg", data=direction)
        t.create_dataset("speed_mm_s", data=speed)
        t.attrs["frame_ms"] = frame_ms
        t.attrs["periodic"] = periodic
        t.attrs["origin_mm"] = origin
        t.attrs["grid_basis_mm"] = basis
        t.attrs["grid_spacing_mm"] = float(np.linalg.norm(basis[0]))
        t.attrs["max_rel_error"] = max_rel_error
        t.attrs["rms_rel_error"] = max_rel_error / 3
        t.attrs["tolerance"] = 0.05
        sc = f.create_group("scene")
        sc.attrs["text"] = ""
        sc.attrs["resolved"] = json.dumps({"contactors": "haptex24"})
        sc.create_dataset("contactors_mm", data=contactors)
    return path
