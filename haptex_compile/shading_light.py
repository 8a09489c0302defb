"""Light and albedo from the image: moments of the intensities for a first guess, then a
joint search of the light with the shape (the misfit the default solver leaves under each
candidate light), with its uncertainty and a flag where the misfit does not fix the slant.

:func:`estimate_light` is the entry point; :func:`light_misfit` is the search's ranking of one
light, for diagnosis.
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np
from scipy import ndimage

from haptex_compile import shading_image
from haptex_compile.forked_map import forked_map
from haptex_compile.shading_image import (
    MIN_SLANT_DEG,
    Light,
    _as_image,
    _censored_pixels,
    _finite_or_zero,
    tilt_axis_difference_deg,
    valid_pixels,
)

# Joint light search (see _refine_light): reduced image side, the assumed alignment of the best
# lit normal with the light (cos 35°), and the slant bias that assumption can cause.
SEARCH_SIDE_PX = 96
# Worker processes that solve the search's candidate lights side by side, and the extra
# starts of a tile lit along its axes or a weave direction (_bare_tile_starts, _held_starts,
# _fine_starts; None: one per CPU this process may use; 1: in the calling process; see
# forked_map). The same results either way.
SEARCH_PROCESSES: int | None = None
# The final stage's image side at most (the whole image when it is smaller; see _refine_light).
FINAL_SIDE_PX = 256
# A larger image has the final stage run again on the image itself (block-averaged to at most
# this side), and keeps the light that fits it better. Averaging biases the final image (it
# darkens rough shading, and blurs a weave's crossings), and the true light's well is narrow
# at full resolution: the misfits of 512 and 768 px tiles at their true lights were 1.5-8 x
# below those at the 256 px stage's estimates (Brownian, random bumps, plain weave; lit at
# 15° and 45°). The full-resolution stage alone can settle in a side well (a 768 px plain weave
# lit at 30°: 25.5°, 296° where the 256 px stage found 30.5°, 301°, 4.5 x the misfit), hence
# both (FULL_SIDE_PX <= FINAL_SIDE_PX: no such stage). Measured: see bench_shading's table of
# larger tiles.
FULL_SIDE_PX = 1024
# A plain image (not a tile) has that stage only when its longer side is above this: on plain
# crops of up to 420 px the stage bought nothing at twice the time. Measured on the first 18
# of bench_light's crops larger than 256 px (6 per surface; 246-413 x 115-411 px; light
# estimated): mean height error 0.354 with the stage, 0.355 without; 10 of 18 more than 0.05
# worse than the given light either way (4 better and 3 worse by more than 0.02 with it);
# summed seconds 369.9 against 185.4. Its gain on tiles was measured at 512 and 768 px, where
# the final image is reduced 2-3 x (up to 420 px, at most 1.64 x); larger plain images keep it.
# On all of bench_light's 60 crops (90-420 px; its rerun at afc5a38 against 40107eb): mean
# errors 0.478 / 0.230 / 0.259 -> 0.499 / 0.230 / 0.263 (sphere cap, plain weave, random
# bumps), 29 -> 30 estimates more than 5 points worse, 990 -> 566 s.
PLAIN_FULL_ABOVE_PX = 420
# The coarse image is rescanned at the final side when it loses more than this fraction of the
# image's variance.
MAX_REDUCTION_LOSS = 0.05
# The final stage first scans the tilt this far either side of the coarse estimate.
TILT_SCAN_DEG = 30.0
TILT_SCAN_STEP_DEG = 10.0
ALIGN_COS = float(np.cos(np.deg2rad(35.0)))
CAP_BIAS_DEG = 2.0
# An estimate whose fitted albedo is within 2 % of that bound is flagged: there the misfit
# did not fix the slant (a plateau of steep lights with a large albedo fits as well).
AT_BOUND_FRACTION = 0.98
# Below that plateau, a light whose misfit is this fraction of the best at the image
# statistics' slant or less is a well (true lights on lattice reliefs: 0.03-0.21; random
# bumps and Brownian surfaces under near-frontal light, which have none: 0.8-0.9).
WELL_DEPTH = 0.3
# That plateau, where the image does not fix the slant, lies near acos(ALIGN_COS) = 35° plus
# the relief's slopes (measured 34-46°); a flagged estimate steeper than this is a steep light
# with the bound active (photo bench, lattice windows lit at 55°: 50-58°), left as it is (the
# search below it took a plain weave's window from 0.371 to 1.000).
PLATEAU_MAX_DEG = 47.5
# Below the plateau the well is searched from the best tilt of a 180° scan at the statistics'
# slant and, where that tilt's axis lies more than half a scan step from it, from the plateau's
# own tilt as well (False: the scan's tilt alone). The scan runs at the statistics' slant, and
# where that lies below the true light's well the misfit there is high at every tilt, so its
# best tilt can lead to a side well; on the plateau the misfit still has its minimum near the
# true tilt. Measured: a plain weave's painted window (84 x 66 px, bench_photo) lit at 30°,
# 200°, statistics 26.4°, 205.8°: the scan's tilt gave 29.0°, 186.3° (misfit 0.030, height
# error 0.387), the plateau's tilt 31.0°, 200.8° (misfit 5.2e-4; 0.077; with the light given
# 0.030). The bench's 40 tiles, lattices and near-frontal lights, bench_photo's other 15
# photos and bench_light's 60 crops: the same lights.
PLATEAU_TILT_START = True
# A flagged estimate steeper than that is looked at again with the albedo bounded by
# I_top / STEEP_ALIGN_COS (cos 45°; None: not looked at): under a steep light no normal of a
# gentle relief need come within 35° of it, and the bound then lies below the true albedo, so
# the true light cannot fit. Random bumps (RMS slope 0.2) lit at 60°: the bound was 0.75-0.80
# for an albedo of 0.8, and the search stopped at 57.5-59° where the bound bit; with the
# looser bound the misfit has its well at the true slant (256 px: misfit 3.6e-4 at 60°, 3.7e-4
# at 61°, 5.4e-4 at 59°). The compass search is run again from the estimate under that bound,
# and its light kept if its albedo is free there; it stays flagged (on a gentle lattice relief
# lit at 55° the looser bound bites too, and the light it gave was as far off).
STEEP_ALIGN_COS: float | None = float(np.cos(np.deg2rad(45.0)))
KNEE_FACTOR = 1.25
# A final-stage estimate whose fitted albedo sits at the bound is looked at again below it
# (_well_below_the_bound): the reduced image's misfit on a grid of slants from
# WELL_MIN_SLANT_DEG to the estimate's in WELL_SLANT_STEP_DEG steps and tilts within
# WELL_TILT_SPAN_DEG of it in WELL_TILT_STEP_DEG steps (the true light's well on a 512 px plain
# weave's reduced image is about 2.5° x 5° wide), its WELL_CANDIDATES lowest local minima
# followed on the final image (0: no such look). Measured: see bench_shading's table of
# flagged estimates.
WELL_MIN_SLANT_DEG = 10.0
WELL_SLANT_STEP_DEG = 2.5
WELL_TILT_SPAN_DEG = 30.0
WELL_TILT_STEP_DEG = 5.0
WELL_CANDIDATES = 2
# The tilt sweep of the light search (see _swept_tilt): steps over 180° at the first knee's
# slant, and how much lower than the statistical tilt's a free-albedo misfit must be for the
# search to be run again from there. At 10° the true light's well (about 20° wide on the
# reduced image of the lattices measured) is not stepped over.
TILT_SWEEP_STEP_DEG = 10.0
SWEEP_GAIN = 0.5
# The search from the swept tilt goes on to the final image only if its reduced-image result
# fits below this fraction of the first search's (measured: 0.05-0.09 where its light was
# then kept, 0.2-1.0 where it was not; each final stage costs 1.5-8 s).
SECOND_SEARCH_GAIN = 0.15
# The light search solves each candidate light on a periodic domain; on a plain image the
# domain's seam joins edges that do not match, and the misfit there depends on the light.
# So a plain image's misfit leaves out a band of this fraction of each side (the solve still
# fits it). Measured on bench_shading's 16 plain crops (224 px; four surfaces at slants
# 15-60°, light estimated): summed height error 5.72 -> 5.15 / 5.18 / 5.16 with bands of
# 0.05 / 0.1 / 0.15, at no cost; at 0.15 random bumps lit at 30° and 45° 0.300 / 0.417 ->
# 0.215 / 0.206 (light given: 0.208 / 0.199), the plain weave at 45° and 60° 0.258 / 0.283
# -> 0.113 / 0.161 (given 0.099 / 0.143). On 60 random crops of 512 px tiles (90-420 px, the
# sphere cap, the plain weave, random bumps; 20 each), mean error for bands 0 / 0.05 / 0.15 /
# 0.25: sphere 0.485 / 0.481 / 0.469 / 0.457, weave 0.295 / 0.284 / 0.265 / 0.352, bumps
# 0.324 / 0.301 / 0.280 / 0.292 (light given: 0.342, 0.215, 0.219).
PLAIN_MISFIT_BAND = 0.15


def _moment_albedo(values: np.ndarray, slant_deg: float, top: float | None = None) -> float:
    """Albedo from the mean and variance of the intensities, for a known slant.

    For a stationary surface the linear term of ``R`` averages out, so with isotropic slopes
    (``<g²> = 2 <g_l²>``) to second order ``mean = a cos s (1 - var / (a² sin² s))``: a
    quadratic in the albedo ``a``. Bounded below by the brightest pixels (``R <= 1``): `top`,
    the 99.9th percentile of `values` (computed when not given).
    """
    v = values[np.isfinite(values)]
    if v.size == 0:
        return 1.0
    m, var = float(v.mean()), float(v.var())
    s = np.deg2rad(np.clip(slant_deg, 1.0, 85.0))
    c = np.cos(s)
    a = (m + np.sqrt(m * m + 4 * c * c * var / np.sin(s) ** 2)) / (2 * c)
    if top is None:
        top = float(np.percentile(v, 99.9))
    return float(max(a, top, 1e-3))


def _downsample_to(img: np.ndarray, valid: np.ndarray, side: int):
    """Area-average image and weights so that the larger side is at most `side` pixels."""
    import cv2

    rows, cols = img.shape
    f = max(rows, cols) / side
    if f <= 1:
        return img.astype(np.float32), valid.astype(np.float32)
    size = (max(int(round(cols / f)), 8), max(int(round(rows / f)), 8))
    w = valid.astype(np.float32)
    wi = cv2.resize(np.where(valid, img, 0).astype(np.float32), size, interpolation=cv2.INTER_AREA)
    return _normalised(wi, cv2.resize(w, size, interpolation=cv2.INTER_AREA))


def _block_side(shape: tuple[int, int], side: int) -> int:
    """The block side of :func:`_block_average`: the smallest integer f that brings the larger
    of `shape`'s sides to at most `side` pixels (1: no averaging)."""
    return max(1, int(np.ceil(max(shape) / side)))


def _block_average(img: np.ndarray, valid: np.ndarray, side: int):
    """Average image and weights over f x f blocks, f the smallest integer that brings the
    larger side to at most `side` pixels (edges wrap to fill the last blocks).

    The light search's final image: averaging over fractional blocks (:func:`_downsample_to`)
    mixes neighbouring pixels unevenly, which is not the shading of any surface. Measured on
    a lattice relief of 16 px cells at 256 px lit at 45°: reduced to 192 px that way, its
    misfit's minimum moved 15° in tilt; averaged over 2 x 2 blocks (128 px) it stayed on the
    true light. (The coarse stage keeps :func:`_downsample_to`: with 3 x 3 blocks instead, the
    bench's plain weave lost its 60° estimate, 60° -> 66°.)
    """
    rows, cols = img.shape
    f = _block_side(img.shape, side)
    if f <= 1:
        return img.astype(np.float32), valid.astype(np.float32)
    pad = ((0, (-rows) % f), (0, (-cols) % f))
    w = np.pad(valid.astype(np.float32), pad, mode="wrap")
    wi = np.pad(np.where(valid, img, 0).astype(np.float32), pad, mode="wrap")
    r, c = w.shape[0] // f, w.shape[1] // f
    blocks = lambda a: a.reshape(r, f, c, f).mean(axis=(1, 3))  # noqa: E731
    return _normalised(blocks(wi), blocks(w))


def _normalised(wi: np.ndarray, ww: np.ndarray):
    """Weighted image over weights, and the reduced pixels that are mostly valid."""
    out = np.where(ww > 1e-3, wi / np.maximum(ww, 1e-3), 0.0).astype(np.float32)
    return out, (ww > 0.5).astype(np.float32)


def _quarter_blocks(shape: tuple[int, int]) -> list[tuple[slice, slice]]:
    """The 4 x 4 blocks of an image of `shape` (rows, cols), row by row: the spread of an
    estimate over them gives its uncertainty."""
    rows, cols = shape
    return [(slice(i * rows // 4, (i + 1) * rows // 4), slice(j * cols // 4, (j + 1) * cols // 4))
            for i in range(4) for j in range(4)]


def _tilt_axis(img: np.ndarray, valid: np.ndarray) -> tuple[float, float, float]:
    """Axis of the light's tilt from the image-gradient second moments.

    For an isotropic surface under the linear part of the reflectance, the gradient moment
    tensor is proportional to ``1 + 2 l l^T`` (l = tilt direction): its principal axis is the
    tilt, up to 180°. Returns (axis in degrees in [0, 180), anisotropy (l1-l2)/(l1+l2), sd).
    """
    gy, gx = np.gradient(np.where(valid, img, 0.0))
    ok = ndimage.binary_erosion(valid, iterations=1, border_value=0)
    if ok.sum() < 16:
        ok = valid
    gx, gy = gx * ok, gy * ok

    def axis(sl):
        jxx = float(np.sum(gx[sl] ** 2))
        jyy = float(np.sum(gy[sl] ** 2))
        jxy = float(np.sum(gx[sl] * gy[sl]))
        ang = 0.5 * np.arctan2(2 * jxy, jxx - jyy)
        tr = jxx + jyy
        aniso = np.hypot(jxx - jyy, 2 * jxy) / tr if tr > 0 else 0.0
        return ang, aniso

    ang, aniso = axis((slice(None), slice(None)))
    # Spread over 4 x 4 blocks: the axial (doubled-angle) circular spread, / sqrt(blocks).
    doubled = [2 * axis(sl)[0] for sl in _quarter_blocks(img.shape)]
    c, s = np.mean(np.cos(doubled)), np.mean(np.sin(doubled))
    r = min(max(np.hypot(c, s), 1e-9), 1.0)
    sd_block = 0.5 * np.rad2deg(np.sqrt(-2 * np.log(r)))
    sd = float(min(sd_block / 4.0 + (90.0 if aniso < 0.02 else 0.0), 90.0))
    return float(np.rad2deg(ang) % 180.0), float(aniso), sd


def _moment_slant(values: np.ndarray) -> float:
    """Slant from the intensity moments, for Gaussian isotropic slopes (small-slope expansion).

    With ``I = a (c - s g_l) / sqrt(1 + g²)`` and slopes ``N(0, sigma²)`` per component, to
    leading order ``mean = a c``, ``var = a² s² sigma²`` and third central moment
    ``mu3 = -3 a³ s² c sigma⁴``, hence ``tan² slant = -3 var² / (mean mu3)``. The shading of
    a surface is negatively skewed (slopes only darken the flat-surface value ``a c``); no skew
    means grazing light. Returns degrees in [0, 90].
    """
    v = values[np.isfinite(values)]
    m = float(v.mean())
    var = float(v.var())
    mu3 = float(np.mean((v - m) ** 3))
    if m <= 0 or var <= 0:
        return 0.0
    if mu3 >= 0:
        return 90.0
    return float(np.rad2deg(np.arctan(np.sqrt(-3.0 * var * var / (m * mu3)))))


def estimate_light(image, *, mask=None, refine: bool = True, periodic: bool = True) -> tuple[Light, float]:
    """Estimate the light direction (with its uncertainty) and the albedo from one image.

    Statistics of the shading of a stationary, isotropic random surface (in the spirit of
    Pentland 1982 and Lee & Rosenfeld 1985):

    - tilt: the principal axis of the image-gradient moment tensor, which is proportional to
      ``1 + 2 l l^T`` for such surfaces in the linear-shading regime. The sign is not
      observable (a surface lit from ``t`` looks exactly like the inverted surface lit from
      ``t + 180°``); the convention is the human one, light from the top of the image
      (``sin(tilt) <= 0``);
    - slant: from the mean, variance and (negative) skew of the intensities
      (:func:`_moment_slant`);
    - albedo: from the mean and variance at that slant (:func:`_moment_albedo`);
    - with `refine` (default), the light is then estimated jointly with the shape: the light
      whose best surface (default solver, albedo bounded by the brightest pixels) leaves the
      smallest misfit (:func:`_refine_light`), and the albedo is the one fitted there. This
      matters: the solver is very sensitive to the light (1-2° off can double its error).
      When the albedo fitted there sits at its bound (``Light.albedo_at_bound``: the misfit
      did not fix the slant) above the statistical slant and no steeper than
      ``PLATEAU_MAX_DEG``, the light is searched again below that plateau (see
      :func:`_refine_light`) and the estimate stays flagged, with an uncertainty spanning
      the plateau.

    Without `refine`, the uncertainties are the spread of the same estimators over 4 x 4
    blocks divided by 4 (sampling only), with a floor of 5° for the slant's model error;
    surfaces with strongly non-Gaussian slopes (e.g. woven yarns) bias the statistical slant
    by 10-25°.

    Parameters
    ----------
    image : ndarray
        Grey image (integers are scaled by their maximum; floats should be in [0, 1]).
    mask : ndarray of bool, optional
        Pixels to use.
    refine : bool
        Estimate the light jointly with the shape (about 40 solves on a 96-pixel image and
        40 on one of at most 256 pixels; on 2 cores 1.3-2.1 s for the 256 px bench tiles,
        with each step's candidate lights solved side by side in ``SEARCH_PROCESSES``
        worker processes, 2.4-3.6 s in one). A larger image has about 40 more solves on
        itself (up to ``FULL_SIDE_PX``; a plain image only above ``PLAIN_FULL_ABOVE_PX``):
        see ``bench/bench_shading.py`` for their seconds.
    periodic : bool
        Whether the image wraps (a tile). The search solves each light on a periodic domain
        either way; on a plain image (False) its misfit leaves out a band of
        ``PLAIN_MISFIT_BAND`` of each side, where that domain's seam joins edges that do not
        match.

    Returns
    -------
    (Light, float)
        The light with its uncertainty, and the albedo.
    """
    img, _ = _as_image(image)
    return _estimate_light(img, valid_pixels(img, mask), mask, refine, periodic=periodic)


def _estimate_light(img, valid, mask, refine, censored=None, periodic=True) -> tuple[Light, float]:
    """:func:`estimate_light` on a prepared image (`censored`: :func:`_censored_pixels`
    of it, when the caller has them)."""
    if valid.sum() < 16 or float(np.std(img[valid])) < 1e-4:
        # No shading: nothing to estimate. Overhead light with full uncertainty.
        top = float(np.max(img[valid])) if valid.any() else 1.0
        return Light(0.0, 0.0, 90.0, 180.0), max(top, 1e-3)
    axis, _aniso, tilt_sd = _tilt_axis(img, valid)
    tilt = axis if axis == 0 else axis + 180.0  # sin(tilt) <= 0: light from the image top
    slant = _moment_slant(img[valid])
    blocks = []
    for sl in _quarter_blocks(img.shape):
        vb = img[sl][valid[sl]]
        if vb.size >= 16 and float(np.std(vb)) > 1e-4:
            blocks.append(_moment_slant(vb))
    slant_sd = float(np.std(blocks) / np.sqrt(len(blocks))) if len(blocks) > 1 else 90.0
    slant_sd = float(min(max(slant_sd, 5.0), 90.0))
    albedo, at_bound = None, False
    if refine:
        slant, tilt, slant_sd, tilt_sd, albedo, at_bound, _ = _refine_light(
            img, valid, slant, tilt, censored if censored is not None else _censored_pixels(img, mask),
            periodic=periodic,
        )
    if albedo is None:
        albedo = _moment_albedo(img[valid], slant)
    if np.sin(np.deg2rad(tilt)) > 0:
        # The search may cross the horizontal; the flip is exact (heights negated).
        tilt += 180.0
    light = Light(float(np.clip(slant, 0.0, 90.0)), float(tilt % 360.0), slant_sd, tilt_sd, at_bound)
    return light, albedo


def estimated_light_note(light: Light, periodic: bool = True, on: str | None = None) -> str:
    """The one-line warning that states an estimated light and its uncertainty, and what to
    doubt in it (`periodic` False: it was estimated on a plain image, where the search is less
    sure; `on`: what it was estimated on, e.g. "a periodic window of 190 x 142 px"). The
    evidence behind each clause is in docs/shading.md ("Warnings, and what to do").
    """
    where = "" if on is None else f" on {on}"
    note = (
        f"light estimated{where}: slant {light.slant_deg:.1f} ± {light.slant_sd_deg:.1f}°, tilt"
        f" {light.tilt_deg:.1f} ± {light.tilt_sd_deg:.1f}° (lit from the top of the image; the ±"
        " does not cover other minima)"
    )
    if light.slant_sd_deg > 0 and light.slant_deg <= MIN_SLANT_DEG:
        note += (f"; the slant is the search's lowest ({MIN_SLANT_DEG:g}°): the light may be nearer"
                 " the view axis still")
    if light.albedo_at_bound:
        note += "; UNRELIABLE: the image does not fix the slant (fitted albedo at its bound)"
    if not periodic:
        note += "; on a plain image the estimate is less sure"
    return note + "; give --light when it is known"


def _reduction_loss(img: np.ndarray, valid: np.ndarray, side: int, reduce=_downsample_to) -> float:
    """Fraction of the image's variance (valid pixels) lost by reducing it to `side` pixels."""
    small, w = reduce(img, valid, side)
    if small.shape == img.shape:
        return 0.0
    import cv2

    back = cv2.resize(small, img.shape[::-1], interpolation=cv2.INTER_LINEAR)
    v = img[valid]
    var = float(np.var(v))
    return float(np.mean((v - back[valid]) ** 2) / var) if var > 0 else 0.0


class _MisfitInputs(NamedTuple):
    """The reduced image a light search's misfit is taken on (see :func:`_misfit_inputs`)."""

    image: np.ndarray  # reduced intensities (float32)
    weight: np.ndarray  # the solver's data weights (float32, 0 or 1)
    misfit_weight: np.ndarray  # the misfit's weights (a plain image's edge band left out)
    top: float  # 99.9th percentile of the reduced intensities (the albedo bound's base)
    censored: dict  # the solver's "dark" and "bright" keyword arguments


def _misfit_inputs(img, valid, censored, side_px, reduce=_downsample_to, periodic=True) -> _MisfitInputs:
    """The reduced image of :func:`_misfit_function`: `img` reduced to at most `side_px`
    pixels by `reduce`, its weights, the misfit's weights (on a plain image, outside a band of
    ``PLAIN_MISFIT_BAND`` times each side), the top level and the censored pixels' weights."""
    # A reduced image, not a crop: a crop is not periodic, and with free edges grazing
    # lights fit as well (measured on 256 px bumps: slant 15° estimated as 38°). Averaging
    # changes the shading of rough surfaces, though (Brownian tiles of 256 px: see the
    # bench). An image small enough is not reduced: its non-finite pixels (weight 0) must not
    # reach the solver's sums.
    small, w = reduce(_finite_or_zero(img), valid, side_px)
    # Censored pixels of the reduced image: the fraction of black (saturated) pixels in
    # each reduced pixel that has too few valid ones.
    cens = {}
    if shading_image.CENSORED:
        everywhere = np.ones(img.shape, bool)
        for key, full in zip(("dark", "bright"), censored):
            frac = reduce(full, everywhere, side_px)[0] * (w == 0)
            cens[key] = frac if frac.any() else None
    top = float(np.percentile(small[w > 0], 99.9))
    w_misfit = w
    if not periodic:
        w_misfit = np.zeros_like(w)
        br, bc = (int(round(PLAIN_MISFIT_BAND * n)) for n in w.shape)
        w_misfit[br:w.shape[0] - br, bc:w.shape[1] - bc] = w[br:w.shape[0] - br, bc:w.shape[1] - bc]
        if w_misfit.sum() < 0.25 * w.sum():
            w_misfit = w  # a mask that leaves little data inside the band: keep it all
    return _MisfitInputs(small, w, w_misfit, top, cens)


def _misfit_function(img, valid, censored, side_px, reduce=_downsample_to, periodic=True,
                     looser_cos: float | None = None):
    """The light search's misfit: a function ``fit(slant_deg, tilt_deg) -> (misfit, albedo)``
    on `img` reduced to at most `side_px` pixels (cached per light).

    For each light the default solver fits a surface, with the exact reflectance on every
    level and the albedo bounded above by ``I_top / ALIGN_COS``; the misfit is the data energy
    left (thin-plate term excluded); on a plain image (`periodic` False), outside a band of
    ``PLAIN_MISFIT_BAND`` times each side along the edges (:func:`_misfit_inputs`).
    ``fit.at_bound`` is the albedo from which a fit counts as held at that bound
    (``AT_BOUND_FRACTION`` of it). ``fit.looser`` is the same reduced image's misfit with the
    bound at ``I_top / looser_cos`` (its own ``looser`` None), or None without `looser_cos`.
    `censored` is :func:`_censored_pixels` of the image. ``fit.prefetch(lights)`` solves the
    (slant, tilt) pairs not cached yet at once, with ``fit.map_`` (a map over them that
    :func:`_refine_light` runs in worker processes; by default, one by one), and
    ``fit.solve_light(slant, tilt)`` is one uncached solve.
    """
    from haptex_compile.shading_variational import energy, solve_variational

    small, w, w_misfit, top, cens = _misfit_inputs(img, valid, censored, side_px, reduce, periodic)

    def key_of(s, t):
        # A light's cache key (slant clipped to the searched range), and that slant.
        s = float(np.clip(s, MIN_SLANT_DEG, 85.0))
        return (round(s, 3), round(float(t) % 360.0, 3)), s

    def build(align_cos: float, looser_cos: float | None = None):
        # A misfit on the reduced image above, the albedo bounded by top / align_cos.
        cache: dict[tuple[float, float], tuple[float, float]] = {}

        def solve_light(s, t):
            # The exact reflectance on every level: the misfits of different lights are
            # compared, and the coarse levels' damping depends on the light.
            lv = Light(s, t % 360.0).vector
            z, a = solve_variational(small, w, lv, top, albedo_max=top / align_cos, subgrid_damping=0.0, **cens)
            e = energy(small, w_misfit, lv, a, z, lam=0.0, **cens)
            # A failed solve ranks last (np.argmin would take a NaN for the minimum).
            return (e if np.isfinite(e) else np.inf, a)

        def fit(s, t):
            key, s = key_of(s, t)
            if key not in cache:
                cache[key] = solve_light(s, t)
            return cache[key]

        def prefetch(lights):
            # The lights not cached yet, solved at once by fit.map_ (the same solves, in the
            # same order, as fitting them one by one).
            todo: dict = {}
            for s, t in lights:
                key, s = key_of(s, t)
                if key not in cache:
                    todo.setdefault(key, (s, t))
            if todo:
                cache.update(zip(todo, fit.map_(list(todo.values()))))

        fit.at_bound = AT_BOUND_FRACTION * top / align_cos
        fit.looser = None if looser_cos is None else build(looser_cos)
        fit.solve_light, fit.prefetch = solve_light, prefetch
        fit.map_ = lambda lights: [solve_light(s, t) for s, t in lights]
        return fit

    return build(ALIGN_COS, looser_cos)


def light_misfit(image, light: Light, *, mask=None, periodic: bool = True) -> tuple[float, bool]:
    """The misfit by which the light search ranks lights, for one light: the data energy the
    default solver leaves on the image (block-averaged to at most ``FINAL_SIDE_PX`` pixels,
    as in the search's final stage), with the albedo bounded above by ``I_top / ALIGN_COS``.
    Lower is better; compare lights on the same image only. On a plain image
    (`periodic` False) a band of ``PLAIN_MISFIT_BAND`` of each side is left out, as in the
    search.

    Comparing the estimated light with the true one tells a search that missed the true
    light's well (the true light fits better) from shading that cannot tell them apart
    (the estimate fits as well or better), unless the bound excludes the true albedo there
    (steep light on a gentle relief: no normal within ``acos(ALIGN_COS)`` of the light).

    Returns
    -------
    (float, bool)
        The misfit, and whether the fitted albedo sits at its bound (within
        ``1 - AT_BOUND_FRACTION``).
    """
    img, _ = _as_image(image)
    valid = valid_pixels(img, mask)
    fit = _misfit_function(img, valid, _censored_pixels(img, mask), FINAL_SIDE_PX, _block_average,
                           periodic=periodic)
    misfit, albedo = fit(light.slant_deg, light.tilt_deg)
    return float(misfit), bool(albedo >= fit.at_bound)


class _LightFit(NamedTuple):
    """A light search's result (see :func:`_refine_light`)."""

    slant: float
    tilt: float
    slant_sd: float
    tilt_sd: float
    albedo: float
    at_bound: bool
    relaxed: bool = False  # found under the looser albedo bound (STEEP_ALIGN_COS)


def _refine_light(img, valid, slant, tilt, censored, side=SEARCH_SIDE_PX, periodic=True) -> _LightFit:
    """Estimate the light jointly with the shape: the light whose best surface explains the image.

    For each candidate light the default solver fits a surface to a reduced image (at most
    `side` pixels), with the albedo bounded above by ``I_top / ALIGN_COS`` (``I_top`` = 99.9th
    percentile of the intensities): somewhere on the surface a normal lies within
    ``acos(ALIGN_COS)`` of the light, so the brightest pixels are nearly the albedo. Without
    that bound, a grazing light with a large albedo and shallow slopes explains any image
    (the misfit falls monotonically towards grazing light); with it, the data misfit has a
    sharp minimum near the true slant (measured on the bench surfaces at 128 px).

    On a plain image (`periodic` False) the misfit leaves out a band along the edges, where
    the periodic solve must join edges that do not match (see ``PLAIN_MISFIT_BAND``).

    Attached shadows and over-exposed shading (``CENSORED``): each solve takes them as
    one-sided bounds (see :func:`_censored_pixels`), so a light that would leave a shadowed
    surface facing it costs misfit. Measured at slant 60° on 256 px tiles: the sphere cap's
    estimate went from 64° to 60° (height error 0.105 -> 0.031) and the plain weave's from
    66° to 60° (0.137 -> 0.052).

    Search: on an image reduced to at most `side` pixels, the slant on a 5° grid over 5-80°
    at the statistical tilt (the knee, see below), the tilt by halving steps (±8° to 1°), the
    slant on a 1° grid. Then on the final image (the image itself up to ``FINAL_SIDE_PX``,
    else block-averaged to at most that): the 5° slant grid again if the reduced image lost
    more than ``MAX_REDUCTION_LOSS`` of the image's variance, a tilt scan
    (±``TILT_SCAN_DEG`` in ``TILT_SCAN_STEP_DEG`` steps), and a compass search over slant and
    tilt together (steps 2°, 1°, 0.5°; they are coupled). An image larger than
    ``FINAL_SIDE_PX`` (a plain image: than ``PLAIN_FULL_ABOVE_PX``) has the final stage run
    again on the image itself (at most ``FULL_SIDE_PX``, from the same reduced-image stage),
    and keeps, of the two lights, the one that fits the full image better (a free albedo
    before one at the bound). The misfit is invariant under ``tilt -> tilt + 180°`` with the
    height negated (bumps versus dents), so the tilt stays on the side of the statistical
    estimate (light from the top of the image).

    Those steps are local, and the statistical tilt assumes an isotropic surface: a lattice
    relief's own anisotropy can turn it far from the light (31° on a 16 px oblique lattice,
    59° on a plain weave of 47 px cells), where they settle on another minimum. So the tilt
    axis is also swept on the reduced image at the first knee's slant (:func:`_swept_tilt`);
    a well there is searched again from (if its reduced image fits better), and that light
    kept if it fits the final image better with the albedo free. Measured (light estimated,
    noise-free): of 40 cases of ``bench/bench_shading.py`` (its four surfaces and three
    lattices at 15-60°, near-frontal lights) one changed, the oblique 16 px lattice at 15°,
    30° (22°, 349°, flagged, height error 0.828 -> 15°, 210°, 0.057); of the 16 photos of
    ``bench/bench_photo.py``'s first and coarse-lattice tables one, a smooth relief of 47 px
    cells at 40°, 60° (46°, 200°, flagged, 0.844 -> 40°, 240°, 0.018; what users feel, mean
    a40 / a320 against the true relief's, -22 % / -32 % -> 0 % / 0 %); the six real photos
    of ``../shared/fabrics`` kept their lights. Cost: the sweep, 18 solves on the reduced
    image (0.1-0.3 s); a second search's reduced stage where the sweep finds a well (0.3-1.2
    s), and its final stage only where that stage fits below ``SECOND_SEARCH_GAIN`` of the
    first's (+2.1 s on the photo it corrected).

    Returns
    -------
    _LightFit
        (slant, tilt, slant_sd, tilt_sd, albedo, at_bound): degrees, the albedo fitted at
        the chosen light, and whether that albedo is within
        ``1 - AT_BOUND_FRACTION`` of its bound. The uncertainties are the change
        that doubles the misfit (parabola through ±1°), at least 1° for the slant, combined
        in quadrature with ``CAP_BIAS_DEG`` for the bound's possible bias (too low a slant when
        no normal comes within ``acos(ALIGN_COS)`` of the light), and at least 0.5° for the
        tilt. On the bench surfaces (noise-free) the errors are 0-5° in slant and 0-5° in
        tilt; see ``bench/bench_shading.py`` for the calibration. They are local: on smooth
        lattice reliefs (RMS slope 0.16) lit at 15-30° the search settled 4-23° too steep
        with ±2°. Measured causes: the statistical tilt is up to 36° off on lattices; the
        true light's well is narrow (±2.5° at 256 px, where it is the global minimum of the
        misfit) and the solver's few steps leave its misfit above that of a plateau of steep
        lights, each with the albedo at its bound. Near-frontal light (slant 0-5°) lands on
        the same plateau (random bumps: 36°). `at_bound` marks that plateau: on the bench's
        four surfaces and three lattices at 256 px (slants 0, 5, 10, 15, 30, 45, 60°) it
        flagged every estimate 5° or more off in slant except three: overhead light on the
        sphere cap and the plain weave (estimated 14° and 16°) and one lattice at 15°
        (estimated 20°); and, of the good estimates, two at 60°, where the bound is active
        anyway.

        When the plateau lies above the statistical slant `slant` and no steeper than
        ``PLATEAU_MAX_DEG`` (a steeper one is a steep light with the bound active), the
        light is searched again below it (a 180° tilt scan at that slant; a slant scan and a
        compass search from its best tilt and from the plateau's, ``PLATEAU_TILT_START``)
        and a well is taken if its misfit is at most ``WELL_DEPTH`` times the best at that
        slant, else that slant with the search's tilt; `at_bound` stays set and the
        uncertainties span the plateau. Measured at 256 px (bumps, Brownian surface,
        three lattices; 15 such cases, slants 0-30°): the lattices lit at 5-15° came out
        within 0.5° and 1° in 5 of 7 cases, with the height error of the given light (e.g.
        0.867 -> 0.042); the others were left at the statistics' slant (e.g. Brownian at 5°:
        0.960 -> 0.614, 0.603 with the light given). Cost: about 30-50 more solves, 2-4 s at
        256 px.

        A flagged estimate steeper than ``PLATEAU_MAX_DEG`` is searched again (compass) with
        the albedo bound loosened to ``I_top / STEEP_ALIGN_COS``, and that light kept if its
        albedo is free there; it stays flagged. Of two lights from the final and the
        full-resolution stages, both flagged and one of them from the looser bound, that bound
        judges both. Measured: see ``bench/bench_shading.py``'s table of steep lights (random
        bumps lit at 60°, 256 px: 58° -> 60°, height error 0.093 -> 0.071; given 0.066) and of
        larger tiles (a 768 px Brownian surface lit at 60°: 0.186 -> 0.033; given 0.017).

        A final-stage light whose fitted albedo still sits at the bound (not from the plateau
        search, not from the looser bound) is looked at again below it
        (:func:`_well_below_the_bound`): a free-albedo light that fits the final image better
        replaces it, unflagged. Measured (same runs, with and without it): a square-lattice
        relief of 256 px lit at 45°, 200° came out at 45°, 201° instead of 47.5°, 207° (height
        error 0.224 -> 0.025; given 0.002), a 512 px plain weave lit at 30°, 120° at 30.5°, 301°
        instead of 50°, 313° (0.745 -> 0.037; given 0.033); every other estimate of
        bench_shading's tiles (256, 512 and 768 px), lattices and near-frontal lights, and of
        bench_photo's tables and bench_light's crops, was the same. Cost, same run: 2-3 s more
        at 256 px where it runs and finds nothing (the three lattices lit at 60°: 2.7 -> 4.8,
        2.7 -> 5.7 and 1.8 -> 4.6 s); the 512 px plain weave 13.1 -> 16.3 s.
    """
    coarse = _misfit_function(img, valid, censored, side, periodic=periodic)
    # Each final stage also has its misfit under the looser albedo bound, for a steep flagged
    # estimate (the same reduced image).
    final = _misfit_function(img, valid, censored, FINAL_SIDE_PX, _block_average, periodic=periodic,
                             looser_cos=STEEP_ALIGN_COS)
    full = None
    full_above = FINAL_SIDE_PX if periodic else max(FINAL_SIDE_PX, PLAIN_FULL_ABOVE_PX)
    if max(img.shape) > full_above and FULL_SIDE_PX > FINAL_SIDE_PX:
        full = _misfit_function(img, valid, censored, FULL_SIDE_PX, _block_average, periodic=periodic,
                                looser_cos=STEEP_ALIGN_COS)
    lossy = _reduction_loss(img, valid, side) > MAX_REDUCTION_LOSS
    stages = [f for f in (final, full) if f is not None]
    # The candidate lights of each step of the search are solved side by side (forked_map).
    fits = (coarse, *stages, *(f.looser for f in stages if f.looser is not None))
    with forked_map(lambda k, s, t: fits[k].solve_light(s, t), SEARCH_PROCESSES) as map_:
        for k, fit in enumerate(fits):
            fit.map_ = lambda lights, k=k: map_([(k, s, t) for s, t in lights])

        def search(last):
            # The coarse stage, and the final one on the misfit `last`; then the swept tilt's.
            knee, coarse_misfit, found = _search_light(coarse, last, lossy, float(slant), float(tilt))
            swept = _swept_tilt(coarse, knee, float(tilt))
            if swept is None:
                return found
            _, _, other = _search_light(coarse, last, lossy, float(slant), swept,
                                        beat=SECOND_SEARCH_GAIN * coarse_misfit)
            # The other search's light is kept where it fits better with the albedo free (both
            # misfits are cached: each search ended on its light's).
            if (other is not None and not other.at_bound
                    and last(other.slant, other.tilt)[0] < last(found.slant, found.tilt)[0]):
                return other
            return found

        found = _well_below_the_bound(coarse, final, search(final))
        if full is None:
            return found
        # The coarse stage again from its cache, the final stage at full resolution; of the
        # two lights, the one that fits the full image better (a free albedo first).
        at_full = search(full)

        # Where both are flagged and one came from a steep light's second look, the looser
        # bound judges both (a 512 px Brownian surface lit at 60°: the 256 px stage's light,
        # flagged there, is free at full resolution under the search's bound, and would win on
        # that alone); an unflagged light is judged under the search's bound, where a light
        # from the looser one sits at the bound (a plain crop of the sphere cap lit at 45°:
        # 45°, unflagged, against 60° from the looser bound).
        pair = (at_full, found)
        judge = full
        if any(f.relaxed for f in pair) and all(f.at_bound for f in pair):
            judge = full.looser

        def rank(f):
            misfit, albedo = judge(f.slant, f.tilt)
            return albedo >= judge.at_bound, misfit

        return min(pair, key=rank)


def _uncertainty_lights(s: float, t: float) -> list[tuple[float, float]]:
    """The lights whose misfits :func:`_uncertainty` takes: the light and ±1° of slant, of tilt."""
    return [(s, t), (s - 1, t), (s + 1, t), (s, t - 1), (s, t + 1)]


def _uncertainty(errs) -> tuple[float, float]:
    """(slant_sd, tilt_sd) from the misfits at :func:`_uncertainty_lights`: the change that
    doubles the misfit (parabola through ±1°), at least 1° (slant; in quadrature with the
    albedo bound's possible bias, ``CAP_BIAS_DEG``) and 0.5° (tilt)."""
    e0, e_s_minus, e_s_plus, e_t_minus, e_t_plus = errs

    def half_width(e_minus, e_plus):
        curv = 0.5 * (e_minus + e_plus - 2.0 * e0)
        return float(np.sqrt(e0 / curv)) if curv > 0 and e0 > 0 else 90.0

    return (float(np.hypot(max(half_width(e_s_minus, e_s_plus), 1.0), CAP_BIAS_DEG)),
            max(half_width(e_t_minus, e_t_plus), 0.5))


def _compass(e_fn, s: float, t: float, prefetch, top: float = 85.0) -> tuple[float, float]:
    """A compass search of `e_fn` over slant and tilt together (8 neighbours, steps 2°, 1°,
    0.5°; they are coupled; starting at 1° left a plain weave lit at 30° stuck 2° and 4° off)
    from (`s`, `t`), among slants ``MIN_SLANT_DEG``-`top`; each step's lights solved at once
    by `prefetch`. It stops where `e_fn` is infinite all round."""
    step = 2.0
    while step >= 0.5:
        cands = [(s + i * step, t + j * step) for i in (-1, 0, 1) for j in (-1, 0, 1)]
        cands = [(a, b) for a, b in cands if MIN_SLANT_DEG <= a <= 85.0]
        prefetch([(a, b) for a, b in cands if a <= top])
        errs = [e_fn(a, b) if a <= top else np.inf for a, b in cands]
        if not np.isfinite(min(errs)):
            break  # no misfit to follow (the walk would never stop)
        k = int(np.argmin(errs))
        if (s, t) in cands and not errs[k] < errs[cands.index((s, t))]:
            step /= 2  # nothing better around (a neighbour that only ties would walk for ever)
        else:
            s, t = cands[k]
    return s, t


def _well_below_the_bound(coarse, final, found: _LightFit | None) -> _LightFit | None:
    """`found` (the final stage's light), or a light below it that fits the final image
    better with the albedo free, where `found`'s fitted albedo sits at the search's bound.

    There the misfit does not fix the slant (a plateau of steep lights), and the true light's
    well below it can be deep and narrow, missed by the search's steps along the statistical
    tilt: on the reduced image of a 512 px plain weave lit at 30°, 120° the well is about 2.5°
    wide (misfit 0.049 at the true light against 0.116 at 5° more slant), the statistical tilt
    20° off, and the search stopped at 50.5°, 309.8° (height error 0.745; 0.033 with the light
    given). So the reduced image's misfit is scanned below the estimate, slants from
    ``WELL_MIN_SLANT_DEG`` in ``WELL_SLANT_STEP_DEG`` steps, tilts ±``WELL_TILT_SPAN_DEG`` in
    ``WELL_TILT_STEP_DEG`` steps, among lights whose albedo is free; its ``WELL_CANDIDATES``
    lowest local minima are followed on the final image by a compass search (no steeper than
    the estimate), and the best kept if it fits the final image better than the estimate, its
    albedo free (not flagged then). Not for a light whose albedo is free already (the plateau
    search of :func:`_search_light` gave it) or found under the looser bound (a steep light).
    Measured: see bench_shading's table of flagged estimates (``WELL_CANDIDATES = 0``: no
    such look).
    """
    if (WELL_CANDIDATES <= 0 or found is None or not found.at_bound or found.relaxed
            or found.albedo < final.at_bound):
        return found
    slants = np.arange(WELL_MIN_SLANT_DEG, found.slant - WELL_SLANT_STEP_DEG + 1e-9, WELL_SLANT_STEP_DEG)
    tilts = found.tilt + np.arange(-WELL_TILT_SPAN_DEG, WELL_TILT_SPAN_DEG + 1e-9, WELL_TILT_STEP_DEG)
    if slants.size == 0:
        return found
    coarse.prefetch([(a, b) for a in slants for b in tilts])
    grid = np.array([[_free_misfit(coarse, a, b) for b in tilts] for a in slants])
    # Local minima of the scan (each at most its 8 neighbours), lowest first.
    around = ndimage.minimum_filter(grid, size=3, mode="constant", cval=np.inf)
    minima = [(grid[i, j], slants[i], tilts[j]) for i, j in zip(*np.nonzero(np.isfinite(grid) & (grid <= around)))]
    best_misfit, best = final(found.slant, found.tilt)[0], None
    for _, a, b in sorted(minima)[:WELL_CANDIDATES]:
        a, b = _compass(lambda x, y: _free_misfit(final, x, y), float(a), float(b), final.prefetch, top=found.slant)
        misfit = _free_misfit(final, a, b)
        if misfit < best_misfit:
            best_misfit, best = misfit, (a, b)
    if best is None:
        return found
    a, b = best
    final.prefetch(_uncertainty_lights(a, b))
    slant_sd, tilt_sd = _uncertainty([final(x, y)[0] for x, y in _uncertainty_lights(a, b)])
    return _LightFit(a, b % 360.0, min(slant_sd, 90.0), min(tilt_sd, 90.0), final(a, b)[1], False)


def _swept_tilt(coarse, slant: float, tilt: float) -> float | None:
    """A tilt whose coarse misfit at `slant` (the first knee) is well below the statistical
    `tilt`'s, or None.

    The statistical tilt assumes an isotropic surface; a lattice relief's own anisotropy can
    turn it far from the light (measured: 59° on a plain weave of 47 px cells), beyond the
    local searches' reach. So the tilt axis is swept over 180° in ``TILT_SWEEP_STEP_DEG``
    steps at that slant, among lights whose albedo is free; the best is returned if its misfit
    is below ``SWEEP_GAIN`` times the statistical tilt's (or that one's albedo sat at the bound),
    even where it lies within the final stage's tilt scan of the search's light: that scan runs
    at the search's slant, and a well at another slant can be too narrow to show there
    (measured: a lattice relief lit at 15°, 30°, whose search ended free at 20.5°, 20°; the
    well, 10° of tilt away, fits 10 x better). The search from the swept tilt goes on to the
    final image only if it beats the first (``SECOND_SEARCH_GAIN``).
    """
    sweep = tilt + np.arange(0.0, 180.0, TILT_SWEEP_STEP_DEG)
    coarse.prefetch([(slant, t) for t in sweep])
    errs = [_free_misfit(coarse, slant, t) for t in sweep]
    best = int(np.argmin(errs))
    if not np.isfinite(errs[best]) or not errs[best] < SWEEP_GAIN * errs[0]:
        return None
    return float(sweep[best])


def _free_misfit(fit, slant: float, tilt: float) -> float:
    """The misfit `fit` gives the light, or infinity where its fitted albedo sits at the
    search's bound (``fit.at_bound``: there the misfit does not fix the light)."""
    misfit, albedo = fit(slant, tilt)
    return misfit if albedo < fit.at_bound else np.inf


def _search_light(coarse, final, reduction_lossy: bool, slant: float, tilt: float,
                  beat: float | None = None) -> tuple[float, float, _LightFit | None]:
    """One search of :func:`_refine_light` from the statistical `slant` and `tilt`, with the
    misfit functions `coarse` (reduced image) and `final`; `reduction_lossy`: the reduced image
    lost more than ``MAX_REDUCTION_LOSS`` of the variance. Returns the first knee's slant, the
    reduced image's misfit at the end of its stage, and the search's :class:`_LightFit`;
    that is None if `beat` is given and the reduced image's misfit is not below it (the
    final stage is then skipped). A steep estimate at the bound is searched again on
    ``final.looser`` when there is one."""
    stat_slant = float(slant)

    def misfits(e_fn, lights, top=np.inf):
        # e_fn at each (slant, tilt), the uncached ones solved at once (fit.prefetch); `top`:
        # the highest slant e_fn solves for (above it, it returns inf unsolved)
        fit.prefetch([(a, b) for a, b in lights if a <= top])
        return [e_fn(a, b) for a, b in lights]

    def polish_tilt(e_of, s, t, step, stop):
        while step >= stop:
            cands = [t - step, t, t + step]
            errs = misfits(e_of, [(s, c) for c in cands])
            if not np.isfinite(min(errs)):
                break  # no misfit to follow (the walk would never stop)
            k = int(np.argmin(errs))
            if not errs[k] < errs[1]:
                step /= 2  # nothing better either side (as in _compass: ties do not walk)
            else:
                t = cands[k]
        return t

    def best(e_of, slants, t):
        errs = misfits(e_of, [(g, t) for g in slants])
        return float(slants[int(np.argmin(errs))]), np.asarray(errs)

    # Coarse: the misfit drops steeply up to the true slant, then stays low (a plateau that
    # rises slowly) until the albedo bound bites; on the reduced image the plateau can dip
    # below the true slant's misfit, so take the knee: the lowest slant whose misfit is within
    # KNEE_FACTOR of the minimum.
    fit = coarse
    e_of = lambda s_, t_: fit(s_, t_)[0]  # noqa: E731
    grid = np.arange(5.0, 80.0 + 1e-9, 5.0)
    errs = np.asarray(misfits(e_of, [(g, tilt) for g in grid]))
    s = knee = float(grid[errs <= KNEE_FACTOR * errs.min()][0])
    t = polish_tilt(e_of, s, float(tilt), 8.0, 1.0)
    s, _ = best(e_of, np.arange(max(MIN_SLANT_DEG, s - 3.0), min(85.0, s + 6.0) + 1e-9, 1.0), t)
    coarse_misfit = e_of(s, t)
    if beat is not None and not coarse_misfit < beat:
        return knee, coarse_misfit, None
    # Final: the sharp minimum on a larger image (the reduced image blurs it; 1° of slant can
    # cost several points of height error). Images with much detail below the reduced
    # pixel (fractal surfaces) are not the shading of any surface once averaged: their
    # reduced misfit has its knee at too high a slant (Brownian H = 0.7, 256 px, slant 15°:
    # 40° at 96 px, 15° at full resolution). For them the final image is larger and the
    # slant grid is scanned again on it.
    # Final image: the largest affordable. Block-averaging to the smallest image that keeps
    # 95 % of the variance (128 px for most 256 px tiles) misled the search: the misfits that
    # pick the light are far below that 5 % (measured at slants 15-60° on the bench's 256 px
    # tiles: sphere cap worst gap to the given light +0.031 -> +0.006, plain weave
    # +0.018 -> +0.008, a 32 px oblique lattice at 30° 0.294 -> 0.204; 1-1.5 s more).
    fit = final
    e_of = lambda s_, t_: fit(s_, t_)[0]  # noqa: E731
    if reduction_lossy:
        # Averaging biases the slant upwards (it darkens rough shading): scan up to just above
        # the coarse estimate.
        low = grid[grid <= s + 5.0]
        errs = np.asarray(misfits(e_of, [(g, t) for g in low]))
        s = float(low[errs <= KNEE_FACTOR * errs.min()][0])
    # The misfit is narrow in tilt (a few degrees) and the reduced image can settle on a side
    # lobe: scan the tilt around the estimate (measured on a painted plain-weave window lit at
    # 45°: the coarse stage stopped 13° off, with 3.5 times the misfit of the true tilt's).
    tilts = t + np.arange(-TILT_SCAN_DEG, TILT_SCAN_DEG + 1e-9, TILT_SCAN_STEP_DEG)
    t = float(tilts[int(np.argmin(misfits(e_of, [(s, c) for c in tilts])))])
    # Slant and tilt are coupled: a compass search over both (see _compass).
    def compass(e_fn, s, t, top=85.0):
        return _compass(e_fn, s, t, fit.prefetch, top)  # `fit`: the misfit of this step

    s, t = compass(e_of, s, t)
    bound = fit.at_bound  # a fitted albedo this high is at the bound
    plateau = None
    relaxed, steep = False, final.looser
    if steep is not None and fit(s, t)[1] >= bound and s > PLATEAU_MAX_DEG:
        # A steep light with the albedo at its bound: that bound may lie below the true
        # albedo (STEEP_ALIGN_COS). The compass search again under a looser one; its light
        # is kept if its albedo is free there (still flagged).
        fit = steep  # the misfit that misfits() prefetches
        s_r, t_r = compass(lambda a, b: steep(a, b)[0], s, t)
        if steep(s_r, t_r)[1] < steep.at_bound:
            s, t, relaxed, bound = s_r, t_r, True, steep.at_bound
            e_of = lambda s_, t_: steep(s_, t_)[0]  # noqa: E731
        else:
            fit = final
    if fit(s, t)[1] >= bound and stat_slant < s <= PLATEAU_MAX_DEG:
        # On the plateau of steep lights with the albedo at its bound, where the misfit does
        # not fix the slant. Below it the true light's well is deep and narrow (lattice
        # reliefs lit at 15°: misfit 1e-3 against 4e-2 10° of tilt away), but the search's
        # tilt may be far from it (the statistical tilt is up to 36° off on lattices). So,
        # among lights whose albedo is free and no steeper than the image statistics' slant
        # + 5° (the plateau's edge fits better still): scan the tilt over 180° at that slant
        # (the misfit repeats with the height negated), then the slant, then the compass
        # search, from the scan's best tilt and the plateau's own (PLATEAU_TILT_START). A light
        # whose misfit is at most WELL_DEPTH times the best at the statistics' slant (a well)
        # is taken; else that slant, with the search's tilt.
        plateau = (s, t)
        top_slant = stat_slant + 5.0

        def free(a, b):
            return _free_misfit(fit, a, b) if a <= top_slant else np.inf

        tilts = t + np.arange(0.0, 180.0, TILT_SCAN_STEP_DEG)
        errs = misfits(free, [(stat_slant, c) for c in tilts], top_slant)
        e_stat = float(min(errs))
        s = stat_slant
        if np.isfinite(e_stat):
            t_low = float(tilts[int(np.argmin(errs))])
            slants = np.arange(MIN_SLANT_DEG, top_slant + 1e-9, 1.0)
            wells = []
            second = PLATEAU_TILT_START and tilt_axis_difference_deg(t, t_low) > TILT_SCAN_STEP_DEG / 2
            for t_start in [t_low] + ([t] if second else []):
                errs_s = misfits(free, [(c, t_start) for c in slants], top_slant)
                wells.append(compass(free, float(slants[int(np.argmin(errs_s))]), t_start, top_slant))
            s_w, t_w = min(wells, key=lambda w: free(*w))
            if free(s_w, t_w) <= WELL_DEPTH * e_stat:
                s, t = s_w, t_w
    slant_sd, tilt_sd = _uncertainty(misfits(e_of, _uncertainty_lights(s, t)))
    albedo = fit(s, t)[1]
    at_bound = relaxed or albedo >= bound
    if plateau is not None:
        # The plateau fits as well: the ± spans it. Still flagged.
        at_bound = True
        slant_sd = max(slant_sd, plateau[0] - s)
        tilt_sd = max(tilt_sd, tilt_axis_difference_deg(plateau[1], t))
    return knee, coarse_misfit, _LightFit(s, t % 360.0, min(slant_sd, 90.0), min(tilt_sd, 90.0), albedo,
                                          bool(at_bound), relaxed)
