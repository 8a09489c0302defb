"""Reading and validating Kawabata (KES-F) surface data: ``.kes.json`` and ``.kes.csv``.

A ``.kes.json`` file holds one fabric, validated against ``schemas/kes.schema.json``::

    {"fabric": "cotton poplin", "smd_um": {"warp": 3.2, "weft": 4.1},
     "miu": {"warp": 0.18, "weft": 0.2}, "mmd": {"warp": 0.012, "weft": 0.015},
     "ends_per_cm": 48, "picks_per_cm": 30, "weave": "plain"}

A ``.kes.csv`` batch file holds one fabric per row under a header with the columns
``fabric, smd_warp_um, smd_weft_um, miu_warp, miu_weft, mmd_warp, mmd_weft, ends_per_cm,
picks_per_cm, weave`` and optionally ``thickness_mm, source`` (comma or semicolon separated).

Conventions: warp threads run along v (image rows), weft threads along u; a "warp" value was
measured by a traverse along the warp, i.e. along v. Every problem raises one
:class:`~haptex_compile.errors.InputError` whose one-line message names the file (and the row
for CSV) and the field.
"""
from __future__ import annotations

import csv
import io
import json
import math
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path
from typing import Any

import jsonschema

from haptex_compile.errors import InputError
from playback.text_files import read_text

__all__ = ["KesData", "parse_kes", "read_kes", "kes_schema", "WEAVES", "CSV_COLUMNS"]

#: Weave names accepted in the files (aliases: twill = twill_2_2, satin = satin_5).
WEAVES = ("plain", "twill", "twill_2_1", "twill_2_2", "twill_3_1", "satin", "satin_5")

#: CSV column -> (json field, key in a warp/weft pair or None).
CSV_COLUMNS: dict[str, tuple[str, str | None]] = {
    "fabric": ("fabric", None),
    "smd_warp_um": ("smd_um", "warp"),
    "smd_weft_um": ("smd_um", "weft"),
    "miu_warp": ("miu", "warp"),
    "miu_weft": ("miu", "weft"),
    "mmd_warp": ("mmd", "warp"),
    "mmd_weft": ("mmd", "weft"),
    "ends_per_cm": ("ends_per_cm", None),
    "picks_per_cm": ("picks_per_cm", None),
    "weave": ("weave", None),
    "thickness_mm": ("thickness_mm", None),
    "source": ("source", None),
}
_CSV_OPTIONAL = {"thickness_mm", "source"}
_CSV_TEXT = {"fabric", "weave", "source"}


@dataclass(frozen=True)
class KesData:
    """KES-F surface data of one fabric.

    Attributes
    ----------
    fabric : str
        Name of the fabric.
    smd_um : dict of str to float
        ``{"warp": .., "weft": ..}``: SMD, geometric roughness, the mean deviation of the
        surface height in µm; "warp" from traverses along the warp (along v).
    miu : dict of str to float
        Mean friction coefficient, warp and weft.
    mmd : dict of str to float
        Mean deviation of the friction coefficient, warp and weft.
    ends_per_cm, picks_per_cm : float
        Warp threads per cm (counted along u) and weft threads per cm (counted along v).
    weave : str
        One of :data:`WEAVES`.
    thickness_mm : float or None
        Fabric thickness in mm, if known.
    source : str or None
        Citation of the values.
    """

    fabric: str
    smd_um: dict[str, float]
    miu: dict[str, float]
    mmd: dict[str, float]
    ends_per_cm: float
    picks_per_cm: float
    weave: str
    thickness_mm: float | None = None
    source: str | None = None


@lru_cache(maxsize=1)
def kes_schema() -> dict[str, Any]:
    """The JSON Schema of a ``.kes.json`` file (``schemas/kes.schema.json``)."""
    from haptex_compile.io_scene import load_schema

    return load_schema("kes.schema.json")


def _field_name(path: Any) -> str:
    return ".".join(str(p) for p in path) or "(top level)"


def _check_finite(obj: Any, source: str, path: tuple = ()) -> None:
    # json accepts NaN and Infinity literals; jsonschema would give a misleading range message.
    if isinstance(obj, dict):
        for key, value in obj.items():
            _check_finite(value, source, path + (key,))
    elif isinstance(obj, float) and not math.isfinite(obj):
        raise InputError(source, f"field '{_field_name(path)}': must be a finite number (got {obj})")


def parse_kes(obj: dict, source: str) -> KesData:
    """Validate one fabric's KES data (a decoded ``.kes.json`` object) and return it.

    Parameters
    ----------
    obj : dict
        The decoded JSON object.
    source : str
        Name of the file (or file and row) it came from, used in error messages.

    Returns
    -------
    KesData

    Raises
    ------
    InputError
        One line naming `source` and the field: missing or unknown field, wrong type, NaN or
        infinite number, value out of range, unknown weave.
    """
    if not isinstance(obj, dict):
        raise InputError(source, f"expected a JSON object with the KES fields, got {type(obj).__name__}")
    _check_finite(obj, source)
    validator = jsonschema.Draft202012Validator(kes_schema())
    errors = sorted(validator.iter_errors(obj), key=lambda e: (list(e.absolute_path), e.validator))
    if errors:
        error = errors[0]
        field = _field_name(error.absolute_path)
        if error.validator == "required":
            # jsonschema reports a missing key on its parent object.
            missing = error.message.split("'")[1] if "'" in error.message else error.message
            field = _field_name(list(error.absolute_path) + [missing])
            problem = "missing"
        elif error.validator == "additionalProperties":
            problem = error.message
        elif error.validator == "enum":
            problem = f"{error.instance!r} is not one of {', '.join(error.validator_value)}"
        elif error.validator == "type":
            wanted = error.validator_value
            wanted = " or ".join(wanted) if isinstance(wanted, list) else wanted
            problem = f"must be {wanted} (got {error.instance!r})"
        elif error.validator in ("minimum", "exclusiveMinimum", "maximum", "exclusiveMaximum"):
            op = {"minimum": ">=", "exclusiveMinimum": ">", "maximum": "<=", "exclusiveMaximum": "<"}
            problem = f"must be {op[error.validator]} {error.validator_value} (got {error.instance!r})"
        elif error.validator == "const":
            problem = f"must be {error.validator_value!r} (got {error.instance!r})"
        else:
            problem = error.message
        problem = " ".join(str(problem).split())  # one line, whatever jsonschema said
        raise InputError(source, f"field '{field}': {problem}")

    def pair(name: str) -> dict[str, float]:
        return {"warp": float(obj[name]["warp"]), "weft": float(obj[name]["weft"])}

    mmd, miu = pair("mmd"), pair("miu")
    for key in ("warp", "weft"):
        # A deviation larger than the mean would need negative friction somewhere.
        if mmd[key] > miu[key]:
            raise InputError(source, f"field 'mmd.{key}': must not exceed miu.{key} = {miu[key]} (got {mmd[key]})")
    thickness = obj.get("thickness_mm")
    return KesData(
        fabric=obj["fabric"],
        smd_um=pair("smd_um"),
        miu=miu,
        mmd=mmd,
        ends_per_cm=float(obj["ends_per_cm"]),
        picks_per_cm=float(obj["picks_per_cm"]),
        weave=obj["weave"],
        thickness_mm=None if thickness is None else float(thickness),
        source=obj.get("source"),
    )


def _csv_cell(text: str, column: str, source: str) -> Any:
    text = text.strip()
    if column in _CSV_TEXT:
        return text if text or column != "source" else None
    if not text:
        if column in _CSV_OPTIONAL:
            return None
        field, key = CSV_COLUMNS[column]
        raise InputError(source, f"field '{field}{'.' + key if key else ''}' (column {column}): missing")
    try:
        return float(text)
    except ValueError:
        field, key = CSV_COLUMNS[column]
        raise InputError(source, f"field '{field}{'.' + key if key else ''}' (column {column}): "
                                 f"not a number ({text!r})") from None


def _read_csv(path: Path) -> list[KesData]:
    text = read_text(path, "Kawabata file")
    first = text.split("\n", 1)[0]
    delimiter = ";" if first.count(";") > first.count(",") else ","
    reader = csv.reader(io.StringIO(text), delimiter=delimiter)
    try:
        header = [h.strip().lower() for h in next(reader)]
    except StopIteration:
        raise InputError(path, "empty file (expected a header and one row per fabric)") from None
    unknown = [h for h in header if h not in CSV_COLUMNS]
    if unknown:
        raise InputError(path, f"unknown column {unknown[0]!r} (expected {', '.join(CSV_COLUMNS)})")
    missing = [c for c in CSV_COLUMNS if c not in header and c not in _CSV_OPTIONAL]
    if missing:
        raise InputError(path, f"missing column {missing[0]!r}")
    if len(set(header)) != len(header):
        raise InputError(path, "a column appears twice in the header")
    fabrics = []
    for line_no, row in enumerate(reader, start=2):
        if not any(cell.strip() for cell in row):
            continue  # blank line
        source = f"{path} row {line_no}"
        if len(row) != len(header):
            raise InputError(source, f"{len(row)} cells, the header has {len(header)}")
        obj: dict[str, Any] = {}
        for column, cell in zip(header, row):
            value = _csv_cell(cell, column, source)
            field, key = CSV_COLUMNS[column]
            if key is None:
                if value is not None or column not in _CSV_OPTIONAL:
                    obj[field] = value
            else:
                obj.setdefault(field, {})[key] = value
        fabrics.append(parse_kes(obj, source))
    if not fabrics:
        raise InputError(path, "no fabric rows under the header")
    return fabrics


def read_kes(path: str | Path) -> KesData | list[KesData]:
    """Read KES data: a ``.kes.json`` gives one :class:`KesData`, a ``.kes.csv`` a list.

    Parameters
    ----------
    path : str or Path
        A ``*.json`` (one fabric) or ``*.csv`` (one fabric per row, with a header) file.

    Returns
    -------
    KesData or list of KesData

    Raises
    ------
    InputError
        One line naming the file (and row) and the field on any problem.
    """
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix == ".csv":
        return _read_csv(path)
    if suffix != ".json":
        raise InputError(path, "unknown KES file type (expected .kes.json or .kes.csv)")
    text = read_text(path, "Kawabata file")
    try:
        obj = json.loads(text)
    except json.JSONDecodeError as exc:
        raise InputError(path, f"not valid JSON: {exc.msg} at line {exc.lineno} column {exc.colno}") from None
    return parse_kes(obj, str(path))
