"""Stop signals: SIGTERM and SIGHUP stop the tools the way Ctrl-C does.

Python turns SIGINT (Ctrl-C) into :class:`KeyboardInterrupt`, which the tools handle: the
player sends an all-zero frame and finishes its record, the compiler and the writers remove
their temporary files. SIGTERM (``kill``, a supervisor, a batch system) and SIGHUP (the
terminal closed) kill a Python process outright, with none of that. Measured before this
module: ``haptex-play`` sent SIGTERM during a sweep sent no zero frame (the array kept the last
frame until the device's TTL), lost the frames it had recorded and left its ``.NAME.tmpPID``
file behind. Under :func:`stop_signals_raise` they raise :class:`StopRequested`, a
``KeyboardInterrupt``, so every path that handles Ctrl-C handles them too.

:func:`deferred` holds every stop signal (Ctrl-C included) back for the few steps that must
finish once a stop has begun: a second Ctrl-C, pressed while the zero frame was being sent,
would otherwise interrupt that send.
"""
from __future__ import annotations

import os
import signal
import sys
import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager

STOP_SIGNALS = ("SIGTERM", "SIGHUP")  # (SIGHUP is absent on Windows: skipped there)
_held: list[list[str]] = []  # one list per active deferred() (innermost last)


class StopRequested(KeyboardInterrupt):
    """A stop signal other than Ctrl-C, raised where the main thread is."""

    def __init__(self, signal_name: str = "SIGTERM") -> None:
        super().__init__(signal_name)
        self.signal_name = signal_name


def stop_reason(exc: BaseException) -> str:
    """What stopped the run: ``"Ctrl-C"`` or the signal's name (``"SIGTERM"``)."""
    return exc.signal_name if isinstance(exc, StopRequested) else "Ctrl-C"


def exit_status(exc: BaseException) -> int:
    """The shell's status for a process stopped by this signal: 128 + its number (130 for Ctrl-C)."""
    name = exc.signal_name if isinstance(exc, StopRequested) else "SIGINT"
    return 128 + int(getattr(signal, name))


def _raise_stop(signum: int, frame: object) -> None:
    raise StopRequested(signal.Signals(signum).name)


def _hold(signum: int, frame: object) -> None:
    _held[-1].append(signal.Signals(signum).name)


def _in_main_thread() -> bool:
    return threading.current_thread() is threading.main_thread()


def set_handlers(handler: Callable[[int, object], None], names: tuple[str, ...] = STOP_SIGNALS
                 ) -> dict[signal.Signals, object]:
    """Give the signals `names` (those this platform has) `handler`, except those ignored (as
    ``nohup`` ignores SIGHUP: they stay ignored); their previous handlers, to put back."""
    previous = {}
    for sig in (getattr(signal, n) for n in names if hasattr(signal, n)):
        if signal.getsignal(sig) is not signal.SIG_IGN:
            previous[sig] = signal.signal(sig, handler)
    return previous


def _restore(previous: dict[signal.Signals, object]) -> None:
    for sig, handler in previous.items():
        signal.signal(sig, handler)


@contextmanager
def stop_signals_raise() -> Iterator[None]:
    """SIGTERM and SIGHUP raise :class:`StopRequested` in the main thread while in the context
    (the previous handlers come back after it). Signals the process was started with ignored
    stay ignored. Outside the main thread, nothing changes: Python runs signal handlers there
    only."""
    if not _in_main_thread():
        yield
        return
    previous = set_handlers(_raise_stop)
    try:
        yield
    finally:
        _restore(previous)


def exit_now(signum: int, frame: object = None) -> None:
    """End this process at once, quietly, with the shell's status for signal `signum` (a
    signal handler)."""
    os._exit(128 + signum)


def worker_signals(stop: Callable[[int, object], None] = exit_now) -> None:
    """Signals in a worker process: Ctrl-C, which reaches the whole process group, is ignored
    (the parent handles it, and stops its workers), and SIGTERM and SIGHUP go to `stop`. The
    default ends the worker at once (:func:`exit_now`), for workers that hold no files of
    their own. Inherited from a parent under :func:`stop_signals_raise`, they would raise
    :class:`StopRequested` instead, and a pool worker waiting for work prints multiprocessing's
    traceback of it. The parent notices a lost worker (and is being stopped itself when the
    signal went to the whole process group)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    set_handlers(stop)


PR_SET_PDEATHSIG = 1  # prctl(2) option: a signal for this process when its parent dies


def end_with_parent(parent_pid: int, sig: int = signal.SIGTERM) -> None:
    """In a worker process (Linux): be sent `sig` when the parent dies, even by SIGKILL, which
    the parent cannot pass on. Orphaned pool workers otherwise went on: measured, a
    ``haptex-compile -j 2`` parent killed with three inputs queued left its two workers to
    compile all three, then wait for work for ever. Elsewhere (or if prctl is unavailable) a
    no-op. Call it from the worker; `parent_pid` is the parent's pid as the parent saw it, to
    catch a parent already gone before the call."""
    if not sys.platform.startswith("linux"):
        return
    import ctypes

    try:
        libc = ctypes.CDLL(None, use_errno=True)
        if libc.prctl(PR_SET_PDEATHSIG, int(sig), 0, 0, 0) != 0:
            return
    except (OSError, AttributeError):
        return
    if os.getppid() != parent_pid:  # gone between the fork and the call
        os.kill(os.getpid(), sig)


@contextmanager
def deferred() -> Iterator[list[str]]:
    """Hold back SIGINT, SIGTERM and SIGHUP while in the context: nothing is raised, and the
    names of the signals that arrived are in the yielded list (the caller decides what they
    mean: a run already stopping can ignore them). Nested uses hold into the innermost list.
    Outside the main thread the list stays empty and signals act as usual."""
    held: list[str] = []
    if not _in_main_thread():
        yield held
        return
    previous = {}
    _held.append(held)
    try:
        # (SIGTERM/SIGHUP at their default, without stop_signals_raise around, would kill the
        # process: held too, as the caller asks)
        previous = set_handlers(_hold, ("SIGINT",) + STOP_SIGNALS)
        yield held
    finally:
        _restore(previous)
        _held.pop()
