"""What one contactor feels during one frame: the shared definition of the analysis.

For a contactor moving along a path p(t) over the surface, with frame centre t_c:

1. the height under it, P(t) = h(p(t)), is weighted per channel by ``W_c(f)``
   (:meth:`haptex_compile.colours.TwoColourModel.weights`) as a filter over the whole signal,
   not only the frame (the analysis looks along the surface beyond the frame, which removes the
   paper's window leakage: a pure tone gives a constant envelope);
2. the squared envelope ``|z_c(t)|^2`` of the weighted analytic signal is averaged with the
   *frame window* ``w(t - t_c)``: a Hann window of full width 2 x frame (consecutive frames'
   windows add up to one, so every instant counts once), convolved with the footprint's extent
   along the motion (Gaussian of ``sigma / speed`` in time);
3. the footprint's extent across the motion is a Gaussian average over parallel paths offset by
   ``b`` (:func:`footprint_offsets`);
4. the channel intensity is the square root of that mean power, and
   :meth:`~haptex_compile.colours.TwoColourModel.decompose` turns (I_p, I_np) into (a40, a320).

The reference renderer evaluates this on finite stretches (``margin_ms`` beyond the window on
each side, mean and linear trend removed, flat for half the margin and tapered in the outer half); the tables evaluate the same filter
along whole lines. Both sample heights through :func:`haptex_compile.surface.sample_height`.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from haptex_compile.colours import TwoColourModel

ANALYSIS_RATE_HZ = 2048.0  # output rate of the envelope; Nyquist 1024 Hz > band top (800 Hz)
DEFAULT_FOOTPRINT_SIGMA_MM = 0.25
RESOLVED_PASS = 0.6  # resolution weight: 1 up to this fraction of the map's Nyquist frequency,
RESOLVED_STOP = 0.9  # and 0 from this one on (see resolution_weight)
FOOTPRINT_TRUNCATION = 4.0  # footprint Gaussians are cut at 4 sigma (tails of e^-8: a power spike beside the
# footprint, e.g. at a step, must not change the result the way a 3-sigma cut lets it)


@dataclass(frozen=True)
class AnalysisSettings:
    """Parameters of the frame analysis (stored in every asset).

    Attributes
    ----------
    frame_ms : float
        Frame duration (25 ms as in the paper).
    footprint_sigma_mm : float
        Standard deviation of the Gaussian skin footprint of a contactor; 0 is the paper's point.
    margin_ms : float
        How far the reference renderer looks beyond the frame window on each side.
    """

    frame_ms: float = 25.0
    footprint_sigma_mm: float = DEFAULT_FOOTPRINT_SIGMA_MM
    margin_ms: float = 300.0

    def __post_init__(self) -> None:
        if not (1.0 <= self.frame_ms <= 1000.0):
            raise ValueError("frame_ms must be between 1 and 1000")
        if not (0.0 <= self.footprint_sigma_mm <= 5.0):
            raise ValueError("footprint sigma must be between 0 and 5 mm")

    def window_half_s(self, speed_mm_s: float) -> float:
        """Half support of the frame window (s) including the along-motion footprint."""
        sigma_t = self.footprint_sigma_mm / speed_mm_s if speed_mm_s > 0 else 0.0
        return self.frame_ms / 1000.0 + FOOTPRINT_TRUNCATION * sigma_t


# Window tables are sampled at 1/200 of the shorter of the frame and the footprint's passage;
# a passage shorter than this fraction of the frame is taken as a point (the Gaussian's whole
# support within one step of the frame's table: it changes the window by about (sigma/T)^2,
# below 1e-5). A footprint of 0.1 um at 2000 mm/s asked for 2e8 samples (24 GB, killed).
POINT_PASSAGE_FRACTION = 1.0 / (200.0 * FOOTPRINT_TRUNCATION)
# The other way round, a passage longer than the frame by that factor makes the window the
# footprint's Gaussian times the Hann's area (the frame a point in it; the same order of error).
# Between the two the direct convolution's cost grows as (sigma / T)^2: 0.33 s at 30 x the
# frame, hours at 1e4 x (a 0.25 mm footprint at 0.001 mm/s); above DIRECT_CONVOLUTION_MAX
# products it goes through FFTs (the same values to rounding; default scenes stay direct).
DIRECT_CONVOLUTION_MAX = 10**9


@lru_cache(maxsize=64)
def _window_table(frame_ms: float, sigma_t_s: float) -> tuple[np.ndarray, np.ndarray]:
    t_frame = frame_ms / 1000.0
    if sigma_t_s < POINT_PASSAGE_FRACTION * t_frame:
        sigma_t_s = 0.0
    half = t_frame + FOOTPRINT_TRUNCATION * sigma_t_s
    if sigma_t_s * POINT_PASSAGE_FRACTION > t_frame:
        step = sigma_t_s / 200.0
        n = int(np.ceil(half / step))
        t = np.arange(-n, n + 1) * step
        # (normalised over the truncated support, as the convolution's g / g.sum() is)
        mass = math.erf(FOOTPRINT_TRUNCATION / math.sqrt(2.0))
        gauss = np.exp(-0.5 * (t / sigma_t_s) ** 2) * (t_frame / (sigma_t_s * math.sqrt(2.0 * math.pi) * mass))
        return t, np.where(np.abs(t) <= half, gauss, 0.0)
    step = (min(t_frame, sigma_t_s) if sigma_t_s > 0 else t_frame) / 200.0
    n = int(np.ceil(half / step))
    t = np.arange(-n, n + 1) * step
    hann = np.where(np.abs(t) < t_frame, np.cos(np.pi * t / (2 * t_frame)) ** 2, 0.0)
    if sigma_t_s > 0:
        m = int(np.ceil(FOOTPRINT_TRUNCATION * sigma_t_s / step))
        g = np.exp(-0.5 * (np.arange(-m, m + 1) * step / sigma_t_s) ** 2)
        if hann.size * g.size <= DIRECT_CONVOLUTION_MAX:
            hann = np.convolve(hann, g / g.sum(), mode="same")
        else:
            from scipy.signal import fftconvolve

            hann = fftconvolve(hann, g / g.sum(), mode="same")
    return t, hann


def frame_window(offset_s: np.ndarray, frame_ms: float, sigma_t_s: float = 0.0) -> np.ndarray:
    """Frame window at time offsets from the frame centre (unnormalised, peak about 1).

    Hann of full width ``2 * frame_ms`` convolved with a Gaussian of ``sigma_t_s`` (the
    footprint along the motion, in time), truncated at 4 sigma.
    """
    t, w = _window_table(float(frame_ms), float(sigma_t_s))
    return np.interp(np.asarray(offset_s, dtype=float), t, w, left=0.0, right=0.0)


def footprint_offsets(sigma_mm: float, spacing_mm: float) -> tuple[np.ndarray, np.ndarray]:
    """Across-motion offsets (mm) and normalised Gaussian weights of the footprint.

    Offsets are multiples of `spacing_mm` within 4 sigma; sigma 0 gives the single point 0.
    """
    if sigma_mm <= 0:
        return np.zeros(1), np.ones(1)
    m = int(np.floor(FOOTPRINT_TRUNCATION * sigma_mm / spacing_mm))
    b = np.arange(-m, m + 1) * spacing_mm
    g = np.exp(-0.5 * (b / sigma_mm) ** 2)
    return b, g / g.sum()


def resolution_weight(k_cyc_per_mm: np.ndarray, pixel_size_mm: float) -> np.ndarray:
    """Weight of spatial frequencies the height map resolves: 1 up to 0.6 of its Nyquist
    frequency, raised-cosine to 0 at 0.9 of it.

    Bilinear sampling adds content above the map's Nyquist frequency (its corners) that is not
    in the surface; cutting it keeps fast strokes from feeling the pixel grid, and the tables
    and the reference renderer see the same band however their samples fall.
    """
    k_nyq = 0.5 / pixel_size_mm
    t = np.clip((np.abs(np.asarray(k_cyc_per_mm, dtype=float)) / k_nyq - RESOLVED_PASS) / (RESOLVED_STOP - RESOLVED_PASS), 0.0, 1.0)
    return 0.5 * (1.0 + np.cos(np.pi * t))


def across_spacing_mm(sigma_mm: float, pixel_size_mm: float, speed_mm_s: float, model: TwoColourModel) -> float:
    """Spacing of the parallel paths that sample the footprint across the motion.

    The weighted signal varies across the motion on the scale of its shortest wavelength,
    ``speed / band_top``; paths are spaced by half of that (at least one pixel, at most sigma/3),
    rounded down to a whole number of pixels so the tables can use a subset of their lines.
    """
    if sigma_mm <= 0:
        return pixel_size_mm
    want = min(sigma_mm / 3.0, speed_mm_s / (2.0 * model.band.high_stop_hz))
    return pixel_size_mm * max(1, int(np.floor(want / pixel_size_mm)))


def _cached_weights(model: TwoColourModel, n_fine: int, fine_dt_s: float) -> tuple[np.ndarray, np.ndarray]:
    """Channel weights on a stretch's frequency grid, kept on the model (frames repeat grids)."""
    cache = model.__dict__.setdefault("_stretch_weights", {})
    key = (n_fine, round(fine_dt_s, 15))
    if key not in cache:
        cache[key] = model.weights(np.fft.rfftfreq(n_fine, d=fine_dt_s))
        if len(cache) > 256:
            cache.pop(next(iter(cache)))
    wp, wnp = cache[key]
    return wp, wnp


def stretch_channel_power(
    heights_um: np.ndarray,
    fine_dt_s: float,
    decimation: int,
    window_weights: np.ndarray,
    model: TwoColourModel,
    speed_mm_s: float,
    pixel_size_mm: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Mean channel power of finite stretches (reference renderer's inner step).

    Parameters
    ----------
    heights_um : ndarray [..., n_fine]
        Heights sampled every `fine_dt_s`; the stretch is centred on the frame centre.
    fine_dt_s : float
        Fine sample spacing; ``decimation * fine_dt_s`` is the envelope's sample spacing.
    decimation : int
        Ratio of fine samples to envelope samples; ``n_fine`` must be a multiple of it.
    window_weights : ndarray [n_fine // decimation]
        Frame-window weights at the envelope's sample times (zero in the margins).
    model : TwoColourModel
    speed_mm_s, pixel_size_mm : float
        Speed of the path and pixel size of the map, for :func:`resolution_weight`.

    Returns
    -------
    (power_p, power_np) : ndarrays [...]
        Window-weighted mean of the squared envelopes (dimensionless, in threshold units squared).
    """
    h = np.asarray(heights_um, dtype=float)
    n_fine = h.shape[-1]
    if n_fine % decimation:
        raise ValueError("stretch length must be a multiple of the decimation")
    n_out = n_fine // decimation
    # Taper: flat where the window is, raised cosine in the margins (so no edge step reaches it).
    support = np.nonzero(window_weights > 0)[0]
    j = np.arange(n_fine) / decimation
    # The taper stays flat for half of each margin beyond the window, so the weighting filter's
    # response inside the window hardly reaches the tapered part.
    lo = 0.5 * (support[0] - 0.5)
    hi = support[-1] + 0.5 + 0.5 * (n_out - 0.5 - support[-1] - 0.5)
    taper = np.ones(n_fine)
    left = j < lo
    right = j > hi
    taper[left] = 0.5 * (1 - np.cos(np.pi * (j[left] + 0.5) / (lo + 0.5)))
    taper[right] = 0.5 * (1 - np.cos(np.pi * (n_out - 0.5 - j[right]) / (n_out - 0.5 - hi)))
    # Remove the mean and linear trend (fitted with smooth cos^4 weights, so in-band tones project
    # almost nothing onto them): slow trends carry no vibration, and a trend left in would be
    # tapered in the margins, which the analytic signal would carry into the window.
    t = np.arange(n_fine) - (n_fine - 1) / 2.0
    fit_w = np.cos(np.pi * t / n_fine) ** 4
    mean_h = (h * fit_w).sum(axis=-1, keepdims=True) / fit_w.sum()
    tc = t - (t * fit_w).sum() / fit_w.sum()
    slope = (h * fit_w * tc).sum(axis=-1, keepdims=True) / (fit_w * tc * tc).sum()
    x = (h - mean_h - slope * tc) * taper
    spec = np.fft.rfft(x, axis=-1)
    freqs = np.fft.rfftfreq(n_fine, d=fine_dt_s)[: n_out // 2]
    spec = spec[..., : n_out // 2]
    wp, wnp = (w[: n_out // 2] for w in _cached_weights(model, n_fine, fine_dt_s))
    res = resolution_weight(freqs / speed_mm_s, pixel_size_mm)
    wp, wnp = wp * res, wnp * res
    scale = 2.0 / decimation  # analytic signal (x2 for positive bins), n_fine -> n_out inverse FFT
    full = np.zeros(h.shape[:-1] + (n_out,), dtype=complex)
    wsum = window_weights.sum()
    powers = []
    for w in (wp, wnp):
        full[..., : n_out // 2] = spec * (scale * w)
        z = np.fft.ifft(full, axis=-1)
        powers.append((np.abs(z) ** 2 * window_weights).sum(axis=-1) / wsum)
    return powers[0], powers[1]
