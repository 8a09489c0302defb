"""Vibrotactile detection thresholds of the Pacinian (P) and non-Pacinian (NP I) channels.

A :class:`ThresholdCurves` holds tabulated thresholds (displacement amplitude at threshold,
µm peak) and evaluates them at any frequency by linear interpolation of dB against
log-frequency, with every corner rounded over about ``SMOOTHING_HZ`` (8 Hz: a sharp corner
would give the weighting filter a long ringing tail). Outside the tabulated range the end
segments' slopes are continued (a monotone extrapolation on each side; never NaN, never
below ``FLOOR_UM``);
non-positive frequencies get an infinite threshold, so they weigh nothing.

The built-in curves (:func:`idealised_thresholds`) are *constructed*, not measured: straight
lines after the shapes of Gescheider et al. 2002 and Bolanowski et al. 1988 (see
``data/thresholds_idealised.csv``). Users load their own with
:func:`haptex_compile.io_thresholds.read_thresholds_csv`.
"""
from __future__ import annotations

from dataclasses import dataclass
from importlib import resources

import numpy as np

SMOOTHING_HZ = 8.0  # width (Hz) over which each corner of a threshold curve is rounded
# Evaluated thresholds never fall below this (µm): a steep end segment of a user's table,
# continued far outside it, underflowed to 0 and made 0 / 0 weights outside the band. Within
# the band, :class:`haptex_compile.colours.TwoColourModel` refuses curves below
# ``PLAUSIBLE_MIN_UM`` instead (1e-6 um, a picometre: no skin feels that).
FLOOR_UM = 1e-12
PLAUSIBLE_MIN_UM = 1e-6
RAMP_CHUNK = 1024  # frequencies whose corner ramps are evaluated together


def _norm_cdf(r: np.ndarray) -> np.ndarray:
    """Standard normal CDF (Abramowitz & Stegun 7.1.26 erf, |error| < 1.5e-7); numpy only."""
    z = np.abs(r) / np.sqrt(2.0)
    t = 1.0 / (1.0 + 0.3275911 * z)
    poly = t * (0.254829592 + t * (-0.284496736 + t * (1.421413741 + t * (-1.453152027 + t * 1.061405429))))
    erf = 1.0 - poly * np.exp(-z * z)
    return 0.5 * (1.0 + np.sign(r) * erf)


IDEALISED_PROVENANCE = (
    "idealised (constructed, not measured) after Gescheider et al. 2002 / Bolanowski et al. 1988: "
    "P -20 dB re 1 um at 250 Hz, +12 dB/oct below, +10 dB/oct above; NP +8 dB flat to 40 Hz, +6 dB/oct above"
)


@dataclass(frozen=True)
class ThresholdCurves:
    """Tabulated thresholds of the two channels.

    Attributes
    ----------
    frequency_hz : ndarray
        Strictly increasing, positive frequencies of the table.
    p_um, np_um : ndarray
        Pacinian and non-Pacinian thresholds at those frequencies (µm, peak amplitude).
    provenance : str
        Where the numbers come from (stored in every asset).
    """

    frequency_hz: np.ndarray
    p_um: np.ndarray
    np_um: np.ndarray
    provenance: str

    def __post_init__(self) -> None:
        f = np.asarray(self.frequency_hz, dtype=float)
        for name, values in (("threshold_p_um", self.p_um), ("threshold_np_um", self.np_um)):
            v = np.asarray(values, dtype=float)
            if v.shape != f.shape:
                raise ValueError(f"{name} has {v.size} values for {f.size} frequencies")
            if not np.all(np.isfinite(v)) or np.any(v <= 0):
                raise ValueError(f"{name} must be finite and positive")
        if f.ndim != 1 or f.size < 2:
            raise ValueError("threshold table needs at least two frequencies")
        if not np.all(np.isfinite(f)) or f[0] <= 0 or np.any(np.diff(f) <= 0):
            raise ValueError("threshold frequencies must be positive and strictly increasing")

    def _interp_db(self, freq_hz: np.ndarray, table_um: np.ndarray) -> np.ndarray:
        f = np.asarray(freq_hz, dtype=float)
        x_nodes = np.log2(np.asarray(self.frequency_hz, dtype=float))
        y = 20.0 * np.log10(np.asarray(table_um, dtype=float))
        positive = (f > 0) & np.isfinite(f)  # +inf (and NaN) weigh nothing; inf - inf would give NaN
        x = np.log2(np.where(positive, f, 1.0))
        slopes = np.diff(y) / np.diff(x_nodes)
        # Piecewise linear in (log2 f, dB) with the end slopes continued, written as a line plus
        # ramps at the inner nodes; each ramp is rounded by a Gaussian of SMOOTHING_HZ (in
        # octaves at that node) so the weighting filters have short impulse responses.
        db = y[0] + slopes[0] * (x - x_nodes[0])
        jumps = np.diff(slopes)
        inner = x_nodes[1:-1][jumps != 0.0]
        jumps = jumps[jumps != 0.0]
        if inner.size:
            sigma = np.clip(SMOOTHING_HZ / (2.0**inner * np.log(2.0)), 0.005, 0.3)
            xs = x.reshape(-1)
            ramps = np.empty(xs.size)
            # a chunk of frequencies at a time: the [frequency, corner] arrays stay in cache
            for lo in range(0, xs.size, RAMP_CHUNK):
                r = (xs[lo:lo + RAMP_CHUNK, None] - inner) / sigma  # [n, nodes]
                # A rounded ramp r Phi(r) + phi(r); beyond 9 sigma it is the bare ramp to double precision.
                ramp = np.maximum(r, 0.0)
                near = np.abs(r) < 9.0
                rn = r[near]
                ramp[near] = rn * _norm_cdf(rn) + np.exp(-0.5 * rn * rn) / np.sqrt(2 * np.pi)
                # einsum, not a BLAS product: BLAS would wake its own threads for this (thousands
                # of frequencies x tens of corners), which then spin beside the callers' threads
                ramps[lo:lo + RAMP_CHUNK] = np.einsum("ij,j->i", ramp, jumps * sigma)
            db = db + ramps.reshape(x.shape)
        with np.errstate(over="ignore"):
            out = np.maximum(np.power(10.0, db / 20.0), FLOOR_UM)
        return np.where(positive, out, np.inf)

    def p(self, freq_hz: np.ndarray | float) -> np.ndarray:
        """Pacinian threshold T_p(f) in µm."""
        return self._interp_db(freq_hz, self.p_um)

    def np_(self, freq_hz: np.ndarray | float) -> np.ndarray:
        """Non-Pacinian threshold T_np(f) in µm."""
        return self._interp_db(freq_hz, self.np_um)

    def best_frequency_p_hz(self) -> float:
        """Frequency of the lowest Pacinian threshold (on a fine grid over the table's range)."""
        f = np.geomspace(self.frequency_hz[0], self.frequency_hz[-1], 4001)
        return float(f[np.argmin(self.p(f))])


def parse_thresholds_csv(text: str, provenance: str) -> ThresholdCurves:
    """Parse CSV text with columns ``frequency_hz,threshold_p_um,threshold_np_um``.

    Lines starting with ``#`` are comments; the header line is required.
    """
    rows = [line.strip() for line in text.splitlines() if line.strip() and not line.lstrip().startswith("#")]
    if not rows:
        raise ValueError("threshold CSV is empty")
    header = [h.strip() for h in rows[0].split(",")]
    wanted = ["frequency_hz", "threshold_p_um", "threshold_np_um"]
    if header != wanted:
        raise ValueError(f"threshold CSV header must be {','.join(wanted)}, got {rows[0]!r}")
    try:
        data = np.array([[float(v) for v in row.split(",")] for row in rows[1:]], dtype=float)
    except ValueError as exc:
        raise ValueError(f"threshold CSV has a non-numeric value ({exc})") from None
    if data.ndim != 2 or data.shape[1] != 3:
        raise ValueError("threshold CSV rows must have exactly three values")
    return ThresholdCurves(data[:, 0], data[:, 1], data[:, 2], provenance)


def idealised_thresholds() -> ThresholdCurves:
    """The built-in idealised curves (constructed from stated slopes, not measured data)."""
    text = resources.files("haptex_compile").joinpath("data/thresholds_idealised.csv").read_text()
    return parse_thresholds_csv(text, IDEALISED_PROVENANCE)
