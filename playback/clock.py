"""Clocks for the frame scheduler: the real monotonic clock, and a virtual one for tests."""
from __future__ import annotations

import time


class MonotonicClock:
    """``time.monotonic`` seconds; :meth:`sleep_until` sleeps, then busy-waits the last ~2 ms.

    Deadlines are absolute, so sleep overshoot never accumulates into drift. The final stretch
    is a busy wait without yielding: on a loaded machine ``sched_yield`` (``time.sleep(0)``)
    can hand the CPU away for a whole time slice (several ms).
    """

    virtual = False

    def __init__(self, spin_s: float = 0.002) -> None:
        self.spin_s = spin_s

    def now(self) -> float:
        """Seconds on the monotonic clock."""
        return time.monotonic()

    def sleep_until(self, t_s: float) -> None:
        """Return at (or just after) monotonic time `t_s`; immediately if it has passed."""
        while True:
            remaining = t_s - time.monotonic()
            if remaining <= 0:
                return
            if remaining > self.spin_s:
                time.sleep(remaining - self.spin_s)  # the OS may oversleep; the spin absorbs it


class VirtualClock:
    """A clock that only moves when told: sleeping jumps to the deadline, no real time passes.

    Tests and ``--fast`` runs use it; a simulated stall can :meth:`advance` it.
    """

    virtual = True

    def __init__(self, start_s: float = 0.0) -> None:
        self.t = float(start_s)

    def now(self) -> float:
        """Current virtual time (s)."""
        return self.t

    def sleep_until(self, t_s: float) -> None:
        """Jump forward to `t_s` (never backwards)."""
        if t_s > self.t:
            self.t = float(t_s)

    def advance(self, dt_s: float) -> None:
        """Let `dt_s` seconds pass (e.g. a USB timeout in the emulator)."""
        self.t += max(0.0, float(dt_s))
