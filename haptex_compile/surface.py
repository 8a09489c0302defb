"""A rigid surface: height map in µm on a pixel grid, and the continuous surface it stands for.

Coordinates: sample (row r, column c) of ``height_um`` sits at ``(u, v) = (c, r) * pixel_size_mm``
(u along columns, v along rows, millimetres).

Between samples the surface is the cubic B-spline interpolant of the map after removing detail
finer than about 3 pixels (an isotropic raised-cosine low-pass from 0.5 to 0.75 of the Nyquist
frequency): neither the map nor any interpolant renders such detail faithfully, and bilinear
interpolation would make the vibration depend on where a path falls between pixel rows. The
spline coefficients are computed once (numpy FFT) and both the tables and the reference renderer
evaluate exactly this surface.

Outside the map:

* a *periodic* surface repeats along its lattice ``t1_px, t2_px`` ((x, y) pixel vectors): any
  point is moved by whole lattice vectors into the reference cell, whose corner is
  ``cell_origin_px``; indices then wrap around the array (so a lattice equal to the array's own
  shape tiles it seamlessly);
* a *non-periodic* surface is mirrored about its edge samples (even reflection, period
  ``2 (n - 1)`` samples): no step at the edge, so crossing it adds no spurious vibration.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.fft
from scipy import ndimage

from haptex_compile.errors import InputError


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


def count_text(n: float) -> str:
    """A count or size for a message: whole below a billion, else 3 significant digits (a
    surface of 1e-300 um pixels gave 300-digit numbers)."""
    return f"{int(n)}" if n < 1e9 else f"{n:.3g}"


def refuse_out_of_scale(surface: Surface, n_bytes: int, limit_bytes: int, stage: str, what: str, per: str,
                        advice: str) -> None:
    """Raise :class:`InputError` when an array of `n_bytes` that `stage` would make for
    `surface` exceeds `limit_bytes` (`per`: of what unit of work), before it is allocated:
    pixels far finer (or an extent far larger) than the scene needs would otherwise exhaust the
    machine's memory. The message gives the surface's size and pixel size, `what` the array
    is, and the `advice`."""
    if n_bytes > limit_bytes:
        rows, cols = surface.shape
        px_mm = surface.pixel_size_mm
        raise InputError(
            None, f"the surface ({cols} x {rows} px of {px_mm * 1000:.4g} um, {cols * px_mm:.4g} x {rows * px_mm:.4g} mm)"
            f" is out of scale for {stage}: {what} would take {_gib(n_bytes)} GiB, above"
            f" {limit_bytes / 2 ** 30:.3g} GiB {per}; {advice}")


def _gib(n_bytes: float) -> str:
    gib = n_bytes / 2 ** 30
    return f"{gib:.1f}" if gib < 1e6 else f"{gib:.3g}"


def periodic_surface_from_tile(height_um: np.ndarray, pixel_size_um: float) -> Surface:
    """A surface that repeats its whole array (rectangular lattice = the array's shape)."""
    ny, nx = np.asarray(height_um).shape
    return Surface(np.asarray(height_um, dtype=float), pixel_size_um, True,
                   np.array([nx, 0.0]), np.array([0.0, ny]), np.zeros(2))


RESOLUTION_PASS = 0.5  # fraction of the Nyquist frequency kept whole
RESOLUTION_STOP = 0.75  # fraction above which nothing is kept


def _wraps(surface: "Surface") -> bool:
    """Whether indices wrap around the array (lattice equal to the array's shape)."""
    if not surface.periodic:
        return False
    ny, nx = surface.shape
    basis = np.column_stack([surface.t1_px, surface.t2_px]).astype(float)
    return bool(np.allclose(np.abs(np.linalg.det(basis)), nx * ny) and np.allclose(basis % np.array([[nx], [ny]]), 0))


def spline_coefficients(surface: "Surface") -> np.ndarray:
    """Cubic B-spline coefficients of the resolution-limited map (cached on the surface)."""
    cached = surface.__dict__.get("_coefficients")
    if cached is not None:
        return cached
    h = np.asarray(surface.height_um, dtype=float)
    ny, nx = h.shape
    wrap = _wraps(surface)
    if wrap:
        ext = h
    else:  # whole-sample symmetric extension: period 2(n - 1), no step anywhere
        ext = np.concatenate([h, h[-2:0:-1]], axis=0) if ny > 2 else np.concatenate([h, h[:0:-1]], axis=0)
        ext = np.concatenate([ext, ext[:, -2:0:-1]], axis=1) if nx > 2 else np.concatenate([ext, ext[:, :0:-1]], axis=1)
    my, mx = ext.shape
    ky = np.fft.fftfreq(my)[:, None]
    kx = np.fft.rfftfreq(mx)[None, :]
    rho = np.sqrt(kx**2 + ky**2) / 0.5
    t = np.clip((rho - RESOLUTION_PASS) / (RESOLUTION_STOP - RESOLUTION_PASS), 0.0, 1.0)
    lowpass = 0.5 * (1.0 + np.cos(np.pi * t))
    bspline = ((4.0 + 2.0 * np.cos(2 * np.pi * ky)) / 6.0) * ((4.0 + 2.0 * np.cos(2 * np.pi * kx)) / 6.0)
    coeffs = scipy.fft.irfft2(scipy.fft.rfft2(ext, workers=2) * (lowpass / bspline), s=ext.shape, workers=2)[:ny, :nx]
    object.__setattr__(surface, "_coefficients", coeffs)
    return coeffs


def pixel_coordinates(surface: "Surface", u_mm: np.ndarray, v_mm: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pixel coordinates (x, y) of points, periodic ones moved into the reference cell."""
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
        a = a - np.floor(a)
        b = b - np.floor(b)
        x = o[0] + basis[0, 0] * a + basis[0, 1] * b
        y = o[1] + basis[1, 0] * a + basis[1, 1] * b
    return x, y


def _bspline_weights(t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    t2 = t * t
    t3 = t2 * t
    return (1 - t) ** 3 / 6.0, (3 * t3 - 6 * t2 + 4) / 6.0, (-3 * t3 + 3 * t2 + 3 * t + 1) / 6.0, t3 / 6.0


def sample_height(surface: Surface, u_mm: np.ndarray, v_mm: np.ndarray) -> np.ndarray:
    """Heights (µm) of the continuous surface at points (u, v) in mm, any shape (numpy only).

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
    c = spline_coefficients(surface)
    # The cubic B-spline of the coefficients, extended periodically (wrapping maps) or by
    # whole-sample mirroring (period 2 (n - 1)), as ndimage's "grid-wrap" and "mirror" modes.
    wraps = _wraps(surface)
    mode = "grid-wrap" if wraps else "mirror"
    if wraps:  # the array is one period: "grid-wrap" reduces the coordinates itself
        x, y = np.broadcast_arrays(np.asarray(u_mm, dtype=float) / surface.pixel_size_mm,
                                   np.asarray(v_mm, dtype=float) / surface.pixel_size_mm)
    else:
        x, y = pixel_coordinates(surface, u_mm, v_mm)
    coords = np.vstack([np.ravel(y), np.ravel(x)])
    return ndimage.map_coordinates(c, coords, order=3, mode=mode, prefilter=False).reshape(x.shape)
