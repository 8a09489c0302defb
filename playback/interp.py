"""Interpolation in the amplitude tables: (u, v, speed, direction) -> (a40, a320) in µm.

This is THE lookup used by the player and by the compiler when it measures the tables' error
against the reference renderer; ``docs/interpolation.md`` states the scheme. In short:

* direction: taken mod 180° (the amplitude spectrum does not change when the motion reverses),
  linear between nodes, periodic over 180°; a single node means isotropic;
* speed: linear in log(speed) between nodes; clamped to the top node above the range
  (flag ``ABOVE_RANGE``); below the lowest node ``s0`` the amplitude fades linearly to 0 at
  speed 0 (flag ``BELOW_RANGE``), so nothing vibrates at rest;
* space: (u, v) = origin + i * g_i + j * g_j solved for fractional (i, j), bilinear between
  nodes; periodic tables wrap i mod n_i and j mod n_j, others clamp to the edge (flag ``OUTSIDE``);
* non-finite inputs give 0 µm and flag ``INVALID``.

Outputs are finite, non-negative float64 (weights are convex, table values are >= 0).
"""
from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:  # the asset module imports this one lazily; avoid a cycle at import time
    from playback.asset import Tables

ABOVE_RANGE = np.uint8(1)
BELOW_RANGE = np.uint8(2)
OUTSIDE = np.uint8(4)
INVALID = np.uint8(8)
FLAG_NAMES = {1: "above_range", 2: "below_range", 4: "outside", 8: "invalid"}


class TableInterpolator:
    """Precomputed state for fast lookups in one :class:`~playback.asset.Tables`.

    The two channels are interleaved in one contiguous complex64 array (a40 + i a320) of shape
    ``[n_dir * n_speed * n_j * n_i]`` so each of the 16 corner gathers fetches both amplitudes.

    Parameters
    ----------
    tables : Tables
        Validated tables.
    """

    def __init__(self, tables: "Tables") -> None:
        nd, ns, nj, ni = tables.a40.shape
        self.shape = (nd, ns, nj, ni)
        self.periodic = bool(tables.periodic)
        # complex64 = (a40, a320) interleaved float32: one gather fetches both channels.
        self._complex = np.empty(nd * ns * nj * ni, dtype=np.complex64)
        self._complex.real = tables.a40.ravel()
        self._complex.imag = tables.a320.ravel()
        dirs = tables.direction_deg
        self._nd = nd
        self._dir0 = float(dirs[0])
        self._dir_rel = np.append(dirs - dirs[0], 180.0)  # nodes shifted so node 0 is at 0°
        self._dir_pos = np.arange(nd + 1, dtype=np.float64)
        speeds = tables.speed_mm_s
        self._s0 = float(speeds[0])
        self._s_top = float(speeds[-1])
        self._log_s = np.log(speeds)
        self._s_pos = np.arange(ns, dtype=np.float64)
        basis = tables.grid_basis_mm  # rows g_i, g_j: p - o = B.T @ (i, j)
        self._inv = np.linalg.inv(basis.T)
        self._origin = tables.origin_mm.copy()
        self._nij = np.array([[ni], [nj]], dtype=np.float64)
        self._nij_max = self._nij - 1.0
        # Per-axis constants for the [4, n] pipeline (rows: direction, speed, i, j).
        self._kmax = np.array([[nd - 1], [ns - 1], [ni - 1], [nj - 1]], dtype=np.intp)
        # Where the upper neighbour goes past the last node: direction always wraps (180°
        # period), speed sticks at the top node, space wraps only for periodic tables.
        self._kwrap = np.array([[0], [ns - 1], [0 if self.periodic else ni - 1],
                                [0 if self.periodic else nj - 1]], dtype=np.intp)
        self._kstride = np.array([[ns * nj * ni], [nj * ni], [1], [ni]], dtype=np.intp)

    def __call__(
        self,
        u_mm: np.ndarray,
        v_mm: np.ndarray,
        speed_mm_s: np.ndarray,
        direction_deg: np.ndarray,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Amplitudes (µm) at each point; see :func:`table_amplitudes`."""
        # Each numpy call costs ~1 µs at 24 points, so the four axes (direction, speed, i, j)
        # go through one [4, n] pipeline of fractional node indices, and the 16 corners are
        # gathered once as complex a40 + i a320.
        args = (u_mm, v_mm, speed_mm_s, direction_deg)
        if all(type(a) is np.ndarray and a.dtype == np.float64 and a.ndim == 1 for a in args) and (
                u_mm.shape == v_mm.shape == speed_mm_s.shape == direction_deg.shape):
            u, v, s, d = args
            out_shape = u.shape
        else:
            u, v, s, d = np.broadcast_arrays(*(np.asarray(a, dtype=np.float64) for a in args))
            out_shape = u.shape
            u, v, s, d = u.ravel(), v.ravel(), s.ravel(), d.ravel()
        n = u.shape[0]

        # Non-finite input: compute at a harmless point and zero the result afterwards.
        finite = np.isfinite(u + v + s + d)
        all_finite = bool(finite.all())
        if not all_finite:
            u = np.where(finite, u, 0.0)
            v = np.where(finite, v, 0.0)
            s = np.where(finite, s, 0.0)
            d = np.where(finite, d, 0.0)
        s = np.abs(s)

        frac = np.empty((4, n))  # fractional node index along direction, speed, i, j
        # Speed: linear in log(speed); np.interp clamps to the end nodes.
        below = s < self._s0
        above = s > self._s_top
        frac[1] = np.interp(np.log(np.maximum(s, self._s0)), self._log_s, self._s_pos)
        # Space: solve (u, v) = origin + i g_i + j g_j.
        du = u - self._origin[0]
        dv = v - self._origin[1]
        np.multiply(du, self._inv[0, 0], out=frac[2])
        frac[2] += self._inv[0, 1] * dv
        np.multiply(du, self._inv[1, 0], out=frac[3])
        frac[3] += self._inv[1, 1] * dv
        space = frac[2:]
        outside = None
        if self.periodic:
            np.mod(space, self._nij, out=space)
        else:
            # The surface beyond its edge is its mirror image (as the compiler samples it), so a
            # point outside reads the reflected node with the reflected direction of motion:
            # reflecting u maps direction d to 180 - d, reflecting v maps d to -d.
            outside = ((space < 0.0) | (space > self._nij_max)).any(axis=0)
            if outside.any():
                period = 2.0 * self._nij_max
                folded = np.mod(space, np.where(period > 0, period, 1.0))
                flips = folded > self._nij_max
                space[:] = np.where(flips, period - folded, folded)
                d = np.where(flips[0], 180.0 - d, d)
                d = np.where(flips[1], -d, d)
            np.clip(space, 0.0, self._nij_max, out=space)
        # Direction: mod 180 relative to node 0; np.interp maps degrees to a fractional node
        # index in [0, n_dir] (n_dir is node 0 again, half a turn later).
        if self._nd == 1:
            frac[0] = 0.0
        else:
            frac[0] = np.interp(np.mod(d - self._dir0, 180.0), self._dir_rel, self._dir_pos)

        # Lower node k0 (clamped so an index that rounded up to n wraps via k1), upper node k1.
        k = np.empty((2, 4, n), dtype=np.intp)
        w = np.empty((2, 4, n))
        k0, k1 = k[0], k[1]
        np.copyto(k0, frac, casting="unsafe")  # frac >= 0: truncation is floor
        np.minimum(k0, self._kmax, out=k0)
        np.subtract(frac, k0, out=w[1])
        np.subtract(1.0, w[1], out=w[0])
        np.add(k0, 1, out=k1)
        np.copyto(k1, self._kwrap, where=k1 > self._kmax)
        k *= self._kstride  # node index -> flat offset, per axis

        # Sum over the 16 corners: one of (k0, k1) per axis; weights multiply.
        idx = k[:, 0, None, None, None, :] + k[None, :, 1, None, None, :]
        idx = idx + k[None, None, :, 2, None, :]
        idx = idx + k[None, None, None, :, 3, :]
        wt = w[:, 0, None, None, None, :] * w[None, :, 1, None, None, :]
        wt = wt * w[None, None, :, 2, None, :]
        wt = wt * w[None, None, None, :, 3, :]
        vals = self._complex[idx] * wt
        amp = vals.reshape(16, n).sum(axis=0)
        a40 = amp.real.copy()
        a320 = amp.imag.copy()

        # Fade to zero below the lowest speed node: nothing vibrates at rest.
        if below.any() or not all_finite:
            fade = np.where(below, s / self._s0, 1.0)
            fade[~finite] = 0.0
            a40 *= fade
            a320 *= fade
        np.maximum(a40, 0.0, out=a40)  # guards rounding; values are convex sums of >= 0
        np.maximum(a320, 0.0, out=a320)

        flags = above.view(np.uint8) | (below.view(np.uint8) << 1)
        if outside is not None:
            flags |= outside.view(np.uint8) << 2
        if not all_finite:
            flags[~finite] = INVALID  # a bad point carries only INVALID
        return a40.reshape(out_shape), a320.reshape(out_shape), flags.reshape(out_shape)


def table_amplitudes(
    tables: "Tables",
    u_mm: np.ndarray,
    v_mm: np.ndarray,
    speed_mm_s: np.ndarray,
    direction_deg: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Interpolate the tables at points (one per contactor), vectorised.

    Parameters
    ----------
    tables : Tables
        The asset's tables (the precomputed interpolator is cached on them).
    u_mm, v_mm : array_like
        Position of the frame centre on the fabric (mm).
    speed_mm_s : array_like
        Speed (mm/s, >= 0; the sign is ignored).
    direction_deg : array_like
        Direction of motion (degrees CCW from +u towards +v; taken mod 180).

    Returns
    -------
    a40, a320 : ndarray of float64
        Amplitudes in µm (peak), finite and >= 0, broadcast shape of the inputs.
    flags : ndarray of uint8
        Bitmask: ``ABOVE_RANGE`` (1), ``BELOW_RANGE`` (2), ``OUTSIDE`` (4), ``INVALID`` (8).
    """
    return tables.interpolator(u_mm, v_mm, speed_mm_s, direction_deg)
