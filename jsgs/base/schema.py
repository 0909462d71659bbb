"""Loading the JSON Schemas that ``jsgs/schemas/*.schema.json`` ship as package data, and the one-line
validation error built from them (:class:`~jsgs.base.errors.JsgsError` naming the file).

Every schema's ``$id`` is :data:`BASE_URI` + its file name, so one schema refers to another by file name
(``"$ref": "config.schema.json#/properties/settings"``); :func:`validate` resolves such references among the
shipped schemas only, never over the network."""

from __future__ import annotations

import json
from functools import cache
from pathlib import Path
from typing import Any

from jsgs.base.errors import JsgsError

#: the folder of the schema files: the data package :mod:`jsgs.schemas`
SCHEMA_DIR = Path(__file__).resolve().parents[1] / "schemas"
#: the ``$id`` of every shipped schema is this followed by its file name (``manifest.schema.json``)
BASE_URI = "https://jsgs.dev/schemas/"


@cache
def load_schema(name: str) -> dict[str, Any]:
    """``name`` without extension, e.g. ``"manifest"`` -> ``jsgs/schemas/manifest.schema.json``."""
    path = SCHEMA_DIR / f"{name}.schema.json"
    return json.loads(path.read_text())


@cache
def registry() -> Any:
    """A :class:`referencing.Registry` of every shipped schema under its ``$id`` (:data:`BASE_URI` + file
    name), for the references between them; a reference to anything else is unresolvable, not fetched."""
    from referencing import Registry, Resource
    from referencing.jsonschema import DRAFT202012

    names = sorted(p.name.removesuffix(".schema.json") for p in SCHEMA_DIR.glob("*.schema.json"))
    return Registry().with_resources(
        (f"{BASE_URI}{n}.schema.json", Resource.from_contents(load_schema(n), DRAFT202012)) for n in names
    )


def validate(doc: Any, name: str, where: str) -> None:
    """Raise JsgsError (one line, naming ``where``) if ``doc`` does not satisfy schema ``name``."""
    import jsonschema

    validator = jsonschema.Draft202012Validator(load_schema(name), registry=registry())
    errors = list(validator.iter_errors(doc))
    if errors:
        # best_match descends into oneOf/anyOf to the most specific failure instead of echoing the object.
        e = jsonschema.exceptions.best_match(errors)
        loc = "/".join(str(p) for p in e.absolute_path) or "(top level)"
        more = f" (and {len(errors) - 1} more)" if len(errors) > 1 else ""
        msg = e.message if len(e.message) <= 200 else e.message[:197] + "..."
        raise JsgsError(f"{where}: not a valid {name} file: at {loc}: {msg}{more}")
