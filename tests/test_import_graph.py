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

# The module of each pipeline stage: dexflow/stages/<name>.py for stage <name> of dvc.yaml
# (tests/test_registry.py checks that the two lists are the same).
STAGE_MODULES = tuple(
    f"dexflow.stages.{path.stem}"
    for path in sorted((ROOT / PACKAGE / "stages").glob("*.py"))
    if path.stem != "__init__"
)

# The layers of the package, lowest first: a module imports only from its own layer and those
# below (a name is a module or a package and everything below it). `dexflow` itself (the
# package root) is the lowest.
LAYERS = (
    ("foundation", ("dexflow", "dexflow.errors", "dexflow.geometry")),
    ("models", ("dexflow.io", "dexflow.objects", "dexflow.human", "dexflow.hands")),
    ("schema and measures", ("dexflow.config", "dexflow.params", "dexflow.measures",
                             "dexflow.stats", "dexflow.plots")),
    ("pipeline plumbing", ("dexflow.pipeline",)),
    ("engines and data", ("dexflow.sim", "dexflow.data")),
    ("stages", ("dexflow.stages",)),
    ("tools", ("dexflow.tools",)),
)  # fmt: skip


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
    assert "dexflow.hands.robot" in graph["dexflow.stages.refine"]  # a top-level `from ... import`
    assert "dexflow.measures" in graph["dexflow.stages.retarget"]  # a function-local one
    assert "dexflow.objects.sdf" in graph["dexflow.measures"]  # a TYPE_CHECKING one
    # `from dexflow.stages import report`: a submodule, function-local
    assert "dexflow.stages.report" in graph["dexflow.tools.cli.reports"]
    assert "dexflow.errors" in closure(
        {"dexflow.stages.refine"}
    )  # transitively, via dexflow.hands...
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


def layer_of(module: str) -> int | None:
    """The index in :data:`LAYERS` of the most specific name ``module`` falls under."""
    found, depth = None, -1
    for i, (_, names) in enumerate(LAYERS):
        for name in names:
            under = module == name or (name != PACKAGE and module.startswith(name + "."))
            if under and name.count(".") > depth:
                found, depth = i, name.count(".")
    return found


def test_every_module_has_a_layer():
    unplaced = sorted(m for m in module_files() if layer_of(m) is None)
    assert not unplaced, f"modules in no layer of LAYERS (add them to one): {unplaced}"


def test_no_layer_imports_upward():
    found = []
    for module, imported in sorted(import_graph().items()):
        for name in sorted(imported):
            if layer_of(name) > layer_of(module):
                found.append(
                    f"{module} ({LAYERS[layer_of(module)][0]}) imports {name} "
                    f"({LAYERS[layer_of(name)][0]})"
                )
    assert not found, "imports upward across the layers:\n" + "\n".join(found)


def test_layer_check_sees_an_upward_import(tmp_path):
    """The check is no empty one: a pipeline module importing a stage would be flagged."""
    bad = tmp_path / "bad.py"
    bad.write_text("def f():\n    from dexflow.stages.refine import STAGE\n    return STAGE\n")
    imported = imports_of_file(bad, "dexflow.pipeline.bad")
    assert "dexflow.stages.refine" in imported
    assert layer_of("dexflow.stages.refine") > layer_of("dexflow.pipeline.bad")
    assert layer_of("dexflow.tools.cli") == len(LAYERS) - 1
    assert layer_of("dexflow") == 0 and layer_of("dexflow.hands.robot") == 1


MAX_LINES = 500  # a module longer than this says why in its docstring (``**One file**``)


def test_long_modules_say_why_they_are_one_file():
    found = []
    for module, path in sorted(module_files().items()):
        text = path.read_text(encoding="utf-8")
        if len(text.splitlines()) > MAX_LINES:
            doc = ast.get_docstring(ast.parse(text)) or ""
            if "**One file**" not in doc:
                found.append(f"{module}: {len(text.splitlines())} lines")
    assert not found, (
        f"modules over {MAX_LINES} lines without a **One file** reason in their docstring "
        "(split them by job, or say why not):\n" + "\n".join(found)
    )
