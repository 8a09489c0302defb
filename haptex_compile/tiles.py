"""Tile averaging: one clean, exactly periodic synthetic image from all repetitions of the tile.

Given the lattice (t1, t2) of a photograph, the image is resampled (bicubic, sub-pixel) onto a
grid in fractional lattice coordinates, which turns every repetition of the tile into one block
of a rectified image; the blocks are combined robustly per tile sample (median by default, so
noise, stains and slubs are voted out), and the averaged tile is painted back over the whole
image. Slow illumination gradients are removed first (`flatten_illumination`).

Vectors are (x, y) in px; pixel (row y, column x) has its centre at (x, y). The tile origin is the
centre of pixel (0, 0), so tile sample [j, i] sits at (i / n1) t1 + (j / n2) t2 (mod the lattice).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from haptex_compile.lattice import Lattice, _as_grey_array, _gaussian_blur

__all__ = ["flatten_illumination", "TileAverage", "average_tile"]

_IQR_TO_SIGMA = 1.0 / 1.349  # inter-quartile range of a Gaussian is 1.349 sigma


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
    """

    synthetic: np.ndarray
    spread: np.ndarray
    tile: np.ndarray
    n_repetitions: int
    counts: np.ndarray
    t1_px: np.ndarray
    t2_px: np.ndarray
    combine: str

    def tile_spread(self) -> np.ndarray:
        """Median over the cell of the spread map (a single noise figure), image units."""
        return np.asarray(np.median(self.spread))


def _rectify_geometry(shape: tuple[int, int], basis: np.ndarray, n1: int, n2: int):
    """Affine map from the rectified grid (u, v) to image (x, y), and the grid's extent.

    u = n1 (f1 - m0), v = n2 (f2 - k0) with f = B^-1 p the fractional coordinates; (m0, k0)
    are the integer cell indices of the lower corner, so each (n1 x n2) block is one cell.
    """
    rows, cols = shape
    corners = np.array([[0, 0], [cols - 1, 0], [0, rows - 1], [cols - 1, rows - 1]], float).T
    frac = np.linalg.solve(basis, corners)
    m0, k0 = np.floor(frac.min(axis=1)).astype(int)
    m1, k1 = np.ceil(frac.max(axis=1)).astype(int)
    nb1, nb2 = int(m1 - m0), int(k1 - k0)
    lin = basis @ np.diag([1.0 / n1, 1.0 / n2])
    offset = basis @ np.array([m0, k0], float)
    mat = np.hstack([lin, offset[:, None]])  # (u, v, 1) -> (x, y)
    return mat, nb1, nb2, int(m0), int(k0)


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


def _paint(tile: np.ndarray, mat: np.ndarray, nb1: int, nb2: int, shape: tuple[int, int],
           interpolation: int) -> np.ndarray:
    """Paint a periodic tile over the image through the rectifying map (wrapped borders).

    The mosaic is a whole number of tiles, so wrapping at its border is the lattice's own
    periodicity: the painted image is periodic under t1, t2 everywhere."""
    mosaic = np.tile(tile.astype(np.float32), (nb2, nb1))
    rows, cols = shape
    return cv2.warpAffine(mosaic, mat, (cols, rows), flags=interpolation,
                          borderMode=cv2.BORDER_WRAP)


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
    by the border contribute the samples they have.
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
        img = flatten_illumination(img, 2.0 * longest)
    elif flatten_sigma_px is not None:
        img = flatten_illumination(img, float(flatten_sigma_px))
    img = np.ascontiguousarray(img, dtype=np.float32)

    n1 = max(2, math.ceil(np.linalg.norm(basis[:, 0]) * samples_per_px))
    n2 = max(2, math.ceil(np.linalg.norm(basis[:, 1]) * samples_per_px))
    mat, nb1, nb2, m0, k0 = _rectify_geometry(img.shape, basis, n1, n2)
    blocks = _gather_repetitions(img, basis, mat, n1, n2, nb1, nb2, m0, k0)
    complete = np.isfinite(blocks).all(axis=0)
    if complete.sum() >= max(16, 0.5 * blocks.shape[1]):
        blocks = blocks[:, complete]
    centre, spread, count = _robust_rows(blocks, combine)
    if np.isnan(centre).any():  # a tile sample no repetition reached (tiny images only)
        centre = np.where(np.isnan(centre), np.nanmean(centre), centre)
        spread = np.where(np.isnan(spread), np.nanmean(spread), spread)
    tile = centre.reshape(n2, n1)
    spread_tile = np.nan_to_num(spread.reshape(n2, n1), nan=0.0)
    synthetic = _paint(tile, mat, nb1, nb2, img.shape, cv2.INTER_CUBIC)
    spread_map = _paint(spread_tile, mat, nb1, nb2, img.shape, cv2.INTER_LINEAR)
    np.maximum(spread_map, 0.0, out=spread_map)
    return TileAverage(
        synthetic=synthetic,
        spread=spread_map,
        tile=tile,
        n_repetitions=int(blocks.shape[1]),
        counts=count.reshape(n2, n1),
        t1_px=basis[:, 0].copy(),
        t2_px=basis[:, 1].copy(),
        combine=combine,
    )


def _gather_repetitions(img: np.ndarray, basis: np.ndarray, mat: np.ndarray, n1: int, n2: int,
                        nb1: int, nb2: int, m0: int, k0: int) -> np.ndarray:
    """Resample every repetition that touches the image onto the tile grid.

    Returns [n2 * n1, n_cells] float32, NaN where a sample falls outside the image (or within
    the 2 px a bicubic needs). One warp per row of cells, restricted to the cells of that row
    that can touch the image, so an oblique lattice does not pay for its empty bounding box.
    """
    rows, cols = img.shape
    binv = np.linalg.inv(basis)
    margin = 2.0  # px of bicubic support
    box = np.array([[-margin, -margin], [cols - 1 + margin, -margin],
                    [-margin, rows - 1 + margin], [cols - 1 + margin, rows - 1 + margin]]).T
    pieces = []
    for kb in range(nb2):
        # f2 in [k, k + 1]: the f1 range where the row of cells meets the (margin-grown) image
        k = k0 + kb
        lo, hi = _f1_range_in_box(binv, box, k, k + 1.0)
        if lo is None:
            continue
        mb0 = max(0, int(math.floor(lo)) - m0)
        mb1 = min(nb1, int(math.ceil(hi)) - m0)
        if mb1 <= mb0:
            continue
        sub = mat.copy()
        # output (u, v) of this piece starts at (mb0 n1, kb n2) of the full rectified grid
        sub[:, 2] = mat[:, :2] @ np.array([mb0 * n1, kb * n2], float) + mat[:, 2]
        piece = cv2.warpAffine(img, sub, ((mb1 - mb0) * n1, n2),
                               flags=cv2.INTER_CUBIC | cv2.WARP_INVERSE_MAP,
                               borderMode=cv2.BORDER_CONSTANT, borderValue=float("nan"))
        pieces.append(piece.reshape(n2, mb1 - mb0, n1).transpose(0, 2, 1).reshape(n2 * n1, -1))
    if not pieces:
        raise ValueError("average_tile: no lattice cell overlaps the image")
    return np.concatenate(pieces, axis=1)


def _f1_range_in_box(binv: np.ndarray, box: np.ndarray, f2_lo: float, f2_hi: float):
    """Range of f1 over the intersection of the strip f2 in [f2_lo, f2_hi] with the image box.

    The image box is convex, so the extremes of f1 over the intersection lie on its vertices:
    box corners inside the strip, and the points where the box edges cross the strip lines.
    """
    frac = binv @ box  # corners in fractional coordinates (convex quadrilateral)
    order = [0, 1, 3, 2]  # walk the corners around the rectangle
    poly = frac[:, order].T
    cand = [p[0] for p in poly if f2_lo <= p[1] <= f2_hi]
    for i in range(4):
        p, q = poly[i], poly[(i + 1) % 4]
        for level in (f2_lo, f2_hi):
            if (p[1] - level) * (q[1] - level) < 0:
                w = (level - p[1]) / (q[1] - p[1])
                cand.append(p[0] + w * (q[0] - p[0]))
    if not cand:
        return None, None
    return min(cand), max(cand)
