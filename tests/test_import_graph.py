"""The import graph of ``jsgs`` and ``jsgstools``: no cycles, and the layers in order.

Every import statement is an edge: those inside functions (lazy) and those under ``if TYPE_CHECKING:``
included, since a lazy import only defers a cycle to run time and a type-only one still ties the two modules
together for a reader. ``from package import name`` is an edge to the submodule ``package.name`` when that is
a module, else to ``package``. The trainer's method registry names its built-in methods as strings
(``jsgs.train.method.BUILTIN_METHODS``), which is no import.

The layers, bottom first (:data:`LAYERS`): a module imports only from its own layer and those below, so the
bottom never imports upward. Every module is in one."""

from __future__ import annotations

import ast
import functools
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("jsgs", "jsgstools")
#: The layers, bottom first: (name, the packages or modules in it). ``jsgs`` is the top package's
#: ``__init__`` alone (its version); the rest stand for themselves and everything under them.
LAYERS: tuple[tuple[str, tuple[str, ...]], ...] = (
    ("base", ("jsgs", "jsgs.base", "jsgs.schemas")),
    ("kernels and image math", ("jsgs.kernels", "jsgs.jpeg", "jsgs.render", "jsgs.metrics")),
    ("dataset toolkit", ("jsgstools",)),
    ("trainer", ("jsgs.train",)),
    ("method", ("jsgs.method",)),
    ("apps", ("jsgs.apps",)),
    ("bench", ("jsgs.bench",)),
    ("command line", ("jsgs.cli",)),
)


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def _modules() -> dict[str, Path]:
    return {_module_name(p): p for pkg in PACKAGES for p in sorted((ROOT / pkg).rglob("*.py"))}


def _imports(tree: ast.Module) -> list[ast.Import | ast.ImportFrom]:
    """Every import statement of a module: at its top, inside functions, under ``if TYPE_CHECKING:``."""
    return [n for n in ast.walk(tree) if isinstance(n, (ast.Import, ast.ImportFrom))]


@functools.cache
def import_graph() -> dict[str, set[str]]:
    """module -> the modules of the tree it imports (read once; the tests only read it)."""
    modules = _modules()
    graph: dict[str, set[str]] = {m: set() for m in modules}
    for name, path in modules.items():
        package = name if path.name == "__init__.py" else name.rpartition(".")[0]
        for node in _imports(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.Import):
                targets = [a.name for a in node.names]
            else:
                base = node.module or ""
                if node.level:
                    anchor = package.split(".")
                    anchor = anchor[: len(anchor) - (node.level - 1)]
                    base = ".".join([*anchor, base] if base else anchor)
                targets = [f"{base}.{a.name}" if f"{base}.{a.name}" in modules else base for a in node.names]
            for t in targets:
                # the nearest module of the jsgs/jsgstools tree that the name lies in
                while t and t not in modules:
                    t = t.rpartition(".")[0]
                if t and t != name:
                    graph[name].add(t)
    return graph


def find_cycle(graph: dict[str, set[str]]) -> list[str] | None:
    """One cycle as a list of modules (first = last), or None."""
    state: dict[str, int] = {}
    stack: list[str] = []

    def dfs(u: str) -> list[str] | None:
        state[u] = 1
        stack.append(u)
        for v in sorted(graph[u]):
            if state.get(v) == 1:
                return [*stack[stack.index(v) :], v]
            if v not in state:
                c = dfs(v)
                if c:
                    return c
        stack.pop()
        state[u] = 2
        return None

    for m in sorted(graph):
        if m not in state:
            c = dfs(m)
            if c:
                return c
    return None


def test_no_import_cycles() -> None:
    graph = import_graph()
    assert "jsgs.train.trainer" in graph and "jsgs.method.hook" in graph
    cycle = find_cycle(graph)
    assert cycle is None, " -> ".join(cycle or [])


def layer_of(module: str) -> int | None:
    """The index in :data:`LAYERS` of the layer holding ``module`` (its longest matching entry), or None."""
    best: tuple[int, int] | None = None
    for i, (_, entries) in enumerate(LAYERS):
        for e in entries:
            holds = module == e if e == "jsgs" else module == e or module.startswith(e + ".")
            if holds and (best is None or len(e) > best[1]):
                best = (i, len(e))
    return None if best is None else best[0]


def upward_imports(graph: dict[str, set[str]]) -> list[str]:
    """Every edge from a lower layer to a higher one, as ``a (layer) -> b (layer)``."""
    out = []
    for a in sorted(graph):
        for b in sorted(graph[a]):
            la, lb = layer_of(a), layer_of(b)
            if la is not None and lb is not None and lb > la:
                out.append(f"{a} ({LAYERS[la][0]}) -> {b} ({LAYERS[lb][0]})")
    return out


def test_every_module_is_in_a_layer() -> None:
    graph = import_graph()
    assert not [m for m in sorted(graph) if layer_of(m) is None]


def test_no_layer_imports_upward() -> None:
    graph = import_graph()
    assert "jsgs.base.errors" in graph and "jsgs.apps.viewer" in graph
    assert upward_imports(graph) == []


def test_the_layer_check_sees_an_upward_import() -> None:
    graph = {"jsgs.base.io": {"jsgs.train.trainer"}, "jsgs.train.trainer": {"jsgs.base.io"}}
    assert upward_imports(graph) == ["jsgs.base.io (base) -> jsgs.train.trainer (trainer)"]
    assert layer_of("jsgs") == 0 and layer_of("jsgs.cli.train") == len(LAYERS) - 1
    assert layer_of("jsgstools.dqt.parser") == 2 and layer_of("jsgsx") is None


def test_the_graph_counts_lazy_and_type_checking_imports() -> None:
    code = (
        "from typing import TYPE_CHECKING\n"
        "import a\n"
        "if TYPE_CHECKING:\n    from b import x\n"
        "def f():\n    import c.d\n"
    )
    found = [ast.unparse(n) for n in _imports(ast.parse(code))]
    assert sorted(found) == ["from b import x", "from typing import TYPE_CHECKING", "import a", "import c.d"]


def test_the_generic_trainer_does_not_import_the_method() -> None:
    graph = import_graph()
    reach: set[str] = set()
    todo = [m for m in graph if m.startswith("jsgs.train")]
    while todo:
        m = todo.pop()
        if m not in reach:
            reach.add(m)
            todo.extend(graph[m])
    assert not [m for m in reach if m.startswith("jsgs.method")]


def test_the_bottom_packages_import_only_themselves() -> None:
    """``jsgs.base`` imports nothing else of the project but the top package's version, and ``jsgs.schemas``
    (the schema files, data only) imports nothing at all: no package-level arrow inside the bottom layer."""
    graph = import_graph()
    base_out = sorted(f"{m} -> {t}" for m in graph if m.startswith("jsgs.base") for t in graph[m]
                      if t != "jsgs" and not t.startswith("jsgs.base"))
    assert base_out == []
    assert not [t for m in graph if m.startswith("jsgs.schemas") for t in graph[m]]


def test_the_finder_sees_a_cycle() -> None:
    assert find_cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}}) == ["a", "b", "c", "a"]
    assert find_cycle({"a": {"b"}, "b": set()}) is None
