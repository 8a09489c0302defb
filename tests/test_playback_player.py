"""The player end to end through the emulator (pyusb path) on a virtual clock, and the CLI."""
from __future__ import annotations

import io
import math
import subprocess
import sys
import types

import h5py
import numpy as np
import pytest
from click.testing import CliRunner

from playback import protocol
from playback.asset import read_asset
from playback.cli import main
from playback.clock import VirtualClock
from playback.device import load_profile
from playback.errors import DeviceError, InputError
from playback.player import Player
from playback.record import Recorder
from asset_factory import smooth_field, write_test_asset
from playback.trajectory import LiveSource, read_csv_trajectory, sweep_trajectory
from playback.transport import make_transport

T = 0.025


class HookClock(VirtualClock):
    """Virtual clock that runs a hook before the n-th wake-up (fault injection at a given frame)."""

    def __init__(self, hooks=None):
        super().__init__(100.0)
        self.hooks = hooks or {}
        self.calls = 0

    def sleep_until(self, t_s):
        super().sleep_until(t_s)
        fn = self.hooks.get(self.calls)
        self.calls += 1
        if fn is not None:
            fn()


@pytest.fixture(scope="module")
def asset_path(tmp_path_factory):
    return write_test_asset(tmp_path_factory.mktemp("a") / "smooth.tact.h5")


def play(asset_path, source, *, clock=None, record=None, mode="tables", profile=None, render_direct=None, **kw):
    asset = read_asset(asset_path, load_surface=(mode == "direct"))
    profile = profile or load_profile(None)
    clock = clock or HookClock()
    tr, emu = make_transport("sim", profile, clock)
    rec = None
    if record is not None:
        rec = Recorder(record, asset.n_contactors, profile.n_channels, protocol.frame_size(profile.n_channels))
    player = Player(asset, profile, tr, source, clock=clock, mode=mode, recorder=rec, emulator=emu,
                    render_direct=render_direct, **kw)
    return player, emu, clock


def rotating_csv(path, duration=3.0):
    t = np.arange(0.0, duration + 1e-9, 0.005)
    u = 3.0 + 60.0 * t
    v = -1.0 + 20.0 * np.sin(2 * np.pi * 0.5 * t)
    phi = 10.0 + 40.0 * t  # deg, 40 deg/s: the rotation term changes each contactor's velocity
    lines = ["t_s,u_mm,v_mm,phi_deg"] + [f"{a:.17g},{b:.17g},{c:.17g},{d:.17g}" for a, b, c, d in zip(t, u, v, phi)]
    path.write_text("\n".join(lines) + "\n")
    return path


def reference_amplitudes(tc, xy, frame_s=T):
    """Independent of playback: positions from the closed form, velocity as the chord over the frame."""
    def origin(t):
        return 3.0 + 60.0 * t, -1.0 + 20.0 * np.sin(2 * np.pi * 0.5 * t), np.radians(10.0 + 40.0 * t)

    def contactor(t):
        ou, ov, ph = origin(t)
        return ou + np.cos(ph) * xy[:, 0] - np.sin(ph) * xy[:, 1], ov + np.sin(ph) * xy[:, 0] + np.cos(ph) * xy[:, 1]

    u, v = contactor(tc)
    u0, v0 = contactor(tc - frame_s / 2)
    u1, v1 = contactor(tc + frame_s / 2)
    speed = np.hypot(u1 - u0, v1 - v0) / frame_s
    direction = np.degrees(np.arctan2(v1 - v0, u1 - u0))
    return smooth_field(direction, speed, u, v)


def test_recorded_frames_match_reference_within_table_error(tmp_path, asset_path):
    traj = read_csv_trajectory(rotating_csv(tmp_path / "rot.csv"))
    rec = tmp_path / "rec.h5"
    player, emu, _ = play(asset_path, traj, record=rec)
    summary = player.run()
    assert summary.frames_sent == 120 and summary.frames_late == 0 and summary.zero_frame_sent
    asset = read_asset(asset_path)
    with h5py.File(rec) as f:
        fr = f["frames"]
        t = fr["t_s"][:]
        np.testing.assert_allclose(t, (np.arange(120) + 0.5) * T, atol=1e-12)
        worst = 0.0
        for k in range(120):
            e40, e320 = reference_amplitudes(t[k], asset.contactors_mm)
            err = max(np.max(np.abs(fr["a40"][k] - e40) / e40), np.max(np.abs(fr["a320"][k] - e320) / e320))
            worst = max(worst, err)
        assert worst <= asset.tables.max_rel_error
        # What was sent is what the controller accepted, frame by frame, then one zero frame.
        assert len(emu.frames) == 121 and not emu.frames[-1].codes40.any()
        for k in (0, 57, 119):
            np.testing.assert_array_equal(emu.frames[k].codes40, fr["codes"][k, 0])
            assert bytes(fr["packet"][k]) == emu.raw[k]
        assert f.attrs["format"] == "haptex-playback-record"


def test_schedule_has_no_drift_and_counts_late_and_skipped(tmp_path, asset_path):
    profile = load_profile(None)
    clock = HookClock()
    src = sweep_trajectory(80.0, 0.0, 60.0)  # 2400 frames
    player, emu, _ = play(asset_path, src, clock=clock, record=tmp_path / "r.h5", profile=profile)
    # Frame 100: two write timeouts of 10 ms -> sent 15 ms after its deadline (late, not skipped).
    clock.hooks[100] = lambda: emu.inject("timeout", 2)
    # Frame 200: the machine hangs 70 ms before it: frames 200 and 201 are over -> skipped;
    # frame 202 (window started 15 ms ago) is sent, late.
    clock.hooks[200] = lambda: clock.advance(0.070)
    s = player.run()
    assert s.frames_late == 2
    with h5py.File(tmp_path / "r.h5") as f:
        fr = f["frames"]
        idx = fr["index"][:]
        late = fr["late"][:]
        deadline = fr["deadline_s"][:]
        sent = fr["sent_s"][:]
    # Absolute deadlines: frame k is due at k T exactly, whatever happened before.
    np.testing.assert_allclose(deadline, idx * T, atol=1e-9)
    assert late[list(idx).index(100)] == 1
    assert sent[list(idx).index(100)] - deadline[list(idx).index(100)] == pytest.approx(0.015, abs=1e-9)
    # After the 80 ms hang at frame 200 the player skipped the frames whose window had passed
    # and resumed on the original grid.
    assert s.frames_skipped == 2 and 200 not in idx and 201 not in idx and 202 in idx
    assert s.frames_sent + s.frames_skipped == 2400
    # The last frames are on time: no accumulated drift.
    assert np.all(sent[-100:] - deadline[-100:] == pytest.approx(-0.005, abs=1e-9))


def test_unplug_mid_stream_stops_and_keeps_record(tmp_path, asset_path):
    clock = HookClock()
    player, emu, _ = play(asset_path, sweep_trajectory(80.0, 0.0, 5.0), clock=clock, record=tmp_path / "r.h5")
    clock.hooks[30] = emu.unplug
    with pytest.raises(DeviceError, match="disconnected"):
        player.run()
    with h5py.File(tmp_path / "r.h5") as f:
        assert f["frames/t_s"].shape == (30,)
        assert "device error" in f.attrs["stopped_by"]
        assert not f.attrs["zero_frame_sent"]


def test_persistent_stall_stops_after_bounded_retries(asset_path):
    clock = HookClock()
    player, emu, _ = play(asset_path, sweep_trajectory(80.0, 0.0, 5.0), clock=clock)
    clock.hooks[10] = lambda: emu.inject("stall", 100)
    with pytest.raises(DeviceError, match="stalled; gave up after 3 attempts"):
        player.run()
    assert emu.writes == 10 + 3 + 3  # 10 good frames, 3 attempts, 3 for the zero frame (also stalled)


def test_ctrl_c_sends_zero_frame_then_returns(tmp_path, asset_path):
    clock = HookClock()
    player, emu, _ = play(asset_path, sweep_trajectory(80.0, 0.0, 5.0), clock=clock, record=tmp_path / "r.h5")

    def interrupt():
        raise KeyboardInterrupt
    clock.hooks[40] = interrupt
    s = player.run()
    assert s.interrupted and s.zero_frame_sent and s.frames_sent == 40
    assert emu.frames[-2].codes40.any() and not emu.frames[-1].codes40.any() and not emu.frames[-1].codes320.any()
    with h5py.File(tmp_path / "r.h5") as f:
        assert f["frames/a40"].shape == (40, 24) and f.attrs["stopped_by"] == "Ctrl-C"


def fake_render_direct(asset, frame_centres_s, trajectory):
    """Stand-in reference renderer (until haptex_compile.render exists): the exact field along the
    trajectory callable, velocity as the chord over the frame."""
    xy = asset.contactors_mm
    out40, out320 = [], []
    for tc in frame_centres_s:
        pts = []
        for t in (tc - T / 2, tc, tc + T / 2):
            ou, ov, ph = (float(np.asarray(x).reshape(-1)[0]) for x in trajectory(np.array([t])))
            ph = math.radians(ph)
            pts.append((ou + math.cos(ph) * xy[:, 0] - math.sin(ph) * xy[:, 1],
                        ov + math.sin(ph) * xy[:, 0] + math.cos(ph) * xy[:, 1]))
        (u0, v0), (u, v), (u1, v1) = pts
        a40, a320 = smooth_field(np.degrees(np.arctan2(v1 - v0, u1 - u0)), np.hypot(u1 - u0, v1 - v0) / T, u, v)
        out40.append(a40)
        out320.append(a320)
    return np.array(out40), np.array(out320)


def test_direct_mode_same_layout_and_agrees_with_tables(tmp_path, asset_path, monkeypatch):
    mod = types.ModuleType("haptex_compile.render")
    mod.render_direct = fake_render_direct
    monkeypatch.setitem(sys.modules, "haptex_compile.render", mod)
    traj_path = rotating_csv(tmp_path / "rot.csv", duration=1.0)
    recs = {}
    for mode in ("tables", "direct"):
        recs[mode] = tmp_path / f"{mode}.h5"
        player, _, _ = play(asset_path, read_csv_trajectory(traj_path), record=recs[mode], mode=mode)
        player.run()
    with h5py.File(recs["tables"]) as ft, h5py.File(recs["direct"]) as fd:
        assert {k: ft["frames"][k].shape for k in ft["frames"]} == {k: fd["frames"][k].shape for k in fd["frames"]}
        assert fd.attrs["mode"] == "direct"
        a_t, a_d = ft["frames/a40"][:], fd["frames/a40"][:]
        assert np.max(np.abs(a_t - a_d) / a_d) <= read_asset(asset_path).tables.max_rel_error


def test_direct_mode_without_compiler_is_one_line(asset_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "haptex_compile.render", None)  # import fails
    with pytest.raises(InputError, match="--mode direct needs the compiler's reference renderer"):
        play(asset_path, sweep_trajectory(80.0, 0.0, 1.0), mode="direct")
    empty = types.ModuleType("haptex_compile.render")
    monkeypatch.setitem(sys.modules, "haptex_compile.render", empty)
    with pytest.raises(InputError, match="has no render_direct"):
        play(asset_path, sweep_trajectory(80.0, 0.0, 1.0), mode="direct")


def test_live_source_plays_and_fades_out_at_eof(asset_path):
    t = np.arange(0, 1.0, 0.01)
    text = "t_s,u_mm,v_mm,phi_deg\n" + "".join(f"{x:.3f},{50 * x:.4f},0,0\n" for x in t)
    src = LiveSource(io.StringIO(text))
    player, emu, _ = play(asset_path, src)
    s = player.run()
    assert s.stopped_by.startswith("end of live input")
    assert s.frames_sent >= 2 and not emu.frames[-1].codes40.any()


def test_profile_mismatch(asset_path):
    import copy

    from playback.device import DEFAULT_PROFILE, profile_from_dict
    doc = copy.deepcopy(DEFAULT_PROFILE)
    doc["contactors"] = {"count": 25}
    with pytest.raises(InputError, match="24 contactors"):
        play(asset_path, sweep_trajectory(80.0, 0.0, 1.0), profile=profile_from_dict(doc))


# ---------------------------------------------------------------- CLI
def test_cli_record_and_waveforms(tmp_path, asset_path):
    rec = tmp_path / "out.h5"
    r = CliRunner().invoke(main, [str(asset_path), "--device", "sim", "--fast", "--sweep",
                                  "speed=80,direction=30,duration=0.5", "--record", str(rec), "--waveforms"])
    assert r.exit_code == 0, r.output
    assert "20 frames" in r.output
    with h5py.File(rec) as f:
        assert f["frames/a40"].shape == (20, 24) and f["frames/codes"].shape == (20, 2, 24)
        w = f["waveforms/volts"]
        assert w.shape[1] == 24 and w.attrs is not None
        assert np.all(np.abs(w[:]) <= math.sqrt(2) * 2 * 40.0)
    assert not list(tmp_path.glob(".out.h5.tmp*"))  # atomic: no temp left behind


def test_cli_file_sink(tmp_path, asset_path):
    out = tmp_path / "pk.bin"
    r = CliRunner().invoke(main, [str(asset_path), "--device", f"file:{out}", "--fast", "--sweep",
                                  "speed=80,duration=0.25"])
    assert r.exit_code == 0, r.output
    pk = protocol.split_packets(out.read_bytes())
    assert len(pk) == 11 and not protocol.decode_frame(pk[-1]).codes40.any()


def test_cli_errors(tmp_path, asset_path):
    bad = tmp_path / "x.h5"
    bad.write_bytes(b"not hdf5 at all")
    r = CliRunner().invoke(main, [str(bad), "--sweep", "speed=80,duration=1", "--fast"])
    assert r.exit_code == 1 and str(bad) in r.output and len(r.output.strip().splitlines()) == 1
    r = CliRunner().invoke(main, [str(asset_path), "--fast"])
    assert r.exit_code == 2
    r = CliRunner().invoke(main, [str(asset_path), "--sweep", "speed=1,duration=1", "--device", "null", "--waveforms"])
    assert r.exit_code == 2
    r = CliRunner().invoke(main, [str(asset_path), "--sweep", "speed=1", "--fast"])
    assert r.exit_code == 1 and "duration" in r.output


def test_cli_never_overwrites_what_it_reads(tmp_path, asset_path):
    # `--record` naming the asset being played replaced the asset with the record; the raw
    # packet sink likewise. Refused in one line (exit 2), the asset intact.
    before = asset_path.read_bytes()
    args = [str(asset_path), "--device", "null", "--fast", "--sweep", "speed=80,duration=0.25"]
    for extra in (["--record", str(asset_path)], ["--device", f"file:{asset_path}"],
                  ["--record", str(tmp_path / "pk.bin"), "--device", f"file:{tmp_path / 'pk.bin'}"]):
        r = CliRunner().invoke(main, args + extra)
        assert r.exit_code == 2, (extra, r.output)
        lines = r.output.strip().splitlines()
        assert len(lines) == 1 and ("input of this run" in lines[0] or "both write" in lines[0]), lines
    assert asset_path.read_bytes() == before
    assert not (tmp_path / "pk.bin").exists()


def test_record_never_replaces_a_device_pipe_or_socket(tmp_path, asset_path):
    # The record is renamed over its name from a temporary file: `--record /dev/null` would
    # replace the device. A FIFO stands in for it: refused (exit 2), still a FIFO, and the
    # recorder itself refuses it too.
    import os
    import stat

    from playback.record import Recorder

    fifo = tmp_path / "pipe"
    os.mkfifo(fifo)
    r = CliRunner().invoke(main, [str(asset_path), "--device", "null", "--fast", "--sweep", "speed=80,duration=0.25",
                                  "--record", str(fifo)])
    assert r.exit_code == 2 and len(r.output.strip().splitlines()) == 1, r.output
    with pytest.raises(InputError, match="pipe"):
        Recorder(fifo, 24, 24, 64)
    assert stat.S_ISFIFO(os.lstat(fifo).st_mode)


def test_cli_ctrl_c_exit_0(tmp_path, asset_path, monkeypatch):
    calls = {"n": 0}
    orig = VirtualClock.sleep_until

    def sleep_until(self, t):
        calls["n"] += 1
        if calls["n"] == 15:
            raise KeyboardInterrupt
        orig(self, t)
    monkeypatch.setattr(VirtualClock, "sleep_until", sleep_until)
    out = tmp_path / "pk.bin"
    r = CliRunner().invoke(main, [str(asset_path), "--device", f"file:{out}", "--fast", "--sweep", "speed=80,duration=5"])
    assert r.exit_code == 0 and "Ctrl-C" in r.output
    pk = protocol.split_packets(out.read_bytes())
    assert len(pk) == 15 and not protocol.decode_frame(pk[-1]).codes40.any()


def test_cli_usb_absent_one_line(asset_path):
    r = CliRunner().invoke(main, [str(asset_path), "--device", "usb", "--sweep", "speed=80,duration=1"])
    assert r.exit_code == 1 and len(r.output.strip().splitlines()) == 1


def test_import_stays_light():
    out = subprocess.run([sys.executable, "-X", "importtime", "-c", "import playback.cli, playback.player"],
                         capture_output=True, text=True, check=True).stderr
    modules = {line.split("|")[-1].strip().split(".")[0] for line in out.splitlines() if "|" in line}
    for heavy in ("scipy", "cv2", "skimage", "OpenEXR", "matplotlib", "jsonschema", "haptex_compile"):
        assert heavy not in modules


def test_table_renderer_falls_back_to_general_path(tmp_path):
    """A non-finite state and contactors beyond a non-periodic table's edge go through the general
    path (INVALID, OUTSIDE with mirroring); both paths give the same frame where both apply."""
    from playback.interp import INVALID, OUTSIDE, table_amplitudes
    from playback.player import TableRenderer
    from playback.trajectory import MotionState, contactor_kinematics

    from asset_factory import haptex24_layout_mm

    # Grid 0 .. 7.75 mm; the array at 1 mm pitch spans 5 x 3 mm.
    asset = read_asset(write_test_asset(tmp_path / "np.tact.h5", periodic=False, contactors_mm=haptex24_layout_mm(1.0)))
    r = TableRenderer(asset)
    inside = MotionState(0.0, 4.0, 4.0, 20.0, 80.0, 10.0, 30.0)
    outside = MotionState(0.0, 7.0, 4.0, 0.0, 80.0, 0.0, 0.0)  # the right columns are beyond the edge
    bad = MotionState(0.0, float("nan"), 4.0, 0.0, 80.0, 0.0, 0.0)
    assert r.lookup(4.0, 4.0, 20.0, 80.0, 10.0, 30.0) is not None  # the per-frame path applies
    assert r.lookup(7.0, 4.0, 0.0, 80.0, 0.0, 0.0) is None
    for state in (inside, outside):
        got = r.render(0, state)
        want = table_amplitudes(asset.tables, *contactor_kinematics(state, asset.contactors_mm))
        for g, w in zip(got, want):
            np.testing.assert_allclose(g, w, rtol=1e-12)
    assert np.any(r.render(0, outside)[2] & OUTSIDE)
    a40, a320, flags = r.render(0, bad)
    assert not a40.any() and not a320.any() and np.all(flags == INVALID)
