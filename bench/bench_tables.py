"""Benchmark of the lookup tables (issue 4): speed against error.

Run ``python bench/bench_tables.py [--quick]``. Prints markdown tables:

1. for tolerances 10 %, 5 %, 2 %, 1 % (0.5 % in the full run) on (a) a Brownian surface (H = 0.5,
   20 x 20 mm at 20 µm; 10 x 10 mm in --quick), (b) a periodic 2/2 twill relief
   (``kes.weave_relief``, 10 µm RMS), (c) ``../shared/fabrics/plain-2000px.jpg`` through the photo
   pipeline (a 600 px crop in --quick): compile time of ``build_checked_tables`` (default scene:
   10-200 mm/s, all directions, footprint 0.25 mm), nodes, raw table size (a40 + a320 as float32,
   before HDF5 compression), the error the compiler stored, and the RMS / max relative error of
   table playback (``playback.interp`` through ``_as_player_tables``) against the reference
   renderer (``render_frames``) on random strokes: straight strokes at random positions, speeds
   log-uniform in 10-200 mm/s (so between nodes), directions and array rotations uniform, 24
   contactors; the reference is computed once per surface and shared by the tolerances;
2. per-frame playback cost: one ``TableInterpolator`` call for 24 and for 1000 contactors against
   two baselines measured in the same run: the reference renderer (``render_frames``, 24
   contactors, one frame; scaled linearly to 1000) and a vectorised direct renderer of the paper's
   kind (B-spline sampling of 128 heights per contactor + the literal FFT, :mod:`haptex_compile.literal`);
3. point model against footprint 0.25 mm: relative error of interpolating channel intensities
   half-way between two nodes (direction steps 45, 15, 5 deg; speed ratios 2, 1.41, 1.19) on a
   Brownian surface, H = 0.45, 20 µm pixels, 57 mm/s (the DOMAIN table), from the reference
   renderer at the two nodes and at the mid-point.
"""
from __future__ import annotations

import argparse
import dataclasses
import time
from pathlib import Path

import numpy as np

from haptex_compile.colours import TwoColourModel
from haptex_compile.compile import _as_player_tables, build_checked_tables, relative_errors
from haptex_compile.fractal import brownian_surface
from haptex_compile.frame_analysis import AnalysisSettings
from haptex_compile.render import contactor_positions, point_intensities, render_frames, straight_path
from haptex_compile.scene import default_scene
from haptex_compile.surface import Surface, periodic_surface_from_tile

PHOTO = Path(__file__).resolve().parents[1].parent / "shared" / "fabrics" / "plain-2000px.jpg"
MODEL = TwoColourModel()
FOOTPRINT_SAMPLES = {True: 2, False: 24}
SETTINGS = AnalysisSettings(footprint_sigma_mm=0.25)


# ---------------------------------------------------------------------------------------------
# Surfaces


def brownian(quick: bool) -> tuple[str, Surface]:
    n = 250 if quick else 1000
    h = brownian_surface((n, n), 0.5, pixel_size_um=20.0, rms_um=10.0, seed=0)
    return f"(a) Brownian H=0.5, {n // 50} x {n // 50} mm, 20 µm px", Surface(h, 20.0)


def twill() -> tuple[str, Surface]:
    from haptex_compile.kes import weave_relief

    relief, _ = weave_relief(25.0, 25.0, "twill_2_2", pixel_size_um=20.0, min_extent_mm=1.0)
    h = np.asarray(relief, dtype=float)
    h = (h - h.mean()) * (10.0 / h.std())
    return f"(b) 2/2 twill, 25 ends & picks/cm, tile {h.shape[1] * 0.02:.2f} mm, 10 µm RMS", periodic_surface_from_tile(h, 20.0)


def photo(quick: bool) -> tuple[str, Surface | None, str]:
    if not PHOTO.is_file():
        return "(c) plain-2000px.jpg", None, f"skipped: {PHOTO} is absent"
    import logging

    from haptex_compile.io_images import read_image
    from haptex_compile.photo import photo_surface
    from haptex_compile.sources import SourceOptions

    logging.getLogger("haptex").setLevel(logging.ERROR)
    grey = read_image(str(PHOTO)).grey
    note = "2000 px"
    if quick:
        ny, nx = grey.shape
        grey = grey[ny // 2 - 200: ny // 2 + 200, nx // 2 - 200: nx // 2 + 200]
        note = "400 px centre crop (quick)"
    t0 = time.perf_counter()
    res = photo_surface(grey, 20.0, SourceOptions(), PHOTO.name, {})
    dt = time.perf_counter() - t0
    s = res.surface
    kind = "periodic cell" if s.periodic else "not periodic"
    return (f"(c) plain-2000px.jpg ({note}, 20 µm px default, 10 µm RMS default; {kind})", s,
            f"photo pipeline {dt:.1f} s (not in compile time)")


# ---------------------------------------------------------------------------------------------
# Reference samples on random strokes


@dataclasses.dataclass
class Samples:
    u: np.ndarray
    v: np.ndarray
    speed: np.ndarray
    direction: np.ndarray
    a40: np.ndarray
    a320: np.ndarray
    seconds_per_frame_24: float


def reference_samples(surface: Surface, n_strokes: int, frames_per_stroke: int, n_contactors: int, seed: int = 0) -> Samples:
    rng = np.random.default_rng(seed)
    contactors = default_scene().contactors_mm
    pick = np.sort(rng.choice(contactors.shape[0], n_contactors, replace=False))
    contactors = contactors[pick]
    if surface.periodic:
        lat = surface.lattice_mm()
        lo, hi = np.zeros(2), np.abs(lat).sum(axis=0)
    else:
        w, h = surface.extent_mm
        lo, hi = np.array([0.2 * w, 0.2 * h]), np.array([0.8 * w, 0.8 * h])
    cols = {k: [] for k in ("u", "v", "speed", "direction", "a40", "a320")}
    times = []
    for _ in range(n_strokes):
        c = rng.uniform(lo, hi)
        speed = float(np.exp(rng.uniform(np.log(10.0), np.log(200.0))))
        theta = float(rng.uniform(0.0, 360.0))
        phi = float(rng.uniform(0.0, 360.0))
        vel = speed * np.array([np.cos(np.deg2rad(theta)), np.sin(np.deg2rad(theta))])

        def trajectory(t, c=c, vel=vel, phi=phi):
            t = np.asarray(t, dtype=float)
            return c[0] + vel[0] * t, c[1] + vel[1] * t, np.full_like(t, phi)

        centres = (np.arange(frames_per_stroke) - (frames_per_stroke - 1) / 2.0) * 0.1
        t0 = time.perf_counter()
        fr = render_frames(surface, MODEL, SETTINGS, contactors, centres, trajectory)
        times.append((time.perf_counter() - t0) / centres.size * 24.0 / contactors.shape[0])
        ou, ov, ph = trajectory(centres)
        pu, pv = contactor_positions(ou, ov, ph, contactors)
        cols["u"].append(pu.ravel())
        cols["v"].append(pv.ravel())
        cols["speed"].append(np.full(pu.size, speed))
        cols["direction"].append(np.full(pu.size, theta))
        cols["a40"].append(fr.a40.ravel())
        cols["a320"].append(fr.a320.ravel())
    arrays = {k: np.concatenate(v) for k, v in cols.items()}
    return Samples(**arrays, seconds_per_frame_24=float(np.median(times)))


# ---------------------------------------------------------------------------------------------


def _time_call(fn, min_time: float = 0.3) -> float:
    fn()
    n, t0 = 0, time.perf_counter()
    while time.perf_counter() - t0 < min_time:
        fn()
        n += 1
    return (time.perf_counter() - t0) / n


def tolerance_rows(name: str, surface: Surface, samples: Samples, tolerances: list[float]) -> tuple[list[str], object]:
    rows = []
    last = None
    for tol in tolerances:
        scene = dataclasses.replace(default_scene(), tolerance=tol)
        t0 = time.perf_counter()
        tables, stats, plan = build_checked_tables(surface, MODEL, SETTINGS, scene, seed=0)
        dt = time.perf_counter() - t0
        interp = _as_player_tables(tables, SETTINGS.frame_ms).interpolator
        a40, a320, _ = interp(samples.u, samples.v, samples.speed, samples.direction)
        e = relative_errors(MODEL, a40, a320, samples.a40, samples.a320)
        mb = 2 * 4 * tables.a40.size / 1e6
        nd, ns, nj, ni = tables.a40.shape
        rows.append(f"| {name} | {100 * tol:g} % | {dt:.1f} s | {nd} x {ns} x {nj} x {ni} ({plan.spacing_mm:.3g} mm) | {mb:.2f} MB "
                    f"| {100 * stats['rms_rel_error']:.2f} % {'' if stats['tolerance_met'] else '(not met)'} "
                    f"| {100 * stats['rms_rel_error_upper95']:.2f} % "
                    f"| {100 * float(np.sqrt(np.mean(e ** 2))):.2f} % | {100 * float(e.max()):.1f} % | {e.size} |")
        last = tables
    return rows, last


def _reference_frame_seconds(surface: Surface, contactors: np.ndarray, reps: int) -> float:
    """render_frames for one frame at 80 mm/s (median of `reps`)."""
    def traj(t):
        t = np.asarray(t, dtype=float)
        return 1.0 + 80.0 * np.cos(0.5) * t, 1.0 + 80.0 * np.sin(0.5) * t, np.full_like(t, 20.0)

    times = []
    for _ in range(reps):
        t0 = time.perf_counter()
        render_frames(surface, MODEL, SETTINGS, contactors, np.array([0.0]), traj)
        times.append(time.perf_counter() - t0)
    return float(np.median(times))


def _literal_direct_seconds(surface: Surface, n: int) -> float:
    """A vectorised direct renderer of the paper's kind: sample 128 heights per contactor along a
    straight path and run the literal 25 ms FFT (the issue's ~0.26 ms class of baseline)."""
    from haptex_compile.literal import literal_frame_amplitudes, literal_inverse_thresholds
    from haptex_compile.surface import sample_height

    rng = np.random.default_rng(5)
    u0, v0 = rng.uniform(0, 5, (n, 1)), rng.uniform(0, 5, (n, 1))
    t = (np.arange(128) - 63.5) / 5120.0
    curves = MODEL.thresholds
    inv = literal_inverse_thresholds(128, 5120.0, curves)  # once, as a renderer would

    def frame():
        h = sample_height(surface, u0 + 80.0 * t, v0 + 20.0 * t)
        return literal_frame_amplitudes(h, 5120.0, curves, inverse_thresholds=inv)

    return _time_call(frame)


def playback_cost_rows(name: str, surface: Surface, tables, quick: bool) -> list[str]:
    interp = _as_player_tables(tables, SETTINGS.frame_ms).interpolator
    rng = np.random.default_rng(3)
    contactors = default_scene().contactors_mm
    ref24 = _reference_frame_seconds(surface, contactors, 1 if quick else 3)
    out = [f"| {name}: reference renderer (render_frames), 24 contactors, 1 frame at 80 mm/s | {1e3 * ref24:.0f} ms | | |"]
    for n in (24, 1000):
        u, v = rng.uniform(0, 10, n), rng.uniform(0, 10, n)
        s, d = rng.uniform(10, 200, n), rng.uniform(0, 360, n)
        t = _time_call(lambda: interp(u, v, s, d))
        lit = _literal_direct_seconds(surface, n)
        ref = ref24 * n / 24.0
        out.append(f"| tables (TableInterpolator), {n} contactors | {1e6 * t:.1f} µs "
                   f"| {1e3 * ref:.0f} ms{'' if n == 24 else ' (24-contactor time x ' + f'{n / 24:.1f})'}; literal direct FFT renderer {1e3 * lit:.2f} ms "
                   f"| {ref / t:,.0f} x; {lit / t:.1f} x |")
    return out


def footprint_rows(quick: bool) -> list[str]:
    n_px = 600 if quick else 1000
    h = brownian_surface((n_px, n_px), 0.45, pixel_size_um=20.0, rms_um=10.0, seed=7)
    surf = Surface(h, 20.0)
    w = surf.extent_mm[0]
    n_samples = FOOTPRINT_SAMPLES[quick]
    speed = 57.0
    rows = []
    for sigma in (0.0, 0.25):
        s = AnalysisSettings(footprint_sigma_mm=sigma)
        rng = np.random.default_rng(11)

        def intens(p, spd, d):
            return np.array(point_intensities(surf, MODEL, s, straight_path(p[0], p[1], spd, d), 0.0))

        cells = []
        for kind, steps in (("dir", (45.0, 15.0, 5.0)), ("speed", (2.0, np.sqrt(2.0), 2 ** 0.25))):
            for step in steps:
                errs = []
                for _ in range(n_samples):
                    p = rng.uniform(0.3 * w, 0.7 * w, 2)
                    if kind == "dir":
                        d0 = rng.uniform(0, 180)
                        lo, hi, mid = intens(p, speed, d0), intens(p, speed, d0 + step), intens(p, speed, d0 + step / 2)
                    else:
                        d0 = rng.uniform(0, 180)
                        r = np.sqrt(step)
                        lo, hi, mid = intens(p, speed / r, d0), intens(p, speed * r, d0), intens(p, speed, d0)
                    errs.append(np.abs(0.5 * (lo + hi) - mid) / mid)  # both channels
                cells.append(float(np.sqrt(np.mean(np.square(errs)))))
        label = "point (paper)" if sigma == 0 else f"footprint, Gaussian σ = {sigma:g} mm"
        rows.append(f"| {label} | " + " | ".join(f"{100 * c:.1f} %" for c in cells) + " |")
    return rows


def run(quick: bool = False) -> str:
    """All tables as one markdown string."""
    tolerances = [0.05] if quick else [0.10, 0.05, 0.02, 0.01, 0.005]
    n_strokes, per_stroke, n_cont = (2, 1, 4) if quick else (8, 3, 24)
    surfaces = [brownian(quick), twill()]
    notes = []
    if quick:
        notes.append("(c) photo: skipped in --quick (its compile alone takes tens of seconds); run without --quick")
    else:
        ph = photo(quick)
        notes.append(ph[2])
        if ph[1] is not None:
            surfaces.append((ph[0], ph[1]))
    head = ["| surface | tolerance | compile time | nodes dir x speed x j x i (spacing) | table size | stored RMS error "
            "| its 95 % upper bound | playback RMS error vs reference | playback max error | samples |",
            "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    rows, cost = [], []
    for name, surf in surfaces:
        samples = reference_samples(surf, n_strokes, per_stroke, n_cont)
        r, tables = tolerance_rows(name, surf, samples, tolerances)
        rows += r
        cost += playback_cost_rows(name, surf, tables, quick)
    fp = footprint_rows(quick)
    parts = [
        "### Tables: speed against error (default scene: 10-200 mm/s, all directions, footprint 0.25 mm)", "",
        *head, *rows, "",
        *(f"- {n}" for n in notes if n), "",
        "### Per-frame playback cost (tables from the tightest tolerance above)", "",
        "| what | time per frame | baselines: reference renderer; vectorised literal renderer | ratio (baseline / tables) |",
        "| --- | --- | --- | --- |", *cost, "",
        f"### Interpolation half-way between nodes (Brownian H = 0.45, 20 µm px, 57 mm/s; RMS over "
        f"{FOOTPRINT_SAMPLES[quick]} positions x 2 channels of |mean of nodes - mid| / mid)", "",
        "| model | 45° step | 15° step | 5° step | speed ratio 2 | ratio 1.41 | ratio 1.19 |",
        "| --- | --- | --- | --- | --- | --- | --- |", *fp, "",
    ]
    return "\n".join(parts)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="smaller surfaces, fewer samples, no 0.5 % row")
    print(run(quick=parser.parse_args().quick))


if __name__ == "__main__":
    main()
