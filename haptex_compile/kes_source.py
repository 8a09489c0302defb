"""Kawabata (KES-F) files as compiler inputs: a synthetic fabric whose simulated SMD matches."""
from __future__ import annotations

from haptex_compile.errors import InputError
from haptex_compile.sources import SourceOptions, SourceResult
from haptex_compile.surface import periodic_surface_from_tile

DEFAULT_KES_PIXEL_UM = 20.0  # fine enough for the 0.5 mm probe and for threads of 0.1 mm or more


def kes_source(spec: str, options: SourceOptions) -> SourceResult:
    """Read one fabric from a ``.kes.json`` (or a one-row ``.kes.csv``) and synthesise it."""
    from haptex_compile.kes import kes_surface
    from haptex_compile.kes_io import read_kes

    kes = read_kes(spec)
    if isinstance(kes, list):
        if len(kes) != 1:
            raise InputError(spec, f"holds {len(kes)} fabrics; compile them one by one (split the CSV) ")
        kes = kes[0]
    px = options.pixel_size_um or DEFAULT_KES_PIXEL_UM
    result = kes_surface(kes, pixel_size_um=px, seed=options.seed)
    surface = periodic_surface_from_tile(result.height_um.astype(float), result.pixel_size_um)
    report = {
        "fabric": kes.fabric,
        "pixel_size": f"{px:g} um ({'from --pixel-size' if options.pixel_size_um else 'KES default'})",
        "smd_given_um": dict(kes.smd_um),
        "smd_simulated_um": dict(result.smd_simulated_um),
    }
    friction = {"warp": result.friction[0], "weft": result.friction[1]}
    return SourceResult(surface, "kes", spec, report, friction=friction)
