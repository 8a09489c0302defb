"""The compiler's pipeline: source -> surface -> tables (error-controlled) -> asset."""
from __future__ import annotations

import functools
import itertools
import logging
import math
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

import numpy as np

from haptex_compile.asset_writer import AssetContent, write_asset
from haptex_compile.colours import TwoColourModel
from haptex_compile.node_refinement import direction_draws, speed_draws, split_directions, split_speeds
from haptex_compile.errors import InputError
from haptex_compile.frame_analysis import AnalysisSettings
from haptex_compile.render import point_intensities, straight_path
from haptex_compile.scene import Scene
from haptex_compile.sources import SourceOptions, SourceResult, load_source
from haptex_compile.surface import Surface
from haptex_compile.tables import (MAX_TABLE_NODES, TableGrid, Tables, build_tables, halve_grid, stored_speeds,
                                   table_grid)
from playback.file_modes import new_file_mode

LOG = logging.getLogger("haptex.compile")
CHECK_SAMPLES_PER_FAMILY = 16
# Draws of check points added to a round whose measured error meets the tolerance while its 95 %
# upper bound does not (see build_checked_tables); each is CHECK_SAMPLES_PER_FAMILY per family.
CHECK_EXTRA_DRAWS = 3
CHECK_WORKERS = 2
# Refinement stops before the tables would hold more values than this per colour (64 MB as
# float32; memory while compiling is several times that), and the asset says the tolerance
# was not met.
MAX_TABLE_VALUES = 16_000_000
MAX_REFINEMENTS = 3
REFINE_BUDGET = 0.85  # refinement aims at this fraction of the tolerance
MAX_DIRECTIONS = 144  # direction nodes in [0, 180): 1.25 deg on average
MAX_HALVINGS_PER_ROUND = 2


@dataclass
class NodePlan:
    """Table nodes: directions (deg, in [0, 180)), speeds (mm/s), grid spacing (mm)."""

    directions_deg: np.ndarray
    speeds_mm_s: np.ndarray
    spacing_mm: float
    explicit_directions: bool = False
    explicit_speeds: bool = False
    explicit_spacing: bool = False


def model_for(scene: Scene) -> TwoColourModel:
    """The two-colour model a scene asks for (user threshold curves when given)."""
    from haptex_compile.thresholds import idealised_thresholds

    if scene.thresholds_csv:
        from haptex_compile.io_thresholds import read_thresholds_csv

        curves = read_thresholds_csv(scene.thresholds_csv)
    else:
        curves = idealised_thresholds()
    try:
        return TwoColourModel(thresholds=curves, base_frequencies_hz=scene.base_frequencies_hz,
                              summation_exponent=scene.summation_exponent)
    except ValueError as exc:
        raise InputError(scene.thresholds_csv or "scene", str(exc)) from None


def settings_for(scene: Scene) -> AnalysisSettings:
    return AnalysisSettings(frame_ms=scene.frame_ms, footprint_sigma_mm=scene.footprint_sigma_mm)


def _direction_nodes(lo: float, hi: float, step: float) -> np.ndarray:
    if hi - lo >= 180.0 - 1e-9:  # all directions: periodic over 180 deg
        n = max(1, int(math.ceil(180.0 / step)))
        return np.arange(n) * (180.0 / n)
    n = max(1, int(math.ceil((hi - lo) / step)))
    return np.unique(np.round(np.mod(np.linspace(lo, hi, n + 1), 180.0), 9))


def _speed_nodes(lo: float, hi: float, ratio: float) -> np.ndarray:
    n = max(1, int(math.ceil(math.log(hi / lo) / math.log(ratio))))
    return np.geomspace(lo, hi, n + 1)


# Node steps that meet the default 2 % tolerance on a Brownian surface (H = 0.5) with the default
# footprint (bench/bench_tables.py): interpolation error grows with the square of the step, so
# other tolerances start from steps scaled by sqrt(tolerance / 2 %).
PLAN_TOLERANCE = 0.02
PLAN_DIRECTION_STEP_DEG = 15.0
PLAN_SPEED_RATIO = 1.24


def initial_plan(scene: Scene, surface: Surface) -> NodePlan:
    """Starting nodes: explicit lists as given, else steps scaled from the 2 % plan (refined later)."""
    sigma = scene.footprint_sigma_mm
    spacing = scene.grid_spacing_mm or (sigma if sigma > 0 else 2 * surface.pixel_size_mm)
    spacing = max(spacing, surface.pixel_size_mm)
    scale = math.sqrt(scene.tolerance / PLAN_TOLERANCE)
    step = min(45.0, max(3.75, PLAN_DIRECTION_STEP_DEG * scale))
    ratio = min(2.0, max(1.04, math.exp(math.log(PLAN_SPEED_RATIO) * scale)))
    directions = (np.asarray(scene.directions_deg) if scene.directions_deg is not None
                  else _direction_nodes(*scene.direction_range_deg, step=step))
    speeds = (np.asarray(scene.speeds_mm_s) if scene.speeds_mm_s is not None
              else _speed_nodes(*scene.speed_range_mm_s, ratio=ratio))
    return NodePlan(directions, speeds, spacing, scene.directions_deg is not None,
                    scene.speeds_mm_s is not None, scene.grid_spacing_mm is not None)


def _as_player_tables(tables: Tables, frame_ms: float):
    from playback.asset import Tables as PlayerTables

    g = tables.grid
    return PlayerTables(a40=tables.a40, a320=tables.a320, direction_deg=tables.direction_deg,
                        speed_mm_s=tables.speed_mm_s, origin_mm=g.origin_mm, grid_basis_mm=g.basis_mm,
                        frame_ms=frame_ms, periodic=g.periodic)


def _threshold_scales(model: TwoColourModel) -> tuple[float, float]:
    """Factors that put (a40, a320) in threshold units: 1 / T_np(40), 1 / T_p(320)."""
    f40, f320 = model.base_frequencies_hz
    return 1.0 / float(model.thresholds.np_(f40)), 1.0 / float(model.thresholds.p(f320))


def _drawer(rng: np.random.Generator, values: np.ndarray, p: np.ndarray, uniform: bool) -> Callable[[], float]:
    """A function drawing one of `values`, with probabilities `p` or, if `uniform`, evenly."""
    if uniform:
        return lambda: float(values[rng.integers(values.size)])
    return lambda: float(values[rng.choice(values.size, p=p)])


def relative_errors(model: TwoColourModel, a40_t, a320_t, a40_r, a320_r) -> np.ndarray:
    """Relative error of table amplitudes against reference ones, in threshold units.

    Each colour is divided by its channel's threshold at its base frequency (T_np(40), T_p(320)),
    so the two colours count as felt; error = |difference| / |reference| of that 2-vector
    (with a floor of 1 % of the reference level over all samples, so silence does not divide by 0).
    """
    s40, s320 = _threshold_scales(model)
    diff = np.hypot((np.asarray(a40_t) - a40_r) * s40, (np.asarray(a320_t) - a320_r) * s320)
    ref = np.hypot(np.asarray(a40_r) * s40, np.asarray(a320_r) * s320)
    floor = 0.01 * float(np.sqrt(np.mean(ref**2))) + 1e-12
    return diff / np.maximum(ref, floor)


CheckPoint = tuple[str, np.ndarray, float, float]  # (family, position (u, v) mm, speed mm/s, direction deg)
CHECK_FAMILIES = ("direction", "speed", "position", "stroke")


def check_points(direction_deg: np.ndarray, speed_mm_s: np.ndarray, grid: TableGrid, seed: int = 0,
                 per_family: int = CHECK_SAMPLES_PER_FAMILY,
                 direction_range_deg: tuple[float, float] | None = None,
                 computed_speed_mm_s: np.ndarray | None = None) -> list[CheckPoint]:
    """The random points at which :func:`check_tables` measures tables with these nodes.

    They depend on the nodes only, not on the table values, so the reference amplitudes there
    can be computed while the tables are built (:func:`build_checked_tables`).

    Parameters
    ----------
    direction_deg, speed_mm_s : ndarray
        The tables' direction and (stored) speed nodes.
    grid : TableGrid
        The tables' node grid.
    seed, per_family, direction_range_deg
        As for :func:`check_tables`.
    computed_speed_mm_s : ndarray, optional
        The speed nodes that were computed, if the stored ones include cubic midpoints
        (:func:`~haptex_compile.tables.stored_speeds`); default: all stored speeds. Those
        midpoints are between nodes: the speed and stroke families draw them (beside the
        geometric midpoints between stored speeds), and the other families, which hold the
        speed at a node, do not. Drawn as nodes, their cubic error counted as the position's
        and the direction's: measured on a twill photo, the position family stayed at 2.2-2.9 %
        while its grid was halved twice, and fell to 0.8 % once the speeds were.

    Returns
    -------
    list of (family, position, speed, direction)
        ``per_family`` points of each family in :data:`CHECK_FAMILIES`, in that order.
    """
    rng = np.random.default_rng(seed)
    dirs, speeds = np.asarray(direction_deg, dtype=float), np.asarray(speed_mm_s, dtype=float)
    nj, ni = grid.shape

    def random_position() -> np.ndarray:
        fi, fj = rng.uniform(0, ni - 1), rng.uniform(0, nj - 1)
        return grid.origin_mm + fi * grid.basis_mm[0] + fj * grid.basis_mm[1]

    # Evenly spaced nodes draw uniformly (the same draws as before nodes could be uneven).
    mids, mid_p, node_dirs, node_p = direction_draws(dirs, direction_range_deg)
    even = bool(np.allclose(mid_p, mid_p[0]) and np.allclose(node_p, node_p[0]))
    node_direction = _drawer(rng, node_dirs, node_p, even)
    if dirs.size == 1:
        def mid_direction() -> float:
            return float(dirs[0] + rng.uniform(0, 180))
    else:
        mid_direction = _drawer(rng, mids, mid_p, even)
    computed = speeds if computed_speed_mm_s is None else np.asarray(computed_speed_mm_s, dtype=float)
    if speeds.size > 1:
        s_mids, s_mid_p, _, s_node_p = speed_draws(speeds)
        midpoints = ~np.isin(speeds, computed)
        if midpoints.any():  # the cubic midpoints too, each as often as a node there would be
            s_mids, s_mid_p = np.concatenate([s_mids, speeds[midpoints]]), np.concatenate([s_mid_p, s_node_p[midpoints]])
            s_mid_p = s_mid_p / s_mid_p.sum()
        c_node_p = speed_draws(computed)[3] if computed.size > 1 else np.ones(1)
        even_s = bool(np.allclose(s_mid_p, s_mid_p[0]) and np.allclose(c_node_p[1:-1], c_node_p[1])
                      and not midpoints.any())
        mid_speed, node_speed = _drawer(rng, s_mids, s_mid_p, even_s), _drawer(rng, computed, c_node_p, even_s)
    else:
        mid_speed, node_speed = (lambda: float(speeds[0])), _drawer(rng, speeds, np.ones(1), True)

    points: list[CheckPoint] = []
    for family in CHECK_FAMILIES:
        for _ in range(per_family):
            p = random_position()
            # "stroke": every axis between nodes at once, as a random stroke meets them.
            d = mid_direction() if family in ("direction", "stroke") else node_direction()
            s = mid_speed() if family in ("speed", "stroke") else node_speed()
            points.append((family, p, s, d))
    return points


def reference_amplitudes(surface: Surface, model: TwoColourModel, settings: AnalysisSettings,
                         point: CheckPoint) -> tuple[float, float]:
    """(a40, a320) of the reference renderer at one check point (a straight stroke through it)."""
    _, p, s, d = point
    ref = model.decompose(*point_intensities(surface, model, settings, straight_path(p[0], p[1], s, d), 0.0))
    return float(ref.a40), float(ref.a320)


def check_stats(model: TwoColourModel, settings: AnalysisSettings, tables: Tables, points: list[CheckPoint],
                references: list[tuple[float, float]], seed: int = 0, player: Any = None) -> dict[str, Any]:
    """The error statistics of :func:`check_tables` from its points and their reference amplitudes.

    `player` is the tables as the player reads them (:func:`_as_player_tables`), if already made.
    """
    player = _as_player_tables(tables, settings.frame_ms) if player is None else player
    families: dict[str, list[tuple[float, float, float, float]]] = {f: [] for f in CHECK_FAMILIES}
    for (family, p, s, d), (r40, r320) in zip(points, references, strict=True):
        a40, a320, _ = player.interpolator(np.array([p[0]]), np.array([p[1]]), np.array([s]), np.array([d]))
        families[family].append((float(a40[0]), float(a320[0]), r40, r320))
    stats: dict[str, Any] = {}
    all_rows = np.array([row for rows in families.values() for row in rows])
    errs = relative_errors(model, all_rows[:, 0], all_rows[:, 1], all_rows[:, 2], all_rows[:, 3])
    offset = 0
    for family, rows in families.items():
        e = errs[offset: offset + len(rows)]
        offset += len(rows)
        stats[f"rms_rel_error_{family}"] = float(np.sqrt(np.mean(e**2)))
    stats["rms_rel_error"] = float(np.sqrt(np.mean(errs**2)))
    stats["rms_rel_error_upper95"] = rms_upper_bound(errs, seed=seed)
    stats["max_rel_error"] = float(errs.max())
    stats["p95_rel_error"] = float(np.quantile(errs, 0.95))
    stats["n_check_samples"] = int(errs.size)
    return stats


def draw_seed(seed: int, draw: int) -> int:
    """The seed of a check's `draw`-th set of points (0: the first, `seed` itself)."""
    return seed + 1_000_003 * draw


def check_tables(surface: Surface, model: TwoColourModel, settings: AnalysisSettings, tables: Tables,
                 seed: int = 0, per_family: int = CHECK_SAMPLES_PER_FAMILY,
                 direction_range_deg: tuple[float, float] | None = None,
                 computed_speed_mm_s: np.ndarray | None = None, draws: int = 1) -> dict[str, Any]:
    """Measure table playback against the reference renderer at random points between nodes.

    Three families of samples isolate where the error comes from: directions halfway between
    nodes, speeds halfway (geometric mean) between nodes, and random positions at node
    directions and speeds; a fourth ("stroke") puts every axis between nodes at once. The union
    gives the stored statistics. Direction nodes need not be evenly spaced: an interval is
    drawn with a probability proportional to its width, and a node with half the width of its
    two intervals, as strokes in random directions meet them. `direction_range_deg` (the
    scene's range) keeps the intervals within a partial range; by default the nodes wrap
    around the half turn. `computed_speed_mm_s`: the speeds computed, when the stored ones
    include cubic midpoints (see :func:`check_points`). `draws` sets of points are pooled
    (seeds from :func:`draw_seed`). The steps are :func:`check_points`,
    :func:`reference_amplitudes` and :func:`check_stats`.
    """
    points = [p for k in range(draws)
              for p in check_points(tables.direction_deg, tables.speed_mm_s, tables.grid, draw_seed(seed, k), per_family,
                                    direction_range_deg, computed_speed_mm_s)]
    # The reference renderer's FFTs release the GIL: two threads use both cores.
    with ThreadPoolExecutor(max_workers=CHECK_WORKERS) as pool:
        references = list(pool.map(functools.partial(reference_amplitudes, surface, model, settings), points))
    return check_stats(model, settings, tables, points, references, seed=seed)


def rms_upper_bound(errors: np.ndarray, level: float = 0.95, seed: int = 0, n_boot: int = 2000) -> float:
    """One-sided upper confidence bound of the RMS of `errors` (studentized bootstrap).

    The stored RMS error comes from a few dozen random points; this says how large the RMS over
    all points between nodes could plausibly be. Coverage is close to `level` for near-Gaussian
    errors and lower for heavy-tailed ones, whose rare large errors a small sample misses
    (measured with 64 samples: 0.95 for half-normal, 0.86 for lognormal errors of sigma 0.8).
    """
    e2 = np.asarray(errors, dtype=float) ** 2
    n = e2.size
    mean, se = float(e2.mean()), float(e2.std(ddof=1)) / math.sqrt(n)
    rng = np.random.default_rng(seed)
    boot = e2[rng.integers(0, n, size=(n_boot, n))]
    t = (boot.mean(axis=1) - mean) / np.maximum(boot.std(axis=1, ddof=1) / math.sqrt(n), 1e-300)
    return float(math.sqrt(max(mean - float(np.quantile(t, 1.0 - level)) * se, mean)))


def _axis_shares(stats: dict[str, Any]) -> dict[str, float]:
    """Each axis's own share of the measured error: the direction and speed families are at
    random positions too, so the position family's error is taken out of theirs in quadrature."""
    pos = stats["rms_rel_error_position"]
    return {"position": pos,
            "direction": math.sqrt(max(stats["rms_rel_error_direction"] ** 2 - pos**2, 0.0)),
            "speed": math.sqrt(max(stats["rms_rel_error_speed"] ** 2 - pos**2, 0.0))}


AXIS_GROWTH = {"direction": 2, "speed": 2, "position": 4}  # table values per halving of each axis
PLAN_HALVINGS = 3  # halvings per axis that a plan looks ahead (8 x the nodes along directions or speeds)


def axes_to_refine(stats: dict[str, Any], tolerance: float, room: float = math.inf,
                   limits: dict[str, int] | None = None) -> list[str]:
    """Which node axes to halve this round, and how often, so that the predicted RMS error falls below the tolerance.

    Each axis's own share of the error comes from :func:`_axis_shares`. Halving a step
    divides linear-interpolation error by about 4 (by 3 here, to be safe). The halvings are
    planned to the end, not this round only: of the combinations of halvings per axis that fit
    in `room` (the factor by which the tables may still grow, ``AXIS_GROWTH`` per halving)
    and `limits` (the most halvings each axis has left; ``PLAN_HALVINGS`` by default), the
    one with the fewest table values whose predicted shares add up (in quadrature) to 85 % of
    the tolerance, or, when none does, the one of least predicted error. This round takes at
    most ``MAX_HALVINGS_PER_ROUND`` of each axis's halvings (the others wait for the next
    round's measurement), the axes with the largest shares first. Planning to the end keeps a
    small share from being halved now with table values that the largest share needs in a
    later round (measured on a slub weave photo: speed nodes doubled in the first round left no
    room for the directions it then lacked). A share below a quarter of the tolerance is not
    halved. An axis appears in the list once per halving.
    """
    share = _axis_shares(stats)
    axes = list(share)
    limits = {a: PLAN_HALVINGS for a in axes} if limits is None else limits
    budget = REFINE_BUDGET * tolerance

    def options(axis: str) -> list[int]:  # halvings worth taking: each on a share >= tolerance / 4
        n = 0
        while n < limits.get(axis, 0) and share[axis] / 3.0**n >= 0.25 * tolerance:
            n += 1
        return list(range(n + 1))

    best: tuple[bool, float, float, tuple[int, ...]] | None = None
    for counts in itertools.product(*(options(a) for a in axes)):
        growth = math.prod(AXIS_GROWTH[a] ** n for a, n in zip(axes, counts))
        if growth > room:
            continue
        error = math.sqrt(sum((share[a] / 3.0**n) ** 2 for a, n in zip(axes, counts)))
        # Fitting the budget first, then the fewest values; else the least error, then values.
        key = (error > budget, growth if error <= budget else error, error if error <= budget else growth, counts)
        if best is None or key < best:
            best = key
    planned = dict(zip(axes, best[3])) if best is not None else {}
    chosen = [a for a in sorted(axes, key=lambda a: -share[a])
              for _ in range(min(planned.get(a, 0), MAX_HALVINGS_PER_ROUND))]
    return chosen or [max(share, key=lambda a: share[a])]


def _axis_budget(stats: dict[str, Any], chosen: list[str], axis: str, tolerance: float) -> tuple[float, float]:
    """(measured share, target share) of one axis's error for adaptive refinement.

    The share is the axis's own (:func:`_axis_shares`); the target is what the planned budget leaves after the other axes'
    predicted shares (divided by 3 per halving chosen this round), at least a quarter of the
    tolerance.
    """
    shares = _axis_shares(stats)
    other2 = sum((v / 3.0 ** chosen.count(a)) ** 2 for a, v in shares.items() if a != axis)
    target = math.sqrt(max((REFINE_BUDGET * tolerance) ** 2 - other2, (0.25 * tolerance) ** 2))
    return shares[axis], target


def _colours(model: TwoColourModel, tables: Tables) -> np.ndarray:
    """The tables' colours in threshold units, [direction, colour, speed, j, i]."""
    s40, s320 = _threshold_scales(model)
    return np.stack([tables.a40 * s40, tables.a320 * s320], axis=1)


def _refined_directions(plan: NodePlan, scene: Scene, model: TwoColourModel, tables: Tables, stats: dict[str, Any],
                        chosen: list[str], max_nodes: int) -> np.ndarray:
    """More direction nodes: the intervals with the largest predicted error are split
    (:func:`~haptex_compile.node_refinement.split_directions`) until the direction error fits
    its budget (:func:`_axis_budget`)."""
    lo, hi = scene.direction_range_deg
    share, target = _axis_budget(stats, chosen, "direction", scene.tolerance)
    return split_directions(plan.directions_deg, _colours(model, tables), hi - lo >= 180.0 - 1e-9, lo, share, target,
                            max_nodes)


def _refined_speeds(plan: NodePlan, scene: Scene, model: TwoColourModel, tables: Tables, stats: dict[str, Any],
                    chosen: list[str], max_nodes: int) -> np.ndarray:
    """More speed nodes, as :func:`_refined_directions` does for directions, in log-speed.

    The curvature is read at the computed nodes (the stored cubic midpoints between them,
    :func:`~haptex_compile.tables.speed_midpoints_of`, are left out)."""
    speeds = np.asarray(plan.speeds_mm_s, dtype=float)
    share, target = _axis_budget(stats, chosen, "speed", scene.tolerance)
    computed = np.searchsorted(tables.speed_mm_s, speeds)
    colours = np.swapaxes(np.moveaxis(_colours(model, tables)[:, :, computed], 2, 0), 1, 2)  # [speed, colour, dir, j, i]
    return split_speeds(speeds, colours, share, target, max_nodes)


def _halvings_left(plan: NodePlan, grid: TableGrid, surface: Surface) -> dict[str, int]:
    """How often each node axis may still be halved: the limits of :func:`axes_to_refine`'s plan
    and of the refinement in :func:`build_checked_tables` alike. Explicit nodes none; directions up to
    ``MAX_DIRECTIONS`` and speeds up to 64 computed nodes (once more at least while below the
    limits that allow a halving); the grid while its spacing exceeds two pixels and its nodes
    stay within ``MAX_TABLE_NODES``."""
    n_dir, n_speed = plan.directions_deg.size, plan.speeds_mm_s.size
    left = {"direction": 0, "speed": 0, "position": 0}
    if not plan.explicit_directions and n_dir < MAX_DIRECTIONS // 2:
        left["direction"] = max(1, int(math.log2(MAX_DIRECTIONS / n_dir)))
    if not plan.explicit_speeds and n_speed < 64:
        left["speed"] = max(1, int(math.log2(64 / n_speed)))
    if not plan.explicit_spacing:
        spacing, nodes = grid.spacing_mm, grid.shape[0] * grid.shape[1]
        while spacing > 2 * surface.pixel_size_mm and 4 * nodes <= MAX_TABLE_NODES and left["position"] < PLAN_HALVINGS:
            spacing, nodes, left["position"] = spacing / 2, 4 * nodes, left["position"] + 1
    return left


# Pixels finer than this fraction of the finest felt wavelength are warned of (their cost).
FINE_PIXEL_FRACTION = 0.25


def fine_pixel_note(pixel_size_um: float, scene: Scene, model: TwoColourModel) -> str | None:
    """A note when pixels of `pixel_size_um` are far finer than the scene can make felt, else None.

    The finest wavelength a stroke can turn into felt vibration is the slowest speed over the
    band's top (10 mm/s / 800 Hz = 12.5 um by default); the tables sample lines a pixel apart,
    so their time grows as 1 / pixel² (a 64 px map of 0.5 um pixels took 142 s, of 0.1 um over
    300 s). Finer detail counts only where a stroke crosses it nearly side-on.
    """
    slowest = min(scene.speeds_mm_s) if scene.speeds_mm_s else scene.speed_range_mm_s[0]
    finest_um = 1000.0 * slowest / model.band.high_stop_hz
    if pixel_size_um >= FINE_PIXEL_FRACTION * finest_um:
        return None
    return (f"pixels of {pixel_size_um:g} um are {finest_um / pixel_size_um:.0f} x finer than the finest wavelength"
            f" the scene can make felt ({finest_um:.3g} um: {slowest:g} mm/s at {model.band.high_stop_hz:g} Hz); the"
            f" tables' time grows as 1 / pixel size squared: resampled to about {FINE_PIXEL_FRACTION * finest_um:.2g} um,"
            " the map would compile far faster for little that is felt")


def build_checked_tables(surface: Surface, model: TwoColourModel, settings: AnalysisSettings, scene: Scene,
                         seed: int = 0, progress: Callable[[str], None] | None = None) -> tuple[Tables, dict[str, Any], NodePlan]:
    """Build tables, measure their error and refine nodes until the scene's tolerance is met.

    Each round's check (:func:`check_tables`) draws its points from the nodes alone, so their
    reference amplitudes are queued on the same two threads right behind the round's
    directions and computed while the tables are assembled.
    """
    with ThreadPoolExecutor(max_workers=CHECK_WORKERS) as pool:
        try:
            return _build_checked_tables(surface, model, settings, scene, seed, progress, pool)
        except BaseException:
            # An error (a surface refused as out of scale, an interrupt) is not kept waiting
            # for the queued check frames: only those already running finish.
            pool.shutdown(wait=False, cancel_futures=True)
            raise


def _build_checked_tables(surface: Surface, model: TwoColourModel, settings: AnalysisSettings, scene: Scene,
                          seed: int, progress: Callable[[str], None] | None,
                          pool: ThreadPoolExecutor) -> tuple[Tables, dict[str, Any], NodePlan]:
    plan = initial_plan(scene, surface)
    tol = scene.tolerance
    history = []
    cache: dict = {}
    grid = table_grid(surface, plan.spacing_mm)
    reference = functools.partial(reference_amplitudes, surface, model, settings)
    for attempt in range(MAX_REFINEMENTS + 1):
        stored = stored_speeds(plan.speeds_mm_s, not plan.explicit_speeds)

        def draw_points(draw: int, stored: np.ndarray = stored, grid: TableGrid = grid) -> list[CheckPoint]:
            return check_points(plan.directions_deg, stored, grid, draw_seed(seed + attempt, draw),
                                direction_range_deg=scene.direction_range_deg, computed_speed_mm_s=plan.speeds_mm_s)

        points = draw_points(0)
        pending: list = []

        def queue_references(points: list[CheckPoint] = points, pending: list = pending) -> None:
            pending.extend(pool.submit(reference, p) for p in points)

        tables = build_tables(surface, model, settings, plan.directions_deg, plan.speeds_mm_s, grid, cache=cache,
                              speed_midpoints=not plan.explicit_speeds, pool=pool, after_submit=queue_references)
        assert np.array_equal(tables.speed_mm_s, stored), "check points drawn for other speed nodes"
        # The player's interpolator copies the whole tables: made here, while the references finish.
        player = _as_player_tables(tables, settings.frame_ms)
        player.interpolator
        references = [f.result() for f in pending]
        stats = check_stats(model, settings, tables, points, references, seed=seed + attempt, player=player)
        # A measured error within the tolerance whose upper bound is not: the check's few dozen
        # points may have missed the rare large errors (heavy-tailed: on plain-2000px's tables,
        # 5 % of each family's points carried 62-83 % of its squared error), so more are drawn and pooled
        # before the tables are taken (or refined, if the pooled error is above the tolerance).
        draws = 1
        while stats["rms_rel_error"] <= tol < stats["rms_rel_error_upper95"] and draws <= CHECK_EXTRA_DRAWS:
            more = draw_points(draws)
            points, references = points + more, references + list(pool.map(reference, more))
            stats = check_stats(model, settings, tables, points, references, seed=seed + attempt, player=player)
            draws += 1
        stats["check_draws"] = draws
        history.append({"directions": int(plan.directions_deg.size), "speeds": int(plan.speeds_mm_s.size),
                        "stored_speeds": int(tables.speed_mm_s.size),
                        "spacing_mm": float(grid.spacing_mm), "rms_rel_error": stats["rms_rel_error"],
                        "max_rel_error": stats["max_rel_error"], "n_check_samples": stats["n_check_samples"],
                        **{f"rms_rel_error_{k}": stats[f"rms_rel_error_{k}"] for k in ("direction", "speed", "position", "stroke")}})
        if progress:
            progress(f"tables {tables.a40.shape}: rms error {stats['rms_rel_error']:.3%}")
        if stats["rms_rel_error"] <= tol:
            break
        refined = False
        n_dir, n_speed, n_nodes = plan.directions_deg.size, tables.speed_mm_s.size, grid.shape[0] * grid.shape[1]
        limits = _halvings_left(plan, grid, surface)  # also what the loop below may still halve
        chosen = axes_to_refine(stats, tol, room=MAX_TABLE_VALUES / (n_dir * n_speed * n_nodes), limits=limits)
        # When no chosen axis can be refined (node limits, explicit nodes), try the others.
        fallback = [a for a in ("direction", "speed", "position") if a not in chosen]

        def fits(factor: int) -> bool:  # tables `factor` times larger stay under the value cap
            return factor * n_dir * n_speed * n_nodes <= MAX_TABLE_VALUES

        direction_done = speed_done = False
        for axis in chosen + fallback:
            if refined and axis in fallback:
                break
            if (axis == "direction" and direction_done) or (axis == "speed" and speed_done):
                continue  # all the halvings asked for are in one adaptive split
            if axis == "direction" and limits["direction"] and fits(2):
                direction_done = True
                # never more nodes than uniform halving would give
                uniform = n_dir * 2 ** max(1, chosen.count("direction"))  # once when only a fallback
                new_dirs = _refined_directions(plan, scene, model, tables, stats, chosen,
                                               max_nodes=min(uniform, MAX_DIRECTIONS, MAX_TABLE_VALUES // (n_speed * n_nodes)))
                if new_dirs.size > n_dir:
                    plan.directions_deg = new_dirs
                    n_dir = new_dirs.size
                    refined = True
            elif axis == "speed" and limits["speed"] and fits(2):
                speed_done = True  # as for directions: every halving asked for in one split
                n_computed = plan.speeds_mm_s.size
                uniform = (n_computed - 1) * 2 ** max(1, chosen.count("speed")) + 1
                plan.speeds_mm_s = _refined_speeds(plan, scene, model, tables, stats, chosen, max_nodes=uniform)
                n_speed = n_speed * (plan.speeds_mm_s.size - 1) // max(1, n_computed - 1)
                refined = True
            elif axis == "position" and limits["position"] and fits(4):
                limits["position"] -= 1  # (it may be asked for twice in a round)
                grid = halve_grid(grid)  # nested: the fast path has these nodes already
                plan.spacing_mm = grid.spacing_mm
                n_nodes = grid.shape[0] * grid.shape[1]
                refined = True
        if not refined:
            break
    stats["tolerance"] = tol
    stats["refinements"] = history
    stats["tolerance_met"] = bool(stats["rms_rel_error"] <= tol)
    return tables, stats, plan


def compile_source(spec: str, out_path: str | Path, scene: Scene, options: SourceOptions,
                   exr_path: str | Path | None = None, exr_speed: float = 80.0, exr_direction: float = 0.0,
                   progress: Callable[[str], None] | None = None) -> dict[str, Any]:
    """Compile one input into an asset at `out_path`; returns the compile report."""
    t0 = time.perf_counter()
    source = load_source(spec, options)
    LOG.info("%s: surface in %.1f s", spec, time.perf_counter() - t0)
    return compile_surface(source, out_path, scene, options.seed, exr_path, exr_speed, exr_direction, progress)


def compile_surface(source: SourceResult, out_path: str | Path, scene: Scene, seed: int = 0,
                    exr_path: str | Path | None = None, exr_speed: float = 80.0, exr_direction: float = 0.0,
                    progress: Callable[[str], None] | None = None) -> dict[str, Any]:
    model = model_for(scene)
    settings = settings_for(scene)
    pixel_mm = source.surface.pixel_size_mm
    note = fine_pixel_note(source.surface.pixel_size_um, scene, model)
    if note is not None:
        LOG.warning("%s: %s", source.name, note)
    if scene.grid_spacing_mm is not None and scene.grid_spacing_mm < pixel_mm:  # (initial_plan's floor)
        LOG.warning("%s: the scene's grid_spacing_mm %g is below the surface's pixel size: table nodes are one"
                    " pixel (%g mm) apart", source.name, scene.grid_spacing_mm, pixel_mm)
    t0 = time.perf_counter()
    tables, stats, plan = build_checked_tables(source.surface, model, settings, scene, seed=seed, progress=progress)
    t1 = time.perf_counter()
    report = dict(source.report)
    report["tables"] = {k: v for k, v in stats.items()}
    report["out_of_gamut_fraction"] = float(np.mean(tables.out_of_gamut > 0))
    report["out_of_gamut_max"] = float(tables.out_of_gamut.max())
    if not stats["tolerance_met"]:
        LOG.warning("%s: tables reach %.2f%% RMS error, above the tolerance %.2f%% (node limits reached)",
                    source.name, 100 * stats["rms_rel_error"], 100 * scene.tolerance)
    table_errors = {k: stats[k] for k in ("max_rel_error", "rms_rel_error", "rms_rel_error_upper95", "p95_rel_error", "n_check_samples",
                                           "rms_rel_error_direction", "rms_rel_error_speed", "rms_rel_error_position",
                                           "rms_rel_error_stroke")}
    table_errors["tolerance"] = scene.tolerance
    table_errors["error_metric"] = "|a_table - a_reference| / |a_reference|, colours in threshold units (T_np(40), T_p(320))"
    content = AssetContent(surface=source.surface, tables=tables, model=model, settings=settings, scene=scene,
                           source_name=Path(source.name).name if source.kind != "brownian" else source.name,
                           source_kind=source.kind, report=report, lattice=source.lattice,
                           roughness=source.roughness, friction=source.friction, table_errors=table_errors,
                           source_image=source.source_image)
    extra = []
    if exr_path is not None:  # written with the asset, both or neither
        extra.append((exr_path, exr_maps(source.surface, tables, exr_speed, exr_direction, settings.frame_ms,
                                         file_name=exr_path), new_file_mode()))
    write_asset(out_path, content, also=extra)
    # Only the log has the times: the asset stays byte-identical from run to run.
    LOG.info("%s: tables in %.1f s (%d checked samples), asset written in %.1f s", source.name, t1 - t0,
             stats["n_check_samples"], time.perf_counter() - t1)
    return report


def exr_maps(surface: Surface, tables: Tables, speed_mm_s: float, direction_deg: float, frame_ms: float,
             file_name: str | Path = "EXR") -> bytes:
    """An EXR (its bytes) of the height plus a40/a320 maps (for one speed and direction) on the
    height map's pixel grid."""
    from haptex_compile.io_exr import exr_image

    player = _as_player_tables(tables, frame_ms)
    ny, nx = surface.shape
    v, u = np.mgrid[0:ny, 0:nx] * surface.pixel_size_mm
    a40, a320, _ = player.interpolator(u.ravel(), v.ravel(), np.full(u.size, speed_mm_s), np.full(u.size, direction_deg))
    return exr_image({"height": np.asarray(surface.height_um, np.float32),
                      "a40": a40.reshape(ny, nx).astype(np.float32), "a320": a320.reshape(ny, nx).astype(np.float32)},
                     attributes={"haptex_speed_mm_s": f"{speed_mm_s:g}", "haptex_direction_deg": f"{direction_deg:g}",
                                 "haptex_units": "height, a40, a320 in micrometres"}, file_name=file_name)
