"""Benchmark of haptex-play: render time per frame, and timing over simulated and real-clock runs.

Run ``python bench/bench_playback.py [--quick]``. Prints a markdown table. Baselines measured in
the same run: scipy's RegularGridInterpolator on the same 4-D table (a generic library lookup) and,
if the compiler provides it, the reference renderer ``haptex_compile.render.render_direct``.
"""
from __future__ import annotations

import argparse
import importlib
import tempfile
import time
from pathlib import Path

import sys

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # the repo root, for tests.asset_factory

from playback import protocol
from playback.asset import read_asset
from playback.clock import MonotonicClock, VirtualClock
from playback.device import load_profile
from playback.interp import table_amplitudes
from playback.player import Player
from playback.record import Recorder
from playback.trajectory import MotionState, contactor_kinematics, sweep_trajectory
from playback.transport import make_transport
from tests.asset_factory import write_test_asset

FRAME_US = 25000.0


def _layout(n: int) -> np.ndarray:
    side = int(np.ceil(np.sqrt(n)))
    x, y = np.meshgrid(np.arange(side) * 0.5, np.arange(side) * 0.5)
    return np.column_stack([x.ravel(), y.ravel()])[:n] - side * 0.25


def _time_frames(fn, n_frames: int) -> np.ndarray:
    out = np.empty(n_frames)
    for k in range(n_frames):
        t0 = time.perf_counter()
        fn(k)
        out[k] = time.perf_counter() - t0
    return out * 1e6


def _render_fn(tables, xy):
    def fn(k):
        st = MotionState(k * 0.025, 0.3 * k, 0.1 * k, 7.0 * k, 80.0, 10.0, 30.0)
        u, v, s, d = contactor_kinematics(st, xy)
        return table_amplitudes(tables, u, v, s, d)
    return fn


def _scipy_fn(tables, xy):
    from scipy.interpolate import RegularGridInterpolator

    nd, ns, nj, ni = tables.shape
    axes = (np.append(tables.direction_deg, 180.0), np.log(tables.speed_mm_s), np.arange(nj + 1.0), np.arange(ni + 1.0))
    a = np.concatenate([tables.a40, tables.a40[:1]], axis=0)
    a = np.concatenate([a, a[:, :, :1]], axis=2)
    a = np.concatenate([a, a[:, :, :, :1]], axis=3)
    rgi = RegularGridInterpolator(axes, a, bounds_error=False, fill_value=None)
    inv = np.linalg.inv(tables.grid_basis_mm.T)

    def fn(k):
        st = MotionState(k * 0.025, 0.3 * k, 0.1 * k, 7.0 * k, 80.0, 10.0, 30.0)
        u, v, s, d = contactor_kinematics(st, xy)
        ij = inv @ np.vstack([u - tables.origin_mm[0], v - tables.origin_mm[1]])
        pts = np.column_stack([np.mod(d, 180.0), np.log(np.clip(s, tables.speed_mm_s[0], tables.speed_mm_s[-1])),
                               np.mod(ij[1], nj), np.mod(ij[0], ni)])
        return rgi(pts)
    return fn


def _run_player(asset, seconds: float, clock) -> dict:
    profile = load_profile(None)
    transport, emu = make_transport("sim", profile, clock)
    with tempfile.TemporaryDirectory() as d:
        rec = Recorder(Path(d) / "r.h5", asset.n_contactors, profile.n_channels, protocol.frame_size(profile.n_channels))
        player = Player(asset, profile, transport, sweep_trajectory(80.0, 20.0, seconds), clock=clock, recorder=rec,
                        emulator=emu)
        w0 = time.monotonic()
        s = player.run()
        wall = time.monotonic() - w0
    return {"summary": s, "wall_s": wall, "accepted": len(emu.frames)}


def run(quick: bool = False) -> str:
    """Run the benchmark; returns the markdown report."""
    n_frames = 2000 if quick else 10000
    rows = []
    with tempfile.TemporaryDirectory() as d:
        asset_path = write_test_asset(Path(d) / "bench.tact.h5")
        asset = read_asset(asset_path, load_surface=True)
    tables = asset.tables
    _ = tables.interpolator
    stats = {}
    for n in (24, 1000):
        xy = _layout(n)
        ours = _time_frames(_render_fn(tables, xy), n_frames)
        try:
            base = _time_frames(_scipy_fn(tables, xy), max(200, n_frames // 5))
        except ImportError:
            base = np.array([np.nan])
        stats[n] = (ours, base)
        target = 100.0 if n == 24 else 1000.0
        rows.append(f"| render/frame, {n} contactors (tables) | {np.median(ours):.1f} µs | {np.percentile(ours, 99):.1f} µs "
                    f"| {np.median(ours) / FRAME_US:.4f} | target ≤ {target:.0f} µs: {'met' if np.median(ours) <= target else 'MISSED'} "
                    f"| {np.median(ours) / np.median(base):.2f}x scipy RGI |")
        rows.append(f"| baseline: scipy RegularGridInterpolator, {n} contactors | {np.median(base):.1f} µs "
                    f"| {np.percentile(base, 99):.1f} µs | {np.median(base) / FRAME_US:.4f} | | 1.00x |")
    try:
        render_direct = getattr(importlib.import_module("haptex_compile.render"), "render_direct")
        traj = sweep_trajectory(80.0, 20.0, 5.0)
        times = []
        for k in range(5 if quick else 20):
            t0 = time.perf_counter()
            render_direct(asset, np.array([0.0125 + 0.025 * k]), traj.position)
            times.append((time.perf_counter() - t0) * 1e6)
        med = float(np.median(times))
        rows.append(f"| baseline: reference renderer render_direct, 24 contactors | {med:.0f} µs | {np.max(times):.0f} µs (max) "
                    f"| {med / FRAME_US:.4f} | | tables are {med / np.median(stats[24][0]):.0f}x faster |")
    except (ImportError, AttributeError) as exc:
        rows.append(f"| baseline: reference renderer render_direct | not available ({type(exc).__name__}) | | | | |")

    sim = _run_player(asset, 60.0, VirtualClock())
    s = sim["summary"]
    rows.append(f"| 60 s simulated run (virtual clock, sim via pyusb) | {s.frames_sent} frames sent, {sim['accepted']} accepted "
                f"| late {s.frames_late}, skipped {s.frames_skipped} | drift {s.drift_ms:.3f} ms "
                f"| render median {s.render_us_median:.0f} µs | wall {sim['wall_s']:.1f} s |")
    real_s = 3.0 if quick else 60.0
    real = _run_player(asset, real_s, MonotonicClock())
    s = real["summary"]
    rows.append(f"| {real_s:.0f} s real-clock run (monotonic, sim via pyusb) | {s.frames_sent} frames "
                f"| late {s.frames_late}, skipped {s.frames_skipped} | drift {s.drift_ms:.3f} ms, max wake error "
                f"{s.wake_error_ms_max:.2f} ms | render median {s.render_us_median:.0f} µs, p99 {s.render_us_p99:.0f} µs "
                f"| latency median {s.latency_us_median:.0f} µs |")
    header = ("| measurement | median | p99 / detail | ratio to 25 ms frame | target | vs baseline |\n"
              "| --- | --- | --- | --- | --- | --- |")
    note = (f"\nTables: {tables.shape} (direction, speed, j, i), synthetic smooth asset; "
            f"{n_frames} frames timed per layout; render = kinematics + interpolation per frame.\n")
    return "### haptex-play benchmark" + (" (quick)" if quick else "") + "\n\n" + header + "\n" + "\n".join(rows) + "\n" + note


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="fewer frames and a 3 s real-clock run (< 60 s)")
    print(run(quick=ap.parse_args().quick))
