"""Light estimated on plain images (issue 7): random crops, the light estimated against given.

Plain images cut at random from the periodic renderings of 512 px tiles of the sphere cap,
the plain weave and random bumps (``bench_shading.random_crops``: 90-420 px sides of any
aspect, any offset, any tilt, slants 15-60°; seed 1; 20 per surface, 4 in quick mode), solved
with ``shape_from_shading(periodic=False)``: the normalised height error with the light given
and estimated, how many estimates leave the heights more than 5 points worse than the given
light and how many of those the estimate flagged UNRELIABLE (``Light.albedo_at_bound``), and
flags on estimates that were not worse. Baseline, same run: the light search without its edge
band on plain images (``shading_light.PLAIN_MISFIT_BAND = 0``: the misfit of each candidate light
includes the seam of its periodic solve). What the 5 points ask of an estimate: how many crops
come out more than 5 points worse with the given light turned by ``TILT_OFF_DEG`` in tilt (the
worse of the two ways), the estimates' median slant and tilt-axis errors, and how many of the
worse estimates the search's own misfit ranks above the true light, and how many of those the
true light fits better from its truth's basin (the search's per-light solve started from the true
heights and polished: the search's solves, not its misfit, missed the true light there).

    python bench/bench_light.py [--quick]
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from unittest import mock

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench_shading import PIXEL_UM, random_crops  # noqa: E402

from haptex_compile import shading, shading_light  # noqa: E402
from haptex_compile.shading import (  # noqa: E402
    Light,
    normalised_height_error,
    shape_from_shading,
    tilt_axis_difference_deg,
    valid_pixels,
)
from haptex_compile.shading_image import _censored_pixels  # noqa: E402
from haptex_compile.shading_variational import energy, solve_variational  # noqa: E402

CROPS_PER_SURFACE = 20
WORSE_BY = 0.05  # "worse": more than 5 points of height error above the given light's
TILT_OFF_DEG = 3.0  # the given light turned this far in tilt, each way: the target's demand
# The truth's basin on the search's final image: rounds of 20 Gauss-Newton steps of 100 CG
# iterations from the true heights, at the true light.
TRUTH_ROUNDS = 3


def _estimated(img, truth, band: float) -> tuple[float, bool, float, Light]:
    """Height error with the light estimated (edge band `band`), its flag, the seconds and the
    estimate."""
    with mock.patch.object(shading_light, "PLAIN_MISFIT_BAND", band):
        t0 = time.perf_counter()
        res = shape_from_shading(img, pixel_size_um=PIXEL_UM, periodic=False)
        seconds = time.perf_counter() - t0
    return normalised_height_error(res.height, truth), bool(res.light.albedo_at_bound), seconds, res.light


def _given_error(img, truth, light: Light) -> float:
    """Height error with `light` given."""
    return normalised_height_error(shape_from_shading(img, pixel_size_um=PIXEL_UM, light=light,
                                                      periodic=False).height, truth)


def _truth_basin_misfit(img, truth, light: Light) -> float:
    """The search's misfit (as ``shading.light_misfit`` takes it: the final image, its edge
    band left out) at the true `light`, its solve started from the true heights (`truth`, µm,
    block-averaged as the image) and polished (``TRUTH_ROUNDS``) rather than run from flat."""
    side = shading_light.FINAL_SIDE_PX
    m = shading_light._misfit_inputs(img, valid_pixels(img), _censored_pixels(img), side,
                                     shading_light._block_average, periodic=False)
    factor = shading_light._block_side(img.shape, side)  # pixels per reduced pixel
    z = shading_light._block_average(truth / PIXEL_UM, np.ones(truth.shape, bool), side)[0] / factor
    z, albedo = z - z.mean(), m.top
    for _ in range(TRUTH_ROUNDS):
        z, albedo = solve_variational(m.image, m.weight, light.vector, albedo, z0=z, max_levels=1, fine_gn=20,
                                      fine_cg=100, albedo_max=m.top / shading_light.ALIGN_COS,
                                      subgrid_damping=0.0, **m.censored)
    return float(energy(m.image, m.misfit_weight, light.vector, albedo, z, lam=0.0, **m.censored))


def run(quick: bool = False) -> str:
    variants = {"without the band": 0.0, "default": shading_light.PLAIN_MISFIT_BAND}
    stats: dict[str, dict] = {}
    for name, truth, img, light in random_crops(4 if quick else CROPS_PER_SURFACE):
        given = _given_error(img, truth, light)
        per_variant = {k: {"err": [], "worse": 0, "worse_flagged": 0, "false_flags": 0, "s": 0.0, "d_slant": [],
                           "d_tilt": []} for k in variants}
        s = stats.setdefault(name, {"given": [], "tilt_off": 0, "preferred": 0, "basin": 0, **per_variant})
        s["given"].append(given)
        turned = max(_given_error(img, truth, Light(light.slant_deg, light.tilt_deg + sign * TILT_OFF_DEG))
                     for sign in (-1, 1))
        s["tilt_off"] += turned > given + WORSE_BY
        for key, band in variants.items():
            err, flagged, seconds, est = _estimated(img, truth, band)
            v = s[key]
            v["err"].append(err)
            v["s"] += seconds
            v["d_slant"].append(abs(est.slant_deg - light.slant_deg))
            v["d_tilt"].append(tilt_axis_difference_deg(est.tilt_deg, light.tilt_deg))
            if err > given + WORSE_BY:
                v["worse"] += 1
                v["worse_flagged"] += flagged
                if key == "default":
                    # The search's own objective, at its estimate and at the true light.
                    misfits = [shading.light_misfit(img, lt, periodic=False)[0] for lt in (est, light)]
                    if misfits[0] < misfits[1]:
                        s["preferred"] += 1
                        s["basin"] += _truth_basin_misfit(img, truth, light) < misfits[0]
            else:
                v["false_flags"] += flagged

    lines = [
        "Light estimated on plain images: random crops of 512 px tiles' periodic renderings (90-420 px"
        " sides, any offset and tilt, slants 15-60°; `bench_shading.random_crops`, seed 1), solved with"
        " `periodic=False`. Mean normalised height error with the light given and estimated; worse ="
        f" estimates more than {WORSE_BY * 100:g} points worse than the given light (of them flagged"
        " UNRELIABLE, `Light.albedo_at_bound`); false flags = flagged estimates that were not worse;"
        " seconds of the estimated-light solves; the estimates' median errors, slant and tilt axis."
        " Baseline, same run: the light search without its edge"
        f" band (`shading_light.PLAIN_MISFIT_BAND = 0`; default {shading_light.PLAIN_MISFIT_BAND:g}). What {WORSE_BY * 100:g}"
        f" points ask of an estimate: crops that come out more than that worse with the given light turned"
        f" by {TILT_OFF_DEG:g}° in tilt (the worse way). Last column: of the default's worse estimates,"
        " those that the search's own misfit (`shading.light_misfit`) ranks above the true light (its"
        " misfit at the estimate below the true light's: a better search of that misfit would not"
        " find the true light), and of those, the ones where the true light fits better than the"
        " estimate from its truth's basin (the true light's solve on the search's final image"
        f" started from the true heights and polished, {TRUTH_ROUNDS} rounds of 20 Gauss-Newton steps of 100"
        " CG iterations: there the search's per-light solves from flat, not its misfit, lose the true"
        " light):",
        "",
        f"| surface | crops | light given: mean | given light turned {TILT_OFF_DEG:g}°: worse | " + " | ".join(
            f"{k}: mean | worse (flagged) | false flags | median error: slant, tilt (°) | s" for k in variants)
        + " | default's worse: misfit prefers the estimate | of them, truth's basin fits better |",
        "| --- | --- | --- | --- | " + " | ".join("--- | --- | --- | --- | ---" for _ in variants) + " | --- | --- |",
    ]
    totals = {k: [0, 0, 0] for k in variants}
    turned = preferred = basin = 0
    for name, s in stats.items():
        cells = []
        for key in variants:
            v = s[key]
            cells.append(f"{np.mean(v['err']):.3f} | {v['worse']} ({v['worse_flagged']}) | {v['false_flags']} |"
                         f" {np.median(v['d_slant']):.1f}, {np.median(v['d_tilt']):.1f} | {v['s']:.0f}")
            totals[key][0] += v["worse"]
            totals[key][1] += v["worse_flagged"]
            totals[key][2] += len(v["err"])
        turned += s["tilt_off"]
        preferred += s["preferred"]
        basin += s["basin"]
        lines.append(f"| {name} | {len(s['given'])} | {np.mean(s['given']):.3f} | {s['tilt_off']} | " + " | ".join(cells)
                     + f" | {s['preferred']} of {s['default']['worse']} | {s['basin']} of {s['preferred']} |")
    count = sum(len(s["given"]) for s in stats.values())
    lines += ["", "All surfaces: " + "; ".join(
        f"{key}, {t[0]} of {t[2]} estimates worse, {t[0] - t[1]} of them not flagged" for key, t in totals.items())
        + f"; the given light turned {TILT_OFF_DEG:g}° in tilt, {turned} of {count} worse; the default's"
        f" worse estimates that its misfit prefers to the true light, {preferred} of {totals['default'][0]};"
        f" of those, the true light fits better from its truth's basin in {basin}."]
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--quick", action="store_true")
    print(run(parser.parse_args().quick))
