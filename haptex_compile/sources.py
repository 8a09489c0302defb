"""Inputs of the compiler, chosen by extension or prefix, turned into a :class:`Surface`.

* ``.npy`` / ``.exr``: a height map in µm (pixel size from ``--pixel-size``, else the stated
  default with a warning);
* ``brownian:H=0.7,size=1024,pixel=10um,rms=5um,seed=3[,method=midpoint][,periodic=true]``:
  a synthetic Brownian surface (Make-friendly spec string);
* ``.jpg .jpeg .png .bmp .tif .tiff``: a photograph (:mod:`haptex_compile.photo`);
* ``.kes.json`` / ``.kes.csv``: Kawabata KES-F data (:mod:`haptex_compile.kes`).
"""
from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from haptex_compile.errors import InputError
from haptex_compile.surface import Surface, periodic_surface_from_tile
from haptex_compile.units import MAX_PIXEL_SIZE_UM, parse_length_um, parse_pixel_size_um

LOG = logging.getLogger("haptex.sources")
DEFAULT_PIXEL_SIZE_UM = 20.0  # used, with a warning, when neither the user nor metadata give one
IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png", ".bmp", ".tif", ".tiff")
HEIGHTMAP_SUFFIXES = (".npy", ".exr")
# A height map's RMS (after levelling) outside this range, in µm, is warned of as a likely unit
# error: fabrics' roughness is 1-20 µm (Kawabata SMD) and their relief up to a few hundred;
# heights in nm read as µm land above it, heights in mm below (and under 0.01 µm nothing is felt).
PLAUSIBLE_RMS_UM = (0.01, 1000.0)


@dataclass
class SourceOptions:
    """Options that shape how an input becomes a surface (from the CLI)."""

    pixel_size_um: float | None = None
    relief_um: float | None = None
    relief_kind: str = "rms"
    sfs: str = "default"
    light: tuple[float, float] | None = None  # slant, tilt in degrees
    kes_path: str | None = None
    roughness: str = "auto"  # "auto" | "none"
    seed: int = 0
    # Which fabric of a .kes.csv of several (0-based; one input each, see kes_source.batch_stems);
    # None: the file must hold one.
    kes_row: int | None = None


@dataclass
class SourceResult:
    """A surface plus what the asset should record about where it came from."""

    surface: Surface
    kind: str
    name: str
    report: dict[str, Any] = field(default_factory=dict)
    lattice: dict[str, Any] | None = None
    roughness: dict[str, Any] | None = None
    friction: dict[str, np.ndarray] | None = None
    source_image: np.ndarray | None = None


def input_kind(spec: str) -> str:
    """Which reader handles `spec`: 'brownian', 'heightmap', 'image' or 'kes'."""
    lower = spec.lower()
    if lower.startswith("brownian:"):
        return "brownian"
    if lower.endswith(".kes.json") or lower.endswith(".kes.csv"):
        return "kes"
    if lower.endswith(HEIGHTMAP_SUFFIXES):
        return "heightmap"
    if lower.endswith(IMAGE_SUFFIXES):
        return "image"
    raise InputError(spec, "unknown input type (expected .npy, .exr, an image, .kes.json/.kes.csv or brownian:...)")


def output_stem(spec: str) -> str:
    """A file stem for --out-dir: the file's name without its suffixes, or a sanitised spec."""
    if input_kind(spec) == "brownian":
        return "".join(c if c.isalnum() or c in "=-." else "_" for c in spec.replace(":", "_").replace(",", "_"))
    name = Path(spec).name
    for suffix in (".kes.json", ".kes.csv"):
        if name.lower().endswith(suffix):
            return name[: -len(suffix)]
    return Path(name).stem


# Largest RMS relief of a Brownian spec (1 m, as --relief-um's), and largest height of a
# height map after levelling.
MAX_RMS_UM = MAX_HEIGHT_UM = 1e6


def parse_brownian_spec(spec: str) -> dict[str, Any]:
    """Parse ``brownian:H=0.7,size=1024,pixel=10um,rms=5um,seed=3`` into keyword arguments.

    Defaults: size=512, pixel=20um, rms=5um, seed=0, method=circulant, periodic=false; H is required.
    ``size`` is one number (square) or ``NXxNY``.
    """
    body = spec.split(":", 1)[1]
    values: dict[str, str] = {}
    for part in filter(None, (p.strip() for p in body.split(","))):
        if "=" not in part:
            raise InputError(spec, f"expected key=value, got {part!r}")
        key, value = (s.strip() for s in part.split("=", 1))
        if key not in {"H", "size", "pixel", "rms", "seed", "method", "periodic"}:
            raise InputError(spec, f"unknown key {key!r} (use H, size, pixel, rms, seed, method, periodic)")
        if key in values:  # (the last one was used)
            raise InputError(spec, f"{key} is given twice")
        values[key] = value
    if "H" not in values:
        raise InputError(spec, "H is required, e.g. brownian:H=0.7")

    def value(key: str, parse, text: str | None = None, default: str = ""):
        # each key's own message: Python's ("invalid literal for int() with base 10") named none
        text = values.get(key, default) if text is None else text
        try:
            return parse(text)
        except ValueError as exc:
            what = {int: "a whole number", float: "a number"}.get(parse)
            message = f"{key}={values.get(key, text)!r} is not {what}" if what else f"{key}: {exc}"
            raise InputError(spec, message) from None

    hurst = value("H", float)
    size_text = values.get("size", "512").lower()
    sides = size_text.split("x", 1) if "x" in size_text else [size_text] * 2
    nx, ny = (value("size", int, side) for side in sides)
    pixel = value("pixel", parse_pixel_size_um, default="20um")
    rms = value("rms", parse_length_um, default="5um")
    if rms > MAX_RMS_UM:  # (1e300 um overflowed the float32 heights: an asset of inf and NaN)
        raise InputError(spec, f"rms {rms:g} um is above 1 m: check its unit")
    seed = value("seed", int, default="0")
    periodic_text = values.get("periodic", "false").lower()
    if periodic_text not in {"true", "false", "1", "0", "yes", "no"}:
        raise InputError(spec, f"periodic must be true or false, got {periodic_text!r}")
    if not (8 <= nx <= 16384 and 8 <= ny <= 16384):
        raise InputError(spec, f"size {nx}x{ny} outside 8..16384 pixels per side")
    return {
        "shape": (ny, nx), "hurst": hurst, "pixel_size_um": pixel, "rms_um": rms, "seed": seed,
        "method": values.get("method", "circulant"), "periodic": periodic_text in {"true", "1", "yes"},
    }


def _pixel_size(options: SourceOptions, spec: str, metadata_um: float | None = None, note: str = "") -> tuple[float, str]:
    if options.pixel_size_um is not None:
        return options.pixel_size_um, "from --pixel-size"
    if metadata_um is not None:
        if metadata_um > MAX_PIXEL_SIZE_UM:
            raise InputError(spec, f"the image's metadata give a pixel of {metadata_um:g} um, above 1 m;"
                                   " give --pixel-size")
        return metadata_um, note or "from image metadata"
    LOG.warning("%s: no pixel size given; using the default %.0f um per pixel (set --pixel-size)", spec, DEFAULT_PIXEL_SIZE_UM)
    return DEFAULT_PIXEL_SIZE_UM, f"default {DEFAULT_PIXEL_SIZE_UM:g} um (no --pixel-size{', ' + note if note else ''})"


def remove_plane(height_um: np.ndarray) -> np.ndarray:
    """Subtract the least-squares plane: a tilt carries no vibration and would only shift heights."""
    ny, nx = height_um.shape
    y, x = np.mgrid[0:ny, 0:nx]
    a = np.column_stack([np.ones(height_um.size), x.ravel() - (nx - 1) / 2, y.ravel() - (ny - 1) / 2])
    coef, *_ = np.linalg.lstsq(a, height_um.ravel(), rcond=None)
    return height_um - (a @ coef).reshape(height_um.shape)


# Options of photographs only: (SourceOptions field, flag, default).
_PHOTO_ONLY = (("relief_um", "--relief-um", None), ("relief_kind", "--relief-kind", "rms"), ("sfs", "--sfs", "default"),
               ("light", "--light", None), ("kes_path", "--kes", None), ("roughness", "--roughness", "auto"))


def not_applying(spec: str, flags: list[str], why: str) -> str | None:
    """The warning that options `flags` given for input `spec` do not apply to it (`why`: how
    the sentence goes on, e.g. " to a height map"), or None when there are none."""
    if not flags:
        return None
    return f"{spec}: {', '.join(flags)} {'does' if len(flags) == 1 else 'do'} not apply{why}: ignored"


def _warn_ignored(spec: str, kind: str, options: SourceOptions) -> None:
    """One warning naming the options given that do not apply to this kind of input (they were
    ignored silently: a Brownian spec with --pixel-size 10um kept the spec's 20 um)."""
    ignored = [flag for field_name, flag, default in _PHOTO_ONLY
               if kind != "image" and getattr(options, field_name) != default]
    if kind in ("brownian", "heightmap") and options.seed != 0:
        ignored.append("--seed")
    if kind == "brownian" and options.pixel_size_um is not None:
        ignored.append("--pixel-size")
    names = {"brownian": "Brownian spec (its pixel= and seed= set those)", "heightmap": "height map",
             "kes": "Kawabata file"}
    said = not_applying(spec, ignored, f" to a {names.get(kind, kind)}")
    if said is not None:
        LOG.warning("%s", said)


def load_source(spec: str, options: SourceOptions) -> SourceResult:
    """Read or synthesise the surface named by `spec`."""
    kind = input_kind(spec)
    _warn_ignored(spec, kind, options)
    if kind == "brownian":
        from haptex_compile.fractal import brownian_surface

        kwargs = parse_brownian_spec(spec)
        try:
            h = brownian_surface(**kwargs)
        except ValueError as exc:
            raise InputError(spec, str(exc)) from None
        px = kwargs["pixel_size_um"]
        surface = periodic_surface_from_tile(h, px) if kwargs["periodic"] else Surface(h, px, False)
        report = {"pixel_size": f"{px:g} um from the spec", "brownian": {k: v for k, v in kwargs.items() if k != "shape"}}
        return SourceResult(surface, "brownian", spec, report,
                            roughness={"hurst": kwargs["hurst"], "dimension": 3.0 - kwargs["hurst"], "rms_um": kwargs["rms_um"]})
    if kind == "heightmap":
        from haptex_compile.io_heightmaps import read_height_exr, read_height_npy

        h = read_height_npy(spec) if spec.lower().endswith(".npy") else read_height_exr(spec)
        px, note = _pixel_size(options, spec)
        with np.errstate(over="ignore", invalid="ignore"):  # (absurd heights are refused just below)
            h = remove_plane(np.asarray(h, dtype=float))
            peak = float(np.max(np.abs(h)))
            rms = float(np.sqrt(np.mean(h * h)))
        if not peak <= MAX_HEIGHT_UM:
            # (1e30 um gave all-zero tables from overflowed powers, 1e300 an asset of infinite heights)
            raise InputError(spec, f"heights reach {peak:.3g} um after levelling, above 1 m: the file's heights"
                                   " must be in micrometres")
        report = {"pixel_size": f"{px:g} um {note}", "plane_removed": True}
        low, high = PLAUSIBLE_RMS_UM
        if not low <= rms <= high:
            report["relief_warning"] = (f"RMS height {rms:.3g} um after levelling, outside {low:g}-{high:g} um:"
                                        " the file's heights must be in micrometres")
            LOG.warning("%s: %s", spec, report["relief_warning"])
        return SourceResult(Surface(h, px, False), "heightmap", Path(spec).name, report)
    if kind == "image":
        from haptex_compile.photo import photo_source

        return photo_source(spec, options)
    from haptex_compile.kes_source import kes_source

    return kes_source(spec, options)
