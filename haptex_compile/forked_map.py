"""Independent evaluations of one function, side by side in forked worker processes.

The light search (:func:`haptex_compile.shading_light._refine_light`) solves one reduced image under
dozens of candidate lights, in batches whose members do not depend on each other. Each solve
is small (96-256 px) and mostly Python-level work that holds the GIL, so threads do not run
two at once (measured: 12 solves of a 256 px image, 0.61 s on one thread, 0.67 s on two);
processes do (0.34 s on two, the pool's start included). Forked workers share the parent's
memory copy-on-write: the function and what it holds (the image, its closures) are not
pickled; only the arguments and the results cross between processes.

:func:`call_beside` runs one call in the calling process and another in a forked child at the
same time (the shading solver's two coarse chains, with and without its prior).

Forking is used on Linux only, and not inside a worker process (``haptex-compile --jobs``
compiles several inputs in worker processes, which already take the CPUs). Elsewhere, and
if the workers cannot be started or one dies, the calls run in the calling process: the
results are the same either way.
"""

from __future__ import annotations

import logging
import multiprocessing
import os
import pickle
import signal
import sys
import threading
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from contextlib import contextmanager
from typing import TypeVar

from playback.stop_signals import end_with_parent, worker_signals

LOG = logging.getLogger("haptex.forked_map")
T = TypeVar("T")
U = TypeVar("U")
_FN: Callable | None = None  # the function of the pool this worker belongs to
_IN_CHILD = False  # set in call_beside's child: it forks no further


def worker_count(processes: int | None = None) -> int:
    """The processes a :func:`forked_map` runs: `processes` (None: the CPUs this process may
    run on), or 1 where forking is not used (not Linux, or already in a worker process)."""
    if not sys.platform.startswith("linux") or multiprocessing.parent_process() is not None or _IN_CHILD:
        return 1
    if processes is None:
        processes = len(os.sched_getaffinity(0))
    return max(1, int(processes))


def _quiet_opencv_threads() -> None:
    """OpenCV single-threaded in this process before it forks: a forked worker inherits the
    state of every lock, and one held at the fork by an OpenCV worker thread is never released
    in the child (a CI run hung for good: a light-search worker waited in cv2.resize on such a
    lock). Setting one thread joins OpenCV's workers. Measured, OpenCV on one thread compiled
    the weave and gravel samples in 0.94 and 0.98 of the time (best of 2), the tools' own
    processes and threads taking the cores anyway."""
    cv2 = sys.modules.get("cv2")
    if cv2 is not None and cv2.getNumThreads() != 1:
        cv2.setNumThreads(1)


def _set_fn(fn: Callable, parent_pid: int) -> None:
    global _FN
    _FN = fn
    # Ctrl-C reaches the whole process group: the caller stops the pool, and a worker
    # interrupted on its own would only break it.
    worker_signals()
    end_with_parent(parent_pid)


def _call(args: tuple):
    return _FN(*args)


@contextmanager
def forked_map(fn: Callable, processes: int | None = None) -> Iterator[Callable[[Sequence[tuple]], list]]:
    """A ``map_(args_list) -> list`` of ``fn(*args)`` for each tuple, in order, run by
    :func:`worker_count` (`processes`) forked workers for the life of the context (in the
    calling process when that is 1, or for a single tuple).

    `fn` must be deterministic and must not rely on side effects in the caller: each call
    may run in another process. An exception raised by a call reaches the caller.
    """
    def here(items):
        return [fn(*args) for args in items]

    count = worker_count(processes)
    if count <= 1:
        yield here
        return
    _quiet_opencv_threads()
    # Fork: the workers inherit `fn` as it is (closures included); the initializer's
    # arguments are not pickled under fork.
    pool: ProcessPoolExecutor | None = ProcessPoolExecutor(
        count, mp_context=multiprocessing.get_context("fork"), initializer=_set_fn, initargs=(fn, os.getpid()))

    def map_(items):
        nonlocal pool
        if pool is None or len(items) < 2:
            return here(items)
        try:
            return list(pool.map(_call, items))
        except (BrokenProcessPool, OSError) as exc:  # a worker died or could not start
            LOG.warning("worker processes failed (%s); going on in this process", exc)
            pool.shutdown(wait=False, cancel_futures=True)
            pool = None
            return here(items)

    try:
        yield map_
    finally:
        if pool is not None:
            pool.shutdown(wait=True, cancel_futures=True)


def _reap(pid: int) -> None:
    """Wait for child `pid` to exit (nothing to wait for if the caller's program has set
    SIGCHLD to be ignored: the kernel reaps it)."""
    try:
        os.waitpid(pid, 0)
    except ChildProcessError:
        pass


def _fork_child(there: Callable[[], object]) -> tuple[int, int] | None:
    """Fork a child that runs `there` and sends ``(True, result)`` or ``(False, exception)``
    down a pipe, pickled, then exits; (its pid, the pipe's read end), or None (with a warning)
    if no child could be started."""
    try:
        read_fd, write_fd = os.pipe()
    except OSError as exc:
        LOG.warning("no pipe for a worker process (%s); going on in this process", exc)
        return None
    try:
        pid = os.fork()
    except OSError as exc:
        os.close(read_fd)
        os.close(write_fd)
        LOG.warning("worker process could not start (%s); going on in this process", exc)
        return None
    if pid:
        os.close(write_fd)
        return pid, read_fd
    global _IN_CHILD
    _IN_CHILD = True  # it forks no further
    status = 1
    try:
        os.close(read_fd)
        worker_signals()  # the parent handles Ctrl-C
        try:
            payload = pickle.dumps((True, there()), pickle.HIGHEST_PROTOCOL)
        except BaseException as exc:  # noqa: BLE001 - handed to the parent
            try:
                payload = pickle.dumps((False, exc), pickle.HIGHEST_PROTOCOL)
            except Exception:  # an exception that does not pickle
                payload = pickle.dumps((False, RuntimeError(f"{type(exc).__name__}: {exc}")))
        with os.fdopen(write_fd, "wb") as out:
            out.write(payload)
        status = 0
    finally:
        os._exit(status)  # no atexit handlers, no flushing of the parent's buffers


def call_beside(here: Callable[[], T], there: Callable[[], U], processes: int | None = None) -> tuple[T, U]:
    """``(here(), there())``, with `there` run in a forked child while this process runs
    `here` (where :func:`worker_count` of `processes` is at least 2).

    One fork and a pipe, no pool: for two independent calls of a fraction of a second each
    (a plain image's two coarse chains in the shading solver: about 20 ms of overhead, the
    fork and the child's first writes to memory it shares with this process). `here` keeps
    this process's warm caches: give it the longer call. As in :func:`forked_map`, the calls
    run one after the other where that count is 1, and `there` runs here if the child cannot
    be started or dies; an exception raised by either call reaches the caller. `there` must
    be deterministic, and its result picklable.
    """
    forking = worker_count(processes) > 1
    if forking:
        _quiet_opencv_threads()
    child = _fork_child(there) if forking else None
    if child is None:
        return here(), there()
    pid, read_fd = child
    with os.fdopen(read_fd, "rb") as src:
        try:
            first = here()
            payload = src.read()  # read before waiting: the result may outgrow the pipe
        except BaseException:
            try:
                os.kill(pid, signal.SIGKILL)
            except ProcessLookupError:  # gone already
                pass
            _reap(pid)
            raise
    # The child has answered; its exit (unmapping its copy of this process) takes about as
    # long as the fork, so a thread waits for it (measured: 9 ms of a 1 s solve).
    threading.Thread(target=_reap, args=(pid,), name="haptex-reap", daemon=True).start()
    if not payload:  # the child died before it could answer
        LOG.warning("worker process failed; going on in this process")
        return first, there()
    ok, value = pickle.loads(payload)
    if not ok:
        raise value
    return first, value
