"""What every command shares: one-line errors and a non-zero exit instead of tracebacks."""

from __future__ import annotations

import functools
import sys
from collections.abc import Callable
from typing import Any, TypeVar

import click

from jsgs.errors import JsgsError

F = TypeVar("F", bound=Callable[..., Any])


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
        except (FileNotFoundError, PermissionError, IsADirectoryError) as e:
            fail(f"{e.filename}: {e.strerror}")
        except KeyboardInterrupt:
            fail("interrupted", 130)

    return wrapper  # type: ignore[return-value]
