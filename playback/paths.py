"""Checks on the paths the tools write through a temporary file and a rename."""
from __future__ import annotations

import os
import stat
from pathlib import Path

from playback.errors import InputError


def check_replaceable(path: str | Path) -> None:
    """Raise :class:`InputError` (one line) if `path` exists and is neither a regular file nor a
    symbolic link (a rename replaces the link, not its target).

    Outputs are written to a temporary file and renamed over their name: over a device, a pipe
    or a socket that rename replaces the special file itself (as root, ``-o /dev/null``
    replaced the system's /dev/null with a regular file).
    """
    try:
        mode = os.lstat(path).st_mode
    except FileNotFoundError:
        return
    except OSError:  # unreadable: the write reports it
        return
    if not (stat.S_ISREG(mode) or stat.S_ISLNK(mode)):
        kind = "a directory" if stat.S_ISDIR(mode) else "a device, pipe or socket"
        raise InputError(path, f"is {kind}, not a file: outputs are written to a temporary file and renamed"
                               " over their name, which would replace it")
