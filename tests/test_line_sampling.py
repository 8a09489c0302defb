"""Sheared line sampling (tables' fast path) returns exactly the continuous surface."""
from __future__ import annotations

import numpy as np
import pytest

from haptex_compile.fractal import brownian_surface
from haptex_compile.line_sampling import FAST_LEN_MAX, LineSampler, fast_len, supports, working_direction
from haptex_compile.surface import Surface, periodic_surface_from_tile, sample_height


@pytest.fixture(scope="module")
def height() -> np.ndarray:
    return brownian_surface((60, 84), 0.5, pixel_size_um=20.0, rms_um=5.0, seed=2)


@pytest.mark.parametrize("periodic", [False, True])
@pytest.mark.parametrize("direction", [0.0, 10.0, 44.0, 45.0, 46.0, 90.0, 120.0, 179.5])
def test_sheared_lines_are_the_spline_surface(height, periodic, direction):
    surface = periodic_surface_from_tile(height, 20.0) if periodic else Surface(height, 20.0, False)
    sampler = LineSampler(surface)
    rng = np.random.default_rng(int(direction))
    nodes = rng.uniform(-0.5, 2.0, (30, 2))  # some outside the map: mirrored or wrapped there
    frame, n_rows, n_cols = sampler.frame(direction, nodes[:, 0], nodes[:, 1], margin_mm=2.0, pad_mm=0.5)
    lines = sampler.sample(frame, n_rows, n_cols)
    r, k = np.mgrid[0:n_rows, 0:n_cols]
    x = frame.x0 + k * frame.h
    y = frame.j0 + r + x * frame.tan_d
    u, v = (y, x) if frame.transposed else (x, y)
    want = sample_height(surface, u * 0.02, v * 0.02)
    assert np.abs(lines - want).max() < 1e-5 * np.abs(want).max()
    # Lines run along the direction (or its reverse), columns a constant step apart along them.
    e = np.array([np.cos(np.deg2rad(direction)), np.sin(np.deg2rad(direction))])
    step = np.array([u[0, 1] - u[0, 0], v[0, 1] - v[0, 0]]) * 0.02
    assert abs(abs(step @ e) - frame.along_mm) < 1e-12 and abs(step[0] * e[1] - step[1] * e[0]) < 1e-12
    # Every node lies between the sampled lines, at least pad_mm from the first and last,
    # unless the rows are one whole period (then the lines repeat across).
    jf, kf = frame.index_coords(nodes[:, 0], nodes[:, 1])
    period_rows = sampler.period(frame.transposed)[0]
    if n_rows < period_rows:
        pad_rows = 0.5 / (0.02 * frame.cos_d)
        assert jf.min() >= pad_rows - 1 and jf.max() <= n_rows - pad_rows
    assert kf.min() * frame.along_mm >= 2.0 - 0.02 and (n_cols - 1 - kf.max()) * frame.along_mm >= 2.0 - 0.02


def test_working_frame_keeps_the_direction_within_45_degrees_of_x():
    for d in np.linspace(0, 180, 37):
        transposed, c, s = working_direction(d)
        assert c > 0 and c >= abs(s) - 1e-12 and abs(c * c + s * s - 1) < 1e-12


def test_general_lattices_are_not_supported(height):
    oblique = Surface(height, 20.0, True, np.array([30.0, 4.0]), np.array([-3.0, 25.0]), np.zeros(2))
    assert supports(Surface(height, 20.0, False)) and supports(periodic_surface_from_tile(height, 20.0))
    assert not supports(oblique)
    with pytest.raises(ValueError):
        LineSampler(oblique)


def test_fast_lengths_do_not_overflow():
    # scipy's next_fast_len raises OverflowError past the C integers; lengths that long are
    # returned as they are, for the tables' size checks to refuse in one line.
    import scipy.fft

    assert fast_len(1000) == scipy.fft.next_fast_len(1000) == 1000 and fast_len(1001, real=True) == 1024
    assert fast_len(10**20) == 10**20 and fast_len(FAST_LEN_MAX + 1) == FAST_LEN_MAX + 1
    with pytest.raises(OverflowError):
        scipy.fft.next_fast_len(10**20)
