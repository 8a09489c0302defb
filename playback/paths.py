"""Checks on the paths the tools write through a temporary file and a rename."""
from __future__ import annotations

import os
import stat
import tempfile
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


def replace_with_bytes(path: str | Path, data: bytes | bytearray | memoryview, mode: int) -> None:
    """Write `data` to `path` through a temporary file beside it and a rename: `path` holds
    either its old content or all of `data`, never part of it. The data is on disk (fsync)
    before the name points at it; the file gets `mode`. Any failure (a full disk, an
    interrupt) removes the temporary file and is raised; the write's own as
    :class:`InputError` naming `path` ("cannot be written: No space left on device").

    The tools build HDF5 files in memory and write them out with this: libhdf5 writing into a
    full disk printed hundreds of lines of tracebacks while closing the file, then crashed the
    process (segmentation fault), where a plain write raises ``OSError`` (ENOSPC) once.
    """
    path = Path(path)
    try:
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    except OSError as exc:
        raise InputError(path, f"cannot be written: {exc.strerror or exc}") from None
    try:
        with os.fdopen(fd, "wb") as out:
            out.write(data)
            out.flush()
            os.fsync(out.fileno())
        os.chmod(tmp, mode)
        os.replace(tmp, path)
    except OSError as exc:
        Path(tmp).unlink(missing_ok=True)
        raise InputError(path, f"cannot be written: {exc.strerror or exc}") from None
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
