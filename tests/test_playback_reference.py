"""Frames played through the emulated device equal the reference renderer's within the tables' stated error.

A tiny surface (64 x 64 px Brownian, 2 x 2 contactors, 2 directions x 2 speeds) is compiled
with the compiler's own API, so its tables and their stated error (measured by the compiler
against ``haptex_compile.render.render_direct`` at random points) belong together. The same
sweep is then played twice through the emulator (pyusb path) and recorded: ``--mode tables``
and ``--mode direct`` (which calls ``render_direct``). The error is the compiler's metric
(``haptex_compile.compile.relative_errors``: the (a40, a320) pair in threshold units).

The sweeps run at node speeds and directions, where the only interpolation is in space, so
every frame must be within the stated maximum and the frames' RMS within the stated RMS. (The
stated figures are statistics over random check points, not bounds: a stroke between direction
*and* speed nodes of this deliberately coarse 2 x 2 table can exceed them.)
"""
from __future__ import annotations

import h5py
import numpy as np
import pytest

from playback import protocol
from playback.asset import read_asset
from playback.clock import VirtualClock
from playback.device import DEFAULT_PROFILE, profile_from_dict
from playback.player import Player
from playback.record import Recorder
from playback.trajectory import sweep_trajectory
from playback.transport import make_transport

from asset_factory import TINY_SCENE as SCENE
from asset_factory import TINY_SPEC as SPEC


@pytest.fixture(scope="module")
def compiled(tmp_path_factory):
    compile_mod = pytest.importorskip("haptex_compile.compile")
    from haptex_compile.io_scene import parse_scene
    from haptex_compile.sources import SourceOptions

    out = tmp_path_factory.mktemp("ref") / "tiny.tact.h5"
    compile_mod.compile_source(SPEC, out, parse_scene(SCENE, "tiny.toml"), SourceOptions())
    return out


def play(path, mode, traj, record):
    asset = read_asset(path, load_surface=(mode == "direct"))
    n = asset.n_contactors
    profile = profile_from_dict({**DEFAULT_PROFILE, "contactors": {"count": n, "n_channels": n, "channel": list(range(n))}})
    clock = VirtualClock()
    transport, emu = make_transport("sim", profile, clock)
    rec = Recorder(record, n, profile.n_channels, protocol.frame_size(profile.n_channels))
    summary = Player(asset, profile, transport, traj, clock=clock, mode=mode, recorder=rec, emulator=emu).run()
    assert summary.frames_late == 0 and summary.zero_frame_sent
    with h5py.File(record) as f:
        fr = f["frames"]
        out = {k: fr[k][()] for k in ("t_s", "a40", "a320", "codes")}
    # What the controller accepted is what was recorded as sent.
    accepted = np.stack([np.stack([a.codes40, a.codes320]) for a in emu.frames[:-1]])
    np.testing.assert_array_equal(accepted, out["codes"])
    return out


@pytest.mark.parametrize("speed, direction", [(80.0, 0.0), (40.0, 90.0)])
def test_emulated_frames_match_reference_renderer(compiled, tmp_path, speed, direction):
    from haptex_compile.compile import relative_errors
    from haptex_compile.render import asset_model

    traj = sweep_trajectory(speed, direction, 0.15, u0_mm=0.6, v0_mm=0.6)  # 6 frames
    tab = play(compiled, "tables", traj, tmp_path / "tables.h5")
    ref = play(compiled, "direct", traj, tmp_path / "direct.h5")
    np.testing.assert_array_equal(tab["t_s"], ref["t_s"])
    asset = read_asset(compiled, load_surface=True)
    model = asset_model(asset)[1]
    err = relative_errors(model, tab["a40"], tab["a320"], ref["a40"], ref["a320"])
    assert err.shape == (6, 4) and np.all(np.isfinite(err))
    assert err.max() <= asset.tables.max_rel_error
    assert np.sqrt(np.mean(err ** 2)) <= asset.tables.rms_rel_error
