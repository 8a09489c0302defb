"""Known surfaces for ground-truth tests and benchmarks (heights in µm on a pixel grid).

Every generator returns a float64 array ``height_um`` of the requested ``shape`` (rows, columns),
sampled at pixel centres ``x = (j + 0.5) * pixel_size_um``, ``y = (i + 0.5) * pixel_size_um``
(x along columns = +u, y along rows = +v). The woven, bump and Brownian surfaces are periodic
over the image when stated, so that they can stand for a cleaned tile.
"""
from __future__ import annotations

import numpy as np

__all__ = ["sphere_cap", "woven_like", "random_bumps", "brownian_surface", "rms_slope"]


def _check_grid(shape: tuple[int, int], pixel_size_um: float) -> tuple[int, int]:
    if len(shape) != 2 or min(shape) < 2:
        raise ValueError(f"shape must be (rows, columns) with at least 2 of each, got {shape!r}")
    if not np.isfinite(pixel_size_um) or pixel_size_um <= 0:
        raise ValueError(f"pixel_size_um must be finite and positive, got {pixel_size_um!r}")
    return int(shape[0]), int(shape[1])


def rms_slope(height_um: np.ndarray, pixel_size_um: float) -> float:
    """RMS of the gradient magnitude ``sqrt(mean(hx**2 + hy**2))`` (dimensionless, µm/µm).

    Central differences (``np.gradient``), as :func:`haptex_compile.shading.render_lambertian`.
    """
    gy, gx = np.gradient(np.asarray(height_um, dtype=float), pixel_size_um)
    return float(np.sqrt(np.mean(gx**2 + gy**2)))


def sphere_cap(
    shape: tuple[int, int],
    pixel_size_um: float,
    radius_um: float | None = None,
    rim_angle_deg: float = 45.0,
    rim_round_um: float | None = None,
) -> np.ndarray:
    """A spherical cap standing on a flat base, centred in the image, its rim rounded.

    The rim is rounded by a soft maximum ``c log(exp(a/c) + exp(b/c))`` of the base and the
    cap continued as its tangent cone (``c`` = `rim_round_um`), like the creases of
    :func:`woven_like`. Why: a sharp rim is a kink, whose slope jumps in one pixel; its
    sampled shading is a step that no pixel grid resolves (a camera integrates it over the
    pixel), and it is what made the cap hard for shape from shading at low slants (measured
    on 128 px tiles, default solver, light given, slants 15/30/45/60°: normalised height
    errors 0.15/0.17/0.08/0.18 with a sharp rim, 0.02/0.03/0.02/0.05 rounded over 2 px; see
    ``bench/bench_shading.py``). Pass ``rim_round_um=0`` for the sharp rim.

    Parameters
    ----------
    shape : (int, int)
        Image shape (rows, columns).
    pixel_size_um : float
        Pixel size in µm.
    radius_um : float, optional
        Radius of the cap's footprint (its rim) in µm; default 0.4 x the smaller image side.
    rim_angle_deg : float
        Angle of the surface at the rim (0 < angle < 90): the largest slope is ``tan(angle)``.
    rim_round_um : float, optional
        Rounding scale of the rim in µm (about the width of the rounded band); default
        0.04 x `radius_um` (2 px at the default radius on a 128 px image); 0 = sharp rim.

    Returns
    -------
    ndarray
        Height in µm; 0 on the base away from the rim (within ``c exp(-d tan(a) / c)`` at
        distance ``d`` outside it).
    """
    rows, cols = _check_grid(shape, pixel_size_um)
    if not 0 < rim_angle_deg < 90:
        raise ValueError(f"rim_angle_deg must be in (0, 90), got {rim_angle_deg!r}")
    if radius_um is None:
        radius_um = 0.4 * min(rows, cols) * pixel_size_um
    y = (np.arange(rows) + 0.5 - rows / 2) * pixel_size_um
    x = (np.arange(cols) + 0.5 - cols / 2) * pixel_size_um
    r2 = x[None, :] ** 2 + y[:, None] ** 2
    # A sphere of radius R cut at angle a has footprint radius R sin(a) and height R (1 - cos a).
    a = np.deg2rad(rim_angle_deg)
    sphere_r = radius_um / np.sin(a)
    h = np.sqrt(np.maximum(sphere_r**2 - r2, 0.0)) - sphere_r * np.cos(a)
    c = 0.04 * radius_um if rim_round_um is None else float(rim_round_um)
    if not np.isfinite(c) or c < 0:
        raise ValueError(f"rim_round_um must be finite and >= 0, got {rim_round_um!r}")
    if c == 0:
        return np.maximum(h, 0.0)
    # Outside the rim, continue the cap as its tangent cone (slope tan a) so that the soft
    # maximum with the base (height 0) only rounds the kink: it adds c log 2 at the rim and
    # almost nothing a few c away from it.
    r = np.sqrt(r2)
    cap = np.where(r < radius_um, h, -(r - radius_um) * np.tan(a))
    return c * np.logaddexp(cap / c, 0.0)


def woven_like(
    shape: tuple[int, int],
    pixel_size_um: float,
    thread_spacing_um: float | None = None,
    yarn_width: float = 0.9,
    crimp_um: float | None = None,
    yarn_height_um: float | None = None,
    crease_um: float | None = None,
) -> np.ndarray:
    """A plain weave: warp yarns along v, weft yarns along u, each passing over and under.

    The height is a smooth upper envelope of both yarn layers: yarn cross-sections are
    ``cos²`` arches of width ``yarn_width * thread_spacing_um`` and height `yarn_height_um`, and
    each yarn's axis undulates by ``± crimp_um`` with period twice the thread spacing, in
    opposite phase for warp and weft, so that the crossing yarns alternate on top. Where the
    layers meet, the envelope has creases rounded over about `crease_um` (a soft maximum
    ``c log(exp(a/c) + exp(b/c))``): fibrous yarns have no sharp edges. The tile is
    ``2 * thread_spacing_um`` square: the surface is periodic over the image when each image
    side is a multiple of it.

    Parameters
    ----------
    shape : (int, int)
        Image shape (rows, columns).
    pixel_size_um : float
        Pixel size in µm.
    thread_spacing_um : float, optional
        Distance between neighbouring yarns; default: 4 tiles across the smaller side.
    yarn_width : float
        Yarn width as a fraction of the spacing, in (0, 1].
    crimp_um, yarn_height_um, crease_um : float, optional
        Crimp amplitude, arch height and crease rounding; defaults 0.1, 0.25 and 0.03 x the
        spacing (RMS slope about 0.5, steepest about 1.2).

    Returns
    -------
    ndarray
        Height in µm, minimum 0.
    """
    rows, cols = _check_grid(shape, pixel_size_um)
    if not 0 < yarn_width <= 1:
        raise ValueError(f"yarn_width must be in (0, 1], got {yarn_width!r}")
    d = thread_spacing_um or min(rows, cols) * pixel_size_um / 8.0
    crimp = 0.1 * d if crimp_um is None else crimp_um
    arch = 0.25 * d if yarn_height_um is None else yarn_height_um
    crease = 0.03 * d if crease_um is None else crease_um
    if crease <= 0:
        raise ValueError(f"crease_um must be positive, got {crease!r}")
    x = (np.arange(cols) + 0.5) * pixel_size_um
    y = (np.arange(rows) + 0.5) * pixel_size_um

    def layer(along: np.ndarray, across: np.ndarray, sign: float) -> np.ndarray:
        # Yarn index and offset from its axis, across the yarns.
        k = np.floor(across / d)
        off = (across - (k + 0.5) * d) / (0.5 * yarn_width * d)
        section = np.where(np.abs(off) < 1, np.cos(0.5 * np.pi * np.clip(off, -1, 1)) ** 2, 0.0)
        axis = sign * crimp * np.sin(np.pi * along[:, None] / d + np.pi * k[None, :])
        return axis + arch * section[None, :]

    warp = layer(y, x, +1.0)  # rows follow y, columns x
    weft = layer(x, y, -1.0).T
    h = np.logaddexp(warp / crease, weft / crease) * crease
    return h - h.min()


def _spectral_filter(
    shape: tuple[int, int], pixel_size_um: float, amplitude_of_k, seed: int
) -> np.ndarray:
    """Periodic Gaussian random field with amplitude spectrum ``amplitude_of_k(|k|)``."""
    rows, cols = shape
    rng = np.random.default_rng(seed)
    noise = np.fft.rfft2(rng.standard_normal((rows, cols)))
    ky = np.fft.fftfreq(rows, d=pixel_size_um)[:, None]
    kx = np.fft.rfftfreq(cols, d=pixel_size_um)[None, :]
    k = np.hypot(kx, ky)  # cycles per µm
    amp = amplitude_of_k(k)
    amp[0, 0] = 0.0  # mean 0
    return np.fft.irfft2(noise * amp, s=(rows, cols))


def random_bumps(
    shape: tuple[int, int],
    pixel_size_um: float,
    correlation_um: float = 100.0,
    slope_rms: float = 0.2,
    seed: int = 0,
) -> np.ndarray:
    """Smooth random bumps: periodic Gaussian-filtered white noise.

    Parameters
    ----------
    shape : (int, int)
        Image shape (rows, columns).
    pixel_size_um : float
        Pixel size in µm.
    correlation_um : float
        Standard deviation of the Gaussian filter in µm (bump radius ~ 2 x this).
    slope_rms : float
        RMS gradient magnitude after scaling (see :func:`rms_slope`).
    seed : int
        Seed of ``np.random.default_rng``.

    Returns
    -------
    ndarray
        Height in µm, mean 0, periodic over the image.
    """
    shape = _check_grid(shape, pixel_size_um)
    s = correlation_um
    h = _spectral_filter(shape, pixel_size_um, lambda k: np.exp(-2 * (np.pi * s * k) ** 2), seed)
    return h * (slope_rms / rms_slope(h, pixel_size_um))


def brownian_surface(
    shape: tuple[int, int],
    pixel_size_um: float,
    hurst: float = 0.7,
    slope_rms: float = 0.3,
    seed: int = 0,
    smallest_wavelength_px: float = 2.0,
) -> np.ndarray:
    """Brownian-like (fractional Brownian) surface by FFT power-law filtering.

    White noise is filtered by ``|k|**-(hurst + 1)`` (power spectrum ``|k|**-(2 hurst + 2)``,
    fractal dimension ``3 - hurst``) and cut off smoothly below `smallest_wavelength_px` pixels.

    Parameters
    ----------
    shape : (int, int)
        Image shape (rows, columns).
    pixel_size_um : float
        Pixel size in µm.
    hurst : float
        Hurst index H in (0, 1).
    slope_rms : float
        RMS gradient magnitude after scaling (see :func:`rms_slope`).
    seed : int
        Seed of ``np.random.default_rng``.
    smallest_wavelength_px : float
        Wavelength (pixels) where a Gaussian roll-off starts; 2 = none before Nyquist.

    Returns
    -------
    ndarray
        Height in µm, mean 0, periodic over the image.
    """
    shape = _check_grid(shape, pixel_size_um)
    if not 0 < hurst < 1:
        raise ValueError(f"hurst must be in (0, 1), got {hurst!r}")
    k_cut = 1.0 / (smallest_wavelength_px * pixel_size_um)

    def amp(k: np.ndarray) -> np.ndarray:
        with np.errstate(divide="ignore"):
            a = np.where(k > 0, k, np.inf) ** -(hurst + 1.0)
        if smallest_wavelength_px > 2.0:
            a = a * np.exp(-0.5 * (k / k_cut) ** 2)
        return a

    h = _spectral_filter(shape, pixel_size_um, amp, seed)
    return h * (slope_rms / rms_slope(h, pixel_size_um))
