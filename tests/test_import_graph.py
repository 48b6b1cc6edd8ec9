"""The import graph of ``dexflow``: stage modules stay independent of each other, and the config
and params-schema modules never pull a stage in.

The graph is read statically with :mod:`ast` (nothing is imported): every ``import`` and
``from ... import`` at any depth of a module counts, function-local and ``TYPE_CHECKING`` ones
included. ``tests/test_dvc_deps.py`` uses the same graph to check the deps of ``dvc.yaml``.
"""

from __future__ import annotations

import ast
from collections import deque
from functools import cache
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = "dexflow"

# The module of each pipeline stage (the stage of dvc.yaml in the comment).
STAGE_MODULES = (
    "dexflow.data.demo",  # demo
    "dexflow.align",  # scale_align
    "dexflow.retarget",  # retarget
    "dexflow.contact",  # contact
    "dexflow.refine",  # refine
    "dexflow.simulate",  # simulate
    "dexflow.metrics",  # metrics
    "dexflow.report",  # report
)


@cache
def module_files() -> dict[str, Path]:
    """Every module of the package by dotted name (``dexflow.io`` -> ``dexflow/io/__init__.py``)."""
    files = {}
    for path in sorted((ROOT / PACKAGE).rglob("*.py")):
        parts = path.relative_to(ROOT).with_suffix("").parts
        if parts[-1] == "__init__":
            parts = parts[:-1]
        files[".".join(parts)] = path
    return files


def _is_package(module: str) -> bool:
    return module_files()[module].name == "__init__.py"


def _ancestors(module: str) -> list[str]:
    """``dexflow.io.layout`` -> ``[dexflow, dexflow.io]``: the packages importing it runs first."""
    parts = module.split(".")
    return [".".join(parts[:i]) for i in range(1, len(parts))]


def imports_of_file(path: Path, module: str | None = None) -> set[str]:
    """The dexflow modules that ``path`` imports directly, as written (at any depth).

    ``module`` is the file's dotted name, needed for relative imports (``None`` for a script).
    ``from X import y`` names ``X.y`` when that is a module, and ``X`` (whose ``__init__`` runs)
    in any case.
    """
    known = module_files()
    tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
    found: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                if module is None:
                    raise AssertionError(f"{path}: relative import in a script")
                package = module if _is_package(module) else module.rpartition(".")[0]
                parts = package.split(".")
                if node.level > 1:
                    parts = parts[: -(node.level - 1)]
                base = ".".join([*parts, node.module] if node.module else parts)
            else:
                base = node.module or ""
            found.add(base)
            found.update(f"{base}.{alias.name}" for alias in node.names)
    # Keep the dexflow modules only (a name that is no module, e.g. `from dexflow.x import f`,
    # drops out: ``dexflow.x`` itself is in ``found``).
    return {name for name in found if name in known}


@cache
def import_graph() -> dict[str, frozenset[str]]:
    """module -> the dexflow modules it imports directly, for every module of the package."""
    return {
        name: frozenset(imports_of_file(path, name) - {name})
        for name, path in module_files().items()
    }


def import_chains(starts: set[str] | frozenset[str]) -> dict[str, list[str]]:
    """Every module that importing ``starts`` runs, each with one import chain that reaches it.

    Following Python, importing ``a.b.c`` also runs the packages ``a`` and ``a.b``.
    """
    graph = import_graph()
    chains: dict[str, list[str]] = {}
    queue: deque[str] = deque()

    def visit(module: str, chain: list[str]) -> None:
        for name in [*_ancestors(module), module]:
            if name not in chains:
                chains[name] = [*chain, name] if name == module else [*chain, f"{name} (package)"]
                queue.append(name)

    for start in sorted(starts):
        visit(start, [])
    while queue:
        module = queue.popleft()
        for imported in sorted(graph[module]):
            visit(imported, chains[module])
    return chains


def closure(starts: set[str] | frozenset[str]) -> set[str]:
    """The dexflow modules that importing ``starts`` runs (``starts`` included)."""
    return set(import_chains(starts))


def test_graph_sees_imports():
    """The graph is no empty one that would pass everything: known imports are found."""
    graph = import_graph()
    assert set(STAGE_MODULES) <= set(graph), "a stage module is missing from dexflow/"
    assert "dexflow.hands.robot" in graph["dexflow.refine"]  # a top-level `from ... import`
    assert "dexflow.measures" in graph["dexflow.retarget"]  # a function-local one
    assert "dexflow.objects.sdf" in graph["dexflow.measures"]  # a TYPE_CHECKING one
    assert "dexflow.report" in graph["dexflow.cli"]  # `from dexflow import report`: a submodule
    assert "dexflow.errors" in closure({"dexflow.refine"})  # transitively, via dexflow.hands...
    assert "dexflow.hands" in closure({"dexflow.hands.robot"})  # its package runs too


def test_stage_modules_do_not_import_each_other():
    graph = import_graph()
    found = [
        f"{module} imports {imported}"
        for module in STAGE_MODULES
        for imported in sorted(graph[module] & set(STAGE_MODULES))
    ]
    assert not found, "stage modules must not import each other:\n" + "\n".join(found)


def _stages_reached(start: str) -> list[str]:
    chains = import_chains({start})
    return [" -> ".join(chains[stage]) for stage in STAGE_MODULES if stage in chains]


def test_config_imports_no_stage():
    found = _stages_reached("dexflow.config")
    assert not found, "dexflow.config must not import a stage module:\n" + "\n".join(found)


def test_params_imports_no_stage():
    found = _stages_reached("dexflow.params")
    assert not found, "dexflow.params must not import a stage module:\n" + "\n".join(found)
