"""Loading the JSON Schemas that ``jsgs/schemas/*.schema.json`` ship as package data, and the one-line
validation error built from them (:class:`~jsgs.base.errors.JsgsError` naming the file)."""

from __future__ import annotations

import json
from functools import cache
from pathlib import Path
from typing import Any

from jsgs.base.errors import JsgsError

#: the folder of the schema files: the data package :mod:`jsgs.schemas`
SCHEMA_DIR = Path(__file__).resolve().parents[1] / "schemas"


@cache
def load_schema(name: str) -> dict[str, Any]:
    """``name`` without extension, e.g. ``"manifest"`` -> ``jsgs/schemas/manifest.schema.json``."""
    path = SCHEMA_DIR / f"{name}.schema.json"
    return json.loads(path.read_text())


def validate(doc: Any, name: str, where: str) -> None:
    """Raise JsgsError (one line, naming ``where``) if ``doc`` does not satisfy schema ``name``."""
    import jsonschema

    validator = jsonschema.Draft202012Validator(load_schema(name))
    errors = list(validator.iter_errors(doc))
    if errors:
        # best_match descends into oneOf/anyOf to the most specific failure instead of echoing the object.
        e = jsonschema.exceptions.best_match(errors)
        loc = "/".join(str(p) for p in e.absolute_path) or "(top level)"
        more = f" (and {len(errors) - 1} more)" if len(errors) > 1 else ""
        msg = e.message if len(e.message) <= 200 else e.message[:197] + "..."
        raise JsgsError(f"{where}: not a valid {name} file: at {loc}: {msg}{more}")
