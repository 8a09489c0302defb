"""Adaptive direction and speed nodes (haptex_compile.node_refinement).

Expected values are closed forms: linear interpolation of a smooth function misses its
midpoint by h^2/8 |f''|; strokes in random directions meet an interval in proportion to its width.
"""
from __future__ import annotations

import numpy as np
import pytest

from haptex_compile.node_refinement import direction_draws, midpoint_errors, speed_draws, split_directions, split_speeds


def colours_of(f, dirs: np.ndarray) -> np.ndarray:
    """Both colours equal to f(direction), one point per node: shape [n, 2, 1]."""
    v = f(np.asarray(dirs, dtype=float))
    return np.stack([v, v], axis=1)[:, :, None]


def smooth(theta_deg):
    return 2.0 + np.cos(np.radians(2.0 * theta_deg))


def peaked(theta_deg):
    """A sharp peak at 0 deg (period 180): what a weave's rows do to a frame's amplitude."""
    t = (np.asarray(theta_deg) + 90.0) % 180.0 - 90.0
    return 1.0 + 2.0 * np.exp(-np.abs(t) / 4.0)


def true_interpolation_error(f, nodes: np.ndarray) -> float:
    """RMS relative error of linear interpolation (wrapping over 180 deg) over all directions."""
    fine = np.linspace(0.0, 180.0, 18001)[:-1]
    xp = np.append(nodes, nodes[0] + 180.0)
    approx = np.interp(np.mod(fine - nodes[0], 180.0) + nodes[0], xp, np.append(f(nodes), f(nodes[0])))
    return float(np.sqrt(np.mean(((approx - f(fine)) / f(fine)) ** 2)))


def test_predicted_midpoint_error_is_that_of_linear_interpolation():
    nodes = np.arange(24) * 7.5
    pred = midpoint_errors(nodes, colours_of(smooth, nodes), period=180.0)
    mids = nodes + 3.75
    actual = np.abs(0.5 * (smooth(nodes) + smooth(nodes + 7.5)) - smooth(mids)) / smooth(mids)
    # h^2/8 |f''| with f'' taken at the worse end node: the RMS over intervals within 15 %
    ratio = np.sqrt(np.mean(pred**2)) / np.sqrt(np.mean(actual**2))
    assert 0.95 < ratio < 1.15


def test_a_dependence_alike_in_every_interval_is_split_evenly():
    """Points whose amplitudes are the same smooth function at 24 phases: every 15-degree interval
    has the same error, so splitting up to 24 nodes is uniform halving."""
    nodes = np.arange(12) * 15.0
    phases = np.arange(24) * 7.5
    colours = np.stack([smooth(nodes[:, None] + phases[None, :])] * 2, axis=1)  # [n, 2, 24]
    new = split_directions(nodes, colours, True, 0.0, measured_share=0.05, target_share=1e-6, max_nodes=24)
    assert np.allclose(new, np.arange(24) * 7.5)


def test_splits_go_to_a_sharp_peak_and_beat_uniform_halving():
    nodes = np.arange(12) * 15.0
    share = true_interpolation_error(peaked, nodes)
    new = split_directions(nodes, colours_of(peaked, nodes), True, 0.0, measured_share=share,
                           target_share=share / 3.0, max_nodes=24)
    added = np.setdiff1d(new, nodes)
    assert added.size < 12
    assert np.all(np.minimum(added, 180.0 - added) < 30.0)  # next to the peak only
    uniform = np.arange(24) * 7.5
    assert true_interpolation_error(peaked, new) < true_interpolation_error(peaked, uniform)


def test_direction_draws_weight_intervals_and_nodes_by_width():
    mids, mid_p, nodes, node_p = direction_draws(np.array([0.0, 10.0, 90.0]))
    assert np.allclose(mids, [5.0, 50.0, 135.0])
    assert np.allclose(mid_p, np.array([10.0, 80.0, 90.0]) / 180.0)
    assert np.allclose(nodes, [0.0, 10.0, 90.0])
    assert np.allclose(node_p, np.array([50.0, 45.0, 85.0]) / 180.0)


@pytest.mark.parametrize("rng_deg, dirs, expect_mids, expect_p", [
    ((0.0, 90.0), [0.0, 45.0, 90.0], [22.5, 67.5], [0.5, 0.5]),
    ((150.0, 210.0), [0.0, 30.0, 150.0, 165.0], [157.5, 172.5, 15.0], [0.25, 0.25, 0.5]),
])
def test_direction_draws_stay_inside_a_partial_range(rng_deg, dirs, expect_mids, expect_p):
    mids, mid_p, nodes, node_p = direction_draws(np.array(dirs), rng_deg)
    assert np.allclose(mids, expect_mids) and np.allclose(mid_p, expect_p)
    assert np.isclose(node_p.sum(), 1.0) and set(nodes) == set(dirs)


def test_speed_draws_weight_by_log_width():
    mids, mid_p, nodes, node_p = speed_draws(np.array([10.0, 20.0, 80.0]))
    assert np.allclose(mids, [np.sqrt(200.0), 40.0])  # geometric midpoints
    assert np.allclose(mid_p, [1 / 3, 2 / 3])  # ln 2 and ln 4 of ln 8
    assert np.allclose(node_p, [1 / 6, 1 / 2, 1 / 3])


def test_speed_splits_go_to_a_resonance():
    """Amplitudes peaked at 50 mm/s (a weave's tone crossing a threshold minimum) get the new
    speed nodes, at geometric midpoints of the old ones."""
    speeds = np.geomspace(10.0, 200.0, 15)

    def resonance(s):
        return 1.0 + 2.0 * np.exp(-np.abs(np.log(s / 50.0)) / 0.1)

    share = 0.05
    new = split_speeds(speeds, colours_of(resonance, speeds), measured_share=share, target_share=share / 3.0,
                       max_nodes=29)
    added = np.setdiff1d(new, speeds)
    assert 0 < added.size < 14
    assert np.all(np.abs(np.log(added / 50.0)) < np.log(2.0))  # within a factor 2 of the peak
    ratio = np.log(new[1:] / new[:-1])
    assert np.all(np.isin(np.round(ratio / ratio.max(), 6), [0.25, 0.5, 1.0]))  # nested halvings


def test_a_partial_range_is_split_inside_it():
    """Directions from 150 to 210 deg (nodes 150 ... 180 = 0 ... 30) with the peak at 0: new nodes
    go next to it and never into the gap outside the range (30 to 150 deg)."""
    nodes = np.array([0.0, 15.0, 30.0, 150.0, 165.0])
    share = 0.05
    new = split_directions(nodes, colours_of(peaked, nodes), False, 150.0, measured_share=share,
                           target_share=share / 3.0, max_nodes=8)
    added = np.setdiff1d(new, nodes)
    assert added.size > 0
    assert np.all((added < 30.0) | (added > 150.0))
    assert np.any(np.isclose(added, 172.5) | np.isclose(added, 7.5))  # next to the peak
