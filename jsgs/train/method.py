"""The method registry of the generic trainer: the methods ``--method`` takes.

A method is a name (``--method``), a factory (config, scene, device) -> hook
(:class:`jsgs.train.hook.LossHook`) or None, and optionally an options dataclass for ``method_options``
(parsed and checked by :func:`jsgs.train.config.parse_method_options` like every other section), its recipes
(the ``method_options`` each preset of :data:`jsgs.train.config.PRESETS` gives it: :func:`method_recipe`) and
its ``jsgs train`` switches (:class:`MethodFlag`, each setting one of its options: :func:`method_flags`). The
built-in ones are listed as ``"module:attribute"`` strings in :data:`BUILTIN_METHODS` and imported when a run
asks for them, so that the trainer never imports a method (the JSGS method is the package :mod:`jsgs.method`);
others are added with :func:`register_method`. This module imports no torch: the command line reads it.
"""

from __future__ import annotations

import copy
import importlib
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from jsgs.base.errors import JsgsError

#: A method is a factory (config, scene, device) -> :class:`jsgs.train.hook.LossHook` or None (None: the
#: plain gsplat baseline); the registry holds it without importing what it takes (the settings import the
#: registry).
MethodFactory = Callable[..., Any]


@dataclass(frozen=True)
class MethodFlag:
    """A ``jsgs train`` switch of a method: it sets ``method_options.<option>`` (dotted for a nested section,
    e.g. ``speed.compile``) and applies to that method alone. With ``choices`` the switch takes one of them
    as its value; without, it is an on/off flag that sets ``value`` when given."""

    flag: str
    option: str
    help: str
    choices: tuple[str, ...] = ()
    value: Any = None

    @property
    def dest(self) -> str:
        """The switch's parameter name (``--no-jo``: ``no_jo``)."""
        return self.flag.lstrip("-").replace("-", "_")

    def options(self, given: Any) -> dict[str, Any]:
        """The ``method_options`` the switch sets when given ``given`` (its choice, or True for a flag)."""
        value = given if self.choices else self.value
        *sections, name = self.option.split(".")
        out: dict[str, Any] = {name: value}
        for section in reversed(sections):
            out = {section: out}
        return out


@dataclass(frozen=True)
class MethodEntry:
    """A method of ``--method``: its hook factory, its options section (a dataclass of
    :func:`jsgs.train.config.setting` fields, or None for a method without options), its recipes (preset
    name -> ``method_options``) and its switches (:class:`MethodFlag`), each either the object or a
    ``"module:attribute"`` string imported on first use."""

    factory: MethodFactory | str
    options: type | str | None = None
    recipes: Mapping[str, dict[str, Any]] | str | None = None
    flags: Sequence[MethodFlag] | str | None = None


#: The built-in methods, named by strings so that the generic trainer imports no method when it is imported.
BUILTIN_METHODS: dict[str, MethodEntry] = {
    "gsplat": MethodEntry("jsgs.train.hook:gsplat_baseline"),
    "jsgs": MethodEntry(
        "jsgs.method.hook:make_jsgs_hook",
        "jsgs.method.options:JsgsOptions",
        "jsgs.method.recipes:RECIPES",
        "jsgs.method.flags:FLAGS",
    ),
}

_METHODS: dict[str, MethodEntry] = {}


def register_method(
    name: str,
    factory: MethodFactory,
    options: type | None = None,
    recipes: Mapping[str, dict[str, Any]] | None = None,
    flags: Sequence[MethodFlag] | None = None,
) -> None:
    """Make ``--method name`` available (a method defined outside :data:`BUILTIN_METHODS`); ``options``: its
    options dataclass (``method_options``), parsed by :func:`jsgs.train.config.parse_method_options`, with an
    optional ``check(where)`` method; ``recipes``: the ``method_options`` a preset gives it (preset name ->
    options); ``flags``: its ``jsgs train`` switches (those of a method registered after the command line
    was built do not show there)."""
    _METHODS[name] = MethodEntry(factory, options, recipes, flags)


def method_names() -> list[str]:
    """Every method ``--method`` takes."""
    return sorted({*BUILTIN_METHODS, *_METHODS})


def _resolve(target: Any) -> Any:
    if isinstance(target, str):
        module, attr = target.split(":")
        return getattr(importlib.import_module(module), attr)
    return target


def _entry(name: str) -> MethodEntry:
    entry = _METHODS.get(name) or BUILTIN_METHODS.get(name)
    if entry is None:
        raise JsgsError(f"unknown method {name!r} (available: {', '.join(method_names())})")
    return entry


def options_class(name: str) -> type | None:
    """The options dataclass of method ``name`` (None: it takes no method_options)."""
    cls: type | None = _resolve(_entry(name).options)
    return cls


def method_factory(name: str) -> MethodFactory:
    """The hook factory of method ``name`` (JsgsError naming the available methods when unknown)."""
    factory: MethodFactory = _resolve(_entry(name).factory)
    return factory


def method_recipe(name: str, preset: str) -> dict[str, Any]:
    """The ``method_options`` preset ``preset`` gives method ``name`` (a copy; empty where it gives none,
    and for a method not registered, which the settings' check then names)."""
    if name not in method_names():
        return {}
    recipes: Mapping[str, dict[str, Any]] = _resolve(_entry(name).recipes) or {}
    return copy.deepcopy(recipes.get(preset, {}))


def method_flags(name: str) -> tuple[MethodFlag, ...]:
    """The ``jsgs train`` switches of method ``name``."""
    return tuple(_resolve(_entry(name).flags) or ())
