"""``haptex-inspect``: summarise, validate (and plot) tactile assets."""
from __future__ import annotations

import json
import sys
from pathlib import Path

import click
import numpy as np

from playback.cli_common import EXIT_BAD_INPUT, common_options


def summary(path: str) -> str:
    """A readable multi-line summary of an asset."""
    import h5py

    from playback.asset import read_asset

    asset = read_asset(path)
    t = asset.tables
    p = asset.perception
    lines = [
        f"{path}: haptex tactile asset {asset.format_version} ({asset.generator})",
        f"  source     {asset.source_kind}: {asset.source_name}",
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
        f"             thresholds: {p.get('threshold_provenance', '?')}",
        f"  tables     {t.shape[0]} directions x {t.shape[1]} speeds x {t.shape[2]} x {t.shape[3]} nodes, "
        f"grid {t.grid_spacing_mm:.3g} mm, {'wrapping' if t.periodic else 'mirrored at the edges'}",
        f"             directions {np.round(t.direction_deg, 2).tolist()} deg",
        f"             speeds {np.round(t.speed_mm_s, 2).tolist()} mm/s",
        f"             a40 mean {float(t.a40.mean()):.3g} um (max {float(t.a40.max()):.3g}), "
        f"a320 mean {float(t.a320.mean()):.3g} um (max {float(t.a320.max()):.3g})",
        f"             measured error vs reference: RMS {t.rms_rel_error:.2%}, max {t.max_rel_error:.2%} "
        f"(tolerance {t.tolerance:.2%}, {int(t.attrs.get('n_check_samples', 0))} samples)",
        f"  scene      {asset.n_contactors} contactors; {'default scene' if not asset.scene_text else 'scene file as given is stored'}",
        f"  file       {Path(path).stat().st_size / 1e6:.2f} MB",
    ]
    if "out_of_gamut_fraction" in report:
        lines.append(f"  gamut      {report['out_of_gamut_fraction']:.1%} of table values out of gamut (max measure {report['out_of_gamut_max']:.3g})")
    for key in ("pixel_size", "relief", "surface"):
        if key in report:
            lines.append(f"  {key:<10} {report[key]}")
    return "\n".join(lines)


@click.command(context_settings={"help_option_names": ["-h", "--help"]})
@click.argument("files", nargs=-1, required=True, type=click.Path(dir_okay=False))
@click.option("--validate", is_flag=True, help="Check each file against schemas/asset.schema.json and the reader; exit 1 if any fails.")
@click.option("--plot", "plot_path", type=click.Path(dir_okay=False), help="Write a PNG of the asset (or playback record); needs matplotlib.")
@click.option("--speed", type=click.FloatRange(min=0, min_open=True), default=80.0, show_default=True, help="Speed (mm/s) of the plotted a40/a320 maps.")
@click.option("--direction", type=float, default=0.0, show_default=True, help="Direction (deg) of the plotted maps.")
@common_options
def main(files, validate, plot_path, speed, direction):
    """Print a summary of tactile assets (FILES), validate them, or plot them."""
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
    for path in files:
        click.echo(summary(path))
