"""Asset reader: valid files load; every kind of bad file gives one AssetError line naming it."""
from __future__ import annotations

import h5py
import numpy as np
import pytest

from playback.asset import read_asset
from playback.errors import AssetError
from asset_factory import haptex24_layout_mm, smooth_field, write_test_asset


@pytest.fixture
def asset_path(tmp_path):
    return write_test_asset(tmp_path / "a.tact.h5")


def test_reads_layout_and_values(asset_path):
    a = read_asset(asset_path)
    t = a.tables
    assert t.shape == (24, 21, 32, 32)
    assert a.n_contactors == 24
    np.testing.assert_allclose(a.contactors_mm, haptex24_layout_mm())
    # Node [d, s, j, i] holds the field at origin + i g_i + j g_j.
    d, s, j, i = 3, 5, 7, 9
    e40, e320 = smooth_field(t.direction_deg[d], t.speed_mm_s[s], i * 0.25, j * 0.25)
    # The writer keeps 12 significant mantissa bits (relative rounding at most 2^-13).
    assert t.a40[d, s, j, i] == pytest.approx(e40, rel=2.0**-13)
    assert t.a320[d, s, j, i] == pytest.approx(e320, rel=2.0**-13)
    assert a.height_um is None and a.surface_shape == (16, 16)
    assert not t.a40.flags.writeable


def test_load_surface(asset_path):
    a = read_asset(asset_path, load_surface=True)
    assert a.height_um is not None and a.height_um.shape == (16, 16)


def test_a_file_that_crashes_the_hdf5_library_is_one_line(asset_path, monkeypatch):
    # Reading is tried first in a forked child: a crash there (as libhdf5 crashes on some
    # corrupt files; here the child's read is made to crash) is one AssetError line naming
    # the file, and this process goes on. A file that reads is read as before.
    import os
    import signal

    from playback import asset as asset_module

    assert asset_module.crash_signal(asset_path) is None
    monkeypatch.setattr(asset_module, "read_everything", lambda path: os.kill(os.getpid(), signal.SIGSEGV))
    asset_module._probe.cache_clear()  # (the unchanged file's answer is kept)
    assert asset_module.crash_signal(asset_path) == "SIGSEGV"
    with pytest.raises(AssetError) as err:
        read_asset(asset_path)
    message = str(err.value)
    assert message.startswith(str(asset_path)) and "\n" not in message and "crashed" in message


def _mutate(path, fn):
    with h5py.File(path, "r+") as f:
        fn(f)
    return path


def _set(name, value):
    def fn(f):
        del f[name]
        f.create_dataset(name, data=value)
    return fn


@pytest.mark.parametrize("mutation, fragment", [
    (lambda f: f.attrs.__setitem__("format", "something-else"), "not a haptex tactile asset"),
    (lambda f: f.attrs.__setitem__("format_version", "2.0"), "format version 2.0 not supported (this reader reads 1.x)"),
    (lambda f: f.attrs.__delitem__("format_version"), "missing attribute 'format_version'"),
    (lambda f: f["tables"].__delitem__("a320"), "missing dataset /tables/a320"),
    (lambda f: f.__delitem__("scene"), "missing group /scene"),
    (lambda f: f["tables"].attrs.__delitem__("grid_basis_mm"), "grid_basis_mm"),
    (_set("tables/a40", np.full((24, 21, 32, 32), np.nan, np.float32)), "NaN"),
    (_set("tables/a320", -np.ones((24, 21, 32, 32), np.float32)), "negative"),
    (_set("tables/a40", np.ones((24, 21, 32), np.float32)), "must have 4 dims"),
    (_set("tables/a320", np.ones((24, 21, 32, 31), np.float32)), "differs from a40"),
    (_set("tables/speed_mm_s", np.geomspace(320, 10, 21)), "strictly ascending"),
    (_set("tables/speed_mm_s", np.linspace(0, 10, 21)), "> 0"),
    (_set("tables/direction_deg", np.arange(0, 360, 15.0)), "[0, 180)"),
    (_set("tables/direction_deg", np.arange(0, 165, 7.5)), "24 directions"),
    (_set("scene/contactors_mm", np.zeros((24, 3))), "contactors_mm"),
    (lambda f: f["tables"].attrs.__setitem__("grid_basis_mm", np.array([[1.0, 0], [2.0, 0]])), "singular"),
    (lambda f: f["scene"].attrs.__setitem__("resolved", "{not json"), "not valid JSON"),
])
def test_bad_assets_one_line(asset_path, mutation, fragment):
    _mutate(asset_path, mutation)
    with pytest.raises(AssetError) as info:
        read_asset(asset_path)
    msg = str(info.value)
    assert fragment in msg
    assert str(asset_path) in msg and "\n" not in msg


def test_not_hdf5_and_truncated(tmp_path, asset_path):
    txt = tmp_path / "x.tact.h5"
    txt.write_text("hello")
    with pytest.raises(AssetError, match="not an HDF5 file"):
        read_asset(txt)
    with pytest.raises(AssetError, match="no such file"):
        read_asset(tmp_path / "missing.h5")
    data = asset_path.read_bytes()
    cut = tmp_path / "cut.tact.h5"
    cut.write_bytes(data[: len(data) // 2])  # truncated download
    with pytest.raises(AssetError) as info:
        read_asset(cut)
    assert str(cut) in str(info.value) and "\n" not in str(info.value)


def test_other_hdf5_file(tmp_path):
    p = tmp_path / "other.h5"
    with h5py.File(p, "w") as f:
        f.create_dataset("x", data=[1, 2, 3])
    with pytest.raises(AssetError, match="not a haptex tactile asset"):
        read_asset(p)


def test_minor_version_accepted(tmp_path):
    p = write_test_asset(tmp_path / "a.h5", format_version="1.7")
    assert read_asset(p).format_version == "1.7"
