"""haptex_compile.real_fft: scipy.fft's real 2-D pair, bit for bit, without its argument handling."""
import numpy as np
import pytest
import scipy.fft

from haptex_compile import real_fft


def test_the_installed_scipy_takes_the_direct_path():
    # The module falls back to the public functions silently (same bits, slower): this says
    # when an installed scipy no longer has the binding it calls, or its signature changed.
    assert real_fft._pocketfft is not None, "scipy.fft's pocketfft binding not found or disagrees: real_fft is on its slow path"


@pytest.mark.parametrize("shape", [(1, 1), (3, 1), (1, 4), (12, 12), (24, 17), (17, 24), (96, 96), (150, 126)])
@pytest.mark.parametrize("workers", [1, 2])
def test_float32_pair_gives_scipys_bits(shape, workers):
    real = np.random.default_rng(sum(shape)).standard_normal(shape).astype(np.float32)
    spec = real_fft.rfft2(real, workers)
    want = scipy.fft.rfft2(real, workers=workers)
    assert spec.dtype == np.complex64 and np.array_equal(spec, want)
    back = real_fft.irfft2(spec.copy(), shape, workers)
    assert back.dtype == np.float32 and np.array_equal(back, scipy.fft.irfft2(want, s=shape, workers=workers))
    # and it is the inverse: a real array comes back as itself (float32 round-off)
    np.testing.assert_allclose(back, real, atol=1e-5 * max(1.0, float(np.abs(real).max())))


def test_a_pure_wave_has_one_coefficient_and_comes_back():
    rows, cols = 16, 20
    y, x = np.mgrid[:rows, :cols]
    wave = np.cos(2 * np.pi * (3 * x / cols + 2 * y / rows)).astype(np.float32)
    spec = real_fft.rfft2(wave, 1)
    big = np.argwhere(np.abs(spec) > 1e-3)
    # cos splits between (ky, kx) = (2, 3) and its mirror (-2, -3), which the half spectrum
    # holds as its conjugate: one coefficient of N/2
    assert big.tolist() == [[2, 3]]
    assert spec[2, 3] == pytest.approx(rows * cols / 2, rel=1e-5)
    np.testing.assert_allclose(real_fft.irfft2(spec, (rows, cols), 1), wave, atol=1e-5)


@pytest.mark.parametrize("dtype", [np.float64, np.float16, np.int32])
def test_other_dtypes_go_through_scipy(dtype):
    real = (np.random.default_rng(1).standard_normal((10, 7)) * 10).astype(dtype)
    spec = real_fft.rfft2(real, 1)
    want = scipy.fft.rfft2(real)
    assert spec.dtype == want.dtype and np.array_equal(spec, want)
    assert np.array_equal(real_fft.irfft2(spec.copy(), real.shape, 1), scipy.fft.irfft2(want, s=real.shape))


def test_strided_and_unaligned_inputs_give_scipys_bits():
    base = np.random.default_rng(2).standard_normal((20, 30)).astype(np.float32)
    strided = base[::2, 1::3]
    assert np.array_equal(real_fft.rfft2(strided, 1), scipy.fft.rfft2(strided))
    raw = np.zeros(4 * 12 * 9 + 1, np.uint8)[1:].view(np.float32).reshape(12, 9)  # misaligned
    raw[...] = base[:12, :9]
    assert not raw.flags.aligned
    assert np.array_equal(real_fft.rfft2(raw, 1), scipy.fft.rfft2(base[:12, :9]))


def test_an_inverse_to_another_shape_goes_through_scipy():
    spec = real_fft.rfft2(np.ones((8, 8), np.float32), 1)
    # a spectrum of 8 x 8 asked back at 8 x 12: zero-padded, as the public function does
    assert np.array_equal(real_fft.irfft2(spec.copy(), (8, 12), 1), scipy.fft.irfft2(spec, s=(8, 12)))
