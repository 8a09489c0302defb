"""Reading scene TOML files, validated against ``schemas/scene.schema.json``."""
from __future__ import annotations

import json
import logging
import tomllib
from functools import lru_cache
from importlib import resources
from pathlib import Path

import jsonschema

from haptex_compile.errors import InputError
from haptex_compile.scene import Scene, scene_from_dict
from playback.text_files import read_text

LOG = logging.getLogger("haptex.scene")


@lru_cache(maxsize=None)
def load_schema(name: str) -> dict:
    """A JSON Schema of ``schemas/`` (installed as the ``haptex_compile.schemas`` resources)."""
    return json.loads(resources.files("haptex_compile.schemas").joinpath(name).read_text(encoding="utf-8"))


def _where(error: jsonschema.ValidationError) -> str:
    return ".".join(str(p) for p in error.absolute_path) or "scene"


def parse_scene(text: str, source: str | Path, base_dir: str | None = None) -> Scene:
    """Parse and validate scene TOML text; errors are one line naming `source`."""
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise InputError(source, f"not valid TOML ({exc})") from None
    validator = jsonschema.Draft202012Validator(load_schema("scene.schema.json"))
    errors = sorted(validator.iter_errors(data), key=lambda e: list(e.absolute_path))
    if errors:
        err = errors[0]
        raise InputError(source, f"{_where(err)}: {err.message}")
    try:
        scene = scene_from_dict(data, text=text, base_dir=base_dir)
    except ValueError as exc:
        raise InputError(source, str(exc)) from None
    # Explicit nodes are used as given, less repeats (a direction and its reverse, d + 180,
    # are one): said, as a list shorter than the one written would puzzle.
    motion = data.get("motion", {})
    for key, kept, what in (("speeds_mm_s", scene.speeds_mm_s, "speeds"),
                            ("directions_deg", scene.directions_deg, "directions (modulo 180 deg)")):
        if key in motion and len(kept) < len(motion[key]):
            LOG.warning("%s: motion.%s: %d values, %d distinct %s: those are the nodes", source, key,
                        len(motion[key]), len(kept), what)
    return scene


def read_scene(path: str | Path) -> Scene:
    """Read a scene TOML file."""
    path = Path(path)
    return parse_scene(read_text(path, "scene file"), path, base_dir=str(path.parent))
