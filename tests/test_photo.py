"""The photograph pipeline against ground truth: a rendered, lattice-periodic relief comes back.

The relief is a smooth function of the lattice coordinates painted with an oblique lattice (so
the photo is not periodic on its pixel array), rendered as a Lambertian image; the pipeline
(illumination flattening, lattice, tile average, shape from shading, relief scale) must return
the relief up to the affine freedom shading leaves.
"""
from __future__ import annotations

import logging
import re

import numpy as np
import pytest

from haptex_compile.photo import heights_at_image_px, photo_surface
from haptex_compile.shading import (
    Light,
    normalised_height_error,
    render_lambertian,
    tilt_axis_difference_deg,
)
from haptex_compile.sources import SourceOptions
from haptex_compile.synth_images import lattice_relief
from haptex_compile.tiles import MAX_WINDOW_STRAIN, paint_tile, periodic_window

PIXEL_UM = 20.0

LATTICES = [((18.3, 3.1), (-4.2, 15.7)), ((21.0, 0.0), (0.0, 16.5)), ((14.2, -5.3), (6.1, 19.8))]


@pytest.mark.parametrize("t1, t2", LATTICES + [((60.3, 11.0), (-7.0, 48.2))])
def test_periodic_window_is_exactly_periodic_and_barely_strained(t1, t2):
    basis = np.column_stack([t1, t2]).astype(float)
    strained, (rows, cols) = periodic_window(basis)
    k = np.linalg.solve(strained, np.diag([float(cols), float(rows)]))
    assert np.allclose(k, np.rint(k), atol=1e-9)  # the window's sides are lattice vectors
    assert np.linalg.norm(strained - basis) <= MAX_WINDOW_STRAIN * np.linalg.norm(basis)
    u = np.arange(16) / 16
    tile = np.cos(2 * np.pi * u)[None, :] + np.sin(2 * np.pi * u)[:, None]  # smooth: OpenCV warps at 1/32 px
    once = paint_tile(tile, strained, (rows, cols))
    twice = paint_tile(tile, strained, (2 * rows, 2 * cols))
    assert np.allclose(twice[rows:, cols:], once, atol=1e-4) and np.allclose(twice[:rows, cols:], once, atol=1e-4)


@pytest.mark.parametrize("t1, t2, light", [(t1, t2, light) for (t1, t2), light in zip(LATTICES, [(40, 60), (30, 200), (55, 300)])])
def test_photo_of_a_periodic_relief_gives_back_the_relief(t1, t2, light):
    truth_um = lattice_relief((768, 768), t1, t2, amplitude_um=12.0)
    image = render_lambertian(truth_um, PIXEL_UM, Light(*light), 0.8)
    options = SourceOptions(light=light, roughness="none", relief_um=float(np.std(truth_um)))
    result = photo_surface(image, PIXEL_UM, options, "rendered", {})
    assert result.surface.periodic and result.surface.shape == tuple(result.report["surface"]["window_px"][::-1])
    y, x = np.mgrid[100:668:3, 100:668:3]
    height = heights_at_image_px(result, x.ravel(), y.ravel())
    # the window's periodic solve reaches 0.02-0.03 here; the whole image with free edges reached
    # 0.02-0.085 on these at 1024-2000 px
    assert normalised_height_error(height, truth_um[y, x].ravel()) < 0.05


def test_a_lattice_with_no_periodic_window_is_solved_whole_and_averaged():
    # Cells of 47 px on an oblique lattice: no window of at most 1024 px strains it by 0.3 % or
    # less, so the photo is solved whole with free edges, then averaged over the lattice, and
    # the surface repeats on the lattice, not on the pixel array (bench_photo's coarse table:
    # 0.008 at 1024 px).
    t1, t2, light = (-22.15, 41.0), (-37.03, -40.52), (40, 60)
    assert periodic_window(np.array([t1, t2]).T, min_px=200, max_px=1024) is None
    truth_um = lattice_relief((768, 768), t1, t2, amplitude_um=40.0)
    image = render_lambertian(truth_um, PIXEL_UM, Light(*light), 0.8)
    options = SourceOptions(light=light, roughness="none", relief_um=float(np.std(truth_um)))
    result = photo_surface(image, PIXEL_UM, options, "rendered", {})
    assert result.report["shading"]["solved_on"].startswith("the whole image")
    assert result.surface.periodic and "surface" not in result.report  # no window recorded
    found = np.column_stack([result.surface.t1_px, result.surface.t2_px])
    # Its lattice is the relief's period: the painted cell vectors are integer combinations of
    # its basis (this relief also repeats at half-sums of them, and the lattice found says so).
    k = np.linalg.solve(found, np.array([t1, t2]).T)
    assert np.allclose(k, np.rint(k), atol=0.02) and abs(round(float(np.linalg.det(np.rint(k))))) >= 1
    y, x = np.mgrid[100:668:3, 100:668:3]
    height = heights_at_image_px(result, x.ravel(), y.ravel())
    assert normalised_height_error(height, truth_um[y, x].ravel()) < 0.05


def test_a_fine_diagonal_weave_is_solved_on_an_oversampled_tile(monkeypatch):
    # A plain weave of 12 px cells (the lattice found on a real 2000 px plain-weave photo):
    # at 1 tile sample per px the tile's two bicubic resamplings blur its shading, and the
    # heights come back with error 0.165; at SFS_SAMPLES_PER_PX = 2, 0.108 (3: 0.108).
    from haptex_compile import photo
    from haptex_compile.synth_images import weave_image

    t1, t2, light = (9.34, 7.85), (-8.53, 9.3), (45, 120)
    truth_um = 40.0 * weave_image((768, 768), t1, t2, kind="plain")
    image = render_lambertian(truth_um, PIXEL_UM, Light(*light), 0.8)
    options = SourceOptions(light=light, roughness="none", relief_um=float(np.std(truth_um)))
    y, x = np.mgrid[100:668:3, 100:668:3]

    def error():
        result = photo_surface(image, PIXEL_UM, options, "rendered", {})
        return normalised_height_error(heights_at_image_px(result, x.ravel(), y.ravel()), truth_um[y, x].ravel())

    assert photo.SFS_SAMPLES_PER_PX == 2.0
    oversampled = error()
    monkeypatch.setattr(photo, "SFS_SAMPLES_PER_PX", 1.0)
    assert oversampled <= 0.13
    assert error() >= 1.2 * oversampled


def test_accurate_solver_is_recorded_and_gives_back_the_relief():
    # ``--sfs accurate`` reaches the photo pipeline and the report says which solver ran.
    (t1, t2), light = LATTICES[0], (40, 60)
    truth_um = lattice_relief((512, 512), t1, t2, amplitude_um=12.0)
    image = render_lambertian(truth_um, PIXEL_UM, Light(*light), 0.8)
    options = SourceOptions(light=light, roughness="none", relief_um=float(np.std(truth_um)), sfs="accurate")
    result = photo_surface(image, PIXEL_UM, options, "rendered", {})
    assert result.report["shading"]["method"] == "accurate"
    y, x = np.mgrid[80:432:3, 80:432:3]
    height = heights_at_image_px(result, x.ravel(), y.ravel())
    assert normalised_height_error(height, truth_um[y, x].ravel()) < 0.05


def test_light_is_estimated_on_a_small_window_at_full_resolution(caplog):
    # A 1024 px photo of a smooth relief on 21 x 16.5 px cells, lit at 30°, 200°: estimated on
    # a window of at most 256 px, the light comes back within a few degrees (estimated on the
    # surface's window, reduced for the search, it came out at 41.5° and the height error was
    # 0.18-0.87), and the heights follow.
    t1, t2, light = (21.0, 0.0), (0.0, 16.5), (30.0, 200.0)
    truth_um = lattice_relief((1024, 1024), t1, t2, amplitude_um=12.0)
    image = render_lambertian(truth_um, PIXEL_UM, Light(*light), 0.8)
    options = SourceOptions(roughness="none", relief_um=float(np.std(truth_um)))
    logger = logging.getLogger("haptex")  # the CLI tests may stop it propagating to the root
    logger.addHandler(caplog.handler)
    try:
        result = photo_surface(image, PIXEL_UM, options, "rendered", {})
    finally:
        logger.removeHandler(caplog.handler)
    shading = result.report["shading"]
    assert not shading["light_given"] and "light_estimated_on" in shading
    cols, rows = (int(v) for v in shading["light_estimated_on"].split(" of ")[1].split(" px")[0].split(" x "))
    assert max(rows, cols) <= 256
    assert abs(shading["light_slant_deg"] - 30.0) <= 3.0
    assert tilt_axis_difference_deg(shading["light_tilt_deg"], 200.0) <= 3.0
    assert shading["light_albedo_at_bound"] is False  # a good estimate is not flagged
    assert any("light estimated" in r.getMessage() for r in caplog.records)
    assert any("light estimated" in w and shading["light_estimated_on"] in w for w in shading["warnings"])
    y, x = np.mgrid[100:924:4, 100:924:4]
    height = heights_at_image_px(result, x.ravel(), y.ravel())
    assert normalised_height_error(height, truth_um[y, x].ravel()) < 0.1


def test_a_long_light_search_is_announced(caplog, monkeypatch):
    # Without a small periodic window the light is searched on the image solved (up to a
    # minute on a 1 Mpx photo): the user is told before it starts, and how to skip it.
    import haptex_compile.photo as photo_module
    import haptex_compile.shading as shading_module

    class Started(Exception):
        pass

    def search_starts(*args, light=None, **kwargs):
        assert light is None
        raise Started

    monkeypatch.setattr(photo_module, "_light_from_small_window", lambda *a: (None, None))
    monkeypatch.setattr(shading_module, "shape_from_shading", search_starts)
    t1, t2 = (21.0, 0.0), (0.0, 16.5)
    image = render_lambertian(lattice_relief((256, 256), t1, t2, amplitude_um=12.0), PIXEL_UM, Light(30.0, 200.0), 0.8)
    logger = logging.getLogger("haptex")
    logger.addHandler(caplog.handler)
    caplog.set_level(logging.INFO, logger="haptex")
    try:
        with pytest.raises(Started):
            photo_surface(image, PIXEL_UM, SourceOptions(roughness="none", relief_um=10.0), "rendered", {})
    finally:
        logger.removeHandler(caplog.handler)
    said = [r.getMessage() for r in caplog.records if r.levelno == logging.INFO]
    assert any("estimating the light on a periodic window" in m and "--light" in m for m in said)


def test_a_steep_light_flagged_at_its_bound_is_left_steep():
    # A plain weave lit at 55°: the window's estimate sits at the albedo bound (flagged) at
    # 58°, above the plateau where the image does not fix the slant (35° + slopes, capped at
    # PLATEAU_MAX_DEG). It is a steep light with the bound active, not that plateau: the search
    # below the plateau, which would settle 12° lower with the tilt 38° off, is not run.
    from haptex_compile.shading_light import PLATEAU_MAX_DEG
    from haptex_compile.synth_images import weave_image

    t1, t2 = (14.2, -5.3), (6.1, 19.8)
    truth = 40.0 * weave_image((512, 512), t1, t2, kind="plain")
    image = render_lambertian(truth, PIXEL_UM, Light(55.0, 300.0), 0.8)
    options = SourceOptions(light=None, roughness="none", relief_um=float(np.std(truth)))
    shading = photo_surface(image, PIXEL_UM, options, "weave", {}).report["shading"]
    assert shading["light_albedo_at_bound"]
    assert shading["light_slant_deg"] > PLATEAU_MAX_DEG
    assert abs(shading["light_slant_deg"] - 55.0) <= 5.0
    assert tilt_axis_difference_deg(shading["light_tilt_deg"], 300.0) <= 15.0


def test_a_residual_larger_than_the_pattern_is_reported():
    """White noise of 1.5 x the pattern's grey RMS: the tile explains about 1 / (1 + 1.5^2) of the
    variance and the roughness scaled from the residual exceeds the relief, which is warned about;
    without the noise the tile explains nearly all of it and nothing is said."""
    t1, t2 = (18.3, 3.1), (-4.2, 15.7)
    truth_um = lattice_relief((512, 512), t1, t2, amplitude_um=12.0)
    clean = render_lambertian(truth_um, PIXEL_UM, Light(45.0, 200.0), 0.8)
    noisy = clean + np.random.default_rng(3).normal(0.0, 1.5 * float(np.std(clean)), clean.shape)
    options = SourceOptions(relief_um=10.0, light=(45.0, 200.0))
    quiet = photo_surface(clean, PIXEL_UM, options, "clean", {}).report
    loud = photo_surface(np.clip(noisy, 0.0, 1.0), PIXEL_UM, options, "noisy", {}).report
    assert quiet["lattice"]["tile_explained_variance"] > 0.9 and "warning" not in quiet["roughness"]
    assert abs(loud["lattice"]["tile_explained_variance"] - 1.0 / (1.0 + 1.5**2)) < 0.05
    assert "explains" in loud["roughness"]["warning"] and loud["roughness"]["rms_um"] > 10.0


def test_a_drifting_weave_is_averaged_where_it_repeats(monkeypatch):
    """A 16 px lattice stretched quadratically from the centre (3 % at the edges, 8 px of drift):
    averaged over the whole photo the tile explains about half the variance and the relief near
    the centre comes back 0.42 off; the central 512 px explain 97 % and the relief comes back
    within 0.2 there (positions counted in the photo's pixels)."""
    import haptex_compile.photo as photo
    from haptex_compile.synth_images import stretch_from_centre

    n = 1024
    truth = lattice_relief((n, n), (16.0, 0.0), (0.0, 16.0), amplitude_um=12.0)
    image = render_lambertian(truth, PIXEL_UM, Light(45.0, 200.0), 0.8)
    photo_img, seen_um = stretch_from_centre(image, 8.0), stretch_from_centre(truth, 8.0)
    options = SourceOptions(relief_um=10.0, light=(45.0, 200.0), roughness="none")
    yy, xx = np.mgrid[412:612:2, 412:612:2]

    def centre_error(result):
        return normalised_height_error(heights_at_image_px(result, xx.ravel(), yy.ravel()), seen_um[yy, xx].ravel())

    result = photo_surface(photo_img, PIXEL_UM, options, "drifting", {})
    lattice = result.report["lattice"]
    assert lattice["region_px"] == [256, 256, 512, 512] and lattice["tile_explained_variance"] > 0.9
    assert "1024 px" in lattice["region_note"]
    assert centre_error(result) < 0.2
    monkeypatch.setattr(photo, "REGION_TOLERANCE", 0.0)  # the whole photo, as before regions
    whole = photo_surface(photo_img, PIXEL_UM, options, "drifting", {})
    assert "region_px" not in whole.report["lattice"] and whole.report["lattice"]["tile_explained_variance"] < 0.7
    assert centre_error(whole) > 2 * centre_error(result)


def test_light_nearly_along_the_weave_is_warned_and_solved_from_full_resolution_starts():
    # A plain weave square to the camera, lit 3° off its yarns: the yarns' cross-sections
    # have almost no slope along the light. The pyramid's coarse levels under-resolve the yarns
    # and set them wrong (measured: height error 0.53 from the pyramid alone); the report
    # warns, and the starts at full resolution recover them (measured 0.048). 25° off the
    # yarns (sin 45° sin 25° = 0.30, above WEAVE_VISIBILITY_MIN) nothing is said and the
    # pyramid alone recovers the weave (measured 0.023).
    from haptex_compile.shading_starts import WEAVE_VISIBILITY_MIN
    from haptex_compile.synth_images import weave_image

    truth = 40.0 * weave_image((512, 512), (16.0, 0.0), (0.0, 16.0), kind="plain")
    y, x = np.mgrid[0:512:2, 0:512:2]
    for tilt, warned in ((183.0, True), (205.0, False)):
        image = render_lambertian(truth, PIXEL_UM, Light(45.0, tilt), 0.8)
        options = SourceOptions(light=(45.0, tilt), roughness="none", relief_um=float(np.std(truth)))
        result = photo_surface(image, PIXEL_UM, options, "weave", {})
        shading = result.report["shading"]
        assert (shading["weave_visibility"] < WEAVE_VISIBILITY_MIN) == warned
        assert any("nearly along the weave direction" in w for w in shading["warnings"]) == warned
        if warned:
            # (the lattice found is within a few thousandths of a degree of the truth)
            assert shading["weave_visibility"] == pytest.approx(np.sin(np.deg2rad(45.0)) * np.sin(np.deg2rad(3.0)), rel=1e-3)
            assert tilt_axis_difference_deg(shading["weave_direction_tilt_deg"], 0.0) < 0.5
        height = heights_at_image_px(result, x.ravel(), y.ravel())
        assert normalised_height_error(height, truth[y, x].ravel()) < (0.1 if warned else 0.05)


def test_the_pipeline_logs_each_stage_time_for_verbose_runs_and_keeps_it_out_of_the_report(caplog, monkeypatch):
    # haptex-compile -v shows where a photo's time goes; the report (stored in the asset) must
    # not hold wall-clock times, or assets would differ from run to run.
    monkeypatch.setattr(logging.getLogger("haptex"), "propagate", True)  # the CLI tests turn it off
    t1, t2, light = (21.0, 0.0), (0.0, 16.5), (30, 200)
    image = render_lambertian(lattice_relief((256, 256), t1, t2, amplitude_um=12.0), PIXEL_UM, Light(*light), 0.8)
    options = SourceOptions(light=light, roughness="none", relief_um=5.0)
    with caplog.at_level(logging.INFO, logger="haptex.photo"):
        result = photo_surface(image, PIXEL_UM, options, "timed", {})
    stages = [r.getMessage() for r in caplog.records if r.levelno == logging.INFO]
    assert any(m.startswith("timed: lattice and averaged tile in ") and m.endswith(" s") for m in stages), stages
    solved_on = result.report["shading"]["solved_on"]
    assert any(m.startswith(f"timed: heights from shading on {solved_on} in ") for m in stages), stages
    assert not any("estimated" in m for m in stages)  # the light was given: no search, none logged
    assert not re.search(r"\bin \d+\.\d s\b", repr(result.report))  # no time in the report


def test_a_pixel_size_that_makes_the_window_too_large_is_refused_before_painting(monkeypatch):
    # The periodic window is ROUGHNESS_CELL_MM or more a side: at 0.001 um pixels, 4e6 px (the
    # painted window asked for 58 TiB). Refused by its smallest size, then by the window found.
    import haptex_compile.photo as photo_module
    from haptex_compile.errors import InputError

    t1, t2 = (21.0, 0.0), (0.0, 16.5)
    image = render_lambertian(lattice_relief((128, 128), t1, t2, amplitude_um=12.0), PIXEL_UM, Light(30.0, 200.0), 0.8)
    options = SourceOptions(light=(30.0, 200.0), roughness="none", relief_um=10.0)
    with pytest.raises(InputError, match=r"at 0\.001 um pixels .* at least 4000000 x 4000000 px .* check the pixel size"):
        photo_surface(image, 0.001, options, "w.png", {})
    # At 20 um the smallest window is 200 x 200 px; the window found is larger (exactly
    # periodic on the lattice), so a limit between the two refuses it by its own size.
    cols, rows = photo_surface(image, PIXEL_UM, options, "w.png", {}).report["surface"]["window_px"]
    assert rows * cols > 200 * 200
    monkeypatch.setattr(photo_module, "MAX_WINDOW_PIXELS", rows * cols - 1)
    with pytest.raises(InputError, match=rf"at 20 um pixels the surface would be a periodic window of {cols} x {rows} px"):
        photo_surface(image, PIXEL_UM, options, "w.png", {})


def test_a_photo_without_a_lattice_is_scaled_as_a_solved_relief_is(monkeypatch, caplog):
    # Its Brownian surface took --relief-um as an RMS whatever --relief-kind said, and the
    # default 10 um for --kes (the Kawabata file ignored), and --light and --sfs without a word.
    from pathlib import Path

    from scipy import ndimage

    from haptex_compile.kes import simulate_kes_smd
    from haptex_compile.kes_io import read_kes

    monkeypatch.setattr(logging.getLogger("haptex"), "propagate", True)  # the CLI tests turn it off
    noise = ndimage.gaussian_filter(np.random.default_rng(3).standard_normal((160, 160)), 2.0)
    grey = 0.5 + 0.1 * noise / noise.std()  # texture without a repeating tile

    def surface(**options):
        result = photo_surface(grey, 20.0, SourceOptions(**options), "noise.png", {})
        assert not result.surface.periodic  # (no credible lattice: the Brownian path)
        return result

    h = surface(relief_um=5.0, relief_kind="pv").surface.height_um
    assert float(np.ptp(h)) == pytest.approx(5.0, rel=1e-9)
    h = surface(relief_um=5.0).surface.height_um
    assert float(np.std(h)) == pytest.approx(5.0, rel=1e-9)
    kes_path = Path(__file__).resolve().parents[1] / "samples" / "kes" / "satin.kes.json"
    result = surface(kes_path=str(kes_path))
    kes = read_kes(kes_path)
    smd = [simulate_kes_smd(result.surface.height_um, 20.0, d, periodic=False) for d in ("warp", "weft")]
    # (one scale for both directions: their geometric mean matched, as for a solved relief)
    assert float(np.sqrt(np.prod(smd))) == pytest.approx(np.sqrt(kes.smd_um["warp"] * kes.smd_um["weft"]), rel=0.01)
    assert result.roughness["rms_um"] == pytest.approx(float(np.std(result.surface.height_um)))
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="haptex"):
        surface(relief_um=5.0, light=(45.0, 30.0), sfs="accurate", roughness="none")
    assert any("noise.png: --light, --sfs, --roughness none do not apply: the photo has no credible lattice" in r.getMessage()
               for r in caplog.records)
