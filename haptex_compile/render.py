"""Reference renderer: every frame of every contactor computed directly from the height map.

Slow but direct: for each frame and contactor it samples the surface along the contactor's own
path over a stretch reaching ``margin_ms`` beyond the frame window, at a fine step no longer
than one pixel, and applies :mod:`haptex_compile.frame_analysis`. A contactor too slow for any
frequency the map resolves to reach the band (``CRAWL_FRACTION``) feels nothing. Tables are
checked against it (issue: tables) and ``haptex-play --mode direct`` uses it. It needs the
compiler's dependencies (scipy, through :mod:`haptex_compile.surface`): the player loads it
lazily, only for ``--mode direct``, so that table playback stays on numpy, h5py and pyusb.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

from haptex_compile.colours import TwoColourModel
from haptex_compile.frame_analysis import (
    ANALYSIS_RATE_HZ,
    RESOLVED_STOP,
    AnalysisSettings,
    across_spacing_mm,
    footprint_offsets,
    frame_window,
    stretch_channel_power,
)
from haptex_compile.surface import Surface, count_text, refuse_out_of_scale, sample_height

Trajectory = Callable[[np.ndarray], tuple[np.ndarray, np.ndarray, np.ndarray]]
_VELOCITY_DT_S = 1e-3
_STILL_MM_S = 1e-6
# The largest array of footprint path heights one frame may sample (bytes, float64); a frame's
# peak is about 7 times it (measured at 0.2-20 um pixels, 10-200 mm/s). Pixels far finer than
# the scene needs asked for tens of GB (a 16 px map of 0.001 um pixels: killed at 24 GB, both
# of the compiler's check threads at once); such a frame is refused with the sizes instead.
MAX_STROKE_BYTES = 2 ** 28
# A contactor this slow that every frequency the map resolves lies below this fraction of the
# band's low edge feels nothing: the band's weight there is below 0.05^4 = 6.3e-6 (its f^4
# roll-off). Its frame would span the footprint's passage (2 x 4 sigma / speed: 2000 s at
# 0.001 mm/s) at the analysis rate, and a tracked finger at rest jitters at such speeds.
CRAWL_FRACTION = 0.05


@dataclass(frozen=True)
class Frames:
    """Per-frame, per-contactor results [n_frames, n_contactors]."""

    a40: np.ndarray
    a320: np.ndarray
    intensity_p: np.ndarray
    intensity_np: np.ndarray
    out_of_gamut: np.ndarray


def contactor_positions(o_u: np.ndarray, o_v: np.ndarray, phi_deg: np.ndarray, contactors_mm: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Positions (u_i, v_i) = o + R(phi) (x_i, y_i) (paper, Sect. 5.2); shapes [..., n_contactors]."""
    phi = np.deg2rad(np.asarray(phi_deg, dtype=float))[..., None]
    x, y = contactors_mm[:, 0], contactors_mm[:, 1]
    c, s = np.cos(phi), np.sin(phi)
    return np.asarray(o_u, float)[..., None] + c * x - s * y, np.asarray(o_v, float)[..., None] + s * x + c * y


def point_intensities(
    surface: Surface,
    model: TwoColourModel,
    settings: AnalysisSettings,
    path: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]],
    t_centre_s: float,
) -> tuple[float, float]:
    """Channel intensities (I_p, I_np) of one contactor following `path` in the frame centred at `t_centre_s`.

    Parameters
    ----------
    path : callable
        ``path(t_s) -> (u_mm, v_mm)`` for an array of times.
    """
    t0 = np.array([t_centre_s - _VELOCITY_DT_S, t_centre_s + _VELOCITY_DT_S])
    pu, pv = path(t0)
    vel = np.array([pu[1] - pu[0], pv[1] - pv[0]]) / (2 * _VELOCITY_DT_S)
    speed = float(np.hypot(*vel))
    if not np.isfinite(speed) or speed < _STILL_MM_S:
        return 0.0, 0.0
    px_mm = surface.pixel_size_mm
    if speed * RESOLVED_STOP * 0.5 / px_mm < CRAWL_FRACTION * model.band.low_hz:
        return 0.0, 0.0
    sigma_t = settings.footprint_sigma_mm / speed
    half_s = settings.window_half_s(speed) + settings.margin_ms / 1000.0
    decimation = max(1, int(np.ceil(speed / ANALYSIS_RATE_HZ / px_mm)))
    n_out = 2 * int(np.ceil(half_s * ANALYSIS_RATE_HZ / 2.0)) + 2
    n_fine = n_out * decimation
    fine_dt = 1.0 / (ANALYSIS_RATE_HZ * decimation)
    b, g = footprint_offsets(settings.footprint_sigma_mm, across_spacing_mm(settings.footprint_sigma_mm, px_mm, speed, model))
    n_bytes = 8 * b.size * n_fine
    if n_bytes > MAX_STROKE_BYTES:  # (the message is made only then: direct playback calls this per frame)
        if decimation > 1:  # samples a pixel apart: the pixels set their count
            advice = "give it coarser pixels (resample it) or check its pixel size"
        else:  # samples at the analysis rate over the frame's window, long at a low speed
            advice = (f"the frame's window spans {2 * half_s:.4g} s at that speed (the footprint's passage); raise"
                      " the scene's slowest speed")
        refuse_out_of_scale(surface, n_bytes, MAX_STROKE_BYTES, "the reference renderer",
                            f"the heights of {b.size} x {count_text(n_fine)} path samples", f"per frame (at {speed:g} mm/s)", advice)
    offsets = (np.arange(n_fine) - (n_fine - 1) / 2.0) * fine_dt
    window = frame_window(offsets[::decimation], settings.frame_ms, sigma_t)
    u, v = path(t_centre_s + offsets)
    normal = np.array([-vel[1], vel[0]]) / speed
    heights = sample_height(surface, u[None, :] + b[:, None] * normal[0], v[None, :] + b[:, None] * normal[1])
    pp, pnp = stretch_channel_power(heights, fine_dt, decimation, window, model, speed, px_mm)
    return float(np.sqrt(np.dot(g, pp))), float(np.sqrt(np.dot(g, pnp)))


def render_frames(
    surface: Surface,
    model: TwoColourModel,
    settings: AnalysisSettings,
    contactors_mm: np.ndarray,
    frame_centres_s: np.ndarray,
    trajectory: Trajectory,
) -> Frames:
    """Render every frame directly.

    Parameters
    ----------
    surface : Surface
    model : TwoColourModel
    settings : AnalysisSettings
    contactors_mm : ndarray [n_contactors, 2]
        Device coordinates (x_i, y_i) in mm.
    frame_centres_s : ndarray [n_frames]
    trajectory : callable
        ``trajectory(t_s) -> (o_u_mm, o_v_mm, phi_deg)`` evaluated at arbitrary times (the caller
        interpolates or extrapolates its samples).

    Returns
    -------
    Frames
    """
    contactors_mm = np.asarray(contactors_mm, dtype=float).reshape(-1, 2)
    centres = np.asarray(frame_centres_s, dtype=float).ravel()
    shape = (centres.size, contactors_mm.shape[0])
    ip = np.zeros(shape)
    inp = np.zeros(shape)
    for k, tc in enumerate(centres):
        for i in range(shape[1]):
            def path(t: np.ndarray, i: int = i) -> tuple[np.ndarray, np.ndarray]:
                ou, ov, phi = trajectory(np.asarray(t, dtype=float))
                pu, pv = contactor_positions(ou, ov, phi, contactors_mm[i : i + 1])
                return pu[..., 0], pv[..., 0]

            ip[k, i], inp[k, i] = point_intensities(surface, model, settings, path, float(tc))
    d = model.decompose(ip, inp)
    return Frames(d.a40, d.a320, ip, inp, d.out_of_gamut)


def straight_path(u0_mm: float, v0_mm: float, speed_mm_s: float, direction_deg: float, t_centre_s: float = 0.0):
    """A constant-velocity path through (u0, v0) at time `t_centre_s`: ``path(t) -> (u, v)``."""
    d = np.deg2rad(direction_deg)
    du, dv = speed_mm_s * np.cos(d), speed_mm_s * np.sin(d)

    def path(t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        t = np.asarray(t, dtype=float) - t_centre_s
        return u0_mm + du * t, v0_mm + dv * t

    return path


def asset_model(asset) -> tuple[Surface, TwoColourModel, AnalysisSettings]:
    """Rebuild the surface, model and analysis settings an asset was compiled with.

    `asset` is a :class:`playback.asset.Asset` read with ``load_surface=True``.
    """
    from haptex_compile.colours import Band
    from haptex_compile.thresholds import ThresholdCurves

    if asset.height_um is None:
        raise ValueError("the asset was read without its surface (load_surface=True is needed)")
    p = asset.perception
    curves = ThresholdCurves(np.asarray(p["frequency_hz"], float), np.asarray(p["threshold_p_um"], float),
                             np.asarray(p["threshold_np_um"], float), str(p.get("threshold_provenance", "asset")))
    band = Band(float(p.get("band_low_hz", 10.0)), float(p.get("band_high_pass_hz", 600.0)), float(p.get("band_high_stop_hz", 800.0)))
    base = np.asarray(p["base_frequencies_hz"], float)
    model = TwoColourModel(curves, band, (float(base[0]), float(base[1])), float(p.get("summation_exponent", 1.23)))
    settings = AnalysisSettings(frame_ms=float(p.get("frame_ms", asset.tables.frame_ms)),
                                footprint_sigma_mm=float(p.get("footprint_sigma_mm", 0.25)),
                                margin_ms=float(p.get("margin_ms", 300.0)))
    height = np.asarray(asset.height_um, dtype=float)
    if asset.surface_periodic:
        geo = asset.surface_geometry
        surface = Surface(height, asset.pixel_size_um, True, np.asarray(geo["period_t1_px"], float),
                          np.asarray(geo["period_t2_px"], float), np.asarray(geo["cell_origin_px"], float))
    else:
        surface = Surface(height, asset.pixel_size_um, False)
    return surface, model, settings


def render_direct(asset, frame_centres_s: np.ndarray, trajectory: Trajectory) -> tuple[np.ndarray, np.ndarray]:
    """Reference frames for ``haptex-play --mode direct``: (a40, a320) [n_frames, n_contactors] in µm.

    Parameters
    ----------
    asset : playback.asset.Asset
        Read with ``load_surface=True``.
    frame_centres_s : ndarray [n_frames]
    trajectory : callable
        ``trajectory(t_s) -> (o_u_mm, o_v_mm, phi_deg)``.
    """
    surface, model, settings = asset_model(asset)
    frames = render_frames(surface, model, settings, asset.contactors_mm, frame_centres_s, trajectory)
    return frames.a40, frames.a320
