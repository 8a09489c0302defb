"""The default shape-from-shading solver: nonlinear least squares on the height, solved by
Gauss-Newton with FFT-preconditioned conjugate gradients, coarse to fine.

Energy (heights ``z`` in pixel units, slopes by central differences):

    E(z) = 1/2 sum_i w_i (albedo R(p_i, q_i) - I_i)**2  +  lam/2 sum_i (laplacian z)_i**2

with the exact Lambertian ``R = (lz - p lx - q ly) / sqrt(1 + p² + q²)``, plus one-sided terms
for censored pixels: ``1/2 max(albedo R - DARK, 0)**2`` where the image is an attached shadow
(the surface must face away from the light) and ``1/2 min(albedo R - SATURATED, 0)**2`` where it
is over-exposed. Integrability holds by construction (the unknown is the height itself); the
small thin-plate term removes the checkerboard that central differences cannot see and fills
masked pixels. All operators are periodic; a non-periodic image is embedded in a larger periodic
domain whose margin has no data (weight 0), so the margin is filled by the smoothness term alone
and the image's edges are free.

Each Gauss-Newton step solves ``(J^T W J + lam L^T L) dz = -grad`` by conjugate gradients
preconditioned with the same operator for constant coefficients (the pixel average of the
reflectance's gradient tensor), which is diagonal in Fourier space; a backtracking line search
guards each step. The first step from a flat start is therefore Pentland's linear shape from
shading; later steps use the exact reflectance, whose nonlinear part is the only information on
slopes perpendicular to the light (without it, smooth random bumps come back with a normalised
error of 0.55-0.75 instead of 0.07).

Coarse to fine: an area-averaged pyramid down to about 8 pixels; the thin-plate weight grows
by `lam_growth` per coarser level (continuation: smooth shapes first, detail last), and each
level starts from the previous one upsampled. The coarse levels get many cheap Gauss-Newton
steps (20): at low slants the linear term of the reflectance is weak and the energy has local
minima (folds: regions whose slopes across the light flip sign, meeting in creases that cost
little), and a converged coarse shape is what keeps the fine levels out of them (measured on
128 px tiles, slants 15-60°: the plain weave 0.03-0.12 with 6 coarse steps and a 24 px
coarsest level, 0.03-0.08 with 20 steps down to 8 px). An averaged image is darker than the
shading of the averaged surface where the surface is rough below the level's pixel; on the
coarse levels the squared slope across the light is therefore damped in proportion to the
image's sub-pixel variance (``subgrid_damping``), or rough surfaces come back with spurious
long waves across the light (Brownian surfaces at 15°: 1.23 x the true RMS relief, 1.12 x
with the damping). A level stops early once a full Gauss-Newton step gains little
(``gn_rtol``): most converge in 2-4 steps, and the time saved pays for converging the
half-resolution level (``mid_gn``, ``mid_cg``), which the finest level's few steps rely on.

Albedo: refitted by least squares after each accepted step (optionally eliminated from the
step itself by variable projection, ``albedo_projection``, on chosen levels without sub-pixel
roughness) (on the finest level bounded below by the 99.9th percentile of the valid pixels,
since ``R <= 1``). The result is very sensitive to it: the mean brightness fixes the mean
squared slope, so a 1 % albedo error can be absorbed as spurious roughness; for the same reason
a wrong light of a few degrees costs a lot (see ``bench/bench_shading.py``).
"""
from __future__ import annotations

import functools
import os
import threading
from collections.abc import Callable, Collection
from concurrent.futures import ThreadPoolExecutor
from typing import NamedTuple

import numpy as np
import cv2

from haptex_compile import real_fft
from haptex_compile.forked_map import call_beside
from haptex_compile.malloc_policy import keep_freed_memory
from haptex_compile.shading_image import DARK as DARK_LEVEL, SATURATED as BRIGHT_LEVEL
from haptex_compile.shading_kernels import (
    add_row_combinations_rows, albedo_sums_rows, cg_direction_rows, cg_update_rows, energy_rows, gn_setup_rows,
    jacobian_rows, normal_rows, reflectance_rows, row_products_rows,
)
from haptex_compile.shading_prior import spectral_symbol

_F = np.float32
# Coarse levels: weight of the squared slope across the light in R's normalisation,
# 1 / (1 + SUBGRID_DAMPING * sub-pixel / resolved image variance) (see solve_variational).
SUBGRID_DAMPING = 2.0
# Levels of at least this many pixels use `workers` threads for their FFTs (smaller ones run
# faster on one: measured, a 2-thread FFT of 128 x 128 costs more) and also run each
# Gauss-Newton step's elementwise work (reflectance, gradient, the CG matvec and vector
# updates, the line search's energy) on `workers` threads, each on a block of rows: numpy
# and the compiled kernels (shading_kernels) release the GIL. A pixel's value does not
# depend on the blocks, and sums over the image are whole or summed by row, so the results
# are identical on any number of threads (at 256 x 256 px the threads cost more than they
# gain: a 256 px solve 66 -> 103 ms).
PARALLEL_FFT_MIN_PIXELS = 1 << 18
# Processes of the low-frequency prior's test (solve_variational's lowfreq_check_level): the
# coarse levels without the prior here and, side by side, with it in a forked child (None: when
# this process may use 2 CPUs or more; 1: one after the other here; see forked_map.call_beside).
# The same heights either way. Measured against one after the other in one run each (16 plain
# images of each size, the bench's surfaces and lights, light given, best of 3, alternating):
# 256 px 0.73-0.75 x the time, 384 px 0.96, 512 px 0.93-0.97, 1024 px 0.99 (best of 2; the
# test's levels are at most 150 px of a side, a fixed cost). The chain without the prior is the
# longer one and runs in this process, whose caches are warm (against the other way round:
# 0.98-0.99 x the time).
CHECK_PROCESSES: int | None = None
# Waves whose low-frequency penalty is below this fraction of its peak are left out of it.
LOWFREQ_SUPPORT = 1e-6
# An axis's factor of the prior's low-pass below which its waves are not computed (see
# _Problem.__init__).
_PHI_FLOOR = 1e-18
_POOLS: dict[int, ThreadPoolExecutor] = {}
_POOLS_LOCK = threading.Lock()


def _forget_pools() -> None:
    """In a forked child (a process pool compiling several inputs): the parent's threads
    are not there, so its pools would never run a block; start afresh."""
    global _POOLS_LOCK
    _POOLS.clear()
    _POOLS_LOCK = threading.Lock()


if hasattr(os, "register_at_fork"):
    os.register_at_fork(after_in_child=_forget_pools)


@functools.lru_cache(maxsize=256)
def _row_blocks(rows: int, parts: int) -> tuple[slice, ...]:
    """`parts` contiguous blocks of row indices covering ``range(rows)`` (cached: a light
    search asks for them some 10 times per Gauss-Newton step on levels of a few pixels)."""
    edges = [rows * k // parts for k in range(parts + 1)]
    return tuple(slice(a, b) for a, b in zip(edges[:-1], edges[1:]) if b > a)


def _run_rows(fn: Callable[[slice], None], blocks: tuple[slice, ...]) -> None:
    """Call ``fn(block)`` for every block of rows, one thread per block: the calling
    thread takes the first block, pool threads the others."""
    futures = []
    if len(blocks) > 1:
        # (measured at 1024 px: with the calling thread idle while two pool threads worked,
        # a solve took 11 % longer)
        with _POOLS_LOCK:
            pool = _POOLS.get(len(blocks) - 1)
            if pool is None:
                pool = _POOLS[len(blocks) - 1] = ThreadPoolExecutor(len(blocks) - 1, "haptex-rows")
        futures = [pool.submit(fn, b) for b in blocks[1:]]
    try:
        fn(blocks[0])
    finally:
        for future in futures:
            future.result()


def _dx2(z: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
    """Twice the periodic central difference along columns (x): z[j+1] - z[j-1] (into `out`,
    not `z`, when given)."""
    out = np.empty_like(z) if out is None else out
    if z.shape[1] < 3:  # a column's neighbours either side are one and the same pixel
        out[...] = 0
        return out
    np.subtract(z[:, 2:], z[:, :-2], out=out[:, 1:-1])
    np.subtract(z[:, 1], z[:, -1], out=out[:, 0])
    np.subtract(z[:, 0], z[:, -2], out=out[:, -1])
    return out


def _dy2(z: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
    """Twice the periodic central difference along rows (y): z[i+1] - z[i-1] (into `out`,
    not `z`, when given)."""
    out = np.empty_like(z) if out is None else out
    _dy2_rows(z, slice(0, z.shape[0]), out)
    return out


def _dy2_rows(z: np.ndarray, rows: slice, out: np.ndarray) -> np.ndarray:
    """Rows `rows` of :func:`_dy2` of `z` (periodic), written to ``out[rows]``, which is
    returned."""
    n = z.shape[0]
    r0, r1 = rows.start, rows.stop
    if n < 3:  # a row's neighbours either side are one and the same row
        out[rows] = 0
        return out[rows]
    i0, i1 = max(r0, 1), min(r1, n - 1)
    if i1 > i0:
        np.subtract(z[i0 + 1:i1 + 1], z[i0 - 1:i1 - 1], out=out[i0:i1])
    if r0 == 0:
        np.subtract(z[1], z[-1], out=out[0])
    if r1 == n:
        np.subtract(z[0], z[-2], out=out[-1])
    return out[rows]


def _dx(z: np.ndarray) -> np.ndarray:
    """Periodic central difference along columns (x), pixel units."""
    out = _dx2(z)
    out *= 0.5
    return out


def _dy(z: np.ndarray) -> np.ndarray:
    """Periodic central difference along rows (y), pixel units."""
    out = _dy2(z)
    out *= 0.5
    return out


_BIHARMONIC = np.array(
    [[0, 0, 1, 0, 0], [0, 2, -8, 2, 0], [1, -8, 20, -8, 1], [0, 2, -8, 2, 0], [0, 0, 1, 0, 0]],
    dtype=np.float32,
)


def _filter_periodic(z: np.ndarray, kernel: np.ndarray) -> np.ndarray:
    """Correlate float32 `z` with a square odd `kernel` on the periodic domain (OpenCV's
    filters have no wrapping border: pad by wrapping, filter, crop)."""
    r = kernel.shape[0] // 2
    padded = cv2.copyMakeBorder(z, r, r, r, r, cv2.BORDER_WRAP)
    return cv2.filter2D(padded, -1, kernel, borderType=cv2.BORDER_CONSTANT)[r:-r, r:-r]


def _lap2(z: np.ndarray, scale: float = 1.0, shift: float = 0.0) -> np.ndarray:
    """Periodic ``scale * _lap(_lap(z)) + shift * z`` (13-point biharmonic) by OpenCV, about
    4 x faster, in one filter pass."""
    if z.dtype != np.float32 or min(z.shape) < 3:
        return scale * _lap(_lap(z)) + shift * z
    kernel = scale * _BIHARMONIC
    kernel[2, 2] += shift
    return _filter_periodic(z, kernel)


def _lap(z: np.ndarray) -> np.ndarray:
    """Periodic 5-point Laplacian."""
    return np.roll(z, 1, 0) + np.roll(z, -1, 0) + np.roll(z, 1, 1) + np.roll(z, -1, 1) - 4 * z


def _across(light) -> tuple[float, float] | None:
    """Unit image-plane direction across the light; None for overhead light, which has none
    (both slopes then enter alike)."""
    lx, ly = float(light[0]), float(light[1])
    n = float(np.hypot(lx, ly))
    return (-ly / n, lx / n) if n > 1e-9 else None


class _PlaneTerm(NamedTuple):
    """The rank-two operator ``weight x sum(w) x |slope|² / 2`` on the slopes of the
    least-squares plane through the data (weights `w`); see :func:`_plane_term`.

    The slopes are ``M^-1 (<ux, z>, <uy, z>)``, with ``u`` the weighted, centred coordinates
    and ``M`` their moments, and ``q = weight x sum(w) x M^-2``. Where the data weigh 1 on a
    top-left box and 0 elsewhere (an unmasked plain image), the ramps are kept as a row `rx`
    and a column `ry` over that box (the solver applies them as row profiles: see
    :class:`_LowFreqOperator`); else `ux`, `uy` are the full ramps.
    """

    q: np.ndarray
    box: tuple[int, int] | None = None
    rx: np.ndarray | None = None
    ry: np.ndarray | None = None
    ux: np.ndarray | None = None
    uy: np.ndarray | None = None

    def moments(self, v: np.ndarray) -> np.ndarray:
        """``(<ux, v>, <uy, v>)`` (with the full ramps)."""
        return np.array([float(np.vdot(self.ux, v)), float(np.vdot(self.uy, v))])

    def add_to(self, v: np.ndarray, out: np.ndarray) -> None:
        """Add the operator applied to `v` to `out` (with the full ramps)."""
        gx, gy = self.q @ self.moments(v)
        out += self.ux * _F(gx)
        out += self.uy * _F(gy)


class _LowFreqOperator:
    """The low-frequency prior's operator on a level: its symbol `lf` (rfft layout of a
    `shape` level) on the rectangle of rows `ky` and columns `kx` that holds the kept waves,
    and the :class:`_PlaneTerm` `plane` (or None).

    The waves are few, so the solver keeps the prior's part of its vectors as those waves'
    coefficients, carried along with the heights and the conjugate gradients' vectors (see
    :meth:`_Problem.gn_step`): the operator then costs no pass over the level. It had been
    applied on the pixels in every CG iteration (on block means of large levels), at about
    the preconditioner's cost: 20 % of a 512 px plain image's solve. Measured against that in
    one run (16 plain images of the bench's surfaces and lights, light given, best of 3,
    alternating): 256 px 7.04 -> 5.90 s, 512 px 14.47 -> 13.18 s, 1024 px (best of 2) 40.55
    -> 38.71 s; summed errors 3.969 -> 3.970, 4.031 -> 3.994, 4.185 -> 4.206 (the block
    means' approximation is gone; a Brownian surface at 60° 0.664 -> 0.683, the others within
    0.002). The plane term over a top-left box works on two row profiles, its ramp and its
    indicator, in the solver's passes over the rows (shading_kernels); a plane over masked
    data, on the pixels.
    """

    def __init__(self, lf: np.ndarray, ky: np.ndarray, kx: np.ndarray, shape: tuple[int, int],
                 plane: _PlaneTerm | None):
        rows, cols = shape
        self.shape = shape
        self.index = np.ix_(ky, kx)
        self.sym = lf[self.index].astype(np.float64)
        # Parseval on the rfft layout: <u, v> = sum(weight x Re(conj(U) V)); the mean and a
        # Nyquist column count once, the others twice. The coefficients are the spectrum's
        # times sqrt(weight), so that inner products are plain ones.
        self.root = np.sqrt(np.where((kx == 0) | (2 * kx == cols), 1.0, 2.0) / (rows * cols))[None, :]
        self.plane = plane
        self.profiles = None
        if plane is not None and plane.box is not None:
            c1 = plane.box[1]
            self.profiles = np.zeros((2, cols), _F)
            self.profiles[0, :c1], self.profiles[1, :c1] = plane.rx, 1.0

    def analyse(self, v: np.ndarray, workers: int) -> np.ndarray:
        """The rectangle's coefficients of `v` (complex128)."""
        return self.waves(real_fft.rfft2(v, workers))

    def waves(self, spectrum: np.ndarray) -> np.ndarray:
        """The rectangle's coefficients in an rfft2 `spectrum` (complex128)."""
        return spectrum[self.index] * self.root

    def add_to_spectrum(self, coef: np.ndarray, spectrum: np.ndarray) -> None:
        """Add the waves of coefficients `coef` to an rfft2 `spectrum`."""
        spectrum[self.index] += coef / self.root

    def inner(self, a: np.ndarray, b: np.ndarray) -> float:
        """The inner product of two vectors made of the rectangle's waves, coefficients `a`
        and `b`."""
        return float(np.vdot(a, b).real)

    def to_pixels(self, coef: np.ndarray, workers: int) -> np.ndarray:
        """The vector (float32, the level's shape) made of the rectangle's waves with
        coefficients `coef`."""
        spec = np.zeros((self.shape[0], self.shape[1] // 2 + 1), np.complex64)
        self.add_to_spectrum(coef, spec)
        return real_fft.irfft2(spec, self.shape, workers).astype(_F, copy=False)

    def products(self) -> np.ndarray | None:
        """An array for the rows' products with the plane's profiles (see
        ``row_products_rows``), None without them."""
        return None if self.profiles is None else np.empty((2, self.shape[0]), _F)

    def products_of(self, v: np.ndarray, blocks: tuple[slice, ...]) -> np.ndarray:
        """`v`'s rows' products with the plane's profiles (in threads by `blocks` of rows)."""
        products = self.products()
        _run_rows(lambda rows: row_products_rows(v, self.profiles, products, rows.start, rows.stop), blocks)
        return products

    def plane_moments(self, products: np.ndarray) -> np.ndarray:
        """The plane's ``(<ux, v>, <uy, v>)`` from `v`'s row products with its profiles."""
        plane, r1 = self.plane, self.plane.box[0]
        return np.array([float(products[0, :r1].sum(dtype=np.float64)),
                         float(np.dot(products[1, :r1].astype(np.float64), plane.ry))])

    def plane_coefficients(self, products: np.ndarray) -> np.ndarray:
        """The plane's profiles' coefficients per row for heights whose row products with
        them are `products` (see ``add_row_combinations_rows``)."""
        plane, r1 = self.plane, self.plane.box[0]
        gx, gy = plane.q @ self.plane_moments(products)
        coef = np.zeros(products.shape, _F)
        coef[0, :r1] = gx
        coef[1, :r1] = plane.ry * _F(gy)
        return coef

    def energy(self, v: np.ndarray, waves: np.ndarray, workers: int) -> float:
        """The prior's energy of heights `v` whose coefficients are `waves`."""
        e = 0.5 * self.inner(waves, self.sym * waves)
        if self.plane is not None:
            if self.profiles is None:
                moments = self.plane.moments(v)
            else:
                moments = self.plane_moments(self.products_of(v, _row_blocks(v.shape[0], workers)))
            e += 0.5 * float(moments @ self.plane.q @ moments)
        return e

    def add_plane(self, v: np.ndarray, out: np.ndarray, workers: int) -> None:
        """Add the plane term applied to `v` to `out` (on the pixels)."""
        if self.plane is None:
            return
        if self.profiles is None:
            self.plane.add_to(v, out)
            return
        blocks = _row_blocks(v.shape[0], workers)
        coef = self.plane_coefficients(self.products_of(v, blocks))
        _run_rows(lambda rows: add_row_combinations_rows(coef, self.profiles, out, rows.start, rows.stop), blocks)


def _plane_term(w: np.ndarray, weight: float) -> _PlaneTerm | None:
    """The :class:`_PlaneTerm` of weights `w`; None where they span no area (a coarse level
    of a mostly masked image: a few pixels in one row or column), whose plane is undefined."""
    r1, c1 = (int(np.count_nonzero(w.any(axis=k))) for k in (1, 0))
    inside = w[:r1, :c1]
    # Ones on a top-left box and zeros elsewhere (tested by reductions, not a pass over a copy).
    box = r1 * c1 > 0 and np.count_nonzero(w) == r1 * c1 and float(inside.min()) == float(inside.max()) == 1.0
    wsum = float(r1 * c1) if box else float(w.sum())
    if wsum <= 0:
        return None
    if box:
        # Ones on the top-left box: the centred ramps are a row and a column, and their
        # moments are sums over them (a 600 px level's term: 26 -> 1 ms).
        rx, ry = (np.arange(n) - (n - 1) / 2.0 for n in (c1, r1))
        moments = np.diag([r1 * float(rx @ rx), c1 * float(ry @ ry)])
    else:
        yy, xx = np.mgrid[: w.shape[0], : w.shape[1]]
        ramps = [((u - float(np.sum(w * u)) / wsum) * w) for u in (xx, yy)]
        moments = np.array([[float(np.sum(a * u)) for u in (xx, yy)] for a in ramps])
    eig = np.linalg.eigvalsh(moments)
    if not eig[0] > 1e-6 * max(eig[1], 1e-30):
        return None
    inv = np.linalg.inv(moments)
    q = weight * wsum * inv @ inv
    if box:
        return _PlaneTerm(q, (r1, c1), rx=rx.astype(_F), ry=ry.astype(_F))
    ux, uy = (a.astype(_F) for a in ramps)
    return _PlaneTerm(q, ux=ux, uy=uy)


class _Problem:
    """One resolution level: image, weights, light, regulariser and the FFT preconditioner."""

    def __init__(self, image, weight, light, lam, workers=2, lowfreq=None, dark=None, bright=None,
                 bound_noise_sigmas=0.0, albedo_bound=True, lowfreq_spectral=None, lowfreq_plane=0.0,
                 plane_support=None, across_weight=1.0):
        # (not copied where they are contiguous float32 already: a level's arrays are only read)
        self.img = np.ascontiguousarray(image, dtype=_F)
        self.w = np.ascontiguousarray(weight, dtype=_F)
        # Censored pixels (weights, fractions of the pixel at coarse levels): black ones say
        # only that albedo R <= DARK_LEVEL (attached shadow: the surface faces away from the
        # light), saturated ones that albedo R >= BRIGHT_LEVEL. One-sided terms.
        self.dark = None if dark is None or not np.any(dark > 0) else dark.astype(_F)
        self.bright = None if bright is None or not np.any(bright > 0) else bright.astype(_F)
        # Lambertian shading never exceeds the albedo: the brightest valid pixels bound it
        # from below (a high percentile, so that a few noisy pixels do not set it; less
        # `bound_noise_sigmas` times the image noise, which raises a high percentile). Levels
        # without `albedo_bound` (coarse ones, whose averaged images are darker) have none.
        vals = self.img[self.w > 0.5]
        self.albedo_min = 0.0
        if albedo_bound and vals.size:
            self.albedo_min = float(np.percentile(vals, 99.9))
            if bound_noise_sigmas > 0:
                self.albedo_min -= bound_noise_sigmas * _noise_sigma(self.img, self.w)
        self.albedo_max = 1e3
        self.project_albedo = False
        # Hold the waves with no slope along the light (see solve_variational's hold_from_level).
        self.hold_across_waves = False
        self.light = np.asarray(light, dtype=float)
        self.lam = float(lam)
        # Weight of the squared slope across the light in R's normalisation (1 = exact R).
        self.across_weight = float(across_weight)
        across = _across(self.light) or (0.0, 0.0)  # see reflectance_args
        self._reflectance_args = (np.asarray(self.light, _F), _F(1.0 - self.across_weight),
                                  np.asarray(across, _F))
        # Threads only pay on large levels (measured: a 2-thread FFT of 128 x 128 costs more).
        self.workers = workers if image.size >= PARALLEL_FFT_MIN_PIXELS else 1
        rows, cols = image.shape
        wy = 2 * np.pi * np.fft.fftfreq(rows)[:, None]
        wx = 2 * np.pi * np.fft.rfftfreq(cols)[None, :]
        self.sx = np.sin(wx).astype(_F)
        self.sy = np.sin(wy).astype(_F)
        self.lap2 = ((2 * np.cos(wx) + 2 * np.cos(wy) - 4) ** 2).astype(_F)
        # The preconditioner's fixed parts (the same float32 values it computed in every step).
        self._sx2, self._sy2, self._lam_lap2 = self.sx**2, self.sy**2, self.lam * self.lap2
        self.shape = (rows, cols)
        # Optional penalty on slopes at wavelengths longer than the data region (non-periodic
        # images: a ramp or bowl across the image is otherwise nearly free, traded against
        # the albedo): mu * phi(w) * |D(w)|^2 with phi a Gaussian low-pass.
        self.lf = None
        if lowfreq is not None:
            mu, w0 = lowfreq
            limit = np.inf
            if lowfreq_spectral is not None:
                # The image's own long-wave power tightens the prior (shading_prior), on the
                # waves of fewer cycles than its table holds (0 on the others).
                limit = 2 * np.pi * (len(lowfreq_spectral["power"]) - 0.5) / lowfreq_spectral["side_px"]
            # The penalty lives on a few waves (phi is below LOWFREQ_SUPPORT of its peak
            # beyond about 4 cycles per data region), which the solver keeps as coefficients
            # (see _LowFreqOperator). It is computed on the rows and columns where an axis's
            # factor of phi reaches _PHI_FLOOR (or the spectral prior has a table): beyond
            # them lf < 2 mu _PHI_FLOOR, which is checked to lie below the kept ones (else
            # the whole level). A 1200 px level's grid took 20 ms.
            ry, rx = (np.flatnonzero((np.exp(-(w / w0) ** 2) >= _PHI_FLOOR) | (np.abs(w) < limit))
                      for w in (wy[:, 0], wx[0]))
            lf, keep, across = self._lowfreq_symbol(wx[:, rx], wy[ry], mu, w0)
            if not 4 * mu * _PHI_FLOOR <= LOWFREQ_SUPPORT * float(lf.max()):
                ry, rx = np.arange(rows), np.arange(wx.shape[1])
                lf, keep, across = self._lowfreq_symbol(wx, wy, mu, w0)
            if lowfreq_spectral is not None:
                iy, ix = np.flatnonzero(np.abs(wy[ry, 0]) < limit), np.flatnonzero(np.abs(wx[0, rx]) < limit)
                spectral = np.zeros(lf.shape)
                spectral[np.ix_(iy, ix)] = spectral_symbol(wx[:, rx[ix]], wy[ry[iy]], across[np.ix_(iy, ix)],
                                                           **lowfreq_spectral)
                lf = np.maximum(np.where(keep, lf, 0.0), spectral)
                keep |= spectral > 0
            # The preconditioner and the operator see the kept waves (the operator on the
            # rectangle of rows and columns that holds them: see _LowFreqOperator).
            self.lf = np.zeros((rows, wx.shape[1]), _F)
            self.lf[np.ix_(ry, rx)] = np.where(keep, lf, 0.0)
            ky, kx = ry[keep.any(axis=1)], rx[keep.any(axis=0)]
            # The slopes of the least-squares plane through the image (weighted by
            # `plane_support`, by default the data weights): a tilt along the light is traded
            # against the albedo, and on the periodic domain it costs only its return in the
            # margin, which the prior's few long waves hardly see. Penalised as
            # lowfreq_plane x mu x (support) x |slope|² / 2: a rank-two term of this
            # operator. (Not the mean of the differences: that telescopes to the edge pixels,
            # which then bend to meet it.)
            support = self.w if plane_support is None else plane_support
            plane = _plane_term(support, lowfreq_plane * mu) if lowfreq_plane > 0 else None
            self._lf = _LowFreqOperator(self.lf, ky, kx, (rows, cols), plane)

    def _lowfreq_symbol(self, wx, wy, mu, w0):
        """The flat-on-average prior's symbol ``mu phi |slope across the light|²`` on the
        grid of angular frequencies `wx`, `wy` (broadcast), the waves kept (above
        ``LOWFREQ_SUPPORT`` of its peak) and the squared slope across the light."""
        phi = np.exp(-(wx**2 + wy**2) / (w0 * w0))
        # Slope across the light only: along it, the linear shading term fixes the slope.
        c = _across(self.light)
        if c is None:
            across = np.sin(wx) ** 2 + np.sin(wy) ** 2
        else:
            across = (c[0] * np.sin(wx) + c[1] * np.sin(wy)) ** 2
        lf = mu * phi * across
        return lf, lf > LOWFREQ_SUPPORT * float(lf.max()), across

    def lowfreq(self, v):
        """The low-frequency penalty's operator applied to `v` (its symbol on the kept waves
        and the plane's rank-two term)."""
        op = self._lf
        out = op.to_pixels(op.sym * op.analyse(v, self.workers), self.workers)
        op.add_plane(v, out, self.workers)
        return out

    def waves(self, z):
        """The prior's coefficients of heights `z` (None without the prior)."""
        return None if self.lf is None else self._lf.analyse(z, self.workers)

    def reflectance_args(self) -> tuple:
        """The kernels' reflectance arguments (float32): the light, the damping ``k`` of the
        squared slope across the light and that direction (see shading_kernels'
        ``_reflectance_pixel``)."""
        return self._reflectance_args

    def censored_args(self) -> tuple:
        """The kernels' censored-pixel arguments: the dark and bright weights and whether
        each is present (an absent one is stood in for by the data weights, not read)."""
        return (self.w if self.dark is None else self.dark, self.w if self.bright is None else self.bright,
                self.dark is not None, self.bright is not None)

    def blocks(self, rows: int) -> tuple[slice, ...]:
        """Row blocks of the elementwise work, one per thread."""
        return _row_blocks(rows, self.workers)

    def energy(self, z, albedo, r=None, zw=None):
        """Total energy; `r` (the reflectance of `z`) and `zw` (its prior's coefficients,
        :meth:`waves`) are computed unless given."""
        if r is None:
            r = self.reflectance(z)
        # By row: w res², the censored pixels' one-sided terms and the thin plate's squared
        # Laplacian (row sums: the same total on any number of threads).
        sums = np.empty((z.shape[0], 3))
        args = (z, r, self.img, self.w, *self.censored_args(), _F(albedo), _F(DARK_LEVEL), _F(BRIGHT_LEVEL), sums)
        _run_rows(lambda rows: energy_rows(*args, rows.start, rows.stop), self.blocks(z.shape[0]))
        data, censored, thin_plate = sums.sum(axis=0)
        e = 0.5 * float(data) + 0.5 * float(censored) + 0.5 * self.lam * float(thin_plate)
        if self.lf is not None:
            e += self._lf.energy(z, self.waves(z) if zw is None else zw, self.workers)
        return e

    def reflectance(self, z):
        """The reflectance (albedo 1) of heights `z` (pixel units), with this level's damping
        of the squared slope across the light."""
        out = np.empty(z.shape, _F)
        args = self.reflectance_args()
        _run_rows(lambda rows: reflectance_rows(z, *args, out, rows.start, rows.stop), self.blocks(z.shape[0]))
        return out

    def precond(self, sums, albedo):
        """The preconditioner's inverse symbol from the weighted sums of ``rp²``, ``rp rq``
        and ``rq²`` over the pixels."""
        w = self.w
        wsum = float(w.sum()) or 1.0
        # Average reflectance-gradient tensor over the pixels, weighted by data weight; the
        # preconditioner sees the mean data weight, so masked margins are accounted for.
        wm = wsum / w.size
        txx, txy, tyy = (t / wsum * wm for t in sums)
        a2 = albedo * albedo
        sym = a2 * (txx * self._sx2 + 2 * txy * self.sx * self.sy + tyy * self._sy2)
        sym = sym + self._lam_lap2 + 1e-6 * (a2 * (txx + tyy) + self.lam)
        if self.lf is not None:
            sym = sym + self.lf
        inv = (1.0 / sym).astype(_F)
        if self.hold_across_waves:
            # CG's directions are preconditioned residuals: with these waves' symbol at 0 the
            # step never contains them.
            lx, ly = float(self.light[0]), float(self.light[1])
            along = (lx * self.sx + ly * self.sy) ** 2
            held = along <= 1e-9 * (lx * lx + ly * ly)
            held[0, 0] = False
            inv[held] = 0.0
        return inv

    def apply_pre(self, inv_sym, v, waves=None):
        """The preconditioner applied to `v` plus, with the prior, the vector of the prior's
        waves with coefficients `waves`: (result, its waves' coefficients, `v`'s waves'
        coefficients), the last two None without `waves`."""
        f = real_fft.rfft2(v, self.workers)
        v_waves = z_waves = None
        if waves is not None:
            v_waves = self._lf.waves(f)
            self._lf.add_to_spectrum(waves, f)
        f *= inv_sym
        if waves is not None:
            z_waves = self._lf.waves(f)
        # The spectrum is a temporary: the inverse may work in it.
        return real_fft.irfft2(f, self.shape, self.workers), z_waves, v_waves

    def gn_step(self, z, albedo, max_cg, tol, previous=(), zw=None):
        """One Gauss-Newton direction by PCG, then the minimum of the Gauss-Newton model over
        the span of that direction and the `previous` steps (pairs of a step and its prior's
        coefficients); returns (dz, its prior's coefficients, the energy's gradient less the
        prior's waves). With the prior, `zw` are `z`'s coefficients (computed if not given)."""
        blocks = self.blocks(z.shape[0])
        ha, hb, nwa, nwb, fa, fb, grad, b, tb = (np.empty(z.shape, _F) for _ in range(9))
        # By row: the sums of w rp², w rp rq, w rq² (the preconditioner's tensor) and w r².
        row_sums = np.empty((z.shape[0], 4))
        project = self.project_albedo and self._albedo_free(albedo)
        ua, ub, u = (np.empty(z.shape, _F) for _ in range(3)) if project else (None, None, None)
        lam_l2 = self.lam * _lap2(z)
        # gn_setup_rows's inputs and outputs (arrays it does not read or write stand in for
        # absent censored weights and projection factors).
        setup_args = (
            z, self.img, self.w, *self.censored_args(), *self.reflectance_args(), _F(albedo),
            _F(DARK_LEVEL), _F(BRIGHT_LEVEL), project, fa, fb, ha, hb, nwa, nwb,
            fa if ua is None else ua, fb if ub is None else ub, row_sums,
        )

        def minus_divergence(f1, f2, rows, out):
            # -(D_x f1 + D_y f2) on these rows into out's (periodic central differences)
            o = _dx2(f1[rows], out[rows])
            o *= 0.5
            o2 = _dy2_rows(f2, rows, tb)
            o2 *= 0.5
            np.add(o, o2, out=o)
            np.negative(o, out=o)
            return o

        def gradient(rows):
            # grad = J^T W res + lam L L z, and the CG's right-hand side -grad
            g = minus_divergence(fa, fb, rows, grad)
            g += lam_l2[rows]
            np.negative(g, out=b[rows])
            if project:
                minus_divergence(ua, ub, rows, u)

        # Reflectance, residual, Jacobian (halves of the central differences folded into the
        # coefficients, the sign of D^T = -D into the data weights), the gradient's and the
        # projection's factors, and the preconditioner's tensor; then the gradient.
        _run_rows(lambda rows: gn_setup_rows(*setup_args, rows.start, rows.stop), blocks)
        _run_rows(gradient, blocks)
        lf = self._lf if self.lf is not None else None
        b_waves = None
        if lf is not None:
            # The gradient's prior part: the plane's on the pixels, the waves' as coefficients.
            lf.add_plane(z, grad, self.workers)
            np.negative(grad, out=b)
            b_waves = -(lf.sym * (self.waves(z) if zw is None else zw))
        jv = np.empty(z.shape, _F)
        vp = None  # (u, s) of the variable projection, when it applies

        lam32, shift32 = _F(self.lam), _F(1e-6)
        profiles = None if lf is None else lf.profiles

        def matvec(v):
            # J v, then the thin plate, D^T of J v's weighted terms and the projection's
            # rank-one term, in two compiled passes (shading_kernels); the plane term's row
            # products in the first, its rows' combinations in the second. Not the prior's
            # waves: conjugate gradients keep them as coefficients.
            out = np.empty_like(v)
            u, cu = (v, _F(0.0)) if vp is None else (vp[0], _F(float(np.vdot(vp[0], v)) / vp[1]))
            products = None if lf is None else lf.products()

            def first(rows):
                jacobian_rows(v, ha, hb, jv, rows.start, rows.stop)
                if profiles is not None:
                    row_products_rows(v, profiles, products, rows.start, rows.stop)

            _run_rows(first, blocks)
            coef = None if profiles is None else lf.plane_coefficients(products)

            def second(rows):
                normal_rows(v, jv, nwa, nwb, lam32, shift32, u, cu, out, rows.start, rows.stop)
                if profiles is not None:
                    add_row_combinations_rows(coef, profiles, out, rows.start, rows.stop)

            _run_rows(second, blocks)
            if lf is not None and profiles is None:
                lf.add_plane(v, out, self.workers)  # a plane over masked data, on the pixels
            return out

        totals = row_sums.sum(axis=0)
        s_vp = float(totals[3])
        if project and s_vp > 0:
            # Variable projection (Golub-Pereyra): the albedo, refitted after every step, is
            # eliminated, so the step solves the Schur complement J^T W J - u u^T / s of the
            # joint (height, albedo) Gauss-Newton system, with u = J^T W r and s = r^T W r:
            # one step may trade slope against albedo, which alternating steps do slowly.
            vp = (u, s_vp)

        inv_sym = self.precond([float(t) for t in totals[:3]], albedo)
        # With the prior, the residual is `rr` plus the waves of coefficients `rho`, and the
        # iterates' coefficients are kept beside them (`d_waves`, `x_waves`): the prior's
        # operator never touches the pixels, and inner products take its waves' part by
        # Parseval. The same iterations as on the pixels.
        x = np.zeros_like(b)
        rr = b.copy()
        rho = None if lf is None else b_waves.copy()
        zz, z_waves, r_waves = self.apply_pre(inv_sym, rr, rho)
        d, d_waves = zz.copy(), z_waves
        rz = float(np.vdot(rr, zz))
        b_sq = float(np.vdot(b, b))
        if lf is not None:
            rz += lf.inner(rho, z_waves)
            b_sq += 2 * lf.inner(r_waves, b_waves) + lf.inner(b_waves, b_waves)
            x_waves = np.zeros_like(rho)
        b_norm = float(np.sqrt(max(b_sq, 0.0))) or 1.0
        row_sq = np.empty(z.shape[0])  # sums of rr² by row (see cg_update_rows)
        for it in range(max_cg):
            ad = matvec(d)
            dad = float(np.vdot(d, ad))
            if lf is not None:
                ad_waves = lf.sym * d_waves
                dad += lf.inner(d_waves, ad_waves)
            if dad <= 0 or not np.isfinite(dad):
                break
            alpha = rz / dad

            a32 = _F(alpha)
            _run_rows(lambda rows: cg_update_rows(x, rr, d, ad, a32, row_sq, rows.start, rows.stop), blocks)
            if lf is None:
                if float(np.sqrt(row_sq.sum())) < tol * b_norm or it == max_cg - 1:
                    break  # converged, or the last iteration: no next direction (and its transforms)
                zz, _, _ = self.apply_pre(inv_sym, rr)
            else:
                x_waves += alpha * d_waves
                rho -= alpha * ad_waves
                if it == max_cg - 1:
                    break
                zz, z_waves, r_waves = self.apply_pre(inv_sym, rr, rho)
                sq = row_sq.sum() + 2 * lf.inner(r_waves, rho) + lf.inner(rho, rho)
                if float(np.sqrt(max(sq, 0.0))) < tol * b_norm:
                    break
            rz_new = float(np.vdot(rr, zz))
            if lf is not None:
                rz_new += lf.inner(rho, z_waves)
            if not rz_new > 0:  # nothing left that the preconditioner lets through
                break
            b32 = _F(rz_new / rz)
            _run_rows(lambda rows: cg_direction_rows(d, zz, b32, rows.start, rows.stop), blocks)
            if lf is not None:
                d_waves = (rz_new / rz) * d_waves + z_waves
            rz = rz_new
        if lf is None:
            if previous:
                x = _subspace_minimum([x, *(p for p, _ in previous)], [b - rr, *(matvec(p) for p, _ in previous)], b)
            return x, None, grad
        if previous:
            # A x = b - r; A u = the pixels' part and the prior's on coefficients.
            x, x_waves = _subspace_minimum(
                [(x, x_waves), *previous],
                [(b - rr, b_waves - rho), *((matvec(p), lf.sym * w) for p, w in previous)],
                (b, b_waves), lf.inner)
        return x, x_waves, grad

    def solve(self, z, albedo, n_gn, max_cg, tol, fit_albedo, gn_rtol=0.0, subspace_steps=0):
        zw = self.waves(z)  # the prior's coefficients, carried along with the heights
        if self.project_albedo:
            albedo, e = self.fit_albedo(z, albedo, zw=zw)
        else:
            e = self.energy(z, albedo, zw=zw)
        previous = []  # the last accepted steps and their coefficients, newest first
        for _ in range(n_gn):
            dz, dzw, _ = self.gn_step(z, albedo, max_cg, tol, previous, zw)
            step = 1.0
            accepted = False
            for _ in range(8):  # backtracking: GN may overshoot where R is far from linear
                zt = z + step * dz
                zwt = None if zw is None else zw + step * dzw
                rt = self.reflectance(zt)
                if self.project_albedo:
                    at, et = self.fit_albedo(zt, albedo, rt, zwt)
                else:
                    et = self.energy(zt, albedo, rt, zwt)
                if np.isfinite(et) and et <= e:
                    accepted = True
                    break
                step *= 0.5
            if not accepted:
                break
            small = step == 1.0 and e - et < gn_rtol * e
            if subspace_steps:
                previous = [(step * dz, None if dzw is None else step * dzw), *previous][:subspace_steps]
            z, zw, e = zt, zwt, et
            if self.project_albedo:
                albedo = at
            elif fit_albedo:
                albedo, e = self.fit_albedo(z, albedo, rt, zw)
            if small:
                break  # a full step gained little: converged on this level
        return z, albedo

    def _albedo_free(self, albedo: float) -> bool:
        """The least-squares albedo is not held at one of its bounds."""
        low = max(self.albedo_min, 1e-3)
        return low * (1 + 1e-6) < albedo < self.albedo_max * (1 - 1e-6)

    def fit_albedo(self, z, albedo, r=None, zw=None):
        """The least-squares albedo for heights `z` (within bounds) and the energy there (`r`,
        `zw`: as for :meth:`energy`)."""
        if r is None:
            r = self.reflectance(z)
        sums = np.empty((z.shape[0], 2))  # by row: w r², w r img
        _run_rows(lambda rows: albedo_sums_rows(r, self.img, self.w, sums, rows.start, rows.stop),
                  self.blocks(z.shape[0]))
        den, num = (float(t) for t in sums.sum(axis=0))
        if den > 0:
            a = num / den
            if np.isfinite(a) and a > 0:
                albedo = self.bounded_albedo(a)
        return albedo, self.energy(z, albedo, r, zw)

    def bounded_albedo(self, albedo: float) -> float:
        """`albedo` held within this level's bounds."""
        return min(max(albedo, self.albedo_min, 1e-3), self.albedo_max)


def _subspace_minimum(directions, products, b, inner=None):
    """The minimum of the quadratic model ``1/2 x.A x - b.x`` over the span of `directions`.

    `products` are the directions times A. The model's 2-3 dimensional restriction is solved
    exactly; when it is not positive definite (nearly parallel directions, float32 round-off),
    the first direction is returned unchanged. With `inner`, every vector is a pair (pixels,
    the prior's coefficients), `inner` the coefficients' inner product, and so is the result.
    """
    def dot(u, v):
        if inner is None:
            return float(np.vdot(u, v))
        return float(np.vdot(u[0], v[0])) + inner(u[1], v[1])

    h = np.array([[dot(u, av) for av in products] for u in directions])
    h = 0.5 * (h + h.T)
    g = np.array([dot(u, b) for u in directions])
    scale = np.sqrt(np.abs(np.diag(h)))
    if not np.all(np.isfinite(h)) or np.any(scale == 0):
        return directions[0]
    hn = h / np.outer(scale, scale)
    if np.linalg.eigvalsh(hn)[0] < 1e-4:
        return directions[0]
    coef = np.linalg.solve(hn, g / scale) / scale
    if not np.all(np.isfinite(coef)):
        return directions[0]
    if inner is not None:
        out = directions[0][0] * _F(coef[0])
        for c, u in zip(coef[1:], directions[1:]):
            out += u[0] * _F(c)
        return out, sum(c * u[1] for c, u in zip(coef, directions))
    out = directions[0] * _F(coef[0])
    for c, u in zip(coef[1:], directions[1:]):
        out += u * _F(c)
    return out


def _subpixel_variance_ratio(mean, mean_square, weight) -> float:
    """Image variance within a coarse level's pixels over the variance between them.

    `mean` and `mean_square` are the area averages of the full-resolution image and of its
    square; pixels with weight <= 0.5 (mostly masked) are left out. 0 for a uniform image,
    infinite when all the variance is within the pixels.
    """
    sel = weight > 0.5
    if not sel.any():
        return 0.0
    within = float(np.mean(np.maximum(mean_square - mean * mean, 0.0)[sel]))
    between = float(np.var(mean[sel]))
    if between > 0:
        return within / between
    return float("inf") if within > 0 else 0.0


_NOISE_KERNEL = np.array([[1, -2, 1], [-2, 4, -2], [1, -2, 1]], dtype=np.float32)


def _noise_sigma(img, w):
    """Robust estimate of white image noise (Immerkaer's mask, median of its response over
    pixels whose 3 x 3 neighbourhood is valid; the mask's norm is 6)."""
    resp = _filter_periodic(img.astype(np.float32, copy=False), _NOISE_KERNEL)
    valid = cv2.copyMakeBorder((w > 0.5).astype(np.uint8), 1, 1, 1, 1, cv2.BORDER_WRAP)
    full = cv2.erode(valid, np.ones((3, 3), np.uint8))[1:-1, 1:-1] > 0
    if not full.any():
        return 0.0
    return float(np.median(np.abs(resp[full]))) / (0.6745 * 6.0)


def _downsample(img, w):
    """Halve an image and its weights (area average over weighted pixels)."""
    wi, ww = _area_half(img * w), _area_half(w)
    out = np.where(ww > 1e-6, wi / np.maximum(ww, 1e-6), 0.0)
    return out.astype(_F), ww.astype(_F)


def _uncensored_weight(w, dark, bright):
    """Data weights of a level without the pixels that are partly censored (coarse levels).

    Such a pixel's intensity is the mean of its valid sub-pixels only, which is not the
    shading of its mean normal: at an attached shadow's edge the lit part is brighter than
    the whole, beside a saturated patch darker. Fitted as data, those pixels bias the albedo
    and the slopes near shadows, and the finest level keeps the bias. Measured on the bench
    surfaces at 256 px, light given: slants 70-75° (shadows on 5-30 % of the tile), Brownian
    0.188 -> 0.075 and 0.494 -> 0.199, plain weave 0.163 -> 0.120 and 0.282 -> 0.190, bumps
    0.135 -> 0.099 (at 75°); plain weave at 60° 0.030 -> 0.015, with noise of sigma 0.01
    0.107 -> 0.049; unshadowed images unchanged. (The sphere cap at 60° keeps its albedo
    0.12 % high: that one comes from the heights the shadow hides, see the bench.)
    """
    censored = [c > 0 for c in (dark, bright) if c is not None]
    mixed = np.logical_or.reduce(censored) & (w > 0) if censored else None
    if mixed is None or not mixed.any():
        return w
    return np.where(mixed, 0.0, w).astype(w.dtype)


def _area_half(a):
    """Halve a weight map by area averaging (None stays None)."""
    if a is None:
        return None
    size = (max(a.shape[1] // 2, 1), max(a.shape[0] // 2, 1))
    return cv2.resize(a.astype(np.float32), size, interpolation=cv2.INTER_AREA)


def _data_region(shape: tuple[int, int], data_shape: tuple[int, int]) -> np.ndarray:
    """Ones on the data region (`data_shape`, in the top-left corner) of a domain of
    `shape`, zeros in the margin (float32)."""
    region = np.zeros(shape, _F)
    region[: data_shape[0], : data_shape[1]] = 1.0
    return region


def _upsample(z, shape):
    """Upsample a height in pixel units to `shape` (values scale with the pixel ratio)."""
    factor = shape[1] / z.shape[1]
    big = cv2.resize(z.astype(np.float32), (shape[1], shape[0]), interpolation=cv2.INTER_LINEAR)
    return (big * factor).astype(_F)


def _level_prior(scale: float, albedo: float, data_shape, weight: float, cycles: float, power,
                 power_weight: float) -> tuple:
    """The (lowfreq, spectral) arguments of :class:`_Problem` for the low-frequency prior on a
    level `scale` times the finest one's size (see :func:`solve_variational`'s `lowfreq_*`
    parameters; weights relative to `albedo`²); (None, None) without a prior."""
    if not weight > 0 or data_shape is None:
        return None, None
    side = max(data_shape) * scale
    lowfreq = (weight * albedo * albedo, 2 * np.pi * cycles / side)
    spectral = None
    if power is not None and power_weight > 0:
        spectral = dict(albedo=albedo, side_px=side, data_pixels=data_shape[0] * data_shape[1] * scale * scale,
                        power=power, weight=power_weight)
    return lowfreq, spectral


def solve_variational(
    image: np.ndarray,
    weight: np.ndarray,
    light_vec: np.ndarray,
    albedo: float,
    *,
    lam: float = 1e-4,
    lam_growth: float = 8.0,
    smooth_lam_growth: float | None = None,
    smooth_ratio_max: float = 0.1,
    fit_albedo: bool = True,
    z0: np.ndarray | None = None,
    coarse_gn: int = 20,
    mid_gn: int = 6,
    fine_gn: int = 3,
    coarse_cg: int = 10,
    fine_cg: int = 6,
    mid_cg: int | None = None,
    gn_rtol: float = 0.0,
    tol: float = 0.02,
    min_size: int = 8,
    max_levels: int = 12,
    workers: int = 2,
    data_shape: tuple[int, int] | None = None,
    lowfreq_weight: float = 0.0,
    lowfreq_cycles: float = 1.0,
    lowfreq_power: np.ndarray | None = None,
    lowfreq_power_weight: float = 0.0,
    lowfreq_plane_weight: float = 0.0,
    lowfreq_plane_coarse: float = 1.0,
    lowfreq_plane_coarse_level: int = 2,
    lowfreq_fine_factor: float = 1.0,
    fit_min_level: int = 0,
    bound_max_level: int = 0,
    albedo_max: float = 1e3,
    dark: np.ndarray | None = None,
    bright: np.ndarray | None = None,
    albedo_projection: bool = False,
    projection_levels: Collection[int] | None = None,
    projection_max_ratio: float = np.inf,
    subgrid_damping: float | None = None,
    bound_noise_sigmas: float = 0.0,
    censored_data: bool = True,
    subspace_steps: int = 0,
    bound_start_albedo: bool = False,
    hold_from_level: int | None = None,
    large_level_cap: tuple[int, int, int] | None = None,
    lowfreq_check_level: int | None = None,
    lowfreq_reject_ratio: float = np.inf,
    lowfreq_reject_albedo: float = np.inf,
) -> tuple[np.ndarray, float]:
    """Minimise the shading energy coarse to fine on a periodic domain.

    Parameters
    ----------
    image, weight : ndarray
        Image in [0, 1] and data weights (0 = no information) on the periodic domain.
    light_vec : ndarray
        Unit light vector (lx, ly, lz).
    albedo : float
        Initial albedo.
    lam : float
        Thin-plate weight at full resolution (heights in pixel units).
    lam_growth : float
        Factor on `lam` per coarser level (continuation: smooth first, detail last).
    smooth_lam_growth, smooth_ratio_max : float or None, float
        On smooth shading (the half-resolution level's sub-pixel variance ratio, as for
        `subgrid_damping`, at most `smooth_ratio_max`), the factor per level beyond the
        half-resolution one instead of `lam_growth` (None = `lam_growth` on every level): a
        weaker continuation on the coarse levels (see ``shading.LOW_SLANT_LAM_GROWTH``).
    fit_albedo : bool
        Refit the albedo by least squares after each accepted step.
    fit_min_level : int
        Refit the albedo only on this level and coarser ones (0 = all); the finer levels keep
        it. With missing data (masked pixels, the margin of a non-periodic image) the albedo
        trades against free height offsets between characteristic strips.
    bound_max_level : int
        Apply the albedo's lower bound on this level and finer ones only (averaging makes
        the coarse images darker than the coarse surface's shading).
    albedo_max : float
        Upper bound on the fitted albedo (the light search uses it: see
        :func:`haptex_compile.shading_light._refine_light`).
    z0 : ndarray, optional
        Starting height at full resolution (pixel units); flat by default.
    coarse_gn, mid_gn, fine_gn : int
        Gauss-Newton steps on the coarse levels, on the half-resolution level and at full
        resolution.
    coarse_cg, fine_cg : int
        Conjugate-gradient iterations per step on the coarse levels and on the two finest.
    mid_cg : int, optional
        Conjugate-gradient iterations per step on the half-resolution level (default
        `fine_cg`).
    gn_rtol : float
        A level stops once a full Gauss-Newton step (no backtracking) lowers the energy by
        less than this fraction; 0 = always take the level's steps. Measured at 1 Mpx (random
        bumps): with 1e-3 the 256 px level stops after 3 of its 20 steps, the half-resolution
        level after 4 of 6, with the same energies.
    tol : float
        Relative residual at which conjugate gradients stop (inexact Newton).
    min_size : int
        Coarsest level's smaller side.
    max_levels : int
        Most pyramid levels (1 = full resolution only).
    workers : int
        Threads of the FFTs and, on levels of ``PARALLEL_FFT_MIN_PIXELS`` or more, of each
        Gauss-Newton step's elementwise work (in blocks of rows; the same heights as one
        thread, bit for bit).
    data_shape : (int, int), optional
        Size of the data region (non-periodic images embedded in a larger domain, at its
        top-left corner).
    lowfreq_weight : float
        Weight (relative to ``albedo²``) of the penalty on slopes at wavelengths longer than
        the data region; 0 = none. Non-periodic images need it: the fabric lies flat on
        average, and a ramp across the image is otherwise traded against the albedo. Only
        slopes across the light are penalised (along it, the linear shading term fixes them).
    lowfreq_cycles : float
        Cut-off of that penalty: a Gaussian low-pass at this many cycles per data region.
    lowfreq_power, lowfreq_power_weight : ndarray or None, float
        With `lowfreq_weight`: the height's expected power per radial frequency (px², at
        ``c = 0 .. len - 1`` cycles per data region's longer side; see
        :func:`haptex_compile.shading_prior.along_light_power`) and the noise variance over
        albedo² of a Gaussian prior on the waves across the light with that power
        (:func:`haptex_compile.shading_prior.spectral_symbol`); the penalty on each of those
        waves is the larger of the two.
    lowfreq_plane_weight : float
        With `lowfreq_weight`: also penalise the slopes (x and y) of the least-squares plane
        through the data region (all its pixels, masked and censored ones included),
        ``lowfreq_plane_weight x lowfreq_weight x albedo² x N x |slope|² / 2`` on a level
        where it covers N pixels (0 = off).
    lowfreq_plane_coarse, lowfreq_plane_coarse_level : float, int
        That weight is multiplied by `lowfreq_plane_coarse` on pyramid level
        `lowfreq_plane_coarse_level` (0 = full resolution) and coarser ones: a large factor
        holds the plane there. Coarse levels' fits of plain images came out tilted along the
        light, which the finer levels then spent their steps removing (measured: see
        ``shading.COARSE_PLANE_FACTOR``).
    lowfreq_fine_factor : float
        On the finest level, `lowfreq_weight` (and with it the plane's weight) is multiplied
        by this; the spectral prior (`lowfreq_power_weight`) is not. The coarse levels set the
        long waves under the full prior; the finest level's thin plate and data may then move
        them (see ``shading.PLAIN_FINE_PRIOR_PX``).
    albedo_projection : bool
        Eliminate the albedo from each Gauss-Newton step by variable projection (where it
        is fitted and not held at a bound): the step solves for the height with the albedo
        at its least-squares value for that height, so shape and albedo move together.
        Measured with ``method="accurate"``'s iteration counts on the bench surfaces: random
        bumps 0.014-0.029 -> 0.009-0.020, the sphere cap's a320 within 2 % at 15-45°
        (instead of up to 28 %); with few steps on every level it was no better (the
        default method projects on its converged half-resolution level only: see
        ``shading.DEFAULT_SOLVER``).
    projection_levels : collection of int, optional
        Pyramid levels (0 = full resolution, 1 = half) on which `albedo_projection` applies;
        None = all.
    projection_max_ratio : float
        Project only on levels whose sub-pixel variance ratio (as for `subgrid_damping`) is
        at most this: where sub-pixel roughness darkens the level's image, eliminating the
        albedo trades that darkening against slope (measured on Brownian surfaces at 128 px,
        ratio 0.25-0.3: mean a320 error -8 % -> -11 % with projection).
    subgrid_damping : float, optional
        Damping of the squared slope across the light on the coarse levels (default
        `SUBGRID_DAMPING`; 0 = the exact reflectance everywhere). A coarse level's image is
        the average of the shading over its pixels, darker than the shading of the averaged
        surface by the variance of the slopes within them (the sub-pixel roughness); the
        exact reflectance explains that darkening with coarse slopes across the light, which
        nothing else in the data contradicts, and the finer levels do not undo them (they are
        a local minimum: the true surface has the lower energy). So on level ``k >= 1`` the
        squared slope across the light in ``sqrt(1 + p² + q²)`` is weighted by
        ``1 / (1 + subgrid_damping * v_k)``, with ``v_k`` the image's variance within that
        level's pixels over its variance between them: about 1 at 64 px on a Brownian
        surface's 256 px image, below 0.2 on the sphere cap, the plain weave and the bumps.
        Measured on Brownian surfaces (H = 0.7, 256 px, slant 15°, 7 seeds x 2 tilts, light
        given): RMS relief 1.23 -> 1.12 x the truth's (means), mean a320 error -21 % -> -9 %.
    bound_noise_sigmas : float
        The albedo's lower bound (the finest level's 99.9th percentile) is lowered by this
        many times the image noise (estimated by :func:`_noise_sigma`; 0 = not lowered).
        Noise raises a high percentile, by 3.09 sigma for Gaussian noise on a plateau, and an
        albedo held a few per cent too high is absorbed as spurious relief. Noise-free smooth
        shading has an estimate near 0 (1e-7 to 2e-4 on the bench surfaces) and keeps its
        bound; rough shading (the Brownian surfaces: 0.014-0.033) counts as noise and has its
        bound loosened. Measured with 3.09 and noise of sigma 0.01 on the bench surfaces
        (256 px, light given): worst height error of random bumps 0.33 -> 0.20, sphere cap
        0.10 -> 0.06, Brownian surface 0.25 -> 0.20; noise-free results unchanged except the
        Brownian surface (worst 0.184 -> 0.171; over 7 seeds x 2 tilts at 15°, mean RMS relief
        1.12 -> 1.04 x the truth's, mean a320 error -8 % -> -6 %).
    dark, bright : ndarray, optional
        Weights of the censored pixels: black ones (attached shadows), which only say that
        ``albedo R <= DARK_LEVEL``, and saturated ones, ``albedo R >= BRIGHT_LEVEL``. Each
        adds a one-sided term (zero when the bound holds); `weight` should be 0 there.
    censored_data : bool
        On the coarse levels, fit the intensity of pixels that are partly censored (their
        valid part's mean) as well. False: they keep their one-sided term (for their censored
        fraction) but carry no intensity, see :func:`_uncensored_weight` (the default
        solver's choice; the light search keeps True, measured: the sphere cap's estimate at
        60° moved to 63° without them).
    subspace_steps : int
        Join this many previous accepted steps of the level to each Gauss-Newton direction:
        the step is the minimum of the Gauss-Newton model over their span (one more matvec
        per previous step), as nonlinear CG joins the previous direction. Each step's
        truncated CG re-finds the slow directions from scratch; across steps they add up.
        The slow direction measured: on flat ground the shading does not see slopes across
        the light at first order, so ridges along the light trade against a higher albedo
        (the sphere cap at 60°, light given: the default stopped 9 % above its energy's
        minimum, albedo +0.12 %, a320 +30 %; with 2 steps joined, +0.09 % and +19 %).
    bound_start_albedo : bool
        Hold the albedo a level starts from within that level's bounds before its first step
        (when the albedo is fitted). The finest level's lower bound (its 99.9th percentile)
        lies above the coarser levels', whose averaged images are darker, so the albedo it
        inherits may lie below it; without this, the first step is solved at that albedo,
        and the albedo fit after it raises it to the bound and undoes part of the step
        (random bumps of 1 Mpx lit at 15°: energy 1.08 -> 0.37 by the step, 0.83 after the
        fit). Measured with ``shading.DEFAULT_SOLVER`` on random bumps (256 px tiles, 30
        seeds, lights (15°, 30°), (20°, 120°), (15°, 300°)): mean height error 0.067 / 0.051
        / 0.080 -> 0.059 / 0.042 / 0.073; the bench's tiles at 15-60° within 0.001 except
        random bumps at 15° (0.050 -> 0.040).
    hold_from_level : int, optional
        On this pyramid level and coarser ones (0 = full resolution), hold the waves that have
        no slope along the light (the steps leave them as they are: their preconditioner
        symbol is 0). On a periodic domain they exist when the light runs along its axes or
        diagonals; the shading sees them only at second order, and a coarse level's
        averaged, darkened image sets them wrong. None = hold nothing. See
        ``shading_starts.ALIGNED_TILT_DEG``.
    large_level_cap : (int, int, int), optional
        ``(pixels, steps, cg)``: the levels other than the finest with at least `pixels`
        pixels take at most `steps` Gauss-Newton steps of at most `cg` CG iterations each
        (large images: those levels only give the next one its start; see
        ``shading.DEFAULT_SOLVER``). None = no cap.
    lowfreq_check_level, lowfreq_reject_ratio : int or None, float
        Test the `lowfreq_weight` prior on this pyramid level (the coarsest if the pyramid
        is shorter; None = no test): the levels down to it are solved again without the
        prior (side by side, see ``CHECK_PROCESSES``), and if the prior's result has more
        than `lowfreq_reject_ratio` times the energy (data and thin plate, without the prior)
        of the result without it, the data contradict the prior and the solve goes on
        without it. A scene that is not flat at the image's scale (an object on a flat
        ground) is flattened by the prior and its shading then fits badly; a texture that the
        prior suits fits about as well with it (see ``shading.LOWFREQ_REJECT_RATIO``).
    lowfreq_reject_albedo : float
        The prior is dropped only if, as well, the albedo without it is at most this factor
        times the albedo with it: a result that fits better under a much brighter albedo is a
        steeper surface that has run away, not a scene that the prior flattened (see
        ``shading.LOWFREQ_REJECT_ALBEDO``).

    Returns
    -------
    z : ndarray
        Height in pixel units (float32), mean 0.
    albedo : float
    """
    keep_freed_memory()  # the levels' temporaries are reused, not faulted in afresh
    pyramid = [(image.astype(_F), weight.astype(_F), dark, bright)]
    mid_cg = fine_cg if mid_cg is None else mid_cg
    damping = SUBGRID_DAMPING if subgrid_damping is None else float(subgrid_damping)
    if _across(light_vec) is None:
        damping = 0.0  # overhead light: nothing to damp
    squares = pyramid[0][0] ** 2  # area averages of the squared image, for the sub-pixel variance
    ratios = [0.0]  # sub-pixel variance ratio of each level (none at full resolution)
    while min(pyramid[-1][0].shape) // 2 >= min_size and len(pyramid) < max_levels:
        img, w, d, b = pyramid[-1]
        pyramid.append((*_downsample(img, w), _area_half(d), _area_half(b)))
        squares, _ = _downsample(squares, w)
        ratios.append(_subpixel_variance_ratio(pyramid[-1][0], squares, pyramid[-1][1]))
    # The data region on each level (area fractions): the prior's plane is fitted over it,
    # masked and shadowed pixels included (their heights belong to the surface as much), and
    # where it is a box of ones, as on an image's finest levels, the plane term works on row
    # profiles; over data weights with holes it was a pass over the level per CG iteration.
    regions = None
    if data_shape is not None:
        regions = [_data_region(image.shape, data_shape)]
        while len(regions) < len(pyramid):
            regions.append(_area_half(regions[-1]))
    # The thin plate's weight on each level (continuation: smooth first, detail last); beyond
    # the half-resolution level it grows by `smooth_lam_growth` on smooth shading.
    smooth = smooth_lam_growth is not None and len(ratios) > 1 and ratios[1] <= smooth_ratio_max
    beyond = smooth_lam_growth if smooth else lam_growth
    level_lams = [lam * lam_growth**min(k, 1) * beyond**max(k - 1, 0) for k in range(len(pyramid))]
    z = None
    if z0 is not None:
        zf = z0.astype(_F)
        z = cv2.resize(zf, pyramid[-1][0].shape[::-1], interpolation=cv2.INTER_AREA)
        z = z * (pyramid[-1][0].shape[1] / zf.shape[1])

    def level_problem(level, albedo, prior_weight):
        """The problem of pyramid level `level` with the low-frequency prior of weight
        `prior_weight` (relative to `albedo`²), with the level's settings."""
        img, w, d, b = pyramid[level]
        if not censored_data:
            w = _uncensored_weight(w, d, b)
        if level == 0:
            prior_weight *= lowfreq_fine_factor
        lowfreq, spectral = _level_prior(img.shape[1] / image.shape[1], albedo, data_shape, prior_weight,
                                         lowfreq_cycles, lowfreq_power, lowfreq_power_weight)
        prob = _Problem(
            img, w, light_vec, level_lams[level], workers, lowfreq, d, b,
            bound_noise_sigmas, albedo_bound=level <= bound_max_level, lowfreq_spectral=spectral,
            lowfreq_plane=lowfreq_plane_weight * (lowfreq_plane_coarse if level >= lowfreq_plane_coarse_level else 1.0),
            plane_support=None if regions is None else regions[level],
            across_weight=1.0 / (1.0 + damping * ratios[level]),
        )
        prob.albedo_max = max(albedo_max, prob.albedo_min)
        prob.project_albedo = albedo_projection and fit_albedo and level >= fit_min_level
        prob.project_albedo &= projection_levels is None or level in projection_levels
        prob.project_albedo &= ratios[level] <= projection_max_ratio
        prob.hold_across_waves = hold_from_level is not None and level >= hold_from_level
        return prob

    def run_levels(first, last, z, albedo, prior_weight):
        """Solve the levels `first` down to `last` from `z` (None: flat) with the
        low-frequency prior of weight `prior_weight`; (z, albedo, the last level's problem, None
        when there is no level to solve: a check level that is the finest)."""
        prob = None
        for level in range(first, last - 1, -1):
            prob = level_problem(level, albedo, prior_weight)
            z = np.zeros(prob.shape, _F) if z is None else _upsample(z, prob.shape)
            if bound_start_albedo and fit_albedo and level >= fit_min_level:
                albedo = prob.bounded_albedo(albedo)
            steps = fine_gn if level == 0 else (mid_gn if level == 1 else coarse_gn)
            cg = fine_cg if level == 0 else (mid_cg if level == 1 else coarse_cg)
            if large_level_cap is not None and level > 0 and z.size >= large_level_cap[0]:
                steps, cg = min(steps, large_level_cap[1]), min(cg, large_level_cap[2])
            z, albedo = prob.solve(z, albedo, steps, cg, tol, fit_albedo and level >= fit_min_level, gn_rtol,
                                   subspace_steps)
        return z, albedo, prob

    top = len(pyramid) - 1
    first = top
    if lowfreq_check_level is not None and lowfreq_weight > 0 and data_shape is not None:
        # The levels down to the check level without the prior (the longer chain, here) and,
        # side by side in a forked child, with it (the same heights as one after the other).
        check_level = min(lowfreq_check_level, top)
        (z_free, albedo_free, free), (z, albedo) = call_beside(
            functools.partial(run_levels, top, check_level, z, albedo, 0.0),
            lambda: run_levels(top, check_level, z, albedo, lowfreq_weight)[:2], CHECK_PROCESSES)
        # Both energies without the prior (`free`, the last problem without it, has none).
        worse = free.energy(z, albedo) > lowfreq_reject_ratio * free.energy(z_free, albedo_free)
        if worse and albedo_free <= lowfreq_reject_albedo * albedo:
            z, albedo, lowfreq_weight = z_free, albedo_free, 0.0
        first = check_level - 1
    z, albedo, _ = run_levels(first, 0, z, albedo, lowfreq_weight)
    return z - z.mean(), albedo


def reflectance(z: np.ndarray, light_vec: np.ndarray) -> np.ndarray:
    """Lambertian reflectance (albedo 1, not clipped) of height `z` (pixel units), periodic."""
    lx, ly, lz = (float(c) for c in light_vec)
    p, q = _dx(z.astype(np.float64)), _dy(z.astype(np.float64))
    return (lz - p * lx - q * ly) / np.sqrt(1.0 + p * p + q * q)


def energy(image, weight, light_vec, albedo, z, lam=1e-4, *, dark=None, bright=None, data_shape=None,
           lowfreq_weight=0.0, lowfreq_cycles=1.0, lowfreq_power=None, lowfreq_power_weight=0.0,
           lowfreq_plane_weight=0.0, lowfreq_fine_factor=1.0) -> float:
    """The shading energy of height `z` (pixel units) on the periodic domain (`dark` and
    `bright`: censored pixels, as in :func:`solve_variational`). With `data_shape` and a
    `lowfreq_weight` (a plain image's domain), the low-frequency prior as on the finest level of
    :func:`solve_variational` with those parameters, its weights relative to this `albedo`²."""
    lowfreq, spectral = _level_prior(1.0, albedo, data_shape, lowfreq_weight * lowfreq_fine_factor, lowfreq_cycles,
                                     lowfreq_power, lowfreq_power_weight)
    region = None if data_shape is None else _data_region(image.shape, data_shape)
    prob = _Problem(image, weight, light_vec, lam, 1, lowfreq, dark, bright, albedo_bound=False,
                    lowfreq_spectral=spectral, lowfreq_plane=lowfreq_plane_weight, plane_support=region)
    return prob.energy(z.astype(_F), albedo)
