"""The paper's literal two-colour method (Allerkamp et al. 2007, Sect. 5.4), kept as a baseline.

Per frame and contactor:

1. the height signal over the frame alone (25 ms) is multiplied by a Blackman window and
   Fourier transformed;
2. the amplitude spectrum is normalised so a sine of amplitude A whose frequency falls on a bin
   gives a peak of A there (``F = 2 |X| / sum(w)``);
3. the channel intensities are the sums over the bins f > 0 of ``F(f) / T_c(f)`` with the raw
   threshold curves (no band limits, summation exponent n = 1);
4. (a40, a320) solve ``I_p = a40 / T_p(40) + a320 / T_p(320)``,
   ``I_np = a40 / T_np(40) + a320 / T_np(320)``; negative results are clipped to 0 so they can be
   played (the paper does not say what to do with them).

This is *not* what the compiler uses: a 25 ms window has 40 Hz bins, so a 40 Hz tone is one
period long and leaks over 0-160 Hz, and the sum of bin amplitudes counts a tone's main lobe
several times. It exists to show how far the literal method is from the exact analysis
(:mod:`haptex_compile.frame_analysis`), in tests and in ``bench/bench_perception.py``.
"""
from __future__ import annotations

import numpy as np

from haptex_compile.thresholds import ThresholdCurves


def literal_matrix(thresholds: ThresholdCurves, base_frequencies_hz: tuple[float, float] = (40.0, 320.0)) -> np.ndarray:
    """The paper's 2 x 2 matrix: rows (p, np), columns (40, 320), entries 1/T_c(f_k) in 1/µm."""
    f = np.asarray(base_frequencies_hz, dtype=float)
    return np.stack([1.0 / thresholds.p(f), 1.0 / thresholds.np_(f)])


def literal_inverse_thresholds(n: int, rate_hz: float, thresholds: ThresholdCurves) -> np.ndarray:
    """1/T_p and 1/T_np (1/µm) at the FFT bins f > 0 of an n-sample frame: array [2, n // 2].

    Evaluating the curves costs far more than a frame's FFT; a renderer computes this once.
    """
    f = np.fft.rfftfreq(n, d=1.0 / rate_hz)[1:]
    return np.stack([1.0 / thresholds.p(f), 1.0 / thresholds.np_(f)])


def literal_channel_intensities(
    signal_um: np.ndarray, rate_hz: float, thresholds: ThresholdCurves, normalisation: str = "peak",
    inverse_thresholds: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """(I_p, I_np) of frames by the paper's rule: sum over bins f > 0 of F(f) / T_c(f).

    Parameters
    ----------
    signal_um : ndarray [..., n]
        Heights (µm) under the contactor during one frame, sampled at `rate_hz`
        (n = frame duration x rate, e.g. 128 samples for 25 ms at 5120 Hz).
    rate_hz : float
        Sampling rate of the signal (Hz).
    thresholds : ThresholdCurves
        Raw threshold curves T_p, T_np (µm).
    normalisation : {"peak", "sum"}
        ``"peak"`` (the paper): an on-bin sine of amplitude A gives a peak of A. ``"sum"``: the
        spectrum is further divided by the window's sum-to-peak ratio (1/0.42 for Blackman), so
        the *sum* over its bins is A (far from DC); not in the paper, it isolates the leakage
        from the normalisation in the benchmark.
    inverse_thresholds : ndarray [2, n // 2], optional
        :func:`literal_inverse_thresholds` for this n and rate, precomputed.

    Returns
    -------
    (I_p, I_np) : ndarrays [...]
        Dimensionless (multiples of threshold).
    """
    x = np.asarray(signal_um, dtype=float)
    if x.ndim < 1 or x.shape[-1] < 4:
        raise ValueError("a frame needs at least 4 samples along its last axis")
    if not (np.isfinite(rate_hz) and rate_hz > 0):
        raise ValueError(f"rate_hz must be finite and positive, got {rate_hz!r}")
    if normalisation not in ("peak", "sum"):
        raise ValueError(f"normalisation must be 'peak' or 'sum', got {normalisation!r}")
    n = x.shape[-1]
    w = np.blackman(n)
    spec = np.fft.rfft(x * w, axis=-1)
    # Peak normalisation: a sine of amplitude A on a bin gives |X| = A sum(w) / 2 there.
    amp = 2.0 * np.abs(spec) / w.sum()
    if normalisation == "sum":
        # Blackman's DFT at whole-bin offsets 0, +-1, +-2 is 0.42, -0.25, 0.04 (relative):
        # an on-bin sine's bins sum to (0.42 + 0.5 + 0.08) / 0.42 times its peak.
        amp = amp * 0.42
    inv = literal_inverse_thresholds(n, rate_hz, thresholds) if inverse_thresholds is None else inverse_thresholds
    amp = amp[..., 1:]  # bins f > 0 only (the paper drops DC)
    return amp @ inv[0], amp @ inv[1]


def literal_frame_amplitudes(
    signal_um: np.ndarray,
    rate_hz: float,
    thresholds: ThresholdCurves,
    base_frequencies_hz: tuple[float, float] = (40.0, 320.0),
    normalisation: str = "peak",
    inverse_thresholds: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """(a40, a320) in µm of frames by the paper's literal method (negative results clipped to 0).

    Parameters
    ----------
    signal_um : ndarray [..., n]
        Heights (µm) during one frame per leading index, sampled at `rate_hz`.
    rate_hz : float
        Sampling rate (Hz).
    thresholds : ThresholdCurves
        Raw threshold curves (no band, n = 1).
    base_frequencies_hz : (float, float)
        The two colours (40 and 320 Hz in the paper).
    normalisation : {"peak", "sum"}
        See :func:`literal_channel_intensities` (``"peak"`` is the paper's).
    inverse_thresholds : ndarray [2, n // 2], optional
        :func:`literal_inverse_thresholds`, precomputed (a renderer does this once).

    Returns
    -------
    (a40, a320) : ndarrays [...]
        Amplitudes (µm peak), finite and >= 0 for finite input.
    """
    ip, inp = literal_channel_intensities(signal_um, rate_hz, thresholds, normalisation, inverse_thresholds)
    minv = np.linalg.inv(literal_matrix(thresholds, base_frequencies_hz))
    a40 = minv[0, 0] * ip + minv[0, 1] * inp
    a320 = minv[1, 0] * ip + minv[1, 1] * inp
    return np.maximum(a40, 0.0), np.maximum(a320, 0.0)
