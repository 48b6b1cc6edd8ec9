"""The ``deps`` of ``dvc.yaml`` are truthful: a stage lists every file of dexflow its script runs.

For each stage the script is read from ``cmd`` (``python stages/<name>.py ...``); the dexflow
modules it runs are the closure of its imports in the static import graph of
``tests/test_import_graph.py`` (function-local and ``TYPE_CHECKING`` imports included; importing a
module runs its packages' ``__init__`` too). Each of their files must be a dep, or lie in a
directory that is one.
"""

from __future__ import annotations

import re
from functools import cache
from pathlib import Path
from typing import Any

import pytest
import yaml

from tests.test_import_graph import ROOT, closure, imports_of_file, module_files

# Modules a stage runs but need not list, each with the reason. Only the module's own file is
# exempt: what it imports is still in the closure, and must be listed.
NOT_DEPS = {
    # The package root: docstring, ``__version__`` and a re-export of dexflow.errors (which the
    # stages list). A version bump must not rerun the pipeline.
    "dexflow": "package root",
}

SCRIPT = re.compile(r"\bpython3?\s+(stages/[\w/]+\.py)\b")


def _substitute(value: Any, key: str | None, item: Any) -> Any:
    """``value`` with ``${key}`` and ``${item}`` replaced (in dict keys too); others left as is."""
    if isinstance(value, str):
        if key is not None:
            value = value.replace("${key}", key)
        if item is not None and not isinstance(item, (dict, list)):
            value = value.replace("${item}", str(item))
        return value
    if isinstance(value, list):
        return [_substitute(v, key, item) for v in value]
    if isinstance(value, dict):
        return {_substitute(k, key, item): _substitute(v, key, item) for k, v in value.items()}
    return value


@cache
def _params_with_track() -> dict:
    import tempfile

    from dexflow.config import compose_params

    with tempfile.TemporaryDirectory() as tmp:
        path = compose_params(["track=on"], Path(tmp) / "params.yaml")
        return yaml.safe_load(path.read_text())


def _resolved(foreach):
    """A ``foreach``, a ``${a.b}`` template looked up in :func:`_params_with_track`."""
    if isinstance(foreach, str) and foreach.startswith("${"):
        value = _params_with_track()
        for key in foreach.removeprefix("${").removesuffix("}").split("."):
            value = value[key]
        return value
    return foreach


@cache
def stages() -> dict[str, dict]:
    """Every stage of dvc.yaml, ``foreach`` ones expanded (``name@key``, as DVC names them).

    A ``foreach`` over a ``${...}`` template is resolved as DVC resolves it, from params.yaml
    as ``dexflow params track=on`` composes it (every stage present: the demo's, track's).
    """
    dvc = yaml.safe_load((ROOT / "dvc.yaml").read_text(encoding="utf-8"))
    expanded = {}
    for name, stage in dvc["stages"].items():
        if "foreach" not in stage:
            expanded[name] = stage
            continue
        foreach, do = _resolved(stage["foreach"]), stage["do"]
        if isinstance(foreach, dict):
            for key, item in foreach.items():
                expanded[f"{name}@{key}"] = _substitute(do, str(key), item)
        elif isinstance(foreach, list):
            for item in foreach:
                expanded[f"{name}@{item}"] = _substitute(do, None, item)
        else:
            assert isinstance(foreach, str) and "${" in foreach, f"{name}: foreach {foreach!r}"
            expanded[f"{name}@*"] = do
    return expanded


def _paths(entries: list | None) -> list[str]:
    """The paths of a deps/outs/metrics/plots list (entries are paths or ``{path: options}``)."""
    paths = []
    for entry in entries or []:
        paths.extend([entry] if isinstance(entry, str) else entry)
    return [p.rstrip("/") for p in paths]


def _deps(stage: dict) -> list[str]:
    """The deps that are paths (``${...}`` templates, e.g. ``${data.root}``, left out)."""
    return [d for d in _paths(stage.get("deps")) if "${" not in d]


def _covered(path: str, deps: list[str]) -> bool:
    return any(path == d or path.startswith(d + "/") for d in deps)


def _script(name: str, stage: dict) -> str:
    cmd = stage["cmd"] if isinstance(stage["cmd"], str) else " && ".join(stage["cmd"])
    found = SCRIPT.search(cmd)
    assert found, f"stage {name}: no `python stages/<script>.py` in cmd {cmd!r}"
    return found.group(1)


@cache
def _outputs() -> frozenset[str]:
    keys = ("outs", "metrics", "plots")
    return frozenset(p for s in stages().values() for k in keys for p in _paths(s.get(k)))


def test_dvc_yaml_is_read():
    """The expansion finds the stages (so the tests below cannot pass on an empty list)."""
    names = set(stages())
    assert {"scale_align", "contact", "refine", "metrics", "report", "demo@demo"} <= names
    assert {"track@refine", "simulate@track", "replay@track"} <= names
    assert {"retarget@dexflow", "retarget@position"} <= names
    assert {"simulate@baseline", "simulate@retarget", "simulate@refine"} <= names
    assert "data/refine" in _paths(stages()["simulate@refine"]["deps"])  # ${item} substituted
    assert "data/simulate/refine" in _paths(stages()["simulate@refine"]["outs"])  # ${key}
    assert _script("refine", stages()["refine"]) == "stages/refine.py"


@pytest.mark.parametrize("name", sorted(stages()))
def test_deps_cover_the_code_the_stage_runs(name):
    stage = stages()[name]
    script = _script(name, stage)
    deps = _deps(stage)
    files = module_files()
    modules = closure(imports_of_file(ROOT / script))
    assert modules, f"stage {name}: {script} imports no dexflow module"
    needed = {script: "the script"} | {
        files[m].relative_to(ROOT).as_posix(): m for m in sorted(modules) if m not in NOT_DEPS
    }
    missing = [f"{path} ({why})" for path, why in needed.items() if not _covered(path, deps)]
    assert not missing, (
        f"stage {name} runs files that are not among its deps (`python -m tests.test_dvc_deps` "
        "rewrites the code deps of dvc.yaml from the imports):\n" + "\n".join(missing)
    )


@pytest.mark.parametrize("name", sorted(stages()))
def test_hand_configs_are_params_not_deps(name):
    """params.yaml holds the composed hand (its ``hand`` section): conf/hand is no dep."""
    listed = [d for d in _deps(stages()[name]) if _covered(d, ["conf/hand"])]
    assert not listed, f"stage {name} lists {listed}: use the `hand` params section instead"


@pytest.mark.parametrize("name", sorted(stages()))
def test_deps_exist(name):
    """Every dep is in the repository, but for those another stage writes (its outs)."""
    outputs = _outputs()
    missing = [
        d
        for d in _deps(stages()[name])
        if not (_covered(d, list(outputs)) or any(_covered(o, [d]) for o in outputs))
        and not (ROOT / d).exists()
    ]
    assert not missing, f"stage {name}: deps that do not exist: {missing}"


def code_deps(script: str) -> list[str]:
    """The dexflow files ``script`` runs, a package folder standing for all of its modules
    when it runs every one: what :func:`write_code_deps` lists."""
    files = module_files()
    paths = sorted(
        files[m].relative_to(ROOT).as_posix()
        for m in closure(imports_of_file(ROOT / script))
        if m not in NOT_DEPS
    )
    chosen = set(paths)
    for folder in sorted({p.rpartition("/")[0] for p in paths}, key=lambda f: f.count("/")):
        if folder == PACKAGE_DIR or any(folder.startswith(c + "/") for c in chosen):
            continue
        every = {q.relative_to(ROOT).as_posix() for q in (ROOT / folder).rglob("*.py")}
        if every <= set(paths):
            chosen = {p for p in chosen if not p.startswith(folder + "/")} | {folder}
    return sorted(chosen, key=lambda p: (p.count("/"), p))


PACKAGE_DIR = "dexflow"


def write_code_deps() -> None:
    """Rewrite each stage's ``dexflow/...`` deps in dvc.yaml from its imports (comments and
    other deps kept; a ``dexflow/`` dep holding no module, such as hand assets, is kept)."""
    lines = (ROOT / "dvc.yaml").read_text(encoding="utf-8").split("\n")
    out, i, script = [], 0, None
    while i < len(lines):
        found = SCRIPT.search(lines[i]) if "cmd:" in lines[i] else None
        script = found.group(1) if found else script
        if lines[i].strip() != "deps:" or script is None:
            out.append(lines[i])
            i += 1
            continue
        out.append(lines[i])
        i += 1
        entries = []
        while i < len(lines) and lines[i].lstrip().startswith("- "):
            entries.append(lines[i])
            i += 1
        indent = entries[0][: len(entries[0]) - len(entries[0].lstrip())]

        def path(entry: str) -> str:
            return entry.strip()[2:].split("#")[0].strip()

        def is_code(entry: str) -> bool:
            dep = path(entry)
            return dep.startswith(PACKAGE_DIR + "/") and (
                dep.endswith(".py") or any((ROOT / dep).rglob("*.py"))
            )

        first = [e for e in entries if path(e) == script]
        rest = [e for e in entries if path(e) != script and not is_code(e)]
        out += first + [f"{indent}- {dep}" for dep in code_deps(script)] + rest
        script = None
    (ROOT / "dvc.yaml").write_text("\n".join(out), encoding="utf-8")


if __name__ == "__main__":
    write_code_deps()
