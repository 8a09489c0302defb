"""The single reader of tactile assets (HDF5, format v1); shared by the player and the inspect tool.

Layout (written by ``haptex_compile.asset_writer``; schema in ``schemas/asset.schema.json``):
root attrs ``format``, ``format_version``, ``generator``, ``source_name``, ``source_kind``;
``/surface`` (height map, µm), ``/perception`` (thresholds), ``/tables`` (a40, a320 per
direction, speed and node) and ``/scene`` (contactor layout). Every problem with a file
becomes one :class:`~playback.errors.AssetError` line naming the file, never an h5py traceback.
"""
from __future__ import annotations

import contextlib
import faulthandler
import functools
import json
import math
import os
import signal
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterator

import h5py
import numpy as np

from playback.errors import AssetError, HaptexError, InputError, one_line, shown_text

FORMAT_NAME = "haptex-tactile-asset"
SUPPORTED_MAJOR = 1
# What h5py raises on truncated or corrupt files (a damaged B-tree, local heap or string type),
# which the reader and the compiler's validator turn into one line.
H5_READ_ERRORS = (OSError, KeyError, RuntimeError, TypeError, ValueError)


@contextlib.contextmanager
def corrupt_file_errors(path: str | Path, what: str, error: type[InputError] = InputError) -> Iterator[None]:
    """Turn what h5py and numpy raise on a corrupt or malformed HDF5 file (a damaged B-tree,
    a dataset of an absurd or inconsistent shape) while reading `what` from `path` into one
    `error` line naming the file. Our own one-line errors pass through."""
    try:
        yield
    except HaptexError:
        raise
    except (*H5_READ_ERRORS, IndexError, MemoryError) as exc:
        raise error(Path(path), f"cannot read {what} ({one_line(exc)})") from None


def read_everything(path: str | Path) -> None:
    """Open `path` and read every attribute and dataset in it (errors are left to the caller)."""
    def read(obj: h5py.HLObject) -> None:
        for name in obj.attrs:
            obj.attrs[name]
        if isinstance(obj, h5py.Dataset):
            obj[()]

    with h5py.File(path, "r") as f:
        read(f)
        f.visititems(lambda _name, obj: read(obj))


def crash_signal(path: str | Path) -> str | None:
    """The signal that killed a forked child reading the whole of HDF5 file `path`, or None.

    libhdf5 does not check everything it reads: some corrupt files crash it (seen: a damaged
    variable-length string attribute's heap gives SIGSEGV in 2 of 300 randomly corrupted
    assets) and the process dies with it, before any error can be reported. Reading the file
    first in a child makes that one line; the child's own errors are ignored (the caller's read
    reports them). None where the platform cannot fork: the read is then not checked.

    A tool probes a file before its own first read, and then calls :func:`read_asset`, which
    probes too: the answer is kept per file (its device, inode, size and modification time), so
    an unchanged file is read in a child once.
    """
    if not hasattr(os, "fork"):  # pragma: no cover - Windows
        return None
    try:
        st = os.stat(path)
    except OSError:  # missing or unreadable: the caller's own read says so
        return None
    return _probe(str(path), st.st_dev, st.st_ino, st.st_size, st.st_mtime_ns)


@functools.lru_cache(maxsize=64)
def _probe(path: str, *identity: int) -> str | None:
    """:func:`crash_signal` for the file `path` as it is (`identity`: its stat, the cache's key)."""
    pid = os.fork()
    if pid == 0:  # the child: read, then leave without running the parent's exit handlers
        code = 0
        try:
            os.dup2(os.open(os.devnull, os.O_WRONLY), 2)  # libhdf5's own messages
            faulthandler.disable()  # (pytest's, or PYTHONFAULTHANDLER's) the crash is expected
            read_everything(path)
        except BaseException:  # noqa: BLE001 - reported by the caller's own read
            code = 1
        finally:
            os._exit(code)
    _, status = os.waitpid(pid, 0)  # (interrupted waits are retried by Python itself)
    if os.WIFSIGNALED(status):
        number = os.WTERMSIG(status)
        try:
            return signal.Signals(number).name
        except ValueError:  # pragma: no cover
            return f"signal {number}"
    return None


def refuse_crashing(path: str | Path) -> None:
    """Raise :class:`AssetError` (one line) if reading HDF5 file `path` crashes libhdf5
    (:func:`crash_signal`); call it before anything in this process opens the file."""
    crash = crash_signal(path)
    if crash is not None:
        raise AssetError(Path(path), f"cannot read (the HDF5 library crashed reading it, {crash}: the file is corrupt)")


@dataclass(frozen=True, eq=False)
class Tables:
    """Amplitude lookup tables of one asset (µm, peak of the 40 Hz and 320 Hz sines).

    Node ``[d, s, j, i]`` holds the amplitudes of the 25 ms frame moving in direction
    ``direction_deg[d]`` at ``speed_mm_s[s]`` whose window is centred on
    ``origin_mm + i * grid_basis_mm[0] + j * grid_basis_mm[1]`` (u, v in mm).

    Construction validates everything and raises ``ValueError`` with one line.
    """

    a40: np.ndarray
    a320: np.ndarray
    direction_deg: np.ndarray
    speed_mm_s: np.ndarray
    origin_mm: np.ndarray
    grid_basis_mm: np.ndarray
    frame_ms: float = 25.0
    periodic: bool = False
    grid_spacing_mm: float = float("nan")
    max_rel_error: float = float("nan")
    rms_rel_error: float = float("nan")
    tolerance: float = float("nan")
    attrs: dict[str, Any] = field(default_factory=dict, repr=False)

    def __post_init__(self) -> None:
        a40 = np.ascontiguousarray(self.a40, dtype=np.float32)
        a320 = np.ascontiguousarray(self.a320, dtype=np.float32)
        if a40.ndim != 4:
            raise ValueError(f"a40 must have 4 dims [direction, speed, j, i], got shape {a40.shape}")
        if a320.shape != a40.shape:
            raise ValueError(f"a320 shape {a320.shape} differs from a40 shape {a40.shape}")
        if min(a40.shape) < 1:
            raise ValueError(f"tables are empty (shape {a40.shape})")
        for name, arr in (("a40", a40), ("a320", a320)):
            if not np.all(np.isfinite(arr)):
                raise ValueError(f"{name} contains NaN or infinite amplitudes")
            if np.any(arr < 0):
                raise ValueError(f"{name} contains negative amplitudes (min {float(arr.min()):.3g} µm)")
        nd, ns = a40.shape[:2]
        direction = np.asarray(self.direction_deg, dtype=np.float64).reshape(-1)
        speed = np.asarray(self.speed_mm_s, dtype=np.float64).reshape(-1)
        if direction.size != nd:
            raise ValueError(f"direction_deg has {direction.size} values, tables have {nd} directions")
        if speed.size != ns:
            raise ValueError(f"speed_mm_s has {speed.size} values, tables have {ns} speeds")
        if not np.all(np.isfinite(direction)) or np.any(direction < 0) or np.any(direction >= 180):
            raise ValueError("direction_deg must be finite and in [0, 180)")
        if np.any(np.diff(direction) <= 0):
            raise ValueError("direction_deg must be strictly ascending")
        if not np.all(np.isfinite(speed)) or np.any(speed <= 0):
            raise ValueError("speed_mm_s must be finite and > 0")
        if np.any(np.diff(speed) <= 0):
            raise ValueError("speed_mm_s must be strictly ascending")
        origin = np.asarray(self.origin_mm, dtype=np.float64).reshape(-1)
        basis = np.asarray(self.grid_basis_mm, dtype=np.float64)
        if origin.shape != (2,) or not np.all(np.isfinite(origin)):
            raise ValueError(f"origin_mm must be 2 finite numbers, got {origin.tolist()}")
        if basis.shape != (2, 2) or not np.all(np.isfinite(basis)):
            raise ValueError(f"grid_basis_mm must be a finite 2x2 array, got shape {basis.shape}")
        det = float(np.linalg.det(basis))
        scale = float(np.abs(basis).max())
        if scale == 0 or abs(det) <= 1e-9 * scale * scale:
            raise ValueError("grid_basis_mm is singular (g_i and g_j are parallel or zero)")
        frame_ms = float(self.frame_ms)
        if not math.isfinite(frame_ms) or frame_ms <= 0:
            raise ValueError(f"frame_ms must be finite and > 0, got {self.frame_ms}")
        for name, arr in (("a40", a40), ("a320", a320), ("direction_deg", direction),
                          ("speed_mm_s", speed), ("origin_mm", origin), ("grid_basis_mm", basis)):
            arr.setflags(write=False)
            object.__setattr__(self, name, arr)
        object.__setattr__(self, "frame_ms", frame_ms)
        object.__setattr__(self, "periodic", bool(self.periodic))
        for name in ("grid_spacing_mm", "max_rel_error", "rms_rel_error", "tolerance"):
            object.__setattr__(self, name, float(getattr(self, name)))

    @property
    def shape(self) -> tuple[int, int, int, int]:
        """(n_direction, n_speed, n_j, n_i)."""
        return tuple(self.a40.shape)  # type: ignore[return-value]

    @functools.cached_property
    def interpolator(self) -> Any:
        """The precomputed :class:`playback.interp.TableInterpolator` (built once, on first use)."""
        from playback.interp import TableInterpolator  # local: interp imports this module

        return TableInterpolator(self)


@dataclass(frozen=True, eq=False)
class Asset:
    """A tactile asset as read from disk.

    ``height_um`` and ``lattice`` are ``None`` unless the file was read with
    ``load_surface=True`` (``lattice`` also when the asset has none).
    """

    path: str
    format_version: str
    generator: str
    source_name: str
    source_kind: str
    tables: Tables
    contactors_mm: np.ndarray
    scene_text: str
    scene_resolved: dict[str, Any]
    perception: dict[str, Any]
    pixel_size_um: float
    surface_periodic: bool
    surface_shape: tuple[int, int]
    height_um: np.ndarray | None = None
    lattice: dict[str, Any] | None = None
    surface_geometry: dict[str, np.ndarray] | None = None  # periodic: period_t1_px, period_t2_px, cell_origin_px

    @property
    def n_contactors(self) -> int:
        """Number of contactors in the asset's scene."""
        return int(self.contactors_mm.shape[0])


def _attr(path: Path, obj: h5py.HLObject, name: str, where: str) -> Any:
    if name not in obj.attrs:
        raise AssetError(path, f"missing attribute {name!r} on {where}")
    value = obj.attrs[name]
    return value.decode("utf-8", "replace") if isinstance(value, bytes) else value


def _str_attr(path: Path, obj: h5py.HLObject, name: str, where: str) -> str:
    value = _attr(path, obj, name, where)
    if isinstance(value, np.ndarray) and value.shape == ():
        value = value[()]
    if isinstance(value, bytes):
        value = value.decode("utf-8", "replace")
    if not isinstance(value, str):
        raise AssetError(path, f"attribute {name!r} on {where} must be a string")
    return value


def _float_attr(path: Path, obj: h5py.HLObject, name: str, where: str, default: float | None = None) -> float:
    if default is not None and name not in obj.attrs:
        return default
    value = np.asarray(_attr(path, obj, name, where))
    if value.size != 1 or value.dtype.kind not in "biuf":
        raise AssetError(path, f"attribute {name!r} on {where} must be a number")
    return float(value.reshape(()))


def _dataset(path: Path, group: h5py.Group, name: str, ndim: int | None = None) -> np.ndarray:
    if name not in group or not isinstance(group[name], h5py.Dataset):
        raise AssetError(path, f"missing dataset {group.name.rstrip('/')}/{name}")
    data = group[name][()]
    arr = np.asarray(data)
    if arr.dtype.kind not in "biuf":
        raise AssetError(path, f"dataset {group.name.rstrip('/')}/{name} is not numeric")
    if ndim is not None and arr.ndim != ndim:
        raise AssetError(path, f"dataset {group.name.rstrip('/')}/{name} must have {ndim} dims, has shape {arr.shape}")
    return arr


def _group(path: Path, f: h5py.File, name: str) -> h5py.Group:
    if name not in f or not isinstance(f[name], h5py.Group):
        raise AssetError(path, f"missing group /{name} (not a complete tactile asset)")
    return f[name]


def _attrs_dict(obj: h5py.HLObject) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for key, value in obj.attrs.items():
        if isinstance(value, bytes):
            value = value.decode("utf-8", "replace")
        out[key] = value
    return out


def read_asset(path: str | Path, *, load_surface: bool = False) -> Asset:
    """Read a tactile asset (HDF5, format 1.x).

    Parameters
    ----------
    path : str or Path
        The ``.tact.h5`` file.
    load_surface : bool
        Also load the height map (µm) and the lattice; the player needs them only in
        ``--mode direct``.

    Returns
    -------
    Asset
        Validated, read-only arrays.

    Raises
    ------
    AssetError
        One line naming the file: not HDF5, wrong format or major version, missing or
        malformed data, non-finite or negative amplitudes, unordered speeds or directions.
    """
    path = Path(path)
    if not path.exists():
        raise AssetError(path, "no such file")
    if path.is_dir():
        raise AssetError(path, "is a directory, not a tactile asset")
    try:
        is_hdf5 = h5py.is_hdf5(str(path))
    except OSError as exc:  # unreadable (permissions)
        raise AssetError(path, f"cannot open ({exc.strerror or exc})") from None
    if not is_hdf5:
        raise AssetError(path, "not an HDF5 file (expected a haptex tactile asset, .tact.h5)")
    refuse_crashing(path)
    with corrupt_file_errors(path, "asset", AssetError):  # truncated or corrupt files
        with h5py.File(path, "r") as f:
            return _read_open(path, f, load_surface)


def _read_open(path: Path, f: h5py.File, load_surface: bool) -> Asset:
    fmt = f.attrs.get("format")
    if isinstance(fmt, bytes):
        fmt = fmt.decode("utf-8", "replace")
    if fmt != FORMAT_NAME:
        raise AssetError(path, f"not a haptex tactile asset (format attribute is {shown_text(repr(fmt))}, expected {FORMAT_NAME!r})")
    version = _str_attr(path, f, "format_version", "/")
    major_text = version.split(".")[0]
    if not major_text.isdigit() or int(major_text) != SUPPORTED_MAJOR:
        raise AssetError(path, f"format version {version} not supported (this reader reads {SUPPORTED_MAJOR}.x)")
    generator = _str_attr(path, f, "generator", "/")
    source_name = _str_attr(path, f, "source_name", "/")
    source_kind = _str_attr(path, f, "source_kind", "/")

    # /surface: metadata always, the height map only on request (it can be large).
    surface = _group(path, f, "surface")
    if "height" not in surface or not isinstance(surface["height"], h5py.Dataset):
        raise AssetError(path, "missing dataset /surface/height")
    hds = surface["height"]
    if hds.ndim != 2:
        raise AssetError(path, f"dataset /surface/height must have 2 dims, has shape {hds.shape}")
    pixel_size_um = _float_attr(path, surface, "pixel_size_um", "/surface")
    if not math.isfinite(pixel_size_um) or pixel_size_um <= 0:
        raise AssetError(path, f"/surface pixel_size_um must be finite and > 0, got {pixel_size_um}")
    surface_periodic = bool(_attr(path, surface, "periodic", "/surface"))
    geometry = None
    if surface_periodic:
        geometry = {}
        for name in ("period_t1_px", "period_t2_px", "cell_origin_px"):
            value = np.asarray(_attr(path, surface, name, "/surface"), dtype=np.float64).reshape(-1)
            if value.shape != (2,) or not np.all(np.isfinite(value)):
                raise AssetError(path, f"/surface {name} must be 2 finite numbers")
            geometry[name] = value
    height = None
    lattice = None
    if load_surface:
        height = np.asarray(hds[()], dtype=np.float32)
        if not np.all(np.isfinite(height)):
            raise AssetError(path, "/surface/height contains NaN or infinite heights")
        height.setflags(write=False)
        if "lattice" in surface:
            lat = surface["lattice"]
            lattice = {k: np.asarray(v) for k, v in _attrs_dict(lat).items()}

    perception_group = _group(path, f, "perception")
    perception: dict[str, Any] = dict(_attrs_dict(perception_group))
    for name in ("frequency_hz", "threshold_p_um", "threshold_np_um"):
        perception[name] = _dataset(path, perception_group, name, ndim=1)
    n_freq = perception["frequency_hz"].shape[0]
    if perception["threshold_p_um"].shape[0] != n_freq or perception["threshold_np_um"].shape[0] != n_freq:
        raise AssetError(path, "/perception thresholds and frequency_hz have different lengths")
    if "base_frequencies_hz" not in perception:
        raise AssetError(path, "missing attribute 'base_frequencies_hz' on /perception")

    tg = _group(path, f, "tables")
    a40 = _dataset(path, tg, "a40", ndim=4)
    a320 = _dataset(path, tg, "a320", ndim=4)
    direction = _dataset(path, tg, "direction_deg", ndim=1)
    speed = _dataset(path, tg, "speed_mm_s", ndim=1)
    extra = {k: v for k, v in _attrs_dict(tg).items()
             if k not in {"frame_ms", "periodic", "origin_mm", "grid_basis_mm", "grid_spacing_mm",
                          "max_rel_error", "rms_rel_error", "tolerance"}}
    try:
        tables = Tables(
            a40=a40, a320=a320, direction_deg=direction, speed_mm_s=speed,
            origin_mm=np.asarray(_attr(path, tg, "origin_mm", "/tables"), dtype=np.float64),
            grid_basis_mm=np.asarray(_attr(path, tg, "grid_basis_mm", "/tables"), dtype=np.float64),
            frame_ms=_float_attr(path, tg, "frame_ms", "/tables"),
            periodic=bool(_attr(path, tg, "periodic", "/tables")),
            grid_spacing_mm=_float_attr(path, tg, "grid_spacing_mm", "/tables", default=float("nan")),
            max_rel_error=_float_attr(path, tg, "max_rel_error", "/tables", default=float("nan")),
            rms_rel_error=_float_attr(path, tg, "rms_rel_error", "/tables", default=float("nan")),
            tolerance=_float_attr(path, tg, "tolerance", "/tables", default=float("nan")),
            attrs=extra,
        )
    except ValueError as exc:
        if isinstance(exc, AssetError):
            raise
        raise AssetError(path, f"/tables: {exc}") from None

    scene = _group(path, f, "scene")
    contactors = _dataset(path, scene, "contactors_mm", ndim=2).astype(np.float64)
    if contactors.shape[1] != 2 or contactors.shape[0] < 1:
        raise AssetError(path, f"/scene/contactors_mm must be [n_contactors, 2], has shape {contactors.shape}")
    if not np.all(np.isfinite(contactors)):
        raise AssetError(path, "/scene/contactors_mm contains NaN or infinite positions")
    contactors.setflags(write=False)
    scene_text = _str_attr(path, scene, "text", "/scene")
    resolved_text = _str_attr(path, scene, "resolved", "/scene")
    try:
        resolved = json.loads(resolved_text) if resolved_text else {}
    except json.JSONDecodeError as exc:
        raise AssetError(path, f"/scene resolved is not valid JSON ({exc.msg} at char {exc.pos})") from None

    return Asset(
        path=str(path), format_version=version, generator=generator, source_name=source_name,
        source_kind=source_kind, tables=tables, contactors_mm=contactors, scene_text=scene_text,
        scene_resolved=resolved, perception=perception, pixel_size_um=pixel_size_um,
        surface_periodic=surface_periodic, surface_shape=(int(hds.shape[0]), int(hds.shape[1])),
        height_um=height, lattice=lattice, surface_geometry=geometry,
    )
