"""Benchmark: the tools stopped by signals mid-run, as a terminal, a supervisor or a batch does.

Each case starts a tool in its own process group (``python -c``, as the console scripts do),
waits until its stderr shows it is at work (``-v`` / ``-vv`` lines: the compile's surface is
made, the player has sent 10 frames), sends a signal, as Ctrl-C does (SIGINT to the process
group), as ``kill`` does (SIGTERM to the process), as a closed terminal does (SIGHUP to the
group) or as ``kill -9`` does (SIGKILL), and reports what the user is left with:

* the exit status and the time from the signal to the tool's exit;
* what the tool said (its last line on stderr), and whether it was a traceback;
* files left in the case's folder beyond what the run should leave (temporary files, assets
  of a stopped compile);
* the player: whether its last packet to the device (``--device file:``) is the all-zero
  frame, and how many frames its record holds (none: lost);
* processes of the run still alive 2 s after the tool exited (orphaned workers), killed then.

Run: ``python bench/bench_stop_signals.py [--quick] [--against DIR]`` (quick: the player's
SIGTERM, a compile's SIGTERM and the --jobs parent's SIGKILL). With ``--against``, every case
also runs with the tools of another checkout (for example a ``git worktree`` of an earlier
commit), in the same run, as the baseline.
"""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))  # the repo root, for tests.asset_factory
sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_hostile_inputs import cases_with_baseline, main_with_baseline, tool_command  # noqa: E402

KES = REPO / "samples" / "kes"
WAIT_EXIT_S = 120.0
ORPHAN_GRACE_S = 2.0
PLAY = ["a.tact.h5", "--device", "file:pk.bin", "--sweep", "speed=80,direction=0,duration=60", "--record", "r.h5",
        "--no-realtime", "-vv"]
THREE_KES = [str(KES / f"{n}.kes.json") for n in ("satin", "denim_twill", "wool_suiting")]
# (name, tool, arguments, the stderr text that shows it is at work, signals in order, to the
# process group?, files the run may leave)
CASES = [
    ("play, Ctrl-C", "haptex-play", PLAY, "frame 10 ", ["SIGINT"], True, {"pk.bin", "r.h5"}),
    ("play, SIGTERM", "haptex-play", PLAY, "frame 10 ", ["SIGTERM"], False, {"pk.bin", "r.h5"}),
    ("play, SIGHUP (terminal closed)", "haptex-play", PLAY, "frame 10 ", ["SIGHUP"], True, {"pk.bin", "r.h5"}),
    ("play, Ctrl-C twice", "haptex-play", PLAY, "frame 10 ", ["SIGINT", "SIGINT"], True, {"pk.bin", "r.h5"}),
    ("compile, Ctrl-C", "haptex-compile", [THREE_KES[0], "-o", "s.tact.h5", "-v"], "surface in", ["SIGINT"], True, set()),
    ("compile, SIGTERM", "haptex-compile", [THREE_KES[0], "-o", "s.tact.h5", "-v"], "surface in", ["SIGTERM"], False,
     set()),
    ("compile -j 2 of 3, Ctrl-C", "haptex-compile", [*THREE_KES, "--out-dir", "o", "-j", "2", "-v"], "surface in",
     ["SIGINT"], True, set()),
    ("compile -j 2 of 3, SIGTERM to the parent", "haptex-compile", [*THREE_KES, "--out-dir", "o", "-j", "2", "-v"],
     "surface in", ["SIGTERM"], False, set()),
    ("compile -j 2 of 3, SIGKILL to the parent", "haptex-compile", [*THREE_KES, "--out-dir", "o", "-j", "2", "-v"],
     "surface in", ["SIGKILL"], False, set()),
]
QUICK = ("play, SIGTERM", "compile, SIGTERM", "compile -j 2 of 3, SIGKILL to the parent")


def _descendants(pid: int) -> list[int]:
    """Every live descendant of `pid` (from /proc)."""
    children: dict[int, list[int]] = {}
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                fields = (entry / "stat").read_text().rsplit(")", 1)[1].split()
            except OSError:
                continue
            children.setdefault(int(fields[1]), []).append(int(entry.name))
    out, todo = [], [pid]
    while todo:
        for child in children.get(todo.pop(), []):
            out.append(child)
            todo.append(child)
    return out


def _alive(pid: int) -> bool:
    try:
        return (Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]) != "Z"
    except OSError:
        return False


def _player_leftovers(folder: Path) -> tuple[str, str]:
    """(is the last packet the zero frame, frames in the record) of a player's case."""
    from playback import protocol
    import h5py

    try:
        packets = protocol.split_packets((folder / "pk.bin").read_bytes())
        last = protocol.decode_frame(packets[-1])
        zero = "yes" if not (last.codes40.any() or last.codes320.any()) else "**no**"
    except (OSError, IndexError, ValueError) as exc:
        zero = f"unreadable ({type(exc).__name__})"
    try:
        with h5py.File(folder / "r.h5", "r") as f:
            frames = str(f["frames/t_s"].shape[0])
    except (OSError, KeyError):
        frames = "**lost**"
    return zero, frames


def run_case(case: tuple, folder: Path, code_dir: Path | None = None) -> dict:
    """Run one case in the new `folder` with the tools of `code_dir` (None: the installed ones)."""
    name, tool, args, ready, signals, group, may_leave = case
    folder.mkdir()
    if tool == "haptex-play":
        from tests.asset_factory import write_test_asset
        write_test_asset(folder / "a.tact.h5")
        may_leave = may_leave | {"a.tact.h5"}
    command, env = tool_command(tool, code_dir)
    proc = subprocess.Popen([*command, *args], cwd=folder, env=env, stdout=subprocess.DEVNULL,
                            stderr=subprocess.PIPE, text=True, errors="replace", start_new_session=True)
    lines = []
    for line in proc.stderr:
        lines.append(line.rstrip("\n"))
        if ready in line:
            break
    workers = _descendants(proc.pid)
    t0 = time.perf_counter()
    for k, sig_name in enumerate(signals):
        sig = getattr(signal, sig_name)
        if k:
            time.sleep(0.002)  # (the second press, 2 ms after the first)
        (os.killpg if group else os.kill)(proc.pid, sig)
    # stderr is read on a thread: orphaned workers may hold it open long after the tool exits
    reader = threading.Thread(target=lambda: lines.extend(line.rstrip("\n") for line in proc.stderr), daemon=True)
    reader.start()
    try:
        proc.wait(timeout=WAIT_EXIT_S)
        status: str = str(proc.returncode)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()
        status = f"**did not exit in {WAIT_EXIT_S:g} s**"
    seconds = time.perf_counter() - t0
    # Workers of the run (the pool's, reparented when the parent died) still alive a little later.
    time.sleep(ORPHAN_GRACE_S)
    orphans = [pid for pid in workers if _alive(pid)]
    for pid in orphans:
        try:
            os.kill(pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
    reader.join(timeout=10.0)
    said = next((line for line in reversed(lines) if line.strip() and " INFO: " not in line
                 and " DEBUG: " not in line), "")
    if any("Traceback (most recent call last)" in line for line in lines):
        said = "traceback: " + said
    left = sorted(str(p.relative_to(folder)) for p in folder.rglob("*") if p.is_file()
                  and str(p.relative_to(folder)) not in may_leave)
    row = {"case": name, "status": status, "seconds": seconds, "said": said, "left": left, "orphans": len(orphans)}
    if tool == "haptex-play":
        row["zero"], row["frames"] = _player_leftovers(folder)
    return row


def _cells(r: dict) -> str:
    left = ", ".join(r["left"])[:60] or "none"
    said = r["said"].replace("|", "\\|")[:70]
    return (f"{r['status']} | {r['seconds']:.2f} | {r.get('zero', '-')} | {r.get('frames', '-')} | {left} | "
            f"{r['orphans']} | {said}")


def run(quick: bool = False, against: Path | None = None) -> str:
    rows, base = cases_with_baseline([c for c in CASES if not quick or c[0] in QUICK], run_case, against)
    head = "| case | tools | exit status | s to exit | last packet zero | record frames | files left | orphans | last line |"
    out = [f"{len(rows)} cases; the signal is sent once the tool is at work (see the module docstring)"
           + (f"; baseline, same run: the tools of `{against}`." if against is not None else "."), "",
           head, "|" + " --- |" * (head.count("|") - 1)]
    for k, r in enumerate(rows):
        out.append(f"| {r['case']} | ours | {_cells(r)} |")
        if base:
            out.append(f"| | baseline | {_cells(base[k])} |")
    return "\n".join(out)


if __name__ == "__main__":
    main_with_baseline(run, __doc__, "three cases")
