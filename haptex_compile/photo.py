"""Photographs to surfaces: lattice, tile averaging, shape from shading, scale, roughness.

The HAPTEX method (paper, Sect. 5.1): find the weave's repeating tile, average its repetitions
into a clean synthetic image, and recover heights by shape from shading. Shading gives shape,
not size: the height scale comes from ``--relief-um`` (RMS, or peak-to-valley with
``--relief-kind pv``), from Kawabata SMD (``--kes``), or from the stated default with a warning.

A photo without a credible lattice is not periodic: its surface is a Brownian surface with the
fractal dimension and RMS estimated from the photo (issue: fractal roughness), and the compile
report says why.
"""
from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import numpy as np

from haptex_compile.errors import InputError
from haptex_compile.sources import SourceOptions, SourceResult, _pixel_size
from haptex_compile.surface import Surface

LOG = logging.getLogger("haptex.photo")
DEFAULT_RELIEF_RMS_UM = 10.0  # RMS height of a photo's relief when nothing else gives a scale


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


def _tile_heights(tile, lattice, shape: tuple[int, int], pixel_size_um: float, light, method: str):
    """Relative heights over an image of `shape` from the averaged tile, by shape from shading.

    The tile is painted over a window that is exactly periodic (the lattice strained by at most
    0.3 %, :func:`haptex_compile.tiles.periodic_window`) and solved as a periodic tile: better
    posed than the whole image with free edges (no ramps shading cannot see) and a fraction of
    its size. The heights are averaged over the window's lattice and painted back with the
    photo's own. Lattices with no such window: the synthetic image is solved whole. Returns the
    heights, the solver's result and what was solved (for the report).
    """
    from haptex_compile.lattice import Lattice
    from haptex_compile.shading import shape_from_shading
    from haptex_compile.tiles import average_tile, paint_tile, periodic_window

    window = periodic_window(lattice.basis_px, max_px=max(256, min(1024, max(shape))))
    if window is None:
        sfs = shape_from_shading(tile.synthetic, pixel_size_um=pixel_size_um, light=light, method=method)
        # Average the heights over the lattice as well, so the surface repeats exactly.
        return average_tile(sfs.height, lattice).synthetic, sfs, f"the whole image ({shape[1]} x {shape[0]} px)"
    basis_w, (rows, cols) = window
    image = paint_tile(tile.tile, basis_w, (rows, cols))
    sfs = shape_from_shading(image, pixel_size_um=pixel_size_um, light=light, method=method, periodic=True)
    cell = Lattice(True, basis_w[:, 0], basis_w[:, 1], 1.0, "periodic window")
    h_tile = average_tile(sfs.height, cell, flatten_sigma_px=None, samples_per_px=1.0).tile
    return paint_tile(h_tile, lattice.basis_px, shape), sfs, f"a periodic window of {cols} x {rows} px"


def photo_surface(grey: np.ndarray, pixel_size_um: float, options: SourceOptions, spec: str,
                  report: dict[str, Any]) -> SourceResult:
    """Surface from a grey image in [0, 1] (no file I/O)."""
    from haptex_compile.fractal import brownian_surface, roughness_from_residual
    from haptex_compile.lattice import find_lattice
    from haptex_compile.shading import Light
    from haptex_compile.tiles import average_tile, flatten_illumination

    ny, nx = grey.shape
    flat = flatten_illumination(grey, sigma_px=max(ny, nx) / 8.0)
    lattice = find_lattice(flat, seed=options.seed)
    report["lattice"] = {"periodic": lattice.periodic, "confidence": float(lattice.confidence), "reason": lattice.reason}
    light = None if options.light is None else Light(slant_deg=options.light[0], tilt_deg=options.light[1])
    if not lattice.periodic:
        # No repeating tile: the fractal model (paper, Sect. 6) with the photo's own roughness.
        estimate, _ = roughness_from_residual(flat - flat.mean(), pixel_size_um=pixel_size_um)
        hurst = float(np.clip(estimate.hurst, 0.05, 0.95))
        rms = options.relief_um if options.relief_um is not None else DEFAULT_RELIEF_RMS_UM
        if options.relief_um is None:
            LOG.warning("%s: no lattice and no height scale; Brownian surface of %g um RMS", spec, rms)
        h = brownian_surface((ny, nx), hurst, pixel_size_um=pixel_size_um, rms_um=rms, seed=options.seed)
        report["surface"] = f"not periodic ({lattice.reason}): Brownian surface, H = {hurst:.3f} (D = {3 - hurst:.3f}) from the photo"
        return SourceResult(Surface(h, pixel_size_um, False), "photo", spec, report,
                            roughness={"hurst": hurst, "dimension": 3.0 - hurst, "rms_um": rms},
                            source_image=grey)
    tile = average_tile(flat, lattice)
    height_rel, sfs, window = _tile_heights(tile, lattice, grey.shape, pixel_size_um, light, options.sfs)
    for w in sfs.warnings:
        LOG.warning("%s: %s", spec, w)
    report["shading"] = {"method": sfs.method, "light_slant_deg": sfs.light.slant_deg, "light_tilt_deg": sfs.light.tilt_deg,
                         "light_given": options.light is not None, "warnings": list(sfs.warnings),
                         "solved_on": window}
    height = relief_scale(options, spec, height_rel, pixel_size_um, report)
    t1, t2 = np.asarray(lattice.t1_px, float), np.asarray(lattice.t2_px, float)
    roughness = None
    if options.roughness != "none":
        est, rms_img = roughness_from_residual(flat - tile.synthetic, pixel_size_um=pixel_size_um)
        pattern_rms = float(np.std(tile.synthetic)) or 1.0
        # Same grey-to-height ratio as the pattern (shading is linear in slope to first order).
        rms_um = float(np.std(height)) * float(rms_img) / pattern_rms
        hurst = float(np.clip(est.hurst, 0.02, 0.98))
        rough, t1, t2 = periodic_roughness(height.shape, t1, t2, hurst, rms_um, pixel_size_um, options.seed)
        height = height + rough
        roughness = {"hurst": hurst, "dimension": 3.0 - hurst, "rms_um": rms_um,
                     "hurst_ci": [float(est.ci_low), float(est.ci_high)],
                     "note": "Brownian roughness from the photo's residual, periodic on a super-cell of the lattice"}
        report["roughness"] = roughness
    # Reference cell near the image centre, so every sample it needs is inside the image.
    centre = np.array([nx, ny], dtype=float) / 2.0 - (t1 + t2) / 2.0
    surface = Surface(height, pixel_size_um, True, t1, t2, np.floor(centre))
    lat = {"t1_px": np.asarray(lattice.t1_px, float), "t2_px": np.asarray(lattice.t2_px, float),
           "confidence": float(lattice.confidence)}
    return SourceResult(surface, "photo", spec, report, lattice=lat, roughness=roughness, source_image=grey)
