"""The method registry of the generic trainer: the methods ``--method`` takes.

A method is a name (``--method``), a factory (config, scene, device) -> hook
(:class:`jsgs.train.hook.LossHook`) or None, and optionally an options dataclass for ``method_options``
(parsed and checked by :func:`jsgs.train.config.parse_method_options` like every other section). The built-in
ones are listed as ``"module:attribute"`` strings in :data:`BUILTIN_METHODS` and imported when a run asks for
them, so that the trainer never imports a method (the JSGS method is the package :mod:`jsgs.method`); others
are added with :func:`register_method`.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from jsgs.base.errors import JsgsError

#: A method is a factory (config, scene, device) -> :class:`jsgs.train.hook.LossHook` or None (None: the
#: plain gsplat baseline); the registry holds it without importing what it takes (the settings import the
#: registry).
MethodFactory = Callable[..., Any]


@dataclass(frozen=True)
class MethodEntry:
    """A method of ``--method``: its hook factory and its options section (a dataclass of
    :func:`jsgs.train.config.setting` fields, or None for a method without options), each either the object
    or a ``"module:attribute"`` string imported on first use."""

    factory: MethodFactory | str
    options: type | str | None = None


#: The built-in methods, named by strings so that the generic trainer imports no method when it is imported.
BUILTIN_METHODS: dict[str, MethodEntry] = {
    "gsplat": MethodEntry("jsgs.train.hook:gsplat_baseline"),
    "jsgs": MethodEntry("jsgs.method.hook:make_jsgs_hook", "jsgs.method.options:JsgsOptions"),
}

_METHODS: dict[str, MethodEntry] = {}


def register_method(name: str, factory: MethodFactory, options: type | None = None) -> None:
    """Make ``--method name`` available (a method defined outside :data:`BUILTIN_METHODS`); ``options``: its
    options dataclass (``method_options``), parsed by :func:`jsgs.train.config.parse_method_options`, with an
    optional ``check(where)`` method."""
    _METHODS[name] = MethodEntry(factory, options)


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
