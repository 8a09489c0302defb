"""``haptex-play``: stream a tactile asset to the stimulator (or its emulator) along a trajectory."""
from __future__ import annotations

import contextlib
import logging
import sys

import click

from playback.cli_common import FiniteFloat, PathParam, command, common_options, refuse_overwrites, warn_ignored_options

LOG = logging.getLogger("haptex.play")


@command()
@click.argument("asset", type=PathParam(dir_okay=False))
@click.option("--device", "device", default="sim", show_default=True,
              help="sim (emulated controller via pyusb), usb, null, or file:PATH (raw packets).")
@click.option("--profile", "profile_path", type=PathParam(dir_okay=False), default=None,
              help="Device profile TOML (default: the built-in HAPTEX profile; for sim, null and file devices sized to the asset's array).")
@click.option("--sweep", default=None, metavar="SPEC",
              help="Constant motion, e.g. speed=80,direction=0,duration=5[,u=0,v=0,phi=0] (mm/s, deg, s, mm).")
@click.option("--trajectory", "trajectory_csv", type=PathParam(dir_okay=False), default=None,
              help="CSV with header t_s,u_mm,v_mm,phi_deg.")
@click.option("--live", is_flag=True, help="Read t_s,u_mm,v_mm,phi_deg lines from stdin as they arrive.")
@click.option("--mode", type=click.Choice(["tables", "direct"]), default="tables", show_default=True,
              help="tables: interpolate the asset's tables; direct: the compiler's reference renderer.")
@click.option("--record", "record_path", type=PathParam(dir_okay=False), default=None,
              help="Save frames, codes and packets to this HDF5 file.")
@click.option("--waveforms", is_flag=True, help="Also record the emulator's drive waveforms (--device sim).")
@click.option("--waveform-rate", type=FiniteFloat(min=640.0, max=192000.0), default=8000.0, show_default=True,
              help="Waveform sample rate (Hz; at least twice 320 Hz, at most 192 kHz).")
@click.option("--fast", is_flag=True,
              help="Run unpaced on a virtual clock (no real-time waiting); not for --device usb or --live.")
@click.option("--lead-ms", type=FiniteFloat(min=0.0, max=1000.0), default=5.0, show_default=True,
              help="Send each frame this long before its window starts (a frame is late if sent after that start).")
@click.option("--prep-ms", type=FiniteFloat(min=0.0, max=1000.0), default=2.0, show_default=True,
              help="Wake up this long before each send to render (absorbs OS wake-up latency).")
@click.option("--realtime/--no-realtime", default=True, show_default=True,
              help="Ask for real-time scheduling (SCHED_FIFO, else nice) while playing on the real clock; "
                   "falls back silently (-v tells) when not permitted.")
@click.option("--max-frames", type=int, default=None, help="Stop after this many frames.")
@common_options
def main(asset: str, device: str, profile_path: str | None, sweep: str | None, trajectory_csv: str | None,
         live: bool, mode: str, record_path: str | None, waveforms: bool, waveform_rate: float, fast: bool,
         lead_ms: float, prep_ms: float, realtime: bool, max_frames: int | None) -> None:
    """Play ASSET (a .tact.h5 tactile asset) on a vibrotactile array.

    Frames are scheduled every frame period (25 ms) on the monotonic clock. The default device is
    the emulator (sim), run in real time; add --fast for an unpaced dry run. Ctrl-C (or SIGTERM,
    SIGHUP) sends an all-zero frame, finishes the record and exits 0.
    """
    from playback.asset import read_asset
    from playback.clock import MonotonicClock, VirtualClock
    from playback.device import load_profile
    from playback.errors import InputError
    from playback.player import Player
    from playback.record import Recorder
    from playback.trajectory import LiveSource, parse_sweep, read_csv_trajectory, sweep_trajectory
    from playback.transport import make_transport

    chosen = [x for x in (sweep is not None, trajectory_csv is not None, live) if x]
    if len(chosen) != 1:
        raise click.UsageError("give exactly one of --sweep, --trajectory or --live")
    if waveforms and device != "sim":
        raise click.UsageError("--waveforms needs --device sim (only the emulator synthesises waveforms)")
    if waveforms and record_path is None:  # (they were synthesised for nothing)
        raise click.UsageError("--waveforms needs --record (the waveforms are saved in the record)")
    if not waveforms:
        warn_ignored_options(["waveform_rate"], "--waveforms")
    if fast and (device == "usb" or live):
        raise click.UsageError("--fast is for dry runs: not with --device usb or --live")
    if max_frames is not None and max_frames < 1:
        raise click.UsageError("--max-frames must be >= 1")

    # Nothing this run reads is overwritten (``--record`` on the asset replaced it).
    sink = [("the device file", device[5:])] if device.startswith("file:") else []
    refuse_overwrites([("--record", record_path)] if record_path else [],
                      [p for p in (asset, profile_path, trajectory_csv) if p], direct=sink)
    data = read_asset(asset, load_surface=(mode == "direct"))
    profile = load_profile(profile_path)
    if profile_path is None and device != "usb" and profile.count != data.n_contactors:
        # No real device: the built-in profile's calibration with one channel per contactor of
        # the asset's own array, so any scene plays on the simulator and the sinks.
        from playback.device import DEFAULT_PROFILE, profile_from_dict

        n = data.n_contactors
        doc = {**DEFAULT_PROFILE, "contactors": {"count": n, "n_channels": n, "channel": list(range(n))}}
        profile = profile_from_dict(doc, f"built-in profile for {n} contactors")
    if profile.count != data.n_contactors:
        raise InputError(asset, f"scene has {data.n_contactors} contactors, the device profile maps {profile.count}")
    if sweep is not None:
        spec = parse_sweep(sweep)
        source = sweep_trajectory(spec["speed"], spec["direction"], spec["duration"],
                                  u0_mm=spec["u"], v0_mm=spec["v"], phi_deg=spec["phi"])
    elif trajectory_csv is not None:
        source = read_csv_trajectory(trajectory_csv)
    else:
        source = LiveSource(sys.stdin, name="stdin")
    clock = VirtualClock() if fast else MonotonicClock()
    transport, emulator = make_transport(device, profile, clock)
    if record_path is not None:
        from playback import protocol

        recording = Recorder(record_path, data.n_contactors, profile.n_channels, protocol.frame_size(profile.n_channels))
    else:
        recording = contextlib.nullcontext()
    with recording as recorder:  # (a run that fails before the record is finished leaves no file)
        player = Player(data, profile, transport, source, clock=clock, mode=mode, recorder=recorder,
                        lead_ms=lead_ms, prep_ms=prep_ms, realtime=realtime and not fast, max_frames=max_frames,
                        emulator=emulator, waveform_rate_hz=waveform_rate if waveforms else None)
        summary = player.run()
    click.echo(f"haptex-play: {summary.line()}")
    if record_path is not None:
        click.echo(f"haptex-play: recorded {record_path}")
