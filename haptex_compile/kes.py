"""Virtual fabrics from Kawabata (KES-F) surface data, and the KES-FB4 measurement simulated.

Conventions (DOMAIN.md): heights in µm; u along image columns (axis 1), v along image rows
(axis 0, increasing downwards). Warp threads run along v, weft threads along u. A "warp"
value (SMD, MIU, MMD) comes from a traverse *along the warp*, i.e. along v (down a column of
the array); a "weft" value from a traverse along u (along a row).

The simulated KES-FB4 roughness measurement (:func:`simulate_kes_smd`)
    The contactor is a 0.5 mm piano wire lying across the traverse. It is modelled as a rigid
    cylinder of radius 0.25 mm whose axis is perpendicular to the traverse, resting on the rigid
    surface: the recorded height at each position is the grey dilation of the height profile by
    the cylinder's cross-section (the wire's lowest point rides on the upper envelope of the
    surface and bridges grooves narrower than it). Traverses are 2 cm long (wrapping around a
    periodic surface); SMD is, as in KES, ``SMD = (1/X) * integral |T(x) - mean(T)| dx`` over the
    traverse, X = 2 cm, with the mean of that traverse removed and no other filtering (no detrend).
    The value returned is the average over `n_traverses` parallel traverses spread over the map.
    The real wire touches the fabric over about 5 mm of its length; a *rigid* 5 mm wire resting
    on the highest point under it bridges a regular weave almost completely (measured here on a
    2/2 twill: SMD near 0 for any relief height), which contradicts the few-µm SMD of real regular
    fabrics, whose compliance lets the wire follow the threads. The default is therefore a line
    contact (``wire_length_um=0``); ``wire_length_um=5000`` gives the rigid long-wire variant.

The synthetic surface (:func:`kes_surface`)
    ``h = alpha * (R + 0.25 * F) + p_u * rho_u(u) + p_v * rho_v(v)`` (R normalised to unit mean
    absolute deviation, F to unit rms, rho to unit mean absolute deviation) where

    * ``R`` is a periodic weave relief: each thread a raised elliptic cross-section, warp and weft
      crossing over and under by the weave matrix with cosine crimp between crossings; the
      visible surface is the upper of the two thread layers. Thread heights are proportional to
      the thread spacing (fewer, thicker threads stand higher).
    * ``F`` is fibre-scale roughness: periodic fractional Brownian noise (H = 0.6), stretched
      along the fibres of whichever thread is on top (along v on warp, along u on weft).
    * ``rho_u(u)`` and ``rho_v(v)`` are periodic 1-D Brownian profiles (H = 0.6, flat below a
      2 mm wavelength): yarn unevenness and waviness that run across the whole fabric, i.e. the
      anisotropic part of the roughness. ``rho_u`` varies along u only, so it is felt by weft
      traverses; ``rho_v`` by warp traverses.
    * ``alpha = 4 * smoothmin(p_u, p_v)`` so the weave carries the isotropic part.

    ``(p_u, p_v)`` are solved (Newton in log space on the simulated measurement) so that the
    simulated SMD matches the given SMD in both directions. The whole surface is an integer
    number of weave repeats (10 mm or more) and every component is periodic on that torus, so
    lookup tables can wrap on it.

The friction map (``KesSurface.friction``)
    ``friction[0]`` is the friction coefficient for sliding along +v (the warp direction, KES
    "warp" MIU/MMD), ``friction[1]`` for sliding along +u (weft). Each is
    ``MIU + MMD * g / mean|g|`` with ``g`` the slope of the surface (smoothed over about half the
    wire radius: three box passes, close to a Gaussian of sigma 0.125 mm) along the sliding direction: the geometric ("ratchet")
    component of friction, which is larger climbing a thread than descending it. Its mean over the
    map is MIU and its mean absolute deviation is MMD (up to clipping at 0, which MMD <= MIU makes
    rare). Sliding the other way (-v or -u) flips the deviation: ``mu(-d) = 2 MIU - mu(+d)``.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np
from scipy import fft as sfft
from scipy import ndimage as ndi

from haptex_compile.kes_io import KesData, parse_kes, read_kes

__all__ = [
    "KES_PROBE_RADIUS_UM",
    "KES_TRAVERSE_MM",
    "KES_WIRE_LENGTH_UM",
    "KesData",
    "KesSurface",
    "friction_map",
    "kes_relief_scale",
    "kes_surface",
    "parse_kes",
    "periodic_fbm_profile",
    "periodic_fbm_surface",
    "read_kes",
    "simulate_kes_smd",
    "weave_matrix",
    "weave_relief",
]

#: Radius of the KES-FB4 roughness contactor, a 0.5 mm diameter piano wire (µm).
KES_PROBE_RADIUS_UM = 250.0
#: Length of a KES-FB4 traverse (mm).
KES_TRAVERSE_MM = 20.0
#: Length of the real wire in contact across the traverse (µm); not the default model (see top).
KES_WIRE_LENGTH_UM = 5000.0

_ROUGHNESS_HURST = 0.6
_RIB_CUTOFF_MM = 2.0  # 1-D profiles: flat spectrum above this wavelength
_WEAVE_WEIGHT = 4.0  # alpha = _WEAVE_WEIGHT * smoothmin(p_u, p_v)
_FIBRE_WEIGHT = 0.25  # fibre roughness rms relative to the weave relief's mean deviation
_FIBRE_STRETCH = 4.0  # fibre noise correlation is this much longer along the fibres
_FRICTION_SIGMA_UM = 125.0
_N_TRAVERSES = 128
_MAX_SIDE_PX = 4096
_MIN_PITCH_PX = 4.0


@dataclass(frozen=True)
class KesSurface:
    """A synthetic fabric surface made from KES data.

    Attributes
    ----------
    height_um : ndarray, shape (ny, nx), float32
        Height in µm, periodic over its whole extent in both axes (rows along v, columns along u).
    pixel_size_um : float
        Pixel size in µm.
    friction : ndarray, shape (2, ny, nx), float32
        Friction coefficient for sliding along +v (index 0, "warp") and along +u (index 1,
        "weft"); mean MIU and mean absolute deviation MMD per direction (module docstring).
    smd_simulated_um : dict of str to float
        SMD measured on `height_um` by :func:`simulate_kes_smd`, ``{"warp": .., "weft": ..}``.
    period_px : tuple of int
        ``(nx, ny)``, the full periodic extent (the array's shape reversed).
    calibration : dict
        Model parameters and solver record: ``p_u_um``, ``p_v_um``, ``alpha_um`` (scales of the
        components), ``iterations``, ``evaluations``, ``seconds``, ``first_guess_smd_um`` (the
        simulated SMD of the surface scaled without the probe simulation), ``ends_per_cm`` and
        ``picks_per_cm`` as realised on the pixel grid.
    """

    height_um: np.ndarray
    pixel_size_um: float
    friction: np.ndarray
    smd_simulated_um: dict[str, float]
    period_px: tuple[int, int]
    calibration: dict = field(default_factory=dict)


# --------------------------------------------------------------------------------------------
# Weave relief


def weave_matrix(weave: str) -> np.ndarray:
    """Interlacing matrix of one weave repeat.

    Parameters
    ----------
    weave : str
        ``plain`` (1/1), ``twill`` or ``twill_2_2``, ``twill_2_1``, ``twill_3_1`` (warp-faced),
        ``satin`` or ``satin_5`` (5-harness warp-faced satin, move 2).

    Returns
    -------
    ndarray of bool, shape (n_picks, n_ends)
        ``True`` where the warp is on top. Row i is weft pick i (along v), column j warp end j
        (along u). Twill diagonals rise by one end per pick.
    """
    if weave == "plain":
        return np.array([[True, False], [False, True]])
    twills = {"twill": (2, 2), "twill_2_2": (2, 2), "twill_2_1": (2, 1), "twill_3_1": (3, 1)}
    if weave in twills:
        up, down = twills[weave]
        n = up + down
        ii, jj = np.indices((n, n))
        return (jj - ii) % n < up
    if weave in ("satin", "satin_5"):
        ii, jj = np.indices((5, 5))
        return jj != (2 * ii) % 5
    raise ValueError(f"unknown weave {weave!r} (use plain, twill, twill_2_1, twill_2_2, twill_3_1 or satin)")


def _grid(ends_per_cm: float, picks_per_cm: float, weave: str, pixel_size_um: float,
          min_extent_mm: float) -> tuple[np.ndarray, int, int, int, int]:
    for name, value in (("ends_per_cm", ends_per_cm), ("picks_per_cm", picks_per_cm),
                        ("pixel_size_um", pixel_size_um), ("min_extent_mm", min_extent_mm)):
        if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0):
            raise ValueError(f"{name} must be a finite positive number (got {value!r})")
    matrix = weave_matrix(weave)
    picks_rep, ends_rep = matrix.shape
    pitch_u_um, pitch_v_um = 1e4 / ends_per_cm, 1e4 / picks_per_cm
    coarse = min(pitch_u_um, pitch_v_um)
    if coarse / pixel_size_um < _MIN_PITCH_PX:
        raise ValueError(f"pixel_size_um={pixel_size_um:g} is too coarse for a thread spacing of "
                         f"{coarse:.1f} um (need >= {_MIN_PITCH_PX:g} px per thread; use "
                         f"pixel_size_um <= {coarse / _MIN_PITCH_PX:.3g})")
    n_ends, n_picks, nx, ny = _extent(matrix.shape, pitch_u_um, pitch_v_um, pixel_size_um, min_extent_mm)
    if max(nx, ny) > _MAX_SIDE_PX:
        raise ValueError(f"surface of {nx} x {ny} px exceeds {_MAX_SIDE_PX} px per side; "
                         f"use a larger pixel_size_um than {pixel_size_um:g}")
    return matrix, n_ends, n_picks, nx, ny


def _extent(repeat: tuple[int, int], pitch_u_um: float, pitch_v_um: float, pixel_size_um: float,
            min_extent_mm: float) -> tuple[int, int, int, int]:
    """Ends, picks and pixels (nx, ny) of the synthesised surface: whole weave repeats
    (`repeat` = picks, ends per repeat) covering at least `min_extent_mm` each way."""
    picks_rep, ends_rep = repeat
    n_ends = ends_rep * math.ceil(min_extent_mm * 1e3 / (ends_rep * pitch_u_um) - 1e-9)
    n_picks = picks_rep * math.ceil(min_extent_mm * 1e3 / (picks_rep * pitch_v_um) - 1e-9)
    nx, ny = int(round(n_ends * pitch_u_um / pixel_size_um)), int(round(n_picks * pitch_v_um / pixel_size_um))
    return n_ends, n_picks, nx, ny


def synthesis_side_px(ends_per_cm: float, picks_per_cm: float, weave: str, pixel_size_um: float,
                      min_extent_mm: float = 10.0) -> tuple[int, int]:
    """The pixels (nx, ny) of the surface :func:`kes_surface` would synthesise (at most
    ``_MAX_SIDE_PX`` a side are allowed)."""
    _, _, nx, ny = _extent(weave_matrix(weave).shape, 1e4 / ends_per_cm, 1e4 / picks_per_cm, pixel_size_um, min_extent_mm)
    return nx, ny


def _thread_coords(n_px: int, n_threads: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    # Thread k spans [k, k+1) in thread units; its centre at k + 0.5.
    t = (np.arange(n_px) + 0.5) * n_threads / n_px
    k = np.floor(t).astype(np.intp)
    s = 2.0 * (t - k) - 1.0
    cross = np.sqrt(np.clip(1.0 - s * s, 0.0, None))  # elliptic cross-section, 1 at the crown
    # cosine crimp between consecutive thread centres (periodic)
    k0 = np.floor(t - 0.5).astype(np.intp)
    w = 0.5 * (1.0 - np.cos(np.pi * (t - 0.5 - k0)))
    return k, cross, np.stack([k0 % n_threads, (k0 + 1) % n_threads, w])


def weave_relief(ends_per_cm: float, picks_per_cm: float, weave: str, *, pixel_size_um: float,
                 min_extent_mm: float = 10.0, crimp: float = 0.5) -> tuple[np.ndarray, np.ndarray]:
    """Periodic relief of a woven fabric, dimensionless (thread crown height 1 for the thicker set).

    Parameters
    ----------
    ends_per_cm, picks_per_cm : float
        Warp ends per cm (spaced along u) and weft picks per cm (spaced along v).
    weave : str
        See :func:`weave_matrix`.
    pixel_size_um : float
        Pixel size in µm.
    min_extent_mm : float
        The map covers the smallest whole number of weave repeats at least this long per axis.
    crimp : float
        Crimp amplitude of a thread relative to the other set's thickness.

    Returns
    -------
    relief : ndarray, shape (ny, nx), float32
        Upper surface of the two thread layers; periodic over the whole array.
    warp_on_top : ndarray of bool, shape (ny, nx)
        Where the warp layer is the upper one.
    """
    matrix, n_ends, n_picks, nx, ny = _grid(ends_per_cm, picks_per_cm, weave, pixel_size_um, min_extent_mm)
    # thread thickness proportional to spacing; the thicker set has crown height 1
    d_warp, d_weft = 1.0 / ends_per_cm, 1.0 / picks_per_cm
    d_warp, d_weft = d_warp / max(d_warp, d_weft), d_weft / max(d_warp, d_weft)
    up = np.tile(matrix, (n_picks // matrix.shape[0], n_ends // matrix.shape[1])).astype(np.float32) * 2 - 1
    jx, cross_u, (b0, b1, wx) = _thread_coords(nx, n_ends)
    iy, cross_v, (a0, a1, wy) = _thread_coords(ny, n_picks)
    a0, a1, b0, b1 = (x.astype(np.intp) for x in (a0, a1, b0, b1))
    wy32, wx32 = wy.astype(np.float32)[:, None], wx.astype(np.float32)[None, :]
    # warp end j goes up/down along v following column j of the matrix
    z_warp = (up[a0] * (1 - wy32) + up[a1] * wy32)[:, jx]
    # weft pick i goes down where the warp is up, along u following row i
    z_weft = -(up[:, b0] * (1 - wx32) + up[:, b1] * wx32)[iy, :]
    warp = (d_warp * cross_u.astype(np.float32))[None, :] + (crimp * d_weft) * z_warp
    weft = (d_weft * cross_v.astype(np.float32))[:, None] + (crimp * d_warp) * z_weft
    on_top = warp >= weft
    return np.where(on_top, warp, weft), on_top


# --------------------------------------------------------------------------------------------
# Periodic Brownian roughness


def periodic_fbm_profile(n: int, hurst: float, *, pixel_size_um: float, cutoff_wavelength_um: float,
                         rng: np.random.Generator) -> np.ndarray:
    """Periodic 1-D fractional-Brownian-type profile, zero mean, unit mean absolute deviation.

    Power spectrum ``(k^2 + k0^2)^-(H + 1/2)``, k0 = 1 / cutoff: Brownian (index H) at wavelengths
    shorter than the cutoff, flat above it, so the profile does not drift over the period.
    """
    k = np.fft.rfftfreq(n, d=pixel_size_um)
    amp = (k * k + (1.0 / cutoff_wavelength_um) ** 2) ** (-(hurst + 0.5) / 2)
    amp[0] = 0.0
    spec = (rng.standard_normal(k.size) + 1j * rng.standard_normal(k.size)) * amp
    out = np.fft.irfft(spec, n=n)
    out -= out.mean()
    return (out / np.mean(np.abs(out))).astype(np.float32)


def periodic_fbm_surface(shape: tuple[int, int], hurst: float, *, pixel_size_um: float,
                         stretch_along_v: float = 1.0, cutoff_wavelength_um: float | None = None,
                         rng: np.random.Generator) -> np.ndarray:
    """Periodic anisotropic 2-D fractional-Brownian-type surface, zero mean, unit rms.

    Spectral synthesis on the torus: white noise filtered by
    ``(k_u^2 + (s k_v)^2 + k0^2)^-(H + 1)/2`` with s = `stretch_along_v` (s > 1: correlations
    s times longer along v than along u) and k0 = 1 / `cutoff_wavelength_um` (0 if None).
    """
    ny, nx = shape
    kv = np.fft.fftfreq(ny, d=pixel_size_um)[:, None] * stretch_along_v
    ku = np.fft.rfftfreq(nx, d=pixel_size_um)[None, :]
    k0 = 0.0 if cutoff_wavelength_um is None else 1.0 / cutoff_wavelength_um
    k2 = (ku * ku + kv * kv + k0 * k0).astype(np.float32)
    k2[0, 0] = np.inf
    # white noise drawn directly as a half-plane spectrum (the inverse real FFT keeps its
    # Hermitian part), which saves the forward transform
    spec = rng.standard_normal(k2.shape, dtype=np.float32) + 1j * rng.standard_normal(k2.shape, dtype=np.float32)
    spec *= k2 ** np.float32(-(hurst + 1) / 2)
    out = sfft.irfft2(spec, s=shape, workers=-1)
    return (out / out.std()).astype(np.float32)


# --------------------------------------------------------------------------------------------
# KES-FB4 measurement


def _cylinder(probe_radius_um: float, pixel_size_um: float) -> tuple[np.ndarray, np.ndarray]:
    half = int(probe_radius_um // pixel_size_um)
    offsets = np.arange(-half, half + 1)
    sag = np.sqrt(np.maximum(probe_radius_um ** 2 - (offsets * pixel_size_um) ** 2, 0.0)) - probe_radius_um
    return offsets, sag.astype(np.float32)


def _dilate_lines(lines: np.ndarray, offsets: np.ndarray, sag: np.ndarray, periodic: bool) -> np.ndarray:
    """Wire height along each column of `lines` (traverse along axis 0): grey dilation by the cylinder."""
    half = int(offsets.max(initial=0))
    if half == 0:
        return lines
    n = lines.shape[0]
    if periodic:
        padded = lines[np.arange(-half, n + half) % n]  # wraps even when n < the wire width
    else:
        pad = np.full((half,) + lines.shape[1:], -np.inf, dtype=lines.dtype)
        padded = np.concatenate([pad, lines, pad], axis=0)
    out = padded[half + offsets[0]: half + offsets[0] + n] + sag[0]
    for off, s in zip(offsets[1:], sag[1:]):
        np.maximum(out, padded[half + off: half + off + n] + s, out=out)
    return out


def _traverse_columns(n_cols: int, n_traverses: int) -> np.ndarray:
    """Columns for the traverses: a golden-ratio (Kronecker) sequence, sorted.

    Evenly spaced columns would alias with the weave (64 columns over 24 plain-weave repeats hit
    only 8 phases of the repeat); this sequence covers the phase within any period evenly.
    """
    if n_traverses >= n_cols:
        return np.arange(n_cols, dtype=np.intp)
    return np.sort((((np.arange(n_traverses) + 0.5) * 0.6180339887498949) % 1.0 * n_cols).astype(np.intp))


def _smd_of_lines(lines: np.ndarray, pixel_size_um: float, *, probe_radius_um: float,
                  traverse_mm: float, periodic: bool) -> float:
    """KES SMD from raw height lines [length along traverse, n traverses] (probe applied here)."""
    n_len, n_tr = lines.shape
    offsets, sag = _cylinder(probe_radius_um, pixel_size_um)
    wire = _dilate_lines(lines, offsets, sag, periodic)
    length = max(2, int(round(traverse_mm * 1e3 / pixel_size_um)))
    if periodic:
        # Traverse k starts at starts[k] and wraps: q whole periods plus a partial window of r
        # samples. Window sums come from cumulative sums, so no 2 cm copy is ever gathered.
        starts = (((np.arange(n_tr) * 0.41421356237309515) % 1.0) * n_len).astype(np.intp)
        q, r = divmod(length, n_len)
        cols = np.arange(n_tr)

        def window_sum(values: np.ndarray) -> np.ndarray:
            c = np.zeros((n_len + 1, n_tr))
            np.cumsum(values, axis=0, out=c[1:])
            end = starts + r
            part = np.where(end <= n_len, c[np.minimum(end, n_len), cols] - c[starts, cols],
                            c[n_len, cols] - c[starts, cols] + c[np.maximum(end - n_len, 0), cols])
            return q * c[n_len] + part

        mean = window_sum(wire) / length
        return float(np.mean(window_sum(np.abs(wire - mean[None, :].astype(wire.dtype))) / length))
    half = int(offsets.max(initial=0))
    valid = wire[half: n_len - half] if n_len > 2 * half else wire[:0]
    if valid.shape[0] < 2:
        raise ValueError(f"the map is only {n_len} px long along the traverse, shorter than the "
                         f"{2 * probe_radius_um:g} um wire")
    if valid.shape[0] > length:
        first = (valid.shape[0] - length) // 2
        valid = valid[first: first + length]
    z = valid.astype(np.float64)
    return float(np.mean(np.abs(z - z.mean(axis=0)), axis=0).mean())


def _check_direction(direction: str) -> str:
    if direction not in ("warp", "weft"):
        raise ValueError(f"direction must be 'warp' (traverse along v) or 'weft' (along u), got {direction!r}")
    return direction


def simulate_kes_smd(height_um: np.ndarray, pixel_size_um: float, direction: str, *,
                     probe_radius_um: float = KES_PROBE_RADIUS_UM, traverse_mm: float = KES_TRAVERSE_MM,
                     wire_length_um: float = 0.0, n_traverses: int = _N_TRAVERSES,
                     periodic: bool = True) -> float:
    """KES-FB4 geometric roughness SMD measured on a height map (simulated), in µm.

    Parameters
    ----------
    height_um : ndarray, shape (ny, nx)
        Heights in µm; rows along v, columns along u.
    pixel_size_um : float
        Pixel size in µm.
    direction : {"warp", "weft"}
        ``"warp"``: traverses along the warp, i.e. along v, down the columns of the array (axis 0),
        wire axis along u. ``"weft"``: along u, along the rows (axis 1), wire axis along v.
    probe_radius_um : float
        Wire radius (0.25 mm for the KES-FB4's 0.5 mm wire). 0 gives the raw profile.
    traverse_mm : float
        Traverse length (2 cm in KES). On a periodic map traverses wrap around; on a
        non-periodic map they are cut to the map (minus the wire's half width at each end).
    wire_length_um : float
        Length of wire in rigid contact across the traverse: the heights are first maximised over
        this width (flat window). 0 (default) is a line contact; see the module docstring.
    n_traverses : int
        Number of parallel traverses, evenly spread across the map; their SMDs are averaged.
    periodic : bool
        Whether the map wraps around (synthetic surfaces) or not (photos).

    Returns
    -------
    float
        SMD = mean over traverses of ``mean |T - mean(T)|`` over the traverse, where T is the
        wire's height (mean of each traverse removed, no detrending, no other filter).
    """
    _check_direction(direction)
    height = np.asarray(height_um, dtype=np.float32)
    if height.ndim != 2 or min(height.shape) < 2:
        raise ValueError(f"height_um must be a 2-D map, got shape {height.shape}")
    if not np.all(np.isfinite(height)):
        raise ValueError("height_um contains NaN or infinite values")
    for name, value in (("pixel_size_um", pixel_size_um), ("traverse_mm", traverse_mm)):
        if not (math.isfinite(value) and value > 0):
            raise ValueError(f"{name} must be finite and positive (got {value!r})")
    if not (math.isfinite(probe_radius_um) and probe_radius_um >= 0):
        raise ValueError(f"probe_radius_um must be finite and >= 0 (got {probe_radius_um!r})")
    if int(n_traverses) < 1:
        raise ValueError(f"n_traverses must be >= 1 (got {n_traverses!r})")
    if direction == "weft":
        height = height.T  # traverse along u becomes traverse along axis 0
    cols = _traverse_columns(height.shape[1], int(n_traverses))
    wire_px = int(round(wire_length_um / pixel_size_um))
    if wire_px > 1:
        height = ndi.maximum_filter1d(height, min(wire_px, height.shape[1]), axis=1,
                                      mode="wrap" if periodic else "nearest")
    lines = np.ascontiguousarray(height[:, cols])
    return _smd_of_lines(lines, pixel_size_um, probe_radius_um=probe_radius_um,
                         traverse_mm=traverse_mm, periodic=periodic)


# --------------------------------------------------------------------------------------------
# Calibration


def _smoothmin(a: float, b: float) -> float:
    """``(a**-4 + b**-4) ** -0.25`` for positive `a`, `b` (a smooth minimum), from the smaller
    of the two: the powers themselves overflowed for values below about 1e-77."""
    lo, hi = min(a, b), max(a, b)
    return lo * (1.0 + (lo / hi) ** 4) ** -0.25


def _solve_log(measure, target: np.ndarray, x0: np.ndarray, *, rtol: float = 2e-3,
               max_iter: int = 40) -> tuple[np.ndarray, np.ndarray, int, int]:
    """Solve log(measure(exp x)) = log(target) for x in R^2.

    Newton steps with a finite-difference Jacobian, then Broyden updates of it; a step that
    does not reduce the residual is halved, and after a failed step the Jacobian is recomputed.

    Returns
    -------
    x, measured, iterations, evaluations
    """
    log_t = np.log(target)
    n_eval = 0

    def resid_at(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        nonlocal n_eval
        n_eval += 1
        m = measure(np.exp(x))
        return m, np.log(np.maximum(m, 1e-12)) - log_t

    def fd_jacobian(x: np.ndarray, r: np.ndarray, step: float = 0.03) -> np.ndarray:
        jac = np.empty((2, 2))
        for k in range(2):
            xk = x.copy()
            xk[k] += step
            jac[:, k] = (resid_at(xk)[1] - r) / step
        return jac

    x = x0.astype(float).copy()
    m, r = resid_at(x)
    jac = None
    tol = math.log1p(rtol)
    for it in range(max_iter):
        if np.max(np.abs(r)) < tol:
            return x, m, it, n_eval
        if jac is None:
            jac = fd_jacobian(x, r)
        try:
            dx = -np.linalg.solve(jac, r)
        except np.linalg.LinAlgError:
            dx = np.full(2, np.nan)
        if not np.all(np.isfinite(dx)):
            dx = -r / np.maximum(np.abs(np.diag(jac)), 0.1)  # fall back to the diagonal
        dx = np.clip(dx, -1.5, 1.5)
        for _ in range(6):
            m_new, r_new = resid_at(x + dx)
            if np.linalg.norm(r_new) < np.linalg.norm(r):
                break
            dx = dx / 2
        else:
            jac = None  # no descent along this Jacobian: recompute it at the same point
            continue
        # Broyden's rank-one update with the step actually taken
        jac = jac + np.outer((r_new - r) - jac @ dx, dx) / float(dx @ dx)
        x, m, r = x + dx, m_new, r_new
    if np.max(np.abs(r)) < tol:
        return x, m, max_iter, n_eval
    raise ValueError(f"cannot reach SMD warp {target[0]:g} um, weft {target[1]:g} um with this weave "
                     f"(got {m[0]:.3g}, {m[1]:.3g} after {max_iter} iterations)")


class _Model:
    """The surface model's components and cheap evaluation on the traverse lines only."""

    def __init__(self, relief: np.ndarray, fibre: np.ndarray, rho_u: np.ndarray, rho_v: np.ndarray,
                 n_traverses: int) -> None:
        self.base = relief / np.mean(np.abs(relief - relief.mean())) + _FIBRE_WEIGHT * fibre
        self.rho_u, self.rho_v = rho_u, rho_v
        ny, nx = relief.shape
        self.cols = _traverse_columns(nx, n_traverses)  # warp traverses: columns (along v)
        self.rows = _traverse_columns(ny, n_traverses)  # weft traverses: rows (along u)
        self.base_warp = np.ascontiguousarray(self.base[:, self.cols])
        self.base_weft = np.ascontiguousarray(self.base[self.rows, :].T)

    @staticmethod
    def weights(p: np.ndarray) -> tuple[float, float, float]:
        p_u, p_v = float(p[0]), float(p[1])
        return _WEAVE_WEIGHT * _smoothmin(p_u, p_v), p_u, p_v

    def lines(self, p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        alpha, p_u, p_v = self.weights(p)
        warp = alpha * self.base_warp + p_u * self.rho_u[self.cols][None, :] + p_v * self.rho_v[:, None]
        weft = alpha * self.base_weft + p_u * self.rho_u[:, None] + p_v * self.rho_v[self.rows][None, :]
        return warp, weft

    def height(self, p: np.ndarray) -> np.ndarray:
        alpha, p_u, p_v = self.weights(p)
        height = alpha * self.base + p_u * self.rho_u[None, :] + p_v * self.rho_v[:, None]
        return (height - height.mean()).astype(np.float32)  # zero mean: only relief matters


def _build_model(kes: KesData, pixel_size_um: float, seed: int, min_extent_mm: float) -> _Model:
    relief, warp_on_top = weave_relief(kes.ends_per_cm, kes.picks_per_cm, kes.weave,
                                       pixel_size_um=pixel_size_um, min_extent_mm=min_extent_mm)
    ny, nx = relief.shape
    rng = np.random.default_rng(seed)
    pitch = min(1e4 / kes.ends_per_cm, 1e4 / kes.picks_per_cm)
    # fibres run along v on warp threads, along u on weft threads
    along_v = periodic_fbm_surface((ny, nx), _ROUGHNESS_HURST, pixel_size_um=pixel_size_um,
                                   stretch_along_v=_FIBRE_STRETCH, cutoff_wavelength_um=pitch, rng=rng)
    along_u = periodic_fbm_surface((ny, nx), _ROUGHNESS_HURST, pixel_size_um=pixel_size_um,
                                   stretch_along_v=1.0 / _FIBRE_STRETCH, cutoff_wavelength_um=pitch, rng=rng)
    fibre = np.where(warp_on_top, along_v, along_u)
    cutoff = _RIB_CUTOFF_MM * 1e3
    rho_u = periodic_fbm_profile(nx, _ROUGHNESS_HURST, pixel_size_um=pixel_size_um, cutoff_wavelength_um=cutoff, rng=rng)
    rho_v = periodic_fbm_profile(ny, _ROUGHNESS_HURST, pixel_size_um=pixel_size_um, cutoff_wavelength_um=cutoff, rng=rng)
    return _Model(relief, fibre, rho_u, rho_v, _N_TRAVERSES)


def friction_map(height_um: np.ndarray, pixel_size_um: float, miu: dict[str, float],
                 mmd: dict[str, float], *, periodic: bool = True) -> np.ndarray:
    """Friction coefficient map from MIU/MMD: slope ("ratchet") model, see the module docstring.

    Returns
    -------
    ndarray, shape (2, ny, nx), float32
        ``[0]``: sliding along +v (warp), ``[1]``: sliding along +u (weft). Mean MIU, mean
        absolute deviation MMD per direction (before clipping at 0); uniform MIU on a flat map.
    """
    height = np.asarray(height_um, dtype=np.float32)
    # Gaussian-like smoothing: three passes of a box of width ~2 sigma per axis (O(1) per pixel)
    width = max(1, int(round(2.0 * _FRICTION_SIGMA_UM / pixel_size_um)) | 1)
    smooth = height
    for axis in (0, 1):
        for _ in range(3):
            smooth = ndi.uniform_filter1d(smooth, width, axis=axis, mode="wrap" if periodic else "nearest")
    out = np.empty((2,) + height.shape, dtype=np.float32)
    for index, (direction, axis) in enumerate((("warp", 0), ("weft", 1))):
        if periodic:
            slope = (np.roll(smooth, -1, axis) - np.roll(smooth, 1, axis)) / (2 * pixel_size_um)
        else:
            slope = np.gradient(smooth, pixel_size_um, axis=axis)
        slope = slope - slope.mean()
        scale = float(np.mean(np.abs(slope)))
        mu = np.full(height.shape, miu[direction], dtype=np.float32)
        if scale > 0:
            mu += (mmd[direction] / scale) * slope
        out[index] = np.maximum(mu, 0.0)
    return out


def kes_surface(kes: KesData, *, pixel_size_um: float = 10.0, seed: int = 0, min_extent_mm: float = 10.0,
                calibrate: bool = True) -> KesSurface:
    """Synthesise a periodic fabric surface whose simulated KES-FB4 SMD matches `kes`.

    Parameters
    ----------
    kes : KesData
        The fabric's KES data (SMD warp/weft, MIU, MMD, thread densities, weave).
    pixel_size_um : float
        Pixel size in µm (10 by default).
    seed : int
        Seed of the roughness; the result is a deterministic function of all arguments.
    min_extent_mm : float
        The surface covers the smallest whole number of weave repeats at least this long.
    calibrate : bool
        If False, return the first guess: the components scaled so that the raw height profiles
        (no probe) have the given mean deviation; this is the baseline the probe model improves on.

    Returns
    -------
    KesSurface
        `smd_simulated_um` is measured with :func:`simulate_kes_smd` defaults; with `calibrate`
        it is within 0.2 % of `kes.smd_um` (the solver's tolerance).

    Raises
    ------
    ValueError
        Bad parameters, a pixel too coarse for the thread spacing, or an unreachable target.
    """
    start = time.perf_counter()
    target = np.array([kes.smd_um["warp"], kes.smd_um["weft"]], dtype=float)
    if not np.all(np.isfinite(target)) or np.any(target <= 0):
        raise ValueError(f"SMD must be finite and positive, got {kes.smd_um}")
    model = _build_model(kes, pixel_size_um, seed, min_extent_mm)

    def measure(p: np.ndarray, radius: float) -> np.ndarray:
        warp, weft = model.lines(p)
        kw = dict(probe_radius_um=radius, traverse_mm=KES_TRAVERSE_MM, periodic=True)
        return np.array([_smd_of_lines(warp, pixel_size_um, **kw), _smd_of_lines(weft, pixel_size_um, **kw)])

    # first guess: the raw profiles (no wire) have the given mean deviation; p = (p_u, p_v) and
    # p_v mostly drives the warp value, p_u the weft value, hence the reversed start.
    x0 = np.log(target[::-1].copy())
    x, _, it0, ev0 = _solve_log(lambda p: measure(p, 0.0), target, x0)
    first_guess = np.exp(x)
    first_smd = measure(first_guess, KES_PROBE_RADIUS_UM)
    iterations, evaluations = it0, ev0 + 1
    if calibrate:
        x, _, it1, ev1 = _solve_log(lambda p: measure(p, KES_PROBE_RADIUS_UM), target, x)
        iterations += it1
        evaluations += ev1
    p = np.exp(x)
    height = model.height(p)
    ny, nx = height.shape
    smd = {d: simulate_kes_smd(height, pixel_size_um, d) for d in ("warp", "weft")}
    friction = friction_map(height, pixel_size_um, kes.miu, kes.mmd)
    alpha, p_u, p_v = model.weights(p)
    _, n_ends, n_picks, _, _ = _grid(kes.ends_per_cm, kes.picks_per_cm, kes.weave, pixel_size_um, min_extent_mm)
    calibration = {
        "p_u_um": p_u, "p_v_um": p_v, "alpha_um": alpha,
        "iterations": iterations, "evaluations": evaluations,
        "first_guess_smd_um": {"warp": float(first_smd[0]), "weft": float(first_smd[1])},
        "ends_per_cm": n_ends / (nx * pixel_size_um * 1e-4),
        "picks_per_cm": n_picks / (ny * pixel_size_um * 1e-4),
        "seconds": time.perf_counter() - start,
    }
    return KesSurface(height_um=height, pixel_size_um=float(pixel_size_um), friction=friction,
                      smd_simulated_um=smd, period_px=(nx, ny), calibration=calibration)


def kes_relief_scale(kes: KesData, height_um: np.ndarray, pixel_size_um: float, *,
                     periodic: bool = False) -> float:
    """Factor by which to multiply a photo-derived height map so that it measures the KES SMD.

    One factor cannot match two SMDs unless the map's anisotropy happens to agree; the factor
    matches their geometric mean, i.e. minimises the sum of squared log errors of warp and weft.
    The measurement is :func:`simulate_kes_smd` (line-contact wire, traverses up to 2 cm, cut to
    the map when `periodic` is False). The shape of the map comes from the photo; only its scale
    is set here.

    Parameters
    ----------
    kes : KesData
    height_um : ndarray, shape (ny, nx)
        Heights from the photo (any scale; rows along v, columns along u).
    pixel_size_um : float
    periodic : bool
        True if the map wraps (a synthetic tile), False for a photo.

    Returns
    -------
    float
        The positive factor.

    Raises
    ------
    ValueError
        Flat, non-finite or too small map, or bad pixel size.
    """
    height = np.asarray(height_um, dtype=np.float64)
    if height.ndim != 2:
        raise ValueError(f"height_um must be a 2-D map, got shape {height.shape}")
    if not np.all(np.isfinite(height)):
        raise ValueError("height_um contains NaN or infinite values")
    height = (height - height.mean()).astype(np.float32)
    target = math.sqrt(kes.smd_um["warp"] * kes.smd_um["weft"])

    def measured(c: float) -> float:
        scaled = height * np.float32(c)
        return math.sqrt(simulate_kes_smd(scaled, pixel_size_um, "warp", periodic=periodic)
                         * simulate_kes_smd(scaled, pixel_size_um, "weft", periodic=periodic))

    raw = math.sqrt(simulate_kes_smd(height, pixel_size_um, "warp", probe_radius_um=0.0, periodic=periodic)
                    * simulate_kes_smd(height, pixel_size_um, "weft", probe_radius_um=0.0, periodic=periodic))
    if not raw > 0:
        raise ValueError("height map is flat along the KES traverses: no scale can give it an SMD")
    # secant iterations on log c; the wire makes the measurement sub-linear in c
    c0 = target / raw
    m0 = measured(c0)
    if not m0 > 0:
        raise ValueError("height map measures SMD 0 under the KES wire")
    c1 = c0 * target / m0
    m1 = measured(c1)
    for _ in range(30):
        if abs(math.log(m1 / target)) < 1e-3:
            break
        slope = (math.log(m1) - math.log(m0)) / (math.log(c1) - math.log(c0)) if c1 != c0 else 1.0
        slope = min(max(slope, 0.2), 5.0)
        c0, m0 = c1, m1
        c1 = c1 * math.exp(math.log(target / m1) / slope)
        m1 = measured(c1)
    return float(c1)
