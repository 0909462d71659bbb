"""What every command shares: one-line errors and a non-zero exit instead of tracebacks."""

from __future__ import annotations

import functools
import sys
from collections.abc import Callable
from typing import Any, TypeVar

import click

from jsgs.base.errors import JsgsError, Terminated
from jsgs.base.limits import MAX_INT_SETTING

F = TypeVar("F", bound=Callable[..., Any])

#: every group and command answers -h as well as --help, also when a command is invoked on its own
CONTEXT: dict[str, Any] = {"help_option_names": ["-h", "--help"]}
#: the end of every command's --help (``epilog=EXAMPLE.format(command line)``; \b: click keeps the lines)
EXAMPLE = "\b\nExample:\n  {}"


class FiniteFloat(click.ParamType):
    """A command-line number that is finite (``nan``, ``inf`` and ``1e400`` refused) and, when given, in
    [``lo``, ``hi``] (``lo_open``: greater than ``lo``)."""

    name = "number"

    def __init__(self, lo: float | None = None, hi: float | None = None, lo_open: bool = False) -> None:
        self.lo, self.hi, self.lo_open = lo, hi, lo_open

    def convert(self, value: Any, param: click.Parameter | None, ctx: click.Context | None) -> float:
        from jsgs.base.limits import check_number

        try:
            x = float(value)
        except (TypeError, ValueError):
            self.fail(f"{value!r} is not a number", param, ctx)
        try:
            return check_number(x, "it", self.lo, self.hi, lo_open=self.lo_open)
        except JsgsError as e:
            self.fail(str(e).replace("it must be", f"{value!r} is not", 1).split(" (got")[0], param, ctx)


#: a finite command-line number without bounds of its own
FINITE = FiniteFloat()
#: a TCP port to serve on
PORT = click.IntRange(1, 65_535)
#: a seed of a random number generator (what numpy's and torch's take, and the manifest records)
SEED = click.IntRange(0, MAX_INT_SETTING)
#: the most worker processes a command starts
MAX_PROCESSES = 4096
#: a count of worker processes
WORKERS = click.IntRange(1, MAX_PROCESSES)


def fail(message: str, code: int = 1) -> None:
    click.echo(f"error: {message}", err=True)
    sys.exit(code)


def user_errors(func: F) -> F:
    """Turn JsgsError (and a few OS errors) into ``error: <file>: <what>`` on stderr and exit code 1."""

    @functools.wraps(func)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        try:
            return func(*args, **kwargs)
        except JsgsError as e:
            fail(str(e))
        except OSError as e:  # a missing file, no permission, a full disk, a read-only file system, ...
            fail(f"{e.filename}: {e.strerror}" if e.filename else f"{e.strerror or e}")
        except KeyboardInterrupt:
            fail("interrupted", 130)
        except Terminated:
            fail("terminated (SIGTERM)", 143)

    return wrapper  # type: ignore[return-value]


def invocation(ctx: click.Context, program: str) -> str:
    """The command as the user could type it again, for provenance records: ``program``, the subcommand,
    its arguments, then every option that was given a value (canonical order). Built from click's parsed
    parameters rather than ``sys.argv`` so that it is right however the command was invoked."""
    import shlex

    args: list[str] = [program, ctx.info_name or ""]
    opts: list[str] = []
    for param in ctx.command.params:
        value = ctx.params.get(param.name or "")
        if value is None or value is False or value == ():
            continue
        if isinstance(param, click.Argument):
            args += [str(v) for v in value] if isinstance(value, (list, tuple)) else [str(value)]
            continue
        flag = max(param.opts, key=len)
        opts += [flag] if value is True else [flag, str(value)]
    return shlex.join(args + opts)


def terminate_on_sigterm() -> None:
    """SIGTERM raises :class:`~jsgs.base.errors.Terminated` in the main thread (one line, exit 143, the usual
    cleanup of atomic writes and locks) instead of a native handler's stack dump: pycolmap installs glog's
    failure handler, which prints one on SIGTERM, when it is imported, so call this after importing it."""
    import signal
    import threading

    if threading.current_thread() is not threading.main_thread():
        return

    def _raise(signum: int, frame: object) -> None:
        raise Terminated()

    signal.signal(signal.SIGTERM, _raise)
