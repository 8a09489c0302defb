"""The photograph pipeline against ground truth: a rendered, lattice-periodic relief comes back.

The relief is a smooth function of the lattice coordinates painted with an oblique lattice (so
the photo is not periodic on its pixel array), rendered as a Lambertian image; the pipeline
(illumination flattening, lattice, tile average, shape from shading, relief scale) must return
the relief up to the affine freedom shading leaves.
"""
from __future__ import annotations

import numpy as np
import pytest

from haptex_compile.photo import heights_at_image_px, photo_surface
from haptex_compile.shading import Light, normalised_height_error, render_lambertian
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
