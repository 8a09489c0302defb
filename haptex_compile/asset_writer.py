"""The single writer of tactile assets (HDF5, format v1).

Layout (public contract; ``schemas/asset.schema.json``; read by :mod:`playback.asset`):

* root attrs ``format = "haptex-tactile-asset"``, ``format_version = "1.0"``, ``generator``,
  ``source_name``, ``source_kind``;
* ``/surface/height`` float32 [ny, nx] µm; ``/surface`` attrs ``pixel_size_um``, ``periodic``
  and, when periodic, ``period_t1_px``, ``period_t2_px``, ``cell_origin_px`` (the repeat the
  sampler uses); ``/surface/lattice`` (only when a lattice was found in a photograph) attrs
  ``t1_px``, ``t2_px``, ``confidence``; optional ``/surface/roughness`` and ``/surface/friction``;
* ``/perception``: ``frequency_hz``, ``threshold_p_um``, ``threshold_np_um`` (the curves used,
  at their table nodes), ``kernel_frequency_hz``, ``kernel_h40``, ``kernel_h320``; attrs
  ``base_frequencies_hz``, ``summation_exponent``, ``footprint_sigma_mm``, band and analysis
  parameters, ``threshold_provenance``;
* ``/tables/a40``, ``/tables/a320`` float32 [n_direction, n_speed, n_j, n_i] µm, rounded to
  ``TABLE_MANTISSA_BITS`` significant bits (relative rounding at most 1.2e-4, far below any
  table tolerance) so that shuffle + gzip store them in about half the space;
  ``/tables/direction_deg``, ``/tables/speed_mm_s``; attrs ``frame_ms``, ``periodic``,
  ``origin_mm``, ``grid_basis_mm``, ``grid_spacing_mm``, error statistics (``rms_rel_error`` and its
  95 % upper bound ``rms_rel_error_upper95``, ``max_rel_error``, per-family RMS, ``tolerance``);
* ``/scene`` attrs ``text``, ``resolved`` (JSON); dataset ``contactors_mm`` [n, 2];
* ``/report`` attr ``json``: the compile report (warnings, decisions, measured errors).

Writes are atomic (temporary file in the same folder, then rename) and deterministic
(no timestamps: ``track_times=False``; fixed compression settings; table chunks are deflated on
two threads, while the rest is written, and written raw, see :func:`_table_dataset`).
"""
from __future__ import annotations

import itertools
import json
import zlib
from concurrent.futures import Executor, Future, ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import h5py
import numpy as np

from haptex_compile import __version__
from haptex_compile.colours import TwoColourModel
from haptex_compile.frame_analysis import ANALYSIS_RATE_HZ, AnalysisSettings
from haptex_compile.scene import Scene
from haptex_compile.surface import Surface
from haptex_compile.thresholds import SMOOTHING_HZ
from haptex_compile.tables import Tables
from playback.file_modes import new_file_mode
from playback.paths import check_replaceable, replace_files
from playback.text_files import utf8_text

FORMAT_NAME = "haptex-tactile-asset"
FORMAT_VERSION = "1.0"


@dataclass
class AssetContent:
    """Everything that goes into an asset."""

    surface: Surface
    tables: Tables
    model: TwoColourModel
    settings: AnalysisSettings
    scene: Scene
    source_name: str
    source_kind: str
    report: dict[str, Any] = field(default_factory=dict)
    lattice: dict[str, Any] | None = None  # t1_px, t2_px, confidence (photos)
    roughness: dict[str, Any] | None = None  # hurst, dimension, rms_um
    friction: dict[str, np.ndarray] | None = None
    table_errors: dict[str, float] = field(default_factory=dict)
    source_image: np.ndarray | None = None  # grey image the heights came from (for inspect)


TABLE_MANTISSA_BITS = 12


def round_mantissa(values: np.ndarray, bits: int = TABLE_MANTISSA_BITS) -> np.ndarray:
    """float32 values rounded to `bits` significant mantissa bits (round half up on the magnitude).

    The dropped low bits are zero, which the shuffle filter turns into long runs gzip compresses.
    Finite inputs only (tables are).
    """
    x = np.ascontiguousarray(values, dtype=np.float32)
    drop = 23 - bits
    raw = x.view(np.uint32)
    rounded = (raw + np.uint32(1 << (drop - 1))) & np.uint32(~((1 << drop) - 1) & 0xFFFFFFFF)
    return rounded.view(np.float32)


def _dataset(group: h5py.Group, name: str, data: np.ndarray, compress: bool = False) -> h5py.Dataset:
    data = np.ascontiguousarray(data)
    kwargs: dict[str, Any] = {"track_times": False}
    if compress and data.size > 1024:
        kwargs.update(compression="gzip", compression_opts=4, shuffle=True, chunks=True)
    return group.create_dataset(name, data=data, **kwargs)


TABLE_CHUNK_BYTES = 1 << 20
# gzip level of the tables: their rounded mantissas compress as well at level 1 as at 4 when a
# chunk holds whole node grids (measured on the cotton-poplin tables: 23.1 MB in 0.59 s
# against 24.9 MB in 0.76 s with level 4 and h5py's automatic chunks).
TABLE_GZIP_LEVEL = 1


def _table_dataset(group: h5py.Group, name: str, data: np.ndarray) -> h5py.Dataset:
    """A table as a shuffle + gzip dataset whose chunks are compressed on two threads.

    HDF5 runs its filters on one thread; zlib releases the GIL, so the chunks are shuffled and
    deflated here and written as they are (``write_direct_chunk``). Readers see an ordinary
    shuffle + gzip dataset. Edge chunks are padded with zeros, the fill value, as HDF5 does.
    """
    with ThreadPoolExecutor(max_workers=2) as pool:
        return _write_table(group, name, _deflated_table(data, pool))


DeflatedTable = tuple[tuple[int, ...], tuple[int, ...], list[tuple[tuple[int, ...], Future]]]  # shape, chunks, parts


def _deflated_table(data: np.ndarray, pool: Executor) -> DeflatedTable:
    """Start shuffling and deflating a table's chunks on `pool` (see :func:`_table_dataset`).

    Returns the table's shape, its chunk shape and each chunk's start with the future of its
    compressed bytes, for :func:`_write_table`.
    """
    data = np.ascontiguousarray(data, dtype=np.float32)
    chunks = _table_chunks(data.shape)
    starts = list(itertools.product(*(range(0, n, c) for n, c in zip(data.shape, chunks))))

    def deflate(start: tuple[int, ...]) -> bytes:
        src = tuple(slice(o, min(o + c, n)) for o, c, n in zip(start, chunks, data.shape))
        if all(s.stop - s.start == c for s, c in zip(src, chunks)):
            block = data[src]  # whole chunk: read in place
        else:
            block = np.zeros(chunks, data.dtype)
            block[tuple(slice(0, s.stop - s.start) for s in src)] = data[src]
        shuffled = np.ascontiguousarray(block).view(np.uint8).reshape(-1, data.itemsize).T  # byte planes, as HDF5's shuffle filter
        return zlib.compress(np.ascontiguousarray(shuffled), TABLE_GZIP_LEVEL)

    return data.shape, chunks, [(start, pool.submit(deflate, start)) for start in starts]


def _write_table(group: h5py.Group, name: str, table: DeflatedTable) -> h5py.Dataset:
    """The dataset of a table from :func:`_deflated_table`, its chunks written as they are ready."""
    shape, chunks, parts = table
    dset = group.create_dataset(name, shape=shape, dtype=np.float32, chunks=chunks, compression="gzip",
                                compression_opts=TABLE_GZIP_LEVEL, shuffle=True, track_times=False)
    for start, payload in parts:
        dset.id.write_direct_chunk(start, payload.result())
    return dset


def _table_chunks(shape: tuple[int, ...]) -> tuple[int, ...]:
    """Chunks of whole node grids (for one direction, as many speeds as fit in about 1 MiB)."""
    nd, ns, nj, ni = shape
    grid_bytes = 4 * nj * ni
    if grid_bytes <= TABLE_CHUNK_BYTES:
        return (1, max(1, min(ns, TABLE_CHUNK_BYTES // grid_bytes)), nj, ni)
    return (1, 1, max(1, min(nj, TABLE_CHUNK_BYTES // (4 * ni))), ni)


def write_asset(path: str | Path, content: AssetContent, also: list[tuple] = ()) -> None:
    """Write `content` to `path` atomically (temp file + rename); an error leaves no file.

    The HDF5 file is built in memory and written out in one piece
    (:func:`playback.paths.replace_files`): a full disk is then one ``OSError``, where libhdf5
    writing into it crashed the process. `also`: more ``(path, bytes, mode)`` files written
    with it, all or none (the asset's EXR); their folders are made as the asset's is.
    """
    for out in [path, *(entry[0] for entry in also)]:
        check_replaceable(out)
        Path(out).parent.mkdir(parents=True, exist_ok=True)
    replace_files([(Path(path), hdf5_image(lambda f: _fill(f, content)), new_file_mode()), *also])


def hdf5_image(fill: Callable[[h5py.File], None]) -> bytes:
    """The bytes of a new HDF5 file that `fill` writes, built in memory (the core driver
    without a backing store)."""
    with h5py.File(f"haptex-asset-{id(fill)}", "w", driver="core", backing_store=False, track_order=False) as f:
        fill(f)
        f.flush()
        return f.id.get_file_image()


def _fill(f: h5py.File, c: AssetContent) -> None:
    # The tables' chunks (most of the work) are deflated on two threads while the rest is written.
    with ThreadPoolExecutor(max_workers=2) as pool:
        tables = {name: _deflated_table(round_mantissa(getattr(c.tables, name)), pool)
                  for name in ("a40", "a320", "out_of_gamut")}
        _fill_groups(f, c, tables)


def _fill_groups(f: h5py.File, c: AssetContent, tables: dict[str, DeflatedTable]) -> None:
    f.attrs["format"] = FORMAT_NAME
    f.attrs["format_version"] = FORMAT_VERSION
    f.attrs["generator"] = f"haptex {__version__}"
    f.attrs["source_name"] = utf8_text(c.source_name)
    f.attrs["source_kind"] = c.source_kind

    s = f.create_group("surface", track_order=False)
    _dataset(s, "height", np.asarray(c.surface.height_um, dtype=np.float32), compress=True)
    s.attrs["pixel_size_um"] = float(c.surface.pixel_size_um)
    s.attrs["periodic"] = bool(c.surface.periodic)
    if c.surface.periodic:
        s.attrs["period_t1_px"] = np.asarray(c.surface.t1_px, dtype=np.float64)
        s.attrs["period_t2_px"] = np.asarray(c.surface.t2_px, dtype=np.float64)
        s.attrs["cell_origin_px"] = c.surface.origin_px().astype(np.float64)
    if c.lattice is not None:
        g = s.create_group("lattice")
        for key, value in c.lattice.items():
            g.attrs[key] = value
    if c.roughness is not None:
        g = s.create_group("roughness")
        for key, value in c.roughness.items():
            g.attrs[key] = value
    if c.friction is not None:
        g = s.create_group("friction")
        for key, value in c.friction.items():
            _dataset(g, key, np.asarray(value, dtype=np.float32), compress=True)
    if c.source_image is not None:
        _dataset(s, "source_image", np.asarray(c.source_image, dtype=np.float32), compress=True)

    p = f.create_group("perception")
    th = c.model.thresholds
    _dataset(p, "frequency_hz", np.asarray(th.frequency_hz, dtype=np.float64))
    _dataset(p, "threshold_p_um", np.asarray(th.p_um, dtype=np.float64))
    _dataset(p, "threshold_np_um", np.asarray(th.np_um, dtype=np.float64))
    kf = np.geomspace(1.0, 1000.0, 301)
    h40, h320 = c.model.kernels(kf)
    _dataset(p, "kernel_frequency_hz", kf)
    _dataset(p, "kernel_h40", h40)
    _dataset(p, "kernel_h320", h320)
    p.attrs["threshold_provenance"] = utf8_text(th.provenance)
    p.attrs["threshold_smoothing_hz"] = SMOOTHING_HZ
    p.attrs["base_frequencies_hz"] = np.asarray(c.model.base_frequencies_hz, dtype=np.float64)
    p.attrs["summation_exponent"] = float(c.model.summation_exponent)
    p.attrs["band_low_hz"] = c.model.band.low_hz
    p.attrs["band_high_pass_hz"] = c.model.band.high_pass_hz
    p.attrs["band_high_stop_hz"] = c.model.band.high_stop_hz
    p.attrs["footprint_sigma_mm"] = float(c.settings.footprint_sigma_mm)
    p.attrs["frame_ms"] = float(c.settings.frame_ms)
    p.attrs["margin_ms"] = float(c.settings.margin_ms)
    p.attrs["analysis_rate_hz"] = ANALYSIS_RATE_HZ
    p.attrs["condition_number"] = c.model.condition_number()

    t = f.create_group("tables")
    tab = c.tables
    _write_table(t, "a40", tables["a40"])
    _write_table(t, "a320", tables["a320"])
    _dataset(t, "direction_deg", np.asarray(tab.direction_deg, dtype=np.float64))
    _dataset(t, "speed_mm_s", np.asarray(tab.speed_mm_s, dtype=np.float64))
    _write_table(t, "out_of_gamut", tables["out_of_gamut"])
    t.attrs["frame_ms"] = float(c.settings.frame_ms)
    t.attrs["periodic"] = bool(tab.grid.periodic)
    t.attrs["origin_mm"] = np.asarray(tab.grid.origin_mm, dtype=np.float64)
    t.attrs["grid_basis_mm"] = np.asarray(tab.grid.basis_mm, dtype=np.float64)
    t.attrs["grid_spacing_mm"] = float(tab.grid.spacing_mm)
    t.attrs["interpolation"] = (
        "direction: linear, periodic over 180 deg; speed: linear in log(speed), clamped above the top node, "
        "fading linearly to 0 at speed 0 below the lowest; space: bilinear in the node grid, wrapping when periodic, "
        "clamped at the edge otherwise (docs/interpolation.md)"
    )
    for key, value in sorted(c.table_errors.items()):
        t.attrs[key] = value

    sc = f.create_group("scene")
    sc.attrs["text"] = c.scene.text
    sc.attrs["resolved"] = c.scene.resolved_json()
    _dataset(sc, "contactors_mm", np.asarray(c.scene.contactors_mm, dtype=np.float64))

    r = f.create_group("report")
    r.attrs["json"] = json.dumps(c.report, sort_keys=True, default=_jsonable)


def _jsonable(value: Any) -> Any:
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, (np.floating, np.integer, np.bool_)):
        return value.item()
    raise TypeError(f"not JSON-serialisable: {type(value).__name__}")
