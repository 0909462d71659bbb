"""The one exception type that reaches the user as a single line (CLI: message, exit code 1, no traceback)."""


def one_line(err: BaseException) -> str:
    """``Type: first line of the message`` (just ``Type`` for an empty message): an exception from a library
    (torch, Pillow) quoted inside a one-line message of ours."""
    text = str(err).strip()
    return f"{type(err).__name__}: {text.splitlines()[0]}" if text else type(err).__name__


class JsgsError(Exception):
    """Bad input or a refused operation. ``str(err)`` is the whole user-facing message: it names the file
    and what is wrong."""


class Terminated(Exception):  # noqa: N818 - named for the signal, like KeyboardInterrupt
    """SIGTERM reached a command that installed :func:`jsgs.cli._common.terminate_on_sigterm` (exit 143)."""
