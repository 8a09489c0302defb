"""Validation of tactile assets against ``schemas/asset.schema.json``.

The HDF5 tree is described as JSON (groups, datasets with dtype and shape, attributes) and that
description is checked against the schema; then the player's reader (:func:`playback.asset.read_asset`)
checks what a schema cannot (finite values, consistent shapes, ascending nodes).
"""
from __future__ import annotations

from pathlib import Path
from typing import Any

import h5py
import jsonschema
import numpy as np

from haptex_compile.io_scene import load_schema
from playback.asset import H5_READ_ERRORS, read_asset, refuse_crashing
from playback.errors import AssetError, one_line, shown_text
from playback.record import RECORD_FORMAT


def _json_value(value: Any) -> Any:
    if isinstance(value, bytes):
        return value.decode("utf-8", "replace")
    if isinstance(value, np.ndarray):
        return [_json_value(v) for v in value.tolist()] if value.ndim else _json_value(value[()])
    if isinstance(value, (np.bool_, bool)):
        return bool(value)
    if isinstance(value, np.integer):
        return int(value)
    if isinstance(value, np.floating):
        return float(value) if np.isfinite(value) else str(value)
    if isinstance(value, float) and not np.isfinite(value):
        return str(value)
    if isinstance(value, list):
        return [_json_value(v) for v in value]
    return value


def describe_h5(obj: h5py.Group) -> dict[str, Any]:
    """JSON description of an HDF5 group: its attributes, sub-groups and datasets (dtype, shape)."""
    out: dict[str, Any] = {"attrs": {k: _json_value(v) for k, v in obj.attrs.items()}, "groups": {}, "datasets": {}}
    for name, item in obj.items():
        if isinstance(item, h5py.Group):
            out["groups"][name] = describe_h5(item)
        elif isinstance(item, h5py.Dataset):
            out["datasets"][name] = {"dtype": str(item.dtype), "shape": list(item.shape),
                                     "attrs": {k: _json_value(v) for k, v in item.attrs.items()}}
    return out


def validate_asset(path: str | Path) -> list[str]:
    """Problems found in the asset at `path` (empty when valid); each is one line."""
    path = Path(path)
    if not path.exists():
        return [f"{path}: no such file"]
    if path.is_dir():
        return [f"{path}: is a directory, not a tactile asset"]
    try:
        if not h5py.is_hdf5(str(path)):
            return [f"{path}: not an HDF5 file"]
        refuse_crashing(path)  # before this process opens it: a corrupt file may crash libhdf5
        with h5py.File(path, "r") as f:
            description = describe_h5(f)
    except AssetError as exc:  # a file that crashes libhdf5
        return [str(exc)]
    except H5_READ_ERRORS as exc:  # corrupt files: h5py's errors as one line, as the reader does
        return [f"{path}: cannot read ({one_line(exc)})"]
    if description["attrs"].get("format") == RECORD_FORMAT:
        return [f"{path}: a playback record (haptex-play --record), not a tactile asset: --validate checks"
                " assets (haptex-inspect without --validate summarises a record)"]
    problems = []
    validator = jsonschema.Draft202012Validator(load_schema("asset.schema.json"))
    for err in sorted(validator.iter_errors(description), key=lambda e: list(e.absolute_path)):
        where = "/".join(str(p) for p in err.absolute_path if p not in ("groups", "datasets", "attrs")) or "/"
        problems.append(f"{path}: {where}: {shown_text(err.message)}")
    if not problems:
        try:
            read_asset(path, load_surface=True)
        except AssetError as exc:
            problems.append(str(exc))
    return problems
