"""The scheduler's timing: absolute deadlines (no drift), what "late" means, GC and priority handling.

Frame k's window starts at D_k = t0 + k T; its packet is due at S_k = D_k - lead and the player
wakes at S_k - prep. On simulated time with a simulated OS oversleep o_k at the wake-up, the
packet therefore leaves at S_k + max(0, o_k - prep) exactly; it is late iff that is after D_k,
i.e. o_k > prep + lead.
"""
from __future__ import annotations

import gc
import logging
import os

import numpy as np
import pytest

from asset_factory import write_test_asset
from playback.asset import read_asset
from playback.clock import MonotonicClock, VirtualClock
from playback.device import load_profile
from playback.player import Player
from playback.trajectory import sweep_trajectory
from playback.transport import Transport

T = 0.025
LEAD = 0.005
PREP = 0.002


class StampSink(Transport):
    """Accepts packets and notes the clock time and the GC state at each one."""

    name = "stamp"

    def __init__(self, clock) -> None:
        super().__init__()
        self.clock = clock
        self.times: list[float] = []
        self.gc_enabled: list[bool] = []

    def send(self, packet: bytes) -> None:  # noqa: D102
        self.times.append(self.clock.now())
        self.gc_enabled.append(gc.isenabled())
        self.packets_sent += 1


class ScriptedOversleep:
    """Oversleep per wake-up from a table (0 elsewhere); remembers what it handed out."""

    def __init__(self, table: dict[int, float] | None = None, rng: np.random.Generator | None = None,
                 p: float = 0.0, high: float = 0.0) -> None:
        self.table = table or {}
        self.rng, self.p, self.high = rng, p, high
        self.drawn: list[float] = []

    def __call__(self) -> float:
        k = len(self.drawn)
        o = self.table.get(k, 0.0)
        if self.rng is not None and self.rng.random() < self.p:
            o = float(self.rng.uniform(0.0, self.high))
        self.drawn.append(o)
        return o


@pytest.fixture(scope="module")
def asset(tmp_path_factory):
    return read_asset(write_test_asset(tmp_path_factory.mktemp("timing") / "a.tact.h5"))


def run(asset, seconds, clock, **kw):
    sink = StampSink(clock)
    player = Player(asset, load_profile(None), sink, sweep_trajectory(80.0, 20.0, seconds), clock=clock,
                    lead_ms=LEAD * 1e3, prep_ms=PREP * 1e3, **kw)
    return player.run(), sink


def test_ten_minutes_on_simulated_time_do_not_drift(asset):
    """24 000 frames from t = 1e6 s (where a float has ~1e-10 s resolution), with random
    oversleeps up to 6.5 ms (past the 2 ms prep, short of prep + lead): every send is at S_k, or
    exactly o_k - prep after it, and the last frames are as punctual as the first."""
    start = 1.0e6
    over = ScriptedOversleep(rng=np.random.default_rng(7), p=0.03, high=0.0065)
    s, sink = run(asset, 600.0, VirtualClock(start, oversleep=over))
    n = 24000
    assert s.frames_sent == n and s.frames_skipped == 0 and s.frames_late == 0
    sent = np.asarray(sink.times[:n])  # then the all-zero frame
    due = start + (np.arange(n) + 1) * T - LEAD  # t0 = start + T
    o = np.asarray(over.drawn[:n])
    np.testing.assert_allclose(sent - due, np.maximum(0.0, o - PREP), rtol=0, atol=1e-9)
    assert (o > PREP).sum() > 100  # the margin was really exercised
    assert s.drift_ms == pytest.approx(0.0, abs=1e-6)
    assert s.send_error_ms_max == pytest.approx((o.max() - PREP) * 1e3, abs=1e-6)
    assert s.lateness_ms_max == pytest.approx((o.max() - PREP - LEAD) * 1e3, abs=1e-6)


def test_late_means_accepted_after_the_window_started(asset):
    # Frame 10 wakes 1 ms too late to make its window start, frame 20 1 ms early enough,
    # frame 30 so late that its whole window is over: skipped, and frame 31, whose window
    # started 1 ms before that wake-up, is sent at once, late.
    over = ScriptedOversleep({10: PREP + LEAD + 0.001, 20: PREP + LEAD - 0.001, 30: PREP + LEAD + T + 0.001})
    s, sink = run(asset, 2.0, VirtualClock(50.0, oversleep=over))
    assert s.frames_late == 2 and s.frames_skipped == 1 and s.frames_sent == 79
    assert s.lateness_ms_max == pytest.approx(1.0, abs=1e-6)
    assert s.send_error_ms_max == pytest.approx((LEAD + 0.001) * 1e3, abs=1e-6)


def test_gc_is_paused_while_playing_and_restored(asset):
    assert gc.isenabled()
    s, sink = run(asset, 0.5, VirtualClock())
    assert s.frames_sent == 20 and not any(sink.gc_enabled)
    assert gc.isenabled() and gc.get_freeze_count() == 0


class ListHandler(logging.Handler):
    def __init__(self) -> None:
        super().__init__(logging.DEBUG)
        self.records: list[logging.LogRecord] = []

    def emit(self, record: logging.LogRecord) -> None:  # noqa: D102
        self.records.append(record)


def test_realtime_refused_falls_back_silently(asset, monkeypatch):
    def refuse(*args):
        raise PermissionError(1, "Operation not permitted")
    monkeypatch.setattr(os, "sched_setscheduler", refuse)
    monkeypatch.setattr(os, "setpriority", refuse)
    # The CLI tests configure the "haptex" logger (no propagation), so listen on it directly.
    log = logging.getLogger("haptex.play")
    handler = ListHandler()
    log.addHandler(handler)
    old_level = log.level
    log.setLevel(logging.INFO)  # setLevel, not the attribute: it clears the loggers' level caches
    try:
        s, _ = run(asset, 0.1, MonotonicClock(), realtime=True, max_frames=3)
    finally:
        log.removeHandler(handler)
        log.setLevel(old_level)
    assert s.frames_sent == 3 and s.scheduling == "normal"
    msgs = [(r.levelno, r.getMessage()) for r in handler.records]
    assert any("SCHED_FIFO" in m and "not available" in m for _, m in msgs)  # said with -v ...
    assert all(level <= logging.INFO for level, m in msgs if "priority" in m or "SCHED" in m)  # ... only with -v


def test_realtime_granted_is_restored(asset, monkeypatch):
    calls = []
    monkeypatch.setattr(os, "sched_setscheduler", lambda *a: calls.append(a))
    s, _ = run(asset, 0.1, MonotonicClock(), realtime=True, max_frames=2)
    assert s.scheduling.startswith("SCHED_FIFO")
    assert [c[1] for c in calls] == [os.SCHED_FIFO, os.sched_getscheduler(0)]  # set, then restored
    # The virtual clock never asks (nothing real-time about a dry run).
    calls.clear()
    s, _ = run(asset, 0.1, VirtualClock(), realtime=True)
    assert calls == [] and s.scheduling == "normal"


def test_cli_timing_options_reach_the_record(tmp_path):
    import h5py
    from click.testing import CliRunner

    from playback.cli import main

    path = write_test_asset(tmp_path / "a.tact.h5")
    rec = tmp_path / "r.h5"
    r = CliRunner().invoke(main, [str(path), "--fast", "--sweep", "speed=80,duration=0.25", "--lead-ms", "4",
                                  "--prep-ms", "1.5", "--no-realtime", "--record", str(rec)])
    assert r.exit_code == 0, r.output
    assert "0 late" in r.output
    with h5py.File(rec) as f:
        assert f.attrs["lead_ms"] == pytest.approx(4.0) and f.attrs["prep_ms"] == pytest.approx(1.5)
        assert f.attrs["scheduling"] == "normal"
        # On simulated time every packet leaves exactly at its due time, lead before its window.
        np.testing.assert_allclose(f["frames/sent_s"][()] - f["frames/deadline_s"][()], -0.004, atol=1e-9)
    r = CliRunner().invoke(main, [str(path), "--fast", "--sweep", "speed=80,duration=0.25", "--prep-ms", "-1"])
    assert r.exit_code == 2
