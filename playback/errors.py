"""Exceptions shared by the player and the compiler; the CLIs print them as one line."""
from __future__ import annotations

from pathlib import Path

# Longest text read from a file that a message or summary shows whole.
SHOWN_CHARS = 300


def shown_text(value: object, limit: int | None = SHOWN_CHARS) -> str:
    """Text read from a file as a message or summary shows it: control characters escaped (a
    newline or a terminal's escape sequence in an attribute split the line or recoloured the
    terminal), and a text longer than `limit` (None: no limit) cut in the middle, its length
    stated (the start and the end are kept: the end of a validator's message says what was
    expected)."""
    text = "".join(c if c.isprintable() else repr(c)[1:-1] for c in str(value))
    if limit is not None and len(text) > limit:
        head = limit * 2 // 3
        text = f"{text[:head]} ... [{len(text)} characters] ... {text[len(text) - (limit - head):]}"
    return text


def one_line(exc: BaseException) -> str:
    """An exception's message as one line of printable text (its type's name if it has none):
    libraries' messages (h5py's, the OS's) may span lines or quote a file's bytes."""
    return shown_text(" ".join(str(exc).split()), limit=None) or type(exc).__name__


class HaptexError(Exception):
    """Base class: an expected failure with a message meant for the user (no traceback)."""


class InputError(HaptexError, ValueError):
    """A bad input file or parameter: the message names the file (when there is one) and the problem.

    Parameters
    ----------
    source : str or Path or None
        The file or spec the problem is in; ``None`` for a bare parameter.
    problem : str
        What is wrong, as one line.
    """

    def __init__(self, source: str | Path | None, problem: str) -> None:
        self.source = None if source is None else str(source)
        self.problem = problem
        super().__init__(problem if source is None else f"{source}: {problem}")


class AssetError(InputError):
    """A tactile asset that cannot be read: not HDF5, wrong format or version, missing or bad data."""


class DeviceError(HaptexError):
    """The stimulator could not be found, written to, or stopped answering."""
