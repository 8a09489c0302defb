"""Compiled (numba) kernels of the shape-from-shading solver's per-pixel work: a Gauss-Newton
step's pixel terms, the conjugate-gradient operator and the CG vector updates, and the line
search's reflectance, albedo fit and energy.

The Gauss-Newton system's operator, ``A v = J^T W J v + lam L^T L v + shift v`` (periodic
central differences for J, the 13-point biharmonic for ``L^T L``), was a chain of a dozen numpy
passes over the image, each reading and writing whole arrays; it cost more than the FFT
preconditioner. Here it is two passes: the Jacobian's product ``J v``, then the rest, each
pixel's sum computed once from its neighbours. The kernels work on a block of rows (periodic
neighbours from the whole array) and release the GIL, so the solver's row-block threads run
them side by side; a pixel's value does not depend on the blocks, and sums are returned by
row (in float64), so results are the same on any number of threads. Kernels with such sums
let LLVM reassociate them (``fastmath={"reassoc"}``) so that the loops vectorise: the order of
a row's sum then follows the CPU's vector width, not the threads.

Compiled on first use and cached (next to this file or in numba's user cache directory; see
:func:`_kernel` where neither is writable): measured here, the first solve of a fresh install
took 3.1 s longer, the first of a later process 0.35 s.

The line search's passes (reflectance, the albedo's sums, the energy's sums) replaced numpy
passes too: at 1024 px, 2.2 -> 1.3 ms, 6.6 -> 0.9 ms and 2.7 -> 0.5 ms per call.
"""

from __future__ import annotations

import logging

import numba
import numpy as np

LOG = logging.getLogger("haptex.shading")
_UNCACHED: list[str] = []  # kernels compiled without a cache (no writable cache directory)


def _kernel(**options):
    """``numba.njit(nogil=True, cache=True, **options)``; where numba finds no writable cache
    directory (a read-only install and no writable home), it refuses ``cache=True`` at import,
    and the kernel is then compiled on each run instead (about 3 s for all of them)."""
    def decorate(fn):
        try:
            return numba.njit(nogil=True, cache=True, **options)(fn)
        except RuntimeError:  # "cannot cache function ...: no locator available"
            if not _UNCACHED:
                LOG.warning("numba has no writable cache directory: the shape-from-shading kernels"
                            " are compiled on each run (about 3 s); set NUMBA_CACHE_DIR to keep them")
            _UNCACHED.append(fn.__name__)
            return numba.njit(nogil=True, **options)(fn)
    return decorate

# float32 constants: a Python int or float would promote the sums to float64.
_F20, _F8, _F2 = np.float32(20.0), np.float32(8.0), np.float32(2.0)
_HALF, _ONE = np.float32(0.5), np.float32(1.0)


# Numba checks every signed index for wrap-around (a negative index counts from the end), which
# keeps LLVM from vectorising a loop that reads ``x[c - 1]``; the loops below therefore index
# shifted slices with ``c >= 0`` only (measured: the thin-plate and transpose pass at 1024 px,
# 3.7 -> 0.9 ms). Edge columns, whose neighbours wrap, are done one by one.


@_kernel()
def jacobian_rows(v, ha, hb, out, r0, r1):
    """Rows ``r0:r1`` of ``ha * (v[:, j+1] - v[:, j-1]) + hb * (v[i+1] - v[i-1])`` (periodic)
    into `out`: the Jacobian's product with `v`, its halves folded into `ha`, `hb`."""
    n, m = v.shape
    for i in range(r0, r1):
        vr, vu, vd = v[i], v[(i + 1) % n], v[(i - 1) % n]
        a, b, o = ha[i], hb[i], out[i]
        for c in (0, m - 1):
            o[c] = a[c] * (vr[(c + 1) % m] - vr[(c - 1) % m]) + b[c] * (vu[c] - vd[c])
        if m > 2:
            vp, vm, vuc, vdc = vr[2:], vr[:m - 2], vu[1:m - 1], vd[1:m - 1]
            ac, bc, oc = a[1:m - 1], b[1:m - 1], o[1:m - 1]
            for c in range(m - 2):
                oc[c] = ac[c] * (vp[c] - vm[c]) + bc[c] * (vuc[c] - vdc[c])


@numba.njit(inline="always")
def _operator_value(v0, v_r, v_l, v_u, v_d, v_ur, v_ul, v_dr, v_dl, v_rr, v_ll, v_uu, v_dd,
                    ja_r, ja_l, jb_u, jb_d, lam, shift):
    """One pixel of :func:`normal_rows` from `v` at it and its neighbours (r, l: columns
    c ± 1; u, d: rows i ± 1; doubled: ± 2) and the weighted Jacobian products ``jv * nwa`` at
    columns c ± 1 (`ja_*`) and ``jv * nwb`` at rows i ± 1 (`jb_*`). Scalars only: arrays
    passed per pixel would be reference-counted per pixel."""
    bih = (_F20 * v0 - _F8 * (v_r + v_l + v_u + v_d) + _F2 * (v_ur + v_ul + v_dr + v_dl)
           + (v_rr + v_ll + v_uu + v_dd))
    return lam * bih + shift * v0 + (ja_r - ja_l) + (jb_u - jb_d)


@_kernel()
def normal_rows(v, jv, nwa, nwb, lam, shift, u, cu, out, r0, r1):
    """Rows ``r0:r1`` of ``lam * biharmonic(v) + shift * v + Dx(jv * nwa) + Dy(jv * nwb)
    - cu * u`` into `out` (periodic; ``Dx f = f[:, j+1] - f[:, j-1]``, likewise Dy): with
    ``jv`` from :func:`jacobian_rows` and ``nwa, nwb`` the Jacobian's coefficients times
    minus the data weights, the operator ``J^T W J v`` plus the thin plate, a small shift and
    a rank-one term (``cu = 0``: none). `lam`, `shift` and `cu` are float32."""
    n, m = v.shape
    for i in range(r0, r1):
        i1, i2, k1, k2 = (i + 1) % n, (i + 2) % n, (i - 1) % n, (i - 2) % n
        v0, vu1, vu2, vd1, vd2 = v[i], v[i1], v[i2], v[k1], v[k2]
        j0, ju, jd = jv[i], jv[i1], jv[k1]
        a0, bu, bd = nwa[i], nwb[i1], nwb[k1]
        o = out[i]
        for e in range(min(m, 4)):  # the edge columns, with wrapped neighbours
            c = e if e < 2 or m < 4 else m - 4 + e
            cp, cm, cp2, cm2 = (c + 1) % m, (c - 1) % m, (c + 2) % m, (c - 2) % m
            o[c] = _operator_value(v0[c], v0[cp], v0[cm], vu1[c], vd1[c], vu1[cp], vu1[cm], vd1[cp], vd1[cm],
                                   v0[cp2], v0[cm2], vu2[c], vd2[c], j0[cp] * a0[cp], j0[cm] * a0[cm],
                                   ju[c] * bu[c], jd[c] * bd[c], lam, shift)
        if m > 4:
            # Column offsets -2..2 as slices of the interior, all indexed by c >= 0.
            w = m - 4
            vm2, vm1, vc, vp1, vp2 = v0[0:w], v0[1:w + 1], v0[2:w + 2], v0[3:w + 3], v0[4:w + 4]
            u1m, u1c, u1p = vu1[1:w + 1], vu1[2:w + 2], vu1[3:w + 3]
            d1m, d1c, d1p = vd1[1:w + 1], vd1[2:w + 2], vd1[3:w + 3]
            u2c, d2c = vu2[2:w + 2], vd2[2:w + 2]
            jm, jp, am, ap = j0[1:w + 1], j0[3:w + 3], a0[1:w + 1], a0[3:w + 3]
            juc, jdc, buc, bdc = ju[2:w + 2], jd[2:w + 2], bu[2:w + 2], bd[2:w + 2]
            oc = o[2:w + 2]
            for c in range(w):
                oc[c] = _operator_value(vc[c], vp1[c], vm1[c], u1c[c], d1c[c], u1p[c], u1m[c], d1p[c], d1m[c],
                                        vp2[c], vm2[c], u2c[c], d2c[c], jp[c] * ap[c], jm[c] * am[c],
                                        juc[c] * buc[c], jdc[c] * bdc[c], lam, shift)
        if cu != 0:
            ur = u[i]
            for c in range(m):
                o[c] -= cu * ur[c]


@_kernel(fastmath={"reassoc"})
def cg_update_rows(x, rr, d, ad, alpha, row_sq, r0, r1):
    """Rows ``r0:r1`` of the conjugate-gradient update ``x += alpha d``, ``rr -= alpha ad``;
    ``row_sq[i]`` = the sum of the new ``rr[i]²`` (float64; summed by row, so the total is
    the same for any blocks of rows)."""
    m = x.shape[1]
    for i in range(r0, r1):
        xi, ri, di, adi = x[i], rr[i], d[i], ad[i]
        s = 0.0
        for c in range(m):
            xi[c] += alpha * di[c]
            r = ri[c] - alpha * adi[c]
            ri[c] = r
            s += np.float64(r) * np.float64(r)
        row_sq[i] = s


@_kernel()
def cg_direction_rows(d, zz, beta, r0, r1):
    """Rows ``r0:r1`` of the conjugate-gradient direction ``d = beta d + zz``."""
    m = d.shape[1]
    for i in range(r0, r1):
        di, zi = d[i], zz[i]
        for c in range(m):
            di[c] = beta * di[c] + zi[c]


@numba.njit(inline="always")
def _reflectance_pixel(p, q, lx, ly, lz, k, cx, cy):
    """R(p, q) and its partial derivatives (float32) for the unit light (lx, ly, lz), the
    squared slope across the light (the unit direction (cx, cy)) weighted by 1 - k in the
    normalisation ``sqrt(1 + p² + q²)`` (k = 0: the exact reflectance)."""
    pc = cx * p + cy * q
    g = _ONE + p * p + q * q - k * pc * pc
    gp = p - k * cx * pc
    gq = q - k * cy * pc
    inv = _ONE / np.sqrt(g)
    num = lz - p * lx - q * ly
    inv3 = inv / g
    return num * inv, -lx * inv - num * gp * inv3, -ly * inv - num * gq * inv3


@numba.njit(inline="always")
def _half_differences(zc, zu, zd, p, q):
    """Halved periodic central differences of a row `zc` (into `p`) and between the rows
    below and above it (into `q`)."""
    m = zc.shape[0]
    for c in range(m):
        q[c] = (zu[c] - zd[c]) * _HALF
    p[0] = (zc[1 % m] - zc[m - 1]) * _HALF
    p[m - 1] = (zc[0] - zc[(m - 2) % m]) * _HALF
    if m > 2:
        zp, zm, pc = zc[2:], zc[:m - 2], p[1:m - 1]
        for c in range(m - 2):
            pc[c] = (zp[c] - zm[c]) * _HALF


@numba.njit(inline="always")
def _censored_residuals(model, dark_level, bright_level):
    """The one-sided residuals of a censored pixel at model intensity ``albedo R``: above
    `dark_level` for a black one (0 below), below `bright_level` for a saturated one (0
    above)."""
    zero = np.float32(0.0)
    return max(model - dark_level, zero), min(model - bright_level, zero)


@_kernel(fastmath={"reassoc"})
def gn_setup_rows(z, img, w, dark, bright, has_dark, has_bright, light, k, across, albedo,
                  dark_level, bright_level, project, fa, fb, ha, hb, nwa, nwb, ua, ub, sums, r0, r1):
    """Rows ``r0:r1`` of a Gauss-Newton step's pixel terms at heights `z` (pixel units), from
    the reflectance (see :func:`_reflectance_pixel` for `light`, `k` and `across`): the
    gradient's factors ``fa, fb = J * W res`` (J = albedo x R's partial derivatives; W res
    with the one-sided terms of the `dark` and `bright` weights where `has_dark`,
    `has_bright`, else those arrays are not read), the Jacobian's halves ``ha, hb`` and
    ``nwa, nwb`` = minus them times the active weights (for :func:`normal_rows`), with
    `project` the variable projection's ``ua, ub = J * w r`` (else not written); and by row,
    into ``sums[i]`` (float64), the sums of ``w rp²``, ``w rp rq``, ``w rq²`` and ``w r²``.
    Scalars are float32 (`has_*`, `project`: bool)."""
    n, m = z.shape
    lx, ly, lz = light[0], light[1], light[2]
    cx, cy = across[0], across[1]
    p, q = np.empty(m, np.float32), np.empty(m, np.float32)
    zero = np.float32(0.0)
    for i in range(r0, r1):
        _half_differences(z[i], z[(i + 1) % n], z[(i - 1) % n], p, q)
        imr, wr, dkr, btr, far, fbr = img[i], w[i], dark[i], bright[i], fa[i], fb[i]
        har, hbr, nwar, nwbr, uar, ubr = ha[i], hb[i], nwa[i], nwb[i], ua[i], ub[i]
        s0 = s1 = s2 = s3 = 0.0
        for c in range(m):
            rv, rp, rq = _reflectance_pixel(p[c], q[c], lx, ly, lz, k, cx, cy)
            im = imr[c]
            res = albedo * rv - im
            ja, jb = albedo * rp, albedo * rq
            w0 = wr[c]
            wres, wact = w0 * res, w0
            if has_dark or has_bright:
                cd, cb = _censored_residuals(res + im, dark_level, bright_level)
                if has_dark:
                    wres += dkr[c] * cd
                    wact += dkr[c] * np.float32(cd != zero)
                if has_bright:
                    wres += btr[c] * cb
                    wact += btr[c] * np.float32(cb != zero)
            far[c] = ja * wres
            fbr[c] = jb * wres
            h_a, h_b = ja * _HALF, jb * _HALF
            har[c] = h_a
            hbr[c] = h_b
            nwar[c] = -(wact * h_a)
            nwbr[c] = -(wact * h_b)
            wrv = w0 * rv
            if project:
                uar[c] = ja * wrv
                ubr[c] = jb * wrv
            s0 += w0 * rp * rp
            s1 += w0 * rp * rq
            s2 += w0 * rq * rq
            s3 += wrv * rv
        sums[i, 0] = s0
        sums[i, 1] = s1
        sums[i, 2] = s2
        sums[i, 3] = s3


@_kernel()
def reflectance_rows(z, light, k, across, r, r0, r1):
    """Rows ``r0:r1`` of the reflectance (albedo 1) of heights `z` (pixel units) into `r`
    (see :func:`_reflectance_pixel` for `light`, `k` and `across`; `k` float32)."""
    n, m = z.shape
    lx, ly, lz = light[0], light[1], light[2]
    cx, cy = across[0], across[1]
    p, q = np.empty(m, np.float32), np.empty(m, np.float32)
    for i in range(r0, r1):
        _half_differences(z[i], z[(i + 1) % n], z[(i - 1) % n], p, q)
        rr = r[i]
        for c in range(m):
            rr[c] = _reflectance_pixel(p[c], q[c], lx, ly, lz, k, cx, cy)[0]


@_kernel(fastmath={"reassoc"})
def albedo_sums_rows(r, img, w, sums, r0, r1):
    """By row, into ``sums[i]`` (float64), the sums of ``w r²`` and ``w r img``: the
    least-squares albedo's normal equation."""
    m = r.shape[1]
    for i in range(r0, r1):
        rr, ir, wr = r[i], img[i], w[i]
        s0 = s1 = 0.0
        for c in range(m):
            wrv = wr[c] * rr[c]
            s0 += wrv * rr[c]
            s1 += wrv * ir[c]
        sums[i, 0] = s0
        sums[i, 1] = s1


@_kernel(fastmath={"reassoc"})
def energy_rows(z, r, img, w, dark, bright, has_dark, has_bright, albedo, dark_level, bright_level,
                sums, r0, r1):
    """By row, into ``sums[i]`` (float64), the energy's sums at reflectance `r` of heights `z`
    (pixel units): ``w res²`` (``res = albedo r - img``), the one-sided terms of the `dark`
    and `bright` weights (where `has_dark`, `has_bright`; else those arrays are not read),
    and the squared periodic 5-point Laplacian of `z`. Scalars float32 (`has_*`: bool)."""
    n, m = z.shape
    four = np.float32(4.0)
    for i in range(r0, r1):
        zc, zu, zd = z[i], z[(i + 1) % n], z[(i - 1) % n]
        rr, ir, wr, dkr, btr = r[i], img[i], w[i], dark[i], bright[i]
        s0 = s1 = s2 = 0.0
        for c in range(m):
            im = ir[c]
            res = albedo * rr[c] - im
            s0 += wr[c] * res * res
            if has_dark or has_bright:
                cd, cb = _censored_residuals(res + im, dark_level, bright_level)
                if has_dark:
                    s1 += dkr[c] * cd * cd
                if has_bright:
                    s1 += btr[c] * cb * cb
        for e in range(min(m, 2)):  # the edge columns, with wrapped neighbours
            c = 0 if e == 0 else m - 1
            lap = zu[c] + zd[c] + zc[(c + 1) % m] + zc[(c - 1) % m] - four * zc[c]
            s2 += lap * lap
        if m > 2:
            zp, zm, zcc, zuc, zdc = zc[2:], zc[:m - 2], zc[1:m - 1], zu[1:m - 1], zd[1:m - 1]
            for c in range(m - 2):
                lap = zuc[c] + zdc[c] + zp[c] + zm[c] - four * zcc[c]
                s2 += lap * lap
        sums[i, 0] = s0
        sums[i, 1] = s1
        sums[i, 2] = s2


# Row profiles (the plain-image prior's plane term: its ramp and its box's indicator along x):
# per row, the row's products with the profiles and, back, their combination, inside the
# solver's passes over the rows. Each row is one thread's, so the results do not depend on the
# blocks of rows.


@_kernel(fastmath={"reassoc"})
def row_products_rows(v, profiles, out, r0, r1):
    """Rows ``r0:r1`` of ``out[k, i] = sum_c v[i, c] * profiles[k, c]`` (float32)."""
    m = v.shape[1]
    for i in range(r0, r1):
        vi = v[i]
        for k in range(profiles.shape[0]):
            pk = profiles[k]
            s = np.float32(0.0)
            for c in range(m):
                s += vi[c] * pk[c]
            out[k, i] = s


@_kernel()
def add_row_combinations_rows(coef, profiles, out, r0, r1):
    """Rows ``r0:r1`` of ``out[i, c] += sum_k coef[k, i] * profiles[k, c]`` (float32)."""
    m = out.shape[1]
    for i in range(r0, r1):
        o = out[i]
        for k in range(profiles.shape[0]):
            a = coef[k, i]
            if a != 0:
                pk = profiles[k]
                for c in range(m):
                    o[c] += a * pk[c]
