"""The long-wave prior of plain images: the power of the waves along the light, and what it
does to a weave's plain image."""
from __future__ import annotations

import numpy as np
import pytest

from haptex_compile import known_surfaces as ts
from haptex_compile import shading
from haptex_compile.shading import Light, normalised_height_error, render_lambertian, shape_from_shading
from haptex_compile.shading_prior import along_light_power, spectral_symbol
from haptex_compile.shading_variational import _across

PX = 20.0


def _tone_image(n: int, cycles: int, amplitude_px: float, light: Light, across: bool = False) -> np.ndarray:
    """Lambertian image (albedo 0.8, not periodic) of a height tone of `cycles` cycles per
    image along x (along y if `across`)."""
    x = np.arange(n) * 2 * np.pi * cycles / n
    z = amplitude_px * np.cos(x)
    z = np.tile(z[:, None] if across else z[None, :], (1, n) if across else (n, 1))
    return render_lambertian(z * PX, PX, light, 0.8, periodic=False)


def _windowed_cone_power(field: np.ndarray, light: Light, ring: int,
                         cone_deg: float = 30.0) -> tuple[np.ndarray, np.ndarray]:
    """Squared amplitudes of the Hann-windowed `field`'s waves at `ring` cycles per side
    within `cone_deg` of the light's azimuth, and the waves' (l . w)²."""
    n = field.shape[0]
    win = np.outer(np.hanning(n), np.hanning(n))
    x = (field - np.sum(field * win) / np.sum(win)) * win
    spec = np.fft.fft2(x) / np.sqrt(np.sum(win * win) * field.size)
    k = np.fft.fftfreq(n, 1.0 / n)
    ky, kx = np.meshgrid(k, k, indexing="ij")
    lx, ly = light.vector[:2]
    along = 2 * np.pi / n * (lx * kx + ly * ky)
    sel = (np.rint(np.hypot(kx, ky)) == ring) & (along**2 >= np.cos(np.deg2rad(cone_deg)) ** 2 * (lx * lx + ly * ly) * (2 * np.pi / n) ** 2 * (kx**2 + ky**2))
    return np.abs(spec[sel]) ** 2, along[sel] ** 2


def test_along_light_power_is_the_slope_along_the_light_over_its_frequency():
    # To first order a Lambertian image is albedo (lz - l . grad z): its waves along the light,
    # divided by albedo² (l . w)², are the height's, as the (windowed) slope along the light
    # shows them (gentle random bumps, slopes about 0.02: the linear regime).
    bumps = ts.random_bumps((128, 128), PX, seed=3)
    z = bumps / PX * (0.02 / ts.rms_slope(bumps, PX))
    gy, gx = np.gradient(z)
    for tilt in (0.0, 200.0):
        light = Light(40.0, tilt)
        img = render_lambertian(z * PX, PX, light, 0.8, periodic=False)
        p = along_light_power(img, light.vector, 0.8, max_cycles=8)
        assert np.isnan(p[0])
        slope = light.vector[0] * gx + light.vector[1] * gy
        for ring in range(1, 9):
            power, along2 = _windowed_cone_power(slope, light, ring)
            assert p[ring] == pytest.approx(np.mean(power / along2), rel=0.05)
        # Where the window mixes waves of very different frequencies (the lowest rings), that
        # is not the height's own power; from ring 3 on it is, within the window's smoothing.
        for ring in range(3, 9):
            power, _ = _windowed_cone_power(z, light, ring)
            assert p[ring] == pytest.approx(np.mean(power), rel=0.25)


def _half_spectrum_power(image: np.ndarray, light: Light, max_cycles: int, albedo: float = 0.8,
                         cone_deg: float = 30.0) -> np.ndarray:
    """along_light_power's definition over the whole half spectrum (rfft2 of the windowed
    image): each ring's mean of |Z|² / (albedo² (l . w)²) over its waves within the cone."""
    rows, cols = image.shape
    win = np.outer(np.hanning(rows), np.hanning(cols))
    x = (image - np.sum(image * win) / np.sum(win)) * win
    spec = np.fft.rfft2(x) / np.sqrt(np.sum(win * win) * image.size)
    ky = np.fft.fftfreq(rows, 1.0 / rows)[:, None]
    kx = np.fft.rfftfreq(cols, 1.0 / cols)[None, :]
    side = max(rows, cols)
    ring = np.rint(np.hypot(kx * side / cols, ky * side / rows))
    lx, ly = light.vector[:2]
    wx, wy = 2 * np.pi * kx / cols, 2 * np.pi * ky / rows
    along, w2 = lx * wx + ly * wy, wx * wx + wy * wy
    cone = along * along >= np.cos(np.deg2rad(cone_deg)) ** 2 * (lx * lx + ly * ly) * w2
    out = np.full(max_cycles + 1, np.nan)
    for c in range(1, max_cycles + 1):
        sel = (ring == c) & cone & (w2 > 0)
        if sel.any():
            out[c] = np.mean(np.abs(spec[sel]) ** 2 / (albedo * albedo * along[sel] ** 2))
    return out


@pytest.mark.parametrize("shape", [(96, 96), (61, 150), (150, 61), (9, 14), (5, 5)])
def test_along_light_power_keeps_every_wave_of_its_rings(shape):
    # Only the low-frequency corner of the spectrum is computed: it must hold every wave of
    # the rings asked for, on any aspect ratio and odd sides (the same means as over the
    # whole half spectrum, to rounding).
    rng = np.random.default_rng(shape[0] * 1000 + shape[1])
    img = 0.5 + 0.2 * rng.random(shape)
    for tilt in (0.0, 35.0, 120.0, 250.0):
        light = Light(40.0, tilt)
        for max_cycles in (1, 6, 10):
            got = along_light_power(img, light.vector, 0.8, max_cycles=max_cycles)
            want = _half_spectrum_power(img, light, max_cycles)
            np.testing.assert_array_equal(np.isnan(got), np.isnan(want))
            np.testing.assert_allclose(got[1:], want[1:], rtol=1e-10)


def test_along_light_power_of_a_tone():
    # A tone along the light: its ring holds the power, which grows as the amplitude squared;
    # the rings below it hold almost nothing (the window's leakage).
    light = Light(40.0, 0.0)  # along x
    n, amp = 128, 0.05  # slopes up to 0.015
    p6 = along_light_power(_tone_image(n, 6, amp, light), light.vector, 0.8, max_cycles=8)
    p6x2 = along_light_power(_tone_image(n, 6, 2 * amp, light), light.vector, 0.8, max_cycles=8)
    assert int(np.nanargmax(p6)) == 6
    assert p6x2[6] == pytest.approx(4 * p6[6], rel=0.02)
    assert np.all(p6[1:4] < 1e-3 * p6[6])


def test_a_tone_across_the_light_is_not_seen_along_it():
    # Light along x, tone along y: no first-order shading, so the cone along the light finds
    # no power at the tone's frequency (the prior may then hold such waves; see the module).
    light = Light(40.0, 0.0)
    p = along_light_power(_tone_image(128, 4, 0.05, light, across=True), light.vector, 0.8, max_cycles=8)
    along = along_light_power(_tone_image(128, 4, 0.05, light), light.vector, 0.8, max_cycles=8)
    assert p[4] < 1e-3 * along[4]
    assert along_light_power(np.full((64, 64), 0.5), Light(2e-4, 0.0).vector, 0.8, max_cycles=4) is None


def test_spectral_symbol_holds_waves_across_the_light_in_proportion_to_their_missing_power():
    light = Light(45.0, 0.0)  # along x: waves along y are across it
    rows, cols = 64, 64
    wy = 2 * np.pi * np.fft.fftfreq(rows)[:, None]
    wx = 2 * np.pi * np.fft.rfftfreq(cols)[None, :]
    c = _across(light.vector)  # the solver's direction across the light
    across = (c[0] * np.sin(wx) + c[1] * np.sin(wy)) ** 2
    power = np.array([np.nan, 1.0, 1.0, 1e-2, 1e-2, 1.0])
    sym = spectral_symbol(wx, wy, across, 0.8, side_px=64.0, data_pixels=4096.0, power=power,
                          weight=1e-3, cap=np.inf)
    # Waves along the light (ky = 0) are the data's: no prior. Across it (kx = 0): the
    # Gaussian prior's weight albedo² / (N power), 100 x larger where the power is 100 x
    # smaller; nothing beyond the table (6 cycles) or at the mean.
    assert np.all(sym[0, :] == 0)
    want = 1e-3 * 0.64 / 4096.0
    assert sym[2, 0] == pytest.approx(want, rel=1e-6)
    assert sym[3, 0] == pytest.approx(100 * want, rel=1e-6)
    assert sym[6, 0] == 0 and sym[-2, 0] == pytest.approx(want, rel=1e-6)
    capped = spectral_symbol(wx, wy, across, 0.8, side_px=64.0, data_pixels=4096.0, power=power,
                             weight=1e-3, cap=1e-6)
    assert capped[3, 0] == pytest.approx(1e-6 * 0.64 * np.sin(wy[3, 0]) ** 2, rel=1e-6)


@pytest.mark.parametrize("slant, tilt", [(15.0, 30.0), (60.0, 300.0)])
def test_plain_image_of_a_weave_comes_back_flat_on_average(slant, tilt, monkeypatch):
    # A weave has no power below its own frequency, and its plain image shows that along the
    # light; the prior then holds the long waves across the light, which the free edges
    # otherwise let curl (measured at 128 px: 0.200 and 0.440 without, 0.032 and 0.068 with).
    # On the narrow margin of level ground's images, where the free edges curl most (on a
    # texture's own margin: 0.133 and 0.510 without, 0.086 and 0.067 with).
    monkeypatch.setattr(shading, "TEXTURE_MARGIN", shading.PLAIN_MARGIN)
    woven = ts.woven_like((128, 128), PX)
    light = Light(slant, tilt)
    img = render_lambertian(woven, PX, light, 0.8, periodic=False)
    with_prior = shape_from_shading(img, pixel_size_um=PX, light=light).height
    monkeypatch.setattr(shading, "SPECTRAL_PRIOR_WEIGHT", 0.0)
    without = shape_from_shading(img, pixel_size_um=PX, light=light).height
    assert normalised_height_error(with_prior, woven) <= 0.10
    assert normalised_height_error(without, woven) >= 0.15
