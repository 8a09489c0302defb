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
        report["relief"] = f"scaled so the simulated KES SMD matches {options.kes_path} ({kes.fabric})"
        return unit * factor
    LOG.warning("%s: no height scale given; using the default relief of %g um RMS (set --relief-um or --kes)",
                spec, DEFAULT_RELIEF_RMS_UM)
    report["relief"] = f"default {DEFAULT_RELIEF_RMS_UM:g} um RMS (no --relief-um or --kes)"
    return scale_relief(h, DEFAULT_RELIEF_RMS_UM, kind="rms")


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
    from haptex_compile.lattice import find_lattice
    from haptex_compile.shading import Light, shape_from_shading
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
    sfs = shape_from_shading(tile.synthetic, pixel_size_um=pixel_size_um, light=light, method=options.sfs)
    for w in sfs.warnings:
        LOG.warning("%s: %s", spec, w)
    report["shading"] = {"method": sfs.method, "light_slant_deg": sfs.light.slant_deg, "light_tilt_deg": sfs.light.tilt_deg,
                         "light_given": options.light is not None, "warnings": list(sfs.warnings)}
    # Average the heights over the lattice as well, so the surface repeats exactly.
    height_rel = average_tile(sfs.height, lattice).synthetic
    height = relief_scale(options, spec, height_rel, pixel_size_um, report)
    t1, t2 = np.asarray(lattice.t1_px, float), np.asarray(lattice.t2_px, float)
    # Reference cell near the image centre, so every sample it needs is inside the image.
    centre = np.array([nx, ny], dtype=float) / 2.0 - (t1 + t2) / 2.0
    surface = Surface(height, pixel_size_um, True, t1, t2, np.floor(centre))
    roughness = None
    if options.roughness != "none":
        est, rms_img = roughness_from_residual(flat - tile.synthetic, pixel_size_um=pixel_size_um)
        pattern_rms = float(np.std(tile.synthetic)) or 1.0
        roughness = {"hurst": float(est.hurst), "dimension": float(est.dimension),
                     "rms_relative_to_pattern": float(rms_img / pattern_rms),
                     "note": "estimated from the photo's residual; recorded, not added to the periodic surface"}
        report["roughness"] = roughness
    lat = {"t1_px": t1, "t2_px": t2, "confidence": float(lattice.confidence)}
    return SourceResult(surface, "photo", spec, report, lattice=lat, roughness=roughness, source_image=grey)
