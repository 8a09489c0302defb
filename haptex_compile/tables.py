"""Lookup tables of (a40, a320) over the surface, per direction and speed.

For a constant velocity the frame analysis (:mod:`haptex_compile.frame_analysis`) is a filter
along straight lines, so the tables evaluate it line by line instead of frame by frame:

1. for a direction d, sample the surface on parallel lines along d (one pixel apart, through
   :func:`~haptex_compile.surface.sample_height`, long enough to hold the analysis margins at
   the fastest speed) and Fourier transform each line once;
2. for each speed s, weight the line spectra by ``W_c(s k)`` (temporal frequency = speed x
   spatial frequency), invert to the analytic signal, square its envelope, and average it with
   the frame window along the line and with the footprint Gaussian across the lines (lines
   ``across_spacing_mm`` apart);
3. read the mean channel power at the table nodes (linear interpolation in the line grid; the
   field is smooth there on the scale of the footprint), take square roots and decompose.

Direction d and d + 180° give the same amplitudes (the envelope power is unchanged when time
reverses), so directions are stored over [0, 180).
"""
from __future__ import annotations

from concurrent.futures import Executor, ThreadPoolExecutor
from dataclasses import dataclass
from typing import Callable

import numpy as np
import scipy.fft
from scipy import ndimage

from haptex_compile.colours import TwoColourModel
from haptex_compile.frame_analysis import (
    FOOTPRINT_TRUNCATION,
    AnalysisSettings,
    across_spacing_mm,
    footprint_offsets,
    frame_window,
    resolution_weight,
)
from haptex_compile.line_analysis import direction_powers, line_margin_mm
from haptex_compile.line_sampling import LineSampler, fast_len, supports
from haptex_compile.surface import Surface, sample_height

PREFETCH_HALF_NODES = 20_000  # half-spacing nodes read in advance up to this many (see build_tables)
MAX_TABLE_NODES = 4_000_000  # per direction and speed; beyond this the grid is refused


@dataclass(frozen=True)
class TableGrid:
    """Node positions: node [j, i] at ``origin_mm + i * basis_mm[0] + j * basis_mm[1]``."""

    origin_mm: np.ndarray
    basis_mm: np.ndarray  # rows g_i, g_j (mm)
    shape: tuple[int, int]  # (n_j, n_i)
    periodic: bool

    def nodes_mm(self) -> np.ndarray:
        nj, ni = self.shape
        j, i = np.meshgrid(np.arange(nj), np.arange(ni), indexing="ij")
        return self.origin_mm + i[..., None] * self.basis_mm[0] + j[..., None] * self.basis_mm[1]

    @property
    def spacing_mm(self) -> float:
        # inf for absurd pixels (1e308 um), which the tables' size checks then refuse, rather
        # than numpy's overflow warning on stderr beside the one-line error
        with np.errstate(over="ignore"):
            return float(np.sqrt(abs(np.linalg.det(self.basis_mm))))


@dataclass(frozen=True)
class Tables:
    """Amplitude tables [n_direction, n_speed, n_j, n_i] in µm, plus what produced them."""

    a40: np.ndarray
    a320: np.ndarray
    intensity_p: np.ndarray
    intensity_np: np.ndarray
    out_of_gamut: np.ndarray
    direction_deg: np.ndarray
    speed_mm_s: np.ndarray
    grid: TableGrid


def table_grid(surface: Surface, spacing_mm: float) -> TableGrid:
    """Grid for a surface: one lattice cell of a periodic surface (wrapping), else the whole map."""
    if not (np.isfinite(spacing_mm) and spacing_mm > 0):
        raise ValueError("grid spacing must be finite and positive")
    if surface.periodic:
        lat = surface.lattice_mm()
        n_i = max(2, int(np.ceil(np.linalg.norm(lat[0]) / spacing_mm)))
        n_j = max(2, int(np.ceil(np.linalg.norm(lat[1]) / spacing_mm)))
        basis = np.array([lat[0] / n_i, lat[1] / n_j])
        origin = surface.origin_px() * surface.pixel_size_mm
        grid = TableGrid(origin, basis, (n_j, n_i), True)
    else:
        w, h = surface.extent_mm
        n_i = max(2, int(round(w / spacing_mm)) + 1)
        n_j = max(2, int(round(h / spacing_mm)) + 1)
        basis = np.array([[w / (n_i - 1), 0.0], [0.0, h / (n_j - 1)]])
        grid = TableGrid(np.zeros(2), basis, (n_j, n_i), False)
    if grid.shape[0] * grid.shape[1] > MAX_TABLE_NODES:
        raise ValueError(f"table grid of {grid.shape[1]} x {grid.shape[0]} nodes is too large; use a coarser spacing")
    return grid


def _direction_powers(
    surface: Surface,
    model: TwoColourModel,
    settings: AnalysisSettings,
    nodes: np.ndarray,
    direction_deg: float,
    speeds: np.ndarray,
    split_speeds: bool = True,
) -> np.ndarray:
    """Mean channel powers [n_speed, 2, n_nodes] for one direction.

    Lines must reach beyond the nodes by the distance covered in the window plus the filter's
    settling time, which grows with speed; slow and fast speeds therefore get their own lines
    (split at the geometric middle of the range) so slow speeds do not pay for long lines.
    """
    speeds = np.asarray(speeds, dtype=float)
    if split_speeds and speeds.size > 1 and speeds.max() / speeds.min() > 3.0:
        split = np.sqrt(speeds.min() * speeds.max())
        slow = speeds <= split
        out = np.empty((speeds.size, 2, nodes.shape[0]))
        out[slow] = _direction_powers(surface, model, settings, nodes, direction_deg, speeds[slow], False)
        out[~slow] = _direction_powers(surface, model, settings, nodes, direction_deg, speeds[~slow], False)
        return out
    px = surface.pixel_size_mm
    sigma = settings.footprint_sigma_mm
    d = np.deg2rad(direction_deg)
    e = np.array([np.cos(d), np.sin(d)])
    nrm = np.array([-np.sin(d), np.cos(d)])
    a_nodes = nodes @ e
    b_nodes = nodes @ nrm
    s_max = float(speeds.max())
    # Whole-line filtering only needs the lines to be long enough that the circular transform's
    # wrap-around stays out of reach of the window (the same margin as the fast path's lines).
    margin = line_margin_mm(s_max, settings, px)
    a0 = a_nodes.min() - margin
    n_a = fast_len(int(np.ceil((a_nodes.max() + margin - a0) / px)) + 1, real=True)
    b0 = b_nodes.min() - FOOTPRINT_TRUNCATION * sigma - 2 * px
    n_b = int(np.ceil((b_nodes.max() + FOOTPRINT_TRUNCATION * sigma + 2 * px - b0) / px)) + 1
    a = a0 + np.arange(n_a) * px
    b = b0 + np.arange(n_b) * px
    # The same continuous surface as the reference renderer samples.
    heights = sample_height(surface, a[None, :] * e[0] + b[:, None] * nrm[0], a[None, :] * e[1] + b[:, None] * nrm[1])
    # Make each line's ends meet (remove the end-to-end ramp: a linear trend is invisible to the
    # weighting, which vanishes like f^2 at 0 Hz) so the circular transform sees no step.
    ramp = np.linspace(0.0, 1.0, n_a)
    heights -= heights[:, :1] + (heights[:, -1:] - heights[:, :1]) * ramp
    # Single precision from here on: table errors are percents, float32 rounding is 1e-7.
    spectrum = scipy.fft.rfft(heights.astype(np.float32), axis=1, workers=2)
    k = scipy.fft.rfftfreq(n_a, d=px)  # cycles/mm
    length_mm = n_a * px
    out = np.empty((speeds.size, 2, nodes.shape[0]))
    for si, s in enumerate(speeds):
        f = s * k
        n_keep = int(np.searchsorted(f, model.band.high_stop_hz))
        step = max(1, int(round(across_spacing_mm(sigma, px, s, model) / px)))
        lines = spectrum[::step, :n_keep]
        spacing_b = step * px
        # |z|^2 of an analytic signal with bins 0..n_keep only holds frequencies within
        # +-n_keep bins, so 2 n_keep + 1 samples per line represent it exactly.
        n_out = scipy.fft.next_fast_len(2 * n_keep + 1)
        da = length_mm / n_out
        # frame window along the line (in space: time offset x speed), normalised, circular
        offsets = (np.arange(n_out) - n_out // 2) * da / s
        kern = frame_window(offsets, settings.frame_ms, sigma / s)
        kern = np.roll(kern / kern.sum(), -(n_out // 2))
        kern_f = scipy.fft.rfft(kern.astype(np.float32))
        bw, gw = footprint_offsets(sigma, spacing_b)
        wp, wnp = model.weights(f[:n_keep])
        res = resolution_weight(k[:n_keep], px)
        wp, wnp = wp * res, wnp * res
        # After the window the power is smooth along the line on the scale of the window and
        # the footprint: keep a quarter of that as the along-line step before going across.
        smooth_mm = max(sigma, s * settings.frame_ms / 1000.0)
        q = max(1, int(smooth_mm / 4.0 / da))
        coords = np.vstack([(b_nodes - b0) / spacing_b, (a_nodes - a0) / (da * q)])
        for ci, w in enumerate((wp, wnp)):
            z_spec = np.zeros((lines.shape[0], n_out), dtype=np.complex64)
            z_spec[:, :n_keep] = lines * (2.0 * w * n_out / n_a).astype(np.float32)
            z_spec[:, 0] = 0.0
            z = scipy.fft.ifft(z_spec, axis=1, workers=2)
            power = z.real**2 + z.imag**2
            power = scipy.fft.irfft(scipy.fft.rfft(power, axis=1, workers=2) * kern_f, n=n_out, axis=1, workers=2)[:, ::q]
            if gw.size > 1:
                power = ndimage.convolve1d(power, gw, axis=0, mode="nearest")
            out[si, ci] = ndimage.map_coordinates(power, coords, order=1, mode="nearest")
    return np.maximum(out, 0.0)


def halve_grid(grid: TableGrid) -> TableGrid:
    """The grid at half the spacing whose every other node (``[::2, ::2]``) is `grid`."""
    nj, ni = grid.shape
    shape = (2 * nj, 2 * ni) if grid.periodic else (2 * nj - 1, 2 * ni - 1)
    return TableGrid(grid.origin_mm, grid.basis_mm / 2.0, shape, grid.periodic)


def line_sampler(surface: Surface) -> LineSampler:
    """The surface's line sampler, kept on the surface so refinement rounds reuse it."""
    sampler = surface.__dict__.get("_line_sampler")
    if sampler is None:
        sampler = LineSampler(surface)
        object.__setattr__(surface, "_line_sampler", sampler)
    return sampler


def build_tables(
    surface: Surface,
    model: TwoColourModel,
    settings: AnalysisSettings,
    directions_deg: np.ndarray,
    speeds_mm_s: np.ndarray,
    grid: TableGrid,
    workers: int = 2,
    cache: dict | None = None,
    speed_midpoints: bool = False,
    pool: Executor | None = None,
    after_submit: Callable[[], None] | None = None,
) -> Tables:
    """Compute the amplitude tables on `grid` for every direction and speed node.

    Parameters
    ----------
    surface, model, settings
        What is felt and how.
    directions_deg : array_like
        Direction nodes in [0, 180), strictly increasing.
    speeds_mm_s : array_like
        Speed nodes (mm/s), positive, strictly increasing.
    grid : TableGrid
    workers : int
        Directions computed in parallel threads (without `pool`).
    cache : dict, optional
        Channel powers already computed, keyed by grid, direction and speed; filled in, so
        refining the nodes (or halving the grid, see :func:`halve_grid`) only computes new ones.
    speed_midpoints : bool
        Also store cubic midpoints between the speed nodes (:func:`speed_midpoints_of`).
    pool : Executor, optional
        Runs the directions instead of a pool of `workers` threads of its own.
    after_submit : callable, optional
        Called once every direction is queued on `pool`: work it queues there runs behind the
        directions (and on a core the last of them leaves idle).
    """
    directions = np.asarray(directions_deg, dtype=float)
    speeds = np.asarray(speeds_mm_s, dtype=float)
    if directions.ndim != 1 or directions.size == 0 or np.any(np.diff(directions) <= 0) or directions[0] < 0 or directions[-1] >= 180:
        raise ValueError("directions must be strictly increasing in [0, 180)")
    if speeds.ndim != 1 or speeds.size == 0 or np.any(np.diff(speeds) <= 0) or speeds[0] <= 0 or not np.all(np.isfinite(speeds)):
        raise ValueError("speeds must be positive, finite and strictly increasing")
    cache = {} if cache is None else cache
    # Fast path (sheared lines, 2-D spectral averaging) where the surface's extension is periodic
    # on its coefficient array and the footprint is not a point; rotated lines otherwise.
    sampler = line_sampler(surface) if settings.footprint_sigma_mm > 0 and supports(surface) else None
    # The fast path's cost is in the averaged fields, not in reading nodes from them: on small
    # grids (periodic cells, where a finer spacing is often needed) it reads the nodes of the
    # half-spacing grid too, so refining the spacing later costs nothing.
    half = halve_grid(grid) if sampler is not None and 4 * grid.shape[0] * grid.shape[1] <= PREFETCH_HALF_NODES else None

    def key(g: TableGrid, d: float, s: float) -> tuple:
        return (g.shape, round(g.spacing_mm, 12), round(float(d), 9), round(float(s), 9))

    def lookup(d: float, s: float) -> np.ndarray | None:
        hit = cache.get(key(grid, d, s))
        if hit is None and half is not None:
            finer = cache.get(key(half, d, s))
            hit = None if finer is None else finer[:, ::2, ::2]
        return hit

    stored = stored_speeds(speeds, speed_midpoints)
    weights = _midpoint_weights(speeds) if stored.size > speeds.size else None
    shape = (directions.size, stored.size) + grid.shape
    ip, inp, a40, a320, gamut = (np.empty(shape, np.float32) for _ in range(5))

    def one(a: int, d: float) -> None:
        """Direction `a`: its missing powers, then its whole slice of the tables (assembled here,
        on the pool's threads, rather than for all directions after them)."""
        missing = np.array([s for s in speeds if lookup(d, s) is None])
        if missing.size:
            target = half if half is not None else grid
            nodes = target.nodes_mm().reshape(-1, 2)
            if sampler is not None:
                powers = direction_powers(sampler, model, settings, nodes, d, missing)
            else:
                powers = _direction_powers(surface, model, settings, nodes, d, missing)
            for s, pw in zip(missing, powers):
                cache[key(target, d, s)] = pw.reshape((2,) + target.shape).astype(np.float32, copy=False)
        computed = (1, speeds.size) + grid.shape
        p, q = np.empty(computed, np.float32), np.empty(computed, np.float32)
        for b, s in enumerate(speeds):
            power = lookup(d, s)
            np.sqrt(power[0], out=p[0, b])
            np.sqrt(power[1], out=q[0, b])
        if weights is not None:
            p, q = _insert_midpoints(weights, p), _insert_midpoints(weights, q)
        ip[a], inp[a] = p[0], q[0]
        # elementwise, so a direction at a time gives the same values as the whole tables
        dec = model.decompose(ip[a], inp[a], threads=1)
        a40[a], a320[a], gamut[a] = dec.a40, dec.a320, dec.out_of_gamut

    if pool is None:
        with ThreadPoolExecutor(max_workers=max(1, workers)) as own:
            list(own.map(one, range(directions.size), directions))
    else:
        futures = [pool.submit(one, a, d) for a, d in enumerate(directions)]
        if after_submit is not None:
            after_submit()
        for f in futures:
            f.result()
    return Tables(a40, a320, ip, inp, gamut, directions, stored, grid)


def stored_speeds(speeds_mm_s: np.ndarray, speed_midpoints: bool) -> np.ndarray:
    """The speed nodes :func:`build_tables` stores for these computed ones: with
    `speed_midpoints` (and at least four nodes) the geometric midpoints are inserted."""
    speeds = np.asarray(speeds_mm_s, dtype=float)
    if not speed_midpoints or speeds.size < 4:
        return speeds
    new_speeds = np.empty(2 * speeds.size - 1)
    new_speeds[0::2], new_speeds[1::2] = speeds, np.sqrt(speeds[:-1] * speeds[1:])
    return new_speeds


def not_a_knot_weights(x: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Weights [n_t, n_x] giving the not-a-knot cubic spline through nodes `x` at points `t`.

    ``not_a_knot_weights(x, t) @ y`` is ``scipy.interpolate.CubicSpline(x, y)(t)`` (to
    rounding): the same slope equations, solved for all data at once. Here so the compiler does
    not import ``scipy.interpolate`` (a fifth of a second at start-up) for one small matrix.

    Parameters
    ----------
    x : ndarray [n_x]
        Strictly increasing nodes, at least four.
    t : ndarray [n_t]
        Points within ``[x[0], x[-1]]`` (the end cubics extend beyond).
    """
    x = np.asarray(x, dtype=float)
    t = np.asarray(t, dtype=float)
    n = x.size
    if n < 4:
        raise ValueError("a not-a-knot spline here needs at least four nodes")
    dx = np.diff(x)
    # chord slopes as a matrix on the data: slope_i = (y[i+1] - y[i]) / dx[i]
    chord = np.zeros((n - 1, n))
    rows = np.arange(n - 1)
    chord[rows, rows], chord[rows, rows + 1] = -1.0 / dx, 1.0 / dx
    # node slopes m solve A m = rhs @ y: continuous curvature inside, not-a-knot at both ends
    a, rhs = np.zeros((n, n)), np.zeros((n, n))
    i = np.arange(1, n - 1)
    a[i, i - 1], a[i, i], a[i, i + 1] = dx[i], 2.0 * (dx[i - 1] + dx[i]), dx[i - 1]
    rhs[i] = 3.0 * (dx[i, None] * chord[i - 1] + dx[i - 1, None] * chord[i])
    d = x[2] - x[0]
    a[0, 0], a[0, 1] = dx[1], d
    rhs[0] = ((dx[0] + 2.0 * d) * dx[1] * chord[0] + dx[0] ** 2 * chord[1]) / d
    d = x[-1] - x[-3]
    a[-1, -1], a[-1, -2] = dx[-2], d
    rhs[-1] = (dx[-1] ** 2 * chord[-2] + (2.0 * d + dx[-1]) * dx[-2] * chord[-1]) / d
    slopes = np.linalg.solve(a, rhs)  # [node, datum]
    # cubic Hermite form on each interval
    k = np.clip(np.searchsorted(x, t, side="right") - 1, 0, n - 2)
    h = dx[k]
    s = (t - x[k]) / h
    s2, s3 = s * s, s * s * s
    w = ((s3 - 2.0 * s2 + s) * h)[:, None] * slopes[k] + ((s3 - s2) * h)[:, None] * slopes[k + 1]
    at = np.arange(t.size)
    w[at, k] += 2.0 * s3 - 3.0 * s2 + 1.0
    w[at, k + 1] += 3.0 * s2 - 2.0 * s3
    return w


def speed_midpoints_of(speeds_mm_s: np.ndarray, *intensities: np.ndarray) -> tuple[np.ndarray, ...]:
    """Speed nodes and intensity tables [n_dir, n_speed, ...] with a node inserted between each
    pair of speed nodes, by cubic interpolation.

    The player interpolates linearly in log-speed. Channel intensities vary smoothly with speed
    (not with direction, where a long window's strip swings across the texture), so a cubic
    spline in log-speed through the computed nodes, sampled at their geometric midpoints,
    halves the playback error between speed nodes for the cost of storage only. Needs at least
    four speed nodes; fewer are returned unchanged.
    """
    speeds = np.asarray(speeds_mm_s, dtype=float)
    if speeds.size < 4:
        return (speeds, *intensities)
    weights = _midpoint_weights(speeds)
    return (stored_speeds(speeds, True), *(_insert_midpoints(weights, x) for x in intensities))


def _midpoint_weights(speeds: np.ndarray) -> np.ndarray:
    """[n_mid, n_speed]: the spline in log-speed is linear in the data, so its values at the
    geometric midpoints are a fixed matrix times the node values."""
    log_s = np.log(speeds)
    return not_a_knot_weights(log_s, np.log(stored_speeds(speeds, True)[1::2]))


def _insert_midpoints(weights: np.ndarray, x: np.ndarray) -> np.ndarray:
    """Intensities [n_dir, n_speed, ...] with the spline's values (:func:`_midpoint_weights`)
    inserted between speed nodes, every direction in one batched product."""
    n_dir, n_speed = x.shape[:2]
    out = np.empty((n_dir, 2 * n_speed - 1) + x.shape[2:], x.dtype)
    out[:, 0::2] = x
    # einsum, not BLAS: this runs on the tables' threads, beside which BLAS's own would spin
    mid = np.einsum("ms,dsk->dmk", weights.astype(x.dtype), x.reshape(n_dir, n_speed, -1))
    # intensities are non-negative: a cubic undershoot is clamped
    np.maximum(mid, 0, out=mid)
    out[:, 1::2] = mid.reshape((n_dir, n_speed - 1) + x.shape[2:])
    return out


def mean_tactile(height_um: np.ndarray, pixel_size_um: float, *, periodic: bool = False,
                 directions_deg=(0.0, 45.0, 90.0, 135.0), speeds_mm_s=(20.0, 80.0, 160.0),
                 footprint_sigma_mm: float = 0.25) -> dict[str, float]:
    """Mean a40 and a320 (µm) of a height map over a few directions and speeds, and the mean
    channel intensities behind them (threshold units).

    A compact tactile summary for comparing two height maps of the same thing (e.g. recovered
    and true heights in the shading benchmark): what users feel is the tables. The
    intensities are the table entries mapped back through the two-colour model,
    ``I_c = (sum_k W_c(f_k)**n a_k**n)**(1/n)``. They are well conditioned when one colour
    dominates, unlike that colour's partner: when a40 carries nearly all the Pacinian
    intensity, a 1 % change of that intensity moves a320 by far more than 1 %.

    Returns
    -------
    dict
        ``a40``, ``a320`` (µm), ``i_p``, ``i_np`` (threshold units).
    """
    from haptex_compile.surface import periodic_surface_from_tile

    h = np.asarray(height_um, dtype=float)
    surface = periodic_surface_from_tile(h, pixel_size_um) if periodic else Surface(h, pixel_size_um, False)
    model = TwoColourModel()
    tables = build_tables(surface, model, AnalysisSettings(footprint_sigma_mm=footprint_sigma_mm),
                          np.asarray(directions_deg), np.asarray(speeds_mm_s),
                          table_grid(surface, max(0.25, surface.pixel_size_mm)))
    i_p, i_np = model.intensities(tables.a40, tables.a320)
    return dict(a40=float(tables.a40.mean()), a320=float(tables.a320.mean()),
                i_p=float(i_p.mean()), i_np=float(i_np.mean()))
