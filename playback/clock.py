"""Clocks for the frame scheduler: the real monotonic clock, and a virtual one for tests.

Both have the same two waits, used once each per frame by :class:`playback.player.Player`:

* :meth:`sleep_until` — the coarse wake-up: give the CPU away until about then (the OS may wake
  the process late; the player leaves a margin for that);
* :meth:`wait_until` — the precise one before a packet is sent: sleep until shortly before,
  then busy-wait to the exact time.
"""
from __future__ import annotations

import time
from typing import Callable


class MonotonicClock:
    """``time.monotonic`` seconds.

    Deadlines are absolute, so a late wake-up never accumulates into drift.

    Parameters
    ----------
    spin_s : float
        How long before a :meth:`wait_until` deadline the OS sleep ends and the busy-wait
        begins. The busy-wait does not yield: on a loaded machine ``sched_yield``
        (``time.sleep(0)``) can hand the CPU away for a whole time slice (several ms).
    """

    virtual = False

    def __init__(self, spin_s: float = 0.001) -> None:
        self.spin_s = spin_s

    def now(self) -> float:
        """Seconds on the monotonic clock."""
        return time.monotonic()

    def sleep_until(self, t_s: float) -> None:
        """Sleep until about `t_s` (never earlier; later by the OS's wake-up latency)."""
        remaining = t_s - time.monotonic()
        if remaining > 0:
            time.sleep(remaining)

    def wait_until(self, t_s: float) -> None:
        """Return at (or just after) `t_s`: OS sleep to ``t_s - spin_s``, then busy-wait."""
        remaining = t_s - time.monotonic()
        if remaining > self.spin_s:
            time.sleep(remaining - self.spin_s)  # an oversleep up to spin_s is absorbed by the spin
        while time.monotonic() < t_s:
            pass


class VirtualClock:
    """A clock that only moves when told: sleeping jumps to the deadline, no real time passes.

    Tests, the benchmark's long drift checks and ``--fast`` runs use it; a simulated stall can
    :meth:`advance` it.

    Parameters
    ----------
    start_s : float
        Initial time.
    oversleep : callable, optional
        ``oversleep() -> seconds >= 0`` added to every :meth:`sleep_until` (a simulated OS
        wake-up latency, e.g. random), so the scheduler's tolerance to late wake-ups can be
        exercised on simulated time. :meth:`wait_until` stays exact, as a busy-wait is.
    """

    virtual = True

    def __init__(self, start_s: float = 0.0, oversleep: Callable[[], float] | None = None) -> None:
        self.t = float(start_s)
        self.oversleep = oversleep

    def now(self) -> float:
        """Current virtual time (s)."""
        return self.t

    def sleep_until(self, t_s: float) -> None:
        """Jump forward to `t_s` (never backwards), plus the simulated oversleep if any."""
        if t_s > self.t:
            self.t = float(t_s)
            if self.oversleep is not None:
                self.t += max(0.0, float(self.oversleep()))

    def wait_until(self, t_s: float) -> None:
        """Jump forward to exactly `t_s` (never backwards)."""
        if t_s > self.t:
            self.t = float(t_s)

    def advance(self, dt_s: float) -> None:
        """Let `dt_s` seconds pass (e.g. a USB timeout in the emulator)."""
        self.t += max(0.0, float(dt_s))
