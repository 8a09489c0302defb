"""Where to add direction nodes: split the intervals whose interpolation error is largest.

Amplitudes of a periodic texture change fastest with direction near its lattice directions,
where a frame's strip of contact swings across rows of threads; between them they are smooth.
On a plain weave (bench: cotton KES sample) linear interpolation over a 7.5° step is off by
20-30 % next to the thread directions and by under 2 % over most of the range. Halving every
interval pays for the smooth ones too; this splits the intervals that need it.

The error of linear interpolation at an interval's midpoint is ``h**2 / 8 |f''|`` for a smooth
``f``; ``f''`` is estimated by second divided differences of the tables at the interval's two
end nodes (the larger of the two, since a sharp peak at one node is what the other misses).
The estimate is relative, point by point, to the amplitudes there (colours in threshold units),
like the measured error it is calibrated against.
"""
from __future__ import annotations

import heapq

import numpy as np

DIRECTION_DECIMALS = 9  # new nodes are rounded like the planner's, so cache keys match
# Error of each half of a split interval, as a fraction of the interval's: 1/4 for a smooth
# function, about 1/2 next to a cusp. 1/2.5 gave the tables of the cotton KES sample the error
# of uniform halving (1.7 % against 1.65 %, 96 checks per family) with 33 directions, not 48;
# 1/3 stopped at 29 with 2.1 %.
SPLIT_REDUCTION = 2.5


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
    ext = np.append(d, d[0] + 180.0) if full_turn else d
    widths = np.mod(np.diff(ext), 180.0)
    widths[widths == 0] = 180.0  # a single node: its interval is the whole half turn
    return np.arange(widths.size), widths


def range_order(direction_deg: np.ndarray, start_deg: float) -> np.ndarray:
    """Indices that walk the nodes from `start_deg` onwards (mod 180)."""
    return np.argsort(np.mod(np.asarray(direction_deg, dtype=float) - start_deg, 180.0), kind="stable")


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
    node_w = np.zeros(walk.size)
    node_w[: widths.size] += 0.5 * widths
    node_w[(np.arange(widths.size) + 1) % walk.size] += 0.5 * widths
    mids = np.mod(walk[: widths.size] + 0.5 * widths, 180.0)
    return mids, widths / widths.sum(), walk, node_w / node_w.sum()


def midpoint_errors(direction_deg: np.ndarray, colours: np.ndarray, full_turn: bool,
                    floor_fraction: float = 0.01) -> np.ndarray:
    """Predicted RMS relative error of linear interpolation at each interval's midpoint.

    Parameters
    ----------
    direction_deg : ndarray, shape (n,)
        Nodes in walk order (see :func:`direction_intervals`).
    colours : ndarray, shape (n, 2, ...)
        The two colours in threshold units at every node (any trailing axes: speeds, positions).
    full_turn : bool
        Whether the walk wraps.
    floor_fraction : float
        Amplitudes below this fraction of their RMS count as that level (silence is not divided by).

    Returns
    -------
    ndarray, shape (n_intervals,)
        One value per interval of :func:`direction_intervals`; zeros when there are fewer than
        three nodes (no curvature can be estimated).
    """
    d = np.asarray(direction_deg, dtype=float)
    f = np.asarray(colours, dtype=np.float32)
    _, widths = direction_intervals(d, full_turn)
    n = d.size
    if n < 3:
        return np.zeros(widths.size)
    if full_turn:
        prev, nxt = np.roll(np.arange(n), 1), np.roll(np.arange(n), -1)
        h1 = np.roll(widths, 1)  # width of the interval ending at node k
        h2 = widths  # width of the interval starting at node k
        interior = np.arange(n)
    else:
        interior = np.arange(1, n - 1)
        prev, nxt = interior - 1, interior + 1
        h1, h2 = widths[:-1], widths[1:]
    shape = (-1,) + (1,) * (f.ndim - 1)
    slope2 = (f[nxt] - f[interior]) / h2.reshape(shape)
    slope1 = (f[interior] - f[prev]) / h1.reshape(shape)
    curvature = 2.0 * (slope2 - slope1) / (h1 + h2).reshape(shape)  # f'' at the interior nodes
    curv2 = np.sum(curvature**2, axis=1)  # |f''|^2 over the two colours, per point
    if not full_turn:  # the end nodes take their neighbour's curvature
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


def split_directions(direction_deg: np.ndarray, colours: np.ndarray, full_turn: bool, start_deg: float,
                     measured_share: float, target_share: float, max_nodes: int,
                     reduction: float = SPLIT_REDUCTION) -> np.ndarray:
    """Nodes with the worst intervals split at their midpoints until the predicted error is met.

    The predicted direction error is the width-weighted RMS of :func:`midpoint_errors` (strokes
    meet intervals in proportion to their width), scaled to `measured_share` (the check's
    direction error less the position error, which calibrates the curvature estimate). Splitting
    an interval divides its error by `reduction` in each half (see ``SPLIT_REDUCTION``), and a
    half can be split again. Intervals are split,
    largest weighted error first, until the prediction reaches `target_share` or the node count
    `max_nodes`; at least one is split.

    Returns
    -------
    ndarray
        The new nodes in [0, 180), sorted, the old ones included.
    """
    d = np.asarray(direction_deg, dtype=float)
    order = range_order(d, start_deg) if not full_turn else np.arange(d.size)
    walk = d[order]
    _, widths = direction_intervals(walk, full_turn)
    errs = midpoint_errors(walk, np.asarray(colours)[order], full_turn)
    contrib = widths / widths.sum() * errs**2
    total = float(contrib.sum())
    scale = measured_share**2 / total if total > 0 else 0.0
    if total <= 0 or not np.isfinite(scale):  # no curvature seen: split everything, as uniform halving does
        mids = walk + 0.5 * widths
    else:
        # heap of (-contribution, start, width); a split pushes its two halves
        heap = [(-float(c), float(a), float(w)) for c, a, w in zip(contrib, walk, widths)]
        heapq.heapify(heap)
        mids_list: list[float] = []
        while heap and d.size + len(mids_list) < max_nodes:
            if mids_list and scale * total <= target_share**2:
                break
            neg_c, a, w = heapq.heappop(heap)
            half_c = -neg_c / 2.0 / reduction**2
            total -= -neg_c - 2.0 * half_c
            mids_list.append(a + 0.5 * w)
            heapq.heappush(heap, (-half_c, a, 0.5 * w))
            heapq.heappush(heap, (-half_c, a + 0.5 * w, 0.5 * w))
        mids = np.array(mids_list)
    new = np.round(np.mod(np.concatenate([d, mids]), 180.0), DIRECTION_DECIMALS)
    return np.unique(new)
