"""Heights from shading: Lambertian rendering, light estimation, solvers and relief scaling.

Conventions (DOMAIN.md): image rows are +v (+y, down), columns +u (+x, right); the height axis
points towards the camera. A light of slant ``s`` and tilt ``t`` is the unit vector
``L = (sin s cos t, sin s sin t, cos s)`` in (x, y, z); a surface of slopes
``p = dh/dx, q = dh/dy`` has normal ``(-p, -q, 1) / sqrt(1 + p**2 + q**2)`` and the Lambertian
image is ``albedo * max(0, n . L)`` (attached shadows only, no cast shadows).

Heights from shading have no absolute scale (the slopes scale with the assumed slant and
albedo); :func:`scale_relief` fixes it from a stated relief.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np
import scipy.fft as sfft
from scipy import ndimage

__all__ = [
    "Light",
    "SfsResult",
    "render_lambertian",
    "estimate_light",
    "tsai_shah",
    "shape_from_shading",
    "scale_relief",
    "normalised_height_error",
    "valid_pixels",
    "METHODS",
]

#: Pixels at or above this (saturated) or at or below DARK (black) carry no slope information.
SATURATED = 0.99
DARK = 0.01
METHODS = ("default", "variational", "tsai-shah", "linear")
# Below this slant the linear term of the reflectance (the only one that fixes the sign of the
# slopes) is too weak: shape from shading is ill-posed and we fall back (see shape_from_shading).
MIN_SLANT_DEG = 5.0
MAX_SLANT_DEG = 89.0


@dataclass(frozen=True)
class Light:
    """A distant point light.

    Attributes
    ----------
    slant_deg : float
        Angle from the camera (view) axis in degrees; 0 = light straight above.
    tilt_deg : float
        Azimuth in degrees, counter-clockwise from +u towards +v: the light lies towards
        ``(cos tilt, sin tilt)`` in image (x, y) (x right, y down).
    slant_sd_deg, tilt_sd_deg : float
        Standard uncertainties in degrees (0 when given by the user).
    """

    slant_deg: float
    tilt_deg: float
    slant_sd_deg: float = 0.0
    tilt_sd_deg: float = 0.0

    def __post_init__(self) -> None:
        for name in ("slant_deg", "tilt_deg", "slant_sd_deg", "tilt_sd_deg"):
            if not math.isfinite(getattr(self, name)):
                raise ValueError(f"Light.{name} must be finite, got {getattr(self, name)!r}")
        if not 0.0 <= self.slant_deg <= 90.0:
            raise ValueError(f"Light.slant_deg must be in [0, 90], got {self.slant_deg!r}")
        if self.slant_sd_deg < 0 or self.tilt_sd_deg < 0:
            raise ValueError("Light uncertainties must be >= 0")

    @property
    def vector(self) -> np.ndarray:
        """Unit vector (lx, ly, lz) in image (x, y) and towards the camera (z)."""
        s, t = np.deg2rad(self.slant_deg), np.deg2rad(self.tilt_deg)
        return np.array([np.sin(s) * np.cos(t), np.sin(s) * np.sin(t), np.cos(s)])


@dataclass(frozen=True)
class SfsResult:
    """Output of :func:`shape_from_shading`.

    Attributes
    ----------
    height : ndarray
        Relative heights in µm as implied by the light and albedo used (no physical scale:
        use :func:`scale_relief`), mean 0.
    light : Light
        The light used (given, or estimated with its uncertainty).
    albedo : float
        The albedo used (estimated).
    method : str
        The solver that produced `height` (after any fallback).
    warnings : tuple of str
        Ill-posed inputs and fallbacks, one sentence each.
    """

    height: np.ndarray
    light: Light
    albedo: float
    method: str
    warnings: tuple[str, ...]


# --------------------------------------------------------------------------------------------
# Input handling


def _as_image(image) -> tuple[np.ndarray, list[str]]:
    """Grey image as float64 in [0, 1] (NaN kept: they are masked later)."""
    warnings: list[str] = []
    a = np.asarray(image)
    if a.ndim != 2:
        raise ValueError(f"image must be a 2-D grey array, got shape {a.shape}")
    if a.shape[0] < 4 or a.shape[1] < 4:
        raise ValueError(f"image must be at least 4 x 4 pixels, got {a.shape}")
    if np.issubdtype(a.dtype, np.integer):
        img = a.astype(np.float64) / float(np.iinfo(a.dtype).max)
    elif np.issubdtype(a.dtype, np.floating) or a.dtype == bool:
        img = a.astype(np.float64)
    else:
        raise ValueError(f"image must be numeric, got dtype {a.dtype}")
    finite = np.isfinite(img)
    if not finite.all():
        warnings.append(f"{int((~finite).sum())} non-finite pixels ignored")
    if finite.any():
        top = float(np.max(img[finite]))
        low = float(np.min(img[finite]))
        if top > 1.0 + 1e-6 or low < -1e-6:
            # Float images outside [0, 1]: map the range to [0, 1] rather than clip the data.
            span = top - min(low, 0.0)
            img = (img - min(low, 0.0)) / (span if span > 0 else 1.0)
            warnings.append("image values outside [0, 1] were rescaled to [0, 1]")
    return img, warnings


def valid_pixels(image: np.ndarray, mask=None) -> np.ndarray:
    """Pixels that carry slope information: finite, not saturated (>= 0.99), not black (<= 0.01).

    Parameters
    ----------
    image : ndarray
        Grey image in [0, 1].
    mask : ndarray of bool, optional
        Extra pixels to use (True) or ignore (False).

    Returns
    -------
    ndarray of bool
    """
    img = np.asarray(image, dtype=float)
    with np.errstate(invalid="ignore"):
        ok = np.isfinite(img) & (img > DARK) & (img < SATURATED)
    if mask is not None:
        m = np.asarray(mask, dtype=bool)
        if m.shape != img.shape:
            raise ValueError(f"mask shape {m.shape} differs from image shape {img.shape}")
        ok &= m
    return ok


# --------------------------------------------------------------------------------------------
# Rendering


def render_lambertian(
    height_um: np.ndarray,
    pixel_size_um: float,
    light: Light,
    albedo: float = 1.0,
    *,
    periodic: bool = False,
) -> np.ndarray:
    """Lambertian image of a height map under a distant light (orthographic camera).

    Parameters
    ----------
    height_um : ndarray
        Height map in µm (rows = +v, columns = +u).
    pixel_size_um : float
        Pixel size in µm.
    light : Light
        The light.
    albedo : float
        Albedo in [0, 1].
    periodic : bool
        The height map is a tile: central differences wrap around at the edges (otherwise
        ``np.gradient``, one-sided at the edges).

    Returns
    -------
    ndarray
        Image ``albedo * max(0, n . L)`` in [0, 1]; slopes by central differences;
        attached shadows are 0, cast shadows are not modelled.
    """
    h = np.asarray(height_um, dtype=float)
    if h.ndim != 2:
        raise ValueError(f"height_um must be 2-D, got shape {h.shape}")
    if not np.isfinite(pixel_size_um) or pixel_size_um <= 0:
        raise ValueError(f"pixel_size_um must be finite and positive, got {pixel_size_um!r}")
    if not 0.0 <= albedo <= 1.0:
        raise ValueError(f"albedo must be in [0, 1], got {albedo!r}")
    if periodic:
        p = (np.roll(h, -1, axis=1) - np.roll(h, 1, axis=1)) / (2.0 * pixel_size_um)
        q = (np.roll(h, -1, axis=0) - np.roll(h, 1, axis=0)) / (2.0 * pixel_size_um)
    else:
        q, p = np.gradient(h, pixel_size_um)
    lx, ly, lz = light.vector
    shade = (lz - p * lx - q * ly) / np.sqrt(1.0 + p * p + q * q)
    return np.clip(albedo * shade, 0.0, 1.0)


def normalised_height_error(height: np.ndarray, height_true: np.ndarray) -> float:
    """RMS residual of the best affine fit ``h_true ~ a h + b``, over RMS(h_true - mean).

    0 is perfect; 1 means the recovered height explains nothing. NaN entries count as failure
    (the error is then 1.0 or more).
    """
    h = np.asarray(height, dtype=float).ravel()
    t = np.asarray(height_true, dtype=float).ravel()
    t = t - t.mean()
    denom = float(np.sqrt(np.mean(t * t)))
    if denom == 0:
        raise ValueError("height_true is flat: the normalised error is undefined")
    if not np.all(np.isfinite(h)):
        return float("inf")
    hc = h - h.mean()
    var = float(np.dot(hc, hc))
    a = float(np.dot(hc, t)) / var if var > 0 else 0.0
    return float(np.sqrt(np.mean((t - a * hc) ** 2)) / denom)


# --------------------------------------------------------------------------------------------
# Tsai & Shah (1994)


def tsai_shah(
    image: np.ndarray, light: Light, *, n_iter: int = 50, pixel_size_um: float = 1.0
) -> np.ndarray:
    """Shape from shading by Tsai & Shah's linear approximation (Image Vis. Comput. 12, 1994).

    A faithful port: the slopes are backward differences ``p = Z[i, j] - Z[i, j-1]``,
    ``q = Z[i, j] - Z[i-1, j]`` (0 on the first row and column), the reflectance
    ``R = (1 + p ps + q qs) / (sqrt(1 + p² + q²) sqrt(1 + ps² + qs²))`` clipped at 0, and each
    pixel takes a Newton step on ``f(Z) = E - R(p, q)`` linearised in ``Z[i, j]`` alone, damped by
    the paper's gain ``K = S df / (W + df S df)`` with ``S`` updated as ``S = (1 - K df) S``
    (``S0 = 0.01``, ``W = 1e-8``), from a flat start ``Z = 0`` (Jacobi sweep: all pixels from the
    previous iterate). Here ``(ps, qs) = -tan(slant) (cos tilt, sin tilt)`` follows this module's
    light convention. No safeguards are added: with light along the view axis ``df/dZ`` is 0 at
    the flat start and nothing moves; for many other lights it diverges (values are returned as
    they are, which may be huge, but NaN/inf are replaced by 0 so that callers can score them).

    Parameters
    ----------
    image : ndarray
        Grey image in [0, 1] (the albedo is taken as 1, as in the paper).
    light : Light
        Light direction.
    n_iter : int
        Number of iterations.
    pixel_size_um : float
        Pixel size in µm: the returned heights are ``Z * pixel_size_um``.

    Returns
    -------
    ndarray
        Relative heights in µm (the paper's Z, which increases towards the camera), mean 0.
    """
    E, _ = _as_image(image)
    E = np.where(np.isfinite(E), E, 0.0)
    if n_iter < 0:
        raise ValueError(f"n_iter must be >= 0, got {n_iter!r}")
    slant = min(light.slant_deg, MAX_SLANT_DEG)
    t = np.deg2rad(light.tilt_deg)
    ps = -np.tan(np.deg2rad(slant)) * np.cos(t)
    qs = -np.tan(np.deg2rad(slant)) * np.sin(t)
    norm_s = np.sqrt(1.0 + ps * ps + qs * qs)
    Z = np.zeros_like(E)
    S = np.full_like(E, 0.01)
    W = 1e-8
    with np.errstate(all="ignore"):
        for _ in range(n_iter):
            p = np.zeros_like(Z)
            q = np.zeros_like(Z)
            p[1:, 1:] = Z[1:, 1:] - Z[1:, :-1]
            q[1:, 1:] = Z[1:, 1:] - Z[:-1, 1:]
            pq = 1.0 + p * p + q * q
            R = np.maximum(0.0, (1.0 + p * ps + q * qs) / (np.sqrt(pq) * norm_s))
            f = E - R
            df = -((ps + qs) / (np.sqrt(pq) * norm_s) - (p + q) * (1.0 + p * ps + q * qs)
                   / (np.sqrt(pq**3) * norm_s))
            K = S * df / (W + df * S * df)
            S = (1.0 - K * df) * S
            Z = Z - K * f  # Newton: Z - f / f' when W -> 0
    Z = np.where(np.isfinite(Z), Z, 0.0)
    return (Z - Z.mean()) * pixel_size_um
