"""More starts for lights that leave some waves unseen: a periodic tile lit along its axes or
diagonals, and a weave lit nearly along one of its directions. The waves across such a light
have no slope along it and the shading fixes them only at second order, so the pyramid alone
can leave them wrong; the extra solves run side by side and the one of lowest energy is kept.
"""
from __future__ import annotations

import functools

import numpy as np
import scipy.fft as sfft

from haptex_compile import shading_image, shading_light
from haptex_compile.forked_map import forked_map
from haptex_compile.shading_image import Light, _censored_pixels, tilt_axis_difference_deg, valid_pixels

# On a periodic tile, light within this angle of a direction across which a tile-sized wave
# runs (the tile's axes and diagonals, i.e. perpendicular to the wave vectors of 1 cycle per
# tile along x, y or both) is warned of: those waves have no slope along the light, so the
# shading sees them only at second order and the solver leaves them wrong. Measured on the
# bench surfaces at 60° (256 px, light given): plain weave tilt 0, +1, +2, +3° 0.885, 0.881,
# 0.823, 0.067; bumps at 270° 0.758, 0.450 (+1), 0.070 (+2), 0.023 (+3); Brownian at 0°
# 0.213, 0.187 (+1), 0.092 (+2), 0.040 (+3); off these directions 0.02-0.07.
ALIGNED_TILT_DEG = 3.0
# A lattice relief (a weave photo's tile) lit nearly along one of its weave directions: the
# profiles across that direction (a yarn's cross-section) have little slope along the light,
# and the shading sees them at first order only in proportion to sin(slant) |sin(angle between
# the tilt and the direction)| (see weave_visibility), which is warned of below this. Measured
# with bench/bench_photo.py (1024 px photos of 20 µm pixels, light given; plain weaves and
# smooth cells on a square and an oblique lattice, slants 15-60°, tilts 0-30° off a weave
# direction 0, 3, 8, 12, 20, 30°): 54 lights below 0.15, 25 of them with height errors above
# 0.1 from the pyramid alone (up to 0.76, plain weaves lit 3° off their yarns at 30°); 18 above
# it, errors at most 0.105. Below it the solve adds starts at full resolution
# (_fine_starts, on a small window of the lattice: _start_from_cell), which leaves 3
# above 0.1 (0.106-0.263; 7, up to 0.74, before FINE_START_SMOOTH_LAMS); at slant 15° every
# tilt is below it on a square lattice.
WEAVE_VISIBILITY_MIN = 0.15


# Light nearly along a weave direction and along its window's axis or diagonal: the solve is
# repeated with the waves that have no slope along the light held on the coarse levels (from
# these pyramid levels on), and the result of lowest energy is kept (see _held_starts).
HELD_START_LEVELS = (2, 1)
# A tile with no lattice given holds them from this level only (see _bare_tile_starts).
BARE_TILE_HELD_LEVEL = 2


def _lowest_energy(img, weight, light: Light, domain_kwargs: dict, starts: list, basis_px=None):
    """Of the solves `starts`, (z, albedo) pairs on the domain, the one of lowest energy (the
    same energy for all: the finest level's; the first of equals).

    With `basis_px` (a weave's lattice, on which the domain is periodic), when a solve does
    not repeat cell by cell (its RMS departure from its cell average above
    ``CELL_REPEAT_MAX`` of its RMS), the solves are scored by the energies of their cell
    averages (:func:`_cell_average`), painted back over the domain: the heights a weave's
    surface keeps (``photo.photo_surface`` averages them over the lattice). On the real
    photos in ``../shared/fabrics`` lit near a weave direction or overhead (as estimated) the
    solves depart by 32-100 % and their averages' energies are 3-34 x their own, in another
    order. Solves that repeat (the bench's synthetic weaves: 1-5 %) keep their own energies:
    the average's interpolation doubles them there, and ranked by it the bench's
    weave-direction table lost (plain weave on the oblique lattice at 45°, 8° off t1: 0.081
    -> 0.147).
    """
    from haptex_compile.shading_variational import energy

    censored = {k: domain_kwargs[k] for k in ("dark", "bright") if k in domain_kwargs}
    finite = [bool(np.all(np.isfinite(z))) for z, _ in starts]  # a non-finite solve comes last
    scored = [z for z, _ in starts]
    if basis_px is not None:
        averages = [_cell_average(z, basis_px).synthetic if ok else z for (z, _), ok in zip(starts, finite)]
        if any(ok and np.std(z - a) > CELL_REPEAT_MAX * np.std(z) for z, a, ok in zip(scored, averages, finite)):
            scored = averages
    energies = [energy(img, weight, light.vector, a, z, **censored) if ok else np.inf
                for z, (_, a), ok in zip(scored, starts, finite)]
    return starts[int(np.argmin(np.nan_to_num(energies, nan=np.inf)))]


def _cell_average(z: np.ndarray, basis_px):
    """The mean of periodic `z` over the cells of its lattice (columns t1, t2 in pixels; `z` is
    periodic on it): a ``tiles.TileAverage`` whose ``synthetic`` is painted over `z`'s shape."""
    from haptex_compile.lattice import Lattice
    from haptex_compile.tiles import average_tile

    b = np.asarray(basis_px, dtype=float)
    return average_tile(z, Lattice(True, b[:, 0], b[:, 1], 1.0, "the domain's lattice"),
                        combine="mean", samples_per_px=2.0, flatten_sigma_px=None)


def _held_starts(img, weight, light: Light, albedo0: float, kwargs: dict) -> list:
    """The solves (z, albedo) holding the waves with no slope along the light from each of
    ``HELD_START_LEVELS`` on (`kwargs`: the main solve's settings).

    A coarse level's averaged image sets those waves wrong, and the finest level cannot undo
    them. Measured at 256 px, light given along the axes and diagonals, slants 30-60°: plain
    weave at worst 0.885 -> 0.063, random bumps 0.758 -> 0.311 (60°, along y), 0.233 -> 0.096
    (30°, along x); the sphere cap along the diagonal at 60° stays at 0.470 (no start finds
    its minimum), Brownian surfaces within 0.02 except one at 0.053 -> 0.076.
    """
    return _side_by_side(*(functools.partial(_held_start, img, weight, light, albedo0, kwargs, level)
                           for level in HELD_START_LEVELS))


def _held_start(img, weight, light: Light, albedo0: float, kwargs: dict, level: int):
    """The pyramid solve (z, albedo) with `kwargs` (the main solve's settings), holding the
    waves with no slope along the light from pyramid level `level` on."""
    from haptex_compile.shading_variational import solve_variational

    return solve_variational(img, weight, light.vector, albedo0, hold_from_level=level, **kwargs)


def _side_by_side(*calls) -> list:
    """The results of the independent zero-argument `calls`, in order, run side by side in
    forked workers (``SEARCH_PROCESSES``; the same results in one process)."""
    with forked_map(lambda k: calls[k](), shading_light.SEARCH_PROCESSES) as map_:
        return map_([(k,) for k in range(len(calls))])


# Full-resolution starts for light along a tile's axis or diagonal or nearly along a weave
# direction (see _fine_starts): Gauss-Newton steps and CG iterations of each solve,
# the relative gain at which it stops, and the thin-plate weights of the continuation start.
FINE_START_GN = 30
FINE_START_CG = 20
FINE_START_RTOL = 1e-5
FINE_START_LAMS = (1e-3, 1e-4)
# A second continuation starts smoother (see _continuation_start): near a weave direction the
# energy has several minima close in value, and the one a continuation ends in depends on where
# it starts. Measured with bench/bench_photo.py's table of lights near a weave direction (72
# cases, light given), this added to the starts against without it: the plain weave on the
# 16 px square lattice lit along x at 15° 0.585 -> 0.021, 30° off x at 15° 0.130 -> 0.021,
# 3° off x at 30° 0.655 -> 0.033, the oblique lattice's plain weave 3° off t2 at 30° 0.759 ->
# 0.018; the other 68 within 0.002; errors above 0.1: 7 of 54 warned -> 3 (0.106, 0.135,
# 0.263). In their place (one continuation, from 1e-2) it lost a case: the oblique weave 3° off
# t1 at 45° 0.056 -> 0.722, a minimum of lower energy on the small window. Bare tiles lit along
# their axes and diagonals (bench_shading, 256 px, slants 30-60°): summed error of the 24
# warned lights 1.256 -> 1.030 (random bumps along x at 45° 0.222 -> 0.049, the plain weave
# along x at 30° and 45° 0.030 / 0.028 -> 0.008; Brownian along the diagonal at 30° 0.058 ->
# 0.076), the sphere cap along the diagonal at 60° still 0.46; that table's solves 13.2 ->
# 20.8 s.
FINE_START_SMOOTH_LAMS = (1e-2, 1e-3, 1e-4)


def _fine_starts(img, weight, light: Light, albedo0: float, domain_kwargs: dict) -> list:
    """Three or four solves (z, albedo) at full resolution only, from flat starts; the caller
    keeps the one of lowest energy (:func:`_lowest_energy`).

    A coarse level of a lattice relief lit nearly along a weave direction under-resolves the
    yarns, and its averaged image sets their cross-sections (the waves the light barely sees)
    wrong; the finer levels keep that. From a flat start at full resolution the shading's
    coupling with the well-seen waves sets them (plain weave, 16 px cells, lit 3° off its
    yarns at 45°: 0.649 from the pyramid, 0.024 from the flat start, which is the truth's
    energy). The starts: flat (``FINE_START_GN`` steps); that result with the waves that have
    no slope at all along the light (light along the domain's axes or diagonals) negated,
    since the shading sees them only at second order, where a ridge and a groove look alike;
    and flat with the thin-plate weight stepped down through ``FINE_START_LAMS`` (smooth
    shapes first), and again from a smoother start through ``FINE_START_SMOOTH_LAMS`` (added
    later: measured there). Measured (plain weaves and smooth cells in 208 px periodic windows of a
    square and an oblique lattice, slants 30-60°, 0-12° off a weave direction, light given):
    summed height errors 8.6 -> 3.1 and 9.6 -> 5.9; at 1° off, where no start finds the
    truth's basin, the energy can pick worse (0.475 -> 0.990 once). On bench/bench_photo.py's
    photos (54 lights below ``WEAVE_VISIBILITY_MIN``): errors above 0.1 in 25 cases -> 7.
    Bench tiles lit along their axes and diagonals (slants 30-60°): summed 3.58 -> 1.74,
    random bumps along the axes at 60° 0.474 -> 0.123 and 0.524 -> 0.075; none worse by more
    than 0.03. Cost: up to 2 x ``FINE_START_GN`` steps at full resolution (3 x when the light
    runs along the domain's axes or diagonals): on a plain weave tile of 1024 px lit 3° off
    its yarns, 12-13 s instead of 0.6 s. A weave's tile runs them on a small window of its
    lattice instead (:func:`_start_from_cell`). The chains (flat, then its unseen waves
    negated; each continuation) run side by side in worker processes, as do
    :func:`_held_starts`' two solves (``SEARCH_PROCESSES``; the same heights): measured on 2
    cores, bench tiles of 256 px lit along their axes and diagonals (three surfaces, three
    lights, and a lattice along a weave direction) 12.5 -> 8.7 s in all, random bumps of
    512 px and 1024 px lit along x 5.7 -> 4.1 s and 17.1 -> 15.8 s. A tile with no lattice
    given runs the continuations and one held pyramid start instead (:func:`_bare_tile_starts`).
    """
    def flat_and_negated():
        zf, af = _full_resolution_solve(img, weight, light, albedo0, domain_kwargs)
        invisible = _unseen_waves(zf, light)
        return [(zf, af)] + ([] if invisible is None else
                             [_full_resolution_solve(img, weight, light, af, domain_kwargs, zf - 2.0 * invisible)])

    # The chains are independent: side by side.
    first, *continued = _side_by_side(flat_and_negated, *_continuations(img, weight, light, albedo0, domain_kwargs))
    return first + continued


def _full_resolution_solve(img, weight, light: Light, albedo0: float, domain_kwargs: dict, z_start=None,
                           steps: int = FINE_START_GN, **thin_plate):
    """One solve of the full-resolution starts (see :func:`_fine_starts`): `steps`
    Gauss-Newton steps on the domain only, from `z_start` (flat by default)."""
    from haptex_compile.shading_variational import solve_variational

    return solve_variational(img, weight, light.vector, albedo0, z0=z_start, max_levels=1, fine_gn=steps,
                             fine_cg=FINE_START_CG, gn_rtol=FINE_START_RTOL, **thin_plate, **domain_kwargs)


def _continuation_start(img, weight, light: Light, albedo0: float, domain_kwargs: dict,
                        lams: tuple[float, ...]):
    """A continuation of :func:`_fine_starts`: from flat at full resolution, with the thin
    plate's weight stepped down through `lams` (smooth shapes first; ``FINE_START_GN`` steps
    shared between them); (z, albedo)."""
    zc, ac = None, albedo0
    for lam in lams:
        zc, ac = _full_resolution_solve(img, weight, light, ac, domain_kwargs, zc, FINE_START_GN // len(lams), lam=lam)
    return zc, ac


def _continuations(img, weight, light: Light, albedo0: float, domain_kwargs: dict) -> list:
    """The zero-argument calls of :func:`_continuation_start`, one per schedule of the thin
    plate's weight (``FINE_START_LAMS``, ``FINE_START_SMOOTH_LAMS``), to run side by side."""
    return [functools.partial(_continuation_start, img, weight, light, albedo0, domain_kwargs, lams)
            for lams in (FINE_START_LAMS, FINE_START_SMOOTH_LAMS)]


def _bare_tile_starts(img, weight, light: Light, albedo0: float, kwargs: dict, domain_kwargs: dict) -> list:
    """The starts of a tile with no lattice given, lit along its axis or diagonal: the pyramid
    with the waves that have no slope along the light held from level ``BARE_TILE_HELD_LEVEL``
    on (`kwargs`: the main solve's settings), and the two continuations at full resolution
    (:func:`_continuation_start` through ``FINE_START_LAMS`` and ``FINE_START_SMOOTH_LAMS``),
    side by side; the caller keeps the lowest energy.

    Of the starts a weave's tile runs (:func:`_held_starts`, :func:`_fine_starts`), the held
    start and the first continuation are the ones that were kept (the smoother continuation
    was added later, see ``FINE_START_SMOOTH_LAMS``): measured at 256, 512 and 1024 px (the
    bench's four surfaces and random bumps of seeds 5 and 9, only 5 at 1024 px; slants 30°,
    45° and 60°, light along x and along the diagonal: 36, 36 and 30 cases), the lowest energy
    was the continuation's in 24, 22 and 12 cases, the plain pyramid's in 7, 10 and 11, the start held
    from level 2 in 3, 4 and 6, and the flat start or its negation in 2, 0 and 1 (the plain
    weave along the diagonal at 45° and 60° at 256 px, the bumps of seed 5 along x at 60° at
    1024 px, where the continuation came within 0.1 % of their energy, with height errors
    0.005 -> 0.006, 0.009 -> 0.009 and 0.068 -> 0.062); the start held from level 1, in none.
    Measured without the other three on the bench's four surfaces (24 lights along x and the
    diagonal at 256 px, 12 at 512 and 1024 px): the same errors (to 0.001) but for the plain
    weave along the diagonal at 45° (256 px: 0.005 -> 0.006), and a solve takes 0.47 s
    instead of 0.94 s at 256 px, 1.8 s instead of 4.0 s at 512 px and 6.1 s instead of 15.9 s
    at 1024 px (means, one run each). With the smoother continuation (the report at e41cea3),
    random bumps lit along x at 45° took 9.6-10.4 s per megapixel at 256-1024 px, against
    5.6-7.1 s in the previous report (the host about 20 % slower; at 256 px the error 0.330 ->
    0.044).
    """
    return _side_by_side(lambda: _held_start(img, weight, light, albedo0, kwargs, BARE_TILE_HELD_LEVEL),
                         *_continuations(img, weight, light, albedo0, domain_kwargs))


# The full-resolution starts of a weave's tile run on a small periodic window of its lattice
# (tiles.small_periodic_window, as for the light search), and the best is averaged over the
# cell, painted over the domain and polished there with FINE_POLISH_GN steps (see
# _start_from_cell). A solve departing from its cell average by more than CELL_REPEAT_MAX of
# its RMS does not repeat cell by cell (see _lowest_energy).
FINE_POLISH_GN = 3
CELL_REPEAT_MAX = 0.2


def _start_from_cell(img, weight, light: Light, albedo0: float, domain_kwargs: dict,
                     basis_px, raw: np.ndarray) -> list | None:
    """:func:`_fine_starts` for a domain that repeats a weave's lattice (`basis_px`, columns
    t1, t2 in pixels; the domain is exactly periodic on it), run on a small periodic window of
    the lattice's averaged tile (a weave's solution repeats in every cell): the one of lowest
    energy there is averaged over the cell, painted over the domain and polished with
    ``FINE_POLISH_GN`` Gauss-Newton steps; returned as a list of one.

    None (the caller runs the starts on the domain itself) when no window of at most a
    quarter of the domain strains the lattice by ``tiles.SMALL_WINDOW_STRAIN`` or less.
    Where the window's solution does not repeat in every cell (the real ``plain-2000px.jpg``,
    light estimated 10° off a weave direction at slant 30°: it departs from its cell average
    by 85 %; the bench's synthetic weaves by 0-5 %), its average, polished, has a higher
    energy than the starts run on the domain; but those do not repeat either, and it is their
    cell averages that the surface keeps, whose energies are higher still: the solves are
    then compared by their averages (see :func:`_lowest_energy`), and the starts need not
    run on the domain. Measured on the three real photos whose window's solution does not
    repeat (``photo_surface``, light estimated), the energy of the kept heights' cell
    average against the starts run on the domain: ``plain-2000px.jpg`` 829 -> 358 (15.9 s
    -> 5.2 s), ``plain-defect-e2r10.jpg`` 411 -> 210 (6.8 s -> 2.4 s), ``plain-slub-a10.bmp``
    600 -> 322 (4.7 s -> 2.9 s).

    `raw` is the image with its unknown pixels NaN: the window is painted from the raw
    intensities, attached shadows included (from the domain image, whose invalid pixels hold
    the mean, a plain weave lit at 60°, 3° off its yarns, came back at 0.76 instead of 0.04).

    Measured: plain weave tile of 1024 px (16 px cells, 64 px window) lit 3° off its yarns
    at 45°: 1.44 s instead of 13.6 s for the same height error (0.024);
    bench/bench_photo.py's plain weave lit 7° off t1 + t2 (a 975 x 787 px window): the
    pipeline 3.1 s instead of 13.6 s (0.024 against 0.023). The bench's 54 warned lights:
    summed errors 3.87 -> 3.83, the same 7 above 0.1; the one worse by more than 0.01 is the
    oblique lattice's plain weave exactly along t1 at 45° (0.225 -> 0.263, 0.087 from the
    pyramid alone). Polishing every start (not only the best) or with 6 steps: 3.87 either
    way, slower.
    """
    from haptex_compile.tiles import paint_tile, small_periodic_window

    basis = np.asarray(basis_px, dtype=float)
    small = small_periodic_window(basis)
    if small is None or small[1][0] * small[1][1] > img.size / 4:
        return None

    b_small, shape_small = small
    small_img = np.clip(paint_tile(_cell_average(raw, basis).tile, b_small, shape_small), 0.0, None)
    small_weight = valid_pixels(small_img).astype(np.float32)
    small_kwargs = dict(zip(("dark", "bright"), _censored_pixels(small_img))) if shading_image.CENSORED else {}
    z, a = _lowest_energy(small_img, small_weight, light, small_kwargs,
                          _fine_starts(small_img, small_weight, light, albedo0, small_kwargs))
    z0 = paint_tile(_cell_average(z, b_small).tile, basis, img.shape)
    return [_full_resolution_solve(img, weight, light, a, domain_kwargs, z0, FINE_POLISH_GN)]


def _unseen_waves(z: np.ndarray, light: Light) -> np.ndarray | None:
    """The part of periodic `z` made of waves with no slope along the light's tilt (wave
    vector perpendicular to it: the light runs along the domain's axes or diagonals), or None
    when there are none."""
    rows, cols = z.shape
    ky = np.fft.fftfreq(rows)[:, None]
    kx = np.fft.rfftfreq(cols)[None, :]
    t = np.deg2rad(light.tilt_deg)
    unseen = np.abs(kx * np.cos(t) + ky * np.sin(t)) <= 1e-6 * np.hypot(kx, ky)
    unseen[0, 0] = False
    if not unseen.any():
        return None
    spec = sfft.rfft2(z.astype(np.float64))
    return sfft.irfft2(np.where(unseen, spec, 0.0), s=z.shape).astype(z.dtype)


def _tile_aligned_tilt(tilt_deg: float, shape: tuple[int, int]) -> tuple[str, float] | None:
    """The periodic tile's axis or diagonal within ``ALIGNED_TILT_DEG`` of the light's tilt,
    as (name, its tilt in degrees), or None.

    Those directions are perpendicular to the wave vectors of one cycle per tile along x
    (``(1/cols, 0)``), y, or both (``(1/cols, ±1/rows)``): a wave with such a vector has no
    slope along the light. For a square tile they are the axes and the diagonals.
    """
    rows, cols = shape
    directions = {
        "x axis": 0.0,
        "y axis": 90.0,
        "diagonal": float(np.degrees(np.arctan2(rows, cols))),  # across the (1, -1) wave
        "anti-diagonal": float(np.degrees(np.arctan2(rows, -cols))),  # across the (1, 1) wave
    }
    for name, direction in directions.items():
        if tilt_axis_difference_deg(tilt_deg, direction) < ALIGNED_TILT_DEG:
            return name, direction % 180.0
    return None


def weave_visibility(light: Light, basis_px) -> tuple[float, float]:
    """How directly `light` sees the profiles across a lattice relief's weave directions.

    The weave directions are the lattice's shortest vectors t1, t2 (the columns of
    `basis_px`, a reduced basis as :func:`haptex_compile.lattice.find_lattice` returns) and
    t1 ± t2 (a plain weave's yarns run along its reduced vectors or along their sum and
    difference, depending on which repeat the lattice found). A wave across direction d has
    no slope along d, and the first-order (linear) shading term sees its slope in proportion
    to ``sin(slant) |sin(angle between the tilt and d)|``; lit along d it is seen only at
    second order, where a ridge and a groove look alike (see ``WEAVE_VISIBILITY_MIN``).

    Returns
    -------
    (float, float)
        The smallest of those visibilities over the four directions (0 to 1), and the tilt in
        degrees (in [0, 180)) of the direction that has it.
    """
    basis = np.asarray(basis_px, float)
    t1, t2 = basis[:, 0], basis[:, 1]
    sin_slant = float(np.sin(np.deg2rad(light.slant_deg)))
    best = (np.inf, 0.0)
    for d in (t1, t2, t1 + t2, t1 - t2):
        direction = float(np.degrees(np.arctan2(d[1], d[0]))) % 180.0
        off = tilt_axis_difference_deg(light.tilt_deg, direction)
        best = min(best, (sin_slant * float(np.sin(np.deg2rad(off))), direction))
    return best
