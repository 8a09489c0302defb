"""Tile averaging: one clean, exactly periodic synthetic image from all repetitions of the tile.

Given the lattice (t1, t2) of a photograph, every repetition (lattice cell) is resampled (bicubic,
sub-pixel) onto the tile grid in fractional lattice coordinates; the repetitions are combined
robustly per tile sample (median by default, so noise, stains and slubs are voted out), and the
averaged tile is painted back over the whole image. Slow illumination gradients are removed
first (`flatten_illumination`); `average_tile` applies the same correction at the sample
positions only, so a large photo is never copied at full size before painting.

Large photos hold far more repetitions than a robust average needs (an 18.7 MP photo of a 13 px
weave holds ~10^5): at most `MAX_REPETITIONS` (256) cells, drawn at random with a fixed seed
among the cells wholly inside the image, are combined. The median of 256 Gaussian samples has a
standard error of 1.2533 sigma / 16 = 0.08 sigma, well below the repetition-to-repetition spread
of real fabrics.

Vectors are (x, y) in px; pixel (row y, column x) has its centre at (x, y). The tile origin is the
centre of pixel (0, 0), so tile sample [j, i] sits at (i / n1) t1 + (j / n2) t2 (mod the lattice).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from haptex_compile.lattice import Lattice, _as_grey_array, _gaussian_blur

__all__ = ["flatten_illumination", "TileAverage", "average_tile", "paint_tile", "periodic_window", "MAX_REPETITIONS"]

_IQR_TO_SIGMA = 1.0 / 1.349  # inter-quartile range of a Gaussian is 1.349 sigma
MAX_REPETITIONS = 256        # repetitions combined per tile sample at most (see module docstring)
_SUBSET_SEED = 0             # fixed seed of the repetition subset: results are deterministic
_BLOCK_PX = 256              # painting block: its source mosaic stays in the CPU cache
_CUBIC_MARGIN_PX = 2.0       # px a bicubic sample needs on each side


def flatten_illumination(image: np.ndarray, sigma_px: float, *, mode: str = "auto"
                         ) -> np.ndarray:
    """Remove slow illumination gradients by comparing the image with a heavy Gaussian blur.

    Parameters
    ----------
    image : numpy.ndarray
        2-D grey image.
    sigma_px : float
        Blur scale in px; use at least one or two periods of the texture so the blur sees only
        the light (the tile averaging uses twice the longest lattice vector).
    mode : {"auto", "divide", "subtract"}
        "divide": image / blur x mean(blur), the model of reflectance under multiplicative light
        (keeps the mean level and the relative contrast). "subtract": image - blur + mean(blur),
        for additive offsets or signed data. "auto" divides when the image is non-negative and
        the blur stays above 2 % of its maximum, and subtracts otherwise.

    Returns
    -------
    numpy.ndarray
        Image (float32 for integer or float32 input, else float64) with the same mean level and
        no gradient on scales above ~sigma_px.
    """
    img = _as_grey_array(image)
    img = img if img.dtype in (np.float32, np.float64) else img.astype(np.float32)
    if not (math.isfinite(sigma_px) and sigma_px > 0):
        raise ValueError(f"sigma_px must be positive, got {sigma_px}")
    if mode not in ("auto", "divide", "subtract"):
        raise ValueError(f"mode must be auto, divide or subtract, got {mode!r}")
    blur = _gaussian_blur(img, sigma_px).astype(img.dtype, copy=False)
    level = float(blur.mean())
    positive = img.min() >= 0 and blur.min() > 0.02 * max(float(blur.max()), 1e-300)
    if mode == "divide" and not positive:
        raise ValueError("flatten_illumination: 'divide' needs a positive image and blur; "
                         "use mode='subtract'")
    if mode == "divide" or (mode == "auto" and positive):
        out = img / blur
        out *= level
        return out
    out = img - blur
    out += level
    return out


@dataclass(frozen=True)
class TileAverage:
    """Result of tile averaging.

    Attributes
    ----------
    synthetic : numpy.ndarray
        Same shape as the input: every pixel replaced by the robust average over all its
        lattice-equivalent positions, painted from `tile`, so exactly lattice-periodic.
    spread : numpy.ndarray
        Same shape: per-pixel robust spread across repetitions (sigma from the inter-quartile
        range, IQR / 1.349), in the image's units.
    tile : numpy.ndarray
        The averaged cell [n2, n1]; sample [j, i] at fractional lattice coordinates
        (i / n1, j / n2), i.e. at (i / n1) t1 + (j / n2) t2 from the centre of pixel (0, 0).
    n_repetitions : int
        Repetitions (lattice cells) that contributed at least one sample.
    counts : numpy.ndarray
        [n2, n1] number of repetitions that contributed to each tile sample.
    t1_px, t2_px : numpy.ndarray
        The lattice used.
    combine : str
        How the repetitions were combined.
    n_repetitions_available : int
        Cells that could have contributed (wholly inside the image, or touching it when too few
        are); `n_repetitions` of them, at most MAX_REPETITIONS, were combined.
    """

    synthetic: np.ndarray
    spread: np.ndarray
    tile: np.ndarray
    n_repetitions: int
    counts: np.ndarray
    t1_px: np.ndarray
    t2_px: np.ndarray
    combine: str
    n_repetitions_available: int = 0

    def tile_spread(self) -> np.ndarray:
        """Median over the cell of the spread map (a single noise figure), image units."""
        return np.asarray(np.median(self.spread))


def _light_field(img: np.ndarray, sigma_px: float) -> tuple[np.ndarray, float, float]:
    """Gaussian blur of the image at scale sigma_px, kept on a reduced grid (light is smooth).

    Returns the reduced float32 blur and the reduction factors (fx, fy): the blur at image pixel
    (x, y) is the bilinear sample of the reduced grid at ((x + 0.5) / fx - 0.5, (y + 0.5) / fy
    - 0.5), which is what `_gaussian_blur` returns at full size (cv2.resize INTER_LINEAR).
    """
    rows, cols = img.shape
    if sigma_px <= 6.0:
        return _gaussian_blur(img, sigma_px).astype(np.float32), 1.0, 1.0
    factor = sigma_px / 3.0
    small_shape = (max(2, round(cols / factor)), max(2, round(rows / factor)))
    src = img if img.dtype in (np.uint8, np.uint16, np.float32) else img.astype(np.float32)
    small = cv2.resize(src, small_shape, interpolation=cv2.INTER_AREA).astype(np.float32)
    fx, fy = cols / small_shape[0], rows / small_shape[1]
    # the area average already blurred by a box of width f (variance f^2 / 12)
    sx = math.sqrt(max(sigma_px ** 2 - fx ** 2 / 12.0, 0.25)) / fx
    sy = math.sqrt(max(sigma_px ** 2 - fy ** 2 / 12.0, 0.25)) / fy
    small = cv2.GaussianBlur(small, (0, 0), sigmaX=sx, sigmaY=sy, borderType=cv2.BORDER_REFLECT)
    return small, fx, fy


REMAP_ROWS = 16384  # rows of 4096 points per cv2.remap call (its limit is 32766)
REMAP_SRC_MAX = 32766  # cv2.remap's limit on the source's sides too
REMAP_BLOCK = 30000  # larger sources are sampled a block of this many px a side at a time
REMAP_MARGIN = 4  # px beyond a block that its points' cubic kernels reach (2 needed)


def _remap_points_in_blocks(src: np.ndarray, x: np.ndarray, y: np.ndarray, interpolation: int,
                            border: int, border_value: float) -> np.ndarray:
    """:func:`_remap_points` for a source with a side over ``REMAP_SRC_MAX`` (a flatbed scan
    of 33 000 px was an OpenCV assertion traceback): the points are grouped by the block of
    the source they fall in and sampled from that block plus a margin, which the kernel does not
    reach past, so the values are the whole source's. Points beyond the source go with the
    block at its edge, which holds that edge, so the border rule is the same."""
    rows, cols = src.shape
    out = np.empty(x.size, np.float32)
    bx = np.clip(np.floor(x / REMAP_BLOCK), 0, (cols - 1) // REMAP_BLOCK).astype(np.int64)
    by = np.clip(np.floor(y / REMAP_BLOCK), 0, (rows - 1) // REMAP_BLOCK).astype(np.int64)
    key = by * (cols // REMAP_BLOCK + 1) + bx
    for block in np.unique(key):
        sel = np.nonzero(key == block)[0]
        r0 = max(0, int(by[sel[0]]) * REMAP_BLOCK - REMAP_MARGIN)
        c0 = max(0, int(bx[sel[0]]) * REMAP_BLOCK - REMAP_MARGIN)
        part = src[r0:(int(by[sel[0]]) + 1) * REMAP_BLOCK + REMAP_MARGIN,
                   c0:(int(bx[sel[0]]) + 1) * REMAP_BLOCK + REMAP_MARGIN]
        out[sel] = _remap_points(np.ascontiguousarray(part), x[sel] - c0, y[sel] - r0, interpolation, border,
                                 border_value)
    return out


def _remap_points(src: np.ndarray, x: np.ndarray, y: np.ndarray, interpolation: int,
                  border: int, border_value: float = 0.0) -> np.ndarray:
    """Sample `src` at (x, y) px (any shape) with cv2.remap; float32 result of the same shape.

    cv2.remap limits each map side to < 32767, so the points are laid out 4096 per row, and
    at most ``REMAP_ROWS`` rows a call (a 48 Mpx photo's tile average samples 200 M points:
    49 000 rows, and OpenCV's assertion was a traceback).
    """
    shape = x.shape
    if max(src.shape) > REMAP_SRC_MAX:
        return _remap_points_in_blocks(src, np.ravel(x), np.ravel(y), interpolation, border,
                                       border_value).reshape(shape)
    n = x.size
    width = 4096
    pad = (-n) % width
    mx = np.concatenate([x.ravel(), np.zeros(pad)]).astype(np.float32).reshape(-1, width)
    my = np.concatenate([y.ravel(), np.zeros(pad)]).astype(np.float32).reshape(-1, width)
    out = np.empty(mx.shape, np.float32)
    for r0 in range(0, mx.shape[0], REMAP_ROWS):
        rows = slice(r0, r0 + REMAP_ROWS)
        out[rows] = cv2.remap(src, mx[rows], my[rows], interpolation, borderMode=border, borderValue=border_value)
    return out.ravel()[:n].reshape(shape)


def _cell_range(shape: tuple[int, int], basis: np.ndarray) -> tuple[int, int, int, int]:
    """Integer cell indices (m0, m1, k0, k1): cells m t1 + k t2 + [0, 1)^2 basis, m0 <= m < m1,
    k0 <= k < k1, cover the image."""
    rows, cols = shape
    corners = np.array([[0, 0], [cols - 1, 0], [0, rows - 1], [cols - 1, rows - 1]], float).T
    frac = np.linalg.solve(basis, corners)
    m0, k0 = np.floor(frac.min(axis=1)).astype(int) - 1
    m1, k1 = np.ceil(frac.max(axis=1)).astype(int) + 1
    return int(m0), int(m1), int(k0), int(k1)


def _choose_cells(shape: tuple[int, int], basis: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray, int]:
    """Cells to combine: (m, k) index arrays and how many were available.

    Cells wholly inside the image (with the bicubic margin) are preferred; when fewer than 16
    (or than half of the cells touching the image) are, the touching cells contribute the samples
    they have. At most MAX_REPETITIONS are drawn, at random with a fixed seed, so they spread over
    the whole photo and the result is deterministic.
    """
    rows, cols = shape
    m0, m1, k0, k1 = _cell_range(shape, basis)
    k, m = np.mgrid[k0:k1, m0:m1]
    m, k = m.ravel().astype(float), k.ravel().astype(float)
    t1, t2 = basis[:, 0], basis[:, 1]
    # the 4 corners of each cell (x and y); the cell is convex, so corners decide containment
    cx = np.stack([m * t1[0] + k * t2[0] + a * t1[0] + b * t2[0]
                   for a, b in ((0, 0), (1, 0), (0, 1), (1, 1))])
    cy = np.stack([m * t1[1] + k * t2[1] + a * t1[1] + b * t2[1]
                   for a, b in ((0, 0), (1, 0), (0, 1), (1, 1))])
    g = _CUBIC_MARGIN_PX
    inside = ((cx.min(0) >= g) & (cx.max(0) <= cols - 1 - g) &
              (cy.min(0) >= g) & (cy.max(0) <= rows - 1 - g))
    touching = ((cx.max(0) >= -g) & (cx.min(0) <= cols - 1 + g) &
                (cy.max(0) >= -g) & (cy.min(0) <= rows - 1 + g))
    use = inside if inside.sum() >= max(16, 0.5 * touching.sum()) else touching
    idx = np.flatnonzero(use)
    available = int(idx.size)
    if idx.size > MAX_REPETITIONS:
        rng = np.random.default_rng(_SUBSET_SEED)
        idx = np.sort(rng.choice(idx, size=MAX_REPETITIONS, replace=False))
    return m[idx], k[idx], available


def _robust_rows(values: np.ndarray, combine: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per-row robust location and spread of `values` [n_samples, n_reps], NaN = missing."""
    ordered = np.sort(values, axis=1)  # NaN sort last
    count = np.count_nonzero(np.isfinite(ordered), axis=1)
    k = np.maximum(count, 1)

    def at(pos: np.ndarray) -> np.ndarray:
        lo = np.floor(pos).astype(int)
        hi = np.minimum(lo + 1, k - 1)
        w = pos - lo
        a = np.take_along_axis(ordered, lo[:, None], axis=1)[:, 0].astype(np.float64)
        b = np.take_along_axis(ordered, hi[:, None], axis=1)[:, 0].astype(np.float64)
        return a + w * (b - a)

    q1, q2, q3 = at(0.25 * (k - 1)), at(0.5 * (k - 1)), at(0.75 * (k - 1))
    spread = (q3 - q1) * _IQR_TO_SIGMA
    if combine == "median":
        centre = q2
    elif combine == "trimmed_mean":
        # mean of the central 60 % (20 % trimmed at each end)
        cut = np.floor(0.2 * k).astype(int)
        csum = np.concatenate([np.zeros((len(ordered), 1)),
                               np.cumsum(np.nan_to_num(ordered, nan=0.0), axis=1, dtype=np.float64)], axis=1)
        hi = k - cut
        total = (np.take_along_axis(csum, hi[:, None], axis=1)
                 - np.take_along_axis(csum, cut[:, None], axis=1))[:, 0]
        centre = total / np.maximum(hi - cut, 1)
    else:  # mean
        centre = np.nansum(values, axis=1, dtype=np.float64) / k
    empty = count == 0
    centre[empty] = np.nan
    spread[empty] = np.nan
    return centre, spread, count


def _paint(tile: np.ndarray, basis: np.ndarray, shape: tuple[int, int],
           interpolation: int) -> np.ndarray:
    """Paint a periodic tile [n2, n1] over an image of `shape` (float32 result).

    Pixel (x, y) takes the tile at (u, v) = diag(n1, n2) B^-1 (x, y), wrapped modulo (n1, n2).
    The image is painted in _BLOCK_PX blocks, each from a small mosaic of whole tiles shifted by
    whole tiles (the lattice's own periodicity, so nothing changes), because one warp over an
    image-sized mosaic runs diagonally through memory and is 2-3 times slower.
    """
    rows, cols = shape
    n2, n1 = tile.shape
    a = np.diag([float(n1), float(n2)]) @ np.linalg.inv(basis)  # (x, y) -> (u, v)
    bs = _BLOCK_PX
    local = a @ np.array([[0, bs, 0, bs], [0, 0, bs, bs]], float)
    lo, hi = local.min(axis=1), local.max(axis=1)
    margin = 3.0  # tile samples of interpolation support
    n = np.array([n1, n2], float)
    reps = np.ceil((hi - lo + 2 * margin) / n).astype(int) + 1
    mosaic = np.tile(tile.astype(np.float32), (int(reps[1]), int(reps[0])))
    out = np.empty((rows, cols), np.float32)
    mat = np.zeros((2, 3))
    mat[:, :2] = a
    for y0 in range(0, rows, bs):
        for x0 in range(0, cols, bs):
            uv0 = a @ np.array([x0, y0], float)
            shift = np.floor((uv0 + lo - margin) / n) * n  # whole tiles: the same pattern
            mat[:, 2] = uv0 - shift
            bw, bh = min(bs, cols - x0), min(bs, rows - y0)
            cv2.warpAffine(mosaic, mat, (bw, bh), dst=out[y0:y0 + bh, x0:x0 + bw],
                           flags=interpolation | cv2.WARP_INVERSE_MAP,
                           borderMode=cv2.BORDER_WRAP)
    return out


def paint_tile(tile: np.ndarray, basis_px: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """Paint a periodic tile [n2, n1] (as in :class:`TileAverage`) over an image of `shape` (bicubic, float32).

    `basis_px` is the 2x2 matrix with columns t1, t2 (px); tile sample [j, i] lands at
    (i / n1) t1 + (j / n2) t2 from the centre of pixel (0, 0), modulo the lattice.
    """
    return _paint(np.asarray(tile, dtype=np.float32), np.asarray(basis_px, dtype=float), shape, cv2.INTER_CUBIC)


# An array-periodic window may strain the lattice by at most MAX_WINDOW_STRAIN (relative change of
# the basis; 3e-3 moves a 20 px cell's samples by 0.06 px, invisible to shading); the smallest
# side whose lattice vector strains it by WINDOW_STRAIN or less is taken.
MAX_WINDOW_STRAIN = 3e-3
WINDOW_STRAIN = 1e-3


def periodic_window(basis_px: np.ndarray, min_px: int = 256, max_px: int = 1024, *,
                    strain: float = WINDOW_STRAIN, max_strain: float = MAX_WINDOW_STRAIN
                    ) -> tuple[np.ndarray, tuple[int, int]] | None:
    """A window shape (rows, cols) and a slightly strained lattice for which the window is periodic.

    Finds integer lattice vectors close to (W, 0) and (0, H) for W, H in [min_px, max_px] (the
    smallest side within `strain`, else the least strain) and returns the basis B' with
    ``B' K = diag(W, H)`` (K: those integer vectors). Painting a tile with B' over a rows x cols
    = H x W image gives an exactly array-periodic image of the same texture, which array-periodic
    solvers (shape from shading, the tables' fast path) take as a tile. None when no window
    strains the lattice by less than `max_strain`.

    Parameters
    ----------
    basis_px : ndarray [2, 2]
        Columns t1, t2 in px.
    min_px, max_px : int
        Range of the window's sides.
    strain, max_strain : float
        Relative strain of the basis accepted for the smallest side, and at most.
    """
    basis = np.asarray(basis_px, dtype=float)
    inv = np.linalg.inv(basis)
    sides = np.arange(min_px, max_px + 1)
    columns = []
    for axis in (0, 1):
        target = np.zeros((2, sides.size))
        target[axis] = sides
        k = np.rint(inv @ target)  # integer lattice coordinates nearest to (side, 0) or (0, side)
        miss = np.linalg.norm(basis @ k - target, axis=0)
        miss[~np.any(k != 0, axis=0)] = np.inf
        close = np.flatnonzero(miss <= strain * sides)
        best = int(close[0]) if close.size else int(np.argmin(miss / sides))  # else the least strain
        columns.append((int(sides[best]), k[:, best]))
    (w, k_a), (h, k_b) = columns
    kmat = np.column_stack([k_a, k_b])
    if abs(np.linalg.det(kmat)) < 0.5:
        return None
    strained = np.diag([float(w), float(h)]) @ np.linalg.inv(kmat)
    if np.linalg.norm(strained - basis) > max_strain * np.linalg.norm(basis):
        return None
    return strained, (h, w)


# The smallest periodic windows of a lattice, for solvers that need its cell only (the light
# search, the weave starts of shape from shading): sides in this range (px), the lattice
# strained by at most this much (a third of it preferred).
SMALL_WINDOW_PX = (64, 256)
SMALL_WINDOW_STRAIN = 0.02


def small_periodic_window(basis_px: np.ndarray) -> tuple[np.ndarray, tuple[int, int]] | None:
    """:func:`periodic_window` with sides in ``SMALL_WINDOW_PX``, the lattice strained by at
    most ``SMALL_WINDOW_STRAIN`` (the smallest side within a third of it, else the least
    strain); None when there is none."""
    return periodic_window(basis_px, min_px=SMALL_WINDOW_PX[0], max_px=SMALL_WINDOW_PX[1],
                           strain=SMALL_WINDOW_STRAIN / 3.0, max_strain=SMALL_WINDOW_STRAIN)


def average_tile(image: np.ndarray, lattice: Lattice, *, combine: str = "median",
                 samples_per_px: float = 1.0, flatten_sigma_px: float | str | None = "auto"
                 ) -> TileAverage:
    """Average all repetitions of the lattice cell into one clean, exactly periodic image.

    Parameters
    ----------
    image : numpy.ndarray
        2-D grey image (any range).
    lattice : Lattice
        A periodic lattice (from `find_lattice`).
    combine : {"median", "trimmed_mean", "mean"}
        Robust combination across repetitions ("trimmed_mean" drops 20 % at each end).
    samples_per_px : float
        Tile samples per px along t1 and t2 (n_i = ceil(|t_i| x samples_per_px), at least 2).
    flatten_sigma_px : float, "auto" or None
        Illumination flattening before averaging (`flatten_illumination`, mode "auto"): "auto"
        uses sigma = 2 x the longest lattice vector; None disables it.

    Returns
    -------
    TileAverage
        Maps are float32 (the photographs are 8-bit; float32 halves memory and time).

    Notes
    -----
    Each repetition is resampled bicubically onto the tile grid. When at least 16 repetitions
    (and half of all) lie wholly inside the image, only those are combined; otherwise cells cut
    by the border contribute the samples they have. At most MAX_REPETITIONS (256) repetitions,
    drawn with a fixed seed, are combined: `n_repetitions` says how many were,
    `n_repetitions_available` how many there were. The illumination flattening is applied to
    the samples (same result as flattening the image first, without a full-size copy).
    """
    img = _as_grey_array(image)
    if not isinstance(lattice, Lattice) or not lattice.periodic:
        reason = getattr(lattice, "reason", "")
        raise ValueError(f"average_tile needs a periodic lattice ({reason or 'none given'})")
    if combine not in ("median", "trimmed_mean", "mean"):
        raise ValueError(f"combine must be median, trimmed_mean or mean, got {combine!r}")
    if not (math.isfinite(samples_per_px) and 0.05 <= samples_per_px <= 16):
        raise ValueError(f"samples_per_px must be within 0.05 ... 16, got {samples_per_px}")
    basis = lattice.basis_px.astype(float)
    if abs(np.linalg.det(basis)) < 1.0:
        raise ValueError("average_tile: the lattice cell is smaller than one pixel")
    longest = float(np.linalg.norm(basis, axis=0).max())
    if flatten_sigma_px == "auto":
        sigma = 2.0 * longest
    elif flatten_sigma_px is None:
        sigma = None
    else:
        sigma = float(flatten_sigma_px)
        if not (math.isfinite(sigma) and sigma > 0):
            raise ValueError(f"flatten_sigma_px must be positive, got {flatten_sigma_px}")
    src = img if img.dtype == np.float32 else img.astype(np.float32)

    n1 = max(2, math.ceil(np.linalg.norm(basis[:, 0]) * samples_per_px))
    n2 = max(2, math.ceil(np.linalg.norm(basis[:, 1]) * samples_per_px))
    m, k, available = _choose_cells(img.shape, basis)
    if m.size == 0:
        raise ValueError("average_tile: no lattice cell overlaps the image")
    # sample positions [rep, j, i]: (m + i / n1) t1 + (k + j / n2) t2
    f1 = m[:, None, None] + (np.arange(n1) / n1)[None, None, :]
    f2 = k[:, None, None] + (np.arange(n2) / n2)[None, :, None]
    x = f1 * basis[0, 0] + f2 * basis[0, 1]
    y = f1 * basis[1, 0] + f2 * basis[1, 1]
    values = _remap_points(src, x, y, cv2.INTER_CUBIC, cv2.BORDER_CONSTANT, float("nan"))
    if sigma is not None:
        values = _flatten_samples(img, values, x, y, sigma)
    blocks = values.reshape(len(m), n2 * n1).T  # [tile sample, repetition]
    centre, spread, count = _robust_rows(blocks, combine)
    if np.isnan(centre).any():  # a tile sample no repetition reached (tiny images only)
        centre = np.where(np.isnan(centre), np.nanmean(centre), centre)
        spread = np.where(np.isnan(spread), np.nanmean(spread), spread)
    tile = centre.reshape(n2, n1)
    spread_tile = np.nan_to_num(spread.reshape(n2, n1), nan=0.0)
    synthetic = _paint(tile, basis, img.shape, cv2.INTER_CUBIC)
    spread_map = _paint(spread_tile, basis, img.shape, cv2.INTER_LINEAR)
    np.maximum(spread_map, 0.0, out=spread_map)
    return TileAverage(
        synthetic=synthetic,
        spread=spread_map,
        tile=tile,
        n_repetitions=int(len(m)),
        counts=count.reshape(n2, n1),
        t1_px=basis[:, 0].copy(),
        t2_px=basis[:, 1].copy(),
        combine=combine,
        n_repetitions_available=available,
    )


def _flatten_samples(img: np.ndarray, values: np.ndarray, x: np.ndarray, y: np.ndarray,
                     sigma_px: float) -> np.ndarray:
    """`flatten_illumination` (mode "auto") applied to samples of the image at (x, y) only.

    The light (a heavy blur) is smooth, so it is kept on a reduced grid and sampled bilinearly;
    this avoids two full-size passes over a large photo.
    """
    small, fx, fy = _light_field(img, sigma_px)
    level = float(small.mean())
    positive = float(img.min()) >= 0 and float(small.min()) > 0.02 * max(float(small.max()),
                                                                         1e-300)
    light = _remap_points(small, (x + 0.5) / fx - 0.5, (y + 0.5) / fy - 0.5, cv2.INTER_LINEAR,
                          cv2.BORDER_REPLICATE)
    if positive:
        return values / light * level
    return values - light + level
