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
        check_name_length(path)
        return
    if not (stat.S_ISREG(mode) or stat.S_ISLNK(mode)):
        kind = "a directory" if stat.S_ISDIR(mode) else "a device, pipe or socket"
        raise InputError(path, f"is {kind}, not a file: outputs are written to a temporary file and renamed"
                               " over their name, which would replace it")
    _check_writable(path, Path(path).absolute().parent)  # (the temporary file is made in its folder)


def check_folders(path: str | Path) -> None:
    """Raise :class:`InputError` if the nearest existing folder above `path` is a file, or, when
    `path` is not there yet, one this process may not write in (read-only file system,
    permissions): the write would fail there, after all the work (``-o a.tact.h5/x.tact.h5``
    failed after the tables with "[Errno 17] File exists"; an output on a read-only file system
    after them with "Read-only file system"). An existing file may be written in place (a
    packet sink such as /dev/null) wherever it is."""
    for above in Path(path).absolute().parents:
        if above.exists():
            if not above.is_dir():
                raise InputError(path, f"cannot be written: {above} is a file, not a folder")
            if not os.path.lexists(path):
                _check_writable(path, above)
            return


def _check_writable(path: str | Path, folder: Path) -> None:
    """Raise :class:`InputError` naming `path` if this process may not create files in `folder`."""
    if folder.is_dir() and not os.access(folder, os.W_OK | os.X_OK):  # (EROFS even for root)
        try:
            read_only = bool(os.statvfs(folder).f_flag & os.ST_RDONLY)
        except (OSError, AttributeError):
            read_only = False
        raise InputError(path, f"cannot be written: {folder} is on a read-only file system" if read_only
                         else f"cannot be written: no permission to write in {folder}")


DEFAULT_NAME_MAX = 255  # bytes in a file name, where the file system does not say
TEMPORARY_EXTRA = 14  # bytes a temporary name adds: "." + name + "." + 8 random + ".tmp"


def name_max(folder: str | Path) -> int:
    """The longest file name (bytes) the file system of `folder` (or of its nearest existing
    folder above) takes."""
    for above in [Path(folder).absolute(), *Path(folder).absolute().parents]:
        if above.is_dir():
            try:
                return int(os.pathconf(above, "PC_NAME_MAX"))
            except (OSError, ValueError, AttributeError):
                break
    return DEFAULT_NAME_MAX


def check_name_length(path: str | Path) -> None:
    """Raise :class:`InputError` if the name of `path` is longer than its file system takes:
    found before the work, not when the output is written after it."""
    size, limit = len(os.fsencode(Path(path).name)), name_max(Path(path).parent)
    if size > limit:
        raise InputError(path, f"cannot be written: its name is {size} bytes, over the file system's {limit}")


def temporary_beside(path: str | Path) -> tuple[int, str]:
    """``(fd, name)`` of a new temporary file in the folder of `path`, named ``.NAME.XXXXXXXX.tmp``
    with NAME cut so that the name fits the file system (a valid name of 242 or more bytes
    could not be written: its temporary name was too long)."""
    path = Path(path)
    room = max(1, name_max(path.parent) - TEMPORARY_EXTRA)
    short = os.fsdecode(os.fsencode(path.name)[:room])
    return tempfile.mkstemp(prefix=f".{short}.", suffix=".tmp", dir=path.parent)


def replace_files(files: list[tuple[str | Path, bytes | bytearray | memoryview, int]]) -> None:
    """Write each ``(path, data, mode)`` through a temporary file beside it and a rename, every
    temporary file first: each path holds either its old content or all of its data, and a
    failure before the renames (a full disk, an interrupt) leaves every path as it was, so the
    outputs of one run are all written or none (``haptex-compile --exr`` wrote the asset and
    then failed on the EXR). The data is on disk (fsync) before a name points at it; a file
    gets its `mode`. The temporary files are removed on any failure, which is raised; the
    writes' own as :class:`InputError` naming the path ("cannot be written: No space left on
    device").

    The tools build HDF5 files in memory and write them out with this: libhdf5 writing into a
    full disk printed hundreds of lines of tracebacks while closing the file, then crashed the
    process (segmentation fault), where a plain write raises ``OSError`` (ENOSPC) once.
    """
    staged: list[tuple[Path, str]] = []
    current = None
    try:
        for path, data, mode in files:
            current = Path(path)
            fd, tmp = temporary_beside(current)
            staged.append((current, tmp))
            with os.fdopen(fd, "wb") as out:
                out.write(data)
                out.flush()
                os.fsync(out.fileno())
            os.chmod(tmp, mode)
        for path, tmp in staged:
            current = path
            os.replace(tmp, path)
    except BaseException as exc:
        for _, tmp in staged:
            Path(tmp).unlink(missing_ok=True)
        if isinstance(exc, OSError) and current is not None:
            raise InputError(current, f"cannot be written: {exc.strerror or exc}") from None
        raise


def replace_with_bytes(path: str | Path, data: bytes | bytearray | memoryview, mode: int) -> None:
    """Write `data` to `path` atomically: :func:`replace_files` for one file."""
    replace_files([(path, data, mode)])
