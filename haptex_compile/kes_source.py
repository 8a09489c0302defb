"""Kawabata (KES-F) files as compiler inputs: a synthetic fabric whose simulated SMD matches."""
from __future__ import annotations

import math

from haptex_compile.errors import InputError
from haptex_compile.sources import SourceOptions, SourceResult
from haptex_compile.surface import periodic_surface_from_tile

DEFAULT_KES_PIXEL_UM = 20.0  # fine enough for the 0.5 mm probe and for threads of 0.1 mm or more


def kes_pixel_um(ends_per_cm: float, picks_per_cm: float, cap_um: float = DEFAULT_KES_PIXEL_UM) -> float:
    """The default pixel size (µm) for a KES fabric: `cap_um` (``DEFAULT_KES_PIXEL_UM``), or
    finer where the threads are closer than 4 of those pixels (the synthesis needs
    ``kes._MIN_PITCH_PX`` per thread: a silk of 150 ends/cm was refused at 20 um), rounded down
    to 0.01 um."""
    from haptex_compile.kes import _MIN_PITCH_PX

    spacing_um = 1e4 / max(ends_per_cm, picks_per_cm)
    return min(cap_um, math.floor(100.0 * spacing_um / _MIN_PITCH_PX) / 100.0)


def batch_stems(spec: str, stem: str) -> list[str] | None:
    """For a ``.kes.csv`` of several fabrics, the file stems of their assets: `stem`, a dash and
    the fabric's name in letters, digits, '-' and '.' (others become '_'), with its row number
    after a name that recurs; None for any other input (one asset)."""
    from haptex_compile.kes_io import read_kes

    if not spec.lower().endswith(".kes.csv"):
        return None
    fabrics = read_kes(spec)
    if len(fabrics) < 2:
        return None
    names = ["".join(c if c.isalnum() or c in "-." else "_" for c in k.fabric).strip("_.") or "fabric" for k in fabrics]
    return [f"{stem}-{name}" + (f"-{row + 1}" if names.count(name) > 1 else "") for row, name in enumerate(names)]


def kes_source(spec: str, options: SourceOptions) -> SourceResult:
    """Read one fabric from a ``.kes.json`` or a ``.kes.csv`` (the one it holds, or row
    ``options.kes_row`` of several) and synthesise it."""
    from haptex_compile.kes import _MAX_SIDE_PX as MAX_SIDE_PX
    from haptex_compile.kes import kes_surface, synthesis_side_px
    from haptex_compile.kes_io import read_kes

    kes = read_kes(spec)
    where = spec  # what the errors name
    if isinstance(kes, list):
        if options.kes_row is not None:
            kes = kes[options.kes_row]
            where = f"{spec} (fabric {options.kes_row + 1}, {kes.fabric})"
        elif len(kes) != 1:
            raise InputError(spec, f"holds {len(kes)} fabrics: give --out-dir for an asset of each")
        else:
            kes = kes[0]
    px = options.pixel_size_um or kes_pixel_um(kes.ends_per_cm, kes.picks_per_cm)
    coarsest = kes_pixel_um(kes.ends_per_cm, kes.picks_per_cm, cap_um=math.inf)
    spacing_um = 1e4 / max(kes.ends_per_cm, kes.picks_per_cm)
    if px > coarsest:  # the synthesis's own message names its keyword, not the option
        raise InputError(where, f"--pixel-size {px:g} um is too coarse for threads {spacing_um:.3g} um apart"
                               f" (at least 4 px per thread: give {coarsest:g} um or less, or leave it out)")
    nx, ny = synthesis_side_px(kes.ends_per_cm, kes.picks_per_cm, kes.weave, px)
    if max(nx, ny) > MAX_SIDE_PX:  # threads fine one way, a weave repeat long the other
        fits = max(synthesis_side_px(kes.ends_per_cm, kes.picks_per_cm, kes.weave, coarsest)) <= MAX_SIDE_PX
        advice = (f"give a coarser --pixel-size (up to {coarsest:g} um fits its threads)" if fits else
                  "no pixel size fits both that and its threads (4 px each): check its thread counts")
        raise InputError(where, f"at {px:g} um pixels its weave repeat takes {nx} x {ny} px, above {MAX_SIDE_PX} a side: {advice}")
    try:
        result = kes_surface(kes, pixel_size_um=px, seed=options.seed)
    except ValueError as exc:  # (the fabric that cannot be made, named)
        raise InputError(where, str(exc)) from None
    surface = periodic_surface_from_tile(result.height_um.astype(float), result.pixel_size_um)
    note = "from --pixel-size" if options.pixel_size_um else (
        "KES default" if px == DEFAULT_KES_PIXEL_UM else "KES default, finer for 4 px per thread")
    report = {
        "fabric": kes.fabric,
        "pixel_size": f"{px:g} um ({note})",
        "smd_given_um": dict(kes.smd_um),
        "smd_simulated_um": dict(result.smd_simulated_um),
    }
    friction = {"warp": result.friction[0], "weft": result.friction[1]}
    return SourceResult(surface, "kes", spec, report, friction=friction)
