"""Speed/direction lookup tables (issue 4) against the reference renderer.

Expected values come from the reference renderer evaluated at the same (position, speed,
direction), from the symmetry of the problem, or from closed forms for gratings (a sinusoid along
u seen at direction d and speed s is a tone at s |cos d| / lambda).
"""
from __future__ import annotations

import contextlib
import dataclasses
import tracemalloc

import numpy as np
import pytest

from haptex_compile.colours import TwoColourModel
from haptex_compile.compile import (MAX_HALVINGS_PER_ROUND, _as_player_tables, axes_to_refine, build_checked_tables,
                                   check_points, check_tables, relative_errors, rms_upper_bound)
from haptex_compile.fractal import brownian_surface
from haptex_compile.frame_analysis import AnalysisSettings
from haptex_compile.render import point_intensities, straight_path
from haptex_compile.scene import default_scene
from haptex_compile.surface import Surface, periodic_surface_from_tile, sample_height
from haptex_compile.tables import Tables, build_tables, speed_midpoints_of, stored_speeds, table_grid

MODEL = TwoColourModel()
SETTINGS = AnalysisSettings(footprint_sigma_mm=0.25)


@contextlib.contextmanager
def traced_peak():
    """The peak of the Python-traced allocations (numpy's included) made in the block, in bytes:
    ``with traced_peak() as peak: ...`` then ``peak[0]``."""
    peak = [0]
    tracemalloc.start()
    try:
        yield peak
    finally:
        peak[0] = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()


def reference(surface: Surface, u: float, v: float, speed: float, direction: float,
              settings: AnalysisSettings = SETTINGS) -> tuple[float, float]:
    d = MODEL.decompose(*point_intensities(surface, MODEL, settings, straight_path(u, v, speed, direction), 0.0))
    return float(d.a40), float(d.a320)


@pytest.fixture(scope="module")
def brownian_small() -> Surface:
    """5 x 5 mm Brownian surface (H = 0.5, 20 µm pixels), not periodic: edges are mirrored."""
    return Surface(brownian_surface((250, 250), 0.5, pixel_size_um=20.0, rms_um=10.0, seed=1), 20.0)


@pytest.fixture(scope="module")
def brownian_tile() -> Surface:
    """2.56 mm periodic Brownian tile."""
    h = brownian_surface((128, 128), 0.5, pixel_size_um=20.0, rms_um=10.0, seed=4, periodic=True)
    return periodic_surface_from_tile(h, 20.0)


def grating(lambda_mm: float = 1.0, amp_um: float = 5.0, periods: int = 2) -> Surface:
    """Periodic sinusoid along u (ridges along v), 20 µm pixels."""
    nx = int(round(periods * lambda_mm * 50))
    u = np.arange(nx) * 0.02
    return periodic_surface_from_tile(np.tile(amp_um * np.sin(2 * np.pi * u / lambda_mm), (16, 1)), 20.0)


def tone_pair(freq_hz: float, amp_um: float) -> tuple[float, float]:
    d = MODEL.decompose(*MODEL.tone_intensities(freq_hz, amp_um))
    return float(d.a40), float(d.a320)


# ---------------------------------------------------------------------------------------------


def test_table_nodes_match_the_reference_renderer(brownian_small):
    grid = table_grid(brownian_small, 0.25)
    dirs, speeds = np.array([0.0, 60.0, 130.0]), np.array([25.0, 100.0])
    tab = build_tables(brownian_small, MODEL, SETTINGS, dirs, speeds, grid)
    assert tab.a40.shape == (3, 2) + grid.shape and grid.shape == (21, 21)
    nodes = grid.nodes_mm()
    rng = np.random.default_rng(0)
    errs = []
    for di, d in enumerate(dirs):
        for si, s in enumerate(speeds):
            for _ in range(5):
                j, i = rng.integers(grid.shape[0]), rng.integers(grid.shape[1])
                r40, r320 = reference(brownian_small, *nodes[j, i], s, d)
                errs.append(relative_errors(MODEL, tab.a40[di, si, j, i], tab.a320[di, si, j, i], r40, r320))
    errs = np.array(errs)
    assert np.sqrt(np.mean(errs**2)) < 0.025 and errs.max() < 0.05


def test_periodic_tables_store_one_period_and_wrap(brownian_tile):
    grid = table_grid(brownian_tile, 0.25)
    assert grid.periodic and grid.shape == (11, 11)  # ceil(2.56 mm / 0.25 mm) nodes per period
    assert np.allclose(grid.basis_mm, np.diag([2.56, 2.56]) / 11)
    dirs, speeds = np.array([0.0, 45.0]), np.array([60.0])
    tab = build_tables(brownian_tile, MODEL, SETTINGS, dirs, speeds, grid)
    period = brownian_tile.lattice_mm()
    nodes = grid.nodes_mm()
    for j in (0, 4, 9):
        p = nodes[j, 0]
        for di, d in enumerate(dirs):
            # The surface repeats exactly, so the reference one period away is the same frame ...
            here = np.array(reference(brownian_tile, *p, 60.0, d))
            there = np.array(reference(brownian_tile, *(p + period[0] - 2 * period[1]), 60.0, d))
            assert np.allclose(here, there, rtol=1e-9, atol=1e-12)
            # ... and it is what the node i = 0 stores.
            err = relative_errors(MODEL, tab.a40[di, 0, j, 0], tab.a320[di, 0, j, 0], *there)
            assert err < 0.03
    # Playback wraps: a point and its images by whole periods read the same amplitudes.
    interp = _as_player_tables(tab, SETTINGS.frame_ms).interpolator
    rng = np.random.default_rng(1)
    u, v = rng.uniform(0, 2.56, 20), rng.uniform(0, 2.56, 20)
    s, d = np.full(20, 60.0), rng.uniform(0, 45, 20)
    a = interp(u, v, s, d)
    b = interp(u + 3 * period[0, 0], v - 2 * period[1, 1], s, d)
    assert np.allclose(a[0], b[0], rtol=1e-5) and np.allclose(a[1], b[1], rtol=1e-5)


@pytest.mark.parametrize("speed", [30.0, 200.0])
def test_reversed_direction_feels_the_same(brownian_small, speed):
    """Reversing the motion reverses the signal in time; the zero-phase weighting and the
    symmetric frame window leave the envelope power unchanged."""
    for u, v, d in ((2.1, 2.6, 10.0), (3.3, 1.7, 75.0), (1.0, 4.0, 150.0)):
        fwd = np.array(point_intensities(brownian_small, MODEL, SETTINGS, straight_path(u, v, speed, d), 0.0))
        back = np.array(point_intensities(brownian_small, MODEL, SETTINGS, straight_path(u, v, speed, d + 180.0), 0.0))
        assert np.allclose(fwd, back, rtol=1e-3)
    with pytest.raises(ValueError, match="180"):
        build_tables(brownian_small, MODEL, SETTINGS, np.array([0.0, 180.0]), np.array([50.0]),
                     table_grid(brownian_small, 1.0))


def test_gratings_have_their_closed_form_tables():
    """On a grating, every table value is the two-colour pair of the tone s |cos d| / lambda."""
    surf = grating(lambda_mm=1.0, amp_um=5.0)
    grid = table_grid(surf, 0.25)
    dirs, speeds = np.array([0.0, 60.0]), np.array([40.0, 160.0])
    tab = build_tables(surf, MODEL, SETTINGS, dirs, speeds, grid)
    for di, d in enumerate(dirs):
        for si, s in enumerate(speeds):
            want = tone_pair(s * abs(np.cos(np.deg2rad(d))) / 1.0, 5.0)
            assert np.allclose(tab.a40[di, si], want[0], rtol=0.01, atol=1e-3)
            assert np.allclose(tab.a320[di, si], want[1], rtol=0.01, atol=1e-3)


def test_cubic_speed_midpoints_are_checked_as_between_nodes(brownian_small):
    """Stored speeds include cubic midpoints, which were not computed: the families that hold
    the speed at a node draw computed speeds only, and the speed and stroke families draw the
    midpoints as well as the geometric means between stored speeds."""
    computed = np.geomspace(10.0, 200.0, 8)
    stored = stored_speeds(computed, True)
    midpoints = stored[1::2]
    grid = table_grid(brownian_small, 0.25)
    points = check_points(np.arange(12) * 15.0, stored, grid, seed=3, per_family=400, computed_speed_mm_s=computed)
    speeds = {f: np.array([s for fam, _, s, _ in points if fam == f]) for f in ("direction", "speed", "position", "stroke")}
    for f in ("direction", "position"):
        assert np.isin(speeds[f], computed).all()
    between = np.sqrt(stored[:-1] * stored[1:])
    for f in ("speed", "stroke"):
        assert np.isin(speeds[f], np.concatenate([between, midpoints])).all()
        # each midpoint as often as a node there (half its two intervals): 7 of 21 equal shares
        assert np.isin(speeds[f], midpoints).mean() == pytest.approx(7 / 21, abs=0.07)
    # Without the computed speeds every stored speed counts as a node (explicit speed lists).
    plain = check_points(np.arange(12) * 15.0, stored, grid, seed=3, per_family=400)
    assert np.isin([s for fam, _, s, _ in plain if fam == "position"], midpoints).any()


def test_check_tables_measures_interpolation_between_nodes():
    """check_tables' families hit the mid-points between nodes; on a grating the error there is known.

    Directions 0 and 90 deg at 80 mm/s: the mid-direction 45 deg (or 135) is a tone at 80/sqrt(2) Hz
    while playback averages the 80 Hz pair and silence. Speeds 40 and 160 at 0 deg: the mid-speed 80
    mm/s is an 80 Hz tone while playback averages the 40 Hz and 160 Hz pairs.
    """
    surf = grating(lambda_mm=1.0, amp_um=5.0)
    grid = table_grid(surf, 0.25)
    amp = 5.0

    tab = build_tables(surf, MODEL, SETTINGS, np.array([0.0, 90.0]), np.array([80.0]), grid)
    stats = check_tables(surf, MODEL, SETTINGS, tab, seed=3, per_family=4)
    mid = np.array(tone_pair(80.0 / np.sqrt(2.0), amp))
    played = 0.5 * np.array(tone_pair(80.0, amp))
    want = float(relative_errors(MODEL, played[0], played[1], mid[0], mid[1]))
    assert want > 0.2  # a large, easily measured interpolation error
    assert stats["rms_rel_error_direction"] == pytest.approx(want, rel=0.03)
    # At node directions and speeds only the position varies, and a grating's tables are flat.
    assert stats["rms_rel_error_position"] < 0.01

    tab = build_tables(surf, MODEL, SETTINGS, np.array([0.0]), np.array([40.0, 160.0]), grid)
    stats = check_tables(surf, MODEL, SETTINGS, tab, seed=4, per_family=4)
    ref = np.array(tone_pair(80.0, amp))
    played = 0.5 * (np.array(tone_pair(40.0, amp)) + np.array(tone_pair(160.0, amp)))  # linear in log speed
    want = float(relative_errors(MODEL, played[0], played[1], ref[0], ref[1]))
    assert want > 0.05
    # The speed family keeps the node direction (0 deg): exactly the case above.
    assert stats["rms_rel_error_speed"] == pytest.approx(want, rel=0.03)


def test_check_tables_detects_wrong_tables(brownian_tile):
    grid = table_grid(brownian_tile, 0.25)
    tab = build_tables(brownian_tile, MODEL, SETTINGS, np.arange(6) * 30.0, np.array([40.0, 80.0]), grid)
    good = check_tables(brownian_tile, MODEL, SETTINGS, tab, seed=0, per_family=4)
    bad_tab = Tables(1.5 * tab.a40, 1.5 * tab.a320, tab.intensity_p, tab.intensity_np, tab.out_of_gamut,
                     tab.direction_deg, tab.speed_mm_s, tab.grid)
    bad = check_tables(brownian_tile, MODEL, SETTINGS, bad_tab, seed=0, per_family=4)
    # Same samples (same seed): every amplitude 50 % too large, so the error is 0.5 +- the tables' own.
    assert abs(bad["rms_rel_error"] - 0.5) <= good["max_rel_error"] * 1.5 + 1e-3
    assert bad["n_check_samples"] == good["n_check_samples"] == 16  # 4 families x 4


def test_build_checked_tables_meets_the_tolerance_and_stores_stats(brownian_tile):
    scene = dataclasses.replace(default_scene(), tolerance=0.05, speed_range_mm_s=(30.0, 120.0))
    tables, stats, plan = build_checked_tables(brownian_tile, MODEL, SETTINGS, scene, seed=2)
    for key in ("rms_rel_error", "max_rel_error", "p95_rel_error", "n_check_samples", "tolerance",
                "tolerance_met", "refinements", "rms_rel_error_direction", "rms_rel_error_speed",
                "rms_rel_error_position"):
        assert key in stats
    assert stats["tolerance_met"] and stats["rms_rel_error"] <= 0.05 and stats["tolerance"] == 0.05
    assert stats["refinements"][-1]["rms_rel_error"] == stats["rms_rel_error"]
    assert tables.speed_mm_s[0] == pytest.approx(30.0) and tables.speed_mm_s[-1] == pytest.approx(120.0)
    assert np.all((tables.direction_deg >= 0) & (tables.direction_deg < 180))
    # The stored figure is a measurement: a fresh sample of the same tables agrees with it.
    fresh = check_tables(brownian_tile, MODEL, SETTINGS, tables, seed=99)
    assert fresh["rms_rel_error"] <= 2.0 * max(stats["rms_rel_error"], 0.01)


def test_build_checked_tables_stores_what_check_tables_measures(brownian_tile):
    """The compiler renders each round's check references while it builds the tables; the stored
    statistics are still exactly those of :func:`check_tables` on the final tables (same seed)."""
    scene = dataclasses.replace(default_scene(), tolerance=0.05, speed_range_mm_s=(30.0, 120.0))
    tables, stats, plan = build_checked_tables(brownian_tile, MODEL, SETTINGS, scene, seed=2)
    last = len(stats["refinements"]) - 1
    again = check_tables(brownian_tile, MODEL, SETTINGS, tables, seed=2 + last, direction_range_deg=scene.direction_range_deg,
                         computed_speed_mm_s=plan.speeds_mm_s, draws=stats["check_draws"])
    for key, value in again.items():
        assert stats[key] == value, key


def test_an_uncertain_pass_draws_more_check_points(brownian_tile, monkeypatch):
    """A round whose measured error meets the tolerance while its upper bound does not pools
    another draw of points before the tables are taken: here the bound is made 100 x the RMS
    for one draw's 64 errors and the RMS itself for more, so exactly one draw is added."""
    import haptex_compile.compile as compile_mod

    monkeypatch.setattr(compile_mod, "rms_upper_bound",
                        lambda errors, seed=0: float(np.sqrt(np.mean(np.square(errors)))) * (100.0 if len(errors) <= 64 else 1.0))
    scene = dataclasses.replace(default_scene(), tolerance=0.05, speed_range_mm_s=(30.0, 120.0))
    tables, stats, plan = build_checked_tables(brownian_tile, MODEL, SETTINGS, scene, seed=2)
    assert stats["tolerance_met"] and stats["check_draws"] == 2 and stats["n_check_samples"] == 128
    assert stats["refinements"][-1]["n_check_samples"] == 128
    last = len(stats["refinements"]) - 1
    pooled = check_tables(brownian_tile, MODEL, SETTINGS, tables, seed=2 + last, direction_range_deg=scene.direction_range_deg,
                          computed_speed_mm_s=plan.speeds_mm_s, draws=2)
    assert pooled["n_check_samples"] == 128 and pooled["rms_rel_error"] == stats["rms_rel_error"]


def test_tables_from_a_shared_pool_equal_their_own(brownian_tile):
    """build_tables on a caller's pool (with work queued behind its directions) gives the same
    tables as on its own threads."""
    from concurrent.futures import ThreadPoolExecutor

    grid = table_grid(brownian_tile, 0.25)
    dirs, speeds = np.arange(6) * 30.0, np.geomspace(20.0, 160.0, 5)
    own = build_tables(brownian_tile, MODEL, SETTINGS, dirs, speeds, grid, speed_midpoints=True)
    queued = []
    with ThreadPoolExecutor(max_workers=2) as pool:
        shared = build_tables(brownian_tile, MODEL, SETTINGS, dirs, speeds, grid, speed_midpoints=True, pool=pool,
                              after_submit=lambda: queued.append(pool.submit(lambda: 42)))
    assert queued[0].result() == 42
    for name in ("a40", "a320", "intensity_p", "intensity_np", "out_of_gamut", "speed_mm_s"):
        assert np.array_equal(getattr(own, name), getattr(shared, name)), name


def test_rms_upper_bound_covers_the_true_rms_95_percent_of_the_time():
    # 64 half-normal errors of RMS 1 %: the true RMS is below the bound in 95 % of samples
    # (binomial SD over 400 samples: 1.1 %).
    rng = np.random.default_rng(1)
    covered = [rms_upper_bound(np.abs(rng.normal(0.0, 0.01, 64)), seed=i) >= 0.01 for i in range(400)]
    assert 0.92 <= np.mean(covered) <= 0.98
    e = np.abs(rng.normal(0.0, 0.01, 64))
    assert rms_upper_bound(e) >= np.sqrt(np.mean(e**2))


def _predicted_after(stats: dict, axes: list[str]) -> float:
    """RMS error left after halving `axes`: each axis's own share (family minus position, in
    quadrature) divided by 3 per halving, as the refinement plans."""
    pos = stats["rms_rel_error_position"]
    share = {"position": pos, **{a: np.sqrt(max(stats[f"rms_rel_error_{a}"] ** 2 - pos**2, 0.0)) for a in ("direction", "speed")}}
    return float(np.sqrt(sum((v / 3.0 ** axes.count(a)) ** 2 for a, v in share.items())))


def _values_after(axes: list[str]) -> int:
    """How many times the tables' values grow by halving `axes` (2 per direction or speed
    halving, 4 per grid halving)."""
    return 2 ** axes.count("direction") * 2 ** axes.count("speed") * 4 ** axes.count("position")


def test_refinement_halves_each_axis_as_often_as_its_share_needs():
    # Only speed is off (share 2.97 %): one halving (to 0.99 %) fits the budget of 1.7 %.
    stats = {"rms_rel_error_position": 0.004, "rms_rel_error_direction": 0.005, "rms_rel_error_speed": 0.03}
    assert axes_to_refine(stats, 0.02) == ["speed"]
    assert _predicted_after(stats, ["speed"]) <= 0.85 * 0.02 < _predicted_after(stats, [])


def test_refinement_plans_the_fewest_values_over_rounds():
    # A fine weave's first round (cotton poplin): direction share 5.81 %, position 1.6 %, speed
    # none. Three direction halvings fit the budget (0.22 and 1.6: 1.61 %) with 8 x the values;
    # two direction halvings and a grid halving also fit (0.65 and 0.53: 0.84 %) with 16 x.
    stats = {"rms_rel_error_position": 0.016, "rms_rel_error_direction": 0.0603, "rms_rel_error_speed": 0.0142}
    plan = ["direction"] * 3
    assert _predicted_after(stats, plan) <= 0.85 * 0.02 < _predicted_after(stats, ["direction"] * 2)
    assert _values_after(plan) < _values_after(["direction", "direction", "position"])
    # This round takes two of the three; the next round's measurement decides on the third.
    assert axes_to_refine(stats, 0.02) == ["direction", "direction"] == plan[:MAX_HALVINGS_PER_ROUND]


def test_refinement_keeps_the_room_for_the_largest_share():
    # A slub weave photo's first round: direction share 18.86 %, speed 1.68 %, position 1.3 %.
    stats = {"rms_rel_error_position": 0.013, "rms_rel_error_direction": 0.189, "rms_rel_error_speed": 0.0212}
    # The plan: directions 3 times (0.70 %) and speeds once (0.56 %), with position's 1.3 %:
    # 1.58 % in 16 x the values. The grid is not halved, nor speeds a second time, although
    # the largest share stays above the budget after this round's two direction halvings.
    plan = ["direction"] * 3 + ["speed"]
    assert _predicted_after(stats, plan) <= 0.85 * 0.02
    assert axes_to_refine(stats, 0.02) == ["direction", "direction", "speed"]
    # With room for 10 x the values no plan fits the budget: the least error within it is the
    # three direction halvings (2.23 %; two and a speed halving, also 8 x: 2.53 %).
    assert _predicted_after(stats, ["direction"] * 3) < _predicted_after(stats, ["direction"] * 2 + ["speed"])
    assert axes_to_refine(stats, 0.02, room=10.0) == ["direction", "direction"]
    # With one direction halving left (the node limit) nothing fits either: the plan takes it
    # and every halving of the others worth taking (speed 1.68 -> 0.56 -> 0.19 %, position
    # 1.3 -> 0.43 %, none halved below a quarter of the tolerance).
    limited = axes_to_refine(stats, 0.02, limits={"direction": 1, "speed": 3, "position": 3})
    assert limited == ["direction", "speed", "speed", "position"]


def test_refinement_halves_an_axis_at_most_twice_per_round():
    stats = {"rms_rel_error_position": 0.01, "rms_rel_error_direction": 0.5, "rms_rel_error_speed": 0.01}
    axes = axes_to_refine(stats, 0.02)
    assert axes.count("direction") == MAX_HALVINGS_PER_ROUND == 2
    # position's share (1 %) is above a quarter of the tolerance: halved once; speed has no share of its own
    assert axes == ["direction", "direction", "position"]


def test_build_checked_tables_refines_until_the_tolerance_is_met():
    """A grating at 45-degree steps misses 5 %: the compiler must add direction nodes."""
    surf = grating(lambda_mm=1.0, amp_um=5.0)
    scene = dataclasses.replace(default_scene(), tolerance=0.05, speeds_mm_s=(80.0,))
    tables, stats, plan = build_checked_tables(surf, MODEL, SETTINGS, scene, seed=0)
    history = stats["refinements"]
    assert len(history) >= 2 and history[0]["rms_rel_error"] > 0.05
    assert history[-1]["directions"] > history[0]["directions"]
    assert stats["tolerance_met"] and stats["rms_rel_error"] <= 0.05
    # The tone is at 80 |cos d| Hz: it sweeps through the band's low edge (10 Hz) within 7 deg
    # of 90 deg, where the amplitudes change fastest; the added nodes go there.
    d = plan.directions_deg
    near_ridges = np.sum(np.abs(d - 90.0) <= 15.0)
    across = np.sum(np.minimum(d, 180.0 - d) <= 15.0)
    assert near_ridges >= 3 * across


def test_refinement_falls_back_to_another_axis(monkeypatch):
    """When the axis asked for cannot be refined (an explicit grid spacing), the others are:
    directions are added (the speed list is explicit too)."""
    import haptex_compile.compile as compile_mod

    surf = grating(lambda_mm=1.0, amp_um=5.0)
    scene = dataclasses.replace(default_scene(), tolerance=0.001, speeds_mm_s=(80.0,), grid_spacing_mm=0.25)
    monkeypatch.setattr(compile_mod, "axes_to_refine", lambda stats, tol, **limits: ["position"])
    monkeypatch.setattr(compile_mod, "MAX_REFINEMENTS", 1)
    _, stats, plan = build_checked_tables(surf, MODEL, SETTINGS, scene, seed=0)
    history = stats["refinements"]
    assert len(history) == 2 and history[1]["directions"] > history[0]["directions"]
    assert history[1]["spacing_mm"] == history[0]["spacing_mm"]


def test_tables_and_renderer_sample_the_same_surface(brownian_small):
    """Both go through the same continuous (B-spline) surface: heights match scipy's evaluation."""
    from scipy import ndimage

    from haptex_compile.surface import pixel_coordinates, spline_coefficients

    rng = np.random.default_rng(5)
    u, v = rng.uniform(-3, 8, 200), rng.uniform(-3, 8, 200)  # inside and beyond the edges (mirror)
    x, y = pixel_coordinates(brownian_small, u, v)
    scipy_h = ndimage.map_coordinates(spline_coefficients(brownian_small), np.stack([y, x]), order=3,
                                      prefilter=False, mode="mirror")
    assert np.allclose(sample_height(brownian_small, u, v), scipy_h, atol=1e-9)


def test_a_wrapping_surface_is_sampled_the_same_anywhere():
    """A tile whose lattice is its array: heights at u + m t1 + n t2 equal those at u, and both
    equal the spline read at the point moved into the reference cell."""
    from scipy import ndimage

    from haptex_compile.surface import pixel_coordinates, spline_coefficients

    rng = np.random.default_rng(6)
    surf = periodic_surface_from_tile(rng.standard_normal((50, 70)), 20.0)  # 1.4 x 1.0 mm
    u, v = rng.uniform(-50, 50, 500), rng.uniform(-50, 50, 500)
    x, y = pixel_coordinates(surf, u, v)
    in_cell = ndimage.map_coordinates(spline_coefficients(surf), np.stack([y, x]), order=3, prefilter=False,
                                      mode="grid-wrap")
    assert np.allclose(sample_height(surf, u, v), in_cell, atol=1e-9)
    assert np.allclose(sample_height(surf, u + 7 * 1.4, v - 3 * 1.0), sample_height(surf, u, v), atol=1e-9)


def test_sheared_fast_path_agrees_with_rotated_lines_and_the_reference(brownian_small):
    """Both table algorithms evaluate the same definition: at nodes they agree with the
    reference renderer (and so with each other) to well within the 2 % default tolerance."""
    from haptex_compile.line_analysis import direction_powers
    from haptex_compile.tables import _direction_powers, line_sampler

    rng = np.random.default_rng(5)
    nodes = rng.uniform(0.5, 4.5, (6, 2))
    speeds = np.array([12.0, 60.0, 180.0])
    fast_err, slow_err = [], []
    for d in (0.0, 35.0, 100.0):
        fast = MODEL.decompose(*np.sqrt(direction_powers(line_sampler(brownian_small), MODEL, SETTINGS, nodes, d, speeds)).transpose(1, 0, 2))
        slow = MODEL.decompose(*np.sqrt(_direction_powers(brownian_small, MODEL, SETTINGS, nodes, d, speeds)).transpose(1, 0, 2))
        for si, s in enumerate(speeds):
            for n, p in enumerate(nodes):
                r40, r320 = reference(brownian_small, p[0], p[1], s, d)
                fast_err.append(relative_errors(MODEL, fast.a40[si, n], fast.a320[si, n], r40, r320))
                slow_err.append(relative_errors(MODEL, slow.a40[si, n], slow.a320[si, n], r40, r320))
    fast_err, slow_err = np.array(fast_err), np.array(slow_err)
    assert np.sqrt(np.mean(fast_err**2)) < 0.01 and fast_err.max() < 0.04
    assert np.sqrt(np.mean(slow_err**2)) < 0.015


def test_not_a_knot_weights_are_scipys_cubic_spline():
    from scipy.interpolate import CubicSpline

    from haptex_compile.tables import not_a_knot_weights

    rng = np.random.default_rng(2)
    for n in (4, 5, 9, 22):
        x = np.sort(rng.uniform(0.0, 3.0, n)) + np.arange(n) * 0.05  # uneven, strictly increasing
        t = np.concatenate([rng.uniform(x[0] - 0.2, x[-1] + 0.2, 30), x])
        want = CubicSpline(x, np.eye(n), axis=0)(t)
        assert np.allclose(not_a_knot_weights(x, t), want, rtol=0, atol=1e-12)


def test_speed_midpoints_are_the_log_speed_cubic_spline_through_the_nodes():
    from scipy.interpolate import CubicSpline

    speeds = np.geomspace(10.0, 200.0, 9)
    x = np.random.default_rng(0).random((3, 9, 5, 4)).astype(np.float32) - 0.1  # some negative: clamped
    new_speeds, dense = speed_midpoints_of(speeds, x)
    mids = np.sqrt(speeds[:-1] * speeds[1:])
    assert np.allclose(new_speeds[0::2], speeds) and np.allclose(new_speeds[1::2], mids)
    assert np.array_equal(dense[:, 0::2], x)
    spline = CubicSpline(np.log(speeds), x.astype(float), axis=1)(np.log(mids))
    assert np.allclose(dense[:, 1::2], np.maximum(spline, 0.0), atol=1e-6)


def test_pixels_coarser_than_the_footprint_agree_with_rotated_lines():
    """Pixels of 0.5 mm (twice the footprint sigma): the averaging kernel reaches beyond the
    frequencies the lines' power holds, where it is zero. The fast path used to fail there
    (arrays of those two lengths multiplied); it gives what the rotated lines give."""
    from haptex_compile.line_analysis import direction_powers
    from haptex_compile.tables import _direction_powers, line_sampler

    surf = Surface(brownian_surface((16, 16), 0.5, pixel_size_um=500.0, rms_um=50.0, seed=1), 500.0)
    nodes = np.random.default_rng(5).uniform(1.0, 7.0, (6, 2))
    speeds = np.array([12.0, 60.0, 180.0])
    for d in (0.0, 35.0):
        fast = direction_powers(line_sampler(surf), MODEL, SETTINGS, nodes, d, speeds)
        slow = _direction_powers(surf, MODEL, SETTINGS, nodes, d, speeds)
        assert np.isfinite(fast).all() and fast.min() >= 0
        assert np.abs(fast - slow).max() < 0.1 * np.abs(slow).max()


def test_a_surface_out_of_scale_for_the_tables_is_refused_with_its_sizes(brownian_small, monkeypatch):
    # Pixels far finer than the scene needs (lines of millions of samples) or an extent far
    # larger (grids of millions of footprint cells) exhausted the memory (killed, or a
    # traceback); the analysis refuses an array above its limit before allocating it.
    from haptex_compile import line_analysis
    from haptex_compile.errors import InputError
    from haptex_compile.tables import line_sampler

    nodes = np.array([[2.0, 2.0], [3.0, 2.5]])
    speeds = np.array([12.0, 180.0])
    assert np.isfinite(line_analysis.direction_powers(line_sampler(brownian_small), MODEL, SETTINGS, nodes, 0.0, speeds)).all()
    monkeypatch.setattr(line_analysis, "MAX_ARRAY_BYTES", 2 ** 20)
    with pytest.raises(InputError, match=r"the surface \(250 x 250 px of 20 um, 5 x 5 mm\) is out of scale for the tables: its lines"):
        line_analysis.direction_powers(line_sampler(brownian_small), MODEL, SETTINGS, nodes, 0.0, speeds)


def test_a_frame_out_of_scale_for_the_reference_renderer_is_refused_before_sampling(monkeypatch):
    # A 16 px map of 0.001 um pixels: one frame's stroke at 200 mm/s spans 0.3 s, 60 mm, which
    # is 6e7 of its pixels; the reference renderer (the compiler's check, haptex-play --mode
    # direct) sampled it at that step on 25 footprint paths and was killed at 24 GB. It is
    # refused with the sizes before anything of that size is made. Here at 0.2 um pixels
    # under a 16 MiB limit (66 MB of heights: a regression allocates about 0.5 GB, not 24).
    import re

    from haptex_compile import render
    from haptex_compile.errors import InputError

    monkeypatch.setattr(render, "MAX_STROKE_BYTES", 2 ** 24)
    surf = Surface(np.random.default_rng(2).normal(size=(16, 16)), 0.2)
    with traced_peak() as peak, pytest.raises(InputError) as refused:
        point_intensities(surf, MODEL, SETTINGS, straight_path(0.0, 0.0, 200.0, 30.0), 0.0)
    assert peak[0] < 2 ** 20
    m = re.fullmatch(r"the surface \(16 x 16 px of 0\.2 um, 0\.0032 x 0\.0032 mm\) is out of scale for the reference"
                     r" renderer: the heights of (\d+) x (\d+) path samples would take ([0-9.]+) GiB, above 0\.0156 GiB"
                     r" per frame \(at 200 mm/s\); give it coarser pixels \(resample it\) or check its pixel size",
                     str(refused.value))
    assert m, str(refused.value)
    paths, samples = int(m.group(1)), int(m.group(2))
    assert samples * 0.2e-3 >= 0.3 * 200.0  # the stroke (mm) at a step no longer than a pixel
    assert float(m.group(3)) == pytest.approx(8 * paths * samples / 2 ** 30, abs=0.05)
    # The limit is on that array: a frame of 20 um pixels passes; under a limit one byte below
    # its heights it is refused.
    ok = Surface(np.random.default_rng(2).normal(size=(64, 64)), 20.0)
    path = straight_path(0.3, 0.3, 80.0, 30.0)
    monkeypatch.setattr(render, "MAX_STROKE_BYTES", 0)
    with pytest.raises(InputError, match="reference renderer") as refused:
        point_intensities(ok, MODEL, SETTINGS, path, 0.0)
    paths, samples = (int(v) for v in re.search(r"the heights of (\d+) x (\d+)", str(refused.value)).groups())
    monkeypatch.setattr(render, "MAX_STROKE_BYTES", 8 * paths * samples - 1)
    with pytest.raises(InputError, match="reference renderer"):
        point_intensities(ok, MODEL, SETTINGS, path, 0.0)
    monkeypatch.setattr(render, "MAX_STROKE_BYTES", 8 * paths * samples)
    assert np.isfinite(point_intensities(ok, MODEL, SETTINGS, path, 0.0)).all()


def test_a_refused_surface_does_not_wait_for_the_queued_check_frames(brownian_small, monkeypatch):
    # The check's reference frames are queued behind the tables' directions on the same two
    # threads; when the tables fail (a surface out of scale), the queued frames are cancelled:
    # only the two already running finish. Each frame here takes 0.5 s, and a round has dozens.
    import time

    from haptex_compile import compile as compile_module
    from haptex_compile.errors import InputError

    started = []

    def slow_reference(*args):
        started.append(1)
        time.sleep(0.5)
        return 1.0, 1.0

    def failing_tables(*args, after_submit=None, **kwargs):
        after_submit()
        time.sleep(0.1)  # the two threads take their first frames
        raise InputError(None, "out of scale")

    monkeypatch.setattr(compile_module, "reference_amplitudes", slow_reference)
    monkeypatch.setattr(compile_module, "build_tables", failing_tables)
    t0 = time.perf_counter()
    with pytest.raises(InputError, match="out of scale"):
        build_checked_tables(brownian_small, MODEL, SETTINGS, default_scene())
    assert time.perf_counter() - t0 < 2.0
    time.sleep(0.6)
    assert len(started) == compile_module.CHECK_WORKERS < 8


def test_footprint_grids_out_of_scale_are_refused_before_their_kernels_are_made():
    # Pixels of 1 km (a unit mistaken): a 128 px map took 6.3 GB in the grids' kernels (each
    # about a quarter of the grids' values, several alive at once) before the grids' own size
    # was checked. The check comes first now; on 32 px the kernels made 137 MB first.
    from haptex_compile import line_analysis
    from haptex_compile.errors import InputError
    from haptex_compile.tables import line_sampler

    surf = Surface(np.random.default_rng(1).normal(size=(32, 32)), 1e6)
    ext = 31 * 1000.0
    nodes = np.array([[0.0, 0.0], [ext, ext], [ext, 0.0]])
    with traced_peak() as peak, pytest.raises(InputError, match=r"its footprint grids \(8 x 2 x \d+ x \d+\) would take [0-9.]+ GiB"):
        line_analysis.direction_powers(line_sampler(surf), MODEL, SETTINGS, nodes, 0.0, np.geomspace(150.0, 190.0, 8))
    assert peak[0] < 16 * 2 ** 20


def test_a_crawling_contactor_feels_nothing_and_a_long_frame_is_refused_for_its_speed():
    # At 0.001 mm/s the footprint (4 sigma of 0.25 mm each side) takes 1000 s to pass: the
    # frame's window would be 2 x (25 ms + 1000 s + the 300 ms margin) = 2001 s, sampled at the
    # analysis rate (2048 Hz). On 20 um pixels every resolved frequency (0.9 x 25 cyc/mm) is
    # then below 0.5 Hz, 1/20 of the band's low edge, where the band weighs under 6.3e-6:
    # nothing is felt, and nothing is sampled.
    from haptex_compile import render
    from haptex_compile.errors import InputError

    surf = Surface(brownian_surface((64, 64), 0.7, pixel_size_um=20.0, rms_um=5.0, seed=1), 20.0)
    cutoff = render.CRAWL_FRACTION * MODEL.band.low_hz / (0.9 * 0.5 / 0.02)  # mm/s
    with traced_peak() as peak:
        assert point_intensities(surf, MODEL, SETTINGS, straight_path(0.6, 0.6, 0.001, 30.0), 0.0) == (0.0, 0.0)
        assert point_intensities(surf, MODEL, SETTINGS, straight_path(0.6, 0.6, 0.99 * cutoff, 30.0), 0.0) == (0.0, 0.0)
    assert peak[0] < 2 ** 20
    # Just above the cutoff the frame is rendered, and is negligible: no step where the cutoff
    # lies. (On 200 um pixels, whose cutoff is 10 x higher and its window 10 x shorter; its
    # intensity measured 1.3e-7 of that at 100 mm/s.)
    coarse = Surface(brownian_surface((64, 64), 0.7, pixel_size_um=200.0, rms_um=5.0, seed=1), 200.0)
    cutoff = render.CRAWL_FRACTION * MODEL.band.low_hz / (0.9 * 0.5 / 0.2)
    assert point_intensities(coarse, MODEL, SETTINGS, straight_path(6.0, 6.0, 0.99 * cutoff, 30.0), 0.0) == (0.0, 0.0)
    slow = point_intensities(coarse, MODEL, SETTINGS, straight_path(6.0, 6.0, 1.01 * cutoff, 30.0), 0.0)
    felt = point_intensities(coarse, MODEL, SETTINGS, straight_path(6.0, 6.0, 100.0, 30.0), 0.0)
    assert 0.0 < max(slow) < 1e-5 * max(felt)
    # On 1 um pixels 0.005 mm/s is above the cutoff (0.0011 mm/s), and its 400 s window on
    # 2001 paths one pixel apart would be 13 GB of heights: refused, and the speed named as
    # the cause (the samples are the analysis rate's, not the pixels').
    fine = Surface(np.random.default_rng(2).normal(size=(64, 64)), 1.0)
    with pytest.raises(InputError, match=r"per frame \(at 0\.005 mm/s\); the frame's window spans 400\.\d s at that speed"
                                         r" \(the footprint's passage\); raise the scene's slowest speed$"):
        point_intensities(fine, MODEL, SETTINGS, straight_path(0.03, 0.03, 0.005, 30.0), 0.0)
