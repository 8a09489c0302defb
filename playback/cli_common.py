"""Options and error handling shared by the three command-line tools (defined once, here).

``-v/-q`` set the log level, ``--debug`` shows tracebacks. Expected failures
(:class:`~playback.errors.HaptexError`, ``OSError``) become one line on stderr and exit
status 1; usage errors (a bad option value, a missing argument) are one line too and exit 2
(click's convention). SIGTERM and SIGHUP stop a command as Ctrl-C does
(:mod:`playback.stop_signals`); an interrupt the command does not handle itself is one line
and the shell's status for the signal (130 for Ctrl-C, 143 for SIGTERM); a closed stdout (the
reader of a pipe gone) ends a command quietly with status 141, as SIGPIPE ends other tools.
Progress bars are shown only when stderr is a terminal.
"""
from __future__ import annotations

import functools
import inspect
import logging
import math
import os
import signal
import sys
from pathlib import Path
from typing import Any, Callable

import click

from playback.errors import HaptexError, one_line
from playback.paths import check_folders, check_replaceable
from playback.stop_signals import exit_status, stop_reason, stop_signals_raise

LOG = logging.getLogger("haptex")
EXIT_BAD_INPUT = 1
EXIT_USAGE = 2


class _OneLineUsageError(click.UsageError):
    """A usage error shown as one line, ``PROG: error: MESSAGE (see PROG --help)``: click's own
    display is three (usage, hint, error), and a batch log should hold one line per failure."""

    def __init__(self, error: click.UsageError, prog: str) -> None:
        super().__init__(error.format_message(), error.ctx)
        self.prog = error.ctx.command_path if error.ctx is not None else prog

    def show(self, file: Any = None) -> None:
        message = " ".join(self.format_message().split())
        click.echo(f"{self.prog}: error: {message} (see {self.prog} --help)", file=file, err=file is None)


class OneLineUsageCommand(click.Command):
    """A click command whose usage errors, from parsing or from the command's own checks, are
    one line (:class:`_OneLineUsageError`); the exit status stays 2."""

    def make_context(self, info_name: str | None, args: list[str], parent: click.Context | None = None,
                     **extra: Any) -> click.Context:
        try:
            return super().make_context(info_name, args, parent=parent, **extra)
        except click.UsageError as exc:
            raise _OneLineUsageError(exc, info_name or self.name or "haptex") from None

    def invoke(self, ctx: click.Context) -> Any:
        try:
            return super().invoke(ctx)
        except click.UsageError as exc:
            raise _OneLineUsageError(exc, ctx.command_path) from None


def command() -> Callable[[Callable[..., Any]], click.Command]:
    """The decorator of the three tools' commands: ``-h/--help`` and one-line usage errors."""
    return click.command(cls=OneLineUsageCommand, context_settings={"help_option_names": ["-h", "--help"]})


def _configure_logging(verbose: int, quiet: int) -> None:
    level = logging.WARNING - 10 * verbose + 10 * quiet
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(logging.Formatter("%(name)s: %(levelname)s: %(message)s"))
    root = logging.getLogger("haptex")
    root.handlers[:] = [handler]
    root.setLevel(max(logging.DEBUG, min(level, logging.CRITICAL)))
    root.propagate = False


def common_options(func: Callable[..., Any]) -> Callable[..., Any]:
    """Add ``-v/--verbose``, ``-q/--quiet`` and ``--debug``, and turn expected errors into one line.

    The wrapped command receives ``debug`` as a keyword argument only if it declares it.
    """
    wants_debug = "debug" in inspect.signature(func).parameters

    @click.option("-v", "--verbose", count=True, help="More messages on stderr (repeatable).")
    @click.option("-q", "--quiet", count=True, help="Fewer messages on stderr (repeatable).")
    @click.option("--debug", is_flag=True, help="Show full tracebacks on errors.")
    @functools.wraps(func)
    def wrapper(*args: Any, verbose: int, quiet: int, debug: bool, **kwargs: Any) -> Any:
        _configure_logging(verbose, quiet)
        if wants_debug:
            kwargs["debug"] = debug
        try:
            with stop_signals_raise():
                return func(*args, **kwargs)
        except BrokenPipeError:
            if debug:
                raise
            # The reader of stdout left (``haptex-inspect *.tact.h5 | head``): stop quietly, as
            # tools killed by SIGPIPE do, not with an error line per file; stdout is pointed at
            # the null device so Python's final flush does not complain of it either.
            os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
            sys.exit(128 + int(getattr(signal, "SIGPIPE", 13)))
        except (HaptexError, OSError) as exc:
            if debug:
                raise
            click.echo(f"{click.get_current_context().info_name}: error: {one_line(exc)}", err=True)
            sys.exit(EXIT_BAD_INPUT)
        except KeyboardInterrupt as exc:  # Ctrl-C, SIGTERM or SIGHUP, not handled by the command
            if debug:
                raise
            # one line (click's own is "Aborted!" after an empty line, status 1), and the shell's
            # status for the signal, so a batch (make) sees the run was stopped, not failed
            click.echo(f"{click.get_current_context().info_name}: error: interrupted by {stop_reason(exc)}", err=True)
            sys.exit(exit_status(exc))

    return wrapper


def warn_ignored_options(names: list[str], needs: str) -> None:
    """Warn, in one line, of the options among `names` (parameter names) given on the command
    line that apply only with the option `needs`, which was not given: they were ignored
    without a word (``--exr-speed 40`` without ``--exr``)."""
    ctx = click.get_current_context()
    given = [param.opts[0] for param in ctx.command.params
             if param.name in names and ctx.get_parameter_source(param.name) == click.core.ParameterSource.COMMANDLINE]
    if given:
        LOG.warning("%s %s only with %s: ignored", ", ".join(given), "applies" if len(given) == 1 else "apply", needs)


def show_progress() -> bool:
    """Progress bars only when stderr is an interactive terminal."""
    return sys.stderr.isatty()


def _same_file(a: str, b: str) -> bool:
    """`a` and `b` name one file: the same existing file (links included), or the same path."""
    pa, pb = Path(a), Path(b)
    try:
        if pa.exists() and pb.exists():
            return os.path.samefile(pa, pb)
        return pa.resolve() == pb.resolve()
    except (OSError, RuntimeError):  # unreadable, or a symlink loop: not known to be one file
        return False


def refuse_overwrites(outputs: list[tuple[str, str]], inputs: list[str],
                      direct: list[tuple[str, str]] = ()) -> None:
    """A usage error (one line) where an output would overwrite an input of the run or another
    output: `outputs` are (what writes it, path) pairs written through a temporary file and a
    rename, which must not be devices, pipes or sockets either (see
    :func:`playback.paths.check_replaceable`); `direct` those opened and written in place (a
    raw packet sink may be a pipe); `inputs` paths. A typo such as
    ``haptex-compile h.npy -o h.npy`` replaced the input with the asset."""
    checks = [(check_replaceable, what, out) for what, out in outputs]
    checks += [(check_folders, what, out) for what, out in direct]
    for check, what, out in checks:
        try:
            check(out)
        except HaptexError as exc:
            raise click.UsageError(f"{what} {exc}") from None
    every = [*outputs, *direct]
    for i, (what, out) in enumerate(every):
        for source in inputs:
            if _same_file(out, source):
                raise click.UsageError(f"{what} {out} is an input of this run: it would be overwritten")
        for other_what, other in every[:i]:
            if _same_file(out, other):
                raise click.UsageError(f"{other_what} and {what} would both write {out}")


class PathParam(click.Path):
    """:class:`click.Path` that refuses an empty string: ``-o ''`` ended in a TypeError
    traceback (an empty output counted as none), and ``--record ''`` named the current
    directory."""

    def convert(self, value: Any, param: click.Parameter | None, ctx: click.Context | None) -> Any:
        if isinstance(value, (str, bytes)) and not value:
            self.fail("empty path", param, ctx)
        return super().convert(value, param, ctx)


class FiniteFloat(click.FloatRange):
    """:class:`click.FloatRange` that refuses NaN and infinities, which pass a range's
    comparisons (NaN) or sit at its open end: ``--lead-ms nan`` played with NaN schedules,
    ``--waveform-rate 1e12`` asked for 1.8 TiB, ``--relief-um 1e308`` overflowed to NaN heights."""

    def convert(self, value: Any, param: click.Parameter | None, ctx: click.Context | None) -> Any:
        number = super().convert(value, param, ctx)
        if not math.isfinite(number):
            self.fail(f"{value!r} is not a finite number", param, ctx)
        return number

    def _describe_range(self) -> str:
        # click's own says "x<=None" for a range with neither bound
        if self.min is None and self.max is None:
            return "finite"
        return super()._describe_range()
