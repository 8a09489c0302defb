"""Table storage precision: rounding keeps 12 significant bits and lets gzip halve the size."""
from __future__ import annotations

import h5py
import numpy as np
import pytest

from haptex_compile.asset_writer import (TABLE_CHUNK_BYTES, TABLE_GZIP_LEVEL, TABLE_MANTISSA_BITS, _table_chunks,
                                         _table_dataset, round_mantissa)


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
            f.create_dataset("a", data=data, compression="gzip", compression_opts=TABLE_GZIP_LEVEL, shuffle=True,
                             chunks=_table_chunks(data.shape), track_times=False)
        sizes[name] = path.stat().st_size
    assert sizes["rounded"] < 0.75 * sizes["raw"]


@pytest.mark.parametrize("shape", [(12, 29, 83, 83), (48, 29, 80, 80), (3, 5, 700, 700), (1, 1, 2, 2)])
def test_table_chunks_hold_whole_node_grids_within_a_mebibyte(shape):
    chunks = _table_chunks(shape)
    assert all(1 <= c <= n for c, n in zip(chunks, shape))
    assert 4 * np.prod(chunks) <= max(TABLE_CHUNK_BYTES, 4 * shape[3])
    if 4 * shape[2] * shape[3] <= TABLE_CHUNK_BYTES:
        assert chunks[2:] == shape[2:]  # a player reads whole grids


@pytest.mark.parametrize("shape", [(3, 57, 90, 80), (2, 3, 700, 530)])  # edge chunks along speed; along j
def test_tables_compressed_outside_hdf5_read_back_exactly_through_its_filters(tmp_path, shape):
    data = round_mantissa(np.random.default_rng(3).lognormal(0.0, 1.0, shape).astype(np.float32))
    path = tmp_path / "t.h5"
    with h5py.File(path, "w") as f:
        _table_dataset(f, "a40", data)
    with h5py.File(path) as f:
        d = f["a40"]
        assert d.compression == "gzip" and d.shuffle and d.chunks == _table_chunks(shape)
        assert np.array_equal(d[()], data)
