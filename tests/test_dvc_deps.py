"""``dvc.yaml`` knows every line of code a stage runs: each stage's import closure is covered by its ``deps:``.

A stage's code is its module ``aumesh.stages.<stage>`` and everything that imports, function-local imports included
(the import graph of ``test_layers``). A file counts as covered when ``deps:`` lists it or a folder above it. Without
this, an edit to an unlisted file leaves ``dvc repro`` "up to date" with outputs of the old code.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest
import yaml

from test_layers import SRC, import_graph, read_modules

ROOT = SRC.parent

#: files a stage imports that cannot change its outputs, with why (everything else must be a dep)
CANNOT_CHANGE_RESULTS = {
    "src/aumesh/__init__.py": "the package's lazy public names: it runs nothing a stage computes with",
    "src/aumesh/core/progress.py": "progress bars on stderr",
    "src/aumesh/core/signals.py": "stopping on a signal or when DVC is gone",
    "src/aumesh/core/settings.py": "this machine's tracking server and cluster address (like the `tracking` params)",
    "src/aumesh/tracking/": "where runs are logged (the `tracking` params are not stage params either)",
    "src/aumesh/experiments/promotion_journal.py": "completes or rolls back a killed `aumesh promote` before a stage "
    "reads params.yaml/promotion.json, and stops the stage if they changed: it computes nothing",
}


def module_file(module: str, src: Path = SRC) -> str:
    """``aumesh.core.io`` -> ``src/aumesh/core/io.py`` (a package's ``__init__.py``), relative to the repository."""
    path = src.joinpath(*module.split("."))
    path = path / "__init__.py" if path.is_dir() else path.with_suffix(".py")
    return path.relative_to(src.parent).as_posix()


def closure(start: str, graph: dict[str, set[str]]) -> set[str]:
    """``start`` and every module it imports, directly or not; a module's packages run their ``__init__`` too."""
    seen, todo = set(), [start]
    while todo:
        module = todo.pop()
        if module in seen:
            continue
        seen.add(module)
        parents = [".".join(module.split(".")[:i]) for i in range(1, module.count(".") + 1)]
        todo += [*graph.get(module, ()), *(p for p in parents if p in graph)]
    return seen


def uncovered(files: set[str], deps: list[str], allowed: dict[str, str] = CANNOT_CHANGE_RESULTS) -> list[str]:
    """The ``files`` that no dep (a file, or a folder above it) and no allowed entry covers."""

    def covered(file: str, entries) -> bool:
        return any(file == e.rstrip("/") or file.startswith(e.rstrip("/") + "/") for e in entries)

    return sorted(f for f in files if not covered(f, deps) and not covered(f, allowed))


def _is_face(path: Path) -> bool:
    """An ``__init__.py`` that is a docstring and nothing else: importing it runs no code."""
    body = ast.parse(path.read_text()).body
    return path.name == "__init__.py" and all(
        isinstance(n, ast.Expr) and isinstance(n.value, ast.Constant) for n in body
    )


def stage_code(stage: str, graph: dict[str, set[str]], src: Path = SRC) -> set[str]:
    files = {module_file(m, src) for m in closure(f"aumesh.stages.{stage}", graph)}
    return {f for f in files if not _is_face(src.parent / f)}


def source_deps(stage: dict) -> list[str]:
    return [d for d in stage.get("deps", []) if isinstance(d, str) and d.startswith("src/")]


@pytest.fixture(scope="module")
def pipeline():
    """The stages of ``dvc.yaml``; a ``foreach`` stage (``release_family``) as its ``do:`` template, ``${item}`` and
    all, which DVC runs once per item."""
    stages = yaml.safe_load((ROOT / "dvc.yaml").read_text())["stages"]
    return {name: spec.get("do", spec) for name, spec in stages.items()}


@pytest.fixture(scope="module")
def graph():
    return import_graph()[0]


def test_every_stage_has_its_module_and_names_it(pipeline):
    for stage, spec in pipeline.items():
        path = f"src/aumesh/stages/{stage}.py"
        assert (ROOT / path).is_file(), f"dvc.yaml stage {stage!r} has no module {path}"
        assert f" {stage} " in f" {spec['cmd']} ", spec["cmd"]
        assert path in source_deps(spec), f"{stage}: deps must list its module {path}"


def test_each_stage_depends_on_all_the_code_it_imports(pipeline, graph):
    missing = {stage: uncovered(stage_code(stage, graph), source_deps(spec)) for stage, spec in pipeline.items()}
    assert {stage: files for stage, files in missing.items() if files} == {}


def test_every_listed_source_dep_exists(pipeline):
    gone = [(stage, d) for stage, spec in pipeline.items() for d in source_deps(spec) if not (ROOT / d).exists()]
    assert gone == []


def test_the_check_finds_a_file_the_deps_forgot(tmp_path):
    """A stage whose module imports, inside a function, a file its deps do not list: the check names that file."""
    src = tmp_path / "src"
    files = {
        "aumesh/__init__.py": "__version__ = '0'\n",
        "aumesh/stages/__init__.py": '"""stages"""\n',
        "aumesh/stages/fit.py": "from aumesh.model import pls\n\n\ndef main():\n    from aumesh.model import stats\n",
        "aumesh/model/__init__.py": '"""model"""\n',
        "aumesh/model/pls.py": "from aumesh.core import io\n",
        "aumesh/model/stats.py": "",
        "aumesh/core/__init__.py": '"""core"""\n',
        "aumesh/core/io.py": "",
    }
    for rel, text in files.items():
        (src / rel).parent.mkdir(parents=True, exist_ok=True)
        (src / rel).write_text(text)
    trees = read_modules(src)
    assert set(trees) >= {"aumesh.stages.fit", "aumesh.model.stats"}
    small = import_graph(src)[0]
    code = stage_code("fit", small, src)
    assert code == {"src/aumesh/__init__.py", *(f"src/{r}" for r in files if not r.endswith("__init__.py"))}
    deps = ["src/aumesh/stages/fit.py", "src/aumesh/model/pls.py", "src/aumesh/core"]
    assert uncovered(code, deps, allowed={}) == ["src/aumesh/__init__.py", "src/aumesh/model/stats.py"]
    assert uncovered(code, [*deps, "src/aumesh/model", "src/aumesh/__init__.py"], allowed={}) == []
