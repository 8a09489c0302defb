"""forked_map and call_beside: the same results, in order, whether the calls run in forked
workers or in the calling process (one conformance suite for both)."""
from __future__ import annotations

import logging
import os
import signal
import sys
import threading

import numpy as np
import pytest

from haptex_compile.forked_map import call_beside, forked_map, worker_count

linux = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="forked workers are used on Linux only")
MODES = [1, pytest.param(2, marks=linux)]


@pytest.mark.parametrize("processes", MODES)
def test_results_come_back_in_order_and_equal_to_direct_calls(processes):
    rng = np.random.default_rng(0)
    data = rng.random((64, 64))  # held by the closure, not passed: the workers inherit it

    def fn(i, scale):
        return float(np.sum(np.roll(data, i, axis=0)[:8] * scale)), i

    items = [(i, 0.5 * i) for i in range(9)]
    with forked_map(fn, processes) as map_:
        assert map_(items) == [fn(*args) for args in items]
        assert map_(items[:1]) == [fn(*items[0])]
        assert map_([]) == []


@pytest.mark.parametrize("processes", MODES)
def test_an_error_in_a_call_reaches_the_caller(processes):
    def fn(x):
        if x == 3:
            raise ValueError("three")
        return x

    with forked_map(fn, processes) as map_:
        with pytest.raises(ValueError, match="three"):
            map_([(1,), (3,), (5,)])


@linux
def test_two_workers_are_other_processes_that_fork_no_further():
    parent = os.getpid()
    with forked_map(lambda i: (os.getpid(), worker_count(), signal.getsignal(signal.SIGINT) == signal.SIG_IGN), 2) as map_:
        out = map_([(i,) for i in range(6)])
    assert all(pid != parent for pid, _, _ in out)
    # Inside a worker (as under haptex-compile --jobs) nothing forks again.
    assert all(count == 1 for _, count, _ in out)
    # Ctrl-C is the caller's to handle (it stops the pool): the workers ignore it.
    assert all(ignored for _, _, ignored in out)


def test_one_process_runs_in_the_caller():
    parent = os.getpid()
    with forked_map(lambda i: os.getpid(), 1) as map_:
        assert map_([(0,), (1,)]) == [parent, parent]
    assert worker_count(1) == 1


@linux
def test_a_worker_that_dies_leaves_the_calls_to_the_caller(caplog, monkeypatch):
    monkeypatch.setattr(logging.getLogger("haptex"), "propagate", True)  # the CLI tests turn it off
    parent = os.getpid()

    def fn(x):
        if os.getpid() != parent:
            os._exit(3)  # killed, as by the kernel's out-of-memory killer
        return 2 * x

    with forked_map(fn, 2) as map_:
        assert map_([(1,), (2,), (3,)]) == [2, 4, 6]
        assert map_([(4,), (5,)]) == [8, 10]  # no pool any more: in this process
    assert "worker processes failed" in caplog.text


@pytest.mark.parametrize("processes", MODES)
def test_call_beside_returns_both_results_as_direct_calls(processes):
    data = np.random.default_rng(1).random((300, 300))  # a result larger than a pipe's buffer
    here, there = call_beside(lambda: float(data.sum()), lambda: data * 2.0, processes)
    assert here == float(data.sum())
    assert np.array_equal(there, data * 2.0)


@pytest.mark.parametrize("processes", MODES)
def test_call_beside_hands_an_error_of_either_call_to_the_caller(processes):
    def fail():
        raise ValueError("there")

    with pytest.raises(ValueError, match="there"):
        call_beside(lambda: 1, fail, processes)
    with pytest.raises(KeyError):
        call_beside(lambda: {}["missing"], lambda: 1, processes)


@linux
def test_call_beside_runs_there_in_a_child_that_forks_no_further():
    parent = os.getpid()
    (pid_here, _), (pid_there, count, ignored) = call_beside(
        lambda: (os.getpid(), worker_count()),
        lambda: (os.getpid(), worker_count(), signal.getsignal(signal.SIGINT) == signal.SIG_IGN), 2)
    assert pid_here == parent and pid_there != parent
    assert count == 1 and ignored
    assert call_beside(os.getpid, os.getpid, 1) == (parent, parent)


@linux
def test_call_beside_runs_there_here_when_the_child_dies(caplog, monkeypatch):
    monkeypatch.setattr(logging.getLogger("haptex"), "propagate", True)  # the CLI tests turn it off
    parent = os.getpid()

    def there():
        if os.getpid() != parent:
            os._exit(3)  # killed, as by the kernel's out-of-memory killer
        return "here"

    assert call_beside(lambda: 1, there, 2) == (1, "here")
    assert "worker process failed" in caplog.text


@linux
def test_call_beside_with_sigchld_ignored_still_answers(monkeypatch):
    # A program that sets SIGCHLD to be ignored has its children reaped by the kernel: there
    # is nothing to wait for, and no thread may fail on it.
    failures = []
    monkeypatch.setattr(threading, "excepthook", failures.append)
    previous = signal.signal(signal.SIGCHLD, signal.SIG_IGN)
    try:
        assert call_beside(lambda: 1, lambda: 2, 2) == (1, 2)
        with pytest.raises(KeyError):
            call_beside(lambda: {}["missing"], lambda: 2, 2)
        for thread in threading.enumerate():
            if thread.name == "haptex-reap":
                thread.join(10.0)
    finally:
        signal.signal(signal.SIGCHLD, previous)
    assert failures == []


@linux
@pytest.mark.parametrize("kind", ["forked_map", "call_beside"])
def test_a_worker_sent_sigterm_ends_quietly_and_the_caller_goes_on(kind, caplog, monkeypatch):
    """Under the tools' stop signals (SIGTERM raises in the caller: playback.stop_signals), a
    worker sent SIGTERM on its own ends, and its calls run in the caller; before, the worker
    inherited the raising handler and its StopRequested stopped the caller as if it had been sent
    the signal."""
    from playback.stop_signals import stop_signals_raise

    monkeypatch.setattr(logging.getLogger("haptex"), "propagate", True)
    parent = os.getpid()

    def fn(i):
        if os.getpid() != parent and i == 2:
            os.kill(os.getpid(), signal.SIGTERM)
            for _ in range(100):  # (the handler runs between bytecodes)
                threading.Event().wait(0.001)
        return i * i

    with stop_signals_raise():
        if kind == "forked_map":
            with forked_map(fn, 2) as map_:
                assert map_([(i,) for i in range(5)]) == [0, 1, 4, 9, 16]
        else:
            assert call_beside(lambda: fn(1), lambda: fn(2), 2) == (1, 4)
    assert "failed" in caplog.text


@linux
def test_opencv_runs_on_one_thread_before_workers_fork():
    """A forked worker inherits every lock as it was: one held by an OpenCV worker thread at the
    fork stays held in the child (a CI run hung for good in cv2.resize in a light-search
    worker). OpenCV is made single-threaded before the fork, its workers joined."""
    import cv2

    cv2.setNumThreads(2)
    image = np.random.default_rng(0).random((1200, 1200)).astype(np.float32)
    cv2.GaussianBlur(image, (0, 0), 3.0)  # OpenCV's worker threads started
    with forked_map(lambda k: (cv2.getNumThreads(), float(cv2.resize(image, (300, 300))[k, k])), 2) as map_:
        out = map_([(k,) for k in range(4)])
    assert cv2.getNumThreads() == 1 and all(n == 1 for n, _ in out)
    assert [v for _, v in out] == [float(cv2.resize(image, (300, 300))[k, k]) for k in range(4)]
    cv2.setNumThreads(2)
    assert call_beside(cv2.getNumThreads, cv2.getNumThreads, 2) == (1, 1)
