"""Heights from shading (issue 7): rendering, Tsai-Shah, the default solver, light estimation,
stability and physical scale. Ground truth comes from haptex_compile.known_surfaces."""
from __future__ import annotations

import os
import sys

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from haptex_compile import known_surfaces as ts
from haptex_compile import shading, shading_image, shading_light, shading_starts
from haptex_compile.shading import (
    Light,
    SfsResult,
    estimate_light,
    normalised_height_error,
    render_lambertian,
    scale_relief,
    shape_from_shading,
    tilt_axis_difference_deg,
    tsai_shah,
    valid_pixels,
)
from haptex_compile.shading_image import _censored_pixels
from haptex_compile.shading_variational import reflectance

PX = 20.0  # µm per pixel, as in the issue's anchors


@pytest.fixture(scope="module")
def bumps128():
    return ts.random_bumps((128, 128), PX, seed=3)


@pytest.fixture(scope="module")
def surfaces256():
    shape = (256, 256)
    return {
        "sphere": ts.sphere_cap(shape, PX),
        "woven": ts.woven_like(shape, PX),
        "bumps": ts.random_bumps(shape, PX, seed=1),
    }


def _slope_rms(h_um):
    gy, gx = np.gradient(h_um, PX)
    return float(np.sqrt(np.mean(gx * gx + gy * gy)))


# ----------------------------------------------------------------------------- rendering


def test_render_plane_matches_lambert_cosine():
    # A plane h = p x has normal (-p, 0, 1)/sqrt(1+p²); n.L for L = (sin s cos t, sin s sin t,
    # cos s) is (cos s - p sin s cos t)/sqrt(1+p²).
    p, s, t, albedo = 0.3, 40.0, 25.0, 0.7
    x = (np.arange(32) * PX)[None, :] * np.ones((32, 1))
    img = render_lambertian(p * x, PX, Light(s, t), albedo)
    sr, tr = np.deg2rad(s), np.deg2rad(t)
    expected = albedo * (np.cos(sr) - p * np.sin(sr) * np.cos(tr)) / np.sqrt(1 + p * p)
    np.testing.assert_allclose(img, expected, rtol=1e-12)


def test_render_tilt_convention_light_towards_plus_v():
    # Tilt 90° puts the light towards +v (down the image): a slope rising towards +v faces
    # away from it and is darker than one falling towards +v.
    y = (np.arange(16) * PX)[:, None] * np.ones((1, 16))
    light = Light(45.0, 90.0)
    rising = render_lambertian(0.2 * y, PX, light)
    falling = render_lambertian(-0.2 * y, PX, light)
    assert rising.mean() < falling.mean()


def test_render_attached_shadow_is_zero_and_flat_is_cos_slant():
    x = (np.arange(16) * PX)[None, :] * np.ones((16, 1))
    steep = render_lambertian(3.0 * x, PX, Light(60.0, 0.0))  # faces away: n.L < 0
    assert np.all(steep == 0.0)
    flat = render_lambertian(np.zeros((8, 8)), PX, Light(60.0, 123.0), albedo=0.8)
    np.testing.assert_allclose(flat, 0.8 * 0.5, rtol=1e-12)


def test_render_periodic_wraps_at_edges():
    h = ts.random_bumps((64, 64), PX, seed=0)
    light = Light(30.0, 10.0)
    img = render_lambertian(h, PX, light, periodic=True)
    shifted = render_lambertian(np.roll(h, 17, axis=1), PX, light, periodic=True)
    np.testing.assert_allclose(np.roll(img, 17, axis=1), shifted, atol=1e-12)


# ----------------------------------------------------------------------------- scoring


def test_normalised_error_is_affine_invariant_and_one_for_unrelated(bumps128):
    assert normalised_height_error(-3.0 * bumps128 + 7.0, bumps128) < 1e-12
    other = ts.random_bumps((128, 128), PX, seed=99)
    assert normalised_height_error(other, bumps128) > 0.9
    assert normalised_height_error(np.zeros_like(bumps128), bumps128) == pytest.approx(1.0)


# ----------------------------------------------------------------------------- Tsai-Shah


def test_tsai_shah_first_iteration_is_the_papers_gain_step():
    # From Z = 0: p = q = 0, R = cos s, df/dZ = -(ps + qs) cos s, and Z1 = -K f with
    # K = S0 df / (W + df S0 df), S0 = 0.01, W = 1e-8 (backward differences leave the first
    # row and column with p = q = 0 too).
    rng = np.random.default_rng(0)
    img = rng.uniform(0.3, 0.9, (12, 12))
    light = Light(35.0, 70.0)
    s, t = np.deg2rad(35.0), np.deg2rad(70.0)
    ps, qs = -np.tan(s) * np.cos(t), -np.tan(s) * np.sin(t)
    df = -(ps + qs) * np.cos(s)
    gain = 0.01 * df / (1e-8 + df * 0.01 * df)
    z1 = -gain * (img - np.cos(s))
    got = tsai_shah(img, light, n_iter=1, pixel_size_um=1.0)
    np.testing.assert_allclose(got, z1 - z1.mean(), rtol=1e-9, atol=1e-12)


def test_tsai_shah_overhead_light_does_not_move(bumps128):
    # Light along the view axis: ps = qs = 0, so df/dZ = 0 at the flat start.
    img = render_lambertian(bumps128, PX, Light(0.0, 0.0), 0.8)
    z = tsai_shah(img, Light(0.0, 0.0), n_iter=50, pixel_size_um=PX)
    assert np.all(z == 0.0)


def test_tsai_shah_recovers_nothing_on_smooth_bumps(bumps128):
    # The issue's anchor: normalised error 0.96-1.0 on bumps of slope ~0.2 with 20 µm pixels.
    light = Light(45.0, 200.0)
    img = render_lambertian(bumps128, PX, light, 0.8, periodic=True)
    z = tsai_shah(img, light, pixel_size_um=PX)
    assert np.all(np.isfinite(z))
    assert normalised_height_error(z, bumps128) > 0.9


# ----------------------------------------------------------------------------- default solver


@pytest.mark.parametrize("slant, tilt", [(15.0, 30.0), (30.0, 120.0), (45.0, 200.0), (60.0, 300.0)])
def test_default_recovers_sphere_woven_and_bumps_with_light_given(surfaces256, slant, tilt):
    # Issue targets: <= 10 % on the sphere and woven surfaces, <= 30 % on random bumps
    # (slants 15-60°).
    light = Light(slant, tilt)
    for name, limit in (("sphere", 0.10), ("woven", 0.10), ("bumps", 0.30)):
        h = surfaces256[name]
        img = render_lambertian(h, PX, light, 0.8, periodic=True)
        res = shape_from_shading(img, pixel_size_um=PX, light=light, periodic=True)
        err = normalised_height_error(res.height, h)
        assert err <= limit, (name, slant, err)
        # Never worse than the paper's method.
        assert err < normalised_height_error(tsai_shah(img, light, pixel_size_um=PX), h)


def test_albedo_projection_step_is_the_joint_gauss_newton_step():
    # Variable projection: with the albedo at its least-squares value, the projected step
    # must equal the height part of the joint (height, albedo) Gauss-Newton step, solved
    # here densely in float64; the plain step is the fixed-albedo one.
    from haptex_compile.shading_variational import _Problem, _dx, _dy, _lap2

    n = 12
    h = ts.random_bumps((n, n), PX, seed=4)
    light = Light(40.0, 70.0)
    img = render_lambertian(h, PX, light, 0.8, periodic=True).astype(np.float32)
    prob = _Problem(img, np.ones_like(img), light.vector, 1e-2)
    prob.albedo_min = 0.0
    z = (0.6 * h / PX).astype(np.float32)  # a wrong shape: the step is far from zero
    albedo, _ = prob.fit_albedo(z, 0.8)

    eye = np.eye(n * n).reshape(n * n, n, n)
    dx = np.stack([_dx(e).ravel() for e in eye], axis=1)
    dy = np.stack([_dy(e).ravel() for e in eye], axis=1)
    lap2 = np.stack([_lap2(e).ravel() for e in eye], axis=1)
    p, q = _dx(z).astype(float).ravel(), _dy(z).astype(float).ravel()
    lx, ly, lz = light.vector
    g = 1.0 + p * p + q * q  # R = (lz - p lx - q ly) / sqrt(g), and its derivatives
    r = (lz - p * lx - q * ly) / np.sqrt(g)
    rp, rq = -lx / np.sqrt(g) - r * p / g, -ly / np.sqrt(g) - r * q / g
    jz = albedo * (rp[:, None] * dx + rq[:, None] * dy)
    hess = jz.T @ jz + prob.lam * lap2 + 1e-6 * np.eye(n * n)
    res = albedo * r - img.ravel()
    grad = jz.T @ res + prob.lam * lap2 @ z.astype(float).ravel()
    joint = np.block([[hess, (jz.T @ r)[:, None]], [(r @ jz)[None, :], np.array([[r @ r]])]])
    step_joint = np.linalg.solve(joint, -np.append(grad, r @ res))[:-1]
    step_fixed = np.linalg.solve(hess, -grad)
    assert np.linalg.norm(step_joint - step_fixed) > 0.1 * np.linalg.norm(step_fixed)  # they differ

    # workers=3: the CG iterations' elementwise work in three blocks of rows (large levels).
    for project, want, workers in ((True, step_joint, 1), (False, step_fixed, 1), (True, step_joint, 3)):
        prob.project_albedo = project
        prob.workers = workers
        dz, _, g = prob.gn_step(z, albedo, 500, 1e-7)
        np.testing.assert_allclose(g.ravel(), grad, rtol=0, atol=1e-4 * np.abs(grad).max())
        diff = dz.ravel() - want
        diff -= diff.mean()  # a uniform offset is the height's null mode: held by 1e-6 only
        assert np.linalg.norm(diff) <= 1e-3 * np.linalg.norm(want), (project, workers)


def test_row_blocks_of_the_periodic_differences_make_the_whole():
    # Bit for bit: the threaded levels must give the heights of one thread.
    from haptex_compile.shading_variational import _dy2, _dy2_rows, _row_blocks

    for n in (3, 5, 12):
        z = np.random.default_rng(n).standard_normal((n, 4)).astype(np.float32)
        for parts in (1, 2, 3, 4):
            blocks = _row_blocks(n, parts)
            assert [i for b in blocks for i in range(n)[b]] == list(range(n))
            out = np.full_like(z, np.nan)
            for b in blocks:
                _dy2_rows(z, b, out)
            np.testing.assert_array_equal(out, _dy2(z))


# Reference periodic differences for the compiled kernels, by np.roll (a[i + k] along an axis).
def _roll_dx2(a):
    return np.roll(a, -1, axis=1) - np.roll(a, 1, axis=1)


def _roll_dy2(a):
    return np.roll(a, -1, axis=0) - np.roll(a, 1, axis=0)


def _roll_lap(a):
    return sum(np.roll(a, k, axis=ax) for k in (1, -1) for ax in (0, 1)) - 4 * a


KERNEL_SHAPES = ((1, 1), (2, 3), (3, 4), (5, 5), (6, 2), (7, 9), (16, 33))


def test_compiled_operator_is_the_composition_of_its_differences():
    # The CG operator's two compiled passes against the numpy operators they fuse: thin plate
    # (the 5-point Laplacian twice) + shift + D^T of the weighted Jacobian product + a rank-one
    # term, periodic, on any shape (edge columns wrap) and any blocks of rows.
    from haptex_compile.shading_kernels import jacobian_rows, normal_rows
    from haptex_compile.shading_variational import _row_blocks

    for shape in KERNEL_SHAPES:
        rng = np.random.default_rng(shape[0] * 100 + shape[1])
        v, ha, hb, nwa, nwb, u = (rng.standard_normal(shape).astype(np.float32) for _ in range(6))
        lam, shift, cu = np.float32(0.3), np.float32(1e-3), np.float32(0.7)
        v64 = v.astype(float)
        jv = ha * _roll_dx2(v64) + hb * _roll_dy2(v64)
        want = (lam * _roll_lap(_roll_lap(v64)) + shift * v64 + _roll_dx2(jv * nwa) + _roll_dy2(jv * nwb)
                - cu * u)
        scale = np.abs(want).max()
        for parts in (1, 2, 3):
            j, out = np.full_like(v, np.nan), np.full_like(v, np.nan)
            for b in _row_blocks(shape[0], parts):
                jacobian_rows(v, ha, hb, j, b.start, b.stop)
            np.testing.assert_allclose(j, jv, rtol=0, atol=1e-5 * np.abs(jv).max())
            for b in _row_blocks(shape[0], parts):
                normal_rows(v, j, nwa, nwb, lam, shift, u, cu, out, b.start, b.stop)
            np.testing.assert_allclose(out, want, rtol=0, atol=1e-5 * scale, err_msg=str((shape, parts)))


def test_compiled_line_search_terms_are_the_energys_formulas():
    # The line search's compiled passes against the energy written out in float64: the
    # Lambertian reflectance of central differences (damped across the light: weight 1 - k),
    # the least-squares albedo's sums, and the energy's data, one-sided and thin-plate terms,
    # on any shape and any blocks of rows.
    from haptex_compile.shading_kernels import albedo_sums_rows, energy_rows, reflectance_rows
    from haptex_compile.shading_variational import _across, _row_blocks

    light = np.array(Light(35.0, 120.0).vector, np.float32)
    across = np.array(_across(light), np.float32)
    albedo, dark_level, bright_level = np.float32(0.8), np.float32(0.05), np.float32(0.7)
    for shape in KERNEL_SHAPES:
        rng = np.random.default_rng(shape[0] * 100 + shape[1])
        z = rng.normal(0, 0.3, shape).astype(np.float32)
        img, w, dark, bright = (rng.random(shape).astype(np.float32) for _ in range(4))
        z64 = z.astype(float)
        p, q = 0.5 * _roll_dx2(z64), 0.5 * _roll_dy2(z64)
        pc = float(across[0]) * p + float(across[1]) * q
        lx, ly, lz = (float(c) for c in light)
        for k in (0.0, 0.6):
            want_r = (lz - p * lx - q * ly) / np.sqrt(1 + p * p + q * q - k * pc * pc)
            res = float(albedo) * want_r - img
            one_sided = (dark * np.maximum(res + img - float(dark_level), 0) ** 2
                         + bright * np.minimum(res + img - float(bright_level), 0) ** 2)
            want_e = [np.sum(w * res**2), np.sum(one_sided), np.sum(_roll_lap(z64) ** 2)]
            want_a = [np.sum(w * want_r**2), np.sum(w * want_r * img)]
            for parts in (1, 2, 3):
                r = np.full_like(z, np.nan)
                e_sums, a_sums = np.full((shape[0], 3), np.nan), np.full((shape[0], 2), np.nan)
                for b in _row_blocks(shape[0], parts):
                    reflectance_rows(z, light, np.float32(k), across, r, b.start, b.stop)
                for b in _row_blocks(shape[0], parts):
                    energy_rows(z, r, img, w, dark, bright, True, True, albedo, dark_level, bright_level,
                                e_sums, b.start, b.stop)
                    albedo_sums_rows(r, img, w, a_sums, b.start, b.stop)
                msg = str((shape, k, parts))
                np.testing.assert_allclose(r, want_r, rtol=0, atol=1e-6, err_msg=msg)
                np.testing.assert_allclose(e_sums.sum(axis=0), want_e, rtol=1e-5, err_msg=msg)
                np.testing.assert_allclose(a_sums.sum(axis=0), want_a, rtol=1e-5, err_msg=msg)
                # Without censored weights, the one-sided terms are not read.
                energy_rows(z, r, img, w, w, w, False, False, albedo, dark_level, bright_level, e_sums, 0, shape[0])
                assert e_sums[:, 1].sum() == 0


def test_kernels_compile_without_a_writable_cache(monkeypatch, caplog):
    # A read-only install with no writable home: numba refuses cache=True when the kernel is
    # defined ("no locator available"); the kernel must still work, compiled uncached, with one
    # warning that says so.
    import logging

    import numba.core.dispatcher

    from haptex_compile import shading_kernels

    def refuse(self):
        raise RuntimeError(f"cannot cache function {self.py_func.__name__!r}: no locator available for file 'x'")

    monkeypatch.setattr(numba.core.dispatcher.Dispatcher, "enable_caching", refuse)
    monkeypatch.setattr(shading_kernels, "_UNCACHED", [])
    monkeypatch.setattr(logging.getLogger("haptex"), "propagate", True)  # the CLI tests turn it off

    def row_sums(a, out, r0, r1):
        for i in range(r0, r1):
            out[i] = a[i].sum()

    with caplog.at_level(logging.WARNING, logger="haptex.shading"):
        kernel = shading_kernels._kernel()(row_sums)
        shading_kernels._kernel()(row_sums)
    a = np.arange(12.0).reshape(3, 4)
    out = np.zeros(3)
    kernel(a, out, 0, 3)
    np.testing.assert_array_equal(out, a.sum(axis=1))
    assert shading_kernels._UNCACHED == ["row_sums", "row_sums"]
    assert len([r for r in caplog.records if "NUMBA_CACHE_DIR" in r.getMessage()]) == 1


def test_threaded_levels_give_identical_heights():
    # A level of 512 x 512 px runs its Gauss-Newton steps' elementwise work on two threads,
    # in blocks of rows, in the single thread's order: the heights must be bit-identical.
    # Sphere cap at 60°: attached shadows (one-sided terms) and the albedo projection.
    from haptex_compile.shading import DEFAULT_SOLVER, _solve_domain, valid_pixels
    from haptex_compile.shading_variational import solve_variational

    n = 512
    light = Light(60.0, 300.0)
    img = render_lambertian(ts.sphere_cap((n, n), PX), PX, light, 0.8, periodic=True)
    dom, w, kwargs = _solve_domain(img, valid_pixels(img), _censored_pixels(img), periodic=True)
    assert np.any(kwargs["dark"] > 0)
    solver = dict(DEFAULT_SOLVER, projection_levels=(0, 1))
    one, a1 = solve_variational(dom, w.astype(np.float32), light.vector, 0.8, workers=1, **solver, **kwargs)
    two, a2 = solve_variational(dom, w.astype(np.float32), light.vector, 0.8, workers=2, **solver, **kwargs)
    np.testing.assert_array_equal(one, two)
    assert a1 == a2


@pytest.mark.skipif(not hasattr(os, "fork"), reason="no fork here")
def test_threaded_level_runs_in_a_forked_child():
    # haptex-compile --jobs forks worker processes; a child must not wait on the parent's
    # row threads, which it does not have.
    import multiprocessing

    from haptex_compile.shading_variational import solve_variational

    n = 512
    light = Light(45.0, 200.0)
    img = render_lambertian(ts.random_bumps((n, n), PX, seed=2), PX, light, 0.8, periodic=True)
    img = img.astype(np.float32)
    solve_variational(img, np.ones_like(img), light.vector, 0.8, max_levels=1, fine_gn=1)  # the pool exists
    ctx = multiprocessing.get_context("fork")
    child = ctx.Process(target=solve_variational, args=(img, np.ones_like(img), light.vector, 0.8),
                        kwargs=dict(max_levels=1, fine_gn=1))
    child.start()
    child.join(timeout=60)
    if child.is_alive():
        child.kill()
    assert child.exitcode == 0


@pytest.mark.parametrize("shape", [(1, 6), (2, 6), (6, 1), (6, 2), (1, 1)])
def test_reflectance_of_a_strip_one_or_two_pixels_wide(shape):
    # Along an axis of one or two pixels, a pixel's periodic neighbours either side are the same
    # pixel: no slope along it. A ramp along the other axis (if it is 3 px or more) keeps its
    # slope, wrapped ends included: R = (lz - p lx - q ly) / sqrt(1 + p² + q²).
    light = Light(40.0, 70.0)
    lx, ly, lz = light.vector
    rows, cols = shape
    z = 0.3 * np.arange(rows)[:, None] + 0.2 * np.arange(cols)[None, :]
    p = np.zeros(shape) if cols < 3 else np.gradient(np.pad(z, ((0, 0), (1, 1)), mode="wrap"), axis=1)[:, 1:-1]
    q = np.zeros(shape) if rows < 3 else np.gradient(np.pad(z, ((1, 1), (0, 0)), mode="wrap"), axis=0)[1:-1]
    expected = (lz - p * lx - q * ly) / np.sqrt(1 + p * p + q * q)
    np.testing.assert_allclose(reflectance(z, light.vector), expected, rtol=1e-12)


def test_damped_reflectance_weights_only_the_slope_across_the_light():
    from haptex_compile.shading_kernels import _reflectance_pixel
    from haptex_compile.shading_variational import _across

    def _reflectance(p, q, light_vec, w):
        # The solver's pixel formula (float64 here), weight w = 1 - k of the slope across
        out = [_reflectance_pixel(a, b, *light_vec, 1.0 - w, *_across(light_vec)) for a, b in zip(p, q)]
        return tuple(np.array(c) for c in zip(*out))

    light = Light(35.0, 40.0)
    lx, ly, lz = light.vector
    n = np.hypot(lx, ly)
    ax, ay, cx, cy = lx / n, ly / n, -ly / n, lx / n  # along and across the light
    rng = np.random.default_rng(0)
    p, q = rng.normal(0, 0.5, 50), rng.normal(0, 0.5, 50)
    along, across = ax * p + ay * q, cx * p + cy * q
    for w in (1.0, 0.3, 0.0):
        r, rp, rq = _reflectance(p, q, light.vector, w)
        want = (lz - p * lx - q * ly) / np.sqrt(1 + along**2 + w * across**2)
        np.testing.assert_allclose(r, want, rtol=1e-12)
        eps = 1e-6  # the derivatives are those of the damped R
        np.testing.assert_allclose(
            rp, (_reflectance(p + eps, q, light.vector, w)[0] - _reflectance(p - eps, q, light.vector, w)[0])
            / (2 * eps), atol=1e-8)
        np.testing.assert_allclose(
            rq, (_reflectance(p, q + eps, light.vector, w)[0] - _reflectance(p, q - eps, light.vector, w)[0])
            / (2 * eps), atol=1e-8)
    # Weight 0: the slope across the light does not enter at all.
    r0 = _reflectance(ax * along, ay * along, light.vector, 0.0)[0]
    np.testing.assert_allclose(_reflectance(p, q, light.vector, 0.0)[0], r0, rtol=1e-12)


def test_subpixel_variance_ratio_of_known_images():
    from haptex_compile.shading_variational import _downsample, _subpixel_variance_ratio

    rng = np.random.default_rng(1)
    blocks = np.kron(rng.normal(0.5, 0.1, (16, 16)), np.ones((2, 2)))  # constant in 2 x 2 blocks
    checker = 0.05 * (np.indices((32, 32)).sum(axis=0) % 2 * 2 - 1)  # all within the blocks
    w = np.ones((32, 32), np.float32)

    def ratio(img):
        img = img.astype(np.float32)
        mean, ww = _downsample(img, w)
        return _subpixel_variance_ratio(mean, _downsample(img * img, w)[0], ww)

    assert ratio(blocks) == pytest.approx(0.0, abs=1e-5)
    assert ratio(0.5 + checker) == np.inf
    assert ratio(np.full((32, 32), 0.5)) == 0.0
    # Both: the checker's variance 0.05² within, the blocks' variance between.
    assert ratio(blocks + checker) == pytest.approx(0.05**2 / np.var(blocks), rel=1e-3)


def test_coarse_damping_removes_spurious_relief_of_rough_surfaces(monkeypatch):
    # Brownian surfaces under a 15° light: without the coarse levels' damping the recovered
    # RMS relief is about 1.14 x the truth's (spurious long waves across the light, which the
    # tactile tables then pay for by scaling the fine detail down: mean a320 error -15 %);
    # with it about 1.04 x (a320 -6 %) (measured on 7 seeds x 2 tilts, 256 px). Mean over
    # 3 seeds x 2 tilts here (measured 1.145 and 1.046).
    from haptex_compile import shading_variational

    def mean_rms_ratio():
        ratios = []
        for seed in (2, 3, 4):
            h = ts.brownian_surface((256, 256), PX, hurst=0.7, seed=seed)
            for tilt in (30.0, 120.0):
                light = Light(15.0, tilt)
                img = render_lambertian(h, PX, light, 0.8, periodic=True)
                res = shape_from_shading(img, pixel_size_um=PX, light=light, periodic=True)
                ratios.append(np.std(res.height) / np.std(h))
        return float(np.mean(ratios))

    damped = mean_rms_ratio()
    monkeypatch.setattr(shading_variational, "SUBGRID_DAMPING", 0.0)
    exact = mean_rms_ratio()
    assert exact >= 1.10
    assert damped <= 1.08
    assert damped - 1 <= 0.5 * (exact - 1)


def test_gauss_newton_stops_once_a_full_step_gains_little(bumps128, monkeypatch):
    # Most levels converge in a few steps: stopping once a full step gains < 0.1 % of the
    # energy must leave the energy where the full step counts leave it (measured here:
    # 36 -> 16 steps, same energy within 0.01 %; on 256 px bumps 55 -> 23).
    from haptex_compile import shading_variational as sv

    light = Light(30.0, 120.0)
    img = render_lambertian(bumps128, PX, light, 0.8, periodic=True).astype(np.float32)
    w = np.ones_like(img)
    calls = []
    step = sv._Problem.gn_step

    def counted(self, *args, **kwargs):
        calls.append(1)
        return step(self, *args, **kwargs)

    monkeypatch.setattr(sv._Problem, "gn_step", counted)
    result = {}
    for rtol in (0.0, 1e-3):
        calls.clear()
        z, albedo = sv.solve_variational(img, w, light.vector, 0.8, gn_rtol=rtol)
        result[rtol] = (len(calls), sv.energy(img, w, light.vector, albedo, z))
    assert result[1e-3][0] <= 0.6 * result[0.0][0]
    assert result[1e-3][1] == pytest.approx(result[0.0][1], rel=0.01)


def test_large_levels_above_the_finest_take_capped_steps(bumps128, monkeypatch):
    # large_level_cap (pixels, steps, cg): levels other than the finest with at least that
    # many pixels take at most that many steps of at most that many CG iterations; smaller
    # levels and the finest keep theirs. Here a 128 px tile, cap from 32 x 32 px.
    from haptex_compile import shading_variational as sv

    light = Light(45.0, 200.0)
    img = render_lambertian(bumps128, PX, light, 0.8, periodic=True).astype(np.float32)
    levels = []
    solve = sv._Problem.solve

    def recorded(self, z, albedo, n_gn, max_cg, *args, **kwargs):
        levels.append((self.shape[0], n_gn, max_cg))
        return solve(self, z, albedo, n_gn, max_cg, *args, **kwargs)

    monkeypatch.setattr(sv._Problem, "solve", recorded)
    kwargs = dict(coarse_gn=20, coarse_cg=10, mid_gn=8, mid_cg=20, fine_gn=3, fine_cg=9)
    sv.solve_variational(img, np.ones_like(img), light.vector, 0.8, large_level_cap=(32 * 32, 2, 4), **kwargs)
    assert levels == [(8, 20, 10), (16, 20, 10), (32, 2, 4), (64, 2, 4), (128, 3, 9)]


def _capped_solves(monkeypatch, periodic: bool, level_shape: tuple[int, int], caps) -> tuple[dict, dict]:
    """Random bumps (seed 2, 512 px, lit at 30°, 120°) solved as a tile or a plain image with
    each of `caps` as the large-level cap (of ``DEFAULT_SOLVER``, or ``PLAIN_SOLVER`` for a
    plain image): their normalised height errors and the sets of CG iteration limits of the
    steps on the level of `level_shape`, both keyed by cap."""
    from haptex_compile import shading_variational as sv

    truth = ts.random_bumps((512, 512), PX, seed=2)
    light = Light(30.0, 120.0)
    img = render_lambertian(truth, PX, light, 0.8, periodic=periodic)
    settings = shading.DEFAULT_SOLVER if periodic else shading.PLAIN_SOLVER
    counted = []
    gn_step = sv._Problem.gn_step

    def step(self, z, albedo, max_cg, *args, **kwargs):
        if z.shape == level_shape:
            counted.append(max_cg)
        return gn_step(self, z, albedo, max_cg, *args, **kwargs)

    monkeypatch.setattr(sv._Problem, "gn_step", step)
    errors, iterations = {}, {}
    for cap in caps:
        counted.clear()
        monkeypatch.setitem(settings, "large_level_cap", cap)
        errors[cap] = normalised_height_error(
            shape_from_shading(img, pixel_size_um=PX, light=light, periodic=periodic).height, truth)
        iterations[cap] = set(counted)
    return errors, iterations


def test_the_large_level_cap_keeps_a_512_px_tiles_heights(monkeypatch):
    # The default caps the 256 px half-resolution level of a 512 px tile at 8 steps of 12 CG
    # iterations (20 without): fewer iterations, the same heights within 0.005 of normalised
    # error (measured on the bench's surfaces at 512 px: summed error 0.605 -> 0.610).
    cap = shading.DEFAULT_SOLVER["large_level_cap"]
    errors, iterations = _capped_solves(monkeypatch, True, (256, 256), (None, cap))
    assert cap == (256 * 256, 8, 12)
    assert iterations == {None: {20}, cap: {12}}
    assert errors[cap] == pytest.approx(errors[None], abs=0.005)
    assert errors[cap] < 0.1


def test_a_plain_images_large_levels_take_fewer_cg_iterations(monkeypatch):
    # A plain image of 512 px lies in a 600 px periodic domain, whose 300 px half-resolution
    # level takes steps of 8 CG iterations (PLAIN_SOLVER), not a tile's 12: the same heights
    # within 0.01 of normalised error and the issue's 0.3 for random bumps met (measured on the
    # bench's surfaces at 512 and 768 px and 800 px crops: summed error 13.125 -> 13.171 of 48).
    tile_cap, cap = shading.DEFAULT_SOLVER["large_level_cap"], shading.PLAIN_SOLVER["large_level_cap"]
    errors, iterations = _capped_solves(monkeypatch, False, (300, 300), (tile_cap, cap))
    assert cap == (256 * 256, 8, 8)
    assert iterations == {tile_cap: {12}, cap: {8}}
    assert errors[cap] == pytest.approx(errors[tile_cap], abs=0.01)
    assert errors[cap] < 0.3


def test_the_finest_level_starts_from_an_albedo_within_its_bounds(bumps128, monkeypatch):
    # Lambertian shading never exceeds the albedo, so the finest level holds it at or above
    # its brightest pixels; the half-resolution level, whose averaged image is darker,
    # hands down a lower one at 15° (measured: 0.7986 against 0.7998). Its first step is then
    # solved at the albedo it will not keep: the default starts from the bound instead.
    from haptex_compile import shading_variational as sv

    light = Light(15.0, 30.0)
    img = render_lambertian(bumps128, PX, light, 0.8, periodic=True).astype(np.float32)
    w = np.ones_like(img)
    step = sv._Problem.gn_step
    firsts = {}

    for bound in (False, True):
        seen = []

        def recorded(self, z, albedo, *args, **kwargs):
            if z.shape == img.shape:
                seen.append((albedo, self.albedo_min))
            return step(self, z, albedo, *args, **kwargs)

        monkeypatch.setattr(sv._Problem, "gn_step", recorded)
        z, albedo = sv.solve_variational(img, w, light.vector, 0.8,
                                         **{**shading.DEFAULT_SOLVER, "bound_start_albedo": bound})
        firsts[bound] = (*seen[0], sv.energy(img, w, light.vector, albedo, z))
    start, low, _ = firsts[False]
    assert start < low  # the case arises
    start, low, energy = firsts[True]
    assert start >= low >= np.percentile(img, 99.9) - 0.01
    assert energy <= firsts[False][2]


@pytest.mark.parametrize("slant, tilt", [(15.0, 30.0), (30.0, 120.0), (45.0, 200.0)])
def test_default_sphere_cap_feels_like_the_true_one(surfaces256, slant, tilt):
    # The tactile target (mean a40 and a320 within 20 %) on the smooth sphere cap, whose
    # a320 (the rim's crease) is the most fragile: the half-resolution level must converge
    # with the albedo projected, or the finest level starts from an albedo 0.3 % low and
    # stops in a worse minimum (measured before: a320 +30 % at 30°, height error 0.02;
    # now within 5 % and 0.006). At 60° (attached shadow) see the next test.
    from haptex_compile.tables import mean_tactile

    h = surfaces256["sphere"]
    light = Light(slant, tilt)
    img = render_lambertian(h, PX, light, 0.8, periodic=True)
    res = shape_from_shading(img, pixel_size_um=PX, light=light, periodic=True)
    assert normalised_height_error(res.height, h) <= 0.01
    truth = mean_tactile(h, PX, periodic=True)
    got = mean_tactile(res.height * (np.std(h) / np.std(res.height)), PX, periodic=True)
    for key in ("a40", "a320"):
        assert got[key] / truth[key] - 1 == pytest.approx(0.0, abs=0.10), key


def test_sphere_cap_at_60_degrees_meets_the_tactile_target_with_steps_joined(surfaces256, monkeypatch):
    # At 60° the attached shadow (4 % of the tile) leaves a slow valley: on the flat ground
    # the shading does not see slopes across the light at first order, so ridges along the
    # light trade against a higher albedo. Plain Gauss-Newton steps (each CG truncated) stop
    # in it (measured: albedo +0.12 %, a320 +30 %); joining each step to the previous two
    # reaches the tactile target (measured: +0.09 %, a320 +16 %, height error 0.016). The
    # same shading continued below zero (no pixel censored) has no such valley (0.001).
    from haptex_compile.shading_variational import solve_variational
    from haptex_compile.tables import mean_tactile

    h = surfaces256["sphere"]
    light = Light(60.0, 300.0)
    truth = mean_tactile(h, PX, periodic=True)

    def a320_error(height):
        got = mean_tactile(height * (np.std(h) / np.std(height)), PX, periodic=True)
        assert got["a40"] / truth["a40"] - 1 == pytest.approx(0.0, abs=0.02)
        return got["a320"] / truth["a320"] - 1

    img = render_lambertian(h, PX, light, 0.8, periodic=True)
    res = shape_from_shading(img, pixel_size_um=PX, light=light, periodic=True)
    assert normalised_height_error(res.height, h) <= 0.02
    assert abs(a320_error(res.height)) <= 0.20
    monkeypatch.setitem(shading.DEFAULT_SOLVER, "subspace_steps", 0)
    plain = shape_from_shading(img, pixel_size_um=PX, light=light, periodic=True)
    assert a320_error(plain.height) >= 0.25
    assert plain.albedo > res.albedo > 0.8

    unclipped = (0.8 * reflectance(h / PX, light.vector)).astype(np.float32)
    assert np.mean(unclipped < 0) > 0.03  # the clipped render's shadow: 4 % of the tile
    z, albedo = solve_variational(unclipped, np.ones_like(unclipped), light.vector, 0.7,
                                  **shading.DEFAULT_SOLVER)
    assert albedo == pytest.approx(0.8, rel=1e-3)
    assert normalised_height_error(z.astype(float) * PX, h) <= 0.01
    assert abs(a320_error(z.astype(float) * PX)) <= 0.10


def test_subspace_minimum_of_a_quadratic_model():
    # The minimum of 1/2 x.A x - b.x over span(V) solves (V^T A V) c = V^T b; a direction
    # parallel to another leaves the first direction as it was.
    from haptex_compile.shading_variational import _subspace_minimum

    rng = np.random.default_rng(3)
    m = rng.standard_normal((16, 16))
    a = m @ m.T + 16 * np.eye(16)
    b = rng.standard_normal(16)
    vs = [rng.standard_normal(16) for _ in range(3)]
    got = _subspace_minimum([v.astype(np.float32) for v in vs],
                            [(a @ v).astype(np.float32) for v in vs], b.astype(np.float32))
    basis = np.stack(vs, axis=1)
    want = basis @ np.linalg.solve(basis.T @ a @ basis, basis.T @ b)
    np.testing.assert_allclose(got, want, rtol=1e-4, atol=1e-4 * np.abs(want).max())
    model = lambda x: 0.5 * x @ a @ x - b @ x  # noqa: E731
    assert model(want) < model(vs[0]) and model(want) <= model(got) + 1e-6
    first = vs[0].astype(np.float32)
    same = _subspace_minimum([first, 2 * first], [(a @ first).astype(np.float32), (2 * a @ first).astype(np.float32)],
                             b.astype(np.float32))
    assert same is first


def test_partly_shadowed_coarse_pixels_carry_no_intensity():
    from haptex_compile.shading_variational import _uncensored_weight

    w = np.array([[1.0, 0.5, 0.25, 0.0, 0.6]], np.float32)
    dark = np.array([[0.0, 0.5, 0.0, 1.0, 0.0]], np.float32)
    bright = np.array([[0.0, 0.0, 0.75, 0.0, 0.0]], np.float32)
    # Only the pixels with both valid and censored parts lose their intensity.
    np.testing.assert_array_equal(_uncensored_weight(w, dark, bright), w * [[1, 0, 0, 0, 1]])
    assert _uncensored_weight(w, None, None) is w


def test_steep_light_on_a_brownian_surface_with_shadowed_coarse_pixels_left_out():
    # Lit at 70°, 5 % of a Brownian tile is in attached shadow. The coarse levels' pixels at
    # the shadows' edges average only their lit part, brighter than the shading of their
    # mean normal; fitted as data they bias the albedo and the slopes, and the finest level
    # inherits it (measured: 0.188 with them, 0.075 without).
    from unittest import mock

    h = ts.brownian_surface((256, 256), PX, hurst=0.7, seed=2)
    light = Light(70.0, 250.0)
    img = render_lambertian(h, PX, light, 0.8, periodic=True)
    assert 0.03 < np.mean(img <= shading_image.DARK) < 0.08
    err = normalised_height_error(shape_from_shading(img, pixel_size_um=PX, light=light, periodic=True).height, h)
    with mock.patch.dict(shading.DEFAULT_SOLVER, censored_data=True):
        fitted = shape_from_shading(img, pixel_size_um=PX, light=light, periodic=True).height
    assert err <= 0.10
    assert normalised_height_error(fitted, h) >= 1.5 * err


def test_accurate_method_is_more_exact_on_bumps(bumps128):
    # Measured (128 px bumps, slants 15-60°): default 0.02-0.07, accurate 0.006-0.010.
    light = Light(30.0, 120.0)
    img = render_lambertian(bumps128, PX, light, 0.8, periodic=True)
    errs = {m: normalised_height_error(shape_from_shading(img, pixel_size_um=PX, light=light, method=m,
                                                          periodic=True).height, bumps128)
            for m in ("default", "accurate")}
    assert errs["accurate"] <= 0.02
    assert errs["accurate"] <= 0.5 * errs["default"]


def test_default_recovers_sphere_at_45_degrees(surfaces256):
    h = surfaces256["sphere"]
    light = Light(45.0, 200.0)
    img = render_lambertian(h, PX, light, 0.8, periodic=True)
    res = shape_from_shading(img, pixel_size_um=PX, light=light, periodic=True)
    assert normalised_height_error(res.height, h) <= 0.10
    assert res.height.mean() == pytest.approx(0.0, abs=1e-6)


def test_sharp_rim_sphere_is_stable_and_beats_tsai_shah():
    # A kink (rim_round_um=0) is the solver's known limit at low slants (see the bench): the
    # result must stay finite and physical and still beat the paper's method.
    h = ts.sphere_cap((128, 128), PX, rim_round_um=0.0)
    light = Light(15.0, 30.0)
    img = render_lambertian(h, PX, light, 0.8, periodic=True)
    res = shape_from_shading(img, pixel_size_um=PX, light=light, periodic=True)
    _no_runaway(res, h)
    err = normalised_height_error(res.height, h)
    assert err < 0.5 * normalised_height_error(tsai_shah(img, light, pixel_size_um=PX), h)


def test_default_slopes_have_the_right_scale_when_light_and_albedo_are_right(bumps128):
    # With the exact Lambertian model, the recovered slopes are in µm/µm: the affine factor
    # between truth and result must be close to 1, not only the shape.
    light = Light(45.0, 200.0)
    img = render_lambertian(bumps128, PX, light, 0.8, periodic=True)
    res = shape_from_shading(img, pixel_size_um=PX, light=light, periodic=True)
    h = res.height - res.height.mean()
    a = float(np.sum(h * bumps128) / np.sum(h * h))
    assert 0.85 < a < 1.15
    assert res.albedo == pytest.approx(0.8, rel=0.02)


def test_periodic_result_wraps_seamlessly(bumps128):
    light = Light(40.0, 100.0)
    img = render_lambertian(bumps128, PX, light, 0.8, periodic=True)
    h = shape_from_shading(img, pixel_size_um=PX, light=light, periodic=True).height
    # The jump across the wrap seam is like any step between neighbouring columns/rows.
    seam_x = np.sqrt(np.mean((h[:, 0] - h[:, -1]) ** 2))
    seam_y = np.sqrt(np.mean((h[0] - h[-1]) ** 2))
    step_x = np.sqrt(np.mean(np.diff(h, axis=1) ** 2))
    step_y = np.sqrt(np.mean(np.diff(h, axis=0) ** 2))
    assert seam_x < 2.0 * step_x and seam_y < 2.0 * step_y


def test_the_flat_prior_is_dropped_on_a_dome_without_flat_ground(monkeypatch):
    # A 134 x 388 strip across the middle of a sphere cap (no flat ground in it), lit along its
    # short side: the flat-on-average prior flattens the dome (error 0.97), and its energy at
    # the check level is only 3.2 x that without the prior, under the old threshold of 4;
    # without the prior the albedo is the same within 3 %.
    tile = ts.sphere_cap((512, 512), PX)
    crop = (slice(177, 177 + 134), slice(62, 62 + 388))
    light = Light(30.0, 270.1)
    img = render_lambertian(tile, PX, light, 0.8, periodic=True)[crop]
    res = shape_from_shading(img, pixel_size_um=PX, light=light, periodic=False)
    assert normalised_height_error(res.height, tile[crop]) < 0.2
    monkeypatch.setattr(shading, "LOWFREQ_REJECT_RATIO", 4.0)
    res = shape_from_shading(img, pixel_size_um=PX, light=light, periodic=False)
    assert normalised_height_error(res.height, tile[crop]) > 0.9


def test_a_runaway_without_the_flat_prior_does_not_drop_it(monkeypatch):
    # The plain weave lit at 60° on a 320 px domain: without the prior the solve runs away to
    # a steep surface under twice the albedo, which fits the image 3 x better than the prior's
    # result at the check level. That is no evidence against the prior, which is kept.
    monkeypatch.setattr(shading, "TEXTURE_MARGIN", 0.25)
    h = ts.woven_like((256, 256), PX)
    light = Light(60.0, 300.0)
    img = render_lambertian(h, PX, light, 0.8, periodic=False)
    res = shape_from_shading(img, pixel_size_um=PX, light=light, periodic=False)
    assert normalised_height_error(res.height, h) < 0.12
    assert res.albedo == pytest.approx(0.8, rel=0.03)
    monkeypatch.setattr(shading, "LOWFREQ_REJECT_ALBEDO", np.inf)
    res = shape_from_shading(img, pixel_size_um=PX, light=light, periodic=False)
    assert normalised_height_error(res.height, h) > 0.9
    assert res.albedo > 1.5 * 0.8


def test_a_plain_images_light_misfit_leaves_out_the_seam():
    # The light search solves each light on a periodic domain; a plain image's seam joins
    # edges that do not match. A 224 px crop of random bumps' periodic rendering lit at
    # (45°, 200°): searched as a tile, the seam's misfit drew the light to (50.5°, 195.6°)
    # (height error 0.417 against 0.199 with the light given); with the band along the edges
    # left out, (44.5°, 200.6°).
    truth = ts.random_bumps((256, 256), PX, seed=1)
    crop = (slice(13, 13 + 224), slice(19, 19 + 224))
    img = render_lambertian(truth, PX, Light(45.0, 200.0), 0.8, periodic=True)[crop]
    found, _ = estimate_light(img, periodic=False)
    assert abs(found.slant_deg - 45.0) <= 1.5
    assert abs(found.tilt_deg - 200.0) <= 2.0
    as_tile, _ = estimate_light(img)
    assert as_tile.slant_deg >= 49.0


def test_a_light_estimated_on_a_plain_image_says_it_is_less_sure():
    light = Light(30.0, 200.0, 2.0, 1.0)
    assert "plain image" in shading.estimated_light_note(light, periodic=False)
    assert "plain image" not in shading.estimated_light_note(light)


def test_the_estimated_lights_note_is_one_short_line_with_every_clause():
    # Every clause at once (the lowest slant, flagged, on a plain image, and where it was
    # estimated): still one line a terminal shows in three or four rows, ending in the remedy.
    light = Light(shading.MIN_SLANT_DEG, 200.0, 20.0, 30.0, albedo_at_bound=True)
    note = shading.estimated_light_note(light, periodic=False, on="a periodic window of 190 x 142 px")
    assert "\n" not in note and len(note) <= 400
    for clause in ("on a periodic window of 190 x 142 px:", "slant 5.0 ± 20.0°", "search's lowest",
                   "UNRELIABLE", "plain image", "give --light"):
        assert clause in note
    assert note.endswith("give --light when it is known")


def test_non_periodic_image_beats_tsai_shah():
    h = ts.random_bumps((128, 128), PX, seed=4)
    light = Light(45.0, 200.0)
    img = render_lambertian(h, PX, light, 0.8)  # one-sided differences at the edges
    res = shape_from_shading(img, pixel_size_um=PX, light=light, periodic=False)
    assert res.height.shape == h.shape and np.all(np.isfinite(res.height))
    err = normalised_height_error(res.height, h)
    assert err < 0.6
    assert err < normalised_height_error(tsai_shah(img, light, pixel_size_um=PX), h)


def test_flat_prior_of_plain_images_is_dropped_where_the_scene_is_not_flat(monkeypatch):
    # A plain image's flat-on-average prior flattens an object on a flat ground (a sphere cap
    # filling the image): its shading then fits far worse than without the prior, and the
    # solver drops it. Random bumps fit about as well with it and keep it, bit for bit.
    light = Light(45.0, 200.0)
    cap = ts.sphere_cap((128, 128), 2 * PX)
    bumps = ts.random_bumps((128, 128), PX, seed=4)
    results, default = {}, shading.LOWFREQ_REJECT_RATIO
    for ratio in (default, np.inf):
        monkeypatch.setattr(shading, "LOWFREQ_REJECT_RATIO", ratio)
        for name, truth, px in (("cap", cap, 2 * PX), ("bumps", bumps, PX)):
            img = render_lambertian(truth, px, light, 0.8)
            results[name, ratio] = shape_from_shading(img, pixel_size_um=px, light=light,
                                                      periodic=False).height
    assert normalised_height_error(results["cap", default], cap) <= 0.10
    assert normalised_height_error(results["cap", np.inf], cap) >= 0.5  # the prior kept
    assert np.array_equal(results["bumps", default], results["bumps", np.inf])


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="forked workers are used on Linux only")
def test_the_flat_priors_test_gives_the_same_heights_side_by_side(monkeypatch):
    # The test's two chains (without the prior and with it) run side by side, the second in a
    # forked child; one after the other in this process they must give the same heights, bit
    # for bit, whether the prior is dropped (the sphere cap) or kept (the bumps).
    from haptex_compile import shading_variational

    light = Light(45.0, 200.0)
    cases = ((ts.sphere_cap((128, 128), 2 * PX), 2 * PX), (ts.random_bumps((96, 128), PX, seed=4), PX))
    for truth, px in cases:
        img = render_lambertian(truth, px, light, 0.8)
        heights = []
        for processes in (2, 1):
            monkeypatch.setattr(shading_variational, "CHECK_PROCESSES", processes)
            heights.append(shape_from_shading(img, pixel_size_um=px, light=light, periodic=False).height)
        assert np.array_equal(heights[0], heights[1])


def test_low_frequency_prior_is_its_symbol_on_the_kept_waves():
    # The prior is applied on the coefficients of the waves it keeps; it must equal the full
    # FFT with the kept symbol (odd and even sides, light with both components), on small
    # levels and on large ones (two threads of rows there).
    import scipy.fft as sfft

    from haptex_compile.shading_variational import _Problem

    rng = np.random.default_rng(3)
    # With the spectral prior too (shading_prior): more waves, up to 6 cycles.
    spectral = dict(albedo=0.8, side_px=130.0, data_pixels=130.0 * 70.0, weight=3e-4,
                    power=np.array([np.nan, 1.0, 1e-3, 1e-4, 1e-4, 1e-4, 1e-2]))
    large = dict(spectral, side_px=500.0, data_pixels=500.0 * 480.0)
    for (rows, cols), extra in (((144, 144), None), ((145, 77), None), ((96, 160), None), ((145, 77), spectral),
                                ((576, 576), None), ((512, 640), large)):
        img = rng.random((rows, cols)).astype(np.float32)
        side = 0.9 * max(rows, cols)
        prob = _Problem(img, np.ones_like(img), Light(40.0, 200.0).vector, 1e-4, 2,
                        (0.64, 2 * np.pi / side), lowfreq_spectral=extra)
        kept = np.count_nonzero(prob.lf)
        assert 0 < kept < (0.1 if extra else 0.02) * prob.lf.size  # a few waves
        v = rng.standard_normal((rows, cols)).astype(np.float32)
        want = sfft.irfft2(sfft.rfft2(v) * prob.lf, s=(rows, cols))
        assert np.abs(prob.lowfreq(v) - want).max() <= 1e-5 * np.abs(want).max()


def test_low_frequency_prior_with_its_plane_is_symmetric_and_the_same_on_any_threads():
    # The operator (waves and plane term) is symmetric, as its energy's Hessian must be, and
    # each row's sums belong to one thread: one thread or two give the same bits.
    from haptex_compile.shading_variational import _Problem

    rng = np.random.default_rng(5)
    spectral = dict(albedo=0.8, side_px=500.0, data_pixels=500.0 * 480.0, weight=3e-4,
                    power=np.array([np.nan, 1.0, 1e-3, 1e-4, 1e-4, 1e-4, 1e-2]))
    for (rows, cols), extra in (((576, 576), None), ((512, 640), spectral)):
        img = rng.random((rows, cols)).astype(np.float32)
        w = np.zeros((rows, cols), np.float32)
        w[:500, :480] = 1.0
        probs = [_Problem(img, w, Light(40.0, 200.0).vector, 1e-4, workers, (0.64, 2 * np.pi / 500.0),
                          lowfreq_spectral=extra, lowfreq_plane=0.1) for workers in (1, 2)]
        assert [p.workers for p in probs] == [1, 2]
        u, v = (rng.standard_normal((rows, cols)).astype(np.float32) for _ in range(2))
        one, two = (p.lowfreq(v) for p in probs)
        assert np.array_equal(one, two)
        uv, vu = float(np.vdot(u, probs[1].lowfreq(v))), float(np.vdot(v, probs[1].lowfreq(u)))
        assert abs(uv - vu) <= 1e-4 * float(np.vdot(v, two))


def test_the_prior_charges_a_tilt_of_the_data_region_and_nothing_in_the_margin():
    # The plane term: a tilt of slope (sx, sy) over the data region costs
    # weight x mu x N x (sx² + sy²) / 2 on top of the prior's waves, whatever the margin holds.
    from haptex_compile.shading_variational import _Problem

    rows, cols, data = 150, 120, (110, 90)
    box = np.zeros((rows, cols), np.float32)
    box[: data[0], : data[1]] = 1.0
    holed = box.copy()
    holed[40:50, 30:45] = 0.0  # masked pixels: the general path
    img = np.full((rows, cols), 0.5, np.float32)
    lowfreq = (0.64, 2 * np.pi / 110.0)
    yy, xx = np.mgrid[:rows, :cols].astype(np.float32)
    rng = np.random.default_rng(0)
    for w in (box, holed):
        off_data = np.where(w > 0, 0.0, rng.standard_normal((rows, cols))).astype(np.float32)
        with_plane = _Problem(img, w, Light(40.0, 200.0).vector, 1e-4, 1, lowfreq, lowfreq_plane=0.1)
        without = _Problem(img, w, Light(40.0, 200.0).vector, 1e-4, 1, lowfreq)
        for sx, sy in ((0.3, 0.0), (0.0, -0.2), (0.1, 0.25)):
            z = (sx * xx + sy * yy + 3.0) * w + off_data
            extra = 0.5 * float(np.vdot(z, with_plane.lowfreq(z) - without.lowfreq(z)))
            want = 0.5 * 0.1 * 0.64 * w.sum() * (sx * sx + sy * sy)
            assert extra == pytest.approx(want, rel=1e-4)


def test_the_plane_is_fitted_over_the_whole_data_region_holes_included():
    # On a plain image's domain the plane term charges a tilt of the data region
    # weight x mu x N x |slope|² / 2 with N the region's pixels, masked and shadowed ones
    # included (their heights are the surface's too): the data weights' holes change nothing.
    from haptex_compile.shading_variational import energy

    rows, cols, data = 150, 120, (110, 90)
    w = np.zeros((rows, cols), np.float32)
    w[: data[0], : data[1]] = 1.0
    dark = np.zeros_like(w)
    w[40:50, 30:45] = 0.0  # masked
    w[70:74, 10:20] = 0.0
    dark[70:74, 10:20] = 1.0  # an attached shadow
    img = np.full((rows, cols), 0.5, np.float32)
    light, albedo, plane_weight, prior_weight = Light(40.0, 200.0).vector, 0.8, 0.1, 0.3
    yy, xx = np.mgrid[:rows, :cols]
    region = (yy < data[0]) & (xx < data[1])
    off_data = np.where(region, 0.0, np.random.default_rng(2).standard_normal((rows, cols)))
    for sx, sy in ((0.3, 0.0), (0.0, -0.2), (0.1, 0.25)):
        z = np.where(region, sx * xx + sy * yy + 3.0, off_data).astype(np.float32)
        with_plane, without = (energy(img, w, light, albedo, z, dark=dark, data_shape=data,
                                      lowfreq_weight=prior_weight, lowfreq_plane_weight=pw)
                               for pw in (plane_weight, 0.0))
        want = 0.5 * plane_weight * prior_weight * albedo**2 * data[0] * data[1] * (sx * sx + sy * sy)
        assert with_plane - without == pytest.approx(want, rel=1e-4)


def test_on_a_large_level_the_prior_charges_the_same_tilt():
    # On a level of two threads of rows, the plane term charges a tilt of the data region the
    # same weight x mu x N x |slope|² / 2, whatever the margin holds.
    from haptex_compile.shading_variational import _Problem

    rows, cols, data = 576, 480, (512, 448)
    w = np.zeros((rows, cols), np.float32)
    w[: data[0], : data[1]] = 1.0
    img = np.full((rows, cols), 0.5, np.float32)
    lowfreq = (0.64, 2 * np.pi / 512.0)
    with_plane = _Problem(img, w, Light(40.0, 200.0).vector, 1e-4, 2, lowfreq, lowfreq_plane=0.1)
    without = _Problem(img, w, Light(40.0, 200.0).vector, 1e-4, 2, lowfreq)
    assert with_plane.workers == 2
    yy, xx = np.mgrid[:rows, :cols].astype(np.float32)
    off_data = np.where(w > 0, 0.0, np.random.default_rng(1).standard_normal((rows, cols))).astype(np.float32)
    for sx, sy in ((0.3, 0.0), (0.0, -0.2), (0.1, 0.25)):
        z = (sx * xx + sy * yy + 3.0) * w + off_data
        extra = 0.5 * float(np.vdot(z, with_plane.lowfreq(z) - without.lowfreq(z)))
        want = 0.5 * 0.1 * 0.64 * w.sum() * (sx * sx + sy * sy)
        assert extra == pytest.approx(want, rel=1e-4)


def _plain_domain(shape, data):
    """Data weights (1 on the top-left `data` box) and a uniform image on a plain image's
    periodic domain of `shape`."""
    w = np.zeros(shape, np.float32)
    w[: data[0], : data[1]] = 1.0
    return w, np.full(shape, 0.5, np.float32)


def test_the_energy_of_a_plain_domain_includes_its_prior():
    # energy() with a plain image's domain keywords adds the finest level's prior: a wave
    # A cos(w y) across a light along x costs 0.5 x mu x phi(w) x sin²(w) x A² x N / 2 more
    # (mu = weight x albedo², phi the Gaussian cut at `cycles` per data region's side, N the
    # domain's pixels), and a wave along the light nothing.
    from haptex_compile.shading_variational import energy

    rows, cols, data = 288, 288, (256, 256)
    w, img = _plain_domain((rows, cols), data)
    light = Light(40.0, 0.0).vector
    yy, xx = np.mgrid[:rows, :cols].astype(np.float32)
    albedo, weight, amp = 0.8, 0.3, 2.0
    prior = dict(data_shape=data, lowfreq_weight=weight, lowfreq_cycles=1.0)
    for m in (1, 2):
        wave = 2 * np.pi * m / rows
        across = (amp * np.cos(wave * yy)).astype(np.float32)
        extra = energy(img, w, light, albedo, across, **prior) - energy(img, w, light, albedo, across)
        phi = np.exp(-(wave / (2 * np.pi / max(data))) ** 2)
        want = 0.5 * weight * albedo**2 * phi * np.sin(wave) ** 2 * amp**2 * rows * cols / 2
        assert extra == pytest.approx(want, rel=0.01)
        along = (amp * np.cos(wave * xx)).astype(np.float32)
        extra = energy(img, w, light, albedo, along, **prior) - energy(img, w, light, albedo, along)
        assert abs(extra) <= 1e-6 * want


@pytest.mark.parametrize(
    "periodic, method, target",
    [(True, "default", 0.3), (True, "accurate", 0.05), (False, "default", 0.3)],
)
def test_low_slant_random_bumps_meet_the_target(monkeypatch, periodic, method, target):
    # Random bumps lit at 15° (the bench's generator, seed 2): the energy's minimum near the
    # truth has a height error of 0.007, and the solvers used to settle in another one from
    # their heavily smoothed coarse levels: tile 0.381 with either method, plain image 0.339
    # (above the issue's 30 % for random bumps). With the weaker continuation at low slants:
    # tile 0.205 (default) and 0.009 (accurate), plain image 0.255.
    truth = ts.random_bumps((256, 256), PX, seed=2)
    light = Light(15.0, 30.0)
    img = render_lambertian(truth, PX, light, 0.8, periodic=periodic)

    def error():
        result = shape_from_shading(img, pixel_size_um=PX, light=light, periodic=periodic,
                                    method=method)
        return normalised_height_error(result.height, truth)

    assert error() < target
    monkeypatch.setattr(shading, "LOW_SLANT_MAX_DEG", 0.0)
    assert error() > 0.3


def test_a_small_plain_images_finest_level_weakens_the_flat_prior(monkeypatch):
    # Random bumps of 256 px as a plain image lit at 15° (seed 7), on the narrow margin it was
    # measured with: with the flat-on-average prior at full weight on the finest level the
    # error was 0.322, above the issue's 30 %; weakened by (256 / PLAIN_FINE_PRIOR_PX)², the
    # thin plate sets the lines' offsets: 0.250. (On the texture's margin: 0.298 and 0.235.)
    monkeypatch.setattr(shading, "TEXTURE_MARGIN", shading.PLAIN_MARGIN)
    truth = ts.random_bumps((256, 256), PX, seed=7)
    light = Light(15.0, 30.0)
    img = render_lambertian(truth, PX, light, 0.8, periodic=False)

    def error():
        result = shape_from_shading(img, pixel_size_um=PX, light=light, periodic=False)
        return normalised_height_error(result.height, truth)

    assert error() < 0.3
    monkeypatch.setattr(shading, "PLAIN_FINE_PRIOR_PX", 1)  # full weight
    assert error() > 0.3


def test_the_fine_prior_factor_scales_the_finest_levels_prior():
    # energy() charges the finest level's prior at lowfreq_weight x lowfreq_fine_factor, as
    # solve_variational's finest level does.
    from haptex_compile.shading_variational import energy

    rows, cols, data = 160, 160, (128, 128)
    w, img = _plain_domain((rows, cols), data)
    z = np.random.default_rng(3).standard_normal((rows, cols)).astype(np.float32)
    light = Light(30.0, 70.0).vector
    base = energy(img, w, light, 0.8, z)
    half = energy(img, w, light, 0.8, z, data_shape=data, lowfreq_weight=0.3, lowfreq_fine_factor=0.5)
    same = energy(img, w, light, 0.8, z, data_shape=data, lowfreq_weight=0.15)
    assert half - base == pytest.approx(same - base, rel=1e-5)
    assert half - base > 0


def test_coarse_levels_of_a_plain_image_hold_its_plane(monkeypatch):
    # Random bumps of 512 px lit at 45° (light given), whose plane through the image slopes by
    # 3e-4 px / px at a quarter of the resolution: with the plane term's usual weight the
    # quarter-resolution level came out sloping 0.005 towards the light (18 x), which the
    # finer levels then had to remove; with COARSE_PLANE_FACTOR the coarse levels hold it.
    import haptex_compile.shading_variational as sv

    # The coarse levels with the prior run in a forked child beside their test without it:
    # here, in this process, where the spy sees them (the same heights).
    monkeypatch.setattr(sv, "CHECK_PROCESSES", 1)
    default = shading.COARSE_PLANE_FACTOR
    n, light = 512, Light(45.0, 200.0)
    truth = ts.random_bumps((n, n), PX, seed=5)
    img = render_lambertian(truth, PX, light, 0.8, periodic=False)
    towards = light.vector[:2] / np.hypot(*light.vector[:2])

    def plane_slope(z, w):  # the data-weighted least-squares plane's slope (px / px)
        yy, xx = np.mgrid[: z.shape[0], : z.shape[1]]
        m = w > 0
        design = np.column_stack([np.ones(m.sum()), xx[m], yy[m]])
        return np.linalg.lstsq(design, z[m], rcond=None)[0][1:]

    quarter = truth.reshape(n // 4, 4, n // 4, 4).mean(axis=(1, 3)) / (4 * PX)
    true_slope = float(np.hypot(*plane_slope(quarter, np.ones_like(quarter))))
    assert true_slope < 5e-4

    def slopes_along_light(factor):
        monkeypatch.setattr(shading, "COARSE_PLANE_FACTOR", factor)
        solve, found = sv._Problem.solve, {}

        def spy(self, z, *args, **kwargs):
            out = solve(self, z, *args, **kwargs)
            if self.lf is not None:  # the solve with the prior (not its test without it)
                found[self.shape[0]] = float(plane_slope(out[0], self.w) @ towards)
            return out

        monkeypatch.setattr(sv._Problem, "solve", spy)
        shape_from_shading(img, pixel_size_um=PX, light=light, periodic=False)
        monkeypatch.setattr(sv._Problem, "solve", solve)
        return found

    usual = slopes_along_light(1.0)
    quarter_side, *coarser = sorted(usual, reverse=True)[2:5]  # the domain's quarter, 1/8, 1/16
    assert usual[quarter_side] > 10 * true_slope
    held = slopes_along_light(default)
    assert max(abs(held[side]) for side in (quarter_side, *coarser)) < true_slope


def test_the_plane_term_is_left_out_where_the_data_span_no_area():
    # A coarse level of a mostly shadowed or masked image may keep a few pixels in one
    # column: no plane through them (its moments are singular), and no error.
    from haptex_compile.shading_variational import _Problem

    w = np.zeros((10, 9), np.float32)
    w[2:7, 4] = 0.1
    img = np.full(w.shape, 0.3, np.float32)
    lowfreq = (0.64, 2 * np.pi / 9.0)
    plane = _Problem(img, w, Light(60.0, 183.0).vector, 1e-3, 1, lowfreq, lowfreq_plane=0.1)
    plain = _Problem(img, w, Light(60.0, 183.0).vector, 1e-3, 1, lowfreq)
    v = np.random.default_rng(1).standard_normal(w.shape).astype(np.float32)
    assert np.array_equal(plane.lowfreq(v), plain.lowfreq(v))


def test_a_masked_plain_image_with_attached_shadows_is_solved():
    # Grazing-ish light on a weave casts attached shadows; with masked holes as well, the
    # coarsest levels keep almost no data (this crashed once on a singular plane fit).
    from scipy import ndimage

    tile = ts.woven_like((512, 512), PX)
    crop = (slice(40, 340), slice(60, 330))
    light = Light(60.0, 183.0)
    img = render_lambertian(tile, PX, light, 0.8, periodic=True)[crop]
    rng = np.random.default_rng(0)
    for _ in range(6):  # the sixth draw's holes (7.5 % of the pixels) reproduced the crash
        seeds = rng.random(img.shape) < 0.002
    mask = ~ndimage.binary_dilation(seeds, iterations=4)
    res = shape_from_shading(img, pixel_size_um=PX, light=light, periodic=False, mask=mask)
    assert np.all(np.isfinite(res.height))
    assert normalised_height_error(res.height, tile[crop]) < 0.2


@pytest.mark.parametrize("side", [4, 5, 7])
def test_a_plain_image_of_a_few_pixels_is_solved(side):
    # Its domain has one pyramid level, which is the flat prior's check level too: nothing is
    # left to solve after the check (this raised UnboundLocalError at e44aa9e). A Gaussian bump
    # lit from the side must come back as a bump: heights correlated with the true ones.
    y, x = np.mgrid[:side, :side] - (side - 1) / 2
    bump = 40.0 * np.exp(-(x**2 + y**2) / (2 * (side / 4) ** 2))
    light = Light(45.0, 30.0)
    res = shape_from_shading(render_lambertian(bump, PX, light, 0.8), pixel_size_um=PX, light=light,
                             periodic=False)
    assert res.height.shape == (side, side) and np.all(np.isfinite(res.height))
    assert np.corrcoef(res.height.ravel(), bump.ravel())[0, 1] > 0.5


def test_a_plain_texture_lit_along_the_image_axis_is_not_tilted():
    # Light along x: a tilt of the image along the light dims it uniformly, which the albedo
    # undoes. A 371 x 355 crop of random bumps came back tilted (mean slope along the light
    # 0.018 against the truth's 0.002, albedo 0.822 against 0.8, error 0.87) before the prior
    # held the data region's plane; now 0.15.
    tile = ts.random_bumps((512, 512), PX, seed=7)
    crop = (slice(36, 36 + 371), slice(54, 54 + 355))
    light = Light(60.0, 180.0)
    img = render_lambertian(tile, PX, light, 0.8, periodic=True)[crop]
    h = tile[crop]
    res = shape_from_shading(img, pixel_size_um=PX, light=light, periodic=False)
    along = -float(np.mean(np.gradient(res.height / PX, axis=1)))
    want = -float(np.mean(np.gradient(h / PX, axis=1)))
    assert abs(along - want) < 0.003
    assert res.albedo == pytest.approx(0.8, rel=0.01)
    assert normalised_height_error(res.height, h) < 0.3


def test_level_edges_are_told_from_a_texture_filling_the_image():
    # A sphere cap on flat ground: its image's edges are the ground's uniform shading (noise
    # of sigma 0.03 too, which the blur averages out); a texture's edges vary.
    rng = np.random.default_rng(0)
    light = Light(45.0, 200.0)
    cap = render_lambertian(ts.sphere_cap((256, 256), PX), PX, light, 0.8, periodic=False)
    assert shading.level_edge_fraction(cap) == 1.0
    assert shading.level_edge_fraction(np.clip(cap + rng.normal(0, 0.03, cap.shape), 0, 1)) > 0.8
    for h in (ts.woven_like((256, 256), PX), ts.random_bumps((256, 256), PX, seed=1)):
        img = render_lambertian(h, PX, light, 0.8, periodic=True)[13:237, 19:243]
        assert shading.level_edge_fraction(img) < shading.LEVEL_EDGE_FRACTION / 2
    assert shading.level_edge_fraction(cap, np.zeros(cap.shape, bool)) == 0.0
    # Each gets its margin: 256 + 8 % -> 288 px; 256 + 15 % = 294 -> 300.
    sides = [shading._solve_domain(img, np.ones(img.shape, bool), _censored_pixels(img), False)[0].shape[0]
             for img in (cap, render_lambertian(ts.woven_like((256, 256), PX), PX, light, 0.8, periodic=False))]
    assert sides == [288, 300]


def test_a_textures_crop_is_solved_with_free_edges(monkeypatch):
    # The plain weave's 224 px crop lit at 15°: on the narrow margin the smooth join across it
    # pulled the top and left edges' rows about one RMS height off (error 0.289); the
    # texture's wider margin frees them (0.146).
    woven, crop = ts.woven_like((256, 256), PX), np.s_[13:237, 19:243]
    truth = woven[crop]
    light = Light(15.0, 30.0)
    img = render_lambertian(woven, PX, light, 0.8, periodic=True)[crop]
    wide = shape_from_shading(img, pixel_size_um=PX, light=light, periodic=False)
    monkeypatch.setattr(shading, "TEXTURE_MARGIN", shading.PLAIN_MARGIN)
    narrow = shape_from_shading(img, pixel_size_um=PX, light=light, periodic=False)
    assert normalised_height_error(wide.height, truth) < 0.2 < 0.25 < normalised_height_error(narrow.height, truth)


def test_plain_image_domain_halves_to_fast_fft_sizes():
    # The embedding domain holds the image and its margin, and halves to sizes with only the
    # factors 2, 3 and 5 down to FAST_HALF_PX or so (1024 px: 1152, not 1125 -> 562 = 2 x 281).
    def smooth(n):
        for f in (2, 3, 5):
            while n % f == 0:
                n //= f
        return n == 1

    for side in (100, 256, 1000, 1024, 3000):
        img = np.full((side, side // 2 + 7), 0.5)
        dom, _, kwargs = shading._solve_domain(img, np.ones(img.shape, bool), _censored_pixels(img), False)
        assert kwargs["data_shape"] == img.shape
        for n, data in zip(dom.shape, img.shape):
            assert n >= data + max(8, int(0.08 * side))
            assert smooth(n)
            while n >= 2 * shading.FAST_HALF_PX:  # its half is a level above FAST_HALF_PX
                assert n % 2 == 0 and smooth(n // 2), (side, dom.shape)
                n //= 2


@pytest.mark.parametrize("bounded", [True, False])
def test_the_albedo_is_bounded_by_the_brightest_pixels_over_cos_slant(monkeypatch, bounded):
    # A surface's extremum has slope 0 and shading albedo x cos(slant), so the albedo is at
    # most the brightest pixels' level over cos(slant). A plain weave lit at 60° on a 320 px
    # domain (a 256 px image with a 25 % margin), solved without the flat-on-average prior,
    # runs away without that bound: a steep surface under 3 x the true albedo.
    monkeypatch.setattr(shading, "TEXTURE_MARGIN", 0.25)
    monkeypatch.setattr(shading, "LOWFREQ_WEIGHT", 0.0)
    if not bounded:
        monkeypatch.setattr(shading, "ALBEDO_SLACK", np.inf)
    h = ts.woven_like((256, 256), PX)
    light = Light(60.0, 300.0)
    img = render_lambertian(h, PX, light, 0.8, periodic=False)
    dom, _, _ = shading._solve_domain(img, np.ones(img.shape, bool), _censored_pixels(img), False)
    assert dom.shape == (320, 320)
    res = shape_from_shading(img, pixel_size_um=PX, light=light, periodic=False)
    bound = 1.1 * np.percentile(img, 99.9) / np.cos(np.deg2rad(60.0))
    if bounded:
        assert res.albedo <= bound * (1 + 1e-6)
    else:  # the failure the bound removes (if the solver stops running away here, this case
        # no longer tests the bound: find another)
        assert res.albedo > 1.2 * bound


# ----------------------------------------------------------------------------- stability


def _no_runaway(res: SfsResult, truth: np.ndarray) -> None:
    assert np.all(np.isfinite(res.height))
    # Slopes stay physical: at most a few times the truth's (runaway inversions reach 1e3+).
    assert _slope_rms(res.height) < 5.0 * _slope_rms(truth) + 0.5


@pytest.mark.parametrize("kind, slope, falls_back", [("ramp", 40.0, False), ("ramp", 60.0, True), ("nan", 0.0, True)])
def test_a_runaway_solve_falls_back_to_a_flat_height(kind, slope, falls_back, monkeypatch):
    # The driver's last guard: heights with a non-finite value or a slope above 50 (pixel
    # units) are replaced by a flat height, warned of and named in the method; below that
    # the solver's heights pass through.
    from haptex_compile import shading_variational

    n = 32
    x = np.arange(n, dtype=np.float32)
    z = np.tile(slope * x, (n, 1)).astype(np.float32)  # slope px per px along x
    if kind == "nan":
        z[5, 7] = np.nan
    monkeypatch.setattr(shading_variational, "solve_variational", lambda *a, **k: (z.copy(), 0.8))
    img = np.full((n, n), 0.5) + 0.1 * np.sin(2 * np.pi * x / 8)[None, :]
    res = shape_from_shading(img, pixel_size_um=PX, light=Light(45.0, 30.0), periodic=True)
    assert np.all(np.isfinite(res.height))
    ran_away = any("ran away" in w for w in res.warnings)
    assert ran_away == falls_back
    assert res.method.endswith("+flat-fallback") == falls_back
    if falls_back:
        assert np.all(res.height == 0.0)
    else:
        # the ramp, in µm, mean 0
        np.testing.assert_allclose(np.diff(res.height, axis=1), slope * PX, rtol=1e-6)


def test_light_straight_above_warns_and_falls_back(bumps128):
    light = Light(0.0, 0.0)
    img = render_lambertian(bumps128, PX, light, 0.8, periodic=True)
    res = shape_from_shading(img, pixel_size_um=PX, light=light, periodic=True)
    _no_runaway(res, bumps128)
    assert "fell back" in " ".join(res.warnings) and "view axis" in " ".join(res.warnings)
    assert res.method != "default"
    ts_res = shape_from_shading(img, pixel_size_um=PX, light=light, method="tsai-shah")
    assert any("df/dZ" in w for w in ts_res.warnings)


def test_grazing_light_is_stable_and_warned(bumps128):
    light = Light(80.0, 45.0)
    img = render_lambertian(bumps128, PX, light, 0.8, periodic=True)
    assert (img <= 0.01).mean() > 0.05  # attached shadows are present
    res = shape_from_shading(img, pixel_size_um=PX, light=light, periodic=True)
    _no_runaway(res, bumps128)
    assert any("grazing" in w for w in res.warnings)
    assert normalised_height_error(res.height, bumps128) < 1.0


def test_light_along_a_tile_axis_or_diagonal_is_warned_and_solved_from_more_starts(surfaces256):
    # A wave of one cycle per tile along x has no slope along a light at tilt 90° or 270°:
    # the shading sees it only at second order. The directions across the tile-sized waves
    # (1, 0), (0, 1), (1, 1), (1, -1) are the axes and, for a w x h tile, the diagonals at
    # atan(h / w); within ALIGNED_TILT_DEG of them the result is warned of, and 3° further
    # the bench's random bumps at 60° come back within the issue's 30 % (measured 0.023
    # against 0.758 along the axis).
    from haptex_compile.shading_starts import ALIGNED_TILT_DEG, _tile_aligned_tilt

    assert _tile_aligned_tilt(271.0, (256, 256)) == ("y axis", 90.0)
    assert _tile_aligned_tilt(178.5, (256, 256)) == ("x axis", 0.0)
    assert _tile_aligned_tilt(226.0, (256, 256))[0] == "diagonal"
    assert _tile_aligned_tilt(314.0, (256, 256))[0] == "anti-diagonal"
    name, tilt = _tile_aligned_tilt(27.0, (128, 256))
    assert name == "diagonal" and tilt == pytest.approx(np.degrees(np.arctan(0.5)))
    assert _tile_aligned_tilt(45.0, (128, 256)) is None
    assert _tile_aligned_tilt(270.0 + ALIGNED_TILT_DEG, (256, 256)) is None

    # Along the x axis the plain weave's coarse levels set those waves wrong (measured 0.885
    # from one start); the start that holds them there has the lower energy and meets the
    # issue's 10 % (measured 0.063).
    from haptex_compile import shading_variational as sv

    light = Light(60.0, 0.0)
    woven = surfaces256["woven"]
    img = render_lambertian(woven, PX, light, 0.8, periodic=True)
    res = shape_from_shading(img, pixel_size_um=PX, light=light, periodic=True)
    assert normalised_height_error(res.height, woven) <= 0.10
    dom, w, kwargs = shading._solve_domain(img, shading.valid_pixels(img), _censored_pixels(img), True)
    one, a1 = sv.solve_variational(dom, w.astype(np.float32), light.vector, 0.8, **shading.DEFAULT_SOLVER, **kwargs)
    assert normalised_height_error(one.astype(float), woven) >= 0.5
    e = {k: sv.energy(dom, w.astype(np.float32), light.vector, a, z, dark=kwargs["dark"], bright=kwargs["bright"])
         for k, (z, a) in (("one start", (one, a1)), ("kept", (res.height / PX, res.albedo)))}
    assert e["kept"] < 0.8 * e["one start"]

    # Random bumps along the y axis: the coarse levels set the waves across the light wrong
    # from every pyramid start (measured 0.758 from one, 0.311 from the start held from
    # level 2); the full-resolution continuation (shading_starts._bare_tile_starts) meets the
    # issue's 30 % (measured 0.134).
    h = surfaces256["bumps"]
    for tilt, warned in ((270.0, True), (273.0, False)):
        light = Light(60.0, tilt)
        img = render_lambertian(h, PX, light, 0.8, periodic=True)
        res = shape_from_shading(img, pixel_size_um=PX, light=light, periodic=True)
        assert any("y axis" in w for w in res.warnings) == warned
        assert normalised_height_error(res.height, h) <= 0.30
        plain = shape_from_shading(img, pixel_size_um=PX, light=light, periodic=False)
        assert not any("axis" in w for w in plain.warnings)  # no periodic tile, no closed lines


def test_weave_starts_run_on_a_small_window_of_the_lattice_and_keep_its_shadows(monkeypatch):
    # A plain weave on a 16 px square lattice over a 208 px tile, lit at 60°, 3° off its
    # yarns: warned (sin 60° sin 3° = 0.045), and attached shadows. The full-resolution
    # starts run on the smallest periodic window of the lattice (64 px: 4 x 4 cells, no
    # strain) and are polished on the tile. The window is painted from the raw intensities:
    # from the domain image, whose shadowed pixels hold the mean, it came back at 0.759
    # (measured); from the raw ones at 0.038, as the starts on the whole tile (0.037).
    from haptex_compile.synth_images import weave_image

    truth = 40.0 * weave_image((208, 208), (16.0, 0.0), (0.0, 16.0), kind="plain")
    light = Light(60.0, 3.0)
    img = render_lambertian(truth, PX, light, 0.8, periodic=True)
    assert (img <= shading_image.DARK).mean() > 0.01  # attached shadows
    shapes = []
    fine = shading_starts._fine_starts
    monkeypatch.setattr(shading_starts, "_fine_starts", lambda im, *a: shapes.append(im.shape) or fine(im, *a))
    res = shape_from_shading(img, pixel_size_um=PX, light=light, periodic=True, weave_basis_px=np.diag([16.0, 16.0]))
    assert shapes == [(64, 64)]
    assert any("nearly along the weave direction" in w for w in res.warnings)
    assert normalised_height_error(res.height, truth) < 0.1

    # A window solution that does not repeat cell by cell (here: noise; the real photos'
    # depart by 32-100 %) is still transferred, as its cell average polished on the tile, and
    # the starts do not run on the whole tile: what the surface keeps is the cell average of
    # any solve, and there the transferred one fitted best (see _lowest_energy).
    def noisy(im, *a):
        shapes.append(im.shape)
        starts = fine(im, *a)
        if im.shape == (64, 64):
            noise = np.random.default_rng(0).standard_normal(im.shape).astype(np.float32)
            starts = [(noise, albedo) for _, albedo in starts]
        return starts

    shapes.clear()
    monkeypatch.setattr(shading_starts, "_fine_starts", noisy)
    again = shape_from_shading(img, pixel_size_um=PX, light=light, periodic=True, weave_basis_px=np.diag([16.0, 16.0]))
    assert shapes == [(64, 64)]
    assert np.all(np.isfinite(again.height))


def test_a_smoother_continuation_finds_a_weave_lit_near_overhead(monkeypatch):
    # A plain weave on a 16 px square lattice lit at 15°, 30° off its yarns: warned (15° off
    # the diagonal t1 + t2: sin 15° sin 15° = 0.067), and the energy has several minima close
    # in value. The continuation from a thin plate of weight 1e-2 (FINE_START_SMOOTH_LAMS)
    # reaches the truth's; without it the starts end in another (measured: 0.044 against 0.158
    # at 128 px; 0.039 against 0.153 at 256 px).
    from haptex_compile.synth_images import weave_image

    truth = 40.0 * weave_image((128, 128), (16.0, 0.0), (0.0, 16.0), kind="plain")
    light = Light(15.0, 30.0)
    img = render_lambertian(truth, PX, light, 0.8, periodic=True)
    basis = np.diag([16.0, 16.0])
    res = shape_from_shading(img, pixel_size_um=PX, light=light, periodic=True, weave_basis_px=basis)
    assert any("nearly along the weave direction at tilt 45.0°" in w for w in res.warnings)
    assert normalised_height_error(res.height, truth) < 0.08
    monkeypatch.setattr(shading_starts, "FINE_START_SMOOTH_LAMS", shading_starts.FINE_START_LAMS)
    without = shape_from_shading(img, pixel_size_um=PX, light=light, periodic=True, weave_basis_px=basis)
    assert normalised_height_error(without.height, truth) > 0.12


def test_a_weaves_solves_are_compared_by_the_energy_of_their_cell_averages():
    # The surface of a weave keeps the heights averaged over its lattice, so its solves are
    # ranked by their averages' energies. Plain weave on a 16 px lattice, 64 px tile: the truth
    # plus noise of zero mean in every cell (its cell average is the truth, energy near 0)
    # against the truth at 0.7 x its relief (it repeats, and fits worse than the truth but
    # better than the noisy heights).
    from haptex_compile.synth_images import weave_image

    truth = 40.0 * weave_image((64, 64), (16.0, 0.0), (0.0, 16.0), kind="plain")
    light = Light(45.0, 30.0)
    img = render_lambertian(truth, PX, light, 0.8, periodic=True).astype(np.float32)
    weight = np.ones(img.shape, np.float32)
    basis = np.diag([16.0, 16.0])
    z_true = (truth / PX).astype(np.float32)
    noise = np.random.default_rng(1).standard_normal(img.shape).astype(np.float32)
    noisy = z_true + noise - shading_starts._cell_average(noise, basis).synthetic.astype(np.float32)
    flatter = (0.7 * z_true).astype(np.float32)
    starts = [(flatter, 0.8), (noisy, 0.8)]
    assert shading_starts._lowest_energy(img, weight, light, {}, starts)[0] is flatter
    assert shading_starts._lowest_energy(img, weight, light, {}, starts, basis)[0] is noisy
    # A non-finite solve is never kept, and does not stop the others being averaged.
    starts.insert(0, (np.full_like(z_true, np.nan), 0.8))
    assert shading_starts._lowest_energy(img, weight, light, {}, starts)[0] is flatter
    assert shading_starts._lowest_energy(img, weight, light, {}, starts, basis)[0] is noisy


def test_a_weave_window_is_not_treated_as_lit_along_its_own_diagonal(monkeypatch):
    # A plain weave on a 16 px square lattice over a 96 x 208 px window, lit along the
    # window's diagonal (atan(96 / 208) = 24.8°), 20-25° from every weave direction
    # (sin 45° sin 20.2° = 0.24 at least): as a bare tile the diagonal is warned of and solved
    # from more starts; as a weave's window (weave_basis_px) neither, and the pyramid alone
    # recovers the weave (measured 0.019; 0.016 from the bare tile's starts).
    from haptex_compile.synth_images import weave_image

    truth = 40.0 * weave_image((96, 208), (16.0, 0.0), (0.0, 16.0), kind="plain")
    light = Light(45.0, float(np.degrees(np.arctan2(96, 208))))
    img = render_lambertian(truth, PX, light, 0.8, periodic=True)
    calls = []
    for name in ("_held_starts", "_bare_tile_starts", "_fine_starts"):
        starts = getattr(shading_starts, name)
        monkeypatch.setattr(shading_starts, name, lambda *a, _n=name, _f=starts: calls.append(_n) or _f(*a))
    bare = shape_from_shading(img, pixel_size_um=PX, light=light, periodic=True)
    assert any("diagonal" in w for w in bare.warnings) and calls == ["_bare_tile_starts"]
    calls.clear()
    weave = shape_from_shading(img, pixel_size_um=PX, light=light, periodic=True, weave_basis_px=np.diag([16.0, 16.0]))
    assert not weave.warnings and calls == []
    assert normalised_height_error(weave.height, truth) < 0.05


def test_saturated_and_black_pixels_are_masked_not_fitted(bumps128):
    light = Light(40.0, 100.0)
    clean = render_lambertian(bumps128, PX, light, 0.8, periodic=True)
    img = clean.copy()
    img[40:70, 40:90] = 0.0  # a black stain
    img[90:110, 10:40] = 1.0  # a specular (saturated) patch
    ok = valid_pixels(img)
    assert not ok[50, 50] and not ok[100, 20] and ok[5, 5]
    res = shape_from_shading(img, pixel_size_um=PX, light=light, periodic=True)
    _no_runaway(res, bumps128)
    assert any("no slope information" in w for w in res.warnings)
    # The stain's values are not fitted: the height there is as smooth as elsewhere.
    inside = res.height[45:65, 45:85]
    assert np.std(np.diff(inside, 2, axis=1)) < 3 * np.std(np.diff(res.height, 2, axis=1))


def test_black_regions_are_shadows_only_behind_a_terminator(bumps128):
    # Rendered attached shadows fade to black (a terminator); a stain cuts in sharply, and so
    # does a specular highlight; over-exposed shading rises to saturation continuously.
    sphere = ts.sphere_cap((128, 128), PX)
    img = render_lambertian(sphere, PX, Light(60.0, 300.0), 0.8, periodic=True)
    dark, bright = _censored_pixels(img)
    assert dark.sum() == (img <= 0.01).sum() > 100 and bright.sum() == 0
    img = render_lambertian(bumps128, PX, Light(40.0, 100.0), 0.8, periodic=True)
    img[40:70, 40:90] = 0.0
    img[90:110, 10:40] = 1.0
    img[:12, 100:] = 0.0  # a stain at the image's corner: its ring lies inside the image
    dark, bright = _censored_pixels(img)
    assert dark.sum() == 0 and bright.sum() == 0
    over = np.clip(render_lambertian(bumps128, PX, Light(40.0, 100.0), 1.0, periodic=True) * 1.25, 0, 1)
    assert _censored_pixels(over)[1].sum() == (over >= 0.99).sum() > 1000


@pytest.mark.parametrize("censored", [True, False])
def test_attached_shadows_face_away_from_the_light(monkeypatch, censored):
    # The one-sided shadow term: where the image is an attached shadow, the recovered
    # surface must not face the light (albedo R <= 0.01 within rounding). Without the term
    # the shadow is only filled smoothly and part of it faces the light (measured 2.6 %).
    monkeypatch.setattr(shading_image, "CENSORED", censored)
    sphere = ts.sphere_cap((128, 128), PX)
    light = Light(60.0, 300.0)
    img = render_lambertian(sphere, PX, light, 0.8, periodic=True)
    shadow = img <= 0.01
    res = shape_from_shading(img, pixel_size_um=PX, light=light, periodic=True)
    lit = res.albedo * reflectance(res.height / PX, light.vector)[shadow]
    facing_away = float(np.mean(lit <= 0.02))
    error = normalised_height_error(res.height, sphere)
    if censored:
        assert facing_away >= 0.99 and error <= 0.03
    else:
        assert facing_away < 0.99


@pytest.mark.parametrize("censored", [True, False])
def test_over_exposed_pixels_are_a_lower_bound(bumps128, monkeypatch, censored):
    monkeypatch.setattr(shading_image, "CENSORED", censored)
    light = Light(40.0, 100.0)
    img = np.clip(render_lambertian(bumps128, PX, light, 1.0, periodic=True) * 1.25, 0, 1)
    over = img >= 0.99
    res = shape_from_shading(img, pixel_size_um=PX, light=light, periodic=True)
    model = res.albedo * reflectance(res.height / PX, light.vector)[over]
    assert (float(np.mean(model >= 0.98)) >= 0.95) == censored


def test_flat_image_gives_flat_height_with_warning():
    img = np.full((64, 64), 0.6)
    for light in (Light(30.0, 0.0), None):
        res = shape_from_shading(img, pixel_size_um=PX, light=light)
        assert np.all(res.height == 0.0)
        assert any("no usable shading" in w for w in res.warnings)


def test_noise_degrades_gracefully(bumps128):
    light = Light(40.0, 100.0)
    clean = render_lambertian(bumps128, PX, light, 0.8, periodic=True)
    rng = np.random.default_rng(1)
    errs = []
    for sigma in (0.005, 0.02):
        img = np.clip(clean + rng.normal(0, sigma, clean.shape), 0, 1)
        res = shape_from_shading(img, pixel_size_um=PX, light=light, periodic=True)
        _no_runaway(res, bumps128)
        errs.append(normalised_height_error(res.height, bumps128))
    # 0.5 % noise is harmless; 2 % (SNR about 6 on this image's contrast) stays useful.
    assert errs[0] < 0.15 and errs[1] < 0.35


def test_noise_estimate_and_the_albedo_bound():
    # The albedo's lower bound is the 99.9th percentile of the brightest pixels: on a flat
    # grey 0.5 with Gaussian noise sigma that is 0.5 + 3.09 sigma; less 3.09 times the
    # estimated noise, 0.5. Smooth noise-free shading estimates (nearly) no noise.
    from haptex_compile.shading_variational import _Problem, _noise_sigma

    sigma = 0.01
    img = (0.5 + np.random.default_rng(0).normal(0, sigma, (256, 256))).astype(np.float32)
    w = np.ones_like(img)
    assert _noise_sigma(img, w) == pytest.approx(sigma, rel=0.03)
    raw = _Problem(img, w, np.array([0.0, 0.0, 1.0]), 1e-4, 1).albedo_min
    lowered = _Problem(img, w, np.array([0.0, 0.0, 1.0]), 1e-4, 1, bound_noise_sigmas=3.09).albedo_min
    assert raw == pytest.approx(0.5 + 3.09 * sigma, abs=0.2 * sigma)
    assert lowered == pytest.approx(0.5, abs=0.2 * sigma)
    smooth = render_lambertian(ts.sphere_cap((128, 128), PX), PX, Light(30.0, 120.0), 0.8, periodic=True)
    assert _noise_sigma(smooth.astype(np.float32), np.ones_like(smooth, np.float32)) < 1e-4


def test_noise_does_not_raise_the_albedo_at_a_low_slant(bumps128, monkeypatch):
    # At a low slant the albedo sits at its bound; with the raw percentile, noise of 1 %
    # raises it by 3 % and the relief absorbs that (measured 0.30 against 0.13 here).
    light = Light(15.0, 30.0)
    clean = render_lambertian(bumps128, PX, light, 0.8, periodic=True)
    img = np.clip(clean + np.random.default_rng(1).normal(0, 0.01, clean.shape), 0, 1)
    errs = {}
    for sigmas in (3.09, 0.0):
        monkeypatch.setitem(shading.DEFAULT_SOLVER, "bound_noise_sigmas", sigmas)
        res = shape_from_shading(img, pixel_size_um=PX, light=light, periodic=True)
        errs[sigmas] = normalised_height_error(res.height, bumps128)
    assert errs[3.09] <= 0.2 < errs[0.0]


def test_nan_and_integer_images_are_handled(bumps128):
    light = Light(45.0, 200.0)
    img = render_lambertian(bumps128, PX, light, 0.8, periodic=True)
    img8 = np.round(img * 255).astype(np.uint8)
    res8 = shape_from_shading(img8, pixel_size_um=PX, light=light, periodic=True)
    assert normalised_height_error(res8.height, bumps128) < 0.15  # 8-bit quantisation
    img_nan = img.copy()
    img_nan[3, 4] = np.nan
    res = shape_from_shading(img_nan, pixel_size_um=PX, light=light, periodic=True)
    assert np.all(np.isfinite(res.height))
    assert any("non-finite" in w for w in res.warnings)


def test_the_light_is_estimated_on_a_small_image_with_nan_pixels():
    # Images at most the light search's sizes are not reduced; their non-finite pixels
    # (weight 0) made every misfit NaN and the search fail (IndexError).
    h = ts.random_bumps((80, 80), PX, seed=3)
    img = render_lambertian(h, PX, Light(45.0, 200.0), 0.8, periodic=True)
    img[np.random.default_rng(0).random(img.shape) < 0.05] = np.nan
    res = shape_from_shading(img, pixel_size_um=PX, periodic=True)  # the light estimated in it
    assert abs(res.light.slant_deg - 45.0) <= 2.0
    assert tilt_axis_difference_deg(res.light.tilt_deg, 200.0) <= 2.0
    assert normalised_height_error(res.height, h) < 0.05


def test_bad_parameters_raise_value_error(bumps128):
    img = np.full((16, 16), 0.5)
    with pytest.raises(ValueError, match="2-D"):
        shape_from_shading(np.zeros((4, 4, 3)), pixel_size_um=PX)
    with pytest.raises(ValueError, match="pixel_size_um"):
        shape_from_shading(img, pixel_size_um=0.0)
    with pytest.raises(ValueError, match="method"):
        shape_from_shading(img, pixel_size_um=PX, method="magic")
    with pytest.raises(ValueError, match="slant"):
        Light(95.0, 0.0)
    with pytest.raises(ValueError, match="mask shape"):
        shape_from_shading(img, pixel_size_um=PX, mask=np.ones((3, 3), bool))


# ----------------------------------------------------------------------------- light estimation


def test_estimated_light_on_bumps_and_its_cost(bumps128):
    light = Light(45.0, 200.0)
    img = render_lambertian(bumps128, PX, light, 0.8, periodic=True)
    # The light estimated inside shape_from_shading (the same search as estimate_light's).
    found = shape_from_shading(img, pixel_size_um=PX, periodic=True)
    est, albedo = found.light, found.albedo
    # The sign of the tilt is unobservable: compare axes, and check the stated convention.
    axis_err = tilt_axis_difference_deg(est.tilt_deg, light.tilt_deg)
    assert axis_err < 3.0
    assert np.sin(np.deg2rad(est.tilt_deg)) <= 1e-9  # light from the top of the image
    assert abs(est.slant_deg - 45.0) < 5.0
    assert est.slant_sd_deg > 0 and est.tilt_sd_deg > 0
    assert albedo == pytest.approx(0.8, rel=0.05)
    given = shape_from_shading(img, pixel_size_um=PX, light=light, periodic=True)
    assert any("light estimated" in w for w in found.warnings)
    # Target: at most 5 points worse with the light estimated.
    e_given = normalised_height_error(given.height, bumps128)
    e_found = normalised_height_error(found.height, bumps128)
    assert e_found <= e_given + 0.05


@pytest.mark.parametrize("name, slant, tilt", [("woven", 30.0, 120.0), ("sphere", 45.0, 200.0)])
def test_estimated_light_costs_at_most_five_points(name, slant, tilt):
    # Joint light-and-shape estimation on the non-Gaussian surfaces that defeat moment
    # estimators: the estimate lies within its stated uncertainty (3 sd) of the truth (tilt
    # modulo 180°), and the height error grows by at most 5 points (the issue's target).
    shape = (128, 128)
    h = ts.woven_like(shape, PX) if name == "woven" else ts.sphere_cap(shape, PX)
    light = Light(slant, tilt)
    img = render_lambertian(h, PX, light, 0.8, periodic=True)
    est, _ = estimate_light(img)
    axis_err = tilt_axis_difference_deg(est.tilt_deg, tilt)
    assert abs(est.slant_deg - slant) <= 3.0 * est.slant_sd_deg
    assert axis_err <= 3.0 * est.tilt_sd_deg
    given = shape_from_shading(img, pixel_size_um=PX, light=light, periodic=True)
    found = shape_from_shading(img, pixel_size_um=PX, light=est, periodic=True)
    e_given = normalised_height_error(given.height, h)
    assert normalised_height_error(found.height, h) <= e_given + 0.05


def test_light_search_keeps_the_fine_detail_of_fractal_images():
    # Averaged to 96 px, the shading of a 256 px Brownian surface (H = 0.7) loses a third of
    # its variance and is no longer the shading of any surface: its misfit's knee sat at 40°
    # for a 15° light. The final stage then works at full detail.
    h = ts.brownian_surface((256, 256), PX, hurst=0.7, seed=2)
    light = Light(15.0, 30.0)
    img = render_lambertian(h, PX, light, 0.8, periodic=True)
    assert shading_light._reduction_loss(img, valid_pixels(img), shading_light.SEARCH_SIDE_PX) > 0.2
    est, _ = estimate_light(img)
    assert abs(est.slant_deg - 15.0) <= 3.0
    assert tilt_axis_difference_deg(est.tilt_deg, 30.0) <= 5.0


def test_block_average_uses_whole_blocks():
    img = np.random.default_rng(0).random((256, 256))
    small, w = shading_light._block_average(img, np.ones(img.shape, bool), 192)
    assert small.shape == (128, 128) and np.all(w == 1)
    np.testing.assert_allclose(small, img.reshape(128, 2, 128, 2).mean(axis=(1, 3)), rtol=1e-6)


def test_light_search_on_an_oblique_lattice_relief():
    # A smooth relief on an oblique 16 px lattice (photo-like cells), lit at 45°, 200°: the
    # final stage on an image averaged over 1.33 px blocks (192 of 256 px) settled 140° off in
    # tilt (height error 0.79); on whole blocks (here the full image) it finds the light.
    from haptex_compile.synth_images import lattice_relief

    h = lattice_relief((256, 256), (16, 0), (4, 16), amplitude_um=12.0)
    light = Light(45.0, 200.0)
    img = render_lambertian(h, PX, light, 0.8, periodic=True)
    est, _ = estimate_light(img)
    assert abs(est.slant_deg - 45.0) <= 3.0
    assert tilt_axis_difference_deg(est.tilt_deg, 200.0) <= 3.0
    found = shape_from_shading(img, pixel_size_um=PX, light=est, periodic=True)
    assert normalised_height_error(found.height, h) <= 0.05


def test_light_search_ends_on_the_whole_tile():
    # The misfits that separate lights are far below the 5 % of variance a 2 x 2 block average
    # loses: with the final stage on the 128 px average, the sphere cap lit at 30°, 120° cost
    # 0.031 of height error over the given light; on the whole 256 px tile, 0.006.
    h = ts.sphere_cap((256, 256), PX)
    light = Light(30.0, 120.0)
    img = render_lambertian(h, PX, light, 0.8, periodic=True)
    given = shape_from_shading(img, pixel_size_um=PX, light=light, periodic=True)
    found = shape_from_shading(img, pixel_size_um=PX, periodic=True)
    assert abs(found.light.slant_deg - 30.0) <= 1.0
    assert tilt_axis_difference_deg(found.light.tilt_deg, 120.0) <= 1.5
    e_given = normalised_height_error(given.height, h)
    assert normalised_height_error(found.height, h) <= e_given + 0.015


def test_a_larger_tiles_light_is_searched_again_at_full_resolution(monkeypatch):
    # A 512 px plain weave lit at 15°, 30°: averaged to 256 px, its crossings blur and the
    # final stage settled at 19.5°, 200° (10° of tilt off; height error 0.39 against 0.05
    # with the light given). At full resolution the true light's misfit is the lower, and the
    # search finds it.
    h = ts.woven_like((512, 512), PX)
    img = render_lambertian(h, PX, Light(15.0, 30.0), 0.8, periodic=True)
    full, final = shading_light.FULL_SIDE_PX, shading_light.FINAL_SIDE_PX
    # The final stage's light is what the search returns without the full-resolution stage
    # (FULL_SIDE_PX = FINAL_SIDE_PX): it is taken here on its way out of the one search.
    stage_lights = []
    well_below = shading_light._well_below_the_bound
    monkeypatch.setattr(shading_light, "_well_below_the_bound",
                        lambda *a: stage_lights.append(well_below(*a)) or stage_lights[-1])
    lights = {full: estimate_light(img)[0]}
    (at_final,) = stage_lights
    lights[final] = Light(at_final.slant, at_final.tilt)
    assert abs(lights[full].slant_deg - 15.0) <= 1.0
    assert tilt_axis_difference_deg(lights[full].tilt_deg, 30.0) <= 1.5
    assert tilt_axis_difference_deg(lights[final].tilt_deg, 30.0) > 5.0
    # The light kept fits the full image better than the averaged stage's.
    fit = shading_light._misfit_function(img, valid_pixels(img), _censored_pixels(img), 512,
                                         shading_light._block_average)
    misfit = {side: fit(light.slant_deg, light.tilt_deg)[0] for side, light in lights.items()}
    assert misfit[full] < misfit[final]


@pytest.mark.parametrize("side, periodic, full", [
    (300, True, True), (300, False, False), (shading_light.PLAIN_FULL_ABOVE_PX, False, False),
    (shading_light.PLAIN_FULL_ABOVE_PX + 1, False, True), (shading_light.FINAL_SIDE_PX, True, False)])
def test_the_full_resolution_stage_is_set_up_for_tiles_and_large_plain_images(monkeypatch, side, periodic, full):
    # The stage runs on tiles larger than the final image, and on plain images only above
    # PLAIN_FULL_ABOVE_PX (below, it bought nothing at twice the time). The search is stopped
    # once its stages are set up: no light is solved.
    import types

    class Stop(Exception):
        pass

    sides = []

    def misfit_function(img, valid, censored, side_px, *args, **kwargs):
        sides.append(side_px)
        return types.SimpleNamespace(looser=None)

    def stop(*args, **kwargs):
        raise Stop

    monkeypatch.setattr(shading_light, "_misfit_function", misfit_function)
    monkeypatch.setattr(shading_light, "forked_map", stop)
    img = render_lambertian(ts.random_bumps((side, side // 2), PX, seed=1), PX, Light(45.0, 200.0), 0.8,
                            periodic=True)
    with pytest.raises(Stop):
        estimate_light(img, periodic=periodic)
    assert (shading_light.FULL_SIDE_PX in sides) == full
    assert sides[:2] == [shading_light.SEARCH_SIDE_PX, shading_light.FINAL_SIDE_PX]


def test_a_steep_light_held_by_the_albedo_bound_is_searched_again_under_a_looser_one(monkeypatch):
    # Random bumps (RMS slope 0.2) lit at 60°: no normal comes within 35° of the light, so the
    # search's albedo bound I_top / cos 35° lies below the true albedo (0.8) and the true light
    # cannot fit; the search stopped where the bound bit (57.5°, flagged). Under the looser
    # bound (cos 45°) the misfit's well is at the true slant.
    h = ts.random_bumps((128, 128), PX, seed=1)
    truth = Light(60.0, 300.0)
    img = render_lambertian(h, PX, truth, 0.8, periodic=True)
    assert np.percentile(img, 99.9) / shading_light.ALIGN_COS < 0.8
    found, _ = estimate_light(img)
    monkeypatch.setattr(shading_light, "STEEP_ALIGN_COS", None)
    tight, _ = estimate_light(img)
    assert tight.albedo_at_bound and tight.slant_deg <= 58.0
    assert found.albedo_at_bound  # still flagged: the looser bound is an assumption too
    assert abs(found.slant_deg - 60.0) <= 0.5
    assert tilt_axis_difference_deg(found.tilt_deg, 300.0) <= 1.0
    given = shape_from_shading(img, pixel_size_um=PX, light=truth, periodic=True)
    e_given = normalised_height_error(given.height, h)
    e_found = normalised_height_error(shape_from_shading(img, pixel_size_um=PX, light=found, periodic=True).height, h)
    e_tight = normalised_height_error(shape_from_shading(img, pixel_size_um=PX, light=tight, periodic=True).height, h)
    assert e_found <= e_given + 0.02 < e_tight


def test_light_search_gives_the_same_light_in_worker_processes(monkeypatch):
    # The candidate lights are solved side by side in forked workers (SEARCH_PROCESSES); each
    # solve is independent of the others, so the estimate is the same bit for bit. A lattice
    # lit at 15° takes every step of the search: the slant grid, the tilt polish and scan,
    # the compass searches, the tilt sweep and the search below the plateau.
    import sys

    from haptex_compile import shading_variational
    from haptex_compile.synth_images import lattice_relief

    img = render_lambertian(lattice_relief((128, 128), (16, 0), (0, 16), amplitude_um=12.0), PX,
                            Light(15.0, 30.0), 0.8, periodic=True)
    solve = shading_variational.solve_variational
    found, here = {}, {}
    for processes in (1, 2):
        calls = []  # the solves run in this process (a worker's calls are its own)
        monkeypatch.setattr(shading_variational, "solve_variational", lambda *a, **k: calls.append(1) or solve(*a, **k))
        monkeypatch.setattr(shading_light, "SEARCH_PROCESSES", processes)
        found[processes] = estimate_light(img)
        here[processes] = len(calls)
    assert found[2] == found[1]
    assert found[1][0].albedo_at_bound  # the search below the plateau ran
    if sys.platform.startswith("linux"):
        # The solves ran in the workers, but for steps with a single new light, which run
        # here (measured: 1 of 208).
        assert here[2] < 0.1 * here[1]


def test_the_extra_starts_give_the_same_heights_in_worker_processes(monkeypatch, bumps128):
    # Lit along the tile's x axis: the held start and the two full-resolution continuations
    # run side by side in forked workers; the heights are the same bit for bit, and only the
    # main pyramid's solve runs here.
    import sys

    from haptex_compile import shading_variational

    light = Light(45.0, 180.0)
    img = render_lambertian(bumps128, PX, light, 0.8, periodic=True)
    solve = shading_variational.solve_variational
    heights, here = {}, {}
    for processes in (1, 2):
        calls = []
        monkeypatch.setattr(shading_variational, "solve_variational", lambda *a, **k: calls.append(1) or solve(*a, **k))
        monkeypatch.setattr(shading_light, "SEARCH_PROCESSES", processes)
        heights[processes] = shape_from_shading(img, pixel_size_um=PX, light=light, periodic=True).height
        here[processes] = len(calls)
    assert np.array_equal(heights[2], heights[1])
    # one pyramid, the held start and the continuations' steps of the thin plate's weight
    assert here[1] == 2 + len(shading_starts.FINE_START_LAMS) + len(shading_starts.FINE_START_SMOOTH_LAMS) == 7
    if sys.platform.startswith("linux"):
        assert here[2] == 1


def test_near_frontal_light_is_flagged_unreliable(bumps128):
    # Under near-frontal light the slant's misfit has no minimum the search can find: a
    # plateau of steep lights, each with the albedo at its bound, fits as well (bumps lit at
    # 5° come out at about 36°). The estimate says so; a well-posed one does not.
    img = render_lambertian(bumps128, PX, Light(5.0, 30.0), 0.8, periodic=True)
    found = shape_from_shading(img, pixel_size_um=PX, periodic=True)  # the light estimated in it
    est = found.light
    assert est.albedo_at_bound
    assert "UNRELIABLE" in shading.estimated_light_note(est)
    # Random bumps have no well below the plateau: the estimate falls back to the image
    # statistics' slant (lower than the plateau's), with a ± that spans the plateau and
    # covers the truth.
    stat, _ = estimate_light(img, refine=False)
    assert est.slant_deg == pytest.approx(stat.slant_deg) and est.slant_deg < 20.0
    assert abs(est.slant_deg - 5.0) <= est.slant_sd_deg and est.slant_deg + est.slant_sd_deg >= 30.0
    assert any("UNRELIABLE" in w for w in found.warnings)
    img = render_lambertian(bumps128, PX, Light(30.0, 30.0), 0.8, periodic=True)
    est, _ = estimate_light(img)
    assert abs(est.slant_deg - 30.0) <= 3.0 and not est.albedo_at_bound
    assert "UNRELIABLE" not in shading.estimated_light_note(est)
    assert not Light(5.0, 30.0).albedo_at_bound  # a given light is never flagged


def _lattice_estimate(side: int, t2, light: Light):
    """A smooth lattice relief (t1 = (16, 0), `t2`) of `side` px lit by `light`: the image, the
    estimated light, and the height errors with the light estimated and given."""
    from haptex_compile.synth_images import lattice_relief

    h = lattice_relief((side, side), (16, 0), t2, amplitude_um=12.0)
    img = render_lambertian(h, PX, light, 0.8, periodic=True)
    found = shape_from_shading(img, pixel_size_um=PX, periodic=True)
    given = shape_from_shading(img, pixel_size_um=PX, light=light, periodic=True)
    return img, found.light, normalised_height_error(found.height, h), normalised_height_error(given.height, h)


def _assert_near(est: Light, light: Light) -> None:
    """The estimate within 1° of slant and 2° of tilt axis of `light`."""
    assert abs(est.slant_deg - light.slant_deg) <= 1.0
    assert tilt_axis_difference_deg(est.tilt_deg, light.tilt_deg) <= 2.0


def test_light_search_sweeps_the_tilt_where_the_statistics_mislead():
    # A smooth relief on an oblique 16 px lattice lit at 15°, 30°: the lattice's own anisotropy
    # turns the image statistics' tilt axis to 179°, and the local searches from there settled
    # on a plateau 41° off (22°, 349°, flagged; height error 0.83). The tilt sweep at the first
    # knee finds the true light's well, where the albedo is free. (Whether the final stage's
    # compass search then stays in the well, unflagged, or first steps onto the plateau, whose
    # misfit on this image is lower still (3.2e-4 at 38°, 10.7° against 2.3e-3), and comes
    # back down to the well by the plateau search, flagged, turns on the last bits of the
    # solver's sums: unflagged on the Intel hosts, flagged on an AMD EPYC. The light is the
    # same.)
    truth = Light(15.0, 30.0)
    img, est, e_found, e_given = _lattice_estimate(256, (4, 16), truth)
    # Beyond the final stage's tilt scan:
    assert tilt_axis_difference_deg(shading_light._tilt_axis(img, valid_pixels(img))[0], 30.0) > shading_light.TILT_SCAN_DEG
    _assert_near(est, truth)
    assert e_found <= e_given + 0.02


def test_tilt_sweep_returns_only_a_deep_well():
    # A misfit with a well at tilt axis 100° (misfit 0.1 against 1 elsewhere), albedo free.
    def coarse(slant, tilt, well=0.1, bound=False):
        axis = tilt % 180.0
        e = well if abs(axis - 100.0) < 6.0 else 1.0
        return e, (2.0 if bound else 0.5)

    def misfit(fn):
        # the misfit function's attributes: its albedo bound, and nothing to solve ahead
        fn.at_bound, fn.prefetch = 1.0, lambda lights: None
        return fn

    swept = shading_light._swept_tilt(misfit(coarse), 30.0, 10.0)
    assert swept is not None and tilt_axis_difference_deg(swept, 100.0) < 6.0
    # A shallow well (above SWEEP_GAIN of the statistical tilt's misfit) is not trusted.
    assert shading_light._swept_tilt(misfit(lambda s, t: coarse(s, t, well=0.6)), 30.0, 10.0) is None
    # Lights whose albedo sits at the bound are not compared (the plateau fits anything).
    assert shading_light._swept_tilt(misfit(lambda s, t: coarse(s, t, bound=True)), 30.0, 10.0) is None


def test_light_below_the_plateau_is_found_on_a_lattice_relief():
    # A smooth square-lattice relief lit at 15°: the search's misfit is lowest on the plateau
    # of steep lights (38° at 256 px, flagged), but below it the true light's well is deep
    # and narrow. The search below the plateau finds it; the estimate stays flagged, with a ±
    # that spans the plateau.
    truth = Light(15.0, 30.0)
    _, est, e_found, e_given = _lattice_estimate(128, (0, 16), truth)
    assert est.albedo_at_bound
    _assert_near(est, truth)
    assert est.slant_sd_deg >= 15.0  # spans the plateau's 35-38°
    assert e_found <= e_given + 0.02


def test_the_well_below_the_plateau_is_also_searched_from_the_plateaus_tilt(monkeypatch):
    # A plain weave's periodic window (4 x 4 cells of 21 x 16.5 px, as the photo pipeline
    # paints) lit at 30°, 200°: the image statistics give 26.4°, 205.8°, the search ends on
    # the plateau (45.5°, 205.3°, flagged). At 26.4° the true light's well does not show, and
    # the 180° tilt scan there picks a tilt near the weave's axis, 186°, whose search below
    # the plateau stops in a side well (28.5°, 186°: 14° of tilt off); the plateau's own tilt
    # leads to the true light's well.
    from haptex_compile.synth_images import weave_image

    truth = Light(30.0, 200.0)
    img = render_lambertian(40.0 * weave_image((66, 84), (21.0, 0.0), (0.0, 16.5), kind="plain"), 20.0, truth, 0.8)
    est, _ = estimate_light(img)
    assert est.albedo_at_bound  # still flagged: the plateau fits as well
    _assert_near(est, truth)
    monkeypatch.setattr(shading_light, "PLATEAU_TILT_START", False)
    scan_only, _ = estimate_light(img)
    assert tilt_axis_difference_deg(scan_only.tilt_deg, truth.tilt_deg) > 10.0


def _bowl_misfit(centre, depth, width_deg, plateau=1.0, bound_above=None):
    """A misfit function as the light search's: a well of `depth` at light `centre` (slant,
    tilt) within `width_deg`, `plateau` elsewhere, the albedo at its bound (2.0 against 1.0)
    above slant `bound_above`; it records the lights it is asked for."""
    def fn(slant, tilt):
        fn.asked.append((slant, tilt))
        if bound_above is not None and slant > bound_above:
            return 0.5 * plateau, 2.0
        d = np.hypot(slant - centre[0], (tilt - centre[1] + 180.0) % 360.0 - 180.0)
        return (depth + 1e-3 * d if d < width_deg else plateau), 0.5

    fn.asked, fn.at_bound, fn.prefetch = [], 1.0, lambda lights: None
    return fn


def test_a_flagged_light_is_looked_at_again_below_its_bound(monkeypatch):
    # The search stopped at 50.5°, 310° with the albedo at the bound (a plateau of steep
    # lights); a narrow well at 30°, 300° with the albedo free fits better: it is found and
    # kept, unflagged, within the compass's last step.
    flagged = shading_light._LightFit(50.5, 310.0, 2.2, 1.0, 2.0, True)
    coarse = _bowl_misfit((30.0, 300.0), 0.05, 4.0, bound_above=45.0)
    final = _bowl_misfit((31.0, 299.0), 0.01, 4.0, bound_above=45.0)
    got = shading_light._well_below_the_bound(coarse, final, flagged)
    assert not got.at_bound and abs(got.slant - 31.0) <= 0.5 and abs(got.tilt - 299.0) <= 0.5
    assert all(s <= 50.5 for s, _ in final.asked)  # never steeper than the estimate
    # A well that does not fit the final image better than the estimate (0.5 there) is not taken.
    shallow = _bowl_misfit((31.0, 299.0), 0.6, 4.0, plateau=1.0, bound_above=45.0)
    assert shading_light._well_below_the_bound(coarse, shallow, flagged) is flagged
    # Nor is the look taken for an estimate whose albedo is free, or with WELL_CANDIDATES = 0.
    free = flagged._replace(albedo=0.5)
    assert shading_light._well_below_the_bound(coarse, final, free) is free
    monkeypatch.setattr(shading_light, "WELL_CANDIDATES", 0)
    assert shading_light._well_below_the_bound(coarse, final, flagged) is flagged


def test_the_compass_search_stops_where_the_misfit_is_flat():
    # Neighbours that only tie the centre do not move the walk (they used to, one after
    # another, for ever): the steps halve and it stops where it started.
    assert shading_light._compass(lambda a, b: 1.0, 30.0, 200.0, lambda lights: None) == (30.0, 200.0)
    # A slope it follows, no steeper than `top`, to the edge of the slants it may visit.
    s, t = shading_light._compass(lambda a, b: -a + 1e-3 * abs(b - 200.0), 30.0, 200.0, lambda lights: None, top=36.0)
    assert (s, t) == (36.0, 200.0)


def test_the_light_search_ends_on_a_flat_misfit():
    # A misfit that is the same for every light (finite, the albedo free): each walk of the
    # search halves its steps and stops (a tie used to move the tilt's walk, step after step,
    # for ever); the uncertainty is the widest.
    def flat(slant, tilt):
        return 1.0, 0.5

    flat.at_bound, flat.prefetch, flat.looser = 1.0, lambda lights: None, None
    knee, misfit, found = shading_light._search_light(flat, flat, False, 30.0, 200.0)
    assert (knee, misfit) == (5.0, 1.0)
    assert (found.slant_sd, found.tilt_sd) == (90.0, 90.0)
    assert not found.at_bound


def test_a_lattice_reliefs_flagged_light_is_replaced_by_the_well_below_it():
    # A smooth square-lattice relief lit at 45°, 200° (256 px): the search stopped at 47.5°,
    # 207° with the albedo at its bound (height error 0.22); below it, the true light's well.
    truth = Light(45.0, 200.0)
    _, est, e_found, e_given = _lattice_estimate(256, (0, 16), truth)
    assert not est.albedo_at_bound
    _assert_near(est, truth)
    # Within the issue's 5 points of the given light's (0.025 against 0.002; 0.224 without the look).
    assert e_found <= e_given + 0.05


def test_light_misfit_is_least_at_the_true_light_and_blind_to_the_tilts_sign(bumps128):
    # The search's ranking: the true light leaves the smallest misfit among lights a few
    # degrees off; a surface lit from t looks like the inverted one lit from t + 180°.
    light = Light(30.0, 120.0)
    img = render_lambertian(bumps128, PX, light, 0.8, periodic=True)
    true, at_bound = shading.light_misfit(img, light)
    assert not at_bound  # the relief has normals near the light: the albedo is free
    for s, t in ((25.0, 120.0), (35.0, 120.0), (30.0, 110.0), (30.0, 130.0)):
        assert shading.light_misfit(img, Light(s, t))[0] > 2 * true, (s, t)
    assert shading.light_misfit(img, Light(30.0, 300.0))[0] == pytest.approx(true, rel=1e-3)


def test_estimated_slant_follows_the_true_slant(bumps128):
    slants = []
    for s in (20.0, 40.0, 60.0):
        img = render_lambertian(bumps128, PX, Light(s, 300.0), 0.8, periodic=True)
        slants.append(estimate_light(img, refine=False)[0].slant_deg)
    assert slants[0] < slants[1] < slants[2]
    np.testing.assert_allclose(slants, [20.0, 40.0, 60.0], atol=6.0)


# ----------------------------------------------------------------------------- physical scale


def test_scale_relief_rms_and_peak_to_valley(bumps128):
    h = scale_relief(bumps128 * 0.123 + 5.0, 12.0, "rms")
    assert h.mean() == pytest.approx(0.0, abs=1e-9)
    assert np.sqrt(np.mean(h * h)) == pytest.approx(12.0, rel=1e-12)
    pv = scale_relief(bumps128, 80.0, kind="pv")
    assert pv.max() - pv.min() == pytest.approx(80.0, rel=1e-12)
    # Shape is kept exactly.
    assert normalised_height_error(pv, bumps128) < 1e-12
    # Kawabata's SMD is a mean absolute deviation: a ±1 square wave has MAD = RMS = 1.
    square = np.where((np.arange(64) // 8) % 2 == 0, 1.0, -1.0)[None, :] * np.ones((4, 1))
    np.testing.assert_allclose(scale_relief(square, 3.0, "mad"), 3.0 * square, rtol=1e-12)
    gauss = scale_relief(np.random.default_rng(2).normal(size=200_000), 1.0, "mad")
    assert np.sqrt(np.mean(gauss**2)) == pytest.approx(np.sqrt(np.pi / 2), rel=0.01)
    assert np.all(scale_relief(np.ones((4, 4)), 10.0) == 0.0)
    with pytest.raises(ValueError):
        scale_relief(bumps128, 10.0, kind="ra")
    with pytest.raises(ValueError):
        scale_relief(bumps128, -1.0)


# ----------------------------------------------------------------------------- test surfaces


def test_surface_generators_have_their_stated_properties():
    shape = (128, 128)
    sphere = ts.sphere_cap(shape, PX, rim_angle_deg=45.0, rim_round_um=0.0)
    gy, gx = np.gradient(sphere, PX)
    steepest = np.hypot(gx, gy).max()
    assert 0.8 < steepest < 1.6  # tan 45° = 1 at the rim, blurred by the kink's difference
    assert sphere.min() == 0.0
    # Rounding: the soft maximum lies above the sharp cap by at most c log 2, is smooth (no
    # slope above tan 45°) and keeps the apex height R (1 - cos 45°).
    c = 30.0
    rounded = ts.sphere_cap(shape, PX, rim_round_um=c)
    assert np.all(rounded >= sphere - 1e-9)
    assert np.max(rounded - sphere) <= c * np.log(2.0) + 1e-9
    gy, gx = np.gradient(rounded, PX)
    assert np.hypot(gx, gy).max() <= 1.0 + 1e-6
    radius = 0.4 * 128 * PX
    apex = radius / np.sin(np.pi / 4) * (1 - np.cos(np.pi / 4))
    assert rounded.max() == pytest.approx(apex, rel=0.01)
    assert ts.rms_slope(ts.random_bumps(shape, PX, slope_rms=0.2), PX) == pytest.approx(0.2)
    woven = ts.woven_like(shape, PX, thread_spacing_um=320.0)  # 32 px tile, 4 tiles across
    np.testing.assert_allclose(woven, np.roll(woven, 32, axis=0), atol=1e-9)
    np.testing.assert_allclose(woven, np.roll(woven, 32, axis=1), atol=1e-9)
    assert not np.allclose(woven, np.roll(woven, 16, axis=1))  # the tile is 2 threads


def test_brownian_surface_has_the_power_law_of_its_hurst_index():
    # Radially averaged power spectrum of fBm: |k|^-(2H + 2).
    n, hurst = 256, 0.7
    h = ts.brownian_surface((n, n), PX, hurst=hurst, seed=5)
    power = np.abs(np.fft.fft2(h)) ** 2
    k = np.hypot(*np.meshgrid(np.fft.fftfreq(n), np.fft.fftfreq(n)))
    bins = np.geomspace(4.0 / n, 0.25, 12)
    idx = np.digitize(k.ravel(), bins)
    centres, means = [], []
    for i in range(1, len(bins)):
        sel = idx == i
        if sel.any():
            centres.append(k.ravel()[sel].mean())
            means.append(power.ravel()[sel].mean())
    slope = np.polyfit(np.log(centres), np.log(means), 1)[0]
    assert slope == pytest.approx(-(2 * hurst + 2), abs=0.25)


# ----------------------------------------------------------------------------- real photo


@pytest.mark.shared
def test_real_fabric_photo_is_stable(shared_fabrics):
    import cv2

    paths = sorted(p for p in shared_fabrics.iterdir() if p.suffix.lower() in (".bmp", ".jpg"))
    img = cv2.imread(str(paths[0]), cv2.IMREAD_GRAYSCALE)
    assert img is not None
    crop = img[: min(256, img.shape[0]), : min(256, img.shape[1])]
    res = shape_from_shading(crop, pixel_size_um=PX)
    assert np.all(np.isfinite(res.height))
    assert _slope_rms(res.height) < 5.0
    assert 0.0 <= res.light.slant_deg <= 90.0


def test_weave_visibility_is_the_linear_shading_of_waves_across_each_weave_direction():
    # A wave across direction d is seen at first order in proportion to the light's component
    # along its wave vector: sin(slant) |sin(tilt - direction of d)|, the smallest over t1,
    # t2, t1 + t2 and t1 - t2 (the tilt's 180° ambiguity does not change it).
    from haptex_compile.shading import weave_visibility

    square = np.array([[16.0, 0.0], [0.0, 16.0]])
    assert weave_visibility(Light(30.0, 180.0), square) == pytest.approx((0.0, 0.0), abs=1e-12)
    v, d = weave_visibility(Light(30.0, 10.0), square)
    assert d == pytest.approx(0.0) and v == pytest.approx(0.5 * np.sin(np.deg2rad(10.0)))
    v, d = weave_visibility(Light(45.0, 22.5 + 180.0), square)  # halfway between t1 and t1 + t2
    assert v == pytest.approx(np.sin(np.deg2rad(45.0)) * np.sin(np.deg2rad(22.5)))
    v, d = weave_visibility(Light(60.0, 131.0), square)  # 4° from t2 - t1, the anti-diagonal
    assert d == pytest.approx(135.0) and v == pytest.approx(np.sin(np.deg2rad(60.0)) * np.sin(np.deg2rad(4.0)))
    oblique = np.array([[7.05, -11.25], [9.4, 6.3]])  # reduced: t1 + t2 is (-4.2, 15.7)
    v, d = weave_visibility(Light(30.0, np.degrees(np.arctan2(15.7, -4.2)) + 180.0), oblique)
    assert v == pytest.approx(0.0, abs=1e-12) and d == pytest.approx(np.degrees(np.arctan2(15.7, -4.2)))


def test_near_overhead_light_is_warned_of_as_such_not_as_along_a_weave_direction():
    # At slant 6°, sin(slant) = 0.105 < WEAVE_VISIBILITY_MIN: every weave direction's profiles
    # shade weakly whatever the tilt, and the warning names the slant (here the tilt is 20°
    # off t1, the nearest direction: sin 6° sin 20° = 0.036). At slant 30°, 2° off t1, the
    # tilt is the cause (0.017).
    from haptex_compile.synth_images import weave_image

    truth = 40.0 * weave_image((64, 64), (16.0, 0.0), (0.0, 16.0), kind="plain")
    basis = np.diag([16.0, 16.0])
    for light, overhead in ((Light(6.0, 20.0), True), (Light(30.0, 2.0), False)):
        img = render_lambertian(truth, PX, light, 0.8, periodic=True)
        res = shape_from_shading(img, pixel_size_um=PX, light=light, periodic=True, weave_basis_px=basis)
        assert any("nearly overhead" in w for w in res.warnings) == overhead
        assert any("nearly along the weave direction" in w for w in res.warnings) != overhead


def test_a_plain_image_lit_along_a_weave_direction_is_warned_without_more_starts(monkeypatch):
    # A coarse lattice's photo is solved whole, as a plain image: light 2° off t1 at slant 30°
    # (sin 30° sin 2° = 0.017) is warned of as on a tile, but the full-resolution starts need
    # a periodic window and do not run; 22.5° off t1 and t1 + t2 (0.19) is not warned of.
    from haptex_compile.synth_images import weave_image

    truth = 40.0 * weave_image((96, 96), (16.0, 0.0), (0.0, 16.0), kind="plain")
    basis = np.diag([16.0, 16.0])
    ran = []
    monkeypatch.setattr(shading_starts, "_start_from_cell", lambda *a: ran.append(1))
    monkeypatch.setattr(shading_starts, "_fine_starts", lambda *a: ran.append(1))
    for light, warned in ((Light(30.0, 2.0), True), (Light(30.0, 22.5), False)):
        img = render_lambertian(truth, PX, light, 0.8)
        res = shape_from_shading(img, pixel_size_um=PX, light=light, periodic=False, weave_basis_px=basis)
        along = [w for w in res.warnings if "nearly along the weave direction" in w]
        assert len(along) == warned
        assert all("not a periodic tile" in w for w in along)
    assert not ran


def test_an_estimated_slant_at_the_searchs_lowest_is_noted():
    # The search's slants start at MIN_SLANT_DEG: an estimate there is an edge, not a minimum.
    low = Light(shading.MIN_SLANT_DEG, 200.0, 2.0, 3.0)
    assert "search's lowest" in shading.estimated_light_note(low)
    assert "search's lowest" not in shading.estimated_light_note(Light(12.0, 200.0, 2.0, 3.0))


def test_conjugate_gradients_keep_the_priors_waves_as_coefficients():
    # Without the data term the energy is quadratic (thin plate, the prior's waves and plane),
    # and one Gauss-Newton step solved to a tight tolerance lands on its minimum, 0.
    # Conjugate gradients carry the prior's waves as coefficients; a slip in that bookkeeping
    # leaves energy behind. The plane over a box (its row profiles) and over masked data.
    from haptex_compile.shading_variational import _Problem

    rng = np.random.default_rng(2)
    rows, cols = 96, 80
    box = np.zeros((rows, cols), np.float32)
    box[:80, :64] = 1.0
    holed = box.copy()
    holed[30:40, 20:30] = 0.0
    yy, xx = np.mgrid[:rows, :cols]
    for w in (box, holed):
        prob = _Problem(np.full((rows, cols), 0.5, np.float32), w, Light(40.0, 200.0).vector,
                        1e-3, 1, (0.64, 2 * np.pi / 80.0), lowfreq_plane=0.1)
        assert (prob._lf.profiles is None) == (w is holed)
        prob.w = np.zeros_like(w)  # no data term; the plane, built on the data weights, stays
        z = (0.02 * xx + 3 * np.sin(2 * np.pi * yy / rows) + rng.standard_normal((rows, cols))).astype(np.float32)
        zw = prob.waves(z)
        e0 = prob.energy(z, 0.8, zw=zw)
        dz, dzw, _ = prob.gn_step(z, 0.8, 300, 1e-7, zw=zw)
        assert np.abs(dzw - prob.waves(dz)).max() <= 1e-4 * np.abs(dzw).max()
        assert prob.energy(z + dz, 0.8) <= 1e-6 * e0


# ----------------------------------------------------------------------------- hostile images


def _hostile_image(kind: int, shape: tuple[int, int], rng: np.random.Generator) -> np.ndarray:
    """Images no Lambertian surface gives: noise, steps, clipped halves, NaN and inf holes,
    16-bit integers, (almost) constant planes."""
    rows, cols = shape
    y, x = np.mgrid[0:rows, 0:cols].astype(float)
    if kind == 0:
        return rng.uniform(0, 1, shape)
    if kind == 1:
        return ((x // rng.integers(1, 6) + y // rng.integers(1, 6)) % 2).astype(float)  # checkerboard
    if kind == 2:
        return np.where(rng.uniform(size=shape) < 0.5, 0.0, 1.0)  # black and saturated only
    if kind == 3:
        img = 0.5 + 0.3 * np.sin(x / 7.0)
        img[rng.uniform(size=shape) < 0.3] = np.nan
        img[rng.uniform(size=shape) < 0.05] = np.inf
        return img
    if kind == 4:
        return rng.integers(0, 65536, shape).astype(np.uint16)
    if kind == 5:
        img = 0.5 + 0.3 * np.sin(x / 5.0 + y / 9.0)
        img[:, : cols // 2] = 0.0  # half the image an attached shadow
        return img
    if kind == 6:
        return 0.5 + 1e-6 * rng.standard_normal(shape)  # flat but for rounding
    img = np.clip(0.9 + 0.1 * rng.standard_normal(shape), 0, None)
    img[rows // 3: 2 * rows // 3] = 1.0  # a saturated band
    return img


@settings(max_examples=40, deadline=None, derandomize=True)
@given(kind=st.integers(0, 7), rows=st.integers(4, 48), cols=st.integers(4, 48), seed=st.integers(0, 2**16),
       slant=st.floats(0.0, 89.9), tilt=st.floats(-360.0, 720.0), periodic=st.booleans(),
       method=st.sampled_from(shading.METHODS))
def test_hostile_images_never_give_non_finite_or_runaway_heights(kind, rows, cols, seed, slant, tilt, periodic,
                                                                  method):
    # Issue 7's stability point on images no Lambertian surface gives, light given, every
    # method: heights of the image's shape, finite, with slopes within the driver's runaway
    # guard (shading.RUNAWAY_SLOPE, 50 px per px: above it every method falls back to flat), and
    # a finite albedo.
    img = _hostile_image(kind, (rows, cols), np.random.default_rng(seed))
    res = shape_from_shading(img, pixel_size_um=PX, light=Light(slant, tilt), periodic=periodic, method=method)
    assert res.height.shape == (rows, cols)
    assert np.all(np.isfinite(res.height))
    gy, gx = np.gradient(res.height / PX)
    assert float(np.max(np.hypot(gx, gy))) <= shading.RUNAWAY_SLOPE == 50.0
    assert np.isfinite(res.albedo) and res.albedo > 0
    assert all(isinstance(w, str) and "\n" not in w for w in res.warnings)


def test_heights_that_overflow_in_um_are_an_error_not_inf():
    # The heights in µm are the solver's (pixel units) times the pixel size: at 1e308 um that
    # overflows (this cap rises some 16 px), and infinite heights went on to the tiles and tables.
    light = Light(45.0, 200.0)
    img = render_lambertian(ts.sphere_cap((96, 96), PX), PX, light, 0.8, periodic=True)
    for method in ("default", "tsai-shah"):
        with pytest.raises(ValueError, match="heights in um overflow"):
            shape_from_shading(img, pixel_size_um=1e308, light=light, periodic=True, method=method)
