"""The house's rules as tests: imports run down the layers, never in a circle, and each heavy library stays home.

The layers, lowest first (README, "Layout"); a module imports only from its own layer or below. Every import is read
with ``ast``, function-local and ``TYPE_CHECKING`` ones too: a late import is still a dependency.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

SRC = Path(__file__).resolve().parents[1] / "src"
PACKAGE = "aumesh"

#: package (or top-level module) -> its layer; 0 is the ground floor of vocabulary and workspace plumbing
LAYERS = {
    "core": 0,
    "geometry": 1,
    "data": 2,
    "model": 3,
    "card": 4,
    "export": 4,
    "synthetic": 4,
    "config": 4,
    "tracking": 5,
    "pipeline": 6,
    "stages": 7,
    "experiments": 7,
    "cli": 8,
}
#: the package's face (lazy public names, imported by string) and ``python -m aumesh``: above every layer
FACES = {"aumesh", "aumesh.__main__"}

#: third-party libraries that only their home packages import (a library user imports aumesh.model without them)
HOMES = {
    "mlflow": {"tracking"},
    "dask": {"pipeline.compute"},
    "distributed": {"pipeline.compute"},
    "matplotlib": {"card"},
    "argparse": {"cli"},
}

#: files that may exceed MAX_LINES, with the reason (none today)
LONG_FILES: dict[str, str] = {}
MAX_LINES = 600


def module_name(path: Path, src: Path = SRC) -> str:
    parts = list(path.relative_to(src).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def read_modules(src: Path = SRC) -> dict[str, ast.Module]:
    """Every module under ``src/aumesh``: dotted name -> parsed tree."""
    return {module_name(p, src): ast.parse(p.read_text(), str(p)) for p in sorted((src / PACKAGE).rglob("*.py"))}


def imports_of(name: str, tree: ast.Module, modules: set[str]) -> tuple[set[str], set[str]]:
    """(aumesh modules, third-party top-level names) that ``name`` imports anywhere in its body.

    ``from aumesh.pkg import x`` counts as importing the module ``aumesh.pkg.x`` when that is a module, else
    ``aumesh.pkg``; relative imports are resolved against ``name``.
    """
    inside, outside = set(), set()
    package = name if name in modules and _is_package(name, modules) else name.rpartition(".")[0]
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            targets = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = package.split(".")[: len(package.split(".")) - node.level + 1]
                base = ".".join([*anchor, base] if base else anchor)
            targets = [f"{base}.{a.name}" if f"{base}.{a.name}" in modules else base for a in node.names]
        else:
            continue
        for target in targets:
            if target == PACKAGE or target.startswith(PACKAGE + "."):
                while target not in modules and "." in target:  # `import aumesh.pkg.mod.attr` forms
                    target = target.rpartition(".")[0]
                if target != name:
                    inside.add(target)
            else:
                outside.add(target.split(".")[0])
    return inside, outside


def _is_package(name: str, modules: set[str]) -> bool:
    return any(m.startswith(name + ".") for m in modules)


def import_graph(src: Path = SRC) -> tuple[dict[str, set[str]], dict[str, set[str]]]:
    trees = read_modules(src)
    names = set(trees)
    graph, third = {}, {}
    for name, tree in trees.items():
        graph[name], third[name] = imports_of(name, tree, names)
    return graph, third


def layer_of(module: str) -> tuple[str, int] | None:
    """(home, layer) of an ``aumesh`` module: its package under aumesh, or None for the faces."""
    if module in FACES:
        return None
    home = module.split(".")[1]
    if home not in LAYERS:
        raise KeyError(f"{module}: in no layer; add its package to LAYERS (and the README's layout)")
    return home, LAYERS[home]


def upward_imports(graph: dict[str, set[str]]) -> list[str]:
    """``a -> b`` for every import from a lower layer to a higher one."""
    found = []
    for a, targets in sorted(graph.items()):
        la = layer_of(a)
        for b in sorted(targets):
            lb = layer_of(b)
            if la is None or lb is None:
                continue
            if lb[1] > la[1]:
                found.append(f"{a} (layer {la[1]}, {la[0]}) -> {b} (layer {lb[1]}, {lb[0]})")
    return found


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components of more than one node (Tarjan), each sorted: the import circles."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in graph.get(v, ()):
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

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return found


def package_graph(graph: dict[str, set[str]]) -> dict[str, set[str]]:
    """The same imports between the packages under aumesh (a package pair that imports each other is a circle)."""
    out: dict[str, set[str]] = {}
    for a, targets in graph.items():
        if a in FACES:
            continue
        pa = a.split(".")[1]
        out.setdefault(pa, set()).update(b.split(".")[1] for b in targets if b not in FACES and b.split(".")[1] != pa)
    return out


def misplaced_libraries(third: dict[str, set[str]]) -> list[str]:
    found = []
    for module, libraries in sorted(third.items()):
        where = module.split(".", 1)[1] if "." in module else ""
        for library in sorted(libraries & set(HOMES)):
            if not any(where == home or where.startswith(home + ".") for home in HOMES[library]):
                found.append(f"{module} imports {library} (home: {', '.join(sorted(HOMES[library]))})")
    return found


@pytest.fixture(scope="module")
def graphs():
    return import_graph()


def test_every_module_has_a_layer(graphs):
    graph, _ = graphs
    for module in graph:
        layer_of(module)  # raises for a package nobody placed


def test_imports_run_down_the_layers(graphs):
    graph, _ = graphs
    assert upward_imports(graph) == []


def test_no_import_circles_between_modules_or_packages(graphs):
    graph, _ = graphs
    assert cycles(graph) == []
    assert cycles(package_graph(graph)) == []


def test_heavy_libraries_stay_in_their_home_packages(graphs):
    _, third = graphs
    assert misplaced_libraries(third) == []


def test_no_source_file_over_600_lines():
    long = {
        str(p.relative_to(SRC)): n
        for p in sorted((SRC / PACKAGE).rglob("*.py"))
        if (n := len(p.read_text().splitlines())) > MAX_LINES and str(p.relative_to(SRC)) not in LONG_FILES
    }
    assert long == {}


def _write(root: Path, files: dict[str, str]) -> Path:
    for rel, text in files.items():
        path = root / PACKAGE / rel
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text)
    return root


def test_the_rules_catch_a_back_up_import_a_circle_and_a_library_away_from_home(tmp_path):
    """The checks above on a small tree that breaks each rule once, in the ways real code hides it."""
    src = _write(
        tmp_path,
        {
            "__init__.py": "",
            "core/__init__.py": "",
            "core/io.py": "def f():\n    from aumesh.core import signals  # function-local\n",
            "core/signals.py": "from . import io\n",  # relative: io <-> signals is a circle
            "model/__init__.py": "",
            "model/fit.py": "from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from aumesh.pipeline import run\n",
            "pipeline/__init__.py": "",
            "pipeline/run.py": "import aumesh.model.fit\nimport matplotlib.pyplot\n",
        },
    )
    graph, third = import_graph(src)
    assert upward_imports(graph) == ["aumesh.model.fit (layer 3, model) -> aumesh.pipeline.run (layer 6, pipeline)"]
    assert cycles(graph) == [["aumesh.core.io", "aumesh.core.signals"], ["aumesh.model.fit", "aumesh.pipeline.run"]]
    assert cycles(package_graph(graph)) == [["model", "pipeline"]]
    assert misplaced_libraries(third) == ["aumesh.pipeline.run imports matplotlib (home: card)"]
