"""Reading user threshold curves from CSV files."""
from __future__ import annotations

from pathlib import Path

from haptex_compile.errors import InputError
from haptex_compile.thresholds import ThresholdCurves, parse_thresholds_csv


def read_thresholds_csv(path: str | Path) -> ThresholdCurves:
    """Read ``frequency_hz,threshold_p_um,threshold_np_um`` rows (µm, peak) from `path`."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(path, f"cannot read threshold CSV ({exc.__class__.__name__})") from None
    try:
        return parse_thresholds_csv(text, provenance=f"user CSV {path.name}")
    except ValueError as exc:
        raise InputError(path, str(exc)) from None
