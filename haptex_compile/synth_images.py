"""Synthetic test images: weave-like lattices with known t1, t2, their degradations, and
non-periodic random surfaces.

Used by the lattice tests and benchmark, so that every image comes with its ground truth.
A weave image is rendered *exactly* from a band-limited Fourier series over the reciprocal
lattice, so it is periodic under the given (sub-pixel) t1, t2 to machine precision and free of
aliasing; the degradations (JPEG, uneven light, stains, slubs, noise, rotation) are applied on top.
Pixel (row y, column x) has its centre at (x, y); vectors are (x, y) in pixels.
"""
from __future__ import annotations

import math

import cv2
import numpy as np

__all__ = [
    "basis_from_geometry",
    "weave_image",
    "lattice_relief",
    "brownian_surface",
    "rotate_image",
    "stretch_from_centre",
    "add_uneven_light",
    "add_stain",
    "add_slub",
    "add_noise",
    "jpeg_roundtrip",
    "make_hard_case",
    "PERIODIC_CASES",
    "NON_PERIODIC_CASES",
]

_TILE_GRID = 64        # tile sampled on 64 x 64 fractional positions before Fourier analysis
_MAX_HARMONIC = 12     # bumps of width >= 0.05 cell have < 1e-4 of their energy beyond this
_NYQUIST_KEEP = 0.45   # keep harmonics below 0.45 cycles/px per axis (Nyquist is 0.5)


def basis_from_geometry(period1_px: float, period2_px: float, angle_deg: float,
                        rotation_deg: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Two lattice vectors (x, y) in px from their lengths, the angle between them and a rotation.

    t1 points along `rotation_deg` (counter-clockwise from +x towards +y, as drawn in image
    coordinates), t2 along `rotation_deg + angle_deg`.
    """
    a1 = math.radians(rotation_deg)
    a2 = math.radians(rotation_deg + angle_deg)
    t1 = period1_px * np.array([math.cos(a1), math.sin(a1)])
    t2 = period2_px * np.array([math.cos(a2), math.sin(a2)])
    return t1, t2


def _periodic_bump(f1: np.ndarray, f2: np.ndarray, c1: float, c2: float,
                   s_along1: float, s_along2: float) -> np.ndarray:
    """Gaussian bump centred at (c1, c2) in fractional coordinates, wrapped on the unit torus."""
    d1 = (f1 - c1 + 0.5) % 1.0 - 0.5
    d2 = (f2 - c2 + 0.5) % 1.0 - 0.5
    return np.exp(-0.5 * ((d1 / s_along1) ** 2 + (d2 / s_along2) ** 2))


def _tile_function(kind: str, rng: np.random.Generator) -> np.ndarray:
    """Weave-like cell on a _TILE_GRID^2 grid of fractional coordinates [f2, f1], values ~[0, 1].

    Every kind breaks the sub-cell symmetries (floats differ in brightness or orientation), so the
    given basis is the *minimal* lattice of the pattern, as the tests assume.
    """
    g = (np.arange(_TILE_GRID) + 0.5) / _TILE_GRID
    f1, f2 = np.meshgrid(g, g)  # f1 varies along columns, f2 along rows
    tile = np.full_like(f1, 0.15)
    if kind == "plain":
        # warp float (along t2) and weft float (along t1) with different brightness
        tile += 0.85 * _periodic_bump(f1, f2, 0.25, 0.25, 0.09, 0.2)
        tile += 0.55 * _periodic_bump(f1, f2, 0.75, 0.75, 0.2, 0.09)
    elif kind == "twill":
        # three floats stepping diagonally, each a little dimmer: a 3/1-like twill cell
        for k, level in enumerate((0.9, 0.7, 0.5)):
            c = (k + 0.5) / 3.0
            tile += level * _periodic_bump(f1, f2, c, c, 0.07, 0.16)
    elif kind == "random":
        for _ in range(int(rng.integers(3, 6))):
            c1, c2 = rng.random(2)
            s1, s2 = rng.uniform(0.06, 0.2, 2)
            tile += rng.uniform(0.3, 0.9) * _periodic_bump(f1, f2, c1, c2, s1, s2)
    else:
        raise ValueError(f"unknown weave kind {kind!r} (use plain, twill or random)")
    # a little random low-order structure so that no two seeds look alike
    for m in range(-2, 3):
        for n in range(0, 3):
            if n == 0 and m <= 0:
                continue
            amp = 0.04 * rng.standard_normal()
            phase = rng.uniform(0, 2 * np.pi)
            tile += amp * np.cos(2 * np.pi * (m * f1 + n * f2) + phase)
    return tile


def weave_image(shape: tuple[int, int], t1_px, t2_px, *, kind: str = "plain",
                origin_px=(0.0, 0.0), seed: int = 0) -> np.ndarray:
    """Render a weave-like image that is exactly periodic under t1, t2 (sub-pixel vectors allowed).

    Parameters
    ----------
    shape : (int, int)
        (rows, columns) of the image.
    t1_px, t2_px : array_like, shape (2,)
        Lattice vectors (x, y) in pixels; must be non-parallel.
    kind : {"plain", "twill", "random"}
        Cell content.
    origin_px : (float, float)
        (x, y) of the cell origin.
    seed : int
        Seed of the random parts of the cell.

    Returns
    -------
    numpy.ndarray
        float64 image scaled to [0, 1]; band-limited below 0.45 cycles/px, so sampling is exact.
    """
    rng = np.random.default_rng(seed)
    basis = np.column_stack([np.asarray(t1_px, float), np.asarray(t2_px, float)])
    if abs(np.linalg.det(basis)) < 1e-6:
        raise ValueError("t1 and t2 are parallel: they do not span a lattice")
    tile = _tile_function(kind, rng)
    coef = np.fft.fft2(tile) / tile.size  # coef[n, m]: harmonic exp(2 pi i (m f1 + n f2))
    freqs = np.fft.fftfreq(_TILE_GRID, 1.0 / _TILE_GRID).round().astype(int)
    # reciprocal basis: f = B^-1 p, so harmonic (m, n) has spatial frequency (m, n) @ B^-1
    binv = np.linalg.inv(basis)
    rows, cols = shape
    y = np.arange(rows, dtype=float) - origin_px[1]
    x = np.arange(cols, dtype=float) - origin_px[0]
    terms_m, terms_n, terms_c = [], [], []
    peak = np.abs(coef).max()
    for n in freqs:
        for m in freqs:
            if abs(m) > _MAX_HARMONIC or abs(n) > _MAX_HARMONIC:
                continue
            if n < 0 or (n == 0 and m < 0):
                continue  # take the half plane; its conjugate is added by the real part below
            c = coef[n % _TILE_GRID, m % _TILE_GRID]
            k = np.array([m, n], float) @ binv  # cycles per px along (x, y)
            if np.abs(k).max() > _NYQUIST_KEEP or abs(c) < 1e-5 * peak:
                continue
            weight = 1.0 if (m == 0 and n == 0) else 2.0
            terms_m.append(m)
            terms_n.append(n)
            terms_c.append(weight * c)
    mn = np.column_stack([terms_m, terms_n]).astype(float)
    k = mn @ binv  # (n_terms, 2): kx, ky
    # separable evaluation: exp(2 pi i (kx x + ky y)) = column(y) * row(x)
    ey = np.exp(2j * np.pi * np.outer(y, k[:, 1])) * np.asarray(terms_c)[None, :]
    ex = np.exp(2j * np.pi * np.outer(x, k[:, 0]))
    image = (ey @ ex.T).real
    lo, hi = image.min(), image.max()
    return (image - lo) / (hi - lo)


def lattice_relief(shape: tuple[int, int], t1_px, t2_px, amplitude_um: float = 12.0) -> np.ndarray:
    """A smooth, asymmetric relief (µm) exactly periodic under t1, t2: ground truth for photos.

    One cell holds ``0.6 cos(2 pi u) cos(2 pi v) + 0.3 cos(4 pi u) + 0.25 cos(4 pi v)
    + 0.2 sin(2 pi (u + v))`` (times `amplitude_um`) in fractional lattice coordinates (u, v);
    the sine makes it asymmetric, so bumps and dents differ. With 12 µm over cells of about
    18 px of 20 µm the RMS slope is about 0.2.
    """
    from haptex_compile.tiles import paint_tile

    n = _TILE_GRID
    u, v = np.meshgrid(np.arange(n) / n, np.arange(n) / n)
    cell = (0.6 * np.cos(2 * np.pi * u) * np.cos(2 * np.pi * v) + 0.3 * np.cos(4 * np.pi * u)
            + 0.25 * np.cos(4 * np.pi * v) + 0.2 * np.sin(2 * np.pi * (u + v)))
    basis = np.column_stack([np.asarray(t1_px, float), np.asarray(t2_px, float)])
    return amplitude_um * paint_tile(cell, basis, shape).astype(np.float64)


def brownian_surface(shape: tuple[int, int], hurst: float, *, seed: int = 0) -> np.ndarray:
    """Non-periodic Brownian surface (exact synthesis of :mod:`haptex_compile.fractal`) scaled to [0, 1]."""
    from haptex_compile.fractal import brownian_surface as exact_brownian

    field = exact_brownian(tuple(shape), hurst, pixel_size_um=1.0, rms_um=1.0, seed=seed)
    lo, hi = field.min(), field.max()
    return (field - lo) / (hi - lo)


def rotate_image(image: np.ndarray, angle_deg: float, out_shape: tuple[int, int]
                 ) -> tuple[np.ndarray, np.ndarray]:
    """Rotate about the image centre (cubic interpolation) and crop the centre to `out_shape`.

    Returns the rotated crop and the 2x2 matrix A that maps a lattice vector t of the input to
    the output's (A @ t). Positive angles turn +x towards -y as drawn (OpenCV convention).
    """
    rows, cols = image.shape
    centre = ((cols - 1) / 2.0, (rows - 1) / 2.0)
    mat = cv2.getRotationMatrix2D(centre, angle_deg, 1.0)
    # shift so that the output crop is centred on the same point
    mat[0, 2] -= centre[0] - (out_shape[1] - 1) / 2.0
    mat[1, 2] -= centre[1] - (out_shape[0] - 1) / 2.0
    out = cv2.warpAffine(image.astype(np.float64), mat, (out_shape[1], out_shape[0]),
                         flags=cv2.INTER_CUBIC, borderMode=cv2.BORDER_REFLECT)
    return out, mat[:, :2].copy()


def stretch_from_centre(image: np.ndarray, drift_px: float) -> np.ndarray:
    """A square image stretched quadratically from its centre (cubic interpolation, float32):
    output pixel x reads the input at ``x + k (x - c) |x - c|`` in each axis, ``drift_px`` of
    displacement at the edges. A weave that drifts across a photo, as real ones do (the local
    period grows by ``2 drift / (n / 2)`` towards the edges)."""
    n = image.shape[0]
    y, x = np.mgrid[0:n, 0:n].astype(np.float32)
    c, k = n / 2, drift_px / (n / 2) ** 2
    mx, my = x + k * (x - c) * np.abs(x - c), y + k * (y - c) * np.abs(y - c)
    return cv2.remap(np.asarray(image, np.float32), mx, my, cv2.INTER_CUBIC, borderMode=cv2.BORDER_REFLECT)


def add_uneven_light(image: np.ndarray, strength: float = 0.7) -> np.ndarray:
    """Multiply by a strong linear + quadratic illumination and add a matching offset.

    The illumination ranges over a factor of about 1 / (1 - strength) across the image.
    """
    rows, cols = image.shape
    y, x = np.mgrid[0:rows, 0:cols]
    u = x / max(cols - 1, 1) - 0.3
    v = y / max(rows - 1, 1) - 0.6
    light = 0.6 * u + 0.4 * v + 0.9 * u * u + 0.5 * u * v
    light = (light - light.min()) / (light.max() - light.min())
    gain = 1.0 - strength * light
    return image * gain + 0.3 * strength * light


def add_stain(image: np.ndarray, area_fraction: float = 0.05, *, seed: int = 0) -> np.ndarray:
    """Dark soft-edged elliptic stain covering `area_fraction` of the image, at a random place."""
    rng = np.random.default_rng(seed)
    rows, cols = image.shape
    area = area_fraction * rows * cols
    aspect = rng.uniform(1.0, 2.0)
    a = math.sqrt(area * aspect / math.pi)
    b = area / (math.pi * a)
    cy, cx = rng.uniform(0.25, 0.75) * rows, rng.uniform(0.25, 0.75) * cols
    theta = rng.uniform(0, math.pi)
    y, x = np.mgrid[0:rows, 0:cols].astype(float)
    xr = (x - cx) * math.cos(theta) + (y - cy) * math.sin(theta)
    yr = -(x - cx) * math.sin(theta) + (y - cy) * math.cos(theta)
    r = np.hypot(xr / a, yr / b)
    mask = np.clip((1.15 - r) / 0.3, 0.0, 1.0)  # soft edge around r = 1
    level = image.min() + 0.1 * np.ptp(image)
    return image * (1 - 0.85 * mask) + 0.85 * mask * level


def add_slub(image: np.ndarray, direction_px, area_fraction: float = 0.05, *,
             seed: int = 0) -> np.ndarray:
    """A thick bright thread (slub) along `direction_px` covering `area_fraction` of the image."""
    rng = np.random.default_rng(seed)
    rows, cols = image.shape
    d = np.asarray(direction_px, float)
    d = d / np.linalg.norm(d)
    length = 0.6 * math.hypot(rows, cols) * 0.7
    width = area_fraction * rows * cols / length
    cy, cx = rng.uniform(0.35, 0.65) * rows, rng.uniform(0.35, 0.65) * cols
    y, x = np.mgrid[0:rows, 0:cols].astype(float)
    along = (x - cx) * d[0] + (y - cy) * d[1]
    across = -(x - cx) * d[1] + (y - cy) * d[0]
    profile = np.clip(1.0 - (2 * across / width) ** 2, 0, 1) ** 0.5
    profile *= np.clip((length / 2 - np.abs(along)) / (0.1 * length), 0, 1)
    level = image.max() + 0.2 * np.ptp(image)
    return image * (1 - profile) + profile * level


def add_noise(image: np.ndarray, fraction_of_contrast: float = 0.2, *, seed: int = 0
              ) -> np.ndarray:
    """Add white Gaussian noise with std = fraction x (max - min) of the image."""
    rng = np.random.default_rng(seed)
    sigma = fraction_of_contrast * float(np.ptp(image))
    return image + sigma * rng.standard_normal(image.shape)


def jpeg_roundtrip(image: np.ndarray, quality: int = 50) -> np.ndarray:
    """Encode as 8-bit JPEG at `quality` and decode (values rescaled to 0..255 first)."""
    lo, hi = float(image.min()), float(image.max())
    u8 = np.clip(np.round((image - lo) / (hi - lo) * 255.0), 0, 255).astype(np.uint8)
    ok, buf = cv2.imencode(".jpg", u8, [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
    if not ok:
        raise RuntimeError("JPEG encoding failed")
    return cv2.imdecode(buf, cv2.IMREAD_GRAYSCALE).astype(np.float64)


# ---- the hard-case sweep shared by the tests and the benchmark -------------------------------

PERIODIC_CASES = ("small period", "large period", "oblique", "rotated", "jpeg q50",
                  "uneven light", "stain 5%", "slub 5%", "noise 20%", "2.5 periods")
NON_PERIODIC_CASES = ("gravel", "grass", "brownian")


def _random_basis(rng: np.random.Generator, lo: float, hi: float, angle=(60.0, 120.0)
                  ) -> tuple[np.ndarray, np.ndarray]:
    p1 = rng.uniform(lo, hi)
    p2 = float(np.clip(p1 * rng.uniform(0.8, 1.3), lo, hi))
    return basis_from_geometry(p1, p2, rng.uniform(*angle), rng.uniform(0.0, 180.0))


def make_hard_case(name: str, seed: int, size: int = 256) -> dict:
    """One generated test image of a named hard case, with its ground truth.

    Returns a dict with ``image`` (float array), ``periodic`` (bool) and, when periodic,
    ``t1_px``/``t2_px`` (a basis of the true lattice; compare lattices, not vectors).
    Periods are drawn at random (seeded) within the case's range; `size` is the image side.
    """
    rng = np.random.default_rng([seed, sum(map(ord, name))])
    kind = ("plain", "twill", "random")[seed % 3]
    shape = (size, size)
    if name in NON_PERIODIC_CASES:
        if name == "brownian":
            return {"image": brownian_surface(shape, rng.uniform(0.15, 0.9), seed=seed),
                    "periodic": False}
        from skimage import data  # only the non-periodic real photos need scikit-image

        full = getattr(data, name)().astype(np.float64)
        if seed == 0 or size >= min(full.shape):
            return {"image": full, "periodic": False}
        y0 = int(rng.integers(0, full.shape[0] - size + 1))
        x0 = int(rng.integers(0, full.shape[1] - size + 1))
        crop = full[y0:y0 + size, x0:x0 + size]
        return {"image": np.rot90(crop, int(rng.integers(0, 4))).copy(), "periodic": False}
    if name == "small period":
        t1, t2 = _random_basis(rng, 3.0, 8.0)
    elif name == "large period":
        t1, t2 = _random_basis(rng, size / 8.0, size / 4.0)
    elif name == "oblique":
        # the *given* basis is oblique (30-45 deg); its reduced form may be less so
        t1, t2 = _random_basis(rng, 6.0, 30.0, angle=(30.0, 45.0))
    elif name == "2.5 periods":
        t1, t2 = _random_basis(rng, 30.0, 80.0)
        # the image spans 2.5 of the longer reduced period along each axis
        from haptex_compile.lattice import reduce_basis

        a, b = reduce_basis(t1, t2)
        side = int(math.ceil(2.5 * max(np.linalg.norm(a), np.linalg.norm(b))))
        shape = (side, side)
    else:
        t1, t2 = _random_basis(rng, 6.0, 30.0)
    origin = tuple(rng.uniform(0, 50, 2))
    if name == "rotated":
        angle = rng.uniform(5.0, 40.0) * rng.choice([-1.0, 1.0])
        t1a, t2a = basis_from_geometry(rng.uniform(8, 24), rng.uniform(8, 24), 90.0, 0.0)
        big = int(math.ceil(size * 1.5))
        src = weave_image((big, big), t1a, t2a, kind=kind, origin_px=origin, seed=seed)
        image, mat = rotate_image(src, angle, shape)
        t1, t2 = mat @ t1a, mat @ t2a
        return {"image": image, "periodic": True, "t1_px": t1, "t2_px": t2}
    image = weave_image(shape, t1, t2, kind=kind, origin_px=origin, seed=seed)
    if name == "jpeg q50":
        image = jpeg_roundtrip(image, 50)
    elif name == "uneven light":
        image = add_uneven_light(image, 0.75)
    elif name == "stain 5%":
        image = add_stain(image, 0.05, seed=seed)
    elif name == "slub 5%":
        image = add_slub(image, t1 if seed % 2 else t2, 0.05, seed=seed)
    elif name == "noise 20%":
        image = add_noise(image, 0.2, seed=seed)
    return {"image": image, "periodic": True, "t1_px": t1, "t2_px": t2}
