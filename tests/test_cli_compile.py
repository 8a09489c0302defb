"""haptex-compile / haptex-inspect / haptex-play as a Makefile would use them."""
from __future__ import annotations

import importlib
import json
import os
import subprocess
from pathlib import Path

import h5py
import numpy as np
import pytest
from asset_factory import TINY_SCENE as SCENE
from asset_factory import TINY_SPEC as SPEC
from asset_factory import TOOL_MODULES, tool_argv


def run(tool: str, *args: str, cwd: Path | None = None) -> subprocess.CompletedProcess:
    return subprocess.run([*tool_argv(tool), *args], capture_output=True, text=True, cwd=cwd, timeout=600)


def run_compile_limited(tmp_path: Path, *args: str, limit: int = 4 * 2 ** 30) -> tuple[int, str, int]:
    """haptex-compile `args` in a child under an address-space `limit` (a regression then fails
    here, its threads filling the limit, rather than taking the machine): (exit status, its
    stderr, the child's own peak RSS in KiB)."""
    import os
    import resource

    err = tmp_path / "stderr.txt"
    with open(err, "w") as stderr:
        child = subprocess.Popen([*tool_argv("haptex-compile"), *args], stdout=subprocess.DEVNULL, stderr=stderr,
                                 preexec_fn=lambda: resource.setrlimit(resource.RLIMIT_AS, (limit, limit)))
        _, status, usage = os.wait4(child.pid, 0)
    return os.waitstatus_to_exitcode(status), err.read_text(), usage.ru_maxrss


@pytest.fixture(scope="module")
def scene_file(tmp_path_factory) -> Path:
    p = tmp_path_factory.mktemp("scene") / "small.toml"
    p.write_text(SCENE)
    return p


@pytest.fixture(scope="module")
def asset(tmp_path_factory, scene_file) -> Path:
    out = tmp_path_factory.mktemp("asset") / "b.tact.h5"
    r = run("haptex-compile", SPEC, "-o", str(out), "--scene", str(scene_file))
    assert r.returncode == 0, r.stderr
    return out


def test_asset_gets_the_permissions_of_a_plainly_created_file(asset, tmp_path):
    # Written through a temporary file (mkstemp makes it 0600): the rename must not keep that.
    probe = tmp_path / "probe"
    probe.touch()
    assert (asset.stat().st_mode & 0o777) == (probe.stat().st_mode & 0o777)


def test_photo_with_kes_takes_its_height_scale_from_smd(tmp_path, scene_file):
    """``haptex-compile fabric.png --kes fabric.kes.json``: geometry from the photo, scale from SMD.

    One factor scales the recovered relief (the photo fixes the warp/weft anisotropy), so the
    simulated KES measurement of the stored heights must return the geometric mean of the
    given SMDs. (The small scene: the tables do not enter the scale.)
    """
    import cv2

    from haptex_compile.kes import simulate_kes_smd
    from haptex_compile.shading import Light, render_lambertian
    from haptex_compile.synth_images import weave_image

    photo = tmp_path / "weave.png"
    relief_um = 12.0 * weave_image((192, 192), (16.0, 0.0), (0.0, 12.0), kind="plain")
    shading = render_lambertian(relief_um, 20.0, Light(40.0, 200.0), 0.8)
    cv2.imwrite(str(photo), np.round(255 * np.clip(shading, 0.0, 1.0)).astype(np.uint8))
    kes = Path(__file__).resolve().parents[1] / "samples" / "kes" / "cotton_poplin.kes.json"
    out = tmp_path / "weave.tact.h5"
    r = run("haptex-compile", str(photo), "-o", str(out), "--pixel-size", "20um", "--kes", str(kes), "-q",
            "--scene", str(scene_file))
    assert r.returncode == 0, r.stderr
    with h5py.File(out) as f:
        height = f["surface/height"][()].astype(float)
        report = f["report"].attrs["json"]
    assert "cotton poplin" in str(report)
    warp, weft = (simulate_kes_smd(height, 20.0, d, periodic=False) for d in ("warp", "weft"))
    assert np.sqrt(warp * weft) == pytest.approx(np.sqrt(3.2 * 4.1), rel=0.05)
    # The photo is exactly periodic: its averaged tile explains (nearly) all of it, and inspect says so.
    import re

    from haptex_compile.inspect_cli import summary

    lines = summary(str(out)).splitlines()
    line = next(x for x in lines if x.lstrip().startswith("tile"))
    assert float(re.search(r"explains ([0-9.]+)% of the photo's variance", line).group(1)) > 95.0
    # No --light: inspect names the estimated light the report holds, and its warnings.
    shading = json.loads(report)["shading"]
    line = next(x for x in lines if x.lstrip().startswith("shading"))
    assert f"light slant {shading['light_slant_deg']:.1f} deg, tilt {shading['light_tilt_deg']:.1f} deg (estimated on" in line
    assert [x.split("warning    ", 1)[1] for x in lines if x.lstrip().startswith("warning")][:len(shading["warnings"])] == shading["warnings"]
    assert shading["warnings"][0].startswith("light estimated")


def test_inspect_puts_the_tolerance_beside_the_rms_it_bounds(asset):
    # The tables' tolerance bounds the RMS error (and its 95 % bound), not the max: inspect
    # used to print it after the max, which read as the max's tolerance.
    import re

    from haptex_compile.inspect_cli import summary

    line = next(x for x in summary(str(asset)).splitlines() if "measured error" in x)
    assert re.search(r"RMS [0-9.]+% \((95 % bound [0-9.]+%; )?tolerance on the RMS [0-9.]+%\), max [0-9.]+%, [0-9]+ samples$",
                     line), line


def test_compile_writes_a_valid_asset(asset):
    from haptex_compile.asset_validate import validate_asset
    from playback.asset import read_asset

    assert validate_asset(asset) == []
    a = read_asset(asset, load_surface=True)
    assert a.tables.shape[:2] == (2, 2)
    assert a.n_contactors == 4
    assert a.height_um.shape == (64, 64)
    # The surface is what the spec asked for: RMS 5 µm (exact normalisation of the generator).
    assert float(np.std(a.height_um)) == pytest.approx(5.0, rel=1e-3)


def _corrupted(data: bytes, seed: int, folder: Path) -> Path:
    """`data` with 1-40 random bytes overwritten (seeded), as ``corrupt<seed>.tact.h5`` in `folder`."""
    import random

    rng = random.Random(seed)
    corrupt = bytearray(data)
    for _ in range(rng.randint(1, 40)):
        corrupt[rng.randrange(len(corrupt))] = rng.randrange(256)
    path = folder / f"corrupt{seed}.tact.h5"
    path.write_bytes(corrupt)
    return path


def test_corrupt_assets_are_invalid_in_one_line_each(tmp_path):
    # Random bytes overwritten in an asset: h5py raises TypeError or RuntimeError on some
    # (a damaged string type, B-tree or local heap), which the validator let through as a
    # traceback (seeds 5, 16 and 35 of these; the reader already caught them).
    from asset_factory import write_test_asset

    from haptex_compile.asset_validate import validate_asset

    data = write_test_asset(tmp_path / "good.tact.h5").read_bytes()
    unreadable = 0
    for seed in range(40):
        path = _corrupted(data, seed, tmp_path)
        problems = validate_asset(path)
        assert all(p.startswith(str(path)) and "\n" not in p for p in problems)
        unreadable += any("cannot read (" in p for p in problems)
    assert unreadable >= 3


def test_assets_that_crash_libhdf5_are_one_line_each(tmp_path):
    # Seeds 126 and 299 of the corruption above (of 300 tried) damage a variable-length string
    # attribute's heap, and libhdf5 crashed (SIGSEGV) reading it: the validator, the summary
    # and the plot died with the process, no line said why. Each tool now reads the file first
    # in a forked child (playback.asset.crash_signal) and refuses it in one line, exit 1.
    from asset_factory import write_test_asset

    data = write_test_asset(tmp_path / "good.tact.h5").read_bytes()
    for seed in (126, 299):
        path = _corrupted(data, seed, tmp_path)
        for args in (["--validate", str(path)], [str(path)], ["--plot", str(tmp_path / "p.png"), str(path)]):
            r = run("haptex-inspect", *args)
            assert r.returncode == 1, (seed, args, r.returncode, r.stderr[-500:])
            assert r.stderr.count("\n") == 1 and str(path) in r.stderr, (seed, args, r.stderr)
        assert not (tmp_path / "p.png").exists()


def test_a_corrupt_exr_is_one_line_and_nothing_on_stdout(tmp_path):
    # An EXR height map cut short in its last chunk (seed 1 of a fuzz of 150 damaged files;
    # 38 alike): the OpenEXR library printed "Warning: Exception raised reading pixel data ..."
    # on stdout and its own error line on stderr before ours. They are kept out of both
    # (logged at -vv).
    from haptex_compile.io_exr import write_exr

    good = tmp_path / "good.exr"
    write_exr(good, {"height": np.random.default_rng(0).standard_normal((48, 64)).astype(np.float32)})
    data = good.read_bytes()
    bad = tmp_path / "bad.exr"
    bad.write_bytes(data[:len(data) - 134])
    out = tmp_path / "bad.tact.h5"
    r = run("haptex-compile", str(bad), "-o", str(out), "--pixel-size", "20um")
    assert r.returncode == 1
    assert r.stdout == ""
    assert r.stderr.count("\n") == 1 and str(bad) in r.stderr and "EXR" in r.stderr, r.stderr
    assert not out.exists()


def test_outputs_never_overwrite_inputs_or_each_other(tmp_path, scene_file):
    # `-o h.npy` on the input h.npy replaced the height map with the asset, and two inputs of
    # one name (a.npy, sub/a.npy) to --out-dir wrote one asset over the other. Refused before
    # any work, in one line (exit 2); nothing written, the inputs intact.
    height = tmp_path / "h.npy"
    np.save(height, np.random.default_rng(0).standard_normal((64, 64)))
    (tmp_path / "sub").mkdir()
    twin = tmp_path / "sub" / "h.npy"
    twin.write_bytes(height.read_bytes())
    before = height.read_bytes(), scene_file.read_bytes()
    cases = [["-o", str(height)], ["-o", str(tmp_path / "h.tact.h5"), "--md", str(scene_file)],
             ["-o", str(tmp_path / "h.tact.h5"), "--exr", str(tmp_path / "h.tact.h5")]]
    for extra in cases:
        r = run("haptex-compile", str(height), "--pixel-size", "20um", "--scene", str(scene_file), *extra)
        assert r.returncode == 2 and r.stderr.count("\n") == 1, (extra, r.stderr)
    r = run("haptex-compile", str(height), str(twin), "--out-dir", str(tmp_path / "out"), "--pixel-size", "20um",
            "--scene", str(scene_file))
    assert r.returncode == 2 and "both write" in r.stderr and r.stderr.count("\n") == 1, r.stderr
    assert (height.read_bytes(), scene_file.read_bytes()) == before
    assert not (tmp_path / "h.tact.h5").exists() and not (tmp_path / "out").exists()


def test_outputs_never_replace_a_device_pipe_or_socket(tmp_path, scene_file):
    # Outputs go to a temporary file renamed over their name: as root, `-o /dev/null` (or
    # --md, --exr) replaced the system's /dev/null with a regular file. A FIFO stands in for the
    # device here: refused in one line (exit 2), still a FIFO.
    import stat

    fifo = tmp_path / "pipe"
    os.mkfifo(fifo)
    out = tmp_path / "x.tact.h5"
    for extra in (["-o", str(fifo)], ["-o", str(out), "--md", str(fifo)], ["-o", str(out), "--exr", str(fifo)]):
        r = run("haptex-compile", SPEC, "--scene", str(scene_file), *extra)
        assert r.returncode == 2 and r.stderr.count("\n") == 1 and "pipe" in r.stderr, (extra, r.stderr)
        assert stat.S_ISFIFO(os.lstat(fifo).st_mode)
    assert not out.exists()


def test_empty_paths_are_usage_errors(tmp_path, scene_file):
    # `-o ''` counted as no output and ended in a TypeError traceback; `--exr ''` named the
    # current directory. Every path option refuses an empty one (playback.cli_common.PathParam).
    for extra in (["-o", ""], ["-o", str(tmp_path / "x.tact.h5"), "--exr", ""], ["--out-dir", ""]):
        r = run("haptex-compile", SPEC, "--scene", str(scene_file), *extra)
        assert r.returncode == 2 and r.stderr.count("\n") == 1 and "empty path" in r.stderr, (extra, r.stderr)
    assert not list(tmp_path.glob("*.tact.h5"))


def test_an_output_under_a_file_is_refused_before_the_work(tmp_path, scene_file):
    # `-o a.txt/x.tact.h5` (a file where a folder should be) failed only when the asset was
    # written, after the tables, with "[Errno 17] File exists: 'a.txt'".
    blocker = tmp_path / "a.txt"
    blocker.write_text("a file")
    for extra in (["-o", str(blocker / "x.tact.h5")], ["-o", str(tmp_path / "x.tact.h5"), "--md", str(blocker / "x.d")]):
        r = run("haptex-compile", SPEC, "--scene", str(scene_file), *extra)
        assert r.returncode == 2 and r.stderr.count("\n") == 1 and "is a file, not a folder" in r.stderr, r.stderr
    assert not (tmp_path / "x.tact.h5").exists()


def test_exr_and_md_go_into_new_folders_as_the_asset_does(tmp_path, scene_file):
    # -o made the asset's missing folders; --exr and --md failed after the work ("the output
    # directory does not exist", "No such file or directory").
    out, exr, md = tmp_path / "a" / "x.tact.h5", tmp_path / "b" / "c" / "x.exr", tmp_path / "d" / "x.d"
    r = run("haptex-compile", SPEC, "--scene", str(scene_file), "-o", str(out), "--exr", str(exr), "--md", str(md))
    assert r.returncode == 0, r.stderr
    assert out.is_file() and exr.is_file() and md.read_text().startswith(f"{out}:")


def test_output_is_byte_identical(tmp_path, scene_file, asset):
    again = tmp_path / "again.tact.h5"
    r = run("haptex-compile", SPEC, "-o", str(again), "--scene", str(scene_file))
    assert r.returncode == 0, r.stderr
    assert again.read_bytes() == asset.read_bytes()


def test_bad_input_is_one_line_exit_1_and_no_output(tmp_path):
    bad = tmp_path / "bad.npy"
    np.save(bad, np.array([[np.nan] * 16] * 16))
    out = tmp_path / "out.tact.h5"
    out.write_bytes(b"older output")
    r = run("haptex-compile", str(bad), "-o", str(out), "--pixel-size", "10um")
    assert r.returncode == 1
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and "bad.npy" in lines[0] and "Traceback" not in r.stderr
    assert out.read_bytes() == b"older output"  # an older file survives
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bad.npy", "out.tact.h5"]  # no temp left


def test_a_map_of_implausibly_fine_pixels_is_one_line_and_small(tmp_path):
    # A 16 px map at 0.001 um pixels: the tables refuse its lines (11.7 GiB), and the check
    # frames queued beside them are refused too, or cancelled, instead of sampling strokes of
    # 6e7 pixels (killed at 24 GB). Run under a 4 GiB address-space limit, so that a
    # regression fails here (its threads fill the limit) rather than taking the machine.
    npy = tmp_path / "fine.npy"
    np.save(npy, np.random.default_rng(0).normal(size=(16, 16)))
    out = tmp_path / "fine.tact.h5"
    status, stderr, peak_kib = run_compile_limited(tmp_path, str(npy), "-o", str(out), "--pixel-size", "0.001um", "-q")
    assert status == 1, stderr
    (line,) = stderr.strip().splitlines()
    assert "fine.npy: the surface (16 x 16 px of 0.001 um" in line and "is out of scale" in line
    assert not out.exists()
    assert peak_kib < 2 ** 20  # under 1 GiB


@pytest.mark.parametrize("pixel, status, fragment", [
    ("1e-20um", 1, "coarse.npy: the surface (38 x 36 px of 1e-20 um"), ("1e20um", 2, "is above 1 m: check its unit"),
    ("1e308um", 2, "is above 1 m: check its unit")])
def test_absurd_pixel_sizes_are_one_line(tmp_path, pixel, status, fragment):
    # The tables' lines were sized by scipy's next_fast_len before their size was checked, and
    # at 1e-20 um it raised OverflowError (a traceback), as its footprint grids did at 1e20 um;
    # at 1e300 um and more numpy's and float32's overflow warnings joined the error on stderr.
    # Pixels above 1 m are now refused as options; finer ones by the tables' size checks.
    npy = tmp_path / "coarse.npy"
    np.save(npy, np.random.default_rng(0).normal(size=(36, 38)))
    out = tmp_path / "coarse.tact.h5"
    # (-q: 1e-20 um pixels are also warned of as far finer than can be felt; numpy's raw
    # warnings, which -q does not silence, would still show)
    r = run("haptex-compile", str(npy), "-o", str(out), "--pixel-size", pixel, "-q")
    assert r.returncode == status, r.stderr
    (line,) = r.stderr.strip().splitlines()
    assert fragment in line
    assert not out.exists()


def test_a_scene_with_a_pinpoint_footprint_at_high_speed_is_one_line_and_small(tmp_path):
    # A footprint of 0.1 um (schema-valid: 0 to 5 mm) at 2000 mm/s: the reference renderer's
    # frame window was tabulated at 1/200 of the footprint's passage (50 ns), 2e8 samples, and
    # the compile was killed at 24 GB before the tables refused their grids. Under a 4 GiB
    # address-space limit (run_compile_limited).
    scene = tmp_path / "pin.toml"
    scene.write_text("[motion]\nspeed_range_mm_s = [1999, 2000]\ndirections_deg = [0, 0.001]\ntolerance = 0.5\n"
                     "[render]\nfootprint_sigma_mm = 0.0001\n")
    out = tmp_path / "pin.tact.h5"
    status, stderr, peak_kib = run_compile_limited(tmp_path, SPEC, "-o", str(out), "--scene", str(scene), "-q")
    assert status == 1, stderr
    (line,) = stderr.strip().splitlines()
    assert "is out of scale for the tables: its footprint grids" in line and "render.footprint_sigma_mm, 0.0001 mm" in line
    assert not out.exists()
    assert peak_kib < 2 ** 20  # under 1 GiB


def test_debug_shows_traceback(tmp_path):
    r = run("haptex-compile", str(tmp_path / "missing.png"), "-o", str(tmp_path / "x.tact.h5"), "--debug")
    assert r.returncode != 0 and "Traceback" in r.stderr


def test_usage_errors_exit_2(tmp_path):
    r = run("haptex-compile", SPEC, SPEC, "-o", str(tmp_path / "x.tact.h5"))
    assert r.returncode == 2
    assert r.stderr.strip().splitlines() == [
        "haptex-compile: error: -o/--output takes one input; use --out-dir for several (see haptex-compile --help)"]
    r = run("haptex-compile", SPEC)
    assert r.returncode == 2


@pytest.mark.parametrize("tool, args, fragment", [
    ("haptex-compile", [SPEC, "--light", "95,30", "-o", "x.tact.h5"], "Invalid value for '--light': slant must be in [0, 90)"),
    # (an infinite tilt was refused only by the solver, after the photo was read: exit 1)
    ("haptex-compile", [SPEC, "--light", "30,inf", "-o", "x.tact.h5"], "Invalid value for '--light': tilt must be a finite number"),
    ("haptex-compile", [SPEC, "--pixel-size", "3furlong", "-o", "x.tact.h5"], "unknown length unit 'furlong'"),
    ("haptex-compile", [SPEC, "--bogus"], "No such option '--bogus'"),
    ("haptex-compile", [], "Missing argument 'INPUTS...'"),
    ("haptex-compile", [SPEC], "give exactly one of -o/--output or --out-dir"),
    ("haptex-inspect", ["a.tact.h5", "b.tact.h5", "--plot", "p.png"], "--plot takes one file"),
    ("haptex-play", ["a.tact.h5", "--fast"], "give exactly one of --sweep, --trajectory or --live"),
    # (the plot was not made; --kes was ignored for --relief-um)
    ("haptex-inspect", ["a.tact.h5", "--validate", "--plot", "p.png"], "give one of --validate or --plot"),
    ("haptex-compile", ["x.jpg", "-o", "x.tact.h5", "--relief-um", "5", "--kes", "k.kes.json"],
     "--relief-um and --kes both set a photo's height scale: give one"),
    # (the waveforms were synthesised and dropped)
    ("haptex-play", ["a.tact.h5", "--sweep", "speed=80,duration=1", "--waveforms"], "--waveforms needs --record"),
    ("haptex-play", ["a.tact.h5", "--max-frames", "two"], "Invalid value for '--max-frames'"),
    # Non-finite or absurd numbers, which passed a plain float or a range's comparisons: NaN
    # schedules, a 1.8 TiB waveform buffer (MemoryError traceback), NaN heights.
    ("haptex-play", ["a.tact.h5", "--lead-ms", "nan"], "Invalid value for '--lead-ms': 'nan' is not a finite number"),
    ("haptex-play", ["a.tact.h5", "--waveform-rate", "1e12"], "Invalid value for '--waveform-rate'"),
    ("haptex-compile", [SPEC, "--relief-um", "1e308", "-o", "x.tact.h5"], "Invalid value for '--relief-um'"),
    ("haptex-compile", [SPEC, "--exr-speed", "nan", "-o", "x.tact.h5"], "'nan' is not a finite number"),
])
def test_usage_errors_are_one_line(tmp_path, monkeypatch, tool, args, fragment):
    # Usage errors from click's parsing and from the commands' own checks alike: one line that
    # names the tool and the problem, exit status 2, nothing written.
    from click.testing import CliRunner

    monkeypatch.chdir(tmp_path)
    r = CliRunner().invoke(importlib.import_module(TOOL_MODULES[tool]).main, args, prog_name=tool)
    assert r.exit_code == 2
    assert r.stdout == ""
    [line] = r.stderr.strip().splitlines()
    assert line.startswith(f"{tool}: error: ") and fragment in line and line.endswith(f"(see {tool} --help)")
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("tool", sorted(TOOL_MODULES))
def test_help_states_every_range(tool):
    # Each numeric option's range is shown in its help; an unbounded (finite-only) one read
    # "x<=None" (click's description of a range without bounds).
    from click.testing import CliRunner

    r = CliRunner().invoke(importlib.import_module(TOOL_MODULES[tool]).main, ["--help"], prog_name=tool,
                           terminal_width=200)
    assert r.exit_code == 0
    assert "None" not in r.stdout
    if tool != "haptex-play":
        assert "0.0; finite]" in r.stdout  # --exr-direction, --direction


@pytest.mark.parametrize("tool, args", [
    ("haptex-compile", ["no\x1b[31msuch.npy", "-o", "x.tact.h5"]),
    ("haptex-play", ["no\x1b[31msuch.tact.h5", "--sweep", "speed=80"]),
    ("haptex-inspect", ["no\x1b[31msuch.tact.h5"]),
])
def test_error_lines_show_control_characters_escaped(tmp_path, tool, args):
    # A file name (or a library's message) with a terminal escape sequence in it: the error
    # line shows it escaped, as the name it is (click dropped the sequence from piped output,
    # naming a file that does not exist, and passed it to a terminal).
    r = run(tool, *args, cwd=tmp_path)
    assert r.returncode == 1
    [line] = r.stderr.strip().splitlines()
    assert line.startswith(f"{tool}: error: no\\x1b[31msuch.") and "\x1b" not in line
    assert list(tmp_path.iterdir()) == []


def test_options_that_apply_only_with_another_are_warned_of(asset, scene_file, tmp_path):
    # --exr-speed without --exr, --waveform-rate without --waveforms, --speed and --direction
    # without --plot were ignored without a word; given with it, no warning.
    cases = [
        ("haptex-compile", [SPEC, "-o", str(tmp_path / "x.tact.h5"), "--scene", str(scene_file), "--exr-speed", "40",
                            "--exr-direction", "10"], ["--exr-speed, --exr-direction apply only with --exr: ignored"]),
        ("haptex-play", [str(asset), "--sweep", "speed=80,duration=0.1", "--fast", "--waveform-rate", "1000"],
         ["--waveform-rate applies only with --waveforms: ignored"]),
        ("haptex-inspect", [str(asset), "--speed", "30", "--direction", "4"],
         ["--speed, --direction apply only with --plot: ignored"]),
    ]
    for tool, args, warnings in cases:
        r = run(tool, *args)
        assert r.returncode == 0, r.stderr
        for warning in warnings:
            assert f"haptex: WARNING: {warning}" in r.stderr.splitlines()
    r = run("haptex-play", str(asset), "--sweep", "speed=80,duration=0.1", "--fast", "--waveforms", "--waveform-rate",
            "1000", "--record", str(tmp_path / "r.h5"))
    assert r.returncode == 0 and "WARNING" not in r.stderr
    # --relief-kind without --relief-um, said once: by the command for a photo (here one that is
    # missing: the warning comes before the work), by the source for other inputs.
    r = run("haptex-compile", str(tmp_path / "none.png"), "-o", str(tmp_path / "i.tact.h5"), "--relief-kind", "pv")
    assert r.returncode == 1
    assert r.stderr.splitlines()[0] == "haptex: WARNING: --relief-kind applies only with --relief-um: ignored"
    r = run("haptex-compile", SPEC, "-o", str(tmp_path / "b.tact.h5"), "--scene", str(scene_file), "--relief-kind", "pv")
    assert r.returncode == 0 and [line for line in r.stderr.splitlines() if "--relief-kind" in line] == [
        f"haptex.sources: WARNING: {SPEC}: --relief-kind does not apply to a Brownian spec (its pixel= and seed= set those): ignored"]


@pytest.mark.parametrize("text, fragment", [
    ("[array]\nfoo = 1\n", "array"),
    ("[motion]\nspeeds_mm_s = [-5]\n", "motion.speeds_mm_s"),
    ("[render\n", "not valid TOML"),
])
def test_malformed_scene_is_one_line(tmp_path, text, fragment):
    scene = tmp_path / "bad.toml"
    scene.write_text(text)
    r = run("haptex-compile", SPEC, "-o", str(tmp_path / "x.tact.h5"), "--scene", str(scene))
    assert r.returncode == 1
    assert len(r.stderr.strip().splitlines()) == 1
    assert "bad.toml" in r.stderr and fragment in r.stderr
    assert not (tmp_path / "x.tact.h5").exists()


def test_make_dependency_file_and_out_dir_with_jobs(tmp_path, scene_file):
    npy = tmp_path / "h.npy"
    rng = np.random.default_rng(0)
    np.save(npy, rng.normal(size=(48, 48)))
    md = tmp_path / "deps.d"
    out_dir = tmp_path / "out"
    r = run("haptex-compile", str(npy), SPEC, "--out-dir", str(out_dir), "--scene", str(scene_file),
            "--pixel-size", "0.02mm", "-j", "2", "--md", str(md))
    assert r.returncode == 0, r.stderr
    outs = sorted(p.name for p in out_dir.iterdir())
    assert "h.tact.h5" in outs and len(outs) == 2
    rules = md.read_text().splitlines()
    assert f"{out_dir / 'h.tact.h5'}: {npy} {scene_file}" in rules


def test_file_names_that_are_not_utf8_or_hold_make_characters(tmp_path, scene_file):
    # A file name's bytes need not be UTF-8: the asset's writer refused the name ("surrogates not
    # allowed"), the EXR binding both reading and writing, and the dependency file was a
    # UnicodeEncodeError traceback that left its temporary file. Make reads a space as the end
    # of a word: "sp ace/a b.npy" was two prerequisites.
    import os

    from haptex_compile.io_exr import read_exr_channels
    from playback.asset import read_asset

    odd = os.fsdecode(b"h\xff\xfe")  # (Python holds those bytes as lone surrogates)
    folder = tmp_path / "sp ace"
    folder.mkdir()
    npy, out, exr, md = (folder / f"{odd} #$1{ext}" for ext in (".npy", ".tact.h5", ".exr", ".d"))
    np.save(npy, np.random.default_rng(0).normal(size=(24, 24)))
    r = run("haptex-compile", str(npy), "-o", str(out), "--scene", str(scene_file), "--pixel-size", "20um",
            "--exr", str(exr), "--md", str(md))
    assert r.returncode == 0, r.stderr
    assert sorted(p.name for p in folder.iterdir()) == sorted(p.name for p in (npy, out, exr, md))
    assert read_asset(out).source_name == "h\ufffd\ufffd #$1.npy"
    assert set(read_exr_channels(exr)) >= {"height", "a40", "a320"}
    word = lambda p: os.fsencode(p).replace(b" ", b"\\ ").replace(b"#", b"\\#").replace(b"$", b"$$")  # noqa: E731
    assert md.read_bytes() == word(out) + b": " + word(npy) + b" " + word(scene_file) + b"\n"


def test_a_kawabata_csv_of_several_fabrics_gives_an_asset_of_each(tmp_path, scene_file):
    # The batch format (one row per fabric) was refused: "holds 3 fabrics; compile them one by
    # one (split the CSV)".
    import json

    import h5py

    csv = tmp_path / "lab.kes.csv"
    csv.write_text("fabric,smd_warp_um,smd_weft_um,miu_warp,miu_weft,mmd_warp,mmd_weft,ends_per_cm,picks_per_cm,weave\n"
                   "cotton poplin,3.2,4.1,0.18,0.2,0.012,0.015,48,30,plain\n"
                   "denim/stretch,5,6,0.2,0.2,0.01,0.01,30,20,twill\n"
                   "cotton poplin,2,2,0.2,0.2,0.01,0.01,48,30,plain\n")
    out, md = tmp_path / "out", tmp_path / "deps.d"
    r = run("haptex-compile", str(csv), "--out-dir", str(out), "--scene", str(scene_file), "--md", str(md))
    assert r.returncode == 0, r.stderr
    names = ["lab-cotton_poplin-1.tact.h5", "lab-denim_stretch.tact.h5", "lab-cotton_poplin-3.tact.h5"]
    assert sorted(p.name for p in out.iterdir()) == sorted(names)
    for name, (fabric, warp, weft) in zip(names, [("cotton poplin", 3.2, 4.1), ("denim/stretch", 5, 6),
                                                  ("cotton poplin", 2, 2)]):
        with h5py.File(out / name) as f:
            report = json.loads(f["report"].attrs["json"])
        assert report["fabric"] == fabric
        assert report["smd_simulated_um"]["warp"] == pytest.approx(warp, rel=0.05)
        assert report["smd_simulated_um"]["weft"] == pytest.approx(weft, rel=0.05)
    assert md.read_text().splitlines() == [f"{out / n}: {csv} {scene_file}" for n in names]
    r = run("haptex-compile", str(csv), "-o", str(tmp_path / "x.tact.h5"), "--scene", str(scene_file))
    assert r.returncode == 1 and r.stderr.strip() == f"haptex-compile: error: {csv}: holds 3 fabrics: give --out-dir for an asset of each"


def test_a_height_map_in_nanometres_is_compiled_with_a_warning(tmp_path, scene_file):
    # Heights of a few µm written in nm read as thousands of µm: compiled, warned of on
    # stderr (naming the file) and in the asset, which haptex-inspect shows.
    npy = tmp_path / "nm.npy"
    np.save(npy, 3000.0 * np.random.default_rng(1).normal(size=(48, 48)))
    out = tmp_path / "nm.tact.h5"
    r = run("haptex-compile", str(npy), "-o", str(out), "--scene", str(scene_file), "--pixel-size", "20um")
    assert r.returncode == 0, r.stderr
    assert any("nm.npy" in line and "micrometres" in line for line in r.stderr.splitlines())
    r = run("haptex-inspect", str(out))
    assert r.returncode == 0 and "warning    RMS height" in r.stdout


def test_exr_export_has_named_channels(tmp_path, scene_file):
    from haptex_compile.io_exr import read_exr_channels

    exr = tmp_path / "maps.exr"
    r = run("haptex-compile", SPEC, "-o", str(tmp_path / "b.tact.h5"), "--scene", str(scene_file),
            "--exr", str(exr), "--exr-speed", "60", "--exr-direction", "45")
    assert r.returncode == 0, r.stderr
    ch = read_exr_channels(exr)
    assert set(ch) >= {"height", "a40", "a320"}
    assert ch["height"].shape == (64, 64)
    assert np.all(np.isfinite(ch["a40"])) and float(ch["a40"].mean()) > 0


def test_inspect_summary_and_validate(asset, tmp_path):
    r = run("haptex-inspect", str(asset))
    assert r.returncode == 0 and "2 directions x 2 speeds" in r.stdout
    r = run("haptex-inspect", "--validate", str(asset))
    assert r.returncode == 0 and "valid" in r.stdout
    broken = tmp_path / "broken.tact.h5"
    broken.write_bytes(asset.read_bytes())
    with h5py.File(broken, "r+") as f:
        f.attrs["format_version"] = "2.0"
    r = run("haptex-inspect", "--validate", str(broken))
    assert r.returncode == 1 and "format_version" in r.stderr


def test_play_rejects_a_wrong_hdf5_file(tmp_path):
    wrong = tmp_path / "wrong.h5"
    with h5py.File(wrong, "w") as f:
        f["x"] = np.zeros(3)
    r = run("haptex-play", str(wrong), "--sweep", "speed=80,direction=0,duration=0.1", "--fast")
    assert r.returncode == 1
    assert len(r.stderr.strip().splitlines()) == 1 and "wrong.h5" in r.stderr


def test_tables_and_direct_modes_agree(asset, tmp_path):
    """Frames played from the tables equal the reference renderer's within the tables' error."""
    rec_t, rec_d = tmp_path / "t.h5", tmp_path / "d.h5"
    sweep = "speed=60,direction=0,duration=0.3,u=0.6,v=0.6"
    for mode, rec in (("tables", rec_t), ("direct", rec_d)):
        r = run("haptex-play", str(asset), "--sweep", sweep, "--fast", "--mode", mode, "--record", str(rec))
        assert r.returncode == 0, r.stderr
    with h5py.File(rec_t) as ft, h5py.File(rec_d) as fd:
        assert ft["frames/a40"].shape == fd["frames/a40"].shape
        a40t, a40d = ft["frames/a40"][()], fd["frames/a40"][()]
        a320t, a320d = ft["frames/a320"][()], fd["frames/a320"][()]
    err40 = np.abs(a40t - a40d).mean() / a40d.mean()
    err320 = np.abs(a320t - a320d).mean() / a320d.mean()
    assert err40 < 0.08 and err320 < 0.08


@pytest.mark.parametrize("error, line", [
    (MemoryError("Unable to allocate 3.0 GiB for an array"), "in.npy: out of memory (Unable to allocate 3.0 GiB for an array)"),
    (ValueError("operands could not be broadcast"), "in.npy: operands could not be broadcast"),
    (ValueError("in.npy: image too small"), "in.npy: image too small"),
])
def test_a_failed_input_gets_one_line_that_names_it(monkeypatch, error, line):
    # With several inputs, a message that does not name its file says nothing of which failed;
    # running out of memory was a traceback.
    from haptex_compile import cli, compile as compile_module

    def fail(*args, **kwargs):
        raise error

    monkeypatch.setattr(compile_module, "compile_source", fail)
    job = {"spec": "in.npy", "out": "in.tact.h5", "scene": None, "options": None, "exr": None, "exr_speed": 80.0,
           "exr_direction": 0.0, "debug": False}
    assert cli._one(job) == ("in.npy", line)
