"""The paper's experiment (Sect. 6.4) as a check: felt roughness rises with fractal dimension.

Brownian surfaces of equal RMS height for H = 0.1 ... 0.9 (D = 3 - H), rendered at 80 mm/s
through the perceptual core (tables over 4 directions); roughness measures built from the
tactile output: the total channel intensity sqrt(I_p^2 + I_np^2) and the 320 Hz share of the
felt amplitude, a320/T_p(320) over a40/T_np(40) + a320/T_p(320). Spearman rank correlation
with D; baseline in the same run: the surfaces' RMS slope (a geometric roughness measure).

    python bench/bench_roughness.py [--quick]
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from haptex_compile.colours import TwoColourModel  # noqa: E402
from haptex_compile.fractal import brownian_surface  # noqa: E402
from haptex_compile.frame_analysis import AnalysisSettings  # noqa: E402
from haptex_compile.surface import Surface  # noqa: E402
from haptex_compile.tables import build_tables, table_grid  # noqa: E402


def spearman(x: np.ndarray, y: np.ndarray) -> float:
    rx = np.argsort(np.argsort(x)).astype(float)
    ry = np.argsort(np.argsort(y)).astype(float)
    return float(np.corrcoef(rx, ry)[0, 1])


def roughness_measures(hursts, *, size: int = 256, pixel_um: float = 20.0, rms_um: float = 5.0,
                       speed_mm_s: float = 80.0, seeds=(0, 1)) -> list[dict]:
    """Tactile and geometric roughness of equal-RMS Brownian surfaces (means over seeds)."""
    model = TwoColourModel()
    settings = AnalysisSettings()
    t40 = float(model.thresholds.np_(40.0))
    t320 = float(model.thresholds.p(320.0))
    rows = []
    for h in hursts:
        total, share, slope = [], [], []
        for seed in seeds:
            z = brownian_surface(size, h, pixel_size_um=pixel_um, rms_um=rms_um, seed=seed)
            s = Surface(z, pixel_um, False)
            tab = build_tables(s, model, settings, np.array([0.0, 45.0, 90.0, 135.0]), np.array([speed_mm_s]),
                               table_grid(s, 0.5))
            total.append(float(np.mean(np.hypot(tab.intensity_p, tab.intensity_np))))
            f40, f320 = tab.a40 / t40, tab.a320 / t320
            share.append(float(np.mean(f320 / np.maximum(f40 + f320, 1e-12))))
            gy, gx = np.gradient(z, pixel_um)
            slope.append(float(np.sqrt(np.mean(gx**2 + gy**2))))
        rows.append({"hurst": h, "dimension": 3 - h, "total_intensity": np.mean(total), "share_320": np.mean(share),
                     "rms_slope": np.mean(slope)})
    return rows


PLOT_DATA: list[dict] = []  # filled by run(): the paper's Fig. 16 analogue for the report


def run(quick: bool = False) -> str:
    hursts = [0.1, 0.3, 0.5, 0.7, 0.9] if quick else [0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9]
    t0 = time.perf_counter()
    rows = roughness_measures(hursts, seeds=(0,) if quick else (0, 1, 2))
    dt = time.perf_counter() - t0
    d = np.array([r["dimension"] for r in rows])
    PLOT_DATA[:] = [{
        "title": "Felt roughness against fractal dimension (equal RMS, 80 mm/s)",
        "x_label": "fractal dimension D = 3 - H", "y_label": "measure / its value at the largest D",
        "series": [
            {"label": "total channel intensity", "x": d.tolist(),
             "y": [r["total_intensity"] / rows[0]["total_intensity"] for r in rows]},
            {"label": "320 Hz share", "x": d.tolist(), "y": [r["share_320"] / rows[0]["share_320"] for r in rows]},
            {"label": "RMS slope (geometric baseline)", "x": d.tolist(),
             "y": [r["rms_slope"] / rows[0]["rms_slope"] for r in rows], "baseline": True},
        ],
        "log_x": False, "log_y": True,
    }]
    lines = ["| H | D | total channel intensity (x threshold) | 320 Hz share of felt amplitude | RMS slope (baseline) |",
             "| --- | --- | --- | --- | --- |"]
    for r in rows:
        lines.append(f"| {r['hurst']:.1f} | {r['dimension']:.1f} | {r['total_intensity']:.2f} | {r['share_320']:.3f} | {r['rms_slope']:.3f} |")
    lines.append("")
    lines.append(f"Spearman rank correlation with D: total intensity {spearman(d, np.array([r['total_intensity'] for r in rows])):.3f}, "
                 f"320 Hz share {spearman(d, np.array([r['share_320'] for r in rows])):.3f}, "
                 f"RMS slope {spearman(d, np.array([r['rms_slope'] for r in rows])):.3f}. "
                 f"256 x 256 px at 20 µm, RMS 5 µm, 80 mm/s, footprint 0.25 mm; {dt:.1f} s.")
    return "\n".join(lines)


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--quick", action="store_true")
    print(run(parser.parse_args().quick))
