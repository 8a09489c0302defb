"""``haptex-inspect rec.h5`` on a playback record prints the run's summary instead of failing."""
from __future__ import annotations

import re

import h5py
import numpy as np
import pytest
from click.testing import CliRunner

from asset_factory import write_test_asset
from playback import protocol
from playback.asset import read_asset
from playback.clock import VirtualClock
from playback.device import DEFAULT_PROFILE, profile_from_dict
from playback.player import Player
from playback.record import Recorder
from playback.trajectory import sweep_trajectory
from playback.transport import make_transport

LEAD_MS, PREP_MS = 5.0, 2.0


@pytest.fixture(scope="module")
def record(tmp_path_factory):
    """80 frames at 80 mm/s; frame 10 wakes 3 ms too late to make its window start; the
    displacement limit (1 µm) is below every amplitude of the test field at that speed
    (a40 + a320 >= (5 - 1.5 - 1) * 0.97 + (0.8 - 0.2 - 0.3) * 0.94 > 2.7 µm), so every
    contactor of every frame is clamped."""
    d = tmp_path_factory.mktemp("rec")
    asset = read_asset(write_test_asset(d / "a.tact.h5"))
    doc = {**DEFAULT_PROFILE, "limits": {"max_voltage_v_rms": 40.0, "max_displacement_um": 1.0}}
    profile = profile_from_dict(doc)
    wakes = []

    def oversleep():
        wakes.append(None)
        return (PREP_MS + LEAD_MS + 3.0) * 1e-3 if len(wakes) == 11 else 0.0
    clock = VirtualClock(10.0, oversleep=oversleep)
    transport, emu = make_transport("sim", profile, clock)
    path = d / "rec.h5"
    rec = Recorder(path, asset.n_contactors, profile.n_channels, protocol.frame_size(profile.n_channels))
    Player(asset, profile, transport, sweep_trajectory(80.0, 0.0, 2.0), clock=clock, recorder=rec, emulator=emu,
           lead_ms=LEAD_MS, prep_ms=PREP_MS).run()
    return path


def test_inspect_summarises_a_playback_record(record):
    from haptex_compile.inspect_cli import main

    r = CliRunner().invoke(main, [str(record)])
    assert r.exit_code == 0, r.output
    out = r.output
    assert "haptex-play record" in out and "mode tables" in out and "device sim" in out
    assert re.search(r"80 sent over 2\.00 s \(25 ms each\), 0 skipped; 24 contactors, 24 device channels", out)
    # One frame late, by exactly the oversleep beyond prep + lead; on simulated time every
    # other send is exactly on time, so no drift, and the worst send error is lead + 3 ms.
    assert re.search(r"1 late .*worst \+3\.00 ms from window start", out)
    assert re.search(r"max 8\.000 ms; drift 0\.000 ms", out)
    assert "1920 contactor amplitudes clamped (in 80 frames)" in out  # 80 frames x 24 contactors
    assert "above_range 0, below_range 0, outside 0, invalid 0" in out
    with h5py.File(record) as f:
        render = f["frames/render_us"][()].astype(np.float64)
    assert f"render     median {np.median(render):.0f} us" in out
    assert "all-zero frame sent: yes" in out


def test_inspect_record_and_asset_together(record, tmp_path):
    from haptex_compile.inspect_cli import main

    asset = write_test_asset(tmp_path / "b.tact.h5")
    r = CliRunner().invoke(main, [str(record), str(asset)])
    assert r.exit_code == 0, r.output
    assert "haptex-play record" in r.output and "haptex tactile asset" in r.output


def _malformed(record, path, edit):
    """A copy of `record` at `path` with `edit(f)` applied to it."""
    path.write_bytes(record.read_bytes())
    with h5py.File(path, "r+") as f:
        edit(f)
    return path


def test_malformed_records_are_one_line_each(record, tmp_path):
    # Records whose layout is damaged (as random bytes overwritten in a record did: 8 of 60
    # gave a KeyError, IndexError or MemoryError traceback from the summary, which trusted
    # the layout): the summary and the plot say so in one line naming the file, exit 1.
    from haptex_compile.inspect_cli import main

    def flat_a40(f):
        a40 = f["frames/a40"][()]
        del f["frames/a40"]
        f["frames/a40"] = a40.ravel()

    def short_late(f):
        late = f["frames/late"][()]
        del f["frames/late"]
        f["frames/late"] = late[:-7]

    edits = {"no_t_s": lambda f: f["frames"].__delitem__("t_s"), "flat_a40": flat_a40, "short_late": short_late}
    for name, edit in edits.items():
        path = _malformed(record, tmp_path / f"{name}.h5", edit)
        for args in ([str(path)], ["--plot", str(tmp_path / f"{name}.png"), str(path)]):
            r = CliRunner().invoke(main, args)
            assert r.exit_code == 1 and isinstance(r.exception, SystemExit), (name, args, r.exception)
            lines = r.output.strip().splitlines()
            assert len(lines) == 1 and str(path) in lines[0], (name, r.output)
        assert not (tmp_path / f"{name}.png").exists()


def test_text_from_files_is_shown_escaped_and_cut(record, tmp_path):
    # Attributes are the file's words, not ours: a newline or a terminal escape in one split the
    # summary's line or recoloured the terminal, and a 5000-character one was printed whole.
    from haptex_compile.inspect_cli import main
    from playback.errors import SHOWN_CHARS

    device, stop = "sim\x1b[31m\nnext\rline", "x" * 2000 + "END"

    def edit(f):
        f.attrs["device"], f.attrs["stopped_by"] = device, stop

    rec = _malformed(record, tmp_path / "texts.h5", edit)
    asset = write_test_asset(tmp_path / "a.tact.h5")
    with h5py.File(asset, "r+") as f:
        f.attrs["source_name"] = "fab\nric\x1b[2J.jpg"
    r = CliRunner().invoke(main, [str(rec), str(asset)])
    assert r.exit_code == 0, r.output
    assert "\x1b" not in r.output and "\r" not in r.output
    assert "device sim\\x1b[31m\\nnext\\rline, " in r.output
    assert ": fab\\nric\\x1b[2J.jpg\n" in r.output
    [stop_line] = [line for line in r.output.splitlines() if line.startswith("  stop ")]
    # Cut in the middle to SHOWN_CHARS, its length stated, its end kept.
    assert f" ... [{len(stop)} characters] ... " in stop_line and "xEND; all-zero frame sent" in stop_line
    assert stop_line.count("x") == SHOWN_CHARS - len("END")


def test_validating_a_record_says_it_is_one(record):
    # --validate checks assets: a record got eight lines of schema violations ("'generator' is a
    # required property", ...), none saying what the file is.
    from haptex_compile.inspect_cli import main

    r = CliRunner().invoke(main, ["--validate", str(record)])
    assert r.exit_code == 1
    [line] = r.output.strip().splitlines()
    assert str(record) in line and "a playback record" in line and "not a tactile asset" in line


def test_files_named_with_bytes_that_are_not_utf8(tmp_path):
    # Python holds such bytes as lone surrogates: the recorder could not store the asset's name
    # (UnicodeEncodeError traceback, no record), and the plot could not draw it in its title
    # (TypeError traceback, no plot). Run as a user runs the tools (the test runner's captured
    # output refuses such names where a terminal shows them).
    import os
    import subprocess
    import sys

    def tool(module: str, *args: str) -> subprocess.CompletedProcess:
        return subprocess.run([sys.executable, "-c", f"from {module} import main; main()", *args],
                              capture_output=True, timeout=300)

    odd = os.fsdecode(b"\xff\xfe")
    asset = write_test_asset(tmp_path / f"a{odd}.tact.h5")
    rec, png = tmp_path / f"r{odd}.h5", tmp_path / f"p{odd}.png"
    r = tool("playback.cli", str(asset), "--sweep", "speed=80,duration=0.2", "--fast", "--record", str(rec))
    assert r.returncode == 0, r.stderr
    with h5py.File(rec) as f:
        assert f.attrs["asset"] == str(asset).replace(odd, "\ufffd\ufffd")
    r = tool("haptex_compile.inspect_cli", str(rec))
    assert r.returncode == 0 and "a\ufffd\ufffd.tact.h5".encode() in r.stdout, r.stderr
    for shown in (rec, asset):
        r = tool("haptex_compile.inspect_cli", "--plot", str(png), str(shown))
        assert r.returncode == 0, (shown, r.stderr)
        assert png.stat().st_size > 0
        png.unlink()


def test_every_file_is_summarised_and_a_missing_one_named_as_such(tmp_path):
    # The first bad file ended a summary run (`haptex-inspect *.tact.h5` stopped there) where
    # --validate checks every file; and --validate called a missing file "not an HDF5 file".
    from haptex_compile.inspect_cli import main

    good, missing = write_test_asset(tmp_path / "a.tact.h5"), tmp_path / "none.tact.h5"
    r = CliRunner().invoke(main, [str(good), str(missing), str(good)])
    assert r.exit_code == 1
    assert r.stdout.count(f"{good}: haptex tactile asset") == 2
    assert r.stderr.strip().splitlines() == [f"haptex-inspect: error: {missing}: no such file"]
    r = CliRunner().invoke(main, ["--validate", str(missing), str(good)])
    assert r.exit_code == 1
    assert r.stderr.strip().splitlines() == [f"haptex-inspect: invalid: {missing}: no such file"]
    assert r.stdout.strip() == f"{good}: valid haptex tactile asset"
