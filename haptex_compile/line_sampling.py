"""Heights along parallel lines of one direction, sampled fast by shearing the spline surface.

The tables analyse the surface along parallel lines (:mod:`haptex_compile.tables`). Sampling
rotated lines through a 2-D cubic B-spline costs 16 taps per point. Sheared lines cost 4: in a
working frame where the direction is within 45 degrees of the x axis (swap u and v otherwise),
line ``j`` is the set of points ``(x, j + x tan d)`` (pixels) at columns ``x = x0 + k h`` with
``h`` half a pixel: whole-pixel columns would fold the spline's spectral images (near 1 / pixel)
back into the band the tables keep, while the continuous surface that the reference renderer
samples finely keeps them out of it. At a column, every line needs the spline at the same
fractional row offset, so the surface is first evaluated at the column positions along x (an
exact 3- or 4-tap filter of the coefficients) and then each column is resampled along y with
its own 4 B-spline weights. The result is exactly :func:`haptex_compile.surface.sample_height`
at those points (float32).

This covers surfaces whose continuous extension is periodic on the coefficient array: mirrored
non-periodic maps (period ``2 (n - 1)``) and periodic maps whose lattice is the array itself.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.fft
from numpy.lib.stride_tricks import sliding_window_view

from haptex_compile.surface import Surface, _bspline_weights, _wraps, spline_coefficients


SAMPLE_BLOCK_COLUMNS = 256  # columns sampled at a time (see LineSampler.sample)


def supports(surface: Surface) -> bool:
    """Whether the surface's extension is periodic on its coefficient array (fast path)."""
    return (not surface.periodic) or _wraps(surface)


def periodic_coefficients(surface: Surface) -> np.ndarray:
    """Spline coefficients over one full period of the surface's extension.

    A mirrored map repeats with period ``2 (n - 1)`` samples (its coefficients are symmetric
    too, since the whole-sample symmetric extension and the filters that made them are); a
    wrapping map is its own period.
    """
    c = spline_coefficients(surface)
    if _wraps(surface):
        return c
    ny, nx = c.shape
    ext = np.concatenate([c, c[-2:0:-1]], axis=0) if ny > 2 else np.concatenate([c, c[:0:-1]], axis=0)
    return np.concatenate([ext, ext[:, -2:0:-1]], axis=1) if nx > 2 else np.concatenate([ext, ext[:, :0:-1]], axis=1)


# Longer than any array the tables' size checks let through: lengths beyond it are returned as
# they are (next_fast_len raises OverflowError past the C integers, as absurd pixel sizes ask,
# 1e-20 or 1e20 um, before those checks refuse them in one line).
FAST_LEN_MAX = 2**40


def fast_len(n: int, real: bool = False) -> int:
    """:func:`scipy.fft.next_fast_len` of `n`, or `n` itself above ``FAST_LEN_MAX``."""
    return n if n > FAST_LEN_MAX else scipy.fft.next_fast_len(n, real=real)


@dataclass(frozen=True)
class ShearFrame:
    """Geometry of sheared lines for one direction.

    Working-frame pixel coordinates are ``(x, y) = (u, v) / pixel`` or, when ``transposed``,
    ``(v, u) / pixel``. Row ``r`` of the lines is line ``j = j0 + r``; column ``k`` lies at
    ``x = x0 + k h``; the sample is the surface at ``(x, j + x tan_d)``.
    """

    transposed: bool
    tan_d: float
    cos_d: float  # cosine of the direction in the working frame (>= 0.707)
    sin_d: float
    h: float  # column step (px)
    x0: float
    j0: int
    pixel_size_mm: float

    @property
    def along_mm(self) -> float:
        """Distance along a line between adjacent columns (mm)."""
        return self.h * self.pixel_size_mm / self.cos_d

    def working_px(self, u_mm: np.ndarray, v_mm: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        x, y = (v_mm, u_mm) if self.transposed else (u_mm, v_mm)
        return np.asarray(x) / self.pixel_size_mm, np.asarray(y) / self.pixel_size_mm

    def index_coords(self, u_mm: np.ndarray, v_mm: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Fractional (row, column) of points in the line array."""
        x, y = self.working_px(u_mm, v_mm)
        return y - x * self.tan_d - self.j0, (x - self.x0) / self.h


def working_direction(direction_deg: float) -> tuple[bool, float, float]:
    """(transposed, cos, sin) of the direction in the working frame, with cos >= |sin|, cos > 0.

    Reversing a direction leaves the tables unchanged, so the sign is chosen freely.
    """
    d = np.deg2rad(direction_deg)
    c, s = float(np.cos(d)), float(np.sin(d))
    transposed = abs(s) > abs(c)
    if transposed:
        c, s = s, c
    if c < 0:
        c, s = -c, -s
    return transposed, c, s


class LineSampler:
    """Samples sheared lines of a surface; keeps the per-surface column data between calls."""

    def __init__(self, surface: Surface) -> None:
        if not supports(surface):
            raise ValueError("sheared line sampling needs a mirrored or array-periodic surface")
        self.surface = surface
        self.coefficients = periodic_coefficients(surface)
        self._columns: dict[tuple[bool, bool], np.ndarray] = {}

    def period(self, transposed: bool) -> tuple[int, int]:
        """(rows, columns) of one period in the working frame."""
        my, mx = self.coefficients.shape
        return (mx, my) if transposed else (my, mx)

    def _column_table(self, transposed: bool, half: bool) -> np.ndarray:
        """Spline values at integer (or half-integer) x, as B-spline coefficients along y.

        Returned transposed (one contiguous row per column x) and extended periodically along
        y by one period plus 3 rows, so any run of up to a period + 3 rows is a plain slice.
        """
        key = (transposed, half)
        if key not in self._columns:
            # Columns as contiguous rows from the start (transpose once, in float32).
            ct = np.ascontiguousarray((self.coefficients if transposed else self.coefficients.T), dtype=np.float32)
            if half:  # B-spline at x = m + 1/2: taps m-1..m+2 with weights 1, 23, 23, 1 (/48)
                vals = (np.roll(ct, 1, axis=0) + 23.0 * ct + 23.0 * np.roll(ct, -1, axis=0) + np.roll(ct, -2, axis=0)) / np.float32(48.0)
            else:  # at integer x: taps m-1, m, m+1 with weights 1, 4, 1 (/6)
                vals = (np.roll(ct, 1, axis=0) + 4.0 * ct + np.roll(ct, -1, axis=0)) / np.float32(6.0)
            self._columns[key] = np.concatenate([vals, vals, vals[:, :3]], axis=1)
        return self._columns[key]

    def frame(self, direction_deg: float, nodes_u_mm: np.ndarray, nodes_v_mm: np.ndarray,
              margin_mm: float, pad_mm: float) -> tuple[ShearFrame, int, int]:
        """Frame, number of rows and number of columns covering the nodes.

        Columns are centred on the nodes and reach at least `margin_mm` (along the line) beyond
        them on each side; their number is a fast FFT length. Rows reach `pad_mm` (across)
        beyond the nodes, unless that is a whole period or more, in which case the rows are
        exactly one period (the sheared array is then periodic across the lines).
        """
        transposed, c, s = working_direction(direction_deg)
        px = self.surface.pixel_size_mm
        h = 0.5  # see the module docstring: half-pixel columns keep the spline's images out of band
        probe = ShearFrame(transposed, s / c, c, s, h, 0.0, 0, px)
        x, y = probe.working_px(nodes_u_mm, nodes_v_mm)
        jf = y - x * probe.tan_d
        margin_x = margin_mm * c / px
        n_cols = fast_len(int(np.ceil((x.max() - x.min() + 2 * margin_x) / h)) + 2, real=True)
        x0 = np.floor(0.5 * (x.min() + x.max()) / h - n_cols / 2) * h
        period_rows, _ = self.period(transposed)
        pad_rows = pad_mm / (px * c)
        j0 = int(np.floor(jf.min() - pad_rows))
        n_rows = int(np.ceil(jf.max() + pad_rows)) - j0 + 1
        if n_rows >= period_rows:
            n_rows = period_rows
        return ShearFrame(transposed, s / c, c, s, h, float(x0), j0, px), n_rows, n_cols

    def sample(self, frame: ShearFrame, n_rows: int, n_cols: int) -> np.ndarray:
        """Heights (µm, float32) on the lines: array [n_rows, n_cols], row = line, column = k."""
        period_rows, period_cols = self.period(frame.transposed)
        if n_rows > period_rows:
            raise ValueError("more rows than one period")
        x = frame.x0 + np.arange(n_cols) * frame.h
        xi = np.floor(x)
        half = x - xi > 0.25
        s = frame.j0 + x * frame.tan_d  # row position of line j0 at each column
        o = np.floor(s)
        w = np.stack(_bspline_weights(s - o)).astype(np.float32)  # [4, n_cols], taps o-1..o+2
        start = (o.astype(np.int64) - 1) % period_rows
        cols = xi.astype(np.int64) % period_cols
        out = np.empty((n_rows, n_cols), dtype=np.float32)
        for is_half in (False, True):
            sel = np.nonzero(half == is_half)[0]
            windows = sliding_window_view(self._column_table(frame.transposed, is_half), n_rows + 3, axis=1)
            # a few hundred columns at a time: the gathered runs and their weighted sum stay in
            # cache until they are written, transposed, as rows
            for b0 in range(0, sel.size, SAMPLE_BLOCK_COLUMNS):
                part = sel[b0:b0 + SAMPLE_BLOCK_COLUMNS]
                blocks = windows[cols[part], start[part]]  # [n_part, n_rows + 3]
                ws = w[:, part, None]
                out[:, part] = (ws[0] * blocks[:, 0:n_rows] + ws[1] * blocks[:, 1:n_rows + 1]
                                + ws[2] * blocks[:, 2:n_rows + 2] + ws[3] * blocks[:, 3:n_rows + 3]).T
        return out
