"""Brownian surfaces and fractal roughness (issue 8): the public API.

A Brownian surface of index H (the paper's Sect. 6.2) has increments of variance
``(sigma**2 + tau**2)**H = r**(2H)`` and fractal dimension ``D = 3 - H``. Synthesis lives in
:mod:`haptex_compile.fractal_synthesis`, estimation in :mod:`haptex_compile.fractal_estimate`.
"""
from __future__ import annotations

from .fractal_estimate import HurstEstimate, estimate_hurst, roughness_from_residual
from .fractal_synthesis import MAX_WORKING_BYTES, brownian_surface, stein_embedding_shape

__all__ = [
    "MAX_WORKING_BYTES",
    "HurstEstimate",
    "brownian_surface",
    "estimate_hurst",
    "roughness_from_residual",
    "stein_embedding_shape",
]
