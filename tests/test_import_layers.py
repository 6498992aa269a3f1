"""The import contract (issue 40): no import cycle between como3r's modules, and no import
that points up the layer list of docs/architecture.md ("Layers").

Every import counts, at module level, inside functions and under ``TYPE_CHECKING`` alike: a
reader follows all of them, and a cycle through a function-level import is still a cycle in
the design. The check reads the source with :mod:`ast`, so it imports nothing.
"""

from __future__ import annotations

import ast
import fnmatch
import functools
import re
from collections.abc import Iterator
from pathlib import Path

import networkx as nx

ROOT = Path(__file__).resolve().parents[1]
SRC = ROOT / "src"
ARCHITECTURE = ROOT / "docs" / "architecture.md"


def modules() -> dict[str, Path]:
    """Every module of the package: dotted name -> file (a package is its __init__)."""
    found = {}
    for path in sorted((SRC / "como3r").rglob("*.py")):
        parts = list(path.relative_to(SRC).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts = parts[:-1]
        found[".".join(parts)] = path
    return found


def imports(name: str, path: Path, known: set[str]) -> Iterator[str]:
    """The como3r modules that module ``name`` imports, anywhere in its source. ``from
    PACKAGE import NAME`` imports the module ``PACKAGE.NAME`` where there is one, else
    ``PACKAGE``."""
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            targets = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                parts = package.split(".")
                anchor = parts[: len(parts) - node.level + 1]
                base = ".".join(anchor + ([base] if base else []))
            targets = [
                f"{base}.{alias.name}" if f"{base}.{alias.name}" in known else base
                for alias in node.names
            ]
        else:
            continue
        for target in targets:
            while target and target not in known and "." in target:
                target = target.rpartition(".")[0]  # import como3r.a.b.function
            if target in known and target != name:
                yield target


@functools.cache
def import_graph() -> dict[str, set[str]]:
    """Module -> the modules it imports (read once per test session)."""
    found = modules()
    known = set(found)
    return {name: set(imports(name, path, known)) for name, path in found.items()}


def cycles(graph: dict[str, set[str]]) -> list[frozenset[str]]:
    """The strongly connected components of more than one module."""
    digraph = nx.DiGraph([(name, target) for name, targets in graph.items() for target in targets])
    return [frozenset(c) for c in nx.strongly_connected_components(digraph) if len(c) > 1]


def layers() -> list[list[str]]:
    """The layer list of docs/architecture.md, top first: each layer's names (a package, a
    top-level module, or a pattern such as ``cli_*``), between the ``layers`` markers."""
    text = ARCHITECTURE.read_text()
    block = re.search(r"<!-- layers -->\n(.*?)<!-- /layers -->", text, re.S)
    assert block, f"{ARCHITECTURE}: no <!-- layers --> ... <!-- /layers --> block"
    found = []
    for line in block.group(1).splitlines():
        item = re.match(r"\d+\. (.*)", line.strip())
        if item:
            names = re.findall(r"`([^`]+)`", item.group(1).split(":")[0])
            found.append([name.removesuffix("/").removesuffix(".py") for name in names])
    return found


def unit(module: str) -> str:
    """The package or top-level module that ``module`` belongs to (``como3r``: the
    package's own ``__init__``)."""
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else "como3r"


def layer_of(name: str, listed: list[list[str]]) -> int | None:
    for depth, names in enumerate(listed):
        if any(fnmatch.fnmatchcase(unit(name), pattern) for pattern in names):
            return depth
    return None


def test_no_import_cycles() -> None:
    found = [sorted(cycle) for cycle in cycles(import_graph())]
    assert not found, f"import cycles: {found}"


def test_every_package_is_in_a_layer() -> None:
    listed = layers()
    assert len(listed) > 5, listed
    missing = sorted({unit(name) for name in modules() if layer_of(name, listed) is None})
    assert not missing, f"not in the layer list of {ARCHITECTURE.name}: {missing}"


def test_imports_point_down_the_layers() -> None:
    listed = layers()
    upward = sorted(
        (name, target)
        for name, targets in import_graph().items()
        for target in targets
        if layer_of(target, listed) < layer_of(name, listed)
    )
    assert not upward, f"imports that point up the layers of {ARCHITECTURE.name}: {upward}"


def test_the_check_sees_cycles_and_layers() -> None:
    """The checks themselves: a planted cycle and an upward import are found."""
    graph = {"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}
    assert cycles(graph) == [frozenset({"a", "b", "c"})]
    listed = [["runtime"], ["store"], ["transport"]]
    assert layer_of("como3r.transport.codec", listed) > layer_of("como3r.runtime.pipeline", listed)
    graph = import_graph()
    assert "como3r.transport.codec" in graph["como3r.transport.messages"]  # a module import
    assert "como3r.store.reader" in graph["como3r.cli"]  # a function-level one
