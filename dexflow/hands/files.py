"""Where a hand's model file is, and every file reading it reads.

A hand yaml names one model file (``model``: a path, or ``pkg://<package>/<path>`` inside an
installed package), but a URDF also reads its meshes and an MJCF its ``<include>`` files, meshes,
textures, height fields and skins. :func:`model_files` lists them all, so that the pipeline can
copy them into a directory DVC tracks (stage ``hand``, :mod:`dexflow.hand_stage`) and no stage
reads a file DVC does not see.

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
    "copy_model",
    "model_files",
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


def resolve_model_path(model: str, base_dir: str | Path | None = None) -> Path:
    """Find a model file: ``pkg://<package>/<path>``, an absolute path, or a relative one.

    Relative paths are tried against ``base_dir`` (the hand yaml's directory), then the
    working directory.
    """
    if not model:
        raise HandConfigError("hand model: empty path; expected a URDF or MJCF file")
    if model.startswith("pkg://"):
        package, _, rel = model[len("pkg://") :].partition("/")
        spec = importlib.util.find_spec(package)
        if spec is None or not spec.submodule_search_locations:
            raise HandConfigError(
                f"hand model '{model}': Python package '{package}' is not installed"
            )
        path = Path(next(iter(spec.submodule_search_locations))) / rel
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
    if filename.startswith("package://"):
        rel = filename[len("package://") :]
        for candidate in (urdf_dir / rel.partition("/")[2], urdf_dir / rel, urdf_dir.parent / rel):
            if candidate.is_file():
                return candidate
        return resolve_model_path("pkg://" + rel)
    if filename.startswith("file://"):
        filename = filename[len("file://") :]
    path = Path(filename)
    return path if path.is_absolute() else urdf_dir / path


def _parse(path: Path, what: str) -> ET.Element:
    try:
        return ET.parse(path).getroot()
    except (OSError, ET.ParseError) as exc:
        raise HandConfigError(f"{path}: cannot read {what}: {exc}") from exc


def _must_exist(path: Path, model: Path, what: str) -> Path:
    if not path.is_file():
        raise HandConfigError(f"{model}: {what} not found at {path}")
    return path.resolve()


def _urdf_files(path: Path) -> list[Path]:
    root = _parse(path, "URDF")
    files = [path]
    for mesh in root.iter("mesh"):
        filename = mesh.get("filename")
        if filename:
            where = f"<mesh filename='{filename}'>"
            files.append(_must_exist(urdf_mesh_path(filename, path.parent), path, where))
    return files


def _mjcf_files(path: Path) -> list[Path]:
    """The MJCF, its includes (recursively) and the asset files they name.

    As MuJoCo resolves them: include files relative to the main file's directory; asset files
    relative to the compiler's ``meshdir`` / ``texturedir`` (themselves relative to the main
    file's directory, defaulting to ``assetdir``), or absolute; ``strippath`` drops their
    directories.
    """
    model_dir = path.parent
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
            pending.append(_must_exist(model_dir / name, path, where))
    compiler: dict[str, str] = {}
    for element in elements:
        if element.tag == "compiler":
            compiler.update(element.attrib)
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
            files.append(_must_exist(file, path, f"<{element.tag} {attr}='{name}'>"))
    return files


def model_files(path: str | Path) -> list[Path]:
    """Every file loading the model at ``path`` reads, the model first, each once.

    Raises:
        HandConfigError: the model or a file it names is missing or unreadable.
    """
    path = Path(path).resolve()
    if not path.is_file():
        raise HandConfigError(f"hand model: no file at {path}")
    files = _urdf_files(path) if path.suffix.lower() == ".urdf" else _mjcf_files(path)
    return list(dict.fromkeys(files))


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
