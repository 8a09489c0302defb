"""The long-wave prior of plain (non-periodic) images, informed by the image's own spectrum.

Shading sees a wave's slope along the light at first order and its slope across the light
only at second order: on an image with free edges, long waves across the light are nearly
free and the solver's flat-on-average prior (``solve_variational``'s `lowfreq_weight`) sets
them. That prior is weak beyond the image's own scale, by design (random bumps have real power
there). But the waves *along* the light are seen: their power, per radial frequency, says how
much power a surface that looks alike in all directions has at that frequency across the light.
A woven fabric has almost none below its weave's frequency, and its across-light long waves
can be held near zero; random bumps have plenty, and theirs stay as free as before.

Measured (bench/bench_shading.py's plain-image table, 256 px, light given, slants 15-60°,
against the same solver without it): the plain weave's height error 0.09-0.36 -> 0.02-0.07,
on crops of its periodic rendering (edges across its cells) 0.12-0.28 -> 0.09-0.28; random
bumps 0.24-0.35 -> 0.23-0.34 (crops 0.21-0.39 -> 0.21-0.36); sphere caps (whose shading
rejects the flat prior) and Brownian surfaces within 0.01. Lattice reliefs cropped from larger
renderings (three lattices, four lights): summed errors 2.15 -> 1.02.

A surface whose long waves run only across the light (ribs along it) would have them held as
well: the image cannot tell it from a weave.
"""
from __future__ import annotations

import numpy as np
import scipy.fft as sfft

# Powers below this fraction of the table's largest count as it, and the symbol never exceeds
# CAP times albedo² sin²θ |ω|² (100 x the flat-on-average prior's largest; float32 conditioning).
FLOOR = 1e-3
CAP = 100.0


def along_light_power(image: np.ndarray, light_vec, albedo: float, *, max_cycles: int,
                      cone_deg: float = 30.0) -> np.ndarray | None:
    """Mean squared Fourier amplitude of the height (px²) per radial frequency, from the
    image's waves that run within `cone_deg` of the light's azimuth.

    To first order a Lambertian image's wave is ``albedo (l · ω) Z(ω)`` (``l`` the light's
    image-plane components, ``ω`` the wave vector in radians per pixel, ``Z`` the height's
    wave), so along the light the height's power is the image's over ``albedo² (l · ω)²``.
    Second-order shading adds power (the squared slopes' own long waves), so the estimate
    errs high, towards a weaker prior. The window smooths the spectrum over about two waves:
    on the lowest rings, whose neighbours differ much in frequency, that mixes the slopes'
    power rather than the heights' (gentle random bumps, 128 px: 0.6-2.6 x the height's own
    power on rings 1-2, within 20 % from ring 3 on).

    Parameters
    ----------
    image : ndarray
        The plain image (invalid pixels filled, e.g. with the mean), intensities in [0, 1].
    light_vec : array_like
        Unit light vector (lx, ly, lz).
    albedo : float
        The image's albedo (intensity of a surface facing the light).
    max_cycles : int
        Highest radial frequency returned, in cycles per the image's longer side.
    cone_deg : float
        Half-angle of the cone of wave directions around the light's azimuth.

    Returns
    -------
    ndarray or None
        ``power[c]`` for ``c = 0 .. max_cycles`` cycles per longer side (Fourier amplitude of a
        wave ``a cos(ω·x)`` counted as ``a / 2`` on each of its two waves; ``power[0]`` is
        NaN), NaN where no wave of that ring lies in the cone; None for overhead light.
    """
    lx, ly = float(light_vec[0]), float(light_vec[1])
    if np.hypot(lx, ly) < 1e-3 or albedo <= 0:
        return None
    rows, cols = image.shape
    # A Hann window, so that the image's edges (not periodic) do not leak into the long waves.
    hy, hx = np.hanning(rows), np.hanning(cols)
    win_sum = float(hy.sum() * hx.sum())
    x = np.asarray(image, dtype=np.float64) * hy[:, None]
    x *= hx[None, :]
    mean = float(x.sum()) / win_sum
    x -= mean * hy[:, None] * hx[None, :]  # (image - windowed mean) x window
    side = max(rows, cols)
    # Only the rings up to max_cycles are wanted: the waves of at most max_cycles + 1/2
    # cycles per longer side along each axis. Their spectrum is the rows' transforms at those
    # columns, transformed along the columns at those rows (1 Mpx: 30 -> 9 ms against an
    # rfft2 of the whole image of which a tiny corner was kept).
    top_x = min(cols // 2, int(np.floor((max_cycles + 0.5) * cols / side)))
    top_y = min(rows // 2, int(np.floor((max_cycles + 0.5) * rows / side)))
    # Two threads where the solver's FFTs take two (smaller transforms cost more so). Imported
    # here: shading_variational imports this module.
    from haptex_compile.shading_variational import PARALLEL_FFT_MIN_PIXELS

    workers = 2 if x.size >= PARALLEL_FFT_MIN_PIXELS else 1
    cols_x = sfft.rfft(x, axis=1, workers=workers)[:, : top_x + 1]
    kept_rows = np.unique(np.r_[np.arange(top_y + 1), np.arange(rows - top_y, rows)] % rows)
    norm = np.sqrt(float(np.sum(hy * hy) * np.sum(hx * hx)) * image.size)
    spec = sfft.fft(cols_x, axis=0)[kept_rows] / norm
    ky = np.fft.fftfreq(rows, 1.0 / rows)[kept_rows][:, None]
    kx = np.arange(top_x + 1, dtype=float)[None, :]
    ring = np.rint(np.hypot(kx * side / cols, ky * side / rows)).astype(int)
    wx, wy = 2 * np.pi * kx / cols, 2 * np.pi * ky / rows
    along = lx * wx + ly * wy
    w2 = wx * wx + wy * wy
    in_cone = along * along >= (np.cos(np.deg2rad(cone_deg)) ** 2) * (lx * lx + ly * ly) * w2
    power = np.full(max_cycles + 1, np.nan)
    for c in range(1, max_cycles + 1):
        sel = (ring == c) & in_cone & (w2 > 0)
        if sel.any():
            power[c] = float(np.mean(np.abs(spec[sel]) ** 2 / (albedo * albedo * along[sel] ** 2)))
    return power


def spectral_symbol(wx: np.ndarray, wy: np.ndarray, across: np.ndarray, albedo: float, *, side_px: float,
                    data_pixels: float, power: np.ndarray, weight: float, floor: float = FLOOR,
                    cap: float = CAP) -> np.ndarray:
    """The prior's symbol on one pyramid level: ``weight albedo² sin²θ / (N a²(c))`` on the
    waves of ``1 <= c <= len(power) - 1`` cycles per data side (0 elsewhere).

    The weight of a Gaussian prior on each wave's amplitude, of variance `power`, against
    image noise of standard deviation ``sqrt(weight) albedo`` (the solver's data term is the
    unscaled squared residual); ``θ`` is the angle between the wave and the light's azimuth
    (the data fix the waves along the light), ``N`` the data region's pixel count on this
    level, so that the prior's energy scales with the level's data energy.

    Parameters
    ----------
    wx, wy : ndarray
        The level's angular frequencies (radians per pixel), broadcastable (rfft layout).
    across : ndarray
        The squared slope across the light of each wave, in the solver's central differences
        (the flat-on-average prior's factor: ``(c · sin ω)²`` with ``c`` the unit direction
        across the light, ``|sin ω|²`` for overhead light).
    albedo : float
    side_px : float
        The data region's longer side on this level, in pixels.
    data_pixels : float
        Pixels of the data region on this level.
    power : ndarray
        :func:`along_light_power`'s table (NaN entries interpolated).
    weight : float
        The noise variance over albedo².
    floor : float
        Powers below this fraction of the table's largest count as it (bounds the symbol).
    cap : float
        The symbol never exceeds ``cap albedo² sin²θ |ω|²`` (conditioning in float32).
    """
    cycles = np.hypot(wx, wy) * side_px / (2 * np.pi)
    c = np.arange(len(power))
    known = np.isfinite(power) & (c > 0)
    if not known.any():
        return np.zeros(np.broadcast_shapes(wx.shape, wy.shape))
    table = np.interp(cycles, c[known], power[known])
    table = np.maximum(table, floor * float(np.max(power[known])))
    s2 = np.sin(wx) ** 2 + np.sin(wy) ** 2
    frac = np.divide(across, s2, out=np.zeros(np.broadcast_shapes(across.shape, s2.shape)), where=s2 > 0)
    limit = cap * albedo * albedo * s2 if np.isfinite(cap) else np.inf
    sym = frac * np.minimum(weight * albedo * albedo / (data_pixels * table), limit)
    return np.where((cycles >= 0.5) & (cycles < len(power) - 0.5), sym, 0.0)
