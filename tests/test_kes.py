"""Tests of KES-F input: file reading/validation, the simulated KES-FB4 probe, surface synthesis."""
from __future__ import annotations

import json
import math
import re
from pathlib import Path

import jsonschema
import numpy as np
import pytest

from haptex_compile.errors import InputError
from haptex_compile.kes import (
    KES_PROBE_RADIUS_UM,
    kes_relief_scale,
    kes_surface,
    simulate_kes_smd,
    weave_matrix,
    weave_relief,
)
from haptex_compile.kes_io import KesData, kes_schema, parse_kes, read_kes

REPO = Path(__file__).resolve().parents[1]
SAMPLES = sorted((REPO / "samples" / "kes").glob("*.kes.json"))

GOOD = {
    "fabric": "cotton poplin",
    "smd_um": {"warp": 3.2, "weft": 4.1},
    "miu": {"warp": 0.18, "weft": 0.2},
    "mmd": {"warp": 0.012, "weft": 0.015},
    "ends_per_cm": 48,
    "picks_per_cm": 30,
    "weave": "plain",
}


def kes(warp: float, weft: float, ends: float = 48, picks: float = 30, weave: str = "plain") -> KesData:
    return KesData("test", {"warp": warp, "weft": weft}, {"warp": 0.2, "weft": 0.25},
                   {"warp": 0.01, "weft": 0.02}, ends, picks, weave)


# --------------------------------------------------------------------------------------------
# files


def test_schema_is_valid_and_samples_conform():
    jsonschema.Draft202012Validator.check_schema(kes_schema())
    assert len(SAMPLES) >= 4
    for path in SAMPLES:
        data = read_kes(path)
        assert isinstance(data, KesData)
        assert data.source and "typical" in data.source.lower()
        jsonschema.validate(json.loads(path.read_text()), kes_schema())


def test_read_json_roundtrip(tmp_path):
    path = tmp_path / "cotton.kes.json"
    path.write_text(json.dumps(dict(GOOD, thickness_mm=0.3, source="lab X")))
    data = read_kes(path)
    assert data == KesData("cotton poplin", {"warp": 3.2, "weft": 4.1}, {"warp": 0.18, "weft": 0.2},
                           {"warp": 0.012, "weft": 0.015}, 48.0, 30.0, "plain", 0.3, "lab X")


def _without(obj: dict, dotted: str) -> dict:
    obj = json.loads(json.dumps(obj))
    *parents, last = dotted.split(".")
    node = obj
    for key in parents:
        node = node[key]
    del node[last]
    return obj


def _with(obj: dict, dotted: str, value) -> dict:
    obj = json.loads(json.dumps(obj))
    *parents, last = dotted.split(".")
    node = obj
    for key in parents:
        node = node[key]
    node[last] = value
    return obj


BAD_CASES = [
    ("missing field", _without(GOOD, "smd_um"), "smd_um", "missing"),
    ("missing nested field", _without(GOOD, "smd_um.weft"), "smd_um.weft", "missing"),
    ("negative SMD", _with(GOOD, "smd_um.warp", -1.0), "smd_um.warp", ">= 0.01"),
    ("zero SMD", _with(GOOD, "smd_um.weft", 0), "smd_um.weft", ">= 0.01"),
    # (1e-300 um passed the schema, and the calibration's smooth minimum overflowed: a traceback)
    ("SMD below 0.01 um", _with(GOOD, "smd_um.weft", 1e-300), "smd_um.weft", ">= 0.01"),
    ("unknown weave", _with(GOOD, "weave", "tweed"), "weave", "tweed"),
    ("string for number", _with(GOOD, "ends_per_cm", "48"), "ends_per_cm", "number"),
    ("bool for number", _with(GOOD, "picks_per_cm", True), "picks_per_cm", "number"),
    ("number for string", _with(GOOD, "fabric", 3), "fabric", "string"),
    ("object expected", _with(GOOD, "miu", 0.2), "miu", "object"),
    ("friction above range", _with(GOOD, "miu.warp", 5.0), "miu.warp", "<= 2"),
    ("MMD larger than MIU", _with(GOOD, "mmd.weft", 0.5), "mmd.weft", "miu.weft"),
    ("unknown field (typo)", _with(GOOD, "smd_warp", 3.0), "smd_warp", "not allowed"),
    ("wrong format version", _with(GOOD, "format_version", 2), "format_version", "1"),
    ("negative thickness", _with(GOOD, "thickness_mm", -0.2), "thickness_mm", "> 0"),
]


@pytest.mark.parametrize("name,obj,field,words", BAD_CASES, ids=[c[0] for c in BAD_CASES])
def test_bad_json_gives_one_line_error_naming_file_and_field(tmp_path, name, obj, field, words):
    path = tmp_path / "bad.kes.json"
    path.write_text(json.dumps(obj))
    with pytest.raises(InputError) as info:
        read_kes(path)
    message = str(info.value)
    assert "\n" not in message
    assert message.startswith(str(path))
    assert f"'{field}'" in message
    assert words in message


@pytest.mark.parametrize("literal", ["NaN", "Infinity", "-Infinity"])
def test_nan_and_infinity_rejected(tmp_path, literal):
    path = tmp_path / "nan.kes.json"
    path.write_text(json.dumps(GOOD).replace("3.2", literal))
    with pytest.raises(InputError) as info:
        read_kes(path)
    assert "'smd_um.warp'" in str(info.value) and "finite" in str(info.value)
    assert "\n" not in str(info.value)


@pytest.mark.parametrize("text,words", [
    ("{\"fabric\": ", "not valid JSON"),
    ("[1, 2]", "JSON object"),
    ("", "not valid JSON"),
])
def test_malformed_json(tmp_path, text, words):
    path = tmp_path / "broken.kes.json"
    path.write_text(text)
    with pytest.raises(InputError, match=words) as info:
        read_kes(path)
    assert str(path) in str(info.value) and "\n" not in str(info.value)


def test_missing_file_and_unknown_extension(tmp_path):
    with pytest.raises(InputError, match="no such Kawabata file"):
        read_kes(tmp_path / "nope.kes.json")
    other = tmp_path / "x.kes.txt"
    other.write_text("{}")
    with pytest.raises(InputError, match="unknown KES file type"):
        read_kes(other)


def test_parse_kes_names_source():
    with pytest.raises(InputError, match=r"^inline: field 'weave'"):
        parse_kes(_with(GOOD, "weave", "knit"), "inline")


CSV_HEADER = ("fabric,smd_warp_um,smd_weft_um,miu_warp,miu_weft,mmd_warp,mmd_weft,"
              "ends_per_cm,picks_per_cm,weave,thickness_mm,source")


def test_csv_batch(tmp_path):
    path = tmp_path / "batch.kes.csv"
    path.write_text("\ufeff" + CSV_HEADER + "\n"
                    "poplin,3.2,4.1,0.18,0.2,0.012,0.015,48,30,plain,0.25,\"Kawabata, 1980\"\n"
                    "\n"
                    "denim,7.5,10.5,0.22,0.24,0.03,0.04,28,18,twill_3_1,,\n"
                    "satin,1.4,1.9,0.15,0.17,0.008,0.01,100,40,satin,0.18,typical\n")
    rows = read_kes(path)
    assert [r.fabric for r in rows] == ["poplin", "denim", "satin"]
    assert rows[0].smd_um == {"warp": 3.2, "weft": 4.1} and rows[0].source == "Kawabata, 1980"
    assert rows[1].thickness_mm is None and rows[1].source is None and rows[1].weave == "twill_3_1"
    assert rows[2].ends_per_cm == 100.0 and rows[2].mmd == {"warp": 0.008, "weft": 0.01}


def test_csv_semicolon_and_without_optional_columns(tmp_path):
    path = tmp_path / "batch.kes.csv"
    header = CSV_HEADER.rsplit(",", 2)[0].replace(",", ";")
    path.write_text(header + "\npoplin;3,2;4.1;0.18;0.2;0.012;0.015;48;30;plain\n".replace("3,2", "3.2"))
    (row,) = read_kes(path)
    assert row.smd_um["warp"] == 3.2 and row.thickness_mm is None


@pytest.mark.parametrize("row,words", [
    ("denim,-7.5,10.5,0.22,0.24,0.03,0.04,28,18,twill,,", "row 3: field 'smd_um.warp'"),
    ("denim,7.5,abc,0.22,0.24,0.03,0.04,28,18,twill,,", "row 3: field 'smd_um.weft' (column smd_weft_um): not a number"),
    ("denim,7.5,nan,0.22,0.24,0.03,0.04,28,18,twill,,", "row 3: field 'smd_um.weft': must be a finite"),
    ("denim,7.5,10.5,0.22,0.24,0.03,0.04,28,18,herringbone,,", "row 3: field 'weave'"),
    ("denim,7.5,10.5,0.22,0.24,0.03,0.04,28,18,twill", "row 3: 10 cells"),
    ("denim,7.5,10.5,0.22,,0.03,0.04,28,18,twill,,", "row 3: field 'miu.weft' (column miu_weft): missing"),
])
def test_csv_errors_name_file_row_and_field(tmp_path, row, words):
    path = tmp_path / "batch.kes.csv"
    path.write_text(CSV_HEADER + "\npoplin,3.2,4.1,0.18,0.2,0.012,0.015,48,30,plain,,\n" + row + "\n")
    with pytest.raises(InputError) as info:
        read_kes(path)
    assert str(info.value).startswith(str(path)) and words in str(info.value)
    assert "\n" not in str(info.value)


@pytest.mark.parametrize("text,words", [
    ("", "empty file"),
    (CSV_HEADER + "\n", "no fabric rows"),
    (CSV_HEADER.replace("smd_weft_um", "smd_wft_um") + "\n", "unknown column 'smd_wft_um'"),
    (CSV_HEADER.replace(",weave", "") + "\n", "missing column 'weave'"),
])
def test_csv_header_errors(tmp_path, text, words):
    path = tmp_path / "batch.kes.csv"
    path.write_text(text)
    with pytest.raises(InputError, match=words):
        read_kes(path)


# --------------------------------------------------------------------------------------------
# the simulated KES-FB4 probe


def _sine_rows(wavelength_um: float, amplitude_um: float, pixel_size_um: float, length_mm: float = 20.0):
    """A map varying only along v (rows): h = A cos(2 pi v / lambda), a whole number of periods."""
    n = int(round(length_mm * 1e3 / pixel_size_um))
    v = np.arange(n) * pixel_size_um
    assert (n * pixel_size_um / wavelength_um) % 1 == 0
    return np.repeat((amplitude_um * np.cos(2 * np.pi * v / wavelength_um))[:, None], 3, axis=1)


def test_long_wavelength_sinusoid_gives_2A_over_pi():
    # lambda = 5 mm >> wire: the wire follows the surface, SMD = mean |A cos| = 2A/pi
    h = _sine_rows(5000.0, 6.0, 10.0)
    assert simulate_kes_smd(h, 10.0, "warp") == pytest.approx(2 * 6.0 / math.pi, rel=0.01)
    # direction convention: this map varies along v only, so a traverse along u (weft) is flat
    assert simulate_kes_smd(h.T, 10.0, "weft") == pytest.approx(2 * 6.0 / math.pi, rel=0.01)
    assert simulate_kes_smd(h, 10.0, "weft") == pytest.approx(0.0, abs=1e-9)


def test_short_wavelength_is_bridged_by_the_wire():
    # lambda = 40 um << wire: the wire rests on the crests; at distance d from the nearest crest
    # its height is A + sqrt(R^2 - d^2) - R with d uniform on [0, lambda/2].
    wavelength, amplitude, radius = 40.0, 5.0, KES_PROBE_RADIUS_UM
    h = _sine_rows(wavelength, amplitude, 1.0)
    d = np.linspace(0, wavelength / 2, 200001)
    sag = np.sqrt(radius ** 2 - d ** 2) - radius
    expected = np.mean(np.abs(sag - sag.mean()))
    measured = simulate_kes_smd(h, 1.0, "warp")
    assert measured == pytest.approx(expected, rel=0.03)
    assert measured < 0.1 * 2 * amplitude / math.pi  # far below the raw mean deviation
    # without the wire the raw profile's mean deviation comes back
    assert simulate_kes_smd(h, 1.0, "warp", probe_radius_um=0) == pytest.approx(2 * amplitude / math.pi, rel=0.01)


def test_smd_falls_monotonically_as_wavelength_shrinks():
    values = [simulate_kes_smd(_sine_rows(lam, 10.0, 5.0), 5.0, "warp") for lam in (4000, 1000, 500, 250, 100)]
    assert all(a > b for a, b in zip(values, values[1:]))
    assert values[0] == pytest.approx(20 / math.pi, rel=0.02)


def test_rigid_long_wire_bridges_diagonal_ridges():
    # twill-like diagonal ridges h = A cos(k (u + v)): a line contact follows them along v, but a
    # rigid 5 mm wire across the traverse always spans a crest, so its height never changes
    u = np.arange(400) * 10.0
    ridges = 5 * np.cos(2 * np.pi * (u[None, :] + u[:, None]) / 1000)
    line = simulate_kes_smd(ridges, 10.0, "warp", traverse_mm=4.0)
    wire = simulate_kes_smd(ridges, 10.0, "warp", traverse_mm=4.0, wire_length_um=5000)
    assert line > 0.8 * 2 * 5 / math.pi
    assert wire < 1e-3 * line


def test_probe_input_errors():
    h = np.zeros((50, 50))
    with pytest.raises(ValueError, match="direction"):
        simulate_kes_smd(h, 10.0, "diagonal")
    h[3, 3] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        simulate_kes_smd(h, 10.0, "warp")
    with pytest.raises(ValueError, match="pixel_size_um"):
        simulate_kes_smd(np.zeros((50, 50)), -1.0, "warp")


# --------------------------------------------------------------------------------------------
# weave and surface synthesis


def test_weave_matrices():
    expected_warp_fraction = {"plain": 0.5, "twill": 0.5, "twill_2_1": 2 / 3, "twill_3_1": 0.75, "satin": 0.8}
    for weave, fraction in expected_warp_fraction.items():
        m = weave_matrix(weave)
        assert m.mean() == pytest.approx(fraction)
        # every end and every pick interlaces (goes both over and under)
        assert m.any(axis=0).all() and (~m).any(axis=0).all() and m.any(axis=1).all() and (~m).any(axis=1).all()
    satin = weave_matrix("satin")
    # satin: the weft-up points of consecutive picks are never adjacent ends (move 2)
    down = [int(np.flatnonzero(~row)[0]) for row in satin]
    assert all(min((a - b) % 5, (b - a) % 5) == 2 for a, b in zip(down, down[1:] + down[:1]))
    with pytest.raises(ValueError, match="unknown weave"):
        weave_matrix("jersey")


def test_weave_relief_thread_period_and_extent():
    relief, on_top = weave_relief(48, 30, "plain", pixel_size_um=10.0)
    ny, nx = relief.shape
    assert nx * 10.0 >= 10_000 and ny * 10.0 >= 10_000
    # the column-mean profile repeats once per warp end: its spectrum peaks at the thread count
    spec = np.abs(np.fft.rfft(relief.mean(axis=0) - relief.mean()))
    n_ends = round(nx * 10.0 * 48 / 1e4)
    assert int(np.argmax(spec)) == n_ends
    assert 0.4 < on_top.mean() < 0.6  # plain weave: as much warp as weft on top


@pytest.mark.parametrize("warp,weft,ends,picks,weave", [
    (1.0, 1.0, 48, 30, "plain"),
    (3.2, 4.1, 48, 30, "plain"),
    (20.0, 20.0, 48, 30, "plain"),
    (2.0, 15.0, 28, 18, "twill_3_1"),
    (15.0, 2.0, 28, 18, "twill_3_1"),
    (1.0, 20.0, 100, 40, "satin"),
    (20.0, 1.0, 32, 28, "twill"),
    (6.0, 9.0, 100, 80, "twill_2_1"),
    (5.0, 5.0, 8, 6, "plain"),
])
def test_calibrated_smd_within_5_percent(warp, weft, ends, picks, weave):
    surface = kes_surface(kes(warp, weft, ends, picks, weave))
    target = {"warp": warp, "weft": weft}
    for direction in ("warp", "weft"):
        assert surface.smd_simulated_um[direction] == pytest.approx(target[direction], rel=0.01)
        # an independent, dense measurement (every column/row) agrees too
        dense = simulate_kes_smd(surface.height_um, surface.pixel_size_um, direction, n_traverses=10_000)
        assert dense == pytest.approx(target[direction], rel=0.05)


def test_smooth_minimum_of_tiny_and_huge_thread_weights():
    # (a^-4 + b^-4)^-1/4: its powers overflowed below about 1e-77 (OverflowError)
    from haptex_compile.kes import _smoothmin

    assert _smoothmin(3.0, 4.0) == pytest.approx((3.0**-4 + 4.0**-4) ** -0.25, rel=1e-15)
    assert _smoothmin(2.0, 2.0) == pytest.approx(2.0 * 2.0**-0.25, rel=1e-15)
    assert _smoothmin(1e-300, 1e-300) == pytest.approx(1e-300 * 2.0**-0.25, rel=1e-15)
    assert _smoothmin(1e-300, 1e300) == 1e-300 and _smoothmin(1e300, 5.0) == 5.0


def test_first_guess_without_probe_misses_at_large_smd():
    # the wire bridges the weave grooves: scaling by the raw mean deviation undershoots
    surface = kes_surface(kes(20.0, 20.0, 100, 40, "satin"), calibrate=False)
    assert surface.smd_simulated_um["warp"] < 0.9 * 20.0


def test_surface_is_periodic_over_its_extent():
    surface = kes_surface(kes(4.0, 6.0, 30, 28, "twill"))
    h = surface.height_um.astype(np.float64)
    assert surface.period_px == (h.shape[1], h.shape[0])
    # the step across the wrap is no larger than ordinary steps between neighbours
    for axis in (0, 1):
        steps = np.abs(np.diff(h, axis=axis)).mean(axis=1 - axis)
        wrap = np.abs(np.take(h, 0, axis=axis) - np.take(h, -1, axis=axis)).mean()
        assert wrap <= np.quantile(steps, 0.95)
    # a traverse is translation invariant on a periodic map
    shifted = np.roll(np.roll(h, 137, axis=0), 251, axis=1)
    for direction in ("warp", "weft"):
        a = simulate_kes_smd(h, 10.0, direction, n_traverses=10_000)
        b = simulate_kes_smd(shifted, 10.0, direction, n_traverses=10_000)
        assert a == pytest.approx(b, rel=0.005)


def test_determinism():
    a = kes_surface(kes(3.0, 4.0), seed=7)
    b = kes_surface(kes(3.0, 4.0), seed=7)
    c = kes_surface(kes(3.0, 4.0), seed=8)
    assert np.array_equal(a.height_um, b.height_um) and np.array_equal(a.friction, b.friction)
    assert not np.array_equal(a.height_um, c.height_um)


def test_friction_map_has_miu_mean_and_mmd_deviation():
    data = kes(3.0, 4.0)
    surface = kes_surface(data)
    f = surface.friction.astype(np.float64)
    assert f.shape == (2,) + surface.height_um.shape
    for index, direction in enumerate(("warp", "weft")):
        assert f[index].mean() == pytest.approx(data.miu[direction], rel=1e-3)
        assert np.abs(f[index] - f[index].mean()).mean() == pytest.approx(data.mmd[direction], rel=0.02)
    # more friction climbing (+v on a rising slope) than descending
    slope_v = np.gradient(surface.height_um.astype(np.float64), axis=0)
    assert np.corrcoef(slope_v.ravel(), f[0].ravel())[0, 1] > 0.3


def test_pixel_too_coarse_for_threads():
    with pytest.raises(ValueError, match="too coarse"):
        kes_surface(kes(3.0, 3.0, ends=300, picks=200), pixel_size_um=10.0)


def test_relief_scale_recovers_calibrated_surface():
    # the calibrated surface measures the target, so its own scale factor is 1
    data = kes(3.0, 5.0, 32, 28, "twill")
    surface = kes_surface(data)
    assert kes_relief_scale(data, surface.height_um, 10.0, periodic=True) == pytest.approx(1.0, rel=0.01)


def test_relief_scale_on_a_photo_like_map():
    # a non-periodic unit-less map (a crop of a synthetic fabric, scaled down by 37)
    source = kes_surface(kes(6.0, 6.0, 20, 18, "plain")).height_um[:700, :800] / 37.0
    data = kes(2.5, 4.0)
    c = kes_relief_scale(data, source, 10.0)
    scaled = source * c
    measured = math.sqrt(simulate_kes_smd(scaled, 10.0, "warp", periodic=False)
                         * simulate_kes_smd(scaled, 10.0, "weft", periodic=False))
    assert measured == pytest.approx(math.sqrt(2.5 * 4.0), rel=0.01)
    with pytest.raises(ValueError, match="flat"):
        kes_relief_scale(data, np.ones((100, 100)), 10.0)


# --------------------------------------------------------------------------------------------
# the compiler's source


def test_a_fine_fabric_gets_pixels_fine_enough_for_its_threads(tmp_path):
    # 20 um pixels fit threads 80 um apart or more (4 px each); a silk of 150 ends/cm (threads
    # 66.7 um apart) was refused at that default and named the library's keyword, not the option.
    from haptex_compile.kes_source import DEFAULT_KES_PIXEL_UM, kes_pixel_um, kes_source
    from haptex_compile.sources import SourceOptions

    assert kes_pixel_um(48, 30) == DEFAULT_KES_PIXEL_UM and kes_pixel_um(125, 30) == DEFAULT_KES_PIXEL_UM
    assert kes_pixel_um(150, 120) == 16.66 and kes_pixel_um(300, 400) == 6.25
    path = tmp_path / "silk.kes.json"
    path.write_text(json.dumps({**GOOD, "fabric": "silk habotai", "ends_per_cm": 150, "picks_per_cm": 120}))
    result = kes_source(str(path), SourceOptions())
    assert result.surface.pixel_size_um == 16.66 and "finer for 4 px per thread" in result.report["pixel_size"]
    for direction in ("warp", "weft"):
        assert result.report["smd_simulated_um"][direction] == pytest.approx(GOOD["smd_um"][direction], rel=0.05)
    with pytest.raises(InputError, match=r"silk\.kes\.json: --pixel-size 20 um is too coarse for threads 66\.7 um apart"
                                         r" \(at least 4 px per thread: give 16\.66 um or less"):
        kes_source(str(path), SourceOptions(pixel_size_um=20.0))


def test_a_weave_repeat_too_long_for_its_pixels_is_one_clear_line(tmp_path):
    # 400 ends and 1 pick per cm in a 4-pick twill: the threads need 6.25 um pixels, and the
    # 40 mm repeat then takes 6400 px, above the synthesis's 4096; the library's message
    # advised "a larger pixel_size_um", which the threads do not allow.
    from haptex_compile.kes import synthesis_side_px
    from haptex_compile.kes_source import kes_source
    from haptex_compile.sources import SourceOptions

    assert synthesis_side_px(400, 1, "twill_3_1", 6.25) == (1600, 6400)
    assert synthesis_side_px(48, 30, "plain", 20.0) == (500, 500)  # 10 mm of whole repeats each way
    path = tmp_path / "odd.kes.json"
    for ends, pixel, words in ((400, None, "no pixel size fits both that and its threads"),
                               (100, 5.0, "give a coarser --pixel-size (up to 25 um fits its threads)")):
        path.write_text(json.dumps({**GOOD, "ends_per_cm": ends, "picks_per_cm": 1, "weave": "twill_3_1"}))
        with pytest.raises(InputError, match=re.escape(words)) as info:
            kes_source(str(path), SourceOptions(pixel_size_um=pixel))
        assert str(info.value).startswith(f"{path}: at ") and "above 4096 a side" in str(info.value)
