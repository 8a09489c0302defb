"""Stop signals: SIGTERM and SIGHUP stop the three tools as Ctrl-C does (playback.stop_signals).

Each case fails without the module: SIGTERM killed haptex-play with no zero frame, no record
and its temporary file left, killed haptex-compile (and its --jobs workers went on compiling
the queued inputs), and a second Ctrl-C during the player's zero frame cut it off."""
from __future__ import annotations

import os
import pickle
import signal
import subprocess
import sys
import time
from pathlib import Path

import h5py
import pytest

from playback import protocol
from playback.stop_signals import StopRequested, deferred, exit_status, stop_reason, stop_signals_raise
from playback.trajectory import sweep_trajectory
from asset_factory import tool_argv, write_test_asset
from test_playback_player import HookClock, play

REPO = Path(__file__).resolve().parents[1]
KES = REPO / "samples" / "kes"
pytestmark = pytest.mark.skipif(not hasattr(signal, "SIGHUP"), reason="POSIX signals")


def _deliver(sig: signal.Signals) -> None:
    """Send `sig` to this process and give Python the bytecode boundary its handler runs at."""
    os.kill(os.getpid(), sig)
    for _ in range(100):
        time.sleep(0.001)


@pytest.mark.parametrize("sig, status", [(signal.SIGTERM, 143), (signal.SIGHUP, 129)])
def test_stop_signal_raises_keyboard_interrupt_with_its_name(sig, status):
    before = signal.getsignal(sig)
    with pytest.raises(KeyboardInterrupt) as info:
        with stop_signals_raise():
            _deliver(sig)
    assert isinstance(info.value, StopRequested) and stop_reason(info.value) == sig.name
    assert exit_status(info.value) == status  # 128 + the signal's number, as the shell reports it
    assert signal.getsignal(sig) is before  # put back


def test_ctrl_c_reason_and_status():
    assert stop_reason(KeyboardInterrupt()) == "Ctrl-C" and exit_status(KeyboardInterrupt()) == 130


def test_ignored_signal_stays_ignored():
    """nohup starts a process with SIGHUP ignored: it must not stop it."""
    before = signal.signal(signal.SIGHUP, signal.SIG_IGN)
    try:
        with stop_signals_raise():
            _deliver(signal.SIGHUP)
            assert signal.getsignal(signal.SIGHUP) is signal.SIG_IGN
    finally:
        signal.signal(signal.SIGHUP, before)


def test_deferred_holds_every_stop_signal_then_restores():
    with stop_signals_raise():
        with deferred() as held:
            _deliver(signal.SIGINT)
            _deliver(signal.SIGTERM)
        assert held == ["SIGINT", "SIGTERM"]
        with pytest.raises(StopRequested):  # raising again once out of it
            _deliver(signal.SIGTERM)
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler


def test_stop_requested_survives_pickling():
    """A --jobs worker's exception crosses to the parent pickled."""
    exc = pickle.loads(pickle.dumps(StopRequested("SIGHUP")))
    assert isinstance(exc, KeyboardInterrupt) and exc.signal_name == "SIGHUP"


@pytest.fixture(scope="module")
def asset_path(tmp_path_factory):
    return write_test_asset(tmp_path_factory.mktemp("a") / "smooth.tact.h5")


def test_second_ctrl_c_during_the_zero_frame_is_held(tmp_path, asset_path):
    """Ctrl-C pressed again while the zero frame is being sent: the frame still goes out and the
    record is finished (before, the second KeyboardInterrupt cut both off)."""
    clock = HookClock()
    player, emu, _ = play(asset_path, sweep_trajectory(80.0, 0.0, 5.0), clock=clock, record=tmp_path / "r.h5")

    def interrupt():
        raise KeyboardInterrupt
    clock.hooks[20] = interrupt
    send = player.transport.send

    def send_then_ctrl_c(packet):
        if player.summary.interrupted:  # the zero frame: Ctrl-C again, mid-send
            signal.raise_signal(signal.SIGINT)
        return send(packet)
    player.transport.send = send_then_ctrl_c
    s = player.run()
    assert s.interrupted and s.zero_frame_sent and s.frames_sent == 20
    assert not emu.frames[-1].codes40.any() and not emu.frames[-1].codes320.any()
    with h5py.File(tmp_path / "r.h5") as f:
        assert f["frames/t_s"].shape == (20,) and f.attrs["stopped_by"] == "Ctrl-C"


def _start(args: list[str], cwd: Path, ready: str) -> subprocess.Popen:
    """A tool (``args[0]``) in its own process, as its console script runs it, once its stderr
    has printed `ready` (by then its signal handlers are set)."""
    proc = subprocess.Popen([*tool_argv(args[0]), *args[1:]], cwd=cwd, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, env={**os.environ, "PYTHONPATH": str(REPO)})
    seen = []
    for line in proc.stderr:
        seen.append(line)
        if ready in line:
            return proc
    proc.wait()
    pytest.fail(f"never printed {ready!r}: {''.join(seen)}")


def _finish(proc: subprocess.Popen, timeout: float = 60.0) -> tuple[int, str, str]:
    out, err = proc.communicate(timeout=timeout)
    return proc.returncode, out, err


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGHUP])
def test_play_stopped_by_signal_sends_zero_frame_and_keeps_record(tmp_path, asset_path, sig):
    proc = _start(["haptex-play", str(asset_path), "--device", "file:pk.bin", "--sweep",
                   "speed=80,direction=0,duration=60", "--record", "r.h5", "--no-realtime", "-vv"],
                  tmp_path, "frame 10 ")
    proc.send_signal(sig)
    code, out, err = _finish(proc)
    assert code == 0, err
    assert f"stopped by {sig.name}" in out and "Traceback" not in err
    packets = protocol.split_packets((tmp_path / "pk.bin").read_bytes())
    last = protocol.decode_frame(packets[-1])
    assert len(packets) > 10 and not last.codes40.any() and not last.codes320.any()
    with h5py.File(tmp_path / "r.h5") as f:
        assert f["frames/t_s"].shape == (len(packets) - 1,)  # every frame sent, then the zero frame
        assert f.attrs["stopped_by"] == sig.name and f.attrs["zero_frame_sent"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["pk.bin", "r.h5"]  # no temporary file


def test_play_failing_before_the_record_leaves_no_temporary_file(tmp_path, asset_path):
    from click.testing import CliRunner
    from playback.cli import main

    (tmp_path / "t.csv").write_text("t_s,u_mm,v_mm,phi_deg\n0,0,0,0\n0.01,0,0,0\n")
    r = CliRunner().invoke(main, [str(asset_path), "--trajectory", str(tmp_path / "t.csv"), "--fast",
                                  "--record", str(tmp_path / "r.h5")])
    assert r.exit_code == 1 and "shorter than one" in r.output
    assert sorted(p.name for p in tmp_path.iterdir()) == ["t.csv"]


def test_compile_stopped_by_sigterm_one_line_and_no_output(tmp_path):
    proc = _start(["haptex-compile", str(KES / "satin.kes.json"), "-o", "s.tact.h5", "-v"], tmp_path, "surface in")
    proc.send_signal(signal.SIGTERM)
    code, out, err = _finish(proc)
    assert code == 143 and err.strip() == "haptex-compile: error: interrupted by SIGTERM", err
    assert list(tmp_path.iterdir()) == []


def test_compile_jobs_stopped_drop_queued_inputs(tmp_path):
    """SIGTERM to the parent of --jobs 2 with three inputs: the two under way stop, the third is
    not begun (the pool's shutdown alone compiled every queued input first), no file is left."""
    names = ["satin", "denim_twill", "wool_suiting"]
    proc = _start(["haptex-compile", *(str(KES / f"{n}.kes.json") for n in names), "--out-dir", "o", "-j", "2",
                   "-v"], tmp_path, "surface in")
    time.sleep(0.5)
    t0 = time.monotonic()
    proc.send_signal(signal.SIGTERM)
    code, out, err = _finish(proc)
    assert code == 143 and "haptex-compile: error: interrupted by SIGTERM" in err and "Traceback" not in err
    assert time.monotonic() - t0 < 5.0  # (measured 0.1-0.2 s; one input takes 5-20 s, and before, 6.4 s)
    assert not (tmp_path / "o").exists() or list((tmp_path / "o").iterdir()) == []


def test_compile_jobs_worker_killed_fails_inputs_in_one_line_each(tmp_path):
    names = ["satin", "denim_twill"]
    proc = _start(["haptex-compile", *(str(KES / f"{n}.kes.json") for n in names), "--out-dir", "o", "-j", "2",
                   "-v"], tmp_path, "surface in")
    children = subprocess.run(["pgrep", "-P", str(proc.pid)], capture_output=True, text=True).stdout.split()
    assert children
    os.kill(int(children[0]), signal.SIGKILL)
    code, out, err = _finish(proc)
    lines = [line for line in err.splitlines() if "INFO" not in line]
    assert code == 1 and len(lines) == 2 and all("a worker process stopped" in line for line in lines), err


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="prctl(PR_SET_PDEATHSIG) is Linux's")
def test_compile_jobs_parent_killed_outright_stops_its_workers(tmp_path):
    """SIGKILL cannot be passed on: before, the orphaned workers compiled every queued input and
    then waited for work for ever."""
    names = ["satin", "denim_twill", "wool_suiting"]
    proc = _start(["haptex-compile", *(str(KES / f"{n}.kes.json") for n in names), "--out-dir", "o", "-j", "2",
                   "-v"], tmp_path, "surface in")
    workers = [int(p) for p in subprocess.run(["pgrep", "-P", str(proc.pid)], capture_output=True, text=True).stdout.split()]
    assert len(workers) == 2
    proc.kill()
    proc.wait()
    deadline = time.monotonic() + 10.0
    alive = workers
    while alive and time.monotonic() < deadline:
        time.sleep(0.1)
        alive = [pid for pid in workers if Path(f"/proc/{pid}").exists()
                 and Path(f"/proc/{pid}/stat").read_text().split()[2] != "Z"]
    assert not alive
    assert not (tmp_path / "o").exists() or list((tmp_path / "o").iterdir()) == []  # temporary files removed
    proc.stdout.close()
    proc.stderr.close()


def test_inspect_into_a_closed_pipe_stops_quietly(tmp_path, asset_path):
    """``haptex-inspect *.tact.h5 | head``: once the reader has gone, the tool stops with
    SIGPIPE's status and nothing on stderr (before: "Broken pipe" as an error line for every
    file after the pipe filled, and status 1)."""
    command = [*tool_argv("haptex-inspect"), *[str(asset_path)] * 120]
    proc = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    assert proc.stdout.readline().startswith(str(asset_path))
    proc.stdout.close()  # as head does after its lines
    err = proc.stderr.read()
    proc.wait(timeout=120)
    assert proc.returncode == 128 + signal.SIGPIPE and err == "", err


def test_play_live_stopped_before_any_sample_says_no_frames(tmp_path, asset_path):
    """--live waiting for its first sample, then SIGTERM: a clean stop whose summary says no frame
    was sent (it read "render median nan µs (p99 nan)"), and the record is kept."""
    proc = subprocess.Popen([*tool_argv("haptex-play"), str(asset_path), "--live", "--device", "null", "--record", "r.h5",
                             "-v"], cwd=tmp_path, stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, env={**os.environ, "PYTHONPATH": str(REPO)})
    for line in proc.stderr:
        if "waiting for the first trajectory sample" in line:
            break
    proc.send_signal(signal.SIGTERM)
    code_, out, err = _finish(proc)
    assert code_ == 0 and "no frames sent" in out and "stopped by SIGTERM" in out and "nan" not in out, out + err
    with h5py.File(tmp_path / "r.h5") as f:
        assert f["frames/t_s"].shape == (0,) and f.attrs["stopped_by"] == "SIGTERM"
