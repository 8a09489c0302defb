"""Benchmark: hostile but well-formed inputs against the three tools, run as a user runs them.

Where ``bench_robustness`` damages files' bytes, this gives the tools inputs that parse and
are absurd or contradictory: scenes, Kawabata files and Brownian specs with values at or past
the ends of their ranges, height maps in the wrong unit by far, images of one pixel, option
values and combinations that cannot be honoured, names and attributes holding terminal escape
sequences, names at the file system's length limit, and a full disk (a file-size limit). Each case runs the tool in its own process (``python -c``, as the console scripts do)
with a time limit, and is classed by what a user sees:

* ``refused``: exit status 1 or 2, one line on stderr (``TOOL: error: ...``), no output file;
* ``accepted``: exit status 0; the tool's own warnings (``haptex...: WARNING: ...``) allowed;
  a compiled asset must pass the validator;
* anything else is a defect: ``traceback``, ``raw output`` (lines not in the tools' own formats,
  such as numpy's RuntimeWarnings), ``crash`` (killed by a signal), ``timeout``, ``partial
  output`` (an output file left by a failed run), ``invalid asset``, or an outcome other than
  the one the case expects (a refusal that should be a warning, or the reverse).

Run: ``python bench/bench_hostile_inputs.py [--quick] [--against DIR]`` (quick: every third
case). With ``--against``, every case also runs with the tools of another checkout (``DIR`` first
on ``PYTHONPATH``: for example a ``git worktree`` of an earlier commit), side by side in the
same run, as the baseline.
"""
from __future__ import annotations

import argparse
import json
import os
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Callable

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))  # the repo root, for tests.asset_factory

from tests.asset_factory import tool_argv  # noqa: E402

TIME_LIMIT_S = 300.0
OWN_LINE = re.compile(r"^haptex(\.\w+)*: (WARNING|INFO|ERROR): ")
SPEC = "brownian:H=0.7,size=24,pixel=20um,rms=5um,seed=1"
SPEC_64 = "brownian:H=0.7,size=64,pixel=20um,rms=5um,seed=1"  # an asset of 57 KB (tiny scene)
SPEC_200 = "brownian:H=0.7,size=200,pixel=20um,rms=5um,seed=1"  # 171 KB, its EXR 463 KB
ODD = os.fsdecode(b"n\xff\xfe #$1")  # a file name's bytes need not be UTF-8
KES = REPO / "samples" / "kes" / "cotton_poplin.kes.json"
# (name, what the case should give, tool, arguments ({d}: the case's folder), files to make
# there first: name -> text, bytes or a function of the path[, a file-size limit in bytes: a
# write past it fails as on a full disk])
Case = tuple


def _npy(scale: float, shape=(32, 32)) -> Callable[[Path], None]:
    return lambda p: np.save(p, scale * np.random.default_rng(0).standard_normal(shape))


def _png(shape, value=None) -> Callable[[Path], None]:
    def make(p: Path) -> None:
        import cv2
        pixels = np.full(shape, value, np.uint8) if value is not None else (
            np.random.default_rng(0).random(shape) * 255).astype(np.uint8)
        cv2.imwrite(str(p), pixels)
    return make


def _kes(**changes) -> str:
    doc = json.loads(KES.read_text(encoding="utf-8"))
    for key, value in changes.items():
        doc[key] = value
    return json.dumps(doc)


def _edited(path_of: Callable[[Path], Path], edit: Callable) -> Callable[[Path], None]:
    """A copy of the file `path_of(folder)` (made by an earlier case file) edited by `edit(f)`."""
    def make(p: Path) -> None:
        import h5py
        p.write_bytes(path_of(p.parent).read_bytes())
        with h5py.File(p, "r+") as f:
            edit(f)
    return make


def _asset(p: Path) -> None:
    from tests.asset_factory import write_test_asset
    write_test_asset(p)


def _set_attrs(**attrs) -> Callable:
    def edit(f) -> None:
        for key, value in attrs.items():
            f.attrs[key] = value
    return edit


def cases() -> list[Case]:
    scene = lambda text: {"s.toml": "[motion]\nspeeds_mm_s = [40, 80]\ndirections_deg = [0, 90]\ntolerance = 0.5\n" + text}
    tiny = ["--scene", "{d}/s.toml"]
    out = ["-o", "{d}/o.tact.h5"]
    play = ["{d}/a.tact.h5"]
    sweep = ["--sweep", "speed=80,duration=0.2", "--fast"]
    return [
        # scenes
        ("scene: speed 1e-300 mm/s", "refused", "haptex-compile", [SPEC, *out, *tiny],
         {"s.toml": "[motion]\nspeeds_mm_s = [1e-300]\n"}),
        ("scene: speed range 1e-300..1e-299 mm/s", "refused", "haptex-compile", [SPEC, *out, *tiny],
         {"s.toml": "[motion]\nspeed_range_mm_s = [1e-300, 1e-299]\n"}),
        ("scene: contactor at 1e300 mm", "refused", "haptex-compile", [SPEC, *out, *tiny],
         {"s.toml": "[array]\ncontactors_mm = [[1e300, 0.0]]\n"}),
        ("scene: grid spacing 1e-300 mm", "accepted", "haptex-compile", [SPEC, *out, *tiny],
         scene("[render]\ngrid_spacing_mm = 1e-300\n")),
        ("scene: base frequencies 0.001, 0.002 Hz", "refused", "haptex-compile", [SPEC, *out, *tiny],
         scene("[render]\nbase_frequencies_hz = [0.001, 0.002]\n")),
        ("scene: base frequencies 320, 40 Hz", "refused", "haptex-compile", [SPEC, *out, *tiny],
         scene("[render]\nbase_frequencies_hz = [320, 40]\n")),
        ("scene: 100 x 100 contactors", "refused", "haptex-compile", [SPEC, *out, *tiny],
         {"s.toml": "[array]\ngrid = { rows = 100, cols = 100, pitch_mm = 1.0 }\n"}),
        ("scene: a speed twice", "accepted", "haptex-compile", [SPEC, *out, *tiny],
         {"s.toml": "[motion]\nspeeds_mm_s = [40, 40]\ndirections_deg = [0]\ntolerance = 0.5\n"}),
        ("scene: not UTF-8", "refused", "haptex-compile", [SPEC, *out, *tiny], {"s.toml": b"\xff\xfe[motion]\n"}),
        ("scene: missing", "refused", "haptex-compile", [SPEC, *out, "--scene", "{d}/none.toml"], {}),
        ("scene: threshold CSV missing", "refused", "haptex-compile", [SPEC, *out, *tiny],
         scene("[render]\nthresholds_csv = 'none.csv'\n")),
        # Kawabata files
        ("KES: SMD 1e-300 um", "refused", "haptex-compile", ["{d}/k.kes.json", *out, *tiny],
         {"k.kes.json": _kes(smd_um={"warp": 1e-300, "weft": 1e-300})} | scene("")),
        ("KES: SMD 0.01 um", "accepted", "haptex-compile", ["{d}/k.kes.json", *out, *tiny],
         {"k.kes.json": _kes(smd_um={"warp": 0.01, "weft": 0.01})} | scene("")),
        ("KES: MIU 1e-300", "accepted", "haptex-compile", ["{d}/k.kes.json", *out, *tiny],
         {"k.kes.json": _kes(miu={"warp": 1e-300, "weft": 1e-300}, mmd={"warp": 0, "weft": 0})} | scene("")),
        ("KES: a byte-order mark", "accepted", "haptex-compile", ["{d}/k.kes.json", *out, *tiny],
         {"k.kes.json": b"\xef\xbb\xbf" + _kes().encode()} | scene("")),
        # Brownian specs
        ("spec: rms 1e300 um", "refused", "haptex-compile", ["brownian:H=0.7,size=24,rms=1e300um", *out, *tiny], scene("")),
        ("spec: rms 1e-300 um", "accepted", "haptex-compile", ["brownian:H=0.7,size=24,rms=1e-300um", *out, *tiny],
         scene("")),
        ("spec: size given twice", "refused", "haptex-compile", ["brownian:H=0.7,size=24,size=32", *out, *tiny], scene("")),
        ("spec: pixel 1e-300 um", "refused", "haptex-compile", ["brownian:H=0.7,size=24,pixel=1e-300um", *out, *tiny],
         scene("")),
        ("spec: H nan", "refused", "haptex-compile", ["brownian:H=nan,size=24", *out, *tiny], scene("")),
        # height maps and images
        ("height map: heights of 1e300 um", "refused", "haptex-compile", ["{d}/h.npy", *out, *tiny, "--pixel-size", "20um"],
         {"h.npy": _npy(1e300)} | scene("")),
        ("height map: heights of 1e30 um", "refused", "haptex-compile", ["{d}/h.npy", *out, *tiny, "--pixel-size", "20um"],
         {"h.npy": _npy(1e30)} | scene("")),
        ("height map: heights in nm (3000 um RMS)", "accepted", "haptex-compile",
         ["{d}/h.npy", *out, *tiny, "--pixel-size", "20um"], {"h.npy": _npy(3000.0)} | scene("")),
        ("height map: 1 x 40 px", "refused", "haptex-compile", ["{d}/h.npy", *out, *tiny, "--pixel-size", "20um"],
         {"h.npy": _npy(5.0, (1, 40))} | scene("")),
        ("image: 1 x 1 px", "refused", "haptex-compile", ["{d}/i.png", *out, *tiny], {"i.png": _png((1, 1))} | scene("")),
        ("image: constant", "refused", "haptex-compile", ["{d}/i.png", *out, *tiny],
         {"i.png": _png((64, 64), 128)} | scene("")),
        ("image: 8 x 8 px", "accepted", "haptex-compile", ["{d}/i.png", *out, *tiny, "--pixel-size", "20um",
                                                        "--relief-um", "5"], {"i.png": _png((8, 8))} | scene("")),
        # options
        ("--relief-um with --kes", "refused", "haptex-compile", ["{d}/i.png", *out, "--relief-um", "5", "--kes", str(KES)],
         {"i.png": _png((64, 64))}),
        ("--exr-speed without --exr", "accepted", "haptex-compile", [SPEC, *out, *tiny, "--exr-speed", "40"], scene("")),
        ("--light 95,30", "refused", "haptex-compile", ["{d}/i.png", *out, "--light", "95,30"], {"i.png": _png((64, 64))}),
        ("--relief-um nan", "refused", "haptex-compile", ["{d}/i.png", *out, "--relief-um", "nan"],
         {"i.png": _png((64, 64))}),
        ("-o the input", "refused", "haptex-compile", ["{d}/h.npy", "-o", "{d}/h.npy"], {"h.npy": _npy(5.0)}),
        ("input named with an escape sequence", "refused", "haptex-compile", ["{d}/no\x1b[31mne.npy", *out], {}),
        ("outputs named with 254 and 255 bytes (-o, --exr, --md)", "accepted", "haptex-compile",
         [SPEC, "-o", "{d}/" + "n" * 246 + ".tact.h5", "--exr", "{d}/" + "e" * 251 + ".exr", "--md",
          "{d}/" + "d" * 253 + ".d", *tiny], scene("")),
        ("-o named with 258 bytes", "refused", "haptex-compile", [SPEC, "-o", "{d}/" + "n" * 250 + ".tact.h5", *tiny],
         scene("")),
        ("full disk (file-size limit 20 KB)", "refused", "haptex-compile", [SPEC_64, *out, *tiny], scene(""), 20_000),
        ("full disk for --exr only (limit 300 KB)", "refused", "haptex-compile",
         [SPEC_200, *out, "--exr", "{d}/o.exr", *tiny], scene(""), 300_000),
        ("names with bytes that are not UTF-8, a space, '#' and '$'", "accepted", "haptex-compile",
         [f"{{d}}/{ODD}.npy", "-o", f"{{d}}/{ODD}.tact.h5", "--exr", f"{{d}}/{ODD}.exr", "--md", f"{{d}}/{ODD}.d",
          *tiny, "--pixel-size", "20um"], {f"{ODD}.npy": _npy(5.0)} | scene("")),
        # the player
        ("--sweep speed given twice", "refused", "haptex-play", [*play, "--sweep", "speed=80,speed=90,duration=1", "--fast"],
         {"a.tact.h5": _asset}),
        ("--sweep speed 1e300", "refused", "haptex-play", [*play, "--sweep", "speed=1e300,duration=1", "--fast"],
         {"a.tact.h5": _asset}),
        ("--sweep direction nan", "refused", "haptex-play", [*play, "--sweep", "speed=80,direction=nan,duration=1",
                                                              "--fast"], {"a.tact.h5": _asset}),
        ("--waveforms without --record", "refused", "haptex-play", [*play, *sweep, "--waveforms"], {"a.tact.h5": _asset}),
        ("--waveform-rate without --waveforms", "accepted", "haptex-play", [*play, *sweep, "--waveform-rate", "1000"],
         {"a.tact.h5": _asset}),
        ("--lead-ms nan", "refused", "haptex-play", [*play, *sweep, "--lead-ms", "nan"], {"a.tact.h5": _asset}),
        ("--record the asset", "refused", "haptex-play", [*play, *sweep, "--record", "{d}/a.tact.h5"], {"a.tact.h5": _asset}),
        ("trajectory: not UTF-8", "refused", "haptex-play", [*play, "--trajectory", "{d}/t.csv", "--fast"],
         {"a.tact.h5": _asset, "t.csv": b"\xff\xfe"}),
        ("trajectory: NaN and 1e300 rows", "accepted", "haptex-play", [*play, "--trajectory", "{d}/t.csv", "--fast"],
         {"a.tact.h5": _asset, "t.csv": "t_s,u_mm,v_mm,phi_deg\n0,0,0,0\n0.1,nan,0,0\n0.2,1e300,0,0\n0.5,4,0,0\n1,8,0,0\n"}),
        ("--record, names with bytes that are not UTF-8", "accepted", "haptex-play",
         [f"{{d}}/{ODD}.tact.h5", *sweep, "--record", f"{{d}}/{ODD}.h5"], {f"{ODD}.tact.h5": _asset}),
        ("--record into a full disk (limit 20 KB)", "refused", "haptex-play", [*play, *sweep, "--record", "{d}/r.h5"],
         {"a.tact.h5": _asset}, 20_000),
        ("profile: missing", "refused", "haptex-play", [*play, *sweep, "--profile", "{d}/none.toml"], {"a.tact.h5": _asset}),
        # the inspector
        ("asset: escape sequences and 5000 characters in attributes", "accepted", "haptex-inspect", ["{d}/b.tact.h5"],
         {"a.tact.h5": _asset, "b.tact.h5": _edited(lambda d: d / "a.tact.h5", _set_attrs(
             source_name="fab\nric\x1b[2J.jpg", generator="g" * 5000))}),
        ("asset: format attribute of 3000 characters", "refused", "haptex-inspect", ["{d}/b.tact.h5"],
         {"a.tact.h5": _asset, "b.tact.h5": _edited(lambda d: d / "a.tact.h5", _set_attrs(format="x\x1b[31m" * 600))}),
        ("--validate with --plot", "refused", "haptex-inspect", ["--validate", "--plot", "{d}/p.png", "{d}/a.tact.h5"],
         {"a.tact.h5": _asset}),
        ("--plot, names with bytes that are not UTF-8", "accepted", "haptex-inspect",
         ["--plot", f"{{d}}/{ODD}.png", f"{{d}}/{ODD}.tact.h5"], {f"{ODD}.tact.h5": _asset}),
        ("--speed without --plot", "accepted", "haptex-inspect", ["{d}/a.tact.h5", "--speed", "30"], {"a.tact.h5": _asset}),
    ]


def _make(folder: Path, files: dict[str, object]) -> None:
    for name, content in files.items():
        path = folder / name
        if isinstance(content, bytes):
            path.write_bytes(content)
        elif isinstance(content, str):
            path.write_text(content, encoding="utf-8")
        else:
            content(path)


def _outcome(tool: str, rc: int | None, stderr: str, new_outputs: list[Path]) -> tuple[str, str]:
    """(outcome, the line a user reads) of a run: see the module docstring."""
    lines = [line for line in stderr.splitlines() if line.strip()]
    said = next((line for line in lines if line.startswith(f"{tool}: error: ")), lines[-1] if lines else "")
    if rc is None:
        return "timeout", said
    if rc < 0:
        return "crash", f"signal {-rc}"
    if "Traceback (most recent call last)" in stderr:
        return "traceback", lines[-1] if lines else ""
    raw = [line for line in lines if not (OWN_LINE.match(line) or line.startswith(f"{tool}: "))]
    if raw:
        return "raw output", raw[0]
    if rc == 0:
        from haptex_compile.asset_validate import validate_asset
        problems = [p for out in new_outputs if out.name.endswith(".tact.h5") for p in validate_asset(out)]
        return ("invalid asset", problems[0]) if problems else ("accepted", said)
    if new_outputs:
        return "partial output", ", ".join(p.name for p in new_outputs)
    errors = [line for line in lines if line.startswith(f"{tool}: error: ")]
    return ("refused", said) if len(errors) == 1 and len(lines) == len(errors) + sum(
        bool(OWN_LINE.match(line)) for line in lines) else ("refused in many lines", said)


def _file_size_limit(limit_bytes: int) -> Callable[[], None]:
    """For the child: files may not grow past `limit_bytes` (a write past it fails with EFBIG,
    as on a full disk, SIGXFSZ being ignored)."""
    def apply() -> None:
        import resource
        import signal

        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit_bytes, limit_bytes))
    return apply


def tool_command(tool: str, code_dir: Path | None = None) -> tuple[list[str], dict[str, str]]:
    """The command line (before the tool's arguments) and environment that run `tool` as its
    console script does, with the tools of the checkout `code_dir` (None: the installed ones)."""
    python, flag, code = tool_argv(tool)
    env = dict(os.environ)
    if code_dir is not None:
        env["PYTHONPATH"] = os.pathsep.join([str(code_dir), *filter(None, [env.get("PYTHONPATH")])])
        # The schemas are the package haptex_compile.schemas, which the installed package maps
        # to its own schemas/ folder: the checkout's are loaded in its place first.
        folder_s = str(code_dir / "schemas")
        code = ("import importlib.util, sys; spec = importlib.util.spec_from_file_location('haptex_compile.schemas',"
                f" {folder_s + '/__init__.py'!r}, submodule_search_locations=[{folder_s!r}]);"
                " module = importlib.util.module_from_spec(spec); spec.loader.exec_module(module);"
                " sys.modules['haptex_compile.schemas'] = module; " + code)
    return [python, flag, code], env


def run_case(case: Case, folder: Path, code_dir: Path | None = None) -> dict:
    """Run `case` in the new `folder`, with the tools of `code_dir` (None: the installed ones)."""
    name, expected, tool, args, files, *limit = case
    folder.mkdir()
    _make(folder, files)
    before = set(folder.iterdir())
    command, env = tool_command(tool, code_dir)
    argv = [a.replace("{d}", str(folder)) for a in args]
    t0 = time.perf_counter()
    try:
        r = subprocess.run([*command, *argv], capture_output=True, text=True, cwd=folder,
                           timeout=TIME_LIMIT_S, errors="replace", env=env,
                           preexec_fn=_file_size_limit(limit[0]) if limit else None)
        rc, stderr = r.returncode, r.stderr
    except subprocess.TimeoutExpired as exc:
        rc, stderr = None, exc.stderr if isinstance(exc.stderr, str) else (exc.stderr or b"").decode(errors="replace")
    seconds = time.perf_counter() - t0
    new_outputs = sorted(set(folder.iterdir()) - before)
    outcome, said = _outcome(tool, rc, stderr, new_outputs)
    said = said.replace(str(folder), "DIR")  # (the temporary folder's name says nothing)
    return {"case": name, "tool": tool, "expected": expected, "outcome": outcome, "said": said, "seconds": seconds}


def _cell(r: dict) -> str:
    return r["outcome"] + ("" if r["outcome"] == r["expected"] else " **(defect)**")


def run(quick: bool = False, against: Path | None = None) -> str:
    rows, base = cases_with_baseline(cases()[::3] if quick else cases(), run_case, against)
    out = [f"{len(rows)} cases, each the tool in its own process (time limit"
           f" {TIME_LIMIT_S:g} s); a defect is any outcome other than the expected one (see the module docstring)"
           + (f"; baseline, same run: the tools of `{against}`." if against is not None else "."), "",
           "| case | tool | expected | outcome | " + ("baseline's outcome | " if base else "")
           + "what the user reads (first 100 characters; DIR: the case's folder) | s |",
           "| --- | --- | --- | --- | " + ("--- | " if base else "") + "--- | --- |"]
    for k, r in enumerate(rows):
        said = r["said"].replace("|", "\\|")[:100]
        out.append(f"| {r['case']} | {r['tool']} | {r['expected']} | {_cell(r)} | "
                   + (f"{_cell(base[k])} | " if base else "") + f"{said} | {r['seconds']:.1f} |")
    count = lambda rs: sum(r["outcome"] != r["expected"] for r in rs)  # noqa: E731
    out += ["", f"Defects: {count(rows)} of {len(rows)} cases" + (f"; the baseline's: {count(base)}." if base else ".")]
    return "\n".join(out)


def cases_with_baseline(chosen: list, run_case: Callable[..., dict], against: Path | None
                        ) -> tuple[list[dict], list[dict]]:
    """Each case's row from ``run_case(case, folder)`` in a new folder, and with `against` (a
    checkout) the baseline's row from ``run_case(case, folder, against)`` right after it, in
    the same run: (ours, the baseline's, empty without `against`)."""
    rows, base = [], []
    with tempfile.TemporaryDirectory() as tmp:
        for k, case in enumerate(chosen):
            rows.append(run_case(case, Path(tmp) / f"case{k}"))
            if against is not None:
                base.append(run_case(case, Path(tmp) / f"base{k}", against))
    return rows, base


def main_with_baseline(run: Callable[..., str], doc: str, quick_help: str) -> None:
    """The command line of a bench of the tools against a checkout: ``[--quick] [--against DIR]``."""
    parser = argparse.ArgumentParser(description=doc.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help=quick_help)
    parser.add_argument("--against", type=Path, help="a checkout whose tools are the baseline")
    args = parser.parse_args()
    print(run(quick=args.quick, against=args.against))


if __name__ == "__main__":
    main_with_baseline(run, __doc__, "every third case")
