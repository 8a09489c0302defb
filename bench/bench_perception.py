"""Benchmark of the perceptual core (issue 3): pure-tone recovery and cost per frame.

Run ``python bench/bench_perception.py [--quick]``. Prints markdown tables:

1. pure-tone recovery at 20-500 Hz: the paper's literal method (25 ms Blackman FFT, sum of bin
   amplitudes over raw thresholds, n = 1; worst over 16 phases; also with the bin sum
   normalised, which isolates the leakage from the normalisation) against ours (the reference
   analysis on a sinusoidal surface at 80 mm/s, footprint 0 and 0.25 mm, n = 1.23). Each method
   is scored against its *own* exact two-colour pair of the tone (its thresholds, band and n), so
   the error is the analysis's, not a difference of models: error = max(|da40|, |da320|) / A;
2. time per frame per contactor: the literal FFT (baseline, vectorised over frames and
   contactors) against ``point_intensities`` (footprint 0 and 0.25 mm) on a Brownian surface;
3. condition numbers of the 2 x 2 system.
"""
from __future__ import annotations

import argparse
import time

import numpy as np

from haptex_compile.colours import TwoColourModel
from haptex_compile.fractal import brownian_surface
from haptex_compile.frame_analysis import AnalysisSettings
from haptex_compile.literal import literal_frame_amplitudes, literal_inverse_thresholds, literal_matrix
from haptex_compile.render import point_intensities, straight_path
from haptex_compile.surface import periodic_surface_from_tile
from haptex_compile.thresholds import idealised_thresholds

FREQS_HZ = (20.0, 40.0, 80.0, 160.0, 250.0, 320.0, 500.0)
SPEED = 80.0
AMP = 5.0
RATE_HZ = 5120.0  # literal method: 128 samples per 25 ms frame


def _tone_surface(freq_hz: float, amp_um: float, speed: float = SPEED):
    lam = speed / freq_hz
    length = max(1, int(np.ceil(4.0 / lam))) * lam
    nx = int(round(length * 100.0))  # ~10 µm pixels
    px_um = length * 1000.0 / nx
    u = np.arange(nx) * px_um / 1000.0
    return periodic_surface_from_tile(np.tile(amp_um * np.sin(2 * np.pi * u / lam), (8, 1)), px_um)


def _literal_ideal(curves, freq_hz: float) -> np.ndarray:
    a = np.linalg.solve(literal_matrix(curves), AMP / np.array([curves.p(freq_hz), curves.np_(freq_hz)]))
    return np.maximum(a, 0.0)


def _ours_ideal(model: TwoColourModel, freq_hz: float) -> tuple[np.ndarray, float]:
    d = model.decompose(*model.tone_intensities(freq_hz, AMP))
    return np.array([float(d.a40), float(d.a320)]), float(d.out_of_gamut)


def _err(got: np.ndarray, want: np.ndarray) -> float:
    return float(np.max(np.abs(np.asarray(got) - want)) / AMP)


def tone_table(quick: bool) -> str:
    curves = idealised_thresholds()
    model = TwoColourModel()
    n_phase = 8 if quick else 16
    t = np.arange(int(round(0.025 * RATE_HZ))) / RATE_HZ
    phases = np.linspace(0, 2 * np.pi, n_phase, endpoint=False)
    rows = ["| f (Hz) | literal exact (a40, a320)/A | literal measured, worst phase | literal err | literal, sum-norm. err "
            "| ours exact (a40, a320)/A (n=1.23) | out of gamut | ours err, footprint 0 | ours err, footprint 0.25 mm |",
            "| --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    for f in FREQS_HZ:
        sig = AMP * np.sin(2 * np.pi * f * t + phases[:, None])
        want_l = _literal_ideal(curves, f)
        errs = {}
        for norm in ("peak", "sum"):
            a40, a320 = literal_frame_amplitudes(sig, RATE_HZ, curves, normalisation=norm)
            e = np.maximum(np.abs(a40 - want_l[0]), np.abs(a320 - want_l[1])) / AMP
            k = int(np.argmax(e))
            errs[norm] = (float(e[k]), a40[k] / AMP, a320[k] / AMP)
        want_o, gamut = _ours_ideal(model, f)
        surf = _tone_surface(f, AMP)
        ours = []
        for fp in (0.0, 0.25):
            ip, inp = point_intensities(surf, model, AnalysisSettings(footprint_sigma_mm=fp),
                                        straight_path(0.37, 0.04, SPEED, 0.0), 0.0)
            d = model.decompose(ip, inp)
            ours.append(_err([float(d.a40), float(d.a320)], want_o))
        rows.append(
            f"| {f:g} | ({want_l[0] / AMP:.3f}, {want_l[1] / AMP:.3f}) | ({errs['peak'][1]:.3f}, {errs['peak'][2]:.3f}) "
            f"| {100 * errs['peak'][0]:.1f} % | {100 * errs['sum'][0]:.1f} % | ({want_o[0] / AMP:.3f}, {want_o[1] / AMP:.3f}) "
            f"| {gamut:.3f} | {100 * ours[0]:.3f} % | {100 * ours[1]:.3f} % |")
    return "\n".join(rows)


def timing_table(quick: bool) -> str:
    curves = idealised_thresholds()
    model = TwoColourModel()
    n_frames, n_cont = (50, 24) if quick else (400, 24)
    rng = np.random.default_rng(0)
    frames = rng.normal(size=(n_frames, n_cont, int(round(0.025 * RATE_HZ))))
    inv = literal_inverse_thresholds(frames.shape[-1], RATE_HZ, curves)  # once per renderer
    literal_frame_amplitudes(frames[:2], RATE_HZ, curves, inverse_thresholds=inv)
    t0 = time.perf_counter()
    reps = 3
    for _ in range(reps):
        literal_frame_amplitudes(frames, RATE_HZ, curves, inverse_thresholds=inv)
    t_lit = (time.perf_counter() - t0) / reps / (n_frames * n_cont)
    h = brownian_surface((500, 500), 0.45, pixel_size_um=20.0, rms_um=10.0, seed=0, periodic=True)
    surf = periodic_surface_from_tile(h, 20.0)
    n_calls = 8 if quick else 40
    rows = ["| method | time per frame per contactor | ratio to literal |", "| --- | --- | --- |",
            f"| literal paper FFT (baseline; heights already sampled) | {1e6 * t_lit:.1f} µs | 1 |"]
    for fp in (0.0, 0.25):
        s = AnalysisSettings(footprint_sigma_mm=fp)
        point_intensities(surf, model, s, straight_path(1.0, 1.0, SPEED, 10.0), 0.0)
        t0 = time.perf_counter()
        for k in range(n_calls):
            u, v = rng.uniform(0, 10, 2)
            ip, inp = point_intensities(surf, model, s, straight_path(u, v, rng.uniform(10, 200), rng.uniform(0, 360)), 0.0)
            model.decompose(ip, inp)
        t = (time.perf_counter() - t0) / n_calls
        rows.append(f"| ours, reference analysis (point_intensities + decompose), footprint {fp:g} mm, 10-200 mm/s "
                    f"| {1e3 * t:.2f} ms | {t / t_lit:.0f} |")
    return "\n".join(rows)


def condition_table() -> str:
    curves = idealised_thresholds()
    rows = ["| system | condition number |", "| --- | --- |",
            f"| literal paper (raw thresholds, n = 1) | {np.linalg.cond(literal_matrix(curves)):.2f} |"]
    for n in (1.0, 1.23):
        rows.append(f"| ours, n = {n:g} (band-weighted, u = a^n) | {TwoColourModel(summation_exponent=n).condition_number():.2f} |")
    return "\n".join(rows)


def run(quick: bool = False) -> str:
    """All tables as one markdown string."""
    parts = [
        "### Pure-tone recovery (A = 5 µm; error = max(|da40|, |da320|) / A against each method's exact pair)",
        "", tone_table(quick), "",
        "### Cost per frame per contactor", "", timing_table(quick), "",
        "### 2 x 2 system", "", condition_table(), "",
    ]
    return "\n".join(parts)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="fewer phases and repetitions (under a minute)")
    print(run(quick=parser.parse_args().quick))


if __name__ == "__main__":
    main()
