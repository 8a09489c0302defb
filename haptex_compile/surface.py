"""A rigid surface: height map in µm on a pixel grid, and how to sample it anywhere.

Coordinates: sample (row r, column c) of ``height_um`` sits at ``(u, v) = (c, r) * pixel_size_mm``
(u along columns, v along rows, millimetres). Between samples heights are bilinear.

Outside the map:

* a *periodic* surface repeats along its lattice ``t1_px, t2_px`` ((x, y) pixel vectors): any
  point is moved by whole lattice vectors into the reference cell, whose corner is
  ``cell_origin_px``; indices then wrap around the array (so a lattice equal to the array's own
  shape tiles it seamlessly);
* a *non-periodic* surface is mirrored about its edge samples (even reflection, period
  ``2 (n - 1)`` samples): no step at the edge, so crossing it adds no spurious vibration.

Both the tables and the reference renderer sample through :func:`sample_height`, so they see
exactly the same surface.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Surface:
    """Height map with its geometry.

    Attributes
    ----------
    height_um : ndarray
        Float array [ny, nx] in µm.
    pixel_size_um : float
        Sample spacing in µm.
    periodic : bool
        Whether the surface repeats along ``t1_px``, ``t2_px``.
    t1_px, t2_px : ndarray or None
        Lattice vectors (x, y) in pixels (periodic surfaces only).
    cell_origin_px : ndarray or None
        (x, y) pixel position of the reference cell's corner (periodic surfaces only).
    """

    height_um: np.ndarray
    pixel_size_um: float
    periodic: bool = False
    t1_px: np.ndarray | None = None
    t2_px: np.ndarray | None = None
    cell_origin_px: np.ndarray | None = None

    def __post_init__(self) -> None:
        h = np.asarray(self.height_um)
        if h.ndim != 2 or min(h.shape) < 2:
            raise ValueError("height map must be 2-D with at least 2 x 2 samples")
        if not np.all(np.isfinite(h)):
            raise ValueError("height map has non-finite values")
        if not (np.isfinite(self.pixel_size_um) and self.pixel_size_um > 0):
            raise ValueError("pixel size must be finite and positive")
        if self.periodic:
            if self.t1_px is None or self.t2_px is None:
                raise ValueError("a periodic surface needs lattice vectors t1_px, t2_px")
            basis = np.column_stack([self.t1_px, self.t2_px]).astype(float)
            if abs(np.linalg.det(basis)) < 1.0:
                raise ValueError("lattice vectors are parallel or the cell is under one pixel")

    @property
    def pixel_size_mm(self) -> float:
        return self.pixel_size_um / 1000.0

    @property
    def shape(self) -> tuple[int, int]:
        return tuple(np.asarray(self.height_um).shape)  # type: ignore[return-value]

    @property
    def extent_mm(self) -> tuple[float, float]:
        """(width along u, height along v) of the sampled region, edge sample to edge sample."""
        ny, nx = self.shape
        return (nx - 1) * self.pixel_size_mm, (ny - 1) * self.pixel_size_mm

    def lattice_mm(self) -> np.ndarray:
        """Lattice vectors as rows [[t1u, t1v], [t2u, t2v]] in mm (periodic surfaces only)."""
        if not self.periodic:
            raise ValueError("surface is not periodic")
        return np.array([self.t1_px, self.t2_px], dtype=float) * self.pixel_size_mm

    def origin_px(self) -> np.ndarray:
        return np.zeros(2) if self.cell_origin_px is None else np.asarray(self.cell_origin_px, float)


def periodic_surface_from_tile(height_um: np.ndarray, pixel_size_um: float) -> Surface:
    """A surface that repeats its whole array (rectangular lattice = the array's shape)."""
    ny, nx = np.asarray(height_um).shape
    return Surface(np.asarray(height_um, dtype=float), pixel_size_um, True,
                   np.array([nx, 0.0]), np.array([0.0, ny]), np.zeros(2))


def _mirror_index(i: np.ndarray, n: int) -> np.ndarray:
    period = 2 * (n - 1)
    i = np.mod(i, period)
    return np.where(i >= n, period - i, i)


def sample_height(surface: Surface, u_mm: np.ndarray, v_mm: np.ndarray) -> np.ndarray:
    """Bilinear heights (µm) at points (u, v) in mm, any shape; periodic or mirrored outside.

    Parameters
    ----------
    surface : Surface
    u_mm, v_mm : array_like
        Coordinates of the points (broadcast together).

    Returns
    -------
    ndarray
        Heights in µm, float64, same shape as the broadcast inputs.
    """
    h = np.asarray(surface.height_um, dtype=float)
    ny, nx = h.shape
    x = np.asarray(u_mm, dtype=float) / surface.pixel_size_mm
    y = np.asarray(v_mm, dtype=float) / surface.pixel_size_mm
    x, y = np.broadcast_arrays(x, y)
    if surface.periodic:
        basis = np.column_stack([surface.t1_px, surface.t2_px]).astype(float)
        inv = np.linalg.inv(basis)
        o = surface.origin_px()
        dx, dy = x - o[0], y - o[1]
        a = inv[0, 0] * dx + inv[0, 1] * dy
        b = inv[1, 0] * dx + inv[1, 1] * dy
        a -= np.floor(a)
        b -= np.floor(b)
        x = o[0] + basis[0, 0] * a + basis[0, 1] * b
        y = o[1] + basis[1, 0] * a + basis[1, 1] * b
    x0 = np.floor(x)
    y0 = np.floor(y)
    fx = x - x0
    fy = y - y0
    x0 = x0.astype(np.int64)
    y0 = y0.astype(np.int64)
    if surface.periodic:
        xa, xb = np.mod(x0, nx), np.mod(x0 + 1, nx)
        ya, yb = np.mod(y0, ny), np.mod(y0 + 1, ny)
    else:
        xa, xb = _mirror_index(x0, nx), _mirror_index(x0 + 1, nx)
        ya, yb = _mirror_index(y0, ny), _mirror_index(y0 + 1, ny)
    top = h[ya, xa] * (1.0 - fx) + h[ya, xb] * fx
    bottom = h[yb, xa] * (1.0 - fx) + h[yb, xb] * fx
    return top * (1.0 - fy) + bottom * fy
