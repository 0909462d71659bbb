"""What the readers accept: the documented limits (``docs/robustness.md``) and the small checks every reader
shares, each raising one :class:`jsgs.base.errors.JsgsError` line that names the file or setting.

Imports only the standard library, numpy, :mod:`jsgs.base.errors` and (to read files) :mod:`jsgs.base.io`, so
any reader of either program may use it.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

from jsgs.base.errors import JsgsError

#: deepest nesting of arrays and objects in a JSON file the tools read (none of the project's is deeper
#: than 6; Python's parser and the schema validator recurse once per level)
MAX_JSON_DEPTH = 64
#: largest magnitude of a world coordinate (camera positions, translations, 3D points) in a manifest or a
#: COLMAP model: at 1e12 a float64 coordinate still resolves 0.1 mm in metres, and its square stays far
#: inside float64
MAX_COORDINATE = 1e12
#: points farther from the cameras' mean than this many times the cameras' extent are dropped before the
#: world is normalised (a note says how many): SfM's far outliers lie within 1e3 of it; beyond this, their
#: squares leave float32 once normalised
MAX_POINT_DISTANCE = 1e6
#: largest image side (pixels) a camera may declare: JPEG's own limit
MAX_IMAGE_SIDE = 65_535
#: smallest side (pixels) of a view the trainer takes: the SSIM window of l_ph, L_obs and the evaluation
MIN_VIEW_SIDE = 11
#: cameras whose centres lie within this fraction of their distance from the origin (or of 1, when nearer)
#: of each other are at one position: there is no camera extent to normalise the world by
COINCIDENT_CAMERAS = 1e-9
#: focal lengths (pixels) lie in [MIN_FOCAL_RATIO, MAX_FOCAL_RATIO] x the camera's longer side: from a
#: 179.9-degree field of view to a 0.006-degree one
MIN_FOCAL_RATIO = 1e-3
MAX_FOCAL_RATIO = 1e4
#: largest magnitude of a numeric setting without bounds of its own (settings files, the command line)
MAX_SETTING = 1e12
#: largest integer setting (seeds, counts): what torch's and numpy's generators take
MAX_INT_SETTING = 2**63 - 1


def _first_problem(doc: Any, finite: bool) -> str | None:
    """Where ``doc`` nests deeper than :data:`MAX_JSON_DEPTH`, or (``finite``) holds a number that is not
    finite or an integer beyond 64 bits: ``at <path>: <what>``; None when it does not."""
    if not isinstance(doc, (dict, list)):
        return _first_problem([doc], finite)
    stack: list[tuple[Any, int, str]] = [(doc, 1, "")]
    while stack:
        node, depth, path = stack.pop()
        if isinstance(node, dict):
            items: Any = node.items()
        elif isinstance(node, list):
            items = enumerate(node)
        else:
            continue
        if depth > MAX_JSON_DEPTH:
            return f"nested deeper than {MAX_JSON_DEPTH} levels"
        for key, child in items:
            if isinstance(child, (dict, list)):
                stack.append((child, depth + 1, f"{path}/{key}"))
            elif not finite or isinstance(child, bool):
                continue
            elif isinstance(child, float) and not math.isfinite(child):
                return f"at {path}/{key}: {child} is not a finite number"
            elif isinstance(child, int) and not -(2**63) <= child < 2**64:
                return f"at {path}/{key}: an integer beyond 64 bits"
    return None


def _suspect(text: str | bytes, finite: bool) -> bool:
    """Whether ``text`` may nest too deeply (brackets counted, strings not told apart) or (``finite``) hold a
    number :func:`_first_problem` refuses (``NaN``, ``Infinity``, an exponent of 3 digits or more, a run of
    19 digits or more not after a decimal point): the exact walk, which costs twice the parse, runs only
    then. numpy over the bytes (a regular expression takes seconds on a 20 MB manifest)."""
    import numpy as np

    data = text.encode("utf-8", "surrogatepass") if isinstance(text, str) else bytes(text)
    a = np.frombuffer(data, dtype=np.uint8)
    if not len(a):
        return False
    opens = (a == 91) | (a == 123)
    closes = (a == 93) | (a == 125)
    where = np.flatnonzero(opens | closes)
    if len(where) and int(np.cumsum(np.where(opens[where], 1, -1)).max()) > MAX_JSON_DEPTH:
        return True
    if not finite:
        return False
    if b"NaN" in data or b"Infinity" in data:
        return True
    digit = (a >= 48) & (a <= 57)
    padded = np.concatenate([digit, np.zeros(4, bool)])
    e = np.flatnonzero((a == 101) | (a == 69))
    plus = np.concatenate([a == 43, np.zeros(4, bool)])
    long_exp = (padded[e + 1] & padded[e + 2] & padded[e + 3]) | (plus[e + 1] & padded[e + 2] & padded[e + 3]
                                                                    & padded[e + 4])  # fmt: skip
    if long_exp.any():
        return True
    change = np.flatnonzero(digit[1:] != digit[:-1]) + 1
    starts = np.concatenate([[0] if digit[0] else [], change[digit[change]]]).astype(np.int64)
    ends = np.concatenate([change[~digit[change]], [len(a)] if digit[-1] else []]).astype(np.int64)
    long_run = (ends - starts) >= 19
    after_point = np.zeros(len(starts), bool)
    inner = starts > 0
    after_point[inner] = a[starts[inner] - 1] == 46
    return bool((long_run & ~after_point).any())


def parse_json(text: str | bytes, where: str | Path, what: str = "JSON", finite: bool = True) -> Any:
    """``text`` parsed as JSON; JsgsError ``<where>: not <what>: ...`` (one line) for malformed text, nesting
    deeper than :data:`MAX_JSON_DEPTH`, an integer too long to convert, and (``finite``) a number that is not
    finite (``NaN``, ``Infinity``, ``1e400``) or an integer beyond 64 bits, naming its place."""
    try:
        doc = json.loads(text)
    except json.JSONDecodeError as e:
        raise JsgsError(f"{where}: not {what}: {e.msg} at line {e.lineno}, column {e.colno}") from None
    except RecursionError:
        raise JsgsError(f"{where}: not {what}: nested deeper than {MAX_JSON_DEPTH} levels") from None
    except (ValueError, UnicodeDecodeError) as e:  # an integer of over 4300 digits; bytes not UTF-8
        raise JsgsError(f"{where}: not {what}: {str(e).splitlines()[0]}") from None
    problem = _first_problem(doc, finite) if _suspect(text, finite) else None
    if problem:
        raise JsgsError(f"{where}: not {what}: {problem}")
    return doc


def read_json(path: str | Path, what: str = "JSON", finite: bool = True) -> Any:
    """The regular file at ``path`` parsed by :func:`parse_json`; JsgsError (one line) when it is missing,
    unreadable or not a regular file."""
    from jsgs.base.io import read_regular_bytes

    path = Path(path)
    try:
        data = read_regular_bytes(path)  # a FIFO or a device: one line, at once
    except FileNotFoundError:
        raise JsgsError(f"{path}: not found") from None
    except OSError as e:
        raise JsgsError(f"{path}: cannot read it: {e.strerror or e}") from None
    return parse_json(data, path, what, finite)


def _fmt(x: float) -> str:
    return f"{x:g}" if isinstance(x, float) else str(x)


def check_number(value: Any, where: str, lo: float | None = None, hi: float | None = None,
                 *, lo_open: bool = False) -> float:  # fmt: skip
    """``value`` as a float when it is a finite number (not a bool) in [lo, hi] (``lo_open``: (lo, hi]);
    else JsgsError ``<where> must be ... (got <value>)``."""
    ok = isinstance(value, (int, float)) and not isinstance(value, bool)
    x = float(value) if ok and (not isinstance(value, int) or abs(value) < 2**1023) else math.inf
    if ok and math.isfinite(x):
        below = lo is not None and (x <= lo if lo_open else x < lo)
        above = hi is not None and x > hi
        if not below and not above:
            return x
    if lo is not None and hi is not None:
        rng = f"in {'(' if lo_open else '['}{_fmt(lo)}, {_fmt(hi)}]"
    elif lo is not None:
        rng = f"{'>' if lo_open else '>='} {_fmt(lo)}"
    elif hi is not None:
        rng = f"<= {_fmt(hi)}"
    else:
        rng = ""
    got = repr(value) if len(repr(value)) <= 40 else repr(value)[:37] + "..."
    raise JsgsError(f"{where} must be a finite number{' ' + rng if rng else ''} (got {got})")


def check_coordinates(values: Any, where: str, by_row: bool = False) -> None:
    """Every entry of ``values`` (nested lists or a numpy array) finite and within ±:data:`MAX_COORDINATE`;
    else JsgsError naming ``where`` (with ``by_row``, ``<where>/<i>`` for the first offending row of a 2-D
    array) and the value."""
    import numpy as np

    a = np.asarray(values, dtype=np.float64)
    bad = ~(np.abs(a) <= MAX_COORDINATE)  # NaN compares false
    if not bad.any():
        return
    flat = int(np.flatnonzero(bad.reshape(-1))[0])
    first = float(a.reshape(-1)[flat])
    if by_row and a.ndim >= 2:
        where = f"{where}/{flat // (a.size // len(a))}"
    what = "not finite" if not math.isfinite(first) else f"beyond ±{MAX_COORDINATE:g} (world units)"
    raise JsgsError(f"{where}: coordinate {first:g} is {what}")
