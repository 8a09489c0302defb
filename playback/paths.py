"""Checks on the paths the tools write through a temporary file and a rename."""
from __future__ import annotations

import os
import stat
from pathlib import Path

from playback.errors import InputError


def check_replaceable(path: str | Path) -> None:
    """Raise :class:`InputError` (one line) if `path` exists and is neither a regular file nor a
    symbolic link (a rename replaces the link, not its target), or if it cannot be created
    because a file stands where a folder above it should be.

    Outputs are written to a temporary file and renamed over their name: over a device, a pipe
    or a socket that rename replaces the special file itself (as root, ``-o /dev/null``
    replaced the system's /dev/null with a regular file).
    """
    try:
        mode = os.lstat(path).st_mode
    except OSError:  # not there (or unreadable: the write says why)
        check_folders(path)
        return
    if not (stat.S_ISREG(mode) or stat.S_ISLNK(mode)):
        kind = "a directory" if stat.S_ISDIR(mode) else "a device, pipe or socket"
        raise InputError(path, f"is {kind}, not a file: outputs are written to a temporary file and renamed"
                               " over their name, which would replace it")


def check_folders(path: str | Path) -> None:
    """Raise :class:`InputError` if the nearest existing folder above `path` is a file: the
    write would fail there, after all the work (``-o a.tact.h5/x.tact.h5`` failed after the
    tables with "[Errno 17] File exists")."""
    for above in Path(path).absolute().parents:
        if above.exists():
            if not above.is_dir():
                raise InputError(path, f"cannot be written: {above} is a file, not a folder")
            return
