"""Where to add table nodes: split the intervals whose interpolation error is largest.

Amplitudes of a periodic texture change fastest with direction near its lattice directions,
where a frame's strip of contact swings across rows of threads; between them they are smooth.
On a plain weave (bench: cotton KES sample) linear interpolation over a 7.5° step is off by
20-30 % next to the thread directions and by under 2 % over most of the range. Along speed,
a weave's tones sweep through the channels' threshold curves, again unevenly. Halving every
interval pays for the smooth ones too; this splits the intervals that need it.

The error of linear interpolation at an interval's midpoint is ``h**2 / 8 |f''|`` for a smooth
``f``; ``f''`` is estimated by second divided differences of the tables at the interval's two
end nodes (the larger of the two, since a sharp peak at one node is what the other misses).
The estimate is relative, point by point, to the amplitudes there (colours in threshold units),
like the measured error it is calibrated against. Directions are split in degrees (wrapping
over the half turn), speeds in log-speed (the player interpolates linearly in log-speed).
"""
from __future__ import annotations

import heapq

import numpy as np

NODE_DECIMALS = 9  # new nodes are rounded like the planner's, so cache keys match
# Error of each half of a split interval, as a fraction of the interval's: 1/4 for a smooth
# function, about 1/2 next to a cusp. 1/2.5 gave the tables of the cotton KES sample the error
# of uniform halving (1.7 % against 1.65 %, 96 checks per family) with 33 directions, not 48;
# 1/3 stopped at 29 with 2.1 %.
SPLIT_REDUCTION = 2.5


def _widths(x: np.ndarray, period: float | None) -> np.ndarray:
    """Widths of the intervals between consecutive nodes `x` (increasing); with a period, the
    last interval wraps to the first node a period later (a single node's is the period)."""
    ext = np.append(x, x[0] + period) if period is not None else x
    widths = np.diff(ext)
    if period is not None:
        widths = np.mod(widths, period)
        widths[widths == 0] = period
    return widths


def direction_intervals(direction_deg: np.ndarray, full_turn: bool) -> tuple[np.ndarray, np.ndarray]:
    """Start index and width (deg) of every interval between consecutive direction nodes.

    Parameters
    ----------
    direction_deg : ndarray
        Nodes in [0, 180), strictly increasing, in the order the interval walk takes them
        (for a partial range: unwrapped from its start, see :func:`range_order`).
    full_turn : bool
        Whether the nodes cover all directions, so the last interval wraps to the first node
        half a turn later.
    """
    d = np.asarray(direction_deg, dtype=float)
    widths = _widths(d, 180.0) if full_turn else np.mod(np.diff(d), 180.0)
    return np.arange(widths.size), widths


def range_order(direction_deg: np.ndarray, start_deg: float) -> np.ndarray:
    """Indices that walk the nodes from `start_deg` onwards (mod 180)."""
    return np.argsort(np.mod(np.asarray(direction_deg, dtype=float) - start_deg, 180.0), kind="stable")


def _node_weights(widths: np.ndarray, n: int) -> np.ndarray:
    """Half the width of each node's intervals, normalised (interval k joins nodes k, k+1 mod n)."""
    w = np.zeros(n)
    w[: widths.size] += 0.5 * widths
    w[(np.arange(widths.size) + 1) % n] += 0.5 * widths
    return w / w.sum()


def direction_draws(direction_deg: np.ndarray, direction_range_deg: tuple[float, float] | None = None
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Where, and how often, a table check should test directions.

    Strokes in random directions meet an interval between nodes in proportion to its width,
    and a node in proportion to half the width of its two intervals. Intervals wrap around the
    half turn unless `direction_range_deg` is a partial range (then only the intervals inside
    it, walked from its start, count).

    Returns
    -------
    tuple of ndarray
        Interval midpoints (deg, in [0, 180)) and their probabilities; nodes and theirs.
    """
    d = np.asarray(direction_deg, dtype=float)
    full_turn = direction_range_deg is None or direction_range_deg[1] - direction_range_deg[0] >= 180.0 - 1e-9
    walk = d if full_turn or d.size < 2 else d[range_order(d, direction_range_deg[0])]
    full_turn = full_turn or d.size < 2
    _, widths = direction_intervals(walk, full_turn)
    mids = np.mod(walk[: widths.size] + 0.5 * widths, 180.0)
    return mids, widths / widths.sum(), walk, _node_weights(widths, walk.size)


def speed_draws(speed_mm_s: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Where, and how often, a table check should test speeds: as :func:`direction_draws`, with
    widths in log-speed (strokes' speeds spread evenly in log-speed); midpoints are geometric.

    Needs at least two nodes.
    """
    s = np.asarray(speed_mm_s, dtype=float)
    widths = np.diff(np.log(s))
    return np.sqrt(s[:-1] * s[1:]), widths / widths.sum(), s, _node_weights(widths, s.size)


def midpoint_errors(x: np.ndarray, colours: np.ndarray, period: float | None = None,
                    floor_fraction: float = 0.01) -> np.ndarray:
    """Predicted RMS relative error of linear interpolation at each interval's midpoint.

    Parameters
    ----------
    x : ndarray, shape (n,)
        Node coordinates, increasing (directions in walk order, or log-speeds).
    colours : ndarray, shape (n, 2, ...)
        The two colours in threshold units at every node (any trailing axes: speeds, positions).
    period : float, optional
        The coordinate's period when the intervals wrap (180 for all directions).
    floor_fraction : float
        Amplitudes below this fraction of their RMS count as that level (silence is not divided by).

    Returns
    -------
    ndarray, shape (n_intervals,)
        One value per interval (n with a period, n - 1 without); zeros when there are fewer
        than three nodes (no curvature can be estimated).
    """
    x = np.asarray(x, dtype=float)
    f = np.asarray(colours, dtype=np.float32)
    widths = _widths(x, period)
    n = x.size
    if n < 3:
        return np.zeros(widths.size)
    # differences to the next node, by slicing (the tables are large: no index gathers)
    if period is not None:
        step = np.roll(f, -1, axis=0) - f  # f[k + 1] - f[k], wrapping
        h1 = np.roll(widths, 1)  # width of the interval ending at node k
        h2 = widths  # width of the interval starting at node k
        after, before = step, np.roll(step, 1, axis=0)
    else:
        step = f[1:] - f[:-1]
        h1, h2 = widths[:-1], widths[1:]
        after, before = step[1:], step[:-1]
    shape = (-1,) + (1,) * (f.ndim - 1)
    slope2 = after / h2.reshape(shape)
    slope1 = before / h1.reshape(shape)
    curvature = 2.0 * (slope2 - slope1) / (h1 + h2).reshape(shape)  # f'' at the interior nodes
    curv2 = np.sum(curvature**2, axis=1)  # |f''|^2 over the two colours, per point
    if period is None:  # the end nodes take their neighbour's curvature
        curv2 = np.concatenate([curv2[:1], curv2, curv2[-1:]], axis=0)
    level2 = np.sum(f**2, axis=1)
    floor2 = (floor_fraction**2) * float(np.mean(level2)) + 1e-300
    out = np.empty(widths.size)
    for k in range(widths.size):
        k2 = (k + 1) % n
        c2 = np.maximum(curv2[k], curv2[k2])
        ref2 = np.maximum(0.5 * (level2[k] + level2[k2]), floor2)
        out[k] = widths[k] ** 2 / 8.0 * float(np.sqrt(np.mean(c2 / ref2)))
    return out


def split_points(x: np.ndarray, colours: np.ndarray, period: float | None, measured_share: float,
                 target_share: float, max_nodes: int, reduction: float = SPLIT_REDUCTION) -> np.ndarray:
    """Midpoints of the intervals to split so that the predicted error is met.

    The predicted error is the width-weighted RMS of :func:`midpoint_errors` (random strokes
    meet intervals in proportion to their width), scaled to `measured_share` (the check's
    error on this axis less the position error, which calibrates the curvature estimate).
    Splitting an interval divides its error by `reduction` in each half (see
    ``SPLIT_REDUCTION``), and a half can be split again. Intervals are split, largest weighted
    error first, until the prediction reaches `target_share` or the node count `max_nodes`;
    at least one is split. Without any curvature seen, or nothing measured to calibrate it
    against (`measured_share` 0: the axis is refined as a fallback), every interval is split
    once, as uniform halving does.

    Returns
    -------
    ndarray
        New coordinates (with a period, possibly beyond it: reduce them).
    """
    x = np.asarray(x, dtype=float)
    widths = _widths(x, period)
    errs = midpoint_errors(x, colours, period)
    contrib = widths / widths.sum() * errs**2
    total = float(contrib.sum())
    scale = measured_share**2 / total if total > 0 else 0.0
    if total <= 0 or measured_share <= 0 or not np.isfinite(scale):
        return x[: widths.size] + 0.5 * widths
    # heap of (-contribution, start, width); a split pushes its two halves
    heap = [(-float(c), float(a), float(w)) for c, a, w in zip(contrib, x, widths)]
    heapq.heapify(heap)
    mids: list[float] = []
    while heap and x.size + len(mids) < max_nodes:
        if mids and scale * total <= target_share**2:
            break
        neg_c, a, w = heapq.heappop(heap)
        half_c = -neg_c / 2.0 / reduction**2
        total -= -neg_c - 2.0 * half_c
        mids.append(a + 0.5 * w)
        heapq.heappush(heap, (-half_c, a, 0.5 * w))
        heapq.heappush(heap, (-half_c, a + 0.5 * w, 0.5 * w))
    return np.array(mids)


def split_directions(direction_deg: np.ndarray, colours: np.ndarray, full_turn: bool, start_deg: float,
                     measured_share: float, target_share: float, max_nodes: int,
                     reduction: float = SPLIT_REDUCTION) -> np.ndarray:
    """Direction nodes with the worst intervals split (:func:`split_points`, in degrees).

    Parameters
    ----------
    direction_deg : ndarray
        Nodes in [0, 180), ascending.
    colours : ndarray, shape (n, 2, ...)
        Colours in threshold units at the nodes.
    full_turn : bool
        The nodes cover all directions (intervals wrap); else they cover a range from `start_deg`.

    Returns
    -------
    ndarray
        The new nodes in [0, 180), sorted, the old ones included.
    """
    d = np.asarray(direction_deg, dtype=float)
    order = np.arange(d.size) if full_turn else range_order(d, start_deg)
    walk = d[order]
    if not full_turn:  # unwrapped, so the walk increases
        walk = start_deg + np.mod(walk - start_deg, 180.0)
    mids = split_points(walk, np.asarray(colours)[order], 180.0 if full_turn else None,
                        measured_share, target_share, max_nodes, reduction)
    return np.unique(np.round(np.mod(np.concatenate([d, mids]), 180.0), NODE_DECIMALS))


def split_speeds(speed_mm_s: np.ndarray, colours: np.ndarray, measured_share: float, target_share: float,
                 max_nodes: int, reduction: float = SPLIT_REDUCTION) -> np.ndarray:
    """Speed nodes with the worst intervals split at their geometric midpoints
    (:func:`split_points` in log-speed).

    Returns
    -------
    ndarray
        The new nodes (mm/s), sorted, the old ones included.
    """
    s = np.asarray(speed_mm_s, dtype=float)
    mids = np.exp(split_points(np.log(s), colours, None, measured_share, target_share, max_nodes, reduction))
    return np.unique(np.concatenate([s, np.round(mids, NODE_DECIMALS)]))
