"""Tests of Brownian-surface synthesis and Hurst estimation (issue 8).

Convention: Var[X(x + s) - X(x)] = |s|**(2H), D = 3 - H.
"""
from __future__ import annotations

import math

import numpy as np
import pytest

from haptex_compile.fractal import (
    HurstEstimate,
    brownian_surface,
    estimate_hurst,
    roughness_from_residual,
    stein_embedding_shape,
)
from haptex_compile.fractal_estimate import _model_sd
from haptex_compile.fractal_synthesis import (
    _circulant_surface,
    _stein_psi,
    _stein_sqrt_eigenvalues,
)

PX = 10.0  # µm/px; irrelevant to the heights (self-similarity), but required


def _surface(n, hurst, seed, **kw):
    return brownian_surface(n, hurst, pixel_size_um=PX, rms_um=3.0, seed=seed, **kw)


# ----------------------------------------------------------------------------- exactness


@pytest.mark.parametrize("shape,hurst", [((20, 33), 0.3), ((17, 17), 0.75), ((12, 40), 0.9)])
def test_embedding_reproduces_stein_covariance_on_the_grid(shape, hurst):
    """The torus covariance, restricted to the grid's own lags, is exactly Stein's psi."""
    ny, nx = shape
    root = _stein_sqrt_eigenvalues(ny, nx, hurst)  # raises if any eigenvalue were negative
    my, mx = stein_embedding_shape(shape, hurst)
    cov = np.fft.irfft2(root**2, s=(my, mx))
    h = 1.0 / math.hypot(nx - 1, ny - 1)
    dy, dx = np.mgrid[0:ny, 0:nx]
    np.testing.assert_allclose(cov[:ny, :nx], _stein_psi(h * np.hypot(dy, dx), hurst), atol=1e-12)


@pytest.mark.parametrize("hurst", [0.25, 0.85])
def test_circulant_increment_variances_follow_power_law(hurst):
    """Across replicates, Var(X(a) - X(b)) / Var(X(0,1) - X(0,0)) = |a - b|^(2H), long lags too
    (the random plane of the intrinsic embedding matters there)."""
    n_rep = 3000
    rng = np.random.default_rng(123)
    far, diag, near = [], [], []
    for _ in range(n_rep):
        z = _circulant_surface(12, 12, hurst, rng)
        near.append(z[0, 1] - z[0, 0])
        far.append(z[0, 11] - z[0, 0])
        diag.append(z[11, 11] - z[0, 0])
    v_near = np.mean(np.square(near))
    # Relative SE of a variance from n Gaussian samples is sqrt(2/n) (2.6 %); a ratio of two: ~3.7 %.
    tol = 4 * math.sqrt(2 * 2 / n_rep)
    assert np.mean(np.square(far)) / v_near == pytest.approx(11 ** (2 * hurst), rel=tol)
    assert np.mean(np.square(diag)) / v_near == pytest.approx(math.hypot(11, 11) ** (2 * hurst), rel=tol)


@pytest.mark.parametrize("hurst", [0.15, 0.5, 0.85])
def test_exact_surfaces_recover_hurst(hurst):
    """Variogram H on exact fields: each within 4 model SDs, the mean within the issue's 0.02."""
    n, seeds = 256, range(4)
    sd = _model_sd(np.ones((n, n), bool), hurst, 2.0, 2, [1, 0])
    got = np.array([estimate_hurst(_surface(n, hurst, s), ci="none").hurst for s in seeds])
    assert np.all(np.abs(got - hurst) <= 4 * sd)
    assert abs(got.mean() - hurst) <= 0.02


@pytest.mark.parametrize("p", [1.0, 2.0])
@pytest.mark.parametrize("hurst", [0.2, 0.5, 0.9])
def test_model_sd_far_offsets_in_cells_match_the_sum_over_every_offset(monkeypatch, hurst, p):
    import haptex_compile.fractal_estimate as fe

    valid = np.ones((400, 330), bool)
    cells = fe._model_sd(valid, hurst, p, 2, [1, 0])
    monkeypatch.setattr(fe, "NEAR_OFFSETS_PX", 10_000)  # every offset its own cell: the exact sum
    exact = fe._model_sd(valid, hurst, p, 2, [1, 0])
    assert cells == pytest.approx(exact, rel=1e-3)


@pytest.mark.parametrize("hurst", [0.3, 0.7])
def test_madogram_and_spectral_agree_on_exact_fields(hurst):
    z = _surface((256, 320), hurst, seed=7)
    mado = estimate_hurst(z, method="madogram", ci="none")
    spec = estimate_hurst(z, method="spectral")
    assert mado.hurst == pytest.approx(hurst, abs=4 * _model_sd(np.ones(z.shape, bool), hurst, 1.0, 2, [1, 0]))
    # Spectral SD measured ~0.02 at 256^2: allow ~3 SD.
    assert spec.hurst == pytest.approx(hurst, abs=0.06)
    assert spec.ci_low < spec.hurst < spec.ci_high
    assert spec.dimension == pytest.approx(3.0 - spec.hurst)


def test_confidence_interval_matches_seed_to_seed_spread():
    """The 95 % interval's half-width / 1.96 estimates the SD across independent surfaces."""
    est = [estimate_hurst(_surface(64, 0.5, s)) for s in range(40)]
    h = np.array([e.hurst for e in est])
    implied_sd = np.mean([(e.ci_high - e.ci_low) / (2 * 1.96) for e in est])
    # SD from 40 samples has ~11 % relative error: accept within -30 % / +60 %.
    assert 0.7 * h.std(ddof=1) <= implied_sd <= 1.6 * h.std(ddof=1)
    assert all(e.ci_low < e.hurst < e.ci_high and e.ci_level == 0.95 for e in est)


def test_midpoint_displacement_is_biased():
    """The paper's midpoint method recovers H too low at H = 0.8 and too high at H = 0.1."""
    hi = np.mean([estimate_hurst(_surface(257, 0.8, s, method="midpoint"), ci="none").hurst for s in range(3)])
    lo = np.mean([estimate_hurst(_surface(257, 0.1, s, method="midpoint"), ci="none").hurst for s in range(3)])
    exact_sd = _model_sd(np.ones((257, 257), bool), 0.8, 2.0, 2, [1, 0])
    assert hi < 0.8 - 0.08 and 0.8 - hi > 4 * exact_sd
    assert lo > 0.1 + 0.08


# ----------------------------------------------------------------------------- properties


@pytest.mark.parametrize(
    "kw", [{}, {"method": "midpoint"}, {"periodic": True}, {"method": "midpoint", "periodic": True}]
)
def test_deterministic_and_rms_exact(kw):
    shape = 128 if kw.get("periodic") and kw.get("method") == "midpoint" else (96, 130)
    a = brownian_surface(shape, 0.6, pixel_size_um=5.0, rms_um=2.5, seed=42, **kw)
    b = brownian_surface(shape, 0.6, pixel_size_um=5.0, rms_um=2.5, seed=42, **kw)
    c = brownian_surface(shape, 0.6, pixel_size_um=5.0, rms_um=2.5, seed=43, **kw)
    assert a.dtype == np.float64 and a.shape == ((shape, shape) if isinstance(shape, int) else shape)
    np.testing.assert_array_equal(a, b)
    assert not np.allclose(a, c)
    assert abs(a.mean()) < 1e-12
    assert math.sqrt(np.mean(a * a)) == pytest.approx(2.5, rel=1e-12)


def test_pixel_size_does_not_change_heights():
    a = brownian_surface(64, 0.4, pixel_size_um=1.0, rms_um=1.0, seed=3)
    b = brownian_surface(64, 0.4, pixel_size_um=50.0, rms_um=1.0, seed=3)
    np.testing.assert_array_equal(a, b)


@pytest.mark.parametrize("hurst", [0.2, 0.7])
def test_periodic_seam_is_like_the_interior(hurst):
    """Across the seam (last column -> first) increments have the interior lag-1 variance;
    rolling the seam into the middle leaves H unchanged. A non-periodic field fails both."""

    def seam_ratio(z):
        seam = np.concatenate([z[:, 0] - z[:, -1], z[0, :] - z[-1, :]])
        inner = np.concatenate([np.diff(z, axis=1).ravel(), np.diff(z, axis=0).ravel()])
        return np.mean(seam**2) / np.mean(inner**2)

    periodic = [_surface((192, 256), hurst, s, periodic=True) for s in range(6)]
    ratios = [seam_ratio(z) for z in periodic]
    # 6 x 448 seam increments: the mean ratio's SE is a few %; allow 15 %.
    assert np.mean(ratios) == pytest.approx(1.0, abs=0.15)
    z = periodic[0]
    rolled = np.roll(z, (96, 128), axis=(0, 1))
    assert estimate_hurst(rolled, ci="none").hurst == pytest.approx(estimate_hurst(z, ci="none").hurst, abs=0.005)
    # Control: the exact non-periodic field has a large jump across its "seam".
    assert seam_ratio(_surface((192, 256), hurst, 0)) > 5.0
    # And the periodic field keeps the small-lag scaling.
    assert np.mean([estimate_hurst(p, ci="none").hurst for p in periodic]) == pytest.approx(hurst, abs=0.02)


def test_periodic_midpoint_wraps():
    z = _surface(128, 0.5, 1, method="midpoint", periodic=True)
    seam = np.mean((z[:, 0] - z[:, -1]) ** 2)
    inner = np.mean(np.diff(z, axis=1) ** 2)
    assert seam / inner < 3.0


# ----------------------------------------------------------------------------- errors


@pytest.mark.parametrize("hurst", [0.0, 1.0, -0.2, 1.3, float("nan"), float("inf"), "x"])
def test_bad_hurst(hurst):
    with pytest.raises(ValueError, match="hurst"):
        brownian_surface(16, hurst, pixel_size_um=PX, rms_um=1.0)


@pytest.mark.parametrize(
    "kw,match",
    [
        ({"pixel_size_um": 0.0}, "pixel_size_um"),
        ({"pixel_size_um": float("nan")}, "pixel_size_um"),
        ({"rms_um": float("inf")}, "rms_um"),
        ({"rms_um": -1.0}, "rms_um"),
        ({"seed": -1}, "seed"),
        ({"method": "fourier"}, "method"),
    ],
)
def test_bad_parameters(kw, match):
    args = {"pixel_size_um": PX, "rms_um": 1.0} | kw
    with pytest.raises(ValueError, match=match):
        brownian_surface(16, 0.5, **args)


@pytest.mark.parametrize("shape", [0, 1, (1, 20), (20, -3), (2.5, 4), True])
def test_bad_shape(shape):
    with pytest.raises(ValueError, match="shape"):
        brownian_surface(shape, 0.5, pixel_size_um=PX, rms_um=1.0)


@pytest.mark.parametrize("method,periodic", [("circulant", False), ("circulant", True), ("midpoint", False)])
def test_refuses_sizes_beyond_memory_cap(method, periodic):
    with pytest.raises(ValueError, match="GiB"):
        brownian_surface(200_000, 0.5, pixel_size_um=PX, rms_um=1.0, method=method, periodic=periodic)


def test_periodic_midpoint_needs_power_of_two():
    with pytest.raises(ValueError, match="power-of-two"):
        brownian_surface((100, 100), 0.5, pixel_size_um=PX, rms_um=1.0, method="midpoint", periodic=True)


def test_zero_rms_gives_flat_surface():
    assert not brownian_surface(16, 0.5, pixel_size_um=PX, rms_um=0.0).any()


def test_estimator_errors():
    z = _surface(64, 0.5, 0)
    bad = z.copy()
    bad[3, 3] = np.nan
    with pytest.raises(ValueError, match="non-finite"):
        estimate_hurst(bad)
    mask = np.isfinite(bad)
    assert estimate_hurst(bad, mask=mask, ci="none").hurst == pytest.approx(estimate_hurst(z, ci="none").hurst, abs=0.01)
    with pytest.raises(ValueError, match="does not vary|plane"):
        estimate_hurst(np.ones((32, 32)))
    with pytest.raises(ValueError, match="plane"):
        estimate_hurst(np.add.outer(np.arange(40.0), np.arange(40.0)), method="spectral")
    with pytest.raises(ValueError, match="method"):
        estimate_hurst(z, method="boxcount")
    with pytest.raises(ValueError, match="mask shape"):
        estimate_hurst(z, mask=np.ones((3, 3), bool))
    with pytest.raises(ValueError, match="at least"):
        estimate_hurst(z[:20, :20], method="spectral")


# ----------------------------------------------------------------------------- masks, photos


def test_spectral_with_mask_uses_valid_rectangle():
    z = _surface(256, 0.6, 5)
    mask = np.ones(z.shape, bool)
    mask[:, 100:110] = False  # a stain across the image: the largest clean part is 256 x 146
    stained = np.where(mask, z, 1e9)
    est = estimate_hurst(stained, method="spectral", mask=mask)
    assert est.hurst == pytest.approx(0.6, abs=0.06)


def test_roughness_from_residual_ignores_masked_stain_and_reports_rms():
    z = _surface(200, 0.35, 11)  # RMS 3 by construction
    mask = np.ones(z.shape, bool)
    mask[50:90, 20:160] = False
    residual = np.where(mask, z, 255.0)  # saturated blob
    est, rms = roughness_from_residual(residual, pixel_size_um=8.0, mask=mask)
    assert isinstance(est, HurstEstimate) and est.method == "madogram" and not est.clipped
    assert est.hurst == pytest.approx(0.35, abs=4 * _model_sd(mask, 0.35, 1.0, 2, [1, 0]))
    assert est.dimension == pytest.approx(3 - est.hurst)
    expected = z[mask] - z[mask].mean()
    assert rms == pytest.approx(math.sqrt(np.mean(expected**2)), rel=1e-12)


def test_roughness_from_white_noise_is_clipped_to_roughest():
    """White noise has V(2) = V(1): H = 0, outside (0, 1): clipped to 0.01 and flagged."""
    noise = np.random.default_rng(0).normal(size=(128, 128))
    est, rms = roughness_from_residual(noise, pixel_size_um=5.0)
    assert est.clipped and est.hurst == 0.01 and est.dimension == pytest.approx(2.99)
    assert rms == pytest.approx(1.0, rel=0.05)
    with pytest.raises(ValueError, match="pixel_size_um"):
        roughness_from_residual(noise, pixel_size_um=float("nan"))


def test_residual_roughness_on_real_photo(shared_fabrics):
    """On a real photo (non-periodic treatment) the estimate is finite, in (0, 1), with a CI."""
    import cv2

    path = next(p for p in sorted(shared_fabrics.iterdir()) if p.suffix.lower() in (".bmp", ".jpg", ".png"))
    img = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
    assert img is not None
    img = img[:256, :256].astype(np.float64)
    est, rms = roughness_from_residual(img - img.mean(), pixel_size_um=10.0)
    assert 0.0 < est.hurst < 1.0 and est.ci_low <= est.hurst <= est.ci_high and rms > 0
