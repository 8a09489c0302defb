"""Reading the tools' text inputs (scenes, device profiles, trajectories, threshold curves,
Kawabata files), with one wording for the ways a file cannot be read: each reader had its own
("cannot read scene (FileNotFoundError)", "file not found", "[Errno 2] No such file or
directory: ...", "not a text TOML file")."""
from __future__ import annotations

from pathlib import Path

from playback.errors import InputError


def utf8_text(text: str) -> str:
    """`text` as UTF-8 (and so HDF5) can hold it: the bytes of a file name that are not UTF-8,
    which Python holds as lone surrogates, become U+FFFD (HDF5 refused such a name, "surrogates
    not allowed")."""
    return text.encode("utf-8", "surrogateescape").decode("utf-8", "replace")


def unreadable(path: str | Path, what: str, exc: OSError | UnicodeDecodeError) -> InputError:
    """The one-line error for text file `path` (a `what`, e.g. "scene file") that raised `exc`
    when opened or decoded."""
    if isinstance(exc, UnicodeDecodeError):
        return InputError(path, f"not UTF-8 text (byte {exc.start}): expected a {what}")
    if isinstance(exc, FileNotFoundError):
        return InputError(path, f"no such {what}")
    if isinstance(exc, IsADirectoryError):
        return InputError(path, f"is a directory, not a {what}")
    return InputError(path, f"cannot read {what}: {exc.strerror or exc}")


def read_text(path: str | Path, what: str) -> str:
    """The whole of UTF-8 text file `path` (a byte-order mark is dropped), or :func:`unreadable`'s
    error."""
    try:
        return Path(path).read_text(encoding="utf-8-sig")
    except (OSError, UnicodeDecodeError) as exc:
        raise unreadable(path, what, exc) from None
