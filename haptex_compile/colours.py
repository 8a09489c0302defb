"""Two tactile colours: reduce a vibration to amplitudes at 40 Hz and 320 Hz.

The model (paper, Sect. 5.4, made exact):

* Each channel c in {p, np} weighs a component of frequency f and amplitude A (µm) by
  ``W_c(f) = B(f) / T_c(f)`` where T_c is the channel threshold and B the *band*: a smooth
  roll-off below ``low_hz`` (10 Hz: slower undulations are felt as indentation, not vibration) and a raised-cosine taper from ``high_pass_hz`` (600 Hz) to zero at
  ``high_stop_hz`` (800 Hz), the top of what the analysis samples without aliasing.
* Within a channel, components add in power: the channel intensity of a line spectrum is
  ``I_c = sqrt(sum_f (A_f W_c(f))^2)``, which is what the time-domain analysis (RMS envelope of
  the weighted signal over the frame, :mod:`haptex_compile.frame_analysis`) measures. It does
  not depend on the analysis length, unlike the paper's sum of FFT-bin amplitudes.
* Across the two colours the measured summation exponent n applies (paper, Fig. 8): with
  ``u = a**n`` the equations ``I_c**n = u40 W_c(40)**n + u320 W_c(320)**n`` are linear in
  (u40, u320). n = 1 is the paper's linear model. A pure tone at 40 or 320 Hz comes back as itself
  for any n.
* Out of gamut (a solution with a negative component): the nearest non-negative pair in relative
  channel error is used, and the relative residual is reported per frame.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from haptex_compile.thresholds import PLAUSIBLE_MIN_UM, ThresholdCurves, idealised_thresholds

DEFAULT_SUMMATION_EXPONENT = 1.23
DECOMPOSE_CHUNK = 1 << 16  # values per pass of the decomposition: temporaries stay in cache


@dataclass(frozen=True)
class Band:
    """Band of frequencies that count as vibration (weights multiply 1/threshold)."""

    low_hz: float = 10.0
    high_pass_hz: float = 600.0
    high_stop_hz: float = 800.0

    def __post_init__(self) -> None:
        if not (0 < self.low_hz < self.high_pass_hz < self.high_stop_hz):
            raise ValueError("band must satisfy 0 < low_hz < high_pass_hz < high_stop_hz")

    def weight(self, freq_hz: np.ndarray | float) -> np.ndarray:
        """B(f) in [0, 1]: ``1 - exp(-(f/low_hz)^4)`` times the high-frequency taper.

        The low roll-off vanishes like f^4 at 0 Hz, so a linear trend gives nothing and the
        analytic filter's impulse response falls off fast (as 1/t^5): finite analysis stretches
        and whole-line filtering agree, and a slope change far from the frame does not leak in.
        It is 0.63 at ``low_hz`` and 1 - 1e-7 at twice that.
        """
        f = np.abs(np.asarray(freq_hz, dtype=float))
        with np.errstate(over="ignore"):  # (f / low)^4 = inf far above the band: the roll-off is 1 there
            low = -np.expm1(-((f / self.low_hz) ** 4))
        t = np.clip((f - self.high_pass_hz) / (self.high_stop_hz - self.high_pass_hz), 0.0, 1.0)
        high = 0.5 * (1.0 + np.cos(np.pi * t))
        return low * high


@dataclass(frozen=True)
class TwoColourModel:
    """Thresholds, band, base frequencies and summation exponent: everything the reduction needs."""

    thresholds: ThresholdCurves = field(default_factory=idealised_thresholds)
    band: Band = field(default_factory=Band)
    base_frequencies_hz: tuple[float, float] = (40.0, 320.0)
    summation_exponent: float = DEFAULT_SUMMATION_EXPONENT

    def __post_init__(self) -> None:
        f_lo, f_hi = self.base_frequencies_hz
        if not (0 < f_lo < f_hi < self.band.high_stop_hz):
            raise ValueError("base frequencies must be increasing and inside the band")
        if not (0.5 <= self.summation_exponent <= 4.0):
            raise ValueError("summation exponent must be in [0.5, 4]")
        # Extreme user thresholds (1e-300 um, 1e300 um) overflow or divide by zero here: the
        # checks below say so in one line, numpy's warnings would only add lines before it.
        with np.errstate(all="ignore"):
            m = self.matrix()
            singular = not np.all(np.isfinite(m)) or abs(np.linalg.det(m)) < 1e-12 * np.abs(m).max() ** 2
            w = self.weights(np.asarray(self.base_frequencies_hz))
        # The curves where the band weighs (from a hundredth of its low corner to its top),
        # continued from the table's ends: a threshold over the band's weight below a
        # picometre is not a skin's (tables of 1e-300 um gave inf weights, then NaN powers and
        # numpy's warnings; the band's roll-off forgives steep ends far below its low corner).
        f = np.geomspace(0.01 * self.band.low_hz, self.band.high_stop_hz, 2001)
        b = self.band.weight(f)
        for name, curve in (("T_p", self.thresholds.p), ("T_np", self.thresholds.np_)):
            t = curve(f)
            k = int(np.argmax(b / t))
            if not t[k] >= PLAUSIBLE_MIN_UM * b[k]:
                raise ValueError(f"{name} falls to {t[k]:.3g} um at {f[k]:.3g} Hz (the table continued from its"
                                 f" ends; band weight {b[k]:.2g} there), below {PLAUSIBLE_MIN_UM:g} um: not a"
                                 " skin's threshold; check the values are um, peak")
        if singular:
            raise ValueError("the 2 x 2 colour system is singular for these thresholds")
        if not (w[1][0] > w[0][0] and w[0][1] > w[1][1]):
            raise ValueError(
                "thresholds must satisfy T_np(f_low) < T_p(f_low) and T_p(f_high) < T_np(f_high)"
            )

    def weights(self, freq_hz: np.ndarray | float) -> tuple[np.ndarray, np.ndarray]:
        """Channel weights (W_p(f), W_np(f)) in 1/µm: band / threshold; 0 outside the band."""
        b = self.band.weight(freq_hz)
        return b / self.thresholds.p(freq_hz), b / self.thresholds.np_(freq_hz)

    def matrix(self) -> np.ndarray:
        """M with rows (p, np) and columns (40, 320): ``I_c^n = M[c, k] u_k``, u = a^n."""
        wp, wnp = self.weights(np.asarray(self.base_frequencies_hz, dtype=float))
        return np.stack([wp, wnp]) ** self.summation_exponent

    def intensities(self, a40: np.ndarray, a320: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Channel intensities (I_p, I_np) of amplitude pairs (µm): the inverse of :meth:`decompose`
        inside the gamut, ``I_c = (sum_k M[c, k] a_k^n)^(1/n)``."""
        n = self.summation_exponent
        a = np.stack(np.broadcast_arrays(np.asarray(a40, dtype=float), np.asarray(a320, dtype=float)))
        u = np.maximum(a, 0.0) ** n
        i = np.tensordot(self.matrix(), u, axes=1) ** (1.0 / n)
        return i[0], i[1]

    def condition_number(self) -> float:
        """2-norm condition number of :meth:`matrix`."""
        return float(np.linalg.cond(self.matrix()))

    def decompose(self, intensity_p: np.ndarray, intensity_np: np.ndarray, threads: int = 2) -> "Decomposition":
        """Amplitudes (a40, a320) in µm that give the channel intensities (dimensionless, x threshold).

        Vectorised over any shape; non-finite or negative intensities are treated as 0. Computed
        in float32 when both inputs are float32 (the tables: their values are stored as float32
        and the 2 x 2 system's condition number is far from costing the stored precision), else
        in float64; large inputs go through in chunks so the temporaries stay in cache, on
        `threads` threads (callers that run several decompositions at once pass 1).
        """
        ip, inp = np.broadcast_arrays(np.asarray(intensity_p), np.asarray(intensity_np))
        dtype = np.float32 if ip.dtype == np.float32 and inp.dtype == np.float32 else np.float64
        shape = ip.shape
        ip, inp = ip.reshape(-1), inp.reshape(-1)
        a40, a320, gamut = (np.empty(ip.size, dtype) for _ in range(3))
        m = self.matrix()

        def chunk(lo: int) -> None:
            hi = min(lo + DECOMPOSE_CHUNK, ip.size)
            a40[lo:hi], a320[lo:hi], gamut[lo:hi] = self._decompose_flat(m, ip[lo:hi].astype(dtype, copy=False),
                                                                         inp[lo:hi].astype(dtype, copy=False))

        starts = range(0, ip.size, DECOMPOSE_CHUNK)
        if threads > 1 and len(starts) >= 4:  # whole tables: numpy's power releases the GIL, two threads use both cores
            from concurrent.futures import ThreadPoolExecutor

            with ThreadPoolExecutor(max_workers=threads) as pool:
                list(pool.map(chunk, starts))
        else:
            for lo in starts:
                chunk(lo)
        return Decomposition(a40=a40.reshape(shape), a320=a320.reshape(shape), out_of_gamut=gamut.reshape(shape))

    def _decompose_flat(self, m: np.ndarray, ip: np.ndarray, inp: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        dtype = ip.dtype.type
        n = dtype(self.summation_exponent)
        b = np.empty((2, ip.size), ip.dtype)
        for row, x in zip(b, (ip, inp)):
            np.maximum(np.where(np.isfinite(x), x, 0), 0, out=row)
            np.power(row, n, out=row)
        # The 2 x 2 solve written out: a BLAS call would wake BLAS's own threads, which spin
        # beside the tables' threads that call this a direction at a time.
        mi = np.linalg.inv(m).astype(ip.dtype)
        u = np.empty_like(b)
        for row, (c0, c1) in zip(u, mi):
            np.multiply(b[0], c0, out=row)
            row += c1 * b[1]
        gamut = np.zeros(ip.size, ip.dtype)
        # Outside the gamut (a negative component; all-zero intensities give u = 0, inside):
        # the nearest non-negative pair on either axis, in relative channel error.
        out = np.flatnonzero((u[0] < 0) | (u[1] < 0))
        if out.size:
            bo = b[:, out].astype(float)
            scale = bo + 1e-12 * bo.max(axis=0) + 1e-300
            best_u = np.zeros((2, out.size))
            best_err = np.full(out.size, np.inf)
            smin = scale.min(axis=0)
            for k in range(2):
                # model per unit u_k relative to the intensities, r = m_k / scale, held as
                # rn = r * smin (no overflow when one intensity is almost zero)
                rn = m[:, k:k + 1] * (smin / scale)
                x_n = np.sum(rn, axis=0) / np.sum(rn * rn, axis=0)
                x = x_n * smin
                resid = np.sqrt(np.mean((rn * x_n - 1.0) ** 2, axis=0))
                take = resid < best_err
                best_err = np.where(take, resid, best_err)
                best_u[k] = np.where(take, x, best_u[k])
                best_u[1 - k] = np.where(take, 0.0, best_u[1 - k])
            u[:, out] = best_u
            gamut[out] = best_err
        np.maximum(u, 0, out=u)
        np.power(u, dtype(1.0) / n, out=u)
        return u[0], u[1], gamut

    def tone_intensities(self, freq_hz: np.ndarray | float, amplitude_um: np.ndarray | float) -> tuple[np.ndarray, np.ndarray]:
        """Channel intensities (I_p, I_np) of pure tones."""
        wp, wnp = self.weights(freq_hz)
        a = np.abs(np.asarray(amplitude_um, dtype=float))
        return a * wp, a * wnp

    def spectrum_intensities(self, freq_hz: np.ndarray, amplitude_um: np.ndarray, axis: int = -1) -> tuple[np.ndarray, np.ndarray]:
        """Channel intensities of a line spectrum: power sum of the weighted components along `axis`."""
        wp, wnp = self.weights(freq_hz)
        a = np.abs(np.asarray(amplitude_um, dtype=float))
        return np.sqrt(np.sum((a * wp) ** 2, axis=axis)), np.sqrt(np.sum((a * wnp) ** 2, axis=axis))

    def decompose_spectrum(self, freq_hz: np.ndarray, amplitude_um: np.ndarray, axis: int = -1) -> "Decomposition":
        """(a40, a320) of a line spectrum (frequencies in Hz, peak amplitudes in µm)."""
        return self.decompose(*self.spectrum_intensities(freq_hz, amplitude_um, axis=axis))

    def kernels(self, freq_hz: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The paper's H40(f), H320(f) for n = 1 (linear combinations of 1/T_p and 1/T_np, with the band).

        For n = 1 and a single component, ``a40 = H40(f) A`` and ``a320 = H320(f) A`` inside the gamut.
        """
        wp, wnp = self.weights(freq_hz)
        m = np.stack(self.weights(np.asarray(self.base_frequencies_hz, dtype=float)))
        minv = np.linalg.inv(m)
        return minv[0, 0] * wp + minv[0, 1] * wnp, minv[1, 0] * wp + minv[1, 1] * wnp


@dataclass(frozen=True)
class Decomposition:
    """Result of the reduction: amplitudes (µm, ≥ 0, finite) and the out-of-gamut measure.

    ``out_of_gamut`` is 0 inside the gamut, else the RMS relative error of the two channel
    intensities (raised to n) that the nearest reproducible pair leaves.
    """

    a40: np.ndarray
    a320: np.ndarray
    out_of_gamut: np.ndarray
