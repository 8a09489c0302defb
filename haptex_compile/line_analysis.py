"""Mean channel power at table nodes from sheared lines, for all speeds of one direction.

This is the tables' fast path (:mod:`haptex_compile.tables` falls back to rotated lines for
surfaces whose lattice is not the array and for the point model). For one direction and speed
the frame analysis (:mod:`haptex_compile.frame_analysis`) is: filter every line with the channel
weights ``W_c(speed x k)`` into an analytic signal z, square its envelope, and average ``|z|^2``
with the frame window along the line and the footprint Gaussian across the lines. Here:

1. lines come from :class:`haptex_compile.line_sampling.LineSampler` (sheared, exact spline
   values) and are Fourier transformed once per group of speeds that need similar line lengths
   (the filter must settle within the line, which takes longer at speed); their ends are
   joined by removing the end-to-end ramp, on the transform;
2. per speed and channel, ``|z|^2`` is formed from the weighted spectrum on just enough samples
   that its aliases miss the low frequencies kept in step 3 (``n_keep + K`` instead of
   ``2 n_keep``);
3. the averaging kernel is applied in the 2-D Fourier domain of the (line, column) index space,
   where the physical kernel (window along, Gaussian across) appears sheared; it is smooth on
   the footprint's scale, so only frequencies where it exceeds ``KERNEL_CUT`` are kept and
   transformed back onto a small grid (twice oversampled);
4. the nodes read that grid with cubic B-spline interpolation (one sparse matrix per group of
   speeds reads all its grids).

The kernel is the continuous one (Hann of full width 2 x frame convolved with the footprint
Gaussian along, the footprint Gaussian across), of which the reference renderer's sampled
weights are a quadrature.
"""
from __future__ import annotations

import numpy as np
import scipy.fft
from scipy import sparse

from haptex_compile.colours import TwoColourModel
from haptex_compile.frame_analysis import FOOTPRINT_TRUNCATION, RESOLVED_STOP, AnalysisSettings, resolution_weight
from haptex_compile.line_sampling import LineSampler, fast_len
from haptex_compile.surface import _bspline_weights, count_text, refuse_out_of_scale

KERNEL_CUT = 1e-4  # relative kernel magnitude below which frequencies are dropped
LINE_SETTLE_MS = 100.0  # line length beyond the window, in time at the speed, for the filter to settle
GROUP_LENGTH_RATIO = 1.3  # speeds share a line transform while their lines differ by less than this
# The largest array one direction's analysis may hold (bytes): its lines, or a group's footprint
# grids. Surfaces whose pixels are far finer than the scene needs (lines of millions of samples)
# or whose extent is far larger (grids of millions of footprint cells) would otherwise exhaust
# the machine's memory (a direction's peak is a few times its largest array, and two run at
# once); they are refused with the sizes instead. The largest seen on the bench's surfaces and
# the real photos: 83 MB (lines of a 1024 px surface of 10 um pixels) and 8 MB (grids, as float64).
MAX_ARRAY_BYTES = 2 ** 30


def kernel_cut_cyc_per_mm(sigma_mm: float) -> float:
    """Spatial frequency where the footprint Gaussian's transform falls to ``KERNEL_CUT``."""
    return float(np.sqrt(np.log(1.0 / KERNEL_CUT) / (2.0 * np.pi**2)) / sigma_mm)


def along_kernel_ft(xi_cyc_mm: np.ndarray, speed_mm_s: float, settings: AnalysisSettings) -> np.ndarray:
    """Transform of the frame window along the motion, in space (unit at 0).

    The window is a Hann of full width 2 x frame in time (transform
    ``sinc(x) + (sinc(x - 1) + sinc(x + 1)) / 2`` with ``x = 2 T f``) convolved with the
    footprint Gaussian; at speed s the temporal frequency is ``f = s xi``.
    """
    x = 2.0 * settings.frame_ms / 1000.0 * speed_mm_s * np.asarray(xi_cyc_mm)
    hann = np.sinc(x) + 0.5 * (np.sinc(x - 1.0) + np.sinc(x + 1.0))
    return hann * across_kernel_ft(xi_cyc_mm, settings.footprint_sigma_mm)


def across_kernel_ft(xi_cyc_mm: np.ndarray, sigma_mm: float) -> np.ndarray:
    """Transform of the footprint Gaussian (unit at 0)."""
    return np.exp(-2.0 * np.pi**2 * sigma_mm**2 * np.asarray(xi_cyc_mm) ** 2)


def line_margin_mm(speed_mm_s: float, settings: AnalysisSettings, pixel_size_mm: float) -> float:
    """How far lines must reach beyond the nodes: window, filter settling and footprint."""
    return speed_mm_s * (settings.frame_ms + LINE_SETTLE_MS) / 1000.0 + FOOTPRINT_TRUNCATION * settings.footprint_sigma_mm + 2 * pixel_size_mm


def _speed_groups(speeds: np.ndarray, settings: AnalysisSettings, span_mm: float, px: float) -> list[np.ndarray]:
    """Indices of speeds grouped (fastest first) so lines within a group differ little in length."""
    order = np.argsort(speeds)[::-1]
    groups: list[list[int]] = []
    for i in order:
        need = span_mm + 2 * line_margin_mm(speeds[i], settings, px)
        if groups and groups[-1][1] <= GROUP_LENGTH_RATIO * need:
            groups[-1][0].append(int(i))
        else:
            groups.append([[int(i)], need])
    return [np.array(g[0]) for g in groups]


def _bspline_taps(x: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Indices and weights [n_points, 4] of a wrapping cubic B-spline on `n` knots at points `x`
    (grid units): taps floor(x) - 1 .. floor(x) + 2."""
    o = np.floor(x)
    return (o.astype(np.int64)[:, None] - 1 + np.arange(4)) % n, np.stack(_bspline_weights(x - o), axis=1)


def _bspline_matrix(y: np.ndarray | tuple[np.ndarray, np.ndarray], x: np.ndarray, ny: int, nx: int) -> sparse.csr_matrix:
    """Sparse matrix reading a wrapping cubic B-spline coefficient grid ``[ny, nx]`` (flattened)
    at points (y, x) in grid units: what ``ndimage.map_coordinates(c, [y, x], order=3,
    mode="grid-wrap", prefilter=False)`` computes, shared by many grids. `y` may be given as
    its taps (:func:`_bspline_taps`), when many matrices share it."""
    iy, wy = _bspline_taps(y, ny) if isinstance(y, np.ndarray) else y
    ix, wx = _bspline_taps(x, nx)
    cols = (iy[:, :, None] * nx + ix[:, None, :]).reshape(-1, 16)
    vals = (wy[:, :, None] * wx[:, None, :]).reshape(-1, 16)
    # 16 entries per row, in order (a repeated column, on grids under 4 wide, sums as it should)
    n = ix.shape[0]
    indptr = np.arange(0, 16 * n + 1, 16)
    return sparse.csr_matrix((vals.ravel(), cols.ravel(), indptr), shape=(n, ny * nx))


def _check_size(n_bytes: int, sampler: LineSampler, what: str, advice: str) -> None:
    """Raise :class:`InputError` when an array of `n_bytes` would exceed ``MAX_ARRAY_BYTES``."""
    refuse_out_of_scale(sampler.surface, n_bytes, MAX_ARRAY_BYTES, "the tables", what, "per direction", advice)


def direction_powers(
    sampler: LineSampler,
    model: TwoColourModel,
    settings: AnalysisSettings,
    nodes_mm: np.ndarray,
    direction_deg: float,
    speeds_mm_s: np.ndarray,
    workers: int = 1,
) -> np.ndarray:
    """Mean channel powers [n_speed, 2, n_nodes] at the nodes for one direction.

    Parameters
    ----------
    sampler : LineSampler
        The surface's line sampler.
    model, settings
        Channel weights and analysis parameters; the footprint sigma must be positive.
    nodes_mm : ndarray [n, 2]
        Node positions (u, v) in mm.
    direction_deg : float
    speeds_mm_s : ndarray
        Speeds (mm/s), any order.
    workers : int
        Threads per FFT.
    """
    sigma = settings.footprint_sigma_mm
    if sigma <= 0:
        raise ValueError("the sheared-line analysis needs a footprint (sigma > 0)")
    speeds = np.asarray(speeds_mm_s, dtype=float)
    px = sampler.surface.pixel_size_mm
    u, v = nodes_mm[:, 0], nodes_mm[:, 1]
    xi_cut = kernel_cut_cyc_per_mm(sigma)
    pad = FOOTPRINT_TRUNCATION * sigma + 2 * px  # the footprint's support (the cropped kernel's ringing is below 1e-4)
    frame, n_rows, n_cols = sampler.frame(direction_deg, u, v, line_margin_mm(speeds.max(), settings, px), pad)
    _check_size(4 * n_rows * n_cols, sampler, f"its lines ({count_text(n_rows)} x {count_text(n_cols)} samples)",
                "give it coarser pixels (resample it) or check its pixel size")
    lines = sampler.sample(frame, n_rows, n_cols)
    jf, kf = frame.index_coords(u, v)
    da = frame.along_mm
    k_nyq_map = 0.5 / px
    centre = 0.5 * (kf.min() + kf.max())
    span = (kf.max() - kf.min()) * da
    out = np.empty((speeds.size, 2, nodes_mm.shape[0]), np.float32)
    taps_j: dict[int, tuple[np.ndarray, np.ndarray]] = {}  # the nodes' row taps, per grid height
    groups = []
    for group in _speed_groups(speeds, settings, span, px):
        need = span + 2 * line_margin_mm(speeds[group].max(), settings, px)
        n_g = min(n_cols, scipy.fft.next_fast_len(int(np.ceil(need / da)) + 2, real=True))
        k = scipy.fft.rfftfreq(n_g, d=da)
        n_res = int(np.searchsorted(k, RESOLVED_STOP * k_nyq_map)) + 1
        keeps = [min(int(np.searchsorted(speeds[si] * k, model.band.high_stop_hz)), n_res, k.size) for si in group]
        groups.append((group, n_g, k, keeps))
    # channel weights of every speed from one call (the threshold curves' interpolation costs per call)
    wp_all, wnp_all = model.weights(np.concatenate([speeds[si] * k[:n_keep] for group, _, k, keeps in groups
                                                    for si, n_keep in zip(group, keeps)]))
    offset = 0
    for group, n_g, k, keeps in groups:
        c_lo = int(np.clip(np.floor(centre - n_g / 2), 0, n_cols - n_g))
        seg = lines[:, c_lo:c_lo + n_g]
        length_mm = n_g * da
        n_max = max(keeps)
        # Join each line's ends (a linear trend is invisible to the weighting, which vanishes at
        # 0 Hz) so the circular transform sees no step: the end-to-end ramp is removed from the
        # transform, on the kept bins only (its constant part reaches the 0 Hz bin alone, which
        # is dropped).
        ramp_ft = scipy.fft.rfft(np.linspace(0.0, 1.0, n_g, dtype=np.float32))[:n_max]
        # the kept bins in an array of their own, which every pass reads (the whole transform,
        # several times larger, is freed at once)
        spectrum = np.ascontiguousarray(scipy.fft.rfft(seg, axis=1, workers=workers)[:, :n_max])
        spectrum -= (seg[:, -1:] - seg[:, :1]) * ramp_ft
        res = resolution_weight(k[:n_max], px)
        kk = int(np.ceil(xi_cut * length_mm))
        kj = int(np.ceil(xi_cut * n_rows * px * (abs(frame.sin_d) + frame.cos_d)))
        kj = min(kj, (n_rows - 1) // 2)
        gj = fast_len(2 * (2 * kj + 1))
        gk = fast_len(2 * (2 * kk + 1), real=True)
        # Checked before the kernels are made: they take about a quarter of the grids' values
        # each, and several are alive at once (8 bytes a value: the nodes' sparse read below
        # makes a float64 copy of the grids).
        _check_size(8 * len(group) * 2 * gj * gk, sampler, f"its footprint grids ({len(group)} x 2 x {gj} x {gk})",
                    "crop it or check its pixel size; they grow with the fastest speed and as 1 / the footprint's"
                    f" width squared: a wider footprint (the scene's render.footprint_sigma_mm, {sigma:g} mm; 0 is"
                    " the point model) or slower speeds shrink them")
        mj = np.concatenate([np.arange(kj + 1), np.arange(-kj, 0)])
        xi_a = np.arange(kk + 1) / length_mm
        xi_b = (mj[:, None] / n_rows - xi_a[None, :] * px * frame.sin_d) / (px * frame.cos_d)
        across = across_kernel_ft(xi_b, sigma)
        rows_dst = np.concatenate([np.arange(kj + 1), gj - np.arange(kj, 0, -1)])
        # Dividing by the discrete B-spline's transform makes the inverse transform return the
        # grid's cubic B-spline coefficients directly (the prefilter, done where it is free).
        prefilter = 1.0 / (((4.0 + 2.0 * np.cos(2 * np.pi * mj / gj)) / 6.0)[:, None]
                           * ((4.0 + 2.0 * np.cos(2 * np.pi * np.arange(kk + 1) / gk)) / 6.0)[None, :])
        base = (across * prefilter * (gj * gk / n_rows)).astype(np.float32)
        bounds = offset + np.cumsum([0] + keeps)
        offset = int(bounds[-1])
        coeffs = np.empty((len(group), 2, gj, gk), dtype=np.float32)
        n_outs = [scipy.fft.next_fast_len(n_keep + kk + 2) for n_keep in keeps]
        zbuf = np.empty(n_rows * max(n_outs), dtype=np.complex64)  # reused by every pass (transformed in place)
        for gi, (si, n_keep, n_out) in enumerate(zip(group, keeps, n_outs)):
            s = speeds[si]
            kernel = along_kernel_ft(xi_a, s, settings).astype(np.float32)[None, :] * base / np.float32(n_out)
            lo, hi = bounds[gi], bounds[gi + 1]
            for ci, w in enumerate((wp_all[lo:hi], wnp_all[lo:hi])):
                z = zbuf[:n_rows * n_out].reshape(n_rows, n_out)
                np.multiply(spectrum[:, :n_keep], (2.0 * w * res[:n_keep] * n_out / n_g).astype(np.float32), out=z[:, :n_keep])
                z[:, n_keep:] = 0.0
                z[:, 0] = 0.0
                z = scipy.fft.ifft(z, axis=1, workers=workers, overwrite_x=True)
                power = np.square(z.real)
                power += np.square(z.imag)
                low = scipy.fft.rfft(power, axis=1, workers=workers)[:, :kk + 1]
                if low.shape[1] < kk + 1:
                    # Pixels coarser than the footprint: the kernel reaches beyond the bins the
                    # power has, where its spectrum is zero (it holds no frequency above
                    # n_keep - 2, below n_out / 2).
                    low = np.pad(low, ((0, 0), (0, kk + 1 - low.shape[1])))
                low = scipy.fft.fft(low, axis=0, workers=workers)[mj]
                low *= kernel
                grid = np.zeros((gj, gk // 2 + 1), dtype=np.complex64)
                grid[rows_dst, :kk + 1] = low
                coeffs[gi, ci] = scipy.fft.irfft2(grid, s=(gj, gk))
        # every grid of the group read at the nodes at once (cubic B-spline, wrapping)
        if gj not in taps_j:
            taps_j[gj] = _bspline_taps(jf * gj / n_rows, gj)
        interp = _bspline_matrix(taps_j[gj], (kf - c_lo) * gk / n_g, gj, gk)
        values = interp @ coeffs.reshape(len(group) * 2, gj * gk).T  # [n_nodes, group x channel]
        out[group] = values.T.reshape(len(group), 2, -1)
    return np.maximum(out, 0.0)
