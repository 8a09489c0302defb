"""Stochastic discovery of the translation lattice of a (fabric) image.

Method (paper section 5.1, "geometrical and stochastic methods"):

1. Flatten: remove a quadratic illumination trend, subtract a heavy blur and equalise the local
   contrast, so uneven light and stains do not dominate the correlation.
2. Candidates from the data: the normalised cross-correlation (NCC) of the image with itself for
   every integer shift (computed with one zero-padded FFT plus integral images, so every lag is
   normalised by its own overlap), and its local maxima, localised to sub-pixel by a quadratic fit.
3. Random-sample consensus: pairs of strong peaks propose a basis (every pair among the 8
   nearest, then random pairs, seeded and weighted by peak height); each proposal is
   Lagrange-Gauss reduced, fitted by least squares to the peaks that are integer combinations of
   it (its consensus), and scored by the *weakest* NCC over its first shell (t1, t2, t1 + t2,
   t1 - t2). A lattice that is too fine (a harmonic: half a period) has a weak point in that
   shell; a lattice that is too coarse (a super-lattice) scores as well as the true one but has
   a larger cell. So the winner is the smallest cell among the proposals whose score is within
   `_eligible_bar` of the best and whose lattice holds the best one: one defect or one strong
   harmonic cannot win.
   The credible proposals are re-scored at sub-pixel lags (`_SpectralAcf`: the self-correlation
   as an exact cosine sum over the power spectrum, with Newton steps to its peaks), because the
   NCC peaks of 3-8 px periods are 1-3 samples wide and an interpolated integer-lag map reads
   them up to 10 % low between samples, which lets super-lattices whose vectors happen to be
   near integers win.
4. Sub-pixel refinement: weighted least squares over every supported peak out to the search radius
   (the error of t shrinks with the integer multiple of the far peaks); on large images, the
   lattice is found on a 384 px full-resolution centre crop (or a reduced copy for coarse
   lattices) and refined at full resolution by template matching at growing multiples k t,
   as far as the photo stays one rigid lattice.
5. Decision from measured evidence (thresholds below were set from the sweep in
   bench/bench_lattice.py): the first-shell NCC, its prominence over the half-lattice points and
   the sub-pixel self-similarity of the image under t1 and t2.

Vectors are (x, y) in pixels: x along columns, y along rows (down).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import cv2
import numpy as np
import scipy.fft as sfft
from scipy import ndimage
from scipy.spatial import cKDTree

__all__ = [
    "Lattice",
    "find_lattice",
    "reduce_basis",
    "self_similarity",
    "lattice_distance_px",
]

# ---- tuning constants (chosen from the generated sweep; see bench/bench_lattice.py) -----------
_WORK_MAX_PX = 1024          # images up to this side are analysed whole; larger ones via ...
_CROP_PX = 384               # ... a full-resolution centre crop (fine lattices) or a copy
                             # reduced to _WORK_MAX_PX (coarse lattices), then refined in full
_SEARCH_FRACTION = 0.7       # NCC peaks are searched out to 0.7 x the short image side
_TEMPLATE_PX = 512           # template side for the full-resolution refinement of large images
_MIN_MATCH_RATIO = 0.5       # ... which stops where the match falls below half its k = 1 value
_MIN_OVERLAP_PX = 8          # never trust an NCC lag whose overlap is thinner than this
_N_NEAREST = 30              # hypotheses are drawn among the 30 nearest strong peaks ...
_N_STRONGEST = 10            # ... plus the 10 strongest
_N_PAIRS = 200               # random pairs drawn per run (all pairs when there are fewer)
_N_PAIRS_AGAIN = 80          # ... in a second pass, which also gets the first pass's winner
_N_EXHAUSTIVE = 8            # all pairs among the 8 nearest peaks are proposed as well
_STRONG_FRACTION = 0.3       # a strong peak has NCC >= 0.3 x the highest peak
_ELIGIBLE_FRACTION = 0.94    # proposals within 94 % of the best shell score compete on cell
                             # area, if their lattice holds the best one (see _select). On the
                             # 24-seed sweep the true lattice scored >= 0.963 of the best (a
                             # slub lowers one shell point) and sub-lattices <= 0.907
_CONTAIN_TOL_PX = 0.3        # a vector is in a lattice when this close to one of its points
_MIN_ANGLE_SIN = 0.2         # pairs closer than ~11.5 degrees to parallel propose nothing
_N_TOP = 3                   # the 3 best hypotheses by map score are re-scored at sub-pixel
_RESCORE_FRACTION = 0.5      # lags, then those within 50 % of the best, smallest cell first ...
_N_RESCORE = 24              # ... (at most 24 of them)
_ACF_TERMS = 4096            # spectral terms kept for the sub-pixel self-correlation
# periodic decision (see _decide): all must hold
# Measured on the 156-case sweep (bench/bench_lattice.py): generated lattices with every hard
# case give shell >= 0.44, prominence >= 0.43, self-similarity >= 0.47 (noise at 20 % of the
# contrast is the lowest); gravel, grass and Brownian surfaces give <= 0.11, <= 0.05, <= 0.16.
# The thresholds sit between, nearer the non-periodic side because real fabrics score lower
# than generated ones (plain-defect-a2r1.jpg: 0.27).
_MIN_SHELL_NCC = 0.25        # weakest NCC over t1, t2, t1 +- t2
_MIN_PROMINENCE = 0.2        # shell NCC minus the mean NCC at the half-lattice points
_MIN_SELF_SIMILARITY = 0.25  # sub-pixel self-similarity at t1 and at t2


@dataclass(frozen=True)
class Lattice:
    """Result of lattice discovery.

    Attributes
    ----------
    periodic : bool
        False when no lattice is credible; t1_px and t2_px are then zeros.
    t1_px, t2_px : numpy.ndarray
        (x, y) in px, sub-pixel; a Lagrange-Gauss reduced basis (t1 shortest, t2 the shortest
        independent vector, angle between 60 and 120 degrees, det[t1 t2] > 0).
    confidence : float
        In [0, 1]; 0.5 is the decision threshold.
    reason : str
        One line: why periodic or why not (for the compile report).
    evidence : dict
        JSON-serialisable measurements behind the decision.
    """

    periodic: bool
    t1_px: np.ndarray
    t2_px: np.ndarray
    confidence: float
    reason: str
    evidence: dict = field(default_factory=dict)

    @property
    def basis_px(self) -> np.ndarray:
        """2x2 matrix with columns t1, t2 (px)."""
        return np.column_stack([self.t1_px, self.t2_px])

    @property
    def cell_area_px2(self) -> float:
        """Area of the unit cell in px^2 (0 when not periodic)."""
        return float(abs(np.linalg.det(self.basis_px)))

    def to_dict(self) -> dict:
        """JSON-serialisable form."""
        return {
            "periodic": bool(self.periodic),
            "t1_px": [float(v) for v in self.t1_px],
            "t2_px": [float(v) for v in self.t2_px],
            "confidence": float(self.confidence),
            "reason": self.reason,
            "evidence": self.evidence,
        }


# ---- small geometry helpers ----------------------------------------------------------------

def reduce_basis(t1, t2) -> tuple[np.ndarray, np.ndarray]:
    """Lagrange-Gauss reduction of a 2-D lattice basis.

    Parameters
    ----------
    t1, t2 : array_like, shape (2,)
        Any basis (x, y) of the lattice, in px; must be non-parallel.

    Returns
    -------
    (numpy.ndarray, numpy.ndarray)
        The reduced basis of the same lattice: t1 is a shortest non-zero lattice vector, t2 the
        shortest one independent of it (so |t1 . t2| <= |t1|^2 / 2 and the angle is within
        60-120 degrees). Signs are fixed: t1 has x > 0 (or x = 0, y > 0) and det[t1 t2] > 0.
    """
    a = np.asarray(t1, dtype=float).copy()
    b = np.asarray(t2, dtype=float).copy()
    if a.shape != (2,) or b.shape != (2,):
        raise ValueError("reduce_basis expects two 2-vectors")
    scale = max(np.abs(a).max(), np.abs(b).max(), 1e-300)
    if abs(a[0] * b[1] - a[1] * b[0]) <= 1e-12 * scale * scale:
        raise ValueError("reduce_basis: t1 and t2 are parallel (no lattice)")
    for _ in range(1000):
        if a @ a > b @ b:
            a, b = b, a
        mu = round(float(a @ b) / float(a @ a))
        if mu == 0:
            break
        b = b - mu * a
    if a[0] < 0 or (a[0] == 0 and a[1] < 0):
        a = -a
    if a[0] * b[1] - a[1] * b[0] < 0:
        b = -b
    # make the tie |b - a| == |b| deterministic: prefer the acute angle... keep t1 . t2 >= 0
    bb = float(b @ b)
    if a @ b < 0 and abs(float((b + a) @ (b + a)) - bb) <= 1e-12 * bb:
        b = b + a
    return a, b


def lattice_distance_px(a1, a2, b1, b2) -> float:
    """How far basis (a1, a2) is from generating the same lattice as (b1, b2), in px.

    The change of basis M = [b1 b2]^-1 [a1 a2] is rounded to integers; if that is not
    unimodular (|det| = 1) the lattices differ and the result is inf. Otherwise the result is the
    largest distance between a_i and the matching vector of the b-lattice, [b1 b2] round(M).
    """
    a = np.column_stack([np.asarray(a1, float), np.asarray(a2, float)])
    b = np.column_stack([np.asarray(b1, float), np.asarray(b2, float)])
    if abs(np.linalg.det(a)) < 1e-9 or abs(np.linalg.det(b)) < 1e-9:
        return math.inf
    m = np.rint(np.linalg.solve(b, a))
    if abs(round(np.linalg.det(m))) != 1:
        return math.inf
    return float(np.linalg.norm(a - b @ m, axis=0).max())


# ---- image preparation -----------------------------------------------------------------------

def _as_grey_float(image: np.ndarray, name: str = "image") -> np.ndarray:
    arr = np.asarray(image)
    if arr.ndim != 2:
        raise ValueError(f"{name} must be a 2-D grey array, got shape {arr.shape}")
    if min(arr.shape) < 8:
        raise ValueError(f"{name} is too small ({arr.shape}); need at least 8 x 8 px")
    arr = arr.astype(np.float64, copy=False)
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} contains NaN or infinite values")
    return arr


def _as_grey_array(image: np.ndarray, name: str = "image") -> np.ndarray:
    """Validate a 2-D grey image without copying it (large photos stay uint8)."""
    arr = np.asarray(image)
    if arr.ndim != 2:
        raise ValueError(f"{name} must be a 2-D grey array, got shape {arr.shape}")
    if min(arr.shape) < 8:
        raise ValueError(f"{name} is too small ({arr.shape}); need at least 8 x 8 px")
    if arr.dtype.kind not in "uif" or arr.dtype.kind == "b":
        raise ValueError(f"{name} must be numeric, got dtype {arr.dtype}")
    if arr.dtype.kind == "f" and not np.isfinite(arr).all():
        raise ValueError(f"{name} contains NaN or infinite values")
    return arr


def _gaussian_blur(x: np.ndarray, sigma_px: float) -> np.ndarray:
    """Gaussian blur; large sigmas are done on a reduced copy (illumination is smooth)."""
    x32 = np.ascontiguousarray(x, dtype=np.float32)
    if sigma_px <= 6.0:
        return cv2.GaussianBlur(x32, (0, 0), sigma_px, borderType=cv2.BORDER_REFLECT).astype(
            np.float64)
    rows, cols = x.shape
    factor = sigma_px / 3.0
    small_shape = (max(2, round(cols / factor)), max(2, round(rows / factor)))
    small = cv2.resize(x32, small_shape, interpolation=cv2.INTER_AREA)
    fx, fy = cols / small_shape[0], rows / small_shape[1]
    # the area average already blurred by a box of width f (variance f^2 / 12)
    sx = math.sqrt(max(sigma_px ** 2 - fx ** 2 / 12.0, 0.25)) / fx
    sy = math.sqrt(max(sigma_px ** 2 - fy ** 2 / 12.0, 0.25)) / fy
    small = cv2.GaussianBlur(small, (0, 0), sigmaX=sx, sigmaY=sy, borderType=cv2.BORDER_REFLECT)
    return cv2.resize(small, (cols, rows), interpolation=cv2.INTER_LINEAR).astype(np.float64)


def _remove_quadratic(x: np.ndarray) -> np.ndarray:
    """Subtract the least-squares quadratic surface (fitted on a <= 64 x 64 sub-grid)."""
    rows, cols = x.shape
    sy, sx = max(1, rows // 64), max(1, cols // 64)
    yy, xx = np.mgrid[0:rows:sy, 0:cols:sx]
    u, v = xx / cols - 0.5, yy / rows - 0.5
    design = np.column_stack([np.ones(u.size), u.ravel(), v.ravel(), (u * u).ravel(),
                              (u * v).ravel(), (v * v).ravel()])
    coef, *_ = np.linalg.lstsq(design, x[::sy, ::sx].ravel(), rcond=None)
    u = np.arange(cols) / cols - 0.5
    v = (np.arange(rows) / rows - 0.5)[:, None]
    trend = coef[0] + coef[1] * u + coef[2] * v + coef[3] * u * u + coef[4] * u * v + coef[5] * v * v
    return x - trend


def _prepare_for_discovery(image: np.ndarray, sigma: float) -> np.ndarray:
    """Trend removal, high-pass and local contrast equalisation; zero-mean float64.

    Subtracting a Gaussian blur of sigma >= 0.75 T keeps the fundamental of period T (its gain
    is 1 - exp(-2 pi^2 sigma^2 / T^2) > 0.99).
    """
    return _prepare_both(image, sigma)[0]


def _prepare_both(image: np.ndarray, sigma: float) -> tuple[np.ndarray, np.ndarray]:
    """`_prepare_for_discovery` (clipped) and the same image before clipping.

    Clipping at 3 robust standard deviations tames defects in the integer-lag NCC, but it is a
    non-linear map of a sampled image: its new harmonics alias, and the clipped image is no
    longer periodic at sub-pixel shifts (its correlation peaks move by up to 0.2 px). The
    sub-pixel self-correlation (`_SpectralAcf`) therefore uses the unclipped image.
    """
    x = _remove_quadratic(image)
    x = x - _gaussian_blur(x, sigma)
    energy = _gaussian_blur(x * x, sigma)
    x = x / np.sqrt(energy + 1e-6 * max(float(energy.mean()), 1e-300))
    soft = x - x.mean()
    # clip what is left of defects (slub edges, specular spots): 3 robust standard deviations
    limit = 3.0 * 1.4826 * float(np.median(np.abs(x - np.median(x))))
    if limit > 0:
        x = np.clip(x, -limit, limit)
    return x - x.mean(), soft


# ---- normalised self-correlation for all integer shifts --------------------------------------

def _ncc_map(x: np.ndarray, max_lag_y: int, max_lag_x: int) -> np.ndarray:
    """NCC of x with itself shifted by every integer (dy, dx), |dy| <= max_lag_y, |dx| <= max_lag_x.

    Each lag is normalised by the means and energies of its own overlap (integral images), so
    the values are the Pearson correlation over the overlap, as for `self_similarity`.
    Returns array [2 max_lag_y + 1, 2 max_lag_x + 1], zero lag at the centre.
    """
    rows, cols = x.shape
    fy = sfft.next_fast_len(rows + max_lag_y, real=True)
    fx = sfft.next_fast_len(cols + max_lag_x, real=True)
    spec = sfft.rfft2(x, s=(fy, fx), workers=-1)
    corr = sfft.irfft2(spec.real * spec.real + spec.imag * spec.imag, s=(fy, fx), workers=-1)
    dy = np.arange(-max_lag_y, max_lag_y + 1)
    dx = np.arange(-max_lag_x, max_lag_x + 1)
    # circular correlation c[d] = sum_p x[p + d] x[p]; no wrap since the padding >= size + lag
    c = corr[np.ix_(dy % fy, dx % fx)]

    # integral images of x and x^2 (float64 sums: the differences of large sums must be exact)
    s1, s2 = cv2.integral2(np.ascontiguousarray(x, dtype=np.float64), sdepth=cv2.CV_64F,
                           sqdepth=cv2.CV_64F)
    # overlap: p runs over A = rows [max(0,-dy), rows - max(0,dy)), B = A + d
    a_r0, a_r1 = np.maximum(0, -dy), rows - np.maximum(0, dy)
    a_c0, a_c1 = np.maximum(0, -dx), cols - np.maximum(0, dx)
    b_r0, b_r1, b_c0, b_c1 = a_r0 + dy, a_r1 + dy, a_c0 + dx, a_c1 + dx

    def rect(ii: np.ndarray, r0, r1, c0, c1) -> np.ndarray:
        # rows first, then columns: two plain gathers are ~3x faster than one np.ix_ gather
        a, b = ii[r1], ii[r0]
        return (a[:, c1] - b[:, c1]) - (a[:, c0] - b[:, c0])

    n = ((a_r1 - a_r0)[:, None] * (a_c1 - a_c0)[None, :]).astype(float)
    sa, sb = rect(s1, a_r0, a_r1, a_c0, a_c1), rect(s1, b_r0, b_r1, b_c0, b_c1)
    ea, eb = rect(s2, a_r0, a_r1, a_c0, a_c1), rect(s2, b_r0, b_r1, b_c0, b_c1)
    cov = c - sa * sb / n
    var = np.maximum(ea - sa * sa / n, 1e-300) * np.maximum(eb - sb * sb / n, 1e-300)
    return np.clip(cov / np.sqrt(var), -1.0, 1.0)


def _taper(n: int, fraction: float = 0.25) -> np.ndarray:
    """Tukey window: flat middle, raised-cosine ends over `fraction` of n at each end (a flat
    middle weighs a centred defect no more than the rest; the ends keep the spectrum compact)."""
    w = np.ones(n)
    m = max(1, int(round(fraction * n)))
    ramp = 0.5 - 0.5 * np.cos(np.pi * (np.arange(m) + 0.5) / m)
    w[:m] = ramp
    w[n - m:] = ramp[::-1]
    return w


class _SpectralAcf:
    """Self-correlation of a prepared image at *sub-pixel* lags, from its power spectrum.

    The image is tapered (`_taper`) and zero-padded, so its power spectrum P is compact around the
    harmonics and c(t) = sum_k P(k) cos(2 pi k . t) is the exact (sinc-interpolated) windowed
    self-correlation at any real lag t. Only the strongest coefficients are kept (those holding
    99.5 % of the energy, at most _ACF_TERMS): the dropped ones are spread over all k, so their
    sum is near zero at any t != 0, and c(0) is taken from the full energy. Dividing by the
    window's own correlation gives a correlation coefficient rho(t), 1 at an exact period.

    Unlike a spline through the integer-lag NCC, rho does not favour lags near integers: NCC
    peaks of 3-8 px periods are 1-3 samples wide and a spline reads them up to 10 % low when
    they fall between samples, which let super-lattices with near-integer vectors outscore the
    true lattice.
    """

    def __init__(self, x: np.ndarray, max_lag: tuple[int, int]):
        rows, cols = x.shape
        self.shape, self.max_lag = (rows, cols), max_lag
        wr, wc = _taper(rows), _taper(cols)
        y = x * wr[:, None] * wc[None, :]
        fy = sfft.next_fast_len(rows + max_lag[0] + 1, real=True)
        fx = sfft.next_fast_len(cols + max_lag[1] + 1, real=True)
        spec = sfft.rfft2(y, s=(fy, fx), workers=-1)
        power = (spec.real * spec.real + spec.imag * spec.imag) / (fy * fx)
        power[:, 1:(fx + 1) // 2] *= 2.0  # fold in the columns whose mirror is not stored
        flat = power.ravel()
        n_keep = min(_ACF_TERMS, flat.size)
        idx = np.argpartition(-flat, n_keep - 1)[:n_keep]
        idx = idx[np.argsort(-flat[idx], kind="stable")]
        cum = np.cumsum(flat[idx])
        n = int(np.searchsorted(cum, 0.995 * float(flat.sum()))) + 1
        idx = np.sort(idx[:n])
        ky = np.fft.fftfreq(fy)[idx // power.shape[1]]
        kx = np.fft.rfftfreq(fx)[idx % power.shape[1]]
        self.k = 2.0 * np.pi * np.column_stack([kx, ky])  # (K, 2) rad per px, (x, y)
        self.p = flat[idx]
        # 1-D window self-correlations at integer lags (linear interpolation in between)
        self.a_r = np.correlate(wr, wr, "full")[rows - 1:] / float(wr @ wr)
        self.a_c = np.correlate(wc, wc, "full")[cols - 1:] / float(wc @ wc)
        self.c0 = max(float((y * y).sum()), 1e-300)

    def _envelope(self, pts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Window correlation A(t) (1 at t = 0) and its gradient (x, y)."""
        def one(a: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
            s = np.abs(t)
            i = np.minimum(s.astype(int), len(a) - 2)  # s >= 0: truncation is floor
            f = s - i
            slope = a[i + 1] - a[i]
            return a[i] + f * slope, slope * np.sign(t)

        ax, gx = one(self.a_c, pts[:, 0])
        ay, gy = one(self.a_r, pts[:, 1])
        return ax * ay, np.column_stack([gx * ay, ax * gy])

    def _valid(self, pts: np.ndarray) -> np.ndarray:
        return (np.abs(pts[:, 1]) <= self.max_lag[0]) & (np.abs(pts[:, 0]) <= self.max_lag[1])

    def at(self, points: np.ndarray) -> np.ndarray:
        """rho at lags (x, y) px, shape (n, 2); NaN beyond the lag range."""
        pts = np.asarray(points, float).reshape(-1, 2)
        if len(pts) == 0:
            return np.zeros(0)
        c = np.cos(pts @ self.k.T) @ self.p
        env, _ = self._envelope(pts)
        out = c / (np.maximum(env, 1e-3) * self.c0)
        out[~self._valid(pts)] = np.nan
        return np.clip(out, -1.0, 1.0)

    def refine_peaks(self, t: np.ndarray, iterations: int = 3) -> np.ndarray:
        """Move lags t (n, 2) to their nearby maxima of rho (Newton steps on the exact
        derivatives of the cosine sum, each limited to 0.5 px)."""
        t = np.asarray(t, float).reshape(-1, 2).copy()
        kk = np.stack([self.k[:, 0] ** 2, self.k[:, 0] * self.k[:, 1], self.k[:, 1] ** 2], 1)
        pk, pkk = self.p[:, None] * self.k, self.p[:, None] * kk
        for _ in range(iterations):
            phase = t @ self.k.T
            cos, sin = np.cos(phase), np.sin(phase)
            c = cos @ self.p
            g = -(sin @ pk)                                       # (n, 2)
            h = -(cos @ pkk)                                      # (n, 3): xx, xy, yy
            env, genv = self._envelope(t)
            env = np.maximum(env, 1e-3)
            g = (g - (c / env)[:, None] * genv) / env[:, None]    # gradient of c / A
            hxx, hxy, hyy = (h / env[:, None]).T
            det = hxx * hyy - hxy * hxy
            ok = (det > 1e-12 * np.maximum(hxx * hxx, 1e-300)) & (hxx < 0)
            safe = np.where(ok, det, 1.0)
            step = np.column_stack([-(hyy * g[:, 0] - hxy * g[:, 1]) / safe,
                                    -(hxx * g[:, 1] - hxy * g[:, 0]) / safe])
            step[~ok] = 0.0
            norm = np.linalg.norm(step, axis=1, keepdims=True)
            step *= np.minimum(1.0, 0.5 / np.maximum(norm, 1e-300))
            t += step
        return t


class _NccField:
    """The NCC map with a cubic-spline interpolant (bilinear under-reads the sharp peaks of
    short periods by up to half their height; the cubic spline by a few percent)."""

    def __init__(self, ncc: np.ndarray, cy: int, cx: int):
        self.ncc, self.cy, self.cx = ncc, cy, cx
        self.coef = ndimage.spline_filter(ncc, order=3, mode="mirror")

    def at(self, points: np.ndarray) -> np.ndarray:
        """NCC at sub-pixel lags (x, y); NaN outside the map."""
        points = np.asarray(points, float).reshape(-1, 2)
        coords = np.vstack([points[:, 1] + self.cy, points[:, 0] + self.cx])
        out = ndimage.map_coordinates(self.coef, coords, order=3, mode="mirror",
                                      prefilter=False)
        inside = ((coords[0] >= 0) & (coords[0] <= self.ncc.shape[0] - 1) &
                  (coords[1] >= 0) & (coords[1] <= self.ncc.shape[1] - 1))
        out[~inside] = np.nan
        return out


def _quadratic_vertex(z: np.ndarray, step: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Vertex of the quadratic through 3x3 samples z[n, 3, 3] spaced `step` apart.

    Returns offsets (x, y), clipped to +-step, and the quadratic's value there."""
    gx = (z[:, 1, 2] - z[:, 1, 0]) / 2
    gy = (z[:, 2, 1] - z[:, 0, 1]) / 2
    hxx = z[:, 1, 2] - 2 * z[:, 1, 1] + z[:, 1, 0]
    hyy = z[:, 2, 1] - 2 * z[:, 1, 1] + z[:, 0, 1]
    hxy = (z[:, 2, 2] - z[:, 2, 0] - z[:, 0, 2] + z[:, 0, 0]) / 4
    det = hxx * hyy - hxy * hxy
    good = (det > 1e-12) & (hxx < 0)
    safe = np.where(good, det, 1.0)
    # fall back to separate parabolas where the 2-D fit is not a maximum
    ox1 = np.where(hxx < 0, -gx / np.where(hxx < 0, hxx, -1.0), 0.0)
    oy1 = np.where(hyy < 0, -gy / np.where(hyy < 0, hyy, -1.0), 0.0)
    ox = np.where(good, -(hyy * gx - hxy * gy) / safe, ox1)
    oy = np.where(good, -(hxx * gy - hxy * gx) / safe, oy1)
    ox, oy = np.clip(ox, -1, 1), np.clip(oy, -1, 1)
    value = z[:, 1, 1] + 0.5 * (gx * ox + gy * oy)
    return ox * step, oy * step, value


_GRID3 = np.array([(dy, dx) for dy in (-1, 0, 1) for dx in (-1, 0, 1)], float)


def _local_maxima(field: _NccField, min_r: float, max_r: float
                  ) -> tuple[np.ndarray, np.ndarray]:
    """Sub-pixel local maxima of the NCC map in the upper half plane of lags.

    Integer maxima, a quadratic fit on the 3x3 integer neighbourhood, then a second quadratic
    fit on the spline sampled +-0.5 px around it. Returns positions (n, 2) as (x, y) lags and
    their spline NCC values, sorted by length.
    """
    ncc, cy, cx = field.ncc, field.cy, field.cx
    peak = ncc == ndimage.maximum_filter(ncc, size=3, mode="nearest")
    peak[[0, -1], :] = False
    peak[:, [0, -1]] = False
    iy, ix = np.nonzero(peak)
    ly, lx = iy - cy, ix - cx
    r = np.hypot(lx, ly)
    keep = ((ly > 0) | ((ly == 0) & (lx > 0))) & (r >= min_r - 1.0) & (r <= max_r) & (
        ncc[iy, ix] > 0)
    iy, ix = iy[keep], ix[keep]
    if iy.size == 0:
        return np.zeros((0, 2)), np.zeros(0)
    z = np.stack([ncc[iy + dy, ix + dx] for dy in (-1, 0, 1) for dx in (-1, 0, 1)], axis=1)
    ox, oy, _ = _quadratic_vertex(z.reshape(-1, 3, 3), 1.0)
    pos = np.column_stack([ix - cx + ox, iy - cy + oy])
    around = pos[:, None, :] + 0.5 * _GRID3[None, :, ::-1]
    z = field.at(around.reshape(-1, 2)).reshape(-1, 3, 3)
    z = np.where(np.isfinite(z), z, -1.0)
    ox, oy, _ = _quadratic_vertex(z, 0.5)
    pos = pos + np.column_stack([ox, oy])
    value = field.at(pos)
    value = np.where(np.isfinite(value), value, ncc[iy, ix])
    r = np.hypot(pos[:, 0], pos[:, 1])
    keep = r >= min_r
    order = np.argsort(r[keep], kind="stable")
    return pos[keep][order], value[keep][order]


# ---- consensus -------------------------------------------------------------------------------

def _tolerance_px(basis: np.ndarray) -> float:
    """Inlier distance: a fifth of the shortest vector, within 0.5 ... 2 px."""
    return float(np.clip(0.2 * np.linalg.norm(basis, axis=0).min(), 0.5, 2.0))


def _fit_basis(points: np.ndarray, weights: np.ndarray, basis: np.ndarray, radius: float,
               iterations: int = 4) -> tuple[np.ndarray, np.ndarray]:
    """Least-squares basis from the peaks that are integer combinations of it (growing radius).

    Returns the refined basis (columns t1, t2) and the boolean inlier mask over `points`.
    (Closed-form 2 x 2 normal equations: this runs for every proposal, so it must be cheap.)
    """
    inliers = np.zeros(len(points), bool)
    lengths = np.sqrt(points[:, 0] ** 2 + points[:, 1] ** 2)
    w_all = np.maximum(weights, 1e-3)
    r_now = min(radius, 4.0 * math.sqrt(float((basis * basis).sum(axis=0).max())))
    for it in range(iterations):
        tol = _tolerance_px(basis)
        det = basis[0, 0] * basis[1, 1] - basis[0, 1] * basis[1, 0]
        if abs(det) < 1e-12:
            break
        # coefficients of every point in the basis (2 x 2 inverse written out)
        c1 = np.rint((basis[1, 1] * points[:, 0] - basis[0, 1] * points[:, 1]) / det)
        c2 = np.rint((-basis[1, 0] * points[:, 0] + basis[0, 0] * points[:, 1]) / det)
        rx = points[:, 0] - c1 * basis[0, 0] - c2 * basis[0, 1]
        ry = points[:, 1] - c1 * basis[1, 0] - c2 * basis[1, 1]
        mask = (rx * rx + ry * ry < tol * tol) & (lengths <= r_now) & ((c1 != 0) | (c2 != 0))
        if mask.sum() < 2:
            break
        a1, a2, w = c1[mask], c2[mask], w_all[mask]
        # weighted normal equations: [sum w a a^T] [t1; t2] = sum w a p^T
        m11, m12, m22 = (w * a1 * a1).sum(), (w * a1 * a2).sum(), (w * a2 * a2).sum()
        dm = m11 * m22 - m12 * m12
        if dm <= 1e-9 * max(m11 * m22, 1e-300):
            break  # the inliers do not span two directions
        px, py = points[mask, 0], points[mask, 1]
        b1 = np.array([(w * a1 * px).sum(), (w * a1 * py).sum()])
        b2 = np.array([(w * a2 * px).sum(), (w * a2 * py).sum()])
        t1 = (m22 * b1 - m12 * b2) / dm
        t2 = (m11 * b2 - m12 * b1) / dm
        basis = np.column_stack([t1, t2])
        inliers = mask
        if r_now >= radius and it >= 1:
            break
        r_now = min(radius, 2.0 * r_now)
    return basis, inliers


@dataclass
class _Hypothesis:
    basis: np.ndarray          # columns t1, t2 (reduced)
    shell: float               # weakest NCC over t1, t2, t1 + t2, t1 - t2
    half: float                # mean NCC over the half-lattice points
    support: int               # strong peaks that are lattice points
    area: float


class _PeakIndex:
    """Nearest-peak look-up over the detected NCC maxima (both half planes)."""

    def __init__(self, points: np.ndarray, values: np.ndarray):
        self.points = np.vstack([points, -points]) if len(points) else np.zeros((0, 2))
        self.values = np.concatenate([values, values]) if len(values) else np.zeros(0)
        self.tree = cKDTree(self.points) if len(self.points) else None

    def value_at(self, field: _NccField, query: np.ndarray, tol: float) -> np.ndarray:
        """NCC at sub-pixel lags: the larger of the spline value there and the value of a peak
        within `tol` (a basis off by a fraction of a pixel must not miss a sharp peak)."""
        value = field.at(query)
        if self.tree is not None:
            dist, idx = self.tree.query(query, distance_upper_bound=tol)
            hit = np.isfinite(dist)
            value[hit] = np.fmax(value[hit], self.values[idx[hit]])
        return value


def _shell_scores(field: _NccField, basis: np.ndarray, peaks: _PeakIndex
                  ) -> tuple[float, float]:
    """Weakest NCC over the first shell and mean NCC over the half-lattice points."""
    t1, t2 = basis[:, 0], basis[:, 1]
    shell = np.array([t1, t2, t1 + t2, t1 - t2])
    tol = _tolerance_px(basis)
    vs = peaks.value_at(field, shell, tol)
    vh = peaks.value_at(field, 0.5 * shell, tol)
    vs = vs[np.isfinite(vs)]
    vh = vh[np.isfinite(vh)]
    if vs.size < 3:
        return -1.0, 1.0
    return float(vs.min()), float(vh.mean()) if vh.size else 0.0


def _propose(points: np.ndarray, values: np.ndarray, field: _NccField,
             min_period: float, max_period: float, rng: np.random.Generator,
             peaks: _PeakIndex, acf: _SpectralAcf | None = None,
             extra: list[np.ndarray] = ()) -> tuple[list[_Hypothesis], np.ndarray, int]:
    """RANSAC-like proposals from random pairs of strong peaks.

    The pool of peaks (the _N_NEAREST nearest and _N_STRONGEST strongest) is first moved to
    the exact sub-pixel maxima of `acf`; every pair among the _N_EXHAUSTIVE nearest is always
    proposed (a fine lattice has thousands of equally strong peaks, and its basis is among the
    nearest ones), then _N_PAIRS random pairs weighted by peak height; `extra` bases (from an
    earlier pass) are proposed too.
    """
    strong = values >= max(_STRONG_FRACTION * values.max(), 0.02)
    sp, sv = points[strong], values[strong]
    nearest = np.arange(min(_N_NEAREST, len(sp)))
    strongest = np.argsort(-sv, kind="stable")[:_N_STRONGEST]
    pool = np.unique(np.concatenate([nearest, strongest]))
    pool_pts = sp[pool]
    if acf is not None and len(pool):
        moved = acf.refine_peaks(pool_pts)
        ok = np.linalg.norm(moved - pool_pts, axis=1) < 1.0  # stayed on its own peak
        pool_pts = np.where(ok[:, None], moved, pool_pts)
    i, j = np.triu_indices(len(pool), k=1)
    hyps: dict[tuple, _Hypothesis] = {}
    tried: set[tuple] = set()
    if len(i) == 0:
        return [], sp, 0
    prob = sv[pool[i]] * sv[pool[j]]
    prob = prob / prob.sum()
    n_draw = min(_N_PAIRS if not len(extra) else _N_PAIRS_AGAIN, len(i))
    picks = rng.choice(len(i), size=n_draw, replace=False, p=prob)
    near = np.flatnonzero((i < _N_EXHAUSTIVE) & (j < _N_EXHAUSTIVE))  # pool is length-sorted
    pairs = [(pool_pts[i[k]], pool_pts[j[k]]) for k in near]
    pairs += [(pool_pts[i[k]], pool_pts[j[k]]) for k in picks]
    pairs = [(b[:, 0], b[:, 1]) for b in extra] + pairs
    fit_p, fit_v = sp[:150], sv[:150]  # sorted by length: the nearest strong peaks
    radius = float(np.linalg.norm(fit_p, axis=1).max()) if len(fit_p) else 0.0
    for p, q in pairs:
        cross = abs(p[0] * q[1] - p[1] * q[0])
        if cross < _MIN_ANGLE_SIN * np.linalg.norm(p) * np.linalg.norm(q):
            continue
        a, b = reduce_basis(p, q)
        basis = np.column_stack([a, b])
        key = tuple(np.round(basis.ravel() / 0.75).astype(int))
        if key in tried:
            continue
        tried.add(key)
        basis, inl = _fit_basis(fit_p, fit_v, basis, radius, iterations=3)
        try:
            a, b = reduce_basis(basis[:, 0], basis[:, 1])
        except ValueError:
            continue
        basis = np.column_stack([a, b])
        lengths = np.linalg.norm(basis, axis=0)
        fitted_key = tuple(np.round(basis.ravel() / 0.75).astype(int))
        if lengths.min() < min_period or lengths.max() > max_period or fitted_key in hyps:
            continue
        shell, half = _shell_scores(field, basis, peaks)
        hyps[fitted_key] = _Hypothesis(basis, shell, half, int(inl.sum()),
                                       float(abs(np.linalg.det(basis))))
    return list(hyps.values()), sp, n_draw


def _rescore(hyps: list[_Hypothesis], acf: _SpectralAcf, field: _NccField, peaks: _PeakIndex,
             min_period: float, max_period: float) -> list[_Hypothesis]:
    """Re-score hypotheses with the sub-pixel self-correlation (`_SpectralAcf`).

    A re-scored hypothesis has t1 and t2 moved to their exact correlation peaks, is reduced
    again and gets its first-shell and half-lattice scores at those vectors: per lattice point
    the larger of rho and the integer-lag NCC (rho is exact between samples but, being
    windowed, weighs a defect near the image centre more; the NCC weighs every pixel alike but
    reads fine peaks low between samples: each one's bias is the other's strength). Only what
    `_select` can
    pick is re-scored: the _N_TOP best by map score (they set the bar), then the others whose
    map score is within _RESCORE_FRACTION of the best, smallest cell first, until one clears
    `_eligible_bar` of the best re-scored shell (nothing larger can be selected after it).
    """
    if not hyps:
        return hyps
    out: dict[tuple, _Hypothesis] = {}

    def rescore(h: _Hypothesis) -> _Hypothesis | None:
        t = acf.refine_peaks(h.basis.T)
        try:
            a, b = reduce_basis(t[0], t[1])
        except ValueError:
            return None
        lengths = (np.linalg.norm(a), np.linalg.norm(b))
        if min(lengths) < min_period or max(lengths) > max_period:
            return None
        key = tuple(np.round(np.concatenate([a, b]) / 0.5).astype(int))
        if key in out:
            return out[key]
        shell_pts = np.array([a, b, a + b, a - b])
        values = acf.at(np.vstack([shell_pts, 0.5 * shell_pts]))
        basis = np.column_stack([a, b])
        tol = _tolerance_px(basis)
        shell = np.fmax(values[:4], peaks.value_at(field, shell_pts, tol))
        half = np.fmax(values[4:], field.at(0.5 * shell_pts))
        shell, half = shell[np.isfinite(shell)], half[np.isfinite(half)]
        if shell.size < 3:
            return None
        out[key] = _Hypothesis(basis, float(shell.min()),
                               float(half.mean()) if half.size else 0.0, h.support,
                               float(abs(np.linalg.det(basis))))
        return out[key]

    best_map = max(h.shell for h in hyps)
    by_score = sorted(hyps, key=lambda h: -h.shell)
    top = [r for r in map(rescore, by_score[:_N_TOP]) if r is not None]
    if not top:
        return []
    best = max(top, key=lambda r: r.shell)
    rest = sorted((h for h in by_score[_N_TOP:] if h.shell >= _RESCORE_FRACTION * best_map),
                  key=lambda h: h.area)
    smallest_top = min(r.area for r in top if _eligible(r, best))
    for h in rest[:_N_RESCORE]:
        if h.area > 1.1 * smallest_top:
            break  # cells this large cannot beat an eligible smaller one
        r = rescore(h)
        if r is not None and r.shell > best.shell:
            best = r  # a new best: what is eligible changes with it
        elif r is not None and _eligible(r, best):
            break
    return list(out.values())


def _eligible_bar(best: float) -> float:
    """Lowest shell score that still competes on cell area with the best one."""
    return _ELIGIBLE_FRACTION * best if best > 0 else best


def _holds(outer: np.ndarray, inner: np.ndarray) -> bool:
    """True when every vector of lattice `inner` (columns) is a point of lattice `outer`.

    Tolerance: _CONTAIN_TOL_PX plus 2 % of the vector (each hypothesis is refined on its own, so
    noise moves long vectors by a few tenths of a px), but never more than 0.15 of the shortest
    vector of `outer` (else a fine lattice would hold any vector by chance).
    """
    coeff = np.linalg.solve(outer, inner)
    resid = np.linalg.norm(inner - outer @ np.rint(coeff), axis=0)
    tol = np.minimum(_CONTAIN_TOL_PX + 0.02 * np.linalg.norm(inner, axis=0),
                     0.15 * float(np.linalg.norm(outer, axis=0).min()))
    return bool(np.all(resid <= tol))


def _eligible(h: _Hypothesis, best: _Hypothesis) -> bool:
    """May `h` be selected when `best` has the highest shell score?

    Its score must be within _ELIGIBLE_FRACTION of the best, and its lattice must hold the best
    one: the true lattice holds all its super-lattices (the usual high scorers), while a wrong
    lattice that happens to score well (a few dominant harmonics, a defect's own correlation)
    does not hold the best hypothesis and so cannot win on area.
    """
    return h.shell >= _eligible_bar(best.shell) and _holds(h.basis, best.basis)


def _select(hyps: list[_Hypothesis]) -> _Hypothesis | None:
    if not hyps:
        return None
    best = max(hyps, key=lambda h: h.shell)
    if best.shell <= 0:
        return best
    eligible = [h for h in hyps if _eligible(h, best)]
    # smallest cell wins (a super-lattice is as self-similar but coarser); ties by score
    return min(eligible, key=lambda h: (round(math.log(h.area) / math.log(1.05)), -h.shell))


# ---- self-similarity -------------------------------------------------------------------------

def self_similarity(image: np.ndarray, t_px) -> float:
    """Normalised correlation of the image with itself shifted by t (sub-pixel).

    Parameters
    ----------
    image : numpy.ndarray
        2-D grey image (any range).
    t_px : array_like, shape (2,)
        Shift (x, y) in px; the image at p is compared with the image at p + t, interpolated
        bicubically, over the overlap.

    Returns
    -------
    float
        Pearson correlation over the overlap, in [-1, 1]; 1 for an image exactly periodic under t.

    Raises
    ------
    ValueError
        If the shifted image does not overlap the original by at least 16 pixels.
    """
    img = _as_grey_float(image)
    t = np.asarray(t_px, dtype=float)
    if t.shape != (2,) or not np.all(np.isfinite(t)):
        raise ValueError(f"t_px must be a finite (x, y) pair, got {t_px!r}")
    rows, cols = img.shape
    tx, ty = float(t[0]), float(t[1])
    # only the overlap (plus the cubic margin) is interpolated
    x0, x1 = max(0, math.floor(-tx) + 2), min(cols, math.ceil(cols - tx) - 2)
    y0, y1 = max(0, math.floor(-ty) + 2), min(rows, math.ceil(rows - ty) - 2)
    if (x1 - x0) * (y1 - y0) < 16 or x1 <= x0 or y1 <= y0:
        raise ValueError(f"shift {tuple(t)} px leaves no overlap in a {rows}x{cols} image")
    src = img.astype(np.float32)
    mat = np.array([[1.0, 0.0, tx + x0], [0.0, 1.0, ty + y0]])
    shifted = cv2.warpAffine(src, mat, (x1 - x0, y1 - y0),
                             flags=cv2.INTER_CUBIC | cv2.WARP_INVERSE_MAP,
                             borderMode=cv2.BORDER_CONSTANT, borderValue=float("nan"))
    base = img[y0:y1, x0:x1]
    ok = np.isfinite(shifted)
    if ok.sum() < 16:
        raise ValueError(f"shift {tuple(t)} px leaves no overlap in a {rows}x{cols} image")
    a = base[ok] - base[ok].mean()
    b = shifted[ok].astype(np.float64)
    b -= b.mean()
    denom = math.sqrt(float(a @ a) * float(b @ b))
    return float(a @ b / denom) if denom > 0 else 0.0


# ---- decision --------------------------------------------------------------------------------

def _ramp(value: float, lo: float, hi: float) -> float:
    return float(np.clip((value - lo) / (hi - lo), 0.0, 1.0))


def _decide(shell: float, prominence: float, s1: float, s2: float) -> tuple[bool, float, str]:
    """Periodic or not, a confidence in [0, 1] and the limiting reason."""
    s_min = min(s1, s2)
    checks = [
        ("first-shell NCC", shell, _MIN_SHELL_NCC),
        ("prominence over half-lattice points", prominence, _MIN_PROMINENCE),
        ("self-similarity under t1 and t2", s_min, _MIN_SELF_SIMILARITY),
    ]
    periodic = all(v >= thr for _, v, thr in checks)
    # each factor is 0.5 at its threshold and saturates at 1 well above it
    parts = [_ramp(v, 0.5 * thr, 1.5 * thr) if v < 1.5 * thr else
             0.75 + 0.25 * _ramp(v, 1.5 * thr, 3.0 * thr) for _, v, thr in checks]
    confidence = float(min(parts))
    if periodic:
        confidence = max(confidence, 0.5)
        why = ""
    else:
        confidence = min(confidence, 0.49)
        failed = [(name, v, thr) for name, v, thr in checks if v < thr]
        why = "; ".join(f"{name} {v:.2f} < {thr:.2f}" for name, v, thr in failed)
    return periodic, confidence, why


# ---- main entry ------------------------------------------------------------------------------

def _discover_pass(prepared: tuple[np.ndarray, np.ndarray], min_period: float,
                   max_period: float, rng: np.random.Generator, search: float | None = None,
                   extra: list[np.ndarray] = ()) -> dict:
    """One pass of candidates + consensus on a prepared (flattened) image, clipped and not
    (`_prepare_both`); `extra` bases (an earlier pass's winner) compete with the proposals."""
    x, soft = prepared
    rows, cols = x.shape
    full = _SEARCH_FRACTION * min(rows, cols)
    search = full if search is None else min(search, full)
    max_ly = int(min(search, rows - _MIN_OVERLAP_PX))
    max_lx = int(min(search, cols - _MIN_OVERLAP_PX))
    ncc = _ncc_map(x, max_ly, max_lx)
    acf = _SpectralAcf(soft, (max_ly, max_lx))
    field_ = _NccField(ncc, max_ly, max_lx)
    points, values = _local_maxima(field_, min_period, search)
    out: dict = {"n_peaks": int(len(points)), "search_radius_px": round(float(search), 2)}
    if len(points) < 2:
        out.update(found=False, why="fewer than two self-correlation peaks")
        return out
    peaks = _PeakIndex(points, values)
    hyps, strong_points, n_draw = _propose(points, values, field_, min_period, max_period, rng,
                                           peaks, acf, extra)
    out.update(n_strong_peaks=int(len(strong_points)), n_pairs_drawn=int(n_draw),
               n_hypotheses=len(hyps))
    hyps = _rescore(hyps, acf, field_, peaks, min_period, max_period)
    best = _select(hyps)
    if best is None:
        out.update(found=False, why="no pair of peaks spans a lattice within the period limits")
        return out
    # final refinement over every peak (not only the strong ones) consistent with the winner
    weight_floor = 0.5 * max(best.shell, 0.0)
    usable = values >= weight_floor
    basis, inliers = _fit_basis(points[usable], values[usable], best.basis, search, iterations=6)
    try:
        a, b = reduce_basis(basis[:, 0], basis[:, 1])
    except ValueError:
        a, b = reduce_basis(best.basis[:, 0], best.basis[:, 1])
    basis = np.column_stack([a, b])
    shell, half = _shell_scores(field_, basis, peaks)
    ranked = sorted(hyps, key=lambda h: -h.shell)[:5]
    out.update(
        found=True, basis=basis, shell=shell, half=half, prominence=shell - half,
        n_refine_peaks=int(inliers.sum()), x=x,
        top_hypotheses=[{"t1_px": [round(float(v), 3) for v in h.basis[:, 0]],
                         "t2_px": [round(float(v), 3) for v in h.basis[:, 1]],
                         "shell_ncc": round(h.shell, 4), "half_ncc": round(h.half, 4),
                         "support": h.support} for h in ranked],
        peaks=[[round(float(p[0]), 3), round(float(p[1]), 3), round(float(v), 4)]
               for p, v in zip(points[:20], values[:20])],
    )
    return out


def _discover(work: np.ndarray, min_period: float, max_period: float,
              rng: np.random.Generator, search: float | None = None) -> dict:
    """Lattice discovery on one working image; vectors in that image's px.

    Pass 1 flattens at the scale of the longest admissible period. When it finds a much finer
    lattice, pass 2 flattens again at the scale of that lattice (sigma = its longest vector):
    large defects (a slub, a stain) then lose their plateau and only keep their edges, so they
    weigh far less in the correlation. Pass 2 re-runs the whole consensus, so a harmonic found
    in pass 1 can still be corrected.
    """
    sigma1 = max(0.75 * max_period, 4.0)
    res = _discover_pass(_prepare_both(work, sigma1), min_period, max_period, rng, search=search)
    res["flatten_sigma_px"] = round(sigma1, 2)
    if res.get("found"):
        longest = float(np.linalg.norm(res["basis"], axis=0).max())
        sigma2 = max(1.0 * longest, 4.0)
        if sigma2 < 0.6 * sigma1:
            # the lattice is known to be fine: 16 of its longest vectors are search enough
            res2 = _discover_pass(_prepare_both(work, sigma2), min_period, max_period,
                                  rng, search=max(64.0, 16.0 * longest), extra=[res["basis"]])
            if res2.get("found"):
                res2["flatten_sigma_px"] = round(sigma2, 2)
                res2["pass1_basis_px"] = [[round(float(v), 3) for v in res["basis"][:, i]]
                                          for i in range(2)]
                res = res2
    if res.get("found") and res["n_refine_peaks"] < 30:
        # few peaks (long periods, few repetitions): the least-squares leverage is small, so
        # maximise the self-similarity of the image gradients directly
        refined = _refine_by_self_similarity(work, res["basis"])
        res["basis"] = np.column_stack(reduce_basis(refined[:, 0], refined[:, 1]))
        res["refined_by"] = "gradient self-similarity"
    return res


def _gradients(image: np.ndarray) -> list[np.ndarray]:
    """x and y derivatives (3-tap Sobel): shift-invariant, blind to offsets and linear light."""
    img = np.ascontiguousarray(image, dtype=np.float32)
    return [cv2.Sobel(img, cv2.CV_32F, 1, 0, ksize=3), cv2.Sobel(img, cv2.CV_32F, 0, 1, ksize=3)]


def _multi_ncc(channels: list[np.ndarray], t: np.ndarray) -> float:
    """Pearson correlation of the channels with themselves shifted by t, pooled over channels."""
    rows, cols = channels[0].shape
    tx, ty = float(t[0]), float(t[1])
    x0, x1 = max(0, math.floor(-tx) + 2), min(cols, math.ceil(cols - tx) - 2)
    y0, y1 = max(0, math.floor(-ty) + 2), min(rows, math.ceil(rows - ty) - 2)
    if x1 - x0 < 4 or y1 - y0 < 4:
        return -1.0
    mat = np.array([[1.0, 0.0, tx + x0], [0.0, 1.0, ty + y0]])
    num = den_a = den_b = 0.0
    for ch in channels:
        shifted = cv2.warpAffine(ch, mat, (x1 - x0, y1 - y0),
                                 flags=cv2.INTER_CUBIC | cv2.WARP_INVERSE_MAP,
                                 borderMode=cv2.BORDER_REFLECT)
        a = ch[y0:y1, x0:x1].astype(np.float64)
        b = shifted.astype(np.float64)
        a = a - a.mean()
        b = b - b.mean()
        num += float((a * b).sum())
        den_a += float((a * a).sum())
        den_b += float((b * b).sum())
    return num / math.sqrt(den_a * den_b) if den_a > 0 and den_b > 0 else -1.0


def _refine_by_self_similarity(image: np.ndarray, basis: np.ndarray) -> np.ndarray:
    """Move each vector to the maximum of the gradient self-similarity (quadratic fits on
    3 x 3 samples spaced 0.5 px, then 0.2 px)."""
    channels = _gradients(image)
    basis = basis.copy()
    for col in range(2):
        t = basis[:, col].copy()
        for h in (0.5, 0.2, 0.2):
            z = np.array([_multi_ncc(channels, t + h * np.array([dx, dy]))
                          for dy, dx in _GRID3]).reshape(1, 3, 3)
            ox, oy, _ = _quadratic_vertex(z, h)
            t = t + np.array([ox[0], oy[0]])
        basis[:, col] = t
    return basis


def _refine_full_resolution(image: np.ndarray, basis: np.ndarray) -> np.ndarray:
    """Refine t1, t2 on the full image by template matching at growing multiples k t.

    A _TEMPLATE_PX (at most) template from the centre is matched against the window around
    centre + round(k t); the sub-pixel offset of the best match divided by k corrects t, so the
    error shrinks by the multiple (k = 1, 4, 16, 64, 256 while the shift fits in the image and
    the match stays at least _MIN_MATCH_RATIO as good as at k = 1).
    The search radius stays below half the shortest vector, so a neighbouring lattice point
    cannot be taken instead.
    """
    rows, cols = image.shape
    img = image if image.dtype in (np.uint8, np.float32) else image.astype(np.float32)
    basis = basis.copy()
    half_short = 0.45 * float(np.linalg.norm(basis, axis=0).min())
    templ = int(min(_TEMPLATE_PX, 0.3 * min(rows, cols)))
    for col in range(2):
        t = basis[:, col].copy()
        first_score = None
        for k in (1, 4, 16, 64, 256):
            shift = k * t
            r = int(max(2, math.ceil(min(half_short, 3.0 + 0.1 * k))))
            cx0 = int(round(cols / 2 - shift[0] / 2 - templ / 2))
            cy0 = int(round(rows / 2 - shift[1] / 2 - templ / 2))
            sx, sy = int(round(cx0 + shift[0])), int(round(cy0 + shift[1]))
            if min(cx0, cy0, sx - r, sy - r) < 0 or max(cx0, sx + r) + templ > cols or max(
                    cy0, sy + r) + templ > rows:
                break
            tmp = img[cy0:cy0 + templ, cx0:cx0 + templ]
            win = img[sy - r:sy + r + templ, sx - r:sx + r + templ]
            score = cv2.matchTemplate(win, tmp, cv2.TM_CCOEFF_NORMED)
            iy, ix = np.unravel_index(int(np.argmax(score)), score.shape)
            if not (0 < iy < score.shape[0] - 1 and 0 < ix < score.shape[1] - 1):
                break  # best match on the window's edge: the guess is off, stop here
            best = float(score[iy, ix])
            first_score = best if first_score is None else first_score
            if best < _MIN_MATCH_RATIO * first_score:
                # the photo is not one rigid lattice this far out (perspective, a curved or
                # stretched fabric): a match this weak would average distortion, not precision
                break
            z = score[iy - 1:iy + 2, ix - 1:ix + 2].astype(np.float64)[None]
            ox, oy, _ = _quadratic_vertex(z, 1.0)
            measured = np.array([sx - r + ix + ox[0] - cx0, sy - r + iy + oy[0] - cy0])
            t = measured / k
        basis[:, col] = t
    return basis


def find_lattice(image: np.ndarray, *, seed: int = 0, min_period_px: float = 2.5,
                 max_period_fraction: float = 0.4) -> Lattice:
    """Find the translation lattice of a grey image, or say that there is none.

    Parameters
    ----------
    image : numpy.ndarray
        2-D grey image, any range (uneven light, JPEG noise and defects are tolerated).
    seed : int
        Seed of the random pair sampling (results are deterministic for a given seed).
    min_period_px : float
        Shortest lattice vector considered, px (>= 2; below that the image cannot hold it).
    max_period_fraction : float
        Longest lattice vector considered, as a fraction of the short image side (<= 0.5: the
        image must show at least two periods).

    Returns
    -------
    Lattice
        Reduced basis, confidence, a one-line reason and the evidence.
    """
    img = _as_grey_array(image)
    if not (2.0 <= min_period_px):
        raise ValueError(f"min_period_px must be >= 2, got {min_period_px}")
    if not (0.0 < max_period_fraction <= 0.5):
        raise ValueError(f"max_period_fraction must be in (0, 0.5], got {max_period_fraction}")
    rows, cols = img.shape
    max_period = max_period_fraction * min(rows, cols) + 1.0  # 1 px slack for 2.5-period images
    if max_period <= min_period_px:
        raise ValueError(f"image {rows}x{cols} too small for periods >= {min_period_px} px")
    rng = np.random.default_rng(seed)
    evidence: dict = {"image_shape": [rows, cols], "seed": int(seed)}

    if max(rows, cols) <= _WORK_MAX_PX:
        work = img.astype(np.float64)
        if float(work.max() - work.min()) == 0.0:
            return _not_periodic("the image is constant", evidence)
        res = _discover(work, min_period_px, max_period, rng)
        scale = np.eye(2)
        evidence["working_image"] = "full"
        refine_at_full = False
    else:
        # fine lattices: a full-resolution centre crop; coarse ones: a reduced copy; either
        # way the vectors are then refined on the full image
        ch, cw = min(rows, _CROP_PX), min(cols, _CROP_PX)
        y0, x0 = (rows - ch) // 2, (cols - cw) // 2
        crop = img[y0:y0 + ch, x0:x0 + cw].astype(np.float64)
        # only lattices up to a quarter of the crop are accepted from it (below), so neither
        # the flattening nor the search needs to reach further (half the cost of the map)
        crop_max = min(max_period, 0.25 * min(ch, cw) + 1.0)
        res = _discover(crop, min_period_px, crop_max, rng,
                        search=2.2 * crop_max) if np.ptp(crop) > 0 else {}
        scale = np.eye(2)
        evidence["working_image"] = f"centre crop {ch}x{cw} at full resolution"
        ok_crop = res.get("found") and res["shell"] >= _MIN_SHELL_NCC and (
            res["prominence"] >= _MIN_PROMINENCE) and (
            np.linalg.norm(res["basis"], axis=0).max() <= 0.25 * min(ch, cw))
        if not ok_crop:
            f = max(rows, cols) / _WORK_MAX_PX
            small_shape = (max(8, round(cols / f)), max(8, round(rows / f)))
            src = img if img.dtype in (np.uint8, np.uint16, np.float32) else img.astype(
                np.float32)
            small = cv2.resize(src, small_shape, interpolation=cv2.INTER_AREA).astype(np.float64)
            sx, sy = cols / small_shape[0], rows / small_shape[1]
            if np.ptp(small) == 0:
                return _not_periodic("the image is constant", evidence)
            res_small = _discover(small, min_period_px, max_period / max(sx, sy),
                                  np.random.default_rng(seed))
            ok_small = res_small.get("found") and res_small["shell"] >= _MIN_SHELL_NCC and (
                res_small["prominence"] >= _MIN_PROMINENCE)
            if ok_small or not res.get("found"):
                res = res_small
                scale = np.diag([sx, sy])
                evidence["working_image"] = (f"reduced copy {small_shape[1]}x{small_shape[0]} "
                                             f"(factor {max(sx, sy):.2f})")
        refine_at_full = True

    evidence.update({k: v for k, v in res.items()
                     if k not in ("basis", "x", "found", "why", "shell", "half", "prominence")})
    if not res.get("found"):
        return _not_periodic(res.get("why", "no lattice"), evidence)

    basis = scale @ res["basis"]
    if refine_at_full:
        basis = _refine_full_resolution(img, basis)
        a, b = reduce_basis(basis[:, 0], basis[:, 1])
        basis = np.column_stack([a, b])
    # self-similarity on the flattened working image, at the vectors in its own px
    x = res["x"]
    t_work = np.linalg.solve(scale, basis)
    try:
        s1 = self_similarity(x, t_work[:, 0])
        s2 = self_similarity(x, t_work[:, 1])
    except ValueError:
        s1 = s2 = 0.0
    shell, half, prom = res["shell"], res["half"], res["prominence"]
    periodic, confidence, why = _decide(shell, prom, s1, s2)
    evidence.update(shell_ncc=round(shell, 4), half_lattice_ncc=round(half, 4),
                    prominence=round(prom, 4), self_similarity_t1=round(s1, 4),
                    self_similarity_t2=round(s2, 4),
                    candidate_t1_px=[round(float(v), 4) for v in basis[:, 0]],
                    candidate_t2_px=[round(float(v), 4) for v in basis[:, 1]])
    t1, t2 = basis[:, 0], basis[:, 1]
    if not periodic:
        return _not_periodic(
            f"best lattice candidate t1=({t1[0]:.2f}, {t1[1]:.2f}) t2=({t2[0]:.2f}, {t2[1]:.2f}) px "
            f"is not credible: {why}", evidence, confidence)
    angle = math.degrees(math.acos(np.clip(t1 @ t2 / (np.linalg.norm(t1) * np.linalg.norm(t2)),
                                           -1, 1)))
    reason = (f"periodic: t1=({t1[0]:.2f}, {t1[1]:.2f}) px, t2=({t2[0]:.2f}, {t2[1]:.2f}) px, "
              f"angle {angle:.1f} deg; self-similarity {s1:.2f}/{s2:.2f}, first-shell NCC "
              f"{shell:.2f}, prominence {prom:.2f}, {res['n_refine_peaks']} peaks in consensus")
    return Lattice(True, t1.copy(), t2.copy(), confidence, reason, evidence)


def _not_periodic(why: str, evidence: dict, confidence: float = 0.0) -> Lattice:
    reason = why if why.startswith("best lattice") else f"not periodic: {why}"
    if not reason.startswith("not periodic"):
        reason = "not periodic: " + reason
    return Lattice(False, np.zeros(2), np.zeros(2), float(confidence), reason, evidence)
