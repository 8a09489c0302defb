"""Permissions of files written through a temporary file (mkstemp creates them 0600)."""
from __future__ import annotations


def process_umask() -> int:
    """The process umask, read without changing it (os.umask would race with threads)."""
    try:
        with open("/proc/self/status", encoding="ascii") as status:
            for line in status:
                if line.startswith("Umask:"):
                    return int(line.split()[1], 8)
    except (OSError, ValueError):
        pass
    return 0o022


def new_file_mode() -> int:
    """The mode a plainly created file would get (0666 less the umask)."""
    return 0o666 & ~process_umask()
