"""Benchmark of KES-F surface synthesis: given vs simulated SMD, error and time.

Run ``python bench/bench_kes.py [--quick]``. For the sample fabrics (samples/kes) and a sweep
of SMD 1..20 µm (including strongly anisotropic cases) it synthesises a surface with
:func:`haptex_compile.kes.kes_surface` and measures it with the simulated KES-FB4 probe.

Baseline, measured in the same run: the uncalibrated first guess (``calibrate=False``): the
same surface model with its components scaled so that the raw height profiles have the given
mean deviation, i.e. heights scaled by the SMD directly without simulating the wire probe.

Columns: given SMD; the baseline's simulated SMD and worst error; the calibrated surface's
simulated SMD (the solver's 128 traverses) and worst error; the worst error re-measured with a
dense probe (every row and column); synthesis times; ratios baseline/calibrated.
"""
from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

from haptex_compile.kes import kes_surface, simulate_kes_smd
from haptex_compile.kes_io import KesData, read_kes

SAMPLES = Path(__file__).resolve().parents[1] / "samples" / "kes"

SWEEP_FULL = [
    ("plain", 48, 30, 1.0, 1.0), ("plain", 48, 30, 2.0, 15.0), ("plain", 48, 30, 20.0, 20.0),
    ("twill", 32, 28, 15.0, 2.0), ("twill", 32, 28, 5.0, 5.0), ("twill", 32, 28, 1.0, 20.0),
    ("twill_3_1", 28, 18, 10.0, 3.0), ("twill_3_1", 28, 18, 20.0, 1.0),
    ("satin", 100, 40, 1.0, 2.0), ("satin", 100, 40, 12.0, 12.0), ("satin", 100, 40, 2.0, 15.0),
    ("twill_2_1", 100, 80, 8.0, 10.0), ("plain", 8, 6, 3.0, 18.0),
]
SWEEP_QUICK = [("plain", 48, 30, 2.0, 15.0), ("satin", 100, 40, 12.0, 12.0), ("twill", 32, 28, 20.0, 1.0)]


def _cases(quick: bool) -> list[tuple[str, KesData]]:
    cases = [(path.name.replace(".kes.json", ""), read_kes(path)) for path in sorted(SAMPLES.glob("*.kes.json"))]
    for weave, ends, picks, warp, weft in (SWEEP_QUICK if quick else SWEEP_FULL):
        data = KesData(f"sweep {weave}", {"warp": warp, "weft": weft}, {"warp": 0.2, "weft": 0.2},
                       {"warp": 0.01, "weft": 0.01}, ends, picks, weave)
        cases.append((f"{weave} {ends}x{picks}/cm", data))
    return cases


def _error_pct(measured: dict[str, float], given: dict[str, float]) -> float:
    return max(abs(measured[d] / given[d] - 1) * 100 for d in ("warp", "weft"))


def run(quick: bool = False) -> str:
    """Run the benchmark and return a markdown report."""
    rows = []
    stats = {"base_err": [], "cal_err": [], "dense_err": [], "base_t": [], "cal_t": []}
    for name, data in _cases(quick):
        t0 = time.perf_counter()
        base = kes_surface(data, calibrate=False)
        t_base = time.perf_counter() - t0
        t0 = time.perf_counter()
        cal = kes_surface(data)
        t_cal = time.perf_counter() - t0
        dense = {d: simulate_kes_smd(cal.height_um, cal.pixel_size_um, d, n_traverses=100_000)
                 for d in ("warp", "weft")}
        given = data.smd_um
        e_base, e_cal, e_dense = (_error_pct(m, given) for m in (base.smd_simulated_um, cal.smd_simulated_um, dense))
        for key, value in zip(stats, (e_base, e_cal, e_dense, t_base, t_cal)):
            stats[key].append(value)
        nx, ny = cal.period_px
        rows.append(
            f"| {name} | {data.weave} | {nx}x{ny} | {given['warp']:g} / {given['weft']:g} "
            f"| {base.smd_simulated_um['warp']:.2f} / {base.smd_simulated_um['weft']:.2f} | {e_base:.1f} "
            f"| {cal.smd_simulated_um['warp']:.2f} / {cal.smd_simulated_um['weft']:.2f} | {e_cal:.2f} "
            f"| {e_dense:.2f} | {t_base:.2f} | {t_cal:.2f} | {e_base / max(e_cal, 1e-3):.0f} | {t_cal / t_base:.2f} |")
    header = [
        "| case | weave | px (nx x ny) | given SMD warp / weft (µm) | baseline SMD (µm) | baseline err % "
        "| calibrated SMD (µm) | calibrated err % | dense re-measure err % | baseline time (s) "
        "| calibrated time (s) | err ratio base/cal | time ratio cal/base |",
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    summary = (
        f"\nWorst error: baseline {max(stats['base_err']):.1f} %, calibrated {max(stats['cal_err']):.2f} % "
        f"(dense re-measure {max(stats['dense_err']):.2f} %); target 5 %.  "
        f"Synthesis + calibration time at 10 µm pixels: median {statistics.median(stats['cal_t']):.2f} s, "
        f"max {max(stats['cal_t']):.2f} s (target < 1.5 s); baseline median {statistics.median(stats['base_t']):.2f} s.\n"
    )
    title = f"### KES-F surface synthesis ({'quick' if quick else 'full'} run, {len(rows)} cases)\n\n"
    return title + "\n".join(header + rows) + "\n" + summary


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="fewer cases (under a minute)")
    args = parser.parse_args(argv)
    print(run(quick=args.quick))
    return 0


if __name__ == "__main__":
    sys.exit(main())
