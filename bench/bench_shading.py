"""Heights from shading against ground truth (issue 7).

Lambertian images (albedo 0.8) of the four known surfaces of ``haptex_compile.known_surfaces``
(a sphere cap, a plain weave, smooth random bumps with RMS slope 0.2 on 20 µm pixels, a
Brownian surface H = 0.7) under lights of slant 15-60°, plus overhead light (slant 0, where
Tsai-Shah's df/dZ vanishes) and grazing light (80°). Each image is solved by Tsai & Shah (the
paper's method, the baseline measured in the same run) and by the default solver, with the
light given and with the light estimated from the image. Score: normalised RMS height error
after the best affine fit ``h_true ~ a h + b`` (0 = perfect, 1 = nothing recovered). Time:
wall-clock seconds per megapixel of each solver (light given), at 45° and at 15°, and of the
default with the light along the tile's x axis (its extra starts) and 3° off it. The
surfaces are periodic, rendered and solved as tiles (``periodic=True``); a table of plain
images (``periodic=False``) follows, and one of random bumps over several seeds.

Tactile error: the tables' mean a40 and a320 (``haptex_compile.tables.mean_tactile``: 4
directions, 20/80/160 mm/s, footprint 0.25 mm) of the recovered heights, given the truth's RMS
relief and the sign of the best fit, against those of the true heights; also the mean channel
intensities behind them (Pacinian, non-Pacinian), which stay well conditioned when one colour
dominates (the sphere's a320 is 0.1 % of its a40: a 0.3 % change in its Pacinian intensity
moves its a320 by 30 %). For the sphere cap the bench also compares the solver's energy with
the true surface's, to tell a solver that stops early from shading that cannot decide; so it does
for plain images of random bumps at 60°, where seeds miss the target. A noise
table adds Gaussian noise (sigma 0.01 and 0.03) and compares the default with its albedo bound
at the raw 99.9th percentile (baseline, same run); a steep-light table (65-75°) compares it with
the same solver fitting the intensity of coarse pixels partly in shadow (baseline, same run).

    python bench/bench_shading.py [--quick]
"""
from __future__ import annotations

import argparse
import contextlib
import functools
import json
import os
import subprocess
import sys
import time
from unittest import mock

import numpy as np

from haptex_compile import known_surfaces as ts
from haptex_compile import malloc_policy, shading, shading_light, shading_variational
from haptex_compile.colours import TwoColourModel
from haptex_compile.forked_map import worker_count
from haptex_compile.sources import remove_plane
from haptex_compile.synth_images import lattice_relief
from haptex_compile.tables import mean_tactile
from haptex_compile.shading import (
    DEFAULT_SOLVER,
    Light,
    estimate_light,
    light_misfit,
    normalised_height_error,
    render_lambertian,
    shape_from_shading,
    _solve_domain,
    tilt_axis_difference_deg,
    tsai_shah,
    valid_pixels,
)
from haptex_compile.shading_image import _censored_pixels, affine_height_residual
from haptex_compile.shading_light import FINAL_SIDE_PX, _moment_albedo
from haptex_compile.shading_starts import _tile_aligned_tilt
from haptex_compile.shading_variational import energy, reflectance, solve_variational

PIXEL_UM = 20.0
ALBEDO = 0.8
LATTICES = [((16, 0), (0, 16)), ((16, 0), (4, 16)), ((32, 0), (8, 32))]
LIGHTS = [(15.0, 30.0), (30.0, 120.0), (45.0, 200.0), (60.0, 300.0), (0.0, 0.0), (80.0, 45.0)]


def _surfaces(n: int) -> dict[str, np.ndarray]:
    shape = (n, n)
    return {
        "sphere cap (rim 45°, rounded)": ts.sphere_cap(shape, PIXEL_UM),
        "woven (plain weave)": ts.woven_like(shape, PIXEL_UM),
        "random bumps (slope 0.2)": ts.random_bumps(shape, PIXEL_UM, seed=1),
        "Brownian H=0.7": ts.brownian_surface(shape, PIXEL_UM, hurst=0.7, seed=2),
    }


def _flag(light: Light) -> str:
    """A dagger for an estimated light flagged unreliable (albedo at the search's bound)."""
    return " †" if light.albedo_at_bound else ""


def _near_frontal_rows(n: int) -> list[str]:
    """Estimated lights under near-frontal light (0-10°), where the misfit cannot fix the slant."""
    rows = []
    for name, truth in _surfaces(n).items():
        cells = []
        for slant in (0.0, 5.0, 10.0):
            img = render_lambertian(truth, PIXEL_UM, Light(slant, 30.0), ALBEDO, periodic=True)
            est, _ = estimate_light(img)
            cells.append(f"{est.slant_deg:.0f}±{est.slant_sd_deg:.0f}{_flag(est)}")
        rows.append(f"| {name} | " + " | ".join(cells) + " |")
    return rows


def _same_rms(height: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """Recovered height with the truth's RMS and the sign of the best affine fit (µm)."""
    h = height - height.mean()
    t = truth - truth.mean()
    rms_h = float(np.sqrt(np.mean(h * h)))
    if rms_h == 0:
        return h
    sign = 1.0 if float(np.sum(h * t)) >= 0 else -1.0
    return sign * h * (float(np.sqrt(np.mean(t * t))) / rms_h)


def cases(quick: bool = False) -> list[dict]:
    """All bench cases with their heights, for the tactile-error column.

    Returns
    -------
    list of dict
        Keys: ``surface``, ``slant_deg``, ``tilt_deg``, ``pixel_size_um``, ``periodic``,
        ``height_true_um``, ``image`` (the rendered image), and for each method (``"tsai-shah"``, ``"default"``,
        ``"default, light estimated"`` (only for slants 15-60°)) an entry in
        ``results`` (and ``"accurate"``, light given, slants 15-60°): a dict with ``height_um``
        (recovered, scaled to the truth's RMS and sign), ``error`` (normalised height error),
        ``seconds`` (wall clock) and, for the estimated light, ``light``.
    """
    n = 128 if quick else 256
    out = []
    for name, truth in _surfaces(n).items():
        for slant, tilt in LIGHTS[:5] if quick else LIGHTS:
            light = Light(slant, tilt)
            img = render_lambertian(truth, PIXEL_UM, light, ALBEDO, periodic=True)
            results = {}
            t0 = time.perf_counter()
            h_ts = tsai_shah(img, light, pixel_size_um=PIXEL_UM)
            results["tsai-shah"] = dict(height_um=h_ts, seconds=time.perf_counter() - t0)
            t0 = time.perf_counter()
            r = shape_from_shading(img, pixel_size_um=PIXEL_UM, light=light, periodic=True)
            results["default"] = dict(height_um=r.height, seconds=time.perf_counter() - t0,
                                      height_raw_um=r.height, albedo=r.albedo)
            if 15 <= slant <= 60:  # the target lights only (the estimate costs a few seconds)
                t0 = time.perf_counter()
                r_acc = shape_from_shading(img, pixel_size_um=PIXEL_UM, light=light, method="accurate",
                                           periodic=True)
                results["accurate"] = dict(height_um=r_acc.height, seconds=time.perf_counter() - t0,
                                           height_raw_um=r_acc.height, albedo=r_acc.albedo)
                t0 = time.perf_counter()
                r_est = shape_from_shading(img, pixel_size_um=PIXEL_UM, periodic=True)
                results["default, light estimated"] = dict(
                    height_um=r_est.height, seconds=time.perf_counter() - t0, light=r_est.light
                )
            for res in results.values():
                res["error"] = normalised_height_error(res["height_um"], truth)
                res["rms_ratio"] = float(np.std(res["height_um"]) / np.std(truth))
                res["height_um"] = _same_rms(res["height_um"], truth)
            out.append(
                dict(
                    surface=name,
                    slant_deg=slant,
                    tilt_deg=tilt,
                    pixel_size_um=PIXEL_UM,
                    periodic=True,
                    height_true_um=truth,
                    image=img,
                    results=results,
                )
            )
    return out


NOISE_SIGMAS = (0.01, 0.03)


def _default_with(patch: dict, img: np.ndarray, light: Light) -> np.ndarray:
    """Heights (µm) of the default method on a tile with some of ``DEFAULT_SOLVER``'s settings
    changed (a baseline in the same run)."""
    from unittest import mock

    with mock.patch.dict(DEFAULT_SOLVER, patch):
        return shape_from_shading(img, pixel_size_um=PIXEL_UM, light=light, periodic=True).height


def _shadowed_fraction(kwargs: dict) -> float:
    """Share of the tile in attached shadow, from the solver's keyword arguments."""
    dark = kwargs.get("dark")
    return 0.0 if dark is None else float(np.mean(dark > 0))


def _noise_rows(n: int, sigmas=NOISE_SIGMAS) -> list[str]:
    """Table rows: the default solver on noisy images (Gaussian, fixed seed, clipped to
    [0, 1]; light given, slants 15-60°), against the same solver with the albedo's bound at
    the raw 99.9th percentile (baseline: no allowance for the noise, which raises it)."""
    from haptex_compile.shading_variational import _noise_sigma

    rows = []
    for sigma in sigmas:
        for name, truth in _surfaces(n).items():
            truth_tactile = mean_tactile(truth, PIXEL_UM, periodic=True)
            worst = {"baseline": [0.0, 0.0, 0.0], "default": [0.0, 0.0, 0.0]}
            estimates = []
            for k, (slant, tilt) in enumerate(LIGHTS[:4]):
                light = Light(slant, tilt)
                clean = render_lambertian(truth, PIXEL_UM, light, ALBEDO, periodic=True)
                noise = np.random.default_rng(100 + k).normal(0.0, sigma, clean.shape)
                img = np.clip(clean + noise, 0.0, 1.0)
                estimates.append(_noise_sigma(img.astype(np.float32), np.ones(img.shape, np.float32)))
                for key, patch in (("baseline", {"bound_noise_sigmas": 0.0}), ("default", {})):
                    height = _default_with(patch, img, light)
                    tact = _tactile_errors(truth_tactile, _same_rms(height, truth), PIXEL_UM)
                    w = worst[key]
                    w[0] = max(w[0], normalised_height_error(height, truth))
                    w[1] = max(w[1], abs(tact["a40"]))
                    w[2] = max(w[2], abs(tact["a320"]))
            b, d = worst["baseline"], worst["default"]
            rows.append(f"| {sigma:g} | {name} | {np.mean(estimates):.4f} | {b[0]:.3f} | {b[1]:.0%} / {b[2]:.0%}"
                        f" | {d[0]:.3f} | {d[1]:.0%} / {d[2]:.0%} | {d[0] / b[0]:.2f} |")
    return rows


STEEP_LIGHTS = [(65.0, 160.0), (70.0, 250.0), (75.0, 20.0)]


def _steep_rows(n: int, lights=STEEP_LIGHTS) -> list[str]:
    """Table rows: steep lights (attached shadows on part of the tile), light given, the
    default solver against the same solver fitting the intensity of coarse pixels partly in
    shadow (baseline: ``censored_data=True``, same run)."""
    rows = []
    for name, truth in _surfaces(n).items():
        cells = []
        for slant, tilt in lights:
            light = Light(slant, tilt)
            img = render_lambertian(truth, PIXEL_UM, light, ALBEDO, periodic=True)
            errs = [normalised_height_error(_default_with(patch, img, light), truth)
                    for patch in ({"censored_data": True}, {})]
            shadowed = float(np.mean(_censored_pixels(img)[0]))
            cells.append(f"{shadowed:.1%} | {errs[0]:.3f} | {errs[1]:.3f}")
        rows.append(f"| {name} | " + " | ".join(cells) + " |")
    return rows


ALIGNED_TILTS = (0.0, 3.0, 45.0, 48.0)


def _aligned_rows(n: int, slants=(30.0, 45.0, 60.0), tilts=ALIGNED_TILTS) -> list[str]:
    """Normalised height errors (light given) with the light along the tile's x axis and
    diagonal and 3° off them; w = the result carries the aligned-light warning."""
    rows = []
    for name, truth in _surfaces(n).items():
        cells = []
        for slant in slants:
            for tilt in tilts:
                light = Light(slant, tilt)
                img = render_lambertian(truth, PIXEL_UM, light, ALBEDO, periodic=True)
                res = shape_from_shading(img, pixel_size_um=PIXEL_UM, light=light, periodic=True)
                warned = _tile_aligned_tilt(tilt, img.shape) is not None
                cells.append(f"{normalised_height_error(res.height, truth):.3f}{' w' if warned else ''}")
        rows.append(f"| {name} | " + " | ".join(cells) + " |")
    return rows


def _sharp_rim_rows(n: int) -> list[tuple[float, float, float, float]]:
    """The sphere cap with a sharp rim (a kink), light given: (slant, tilt, Tsai-Shah, default).

    Reported apart: the kink's sampled shading is a step no pixel grid resolves, and it is
    what breaks the solver at low slants (see ``known_surfaces.sphere_cap``).
    """
    truth = ts.sphere_cap((n, n), PIXEL_UM, rim_round_um=0.0)
    out = []
    for slant, tilt in LIGHTS[:4]:
        light = Light(slant, tilt)
        img = render_lambertian(truth, PIXEL_UM, light, ALBEDO, periodic=True)
        r = shape_from_shading(img, pixel_size_um=PIXEL_UM, light=light, periodic=True)
        e_ts = normalised_height_error(tsai_shah(img, light, pixel_size_um=PIXEL_UM), truth)
        out.append((slant, tilt, e_ts, normalised_height_error(r.height, truth)))
    return out


def _plain_lights(quick: bool) -> list[tuple[float, float]]:
    """The lights of the plain-image tables (slants 15-60°; two in quick mode)."""
    return LIGHTS[:2] if quick else LIGHTS[:4]


def _plain_crop(n: int) -> tuple[slice, slice]:
    """The crop of an n px tile's periodic rendering that the plain-image tables solve: a
    surface that is not periodic on the image, as a real one."""
    return slice(13, 13 + n - n // 8), slice(19, 19 + n - n // 8)


def _signed_tactile_cell(got: dict, want: dict) -> str:
    """Signed relative errors of mean a40 / a320 and, in brackets, of the channel intensities
    I_p / I_np behind them (:func:`mean_tactile` dicts): a320 is small beside a40 on smooth
    reliefs, where its relative error says little of what is felt."""
    e = {k: got[k] / want[k] - 1 for k in ("a40", "a320", "i_p", "i_np")}
    return f"{e['a40']:+.0%} / {e['a320']:+.0%} ({e['i_p']:+.1%} / {e['i_np']:+.1%})"


def _nonperiodic_rows(n: int, quick: bool) -> list[str]:
    """The four surfaces rendered without wrap-around (one-sided differences at the edges)
    and solved as plain images, light given: Tsai-Shah's error, the default's error and
    tactile error (mean a40 / a320 of plain surfaces), both also levelled (``sources.remove_plane``,
    as height maps are: on a plain image a uniform slope hardly changes the shading, and the
    photo pipeline averages a plain solve over the lattice, which removes any plane; the
    Brownian tile has half its variance in its plane over 256 px, 63 % over the crop),
    whether the default kept its flat-on-average prior (the same heights as with the prior forced), and the default's
    error on a crop of the periodic rendering (the bench's surfaces are periodic tiles: a
    solver that wrapped the image would do well on them and not on a real one), with the
    light given and estimated; the baseline is the default without the spectral prior."""
    out = []
    for name, truth in _surfaces(n).items():
        want = mean_tactile(truth, PIXEL_UM)
        want_levelled = mean_tactile(remove_plane(truth), PIXEL_UM)
        for slant, tilt in _plain_lights(quick):
            light = Light(slant, tilt)
            img = render_lambertian(truth, PIXEL_UM, light, ALBEDO, periodic=False)
            r = shape_from_shading(img, pixel_size_um=PIXEL_UM, light=light, periodic=False)
            with mock.patch.object(shading, "LOWFREQ_REJECT_RATIO", np.inf):
                forced = shape_from_shading(img, pixel_size_um=PIXEL_UM, light=light, periodic=False)
            got = mean_tactile(_same_rms(r.height, truth), PIXEL_UM)
            got_levelled = mean_tactile(_same_rms(remove_plane(r.height), remove_plane(truth)), PIXEL_UM)
            e_ts = normalised_height_error(tsai_shah(img, light, pixel_size_um=PIXEL_UM), truth)
            e_forced = normalised_height_error(forced.height, truth)
            kept = "kept" if np.array_equal(r.height, forced.height) else f"dropped (with it: {e_forced:.3f})"
            crop = _plain_crop(n)
            cropped = render_lambertian(truth, PIXEL_UM, light, ALBEDO, periodic=True)[crop]
            on_crop = shape_from_shading(cropped, pixel_size_um=PIXEL_UM, light=light, periodic=False)
            with mock.patch.object(shading, "SPECTRAL_PRIOR_WEIGHT", 0.0):
                base = shape_from_shading(img, pixel_size_um=PIXEL_UM, light=light, periodic=False)
                base_crop = shape_from_shading(cropped, pixel_size_um=PIXEL_UM, light=light, periodic=False)
            found = shape_from_shading(cropped, pixel_size_um=PIXEL_UM, periodic=False)
            out.append(
                f"| {name} | {slant:g}, {tilt:g} | {e_ts:.3f} | {normalised_height_error(base.height, truth):.3f}"
                f" | {normalised_height_error(r.height, truth):.3f}"
                f" | {normalised_height_error(remove_plane(r.height), remove_plane(truth)):.3f}"
                f" | {_signed_tactile_cell(got, want)} | {_signed_tactile_cell(got_levelled, want_levelled)} | {kept}"
                f" | {normalised_height_error(base_crop.height, truth[crop]):.3f}"
                f" | {normalised_height_error(on_crop.height, truth[crop]):.3f}"
                f" ({normalised_height_error(remove_plane(on_crop.height), remove_plane(truth[crop])):.3f})"
                f" | {normalised_height_error(found.height, truth[crop]):.3f} ({found.light.slant_deg:.1f}, {found.light.tilt_deg:.1f}) |"
            )
    return out


CROP_TILE_PX = 512
CROPS_PER_SURFACE = 30


# The baselines of the random crops: the default without the plane term of the flat-on-average
# prior, with the prior as it was before its albedo test (weight 1, dropped above an energy
# ratio of 4 alone), and with the narrow margin of level ground's images on every image.
CROP_BASELINES = {"no plane": {"LOWFREQ_PLANE_WEIGHT": 0.0},
                  "previous prior": {"LOWFREQ_WEIGHT": 1.0, "LOWFREQ_REJECT_RATIO": 4.0,
                                     "LOWFREQ_REJECT_ALBEDO": np.inf},
                  "narrow margin": {"TEXTURE_MARGIN": shading.PLAIN_MARGIN}}


def random_crops(count: int):
    """Plain images cut at random from three surfaces' periodic renderings (CROP_TILE_PX
    tiles; 90-420 px sides of any aspect, any offset, any tilt, slants 15-60°; seed 1;
    sphere caps' crops near the cap, whose footprint is 410 px across), `count` per surface:
    yields (surface name, true heights of the crop (µm), image, light)."""
    n = CROP_TILE_PX
    rng = np.random.default_rng(1)
    surfaces = {"sphere cap (rim 45°, rounded)": ts.sphere_cap((n, n), PIXEL_UM),
                "woven (plain weave)": ts.woven_like((n, n), PIXEL_UM),
                "random bumps (slope 0.2)": ts.random_bumps((n, n), PIXEL_UM, seed=7)}
    for name, truth in surfaces.items():
        for _ in range(count):
            rows, cols = rng.integers(90, 420, 2)
            if name.startswith("sphere"):
                oy, ox = (n - rows) // 2 + rng.integers(-20, 20), (n - cols) // 2 + rng.integers(-20, 20)
            else:
                oy, ox = rng.integers(0, n - rows), rng.integers(0, n - cols)
            light = Light(float(rng.choice([15.0, 30.0, 45.0, 60.0])), float(rng.uniform(0.0, 360.0)))
            crop = (slice(oy, oy + rows), slice(ox, ox + cols))
            yield name, truth[crop], render_lambertian(truth, PIXEL_UM, light, ALBEDO, periodic=True)[crop], light


def _random_crop_rows(quick: bool) -> list[str]:
    """:func:`random_crops`: the default's normalised height error against the baselines of
    ``CROP_BASELINES``, light given: mean, worst and the count above 0.4."""
    errors: dict[str, dict[str, list[float]]] = {}
    for name, truth, img, light in random_crops(6 if quick else CROPS_PER_SURFACE):
        by_key = errors.setdefault(name, {key: [] for key in (*CROP_BASELINES, "default")})
        for key, errs in by_key.items():
            patch = CROP_BASELINES.get(key)
            with mock.patch.multiple(shading, **patch) if patch else contextlib.nullcontext():
                res = shape_from_shading(img, pixel_size_um=PIXEL_UM, light=light, periodic=False)
            errs.append(normalised_height_error(res.height, truth))
    out = []
    for name, by_key in errors.items():
        cells = [f"{np.mean(e):.3f} | {np.max(e):.3f} | {int(np.sum(np.array(e) > 0.4))}" for e in by_key.values()]
        out.append(f"| {name} | {len(by_key['default'])} | " + " | ".join(cells) + " |")
    return out


MARGINS = (0.05, 0.08, 0.15, 0.2, 0.3)


def _margin_rows(n: int, quick: bool) -> list[str]:
    """The plain weave's plain image and its crop (as in :func:`_nonperiodic_rows`) solved on
    periodic domains of other sizes (``shading.TEXTURE_MARGIN`` patched: the weave is a
    texture; the default's first):
    the domain's sides and the normalised height errors, light given."""
    truth = ts.woven_like((n, n), PIXEL_UM)
    crop = _plain_crop(n)
    lights = _plain_lights(quick)
    images = [(render_lambertian(truth, PIXEL_UM, Light(*sl), ALBEDO, periodic=False),
               render_lambertian(truth, PIXEL_UM, Light(*sl), ALBEDO, periodic=True)[crop]) for sl in lights]
    out = []
    for margin in sorted(MARGINS, key=lambda m: m != shading.TEXTURE_MARGIN):
        with mock.patch.object(shading, "TEXTURE_MARGIN", margin):
            sides = [shading._solve_domain(im, np.ones(im.shape, bool), _censored_pixels(im), False)[0].shape[0]
                     for im in images[0]]
            cells = []
            for (slant, tilt), (img, cropped) in zip(lights, images):
                light = Light(slant, tilt)
                full = shape_from_shading(img, pixel_size_um=PIXEL_UM, light=light, periodic=False)
                part = shape_from_shading(cropped, pixel_size_um=PIXEL_UM, light=light, periodic=False)
                cells.append(f"{normalised_height_error(full.height, truth):.3f}"
                             f" / {normalised_height_error(part.height, truth[crop]):.3f}")
        out.append(f"| {margin:g} | {sides[0]} / {sides[1]} | " + " | ".join(cells) + " |")
    return out


# Random bumps from this many seeds (the other tables use seed 1): at low slants the solvers
# can end in a local minimum of the energy, and whether they do depends on the surface.
SEED_COUNT = 10
# The issue's target for random bumps (normalised height error, light given).
BUMPS_TARGET = 0.3


@functools.lru_cache(maxsize=None)
def _plain_bumps(n: int, seed: int, slant: float, tilt: float) -> tuple[np.ndarray, np.ndarray]:
    """Random bumps of `seed` (`n` px) and the default's heights of them as a plain image lit
    at (`slant`, `tilt`), light given: (truth, heights), in µm. Cached: the seeds table and
    the table of line means solve the same images."""
    truth = ts.random_bumps((n, n), PIXEL_UM, seed=seed)
    light = Light(slant, tilt)
    img = render_lambertian(truth, PIXEL_UM, light, ALBEDO, periodic=False)
    return truth, shape_from_shading(img, pixel_size_um=PIXEL_UM, light=light, periodic=False).height


def _seed_rows(n: int, quick: bool) -> list[str]:
    """Table rows: random bumps of seeds 0 .. SEED_COUNT - 1 (3 when quick), light given, per
    light of ``LIGHTS[:4]``: mean and worst error, and how many seeds miss ``BUMPS_TARGET``,
    for the default and accurate solvers on tiles and the default on plain images."""
    seeds = range(3 if quick else SEED_COUNT)
    truths = [ts.random_bumps((n, n), PIXEL_UM, seed=seed) for seed in seeds]
    out = []
    for slant, tilt in LIGHTS[:4]:
        light = Light(slant, tilt)
        tiles = [render_lambertian(truth, PIXEL_UM, light, ALBEDO, periodic=True) for truth in truths]
        cells = []
        for method in ("default", "accurate"):
            errs = np.array([
                normalised_height_error(shape_from_shading(
                    img, pixel_size_um=PIXEL_UM, light=light, periodic=True, method=method).height, truth)
                for img, truth in zip(tiles, truths)])
            cells.append(f"{errs.mean():.3f} / {errs.max():.3f} / {int(np.sum(errs > BUMPS_TARGET))}")
        errs = np.array([normalised_height_error(height, truth)
                         for truth, height in (_plain_bumps(n, seed, slant, tilt) for seed in seeds)])
        cells.append(f"{errs.mean():.3f} / {errs.max():.3f} / {int(np.sum(errs > BUMPS_TARGET))}")
        out.append(f"| {slant:g}, {tilt:g} | " + " | ".join(cells) + " |")
    return out


# Lights of the timing table: the first is the one of the ratios to Tsai-Shah.
TIMING_LIGHTS = ((45.0, 200.0), (15.0, 30.0))


# The timing table's rows: label, and how each solves (image periodic, keyword arguments).
TIMED = {
    "Tsai-Shah (baseline)": (True, None),
    "default solver, light given": (True, {}),
    "accurate solver (`--sfs accurate`), light given": (True, {"method": "accurate"}),
    "default solver, plain image (`periodic=False`), light given": (False, {}),
}


def _timing(n: int, light: Light, repeats: int = 2) -> dict[str, float]:
    """Seconds per megapixel (best of `repeats`) of each row of ``TIMED`` (Tsai-Shah: 50
    iterations), for random bumps (seed 5) lit by `light`."""
    truth = ts.random_bumps((n, n), PIXEL_UM, seed=5)
    images = {periodic: render_lambertian(truth, PIXEL_UM, light, ALBEDO, periodic=periodic)
              for periodic in (True, False)}
    best = dict.fromkeys(TIMED, np.inf)
    for _ in range(repeats):
        # Slowest first, as before (plain image, accurate, default, Tsai-Shah).
        for label in reversed(TIMED):
            periodic, kwargs = TIMED[label]
            t0 = time.perf_counter()
            if kwargs is None:
                tsai_shah(images[periodic], light, pixel_size_um=PIXEL_UM)
            else:
                shape_from_shading(images[periodic], pixel_size_um=PIXEL_UM, light=light,
                                   periodic=periodic, **kwargs)
            best[label] = min(best[label], time.perf_counter() - t0)
    return {label: t / (n * n / 1e6) for label, t in best.items()}


LARGER_SIDES = (512, 768)
LARGER_TARGET = 0.05


def _estimated_against_baseline(sides, lights, attr: str, baseline, bound_column: bool = False) -> list[str]:
    """Rows of a table of the light estimated on the four surfaces at `sides` and `lights`
    (see :func:`_estimated_rows`; each row starts with the side and the surface)."""
    return _estimated_rows([(f"{side} | {name}", truth, light) for side in sides
                            for name, truth in _surfaces(side).items() for light in lights],
                           attr, baseline, bound_column)


def _estimated_rows(cases, attr: str, baseline, bound_column: bool = False) -> list[str]:
    """Rows of a table of the light estimated on `cases` ((label cells, true heights, (slant,
    tilt)) each, periodic tiles): the height error with the light given, then with the light
    estimated under the baseline (``shading_light.<attr> = baseline``, same run) and the
    default (the estimate, † = flagged, and the whole solve's seconds); with `bound_column`,
    the search's albedo bound I_top / ``ALIGN_COS`` first. Then the count of estimates more
    than ``LARGER_TARGET`` worse than the given light, and the summed times."""
    worse, seconds, rows = {"baseline": 0, "default": 0}, {"baseline": 0.0, "default": 0.0}, []
    for label, truth, (slant, tilt) in cases:
        img = render_lambertian(truth, PIXEL_UM, Light(slant, tilt), ALBEDO, periodic=True)
        given = shape_from_shading(img, pixel_size_um=PIXEL_UM, light=Light(slant, tilt), periodic=True)
        e_given = normalised_height_error(given.height, truth)
        cells = []
        if bound_column:
            cells.append(f"{float(np.percentile(img, 99.9)) / shading_light.ALIGN_COS:.3f}")
        cells.append(f"{e_given:.3f}")
        for key, value in (("baseline", baseline), ("default", getattr(shading_light, attr))):
            with mock.patch.object(shading_light, attr, value):
                t0 = time.perf_counter()
                found = shape_from_shading(img, pixel_size_um=PIXEL_UM, periodic=True)
                seconds[key] += (dt := time.perf_counter() - t0)
            light, e = found.light, normalised_height_error(found.height, truth)
            worse[key] += e > e_given + LARGER_TARGET
            cells.append(f"{e:.3f} | {light.slant_deg:.1f}, {light.tilt_deg:.1f}{_flag(light)} | {dt:.1f}")
        rows.append(f"| {label} | {slant:g}, {tilt:g} | " + " | ".join(cells) + " |")
    count = len(cases)
    return rows + ["", f"Estimates more than {LARGER_TARGET:g} worse than the given light: baseline"
                   f" {worse['baseline']} of {count}, default {worse['default']} of {count}; the solves' summed"
                   f" seconds: baseline {seconds['baseline']:.0f}, default {seconds['default']:.0f}"
                   f" ({seconds['default'] / seconds['baseline']:.2f} x)."]


_ESTIMATE_HEADER = ("| side (px) | surface | slant, tilt (°) | {}light given | baseline: error | light | s"
                    " | default: error | light | s |")


def _larger_tile_rows(quick: bool) -> list[str]:
    """The light estimated on tiles larger than the search's final image (``FINAL_SIDE_PX``):
    the four surfaces at ``LARGER_SIDES`` (quick: 384 px, two lights), slants 15-60°, with and
    (baseline, same run) without the full-resolution stage (``FULL_SIDE_PX``); see
    :func:`_estimated_against_baseline`."""
    sides, lights = ((384,), LIGHTS[:2]) if quick else (LARGER_SIDES, LIGHTS[:4])
    return ["", f"Light estimated on tiles larger than the search's final image ({FINAL_SIDE_PX} px; it is"
            " block-averaged to that size, which darkens rough shading and blurs a weave's crossings):"
            " height error with the light given, then with the light estimated, the estimate (slant,"
            " tilt; † = flagged unreliable) and the seconds of the whole solve (search and heights)."
            " Baseline, same run: without the"
            " final stage's second run on the image itself (`shading_light.FULL_SIDE_PX` ="
            f" `FINAL_SIDE_PX`); the default runs it (up to {shading_light.FULL_SIDE_PX} px) and keeps"
            " the light that fits the full image better:", "",
            _ESTIMATE_HEADER.format(""), "| --- " * 10 + "|",
            *_estimated_against_baseline(sides, lights, "FULL_SIDE_PX", FINAL_SIDE_PX)]


# Cases of the table of flagged estimates looked at again below the albedo's bound: the
# lattice reliefs at 256 px (as the photo-like cells' table), and the 512 px plain weave lit at
# 30°, 120°, whose estimate stopped on the plateau at 50°.
WELL_WEAVE = (512, (30.0, 120.0))


def _well_rows(quick: bool) -> list[str]:
    """The light estimated with and (baseline, same run) without the look below a flagged
    estimate's albedo bound (``shading_light.WELL_CANDIDATES = 0``; see
    :func:`_estimated_rows`) on the lattice reliefs and the 512 px plain weave."""
    cases = []
    for t1, t2 in LATTICES[:1] if quick else LATTICES:
        h = lattice_relief((256, 256), t1, t2, amplitude_um=12.0 * t1[0] / 16.0)
        cases += [(f"lattice {t1}; {t2}, 256 px", h, light) for light in LIGHTS[:4]]
    if not quick:
        side, light = WELL_WEAVE
        cases.append((f"plain weave, {side} px", ts.woven_like((side, side), PIXEL_UM), light))
    return ["", "Flagged estimates looked at again below the albedo's bound"
            " (`shading_light._well_below_the_bound`): where the final stage's light has its fitted"
            " albedo at the search's bound (the plateau of steep lights, where the misfit does not fix"
            " the slant), the reduced image's misfit is scanned below it (slants"
            f" {shading_light.WELL_MIN_SLANT_DEG:g}° up to the estimate's in {shading_light.WELL_SLANT_STEP_DEG:g}°"
            f" steps, tilts ±{shading_light.WELL_TILT_SPAN_DEG:g}° in {shading_light.WELL_TILT_STEP_DEG:g}° steps),"
            f" its {shading_light.WELL_CANDIDATES} lowest local minima with the albedo free followed on the"
            " final image, and the best kept if it fits better than the estimate. Baseline, same run:"
            " without that look (`WELL_CANDIDATES = 0`). Height error with the light given, then"
            " estimated (slant, tilt; † = flagged unreliable) and the seconds of the whole solve:", "",
            "| case | slant, tilt (°) | light given | baseline: error | light | s | default: error | light | s |",
            "| --- " * 9 + "|", *_estimated_rows(cases, "WELL_CANDIDATES", 0)]


STEEP_SIDES = (256,)
STEEP_BOUND_LIGHTS = ((55.0, 160.0), (60.0, 300.0))


def _steep_bound_rows(quick: bool) -> list[str]:
    """Steep light with the search's albedo bound below the true albedo: the four surfaces at
    ``STEEP_SIDES`` (quick: 128 px, one light) lit at ``STEEP_BOUND_LIGHTS``, with (default)
    and without (baseline, same run: ``shading_light.STEEP_ALIGN_COS = None``) the second look
    under a looser bound; see :func:`_estimated_against_baseline`."""
    sides, lights = ((128,), STEEP_BOUND_LIGHTS[1:]) if quick else (STEEP_SIDES, STEEP_BOUND_LIGHTS)
    return ["", "Steep light and the light search's albedo bound (I_top / cos 35°, `shading_light.ALIGN_COS`):"
            " under a steep light a gentle relief may have no normal within 35° of it, and the bound then lies"
            f" below the true albedo ({ALBEDO:g}), so the true light cannot fit. A flagged estimate steeper than"
            f" {shading_light.PLATEAU_MAX_DEG:g}° is searched again with the bound at I_top / cos 45°"
            " (`shading_light.STEEP_ALIGN_COS`) and that light kept if its albedo is free there (still flagged)."
            " Baseline, same run: without that second look (`STEEP_ALIGN_COS = None`). The bound, the height"
            " error with the light given, then estimated (slant, tilt; † = flagged unreliable) and the seconds"
            " of the whole solve:", "",
            _ESTIMATE_HEADER.format("bound | "), "| --- " * 11 + "|",
            *_estimated_against_baseline(sides, lights, "STEEP_ALIGN_COS", None, bound_column=True)]


def _light_search_rows(n: int, quick: bool) -> list[str]:
    """The light search's seconds on the bench's tiles, its candidate lights solved in worker
    processes (the default) and in one process (``shading_light.SEARCH_PROCESSES = 1``, the
    baseline), same run, and whether the two estimates are the same."""
    lights = TIMING_LIGHTS[:1] if quick else TIMING_LIGHTS
    rows = ["", f"Light search (`estimate_light`) on the {n} px tiles, light estimated at each timing"
            " light: seconds with the candidate lights of each step solved side by side in"
            f" {worker_count(shading_light.SEARCH_PROCESSES)} worker processes (`shading_light.SEARCH_PROCESSES`,"
            " default: one per CPU) and, baseline, in one process (`SEARCH_PROCESSES = 1`); and"
            " whether the estimates are the same, bit for bit:", "",
            "| surface | slant, tilt (°) | one process: s | worker processes: s | ratio | same light |",
            "| --- | --- | --- | --- | --- | --- |"]
    totals = [0.0, 0.0]
    for name, h in _surfaces(n).items():
        for slant, tilt in lights:
            img = render_lambertian(h, PIXEL_UM, Light(slant, tilt), ALBEDO, periodic=True)
            found, seconds = [], []
            for processes in (1, shading_light.SEARCH_PROCESSES):
                with mock.patch.object(shading_light, "SEARCH_PROCESSES", processes):
                    t0 = time.perf_counter()
                    found.append(estimate_light(img))
                    seconds.append(time.perf_counter() - t0)
            totals = [a + b for a, b in zip(totals, seconds)]
            rows.append(f"| {name} | {slant:g}, {tilt:g} | {seconds[0]:.2f} | {seconds[1]:.2f} |"
                        f" {seconds[0] / seconds[1]:.2f} | {'yes' if found[0] == found[1] else 'NO'} |")
    rows.append(f"| all | | {totals[0]:.1f} | {totals[1]:.1f} | {totals[0] / totals[1]:.2f} | |")
    return rows


# Bands of the spectral diagnosis, in cycles per tile (see _band_power_ratios).
BANDS_CYCLES = ((1, 1), (2, 3), (4, 6), (7, 15), (16, 50), (51, 128))


def _band_power_ratios(height_um: np.ndarray, truth_um: np.ndarray, tilt_deg: float) -> list[tuple[float, float]]:
    """Power of `height_um` over that of `truth_um` per band of ``BANDS_CYCLES`` (radial
    frequency in cycles per tile), along the light (wave vectors within 45° of its azimuth)
    and across it: ``[(along, across), ...]``."""
    n_y, n_x = truth_um.shape
    ky = np.fft.fftfreq(n_y, 1.0 / n_y)[:, None]
    kx = np.fft.fftfreq(n_x, 1.0 / n_x)[None, :]
    k = np.hypot(kx, ky)
    t = np.deg2rad(tilt_deg)
    along = np.abs(kx * np.cos(t) + ky * np.sin(t)) > np.cos(np.pi / 4) * k
    got = np.abs(np.fft.fft2(height_um - height_um.mean())) ** 2
    ref = np.abs(np.fft.fft2(truth_um - truth_um.mean())) ** 2
    out = []
    for lo, hi in BANDS_CYCLES:
        band = (k >= lo - 0.5) & (k < hi + 0.5)
        out.append(tuple(float(got[band & sel].sum() / ref[band & sel].sum()) for sel in (along, ~along)))
    return out


def _domain_inputs(img: np.ndarray, periodic: bool = True, light: Light | None = None,
                   albedo: float = 0.0) -> tuple[np.ndarray, np.ndarray, dict]:
    """`img` as the default solver takes it (domain image, float32 weights, the domain's
    keyword arguments), as :func:`shape_from_shading` prepares it for a tile or, with the
    light and the starting albedo, a plain image."""
    dom_img, dom_w, kwargs = _solve_domain(img, valid_pixels(img), _censored_pixels(img), periodic, light, albedo)
    return dom_img, dom_w.astype(np.float32), kwargs


def _solver_inputs(case: dict) -> tuple[np.ndarray, np.ndarray, dict]:
    """The case's tile image as the default solver takes it (see :func:`_domain_inputs`)."""
    return _domain_inputs(case["image"])


def _undamped_height(case: dict) -> np.ndarray:
    """The default solver's height (µm) for the case's image with the exact reflectance on
    the coarse levels too (no sub-pixel damping): the baseline of the Brownian diagnosis."""
    img, weight, kwargs = _solver_inputs(case)
    albedo = _moment_albedo(case["image"][valid_pixels(case["image"])], case["slant_deg"])
    light = Light(case["slant_deg"], case["tilt_deg"])
    z, _ = solve_variational(img, weight, light.vector, albedo, subgrid_damping=0.0,
                             **DEFAULT_SOLVER, **kwargs)
    return z.astype(float) * PIXEL_UM


POLISH_ROUNDS = 40
# The keyword arguments of a solver's domain that its energy takes (the censored pixels; a
# plain image's data region and low-frequency prior).
ENERGY_KEYS = ("dark", "bright", "data_shape", "lowfreq_weight", "lowfreq_cycles", "lowfreq_power",
               "lowfreq_power_weight", "lowfreq_plane_weight", "lowfreq_fine_factor")


def _domain_energy(img, weight, light: Light, albedo: float, z: np.ndarray, kwargs: dict) -> float:
    """The finest level's energy of `z` (pixel units) on the domain with keyword arguments
    `kwargs` (a plain image's prior included)."""
    return energy(img, weight, light.vector, albedo, z, **{k: kwargs[k] for k in ENERGY_KEYS if k in kwargs})


def _polished(img, weight, light: Light, z: np.ndarray, kwargs: dict, max_rounds: int = POLISH_ROUNDS):
    """The minimum of the solver's energy nearest `z` (pixel units, on the domain): the finest
    level only, started from `z` with the true albedo (albedo projected, steps joined), rounds
    of 20 Gauss-Newton steps of 100 CG iterations until a round lowers the energy by less than
    1e-6 of it (at most `max_rounds`). A plain image's prior is kept, not tested. Returns (z,
    albedo, energy, rounds, the last round's relative gain)."""
    solve_kwargs = {k: v for k, v in kwargs.items() if k != "lowfreq_check_level"}
    albedo, e_prev, gain = ALBEDO, np.inf, np.inf
    for rounds in range(1, max_rounds + 1):
        z, albedo = solve_variational(img, weight, light.vector, albedo, z0=z, max_levels=1, fine_gn=20,
                                      fine_cg=100, albedo_projection=True, subspace_steps=2, **solve_kwargs)
        e = _domain_energy(img, weight, light, albedo, z, kwargs)
        gain = 1.0 - e / e_prev
        if gain <= 1e-6:
            break
        e_prev = e
    return z, albedo, e, rounds, gain


def _polished_truth(img, weight, light: Light, truth: np.ndarray, kwargs: dict):
    """:func:`_polished` from the true heights of a tile. Returns (z in pixel units, albedo,
    energy, rounds)."""
    return _polished(img, weight, light, (truth - truth.mean()) / PIXEL_UM, kwargs)[:4]


def _thin_plate_fill(z: np.ndarray, known: np.ndarray) -> np.ndarray:
    """`z` with its pixels outside `known` filled by the smoothest surface: the least squares
    of the periodic 5-point Laplacian over the whole domain, the known pixels held."""
    import scipy.sparse as sp
    from scipy.sparse.linalg import lsqr

    idx = np.arange(z.size).reshape(z.shape)
    neighbours = [idx] + [np.roll(idx, step, axis) for axis in (0, 1) for step in (1, -1)]
    lap = sp.csr_matrix((np.tile([-4.0, 1.0, 1.0, 1.0, 1.0], z.size),
                         (np.repeat(np.arange(z.size), 5), np.stack([a.ravel() for a in neighbours], 1).ravel())),
                        shape=(z.size, z.size))
    free, held = np.flatnonzero(~known.ravel()), np.flatnonzero(known.ravel())
    values = np.asarray(z, dtype=float).ravel().copy()
    values[free] = lsqr(lap[:, free], -(lap[:, held] @ values[held]), atol=1e-12, btol=1e-12, iter_lim=50000)[0]
    return values.reshape(z.shape)


# The plain images of random bumps whose energy is compared with its minimum nearest the
# truth: this light (the one with seeds above the target), at most this many polish rounds.
PLAIN_MINIMUM_LIGHT = (60.0, 300.0)
PLAIN_MINIMUM_ROUNDS = 5


def _plain_minimum(img: np.ndarray, truth: np.ndarray, light: Light) -> dict:
    """The default's solve of the plain image `img` (true heights `truth`, µm), light given,
    against the energy's minimum nearest the truth (the truth, its margin filled by
    :func:`_thin_plate_fill`, polished by :func:`_polished`, at most ``PLAIN_MINIMUM_ROUNDS``
    rounds): both errors, the default's energy (the finest level's, prior included) over the
    minimum's, the rounds and the last round's gain, and whether the default kept its
    flat-on-average prior (the energy compared includes it)."""
    albedo = _moment_albedo(img[valid_pixels(img)], light.slant_deg)
    dom_img, weight, kwargs = _domain_inputs(img, False, light, albedo)
    settings = {**shading._solver_settings("default", False, light.slant_deg, False), **kwargs}
    z, a = solve_variational(dom_img, weight, light.vector, albedo, **settings)
    height = shape_from_shading(img, pixel_size_um=PIXEL_UM, light=light, periodic=False).height
    rows, cols = img.shape
    crop = z[:rows, :cols].astype(np.float64)
    if not np.array_equal((crop - crop.mean()) * PIXEL_UM, height):
        raise RuntimeError("the bench's plain solve is not shape_from_shading's: update _plain_minimum")
    kept = np.array_equal(z, solve_variational(dom_img, weight, light.vector, albedo,
                                               **{**settings, "lowfreq_reject_ratio": np.inf})[0])
    known = np.zeros(dom_img.shape, bool)
    known[:rows, :cols] = True
    start = np.zeros(dom_img.shape)
    start[:rows, :cols] = (truth - truth.mean()) / PIXEL_UM
    z_min, _, e_min, rounds, gain = _polished(dom_img, weight, light, _thin_plate_fill(start, known).astype(np.float32),
                                              kwargs, PLAIN_MINIMUM_ROUNDS)
    return {"default": normalised_height_error(height, truth), "minimum": normalised_height_error(z_min[:rows, :cols], truth),
            "ratio": _domain_energy(dom_img, weight, light, a, z, kwargs) / e_min, "rounds": rounds, "gain": gain,
            "kept": kept}


def _minimum_cells(m: dict) -> str:
    """The table cells of a :func:`_plain_minimum` result after its first column."""
    return (f" | {m['default']:.3f} | {m['ratio']:.3f} | {m['minimum']:.3f} | {m['rounds']} ({m['gain']:.0e})"
            f" | {'yes' if m['kept'] else 'no'} |")


def _plain_minimum_rows(n: int, quick: bool) -> tuple[list[str], str]:
    """Table rows, one per seed, and a summary: random bumps as plain images lit at
    ``PLAIN_MINIMUM_LIGHT``, light given (:func:`_plain_minimum`)."""
    light = Light(*PLAIN_MINIMUM_LIGHT)
    rows, errors = [], {"default": [], "minimum": []}
    for seed in range(2 if quick else SEED_COUNT):
        truth = ts.random_bumps((n, n), PIXEL_UM, seed=seed)
        m = _plain_minimum(render_lambertian(truth, PIXEL_UM, light, ALBEDO, periodic=False), truth, light)
        for key, errs in errors.items():
            errs.append(m[key])
        rows.append(f"| {seed}" + _minimum_cells(m))
    summary = "; ".join(
        f"{key}: mean {np.mean(e):.3f}, worst {np.max(e):.3f}, {int(np.sum(np.array(e) > BUMPS_TARGET))} of {len(e)}"
        f" above {BUMPS_TARGET:g}" for key, e in (("default", errors["default"]), ("the minimum", errors["minimum"])))
    return rows, summary


def _crop_minimum_rows(n: int, quick: bool) -> list[str]:
    """Table rows, one per light of the plain-image tables: the plain weave's crop
    (:func:`_plain_crop` of its periodic rendering), light given (:func:`_plain_minimum`)."""
    truth = _surfaces(n)["woven (plain weave)"]
    crop = _plain_crop(n)
    out = []
    for slant, tilt in _plain_lights(quick):
        light = Light(slant, tilt)
        img = render_lambertian(truth, PIXEL_UM, light, ALBEDO, periodic=True)[crop]
        out.append(f"| {slant:g}, {tilt:g}" + _minimum_cells(_plain_minimum(img, truth[crop], light)))
    return out


# The true heights' line means along the light, removed in waves of up to this many cycles per
# image side across the light (the long stripes of the default's residual on plain images).
LINE_MEAN_CYCLES = 6


def _line_means(a: np.ndarray, tilt_deg: float, cycles: float | None = None) -> np.ndarray:
    """At each pixel, the mean of `a` along its line of the light's direction in the image
    (bands 1 px wide of the coordinate across the light); with `cycles`, those means' waves of
    at most that many cycles per image side (its longer one), by a cosine transform (no seam
    between the first and last lines)."""
    import scipy.fft

    t = np.deg2rad(tilt_deg)
    yy, xx = np.indices(a.shape)
    band = np.round(np.cos(t) * yy - np.sin(t) * xx).astype(int)
    band -= band.min()
    means = np.bincount(band.ravel(), a.ravel()) / np.bincount(band.ravel())
    if cycles is not None:
        # Cosine k spans k / 2 cycles over the means' length.
        waves = scipy.fft.dct(means, norm="ortho")
        waves[np.arange(means.size) * max(a.shape) > 2 * cycles * means.size] = 0.0
        means = scipy.fft.idct(waves, norm="ortho")
    return means[band]


def line_offset_section(n: int = 256, quick: bool = False) -> list[str]:
    """The report's table of where the default's error on plain images of random bumps comes
    from (:func:`_plain_bumps`: the seeds of :func:`_seed_rows`, the lights of ``LIGHTS[:4]``,
    light given): the share of its residual in line means along the light, and the error of the
    true heights with their line means removed. Can be run alone."""
    rows = []
    for slant, tilt in LIGHTS[:4]:
        errors, shares, removed, removed_long = [], [], [], []
        for seed in range(3 if quick else SEED_COUNT):
            truth, height = _plain_bumps(n, seed, slant, tilt)
            errors.append(normalised_height_error(height, truth))
            residual = affine_height_residual(height, truth)
            shares.append(float(np.sum(_line_means(residual, tilt) ** 2) / np.sum(residual**2)))
            removed.append(normalised_height_error(truth - _line_means(truth, tilt), truth))
            removed_long.append(normalised_height_error(truth - _line_means(truth, tilt, LINE_MEAN_CYCLES), truth))
        rows.append(f"| {slant:g}, {tilt:g} | {np.mean(errors):.3f} / {np.max(errors):.3f} | {np.mean(shares):.2f}"
                    f" ({np.min(shares):.2f}) | {np.mean(removed):.3f} / {np.max(removed):.3f} |"
                    f" {np.mean(removed_long):.3f} / {np.max(removed_long):.3f} |")
    return [
        "",
        f"Random bumps as plain images ({n} px, seeds as above), light given: where the default's error"
        " comes from. With free edges, the shading leaves each line along the light an offset that it"
        " fixes only through the slope across the light, which enters the shading only through its"
        " square (the normal's length; more under a low light; on a tile a line wraps round and goes"
        " on instead). The share of the default's residual (after the affine fit) that is the mean"
        " along each line of the light (mean over"
        " the seeds, least in brackets); for scale, the error of the true heights with their line"
        f" means removed, all of them and their waves of up to {LINE_MEAN_CYCLES} cycles per image side:"
        " what heights right but for those offsets, set to zero, would score:",
        "",
        "| slant, tilt (°) | default: error, mean / worst | its residual in line means | truth less its"
        f" line means: error | less their waves to {LINE_MEAN_CYCLES} cycles: error |",
        "| --- | --- | --- | --- | --- |",
        *rows,
    ]


def _energy_check(case: dict, truth_tactile: dict) -> str:
    """A table row: the energies of the default and accurate solvers' heights over the
    minimum nearest the true surface (:func:`_polished_truth`), and what each gives in a320.
    The solvers' signed tactile errors must be in the case's results already."""
    truth = case["height_true_um"]
    light = Light(case["slant_deg"], case["tilt_deg"])
    img, weight, kwargs = _solver_inputs(case)

    def e_of(z, albedo):
        return _domain_energy(img, weight, light, albedo, z, kwargs)

    z, albedo, e_true, rounds = _polished_truth(img, weight, light, truth, kwargs)
    polished = z.astype(float) * PIXEL_UM
    a320 = _tactile_errors(truth_tactile, _same_rms(polished, truth), PIXEL_UM)["a320"]
    cells = []
    for key in ("default", "accurate"):
        res = case["results"][key]
        ratio = e_of(res["height_raw_um"] / PIXEL_UM, res["albedo"]) / e_true
        cells.append(f"{ratio:.3f} | {res['error']:.3f} | {res['tactile_signed']['a320']:+.0%}")
    return (f"| {case['slant_deg']:g}, {case['tilt_deg']:g} | {_shadowed_fraction(kwargs):.1%} | "
            + " | ".join(cells) + f" | {normalised_height_error(polished, truth):.4f} | {a320:+.0%}"
            f" | {albedo / ALBEDO - 1:+.3%} | {rounds} |")


def _shadow_check(case: dict, truth_tactile: dict) -> str:
    """A table row: where the default solver's error on the sphere cap comes from. Its fitted
    albedo against the true one; the default with the albedo held at the true value; and the
    default on the same shading continued below zero (no attached shadow: every pixel carries
    its data). The default's signed tactile errors must be in the case's results already."""
    truth = case["height_true_um"]
    light = Light(case["slant_deg"], case["tilt_deg"])
    img, weight, kwargs = _solver_inputs(case)
    res = case["results"]["default"]
    cells = [f"{res['albedo'] / ALBEDO - 1:+.2%} | {res['error']:.3f} | {res['tactile_signed']['a320']:+.0%}"]
    held, _ = solve_variational(img, weight, light.vector, ALBEDO, fit_albedo=False, **DEFAULT_SOLVER, **kwargs)
    # The same finite differences as the renderer (periodic central), without the clip at 0.
    unclipped = (ALBEDO * reflectance(truth / PIXEL_UM, light.vector)).astype(np.float32)
    z, _ = solve_variational(unclipped, np.ones_like(unclipped), light.vector,
                             _moment_albedo(unclipped.ravel(), case["slant_deg"]), **DEFAULT_SOLVER)
    for height in (held.astype(float) * PIXEL_UM, z.astype(float) * PIXEL_UM):
        a320 = _tactile_errors(truth_tactile, _same_rms(height, truth), PIXEL_UM)["a320"]
        cells.append(f"{normalised_height_error(height, truth):.3f} | {a320:+.0%}")
    return (f"| {case['slant_deg']:g}, {case['tilt_deg']:g} | {_shadowed_fraction(kwargs):.1%} | "
            + " | ".join(cells) + " |")


def _tactile_errors(truth: dict, height_um: np.ndarray, pixel_size_um: float) -> dict:
    """Signed relative errors of the recovered heights' tactile summary against the truth's."""
    got = mean_tactile(height_um, pixel_size_um, periodic=True)
    return {k: got[k] / truth[k] - 1.0 for k in truth}


def run(quick: bool = False) -> str:
    """Run the bench and return a markdown report."""
    rows = cases(quick)
    n = rows[0]["height_true_um"].shape[0]
    lines = [
        f"Shape from shading, {n} x {n} px of {PIXEL_UM:g} µm, albedo {ALBEDO}, periodic tiles;"
        " error = normalised RMS height error after the best affine fit; tactile error ="
        " relative error of the tables' mean a40 / a320 (channel intensities I_p / I_np in"
        " brackets), recovered against true heights at the same RMS relief; † = estimated light"
        " flagged unreliable (fitted albedo at the search's bound; the light is then the best"
        " below that plateau of steep lights).",
        "",
        "| surface | slant, tilt (°) | Tsai-Shah error (baseline) | default error, light given |"
        " ratio to baseline | default error, light estimated | estimated slant, tilt (°) |"
        " tactile error, light given | tactile error, light estimated |",
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    truth_tactile = {}

    def tactile_cell(c, res):
        key = c["surface"]
        if key not in truth_tactile:
            truth_tactile[key] = mean_tactile(c["height_true_um"], c["pixel_size_um"], periodic=True)
        res["tactile_signed"] = _tactile_errors(truth_tactile[key], res["height_um"], c["pixel_size_um"])
        err = res["tactile"] = {k: abs(v) for k, v in res["tactile_signed"].items()}
        return f"{err['a40']:.0%} / {err['a320']:.0%} ({err['i_p']:.1%} / {err['i_np']:.1%})"

    for c in rows:
        res = c["results"]
        e_ts, e_d = res["tsai-shah"]["error"], res["default"]["error"]
        ratio = e_d / e_ts if e_ts > 0 else float("nan")
        line = (
            f"| {c['surface']} | {c['slant_deg']:g}, {c['tilt_deg']:g} | {e_ts:.3f} | {e_d:.3f} |"
            f" {ratio:.2f} |"
        )
        est = res.get("default, light estimated")
        if est is None:
            line += f" (not run) | | {tactile_cell(c, res['default'])} | |"
        else:
            le = est["light"]
            line += (
                f" {est['error']:.3f} | {le.slant_deg:.0f}±{le.slant_sd_deg:.0f},"
                f" {le.tilt_deg:.0f}±{le.tilt_sd_deg:.0f}{_flag(le)} | {tactile_cell(c, res['default'])} |"
                f" {tactile_cell(c, est)} |"
            )
        lines.append(line)
    lines += ["", "Tactile summaries of the true heights; the last two columns, at the mean amplitudes,"
              " say how much the a320 is felt: its Pacinian intensity alone (threshold units: below 1"
              " it is not detected by itself) and the change of the Pacinian intensity I_p when a320 is"
              " 20 % larger (the issue's tolerance):", "",
              "| surface | mean a40 (µm) | mean a320 (µm) | a320 / a40 | I_p | I_np | I_p of a320 alone |"
              " I_p change, a320 + 20 % |",
              "| --- | --- | --- | --- | --- | --- | --- | --- |"]
    model = TwoColourModel()
    for name, t in truth_tactile.items():
        alone = float(model.intensities(np.array([0.0]), np.array([t["a320"]]))[0][0])
        base, more = (float(model.intensities(np.array([t["a40"]]), np.array([f * t["a320"]]))[0][0])
                      for f in (1.0, 1.2))
        lines.append(f"| {name} | {t['a40']:.3g} | {t['a320']:.3g} | {t['a320'] / t['a40']:.2g} |"
                     f" {t['i_p']:.3g} | {t['i_np']:.3g} | {alone:.2g} | {more / base - 1:+.1%} |")
    # Where a low slant's a320 error comes from: the recovered heights' power by band, before
    # the RMS is matched (the relief a user gives is an RMS, or an SMD: dominated by the
    # longest wavelengths).
    diag = [c for c in rows if c["surface"].startswith("Brownian") and 15 <= c["slant_deg"] <= 30]
    if diag:
        heads = " | ".join(f"{lo}" if lo == hi else f"{lo}-{hi}" for lo, hi in BANDS_CYCLES)
        lines += ["", "Brownian surface, light given: power of the recovered heights over the truth's by"
                  " band (cycles per tile; along / across the light), before the RMS is matched, and the"
                  " RMS ratio. At a low slant the slopes across the light enter the shading only"
                  " quadratically, and a coarse level's averaged image is darker than the shading of"
                  " the averaged surface: with the exact reflectance on the coarse levels (baseline:"
                  " no damping) the longest wavelengths come out too strong, the RMS with them, and"
                  " matching the RMS then scales the fine detail (a320) down; the default damps the"
                  " squared slope across the light on those levels by their sub-pixel variance:", "",
                  f"| slant, tilt (°) | coarse levels | RMS ratio | {heads} | a320 error at the same RMS |",
                  "| --- | --- | --- | " + " | ".join("---" for _ in BANDS_CYCLES) + " | --- |"]
        for c in diag:
            res = c["results"]["default"]
            truth = c["height_true_um"]
            undamped = _undamped_height(c)
            undamped_same = _same_rms(undamped, truth)
            for label, height, rms_ratio, a320_err in (
                ("exact R (baseline)", undamped_same, float(np.std(undamped) / np.std(truth)),
                 _tactile_errors(truth_tactile[c["surface"]], undamped_same, PIXEL_UM)["a320"]),
                ("damped (default)", res["height_um"], res["rms_ratio"], res["tactile_signed"]["a320"]),
            ):
                scale = rms_ratio**2
                cells = " | ".join(f"{a * scale:.2f} / {b * scale:.2f}"
                                   for a, b in _band_power_ratios(height, truth, c["tilt_deg"]))
                lines.append(f"| {c['slant_deg']:g}, {c['tilt_deg']:g} | {label} | {rms_ratio:.2f} |"
                             f" {cells} | {a320_err:+.0%} |")
    # Summary against the issue's targets (slants 15-60°, light given / estimated).
    lines += ["", "| surface | worst default error, 15-60°, light given | worst, light estimated |"
              " worst estimated - given | worst Tsai-Shah | worst tactile error a40 / a320 (I_p / I_np), 15-60°,"
              " light given | light estimated | accurate (light given): worst error | its worst tactile"
              " error a40 / a320 |", "| --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    for name in dict.fromkeys(c["surface"] for c in rows):
        sel = [c for c in rows if c["surface"] == name and 15 <= c["slant_deg"] <= 60]
        worst = lambda k: max(c["results"][k]["error"] for c in sel)  # noqa: E731
        gap = max(c["results"]["default, light estimated"]["error"] - c["results"]["default"]["error"]
                  for c in sel)
        tact = lambda k, q: max(c["results"][k]["tactile"][q] for c in sel)  # noqa: E731
        lines.append(
            f"| {name} | {worst('default'):.3f} | {worst('default, light estimated'):.3f} |"
            f" {gap:+.3f} | {worst('tsai-shah'):.3f} |"
            f" {tact('default', 'a40'):.0%} / {tact('default', 'a320'):.0%}"
            f" ({tact('default', 'i_p'):.1%} / {tact('default', 'i_np'):.1%}) |"
            f" {tact('default, light estimated', 'a40'):.0%} /"
            f" {tact('default, light estimated', 'a320'):.0%}"
            f" ({tact('default, light estimated', 'i_p'):.1%} / {tact('default, light estimated', 'i_np'):.1%}) |"
        )
        acc = [c["results"]["accurate"] for c in sel]
        for res in acc:
            res["tactile_signed"] = _tactile_errors(truth_tactile[name], res["height_um"], PIXEL_UM)
            res["tactile"] = {k: abs(v) for k, v in res["tactile_signed"].items()}
        worst_acc = {q: max(r["tactile"][q] for r in acc) for q in ("a40", "a320", "i_p", "i_np")}
        lines[-1] += (f" {max(r['error'] for r in acc):.3f} | {worst_acc['a40']:.0%} / {worst_acc['a320']:.0%}"
                      f" ({worst_acc['i_p']:.1%} / {worst_acc['i_np']:.1%}) |")
    # Calibration of the estimated light's stated uncertainty (tilt modulo 180°: the sign is
    # a convention).
    d_s, d_t = [], []
    for c in rows:
        est = c["results"].get("default, light estimated")
        if est is None or not 15 <= c["slant_deg"] <= 60:
            continue
        le = est["light"]
        d_s.append(abs(le.slant_deg - c["slant_deg"]) / le.slant_sd_deg)
        d_t.append(tilt_axis_difference_deg(le.tilt_deg, c["tilt_deg"]) / le.tilt_sd_deg)
    if d_s:
        lines += [
            "",
            f"Estimated light, slants 15-60° ({len(d_s)} cases): |error| <= 1 sd in"
            f" {np.mean(np.array(d_s) <= 1):.0%} (slant) and {np.mean(np.array(d_t) <= 1):.0%}"
            f" (tilt axis), <= 2 sd in {np.mean(np.array(d_s) <= 2):.0%} and"
            f" {np.mean(np.array(d_t) <= 2):.0%}; largest |error| / sd: {max(d_s):.1f} (slant),"
            f" {max(d_t):.1f} (tilt). The tilt's sign follows the convention"
            " light-from-the-top (bumps, not dents, when lit from above).",
        ]
    lines += ["", f"Random bumps (slope 0.2) of {3 if quick else SEED_COUNT} seeds, light given: mean /"
              f" worst error / seeds above the issue's {BUMPS_TARGET:g} (the tables above use seed 1):", "",
              "| slant, tilt (°) | tile, default | tile, accurate | plain image, default |",
              "| --- | --- | --- | --- |", *_seed_rows(n, quick)]
    minimum_rows, minimum_summary = _plain_minimum_rows(n, quick)
    lines += ["", f"Random bumps as plain images lit at {PLAIN_MINIMUM_LIGHT[0]:g}°, {PLAIN_MINIMUM_LIGHT[1]:g}°"
              " (light given), where seeds miss the target: the default's energy (the finest level's, its"
              " flat-on-average prior included) over that of the energy's minimum nearest the true surface"
              " (the truth, its margin filled with the smoothest surface, polished by the finest level:"
              f" rounds of 20 steps of 100 CG iterations, at most {PLAIN_MINIMUM_ROUNDS}, until a round gains"
              " less than 1e-6 of the energy; the last round's gain in brackets), and the errors of both."
              " A minimum whose error is above the target: the energy itself puts the best heights near"
              " the truth there, and no solver of it meets the target; a ratio above 1: the default stops"
              " short of that minimum. With an image's free edges, the shading leaves each line along the"
              " light an unknown offset; the thin plate and the prior set them:", "",
              "| seed | default: error | energy ratio | minimum: error | rounds (gain) | prior kept |",
              "| --- | --- | --- | --- | --- | --- |", *minimum_rows, "", minimum_summary + "."]
    lines += line_offset_section(n, quick)
    lines += ["", f"The same for the plain weave's crop ({n - n // 8} px of its periodic rendering, the plain-image"
              " table's 'on the crop' column), light given. Here the minimum nearest the truth meets the"
              " target at every light (the default misses it at 15° and 30°), and the default's energy is"
              " above the minimum's: the energy puts the best heights near the truth, and the default's"
              " pyramid stops in another minimum"
              " (at 15°, its error lies within about 15 px of the edges, most at the edge facing away"
              " from the light, and was there from the quarter-resolution level on):", "",
              "| slant, tilt (°) | default: error | energy ratio | minimum: error | rounds (gain) | prior kept |",
              "| --- | --- | --- | --- | --- | --- |", *_crop_minimum_rows(n, quick)]
    if not quick:
        lines += ["", "Near-frontal light, estimated (tilt 30°; † = flagged unreliable: the fitted"
                  " albedo sits at the search's bound, where the misfit does not fix the slant; the slant"
                  " is then searched below that plateau; the search alone gave 36-38° for the"
                  " bumps and the Brownian surface at 0° and 5°):", "",
                  "| surface | slant 0° | 5° | 10° |", "| --- | --- | --- | --- |", *_near_frontal_rows(n)]
    spheres = [c for c in rows if c["surface"].startswith("sphere") and 15 <= c["slant_deg"] <= 60]
    lines += ["", "Sphere cap, light given: the energies of the default and accurate solvers' heights"
              " over the energy's minimum nearest the true surface (the true heights polished to"
              " convergence by the solver's finest level: rounds of 20 steps of 100 CG iterations"
              " until a round gains less than 1e-6), and what each gives. A ratio above 1: the solver"
              " stopped short of that minimum, and the a320 error between the two is the solver's;"
              " the minimum's own error is the energy's (its regulariser and, at 60°, the attached"
              " shadow):", "",
              "| slant, tilt (°) | shadowed pixels | default: energy ratio | error | a320 error |"
              " accurate: energy ratio | error | a320 error | minimum: error | a320 error |"
              " albedo error | rounds |",
              "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |",
              *(_energy_check(c, truth_tactile[c["surface"]]) for c in spheres)]
    lines += ["", "Sphere cap, light given: where the default's a320 error comes from. Its fitted albedo"
              " against the true one (0.8); the default with the albedo held at the true value; and the"
              " default on the same shading continued below zero, so that no pixel is an attached"
              " shadow (the shadow's heights are not in a real image: only that the surface faces"
              " away from the light there):", "",
              "| slant, tilt (°) | shadowed pixels | default: albedo error | error | a320 error |"
              " albedo held at 0.8: error | a320 error | no attached shadow: error | a320 error |",
              "| --- | --- | --- | --- | --- | --- | --- | --- | --- |",
              *(_shadow_check(c, truth_tactile[c["surface"]]) for c in spheres)]
    lines += ["", "Sphere cap with a sharp rim (kink, `rim_round_um=0`), light given:", "",
              "| slant, tilt (°) | Tsai-Shah error | default error |", "| --- | --- | --- |"]
    for slant, tilt, e_ts, e_d in _sharp_rim_rows(n):
        lines.append(f"| {slant:g}, {tilt:g} | {e_ts:.3f} | {e_d:.3f} |")
    lines += ["", f"Plain (non-periodic) images: the surfaces at {n} px rendered with one-sided"
              " differences at the edges and solved with `periodic=False`, light given. Lines"
              " along the light leave the image, so waves along the light are barely fixed by the"
              " shading; a flat-on-average prior fixes them, and is dropped where the data"
              " contradict it (`shading.LOWFREQ_REJECT_RATIO`, `LOWFREQ_REJECT_ALBEDO`). The prior"
              " is tightened on the long waves across the light that the image's waves along it"
              " show to have little power (`shading_prior`; baseline, same run: the default"
              " without that, "
              "`SPECTRAL_PRIOR_WEIGHT = 0`). Tactile error of plain surfaces: signed relative"
              " errors of the tables' mean a40 / a320, the channel intensities I_p / I_np in brackets"
              " (a sphere cap's a320 is about 1e-3 of its a40: its relative error moves I_p little)."
              " The surfaces are periodic tiles, so the last columns also crop"
              f" {n - n // 8} px of the tile's periodic rendering (offset 13, 19 px): a surface that is"
              " not periodic on the image, as a real one; the last with the light estimated (the"
              " estimate, slant, tilt; a tilt 180° off inverts the relief, which the error allows)."
              " Levelled: the best plane removed from both heights first (their error, and the"
              " tactile error at the same RMS relief after levelling): a uniform slope hardly changes"
              " a plain image's shading, and the photo pipeline averages a plain solve over the"
              " lattice, which removes it; the Brownian tile has half its variance in its plane:", "",
              "| surface | slant, tilt (°) | Tsai-Shah error | baseline error | default error | levelled error |"
              " a40 / a320 error (I_p / I_np) | levelled: a40 / a320 error (I_p / I_np) | flat prior | on the crop: baseline | default (levelled) |"
              " light estimated |",
              "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |",
              *_nonperiodic_rows(n, quick)]
    lines += ["", f"Plain images cut at random from the periodic renderings of {CROP_TILE_PX} px tiles"
              " (90-420 px sides of any aspect, any offset, any tilt, slants 15-60°, light given;"
              " fixed seed; the sphere cap's crops lie on its 410 px footprint, so that most show"
              " no flat ground and its flat-on-average prior should be dropped): normalised height"
              " error. Baselines, same run: the default without the plane term of that prior"
              " (`shading.LOWFREQ_PLANE_WEIGHT = 0`; a tilt along the light is traded against the"
              " albedo), and with the prior as it was before its albedo test (`LOWFREQ_WEIGHT = 1`,"
              " dropped above an energy ratio of 4 alone, `LOWFREQ_REJECT_RATIO = 4`,"
              " `LOWFREQ_REJECT_ALBEDO = inf`), and with the narrow margin of images whose edges"
              " are level ground on every image (`shading.TEXTURE_MARGIN = PLAIN_MARGIN`: the"
              " smooth join across the margin pulls a texture's opposite edges towards each other;"
              " `shading.level_edge_fraction` tells the two kinds apart):", "",
              "| surface | crops | no plane: mean | worst | above 0.4 | previous prior: mean | worst |"
              " above 0.4 | narrow margin: mean | worst | above 0.4 | default: mean | worst | above 0.4 |",
              "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |",
              *_random_crop_rows(quick)]
    margin_lights = _plain_lights(quick)
    lines += ["", f"The plain weave's plain image ({n} px) and its crop ({n - n // 8} px) on periodic"
              " domains of other sizes (the margin around the image, `shading.TEXTURE_MARGIN` for"
              " a texture, as a fraction of its side; the default's first; the sides halve to fast"
              " FFT sizes; `PLAIN_MARGIN` is the margin of images whose edges are level ground):"
              " normalised height error, light given, image / crop. The image is periodic, and"
              " some domains suit it: the crop's figures are a real photo's.", "",
              "| margin | domain side: image / crop (px) | "
              + " | ".join(f"{s:g}, {t:g}" for s, t in margin_lights) + " |",
              "| --- | --- | " + " | ".join("---" for _ in margin_lights) + " |",
              *_margin_rows(n, quick)]
    lines += ["", "Noisy images (Gaussian noise of standard deviation sigma, fixed seeds, clipped to"
              " [0, 1]; light given, slants 15-60°): worst normalised height error and worst"
              " tactile error a40 / a320. Baseline: the default with the albedo's lower bound at the"
              " raw 99.9th percentile, which the noise raises (by about 3 sigma); the default lowers"
              " it by 3.09 x the noise estimated from the image (`shading_variational._noise_sigma`,"
              " mean over the four images in the third column):", "",
              "| sigma | surface | estimated noise | baseline: error | a40 / a320 | default: error"
              " | a40 / a320 | error ratio default / baseline |",
              "| --- | --- | --- | --- | --- | --- | --- | --- |",
              *_noise_rows(n, NOISE_SIGMAS[:1] if quick else NOISE_SIGMAS)]
    steep = STEEP_LIGHTS[1:2] if quick else STEEP_LIGHTS
    lines += ["", "Steep light, given (attached shadows on part of the tile): normalised height error."
              " Baseline: the default fitting, on its coarse levels, the intensity of pixels partly in"
              " shadow (the mean of their lit part, brighter than the shading of their mean normal);"
              " the default gives them only their one-sided shadow term"
              " (`shading_variational._uncensored_weight`):", "",
              "| surface | " + " | ".join(f"{s:g}, {t:g}: shadowed | baseline | default" for s, t in steep) + " |",
              "| --- | " + " | ".join("--- | --- | ---" for _ in steep) + " |",
              *_steep_rows(n, steep)]
    aligned_slants = (60.0,) if quick else (30.0, 45.0, 60.0)
    lines += ["", "Light along the tile's x axis (tilt 0°) and diagonal (45°), and 3° off them, given:"
              " normalised height error (w = warned: `shading_starts.ALIGNED_TILT_DEG`). A tile-sized wave"
              " across the light has no slope along it; on a periodic tile such waves exist only"
              " for these directions (and the other axis and diagonal), where the shading fixes"
              " them only at second order. The issue's lights (tilts 30°, 120°, 200°, 300°) are"
              " off them:", "",
              "| surface | " + " | ".join(f"{s:g}, {t:g}" for s in aligned_slants for t in ALIGNED_TILTS) + " |",
              "| --- | " + " | ".join("---" for _ in aligned_slants for _ in ALIGNED_TILTS) + " |",
              *_aligned_rows(n, aligned_slants)]
    lines += ["", "Photo-like cells: smooth reliefs on square and oblique lattices"
              f" (`synth_images.lattice_relief`, RMS slope about 0.2), {n} px periodic tiles; normalised"
              " height error with the light given / estimated (estimated slant, tilt; † = flagged"
              " unreliable, the fitted albedo at its bound; the light is then searched below that"
              " plateau; then the search's misfit at the estimate over the true light's"
              " (`shading.light_misfit`): above 1 the search missed the true light's well, at or"
              " below 1 the search's misfit cannot tell the two apart; b = at the true light the"
              " fitted albedo sits at the search's bound, which then excludes the true albedo):", "",
              "| lattice t1; t2 (px) | " + " | ".join(f"{s:g}, {t:g}" for s, t in LIGHTS[:4]) + " | worst estimated - given |",
              "| --- | --- | --- | --- | --- | --- |"]
    for t1, t2 in LATTICES if not quick else LATTICES[:1]:
        h = lattice_relief((n, n), t1, t2, amplitude_um=12.0 * t1[0] / 16.0)
        cells, gaps = [], []
        for slant, tilt in LIGHTS[:4]:
            img = render_lambertian(h, PIXEL_UM, Light(slant, tilt), ALBEDO, periodic=True)
            given = shape_from_shading(img, pixel_size_um=PIXEL_UM, light=Light(slant, tilt), periodic=True)
            found = shape_from_shading(img, pixel_size_um=PIXEL_UM, periodic=True)
            e_g = normalised_height_error(given.height, h)
            e_f = normalised_height_error(found.height, h)
            gaps.append(e_f - e_g)
            m_true, true_at_bound = light_misfit(img, Light(slant, tilt))
            ratio = light_misfit(img, found.light)[0] / m_true
            cells.append(f"{e_g:.3f} / {e_f:.3f} ({found.light.slant_deg:.0f}, {found.light.tilt_deg:.0f}{_flag(found.light)};"
                         f" {ratio:.2g}{' b' if true_at_bound else ''})")
        lines.append(f"| {t1}; {t2} | " + " | ".join(cells) + f" | {max(gaps):+.3f} |")
    lines += _larger_tile_rows(quick)
    lines += _steep_bound_rows(quick)
    lines += _well_rows(quick)
    lines += _light_search_rows(128 if quick else n, quick)
    lines += timing_section(quick)
    return "\n".join(lines)


def timing_section(quick: bool = False) -> list[str]:
    """The report's timing tables (Tsai-Shah and the solvers at 1024 px, each surface as a tile
    and a plain image, plain images by side, the prior's test side by side, the malloc policy,
    the light along a tile's axis): its last section, which can be rerun alone."""
    tn = 512 if quick else 1024
    times = [_timing(tn, Light(*light), repeats=1 if quick else 2) for light in TIMING_LIGHTS]
    ts_mp = times[0]["Tsai-Shah (baseline)"]
    lines = [
        "",
        f"Timing at {tn} x {tn} px (random bumps, seed 5): seconds per megapixel, best of"
        f" {1 if quick else 2}, at each light; the ratio is to Tsai-Shah (50 iterations) at the"
        " first light.",
        "",
        "| solver | " + " | ".join(f"s per megapixel, lit at {s:g}°, {t:g}°" for s, t in TIMING_LIGHTS)
        + f" | ratio to Tsai-Shah at {TIMING_LIGHTS[0][0]:g}° |",
        "| --- | " + "--- | " * len(TIMING_LIGHTS) + "--- |",
    ]
    for label in TIMED:
        lines.append(f"| {label} | " + " | ".join(f"{t[label]:.2f}" for t in times)
                     + f" | {times[0][label] / ts_mp:.2f} |")
    lines += ["", f"The default solver on each surface at {tn} x {tn} px, light given, at the issue's"
              f" lights: seconds per megapixel (best of {1 if quick else 2}) and normalised height"
              " error, as a tile and as a plain image (`periodic=False`). Baseline (same run): the"
              " tile without the cap on the large levels above the finest"
              " (`DEFAULT_SOLVER['large_level_cap'] = None`: those levels took up to 20 CG"
              " iterations a step, the quarter-resolution one up to 20 steps; the random bumps"
              " above understate the time of smooth reliefs):", "",
              "| surface | slant, tilt (°) | tile: s per megapixel | error | without the cap: s per"
              " megapixel | error | plain image: s per megapixel | error |",
              "| --- | --- | --- | --- | --- | --- | --- | --- |",
              *_surface_timing_rows(tn, repeats=1 if quick else 2)]
    lines += ["", "Plain images (`periodic=False`) of the four surfaces at the first four lights, light given:"
              " summed seconds (best of each solve's runs), the slowest in seconds per megapixel of the"
              " image and the summed normalised height error; baseline (same run): their large levels"
              " above the finest with the tiles' cap, 12 CG iterations a step"
              " (`PLAIN_SOLVER['large_level_cap'] = DEFAULT_SOLVER['large_level_cap']`; the default 8):", "",
              "| side (px) | default: summed s | slowest: s per megapixel | summed error | tiles' cap: summed s"
              " | slowest: s per megapixel | summed error | time ratio |",
              "| --- | --- | --- | --- | --- | --- | --- | --- |",
              *_plain_timing_rows((tn,) if quick else (tn // 2, 3 * tn // 4, tn),
                                  repeats=1 if quick else 2)]
    lines += ["", "Plain images, the flat-on-average prior's test (its coarse levels solved with the prior"
              " and without it): the two chains side by side, the one with the prior in a forked child"
              " (default, `forked_map.call_beside`), against one after the other in this process"
              " (baseline, same run: `shading_variational.CHECK_PROCESSES = 1`). The 16 solves of each"
              " side as above, light given, best of each solve's runs in alternating order: summed"
              " seconds, and whether the heights are the same bit for bit:", "",
              "| side (px) | side by side: summed s | one after the other: summed s | time ratio | same heights |",
              "| --- | --- | --- | --- | --- |",
              *_check_side_by_side_rows((256,) if quick else (256, 512), repeats=1 if quick else 3)]
    lines += ["", f"The same 16 solves at {tn} x {tn} px, light given, with glibc's default malloc and with"
              " the solver's (`haptex_compile.malloc_policy`: freed blocks kept for reuse rather than"
              " handed back and faulted in again in the next CG iteration), each in a fresh process:", "",
              "| | default malloc | the solver's policy | ratio |", "| --- | --- | --- | --- |",
              *_malloc_policy_rows(tn, repeats=1 if quick else 2)]
    lines += fft_floor_section(quick)
    lines += fft_call_section(quick)
    lines += ["", "The default solver with the light along the tile's x axis (warned, see above: the"
              " pyramid, the pyramid holding the waves across the light from level 2, and the two"
              " full-resolution continuations, the lowest energy kept: `shading_starts._bare_tile_starts`)"
              " and 3° off it (the pyramid alone), random bumps (seed 5), light given, one run"
              " each: seconds per megapixel and normalised height error. Each continuation costs"
              " about the same per pixel at every size, 30 Gauss-Newton steps of 20 CG iterations;"
              " a weave's tile runs its full-resolution starts on a small window of its lattice"
              " instead (the photo pipeline), a tile with no lattice given cannot:", "",
              "| side (px) | along x (45°, 0°): s per megapixel | error | 3° off (45°, 3°): s per megapixel | error |",
              "| --- | --- | --- | --- | --- |",
              *_aligned_timing_rows((256, 512) if quick else (256, 512, 1024))]
    return lines


def _best_solve(img: np.ndarray, light: Light, periodic: bool, repeats: int):
    """The default solver on `img`, light given: its fastest time in seconds over `repeats`
    runs, and its result."""
    best = np.inf
    for _ in range(repeats):
        t0 = time.perf_counter()
        res = shape_from_shading(img, pixel_size_um=PIXEL_UM, light=light, periodic=periodic)
        best = min(best, time.perf_counter() - t0)
    return best, res


def _timing_cases(surfaces: dict[str, np.ndarray]):
    """(name, truth, light, {periodic: image}) of each surface at each of the first four
    ``LIGHTS``: the timing tables' solves, rendered as a tile and as a plain image."""
    for name, truth in surfaces.items():
        for slant, tilt in LIGHTS[:4]:
            light = Light(slant, tilt)
            yield name, truth, light, {periodic: render_lambertian(truth, PIXEL_UM, light, ALBEDO, periodic=periodic)
                                       for periodic in (True, False)}


def _surface_timing_rows(n: int, repeats: int) -> list[str]:
    """Seconds per megapixel (best of `repeats`) and height error of the default solver on
    each surface of side `n` at the first four ``LIGHTS``, light given: as a tile, as a tile
    without ``DEFAULT_SOLVER``'s large-level cap, and as a plain image; then the slowest of
    each, the summed times' ratio and the host's load average at the start and end (these
    are wall-clock times: other work on the host slows them)."""
    rows, slowest, totals = [], [0.0, 0.0, 0.0], [0.0, 0.0]
    load_start = os.getloadavg()[0]
    for name, truth, light, images in _timing_cases(_surfaces(n)):
        slant, tilt = light.slant_deg, light.tilt_deg
        cells = []
        for k, (periodic, patch) in enumerate([(True, {}), (True, {"large_level_cap": None}), (False, {})]):
            with mock.patch.dict(DEFAULT_SOLVER, patch):
                best, res = _best_solve(images[periodic], light, periodic, repeats)
            per_mp = best / (n * n / 1e6)
            slowest[k] = max(slowest[k], per_mp)
            if k < 2:
                totals[k] += best
            cells.append(f"{per_mp:.2f} | {normalised_height_error(res.height, truth):.3f}")
        rows.append(f"| {name} | {slant:g}, {tilt:g} | " + " | ".join(cells) + " |")
    rows += ["", f"Slowest: tile {slowest[0]:.2f} s per megapixel (without the cap {slowest[1]:.2f}),"
             f" plain image {slowest[2]:.2f}; the tiles' summed time with the cap over without it:"
             f" {totals[0] / totals[1]:.2f}. The host's load average (1 min) at the start and end of these"
             f" timings: {load_start:.1f}, {os.getloadavg()[0]:.1f} (on {os.cpu_count()} CPUs; these solves"
             " alone hold it near 1.7, their threads counted: measured 1.4 after 100 s of them from 0.1 on"
             " a quiet host; above that, other work shared the CPUs)."]
    return rows


def _plain_timing_rows(sides, repeats: int) -> list[str]:
    """For each side: the 16 plain-image solves of :func:`_timing_cases` with the default and
    with the tiles' large-level cap (the baseline), best of `repeats` each: summed seconds,
    the slowest in seconds per megapixel, summed height error, and the time ratio."""
    rows = []
    variants = ({}, {"large_level_cap": DEFAULT_SOLVER["large_level_cap"]})
    for n in sides:
        total, slowest, error = np.zeros(2), np.zeros(2), np.zeros(2)
        for _, truth, light, images in _timing_cases(_surfaces(n)):
            for k, patch in enumerate(variants):
                with mock.patch.dict(shading.PLAIN_SOLVER, patch):
                    best, res = _best_solve(images[False], light, False, repeats)
                total[k] += best
                slowest[k] = max(slowest[k], best / (n * n / 1e6))
                error[k] += normalised_height_error(res.height, truth)
        rows.append(f"| {n} | " + " | ".join(f"{total[k]:.2f} | {slowest[k]:.2f} | {error[k]:.3f}" for k in range(2))
                    + f" | {total[0] / total[1]:.2f} |")
    return rows


def _check_side_by_side_rows(sides, repeats: int) -> list[str]:
    """For each side: the 16 plain-image solves of :func:`_timing_cases` with the prior's test
    side by side (``shading_variational.CHECK_PROCESSES`` None) and one after the other (1),
    best of `repeats` runs each in alternating order: summed seconds, their ratio, and whether
    every solve gave the same heights both ways."""
    variants = (None, 1)
    rows = []
    for n in sides:
        total, same = np.zeros(2), True
        for i, (_, _, light, images) in enumerate(_timing_cases(_surfaces(n))):
            best, heights = [np.inf, np.inf], [None, None]
            for rep in range(repeats):
                for k in ((0, 1) if (i + rep) % 2 == 0 else (1, 0)):
                    with mock.patch.object(shading_variational, "CHECK_PROCESSES", variants[k]):
                        t, res = _best_solve(images[False], light, False, 1)
                    best[k] = min(best[k], t)
                    heights[k] = res.height
            total += best
            same &= bool(np.array_equal(heights[0], heights[1]))
        rows.append(f"| {n} | {total[0]:.2f} | {total[1]:.2f} | {total[0] / total[1]:.2f} | {'yes' if same else 'NO'} |")
    return rows


def _policy_times(n: int, repeats: int) -> dict[str, float]:
    """Summed seconds (best of `repeats` each) of the default solver on the four surfaces of
    side `n` at the first four ``LIGHTS``, light given, as tiles and as plain images, and the
    slowest plain image's seconds per megapixel: in this process's malloc policy."""
    out = {"tile": 0.0, "plain": 0.0, "slowest plain": 0.0}
    surfaces = _surfaces(n)
    warm = next(iter(surfaces.values()))[:64, :64]  # the compiled kernels load on a first solve
    for periodic in (True, False):
        shape_from_shading(render_lambertian(warm, PIXEL_UM, Light(*LIGHTS[0]), ALBEDO, periodic=periodic),
                           pixel_size_um=PIXEL_UM, light=Light(*LIGHTS[0]), periodic=periodic)
    for _, _, light, images in _timing_cases(surfaces):
        for periodic, key in ((True, "tile"), (False, "plain")):
            best, _ = _best_solve(images[periodic], light, periodic, repeats)
            out[key] += best
            if not periodic:
                out["slowest plain"] = max(out["slowest plain"], best / (n * n / 1e6))
    return out


def _malloc_policy_rows(n: int, repeats: int) -> list[str]:
    """:func:`_policy_times` with glibc's default malloc and with
    ``haptex_compile.malloc_policy`` (each in a fresh process: the policy is process-wide and
    cannot be undone), and the ratios."""
    times = {}
    for mode in ("off", "on"):
        out = subprocess.run([sys.executable, __file__, "--policy-times", mode, str(n), str(repeats)],
                             capture_output=True, text=True, check=True, timeout=1200)
        times[mode] = json.loads(out.stdout.strip().splitlines()[-1])
    return [f"| {label} | {times['off'][key]:.2f} | {times['on'][key]:.2f} | {times['on'][key] / times['off'][key]:.2f} |"
            for key, label in (("tile", "tiles: summed s"), ("plain", "plain images: summed s"),
                               ("slowest plain", "slowest plain image: s per megapixel"))]


class _CountingFFT:
    """Stands in for ``shading_variational.real_fft``: the real-input transforms it is asked
    for, counted by (kind, real side's shape, workers), passed on to :mod:`haptex_compile.real_fft`."""

    def __init__(self):
        from haptex_compile import real_fft

        self.fft, self.counts = real_fft, {}

    def rfft2(self, a, workers):
        key = ("rfft2", a.shape, workers)
        self.counts[key] = self.counts.get(key, 0) + 1
        return self.fft.rfft2(a, workers)

    def irfft2(self, spectrum, shape, workers):
        key = ("irfft2", tuple(shape), workers)
        self.counts[key] = self.counts.get(key, 0) + 1
        return self.fft.irfft2(spectrum, shape, workers)


def _fft_seconds(kind: str, shape: tuple[int, int], workers, repeats: int = 7) -> float:
    """The fastest of `repeats` single float32 transforms of `kind` at `shape` (the real
    side's), as the solver calls them (:mod:`haptex_compile.real_fft`; the inverse's copy of
    its input, which it overwrites, is not timed)."""
    from haptex_compile import real_fft

    real = np.random.default_rng(0).standard_normal(shape).astype(np.float32)
    spectrum = real_fft.rfft2(real, 1)
    best = np.inf
    for _ in range(repeats):
        scratch = spectrum.copy()
        t0 = time.perf_counter()
        if kind == "rfft2":
            real_fft.rfft2(real, workers)
        else:
            real_fft.irfft2(scratch, shape, workers)
        best = min(best, time.perf_counter() - t0)
    return best


def _fft_call_rows(sides, searches, repeats: int) -> list[str]:
    """Seconds of the default solver (light given, random bumps of seed 5 as tiles of each of
    `sides`) and of light searches (`searches`: (name, image) pairs), with the FFT pair
    through ``real_fft`` and through scipy.fft's public functions (baseline: ``real_fft``'s
    own fallback, its binding set aside), best of `repeats` in alternating order, and whether
    the results have the same bits."""
    from haptex_compile import real_fft

    def timed(fn, public):
        best, out = np.inf, None
        for _ in range(repeats):
            with mock.patch.object(real_fft, "_pocketfft", None) if public else contextlib.nullcontext():
                t0 = time.perf_counter()
                out = fn()
                best = min(best, time.perf_counter() - t0)
        return best, out

    cases = []
    for n in sides:
        light = Light(45.0, 200.0)
        img = render_lambertian(ts.random_bumps((n, n), PIXEL_UM, seed=5), PIXEL_UM, light, ALBEDO, periodic=True)
        solves = max(1, int(round(20 * (96 / n) ** 2)))  # about a second of solves a side
        cases.append((f"{solves} solves of {n} x {n} px tiles, light given",
                      lambda img=img, light=light, k=solves: [
                          shape_from_shading(img, pixel_size_um=PIXEL_UM, light=light, periodic=True).height
                          for _ in range(k)]))
    for name, img in searches:
        cases.append((f"light search, {name}", lambda img=img: estimate_light(img)))
    # Untimed: the first solve of a process loads the compiled kernels (numba's cache), which
    # would fall on the first case's first variant.
    cases[0][1]()
    rows, totals = [], np.zeros(2)
    for name, fn in cases:
        (t_direct, direct), (t_public, public) = timed(fn, False), timed(fn, True)
        if repeats > 1:  # the other order once more: the host's load drifts
            t_public = min(t_public, timed(fn, True)[0])
            t_direct = min(t_direct, timed(fn, False)[0])
        same = all(np.array_equal(a, b) for a, b in zip(direct, public)) if isinstance(direct, list) else direct == public
        totals += (t_direct, t_public)
        rows.append(f"| {name} | {t_direct:.2f} | {t_public:.2f} | {t_direct / t_public:.2f} | {'yes' if same else 'NO'} |")
    rows.append(f"| all | {totals[0]:.2f} | {totals[1]:.2f} | {totals[0] / totals[1]:.2f} | |")
    return rows


def fft_call_section(quick: bool = False) -> list[str]:
    """The timing section's table of ``real_fft`` against scipy.fft's public functions
    (:func:`_fft_call_rows`), runnable alone."""
    searches = [("random bumps 128 px, 30°, 120°", render_lambertian(
        ts.random_bumps((128, 128), PIXEL_UM, seed=1), PIXEL_UM, Light(30.0, 120.0), ALBEDO, periodic=True))]
    if not quick:
        searches.append(("square lattice relief 128 px, 15°, 30°", render_lambertian(
            lattice_relief((128, 128), (16, 0), (0, 16), amplitude_um=12.0), PIXEL_UM, Light(15.0, 30.0), ALBEDO,
            periodic=True)))
    return ["", "The solver's FFT pair straight to scipy's pocketfft binding (`haptex_compile.real_fft`)"
            " against scipy.fft's public functions (baseline, same run), which spend most of a small"
            " level's pair checking their arguments: seconds, best of each case's runs in alternating"
            " order, and whether the heights (lights) are the same bit for bit. The light search runs"
            " hundreds of solves of at most 96 and 256 px a side, whose coarse levels are 6-48 px:", "",
            "| case | real_fft: s | scipy.fft: s | ratio | same bits |", "| --- | --- | --- | --- | --- |",
            *_fft_call_rows((48, 96) if quick else (48, 96, 256), searches, repeats=1 if quick else 2)]


def _fft_floor_rows(n: int, repeats: int) -> list[str]:
    """The default solver's time at `n` px (random bumps, seed 5, light given, the timing
    lights; tile and plain image; best of `repeats`; the prior's test in this process) against
    the time of the FFTs it calls: each transform timed alone at its size (best of 7, same
    run), times the number of calls."""
    truth = ts.random_bumps((n, n), PIXEL_UM, seed=5)
    rows = []
    seconds_of = functools.cache(_fft_seconds)  # each size timed once for the four solves
    for periodic in (True, False):
        for slant, tilt in TIMING_LIGHTS:
            light = Light(slant, tilt)
            img = render_lambertian(truth, PIXEL_UM, light, ALBEDO, periodic=periodic)
            counter = _CountingFFT()
            with mock.patch.object(shading_variational, "CHECK_PROCESSES", 1):
                with mock.patch.object(shading_variational, "real_fft", counter):
                    shape_from_shading(img, pixel_size_um=PIXEL_UM, light=light, periodic=periodic)
                seconds, _ = _best_solve(img, light, periodic, repeats)
            floor = sum(count * seconds_of(kind, shape, workers)
                        for (kind, shape, workers), count in counter.counts.items())
            finest = max(shape for _, shape, _ in counter.counts)
            at_finest = sum(c for (_, shape, _), c in counter.counts.items() if shape == finest)
            mp = n * n / 1e6
            rows.append(f"| {'tile' if periodic else 'plain image'} | {slant:g}, {tilt:g} | {seconds / mp:.2f} |"
                        f" {sum(counter.counts.values())} ({at_finest} at {finest[0]} x {finest[1]} px) |"
                        f" {floor / mp:.2f} | {floor / seconds:.2f} |")
    return rows


def fft_floor_section(quick: bool = False) -> list[str]:
    """The timing section's table of the default solver's time against the FFTs it calls
    (:func:`_fft_floor_rows`), runnable alone."""
    tn = 512 if quick else 1024
    return ["", f"Where the default solver's time goes at {tn} x {tn} px (random bumps, seed 5, light given;"
            " the prior's test of plain images run in this process): seconds per megapixel (best of"
            f" {1 if quick else 2}), the FFTs it calls (the preconditioner's pair in every CG iteration,"
            " the prior's waves; on the finest level's domain in brackets), and the floor those set: each"
            " transform timed alone at its size in the same run (best of 7) times its count, per"
            " megapixel and as a share of the solve. The rest is the compiled passes over the pixels,"
            " the line searches and Python's overhead on the small levels:", "",
            "| image | slant, tilt (°) | s per megapixel | FFTs | FFT floor: s per megapixel | share |",
            "| --- | --- | --- | --- | --- | --- |",
            *_fft_floor_rows(tn, repeats=1 if quick else 2)]


def _aligned_timing_rows(sides) -> list[str]:
    """Seconds per megapixel and height error of the default solver on random bumps (seed 5)
    of each side, lit along the x axis (45°, 0°) and 3° off it (45°, 3°), light given."""
    rows = []
    for n in sides:
        truth = ts.random_bumps((n, n), PIXEL_UM, seed=5)
        cells = []
        for tilt in (0.0, 3.0):
            light = Light(45.0, tilt)
            img = render_lambertian(truth, PIXEL_UM, light, ALBEDO, periodic=True)
            seconds, res = _best_solve(img, light, True, repeats=1)
            cells.append(f"{seconds / (n * n / 1e6):.2f} | {normalised_height_error(res.height, truth):.3f}")
        rows.append(f"| {n} | " + " | ".join(cells) + " |")
    return rows


def _ducc0_pair():
    """``(rfft2, irfft2)`` with :mod:`haptex_compile.real_fft`'s signatures through ducc0's
    FFTs (the successor of the pocketfft that scipy.fft ends in; not a dependency: GPL-2.0-or-later)."""
    import ducc0

    from haptex_compile import real_fft

    def rfft2(a, workers):
        if a.dtype == np.float32 and a.ndim == 2:
            return ducc0.fft.r2c(a, axes=(0, 1), nthreads=workers)
        return real_fft.rfft2(a, workers)

    def irfft2(spectrum, shape, workers):
        if spectrum.dtype == np.complex64 and spectrum.shape == (shape[0], shape[1] // 2 + 1):
            return ducc0.fft.c2r(spectrum, axes=(0, 1), lastsize=shape[1], forward=False, inorm=2,
                                 nthreads=workers, allow_overwriting_input=True)
        return real_fft.irfft2(spectrum, shape, workers)

    return rfft2, irfft2


def fft_backend_section(quick: bool = False) -> list[str]:
    """The default solver on the four surfaces' tiles at the issue's lights (light given) with
    its FFT pair through scipy's pocketfft (``real_fft``, the default) and through ducc0, best
    of 2 in alternating order: seconds per megapixel and normalised height errors. Run alone
    (``--fft-backend``), where ducc0 is installed: it is not a dependency (its licence)."""
    try:
        rfft2, irfft2 = _ducc0_pair()
    except ImportError:
        return ["", "The FFT backend table needs ducc0 (`pip install ducc0`), which is not installed."]
    import ducc0

    n = 256 if quick else 1024
    rows, totals = [], np.zeros(2)
    cases = list(_timing_cases(_surfaces(n)))
    # Untimed: the first solve of a process loads the compiled kernels (numba's cache).
    _best_solve(cases[0][3][True][:64, :64], cases[0][2], True, repeats=1)
    for name, truth, light, images in cases:
        best, errors = [np.inf, np.inf], [0.0, 0.0]
        for order in ((0, 1), (1, 0)):
            for k in order:
                with (contextlib.nullcontext() if k == 0 else mock.patch.multiple(
                        shading_variational.real_fft, rfft2=rfft2, irfft2=irfft2)):
                    seconds, res = _best_solve(images[True], light, True, repeats=1)
                best[k] = min(best[k], seconds)
                errors[k] = normalised_height_error(res.height, truth)
        totals += best
        mpx = n * n / 1e6
        rows.append(f"| {name} | {light.slant_deg:g}, {light.tilt_deg:g} | {best[0] / mpx:.2f} | {errors[0]:.3f}"
                    f" | {best[1] / mpx:.2f} | {errors[1]:.3f} | {best[1] / best[0]:.2f} |")
    rows.append(f"| all | | {totals[0]:.2f} s | | {totals[1]:.2f} s | | {totals[1] / totals[0]:.2f} |")
    return ["", f"The default solver's FFT pair through scipy's pocketfft (`haptex_compile.real_fft`, the default;"
            f" baseline) and through ducc0 {ducc0.__version__} (its successor, GPL-2.0-or-later, not a"
            f" dependency), tiles of {n} x {n} px, light given: seconds per megapixel (best of 2 in"
            " alternating order), normalised height error and the time ratio:", "",
            "| surface | slant, tilt (°) | pocketfft: s per megapixel | error | ducc0: s per megapixel | error | ratio |",
            "| --- | --- | --- | --- | --- | --- | --- |", *rows]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="small images (under a minute)")
    parser.add_argument("--policy-times", nargs=3, metavar=("on|off", "SIDE", "REPEATS"),
                        help="print _policy_times as JSON, with the malloc policy on or off (a fresh process)")
    parser.add_argument("--fft-backend", action="store_true",
                        help="print only the table of the solver's FFTs through pocketfft and ducc0 (needs ducc0)")
    args = parser.parse_args()
    if args.fft_backend:
        print("\n".join(fft_backend_section(quick=args.quick)))
        return
    if args.policy_times:
        mode, side, repeats = args.policy_times
        malloc_policy.ENABLED = mode == "on"
        print(json.dumps(_policy_times(int(side), int(repeats))))
        return
    print(run(quick=args.quick))


if __name__ == "__main__":
    main()
