"""``haptex-inspect``: summarise, validate (and plot) tactile assets."""
from __future__ import annotations

import json
import sys
from pathlib import Path

import click
import numpy as np

from playback.cli_common import EXIT_BAD_INPUT, FiniteFloat, PathParam, command, common_options, warn_ignored_options
from playback.errors import HaptexError, InputError, one_line, shown_text as _shown


def _upper(tables) -> str:
    """"95 % bound x %; " when the asset stores the bound of its measured RMS error."""
    bound = tables.attrs.get("rms_rel_error_upper95")
    return "" if bound is None else f"95 % bound {float(bound):.2%}; "


def summary(path: str) -> str:
    """A readable multi-line summary of an asset."""
    import h5py

    from playback.asset import read_asset

    asset = read_asset(path)
    t = asset.tables
    p = asset.perception
    lines = [
        f"{path}: haptex tactile asset {_shown(asset.format_version)} ({_shown(asset.generator)})",
        f"  source     {_shown(asset.source_kind)}: {_shown(asset.source_name)}",
        f"  surface    {asset.surface_shape[1]} x {asset.surface_shape[0]} px at {asset.pixel_size_um:g} um "
        f"= {asset.surface_shape[1] * asset.pixel_size_um / 1000:.2f} x {asset.surface_shape[0] * asset.pixel_size_um / 1000:.2f} mm, "
        f"{'periodic' if asset.surface_periodic else 'not periodic'}",
    ]
    with h5py.File(path, "r") as f:
        s = f["surface"]
        if "lattice" in s:
            la = s["lattice"].attrs
            lines.append(f"  lattice    t1 = {np.round(la['t1_px'], 2).tolist()} px, t2 = {np.round(la['t2_px'], 2).tolist()} px, "
                         f"confidence {float(la['confidence']):.2f}")
        if "roughness" in s:
            ra = s["roughness"].attrs
            lines.append("  roughness  " + ", ".join(f"{k} {float(v):.3g}" for k, v in ra.items() if np.ndim(v) == 0 and not isinstance(v, str)))
        h = s["height"][()]
        lines.append(f"  heights    RMS {float(np.std(h)):.3g} um, range {float(h.min()):.3g} .. {float(h.max()):.3g} um")
        report = json.loads(f["report"].attrs["json"]) if "report" in f else {}
    lines += [
        f"  perception base {np.asarray(p['base_frequencies_hz']).tolist()} Hz, summation exponent {float(p['summation_exponent']):g}, "
        f"footprint sigma {float(p['footprint_sigma_mm']):g} mm, condition number {float(p.get('condition_number', float('nan'))):.1f}",
        f"             thresholds: {_shown(p.get('threshold_provenance', '?'))}",
        f"  tables     {t.shape[0]} directions x {t.shape[1]} speeds x {t.shape[2]} x {t.shape[3]} nodes, "
        f"grid {t.grid_spacing_mm:.3g} mm, {'wrapping' if t.periodic else 'mirrored at the edges'}",
        f"             directions {np.round(t.direction_deg, 2).tolist()} deg",
        f"             speeds {np.round(t.speed_mm_s, 2).tolist()} mm/s",
        f"             a40 mean {float(t.a40.mean()):.3g} um (max {float(t.a40.max()):.3g}), "
        f"a320 mean {float(t.a320.mean()):.3g} um (max {float(t.a320.max()):.3g})",
        # The tolerance bounds the RMS (and its 95 % bound), not the max: printed beside it.
        f"             measured error vs reference: RMS {t.rms_rel_error:.2%} ({_upper(t)}tolerance on the RMS"
        f" {t.tolerance:.2%}), max {t.max_rel_error:.2%}, {int(t.attrs.get('n_check_samples', 0))} samples",
        f"  scene      {asset.n_contactors} contactors; {'default scene' if not asset.scene_text else 'scene file as given is stored'}",
        f"  file       {Path(path).stat().st_size / 1e6:.2f} MB",
    ]
    photo_lattice = report.get("lattice")
    if isinstance(photo_lattice, dict) and "tile_explained_variance" in photo_lattice:
        where = "the photo's variance"
        if "region_px" in photo_lattice:
            x0, y0, w, h = photo_lattice["region_px"]
            where = f"the variance of the central {w} x {h} px at ({x0}, {y0}), where it was averaged"
        lines.append(f"  tile       explains {photo_lattice['tile_explained_variance']:.1%} of {where}")
    shading = report.get("shading")
    if isinstance(shading, dict) and "light_slant_deg" in shading:
        if shading.get("light_given"):
            how = "given"
        else:
            how = "estimated" + (f" on {_shown(shading['light_estimated_on'])}" if "light_estimated_on" in shading else "")
            how += ", UNRELIABLE" if shading.get("light_albedo_at_bound") else ""
        lines.append(f"  shading    {_shown(shading.get('method', '?'))}, light slant {float(shading['light_slant_deg']):.1f} deg, "
                     f"tilt {float(shading['light_tilt_deg']):.1f} deg ({how}); solved on {_shown(shading.get('solved_on', '?'))}, "
                     f"weave visibility {float(shading.get('weave_visibility', float('nan'))):.3f}")
        # The shading's warnings, as the compile printed them (the estimated light's note first).
        lines += [f"  warning    {_shown(w)}" for w in shading.get("warnings", [])]
    rough = report.get("roughness")
    if isinstance(rough, dict) and "warning" in rough:
        lines.append(f"  warning    {_shown(rough['warning'])}")
    if "relief_warning" in report:  # a height map's implausible relief (likely a unit error)
        lines.append(f"  warning    {_shown(report['relief_warning'])}")
    if "out_of_gamut_fraction" in report:
        lines.append(f"  gamut      {report['out_of_gamut_fraction']:.1%} of table values out of gamut (max measure {report['out_of_gamut_max']:.3g})")
    for key in ("fabric", "pixel_size", "relief", "surface"):
        if key in report:
            lines.append(f"  {key:<10} {_shown(report[key])}")
    return "\n".join(lines)


def is_playback_record(path: str) -> bool:
    """True for an HDF5 file written by ``haptex-play --record``."""
    import h5py

    from playback.asset import H5_READ_ERRORS
    from playback.record import RECORD_FORMAT

    try:
        with h5py.File(path, "r") as f:
            return f.attrs.get("format") == RECORD_FORMAT
    except H5_READ_ERRORS:
        return False  # not HDF5, or corrupt: the asset reader gives the one-line error


def record_summary(path: str) -> str:
    """A readable multi-line summary of a playback record (``haptex-play --record``).

    Counts and statistics are computed from the ``/frames`` datasets (so they hold for any
    record version); the run's own summary attributes fill in what the datasets cannot tell.
    Send error = time the transport accepted the packet minus its due time (window start minus
    the lead); drift = median send error over the last tenth of the frames minus the first tenth
    (the player's definitions, docs/usb-protocol.md). A corrupt or malformed record is one
    :class:`~playback.errors.InputError` line.
    """
    from playback.asset import corrupt_file_errors

    with corrupt_file_errors(path, "playback record"):
        return _record_summary(path)


def _record_summary(path: str) -> str:
    import h5py

    from playback.interp import FLAG_NAMES

    def ms(x: float) -> str:
        return f"{round(float(x), 3) + 0.0:.3f}"  # + 0.0: no "-0.000" from rounding noise

    def attr(f, key, default=None):
        value = f.attrs.get(key, default)
        if isinstance(value, bytes):
            value = value.decode()
        return value.item() if isinstance(value, np.generic) else value

    with h5py.File(path, "r") as f:
        fr = f["frames"]
        n = int(fr["t_s"].shape[0])
        n_contactors = int(fr["a40"].shape[1])
        n_channels = int(fr["codes"].shape[2])
        frame_ms = float(attr(f, "frame_ms", 25.0))
        lead_ms = float(attr(f, "lead_ms", float("nan")))
        prep_ms = attr(f, "prep_ms")
        index = fr["index"][()]
        late = fr["late"][()].astype(bool)
        deadline, sent = fr["deadline_s"][()], fr["sent_s"][()]
        render_us = fr["render_us"][()].astype(np.float64)
        latency_us = fr["latency_us"][()].astype(np.float64)
        clamped = fr["clamped"][()].astype(np.int64)
        nonfinite = fr["nonfinite"][()].astype(np.int64)
        flags = fr["flags"][()]
        a40, a320 = fr["a40"], fr["a320"]
        a40_max = float(np.max(a40)) if n else float("nan")
        a320_max = float(np.max(a320)) if n else float("nan")
        waveforms = f["waveforms/volts"].shape if "waveforms/volts" in f else None
        rate = attr(f["waveforms"], "sample_rate_hz") if waveforms else None
        mode, device, clock = (_shown(attr(f, k, "?")) for k in ("mode", "device", "clock"))
        scheduling = attr(f, "scheduling")
        scheduling = None if scheduling is None else _shown(scheduling)
        skipped = attr(f, "frames_skipped")
        not_recorded = attr(f, "frames_not_recorded")
        stopped_by, zero_sent = _shown(attr(f, "stopped_by", "?")), attr(f, "zero_frame_sent")
        asset, version = _shown(attr(f, "asset", "?")), _shown(attr(f, "format_version", "?"))
        err_max = attr(f, "tables_max_rel_error")
        shapes = {name: fr[name].shape for name in ("index", "late", "deadline_s", "sent_s", "render_us",
                                                    "latency_us", "clamped", "nonfinite", "flags", "a40", "a320",
                                                    "codes")}
    for name, shape in shapes.items():
        if shape[:1] != (n,):
            raise InputError(path, f"malformed playback record (/frames/{name} has shape {shape},"
                                   f" /frames/t_s has {n} frames)")
    if skipped is None:  # older records: gaps in the frame numbers are the skipped frames
        skipped = int(index[-1] + 1 - n) if n else 0
    head = f"{path}: haptex-play record {version} (mode {mode}, device {device}, {clock} clock"
    head += f", {scheduling})" if scheduling else ")"
    lines = [head, f"  asset      {asset}"]
    if not n:
        lines.append("  frames     none sent")
        lines.append(f"  stop       {stopped_by}; all-zero frame sent: {'yes' if zero_sent else 'no'}")
        return "\n".join(lines)
    duration = (deadline[-1] - deadline[0]) + frame_ms * 1e-3  # the schedule they span
    lines.append(f"  frames     {n} sent over {duration:.2f} s ({frame_ms:g} ms each), {int(skipped)} skipped; "
                 f"{n_contactors} contactors, {n_channels} device channels")
    timing = f"  timing     {int(late.sum())} late (accepted after their window started)"
    if np.isfinite(lead_ms):
        send_err = (sent - (deadline - lead_ms * 1e-3)) * 1e3
        m = max(1, n // 10)
        drift = float(np.median(send_err[-m:]) - np.median(send_err[:m]))
        timing += (f", worst {float(np.max(sent - deadline)) * 1e3:+.2f} ms from window start; lead {lead_ms:g} ms"
                   + (f", prep {float(prep_ms):g} ms" if prep_ms is not None else "")
                   + f"\n             send error median {ms(np.median(send_err))} ms, p99 {ms(np.percentile(send_err, 99))} ms, "
                   f"max {ms(send_err.max())} ms; drift {ms(drift)} ms")
    if not_recorded:
        lines.append(f"  record     {int(not_recorded)} later frames sent and not recorded (the record's size limit)")
    lines.append(timing)
    lines.append(f"  render     median {np.median(render_us):.0f} us, p99 {np.percentile(render_us, 99):.0f} us, "
                 f"max {render_us.max():.0f} us; latency median {np.median(latency_us):.0f} us, max {latency_us.max():.0f} us")
    flag_counts = ", ".join(f"{name} {int(np.count_nonzero(flags & bit))}" for bit, name in FLAG_NAMES.items())
    lines.append(f"  safety     {int(clamped.sum())} contactor amplitudes clamped (in {int(np.count_nonzero(clamped))} frames), "
                 f"{int(nonfinite.sum())} non-finite or negative set to 0")
    lines.append(f"  flags      {flag_counts} (contactor-frames)")
    amp = f"  amplitude  max a40 {a40_max:.3g} um, a320 {a320_max:.3g} um before calibration"
    if err_max is not None:
        amp += f"; tables' stated max error {float(err_max):.2%}"
    lines.append(amp)
    if waveforms:
        lines.append(f"  waveforms  {waveforms[0]} samples x {waveforms[1]} channels at {float(rate):g} Hz")
    lines.append(f"  stop       {stopped_by}; all-zero frame sent: {'yes' if zero_sent else 'no'}")
    return "\n".join(lines)


@command()
@click.argument("files", nargs=-1, required=True, type=PathParam(dir_okay=False))
@click.option("--validate", is_flag=True, help="Check each file against schemas/asset.schema.json and the reader; exit 1 if any fails.")
@click.option("--plot", "plot_path", type=PathParam(dir_okay=False), help="Write a PNG of the asset (or playback record); needs matplotlib.")
@click.option("--speed", type=FiniteFloat(min=0, min_open=True, max=2000), default=80.0, show_default=True, help="Speed (mm/s) of the plotted a40/a320 maps.")
@click.option("--direction", type=FiniteFloat(), default=0.0, show_default=True, help="Direction (deg) of the plotted maps.")
@common_options
def main(files, validate, plot_path, speed, direction):
    """Print a summary of tactile assets (FILES), validate them, or plot them."""
    if validate and plot_path:  # (the plot was not made)
        raise click.UsageError("give one of --validate or --plot")
    if not plot_path:
        warn_ignored_options(["speed", "direction"], "--plot")
    if validate:
        from haptex_compile.asset_validate import validate_asset

        bad = 0
        for path in files:
            problems = validate_asset(path)
            if problems:
                bad += 1
                for line in problems:
                    click.echo(f"haptex-inspect: invalid: {line}", err=True)
            else:
                click.echo(f"{path}: valid haptex tactile asset")
        if bad:
            sys.exit(EXIT_BAD_INPUT)
        return
    if plot_path:
        if len(files) != 1:
            raise click.UsageError("--plot takes one file")
        from haptex_compile.plots import plot_file

        plot_file(files[0], plot_path, speed_mm_s=speed, direction_deg=direction)
        click.echo(f"wrote {plot_path}")
        return
    from playback.asset import refuse_crashing

    # Every file is summarised, a bad one in one line, as --validate checks every one (the
    # first bad file ended the run: `haptex-inspect *.tact.h5` stopped there).
    bad = 0
    for path in files:
        try:
            refuse_crashing(path)  # before this process opens it: a corrupt file may crash libhdf5
            click.echo(record_summary(path) if is_playback_record(path) else summary(path))
        except BrokenPipeError:  # stdout's reader left: no file after this one can be shown
            raise
        except (HaptexError, OSError) as exc:
            bad += 1
            click.echo(f"haptex-inspect: error: {one_line(exc)}", err=True)
    if bad:
        sys.exit(EXIT_BAD_INPUT)
