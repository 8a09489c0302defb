"""What compiled libraries print themselves, kept out of the tools' output.

libjpeg (inside OpenCV's decoder) prints "Corrupt JPEG data: ..." on stderr, and the OpenEXR
library "Warning: Exception raised reading pixel data ..." on stdout and its own error line on
stderr, straight to the process's file descriptors: around the tools' one-line errors they made
three lines for one bad input, one of them on stdout. :func:`captured_native_output` runs a
call with descriptors 1 and 2 on a temporary file and hands the lines back to the caller, who
reports them its own way (a warning naming the file, or the reason in its error).
"""
from __future__ import annotations

import contextlib
import ctypes
import os
import sys
import tempfile
from typing import Iterator

# The most of the libraries' output kept (their messages are a few lines).
MAX_CAPTURED_BYTES = 65536


def _flush_c_streams() -> None:
    """Flush the C library's stdio buffers (where the libraries' C and C++ streams write)."""
    try:
        ctypes.CDLL(None).fflush(None)
    except (OSError, AttributeError, TypeError):  # pragma: no cover - no C library to ask (Windows)
        pass


@contextlib.contextmanager
def captured_native_output() -> Iterator[list[str]]:
    """Run the body with file descriptors 1 and 2 on a temporary file; the list it yields holds
    the non-empty lines written there (stripped) once the body is done.

    The descriptors are the process's, shared by its threads: use it only around short library
    calls, not around work during which other threads report progress.
    """
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (AttributeError, ValueError, OSError):  # closed or replaced streams
            pass
    _flush_c_streams()
    lines: list[str] = []
    saved = [os.dup(1), os.dup(2)]
    try:
        with tempfile.TemporaryFile() as sink:
            os.dup2(sink.fileno(), 1)
            os.dup2(sink.fileno(), 2)
            try:
                yield lines
            finally:
                _flush_c_streams()
                os.dup2(saved[0], 1)
                os.dup2(saved[1], 2)
                sink.seek(0)
                text = sink.read(MAX_CAPTURED_BYTES).decode("utf-8", "replace")
                lines.extend(line.strip() for line in text.splitlines() if line.strip())
    finally:
        for fd in saved:
            os.close(fd)
