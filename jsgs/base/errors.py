"""The one exception type that reaches the user as a single line (CLI: message, exit code 1, no traceback)."""

from __future__ import annotations

import functools
import sys
from collections.abc import Callable
from typing import ParamSpec

P = ParamSpec("P")


def one_line(err: BaseException) -> str:
    """``Type: first line of the message`` (just ``Type`` for an empty message): an exception from a library
    (torch, Pillow) quoted inside a one-line message of ours."""
    text = str(err).strip()
    return f"{type(err).__name__}: {text.splitlines()[0]}" if text else type(err).__name__


class JsgsError(Exception):
    """Bad input or a refused operation. ``str(err)`` is the whole user-facing message: it names the file
    and what is wrong."""


class Terminated(Exception):  # noqa: N818 - named for the signal, like KeyboardInterrupt
    """SIGTERM reached a command that installed :func:`jsgs.base.commands.terminate_on_sigterm` (exit 143)."""


def reports_user_errors(main: Callable[P, int]) -> Callable[P, int]:
    """For the ``main`` of an argparse tool (the click commands have ``jsgs.base.commands.user_errors``): a
    JsgsError it raises becomes ``error: <message>`` on stderr and exit code 1, without a traceback."""

    @functools.wraps(main)
    def wrapper(*args: P.args, **kwargs: P.kwargs) -> int:
        try:
            return main(*args, **kwargs)
        except JsgsError as e:
            print(f"error: {e}", file=sys.stderr)
            return 1

    return wrapper
