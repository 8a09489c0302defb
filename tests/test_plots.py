"""Plots of assets and playback records (haptex_compile.plots, haptex-inspect --plot)."""
from __future__ import annotations

import re
import shutil
import sys
from pathlib import Path

import h5py
import numpy as np
import pytest
from click.testing import CliRunner

pytest.importorskip("matplotlib")

from haptex_compile import plots  # noqa: E402
from playback.errors import HaptexError, InputError  # noqa: E402

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
SPEC = "brownian:H=0.5,size=128,pixel=20um,rms=5um"
UNIT = re.compile(r"\((µm|mm|Hz|mm/s|s|ms|µs)[^)]*\)")


@pytest.fixture(scope="module")
def asset_path(tmp_path_factory) -> Path:
    from haptex_compile.cli import main

    out = tmp_path_factory.mktemp("plots") / "b.tact.h5"
    result = CliRunner().invoke(main, [SPEC, "-o", str(out), "-q"])
    assert result.exit_code == 0, result.output
    return out


@pytest.fixture(scope="module")
def record_path(asset_path) -> Path:
    from playback.cli import main

    out = asset_path.with_name("rec.h5")
    result = CliRunner().invoke(main, [str(asset_path), "--device", "sim", "--sweep", "speed=80,direction=0,duration=0.5",
                                       "--fast", "--record", str(out), "-q"])
    assert result.exit_code == 0, result.output
    return out


@pytest.fixture(scope="module")
def asset_fig(asset_path):
    return plots.asset_figure(asset_path, speed_mm_s=80.0, direction_deg=30.0)


def _panels(fig):
    """Axes that are neither colour bars nor the text panel."""
    return [ax for ax in fig.axes if ax.get_label() != "<colorbar>" and ax.axison]


def _by_title(fig, words: str):
    hits = [ax for ax in fig.axes if words in ax.get_title()]
    assert len(hits) == 1, [ax.get_title() for ax in fig.axes]
    return hits[0]


def _line(ax, label: str):
    hits = [ln for ln in ax.get_lines() if ln.get_label() == label]
    assert len(hits) == 1, [ln.get_label() for ln in ax.get_lines()]
    return hits[0]


def _png_ok(path: Path, min_bytes: int = 40_000) -> None:
    data = path.read_bytes()
    assert data[:8] == PNG_SIGNATURE
    assert len(data) > min_bytes  # a figure with images and curves, not an empty canvas
    width, height = int.from_bytes(data[16:20], "big"), int.from_bytes(data[20:24], "big")
    assert width >= 800 and height >= 600


# ----------------------------------------------------------------------------- assets


def test_asset_png_through_the_cli(asset_path, tmp_path):
    from haptex_compile.inspect_cli import main

    out = tmp_path / "asset.png"
    result = CliRunner().invoke(main, [str(asset_path), "--plot", str(out), "--speed", "50", "--direction", "45"])
    assert result.exit_code == 0, result.output
    _png_ok(out)


def test_asset_figure_layout_and_units(asset_fig):
    # No source image (synthetic surface): height, thresholds, kernels, a40, a320, speed + text;
    # colour bars for height, a40 and a320.
    colourbars = [ax for ax in asset_fig.axes if ax.get_label() == "<colorbar>"]
    panels = _panels(asset_fig)
    assert len(panels) == 6 and len(colourbars) == 3 and len(asset_fig.axes) == 10
    for ax in panels:
        assert ax.get_title(), "every panel has a title"
        assert UNIT.search(ax.get_xlabel()), ax.get_xlabel()
        assert UNIT.search(ax.get_ylabel()), ax.get_ylabel()
    for cb in colourbars:
        assert "(µm" in cb.get_ylabel()


def test_kernels_panel_reproduces_pure_tones(asset_fig):
    # H40, H320 invert the 2 x 2 system: a pure 40 Hz tone gives (a40, a320) = (A, 0), 320 Hz gives (0, A).
    ax = _by_title(asset_fig, "two-colour kernels")
    for label, expected in (("H40(f)", (1.0, 0.0)), ("H320(f)", (0.0, 1.0))):
        f, h = _line(ax, label).get_data()
        at = np.interp(np.log([40.0, 320.0]), np.log(f), h)
        np.testing.assert_allclose(at, expected, atol=0.03)


def test_threshold_panel_shows_the_idealised_curves(asset_fig):
    # The default curves: Pacinian minimum -20 dB re 1 µm (0.1 µm) near 250 Hz; NP flat at
    # +8 dB (2.5 µm) below 40 Hz; and the ordering the two-colour system needs.
    ax = _by_title(asset_fig, "detection thresholds")
    f, tp = _line(ax, "T_p (Pacinian)").get_data()
    _, tnp = _line(ax, "T_np (non-Pacinian)").get_data()
    k = int(np.argmin(tp))
    assert 200.0 < f[k] < 320.0 and 0.07 < tp[k] < 0.14
    flat = (f > 8) & (f < 30)
    np.testing.assert_allclose(tnp[flat], 10 ** (8 / 20), rtol=0.1)
    lo, hi = np.interp(np.log([40.0, 320.0]), np.log(f), np.log(tp)), np.interp(np.log([40.0, 320.0]), np.log(f), np.log(tnp))
    assert hi[0] < lo[0] and lo[1] < hi[1]  # T_np(40) < T_p(40), T_p(320) < T_np(320)
    assert ax.get_xscale() == "log" and ax.get_yscale() == "log"


def test_amplitude_maps_hit_the_table_nodes(asset_path):
    # Sampling the map exactly on the table's nodes, at a node speed and direction, must return
    # the stored values (bilinear weights are 0/1 there), and the map must not depend on the
    # sense of motion (amplitude spectra are the same at d and d + 180).
    from playback.asset import read_asset

    t = read_asset(asset_path).tables
    basis = t.grid_basis_mm
    assert np.allclose(basis, np.diag(np.diag(basis))) and np.allclose(t.origin_mm, 0.0), "axis-aligned grid expected"
    nd, ns, nj, ni = t.shape
    assert ni == nj
    d, s = nd // 2, ns // 3
    u, v, a40, a320 = plots.amplitude_maps(t, (ni - 1) * basis[0, 0], (nj - 1) * basis[1, 1],
                                           t.speed_mm_s[s], t.direction_deg[d], n=ni)
    np.testing.assert_allclose(a40, t.a40[d, s], rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(a320, t.a320[d, s], rtol=1e-5, atol=1e-6)
    _, _, b40, b320 = plots.amplitude_maps(t, 2.0, 2.0, 77.0, 33.0, n=40)
    _, _, c40, c320 = plots.amplitude_maps(t, 2.0, 2.0, 77.0, 213.0, n=40)
    np.testing.assert_allclose(b40, c40, rtol=1e-6)
    np.testing.assert_allclose(b320, c320, rtol=1e-6)


def test_speed_panel_fades_to_rest(asset_fig, asset_path):
    # Below the lowest table speed s0 the amplitude falls linearly to 0 at rest: at s0/2 it is half.
    from playback.asset import read_asset

    s0 = float(read_asset(asset_path).tables.speed_mm_s[0])
    ax = _by_title(asset_fig, "amplitude against speed")
    s, a40 = _line(ax, "a40, 30°").get_data()
    assert s[0] == pytest.approx(s0 / 2)
    at_s0 = np.interp(np.log(s0), np.log(s), a40)
    assert a40[0] == pytest.approx(at_s0 / 2, rel=0.02)
    assert np.all(np.isfinite(a40)) and np.all(a40 >= 0)


def test_lattice_drawn_on_the_source_image(asset_path, tmp_path):
    # Give the asset a source image with a known oblique lattice; the arrows must be t1, t2 in mm
    # and every drawn cell must have the lattice's area |det[t1 t2]|.
    path = tmp_path / "lattice.tact.h5"
    shutil.copy(asset_path, path)
    t1, t2 = np.array([5.0, 2.0]), np.array([-1.5, 6.0])
    yy, xx = np.mgrid[0:128, 0:128].astype(float)
    recip = np.linalg.inv(np.column_stack([t1, t2]))  # rows: reciprocal vectors
    image = np.cos(2 * np.pi * (recip[0, 0] * xx + recip[0, 1] * yy)) + np.cos(2 * np.pi * (recip[1, 0] * xx + recip[1, 1] * yy))
    with h5py.File(path, "a") as f:
        f["surface"].create_dataset("source_image", data=image.astype(np.float32))
        g = f["surface"].create_group("lattice")
        g.attrs["t1_px"], g.attrs["t2_px"], g.attrs["confidence"] = t1, t2, 0.9
    fig = plots.asset_figure(path)
    assert len(_panels(fig)) == 7
    ax = _by_title(fig, "source image and lattice")
    pixel_mm = 0.02
    arrows = [a for a in ax.texts if hasattr(a, "xyann")]
    vectors = sorted((np.subtract(a.xy, a.xyann) for a in arrows), key=lambda d: d[0])
    np.testing.assert_allclose(vectors, sorted([t1 * pixel_mm, t2 * pixel_mm], key=lambda d: d[0]), atol=1e-9)
    cells = [ln.get_xydata() for ln in ax.get_lines() if len(ln.get_xydata()) == 5]
    assert len(cells) == plots.CELLS_SHOWN ** 2
    area = abs(np.linalg.det(np.column_stack([t1, t2]))) * pixel_mm ** 2
    for c in cells:
        x, y = c[:-1, 0], c[:-1, 1]
        assert 0.5 * abs(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1))) == pytest.approx(area, rel=1e-9)
    # The weave is fine (cells span < half the image): the panel zooms on them but keeps them all.
    x0, x1 = sorted(ax.get_xlim())
    y0, y1 = sorted(ax.get_ylim())
    pts = np.concatenate(cells)
    assert x1 - x0 < 128 * pixel_mm / 2
    assert np.all((pts[:, 0] >= x0) & (pts[:, 0] <= x1) & (pts[:, 1] >= y0) & (pts[:, 1] <= y1))
    assert ax.yaxis_inverted()  # v grows downwards as in the image


def test_lattice_cells_tile_the_plane():
    t1, t2, o = np.array([3.0, 0.5]), np.array([-2.0, 4.0]), np.array([10.0, 20.0])
    cells = plots.lattice_cells_px(t1, t2, o, n=3)
    assert cells.shape == (9, 5, 2)
    np.testing.assert_allclose(cells[:, 0], cells[:, -1])  # closed polygons
    centroids = cells[:, :4].mean(axis=1)
    # Centroids form the lattice itself, shifted by half a cell; the middle one is the origin's cell.
    np.testing.assert_allclose(centroids[4], o + (t1 + t2) / 2)
    coeff = np.linalg.solve(np.column_stack([t1, t2]), (centroids - o - (t1 + t2) / 2).T).T
    np.testing.assert_allclose(coeff, np.round(coeff), atol=1e-12)
    assert {tuple(c) for c in np.round(coeff).astype(int)} == {(i, j) for i in (-1, 0, 1) for j in (-1, 0, 1)}


def test_bad_parameters_and_files(asset_path, tmp_path):
    with pytest.raises(InputError, match="speed"):
        plots.asset_figure(asset_path, speed_mm_s=0.0)
    with pytest.raises(InputError, match="direction"):
        plots.asset_figure(asset_path, direction_deg=float("nan"))
    text = tmp_path / "notes.h5"
    text.write_text("not hdf5")
    with pytest.raises(InputError, match="not an HDF5 file") as err:
        plots.plot_file(text, tmp_path / "x.png")
    assert "\n" not in str(err.value) and str(text) in str(err.value)
    other = tmp_path / "other.h5"
    with h5py.File(other, "w") as f:
        f.attrs["format"] = "something-else"
    with pytest.raises(InputError, match="neither"):
        plots.plot_file(other, tmp_path / "x.png")
    from haptex_compile.inspect_cli import main

    result = CliRunner().invoke(main, [str(other), "--plot", str(tmp_path / "x.png")])
    assert result.exit_code == 1 and "neither" in result.output
    assert not (tmp_path / "x.png").exists()


def test_missing_matplotlib_gives_the_install_hint(asset_path, tmp_path, monkeypatch):
    for name in [m for m in sys.modules if m == "matplotlib" or m.startswith("matplotlib.")]:
        monkeypatch.delitem(sys.modules, name)
    monkeypatch.setitem(sys.modules, "matplotlib", None)  # import matplotlib -> ImportError
    with pytest.raises(HaptexError, match=r"pip install haptex\[plot\]"):
        plots.plot_file(asset_path, tmp_path / "x.png")


# ----------------------------------------------------------------------------- records


def test_record_png_and_layout(record_path, tmp_path):
    out = tmp_path / "rec.png"
    plots.plot_file(record_path, out)
    _png_ok(out)
    fig = plots.record_figure(record_path)
    panels = _panels(fig)
    assert len(panels) == 4 and len(fig.axes) == 6  # + contactor colour bars of the two timelines
    for ax in panels:
        assert UNIT.search(ax.get_xlabel()) or ax.get_ylabel() == "frames", ax.get_xlabel()
        assert ax.get_title()
    with h5py.File(record_path, "r") as f:
        n, c = f["frames/a40"].shape
        a320 = f["frames/a320"][()]
    ax = _by_title(fig, "a320 per contactor")
    lines = [ln for ln in ax.get_lines() if ln.get_label().startswith("_c")]
    assert len(lines) == c
    np.testing.assert_allclose(_line(ax, "mean over contactors").get_ydata(), a320.mean(axis=1), rtol=1e-6)
    np.testing.assert_allclose(np.column_stack([ln.get_ydata() for ln in lines]), a320)


def _synthetic_record(path: Path, n: int, late_at: list[int], skip_after: list[int]) -> None:
    from playback.record import Recorder

    rec = Recorder(path, n_contactors=3, n_channels=3, packet_size=4, attrs={"frame_ms": 25.0, "mode": "tables"})
    k = 0
    for i in range(n):
        rec.append(t_s=0.0125 + 0.025 * k, index=k, deadline_s=0.025 * k, sent_s=0.025 * k, render_us=100.0 + i,
                   latency_us=300.0, input_age_ms=0.0, gain=1.0, late=int(i in late_at), clamped=0, nonfinite=0,
                   sequence=i, a40=np.array([1.0, 2.0, 3.0]) * (1 + np.sin(i)), a320=np.full(3, 0.5),
                   flags=np.zeros(3, np.uint8), codes=np.zeros((2, 3), np.uint16), packet=np.zeros(4, np.uint8))
        k += 3 if i in skip_after else 1
    rec.close()


def test_record_marks_late_and_skipped_frames(tmp_path):
    path = tmp_path / "late.h5"
    late_at, skip_after = [3, 17, 18], [25]
    _synthetic_record(path, 40, late_at, skip_after)
    fig = plots.record_figure(path)
    ax = _by_title(fig, "a40 per contactor")
    spans = [p for p in ax.patches if p.get_facecolor()[0] > 0.9 and p.get_facecolor()[1] < 0.1]
    assert len(spans) == len(late_at)
    assert "(3)" in ax.get_title()
    skipped = [ln for ln in ax.get_lines() if ln.get_marker() == "x"]
    assert len(skipped) == 1 and len(skipped[0].get_xdata()) == len(skip_after)
    assert skipped[0].get_xdata()[0] == pytest.approx(0.0125 + 0.025 * 25)
    timing = _by_title(fig, "per-frame timing")
    assert len(_line(timing, "late frames").get_xdata()) == len(late_at)


def test_empty_record_is_a_picture_not_a_crash(tmp_path):
    path = tmp_path / "empty.h5"
    _synthetic_record(path, 0, [], [])
    out = tmp_path / "empty.png"
    plots.plot_file(path, out)
    assert out.read_bytes()[:8] == PNG_SIGNATURE
    fig = plots.record_figure(path)
    assert any("no frames" in t.get_text() for ax in fig.axes for t in ax.texts)


# ----------------------------------------------------------------------------- benchmark report

REPO = Path(__file__).resolve().parents[1]


def _bench_main():
    import importlib.util

    spec = importlib.util.spec_from_file_location("haptex_bench_main", REPO / "bench" / "__main__.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_markdown_tables_become_speed_error_plots():
    ru = _bench_main().ru
    md = "\n".join([
        "## Synthesis", "", "| H | method | bias | ms/surface | time / baseline |", "| --- | --- | ---: | ---: | --- |",
        "| 0.3 | midpoint (baseline) | +0.10 | 20.0 | 1.00 |", "| 0.3 | exact | -0.002 | 90.0 | 4.5 |",
        "| 0.7 | midpoint (baseline) | -0.15 | 25.0 | 1.00 |", "| 0.7 | exact | **-0.004** | 110.0 | 4.4 |", "",
        "| case | baseline err % | exact err % | baseline time (s) | exact time (s) |", "| --- | --- | --- | --- | --- |",
        "| a | 14 % | 0.1 % | 0.2 | 0.3 |", "| b | 30 % | 0.2 % | 0.25 | 0.5 |", "",
        "| step | time s | ratio |", "| --- | --- | --- |", "| decode | 0.1 | 1 |", "| fft | 0.2 | 2 |",
    ])
    specs = ru.plots_from_markdown(md)
    assert len(specs) == 2  # the third table has no error column
    first = {s["label"]: s for s in specs[0]["series"]}
    assert set(first) == {"midpoint (baseline)", "exact"} and first["midpoint (baseline)"]["baseline"]
    assert first["exact"]["x"] == [90.0, 110.0] and first["exact"]["y"] == [0.002, 0.004]  # |bias|, bold stripped
    assert specs[0]["x_label"] == "ms/surface"
    second = {s["label"]: (s["x"], s["y"]) for s in specs[1]["series"]}
    assert second == {"baseline err %": ([0.2, 0.25], [14.0, 30.0]), "exact err %": ([0.3, 0.5], [0.1, 0.2])}
    assert specs[1]["x_label"] == "time (s)" and specs[1]["y_label"] == "err %"
    tol = "| surface | tolerance | compile time | stored RMS error |\n| --- | --- | --- | --- |\n" + "\n".join(
        f"| {name} | {t} % | {c} s | {e} % |" for name, t, c, e in
        (("brownian", 5, 4.0, 4.1), ("brownian", 2, 9.0, 1.8), ("twill", 5, 5.0, 3.0), ("twill", 2, 12.0, 1.5)))
    (spec,) = ru.plots_from_markdown(tol)
    assert {s["label"]: (s["x"], s["y"]) for s in spec["series"]} == {
        "brownian": ([4.0, 9.0], [4.1, 1.8]), "twill": ([5.0, 12.0], [3.0, 1.5])}
    assert ru.demote_headings("# A\n```\n# code\n```\n### B", 3) == "### A\n```\n# code\n```\n##### B"


def test_bench_runner_reports_successes_failures_and_timeouts(tmp_path):
    bench = tmp_path / "b"
    bench.mkdir()
    (bench / "helper_values.py").write_text("VALUES = [3.0, 1.0]\n")
    (bench / "bench_good.py").write_text(
        '"""Good bench (issue 0)."""\nfrom helper_values import VALUES\nPLOT_DATA = []\n'
        "def run(quick=False):\n"
        "    PLOT_DATA.append({'title': 't', 'x_label': 'time (ms)', 'y_label': 'error (%)',\n"
        "                      'series': [{'label': 'baseline', 'x': [1, 2], 'y': VALUES, 'baseline': True}]})\n"
        "    return '## Good\\n\\n| a | b |\\n| --- | --- |\\n| 1 | 2 |\\n\\nbaseline in the same run, quick=' + str(quick)\n")
    (bench / "bench_bad.py").write_text('"""Bad bench."""\ndef run(quick=False):\n    raise RuntimeError("no data\\nsecond line")\n')
    (bench / "bench_slow.py").write_text('"""Slow bench."""\nimport time\ndef run(quick=False):\n    time.sleep(30)\n    return "late"\n')
    out = tmp_path / "rep" / "REPORT.md"
    # Plots left from earlier runs: the modules run now lose theirs, the others keep theirs (a
    # report rerun in part still shows them).
    (out.parent / "plots").mkdir(parents=True)
    (out.parent / "plots" / "bench_good_9.png").write_bytes(b"stale")
    (out.parent / "plots" / "bench_other_1.png").write_bytes(b"kept")
    assert _bench_main().main(["--quick", "--bench-dir", str(bench), "--out", str(out), "--timeout", "8"]) == 0
    assert not (out.parent / "plots" / "bench_good_9.png").exists()
    assert (out.parent / "plots" / "bench_other_1.png").read_bytes() == b"kept"
    text = out.read_text()
    assert "# haptex benchmark report" in text and "load average" in text and "numpy" in text
    assert "### Good" in text and "quick=True" in text  # headings demoted under the section
    assert "`RuntimeError: no data second line (at bench_bad.py:3)`" in text
    assert "timed out after 8 s" in text
    for name in ("perception", "tables", "lattice"):
        assert f"`bench/bench_{name}.py`" in text  # expected sections reported missing
    assert "![t](plots/bench_good_1.png)" in text
    assert (out.parent / "plots" / "bench_good_1.png").read_bytes()[:8] == PNG_SIGNATURE


def test_plot_with_an_unwritable_matplotlib_folder_prints_only_its_line(asset_path, tmp_path):
    """HOME read-only (as on some lab accounts): matplotlib's import printed two lines of its own
    on stderr ("mkdir -p failed ...", "Matplotlib created a temporary cache directory ...")."""
    import os
    import subprocess

    from asset_factory import tool_argv

    r = subprocess.run([*tool_argv("haptex-inspect"), str(asset_path), "--plot", str(tmp_path / "p.png")],
                       capture_output=True, text=True, timeout=120,
                       env={**os.environ, "MPLCONFIGDIR": str(asset_path / "below-a-file"),  # (under a file: cannot be made)
                            "PYTHONPATH": str(Path(__file__).resolve().parents[1])})
    assert r.returncode == 0 and r.stderr == "" and r.stdout.strip() == f"wrote {tmp_path / 'p.png'}", r.stderr
    _png_ok(tmp_path / "p.png")
