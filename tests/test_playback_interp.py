"""Table interpolation: the scheme of docs/interpolation.md, checked against exact expectations."""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from playback.asset import Tables
from playback.interp import ABOVE_RANGE, BELOW_RANGE, INVALID, OUTSIDE, table_amplitudes
from asset_factory import make_table_arrays


def tables_from(fn, dirs, speeds, origin=(0.0, 0.0), basis=((1.0, 0.0), (0.0, 1.0)), nj=4, ni=5, periodic=False):
    origin = np.asarray(origin, float)
    basis = np.asarray(basis, float)
    a40, a320 = make_table_arrays(fn, np.asarray(dirs, float), np.asarray(speeds, float), origin, basis, nj, ni)
    return Tables(a40=a40, a320=a320, direction_deg=dirs, speed_mm_s=speeds, origin_mm=origin,
                  grid_basis_mm=basis, periodic=periodic)


def linear_field(d, s, u, v):
    """Bilinear interpolation reproduces a field linear in (u, v) exactly; direction/speed constant."""
    a40 = 3.0 + 0.5 * u + 0.25 * v + 0 * d + 0 * s
    return a40, 2 * a40


def test_oblique_basis_reproduces_linear_field():
    # A very oblique lattice (60° between g_i and g_j), offset origin.
    basis = np.array([[0.5, 0.1], [0.3, 0.45]])
    t = tables_from(linear_field, [0.0], [50.0], origin=(-1.0, 2.0), basis=basis, nj=6, ni=7)
    rng = np.random.default_rng(1)
    ij = rng.uniform([0, 0], [6, 5], size=(200, 2))  # inside the grid
    p = np.array([-1.0, 2.0]) + ij[:, :1] * basis[0] + ij[:, 1:] * basis[1]
    a40, a320, flags = table_amplitudes(t, p[:, 0], p[:, 1], np.full(200, 50.0), np.zeros(200))
    expect = 3.0 + 0.5 * p[:, 0] + 0.25 * p[:, 1]
    np.testing.assert_allclose(a40, expect, rtol=1e-5)
    np.testing.assert_allclose(a320, 2 * expect, rtol=1e-5)
    assert not flags.any()


def test_outside_mirrors_surface_and_direction_and_flags():
    # Beyond the edge the surface is its mirror image (nodes u = 0..4): u = -3 reads u = 3,
    # u = 10 reads u = 2 (reflected twice).
    t = tables_from(linear_field, [0.0], [50.0], nj=4, ni=5)
    a40, _, flags = table_amplitudes(t, [-3.0, 10.0, 2.0], [1.0, 1.0, 1.0], [50.0] * 3, [0.0] * 3)
    np.testing.assert_allclose(a40, [3.0 + 1.5 + 0.25, 3.0 + 1.0 + 0.25, 3.0 + 1.0 + 0.25], rtol=1e-6)
    assert list(flags) == [OUTSIDE, OUTSIDE, 0]
    # A reflection in u maps direction d to 180 - d, one in v maps d to -d (mod 180).
    t = tables_from(dir_field, np.arange(0.0, 180.0, 15.0), [50.0], nj=4, ni=5)
    a40, _, _ = table_amplitudes(t, [-1.0, 2.0, -1.0], [1.0, -1.0, -1.0], [50.0] * 3, [30.0] * 3)
    np.testing.assert_allclose(a40, [10.0 + 15.0, 10.0 + 15.0, 10.0 + 3.0], rtol=1e-6)


def test_periodic_wraps_both_axes():
    def f(d, s, u, v):
        a = 1.0 + np.cos(2 * np.pi * u / 4.0) + 0.5 * np.sin(2 * np.pi * v / 3.0) + 0 * d + 0 * s
        return a + 1.0, a + 2.0
    t = tables_from(f, [0.0], [50.0], nj=12, ni=16, basis=((0.25, 0), (0, 0.25)), periodic=True)
    u = np.array([0.3, 1.7, -2.2])
    v = np.array([0.4, 2.9, -1.1])
    base = table_amplitudes(t, u, v, [50.0] * 3, [0.0] * 3)
    shifted = table_amplitudes(t, u + 4.0 * 3, v - 3.0 * 5, [50.0] * 3, [0.0] * 3)  # whole periods
    np.testing.assert_allclose(shifted[0], base[0], rtol=1e-9)
    assert not shifted[2].any()
    # Between the last node (i = 15) and node 0 of the next period: the average of the two.
    mid = table_amplitudes(t, [15.5 * 0.25], [0.0], [50.0], [0.0])[0]
    assert mid[0] == pytest.approx(0.5 * (t.a40[0, 0, 0, 15] + t.a40[0, 0, 0, 0]), rel=1e-6)


def dir_field(d, s, u, v):
    a = 10.0 + d / 10.0 + 0 * s + 0 * u + 0 * v  # 10 at 0°, 26.5 at 165°
    return a, a


def test_direction_mod_180_and_periodic_wrap():
    dirs = np.arange(0.0, 180.0, 15.0)
    t = tables_from(dir_field, dirs, [50.0])
    q = np.array([30.0, 210.0, -150.0, 37.5, 172.5, -7.5, 352.5])
    a40, _, _ = table_amplitudes(t, np.ones(7), np.ones(7), np.full(7, 50.0), q)
    assert a40[0] == pytest.approx(13.0) and a40[1] == pytest.approx(13.0) and a40[2] == pytest.approx(13.0)
    assert a40[3] == pytest.approx(13.75)  # halfway between 30 and 45
    # Between 165° and 180° (= node 0): the average of nodes 165 and 0, from either side.
    assert a40[4] == pytest.approx(0.5 * (26.5 + 10.0))
    assert a40[5] == pytest.approx(0.5 * (26.5 + 10.0))
    assert a40[6] == pytest.approx(0.5 * (26.5 + 10.0))


def test_nonuniform_directions_and_single_direction():
    t = tables_from(dir_field, np.array([10.0, 40.0, 130.0]), [50.0])
    a40, _, _ = table_amplitudes(t, [1.0] * 3, [1.0] * 3, [50.0] * 3, [25.0, 85.0, 170.0])
    assert a40[0] == pytest.approx(11.0 + 1.5)  # halfway 10..40
    np.testing.assert_allclose(a40[1], 14.0 + 0.5 * (23.0 - 14.0), rtol=1e-6)  # halfway 40..130
    # 170° is 40/60 of the way from 130° to 190° (= node 10°).
    np.testing.assert_allclose(a40[2], 23.0 + (40 / 60) * (11.0 - 23.0), rtol=1e-6)
    iso = tables_from(dir_field, np.array([20.0]), [50.0])
    a, _, _ = table_amplitudes(iso, [1.0] * 4, [1.0] * 4, [50.0] * 4, [0.0, 33.0, 95.0, -170.0])
    np.testing.assert_allclose(a, 12.0, rtol=1e-6)


def speed_field(d, s, u, v):
    a = 2.0 + np.log(s) + 0 * d + 0 * u + 0 * v  # linear in log(speed): reproduced exactly
    return a, 0.1 * a


def test_speed_log_linear_fade_and_clamp():
    speeds = np.array([10.0, 40.0, 160.0])
    t = tables_from(speed_field, [0.0], speeds)
    s = np.array([20.0, 100.0, 160.0, 500.0, 5.0, 0.0, 10.0])
    a40, a320, flags = table_amplitudes(t, np.ones(7), np.ones(7), s, np.zeros(7))
    np.testing.assert_allclose(a40[:3], 2.0 + np.log(s[:3]), rtol=1e-6)
    assert a40[3] == pytest.approx(2.0 + np.log(160.0), rel=1e-6) and flags[3] == ABOVE_RANGE
    assert a40[4] == pytest.approx(0.5 * (2.0 + np.log(10.0)), rel=1e-6) and flags[4] == BELOW_RANGE
    assert a40[5] == 0.0 and a320[5] == 0.0  # nothing vibrates at rest
    assert flags[6] == 0


def test_nonfinite_inputs_give_zero_and_invalid():
    t = tables_from(speed_field, [0.0, 90.0], np.array([10.0, 40.0]))
    a40, a320, flags = table_amplitudes(t, [np.nan, 1.0, 1.0, 1.0], [1.0, np.inf, 1.0, 1.0],
                                        [40.0, 40.0, np.nan, 40.0], [0.0, 0.0, 0.0, -np.inf])
    assert np.all(a40 == 0) and np.all(a320 == 0)
    assert np.all(flags == INVALID)


@settings(max_examples=60, deadline=None)
@given(st.lists(st.tuples(st.floats(-1e6, 1e6), st.floats(-1e6, 1e6), st.floats(0, 1e5), st.floats(-1e4, 1e4)),
                min_size=1, max_size=30), st.booleans())
def test_outputs_finite_nonnegative_bounded(points, periodic):
    rng = np.random.default_rng(3)
    dirs = np.array([0.0, 45.0, 90.0, 135.0])
    speeds = np.array([5.0, 50.0, 500.0])
    a40 = rng.uniform(0, 10, (4, 3, 3, 4)).astype(np.float32)
    a320 = rng.uniform(0, 1, (4, 3, 3, 4)).astype(np.float32)
    t = Tables(a40=a40, a320=a320, direction_deg=dirs, speed_mm_s=speeds, origin_mm=[0, 0],
               grid_basis_mm=[[0.3, 0.1], [-0.1, 0.3]], periodic=periodic)
    p = np.array(points)
    r40, r320, _ = table_amplitudes(t, p[:, 0], p[:, 1], p[:, 2], p[:, 3])
    assert np.all(np.isfinite(r40)) and np.all(r40 >= 0) and np.all(r40 <= a40.max() * (1 + 1e-6))
    assert np.all(np.isfinite(r320)) and np.all(r320 >= 0) and np.all(r320 <= a320.max() * (1 + 1e-6))


def test_scalar_and_broadcast_inputs():
    t = tables_from(speed_field, [0.0], np.array([10.0, 40.0]))
    a40, _, _ = table_amplitudes(t, 1.0, [1.0, 2.0], 20.0, 0.0)
    assert a40.shape == (2,)
    np.testing.assert_allclose(a40, 2.0 + np.log(20.0), rtol=1e-6)


# ---------------------------------------------------------------- the player's per-frame path
def _rigid_reference(t, xy, state):
    """The general path the rigid-array lookup must reproduce: kinematics, then table_amplitudes."""
    from playback.trajectory import MotionState, contactor_kinematics

    return table_amplitudes(t, *contactor_kinematics(MotionState(0.0, *state), xy))


@pytest.mark.parametrize("periodic", [True, False])
def test_rigid_array_lookup_equals_general_path(periodic):
    from playback.interp import RigidArrayLookup

    rng = np.random.default_rng(11)
    dirs = np.array([5.0, 40.0, 95.0, 150.0])  # non-uniform, first node not at 0°
    speeds = np.array([8.0, 30.0, 120.0])
    a40 = rng.uniform(0, 10, (4, 3, 6, 7)).astype(np.float32)
    a320 = rng.uniform(0, 2, (4, 3, 6, 7)).astype(np.float32)
    basis = np.array([[0.3, 0.05], [-0.04, 0.25]])  # oblique
    t = Tables(a40=a40, a320=a320, direction_deg=dirs, speed_mm_s=speeds, origin_mm=[0.2, -0.1],
               grid_basis_mm=basis, periodic=periodic)
    xy = rng.uniform(-0.2, 0.2, (9, 2))  # small array: stays inside the non-periodic grid
    lookup = RigidArrayLookup(t.interpolator, xy)
    centre = np.array([0.2, -0.1]) + 3.0 * basis[0] + 2.5 * basis[1]
    flags_seen = 0
    for k in range(400):
        u0, v0 = centre + rng.uniform(-0.15, 0.15, 2) + (rng.uniform(-30, 30, 2) if periodic else 0.0)
        vel = rng.normal(0, 60, 2) * (0.0 if k % 9 == 0 else 1.0)  # at rest: fades to 0
        if k % 7 == 0:
            vel = vel * 20.0  # above the top node
        state = (u0, v0, rng.uniform(-400, 400), vel[0], vel[1], rng.normal(0, 200) * (k % 2))
        got = lookup(*state)
        assert got is not None
        want = _rigid_reference(t, xy, state)
        np.testing.assert_allclose(got[0], want[0], rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(got[1], want[1], rtol=1e-12, atol=1e-12)
        np.testing.assert_array_equal(got[2], want[2])
        flags_seen |= int(np.bitwise_or.reduce(got[2]))
    assert flags_seen == ABOVE_RANGE | BELOW_RANGE  # both speed clamps were exercised


def test_rigid_array_lookup_defers_outside_and_nonfinite_to_general_path():
    from playback.interp import RigidArrayLookup

    t = tables_from(linear_field, [0.0], [50.0], nj=4, ni=5)
    xy = np.array([[0.0, 0.0], [1.0, 0.0]])
    lookup = RigidArrayLookup(t.interpolator, xy)
    assert lookup(1.0, 1.0, 0.0, 50.0, 0.0, 0.0) is not None
    assert lookup(3.5, 1.0, 0.0, 50.0, 0.0, 0.0) is None  # contactor 2 at u = 4.5 > 4: mirrored elsewhere
    assert lookup(float("nan"), 1.0, 0.0, 50.0, 0.0, 0.0) is None
    assert lookup(1.0, 1.0, 0.0, float("inf"), 0.0, 0.0) is None
