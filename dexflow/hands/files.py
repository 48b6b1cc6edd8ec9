"""Where a hand's model file is, and every file reading it reads.

A hand yaml names one model file (``model``: a path, or ``pkg://<package>/<path>`` inside an
installed package), but a URDF also reads its meshes and an MJCF its ``<include>`` files, meshes,
textures, height fields and skins. :func:`model_files` lists them all, so that the pipeline can
copy them into a directory DVC tracks (stage ``hand``, :mod:`dexflow.stages.hand`) and no stage
reads a file DVC does not see.

A hand model is data someone else wrote, so every file it names must stay inside the folder it
may read (:func:`model_root`): a URDF mesh ``/etc/hostname`` or ``../../secret.stl``, or a
symbolic link inside the model's folder pointing out of it, would otherwise be read by the
loaders and copied into ``data/hand``. Listing (:func:`model_files`) and loading
(:func:`check_model_paths`, called by :mod:`dexflow.hands.model`) refuse such a name with a
one-line :class:`~dexflow.errors.HandConfigError` naming the model, the element and the folder.

This module needs only the standard library: the ``hand`` stage runs it on every ``dvc repro``.
"""

from __future__ import annotations

import dataclasses
import hashlib
import importlib.util
import json
import os
import shutil
import xml.etree.ElementTree as ET
from pathlib import Path
from typing import TYPE_CHECKING

from dexflow.errors import HandConfigError

if TYPE_CHECKING:
    from dexflow.hands.spec import HandSpec

__all__ = [
    "RECORD",
    "check_inside",
    "check_model_paths",
    "copy_model",
    "model_files",
    "model_root",
    "resolve_model_path",
    "staged_model_path",
    "staged_spec",
    "urdf_mesh_path",
]

# What stage ``hand`` writes beside the copied files: the model's path in the copy, what the
# hand yaml said (``model``) and every file's sha256.
RECORD = "hand.json"
_FILES_DIR = "model"

# MJCF elements naming files, with their attributes and the compiler directory they start in
# (MuJoCo's ``compiler`` ``meshdir`` / ``texturedir``, both defaulting to ``assetdir``).
_MJCF_FILE_ATTRS = {
    "mesh": (("file",), "meshdir"),
    "skin": (("file",), "meshdir"),
    "hfield": (("file",), "texturedir"),
    "texture": (
        ("file", "fileright", "fileleft", "fileup", "filedown", "filefront", "fileback"),
        "texturedir",
    ),
}


def _package_dir(package: str, model: str) -> Path:
    """The folder of the installed Python package ``package`` (``model`` names it, for the
    message); found without importing it, so no code of the package runs."""
    try:
        spec = importlib.util.find_spec(package) if package.isidentifier() else None
    except (ImportError, ValueError):
        spec = None
    if spec is None or not spec.submodule_search_locations:
        raise HandConfigError(f"hand model '{model}': Python package '{package}' is not installed")
    return Path(next(iter(spec.submodule_search_locations))).resolve()


def resolve_model_path(model: str, base_dir: str | Path | None = None) -> Path:
    """Find a model file: ``pkg://<package>/<path>``, an absolute path, or a relative one.

    Relative paths are tried against ``base_dir`` (the hand yaml's directory), then the
    working directory. A ``pkg://`` path must stay inside its package (``pkg://dexflow/../..``
    is refused).
    """
    if not model:
        raise HandConfigError("hand model: empty path; expected a URDF or MJCF file")
    if model.startswith("pkg://"):
        package, _, rel = model[len("pkg://") :].partition("/")
        package_dir = _package_dir(package, model)
        path = check_inside(package_dir / rel, package_dir, model, "the model path")
    else:
        path = Path(model)
        if not path.is_absolute():
            candidates = [Path(base_dir) / path] if base_dir is not None else []
            candidates.append(Path.cwd() / path)
            path = next((c for c in candidates if c.is_file()), candidates[0])
    if not path.is_file():
        raise HandConfigError(f"hand model '{model}': no file at {path}")
    return path.resolve()


def urdf_mesh_path(filename: str, urdf_dir: Path) -> Path:
    """A URDF mesh ``filename`` as a path: ``package://`` (tried beside the URDF, then as an
    installed Python package), ``file://``, absolute, or relative to the URDF's directory."""
    path, package_dir = _urdf_mesh(filename, urdf_dir)
    if package_dir is not None and not path.is_file():
        raise HandConfigError(f"hand model '{filename}': no file at {path}")
    return path


def _urdf_mesh(filename: str, urdf_dir: Path) -> tuple[Path, Path | None]:
    """:func:`urdf_mesh_path` (not checked to exist), and the package's folder where a
    ``package://`` name resolved to an installed Python package (its files may stay only
    there), else None."""
    if filename.startswith("package://"):
        rel = filename[len("package://") :]
        inside = rel.partition("/")[2]  # a ROS package: <package>/urdf/ beside <package>/meshes/
        for candidate in (urdf_dir / inside, urdf_dir / rel, urdf_dir.parent / inside,
                          urdf_dir.parent / rel):  # fmt: skip
            if candidate.is_file():
                return candidate, None
        package, _, inside = rel.partition("/")
        package_dir = _package_dir(package, filename)
        return (package_dir / inside).resolve(), package_dir
    if filename.startswith("file://"):
        filename = filename[len("file://") :]
    path = Path(filename)
    return (path if path.is_absolute() else urdf_dir / path), None


def model_root(path: str | Path) -> Path:
    """The folder every file the model at ``path`` names must resolve into (symlinks followed).

    - The model's own folder, for a model of the user's (a relative or absolute path): a model
      is shipped as its folder, and nothing outside it is part of it. (So a URDF's
      ``package://`` mesh found in the URDF's parent folder, the last place tried beside it,
      is refused for such a model.)
    - The folder of the installed Python package the model lies in (``pkg://`` models, or a
      path into one): packages lay out their models' parts in sibling folders (the ShadowHand
      of ``gymnasium_robotics`` reads ``../stls/hand``), and a package is installed as a whole.
      The package is the outermost folder holding an ``__init__.py`` that the interpreter
      finds under the folder's name (nothing is imported to tell).
    - The ROS package folder (holding ``package.xml``) whose sub-folder holds the model, for
      the ROS layout ``<package>/urdf/hand.urdf`` naming ``package://<package>/meshes/...``.
    - The folder of the copy stage ``hand`` wrote (``data/hand/model``), for that copy: its
      tree is the original's, and every file in it was checked when it was copied.
    """
    path = Path(path).resolve()
    return _staged_root(path) or _package_root(path) or _ros_package_root(path) or path.parent


def _ros_package_root(path: Path) -> Path | None:
    """The ROS package folder (it holds ``package.xml``) whose sub-folder (``urdf/``) holds the
    model: its meshes lie in a sibling folder (``meshes/``), named ``package://<package>/...``."""
    folder = path.parent.parent
    return folder if (folder / "package.xml").is_file() else None


def _staged_root(path: Path) -> Path | None:
    """``<out>/model`` if ``path`` is the model a stage ``hand`` record ``<out>/hand.json``
    names, else None."""
    for folder in path.parents:
        if folder.name == _FILES_DIR and (folder.parent / RECORD).is_file():
            try:
                record = json.loads((folder.parent / RECORD).read_text(encoding="utf-8"))
                named = (folder.parent / str(record["model"])).resolve()
            except (OSError, ValueError, KeyError, TypeError):
                return None
            return folder if named == path else None
    return None


def _package_root(path: Path) -> Path | None:
    """The folder of the installed top-level Python package holding ``path``, if any."""
    for folder in reversed(path.parents):  # outermost first
        if not (folder.name.isidentifier() and (folder / "__init__.py").is_file()):
            continue
        try:
            spec = importlib.util.find_spec(folder.name)
        except (ImportError, ValueError):
            continue
        locations = (spec.submodule_search_locations or []) if spec else []
        if any(Path(location).resolve() == folder for location in locations):
            return folder
    return None


def check_inside(file: Path, root: Path, model: str | Path, field: str) -> Path:
    """``file`` resolved (symlinks followed), if it lies inside ``root``.

    Args:
        file: A path the model names, as its loader would open it.
        root: The folder it must stay in (:func:`model_root`, or a package's folder).
        model: The model file, for the message.
        field: The element and attribute naming ``file``, for the message.

    Raises:
        HandConfigError: ``file`` resolves outside ``root``.
    """
    resolved = file.resolve()
    if not resolved.is_relative_to(root):
        raise HandConfigError(
            f"{model}: {field} resolves to {resolved}, outside {root}; a hand model may only "
            f"read files inside that folder"
        )
    return resolved


def _parse(path: Path, what: str) -> ET.Element:
    try:
        return ET.parse(path).getroot()
    except (OSError, ET.ParseError) as exc:
        raise HandConfigError(f"{path}: cannot read {what}: {exc}") from exc


def _must_exist(path: Path, model: Path, what: str) -> Path:
    if not path.is_file():
        raise HandConfigError(f"{model}: {what} not found at {path}")
    return path.resolve()


def _urdf_files(path: Path, must_exist: bool = True) -> list[Path]:
    """The URDF and the files its ``<mesh filename>`` name, each checked to lie in its folder
    (:func:`model_root`, or the package's folder for a ``package://`` name resolved as an
    installed package). With ``must_exist`` False, names that resolve to no file are left out
    rather than refused (the loader reports a missing collision mesh; nobody reads a missing
    visual one)."""
    root = model_root(path)
    files = [path]
    for mesh in _parse(path, "URDF").iter("mesh"):
        filename = mesh.get("filename")
        if not filename:
            continue
        where = f"<mesh filename='{filename}'>"
        try:
            file, package_dir = _urdf_mesh(filename, path.parent)
        except HandConfigError:
            if must_exist:
                raise
            continue
        file = check_inside(file, package_dir or root, path, where)
        if must_exist or file.is_file():
            files.append(_must_exist(file, path, where))
    return files


def _mjcf_files(path: Path) -> list[Path]:
    """The MJCF, its includes (recursively) and the asset files they name.

    As MuJoCo resolves them: include files relative to the main file's directory; asset files
    relative to the compiler's ``meshdir`` / ``texturedir`` (themselves relative to the main
    file's directory, defaulting to ``assetdir``), or absolute; ``strippath`` drops their
    directories. Every include, directory and file must resolve inside :func:`model_root`; an
    include is checked before it is read.
    """
    model_dir, allowed = path.parent, model_root(path)
    files: list[Path] = []
    elements: list[ET.Element] = []
    pending = [path]
    while pending:  # includes first: a compiler element may sit in an included file
        current = pending.pop()
        if current in files:
            raise HandConfigError(f"{path}: {current.name} is included twice (or includes itself)")
        files.append(current)
        root = _parse(current, "MJCF")
        elements += list(root.iter())
        for include in root.iter("include"):
            name = include.get("file") or ""
            where = f"<include file='{name}'> (in {current.name})"
            check_inside(model_dir / name, allowed, path, where)
            pending.append(_must_exist(model_dir / name, path, where))
    compiler: dict[str, str] = {}
    for element in elements:
        if element.tag == "compiler":
            compiler.update(element.attrib)
    for key in ("assetdir", "meshdir", "texturedir"):
        if key in compiler:
            where = f"<compiler {key}='{compiler[key]}'>"
            check_inside(model_dir / compiler[key], allowed, path, where)
    asset_dir = compiler.get("assetdir", "")
    strip = compiler.get("strippath", "false").lower() == "true"
    for element in elements:
        if element.tag not in _MJCF_FILE_ATTRS:
            continue
        attrs, dir_key = _MJCF_FILE_ATTRS[element.tag]
        for attr in attrs:
            name = element.get(attr)
            if not name:
                continue
            file = Path(Path(name).name if strip else name)
            if not file.is_absolute():
                file = model_dir / compiler.get(dir_key, asset_dir) / file
            where = f"<{element.tag} {attr}='{name}'>"
            files.append(_must_exist(check_inside(file, allowed, path, where), path, where))
    return files


def model_files(path: str | Path) -> list[Path]:
    """Every file loading the model at ``path`` reads, the model first, each once.

    Raises:
        HandConfigError: the model or a file it names is missing or unreadable, or a name
            resolves outside the model's folder (:func:`model_root`).
    """
    path = Path(path).resolve()
    if not path.is_file():
        raise HandConfigError(f"hand model: no file at {path}")
    files = _urdf_files(path) if path.suffix.lower() == ".urdf" else _mjcf_files(path)
    return list(dict.fromkeys(files))


def check_model_paths(path: str | Path) -> None:
    """Refuse a model naming a file outside its folder, before a loader reads any.

    An MJCF is checked as :func:`model_files` lists it (MuJoCo needs all its files anyway); a
    URDF checks every ``<mesh filename>`` (visual ones too: the physics engines load them), but
    leaves the report of a missing file to the loader, as before.

    Raises:
        HandConfigError: a name resolves outside :func:`model_root`, or an MJCF file is
            missing or unreadable.
    """
    path = Path(path).resolve()
    if path.suffix.lower() == ".urdf":
        _urdf_files(path, must_exist=False)
    else:
        model_files(path)


def copy_model(model: str, base_dir: str | Path | None, out_dir: str | Path) -> dict:
    """Copy the model ``model`` names and every file it reads into ``out_dir/model/`` (their
    directory tree below the deepest directory holding them all, so relative references still
    resolve), and write ``out_dir/hand.json``.

    Returns:
        The record written: ``model`` (the copy's path relative to ``out_dir``), ``source``
        (``model`` as given) and ``files`` (path relative to ``out_dir`` -> sha256). Nothing in
        it depends on where the files were found, so the same model gives the same bytes on
        every machine.

    Raises:
        HandConfigError: the model or a file it names is missing or unreadable.
    """
    out_dir = Path(out_dir)
    files = model_files(resolve_model_path(model, base_dir))
    top = Path(os.path.commonpath([f.parent for f in files]))
    files_dir = out_dir / _FILES_DIR
    if files_dir.exists():
        shutil.rmtree(files_dir)
    digests = {}
    for file in files:
        rel = Path(_FILES_DIR) / file.relative_to(top)
        (out_dir / rel).parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(file, out_dir / rel)
        digests[rel.as_posix()] = hashlib.sha256((out_dir / rel).read_bytes()).hexdigest()
    record = {
        "source": model,
        "model": (Path(_FILES_DIR) / files[0].relative_to(top)).as_posix(),
        "files": dict(sorted(digests.items())),
    }
    (out_dir / RECORD).write_text(json.dumps(record, indent=1) + "\n", encoding="utf-8")
    return record


def staged_spec(spec: HandSpec, staged_dir: str | Path) -> HandSpec:
    """``spec`` with ``model`` the copy stage ``hand`` wrote into ``staged_dir`` (``data/hand``):
    the pipeline's stages build their hand from it, so they read only files DVC tracks.

    Raises:
        HandConfigError: ``staged_dir`` holds no copy, or the copy of another model.
    """
    return dataclasses.replace(spec, model=str(staged_model_path(staged_dir, spec.model)))


def staged_model_path(staged_dir: str | Path, model: str) -> Path:
    """The copy of ``model`` stage ``hand`` wrote into ``staged_dir``.

    Raises:
        HandConfigError: ``staged_dir`` holds no copy, or the copy of another model (the
            ``hand`` stage has not run since ``hand.model`` changed).
    """
    record_path = Path(staged_dir) / RECORD
    try:
        record = json.loads(record_path.read_text(encoding="utf-8"))
    except (OSError, ValueError) as exc:
        raise HandConfigError(
            f"{record_path}: no copy of the hand model ({exc}); run `dvc repro` (stage hand)"
        ) from exc
    if record.get("source") != model:
        raise HandConfigError(
            f"{record_path}: holds a copy of hand model '{record.get('source')}', but "
            f"hand.model is '{model}'; run `dvc repro` (stage hand)"
        )
    return (Path(staged_dir) / record["model"]).resolve()
