"""Table storage precision: rounding keeps 12 significant bits and lets gzip halve the size."""
from __future__ import annotations

import h5py
import numpy as np

from haptex_compile.asset_writer import TABLE_MANTISSA_BITS, round_mantissa


def test_rounding_error_is_bounded_by_half_a_unit_in_the_last_kept_bit():
    x = np.random.default_rng(0).lognormal(0.0, 3.0, 200_000).astype(np.float32)
    y = round_mantissa(x)
    assert np.abs(y / x - 1).max() <= 2.0 ** -(TABLE_MANTISSA_BITS + 1)
    assert np.array_equal(round_mantissa(np.array([0.0, 1.0, 0.75, 1024.0], np.float32)), [0.0, 1.0, 0.75, 1024.0])
    assert np.array_equal(round_mantissa(y), y)  # idempotent


def test_rounded_tables_compress_to_well_under_the_raw_size(tmp_path):
    rng = np.random.default_rng(1)
    field = np.abs(np.cumsum(np.cumsum(rng.normal(size=(12, 29, 83, 83)), axis=2), axis=3)).astype(np.float32) + 1.0
    sizes = {}
    for name, data in (("raw", field), ("rounded", round_mantissa(field))):
        path = tmp_path / f"{name}.h5"
        with h5py.File(path, "w") as f:
            f.create_dataset("a", data=data, compression="gzip", compression_opts=4, shuffle=True, chunks=True, track_times=False)
        sizes[name] = path.stat().st_size
    assert sizes["rounded"] < 0.75 * sizes["raw"]
