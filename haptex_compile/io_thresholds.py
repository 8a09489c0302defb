"""Reading user threshold curves from CSV files."""
from __future__ import annotations

from pathlib import Path

from haptex_compile.errors import InputError
from haptex_compile.thresholds import ThresholdCurves, parse_thresholds_csv
from playback.text_files import read_text


def read_thresholds_csv(path: str | Path) -> ThresholdCurves:
    """Read ``frequency_hz,threshold_p_um,threshold_np_um`` rows (µm, peak) from `path`."""
    path = Path(path)
    text = read_text(path, "threshold CSV")
    try:
        return parse_thresholds_csv(text, provenance=f"user CSV {path.name}")
    except ValueError as exc:
        raise InputError(path, str(exc)) from None
