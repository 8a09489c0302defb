"""Scenes, input specs and the asset writer/reader round trip."""
from __future__ import annotations

import json
import re
import warnings

import h5py
import numpy as np
import pytest

from haptex_compile.errors import InputError
from haptex_compile.io_scene import parse_scene
from haptex_compile.scene import default_scene, grid_contactors
from haptex_compile.sources import input_kind, output_stem, parse_brownian_spec, remove_plane
from haptex_compile.units import parse_length_um, parse_pixel_size_um


def test_default_scene_is_the_haptex_array():
    s = default_scene()
    assert s.contactors_mm.shape == (24, 2)
    # 6 x 4 at 2 mm pitch, centred: x spans 10 mm, y spans 6 mm, mean at the origin.
    assert np.ptp(s.contactors_mm[:, 0]) == pytest.approx(10.0)
    assert np.ptp(s.contactors_mm[:, 1]) == pytest.approx(6.0)
    np.testing.assert_allclose(s.contactors_mm.mean(axis=0), 0.0, atol=1e-12)
    r = s.resolved()
    assert r["motion"]["speed_range_mm_s"] == [10.0, 200.0] and r["motion"]["tolerance"] == 0.02
    assert r["render"]["frame_ms"] == 25.0 and r["render"]["base_frequencies_hz"] == [40.0, 320.0]
    json.loads(s.resolved_json())


def test_scene_sections_are_optional_and_lists_are_used_as_given():
    s = parse_scene("[motion]\nspeeds_mm_s = [80, 10, 20]\ndirections_deg = [0, 180, 270, 45]\n", "s.toml")
    assert s.speeds_mm_s == (10.0, 20.0, 80.0)
    assert s.directions_deg == (0.0, 45.0, 90.0)  # mod 180, unique
    assert s.contactors_mm.shape == (24, 2)
    s = parse_scene("[array]\ncontactors_mm = [[0.0, 0.0], [2.0, 0.0]]\n", "s.toml")
    np.testing.assert_allclose(s.contactors_mm, [[0, 0], [2, 0]])


@pytest.mark.parametrize("text", [
    "[array]\ngrid = { rows = 0, cols = 6, pitch_mm = 2.0 }",
    "[array]\ncontactors_mm = [[0.0, 0.0]]\ngrid = { rows = 1, cols = 1, pitch_mm = 1.0 }",
    "[motion]\nspeeds_mm_s = [10]\nspeed_range_mm_s = [10, 20]",
    "[motion]\ntolerance = 0",
    "[render]\nframe_ms = 1000",
    "[render]\nbase_frequencies_hz = [320, 40]",
    "[render]\nsummation_exponent = nan",
    "[physics]\nx = 1",
    # Numbers the schema let through and the compiler could not use: a speed range of 1e-300 mm/s
    # (its geometric midpoints underflowed to 0: NaN check weights, "Probabilities contain NaN"
    # after three RuntimeWarnings), contactors at 1e300 mm (overflow warnings, then an asset).
    "[motion]\nspeed_range_mm_s = [1e-300, 1e-299]",
    "[motion]\nspeeds_mm_s = [1e-300]",
    "[array]\ncontactors_mm = [[1e300, 0.0]]",
    # 10000 contactors compiled into an asset the player refused ("count must be <= 4096")
    "[array]\ngrid = { rows = 100, cols = 100, pitch_mm = 1.0 }",
])
def test_bad_scenes_are_input_errors(text):
    with pytest.raises(InputError) as info:
        parse_scene(text, "bad.toml")
    assert str(info.value).startswith("bad.toml: ") and "\n" not in str(info.value)


def test_the_largest_array_a_scene_may_have_is_the_largest_the_player_drives():
    from playback.device import DEFAULT_PROFILE, MAX_CONTACTORS, profile_from_dict

    side = int(MAX_CONTACTORS ** 0.5)
    assert side * side == MAX_CONTACTORS
    scene = parse_scene(f"[array]\ngrid = {{ rows = {side}, cols = {side}, pitch_mm = 0.5 }}\n", "s.toml")
    assert len(scene.contactors_mm) == MAX_CONTACTORS
    n = MAX_CONTACTORS
    profile_from_dict({**DEFAULT_PROFILE, "contactors": {"count": n, "n_channels": n, "channel": list(range(n))}})
    with pytest.raises(InputError, match="at most 4096"):
        parse_scene(f"[array]\ngrid = {{ rows = {side}, cols = {side + 1}, pitch_mm = 0.5 }}\n", "s.toml")


def test_repeated_explicit_nodes_are_merged_and_said(monkeypatch, caplog):
    # [10, 10, 40] mm/s were two speed nodes and 0, 180, 90, -90, 45 deg three directions (a
    # direction and its reverse are one), without a word.
    import logging

    monkeypatch.setattr(logging.getLogger("haptex"), "propagate", True)  # the CLI tests turn it off
    text = "[motion]\nspeeds_mm_s = [10, 10, 40]\ndirections_deg = [0, 180, 90, -90, 45]\n"
    with caplog.at_level(logging.WARNING, logger="haptex"):
        scene = parse_scene(text, "s.toml")
    assert scene.speeds_mm_s == (10.0, 40.0) and scene.directions_deg == (0.0, 45.0, 90.0)
    assert [r.getMessage() for r in caplog.records] == [
        "s.toml: motion.speeds_mm_s: 3 values, 2 distinct speeds: those are the nodes",
        "s.toml: motion.directions_deg: 5 values, 3 distinct directions (modulo 180 deg): those are the nodes"]
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="haptex"):
        parse_scene("[motion]\nspeeds_mm_s = [10, 40]\ndirections_deg = [0, 90]\n", "s.toml")
    assert not caplog.records


def test_grid_contactors_order_and_pitch():
    c = grid_contactors(2, 3, 1.5)
    np.testing.assert_allclose(c[:3, 1], -0.75)
    np.testing.assert_allclose(np.diff(c[:3, 0]), 1.5)


def test_length_units():
    assert parse_length_um("10um") == 10.0
    assert parse_length_um("0.01mm") == pytest.approx(10.0)
    assert parse_length_um("2.5 µm") == 2.5
    for bad in ("10 furlongs", "-1um", "nan", "0mm", "um"):
        with pytest.raises(ValueError):
            parse_length_um(bad)
    # A pixel is at most 1 m: above it lengths and heights leave float range on the way.
    assert parse_pixel_size_um("1m") == 1e6 and parse_pixel_size_um("0.5nm") == 5e-4
    for bad in ("1.01m", "1e308um", "-1um"):
        with pytest.raises(ValueError):
            parse_pixel_size_um(bad)


def test_brownian_spec():
    kw = parse_brownian_spec("brownian:H=0.7,size=1024,pixel=10um,rms=5um,seed=3")
    assert kw["hurst"] == 0.7 and kw["shape"] == (1024, 1024) and kw["pixel_size_um"] == 10.0
    assert kw["rms_um"] == 5.0 and kw["seed"] == 3 and kw["periodic"] is False
    assert parse_brownian_spec("brownian:H=0.5,size=64x32")["shape"] == (32, 64)
    for bad in ("brownian:size=64", "brownian:H=0.5,colour=red", "brownian:H=0.5,size=4", "brownian:H=x",
                "brownian:H=0.5,periodic=maybe"):
        with pytest.raises(InputError):
            parse_brownian_spec(bad)
    # A value that does not parse is named with its key (Python's own messages named none).
    for bad, message in (("brownian:H=x", "H='x' is not a number"), ("brownian:H=0.5,seed=1e3", "seed='1e3' is not a whole number"),
                         ("brownian:H=0.5,size=64xq", "size='64xq' is not a whole number"),
                         ("brownian:H=0.5,rms=0um", "rms: length '0um' must be finite and positive"),
                         # (1e300 um overflowed the float32 heights: RuntimeWarnings, then an asset)
                         ("brownian:H=0.5,rms=1e300um", "rms 1e+300 um is above 1 m: check its unit"),
                         # (the last one was used, without a word)
                         ("brownian:H=0.5,size=64,size=32", "size is given twice")):
        with pytest.raises(InputError, match=re.escape(message)):
            parse_brownian_spec(bad)
    assert parse_brownian_spec("brownian:H=0.5,rms=1m")["rms_um"] == 1e6


@pytest.mark.parametrize("scale_um", [1e7, 1e30, 1e300])
def test_a_height_map_beyond_a_metre_is_refused(tmp_path, scale_um):
    # Heights in the wrong unit by far: 1e30 um gave an asset of all-zero tables (overflowed
    # powers), 1e300 one of infinite heights, both after RuntimeWarnings.
    from haptex_compile.sources import SourceOptions, load_source

    path = tmp_path / "h.npy"
    h = np.random.default_rng(0).standard_normal((16, 16))
    np.save(path, h * scale_um)
    peak = np.max(np.abs(remove_plane(h))) * scale_um
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with pytest.raises(InputError) as info:
            load_source(str(path), SourceOptions(pixel_size_um=20.0))
    assert str(info.value) == (f"{path}: heights reach {peak:.3g} um after levelling, above 1 m: the file's heights"
                               " must be in micrometres")


def test_out_of_scale_messages_keep_numbers_short():
    # Pixels of 1e-300 um were refused with 300-digit sample counts and sizes.
    from haptex_compile.sources import SourceOptions, load_source
    from haptex_compile.surface import count_text
    from haptex_compile.compile import compile_surface

    assert count_text(126) == "126" and count_text(104857600) == "104857600" and count_text(1.04e305) == "1.04e+305"
    source = load_source("brownian:H=0.5,size=16,pixel=1e-300um,rms=5um", SourceOptions())
    with pytest.raises(InputError) as info:
        compile_surface(source, "never-written.tact.h5", default_scene())
    assert "is out of scale for the tables" in str(info.value)
    assert max(len(word) for word in re.findall(r"[0-9.e+]+", str(info.value))) <= 12


def test_input_kinds_and_stems():
    assert input_kind("a/b.kes.json") == "kes" and output_stem("a/b.kes.json") == "b"
    assert input_kind("x.PNG") == "image" and input_kind("h.exr") == "heightmap"
    assert input_kind("brownian:H=0.5") == "brownian"
    assert "/" not in output_stem("brownian:H=0.5,size=64")
    with pytest.raises(InputError):
        input_kind("notes.txt")


@pytest.mark.parametrize("rms_um, warned", [(5.0, False), (5000.0, True), (0.005, True)])
def test_a_height_map_of_implausible_relief_is_warned_of(tmp_path, monkeypatch, caplog, rms_um, warned):
    # A fabric's roughness is micrometres: heights written in nm read as thousands of µm,
    # heights in mm as thousandths; both are compiled, with a warning naming the file.
    import logging

    from haptex_compile.sources import SourceOptions, load_source

    monkeypatch.setattr(logging.getLogger("haptex"), "propagate", True)  # the CLI tests turn it off
    h = np.random.default_rng(0).standard_normal((64, 64))
    path = tmp_path / "relief.npy"
    np.save(path, h * (rms_um / h.std()))
    with caplog.at_level(logging.WARNING, logger="haptex"):
        result = load_source(str(path), SourceOptions(pixel_size_um=20.0))
    assert ("relief_warning" in result.report) is warned
    assert any("relief.npy" in r.getMessage() and "micrometres" in r.getMessage() for r in caplog.records) is warned
    assert float(np.sqrt(np.mean(result.surface.height_um ** 2))) == pytest.approx(rms_um, rel=0.05)


def test_plane_removal_leaves_texture():
    y, x = np.mgrid[0:40, 0:50]
    texture = np.sin(x / 3.0) * np.cos(y / 4.0)
    flat = remove_plane(texture + 3.0 + 0.2 * x - 0.1 * y)
    # The plane is gone: what is left is the texture minus its own (small) best plane.
    assert np.abs(flat - remove_plane(texture)).max() < 1e-9


def test_asset_round_trip_periodic(tmp_path):
    from haptex_compile.asset_writer import AssetContent, write_asset
    from haptex_compile.colours import TwoColourModel
    from haptex_compile.frame_analysis import AnalysisSettings
    from haptex_compile.render import asset_model
    from haptex_compile.surface import periodic_surface_from_tile
    from haptex_compile.tables import build_tables, table_grid
    from playback.asset import read_asset

    rng = np.random.default_rng(0)
    h = rng.normal(size=(40, 50))
    surface = periodic_surface_from_tile(h, 20.0)
    model, settings = TwoColourModel(), AnalysisSettings()
    tables = build_tables(surface, model, settings, [0.0, 90.0], [40.0, 80.0], table_grid(surface, 0.25))
    path = tmp_path / "a.tact.h5"
    write_asset(path, AssetContent(surface, tables, model, settings, default_scene(), "tile", "heightmap",
                                   report={"note": "test"}))
    a = read_asset(path, load_surface=True)
    assert a.surface_periodic and a.tables.periodic
    np.testing.assert_allclose(a.height_um, h.astype(np.float32))
    # Stored with 12 significant mantissa bits (relative rounding at most 2^-13).
    np.testing.assert_allclose(a.tables.a40, tables.a40.astype(np.float32), rtol=2.0**-13)
    s2, m2, st2 = asset_model(a)
    f = np.geomspace(5, 900, 50)
    np.testing.assert_allclose(m2.weights(f), model.weights(f), rtol=1e-12)
    assert st2 == settings
    np.testing.assert_allclose(s2.t1_px, [50, 0]) and np.testing.assert_allclose(s2.t2_px, [0, 40])
    with h5py.File(path) as f5:
        assert json.loads(f5["report"].attrs["json"]) == {"note": "test"}


def test_options_that_do_not_apply_to_the_input_are_warned_of(tmp_path, monkeypatch, caplog):
    # A Brownian spec with --pixel-size 10um kept the spec's 20 um, and photo options given for
    # a height map were dropped, all silently. One warning names them; the surface is as without.
    import logging

    from haptex_compile.sources import SourceOptions, load_source

    monkeypatch.setattr(logging.getLogger("haptex"), "propagate", True)  # the CLI tests turn it off
    spec = "brownian:H=0.5,size=32,pixel=20um,rms=5um,seed=2"
    given = SourceOptions(pixel_size_um=10.0, relief_um=5.0, light=(30.0, 40.0), seed=3, sfs="accurate")
    with caplog.at_level(logging.WARNING, logger="haptex"):
        result = load_source(spec, given)
    [said] = [r.getMessage() for r in caplog.records if "ignored" in r.getMessage()]
    assert said == (f"{spec}: --relief-um, --sfs, --light, --seed, --pixel-size do not apply to a Brownian spec"
                    " (its pixel= and seed= set those): ignored")
    assert result.surface.pixel_size_um == 20.0
    np.testing.assert_array_equal(result.surface.height_um, load_source(spec, SourceOptions()).surface.height_um)
    caplog.clear()
    path = tmp_path / "h.npy"
    np.save(path, np.random.default_rng(0).standard_normal((16, 16)))
    with caplog.at_level(logging.WARNING, logger="haptex"):
        load_source(str(path), SourceOptions(pixel_size_um=20.0, light=(30.0, 40.0)))
    assert [r.getMessage() for r in caplog.records if "ignored" in r.getMessage()] == [
        f"{path}: --light does not apply to a height map: ignored"]
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="haptex"):
        load_source(str(path), SourceOptions(pixel_size_um=20.0))
    assert not [r for r in caplog.records if "ignored" in r.getMessage()]


def test_a_grid_spacing_below_the_pixel_is_warned_of(tmp_path, monkeypatch, caplog):
    # The compiler spaces table nodes a pixel apart at least: a scene asking for less got that
    # without a word.
    import logging

    from haptex_compile.compile import compile_surface
    from haptex_compile.sources import SourceOptions, load_source
    from playback.asset import read_asset

    monkeypatch.setattr(logging.getLogger("haptex"), "propagate", True)  # the CLI tests turn it off
    source = load_source("brownian:H=0.5,size=24,pixel=20um,rms=5um,seed=2", SourceOptions())
    motion = "[motion]\nspeeds_mm_s = [50.0]\ndirections_deg = [0.0]\ntolerance = 0.5\n"
    for spacing, warned in ((1e-6, True), (0.03, False)):
        caplog.clear()
        scene = parse_scene(f"{motion}[render]\ngrid_spacing_mm = {spacing}\n", "s.toml")
        with caplog.at_level(logging.WARNING, logger="haptex"):
            compile_surface(source, tmp_path / "a.tact.h5", scene)
        said = [r.getMessage() for r in caplog.records if "grid_spacing_mm" in r.getMessage()]
        assert said == ([f"{source.name}: the scene's grid_spacing_mm {spacing:g} is below the surface's pixel size:"
                         " table nodes are one pixel (0.02 mm) apart"] if warned else [])
        spacing_mm = read_asset(tmp_path / "a.tact.h5").tables.grid_spacing_mm
        extent_mm = 23 * 0.02  # a non-periodic map's nodes span its first to its last pixel
        assert spacing_mm == pytest.approx(extent_mm / round(extent_mm / max(spacing, 0.02)))


def test_pixels_far_finer_than_the_scene_can_feel_are_noted():
    # A 64 px map of 0.5 um pixels took 142 s to compile, of 0.1 um over 300 s, without a word
    # on why; the finest felt wavelength is the slowest speed over the band's top.
    from haptex_compile.colours import TwoColourModel
    from haptex_compile.compile import fine_pixel_note

    model = TwoColourModel()
    assert model.band.high_stop_hz == 800.0
    default = default_scene()  # 10 mm/s: 12.5 um, noted below a quarter of it
    assert fine_pixel_note(3.2, default, model) is None
    note = fine_pixel_note(0.5, default, model)
    assert note.startswith("pixels of 0.5 um are 25 x finer than the finest wavelength the scene can make felt"
                           " (12.5 um: 10 mm/s at 800 Hz)") and "resampled to about 3.1 um" in note
    slow40 = parse_scene("[motion]\nspeeds_mm_s = [80, 40]\n", "s.toml")  # 50 um
    assert fine_pixel_note(12.5, slow40, model) is None and fine_pixel_note(12.0, slow40, model) is not None
