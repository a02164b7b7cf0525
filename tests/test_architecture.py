"""The import rule of docs/architecture.md, checked over the source: no upward import, no import cycle.

The graph is built with ``ast`` from every module of the project's packages (games, tracing, store, viewers,
pipeline): every ``import`` and ``from ... import`` statement counts, at module level or inside a function,
and inside ``if TYPE_CHECKING:`` too (a type-only import still ties two modules together: the cycle it hides
comes back as soon as the type is needed at run time). The layers are read from the ``layers`` block of
docs/architecture.md, lowest first; names on one line sit side by side and may not import each other.

Run it as a script (``python -m tests.test_architecture``) for the summary of the graph: the edges between
folders and how many imports each stands for.
"""

from __future__ import annotations

import ast
import re
from collections import Counter
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("games", "tracing", "store", "viewers", "pipeline")
ARCHITECTURE = ROOT / "docs" / "architecture.md"


def layers() -> list[list[str]]:
    """The layers of docs/architecture.md's ``layers`` block, lowest first (one list of names per line)."""
    match = re.search(r"^```layers\n(.*?)^```", ARCHITECTURE.read_text(), re.S | re.M)
    assert match, f"{ARCHITECTURE} has no ```layers block"
    rows = []
    for line in match.group(1).splitlines():
        names = line.split("#", 1)[0].split()
        if names:
            rows.append(names)
    return rows


def modules() -> dict[str, Path]:
    """Every module of the project's packages, by dotted name (a package by its ``__init__``). Folders without an
    ``__init__.py`` are no packages: ``games/scaffolds/`` holds policy files, read as text and run in workers."""
    found = {}
    for package in PACKAGES:
        for path in sorted((ROOT / package).rglob("*.py")):
            if any(not (folder / "__init__.py").is_file() for folder in path.parents if ROOT in folder.parents):
                continue
            parts = path.relative_to(ROOT).with_suffix("").parts
            found[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = path
    return found


def _resolve(name: str, known: dict[str, Path]) -> str | None:
    """The project module an imported name stands for: itself, or the closest package that holds it."""
    while name and name not in known:
        name = name.rpartition(".")[0]
    return name or None


def imports(module: str, path: Path, known: dict[str, Path]) -> list[tuple[str, int]]:
    """(imported project module, line) for every import statement of ``module``."""
    tree = ast.parse(path.read_text(), str(path))
    package = module if path.name == "__init__.py" else module.rpartition(".")[0]
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            targets = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = package.split(".")[: len(package.split(".")) - node.level + 1]
                base = ".".join(anchor + ([base] if base else []))
            # `from pipeline.boundary import wire` imports the module pipeline.boundary.wire; `from store import Store`
            # the package
            targets = [f"{base}.{alias.name}" if f"{base}.{alias.name}" in known else base for alias in node.names]
        else:
            continue
        for target in targets:
            resolved = _resolve(target, known)
            if resolved is not None and resolved != module:
                found.append((resolved, node.lineno))
    return found


def graph() -> dict[str, dict[str, int]]:
    """module -> {imported module: line of the first import of it}."""
    known = modules()
    edges: dict[str, dict[str, int]] = {}
    for module, path in known.items():
        edges[module] = {}
        for target, line in imports(module, path, known):
            edges[module].setdefault(target, line)
    return edges


def layer_of(module: str, rows: list[list[str]]) -> tuple[int, str] | None:
    """(layer index, the layer name that holds ``module``): the longest listed name it is or lies under."""
    best = None
    for index, names in enumerate(rows):
        for name in names:
            if (module == name or module.startswith(name + ".")) and (best is None or len(name) > len(best[1])):
                best = (index, name)
    return best


def _where(module: str, line: int) -> str:
    path = modules()[module].relative_to(ROOT)
    return f"{path}:{line}"


def test_every_module_has_a_layer():
    rows = layers()
    unplaced = [m for m in modules() if layer_of(m, rows) is None]
    assert not unplaced, f"modules in no layer of {ARCHITECTURE.name}: {', '.join(unplaced)}"


def test_no_upward_import():
    rows = layers()
    wrong = []
    for module, targets in graph().items():
        here = layer_of(module, rows)
        for target, line in targets.items():
            there = layer_of(target, rows)
            if here is None or there is None or here[1] == there[1]:
                continue
            if there[0] > here[0]:
                wrong.append(f"{module} -> {target} ({_where(module, line)}): {here[1]} is below {there[1]}")
            elif there[0] == here[0]:
                wrong.append(f"{module} -> {target} ({_where(module, line)}): {here[1]} and {there[1]} sit side "
                             "by side")
    assert not wrong, "imports against the direction of docs/architecture.md:\n" + "\n".join(sorted(wrong))


def cycles(edges: dict[str, dict[str, int]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan's algorithm), each sorted."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in edges.get(v, {}):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                found.append(sorted(component))

    for v in sorted(edges):
        if v not in index:
            visit(v)
    return found


def test_no_import_cycle():
    edges = graph()
    found = []
    for component in cycles(edges):
        hops = [f"{a} -> {b} ({_where(a, line)})" for a in component for b, line in sorted(edges[a].items())
                if b in component]
        found.append(f"cycle among {', '.join(component)}:\n  " + "\n  ".join(hops))
    assert not found, "import cycles:\n" + "\n".join(found)


def test_the_graph_sees_every_kind_of_import(tmp_path):
    """The checks above would pass on an empty graph: it must hold imports of each form."""
    edges = graph()
    assert "pipeline.optimizer.assess" in edges["pipeline.optimizer.loop"]  # at module level
    assert "pipeline.play.evaluate" in edges["pipeline.cli.eval"]  # inside a function
    assert "pipeline.boundary.wire" in edges["pipeline.boundary.zygote"]  # from a package, a module
    assert "store" in edges["pipeline.optimizer.loop"]  # from a package, a name of its __init__
    known = modules()
    source = tmp_path / "probe.py"
    source.write_text("from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from pipeline.cli import main\n")
    assert imports("store.probe", source, known) == [("pipeline.cli", 3)]  # a type-only import counts too
    assert cycles({"a": {"b": 1}, "b": {"c": 1}, "c": {"a": 1}, "d": {"a": 1}}) == [["a", "b", "c"]]
    rows = [["games"], ["pipeline"], ["pipeline.play", "pipeline.llm"]]
    assert layer_of("pipeline.play.rollout", rows) == (2, "pipeline.play")
    assert layer_of("pipeline", rows) == (1, "pipeline") and layer_of("examples", rows) is None


def folder_edges() -> Counter:
    """(importing layer name, imported layer name) -> how many module-to-module imports cross between them."""
    rows = layers()
    counts: Counter = Counter()
    for module, targets in graph().items():
        here = layer_of(module, rows)
        for target in targets:
            there = layer_of(target, rows)
            if here and there and here[1] != there[1]:
                counts[here[1], there[1]] += 1
    return counts


if __name__ == "__main__":
    rows = layers()
    print("layers, lowest first:", " < ".join(", ".join(names) for names in rows))
    print(f"{len(modules())} modules, {sum(len(t) for t in graph().values())} module-to-module imports")
    for (a, b), n in sorted(folder_edges().items(), key=lambda kv: (layer_of(kv[0][0], rows), kv[0])):
        print(f"  {a:<20} -> {b:<20} {n:>3}")
    print("cycles:", cycles(graph()) or "none")
