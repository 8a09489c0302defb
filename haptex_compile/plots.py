"""Pictures of tactile assets and playback records (``haptex-inspect FILE --plot out.png``).

An **asset** figure has, in reading order:

1. the source image with the lattice found in it (t1, t2 arrows and a few cells; the paper's
   Fig. 10), when the asset came from a photograph;
2. the height map (µm over u, v in mm; Fig. 11), with the repeat cell of a periodic surface;
3. the detection thresholds T_p, T_np the asset was compiled with (log-log, µm against Hz;
   Fig. 13), dashed where the band roll-off raises them;
4. the kernels H40, H320 (Fig. 14): a40 = sum H40(f) F(f), a320 = sum H320(f) F(f) for n = 1;
5. and 6. the a40 and a320 maps for one speed and direction, interpolated in the tables exactly
   as the player does (:func:`playback.interp.table_amplitudes`);
7. amplitude against speed at the centre of the surface;
8. a text panel with the numbers that matter (table size, measured error, provenance).

A **playback record** figure has per-contactor timelines of a40 and a320 with the late frames
marked, the render-time histogram and the latency per frame.

matplotlib is an optional extra (``pip install haptex[plot]``); it is imported only here, with
the Agg backend and without pyplot, so plotting never touches a display or global state.
"""
from __future__ import annotations

import json
import logging
import textwrap
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from playback.asset import FORMAT_NAME as ASSET_FORMAT
from playback.errors import AssetError, HaptexError, InputError, shown_text
from playback.record import RECORD_FORMAT

if TYPE_CHECKING:  # matplotlib is optional
    from matplotlib.axes import Axes
    from matplotlib.figure import Figure

MAP_SAMPLES = 160  # points per side of the a40/a320 maps (the tables are far coarser)
CELLS_SHOWN = 3  # lattice cells drawn per side on the source image
_MISSING_MPL = "matplotlib is needed for --plot: pip install haptex[plot]"


def _matplotlib() -> Any:
    """Import matplotlib (Agg) or raise the install hint.

    Its import's notices of a configuration folder it cannot write (HOME read-only, as on some
    lab accounts: two lines on stderr, "mkdir -p failed ..." and "Matplotlib created a temporary
    cache directory ...") are kept out of the tools' output: it falls back to a temporary
    folder, and the plot is made the same.
    """
    mpl_log = logging.getLogger("matplotlib")
    level = mpl_log.level
    mpl_log.setLevel(logging.ERROR)
    try:
        import matplotlib

        matplotlib.use("Agg", force=False)
        from matplotlib.figure import Figure  # noqa: F401  (checks the install is complete)
    except ImportError:
        raise HaptexError(_MISSING_MPL) from None
    finally:
        mpl_log.setLevel(level)
    return matplotlib


# --------------------------------------------------------------------------- pure helpers


def file_kind(path: str | Path) -> str:
    """'asset' or 'record', from the HDF5 root attribute ``format``.

    Raises
    ------
    InputError
        One line naming the file when it is missing, not HDF5, or neither kind.
    """
    import h5py

    from playback.asset import refuse_crashing

    path = Path(path)
    if not path.is_file():
        raise InputError(path, "no such file")
    if not h5py.is_hdf5(str(path)):
        raise InputError(path, "not an HDF5 file (expected a tactile asset or a playback record)")
    refuse_crashing(path)  # before this process opens it: a corrupt file may crash libhdf5
    with h5py.File(path, "r") as f:
        fmt = f.attrs.get("format", "")
    fmt = fmt.decode() if isinstance(fmt, bytes) else str(fmt)
    if fmt == ASSET_FORMAT:
        return "asset"
    if fmt == RECORD_FORMAT:
        return "record"
    raise InputError(path, f"format {shown_text(repr(fmt))} is neither {ASSET_FORMAT!r} nor {RECORD_FORMAT!r}")


def lattice_cells_px(t1_px: np.ndarray, t2_px: np.ndarray, origin_px: np.ndarray, n: int = CELLS_SHOWN) -> np.ndarray:
    """Corners of the n x n lattice cells around `origin_px`: array [n*n, 5, 2] of (x, y) px (closed).

    Cell (i, j) has corners ``origin + (i + a) t1 + (j + b) t2`` for a, b in {0, 1}; i and j run
    over ``range(-(n // 2), n - n // 2)`` so the origin's cell is in the middle.
    """
    t1 = np.asarray(t1_px, float)
    t2 = np.asarray(t2_px, float)
    o = np.asarray(origin_px, float)
    unit = np.array([[0, 0], [1, 0], [1, 1], [0, 1], [0, 0]], float)
    k = range(-(n // 2), n - n // 2)
    cells = [o + (i + unit[:, :1]) * t1 + (j + unit[:, 1:]) * t2 for j in k for i in k]
    return np.asarray(cells)


def amplitude_maps(tables: Any, width_mm: float, height_mm: float, speed_mm_s: float, direction_deg: float,
                   n: int = MAP_SAMPLES) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """a40 and a320 (µm) on an n x n grid over [0, width_mm] x [0, height_mm], as the player looks them up.

    Returns
    -------
    u_mm, v_mm : ndarray [n]
        Grid coordinates (u along columns, v along rows).
    a40_um, a320_um : ndarray [n, n]
        Amplitudes; row index follows v, column index follows u.
    """
    from playback.interp import table_amplitudes

    u = np.linspace(0.0, float(width_mm), n)
    v = np.linspace(0.0, float(height_mm), n)
    uu, vv = np.meshgrid(u, v)
    a40, a320, _ = table_amplitudes(tables, uu, vv, np.full(uu.shape, float(speed_mm_s)),
                                    np.full(uu.shape, float(direction_deg)))
    return u, v, a40, a320


def speed_curve(tables: Any, u_mm: float, v_mm: float, direction_deg: float, n: int = 200) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(speed_mm_s, a40_um, a320_um) at one point, from half the lowest to 1.5 x the highest table speed."""
    from playback.interp import table_amplitudes

    s = np.geomspace(0.5 * float(tables.speed_mm_s[0]), 1.5 * float(tables.speed_mm_s[-1]), n)
    a40, a320, _ = table_amplitudes(tables, np.full(n, float(u_mm)), np.full(n, float(v_mm)), s,
                                    np.full(n, float(direction_deg)))
    return s, a40, a320


def _image_extent(shape: tuple[int, int], pixel_mm: float) -> list[float]:
    """imshow extent so that sample (r, c) is centred on (u, v) = (c, r) * pixel_mm, v downwards."""
    ny, nx = shape
    return [-0.5 * pixel_mm, (nx - 0.5) * pixel_mm, (ny - 0.5) * pixel_mm, -0.5 * pixel_mm]


def _decode(value: Any) -> Any:
    return value.decode("utf-8", "replace") if isinstance(value, bytes) else value


# --------------------------------------------------------------------------- asset figure


def _read_asset_extras(path: Path) -> dict[str, Any]:
    """What the reader does not return: source image, lattice, kernels, report."""
    import h5py

    out: dict[str, Any] = {"source_image": None, "lattice": None, "kernels": None, "report": {}}
    with h5py.File(path, "r") as f:
        s = f["surface"]
        if "source_image" in s:
            out["source_image"] = np.asarray(s["source_image"][()], float)
        if "lattice" in s:
            la = s["lattice"].attrs
            out["lattice"] = {k: np.asarray(la[k], float) for k in ("t1_px", "t2_px") if k in la}
            out["lattice"]["confidence"] = float(la.get("confidence", np.nan))
        p = f["perception"]
        if all(k in p for k in ("kernel_frequency_hz", "kernel_h40", "kernel_h320")):
            out["kernels"] = tuple(np.asarray(p[k][()], float) for k in ("kernel_frequency_hz", "kernel_h40", "kernel_h320"))
        if "report" in f and "json" in f["report"].attrs:
            try:
                out["report"] = json.loads(_decode(f["report"].attrs["json"]))
            except ValueError:
                out["report"] = {}
    return out


def _panel_source(ax: "Axes", image: np.ndarray, lattice: dict[str, Any] | None, pixel_mm: float) -> None:
    ny, nx = image.shape
    ax.imshow(image, cmap="gray", extent=_image_extent(image.shape, pixel_mm), interpolation="nearest")
    ax.set_xlabel("u (mm)")
    ax.set_ylabel("v (mm)")
    if not lattice or "t1_px" not in lattice or not np.any(lattice["t1_px"]):
        ax.set_title("source image (no lattice found)")
        return
    t1, t2 = lattice["t1_px"], lattice["t2_px"]
    centre = np.array([(nx - 1) / 2.0, (ny - 1) / 2.0])
    for cell in lattice_cells_px(t1, t2, centre) * pixel_mm:
        ax.plot(cell[:, 0], cell[:, 1], color="yellow", lw=1.0)
    o = centre * pixel_mm
    for t, name, colour in ((t1, "t1", "red"), (t2, "t2", "deepskyblue")):
        d = np.asarray(t) * pixel_mm
        ax.annotate("", xy=o + d, xytext=o, arrowprops=dict(arrowstyle="-|>", color=colour, lw=2))
        ax.text(*(o + 1.1 * d), name, color=colour, fontsize=10, fontweight="bold", ha="center", va="center")
    # Fine weaves: zoom on the drawn cells, or they vanish in a 256-px image.
    corners = lattice_cells_px(t1, t2, centre).reshape(-1, 2)
    span = np.ptp(corners, axis=0)
    zoomed = bool(np.all(span < 0.5 * np.array([nx, ny])))
    if zoomed:
        lo = (corners.min(axis=0) - 0.25 * span) * pixel_mm
        hi = (corners.max(axis=0) + 0.25 * span) * pixel_mm
        ax.set_xlim(lo[0], hi[0])
        ax.set_ylim(hi[1], lo[1])  # v grows downwards
    conf = lattice.get("confidence", np.nan)
    ax.set_title("source image and lattice" + (" (zoom)" if zoomed else "")
                 + f"\nt1 = ({t1[0]:.2f}, {t1[1]:.2f}) px, t2 = ({t2[0]:.2f}, {t2[1]:.2f}) px, conf. {conf:.2f}",
                 fontsize=9)


def _panel_height(fig: "Figure", ax: "Axes", asset: Any) -> None:
    h = np.asarray(asset.height_um, float)
    pixel_mm = asset.pixel_size_um / 1000.0
    im = ax.imshow(h, cmap="viridis", extent=_image_extent(h.shape, pixel_mm), interpolation="nearest")
    fig.colorbar(im, ax=ax, label="height (µm)", shrink=0.85)
    ax.set_xlabel("u (mm)")
    ax.set_ylabel("v (mm)")
    title = f"height map, RMS {np.std(h):.3g} µm, {asset.pixel_size_um:g} µm/px"
    geo = asset.surface_geometry
    if asset.surface_periodic and geo:
        cell = lattice_cells_px(geo["period_t1_px"], geo["period_t2_px"], geo["cell_origin_px"], n=1)[0] * pixel_mm
        ax.plot(cell[:, 0], cell[:, 1], color="white", lw=1.2, ls="--")
        title += "\nperiodic; dashed: repeat cell"
    else:
        title += "\nnot periodic (mirrored beyond the edges)"
    ax.set_title(title, fontsize=9)


def _panel_thresholds(ax: "Axes", model: Any, node_f: np.ndarray) -> None:
    th = model.thresholds
    f = np.geomspace(5.0, 1000.0, 400)
    band = model.band.weight(f)
    with np.errstate(divide="ignore"):
        eff_p = np.where(band > 0, th.p(f) / band, np.inf)
        eff_np = np.where(band > 0, th.np_(f) / band, np.inf)
    ax.loglog(f, th.p(f), color="C0", label="T_p (Pacinian)")
    ax.loglog(f, th.np_(f), color="C1", label="T_np (non-Pacinian)")
    ax.loglog(f, eff_p, color="C0", ls=":", lw=1, label="T / band weight (as used)")
    ax.loglog(f, eff_np, color="C1", ls=":", lw=1)
    inside = (node_f >= f[0]) & (node_f <= f[-1])
    ax.loglog(node_f[inside], th.p(node_f[inside]), ".", color="C0", ms=3)
    ax.loglog(node_f[inside], th.np_(node_f[inside]), ".", color="C1", ms=3)
    lo, hi = model.base_frequencies_hz
    for fb in (lo, hi):
        ax.axvline(fb, color="grey", lw=0.8, ls="--")
        ax.text(fb, 0.98, f" {fb:g} Hz", transform=ax.get_xaxis_transform(), fontsize=8, va="top")
    finite = np.concatenate([th.p(f), th.np_(f)])
    ax.set_ylim(0.5 * finite.min(), 2.0 * finite.max())
    ax.set_xlabel("frequency (Hz)")
    ax.set_ylabel("threshold amplitude (µm, peak)")
    ax.set_title(f"detection thresholds used\nT_np({lo:g})/T_p({hi:g}) = {float(th.np_(lo) / th.p(hi)):.1f}", fontsize=9)
    ax.legend(fontsize=7, loc="lower left")
    ax.grid(True, which="both", alpha=0.3)


def _panel_kernels(ax: "Axes", kernels: tuple[np.ndarray, np.ndarray, np.ndarray], base: tuple[float, float]) -> None:
    f, h40, h320 = kernels
    ax.semilogx(f, h40, color="C2", label="H40(f)")
    ax.semilogx(f, h320, color="C3", label="H320(f)")
    ax.axhline(0.0, color="black", lw=0.6)
    for fb in base:
        ax.axvline(fb, color="grey", lw=0.8, ls="--")
    ax.set_xlabel("frequency (Hz)")
    ax.set_ylabel("kernel (µm of output per µm of input)")
    ax.set_title("two-colour kernels (n = 1)\na40 = Σ H40(f) F(f), a320 = Σ H320(f) F(f)", fontsize=9)
    ax.legend(fontsize=8)
    ax.grid(True, which="both", alpha=0.3)


def _panel_map(fig: "Figure", ax: "Axes", u: np.ndarray, v: np.ndarray, a: np.ndarray, name: str,
               speed: float, direction: float, cmap: str) -> None:
    du = u[1] - u[0] if u.size > 1 else 1.0
    dv = v[1] - v[0] if v.size > 1 else 1.0
    extent = [u[0] - du / 2, u[-1] + du / 2, v[-1] + dv / 2, v[0] - dv / 2]
    im = ax.imshow(a, cmap=cmap, extent=extent, interpolation="nearest", vmin=0.0)
    fig.colorbar(im, ax=ax, label=f"{name} (µm, peak)", shrink=0.85)
    # Direction of motion: CCW from +u towards +v, v drawn downwards.
    c = np.array([u.mean(), v.mean()])
    r = 0.2 * min(np.ptp(u), np.ptp(v)) or 0.1
    d = r * np.array([np.cos(np.radians(direction)), np.sin(np.radians(direction))])
    ax.annotate("", xy=c + d, xytext=c - d, arrowprops=dict(arrowstyle="-|>", color="white", lw=2))
    ax.set_xlabel("u (mm)")
    ax.set_ylabel("v (mm)")
    uniform = float(np.ptp(a)) <= 0.01 * float(a.max())
    note = "uniform: the footprint covers the repeat" if uniform else f"mean {a.mean():.3g} µm"
    ax.set_title(f"{name} at {speed:g} mm/s, {direction:g}° (arrow)\n{note}, max {a.max():.3g} µm", fontsize=9)


def _panel_speed(ax: "Axes", tables: Any, u_mm: float, v_mm: float, speed: float, direction: float) -> None:
    s, a40, a320 = speed_curve(tables, u_mm, v_mm, direction)
    s2, b40, b320 = speed_curve(tables, u_mm, v_mm, direction + 90.0)
    ax.semilogx(s, a40, color="C2", label=f"a40, {direction:g}°")
    ax.semilogx(s, a320, color="C3", label=f"a320, {direction:g}°")
    ax.semilogx(s2, b40, color="C2", ls="--", lw=1, label=f"a40, {direction + 90:g}°")
    ax.semilogx(s2, b320, color="C3", ls="--", lw=1, label=f"a320, {direction + 90:g}°")
    for node in tables.speed_mm_s:
        ax.axvline(node, color="grey", lw=0.3)
    ax.axvline(speed, color="black", lw=1, ls=":")
    ax.set_xlabel("speed (mm/s); grey: table nodes")
    ax.set_ylabel("amplitude (µm, peak)")
    ax.set_title(f"amplitude against speed at (u, v) = ({u_mm:.2f}, {v_mm:.2f}) mm", fontsize=9)
    ax.set_ylim(bottom=0.0)
    ax.legend(fontsize=7)
    ax.grid(True, which="both", alpha=0.3)


def _panel_text(ax: "Axes", asset: Any, extras: dict[str, Any]) -> None:
    t = asset.tables
    p = asset.perception
    lines = [
        f"source: {asset.source_kind}",
        f"surface {asset.surface_shape[1]} x {asset.surface_shape[0]} px at {asset.pixel_size_um:g} µm/px",
        f"tables {t.shape[0]} directions x {t.shape[1]} speeds x {t.shape[2]} x {t.shape[3]} nodes",
        f"  speeds {t.speed_mm_s[0]:g}-{t.speed_mm_s[-1]:g} mm/s, grid {t.grid_spacing_mm:.3g} mm",
        f"  error vs reference renderer: RMS {t.rms_rel_error:.2%} (tolerance on the RMS {t.tolerance:.2%}),",
        f"  max {t.max_rel_error:.2%}",
        f"footprint σ {float(p.get('footprint_sigma_mm', np.nan)):g} mm, summation n = {float(p.get('summation_exponent', np.nan)):g}",
        f"condition number {float(p.get('condition_number', np.nan)):.1f}",
        f"{asset.n_contactors} contactors",
    ]
    gamut = extras["report"].get("out_of_gamut_fraction")
    if gamut is not None:
        lines.append(f"out of gamut: {gamut:.1%} of table values")
    lines += textwrap.wrap("thresholds: " + str(_decode(p.get("threshold_provenance", "?"))), 52)
    ax.axis("off")
    ax.text(0.0, 1.0, "\n".join(lines), va="top", ha="left", fontsize=8, family="monospace", transform=ax.transAxes)
    ax.set_title("asset facts", fontsize=9)


def asset_figure(path: str | Path, *, speed_mm_s: float = 80.0, direction_deg: float = 0.0) -> "Figure":
    """Build the asset figure (see the module docstring) and return it (not saved).

    Parameters
    ----------
    path : str or Path
        A ``.tact.h5`` asset.
    speed_mm_s : float
        Speed of the a40/a320 maps (mm/s, > 0).
    direction_deg : float
        Direction of motion of the maps (degrees CCW from +u towards +v).
    """
    _matplotlib()
    from matplotlib.figure import Figure

    from haptex_compile.render import asset_model
    from playback.asset import read_asset

    if not (np.isfinite(speed_mm_s) and speed_mm_s > 0):
        raise InputError(None, f"speed must be finite and > 0 mm/s, got {speed_mm_s}")
    if not np.isfinite(direction_deg):
        raise InputError(None, f"direction must be finite, got {direction_deg}")
    path = Path(path)
    asset = read_asset(path, load_surface=True)
    extras = _read_asset_extras(path)
    _, model, _ = asset_model(asset)
    pixel_mm = asset.pixel_size_um / 1000.0
    ny, nx = asset.surface_shape
    width, height = (nx - 1) * pixel_mm, (ny - 1) * pixel_mm

    has_source = extras["source_image"] is not None and extras["source_image"].ndim == 2
    fig = Figure(figsize=(16, 13.5), layout="constrained")
    grid = fig.add_gridspec(3, 3)
    slots = iter([grid[r, c] for r in range(3) for c in range(3)])
    if has_source:
        _panel_source(fig.add_subplot(next(slots)), extras["source_image"], extras["lattice"], pixel_mm)
    _panel_height(fig, fig.add_subplot(next(slots)), asset)
    _panel_thresholds(fig.add_subplot(next(slots)), model, np.asarray(asset.perception["frequency_hz"], float))
    kernels = extras["kernels"]
    if kernels is None:  # older files: recompute from the stored curves
        kf = np.geomspace(1.0, 1000.0, 301)
        kernels = (kf, *model.kernels(kf))
    _panel_kernels(fig.add_subplot(next(slots)), kernels, model.base_frequencies_hz)
    u, v, a40, a320 = amplitude_maps(asset.tables, width, height, speed_mm_s, direction_deg)
    _panel_map(fig, fig.add_subplot(next(slots)), u, v, a40, "a40", speed_mm_s, direction_deg, "magma")
    _panel_map(fig, fig.add_subplot(next(slots)), u, v, a320, "a320", speed_mm_s, direction_deg, "magma")
    _panel_speed(fig.add_subplot(next(slots)), asset.tables, width / 2, height / 2, speed_mm_s, direction_deg)
    _panel_text(fig.add_subplot(next(slots)), asset, extras)
    fig.suptitle(shown_text(f"{path.name}: {asset.source_name}"), fontsize=12)
    return fig


# --------------------------------------------------------------------------- record figure


def _read_record(path: Path) -> dict[str, Any]:
    import h5py

    need = ("t_s", "a40", "a320", "late", "render_us")
    with h5py.File(path, "r") as f:
        if "frames" not in f:
            raise InputError(path, "missing group /frames (not a complete playback record)")
        fr = f["frames"]
        missing = [k for k in need if k not in fr]
        if missing:
            raise InputError(path, f"missing dataset(s) {', '.join('/frames/' + k for k in missing)}")
        out = {k: np.asarray(fr[k][()]) for k in fr if k not in ("packet", "codes")}
        out["attrs"] = {k: _decode(v) for k, v in f.attrs.items()}
    n = out["t_s"].shape[0]
    for k in ("a40", "a320"):
        if out[k].ndim != 2 or out[k].shape[0] != n:
            raise InputError(path, f"/frames/{k} must have shape [{n}, contactors], has {out[k].shape}")
    return out


def _timeline(fig: "Figure", ax: "Axes", t: np.ndarray, a: np.ndarray, late: np.ndarray, skipped_t: np.ndarray,
              frame_s: float, name: str) -> None:
    from matplotlib import colormaps
    from matplotlib.cm import ScalarMappable
    from matplotlib.colors import Normalize

    n_c = a.shape[1]
    cmap = colormaps["viridis"]
    norm = Normalize(0, max(n_c - 1, 1))
    # Steps: the device holds a frame's amplitudes for the whole frame.
    for i in range(n_c):
        ax.plot(t, a[:, i], color=cmap(norm(i)), lw=0.7, alpha=0.45, drawstyle="steps-mid", label=f"_c{i}")
    ax.plot(t, a.mean(axis=1), color="black", lw=2, drawstyle="steps-mid", label="mean over contactors")
    for tl in t[late]:
        ax.axvspan(tl - frame_s / 2, tl + frame_s / 2, color="red", alpha=0.2, lw=0)
    if skipped_t.size:
        ax.plot(skipped_t, np.zeros_like(skipped_t), "kx", ms=6, label="skipped frame(s) after this one")
    ax.legend(fontsize=7, loc="lower right")
    fig.colorbar(ScalarMappable(norm=norm, cmap=cmap), ax=ax, label="contactor index")
    ax.set_xlabel("trajectory time (s)")
    ax.set_ylabel(f"{name} (µm, peak, before calibration)")
    ax.set_title(f"{name} per contactor; red: late frames ({int(late.sum())})", fontsize=9)
    ax.set_ylim(bottom=0.0)
    ax.grid(True, alpha=0.3)


def record_figure(path: str | Path) -> "Figure":
    """Build the playback-record figure: a40/a320 timelines, render-time histogram, latency per frame."""
    _matplotlib()
    from matplotlib.figure import Figure

    path = Path(path)
    r = _read_record(path)
    attrs = r["attrs"]
    t = np.asarray(r["t_s"], float)
    late = np.asarray(r["late"], bool)
    frame_s = float(attrs.get("frame_ms", 25.0)) / 1000.0
    index = np.asarray(r.get("index", np.arange(t.size)))
    skipped_t = t[:-1][np.diff(index) > 1] if index.size > 1 else np.empty(0)
    fig = Figure(figsize=(14, 9), layout="constrained")
    axs = fig.subplots(2, 2)
    if t.size == 0:
        for ax in axs.ravel():
            ax.axis("off")
        axs[0, 0].text(0.0, 1.0, "the record holds no frames", va="top", transform=axs[0, 0].transAxes)
        fig.suptitle(shown_text(f"{path.name}: empty playback record"))
        return fig
    _timeline(fig, axs[0, 0], t, np.asarray(r["a40"], float), late, skipped_t, frame_s, "a40")
    _timeline(fig, axs[0, 1], t, np.asarray(r["a320"], float), late, skipped_t, frame_s, "a320")

    ax = axs[1, 0]
    render = np.asarray(r["render_us"], float)
    ax.hist(render, bins=min(50, max(5, t.size // 4)), color="C0")
    med, p99 = np.median(render), np.percentile(render, 99)
    ax.axvline(med, color="black", ls="--", lw=1, label=f"median {med:.0f} µs")
    ax.axvline(p99, color="red", ls=":", lw=1, label=f"99th percentile {p99:.0f} µs")
    ax.set_xlabel("render time per frame (µs)")
    ax.set_ylabel("frames")
    ax.set_title(f"render time ({t.size} frames; frame period {frame_s * 1000:g} ms)", fontsize=9)
    ax.legend(fontsize=8)

    ax = axs[1, 1]
    if "latency_us" in r:
        lat = np.asarray(r["latency_us"], float) / 1000.0
        ax.plot(t, lat, ".-", color="C0", lw=0.6, ms=3, label="latency (input to packet sent)")
        ax.plot(t[late], lat[late], "o", mfc="none", color="red", label="late frames")
    ax.plot(t, render / 1000.0, ".", color="C1", ms=3, label="render time")
    ax.axhline(frame_s * 1000.0, color="grey", ls="--", lw=1, label="frame period")
    ax.set_yscale("log")
    ax.set_xlabel("trajectory time (s)")
    ax.set_ylabel("time (ms)")
    ax.set_title("per-frame timing", fontsize=9)
    ax.legend(fontsize=7)
    ax.grid(True, which="both", alpha=0.3)

    n_late = int(late.sum())
    fig.suptitle(shown_text(f"{path.name}: playback of {Path(str(attrs.get('asset', '?'))).name}, mode {attrs.get('mode', '?')}, "
                            f"device {attrs.get('device', '?')}; {t.size} frames, {n_late} late, "
                            f"{int(attrs.get('frames_skipped', 0))} skipped"), fontsize=11)
    return fig


# --------------------------------------------------------------------------- entry point


def plot_file(path: str | Path, out_png: str | Path, *, speed_mm_s: float = 80.0, direction_deg: float = 0.0,
              dpi: int = 80) -> Path:
    """Write a PNG of an asset or a playback record (chosen by the file's ``format`` attribute).

    Parameters
    ----------
    path : str or Path
        A tactile asset (``.tact.h5``) or a playback record (``haptex-play --record``).
    out_png : str or Path
        The PNG to write.
    speed_mm_s, direction_deg : float
        Motion of the asset's a40/a320 maps (ignored for records).
    dpi : int
        Resolution (the asset figure is 16 x 13.5 inches).

    Returns
    -------
    Path
        `out_png`.

    Raises
    ------
    HaptexError
        matplotlib missing, or (as InputError/AssetError) an unreadable file, one line.
    """
    from playback.asset import corrupt_file_errors

    _matplotlib()
    if file_kind(path) == "asset":
        fig = asset_figure(path, speed_mm_s=speed_mm_s, direction_deg=direction_deg)
    else:
        with corrupt_file_errors(path, "playback record"):  # its reader trusts the file's layout
            fig = record_figure(path)
    out = Path(out_png)
    try:
        fig.savefig(out, dpi=dpi, format="png")
    except OSError as exc:
        raise InputError(out, f"cannot write the PNG ({exc.strerror or exc})") from None
    return out


__all__ = ["AssetError", "amplitude_maps", "asset_figure", "file_kind", "lattice_cells_px", "plot_file",
           "record_figure", "speed_curve"]
