"""Trajectories: kinematics, bad samples, and bounded extrapolation for live input."""
from __future__ import annotations

import io
import logging
import math
import time

import numpy as np
import pytest

from playback.errors import InputError
from playback.trajectory import (LiveEstimator, LiveSource, MotionState, contactor_kinematics, parse_sweep,
                                 read_csv_trajectory, sweep_trajectory)


def test_kinematics_matches_numerical_derivative():
    # Array translating and rotating: each contactor's velocity must equal d/dt of its position.
    xy = np.array([[5.0, -1.5], [-3.0, 3.0], [0.0, 0.0]])

    def pos(t):
        phi = 30.0 + 90.0 * t  # deg
        st = MotionState(t, 1.0 + 20.0 * t, -2.0 + 5.0 * t, phi, 20.0, 5.0, 90.0)
        return st, contactor_kinematics(st, xy)

    st, (u, v, speed, direction) = pos(0.2)
    h = 1e-6
    _, (u1, v1, _, _) = pos(0.2 + h)
    _, (u0, v0, _, _) = pos(0.2 - h)
    vu, vv = (u1 - u0) / (2 * h), (v1 - v0) / (2 * h)
    np.testing.assert_allclose(speed, np.hypot(vu, vv), rtol=1e-6)
    np.testing.assert_allclose(direction, np.degrees(np.arctan2(vv, vu)), atol=1e-6)
    # Rotation convention: phi = 90° maps device +x to fabric +v.
    st90 = MotionState(0, 0, 0, 90.0, 0, 0, 0)
    u, v, _, _ = contactor_kinematics(st90, np.array([[1.0, 0.0]]))
    assert u[0] == pytest.approx(0.0, abs=1e-12) and v[0] == pytest.approx(1.0)


def test_sweep_state():
    tr = sweep_trajectory(80.0, 30.0, 5.0, u0_mm=1.0, v0_mm=2.0)
    assert tr.frame_count(0.025) == 200
    st = tr.state(1.0125, 0.025)
    assert st.u_mm == pytest.approx(1.0 + 80 * math.cos(math.radians(30)) * 1.0125)
    assert math.hypot(st.vu_mm_s, st.vv_mm_s) == pytest.approx(80.0)
    assert math.degrees(math.atan2(st.vv_mm_s, st.vu_mm_s)) == pytest.approx(30.0)
    assert parse_sweep("speed=80,direction=0,duration=5") == {"speed": 80.0, "direction": 0.0, "duration": 5.0,
                                                              "u": 0.0, "v": 0.0, "phi": 0.0}
    for bad in ("speed=80", "speed=x,duration=1", "speed=1,duration=0", "speed=1,duration=1,foo=2", "speed"):
        with pytest.raises(InputError):
            parse_sweep(bad)
    # A key given twice: the last one was used, without a word.
    with pytest.raises(InputError, match="speed is given twice"):
        parse_sweep("speed=80,duration=1,Speed=90")


def test_csv_bad_samples(tmp_path, caplog, monkeypatch):
    monkeypatch.setattr(logging.getLogger("haptex"), "propagate", True)  # the CLI tests turn it off
    lines = ["t_s,u_mm,v_mm,phi_deg"]
    t = np.arange(0, 1.0, 0.01)
    rows = [[ti, 50.0 * ti, 0.0, 0.0] for ti in t]
    rows[10][1] = float("nan")            # NaN -> skipped
    rows.insert(20, [0.05, 2.5, 0.0, 0.0])  # backwards -> skipped
    rows.insert(30, list(rows[29]))       # duplicate -> skipped
    for r in rows[60:]:
        r[1] += 40.0                      # jump of 40 mm in 10 ms -> new segment
    lines += [",".join(str(x) for x in r) for r in rows]
    lines.append("1.5,abc,0,0")           # unparsable -> skipped
    p = tmp_path / "traj.csv"
    p.write_text("\n".join(lines) + "\n")
    tr = read_csv_trajectory(p)
    assert tr.counts == {"nonfinite": 2, "range": 0, "backwards": 1, "duplicate": 1, "jump": 1, "gap": 0}
    assert any("jump" in r.message for r in caplog.records)
    # Normal motion around t = 0.3 s: 50 mm/s.
    st = tr.state(0.3, 0.025)
    assert st.vu_mm_s == pytest.approx(50.0)
    # A frame straddling the jump never sees the 40 mm slide as motion: speed stays ~50 mm/s.
    jump_t = rows[60][0]
    for tc in (jump_t - 0.004, jump_t + 0.004):
        st = tr.state(tc, 0.025)
        assert abs(st.vu_mm_s) <= 50.0 + 1e-9
    # Beyond the last sample: held, silent.
    assert tr.state(5.0, 0.025).vu_mm_s == 0.0


def test_csv_samples_out_of_range_are_skipped(tmp_path):
    # Finite but absurd values: times of +-1e308 s made the span inf and counting the frames
    # raised OverflowError (a traceback from haptex-play); positions of 1e308 mm gave NaN
    # amplitudes. Such samples are skipped, and the rest plays: 0 to 0.2 s, 8 frames of 25 ms.
    p = tmp_path / "traj.csv"
    p.write_text("t_s,u_mm,v_mm,phi_deg\n-1e308,0,0,0\n0,0,0,0\n0.1,5,0,0\n0.15,0,1e308,0\n"
                 "0.2,10,0,0\n0.25,15,0,1e300\n1e308,0,0,0\n")
    tr = read_csv_trajectory(p)
    assert tr.counts["range"] == 4
    assert (tr.t_start, tr.t_end) == (0.0, 0.2)
    assert tr.frame_count(0.025) == 8
    assert tr.state(0.1, 0.025).vu_mm_s == pytest.approx(50.0)


def test_sweeps_out_of_range_are_refused():
    # A 1e308 s sweep failed counting its frames (OverflowError); a 1e308 mm/s one gave NaN
    # positions. Sweeps stay within the limits of a trajectory's samples.
    assert parse_sweep("speed=80,duration=5,u=10")["u"] == 10.0
    for spec, words in (("speed=80,duration=1e308", "duration must be at most"),
                        ("speed=1e308,duration=0.25", "reaches"), ("speed=80,duration=1,u=1e308", "reaches"),
                        ("speed=80,duration=1,phi=1e300", "phi must be within")):
        with pytest.raises(InputError, match=words):
            parse_sweep(spec)


def test_csv_errors(tmp_path):
    p = tmp_path / "x.csv"
    p.write_text("time,x,y\n0,0,0\n")
    with pytest.raises(InputError, match="missing t_s, u_mm, v_mm, phi_deg"):
        read_csv_trajectory(p)
    p.write_text("t_s,u_mm,v_mm,phi_deg\n0,0,0,0\nnan,1,1,1\n")
    with pytest.raises(InputError, match="at least 2 good samples"):
        read_csv_trajectory(p)
    p.write_text("")
    with pytest.raises(InputError, match="empty"):
        read_csv_trajectory(p)


def feed(est, t, u, v, phi=None):
    for k in range(len(t)):
        est.push(t[k], u[k], v[k], 0.0 if phi is None else phi[k])


def test_live_extrapolation_noise_and_spike_bounded():
    rng = np.random.default_rng(7)
    est = LiveEstimator()
    t = np.arange(0, 0.5, 0.01)
    u_true = 80.0 * t
    noise = rng.normal(0, 0.02, t.size)
    u = u_true + noise
    u[-3] += 3.0  # a single tracker spike 3 mm off (300 mm/s implied: not a jump)
    feed(est, t, u, np.zeros_like(t))
    tc = t[-1] + 0.025
    st = est.state(tc, 0.025)
    # Theil-Sen ignores the spike: velocity within 5 mm/s, position within 0.2 mm.
    assert st.vu_mm_s == pytest.approx(80.0, abs=5.0)
    assert st.u_mm == pytest.approx(80.0 * tc, abs=0.2)


def test_live_sudden_stop_overshoot_bounded_and_fade():
    est = LiveEstimator(max_horizon_s=0.05, stale_s=0.1, fade_s=0.1)
    t = np.arange(0, 0.3, 0.01)
    feed(est, t, 100.0 * t, np.zeros_like(t))
    # The tracker stops sending (finger lifted): the position extrapolation is capped...
    far = est.state(t[-1] + 1.0, 0.025)
    assert far.u_mm - 100.0 * t[-1] <= 100.0 * 0.05 + 1e-6
    # ...and the output fades: full at 0.05 s, half at 0.15 s, zero from 0.2 s of silence.
    assert est.state(t[-1] + 0.05, 0.025).gain == 1.0
    assert est.state(t[-1] + 0.15, 0.025).gain == pytest.approx(0.5)
    assert est.state(t[-1] + 0.25, 0.025).gain == 0.0


def test_live_rotation_unwrap_and_bad_samples():
    est = LiveEstimator()
    t = np.arange(0, 0.1, 0.01)
    phi = (350.0 + 100.0 * t) % 360.0  # crosses 360 -> 0
    feed(est, t, np.zeros_like(t), np.zeros_like(t), phi)
    st = est.state(t[-1], 0.025)
    assert st.omega_deg_s == pytest.approx(100.0, rel=1e-6)
    assert not est.push(float("nan"), 0, 0, 0)
    assert not est.push(0.05, 0, 0, 0)
    assert est.counts["nonfinite"] == 1 and est.counts["backwards"] == 1


def test_live_source_reads_stream():
    text = "t_s,u_mm,v_mm,phi_deg\n0,0,0,0\n0.01,0.8,0,0\ngarbage\n0.02,1.6,0,0\n"
    src = LiveSource(io.StringIO(text))
    assert src.wait_first(timeout_s=5)
    deadline = time.monotonic() + 5
    while not src.finished and time.monotonic() < deadline:
        src.poll()
        time.sleep(0.001)
    assert src.finished
    assert src.estimator.counts["nonfinite"] == 1
    assert src.estimator.state(0.02, 0.025).vu_mm_s == pytest.approx(80.0)
