"""Photographs to surfaces: lattice, tile averaging, shape from shading, scale, roughness.

The HAPTEX method (paper, Sect. 5.1): find the weave's repeating tile, average its repetitions
into a clean synthetic image, and recover heights by shape from shading. Shading gives shape,
not size: the height scale comes from ``--relief-um`` (RMS, or peak-to-valley with
``--relief-kind pv``), from Kawabata SMD (``--kes``), or from the stated default with a warning.

The surface of a periodic photo is a window of the averaged tile that repeats exactly on its
pixel array (sides that are lattice vectors, the lattice strained by at most 0.3 %,
:func:`haptex_compile.tiles.periodic_window`): shading solves it as a tile, the synthetic
roughness repeats on it, and the tables take their fast path. :func:`heights_at_image_px`
reads it at the photo's pixels.

A photo without a credible lattice is not periodic: its surface is a Brownian surface with the
fractal dimension and RMS estimated from the photo (issue: fractal roughness), and the compile
report says why.
"""
from __future__ import annotations

import logging
import time
from pathlib import Path
from typing import Any

import numpy as np

from haptex_compile.errors import InputError
from haptex_compile.sources import SourceOptions, SourceResult, _pixel_size, not_applying
from haptex_compile.surface import Surface

LOG = logging.getLogger("haptex.photo")
DEFAULT_RELIEF_RMS_UM = 10.0  # RMS height of a photo's relief when nothing else gives a scale


def _log_stage(spec: str, what: str, t0: float) -> None:
    """Log (INFO, shown with -v) that stage `what` of `spec` took since `t0` (perf_counter).
    Only the log has the times: the asset stays byte-identical from run to run."""
    LOG.info("%s: %s in %.1f s", spec, what, time.perf_counter() - t0)


def relief_scale(options: SourceOptions, spec: str, height: np.ndarray, pixel_size_um: float,
                 report: dict[str, Any]) -> np.ndarray:
    """Scale relative heights to µm from --relief-um, --kes or the default (recorded in `report`)."""
    from haptex_compile.shading import scale_relief

    h = np.asarray(height, dtype=float) - float(np.mean(height))
    if options.relief_um is not None:
        report["relief"] = f"{options.relief_um:g} um {options.relief_kind.upper()} from --relief-um"
        return scale_relief(h, options.relief_um, kind=options.relief_kind)
    if options.kes_path is not None:
        from haptex_compile.kes import kes_relief_scale
        from haptex_compile.kes_io import read_kes

        kes = read_kes(options.kes_path)
        if isinstance(kes, list):
            if len(kes) != 1:
                raise InputError(options.kes_path, f"--kes needs one fabric, the file has {len(kes)}")
            kes = kes[0]
        unit = scale_relief(h, 1.0, kind="rms")
        factor = kes_relief_scale(kes, unit, pixel_size_um)
        report["relief"] = f"scaled so the simulated KES SMD matches {Path(options.kes_path).name} ({kes.fabric})"
        return unit * factor
    LOG.warning("%s: no height scale given; using the default relief of %g um RMS (set --relief-um or --kes)",
                spec, DEFAULT_RELIEF_RMS_UM)
    report["relief"] = f"default {DEFAULT_RELIEF_RMS_UM:g} um RMS (no --relief-um or --kes)"
    return scale_relief(h, DEFAULT_RELIEF_RMS_UM, kind="rms")


ROUGHNESS_CELL_MM = 4.0  # the roughness repeats on a super-cell about this large (or what fits)
# The periodic window's pixels at most (64 Mi: 256 MiB a float32 copy, of which the shading
# solve and the tables hold many). Its side is ROUGHNESS_CELL_MM or more, so pixels finer than
# about 0.5 um would make it larger: such a pixel size is refused before anything is painted (at
# 0.001 um the painted window asked for 58 TiB; at 2 um, 2000 x 2002 px, the tables took over 10
# minutes).
MAX_WINDOW_PIXELS = 2 ** 26
# Samples per px of the tile the shading is solved on, and of the solved heights' average: at
# 1 sample per px the two bicubic resamplings blur a fine weave's shading (a plain weave of
# 12 px cells: 5.2 % of the image's variance lost, 3.0 % at 2 samples per px). Measured on
# bench/bench_photo.py's 8 cases with the light given: mean error 0.047 -> 0.035, the 12 px
# plain weave 0.167 -> 0.109 (one case 0.037 -> 0.045), same time. The light is still estimated
# on the 1-sample tile (the search is sensitive to its input; estimated-light errors within
# 0.02 of before).
SFS_SAMPLES_PER_PX = 2.0


def periodic_roughness(shape: tuple[int, int], t1: np.ndarray, t2: np.ndarray, hurst: float, rms_um: float,
                       pixel_size_um: float, seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Brownian roughness over an image that repeats on a super-cell (m1 t1, m2 t2) of the lattice.

    The field is synthesised periodic on a torus in the super-cell's own coordinates and mapped
    onto the image affinely (so an oblique lattice shears it slightly). The super-cell is about
    ``ROUGHNESS_CELL_MM`` on a side, as large as still fits well inside the image.

    Returns
    -------
    roughness_um, T1_px, T2_px
        The roughness on the image grid and the super-cell vectors (the surface's new period).
    """
    from haptex_compile.fractal import brownian_surface

    ny, nx = shape
    want_px = ROUGHNESS_CELL_MM * 1000.0 / pixel_size_um
    m1 = max(1, int(round(want_px / np.linalg.norm(t1))))
    m2 = max(1, int(round(want_px / np.linalg.norm(t2))))
    while m1 + m2 > 2:  # shrink until the super-cell's bounding box fits in 70 % of the image
        box = np.abs(m1 * t1) + np.abs(m2 * t2)
        if box[0] <= 0.7 * nx and box[1] <= 0.7 * ny:
            break
        if m1 * np.linalg.norm(t1) >= m2 * np.linalg.norm(t2):
            m1 = max(1, m1 - 1)
        else:
            m2 = max(1, m2 - 1)
    big1, big2 = m1 * t1, m2 * t2
    n1 = max(8, int(np.ceil(np.linalg.norm(big1))))
    n2 = max(8, int(np.ceil(np.linalg.norm(big2))))
    field = brownian_surface((n2, n1), hurst, pixel_size_um=pixel_size_um, rms_um=rms_um, seed=seed, periodic=True)
    inv = np.linalg.inv(np.column_stack([big1, big2]))
    y, x = np.mgrid[0:ny, 0:nx].astype(float)
    a = (inv[0, 0] * x + inv[0, 1] * y) * n1
    b = (inv[1, 0] * x + inv[1, 1] * y) * n2
    a0, b0 = np.floor(a), np.floor(b)
    fa, fb = a - a0, b - b0
    i0, j0 = np.mod(a0.astype(np.int64), n1), np.mod(b0.astype(np.int64), n2)
    i1, j1 = np.mod(i0 + 1, n1), np.mod(j0 + 1, n2)
    rough = ((field[j0, i0] * (1 - fa) + field[j0, i1] * fa) * (1 - fb)
             + (field[j1, i0] * (1 - fa) + field[j1, i1] * fa) * fb)
    return rough, big1, big2


MIN_REGION_PX = 256  # the averaging region's side is halved down to this (and 16 lattice cells)
REGION_TOLERANCE = 0.9  # a larger region is kept while it explains this share of the best's variance


def coherent_region(grey: np.ndarray, flat: np.ndarray, lattice, seed: int = 0) -> dict[str, Any]:
    """The central region of a photo over which to average the tile.

    Real fabrics are not exactly periodic over a whole photo: a weave that drifts by a fraction
    of a cell across the image averages into a blurred tile (a plain-weave photo of 2000 px
    with 12 px cells: the tile explains 1.7 % of the image's variance over the whole image, 36 %
    over the central 1000 px, 58 % over 500 px). The lattice is found again on central squares of
    half the side, down to ``MIN_REGION_PX`` or 16 cells, and the tile averaged on each; the
    largest region that explains at least ``REGION_TOLERANCE`` of the best share is kept (more
    cells average out more noise).

    Parameters
    ----------
    grey, flat : ndarray
        The photo and its illumination-flattened version.
    lattice : Lattice
        The lattice found on the whole photo (periodic).

    Returns
    -------
    dict
        ``box`` (x0, y0, rows, cols), ``lattice``, ``flat`` and ``tile`` (:class:`TileAverage`) of
        the region, ``explained`` (its share of variance explained by the tile) and ``tried``
        (side, share) for every region tried, the whole photo first.
    """
    from haptex_compile.lattice import find_lattice
    from haptex_compile.tiles import average_tile, flatten_illumination

    def explained_by(f: np.ndarray, t) -> float:
        return max(0.0, 1.0 - float(np.var(f - t.synthetic)) / (float(np.var(f)) or 1.0))

    ny, nx = grey.shape
    tile = average_tile(flat, lattice)
    regions = [dict(box=(0, 0, ny, nx), lattice=lattice, flat=flat, tile=tile, explained=explained_by(flat, tile))]
    cell = float(max(np.linalg.norm(lattice.t1_px), np.linalg.norm(lattice.t2_px)))
    # A smaller region can only be chosen if it beats the whole photo by 1 / REGION_TOLERANCE.
    side = min(ny, nx) // 2 if regions[0]["explained"] < REGION_TOLERANCE else 0
    while side >= max(MIN_REGION_PX, 16 * cell):
        y0, x0 = (ny - side) // 2, (nx - side) // 2
        crop = grey[y0:y0 + side, x0:x0 + side]
        flat_c = flatten_illumination(crop, sigma_px=side / 8.0)
        lat_c = find_lattice(flat_c, seed=seed)
        if lat_c.periodic:
            tile_c = average_tile(flat_c, lat_c)
            regions.append(dict(box=(x0, y0, side, side), lattice=lat_c, flat=flat_c, tile=tile_c,
                                explained=explained_by(flat_c, tile_c)))
        side //= 2
    best = max(r["explained"] for r in regions)
    chosen = next(r for r in regions if r["explained"] >= REGION_TOLERANCE * best)
    chosen["tried"] = [(max(r["box"][2:]), r["explained"]) for r in regions]
    return chosen


def _check_window_pixels(spec: str, pixel_size_um: float, rows: int, cols: int, at_least: bool = False) -> None:
    """Refuse a periodic window of more than ``MAX_WINDOW_PIXELS`` (an implausible pixel size);
    `at_least`: `rows` x `cols` is the smallest the window can be."""
    if rows * cols > MAX_WINDOW_PIXELS:
        raise InputError(spec, f"at {pixel_size_um:g} um pixels the surface would be a periodic window of"
                               f" {'at least ' if at_least else ''}{cols} x {rows} px (the roughness repeats on"
                               f" {ROUGHNESS_CELL_MM:g} mm),"
                               f" above {MAX_WINDOW_PIXELS / 2 ** 20:.0f} Mpx; check the pixel size (--pixel-size or"
                               " the image's metadata)")


def photo_source(spec: str, options: SourceOptions) -> SourceResult:
    """Compile-side pipeline for a photograph file."""
    from haptex_compile.io_images import read_image

    image = read_image(spec)
    px, note = _pixel_size(options, spec, image.pixel_size_um, image.metadata_note)
    report: dict[str, Any] = {"pixel_size": f"{px:g} um {note}", "image_shape": list(image.grey.shape)}
    grey = image.grey
    if float(np.std(grey)) < 1e-4:
        raise InputError(spec, "image is constant: no texture to compile")
    return photo_surface(grey, px, options, spec, report)


def photo_surface(grey: np.ndarray, pixel_size_um: float, options: SourceOptions, spec: str,
                  report: dict[str, Any]) -> SourceResult:
    """Surface from a grey image in [0, 1] (no file I/O)."""
    from haptex_compile.fractal import brownian_surface, roughness_from_residual
    from haptex_compile.lattice import Lattice, find_lattice
    from haptex_compile.shading import Light, estimated_light_note, shape_from_shading, weave_visibility
    from haptex_compile.surface import periodic_surface_from_tile
    from haptex_compile.tiles import average_tile, flatten_illumination, paint_tile, periodic_window

    ny, nx = grey.shape
    t0 = time.perf_counter()
    flat = flatten_illumination(grey, sigma_px=max(ny, nx) / 8.0)
    lattice = find_lattice(flat, seed=options.seed)
    report["lattice"] = {"periodic": lattice.periodic, "confidence": float(lattice.confidence), "reason": lattice.reason}
    light = None if options.light is None else Light(slant_deg=options.light[0], tilt_deg=options.light[1])
    if not lattice.periodic:
        # No repeating tile: the fractal model (paper, Sect. 6) with the photo's own roughness.
        estimate, _ = roughness_from_residual(flat - flat.mean(), pixel_size_um=pixel_size_um)
        hurst = float(np.clip(estimate.hurst, 0.05, 0.95))
        # Scaled as a solved relief is (--relief-kind pv and --kes were ignored here: the
        # height was --relief-um as an RMS, or the default).
        unit = brownian_surface((ny, nx), hurst, pixel_size_um=pixel_size_um, rms_um=1.0, seed=options.seed)
        h = relief_scale(options, spec, unit, pixel_size_um, report)
        rms = float(np.std(h))
        ignored = [flag for flag, given in (("--light", options.light is not None), ("--sfs", options.sfs != "default"),
                                            ("--roughness none", options.roughness == "none")) if given]
        said = not_applying(spec, ignored, ": the photo has no credible lattice, and its surface is a Brownian surface"
                                           " of its roughness, not heights from shading")
        if said is not None:
            LOG.warning("%s", said)
        report["surface"] = f"not periodic ({lattice.reason}): Brownian surface, H = {hurst:.3f} (D = {3 - hurst:.3f}) from the photo"
        return SourceResult(Surface(h, pixel_size_um, False), "photo", spec, report,
                            roughness={"hurst": hurst, "dimension": 3.0 - hurst, "rms_um": rms},
                            source_image=grey)
    region = coherent_region(grey, flat, lattice, seed=options.seed)
    _log_stage(spec, "lattice and averaged tile", t0)
    (x0, y0, ny, nx), lattice, flat, tile, explained = region["box"], region["lattice"], region["flat"], region["tile"], region["explained"]
    report["lattice"]["tile_explained_variance"] = explained
    if (ny, nx) != grey.shape:
        report["lattice"].update(
            region_px=[x0, y0, nx, ny], t1_px=lattice.t1_px.tolist(), t2_px=lattice.t2_px.tolist(),
            region_note=("the tile is averaged over this central region, where the weave repeats best (share of the"
                         " variance explained, by region side: " + ", ".join(f"{side} px {e:.1%}" for side, e in region["tried"]) + ")"))
        LOG.info("%s: tile averaged over the central %d x %d px (explains %.1f%% of its variance; the whole image %.1f%%)",
                 spec, nx, ny, 100 * explained, 100 * region["tried"][0][1])
    roughness = None
    if options.roughness != "none":
        est, rms_img = roughness_from_residual(flat - tile.synthetic, pixel_size_um=pixel_size_um)
        # Same grey-to-height ratio as the pattern (shading is linear in slope to first order).
        rough_ratio = float(rms_img) / (float(np.std(tile.synthetic)) or 1.0)
        hurst = float(np.clip(est.hurst, 0.02, 0.98))
        roughness = {"hurst": hurst, "dimension": 3.0 - hurst, "hurst_ci": [float(est.ci_low), float(est.ci_high)]}
    # The surface is a window that is exactly periodic on the pixel array (the lattice strained by
    # at most 0.3 %), about ROUGHNESS_CELL_MM or more on a side: shading solves it as a periodic
    # tile (better posed than a whole photo with free edges, and smaller), the roughness repeats
    # on it, and the tables take their fast path. Lattices with no such window: the whole image,
    # with the roughness on a super-cell of the lattice.
    min_px = int(np.ceil(ROUGHNESS_CELL_MM * 1000.0 / pixel_size_um))
    _check_window_pixels(spec, pixel_size_um, min_px, min_px, at_least=True)
    window = periodic_window(lattice.basis_px, min_px=min_px,
                             max_px=max(1024, int(np.ceil(ROUGHNESS_CELL_MM * 2000.0 / pixel_size_um))))
    if window is not None:
        _check_window_pixels(spec, pixel_size_um, *window[1])
    sfs_tile = average_tile(flat, lattice, samples_per_px=SFS_SAMPLES_PER_PX)
    if window is not None:
        basis, (rows, cols) = window
        image = paint_tile(sfs_tile.tile, basis, (rows, cols))
        solved_on = f"a periodic window of {cols} x {rows} px"
    else:
        basis, (rows, cols), image = lattice.basis_px, (ny, nx), sfs_tile.synthetic
        solved_on = f"the whole image ({nx} x {ny} px)"
    light_on = None
    light_notes = []
    if light is None:
        t0 = time.perf_counter()
        light, light_on = _light_from_small_window(tile.tile, lattice.basis_px)
        if light is not None:
            _log_stage(spec, f"light estimated on {light_on}", t0)
            light_notes.append(estimated_light_note(light, on=light_on))
            LOG.warning("%s: %s", spec, light_notes[-1])
        else:
            # The search then runs on the image solved, up to 1024 px at full resolution:
            # 17-58 s on bench_photo's 1 Mpx photos.
            LOG.info("%s: no small periodic window: estimating the light on %s (up to a minute;"
                     " --light skips it)", spec, solved_on)
    t0 = time.perf_counter()
    sfs = shape_from_shading(image, pixel_size_um=pixel_size_um, light=light, method=options.sfs, periodic=window is not None,
                             weave_basis_px=basis)
    _log_stage(spec, f"heights from shading on {solved_on}" + ("" if light is not None else ", light estimated there"), t0)
    for w in sfs.warnings:
        LOG.warning("%s: %s", spec, w)
    visibility, weave_tilt = weave_visibility(sfs.light, basis)
    # The asset's report keeps every warning, the estimated light's included.
    report["shading"] = {"method": sfs.method, "light_slant_deg": sfs.light.slant_deg, "light_tilt_deg": sfs.light.tilt_deg,
                         "light_given": options.light is not None, "warnings": light_notes + list(sfs.warnings),
                         "solved_on": solved_on, "weave_visibility": visibility, "weave_direction_tilt_deg": weave_tilt}
    if light_on is not None:
        report["shading"]["light_estimated_on"] = light_on
        report["shading"]["light_albedo_at_bound"] = sfs.light.albedo_at_bound
    # Average the heights over the lattice as well, so the surface repeats exactly (a whole
    # image's solve has slow ramps from its free edges: flattened out first, as for the photo).
    cell = Lattice(True, basis[:, 0], basis[:, 1], 1.0, "surface lattice")
    averaged = average_tile(sfs.height, cell, flatten_sigma_px=None if window is not None else "auto",
                            samples_per_px=SFS_SAMPLES_PER_PX)
    height_rel = paint_tile(averaged.tile, basis, (rows, cols))
    height = relief_scale(options, spec, height_rel, pixel_size_um, report)
    if roughness is not None:
        roughness["rms_um"] = float(np.std(height)) * rough_ratio
        if rough_ratio > 1.0:
            # Woven relief usually dominates its roughness; a residual larger than the pattern
            # more often means the tile missed it (a skewed or stretched weave averages away).
            roughness["warning"] = (
                f"the repeating tile explains {explained:.1%} of the image's variance: the roughness from the"
                f" residual is {rough_ratio:.1f} x the relief ({roughness['rms_um']:.3g} um RMS); check the lattice,"
                " or use --roughness none")
            LOG.warning("%s: %s", spec, roughness["warning"])
        if window is not None:
            rough = brownian_surface((rows, cols), roughness["hurst"], pixel_size_um=pixel_size_um, rms_um=roughness["rms_um"],
                                     seed=options.seed, periodic=True)
            roughness["note"] = "Brownian roughness from the photo's residual, periodic on the surface's window"
        else:
            rough, t1, t2 = periodic_roughness(height.shape, basis[:, 0], basis[:, 1], roughness["hurst"], roughness["rms_um"],
                                               pixel_size_um, options.seed)
            basis = np.column_stack([t1, t2])
            roughness["note"] = "Brownian roughness from the photo's residual, periodic on a super-cell of the lattice"
        height = height + rough
        report["roughness"] = roughness
    if window is not None:
        surface = periodic_surface_from_tile(height, pixel_size_um)
        report["surface"] = {"window_px": [cols, rows], "window_t1_px": basis[:, 0].tolist(), "window_t2_px": basis[:, 1].tolist(),
                             "note": "the surface is this window, periodic on its pixel array; the lattice strained to fit it"}
    else:
        # Reference cell near the image centre, so every sample it needs is inside the image.
        centre = np.array([nx, ny], dtype=float) / 2.0 - (basis[:, 0] + basis[:, 1]) / 2.0
        surface = Surface(height, pixel_size_um, True, basis[:, 0], basis[:, 1], np.floor(centre))
    lat = {"t1_px": np.asarray(lattice.t1_px, float), "t2_px": np.asarray(lattice.t2_px, float),
           "confidence": float(lattice.confidence)}
    return SourceResult(surface, "photo", spec, report, lattice=lat, roughness=roughness, source_image=grey)


def _light_from_small_window(tile: np.ndarray, basis_px: np.ndarray):
    """The light estimated on a small periodic window of the averaged tile, and its description.

    The light search solves its candidates on images of at most a few hundred pixels; a large
    window reduced that far averages the weave's cells away. A window of at most
    ``tiles.SMALL_WINDOW_PX`` (the lattice strained by up to ``tiles.SMALL_WINDOW_STRAIN``: the
    light does not depend on a 2 % strain) keeps full resolution. Measured with
    ``bench/bench_photo.py``'s eight rendered reliefs: median height error 0.25 against 0.66
    with the light estimated on the surface's window. (None, None) when no such window exists.
    """
    from haptex_compile.shading import estimate_light
    from haptex_compile.tiles import paint_tile, small_periodic_window

    small = small_periodic_window(basis_px)
    if small is None:
        return None, None
    basis, (rows, cols) = small
    light, _ = estimate_light(paint_tile(tile, basis, (rows, cols)))
    return light, f"a periodic window of {cols} x {rows} px"


def heights_at_image_px(result: SourceResult, x_px: np.ndarray, y_px: np.ndarray) -> np.ndarray:
    """Heights (µm) of a photo's surface at positions given in the photo's pixels.

    When the surface is a periodic window (``report["surface"]["window_px"]``), its lattice is the
    photo's strained to fit the window: photo pixel x lies at window pixel ``B' B^-1 x`` (B the
    photo's lattice, B' the window's). Otherwise the surface is on the photo's own grid. When the
    tile was averaged on a central region (``report["lattice"]["region_px"]``), positions count
    from that region's corner (and hold near it: the weave drifts away from it).
    """
    from haptex_compile.surface import sample_height

    x = np.asarray(x_px, dtype=float)
    y = np.asarray(y_px, dtype=float)
    region = result.report.get("lattice", {}).get("region_px")
    if region is not None:  # the tile was averaged on a central region: its pixels are the surface's
        x, y = x - region[0], y - region[1]
    window = result.report.get("surface")
    if isinstance(window, dict) and "window_px" in window:
        found = np.column_stack([result.lattice["t1_px"], result.lattice["t2_px"]])
        to_window = np.column_stack([window["window_t1_px"], window["window_t2_px"]]) @ np.linalg.inv(found)
        x, y = to_window[0, 0] * x + to_window[0, 1] * y, to_window[1, 0] * x + to_window[1, 1] * y
    px_mm = result.surface.pixel_size_mm
    return sample_height(result.surface, x * px_mm, y * px_mm)
