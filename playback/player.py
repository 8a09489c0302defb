"""The frame scheduler: trajectory -> amplitudes -> DAC codes -> packets, every 25 ms.

Timing (docs/usb-protocol.md, "Host timing"): frame k's window on the device starts at its
deadline ``D_k = t0 + k T`` (absolute, so wake-up errors never accumulate into drift). The
packet is due at ``S_k = D_k - lead``; the player wakes ``prep`` before that (a coarse OS
sleep), renders the frame for the window ``[D_k, D_k + T]`` from the state at its centre, then
waits precisely (sleep, then a short busy-wait) until ``S_k`` and sends. A frame is **late** when
the transport accepted its packet after ``D_k``; a frame whose whole window has already passed
when the player wakes is skipped (counted) so the stream catches up instead of lagging further.

During playback the cyclic garbage collector is paused (objects alive at the start are frozen
and a young-generation collection runs only in the slack after a send), HDF5 recording is
flushed only in that slack, and on request the process asks for real-time scheduling
(``SCHED_FIFO``, else a lower nice value), falling back silently when not permitted.

Safety: every exit path (end of trajectory, Ctrl-C or another stop signal, device error) sends an
all-zero frame when it can, with further stop signals held back until it and the record are
done; the controller's time-to-live stops the outputs anyway if the host disappears.
"""
from __future__ import annotations

import contextlib
import gc
import importlib
import logging
import math
import os
import time
from dataclasses import asdict, dataclass, field
from typing import Any, Callable, Iterator

import numpy as np

from playback import protocol
from playback.asset import Asset
from playback.errors import DeviceError, InputError
from playback.interp import RigidArrayLookup, table_amplitudes
from playback.stop_signals import deferred, stop_reason
from playback.trajectory import LiveSource, MotionState, SampledTrajectory, contactor_kinematics

LOG = logging.getLogger("haptex.play")


@dataclass
class RunSummary:
    """What happened during a run (also stored as record attributes).

    Timing fields: ``send_error`` is the time the transport accepted a packet minus its due time
    ``S_k``; ``lateness_ms_max`` is the largest ``sent - D_k`` (negative when every frame reached
    the device before its window started, i.e. ``frames_late == 0``); ``drift_ms`` is the
    median send error over the last tenth of the frames minus that over the first tenth.
    """

    frames_sent: int = 0
    frames_late: int = 0
    frames_skipped: int = 0
    clamped: int = 0
    nonfinite: int = 0
    retries: int = 0
    bad_samples: dict[str, int] = field(default_factory=dict)
    render_us_median: float = float("nan")
    render_us_p99: float = float("nan")
    render_us_max: float = float("nan")
    latency_us_median: float = float("nan")
    latency_us_max: float = float("nan")
    wake_error_ms_max: float = float("nan")
    send_error_ms_median: float = float("nan")
    send_error_ms_p99: float = float("nan")
    send_error_ms_max: float = float("nan")
    lateness_ms_max: float = float("nan")
    drift_ms: float = float("nan")
    duration_s: float = 0.0
    interrupted: bool = False
    stopped_by: str = "end of trajectory"
    zero_frame_sent: bool = False
    scheduling: str = "normal"
    gc_collections: int = 0
    device_status: dict[str, Any] | None = None

    def line(self) -> str:
        """One-line human summary."""
        bad = sum(self.bad_samples.values())
        if not self.frames_sent:  # (no timing to show: "render median nan µs" said nothing)
            return f"no frames sent; bad samples {bad}, retries {self.retries}; stopped by {self.stopped_by}"
        return (f"{self.frames_sent} frames in {self.duration_s:.2f} s, {self.frames_late} late "
                f"(worst {self.lateness_ms_max:+.2f} ms from window start), {self.frames_skipped} skipped; "
                f"render median {self.render_us_median:.0f} µs (p99 {self.render_us_p99:.0f}); "
                f"latency median {self.latency_us_median:.0f} µs; send error p99 {self.send_error_ms_p99:.3f} ms, "
                f"drift {self.drift_ms:.3f} ms; clamped {self.clamped}, non-finite {self.nonfinite}, "
                f"bad samples {bad}, retries {self.retries}; stopped by {self.stopped_by}")


@contextlib.contextmanager
def realtime_priority(enabled: bool, fifo_priority: int = 10, nice: int = -10) -> Iterator[str]:
    """Ask for real-time scheduling of the calling thread for the duration of the block.

    Tries ``SCHED_FIFO`` at `fifo_priority` (the spin before each send is bounded, and Linux's
    RT throttling keeps 5 % of the CPU for others anyway), then a lower nice value; either may
    be refused (no privilege, not Linux): that is logged at INFO (``-v``) and playback goes on.
    The previous policy or nice value is restored afterwards.

    Yields
    ------
    str
        What was obtained: ``"SCHED_FIFO <prio>"``, ``"nice <n>"`` or ``"normal"``.
    """
    if not enabled:
        yield "normal"
        return
    restore: Callable[[], None] | None = None
    got = "normal"
    try:
        old_policy, old_param = os.sched_getscheduler(0), os.sched_getparam(0)
        prio = max(os.sched_get_priority_min(os.SCHED_FIFO), min(fifo_priority, os.sched_get_priority_max(os.SCHED_FIFO)))
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(prio))
        restore = lambda: os.sched_setscheduler(0, old_policy, old_param)  # noqa: E731
        got = f"SCHED_FIFO {prio}"
    except (AttributeError, OSError) as exc:  # PermissionError is an OSError
        LOG.info("real-time scheduling (SCHED_FIFO) not available (%s); trying a lower nice value", exc)
        try:
            old_nice = os.getpriority(os.PRIO_PROCESS, 0)
            if nice < old_nice:
                os.setpriority(os.PRIO_PROCESS, 0, nice)
                restore = lambda: os.setpriority(os.PRIO_PROCESS, 0, old_nice)  # noqa: E731
                got = f"nice {nice}"
        except (AttributeError, OSError) as exc2:
            LOG.info("priority not raised (%s); playing at normal priority", exc2)
    if got != "normal":
        LOG.info("scheduling: %s", got)
    try:
        yield got
    finally:
        if restore is not None:
            with contextlib.suppress(OSError):
                restore()


@contextlib.contextmanager
def gc_paused() -> Iterator[None]:
    """Pause the cyclic garbage collector (a full collection can take milliseconds).

    Everything alive at the start is collected once and frozen (never scanned again); automatic
    collection is disabled and the caller runs cheap young-generation collections when it has
    time. The previous state is restored afterwards.
    """
    was_enabled = gc.isenabled()
    gc.collect()
    gc.freeze()
    gc.disable()
    try:
        yield
    finally:
        gc.unfreeze()
        if was_enabled:
            gc.enable()


class TableRenderer:
    """Amplitudes from the asset's tables for one motion state (the default mode).

    The per-frame path is :class:`~playback.interp.RigidArrayLookup` (work arrays made here,
    before the clock starts); a non-finite state or a contactor beyond the edge of a
    non-periodic table takes the general path ``table_amplitudes(contactor_kinematics(...))``,
    which gives the same numbers and handles those cases.
    """

    mode = "tables"

    def __init__(self, asset: Asset) -> None:
        self.tables = asset.tables
        self.contactors = np.ascontiguousarray(asset.contactors_mm, dtype=np.float64)
        self.lookup = RigidArrayLookup(self.tables.interpolator, self.contactors)

    def render(self, k: int, state: MotionState) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(a40, a320, flags) per contactor, µm, faded by ``state.gain``."""
        out = self.lookup(state.u_mm, state.v_mm, state.phi_deg, state.vu_mm_s, state.vv_mm_s, state.omega_deg_s)
        if out is None:
            u, v, speed, direction = contactor_kinematics(state, self.contactors)
            out = table_amplitudes(self.tables, u, v, speed, direction)
        a40, a320, flags = out
        if state.gain != 1.0:
            a40 *= state.gain  # fresh arrays: scaling in place is safe
            a320 *= state.gain
        return a40, a320, flags


def load_render_direct() -> Callable[..., Any]:
    """The compiler's reference renderer, imported only when ``--mode direct`` asks for it.

    Imported lazily on purpose: the player must stay light (numpy, h5py, pyusb) and direct mode
    is the only one that needs the compiler installed.
    """
    try:
        module = importlib.import_module("haptex_compile.render")
    except ImportError as exc:
        raise InputError(None, f"--mode direct needs the compiler's reference renderer haptex_compile.render ({exc})") from None
    fn = getattr(module, "render_direct", None)
    if not callable(fn):
        raise InputError(None, "--mode direct: haptex_compile.render has no render_direct() (compiler too old?)")
    return fn


class DirectRenderer:
    """Amplitudes from the reference renderer (``haptex_compile.render.render_direct``).

    For a trajectory known in advance all frames are rendered in one batch before playback
    starts (the per-frame render time recorded is the batch time divided by the frame count);
    for a live source each frame is rendered on its own from a snapshot of the extrapolation.
    """

    mode = "direct"

    def __init__(self, asset: Asset, render_direct: Callable[..., Any] | None = None) -> None:
        if asset.height_um is None:
            raise InputError(asset.path, "--mode direct needs the asset read with its surface (load_surface=True)")
        self.asset = asset
        self.fn = render_direct or load_render_direct()
        self._batch: tuple[np.ndarray, np.ndarray] | None = None
        self.batch_us_per_frame = float("nan")

    def _call(self, centres: np.ndarray, traj: Callable[..., Any]) -> tuple[np.ndarray, np.ndarray]:
        a40, a320 = self.fn(self.asset, centres, traj)
        a40 = np.asarray(a40, dtype=np.float64)
        a320 = np.asarray(a320, dtype=np.float64)
        want = (centres.size, self.asset.n_contactors)
        if a40.shape != want or a320.shape != want:
            raise InputError(None, f"render_direct returned shapes {a40.shape}, {a320.shape}; expected {want}")
        return a40, a320

    def prepare(self, traj: SampledTrajectory, centres_s: np.ndarray) -> None:
        """Render every frame of a known trajectory at once."""
        t = time.perf_counter()
        self._batch = self._call(np.asarray(centres_s, dtype=np.float64), traj.position)
        self.batch_us_per_frame = (time.perf_counter() - t) * 1e6 / max(1, len(centres_s))

    def render(self, k: int, state: MotionState, traj: Callable[..., Any] | None = None
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(a40, a320, flags=0) for frame k."""
        if self._batch is not None:
            a40, a320 = self._batch[0][k], self._batch[1][k]
        else:
            a40, a320 = self._call(np.array([state.t_s]), traj)
            a40, a320 = a40[0], a320[0]
        if state.gain != 1.0:
            a40, a320 = a40 * state.gain, a320 * state.gain
        return a40, a320, np.zeros(a40.shape, np.uint8)


class Player:
    """Streams an asset along a trajectory to a transport.

    Parameters
    ----------
    asset : Asset
        Read with ``load_surface=True`` for direct mode.
    profile : DeviceProfile
        Calibration and limits; its contactor count must match the asset's scene.
    transport : Transport
        Opened by :meth:`run`.
    source : SampledTrajectory or LiveSource
        Where the motion comes from.
    clock : MonotonicClock or VirtualClock
        Real time for experiments; virtual for tests and ``--fast``.
    mode : {"tables", "direct"}
    recorder : Recorder, optional
    lead_ms : float
        How long before its window starts (its deadline) a frame's packet is sent.
    prep_ms : float
        How long before the send the player wakes to take the input snapshot, render and encode
        (a budget: it also absorbs the OS's wake-up latency; the send itself is timed precisely).
    realtime : bool
        Ask for real-time scheduling during playback on the real clock (see
        :func:`realtime_priority`; refused silently without privilege).
    max_frames : int, optional
        Stop after this many frames (live sources run until EOF otherwise).
    emulator : ControllerEmulator, optional
        For ``--waveforms``.
    waveform_rate_hz : float, optional
        Synthesise and record waveforms at this rate (sim only).
    render_direct : callable, optional
        Injected reference renderer (tests); default imports it from the compiler.
    """

    def __init__(self, asset: Asset, profile: Any, transport: Any, source: SampledTrajectory | LiveSource, *,
                 clock: Any, mode: str = "tables", recorder: Any = None, lead_ms: float = 5.0,
                 prep_ms: float = 2.0, realtime: bool = False, max_frames: int | None = None, emulator: Any = None, waveform_rate_hz: float | None = None,
                 render_direct: Callable[..., Any] | None = None) -> None:
        if profile.count != asset.n_contactors:
            raise InputError(asset.path, f"scene has {asset.n_contactors} contactors but the device profile "
                                         f"{profile.name or ''} maps {profile.count}")
        if mode not in ("tables", "direct"):
            raise InputError(None, f"unknown mode {mode!r} (use tables or direct)")
        self.asset = asset
        self.profile = profile
        self.transport = transport
        self.source = source
        self.clock = clock
        self.mode = mode
        self.recorder = recorder
        self.frame_s = asset.tables.frame_ms * 1e-3
        self.lead_s = min(max(lead_ms * 1e-3, 0.0), self.frame_s)
        self.prep_s = min(max(prep_ms * 1e-3, 0.0), self.frame_s - self.lead_s)
        self.realtime = realtime
        self.max_frames = max_frames
        self.emulator = emulator
        self.waveform_rate_hz = waveform_rate_hz
        self.frame_us = int(round(asset.tables.frame_ms * 1000))
        self.ttl_us = int(round(profile.ttl_ms * 1000))
        self.renderer = (TableRenderer(asset) if mode == "tables"
                         else DirectRenderer(asset, render_direct))
        self.summary = RunSummary()
        self._seq = 0

    # ------------------------------------------------------------------------------------
    def _send_zero(self) -> bool:
        zeros = np.zeros(self.profile.n_channels, np.uint16)
        pkt = protocol.encode_frame(self._seq, self.frame_us, self.ttl_us, zeros, zeros,
                                    protocol.FLAG_RESYNC if self._seq == 0 else 0)
        try:
            self.transport.send(pkt)
        except DeviceError as exc:
            LOG.warning("could not send the all-zero frame (%s); the controller's %g ms time-to-live stops the output",
                        exc, self.profile.ttl_ms)
            return False
        self._seq += 1
        return True

    def run(self) -> RunSummary:
        """Play until the trajectory ends, ``max_frames``, EOF, Ctrl-C or a device error.

        Returns the summary; a :class:`DeviceError` is re-raised after the zero frame attempt and
        the record are done. Ctrl-C (any ``KeyboardInterrupt``: SIGTERM and SIGHUP raise one
        under :func:`playback.stop_signals.stop_signals_raise`) returns normally with
        ``summary.interrupted`` set and the signal in ``summary.stopped_by``.
        """
        s = self.summary
        T = self.frame_s
        live = isinstance(self.source, LiveSource)
        n_frames = self.max_frames
        if not live:
            n_file = self.source.frame_count(T)
            n_frames = n_file if n_frames is None else min(n_frames, n_file)
            if n_frames < 1:
                raise InputError(self.source.name, f"trajectory is shorter than one {T * 1e3:g} ms frame")
        self.transport.open()
        render_us: list[float] = []
        latency_us: list[float] = []
        wake_err: list[float] = []
        send_err: list[float] = []
        lateness: list[float] = []
        error: DeviceError | None = None
        t_first = None
        rt = contextlib.ExitStack()
        stopping = contextlib.ExitStack()  # stop signals held back while the run ends
        held: list[str] | None = None
        try:
            try:
                if not live and isinstance(self.renderer, DirectRenderer):
                    # The batch can take minutes: before real-time priority, not under it.
                    centres = self.source.t_start + (np.arange(n_frames) + 0.5) * T
                    self.renderer.prepare(self.source, centres)
                # Both before t0 is set: the full collection that starts gc_paused takes time.
                s.scheduling = rt.enter_context(realtime_priority(self.realtime and not self.clock.virtual))
                rt.enter_context(gc_paused())
                if self.recorder is not None:
                    self.recorder.hold = True  # HDF5 writes only in the slack after a send
                if live:
                    LOG.info("waiting for the first trajectory sample on %s", self.source.name)
                    if not self.source.wait_first():
                        raise InputError(self.source.name, "no valid trajectory sample before end of input")
                    est = self.source.estimator
                    arrival = self.clock.now()
                    t0 = arrival + T
                    tau0 = est.t_last + (t0 - arrival)
                else:
                    tau0 = self.source.t_start
                    t0 = self.clock.now() + T
                t_first = t0
                k = 0
                next_log = t0 + 1.0
                next_gc = t0 + 10.0
                ahead = self.lead_s + self.prep_s  # wake-up = deadline - ahead
                while n_frames is None or k < n_frames:
                    deadline = t0 + k * T  # D_k: the frame's window starts on the device
                    due = deadline - self.lead_s  # S_k: the packet is sent then
                    wake = due - self.prep_s
                    self.clock.sleep_until(wake)
                    now = self.clock.now()
                    wake_err.append(now - wake)
                    if now > deadline + T:  # this frame's window is over: skip, do not lag
                        missed = int(math.floor((now - deadline) / T))
                        if n_frames is not None:
                            missed = min(missed, n_frames - k)
                        s.frames_skipped += missed
                        LOG.warning("%d frame(s) skipped: the player was %.1f ms behind", missed, (now - deadline) * 1e3)
                        k += missed
                        continue
                    tau_c = tau0 + (k + 0.5) * T
                    r0 = time.perf_counter()
                    if live:
                        self.source.poll()
                        state = self.source.estimator.state(tau_c, T)
                        traj = self.source.estimator.position_fn() if self.mode == "direct" else None
                    else:
                        state = self.source.state(tau_c, T)
                        traj = None
                    if isinstance(self.renderer, DirectRenderer):
                        a40, a320, flags = self.renderer.render(k, state, traj)
                    else:
                        a40, a320, flags = self.renderer.render(k, state)
                    r1 = time.perf_counter()
                    c40, c320, n_clamped, n_bad = self.profile.to_codes(a40, a320)
                    pkt = protocol.encode_frame(self._seq, self.frame_us, self.ttl_us, c40, c320,
                                                protocol.FLAG_RESYNC if self._seq == 0 else 0)
                    ready = self.clock.now()
                    self.clock.wait_until(due)  # precise: the packet leaves at S_k, not when it is ready
                    self.transport.send(pkt)
                    r2 = time.perf_counter()
                    sent = self.clock.now()
                    seq = self._seq
                    self._seq += 1
                    late = sent > deadline
                    r_us = (r1 - r0) * 1e6
                    if isinstance(self.renderer, DirectRenderer) and self.renderer._batch is not None:
                        r_us = self.renderer.batch_us_per_frame
                    # Input snapshot -> packet accepted (real time; on the virtual clock the CPU
                    # time plus the simulated waits).
                    lat_us = (r2 - r0) * 1e6 if not self.clock.virtual else (r2 - r0) * 1e6 + (sent - ready) * 1e6
                    render_us.append(r_us)
                    latency_us.append(lat_us)
                    send_err.append(sent - due)
                    lateness.append(sent - deadline)
                    s.frames_sent += 1
                    s.frames_late += int(late)
                    s.clamped += n_clamped
                    s.nonfinite += n_bad
                    if self.recorder is not None:
                        self.recorder.append(
                            t_s=tau_c, index=k, deadline_s=deadline - t0, sent_s=sent - t0, render_us=r_us,
                            latency_us=lat_us, input_age_ms=state.age_s * 1e3 if math.isfinite(state.age_s) else -1.0,
                            gain=state.gain, late=int(late), clamped=n_clamped, nonfinite=n_bad, sequence=seq,
                            a40=a40, a320=a320, flags=flags, codes=np.stack([c40, c320]),
                            packet=np.frombuffer(pkt, dtype=np.uint8))
                    if late:
                        LOG.info("frame %d late: sent %.2f ms after its window started", k, (sent - deadline) * 1e3)
                    if LOG.isEnabledFor(logging.DEBUG):
                        LOG.debug("frame %d t=%.3f s render %.0f µs latency %.0f µs send error %.3f ms%s", k, tau_c,
                                  r_us, lat_us, (sent - due) * 1e3, " LATE" if late else "")
                    # Housekeeping only in the slack before the next wake-up (never delays a frame).
                    slack = t0 + (k + 1) * T - ahead - self.clock.now()
                    if slack > 0.010:
                        if self.recorder is not None and self.recorder.flush_due:
                            self.recorder.flush()
                        elif sent >= next_gc:
                            gc.collect(1)  # young objects only: everything older is frozen
                            s.gc_collections += 1
                            next_gc = sent + 10.0
                    if now >= next_log and LOG.isEnabledFor(logging.INFO):
                        LOG.info("t=%.1f s: %d frames, %d late, %d skipped, render median %.0f µs max %.0f µs, "
                                 "latency median %.0f µs, send error max %.3f ms", now - t0, s.frames_sent,
                                 s.frames_late, s.frames_skipped, float(np.median(render_us[-40:])),
                                 float(np.max(render_us[-40:])), float(np.median(latency_us[-40:])),
                                 float(np.max(send_err[-40:])) * 1e3)
                        next_log = now + 1.0
                    k += 1
                    if live and self.source.finished and state.gain == 0.0:
                        s.stopped_by = "end of live input (faded out)"
                        break
                if self.max_frames is not None and k >= self.max_frames:
                    s.stopped_by = "frame limit"
            except KeyboardInterrupt as exc:  # Ctrl-C, or SIGTERM/SIGHUP (playback.stop_signals)
                held = stopping.enter_context(deferred())
                s.interrupted = True
                s.stopped_by = stop_reason(exc)
                LOG.warning("interrupted by %s: sending an all-zero frame and stopping", s.stopped_by)
            except DeviceError as exc:
                error = exc
                s.stopped_by = f"device error: {exc}"
            # From here the stop must finish: a second Ctrl-C would cut the zero frame or the record.
            held = held if held is not None else stopping.enter_context(deferred())
            # Leave nothing vibrating: an explicit all-zero frame (TTL is the backstop).
            s.zero_frame_sent = self._send_zero()
            rt.close()  # normal priority and the garbage collector back before the status and the record
            if error is None:
                try:
                    status = self.transport.status()
                    s.device_status = None if status is None else {**asdict(status), "state": status.state_name}
                except DeviceError as exc:
                    LOG.warning("status read failed: %s", exc)
        finally:
            held = held if held is not None else stopping.enter_context(deferred())
            rt.close()
            s.retries = getattr(self.transport, "retries", 0)
            s.bad_samples = dict(self.source.estimator.counts if live else self.source.counts)
            if render_us:
                s.render_us_median = float(np.median(render_us))
                s.render_us_p99 = float(np.percentile(render_us, 99))
                s.render_us_max = float(np.max(render_us))
                s.latency_us_median = float(np.median(latency_us))
                s.latency_us_max = float(np.max(latency_us))
            if wake_err:
                s.wake_error_ms_max = float(np.max(wake_err) * 1e3)
            if send_err:
                e = np.asarray(send_err) * 1e3
                m = max(1, len(e) // 10)
                s.send_error_ms_median = float(np.median(e))
                s.send_error_ms_p99 = float(np.percentile(e, 99))
                s.send_error_ms_max = float(e.max())
                s.lateness_ms_max = float(np.max(lateness) * 1e3)
                s.drift_ms = float(np.median(e[-m:]) - np.median(e[:m]))
            if t_first is not None:
                s.duration_s = self.clock.now() - t_first
            if self.recorder is not None:
                self.recorder.hold = False
            try:
                self._finish_record()
                self.transport.close()
            finally:
                stopping.close()
        if held:  # the run had ended, or was ending, when they came: nothing more to stop
            LOG.info("%s while stopping: ignored", ", ".join(dict.fromkeys(held)))
        if error is not None:
            raise error
        return s

    def _finish_record(self) -> None:
        if self.recorder is None:
            return
        if self.waveform_rate_hz and self.emulator is not None and self.emulator.frames:
            t_a = self.emulator.frames[0].arrival_s
            t_b = self.emulator.frames[-1].arrival_s + self.frame_s
            t, volts = self.emulator.synthesise(t_a, t_b, self.waveform_rate_hz)
            self.recorder.write_waveforms(t, volts, self.waveform_rate_hz)
        attrs = {k: v for k, v in asdict(self.summary).items()}
        attrs.update(mode=self.mode, asset=self.asset.path, frame_ms=self.asset.tables.frame_ms,
                     ttl_ms=self.profile.ttl_ms, lead_ms=self.lead_s * 1e3, prep_ms=self.prep_s * 1e3,
                     device=self.transport.name,
                     profile=self.profile.to_dict(), clock="virtual" if self.clock.virtual else "monotonic",
                     tables_max_rel_error=self.asset.tables.max_rel_error)
        if isinstance(self.renderer, DirectRenderer) and self.renderer._batch is not None:
            attrs["render_us_note"] = "direct mode, batch: render_us is the batch time per frame"
        self.recorder.close(attrs)
