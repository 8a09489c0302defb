"""Trajectory sources (CSV file, constant sweep, live stdin) and per-contactor kinematics.

A trajectory is a stream of samples ``(t_s, u_mm, v_mm, phi_deg)``: the array origin on the
fabric and its rotation. Frame ``k`` covers ``[t0 + k T, t0 + (k + 1) T]`` and is rendered from
the state at its centre: the position there and the mean velocity over the frame.

* File sources (CSV, sweep) know the whole trajectory: the state is interpolated, and the velocity
  is the chord over the frame window (no extrapolation inside the recording).
* The live source only knows the past: the position is extrapolated from the newest samples with
  a robust (Theil-Sen) velocity over a short window, the horizon is capped, and a source that
  stops sending fades out. This bounds the extrapolation error for jerky input.

Bad samples have one defined behaviour each (counted in :class:`SampleFilter`, warned once per
kind with the first example):

* NaN/inf or unparsable, or beyond ``MAX_TIME_S``, ``MAX_POSITION_MM``, ``MAX_ANGLE_DEG`` -> skipped;
* time not increasing (backwards or duplicate) -> skipped;
* a jump (implied speed above ``max_speed_mm_s``) or a gap longer than ``max_gap_s`` -> the
  sample starts a new segment: no velocity is inferred across the break, so the frames around it
  are rendered at speed 0 (silent) until motion is measured again: a fade-out, never a burst.
"""
from __future__ import annotations

import bisect
import csv
import logging
import math
import queue
import threading
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Callable, Iterable

import numpy as np

from playback.errors import InputError
from playback.text_files import unreadable

LOG = logging.getLogger("haptex.play.trajectory")
COLUMNS = ("t_s", "u_mm", "v_mm", "phi_deg")
# Samples beyond these are skipped. A span between two finite float times can overflow (a file
# from -1e308 s to 1e308 s ended in an OverflowError counting its frames), and far from 0 float64
# times no longer resolve a frame's window (the limit: about 32 years); positions of 1e308 mm
# made the contactors' positions inf - inf (NaN amplitudes, zeroed, and numpy's warnings). A
# kilometre of fabric and 3e9 turns are beyond any experiment.
MAX_TIME_S = 1e9
MAX_POSITION_MM = 1e6
MAX_ANGLE_DEG = 1e12


@dataclass(frozen=True)
class MotionState:
    """State of the array origin at one instant (trajectory time).

    ``gain`` in [0, 1] fades the output (1 = normal; < 1 when a live source went quiet).
    """

    t_s: float
    u_mm: float
    v_mm: float
    phi_deg: float
    vu_mm_s: float
    vv_mm_s: float
    omega_deg_s: float
    gain: float = 1.0
    age_s: float = 0.0  # time from the newest sample used to t_s (extrapolation horizon)


def contactor_kinematics(state: MotionState, contactors_mm: np.ndarray
                         ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Position, speed and direction of every contactor.

    ``(u_i, v_i) = o + R(phi) (x_i, y_i)``; the velocity adds the rotation term
    ``omega x R(phi) (x_i, y_i) = omega (-r_v, r_u)`` (omega in rad/s).

    Parameters
    ----------
    state : MotionState
        Array origin, rotation and their rates.
    contactors_mm : ndarray, shape (n, 2)
        Device coordinates (x_i, y_i) in mm.

    Returns
    -------
    u_mm, v_mm, speed_mm_s, direction_deg : ndarray, shape (n,)
        Direction in degrees CCW from +u towards +v, in (-180, 180].
    """
    phi = math.radians(state.phi_deg)
    c, s = math.cos(phi), math.sin(phi)
    x = contactors_mm[:, 0]
    y = contactors_mm[:, 1]
    ru = c * x - s * y
    rv = s * x + c * y
    w = math.radians(state.omega_deg_s)
    vu = state.vu_mm_s - w * rv
    vv = state.vv_mm_s + w * ru
    return ru + state.u_mm, rv + state.v_mm, np.hypot(vu, vv), np.degrees(np.arctan2(vv, vu))


@dataclass
class SampleFilter:
    """Screens samples in arrival order; counts and warns about bad ones.

    Parameters
    ----------
    max_speed_mm_s : float
        A displacement faster than this between consecutive samples is a jump (finger lifted
        and put down elsewhere, or a tracker glitch): the sample starts a new segment.
    max_gap_s : float
        Samples further apart than this also start a new segment (no velocity across a dropout).
    source : str
        Name used in warnings.
    """

    max_speed_mm_s: float = 1000.0
    max_gap_s: float = 0.25
    source: str = "trajectory"
    counts: dict[str, int] = field(default_factory=lambda: {"nonfinite": 0, "range": 0, "backwards": 0,
                                                             "duplicate": 0, "jump": 0, "gap": 0})
    _last: tuple[float, float, float] | None = None
    segment: int = 0

    def accept(self, t_s: float, u_mm: float, v_mm: float, phi_deg: float, where: str = "") -> int | None:
        """Segment number for a good sample, or ``None`` if it is skipped."""
        if not all(math.isfinite(x) for x in (t_s, u_mm, v_mm, phi_deg)):
            return self._bad("nonfinite", f"a value is not a finite number, sample skipped{where}")
        if abs(t_s) > MAX_TIME_S or max(abs(u_mm), abs(v_mm)) > MAX_POSITION_MM or abs(phi_deg) > MAX_ANGLE_DEG:
            return self._bad("range", f"value out of range (|t_s| <= {MAX_TIME_S:g} s, |u_mm|, |v_mm| <="
                                      f" {MAX_POSITION_MM:g} mm, |phi_deg| <= {MAX_ANGLE_DEG:g}), sample skipped{where}")
        if self._last is not None:
            t_last, u_last, v_last = self._last
            dt = t_s - t_last
            if dt < 0:
                return self._bad("backwards", f"time goes backwards ({t_s:g} s after {t_last:g} s), sample skipped{where}")
            if dt == 0:
                return self._bad("duplicate", f"duplicate time {t_s:g} s, sample skipped{where}")
            dist = math.hypot(u_mm - u_last, v_mm - v_last)
            if dist > self.max_speed_mm_s * dt:
                self._bad("jump", f"jump of {dist:.3g} mm in {dt * 1e3:.3g} ms: new segment, output fades to 0 until motion is measured again{where}")
                self.segment += 1
            elif dt > self.max_gap_s:
                self._bad("gap", f"gap of {dt:.3g} s between samples: new segment{where}")
                self.segment += 1
        self._last = (t_s, u_mm, v_mm)
        return self.segment

    def _bad(self, kind: str, message: str) -> None:
        self.counts[kind] += 1
        n = self.counts[kind]
        if n == 1:
            LOG.warning("%s: %s", self.source, message)
        elif n in (10, 100, 1000, 10000):
            LOG.warning("%s: %d samples of kind %r so far", self.source, n, kind)
        return None


class SampledTrajectory:
    """A whole trajectory known in advance (CSV file or sweep).

    Parameters
    ----------
    t_s, u_mm, v_mm, phi_deg : ndarray
        Good samples in strictly increasing time (use :func:`clean_samples`).
    segment : ndarray of int, optional
        Segment number per sample; velocity is never taken across a segment break.
    name : str
        For messages.
    """

    def __init__(self, t_s: np.ndarray, u_mm: np.ndarray, v_mm: np.ndarray, phi_deg: np.ndarray,
                 segment: np.ndarray | None = None, name: str = "trajectory",
                 counts: dict[str, int] | None = None) -> None:
        self.t = np.asarray(t_s, dtype=np.float64)
        if self.t.size < 2:
            raise InputError(name, f"needs at least 2 good samples, has {self.t.size}")
        self.u = np.asarray(u_mm, dtype=np.float64)
        self.v = np.asarray(v_mm, dtype=np.float64)
        # Unwrap the rotation so interpolation never goes the long way round through 360°.
        self.phi = np.degrees(np.unwrap(np.radians(np.asarray(phi_deg, dtype=np.float64))))
        self.segment = np.zeros(self.t.size, np.int64) if segment is None else np.asarray(segment, np.int64)
        self.name = name
        self.counts = dict(counts or {})
        self.t_start = float(self.t[0])
        self.t_end = float(self.t[-1])
        # First and last sample time of each segment (segments are numbered 0, 1, ... in order).
        n_seg = int(self.segment.max()) + 1 if self.segment.size else 0
        first = np.searchsorted(self.segment, np.arange(n_seg), side="left")
        last = np.searchsorted(self.segment, np.arange(n_seg), side="right") - 1
        self._seg_t0_l = self.t[first].tolist()
        self._seg_t1_l = self.t[last].tolist()
        # Python lists for the per-frame scalar path (numpy costs ~1 µs per call on scalars).
        self._t_l, self._u_l, self._v_l = self.t.tolist(), self.u.tolist(), self.v.tolist()
        self._p_l, self._seg_l = self.phi.tolist(), self.segment.tolist()

    def frame_count(self, frame_s: float) -> int:
        """Number of whole frames between the first and the last sample."""
        return int(math.floor((self.t_end - self.t_start) / frame_s + 1e-9))

    def position(self, t_s: float | np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(u_mm, v_mm, phi_deg) at arbitrary times: linear between samples, held beyond the ends.

        Across a segment break (a jump) the position switches at the first sample of the new
        segment instead of sliding across the fabric.
        """
        t = np.asarray(t_s, dtype=np.float64)
        k = np.clip(np.searchsorted(self.t, t, side="right") - 1, 0, self.t.size - 2)
        same = self.segment[k] == self.segment[k + 1]
        w = np.clip((t - self.t[k]) / (self.t[k + 1] - self.t[k]), 0.0, 1.0)
        w = np.where(same, w, (w >= 1.0).astype(np.float64))
        out = []
        for arr in (self.u, self.v, self.phi):
            out.append(arr[k] + w * (arr[k + 1] - arr[k]))
        return out[0], out[1], out[2]

    def _pos1(self, t: float, seg: int) -> tuple[float, float, float]:
        """Scalar position at `t`, clamped to segment `seg` (pure Python: called per frame)."""
        t = min(max(t, self._seg_t0_l[seg]), self._seg_t1_l[seg])
        k = bisect.bisect_right(self._t_l, t) - 1
        k = min(max(k, 0), len(self._t_l) - 2)
        t0, t1 = self._t_l[k], self._t_l[k + 1]
        if self._seg_l[k + 1] != seg:  # t is the last sample of its segment
            return self._u_l[k + 1 if t >= t1 else k], self._v_l[k + 1 if t >= t1 else k], self._p_l[k + 1 if t >= t1 else k]
        if self._seg_l[k] != seg:
            return self._u_l[k + 1], self._v_l[k + 1], self._p_l[k + 1]
        w = min(max((t - t0) / (t1 - t0), 0.0), 1.0)
        return (self._u_l[k] + w * (self._u_l[k + 1] - self._u_l[k]),
                self._v_l[k] + w * (self._v_l[k + 1] - self._v_l[k]),
                self._p_l[k] + w * (self._p_l[k + 1] - self._p_l[k]))

    def state(self, t_s: float, frame_s: float) -> MotionState:
        """State at a frame centre: interpolated position, chord velocity over the frame.

        The chord is taken within the centre's segment only; a frame with no motion in its
        segment (at a break, or beyond the last sample) gets velocity 0, hence silence.
        """
        half = 0.5 * frame_s
        k = min(max(bisect.bisect_right(self._t_l, t_s) - 1, 0), len(self._t_l) - 1)
        seg = self._seg_l[k]
        lo = max(t_s - half, self._seg_t0_l[seg])
        hi = min(t_s + half, self._seg_t1_l[seg])
        u, v, phi = self._pos1(t_s, seg)
        if t_s > self.t_end or t_s < self.t_start or hi - lo <= 1e-12:
            return MotionState(t_s, u, v, phi, 0.0, 0.0, 0.0)
        u0, v0, p0 = self._pos1(lo, seg)
        u1, v1, p1 = self._pos1(hi, seg)
        dt = hi - lo
        return MotionState(t_s, u, v, phi, (u1 - u0) / dt, (v1 - v0) / dt, (p1 - p0) / dt)


def clean_samples(rows: Iterable[tuple[float, float, float, float, str]], filt: SampleFilter
                  ) -> tuple[np.ndarray, ...]:
    """Run samples through `filt`; returns arrays t, u, v, phi, segment of the good ones."""
    good: list[tuple[float, float, float, float, int]] = []
    for t, u, v, phi, where in rows:
        seg = filt.accept(t, u, v, phi, where)
        if seg is not None:
            good.append((t, u, v, phi, seg))
    if not good:
        return tuple(np.zeros(0) for _ in range(5))
    arr = np.array(good, dtype=np.float64)
    return arr[:, 0], arr[:, 1], arr[:, 2], arr[:, 3], arr[:, 4].astype(np.int64)


def _parse_row(values: list[str]) -> tuple[float, float, float, float]:
    out = []
    for text in values:
        try:
            out.append(float(text))
        except ValueError:
            out.append(float("nan"))
    return out[0], out[1], out[2], out[3]


def _header_index(header: list[str], source: str | Path) -> list[int]:
    names = [h.strip().lower() for h in header]
    missing = [c for c in COLUMNS if c not in names]
    if missing:
        raise InputError(source, f"CSV header must name the columns {', '.join(COLUMNS)}; missing {', '.join(missing)} (header: {','.join(header)})")
    return [names.index(c) for c in COLUMNS]


def read_csv_trajectory(path: str | Path, *, max_speed_mm_s: float = 1000.0,
                        max_gap_s: float = 0.25) -> SampledTrajectory:
    """Read a CSV trajectory with header ``t_s,u_mm,v_mm,phi_deg`` (any order, extra columns ignored).

    Bad rows are skipped or start a new segment (see the module docstring) with a warning.

    Raises
    ------
    InputError
        No such file, no header, or fewer than 2 good samples.
    """
    path = Path(path)
    filt = SampleFilter(max_speed_mm_s=max_speed_mm_s, max_gap_s=max_gap_s, source=str(path))
    try:
        with open(path, newline="", encoding="utf-8-sig") as fh:  # (a byte-order mark is dropped)
            reader = csv.reader(fh)
            header = next(reader, None)
            if header is None:
                raise InputError(path, "empty file (expected a header t_s,u_mm,v_mm,phi_deg)")
            idx = _header_index(header, path)

            def rows() -> Iterable[tuple[float, float, float, float, str]]:
                for line_no, row in enumerate(reader, start=2):
                    if not row or all(not c.strip() for c in row):
                        continue
                    if len(row) <= max(idx):
                        filt._bad("nonfinite", f"line {line_no} has {len(row)} fields, skipped")
                        continue
                    t, u, v, phi = _parse_row([row[i] for i in idx])
                    yield t, u, v, phi, f" (line {line_no})"

            t, u, v, phi, seg = clean_samples(rows(), filt)
    except (OSError, UnicodeDecodeError) as exc:  # (opening it, or a line that is not text)
        raise unreadable(path, "trajectory CSV", exc) from None
    return SampledTrajectory(t, u, v, phi, seg, name=str(path), counts=filt.counts)


def parse_sweep(spec: str) -> dict[str, float]:
    """Parse ``speed=80,direction=0,duration=5[,u=0,v=0,phi=0]`` (mm/s, degrees, s, mm)."""
    allowed = {"speed", "direction", "duration", "u", "v", "phi"}
    values: dict[str, float] = {"direction": 0.0, "u": 0.0, "v": 0.0, "phi": 0.0}
    seen: set[str] = set()
    for part in spec.split(","):
        if not part.strip():
            continue
        if "=" not in part:
            raise InputError("--sweep", f"expected key=value, got {part.strip()!r}")
        key, text = (x.strip().lower() for x in part.split("=", 1))
        if key not in allowed:
            raise InputError("--sweep", f"unknown key {key!r} (use {', '.join(sorted(allowed))})")
        if key in seen:  # (the last one was used)
            raise InputError("--sweep", f"{key} is given twice")
        seen.add(key)
        try:
            values[key] = float(text)
        except ValueError:
            raise InputError("--sweep", f"{key}={text!r} is not a number") from None
        if not math.isfinite(values[key]):
            raise InputError("--sweep", f"{key} must be finite")
    for key in ("speed", "duration"):
        if key not in values:
            raise InputError("--sweep", f"missing {key}= (e.g. speed=80,direction=0,duration=5)")
    if values["speed"] < 0:
        raise InputError("--sweep", "speed must be >= 0 mm/s")
    if values["duration"] <= 0:
        raise InputError("--sweep", "duration must be > 0 s")
    # Within the limits a trajectory's samples have (a 1e308 s sweep failed counting its frames
    # with an OverflowError; a 1e308 mm/s one gave NaN positions, every amplitude zeroed).
    if values["duration"] > MAX_TIME_S:
        raise InputError("--sweep", f"duration must be at most {MAX_TIME_S:g} s")
    if abs(values["phi"]) > MAX_ANGLE_DEG:
        raise InputError("--sweep", f"phi must be within +-{MAX_ANGLE_DEG:g} degrees")
    reach = max(abs(values["u"]), abs(values["v"])) + values["speed"] * values["duration"]
    if reach > MAX_POSITION_MM:
        raise InputError("--sweep", f"the sweep reaches {reach:.3g} mm from the origin (u, v and speed x duration):"
                                    f" at most {MAX_POSITION_MM:g} mm")
    return values


def sweep_trajectory(speed_mm_s: float, direction_deg: float, duration_s: float, *,
                     u0_mm: float = 0.0, v0_mm: float = 0.0, phi_deg: float = 0.0) -> SampledTrajectory:
    """Constant velocity from (u0, v0) for `duration_s` (the paper's passive test: 80 mm/s)."""
    th = math.radians(direction_deg)
    t = np.array([0.0, duration_s])
    u = u0_mm + speed_mm_s * math.cos(th) * t
    v = v0_mm + speed_mm_s * math.sin(th) * t
    return SampledTrajectory(t, u, v, np.full(2, phi_deg), name="sweep")


class LiveEstimator:
    """Causal motion estimate from samples arriving in real time.

    Velocity: Theil-Sen (median of pairwise slopes) over the samples of the current segment
    within ``window_s`` of the newest one; robust to a single spike. Position: the median
    intercept of the same fit, extrapolated at most ``max_horizon_s`` past the newest sample
    (then held). If the newest sample is older than ``stale_s``, the output fades linearly to 0
    over ``fade_s``.

    Bound: for input whose true velocity changes by at most dv within the window plus horizon,
    the position error is at most about (noise + dv * max_horizon_s); a sudden stop overshoots
    by at most speed * max_horizon_s.
    """

    def __init__(self, *, window_s: float = 0.06, max_horizon_s: float = 0.05, stale_s: float = 0.1,
                 fade_s: float = 0.1, max_speed_mm_s: float = 1000.0, max_gap_s: float = 0.25,
                 source: str = "live") -> None:
        self.window_s = window_s
        self.max_horizon_s = max_horizon_s
        self.stale_s = stale_s
        self.fade_s = fade_s
        self.filter = SampleFilter(max_speed_mm_s=max_speed_mm_s, max_gap_s=max_gap_s, source=source)
        self._buf: list[tuple[float, float, float, float]] = []
        self._segment = -1
        self._phi_last: float | None = None

    @property
    def counts(self) -> dict[str, int]:
        """Bad samples by kind."""
        return self.filter.counts

    @property
    def has_samples(self) -> bool:
        """At least one good sample arrived."""
        return bool(self._buf)

    @property
    def t_last(self) -> float:
        """Time of the newest good sample (trajectory time)."""
        return self._buf[-1][0] if self._buf else float("nan")

    def push(self, t_s: float, u_mm: float, v_mm: float, phi_deg: float, where: str = "") -> bool:
        """Add a sample; returns False if it was skipped."""
        seg = self.filter.accept(t_s, u_mm, v_mm, phi_deg, where)
        if seg is None:
            return False
        if seg != self._segment:
            self._buf.clear()
            self._segment = seg
            self._phi_last = None
        if self._phi_last is not None:  # unwrap rotation sample by sample
            phi_deg = self._phi_last + ((phi_deg - self._phi_last + 180.0) % 360.0 - 180.0)
        self._phi_last = phi_deg
        self._buf.append((t_s, u_mm, v_mm, phi_deg))
        cutoff = t_s - self.window_s
        while len(self._buf) > 2 and self._buf[0][0] < cutoff:
            self._buf.pop(0)
        return True

    def _fit(self) -> tuple[float, np.ndarray, np.ndarray]:
        """(t_ref, position at t_ref, velocity) of the robust fit; velocity 0 with one sample."""
        arr = np.asarray(self._buf)
        t_ref = float(arr[-1, 0])
        if arr.shape[0] < 2:
            return t_ref, arr[-1, 1:], np.zeros(3)
        i, j = np.triu_indices(arr.shape[0], k=1)
        slopes = (arr[j, 1:] - arr[i, 1:]) / (arr[j, 0] - arr[i, 0])[:, None]
        vel = np.median(slopes, axis=0)
        pos = np.median(arr[:, 1:] - (arr[:, :1] - t_ref) * vel, axis=0)
        return t_ref, pos, vel

    def state(self, t_s: float, frame_s: float) -> MotionState:
        """Extrapolated state at trajectory time `t_s` (a frame centre)."""
        if not self._buf:
            return MotionState(t_s, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, gain=0.0, age_s=float("inf"))
        t_ref, pos, vel = self._fit()
        age = t_s - t_ref
        horizon = min(max(age, 0.0), self.max_horizon_s)
        p = pos + vel * horizon
        gain = 1.0
        if age > self.stale_s:
            gain = max(0.0, 1.0 - (age - self.stale_s) / self.fade_s)
        return MotionState(t_s, float(p[0]), float(p[1]), float(p[2]), float(vel[0]), float(vel[1]),
                           float(vel[2]), gain=gain, age_s=age)

    def position_fn(self) -> Callable[[np.ndarray], tuple[np.ndarray, np.ndarray, np.ndarray]]:
        """A snapshot of the current extrapolation as a trajectory callable (for direct mode)."""
        if not self._buf:
            return lambda t: (np.zeros_like(np.asarray(t, float)),) * 3
        t_ref, pos, vel = self._fit()
        lo = min(b[0] for b in self._buf)

        def traj(t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
            h = np.clip(np.asarray(t, dtype=np.float64) - t_ref, lo - t_ref, self.max_horizon_s)
            return pos[0] + vel[0] * h, pos[1] + vel[1] * h, pos[2] + vel[2] * h

        return traj


class LiveSource:
    """Samples from a text stream (stdin), one ``t_s,u_mm,v_mm,phi_deg`` line each.

    A reader thread parses lines into a queue; the player calls :meth:`poll` once per frame,
    which moves queued samples into the estimator. A header line is optional. The source is
    finished when the stream ends (EOF). Unparsable lines count as bad samples.
    """

    def __init__(self, stream: IO[str], estimator: LiveEstimator | None = None, name: str = "stdin") -> None:
        self.estimator = estimator or LiveEstimator(source=name)
        self.name = name
        self._queue: queue.Queue[tuple[float, float, float, float, str] | None] = queue.Queue()
        self._eof = False
        self._thread = threading.Thread(target=self._read, args=(stream,), daemon=True, name="haptex-live")
        self._thread.start()

    def _read(self, stream: IO[str]) -> None:
        idx = list(range(4))
        try:
            for line_no, line in enumerate(stream, start=1):
                fields = [f.strip() for f in line.replace(";", ",").split(",")]
                if not line.strip():
                    continue
                if line_no == 1 and fields[0].lower() in COLUMNS:
                    try:
                        idx = _header_index(fields, self.name)
                    except InputError as exc:
                        LOG.warning("%s", exc)
                    continue
                if len(fields) <= max(idx):
                    t = u = v = phi = float("nan")
                else:
                    t, u, v, phi = _parse_row([fields[i] for i in idx])
                self._queue.put((t, u, v, phi, f" (line {line_no})"))
        except (OSError, ValueError) as exc:  # stream closed under us
            LOG.warning("%s: stopped reading (%s)", self.name, exc)
        finally:
            self._queue.put(None)

    def poll(self) -> None:
        """Move every queued sample into the estimator (non-blocking)."""
        while True:
            try:
                item = self._queue.get_nowait()
            except queue.Empty:
                return
            if item is None:
                self._eof = True
                return
            self.estimator.push(*item)

    def wait_first(self, timeout_s: float | None = None) -> bool:
        """Block until the first good sample (or EOF); True if one arrived."""
        while not self.estimator.has_samples and not self._eof:
            try:
                item = self._queue.get(timeout=timeout_s)
            except queue.Empty:
                return False
            if item is None:
                self._eof = True
                break
            self.estimator.push(*item)
        return self.estimator.has_samples

    @property
    def finished(self) -> bool:
        """The stream ended and every sample was consumed."""
        return self._eof
