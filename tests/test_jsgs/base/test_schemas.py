"""The shipped JSON Schemas (``jsgs/schemas/*.schema.json``): each is a valid Draft 2020-12 schema whose
``$id`` is its file's, and every ``$ref`` in it resolves among the shipped schemas (a reference into another
schema, as configs.schema.json's into config.schema.json, is followed by ``jsgs.base.schema.validate``)."""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import jsonschema
import pytest

from jsgs.base.errors import JsgsError
from jsgs.base.schema import BASE_URI, SCHEMA_DIR, load_schema, registry, validate

NAMES = sorted(p.name.removesuffix(".schema.json") for p in SCHEMA_DIR.glob("*.schema.json"))


def _refs(node: Any) -> Iterator[str]:
    if isinstance(node, dict):
        if isinstance(node.get("$ref"), str):
            yield node["$ref"]
        for v in node.values():
            yield from _refs(v)
    elif isinstance(node, list):
        for v in node:
            yield from _refs(v)


@pytest.mark.parametrize("name", NAMES)
def test_a_shipped_schema_is_valid_and_its_references_resolve(name: str) -> None:
    schema = load_schema(name)
    jsonschema.Draft202012Validator.check_schema(schema)
    assert schema.get("$id") == f"{BASE_URI}{name}.schema.json"
    resolver = registry().resolver(base_uri=schema["$id"])
    for ref in _refs(schema):
        resolver.lookup(ref)  # raises where it points at nothing


def test_a_reference_into_another_schema_is_checked() -> None:
    """configs.schema.json's settings are config.schema.json's: a run's complete settings pass, an unknown
    setting and a missing section are refused in one line naming the file."""
    config = load_schema("config")
    refs = set(_refs(load_schema("configs")))
    assert "configs" in NAMES and "config.schema.json#/properties/settings" in refs
    sections = config["properties"]["settings"]["allOf"][1]["required"]
    settings: dict[str, Any] = {k: {} for k in sections}
    settings.update(method="gsplat", iterations=10, eval_at=[10], checkpoint_every=0, checkpoint_keep=0,
                    seed=0, device="cpu", log_every=1)  # fmt: skip
    versions = {"jsgs": "0", "torch": "2", "gsplat": None, "python": "3"}
    entry = {"settings": settings, "versions": versions, "command": "jsgs train m --out r"}
    key = "scene/clean/gsplat/mcmc-1000/s0"
    validate({key: entry}, "configs", "x.json")
    for bad, says in (
        ({**settings, "speedy": True}, "Additional properties are not allowed ('speedy' was unexpected)"),
        ({k: v for k, v in settings.items() if k != "optim"}, "'optim' is a required property"),
        ({**settings, "strategy": {"cap_max": 0}}, "0 is less than the minimum of 1"),
    ):
        with pytest.raises(JsgsError) as e:
            validate({key: {**entry, "settings": bad}}, "configs", "x.json")
        line = str(e.value)
        assert line.startswith(f"x.json: not a valid configs file: at {key}/settings") and says in line
