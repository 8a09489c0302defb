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

import math
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:  # the asset module imports this one lazily; avoid a cycle at import time
    from playback.asset import Tables

ABOVE_RANGE = np.uint8(1)
BELOW_RANGE = np.uint8(2)
OUTSIDE = np.uint8(4)
INVALID = np.uint8(8)
FLAG_NAMES = {1: "above_range", 2: "below_range", 4: "outside", 8: "invalid"}


class _Work:
    """Work arrays for :meth:`TableInterpolator._corners` at one point count.

    A renderer keeps one and reuses it every frame (allocation-free); one-off lookups make a
    fresh one, so concurrent callers never share buffers. Corner-major layout (the point index
    is the fastest axis, so every inner loop runs over the n points), and the broadcast views
    used every frame are made here once.
    """

    __slots__ = ("n", "k0", "w", "off", "idx", "wt", "vals", "prod", "vals16", "wt16", "prod16", "args")

    def __init__(self, n: int) -> None:
        self.n = n
        self.k0 = np.empty((4, n), dtype=np.intp)  # lower node per axis, then lookup-table row
        self.w = np.empty((2, 4, n))  # [lower/upper, axis, point] weights
        self.off = np.empty((2, 4, n), dtype=np.intp)  # flat offsets of the lower/upper nodes
        ids = np.empty((2, 2, n), dtype=np.intp)  # direction x speed corners
        iij = np.empty((2, 2, n), dtype=np.intp)  # i x j corners
        wds = np.empty((2, 2, n))
        wij = np.empty((2, 2, n))
        self.idx = np.empty((2, 2, 2, 2, n), dtype=np.intp)
        self.wt = np.empty((2, 2, 2, 2, n))
        self.vals = np.empty((2, 2, 2, 2, n), dtype=np.complex64)
        self.prod = np.empty((2, 2, 2, 2, n), dtype=np.complex128)
        self.vals16, self.wt16, self.prod16 = (a.reshape(16, n) for a in (self.vals, self.wt, self.prod))
        off, w = self.off, self.w
        # (first, second, out) of the six broadcast sums/products that build the 16 corners.
        self.args = (
            (off[:, 0, None], off[None, :, 1], ids),
            (off[:, 2, None], off[None, :, 3], iij),
            (ids[:, :, None, None], iij, self.idx),
            (w[:, 0, None], w[None, :, 1], wds),
            (w[:, 2, None], w[None, :, 3], wij),
            (wds[:, :, None, None], wij, self.wt),
        )


class TableInterpolator:
    """Precomputed state for fast lookups in one :class:`~playback.asset.Tables`.

    The two channels are interleaved in one contiguous complex64 array (a40 + i a320) of shape
    ``[n_dir * n_speed * n_j * n_i]`` so each of the 16 corner gathers fetches both amplitudes.
    Per axis, two small lookup tables map a lower node index straight to the flat offsets of the
    lower and upper node (wrap or clamp already applied), so the corners cost two ``take`` calls
    instead of a clamp/wrap/stride pipeline.

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
        dirs = np.asarray(tables.direction_deg, dtype=np.float64)
        self._nd = nd
        self._dir0 = float(dirs[0])
        self._dir_rel = np.append(dirs - dirs[0], 180.0)  # nodes shifted so node 0 is at 0°
        self._dir_pos = np.arange(nd + 1, dtype=np.float64)
        speeds = np.asarray(tables.speed_mm_s, dtype=np.float64)
        self._s0 = float(speeds[0])
        self._s_top = float(speeds[-1])
        self._log_s = np.log(speeds)
        self._s_pos = np.arange(ns, dtype=np.float64)
        basis = tables.grid_basis_mm  # rows g_i, g_j: p - o = B.T @ (i, j)
        self._inv = np.linalg.inv(basis.T)
        self._origin = np.asarray(tables.origin_mm, dtype=np.float64).copy()
        self._nij = np.array([[ni], [nj]], dtype=np.float64)
        self._nij_max = self._nij - 1.0
        # Python floats for the per-frame scalar arithmetic (numpy scalars are ~5x slower).
        self._inv_f = tuple(float(x) for x in self._inv.ravel())
        self._origin_f = (float(self._origin[0]), float(self._origin[1]))

        # Node lookup table, axes in the order (direction, speed, i, j): for a lower node k of
        # an axis with m nodes, row base + k holds the flat offsets of the lower and the upper
        # node. Direction always wraps (180° period) and has rows for k up to 2 m (the
        # rigid-array path maps (-180°, 180°] onto [0, 2 m] without a mod); speed sticks at the
        # top node; space wraps only for periodic tables, whose row m (a fraction that rounded up
        # to the period) aliases node 0.
        axes = ((nd, ns * nj * ni, True, 2 * nd + 1), (ns, nj * ni, False, ns + 1),
                (ni, 1, self.periodic, ni + 1), (nj, ni, self.periodic, nj + 1))
        rows, base = [], []
        n_rows = 0
        for m, stride, wraps, length in axes:
            k = np.arange(length)
            lower = k % m if wraps else np.minimum(k, m - 1)
            upper = (lower + 1) % m if wraps else np.minimum(lower + 1, m - 1)
            base.append(n_rows)
            n_rows += length
            rows.append(np.stack([lower * stride, upper * stride]))
        self._offsets = np.ascontiguousarray(np.concatenate(rows, axis=1), dtype=np.intp)  # [lower/upper, row]
        self._axis_base = np.array(base, dtype=np.intp)[:, None]

        # One np.interp call maps both (direction, speed) inputs of the rigid-array path to
        # fractional node indices: the direction relative to node 0 in radians, (-pi, pi] (as
        # arctan2 gives it) onto [0, 2 n_dir] (two half turns), then the log-speed nodes shifted
        # to start at pi + 1. The shift is a scale factor K on the velocity
        # (log(K s) = log(s) + log(K)), folded into the kinematics matrix for free.
        self._speed_scale = math.exp(math.pi + 1.0) / self._s0
        self._ks0 = self._speed_scale * self._s0
        self._ks_top = self._speed_scale * self._s_top
        rel = np.radians(self._dir_rel[:-1])
        self._ds_xp = np.concatenate([rel - math.pi, rel, [math.pi], np.log(self._speed_scale * speeds)])
        self._ds_xp[2 * nd + 1] = math.log(self._ks0)  # the exact value the clamped input takes
        self._ds_fp = np.concatenate([np.arange(2 * nd + 1, dtype=np.float64), self._s_pos])
        theta0 = math.radians(self._dir0)
        self._kcos0 = self._speed_scale * math.cos(theta0)
        self._ksin0 = self._speed_scale * math.sin(theta0)

    def _corners(self, frac: np.ndarray, work: _Work) -> np.ndarray:
        """Multilinear sum over the 16 surrounding nodes.

        Parameters
        ----------
        frac : ndarray, shape (4, n)
            Fractional node index per axis (direction, speed, i, j), already wrapped or clamped
            into ``[0, m]`` (``m`` only on a wrapping axis).
        work : _Work
            Work arrays for n points (overwritten).

        Returns
        -------
        ndarray of complex128, shape (n,)
            a40 + i a320 (a new array).
        """
        k0 = work.k0
        np.copyto(k0, frac, casting="unsafe")  # frac >= 0: truncation is floor
        w = work.w
        np.subtract(frac, k0, out=w[1])
        np.subtract(1.0, w[1], out=w[0])
        k0 += self._axis_base  # per-axis node -> row of the lookup table
        np.take(self._offsets, k0, axis=1, out=work.off, mode="clip")  # rows are in range by construction
        # Corner (a, b, c, d) = (lower/upper node along direction, speed, i, j): offsets add,
        # weights multiply.
        (a0, a1, ids), (b0, b1, iij), (c0, c1, idx), (d0, d1, wds), (e0, e1, wij), (f0, f1, wt) = work.args
        np.add(a0, a1, out=ids)
        np.add(b0, b1, out=iij)
        np.add(c0, c1, out=idx)
        np.multiply(d0, d1, out=wds)
        np.multiply(e0, e1, out=wij)
        np.multiply(f0, f1, out=wt)
        np.take(self._complex, idx, out=work.vals, mode="clip")
        np.multiply(work.vals16, work.wt16, out=work.prod16)
        return np.add.reduce(work.prod16, axis=0)

    def __call__(
        self,
        u_mm: np.ndarray,
        v_mm: np.ndarray,
        speed_mm_s: np.ndarray,
        direction_deg: np.ndarray,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Amplitudes (µm) at each point; see :func:`table_amplitudes`."""
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

        amp = self._corners(frac, _Work(n))
        a40 = np.maximum(amp.real, 0.0)  # a contiguous copy; guards rounding (convex sums of >= 0)
        a320 = np.maximum(amp.imag, 0.0)

        # Fade to zero below the lowest speed node: nothing vibrates at rest.
        if below.any() or not all_finite:
            fade = np.where(below, s / self._s0, 1.0)
            fade[~finite] = 0.0
            a40 *= fade
            a320 *= fade

        flags = above.view(np.uint8) | (below.view(np.uint8) << 1)
        if outside is not None:
            flags |= outside.view(np.uint8) << 2
        if not all_finite:
            flags[~finite] = INVALID  # a bad point carries only INVALID
        return a40.reshape(out_shape), a320.reshape(out_shape), flags.reshape(out_shape)


class RigidArrayLookup:
    """The player's per-frame lookup: every contactor of a rigid array, from one motion state.

    Same scheme and results (to rounding, ~1e-15 relative) as
    ``table_amplitudes(tables, *contactor_kinematics(state, contactors))``, with about half the
    numpy calls and no allocation beyond the outputs: the rotation, the translation, the
    solve for the node indices (i, j), a rotation of the velocity by the first direction node
    and the log-speed shift of the combined ``np.interp`` are composed into one 4 x 3 matrix
    applied to the precomputed (x, y, 1) of the contactors. Each call costs ~30 numpy calls
    whatever the number of contactors (docs/interpolation.md).

    Parameters
    ----------
    interpolator : TableInterpolator
    contactors_mm : ndarray, shape (n, 2)
        Device coordinates (x_i, y_i) in mm.
    """

    # A state beyond this (or non-finite) goes through the general path, so the composed
    # matrix can never overflow.
    MAX_STATE = 1e9

    def __init__(self, interpolator: TableInterpolator, contactors_mm: np.ndarray) -> None:
        xy = np.asarray(contactors_mm, dtype=np.float64).reshape(-1, 2)
        n = xy.shape[0]
        self.interp = interpolator
        self.n = n
        self._xy1 = np.ascontiguousarray(np.vstack([xy.T, np.ones(n)]))  # rows x, y, 1
        self._m = np.empty((4, 3))
        self._m_flat = self._m.reshape(12)
        # Rows: velocity rotated by -theta0 and scaled by K (2 rows), then unwrapped (i, j).
        self._f = np.empty((4, n))
        self._q = np.empty((2, n))  # np.interp inputs: direction - theta0, log(K max(s, s0))
        self._ks = np.empty(n)  # K * speed
        self._frac = np.empty((4, n))
        self._work = _Work(n)
        # Views made once (each slice costs a call per frame otherwise).
        self._vel = (self._f[0], self._f[1])
        self._f_ij = self._f[2:]
        self._q_dir, self._q_speed = self._q[0], self._q[1]
        self._frac_ds = self._frac[:2]
        self._frac_ij = self._frac[2:]
        self._clipped = np.empty((2, n), dtype=bool)

    def __call__(self, u_mm: float, v_mm: float, phi_deg: float, vu_mm_s: float, vv_mm_s: float,
                 omega_deg_s: float) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
        """(a40, a320, flags) per contactor, or ``None`` when the general path must be used.

        ``None`` means: a non-finite or absurd state (the general path flags ``INVALID``), or a
        contactor beyond the edge of a non-periodic table (the general path mirrors it).
        """
        if not (abs(u_mm) + abs(v_mm) + abs(phi_deg) + abs(vu_mm_s) + abs(vv_mm_s) + abs(omega_deg_s)
                < self.MAX_STATE):  # also False for NaN
            return None
        it = self.interp
        phi = math.radians(phi_deg)
        c, s = math.cos(phi), math.sin(phi)
        w = math.radians(omega_deg_s)
        ws, wc = w * s, w * c
        # Contactor velocity: (vu - w (s x + c y), vv + w (c x - s y)); rotate by -theta0, scale K.
        kc, ks = it._kcos0, it._ksin0
        a, b, e, f = it._inv_f
        du, dv = u_mm - it._origin_f[0], v_mm - it._origin_f[1]
        self._m_flat[:] = (
            ks * wc - kc * ws, -kc * wc - ks * ws, kc * vu_mm_s + ks * vv_mm_s,
            ks * ws + kc * wc, ks * wc - kc * ws, kc * vv_mm_s - ks * vu_mm_s,
            a * c + b * s, b * c - a * s, a * du + b * dv,
            e * c + f * s, f * c - e * s, e * du + f * dv,
        )
        np.matmul(self._m, self._xy1, out=self._f)
        vu, vv = self._vel
        q_dir, q_speed, ks_arr = self._q_dir, self._q_speed, self._ks
        np.arctan2(vv, vu, out=q_dir)  # direction - theta0, in (-pi, pi]: np.interp takes it as is
        np.hypot(vu, vv, out=ks_arr)
        np.maximum(ks_arr, it._ks0, out=q_speed)
        np.log(q_speed, out=q_speed)
        self._frac_ds[...] = np.interp(self._q, it._ds_xp, it._ds_fp)
        if it.periodic:
            np.mod(self._f_ij, it._nij, out=self._frac_ij)
        else:
            np.clip(self._f_ij, 0.0, it._nij_max, out=self._frac_ij)
            if np.not_equal(self._frac_ij, self._f_ij, out=self._clipped).any():
                return None  # outside: the general path mirrors the surface and the direction
        lo = np.minimum.reduce(ks_arr)
        hi = np.maximum.reduce(ks_arr)
        amp = it._corners(self._frac, self._work)
        a40 = np.maximum(amp.real, 0.0)  # a contiguous copy; guards rounding (convex sums of >= 0)
        a320 = np.maximum(amp.imag, 0.0)
        if lo >= it._ks0 and hi <= it._ks_top:
            return a40, a320, np.zeros(self.n, dtype=np.uint8)
        below = ks_arr < it._ks0
        above = ks_arr > it._ks_top
        if lo < it._ks0:  # fade to zero below the lowest speed node
            fade = np.where(below, ks_arr / it._ks0, 1.0)
            a40 *= fade
            a320 *= fade
        return a40, a320, above.view(np.uint8) | (below.view(np.uint8) << 1)


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
