"""Parsing of quantities with units given on the command line or in spec strings.

Lengths are returned in micrometres (µm), the project's unit for heights and pixel sizes.
"""
from __future__ import annotations

import math
import re

_LENGTH_UM = {"nm": 1e-3, "um": 1.0, "µm": 1.0, "mm": 1e3, "cm": 1e4, "m": 1e6}
_NUMBER = r"[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?"
_QUANTITY = re.compile(rf"^\s*({_NUMBER})\s*([a-zµ]*)\s*$", re.IGNORECASE)


def parse_length_um(text: str | float, default_unit: str = "um") -> float:
    """Parse a length such as ``"10um"``, ``"0.01mm"`` or ``"20"`` into micrometres.

    Parameters
    ----------
    text : str or float
        The quantity; a bare number is in `default_unit`.
    default_unit : str
        Unit of a bare number (``"um"`` unless stated).

    Returns
    -------
    float
        The length in µm; finite and strictly positive.

    Raises
    ------
    ValueError
        If the text is not a number with a known length unit, or is not finite and positive.
    """
    if isinstance(text, (int, float)):
        value, unit = float(text), default_unit
    else:
        match = _QUANTITY.match(str(text))
        if not match:
            raise ValueError(f"cannot read length {text!r} (expected e.g. 10um or 0.01mm)")
        value, unit = float(match.group(1)), (match.group(2) or default_unit)
    factor = _LENGTH_UM.get(unit.lower() if unit != "µm" else unit)
    if factor is None:
        raise ValueError(f"unknown length unit {unit!r} in {text!r} (use nm, um, mm, cm or m)")
    length = value * factor
    if not math.isfinite(length) or length <= 0:
        raise ValueError(f"length {text!r} must be finite and positive")
    return length


# Above this a "pixel" is not a surface texture's, and the heights and lengths it scales run
# out of float range on the way (1e300 um: float32 tiles overflow; 1e20 um: FFT lengths).
MAX_PIXEL_SIZE_UM = 1e6  # 1 m


def parse_pixel_size_um(text: str | float, default_unit: str = "um") -> float:
    """:func:`parse_length_um` for a pixel size, which must also be at most ``MAX_PIXEL_SIZE_UM``.

    Raises
    ------
    ValueError
        As :func:`parse_length_um`, or if the length is above 1 m.
    """
    length = parse_length_um(text, default_unit)
    if length > MAX_PIXEL_SIZE_UM:
        raise ValueError(f"pixel size {text!r} is above 1 m: check its unit")
    return length
