"""``haptex-compile``: texture sources to tactile assets (a thin click layer over the library)."""
from __future__ import annotations

import logging
import math
import os
import signal
import sys
from pathlib import Path

import click

from playback.cli_common import (EXIT_BAD_INPUT, FiniteFloat, PathParam, command, common_options, refuse_overwrites,
                                 show_progress, warn_ignored_options)
from playback.file_modes import new_file_mode
from playback.paths import replace_with_bytes
from playback.stop_signals import StopRequested, end_with_parent, exit_now, exit_status, worker_signals

LOG = logging.getLogger("haptex.compile")


def _parse_light(ctx: click.Context, param: click.Parameter, value: str | None):
    if value is None:
        return None
    try:
        slant, tilt = (float(v) for v in value.split(","))
    except ValueError:
        raise click.BadParameter("expected SLANT,TILT in degrees, e.g. 30,45") from None
    if not (0 <= slant < 90):
        raise click.BadParameter("slant must be in [0, 90) degrees")
    if not math.isfinite(tilt):  # (any finite tilt is an angle; inf failed only in the solver)
        raise click.BadParameter("tilt must be a finite number of degrees")
    return slant, tilt


def _parse_pixel(ctx: click.Context, param: click.Parameter, value: str | None):
    if value is None:
        return None
    from haptex_compile.units import parse_pixel_size_um

    try:
        return parse_pixel_size_um(value)
    except ValueError as exc:
        raise click.BadParameter(str(exc)) from None


def _make_word(path: str) -> str:
    """`path` as one word of a Make rule: spaces, '#' and '$' escaped (a path with a space was
    two prerequisites)."""
    return path.replace("$", "$$").replace("#", "\\#").replace(" ", "\\ ")


def _write_dependency_file(md_path: str, lines: list[str]) -> None:
    """Write the rules `lines` to `md_path` atomically, as bytes: a file name's bytes that are not
    UTF-8 are written as they are, as Make reads them (writing them as text was a
    UnicodeEncodeError traceback, and left the temporary file)."""
    Path(md_path).parent.mkdir(parents=True, exist_ok=True)  # as the assets' folders are
    replace_with_bytes(md_path, ("\n".join(lines) + "\n").encode("utf-8", "surrogateescape"), new_file_mode())


def _dependencies(spec: str, scene_path: str | None, kes: str | None, scene) -> list[str]:
    deps = []
    if not spec.lower().startswith("brownian:"):
        deps.append(spec)
    for extra in (scene_path, kes, getattr(scene, "thresholds_csv", None)):
        if extra:
            deps.append(extra)
    return deps


_IN_WORKER = False  # this process is a --jobs worker (see _init_worker)
_COMPILING = False  # and is compiling an input


def _worker_stop(signum: int, frame: object) -> None:
    """SIGTERM or SIGHUP in a --jobs worker: the compile under way stops as Ctrl-C stops it
    (its temporary files removed; :func:`_one` then ends the worker, which would otherwise take
    the next input); an idle worker, waiting for work, exits at once (raising there would
    print multiprocessing's traceback)."""
    if _COMPILING:
        raise StopRequested(signal.Signals(signum).name)
    exit_now(signum)


def _init_worker(parent_pid: int) -> None:
    global _IN_WORKER
    _IN_WORKER = True
    worker_signals(_worker_stop)
    end_with_parent(parent_pid)  # a parent killed outright (SIGKILL) stops its workers too


def _one(job: dict) -> tuple[str, str | None]:
    """Compile one input (runs in a worker process for --jobs); returns (input, error line or None)."""
    from playback.errors import HaptexError, one_line, shown_text
    from haptex_compile.compile import compile_source

    global _COMPILING
    _COMPILING = True
    try:
        compile_source(job["spec"], job["out"], job["scene"], job["options"], exr_path=job["exr"],
                       exr_speed=job["exr_speed"], exr_direction=job["exr_direction"])
        return job["spec"], None
    except (HaptexError, OSError, ValueError, MemoryError) as exc:
        if job["debug"]:
            raise
        message = one_line(exc)
        if isinstance(exc, MemoryError):
            message = f"out of memory ({message})"
        # The message names the input (several may be compiled in one run), as it shows it.
        spec = shown_text(job["spec"], limit=None)
        return job["spec"], message if spec in message else f"{spec}: {message}"
    except KeyboardInterrupt as exc:  # (in a worker: a stop signal, see _worker_stop)
        if _IN_WORKER:
            os._exit(exit_status(exc))  # its files are cleaned up; it takes no further input
        raise
    finally:
        _COMPILING = False


def _worker_result(job: dict, future) -> tuple[str, str | None]:
    """:func:`_one`'s result from a --jobs worker; a worker that died (killed, or out of
    memory) fails its input and those queued behind it in one line each, not a traceback."""
    from concurrent.futures.process import BrokenProcessPool
    from playback.errors import shown_text

    try:
        return future.result()
    except BrokenProcessPool:
        return job["spec"], f"{shown_text(job['spec'], limit=None)}: not compiled: a worker process stopped (killed, or out of memory)"


@command()
@click.argument("inputs", nargs=-1, required=True)
@click.option("-o", "--output", type=PathParam(dir_okay=False), help="Output asset (one input).")
@click.option("--out-dir", type=PathParam(file_okay=False), help="Folder for the assets of many inputs (NAME.tact.h5).")
@click.option("--scene", "scene_path", type=PathParam(dir_okay=False), help="Scene TOML (default: HAPTEX 6 x 4 array, 10-200 mm/s, all directions).")
@click.option("--pixel-size", callback=_parse_pixel, help="Pixel size, e.g. 10um or 0.01mm, at most 1 m (default: image metadata, else 20 um with a warning).")
@click.option("--relief-um", type=FiniteFloat(min=0, min_open=True, max=1e6), help="Height scale of a photo's relief (see --relief-kind); default 10 um RMS with a warning.")
@click.option("--relief-kind", type=click.Choice(["rms", "pv"]), default="rms", show_default=True, help="What --relief-um means: RMS or peak-to-valley.")
@click.option("--sfs", type=click.Choice(["default", "accurate", "tsai-shah"]), default="default", show_default=True,
              help="Shape-from-shading solver for photos: accurate is about 3x slower and more exact on clean images (it fits noise closer); tsai-shah is the paper's, for comparison.")
@click.option("--light", callback=_parse_light, help="Light direction SLANT,TILT in degrees (default: estimated from the photo).")
@click.option("--kes", type=PathParam(dir_okay=False), help="KES-F file giving a photo's height scale (SMD).")
@click.option("--roughness", type=click.Choice(["auto", "none"]), default="auto", show_default=True, help="Fractal roughness of photos.")
@click.option("--seed", type=click.IntRange(min=0), default=0, show_default=True, help="Seed of every random choice (results are reproducible).")
@click.option("--exr", "exr_path", type=PathParam(dir_okay=False), help="Also write height, a40, a320 maps as an EXR (one input).")
@click.option("--exr-speed", type=FiniteFloat(min=0, min_open=True, max=2000), default=80.0, show_default=True, help="Speed (mm/s) of the EXR amplitude maps.")
@click.option("--exr-direction", type=FiniteFloat(), default=0.0, show_default=True, help="Direction (deg) of the EXR amplitude maps.")
@click.option("--md", "md_path", type=PathParam(dir_okay=False), help="Write a Make dependency file.")
@click.option("-j", "--jobs", type=click.IntRange(min=1), default=1, show_default=True, help="Inputs compiled in parallel.")
@common_options
def main(inputs, output, out_dir, scene_path, pixel_size, relief_um, relief_kind, sfs, light, kes, roughness, seed,
         exr_path, exr_speed, exr_direction, md_path, jobs, debug=False):
    """Compile INPUT(s) into tactile assets (.tact.h5).

    INPUT is a height map (.npy, .exr; µm), a photograph (.jpg .png .bmp .tif), a Kawabata
    file (.kes.json, .kes.csv) or a Brownian spec such as
    brownian:H=0.7,size=1024,pixel=10um,rms=5um,seed=3.
    """
    from dataclasses import replace

    from haptex_compile.io_scene import read_scene
    from haptex_compile.kes_source import batch_stems
    from haptex_compile.scene import default_scene
    from haptex_compile.sources import SourceOptions, input_kind, output_stem
    from playback.errors import InputError

    if (output is None) == (out_dir is None):
        raise click.UsageError("give exactly one of -o/--output or --out-dir")
    if output is not None and len(inputs) != 1:
        raise click.UsageError("-o/--output takes one input; use --out-dir for several")
    for spec in inputs:
        input_kind(spec)  # unknown types fail before any work
    if exr_path is None:
        warn_ignored_options(["exr_speed", "exr_direction"], "--exr")
    if relief_um is None:
        if any(input_kind(s) == "image" for s in inputs):  # (other inputs' sources say it of every photo option)
            warn_ignored_options(["relief_kind"], "--relief-um")
    elif kes is not None:  # (--relief-um was used and the Kawabata file's SMD ignored)
        raise click.UsageError("--relief-um and --kes both set a photo's height scale: give one")
    if exr_path is not None and len(inputs) != 1:
        raise click.UsageError("--exr takes one input")
    scene = read_scene(scene_path) if scene_path else default_scene()
    options = SourceOptions(pixel_size_um=pixel_size, relief_um=relief_um, relief_kind=relief_kind, sfs=sfs,
                            light=light, kes_path=kes, roughness=roughness, seed=seed)
    # One asset per input, and per fabric of a Kawabata CSV of several (a batch file).
    entries = []  # (input, its row in a batch CSV or None, the asset's file stem)
    for spec in inputs:
        stems = batch_stems(spec, output_stem(spec)) if input_kind(spec) == "kes" else None
        if stems is not None and output is not None:
            raise InputError(spec, f"holds {len(stems)} fabrics: give --out-dir for an asset of each")
        entries += [(spec, None, output_stem(spec))] if stems is None else [(spec, k, st) for k, st in enumerate(stems)]
    if exr_path is not None and len(entries) != 1:
        raise click.UsageError("--exr takes one input (of one fabric)")
    outs = [output] if output is not None else [str(Path(out_dir) / f"{stem}.tact.h5") for _, _, stem in entries]
    # Nothing this run reads is overwritten, and no output twice (a.png and a.jpg to --out-dir).
    writes = [("-o" if output is not None else f"the asset of {s}" + ("" if k is None else f" (fabric {k + 1})"), o)
              for (s, k, _), o in zip(entries, outs)]
    writes += [(what, path) for what, path in (("--exr", exr_path), ("--md", md_path)) if path]
    refuse_overwrites(writes, sorted({d for s in inputs for d in _dependencies(s, scene_path, kes, scene)}))
    jobs_list = [{"spec": s, "out": o, "scene": scene, "options": replace(options, kes_row=k), "exr": exr_path,
                  "exr_speed": exr_speed, "exr_direction": exr_direction, "debug": debug}
                 for (s, k, _), o in zip(entries, outs)]
    failures = []
    if jobs > 1 and len(jobs_list) > 1:
        from concurrent.futures import ProcessPoolExecutor  # here: multiprocessing costs start-up time

        with ProcessPoolExecutor(max_workers=jobs, initializer=_init_worker, initargs=(os.getpid(),)) as pool:
            try:
                results = [_worker_result(job, future) for job, future in
                           zip(jobs_list, [pool.submit(_one, job) for job in jobs_list])]
            except BaseException:
                # Stopped (or failed): the inputs not begun are dropped, and the workers told to
                # stop theirs, which they do as this process would (shutdown alone would compile
                # every input queued before returning). The pool's process table is private:
                # without it the workers finish their inputs.
                processes = list((getattr(pool, "_processes", None) or {}).values())  # (shutdown clears it)
                pool.shutdown(wait=False, cancel_futures=True)
                for process in processes:
                    process.terminate()
                raise
    else:
        results = []
        bar = click.progressbar(jobs_list, label="compiling", file=sys.stderr) if show_progress() and len(jobs_list) > 1 else None
        iterator = bar if bar is not None else jobs_list
        if bar is not None:
            bar.__enter__()
        try:
            for job in iterator:
                results.append(_one(job))
        finally:
            if bar is not None:
                bar.__exit__(None, None, None)
    for (spec, error), out in zip(results, outs):
        if error:
            failures.append(error)
            click.echo(f"haptex-compile: error: {error}", err=True)
        else:
            LOG.info("%s -> %s", spec, out)
    if md_path and not failures:
        lines = [f"{_make_word(out)}: {' '.join(map(_make_word, _dependencies(s, scene_path, kes, scene)))}"
                 for (s, _, _), out in zip(entries, outs)]
        _write_dependency_file(md_path, lines)
    if failures:
        sys.exit(EXIT_BAD_INPUT)
