"""Synthesis of Brownian (fractional Brownian) surfaces of index H.

Convention (the paper's Sect. 6.2): a Brownian surface X_H of index H in (0, 1) has Gaussian
increments with ``Var[X(x + s) - X(x)] = |s|**(2 H)`` (that is ``(sigma**2 + tau**2)**H``), so
the variogram grows as ``r**(2 H)``; its fractal (Hausdorff and box) dimension is ``D = 3 - H``.
Large H is smooth, small H is rough.

Every generator returns heights in µm with the sample mean removed and the sample RMS scaled to
exactly ``rms_um`` (a random per-surface factor, which leaves H and every log-ratio of the
variogram untouched). fBm is self-similar, so the pixel size only scales distances: after the
RMS normalisation it does not change the array at all; it is validated and documented, no more.

Methods
-------
``"circulant"`` (default)
    Exact: Stein's (2002) intrinsic embedding. A stationary Gaussian field with the compactly
    supported covariance ``psi(r) = c0 - r**(2H) + c2 r**2`` (r <= 1) is simulated on a torus by
    FFT; ``psi(0) - psi(r)`` equals ``r**(2H) - c2 r**2`` for every pair of grid points (the grid
    is scaled so its diameter is 1), and adding the random plane ``sqrt(2 c2) (x N1 + y N2)``
    restores the fBm variogram exactly. The torus covariance is the periodic *sum* of psi over
    its images, so by Poisson summation its eigenvalues are samples of a non-negative spectrum
    whenever psi is positive definite on the plane (Stein's theorem), and the torus only needs
    to be ``extent + R`` long (R = 1 for H <= 0.75, R = 2 above), not ``2 R``.
``"midpoint"``
    The paper's random midpoint displacement (Sect. 6.2, after Saupe): fast but biased; kept for
    fidelity with the paper's stimuli.

``periodic=True`` wraps seamlessly on the output shape (for tiles):

* circulant: spectral synthesis on the torus. The field is an exactly stationary Gaussian field
  on the torus whose spectral density at every DFT frequency is the *sampled* fBm spectrum,
  ``sum_m |f + m|**-(2H + 2)`` (aliasing over the lattice images included); the seam is
  statistically identical to the interior, and the variogram follows ``r**(2H)`` for lags small
  compared with the period (it levels off as the lag approaches half the period).
* midpoint: the same displacement scheme on a torus (square, power-of-two sides only).
"""
from __future__ import annotations

import functools
import math
import numbers

import numpy as np
import scipy.fft
import scipy.integrate

__all__ = ["MAX_WORKING_BYTES", "brownian_surface", "stein_embedding_shape"]

#: Refuse a synthesis whose estimated working memory exceeds this (bytes).
MAX_WORKING_BYTES = 4 * 2**30
# Bytes per torus point for the circulant method: white noise (8), the cached square-rooted
# eigenvalues (~4 for half a spectrum), the half spectrum (~8 complex on half), the inverse
# transform (8), plus FFT scratch: a generous round figure.
_CIRCULANT_BYTES_PER_POINT = 48
_MIDPOINT_BYTES_PER_POINT = 40
_FFT_WORKERS = 2


def _check_shape(shape: int | tuple[int, int]) -> tuple[int, int]:
    if isinstance(shape, (bool, np.bool_)):
        raise ValueError(f"shape must be an int or (ny, nx), not {shape!r}")
    if isinstance(shape, numbers.Integral):
        shape = (int(shape), int(shape))
    try:
        ny, nx = shape  # type: ignore[misc]
    except (TypeError, ValueError):
        raise ValueError(f"shape must be an int or a pair (ny, nx), got {shape!r}") from None
    for n in (ny, nx):
        if isinstance(n, (bool, np.bool_)) or not isinstance(n, numbers.Integral):
            raise ValueError(f"shape entries must be integers, got {shape!r}")
        if n < 2:
            raise ValueError(f"shape {tuple(shape)!r}: each side needs at least 2 pixels")
    return int(ny), int(nx)


def _check_positive_finite(name: str, value: float, *, allow_zero: bool = False) -> float:
    try:
        value = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a number, got {value!r}") from None
    if not math.isfinite(value) or value < 0 or (value == 0 and not allow_zero):
        bound = ">= 0" if allow_zero else "> 0"
        raise ValueError(f"{name} must be finite and {bound}, got {value!r}")
    return value


def _check_hurst(hurst: float) -> float:
    try:
        hurst = float(hurst)
    except (TypeError, ValueError):
        raise ValueError(f"hurst must be a number in (0, 1), got {hurst!r}") from None
    if not math.isfinite(hurst) or not 0.0 < hurst < 1.0:
        raise ValueError(f"hurst must be finite and in the open interval (0, 1), got {hurst!r}")
    return hurst


def _check_memory(points: int, bytes_per_point: int, what: str) -> None:
    need = points * bytes_per_point
    if need > MAX_WORKING_BYTES:
        raise ValueError(
            f"{what} needs about {need / 2**30:.1f} GiB of working memory "
            f"(cap {MAX_WORKING_BYTES / 2**30:.0f} GiB); ask for a smaller surface"
        )


def _normalise(field: np.ndarray, rms_um: float) -> np.ndarray:
    field = field - field.mean()
    rms = math.sqrt(float(np.mean(field * field)))
    if rms == 0.0 or rms_um == 0.0:
        return np.zeros_like(field)
    field *= rms_um / rms
    return field


# --------------------------------------------------------------------------- circulant (Stein)


def _stein_parameters(hurst: float) -> tuple[float, float, float, float]:
    """Return (R, beta, c0, c2) of Stein's (2002) intrinsic embedding for alpha = 2 H."""
    alpha = 2.0 * hurst
    if alpha <= 1.5:
        return 1.0, 0.0, 1.0 - alpha / 2.0, alpha / 2.0
    radius = 2.0
    beta = alpha * (2.0 - alpha) / (3.0 * radius * (radius**2 - 1.0))
    c2 = (alpha - beta * (radius - 1.0) ** 2 * (radius + 2.0)) / 2.0
    c0 = beta * (radius - 1.0) ** 3 + 1.0 - c2
    return radius, beta, c0, c2


def _stein_psi(r: np.ndarray, hurst: float) -> np.ndarray:
    """Stein's compactly supported covariance psi(r) (r in units where the grid diameter is 1)."""
    radius, beta, c0, c2 = _stein_parameters(hurst)
    out = np.zeros_like(r)
    inner = r <= 1.0
    ri = r[inner]
    out[inner] = c0 - ri ** (2.0 * hurst) + c2 * ri * ri
    if beta > 0.0:
        outer = (r > 1.0) & (r < radius)
        ro = r[outer]
        out[outer] = beta * (radius - ro) ** 3 / ro
    return out


def stein_embedding_shape(shape: int | tuple[int, int], hurst: float) -> tuple[int, int]:
    """Torus size (My, Mx) the exact method uses for a surface of `shape` and index `hurst`.

    The grid spacing is ``h = 1 / hypot(nx - 1, ny - 1)`` (grid diameter 1); each torus side is
    the smallest FFT-friendly length >= ``(n - 1) + R / h`` pixels, R = 1 for H <= 0.75 and
    R = 2 above (so the embedding grows by about 1.6x per side for H > 0.75).
    """
    ny, nx = _check_shape(shape)
    hurst = _check_hurst(hurst)
    radius = _stein_parameters(hurst)[0]
    support_px = radius * math.hypot(nx - 1, ny - 1)
    return (
        scipy.fft.next_fast_len(int(math.ceil(ny - 1 + support_px)), real=True),
        scipy.fft.next_fast_len(int(math.ceil(nx - 1 + support_px)), real=True),
    )


@functools.lru_cache(maxsize=4)
def _stein_sqrt_eigenvalues(ny: int, nx: int, hurst: float) -> np.ndarray:
    """Square roots of the torus covariance's eigenvalues (half spectrum, for irfft2)."""
    my, mx = stein_embedding_shape((ny, nx), hurst)
    h = 1.0 / math.hypot(nx - 1, ny - 1)
    # Quadrant of lags 0..M/2 per axis; the periodic sum needs the images d and M - d only,
    # because the torus is at least R long and d + M lies beyond the support.
    dy = np.arange(my // 2 + 1, dtype=np.float64)
    dx = np.arange(mx // 2 + 1, dtype=np.float64)
    quadrant = np.zeros((dy.size, dx.size))
    for iy in (dy, my - dy):
        for ix in (dx, mx - dx):
            r = h * np.hypot(iy[:, None], ix[None, :])
            quadrant += _stein_psi(r, hurst)
    # (At d = M/2 the images d and M - d are two distinct lattice images: both count.)
    # Mirror the quadrant into the full even covariance of the torus.
    rows = np.concatenate([quadrant, quadrant[(my + 1) // 2 - 1 : 0 : -1]], axis=0)
    cov = np.concatenate([rows, rows[:, (mx + 1) // 2 - 1 : 0 : -1]], axis=1)
    assert cov.shape == (my, mx)
    eig = scipy.fft.rfft2(cov, workers=_FFT_WORKERS).real
    lowest = float(eig.min())
    if lowest < -1e-9 * float(eig.max()):
        # Cannot happen for Stein's psi (positive definite on the plane); guard anyway.
        raise ArithmeticError(f"circulant embedding not non-negative (min eigenvalue {lowest:.3g})")
    root = np.sqrt(np.clip(eig, 0.0, None))
    root.setflags(write=False)
    return root


def _circulant_surface(ny: int, nx: int, hurst: float, rng: np.random.Generator) -> np.ndarray:
    my, mx = stein_embedding_shape((ny, nx), hurst)
    _check_memory(my * mx, _CIRCULANT_BYTES_PER_POINT, f"a {ny}x{nx} exact surface (torus {my}x{mx})")
    root = _stein_sqrt_eigenvalues(ny, nx, hurst)
    noise = rng.standard_normal((my, mx))
    spectrum = scipy.fft.rfft2(noise, workers=_FFT_WORKERS, overwrite_x=True)
    spectrum *= root
    field = scipy.fft.irfft2(spectrum, s=(my, mx), workers=_FFT_WORKERS, overwrite_x=True)
    field = field[:ny, :nx] - field[0, 0]
    # The random plane that turns the intrinsic covariance into the fBm variogram.
    c2 = _stein_parameters(hurst)[3]
    h = 1.0 / math.hypot(nx - 1, ny - 1)
    slope = math.sqrt(2.0 * c2) * rng.standard_normal(2)
    field += slope[0] * h * np.arange(ny)[:, None] + slope[1] * h * np.arange(nx)[None, :]
    return field


# --------------------------------------------------------------------------- periodic spectral


def _outside_square_integral(exponent: float) -> float:
    """Integral of ``|g|**-exponent`` over the plane outside the square [-1, 1]^2 (exponent > 2)."""
    # Polar, by octants: 8 * int_0^{pi/4} cos(t)^(s - 2) / (s - 2) dt.
    value, _ = scipy.integrate.quad(lambda t: math.cos(t) ** (exponent - 2.0), 0.0, math.pi / 4.0)
    return 8.0 * value / (exponent - 2.0)


def _sampled_fbm_spectrum(fy: np.ndarray, fx: np.ndarray, hurst: float, images: int = 3) -> np.ndarray:
    """Spectral density of fBm sampled on the unit grid, at frequencies (fy, fx) in cycles/px.

    ``sum_m |f + m|**-(2H + 2)`` over all lattice images m: exactly for |m_i| <= `images`, the
    rest by its integral (it converges slowly for small H). The zero frequency returns 0.
    """
    exponent = 2.0 * hurst + 2.0
    total = np.zeros(np.broadcast_shapes(fy.shape, fx.shape))
    for my in range(-images, images + 1):
        for mx in range(-images, images + 1):
            r2 = (fy + my) ** 2 + (fx + mx) ** 2
            with np.errstate(divide="ignore"):
                total += np.where(r2 > 0, r2, np.inf) ** (-exponent / 2.0)
    half_width = images + 0.5
    total += _outside_square_integral(exponent) * half_width ** (2.0 - exponent)
    total[(fy == 0) & (fx == 0)] = 0.0
    return total


def _torus_mode_variances(ny: int, nx: int, hurst: float, cells: int = 6, sub: int = 16) -> np.ndarray:
    """Variance of each rfft2 mode of the periodic surface (up to a common factor).

    Modes far from zero take the sampled spectrum at their frequency. The lowest modes
    (|k_i| <= `cells`) take its average over their frequency cell instead, because the
    spectrum is steep there; and the small-lag variogram that the zero cell would carry
    (``~ r**2 * int_cell0 S f_x**2``, significant for H near 1) goes to the fundamental modes,
    which reproduce it to O(r**4 / N**4).
    """
    fy = scipy.fft.fftfreq(ny)[:, None]
    fx = scipy.fft.rfftfreq(nx)[None, :]
    var = _sampled_fbm_spectrum(fy, fx, hurst)
    exponent = 2.0 * hurst + 2.0
    # Sub-cell quadrature nodes (midpoints), in units of the cell size.
    offs = (np.arange(sub) + 0.5) / sub - 0.5
    ky_max = min(cells, ny // 2 - 1)
    kx_max = min(cells, nx // 2 - 1)
    for ky in range(-ky_max, ky_max + 1):
        for kx in range(0, kx_max + 1):
            gy = (ky + offs[:, None]) / ny
            gx = (kx + offs[None, :]) / nx
            r2 = gy * gy + gx * gx
            # Near zero the aliased images add a smooth part: keep it from the point sample.
            smooth = var[ky % ny, kx] - (ky * ky / ny**2 + kx * kx / nx**2) ** (-exponent / 2.0) if (ky or kx) else 0.0
            core = r2 ** (-exponent / 2.0)
            if ky == 0 and kx == 0:
                # Second moments of the zero cell, handed to the fundamentals (see above).
                ixx = float(np.mean(core * gx * gx))
                iyy = float(np.mean(core * gy * gy))
                continue
            var[ky % ny, kx] = float(np.mean(core)) + smooth
    # Each fundamental pair (+-1/N) carries 2 v (1 - cos(2 pi r / N)) ~ 2 v * 2 pi^2 r^2 / N^2.
    var[0, 1] += ixx * nx * nx / 2.0
    var[1, 0] += iyy * ny * ny / 2.0
    var[-1, 0] += iyy * ny * ny / 2.0
    return var


def _periodic_spectral_surface(ny: int, nx: int, hurst: float, rng: np.random.Generator) -> np.ndarray:
    _check_memory(ny * nx, _CIRCULANT_BYTES_PER_POINT, f"a {ny}x{nx} periodic surface")
    root = np.sqrt(_torus_mode_variances(ny, nx, hurst))
    spectrum = scipy.fft.rfft2(rng.standard_normal((ny, nx)), workers=_FFT_WORKERS)
    spectrum *= root
    return scipy.fft.irfft2(spectrum, s=(ny, nx), workers=_FFT_WORKERS)


# --------------------------------------------------------------------------- midpoint displacement


def _neighbour_mean(values: list[np.ndarray]) -> np.ndarray:
    stack = np.stack(values)
    return np.nanmean(stack, axis=0)


def _midpoint_surface(size_exp: int, hurst: float, rng: np.random.Generator, periodic: bool) -> np.ndarray:
    """Random midpoint displacement (diamond-square) on a (2^k + 1)^2 grid or a 2^k torus.

    Level i (i = 1..k) halves the spacing to 2^-i (unit square). The centre ("diamond") step
    uses the paper's variance 2^(-2 i H) around the mean of the four diagonal neighbours; the
    edge ("square") step, which the paper's text omits, is taken from its source (Saupe):
    mean of the orthogonal neighbours (3 on a border), variance reduced by a further 2^-H
    because those neighbours are sqrt(2) times closer.
    """
    n = 2**size_exp
    size = n if periodic else n + 1
    grid = np.full((size, size), np.nan)
    if periodic:
        grid[0, 0] = 0.0
    else:
        grid[0, 0] = 0.0
        grid[0, n], grid[n, 0], grid[n, n] = rng.standard_normal(3)
    for level in range(1, size_exp + 1):
        step = n >> (level - 1)
        half = step // 2
        sd_diamond = 2.0 ** (-level * hurst)
        sd_square = sd_diamond * 2.0 ** (-hurst / 2.0)
        # Diamond: centres of the coarse squares from their four corners.
        if periodic:
            corners = grid[0:n:step, 0:n:step]
            right = np.roll(corners, -1, axis=1)
            below = np.roll(corners, -1, axis=0)
            diag = np.roll(below, -1, axis=1)
            mean = (corners + right + below + diag) / 4.0
        else:
            corners = grid[0 : n + 1 : step, 0 : n + 1 : step]
            mean = (corners[:-1, :-1] + corners[:-1, 1:] + corners[1:, :-1] + corners[1:, 1:]) / 4.0
        grid[half:size:step, half:size:step] = mean + sd_diamond * rng.standard_normal(mean.shape)
        # Square: edge midpoints from their orthogonal neighbours.
        if periodic:
            # Points (coarse row, half col) and (half row, coarse col); neighbours wrap.
            full = grid
            for r0, c0 in ((0, half), (half, 0)):
                rows = np.arange(r0, n, step)
                cols = np.arange(c0, n, step)
                up = full[np.ix_((rows - half) % n, cols)]
                down = full[np.ix_((rows + half) % n, cols)]
                left = full[np.ix_(rows, (cols - half) % n)]
                right = full[np.ix_(rows, (cols + half) % n)]
                mean = (up + down + left + right) / 4.0
                full[np.ix_(rows, cols)] = mean + sd_square * rng.standard_normal(mean.shape)
        else:
            padded = np.pad(grid, half, constant_values=np.nan)
            for r0, c0 in ((0, half), (half, 0)):
                rows = np.arange(r0, size, step)
                cols = np.arange(c0, size, step)
                pr, pc = rows + half, cols + half
                mean = _neighbour_mean(
                    [
                        padded[np.ix_(pr - half, pc)],
                        padded[np.ix_(pr + half, pc)],
                        padded[np.ix_(pr, pc - half)],
                        padded[np.ix_(pr, pc + half)],
                    ]
                )
                grid[np.ix_(rows, cols)] = mean + sd_square * rng.standard_normal(mean.shape)
    return grid


# --------------------------------------------------------------------------- public entry point


def brownian_surface(
    shape: int | tuple[int, int],
    hurst: float,
    *,
    pixel_size_um: float,
    rms_um: float,
    seed: int = 0,
    method: str = "circulant",
    periodic: bool = False,
) -> np.ndarray:
    """Synthesise a Brownian surface (fBm, Hurst index `hurst`, D = 3 - H) as heights in µm.

    Parameters
    ----------
    shape : int or (int, int)
        Output shape (ny, nx) in pixels (rows along v, columns along u); an int means square.
    hurst : float
        Index H in the open interval (0, 1): increments have variance ``|s|**(2H)``.
    pixel_size_um : float
        Pixel size (µm/px). fBm is self-similar and the RMS is normalised, so it does not
        change the heights; it must be finite and positive.
    rms_um : float
        Requested RMS height (µm, >= 0). The output's sample mean is exactly 0 and its sample
        RMS is exactly `rms_um` (to rounding).
    seed : int
        Seed of ``np.random.default_rng``; the same arguments give an identical array.
    method : {"circulant", "midpoint"}
        ``"circulant"``: exact (Stein 2002 intrinsic embedding; spectral synthesis on the torus
        when `periodic`). ``"midpoint"``: the paper's random midpoint displacement (biased).
    periodic : bool
        Make the surface wrap seamlessly on its own shape (see the module notes for what is
        exact then). ``"midpoint"`` supports it only for square power-of-two shapes.

    Returns
    -------
    numpy.ndarray
        float64 heights in µm, shape (ny, nx).

    Raises
    ------
    ValueError
        H outside (0, 1), non-finite or non-positive parameters, an unknown method, or a size
        whose working memory would exceed :data:`MAX_WORKING_BYTES` (4 GiB).
    """
    ny, nx = _check_shape(shape)
    hurst = _check_hurst(hurst)
    _check_positive_finite("pixel_size_um", pixel_size_um)
    rms_um = _check_positive_finite("rms_um", rms_um, allow_zero=True)
    if isinstance(seed, (bool, np.bool_)) or not isinstance(seed, numbers.Integral) or seed < 0:
        raise ValueError(f"seed must be a non-negative integer, got {seed!r}")
    rng = np.random.default_rng(int(seed))
    if method == "circulant":
        if periodic:
            field = _periodic_spectral_surface(ny, nx, hurst, rng)
        else:
            field = _circulant_surface(ny, nx, hurst, rng)
    elif method == "midpoint":
        if periodic:
            size_exp = int(round(math.log2(nx)))
            if ny != nx or 2**size_exp != nx:
                raise ValueError(
                    f"periodic midpoint surfaces need a square power-of-two shape, got {(ny, nx)}; "
                    "use method='circulant'"
                )
            _check_memory(nx * nx, _MIDPOINT_BYTES_PER_POINT, f"a {ny}x{nx} midpoint surface")
            field = _midpoint_surface(size_exp, hurst, rng, periodic=True)
        else:
            size_exp = max(1, int(math.ceil(math.log2(max(ny, nx) - 1))))
            side = 2**size_exp + 1
            _check_memory(side * side, _MIDPOINT_BYTES_PER_POINT, f"a {ny}x{nx} midpoint surface")
            field = _midpoint_surface(size_exp, hurst, rng, periodic=False)[:ny, :nx]
    else:
        raise ValueError(f"unknown method {method!r} (use 'circulant' or 'midpoint')")
    return _normalise(np.ascontiguousarray(field, dtype=np.float64), rms_um)
