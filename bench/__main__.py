"""Run every benchmark and write ``bench/REPORT.md``: ``python -m bench [--quick]`` (or ``bench/run``).

Every ``bench/bench_*.py`` that exists is run in its own Python process (so one that crashes,
hangs or leaks cannot take the report down; each gets a time limit), one after the other (they
time things: running them side by side on 2 cores would spoil each other's figures). Each module's
``run(quick)`` returns markdown; its plot data, when it offers some (see ``report_utils``), or
else the time and error columns of its tables, become PNGs under ``bench/plots/``. Modules that
are missing, fail or time out are listed with the reason. The header records the commit, the
machine, its load and the package versions.
"""
from __future__ import annotations

import argparse
import ast
import importlib.util
import json
import os
import subprocess
import sys
import tempfile
import time
import traceback
from pathlib import Path
from typing import Any

BENCH_DIR = Path(__file__).resolve().parent
REPO = BENCH_DIR.parent
if str(BENCH_DIR) not in sys.path:  # plain-script imports (bench modules have no package)
    sys.path.insert(0, str(BENCH_DIR))

import report_utils as ru  # noqa: E402

# The sections, in the order the report shows them; others follow alphabetically.
EXPECTED = ("perception", "tables", "playback", "lattice", "shading", "light", "photo", "fractal", "kes", "io")
# Seconds per module. Full mode: bench_shading took 1019 s at 64fb7d6 (its larger tiles' light
# searches), before its table of steep lights (about 80 s); bench_photo 566 s. A shared machine
# (2 cores, load 1.2-1.8) runs 10-35 % slower than an unloaded one.
TIMEOUT_S = {"quick": 240.0, "full": 1500.0}


def discover(bench_dir: Path = BENCH_DIR) -> list[Path]:
    """``bench_*.py`` files, expected sections first."""
    found = {p.stem[len("bench_"):]: p for p in sorted(bench_dir.glob("bench_*.py"))}
    order = [n for n in EXPECTED if n in found] + sorted(n for n in found if n not in EXPECTED)
    return [found[n] for n in order]


def describe(path: Path) -> str:
    """First line of a module's docstring (read without importing it)."""
    try:
        doc = ast.get_docstring(ast.parse(path.read_text(encoding="utf-8"))) or ""
    except (OSError, SyntaxError, ValueError):
        doc = ""
    return doc.strip().splitlines()[0].rstrip(".") if doc.strip() else path.stem


def _exception_line(exc: BaseException) -> str:
    tb = traceback.extract_tb(exc.__traceback__)
    where = f" (at {Path(tb[-1].filename).name}:{tb[-1].lineno})" if tb else ""
    msg = " ".join(str(exc).split())
    return f"{type(exc).__name__}: {msg}{where}"


def worker(path: Path, quick: bool, result_json: Path) -> int:
    """Child process: import one module, call run(quick) and its plot data; write JSON."""
    out: dict[str, Any] = {"markdown": None, "plot_data": None, "error": None, "plot_error": None, "run_s": None}
    if str(path.parent) not in sys.path:  # sibling imports of plain-script modules
        sys.path.insert(0, str(path.parent))
    try:
        spec = importlib.util.spec_from_file_location(path.stem, path)
        module = importlib.util.module_from_spec(spec)
        sys.modules[path.stem] = module
        spec.loader.exec_module(module)
        if not callable(getattr(module, "run", None)):
            raise AttributeError(f"{path.name} has no run(quick) function")
        t0 = time.perf_counter()
        markdown = module.run(quick=quick)
        out["run_s"] = time.perf_counter() - t0
        if not isinstance(markdown, str):
            raise TypeError(f"run() returned {type(markdown).__name__}, not markdown text")
        out["markdown"] = markdown
    except BaseException as exc:  # noqa: BLE001 - the report lists every failure
        out["error"] = _exception_line(exc)
        traceback.print_exc()
    if out["markdown"] is not None:
        try:
            data = getattr(module, "PLOT_DATA", None)
            if not data and callable(getattr(module, "plot_data", None)):
                data = module.plot_data(quick)
            out["plot_data"] = ru.to_jsonable(list(data)) if data else None
        except BaseException as exc:  # noqa: BLE001
            out["plot_error"] = _exception_line(exc)
            traceback.print_exc()
    result_json.write_text(json.dumps(ru.to_jsonable(out)), encoding="utf-8")
    return 0


def run_module(path: Path, quick: bool, timeout_s: float, log_dir: Path) -> dict[str, Any]:
    """Run one bench module in a child process; never raises."""
    result_json = log_dir / f"{path.stem}.json"
    log = log_dir / f"{path.stem}.log"
    cmd = [sys.executable, str(Path(__file__).resolve()), "--worker", str(path), "--result", str(result_json)]
    if quick:
        cmd.append("--quick")
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(filter(None, [str(REPO), os.environ.get("PYTHONPATH")])),
               MPLBACKEND="Agg")
    t0 = time.perf_counter()
    status = "ok"
    with open(log, "w", encoding="utf-8") as fh:
        try:
            proc = subprocess.run(cmd, cwd=REPO, stdout=fh, stderr=subprocess.STDOUT, timeout=timeout_s, env=env)
            code = proc.returncode
        except subprocess.TimeoutExpired:
            code, status = None, "timeout"
    wall = time.perf_counter() - t0
    res: dict[str, Any] = {"markdown": None, "plot_data": None, "error": None, "plot_error": None, "run_s": None}
    if result_json.exists():
        res.update(json.loads(result_json.read_text(encoding="utf-8")))
    if status == "timeout":
        res["error"] = f"timed out after {timeout_s:.0f} s (raise it with --timeout)"
    elif res["error"] is None and res["markdown"] is None:
        tail = [ln for ln in log.read_text(encoding="utf-8", errors="replace").splitlines() if ln.strip()]
        res["error"] = f"the process ended with status {code}" + (f": {tail[-1].strip()}" if tail else "")
    if res["error"]:
        status = "timeout" if status == "timeout" else "failed"
    res.update(status=status, wall_s=wall, module=path.stem, title=describe(path))
    return res


def _section(res: dict[str, Any], plots_dir: Path) -> tuple[str, list[str]]:
    """Markdown of one module and the PNGs it produced."""
    lines = [f"## {res['title']}", "", f"`bench/{res['module']}.py`: {res['status']}, {res['wall_s']:.1f} s "
             f"(run() {res['run_s']:.1f} s)" if res.get("run_s") is not None else
             f"`bench/{res['module']}.py`: {res['status']}, {res['wall_s']:.1f} s", ""]
    if res["error"]:
        lines += [f"**{res['status']}**: `{res['error']}`", ""]
    if res["markdown"]:
        lines += [ru.demote_headings(res["markdown"].strip(), 3), ""]
    pngs: list[str] = []
    specs = res.get("plot_data") or []
    parsed = False
    if not specs and res["markdown"]:
        specs = ru.plots_from_markdown(res["markdown"])
        parsed = bool(specs)
    if res.get("plot_error"):
        lines += [f"(plot data failed: `{res['plot_error']}`)", ""]
    if specs:
        lines += ["### Plots" + (": time against error, from the tables above" if parsed else ""), ""]
    for k, spec in enumerate(specs, 1):
        name = f"{res['module']}_{k}.png"
        try:
            ru.save_plot(spec, plots_dir / name)
        except Exception as exc:  # noqa: BLE001 - a bad plot must not lose the report
            lines += [f"(plot {k} failed: `{_exception_line(exc)}`)", ""]
            continue
        pngs.append(name)
        lines += [f"![{spec.get('title', name)}](plots/{name})", ""]
        if spec.get("note"):
            lines += [str(spec["note"]), ""]
    return "\n".join(lines), pngs


def build_report(results: list[dict[str, Any]], facts: dict[str, Any], quick: bool, load_end, total_s: float,
                 plots_dir: Path, missing: list[str]) -> str:
    """The whole REPORT.md text (writes the PNGs as a side effect)."""
    sections = []
    summary = ["## Summary", "", "| section | module | status | time (s) | baseline named | plots |",
               "| --- | --- | --- | --- | --- | --- |"]
    for res in results:
        text, pngs = _section(res, plots_dir)
        sections.append(text)
        md = res["markdown"] or ""
        named = any(w in md.lower() for w in ("baseline", "floor", "paper", "reference"))
        baseline = "yes" if named else ("-" if not md else "**no**")
        summary.append(f"| {res['title']} | `{res['module']}` | {res['status']} | {res['wall_s']:.1f} | {baseline} | {len(pngs)} |")
    for name in missing:
        summary.append(f"| - | `bench_{name}` | missing (no bench/bench_{name}.py yet) | - | - | - |")
    bad = [r for r in results if r["status"] != "ok"]
    if bad:
        summary += ["", "Not in this report: " + "; ".join(f"`{r['module']}`: {r['error']}" for r in bad) + "."]
    if missing:
        summary += ["", "Expected but absent: " + ", ".join(f"`bench/bench_{m}.py`" for m in missing) + "."]
    summary.append("")
    return "\n".join([ru.header_markdown(facts, quick, load_end, total_s), "\n".join(summary)] + sections) + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench", description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="each module's quick mode (a few minutes in all)")
    parser.add_argument("--only", help="comma-separated section names (e.g. lattice,fractal)")
    parser.add_argument("--timeout", type=float, help="seconds per module (default 240 quick, 1500 full)")
    parser.add_argument("--out", type=Path, default=BENCH_DIR / "REPORT.md", help="report file (default bench/REPORT.md)")
    parser.add_argument("--bench-dir", type=Path, default=BENCH_DIR, help="folder of the bench_*.py modules (default: bench/)")
    parser.add_argument("--worker", type=Path, help=argparse.SUPPRESS)
    parser.add_argument("--result", type=Path, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.worker:
        return worker(args.worker, args.quick, args.result)

    modules = discover(args.bench_dir)
    if args.only:
        wanted = {w.strip() for w in args.only.split(",") if w.strip()}
        modules = [m for m in modules if m.stem[len("bench_"):] in wanted]
        missing = sorted(w for w in wanted if not (args.bench_dir / f"bench_{w}.py").exists())
    else:
        present = {m.stem[len("bench_"):] for m in modules}
        missing = [n for n in EXPECTED if n not in present]
    timeout = args.timeout or TIMEOUT_S["quick" if args.quick else "full"]
    plots_dir = args.out.parent / "plots"
    plots_dir.mkdir(parents=True, exist_ok=True)
    for path in modules:  # the plots of the modules run now (a --only run keeps the others')
        for old in plots_dir.glob(f"{path.stem}_*.png"):
            old.unlink()
    facts = ru.machine_facts(REPO)
    t0 = time.perf_counter()
    results = []
    with tempfile.TemporaryDirectory(prefix="haptex-bench-") as tmp:
        for path in modules:
            print(f"[bench] {path.stem} ...", file=sys.stderr, flush=True)
            res = run_module(path, args.quick, timeout, Path(tmp))
            print(f"[bench] {path.stem}: {res['status']} in {res['wall_s']:.1f} s"
                  + (f" ({res['error']})" if res["error"] else ""), file=sys.stderr, flush=True)
            results.append(res)
    total = time.perf_counter() - t0
    text = build_report(results, facts, args.quick, ru.load_average(), total, plots_dir, missing)
    tmp_out = args.out.with_name(f".{args.out.name}.tmp")
    tmp_out.write_text(text, encoding="utf-8")
    os.replace(tmp_out, args.out)
    print(f"[bench] wrote {args.out} ({total / 60:.1f} min)", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
