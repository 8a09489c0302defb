"""Estimation of the Hurst index H (and fractal dimension D = 3 - H) of a height map.

Convention as in :mod:`haptex_compile.fractal_synthesis`: ``E|X(x + s) - X(x)|**2 ~ |s|**(2H)``.

Methods
-------
``"variogram"``, ``"madogram"``
    Transect estimators of Gneiting, Ševčíková & Percival (2012): along every row (u direction)
    and every column (v direction), the power variations ``V_p(l) = mean |X(i + l) - X(i)|**p``
    at small lags l = 1, 2 px (p = 2 variogram, p = 1 madogram); ``H = slope of log V_p versus
    log l, divided by p``. Rows are pooled into one V_p per direction (more efficient than the
    median of per-transect estimates), and H is the mean of the two directions' values. On a
    sampled fBm ``E V_p(l)`` is exactly proportional to ``l**(p H)``, so only the log's
    non-linearity biases the estimate.
    Confidence interval: 95 % normal interval, H +- 1.96 SD, with SD the larger of two:
    (a) the exact SD under an fBm of the estimated H (Gaussian covariance of the power
    variations summed over all pixel offsets, carried to H by the delta method: right for
    H > 1/2, where distant pixels stay correlated and resampling fails); (b) a block bootstrap
    over adjacent transects (999 replicates, fixed seed: catches non-Gaussian residuals).
``"spectral"``
    Slope of the radially averaged power spectrum (``S(f) ~ |f|**-(2H + 2)``): plane removed,
    2-D Hann window, log-spaced radial bins between 8 / min(ny, nx) and 0.5 cycles/px, fitted
    by least squares in log power against the spectrum of *sampled* fBm (aliasing included, so
    the bins near Nyquist are usable). Estimates lie in (0, 1). With a mask it uses the largest
    all-valid rectangle. Confidence interval: 95 % Student-t interval from the estimates in six
    direction sectors (0-180°); it measures directional spread too (anisotropy widens it).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import scipy.fft
import scipy.optimize
import scipy.stats

from .fractal_synthesis import _sampled_fbm_spectrum

__all__ = ["HurstEstimate", "estimate_hurst", "roughness_from_residual"]

_CI_LEVEL = 0.95
_BOOTSTRAP_REPLICATES = 999
_BOOTSTRAP_BLOCKS = 32
_SPECTRAL_SECTORS = 6
_SPECTRAL_MIN_SIDE = 32
_MIN_PAIRS = 16


@dataclass(frozen=True)
class HurstEstimate:
    """An estimate of the Hurst index H of a surface.

    Attributes
    ----------
    hurst : float
        Estimated H (variance of increments ~ r**(2H)).
    dimension : float
        Fractal dimension of the surface, D = 3 - H.
    ci_low, ci_high : float
        Confidence interval for H at level `ci_level` (see the module notes for how).
    method : str
        ``"variogram"``, ``"madogram"`` or ``"spectral"``.
    ci_level : float
        Level of the interval (0.95).
    n_samples : int
        Increments used (transect methods) or periodogram ordinates fitted (spectral).
    clipped : bool
        True when :func:`roughness_from_residual` clipped H into [0.01, 0.99].
    """

    hurst: float
    dimension: float
    ci_low: float
    ci_high: float
    method: str
    ci_level: float = _CI_LEVEL
    n_samples: int = 0
    clipped: bool = False


def _prepare(height: np.ndarray, mask: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """Return (heights as 2-D float64 with NaN where invalid, validity mask)."""
    z = np.asarray(height)
    if z.ndim == 1:
        z = z[None, :]
    if z.ndim != 2:
        raise ValueError(f"height must be a 2-D array (or a 1-D profile), got shape {z.shape}")
    if not np.issubdtype(z.dtype, np.number) or np.issubdtype(z.dtype, np.complexfloating):
        raise ValueError(f"height must be real numbers, got dtype {z.dtype}")
    z = z.astype(np.float64, copy=True)
    finite = np.isfinite(z)
    if mask is None:
        valid = finite
        if not finite.all():
            raise ValueError(f"height has {int((~finite).sum())} non-finite values; pass a mask that excludes them")
    else:
        m = np.asarray(mask)
        if m.ndim == 1 and np.asarray(height).ndim == 1:
            m = m[None, :]
        if m.shape != z.shape:
            raise ValueError(f"mask shape {m.shape} differs from height shape {z.shape}")
        m = m.astype(bool)
        if (m & ~finite).any():
            raise ValueError("height has non-finite values inside the mask")
        valid = m
    z[~valid] = np.nan
    return z, valid


def _transect_sums(z: np.ndarray, p: float, max_lag: int) -> tuple[np.ndarray, np.ndarray] | None:
    """Per-row sums of |increment|^p and pair counts for lags 1..max_lag (rows = transects)."""
    if z.shape[1] <= max_lag:
        return None
    sums = np.zeros((z.shape[0], max_lag))
    counts = np.zeros((z.shape[0], max_lag))
    for lag in range(1, max_lag + 1):
        d = np.abs(z[:, lag:] - z[:, :-lag])
        ok = np.isfinite(d)
        d = np.where(ok, d, 0.0)
        sums[:, lag - 1] = (d * d if p == 2 else d**p).sum(axis=1)
        counts[:, lag - 1] = ok.sum(axis=1)
    return sums, counts


def _slope_over_p(mean_pv: np.ndarray, p: float) -> np.ndarray:
    """H from power variations V_p(l), l = 1..L along the last axis (least squares in log-log)."""
    lags = np.log(np.arange(1, mean_pv.shape[-1] + 1))
    x = lags - lags.mean()
    with np.errstate(divide="ignore", invalid="ignore"):
        y = np.log(mean_pv)
    return (y * x).sum(axis=-1) / (x * x).sum() / p


def _overlap(n_a: int, n_b: int, offsets: np.ndarray) -> np.ndarray:
    """Number of i in [0, n_a) with i + d in [0, n_b), for each offset d."""
    return np.clip(np.minimum(n_a, offsets + n_b) - np.maximum(0, offsets), 0, None)


# The fully valid case sums over every pixel offset. Beyond NEAR_OFFSETS_PX (in either axis) the
# increment covariance is smooth on the scale of FAR_CELL_PX, so offsets there are summed in
# cells of that size: exact pair counts per cell times the covariance term at the cell's centre
# (midpoint rule; relative error of order (cell / offset)^2 / 24, below 1e-3 of the SD).
NEAR_OFFSETS_PX = 64
FAR_CELL_PX = 8


def _offset_cells(n: int) -> tuple[np.ndarray, np.ndarray]:
    """Cells of the integer offsets -(n-1)..(n-1): start index of each (offset + n - 1) and its centre.

    Single offsets within ``NEAR_OFFSETS_PX`` of 0, cells of ``FAR_CELL_PX`` beyond.
    """
    near = min(NEAR_OFFSETS_PX, n - 1)
    far_right = np.arange(near + 1, n, FAR_CELL_PX)
    starts = np.concatenate([-far_right[::-1] - np.minimum(FAR_CELL_PX, n - far_right[::-1]) + 1,
                             np.arange(-near, near + 1), far_right])
    stops = np.concatenate([starts[1:], [n]])
    return starts + (n - 1), 0.5 * (starts + stops - 1)


def _model_sd(valid: np.ndarray, hurst: float, p: float, max_lag: int, axes: list[int]) -> float:
    """SD of the transect estimate if the data were fBm of index `hurst` (Gaussian).

    The power variations are sums of |increment|^p over the valid pixel pairs. For Gaussian
    increments with correlation rho, Cov(X^2, Y^2) = 2 c^2 and
    Cov(|X|, |Y|) = (2/pi) sx sy (rho asin(rho) + sqrt(1 - rho^2) - 1), so the covariance of
    every pair of sums is a sum over pixel offsets of (pair count at that offset) x (that
    function of the fBm increment covariance): pair counts by FFT cross-correlation of the
    validity masks, all offsets included (for H > 1/2 distant pixels matter, which a block
    bootstrap misses). A fully valid rectangle has separable pair counts, and its distant
    offsets are summed in cells (``FAR_CELL_PX``). The delta method carries the covariance to H.
    """
    ny, nx = valid.shape
    full = bool(valid.all())
    if full:
        cy0, oy_c = _offset_cells(ny)
        cx0, ox_c = _offset_cells(nx)
        oy, ox = oy_c[:, None], ox_c[None, :]
    else:
        py = scipy.fft.next_fast_len(2 * ny - 1, real=True)
        px = scipy.fft.next_fast_len(2 * nx - 1, real=True)
        oy = np.fft.fftfreq(py, 1.0 / py)[:, None]
        ox = np.fft.fftfreq(px, 1.0 / px)[None, :]

    cache: dict[tuple[float, float], np.ndarray] = {}

    def dist(vy: float, vx: float) -> np.ndarray:
        # |d + v|^(2H) on the offset grid; few distinct shifts recur, so cache them.
        key = (vy, vx)
        if key not in cache:
            r2 = (oy + vy) ** 2 + (ox + vx) ** 2
            cache[key] = r2 ** hurst
        return cache[key]

    def cell_overlap(n_a: int, n_b: int, n: int, starts: np.ndarray) -> np.ndarray:
        # pair counts of every integer offset -(n-1)..(n-1), summed over each cell
        return np.add.reduceat(_overlap(n_a, n_b, np.arange(-(n - 1), n)), starts)

    base = dist(0.0, 0.0)
    stats = []  # (axis, lag, indicator spectrum, expected mean per pair)
    for axis in axes:
        for lag in range(1, max_lag + 1):
            ind = np.zeros_like(valid)
            if axis == 1:
                ind[:, :-lag] = valid[:, :-lag] & valid[:, lag:]
            else:
                ind[:-lag, :] = valid[:-lag, :] & valid[lag:, :]
            sigma = float(lag) ** hurst
            mean = sigma**2 if p == 2 else sigma * math.sqrt(2.0 / math.pi)
            spec = None if full else scipy.fft.rfft2(ind.astype(np.float64), s=(py, px), workers=2)
            stats.append((axis, lag, spec, mean, int(ind.sum()), sigma))
    n = len(stats)
    cov = np.zeros((n, n))
    for a in range(n):
        for b in range(a, n):
            axis_a, lag_a, spec_a, _, _, sig_a = stats[a]
            axis_b, lag_b, spec_b, _, _, sig_b = stats[b]
            if full:
                # Rectangles of starts: the counts factor into 1-D overlaps per axis.
                pairs = np.outer(
                    cell_overlap(ny - (lag_a if axis_a == 0 else 0), ny - (lag_b if axis_b == 0 else 0), ny, cy0),
                    cell_overlap(nx - (lag_a if axis_a == 1 else 0), nx - (lag_b if axis_b == 1 else 0), nx, cx0),
                )
            else:
                pairs = np.rint(scipy.fft.irfft2(np.conj(spec_a) * spec_b, s=(py, px), workers=2))
            u = (0.0, float(lag_a)) if axis_a == 1 else (float(lag_a), 0.0)
            v = (0.0, float(lag_b)) if axis_b == 1 else (float(lag_b), 0.0)
            # Cov(X(i+u)-X(i), X(j+v)-X(j)) with d = j - i.
            c = 0.5 * (dist(-u[0], -u[1]) + dist(v[0], v[1]) - dist(v[0] - u[0], v[1] - u[1]) - base)
            if p == 2:
                term = 2.0 * c * c
            else:
                rho = np.clip(c / (sig_a * sig_b), -1.0, 1.0)
                term = (2.0 / math.pi) * sig_a * sig_b * (rho * np.arcsin(rho) + np.sqrt(1.0 - rho * rho) - 1.0)
            cov[a, b] = cov[b, a] = float((pairs * term).sum())
    # Gradient of H = mean over axes of (1/p) * LS slope of log(S_l / N_l) on log l.
    logs = np.log(np.arange(1, max_lag + 1))
    x = logs - logs.mean()
    grad = np.array([x[lag - 1] / (p * (x * x).sum() * mean * count) / len(axes) for _, lag, _, mean, count, _ in stats])
    return float(math.sqrt(max(grad @ cov @ grad, 0.0)))


def _transect_estimate(z: np.ndarray, valid: np.ndarray, method: str, max_lag: int, ci: str) -> HurstEstimate:
    p = 2.0 if method == "variogram" else 1.0
    directions = []
    axes = []
    for axis, field in ((1, z), (0, z.T)):  # rows (u direction), then columns (v direction)
        got = _transect_sums(field, p, max_lag)
        if got is None:
            continue
        sums, counts = got
        if counts[:, -1].sum() < _MIN_PAIRS:
            continue
        directions.append((sums, counts))
        axes.append(axis)
    if not directions:
        raise ValueError(f"too few valid pixel pairs for a {method} estimate (need >= {_MIN_PAIRS} at lag {max_lag})")
    estimates = []
    boot = []
    rng = np.random.default_rng(0)
    n_used = 0
    for sums, counts in directions:
        total_s, total_c = sums.sum(axis=0), counts.sum(axis=0)
        if np.any(total_s <= 0):
            raise ValueError("the height map does not vary along a transect direction; H is undefined")
        n_used += int(total_c[0])
        estimates.append(float(_slope_over_p(total_s / total_c, p)))
        # Block bootstrap over adjacent transects (catches non-Gaussian, short-range spread).
        n_blocks = min(_BOOTSTRAP_BLOCKS, sums.shape[0])
        edges = np.linspace(0, sums.shape[0], n_blocks + 1).astype(int)
        block_s = np.add.reduceat(sums, edges[:-1], axis=0)
        block_c = np.add.reduceat(counts, edges[:-1], axis=0)
        pick = rng.integers(0, n_blocks, size=(_BOOTSTRAP_REPLICATES, n_blocks))
        bs, bc = block_s[pick].sum(axis=1), block_c[pick].sum(axis=1)
        with np.errstate(divide="ignore", invalid="ignore"):
            boot.append(_slope_over_p(bs / bc, p))
    hurst = float(np.mean(estimates))
    replicates = np.mean(boot, axis=0)
    replicates = replicates[np.isfinite(replicates)]
    sd_boot = float(np.std(replicates, ddof=1)) if replicates.size > 1 else 0.0
    if ci == "none":
        return HurstEstimate(hurst, 3.0 - hurst, math.nan, math.nan, method, n_samples=n_used)
    sd_model = _model_sd(valid, float(np.clip(hurst, 0.01, 0.99)), p, max_lag, axes) if ci == "auto" else 0.0
    half = scipy.stats.norm.ppf(0.5 + _CI_LEVEL / 2.0) * max(sd_boot, sd_model)
    return HurstEstimate(hurst, 3.0 - hurst, float(hurst - half), float(hurst + half), method, n_samples=n_used)


def _largest_valid_rectangle(valid: np.ndarray) -> tuple[slice, slice]:
    """Largest axis-aligned all-True rectangle (histogram-stack method, O(ny nx))."""
    ny, nx = valid.shape
    heights = np.zeros(nx, dtype=np.int64)
    best = (0, 0, 0, 0, 0)  # area, top, bottom (excl.), left, right (excl.)
    for row in range(ny):
        heights = np.where(valid[row], heights + 1, 0)
        stack: list[int] = []
        hs = heights.tolist() + [0]
        for col, h in enumerate(hs):
            while stack and hs[stack[-1]] >= h:
                top = stack.pop()
                left = stack[-1] + 1 if stack else 0
                area = hs[top] * (col - left)
                if area > best[0]:
                    best = (area, row + 1 - hs[top], row + 1, left, col)
            stack.append(col)
    _, top, bottom, left, right = best
    return slice(top, bottom), slice(left, right)


def _spectral_estimate(z: np.ndarray, valid: np.ndarray, ci: str) -> HurstEstimate:
    if not valid.all():
        rows, cols = _largest_valid_rectangle(valid)
        z = z[rows, cols]
    ny, nx = z.shape
    if min(ny, nx) < _SPECTRAL_MIN_SIDE:
        raise ValueError(
            f"spectral estimate needs a valid rectangle of at least {_SPECTRAL_MIN_SIDE}x{_SPECTRAL_MIN_SIDE} px, got {ny}x{nx}"
        )
    # Remove the least-squares plane (fBm carries a random tilt that would leak).
    yy, xx = np.mgrid[0:ny, 0:nx]
    design = np.column_stack([np.ones(z.size), yy.ravel(), xx.ravel()])
    coef, *_ = np.linalg.lstsq(design, z.ravel(), rcond=None)
    scale = float(np.abs(z).max())
    z = z - (design @ coef).reshape(ny, nx)
    if float(np.abs(z).max()) <= 1e-10 * scale:
        raise ValueError("the height map is a plane; H is undefined")
    window = np.hanning(ny)[:, None] * np.hanning(nx)[None, :]
    power = np.abs(scipy.fft.rfft2(z * window, workers=2)) ** 2
    fy = scipy.fft.fftfreq(ny)[:, None]
    fx = scipy.fft.rfftfreq(nx)[None, :]
    fy, fx = np.broadcast_arrays(fy, fx)
    radius = np.hypot(fy, fx)
    f_lo, f_hi = 8.0 / min(ny, nx), 0.5
    n_bins = 16
    edges = np.geomspace(f_lo, f_hi, n_bins + 1)
    in_band = (radius >= f_lo) & (radius <= f_hi)
    bin_of = np.clip(np.searchsorted(edges, radius[in_band], side="right") - 1, 0, n_bins - 1)
    angle = np.degrees(np.arctan2(fy[in_band], fx[in_band]))  # (-90, 90]
    sector_of = np.clip(((angle + 90.0) / (180.0 / _SPECTRAL_SECTORS)).astype(int), 0, _SPECTRAL_SECTORS - 1)
    band_power = power[in_band]
    band_fy, band_fx = fy[in_band], fx[in_band]
    # Model values at a bounded, deterministic subsample of each bin's frequencies.
    order = np.lexsort((sector_of, bin_of))

    def fit(select: np.ndarray) -> float:
        bins = bin_of[select]
        counts = np.bincount(bins, minlength=n_bins)
        used = counts > 0
        if used.sum() < 4:
            return math.nan
        mean_p = np.bincount(bins, weights=band_power[select], minlength=n_bins)[used] / counts[used]
        sub = select if select.dtype != bool else np.flatnonzero(select)
        stride = max(1, len(sub) // 4000)
        sub = sub[::stride]
        sub_bins = bin_of[sub]
        sub_counts = np.bincount(sub_bins, minlength=n_bins)[used]
        log_p = np.log(mean_p)

        def cost(h: float) -> float:
            s = _sampled_fbm_spectrum(band_fy[sub], band_fx[sub], h, images=2)
            mean_s = np.bincount(sub_bins, weights=s, minlength=n_bins)[used] / np.maximum(sub_counts, 1)
            resid = log_p - np.log(mean_s)
            resid -= resid.mean()
            return float(resid @ resid)

        res = scipy.optimize.minimize_scalar(cost, bounds=(0.001, 0.999), method="bounded", options={"xatol": 1e-4})
        return float(res.x)

    hurst = fit(order)
    if ci == "none":
        return HurstEstimate(hurst, 3.0 - hurst, math.nan, math.nan, "spectral", n_samples=int(in_band.sum()))
    per_sector = np.array([fit(np.flatnonzero(sector_of == s)) for s in range(_SPECTRAL_SECTORS)])
    per_sector = per_sector[np.isfinite(per_sector)]
    if per_sector.size >= 2:
        half = scipy.stats.t.ppf(0.5 + _CI_LEVEL / 2.0, per_sector.size - 1) * per_sector.std(ddof=1) / math.sqrt(per_sector.size)
    else:
        half = math.nan
    return HurstEstimate(hurst, 3.0 - hurst, float(hurst - half), float(hurst + half), "spectral", n_samples=int(in_band.sum()))


def estimate_hurst(
    height: np.ndarray,
    *,
    method: str = "variogram",
    mask: np.ndarray | None = None,
    max_lag: int = 2,
    ci: str = "auto",
) -> HurstEstimate:
    """Estimate the Hurst index H and fractal dimension D = 3 - H of a height map.

    Parameters
    ----------
    height : numpy.ndarray
        Heights (any unit; µm in this project), shape (ny, nx), or a 1-D profile.
    method : {"variogram", "madogram", "spectral"}
        Transect variogram (p = 2) or madogram (p = 1) at small lags, or the radially averaged
        power-spectrum slope; see the module notes.
    mask : numpy.ndarray of bool, optional
        True where the heights are valid; pixel pairs touching an invalid pixel are skipped.
    max_lag : int
        Largest lag (px) of the transect estimators' log-log fit (2 as in Gneiting et al.).
    ci : {"auto", "bootstrap", "none"}
        Confidence interval: ``"auto"`` as described in the module notes; ``"bootstrap"``
        uses only the block bootstrap (transect methods; faster, too narrow for H > 1/2);
        ``"none"`` skips it (bounds NaN), for bulk runs such as bias tables.

    Returns
    -------
    HurstEstimate
        H, D, a 95 % confidence interval for H, the method and the sample count.

    Raises
    ------
    ValueError
        Unknown method, non-finite heights outside the mask, too few valid pixels, or a map
        without variation.
    """
    if method not in ("variogram", "madogram", "spectral"):
        raise ValueError(f"unknown method {method!r} (use 'variogram', 'madogram' or 'spectral')")
    if ci not in ("auto", "bootstrap", "none"):
        raise ValueError(f"unknown ci {ci!r} (use 'auto', 'bootstrap' or 'none')")
    if isinstance(max_lag, bool) or not isinstance(max_lag, (int, np.integer)) or max_lag < 2:
        raise ValueError(f"max_lag must be an integer >= 2, got {max_lag!r}")
    z, valid = _prepare(height, mask)
    if method == "spectral":
        return _spectral_estimate(z, valid, ci)
    return _transect_estimate(z, valid, method, int(max_lag), ci)


def roughness_from_residual(
    residual: np.ndarray, *, pixel_size_um: float, mask: np.ndarray | None = None
) -> tuple[HurstEstimate, float]:
    """Fractal roughness of an image's unstructured part: (H and D estimate, RMS of the residual).

    Meant for photographs: `residual` is the photo minus its averaged periodic tile (or a whole
    non-periodic photo). H comes from the madogram transect estimator at lags 1-2 px (robust to
    the outliers photos carry), clipped into [0.01, 0.99] so that it can drive
    :func:`~haptex_compile.fractal_synthesis.brownian_surface` (``clipped`` says when). The RMS is
    in the residual's own units (grey levels for a photo), over the valid pixels, about their mean.

    Parameters
    ----------
    residual : numpy.ndarray
        2-D residual image.
    pixel_size_um : float
        Pixel size (µm/px), finite and positive. H and D are scale-free; the lags are 1 and 2 px,
        i.e. `pixel_size_um` and twice that.
    mask : numpy.ndarray of bool, optional
        True where the residual is valid (e.g. not saturated, not a stain).

    Returns
    -------
    (HurstEstimate, float)
        The estimate and the residual's RMS.
    """
    if not (isinstance(pixel_size_um, (int, float, np.floating, np.integer)) and math.isfinite(pixel_size_um) and pixel_size_um > 0):
        raise ValueError(f"pixel_size_um must be finite and > 0, got {pixel_size_um!r}")
    est = estimate_hurst(residual, method="madogram", mask=mask)
    z, valid = _prepare(residual, mask)
    values = z[valid]
    rms = float(np.sqrt(np.mean((values - values.mean()) ** 2)))
    h = float(np.clip(est.hurst, 0.01, 0.99))
    if h != est.hurst:
        est = HurstEstimate(
            h, 3.0 - h, float(np.clip(est.ci_low, 0.01, 0.99)), float(np.clip(est.ci_high, 0.01, 0.99)),
            est.method, est.ci_level, est.n_samples, clipped=True,
        )
    return est, rms
