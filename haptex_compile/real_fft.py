"""The 2-D real FFT pair of the shape-from-shading solver, without scipy.fft's per-call
argument handling.

The solver calls the pair (the preconditioner's) in every conjugate-gradient iteration, and a
light search runs hundreds of solves whose levels are a few dozen pixels across: there
:func:`scipy.fft.rfft2` and :func:`scipy.fft.irfft2` spend most of their time checking and
normalising their arguments (measured on the Intel host: the pair took 73-79 µs at 12-24 px,
of which the transforms 15-22 µs). The functions here pass float32 and complex64 arrays
straight to the pocketfft binding that scipy.fft itself ends in, with the arguments scipy
gives it (the default "backward" normalisation), so the bits are the same; anything else, or a
scipy whose binding is not where or what this module expects (checked once, at import, on a
small array against the public functions), goes through the public functions.
"""
from __future__ import annotations

import numpy as np
import scipy.fft

try:  # scipy's own binding (private; present since scipy 1.4)
    from scipy.fft._pocketfft import pypocketfft as _pocketfft
except ImportError:  # pragma: no cover - depends on the installed scipy
    _pocketfft = None

_AXES = [0, 1]


def _direct_ok(a: np.ndarray, dtype) -> bool:
    """`a` is a 2-D array of `dtype`, aligned and in native byte order: the arrays that
    scipy.fft hands to its binding unchanged."""
    return a.dtype == dtype and a.ndim == 2 and a.flags.aligned and a.dtype.isnative


def rfft2(a: np.ndarray, workers: int) -> np.ndarray:
    """:func:`scipy.fft.rfft2` of 2-D real `a` on `workers` threads (complex64 for float32)."""
    if _pocketfft is not None and _direct_ok(a, np.float32):
        return _pocketfft.r2c(a, _AXES, True, 0, None, workers)
    return scipy.fft.rfft2(a, workers=workers)


def irfft2(spectrum: np.ndarray, shape: tuple[int, int], workers: int) -> np.ndarray:
    """:func:`scipy.fft.irfft2` of `spectrum` (the rfft2 layout) to real arrays of `shape`
    on `workers` threads (float32 for complex64); `spectrum` may be overwritten."""
    if (_pocketfft is not None and _direct_ok(spectrum, np.complex64)
            and spectrum.shape == (shape[0], shape[1] // 2 + 1)):
        return _pocketfft.c2r(spectrum, _AXES, shape[1], False, 2, None, workers)
    return scipy.fft.irfft2(spectrum, s=shape, workers=workers, overwrite_x=True)


def _binding_agrees() -> bool:
    """The direct calls give scipy.fft's public functions' bits on a small array (odd and
    even sides), and raise nothing."""
    real = np.random.default_rng(0).standard_normal((6, 9)).astype(np.float32)
    try:
        for x in (real, real[:, :8].copy()):
            spec = scipy.fft.rfft2(x)
            if not (np.array_equal(rfft2(x, 1), spec)
                    and np.array_equal(irfft2(spec.copy(), x.shape, 1), scipy.fft.irfft2(spec, s=x.shape))):
                return False
    except Exception:  # a binding whose signature changed
        return False
    return True


if _pocketfft is not None and not _binding_agrees():  # pragma: no cover - depends on scipy
    _pocketfft = None
