"""The one exception type that reaches the user as a single line (CLI: message, exit code 1, no traceback)."""


class JsgsError(Exception):
    """Bad input or a refused operation. ``str(err)`` is the whole user-facing message: it names the file
    and what is wrong."""
