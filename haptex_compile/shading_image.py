"""Shading's conventions and inputs: the light, the pixels that carry shading, the Lambertian
image of a surface, and the height error that scores a solve.

Conventions (DOMAIN.md): image rows are +v (+y, down), columns +u (+x, right); the height axis
points towards the camera. A light of slant ``s`` and tilt ``t`` is the unit vector
``L = (sin s cos t, sin s sin t, cos s)`` in (x, y, z); a surface of slopes
``p = dh/dx, q = dh/dy`` has normal ``(-p, -q, 1) / sqrt(1 + p**2 + q**2)`` and the Lambertian
image is ``albedo * max(0, n . L)`` (attached shadows only, no cast shadows).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
from scipy import ndimage

#: Pixels at or above this (saturated) or at or below DARK (black) carry no slope information.
SATURATED = 0.99
DARK = 0.01
# Below this slant the linear term of the reflectance (the only one that fixes the sign of the
# slopes) is too weak: shape from shading is ill-posed and we fall back (see shape_from_shading).
MIN_SLANT_DEG = 5.0
MAX_SLANT_DEG = 89.0
# Black and saturated pixels enter the solve as one-sided bounds (see solve_variational).
CENSORED = True
# The lit ring around a black region that makes it an attached shadow (median at most this
# fraction of the brightest), and around a saturated one that makes it over-exposed shading
# (median at least this level): see _censored_pixels.
TERMINATOR_FRACTION = 0.25
OVEREXPOSED_RING = 0.9


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
    albedo_at_bound : bool
        Estimated lights only: the albedo fitted at this light sat at the light search's upper
        bound, so the image did not fix the slant (see :func:`estimate_light`); False when
        given by the user.
    """

    slant_deg: float
    tilt_deg: float
    slant_sd_deg: float = 0.0
    tilt_sd_deg: float = 0.0
    albedo_at_bound: bool = False

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


def tilt_axis_difference_deg(tilt_a_deg: float, tilt_b_deg: float) -> float:
    """Angle in [0, 90] degrees between two tilts' axes: a tilt and the tilt + 180° light the
    same surface, bumps versus dents (see :func:`estimate_light`)."""
    return abs((tilt_a_deg - tilt_b_deg + 90.0) % 180.0 - 90.0)


def affine_height_residual(height: np.ndarray, height_true: np.ndarray) -> np.ndarray:
    """What is left of the true heights after the best affine fit ``h_true ~ a h + b``:
    ``h_true - mean - a (h - mean(h))`` (a = 0 for a flat `height`), shaped like
    `height_true`."""
    t = np.asarray(height_true, dtype=float)
    shape = t.shape
    h = np.asarray(height, dtype=float).ravel()
    t = t.ravel()
    t = t - t.mean()
    hc = h - h.mean()
    var = float(np.dot(hc, hc))
    a = float(np.dot(hc, t)) / var if var > 0 else 0.0
    return (t - a * hc).reshape(shape)


def normalised_height_error(height: np.ndarray, height_true: np.ndarray) -> float:
    """RMS residual of the best affine fit ``h_true ~ a h + b``, over RMS(h_true - mean)
    (:func:`affine_height_residual`).

    0 is perfect; 1 means the recovered height explains nothing. NaN entries count as failure
    (the error is then 1.0 or more).
    """
    t = np.asarray(height_true, dtype=float).ravel()
    t = t - t.mean()
    denom = float(np.sqrt(np.mean(t * t)))
    if denom == 0:
        raise ValueError("height_true is flat: the normalised error is undefined")
    if not np.all(np.isfinite(np.asarray(height, dtype=float))):
        return float("inf")
    return float(np.sqrt(np.mean(affine_height_residual(height, height_true).ravel() ** 2)) / denom)


def top_level(img: np.ndarray, valid: np.ndarray) -> float:
    """The brightest valid pixels' level: the 99.9th percentile of ``img[valid]`` (a high
    percentile, so that a few noisy pixels do not set it; 1.0 where none is valid). The
    censored pixels' terminator test, the moment albedo's lower bound and the albedo's upper
    bound all start from it; a solve takes it once (1 Mpx: about 12 ms a time)."""
    return float(np.percentile(img[valid], 99.9)) if valid.any() else 1.0


def _finite_or_zero(img: np.ndarray) -> np.ndarray:
    """`img` with its non-finite pixels (which carry no data) set to 0."""
    return np.where(np.isfinite(img), img, 0.0)


# --------------------------------------------------------------------------------------------
# Censored pixels


def _censored_pixels(img: np.ndarray, mask=None, top: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Attached shadows and over-exposed shading, as float32 weights of one-sided bounds.

    A black (``<= DARK``) region is an attached shadow, where the surface faces away from the
    light, only if a terminator bounds it: the shading falls to zero continuously, so the lit
    pixels around it are dim (median at most ``TERMINATOR_FRACTION`` of the brightest). Stains
    and cast shadows have sharp edges and stay plain missing data. Likewise a saturated
    (``>= SATURATED``) region counts as over-exposed shading only if the shading rises to it
    continuously (the pixels around it at least ``OVEREXPOSED_RING``), not a specular highlight.
    `top`: :func:`top_level` of the image, when the caller has it.
    """
    finite = np.isfinite(img)
    with np.errstate(invalid="ignore"):
        dark = finite & (img <= DARK)
        bright = finite & (img >= SATURATED)
    if mask is not None:
        m = np.asarray(mask, bool)
        dark &= m
        bright &= m
    lit = valid_pixels(img, mask)
    if top is None:
        top = top_level(img, lit)

    def bounded(region, keep):
        if not region.any():
            return region
        labels, n = ndimage.label(region, structure=np.ones((3, 3)))
        # 3 x 3 dilations by OpenCV (out-of-image neighbours ignored, as ndimage's reflected
        # border gives for a maximum; labels exact in float32 up to 2**24): 1 Mpx 27 -> 3 ms.
        square = np.ones((3, 3), np.uint8)
        ring = lit & ~region & cv2.dilate(region.astype(np.uint8), square).astype(bool)
        near = cv2.dilate(labels.astype(np.float32), square)
        ring_labels = np.where(ring, near, 0).astype(np.int64)
        # The medians over the ring pixels alone: over the whole image ndimage sorts every
        # pixel (1 Mpx: 83 -> 0.5 ms).
        in_ring = ring_labels > 0
        med = np.asarray(ndimage.median(img[in_ring], ring_labels[in_ring], np.arange(1, n + 1)), dtype=float)
        ok = np.zeros(n + 1, bool)
        ok[1:] = np.isfinite(med) & keep(med)
        return ok[labels]

    dark = bounded(dark, lambda med: med <= TERMINATOR_FRACTION * top)
    bright = bounded(bright, lambda med: med >= OVEREXPOSED_RING)
    return dark.astype(np.float32), bright.astype(np.float32)
