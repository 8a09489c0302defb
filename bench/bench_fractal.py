"""Bias table and timings of Brownian-surface synthesis (issue 8).

For H = 0.1 ... 0.9: each synthesis method's variogram-recovered H (mean, SD over seeds at
512^2) and time per surface; the exact fields also through the madogram and spectral
estimators; then the 1024^2 timing across H. Baseline measured in the same run: the paper's
midpoint displacement.

    python bench/bench_fractal.py [--quick]
"""
from __future__ import annotations

import argparse
import time

import numpy as np

from haptex_compile.fractal import brownian_surface, estimate_hurst, stein_embedding_shape
from haptex_compile.fractal_synthesis import _stein_sqrt_eigenvalues

HURSTS = [0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9]
METHODS = [("midpoint (paper, baseline)", {"method": "midpoint"}), ("circulant (exact)", {}), ("periodic spectral", {"periodic": True})]


def _timed(fn):
    t = time.perf_counter()
    out = fn()
    return out, time.perf_counter() - t


def run(quick: bool = False) -> str:
    n_seeds = 4 if quick else 20
    size = 512
    lines = [
        f"### Recovered H (variogram, lags 1-2 px), {size}x{size}, {n_seeds} seeds; time per surface",
        "",
        "| H | method | mean H | bias | SD | ms/surface | time / baseline |",
        "| --- | --- | --- | --- | --- | --- | --- |",
    ]
    est_lines = [
        f"### Estimators on exact (circulant) fields, {size}x{size}, {n_seeds} seeds",
        "",
        "| H | variogram bias (SD) | madogram bias (SD) | spectral bias (SD) | spectral ms |",
        "| --- | --- | --- | --- | --- |",
    ]
    worst = {name: 0.0 for name, _ in METHODS}
    worst_est = {"variogram": 0.0, "madogram": 0.0, "spectral": 0.0}
    for hurst in HURSTS:
        base_time = None
        for name, kw in METHODS:
            got, secs = [], []
            by_est: dict[str, list[float]] = {"madogram": [], "spectral": []}
            spec_secs = []
            for seed in range(n_seeds):
                z, dt = _timed(lambda: brownian_surface(size, hurst, pixel_size_um=10.0, rms_um=1.0, seed=seed, **kw))
                secs.append(dt)
                got.append(estimate_hurst(z, ci="none").hurst)
                if name.startswith("circulant"):
                    by_est["madogram"].append(estimate_hurst(z, method="madogram", ci="none").hurst)
                    e, dt = _timed(lambda: estimate_hurst(z, method="spectral", ci="none"))
                    by_est["spectral"].append(e.hurst)
                    spec_secs.append(dt)
            # Median time: the first exact call per H also builds the cached embedding.
            t_ms = 1e3 * float(np.median(secs))
            if base_time is None:
                base_time = t_ms
            bias = float(np.mean(got)) - hurst
            worst[name] = max(worst[name], abs(bias))
            lines.append(
                f"| {hurst:.1f} | {name} | {np.mean(got):.4f} | {bias:+.4f} | {np.std(got, ddof=1):.4f} "
                f"| {t_ms:.1f} | {t_ms / base_time:.2f} |"
            )
            if name.startswith("circulant"):
                cells = [f"{bias:+.4f} ({np.std(got, ddof=1):.4f})"]
                worst_est["variogram"] = max(worst_est["variogram"], abs(bias))
                for key in ("madogram", "spectral"):
                    b = float(np.mean(by_est[key])) - hurst
                    worst_est[key] = max(worst_est[key], abs(b))
                    cells.append(f"{b:+.4f} ({np.std(by_est[key], ddof=1):.4f})")
                est_lines.append(f"| {hurst:.1f} | {' | '.join(cells)} | {1e3 * np.median(spec_secs):.0f} |")
    lines.append("")
    lines.append("Worst |bias|: " + ", ".join(f"{k} {v:.4f}" for k, v in worst.items()) + " (target exact <= 0.02)")
    est_lines.append("")
    est_lines.append("Worst |bias|: " + ", ".join(f"{k} {v:.4f}" for k, v in worst_est.items()) + " (target <= 0.03)")

    big = 1024
    timing = [
        f"### {big}x{big} synthesis time across H (2 cores; cold = first call incl. embedding eigenvalues, warm = cached)",
        "",
        "| H | torus | cold s | warm s | warm / midpoint |",
        "| --- | --- | --- | --- | --- |",
    ]
    repeats = 1 if quick else 3
    mid = min(_timed(lambda: brownian_surface(big, 0.5, pixel_size_um=10.0, rms_um=1.0, seed=s, method="midpoint"))[1] for s in range(repeats))
    for hurst in ([0.1, 0.5, 0.75, 0.8, 0.9] if quick else HURSTS):
        _stein_sqrt_eigenvalues.cache_clear()
        _, cold = _timed(lambda: brownian_surface(big, hurst, pixel_size_um=10.0, rms_um=1.0, seed=0))
        warm = min(_timed(lambda: brownian_surface(big, hurst, pixel_size_um=10.0, rms_um=1.0, seed=s + 1))[1] for s in range(repeats))
        my, mx = stein_embedding_shape(big, hurst)
        timing.append(f"| {hurst:.2f} | {my}x{mx} | {cold:.3f} | {warm:.3f} | {warm / mid:.1f} |")
    timing.append("")
    timing.append(f"Baseline: midpoint {big}x{big} (H = 0.5) {mid:.3f} s. Target: exact 1024^2 at H = 0.5 under 1 s.")
    return "\n".join(lines + [""] + est_lines + [""] + timing) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="fewer seeds (under a minute)")
    print(run(quick=parser.parse_args().quick))


if __name__ == "__main__":
    main()
