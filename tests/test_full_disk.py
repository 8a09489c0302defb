"""Writes that fail part-way (a full disk, a file-size limit): one line, no file left, no crash.

libhdf5 writing into a full disk printed hundreds of lines of tracebacks while the file was
closed and then crashed the process (segmentation fault), for assets and playback records
alike. The tools now build HDF5 files in memory and write them out in one piece
(:func:`playback.paths.replace_with_bytes`). A file-size limit (RLIMIT_FSIZE, with SIGXFSZ
ignored) makes writes past it fail as a full disk does, without filling one.
"""
from __future__ import annotations

import errno
import os
import resource
import signal
import subprocess
from pathlib import Path

import pytest

from playback.errors import InputError
from playback.paths import replace_with_bytes
from asset_factory import tool_argv, write_test_asset

REPO = Path(__file__).resolve().parents[1]
posix = pytest.mark.skipif(not hasattr(resource, "RLIMIT_FSIZE"), reason="POSIX file-size limits")


def test_replace_with_bytes_failing_keeps_the_old_file_and_leaves_no_temporary(tmp_path, monkeypatch):
    target = tmp_path / "a.bin"
    target.write_bytes(b"old")

    def full(fd):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
    monkeypatch.setattr(os, "fsync", full)
    with pytest.raises(InputError, match="a.bin: cannot be written: No space left on device"):
        replace_with_bytes(target, b"new content", 0o644)
    assert target.read_bytes() == b"old" and [p.name for p in tmp_path.iterdir()] == ["a.bin"]
    monkeypatch.undo()
    replace_with_bytes(target, b"new content", 0o640)
    assert target.read_bytes() == b"new content" and (target.stat().st_mode & 0o777) == 0o640


def _limited(limit_bytes: int):
    def apply() -> None:
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # a write past the limit fails (EFBIG)
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit_bytes, limit_bytes))
    return apply


def _run(tool: str, args: list[str], cwd: Path, limit_bytes: int) -> subprocess.CompletedProcess:
    return subprocess.run([*tool_argv(tool), *args], cwd=cwd, capture_output=True, text=True, timeout=300,
                          preexec_fn=_limited(limit_bytes), env={**os.environ, "PYTHONPATH": str(REPO)})


@posix
def test_compile_into_a_full_disk_one_line_no_file(tmp_path):
    spec = "brownian:H=0.7,size=64,pixel=20um,rms=5um,seed=1"  # an asset of about 57 KB
    (tmp_path / "s.toml").write_text("[motion]\nspeeds_mm_s = [40, 80]\ndirections_deg = [0, 90]\ntolerance = 0.5\n")
    r = _run("haptex-compile", [spec, "--scene", "s.toml", "-o", "a.tact.h5"], tmp_path, 20_000)
    assert r.returncode == 1, r.stderr[-2000:]
    assert r.stderr.splitlines() == [f"haptex-compile: error: {spec}: a.tact.h5: cannot be written: File too large"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["s.toml"]


@posix
def test_play_record_into_a_full_disk_one_line_no_file(tmp_path):
    write_test_asset(tmp_path / "a.tact.h5")
    r = _run("haptex-play", ["a.tact.h5", "--device", "null", "--fast", "--sweep",
                                             "speed=80,duration=20", "--record", "r.h5"], tmp_path,
             (tmp_path / "a.tact.h5").stat().st_size + 50_000)  # the record of 800 frames is larger
    assert r.returncode == 1, r.stderr[-2000:]
    assert r.stderr.splitlines() == ["haptex-play: error: r.h5: cannot be written: File too large"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.tact.h5"]


def test_record_past_its_memory_limit_drops_later_frames_and_says_so(tmp_path, monkeypatch):
    """The record is held in memory until written: past its limit, frames are counted, not kept."""
    from click.testing import CliRunner
    from haptex_compile.inspect_cli import main as inspect_main
    from playback import record
    from playback.cli import main

    write_test_asset(tmp_path / "a.tact.h5")
    # 30 frames of the 24-contactor layout without its packet bytes: fewer than 30 fit
    frame_bytes = 8 * 4 + 4 * 4 + 1 + 2 * 2 + 4 + 24 * (4 + 4 + 1) + 2 * 24 * 2
    monkeypatch.setattr(record, "MAX_RECORD_BYTES", 30 * frame_bytes)
    r = CliRunner().invoke(main, [str(tmp_path / "a.tact.h5"), "--device", "null", "--fast", "--sweep",
                                  "speed=80,duration=2", "--record", str(tmp_path / "r.h5")])
    assert r.exit_code == 0, r.output
    import h5py
    with h5py.File(tmp_path / "r.h5") as f:
        n, dropped = f["frames/t_s"].shape[0], int(f.attrs["frames_not_recorded"])
    assert n + dropped == 80 and 0 < n < 30  # 2 s of 25 ms frames
    out = CliRunner().invoke(inspect_main, [str(tmp_path / "r.h5")]).output
    assert f"{dropped} later frames sent and not recorded" in out


@posix
def test_compile_with_exr_writes_both_or_neither(tmp_path):
    """The EXR (about 460 KB here) does not fit under the limit, the asset (about 170 KB) does:
    neither is written and the older asset survives (before: the asset was written, then the
    EXR failed)."""
    spec = "brownian:H=0.7,size=200,pixel=20um,rms=5um,seed=1"
    (tmp_path / "s.toml").write_text("[motion]\nspeeds_mm_s = [40, 80]\ndirections_deg = [0, 90]\ntolerance = 0.5\n")
    (tmp_path / "a.tact.h5").write_bytes(b"older")
    r = _run("haptex-compile", [spec, "--scene", "s.toml", "-o", "a.tact.h5", "--exr", "a.exr"],
             tmp_path, 300_000)
    assert r.returncode == 1 and r.stderr.splitlines() == [
        f"haptex-compile: error: {spec}: a.exr: cannot be written: File too large"], r.stderr[-2000:]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.tact.h5", "s.toml"]
    assert (tmp_path / "a.tact.h5").read_bytes() == b"older"


def test_names_up_to_the_file_system_limit_are_written_and_longer_refused_before_work(tmp_path):
    """A name of 254 bytes is valid; its temporary name (14 bytes longer) was not: the compile
    failed after its tables. A name over the limit is refused at once."""
    from click.testing import CliRunner
    from haptex_compile.cli import main

    spec = "brownian:H=0.7,size=24,pixel=20um,rms=5um,seed=1"
    (tmp_path / "s.toml").write_text("[motion]\nspeeds_mm_s = [40, 80]\ndirections_deg = [0, 90]\ntolerance = 0.5\n")
    longest = "n" * 246 + ".tact.h5"  # 254 bytes
    exr = "e" * 251 + ".exr"
    r = CliRunner().invoke(main, [spec, "--scene", str(tmp_path / "s.toml"), "-o", str(tmp_path / longest),
                                  "--exr", str(tmp_path / exr), "--md", str(tmp_path / ("d" * 253 + ".d"))])
    assert r.exit_code == 0, r.output
    assert {p.name for p in tmp_path.iterdir()} == {"s.toml", longest, exr, "d" * 253 + ".d"}
    too_long = "n" * 250 + ".tact.h5"
    r = CliRunner().invoke(main, [spec, "--scene", str(tmp_path / "s.toml"), "-o", str(tmp_path / too_long)])
    assert r.exit_code == 2 and "its name is 258 bytes, over the file system's 255" in r.output


def test_outputs_in_a_folder_that_cannot_be_written_are_refused_before_work(tmp_path, monkeypatch):
    """An output on a read-only file system (or in a folder without write permission) failed
    after all the work; now it is refused at once. os.access is made to say no for one folder
    (a read-only mount needs root); an existing file is still written in place (/dev/null as a
    packet sink for a user who may not write in /dev)."""
    from click.testing import CliRunner
    from haptex_compile import compile as compile_module
    from haptex_compile.cli import main
    from playback.cli import main as play_main

    locked = tmp_path / "locked"
    locked.mkdir()
    real_access = os.access
    monkeypatch.setattr(os, "access", lambda p, mode, **kw: False if Path(p) in (locked, Path("/dev"))
                        else real_access(p, mode, **kw))
    monkeypatch.setattr(compile_module, "build_checked_tables", lambda *a, **k: pytest.fail("the work began"))
    spec = "brownian:H=0.7,size=24,pixel=20um,rms=5um,seed=1"
    for option, name in (("-o", "a.tact.h5"), ("--md", "a.d"), ("--exr", "a.exr")):
        args = [spec, "-o", str(locked / name)] if option == "-o" else [spec, "-o", str(tmp_path / "ok.tact.h5"),
                                                                        option, str(locked / name)]
        r = CliRunner().invoke(main, args)
        assert r.exit_code == 2 and f"cannot be written: no permission to write in {locked}" in r.output, r.output
    asset = write_test_asset(tmp_path / "p.tact.h5")
    r = CliRunner().invoke(play_main, [str(asset), "--device", "null", "--fast", "--sweep", "speed=80,duration=0.2",
                                       "--record", str(locked / "r.h5")])
    assert r.exit_code == 2 and "no permission to write in" in r.output
    r = CliRunner().invoke(play_main, [str(asset), "--device", "file:/dev/null", "--fast", "--sweep", "speed=80,duration=0.2"])
    assert r.exit_code == 0, r.output
