"""The scene: contactor array, motions to cover, and rendering parameters.

A scene is read from TOML (:func:`haptex_compile.io_scene.read_scene`) or is the built-in
default (:func:`default_scene`), which matches HAPTEX: 24 contactors, 6 x 4 at 2 mm pitch
centred on the device origin, speeds 10-200 mm/s, all directions, 2 % tolerance, 25 ms frames,
40 and 320 Hz, summation exponent 1.23, footprint sigma 0.25 mm.
"""
from __future__ import annotations

import json
from dataclasses import dataclass

import numpy as np

from playback.device import MAX_CONTACTORS

DEFAULT_SPEED_RANGE = (10.0, 200.0)
DEFAULT_DIRECTION_RANGE = (0.0, 180.0)
DEFAULT_TOLERANCE = 0.02


@dataclass(frozen=True)
class Scene:
    """A resolved scene.

    Attributes
    ----------
    contactors_mm : ndarray [n, 2]
        Device coordinates (x, y) of the contactors, mm.
    speeds_mm_s : tuple or None
        Explicit speed nodes (used exactly), or None to choose them within `speed_range_mm_s`.
    speed_range_mm_s : tuple
    directions_deg : tuple or None
        Explicit direction nodes in [0, 180) (reduced mod 180), or None to choose them.
    direction_range_deg : tuple
    tolerance : float
    frame_ms, base_frequencies_hz, summation_exponent, footprint_sigma_mm
        Rendering parameters.
    thresholds_csv : str or None
        Path of user threshold curves (resolved against the scene file's folder).
    grid_spacing_mm : float or None
    text : str
        The TOML as given ("" for the default scene).
    """

    contactors_mm: np.ndarray
    speeds_mm_s: tuple[float, ...] | None = None
    speed_range_mm_s: tuple[float, float] = DEFAULT_SPEED_RANGE
    directions_deg: tuple[float, ...] | None = None
    direction_range_deg: tuple[float, float] = DEFAULT_DIRECTION_RANGE
    tolerance: float = DEFAULT_TOLERANCE
    frame_ms: float = 25.0
    base_frequencies_hz: tuple[float, float] = (40.0, 320.0)
    summation_exponent: float = 1.23
    footprint_sigma_mm: float = 0.25
    thresholds_csv: str | None = None
    grid_spacing_mm: float | None = None
    text: str = ""

    def resolved(self) -> dict:
        """JSON-serialisable description of every value in force (defaults included)."""
        return {
            "array": {"contactors_mm": np.asarray(self.contactors_mm).round(9).tolist()},
            "motion": {
                "speeds_mm_s": None if self.speeds_mm_s is None else list(self.speeds_mm_s),
                "speed_range_mm_s": list(self.speed_range_mm_s),
                "directions_deg": None if self.directions_deg is None else list(self.directions_deg),
                "direction_range_deg": list(self.direction_range_deg),
                "tolerance": self.tolerance,
            },
            "render": {
                "frame_ms": self.frame_ms,
                "base_frequencies_hz": list(self.base_frequencies_hz),
                "summation_exponent": self.summation_exponent,
                "footprint_sigma_mm": self.footprint_sigma_mm,
                "thresholds_csv": self.thresholds_csv,
                "grid_spacing_mm": self.grid_spacing_mm,
            },
        }

    def resolved_json(self) -> str:
        return json.dumps(self.resolved(), sort_keys=True)


def grid_contactors(rows: int, cols: int, pitch_mm: float) -> np.ndarray:
    """A rows x cols grid at `pitch_mm`, centred on the device origin; row-major order."""
    y, x = np.meshgrid((np.arange(rows) - (rows - 1) / 2) * pitch_mm, (np.arange(cols) - (cols - 1) / 2) * pitch_mm, indexing="ij")
    return np.column_stack([x.ravel(), y.ravel()])


def default_scene() -> Scene:
    """The built-in scene (HAPTEX array, speeds 10-200 mm/s, all directions)."""
    return Scene(contactors_mm=grid_contactors(4, 6, 2.0))


def scene_from_dict(data: dict, text: str = "", base_dir: str | None = None) -> Scene:
    """Build a :class:`Scene` from parsed TOML already checked against ``scene.schema.json``.

    Raises
    ------
    ValueError
        For values the schema cannot express (non-finite numbers, empty ranges, duplicates).
    """
    array = data.get("array", {})
    motion = data.get("motion", {})
    render = data.get("render", {})
    if "contactors_mm" in array:
        contactors = np.asarray(array["contactors_mm"], dtype=float)
    elif "grid" in array:
        g = array["grid"]
        contactors = grid_contactors(int(g["rows"]), int(g["cols"]), float(g["pitch_mm"]))
    else:
        contactors = grid_contactors(4, 6, 2.0)
    if not np.all(np.isfinite(contactors)):
        raise ValueError("array.contactors_mm has non-finite values")
    if len(contactors) > MAX_CONTACTORS:  # (compiled, such an asset could not be played, not even simulated)
        raise ValueError(f"array has {len(contactors)} contactors; the player drives at most {MAX_CONTACTORS}")

    def finite(values, name: str) -> tuple[float, ...]:
        arr = np.asarray(values, dtype=float)
        if not np.all(np.isfinite(arr)):
            raise ValueError(f"{name} has non-finite values")
        return tuple(float(v) for v in arr)

    speeds = None
    if "speeds_mm_s" in motion:
        speeds = tuple(sorted(set(finite(motion["speeds_mm_s"], "motion.speeds_mm_s"))))
    speed_range = finite(motion.get("speed_range_mm_s", DEFAULT_SPEED_RANGE), "motion.speed_range_mm_s")
    if speed_range[0] >= speed_range[1]:
        raise ValueError("motion.speed_range_mm_s must be [lowest, highest] with lowest < highest")
    directions = None
    if "directions_deg" in motion:
        d = np.mod(np.asarray(finite(motion["directions_deg"], "motion.directions_deg")), 180.0)
        directions = tuple(float(v) for v in np.unique(np.round(d, 9)))
    direction_range = finite(motion.get("direction_range_deg", DEFAULT_DIRECTION_RANGE), "motion.direction_range_deg")
    if direction_range[0] >= direction_range[1] or direction_range[1] - direction_range[0] > 360:
        raise ValueError("motion.direction_range_deg must be [start, end] with start < end, at most 360 deg apart")
    base = finite(render.get("base_frequencies_hz", (40.0, 320.0)), "render.base_frequencies_hz")
    if base[0] >= base[1]:
        raise ValueError("render.base_frequencies_hz must be [low, high] with low < high")
    thresholds = render.get("thresholds_csv")
    if thresholds is not None and base_dir is not None:
        from pathlib import Path

        p = Path(thresholds)
        thresholds = str(p if p.is_absolute() else Path(base_dir) / p)
    for section, key in (("motion", "tolerance"), ("render", "frame_ms"), ("render", "summation_exponent"),
                         ("render", "footprint_sigma_mm"), ("render", "grid_spacing_mm")):
        value = data.get(section, {}).get(key)
        if value is not None and not np.isfinite(float(value)):
            raise ValueError(f"{section}.{key} must be a finite number")
    return Scene(
        contactors_mm=contactors,
        speeds_mm_s=speeds,
        speed_range_mm_s=(speed_range[0], speed_range[1]),
        directions_deg=directions,
        direction_range_deg=(direction_range[0], direction_range[1]),
        tolerance=float(motion.get("tolerance", DEFAULT_TOLERANCE)),
        frame_ms=float(render.get("frame_ms", 25.0)),
        base_frequencies_hz=(base[0], base[1]),
        summation_exponent=float(render.get("summation_exponent", 1.23)),
        footprint_sigma_mm=float(render.get("footprint_sigma_mm", 0.25)),
        thresholds_csv=thresholds,
        grid_spacing_mm=None if render.get("grid_spacing_mm") is None else float(render["grid_spacing_mm"]),
        text=text,
    )
