"""The photograph pipeline against ground truth: heights from a rendered lattice-periodic relief.

Each case paints a relief exactly periodic under an (often oblique) lattice over a 1024 px image
of 20 µm pixels (``synth_images.lattice_relief``: smooth, RMS slope about 0.2; and
``weave_image`` plain, scaled to 40 µm), renders it as a Lambertian image (albedo 0.8) and runs
the photo pipeline (``photo.photo_surface``: flattening, lattice, tile average, shape from
shading, relief scale; no synthetic roughness). Error: normalised RMS height error after the
best affine fit, over every other pixel of the photo (the surface read at the photo's pixels
with ``photo.heights_at_image_px``; 0 perfect, 1 nothing recovered).

Baseline, measured in the same run: the surface on the whole photo, shaded with free edges
(what the pipeline did before its surface became a periodic window of the tile), with the light,
when estimated, estimated on the whole photo (the pipeline estimates it on a small periodic
window of the tile, at most 256 px). For estimated lights the table shows the window's estimate
and its error: the slant's, and the angle between the tilts' axes (a tilt and the tilt + 180°
light the same relief, bumps versus dents, with the heights negated), and what it changes in
what users feel: the window's mean a40 and a320 (``tables.mean_tactile``) against those of
the window solved with the light given.

A second table stretches the photo quadratically from its centre (a weave that drifts across
the photo, as real ones do) and compares the tile averaged over the whole photo (baseline) with
the tile averaged over the central region where the weave repeats best. A third lights plain
weaves and smooth cells (light given) at angles off one of their weave directions and marks
the lights the report warns of (``shading.weave_visibility``). A fourth (not with --quick) gives
the light a few degrees off the true one: how much the heights change, against how well the
solver's heights still explain the image. Another (``_coarse_rows``) takes coarse lattices with
no periodic window, solved whole unless the detected lattice finds one, light given and
estimated: the height error, and the mean a40 / a320 against the true relief's.

    python bench/bench_photo.py [--quick]
"""
from __future__ import annotations

import argparse
import contextlib
import statistics
import sys
import time
from pathlib import Path
from unittest import mock

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from haptex_compile import tiles  # noqa: E402
from haptex_compile.known_surfaces import rms_slope  # noqa: E402
from haptex_compile.photo import heights_at_image_px, photo_surface  # noqa: E402
from haptex_compile.shading import (  # noqa: E402
    Light, normalised_height_error, render_lambertian, tilt_axis_difference_deg,
)
from haptex_compile.shading_starts import WEAVE_VISIBILITY_MIN  # noqa: E402
from haptex_compile.sources import SourceOptions  # noqa: E402
from haptex_compile.tables import mean_tactile  # noqa: E402
from haptex_compile.synth_images import lattice_relief, stretch_from_centre, weave_image  # noqa: E402

PIXEL_UM = 20.0
SIZE = 1024
CASES = [((18.3, 3.1), (-4.2, 15.7), (40.0, 60.0)), ((21.0, 0.0), (0.0, 16.5), (30.0, 200.0)),
         ((14.2, -5.3), (6.1, 19.8), (55.0, 300.0)), ((9.34, 7.85), (-8.53, 9.3), (45.0, 120.0))]


def _reliefs(t1, t2) -> dict[str, np.ndarray]:
    return {"smooth cell": lattice_relief((SIZE, SIZE), t1, t2, amplitude_um=12.0),
            "plain weave": 40.0 * weave_image((SIZE, SIZE), t1, t2, kind="plain")}


def _pipeline(image: np.ndarray, truth: np.ndarray, light, whole: bool):
    """The photo pipeline's result on `image` (the truth's RMS as relief) and its seconds."""
    options = SourceOptions(light=light, roughness="none", relief_um=float(np.std(truth)))
    with mock.patch.object(tiles, "periodic_window", lambda *a, **k: None) if whole else contextlib.nullcontext():
        t0 = time.perf_counter()
        result = photo_surface(image, PIXEL_UM, options, "bench", {})
        return result, time.perf_counter() - t0


def _height_error(result, truth: np.ndarray) -> float:
    """Normalised height error of the pipeline's surface over every other pixel of the photo."""
    y, x = np.mgrid[0:SIZE:2, 0:SIZE:2]
    return normalised_height_error(heights_at_image_px(result, x.ravel(), y.ravel()), truth[y, x].ravel())


def _tactile_change(tactile: dict, reference: dict) -> str:
    """"a40 / a320" relative changes of `tactile` from `reference` (``tables.mean_tactile``)."""
    return " / ".join(f"{tactile[k] / reference[k] - 1:+.0%}" for k in ("a40", "a320"))


def _solve(image: np.ndarray, truth: np.ndarray, light, whole: bool) -> tuple[float, float, dict]:
    result, seconds = _pipeline(image, truth, light, whole)
    return _height_error(result, truth), seconds, result.report["shading"]


def _light_cells(shading: dict, light) -> str:
    """The estimated light's two cells: slant, tilt († when flagged unreliable), and its error
    from the true `light`: slant, and the angle between the tilts' axes (the tilt's 180°
    ambiguity, bumps versus dents, is exact: the heights are negated)."""
    slant, tilt = shading["light_slant_deg"], shading["light_tilt_deg"]
    flag = " †" if shading.get("light_albedo_at_bound") else ""
    return (f"{slant:.1f}, {tilt:.1f}{flag} | {slant - light[0]:+.1f},"
            f" {tilt_axis_difference_deg(tilt, light[1]):.1f}")


def run(quick: bool = False) -> str:
    rows = ["| relief | lattice t1; t2 (px) | light slant, tilt (°) | light | whole image (baseline): error | s | periodic window: error | s | window (px) | window's light: slant, tilt (°) | its error: slant, tilt axis (°) | error ratio window / whole | time ratio | window's a40 / a320 against the given light's |",
            "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    ratios: dict[str, list[float]] = {"given": [], "estimated": []}
    times: list[float] = []
    for t1, t2, light in (CASES[:2] if quick else CASES):
        for name, truth in _reliefs(t1, t2).items():
            image = render_lambertian(truth, PIXEL_UM, Light(*light), 0.8)
            for given in (True, False):
                e_whole, s_whole, _ = _solve(image, truth, light if given else None, whole=True)
                result, s_win = _pipeline(image, truth, light if given else None, whole=False)
                e_win, shading = _height_error(result, truth), result.report["shading"]
                # What users feel: the tables' mean a40, a320 of the window (same relief).
                tactile = mean_tactile(result.surface.height_um, PIXEL_UM, periodic=True)
                if given:
                    tactile_given, change = tactile, ""
                else:
                    change = _tactile_change(tactile, tactile_given)
                where = shading["solved_on"].replace("a periodic window of ", "")
                used = "given | " if given else _light_cells(shading, light)
                label = "given" if given else "estimated"
                ratios[label].append(e_win / e_whole)
                times.append(s_win / s_whole)
                rows.append(f"| {name} | {t1}; {t2} | {light[0]:g}, {light[1]:g} | {label} | {e_whole:.3f} | {s_whole:.2f} "
                            f"| {e_win:.3f} | {s_win:.2f} | {where} | {used} | {e_win / e_whole:.2f} | {s_win / s_whole:.2f} | {change} |")
    summary = (f"\nMedian error ratio window / whole image: light given {statistics.median(ratios['given']):.2f}, "
               f"light estimated {statistics.median(ratios['estimated']):.2f}; median time ratio {statistics.median(times):.2f} "
               f"({SIZE} x {SIZE} px of {PIXEL_UM:g} µm, whole pipeline per case).\n")
    return ("\n".join(rows) + "\n" + summary + "\n" + _coarse_rows(quick) + "\n" + _drift_rows(quick) + "\n"
            + _weave_direction_rows(quick) + ("" if quick else "\n" + _light_sensitivity_rows()))


def _drift_rows(quick: bool) -> str:
    """A weave that drifts across the photo: the tile averaged over the whole photo (baseline)
    against the central region where it repeats best (``photo.coherent_region``)."""
    from haptex_compile import photo

    t1, t2, light = (16.0, 0.0), (0.0, 16.0), (45.0, 200.0)
    truth = lattice_relief((SIZE, SIZE), t1, t2, amplitude_um=12.0)
    image = render_lambertian(truth, PIXEL_UM, Light(*light), 0.8)
    options = SourceOptions(light=light, roughness="none", relief_um=float(np.std(truth)))
    y, x = np.mgrid[SIZE // 2 - 100:SIZE // 2 + 100:2, SIZE // 2 - 100:SIZE // 2 + 100:2]
    rows = ["Drifting weave: the smooth-cell relief on a 16 px square lattice, stretched quadratically from the centre "
            "(the drift is the displacement at the edges); error over the central 200 px; explained = share of the "
            "photo's (region's) variance the averaged tile explains.", "",
            "| drift at the edges (px) | whole photo (baseline): explained | error | s | coherent region: region (px) "
            "| explained | error | s | error ratio region / whole |",
            "| --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    for drift in ((0.0, 8.0) if quick else (0.0, 4.0, 8.0, 16.0)):
        img = stretch_from_centre(image, drift)
        seen = stretch_from_centre(truth, drift)
        out = []
        for tolerance in (0.0, photo.REGION_TOLERANCE):  # 0: the whole photo is always kept
            with mock.patch.object(photo, "REGION_TOLERANCE", tolerance):
                t0 = time.perf_counter()
                result = photo_surface(img, PIXEL_UM, options, "bench", {})
                seconds = time.perf_counter() - t0
            err = normalised_height_error(heights_at_image_px(result, x.ravel(), y.ravel()), seen[y, x].ravel())
            lat = result.report["lattice"]
            region = lat.get("region_px")
            out.append((lat["tile_explained_variance"], err, seconds, f"{region[2]} x {region[3]}" if region else "whole"))
        (ew, errw, sw, _), (er, errr, sr, where) = out
        rows.append(f"| {drift:g} | {ew:.1%} | {errw:.3f} | {sw:.2f} | {where} | {er:.1%} | {errr:.3f} | {sr:.2f} | {errr / errw:.2f} |")
    return "\n".join(rows) + "\n"


OFFSETS_DEG = (0.0, 3.0, 8.0, 12.0, 20.0, 30.0)


def _weave_direction_rows(quick: bool) -> str:
    """Light given at angles off a weave direction: the height error, and whether the report
    warned (``shading.weave_visibility`` below ``WEAVE_VISIBILITY_MIN``)."""
    square, oblique = ((16.0, 0.0), (0.0, 16.0)), ((18.3, 3.1), (-4.2, 15.7))
    cases = [(square, "x axis", 0.0, slant) for slant in ((45.0,) if quick else (15.0, 30.0, 45.0, 60.0))]
    if not quick:
        cases += [(oblique, name, float(np.degrees(np.arctan2(t[1], t[0]))), slant)
                  for name, t, slant in (("t1", oblique[0], 45.0), ("t2", oblique[1], 30.0))]
    rows = ["Light near a weave direction (given): plain weaves and smooth cells lit at these angles off one of the"
            " lattice's directions; normalised height error over every other pixel, w = warned (`shading.weave_visibility`,"
            f" sin(slant) x sin(angle to t1, t2, t1 + t2 or t1 - t2) below {WEAVE_VISIBILITY_MIN:g}: those are also solved"
            " from 3-4 more starts at full resolution on a small periodic window of the lattice, polished on the"
            " surface's window, `shading_starts._start_from_cell`). The profiles across a direction"
            " the light runs along have no slope along it, and the shading sees them only at second order:", "",
            "| relief | lattice t1; t2 (px) | along | slant (°) | " + " | ".join(f"{o:g}°" for o in OFFSETS_DEG) + " |",
            "| --- | --- | --- | --- | " + " | ".join("---" for _ in OFFSETS_DEG) + " |"]
    errors: dict[bool, list[float]] = {True: [], False: []}  # by warned
    seconds: dict[bool, list[float]] = {True: [], False: []}
    for (t1, t2), name, tilt0, slant in cases:
        for relief, truth in _reliefs(t1, t2).items():
            if quick and relief != "plain weave":
                continue
            cells = []
            for off in OFFSETS_DEG:
                light = (slant, tilt0 + off)
                image = render_lambertian(truth, PIXEL_UM, Light(*light), 0.8)
                err, sec, shading = _solve(image, truth, light, whole=False)
                warned = shading["weave_visibility"] < WEAVE_VISIBILITY_MIN
                errors[warned].append(err)
                seconds[warned].append(sec)
                cells.append(f"{err:.3f}{' w' if warned else ''}")
            rows.append(f"| {relief} | {t1}; {t2} | {name} ({tilt0:.1f}°) | {slant:g} | " + " | ".join(cells) + " |")
    rows.append(f"\nWarned: {len(errors[True])} cases, errors {min(errors[True]):.3f}-{max(errors[True]):.3f}; not warned:"
                f" {len(errors[False])}, errors {min(errors[False]):.3f}-{max(errors[False]):.3f}. Median time of the whole"
                f" pipeline: warned {statistics.median(seconds[True]):.2f} s, not warned {statistics.median(seconds[False]):.2f} s"
                f" (slowest {max(seconds[True]):.2f} s and {max(seconds[False]):.2f} s).\n")
    return "\n".join(rows) + "\n"


def _light_sensitivity_rows() -> str:
    """Two of the photos with the light given a few degrees off the true one: the height error,
    the change of the tactile summary (``tables.mean_tactile`` of the surface) from the true
    light's, and the RMS misfit of the solver's heights to the image it solved (the surface's
    window), in 8-bit grey levels."""
    from haptex_compile import shading
    from haptex_compile.shading_variational import reflectance

    solved = {}
    solve = shading.shape_from_shading

    def spy(image, **kwargs):
        solved["image"], solved["result"] = image, solve(image, **kwargs)
        return solved["result"]

    offsets = [(0.0, 0.0), (-3.0, 0.0), (-1.5, 0.0), (1.5, 0.0), (3.0, 0.0), (0.0, -3.0), (0.0, -1.5), (0.0, 1.5), (0.0, 3.0)]
    rows = ["Light given off the true one (slant, tilt offsets): the height error; the change of the surface's mean a40 and"
            " a320 (`tables.mean_tactile`, 4 directions x 3 speeds) from the true light's surface; and the RMS misfit of the"
            " solver's heights to the shading it solved (the surface's window, valid pixels), in 8-bit grey levels: rounding"
            f" to 8 bits alone leaves {1 / np.sqrt(12):.2f}. Lights 1.5-3° off are explained to within about that rounding"
            " (and the solver's own residual at the true light is not zero), so an 8-bit photo hardly fixes the light to"
            " better than a few degrees; the heights are this sensitive to it (the first table's estimated lights):", "",
            "| relief | lattice t1; t2 (px) | true light slant, tilt (°) | " + " | ".join(f"{a:+g}, {b:+g}" for a, b in offsets) + " |",
            "| --- | --- | --- | " + " | ".join("---" for _ in offsets) + " |"]
    for (t1, t2, light), relief in ((CASES[1], "smooth cell"), (CASES[0], "plain weave")):
        truth = _reliefs(t1, t2)[relief]
        image = render_lambertian(truth, PIXEL_UM, Light(*light), 0.8)
        cells, reference = [], None
        for d_slant, d_tilt in offsets:
            with mock.patch.object(shading, "shape_from_shading", spy):
                result, _ = _pipeline(image, truth, (light[0] + d_slant, light[1] + d_tilt), whole=False)
            res, window = solved["result"], solved["image"]
            valid = shading.valid_pixels(window)
            model = res.albedo * reflectance(res.height / PIXEL_UM, res.light.vector)
            misfit = 255.0 * float(np.sqrt(np.mean((model - window)[valid] ** 2)))
            tactile = mean_tactile(result.surface.height_um, PIXEL_UM, periodic=True)
            reference = reference or tactile  # the true light's (the first offset)
            cells.append(f"{_height_error(result, truth):.3f}; {_tactile_change(tactile, reference)}; {misfit:.2f}")
        rows.append(f"| {relief} | {t1}; {t2} | {light[0]:g}, {light[1]:g} | " + " | ".join(cells) + " |")
    return "\n".join(rows) + "\n\nEach cell: height error; a40 / a320 change; misfit RMS (grey levels).\n"


# Coarse lattices (cells of 41-48 px, about 0.9 mm at 20 µm): none has a periodic window of at
# most 1024 px that strains its true basis by 0.3 % or less (tiles.periodic_window, as
# photo_surface asks), so the photo is solved whole unless the detected lattice finds one.
COARSE_CASES = [((-22.15, 41.0), (-37.03, -40.52), (40.0, 60.0)), ((12.79, 39.2), (-37.54, 27.54), (30.0, 200.0)),
                ((38.65, 29.17), (-18.53, 59.94), (55.0, 300.0)), ((43.53, 7.16), (-1.3, 51.86), (45.0, 120.0))]
COARSE_SLOPE = 0.2


def _at_slope(height_um: np.ndarray, slope: float) -> np.ndarray:
    """`height_um` scaled to an RMS slope of `slope` (the fixed amplitudes of ``_reliefs`` are
    gentle on coarse cells: RMS slope 0.05-0.09)."""
    return height_um * (slope / rms_slope(height_um, PIXEL_UM))


def _coarse_rows(quick: bool) -> str:
    """Coarse lattices, light given and estimated: the height error and what users feel (the
    surface's mean a40 / a320 against the true relief's), with where the light was estimated."""
    rows = ["Coarse lattices (cells of 41-48 px; relief scaled to an RMS slope of"
            f" {COARSE_SLOPE:g}): none has a periodic window of at most 1024 px for its true basis"
            " (`tiles.periodic_window`, strain 0.3 %), so the photo is solved whole (with free edges, then"
            " averaged over the lattice) unless the detected lattice finds one; the light is estimated on a"
            " small periodic window of the tile when one exists (at most 256 px, strain 2 %), else on the"
            " image. What users feel: the surface's mean a40 / a320 (`tables.mean_tactile`) against the"
            " true relief's:", "",
            "| relief | lattice t1; t2 (px) | light slant, tilt (°) | solved on | light given: error | s | a40 / a320"
            " | light estimated: error | s | estimated on | slant, tilt (°) | its error: slant, tilt axis (°)"
            " | a40 / a320 |",
            "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    tactile_errors: dict[str, list[float]] = {"given": [], "estimated": []}
    for t1, t2, light in (COARSE_CASES[:1] if quick else COARSE_CASES):
        for name, relief in _reliefs(t1, t2).items():
            truth = _at_slope(relief, COARSE_SLOPE)
            image = render_lambertian(truth, PIXEL_UM, Light(*light), 0.8)
            reference = mean_tactile(truth, PIXEL_UM)
            cells = []
            for given in (True, False):
                result, seconds = _pipeline(image, truth, light if given else None, whole=False)
                shading = result.report["shading"]
                windowed = shading["solved_on"].startswith("a periodic window")
                tactile = mean_tactile(result.surface.height_um, PIXEL_UM, periodic=windowed)
                tactile_errors["given" if given else "estimated"] += [abs(tactile[k] / reference[k] - 1) for k in ("a40", "a320")]
                error = f"{_height_error(result, truth):.3f} | {seconds:.2f}"
                if given:
                    where = shading["solved_on"].replace("a periodic window of ", "window ").replace("the whole image", "whole")
                    cells += [where, error]
                else:
                    on = shading.get("light_estimated_on", "the image").replace("a periodic window of ", "window ")
                    cells += [error, on, _light_cells(shading, light)]
                cells.append(_tactile_change(tactile, reference))
            rows.append(f"| {name} | {t1}; {t2} | {light[0]:g}, {light[1]:g} | " + " | ".join(cells) + " |")
    rows.append(f"\nWorst |a40| or |a320| change against the true relief: light given {max(tactile_errors['given']):.0%},"
                f" estimated {max(tactile_errors['estimated']):.0%}.\n")
    return "\n".join(rows) + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="two lattices only")
    print(run(parser.parse_args(argv).quick))
    return 0


if __name__ == "__main__":
    sys.exit(main())
