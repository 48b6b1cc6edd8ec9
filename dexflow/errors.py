"""Typed exceptions raised at dexflow's boundaries (files, configs, hands)."""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path

__all__ = [
    "ArtifactError",
    "ConfigError",
    "DexflowError",
    "HandConfigError",
    "IncompleteStageError",
    "MeshError",
    "SequenceFormatError",
    "UnsafePickleError",
]


class DexflowError(Exception):
    """Base class of every error dexflow raises on purpose: something the user gave (data,
    config, a hand) is wrong, so running again cannot help. A stage drops a sequence that raises
    one and goes on; any other exception fails the stage (see :class:`IncompleteStageError`)."""


class ConfigError(DexflowError, ValueError):
    """A configuration value (params.yaml or conf/) is missing, unknown or out of range."""


class HandConfigError(ConfigError):
    """A hand configuration names links or joints its model does not have."""


class ArtifactError(DexflowError, ValueError):
    """A stage output is missing, incomplete or does not fit its reader (another hand's joints,
    another frame count); the message names the file and what was expected."""


class MeshError(DexflowError, ValueError):
    """An object mesh is missing, unreadable or degenerate."""


class SequenceFormatError(DexflowError, ValueError):
    """A sequence file does not follow the canonical format.

    The message always says where (file, field, frame), what was expected and what was found.
    """

    def __init__(
        self,
        path: str | Path | None,
        field: str,
        expected: str,
        found: str,
        frame: int | None = None,
    ) -> None:
        self.path = None if path is None else Path(path)
        self.field = field
        self.frame = frame
        self.expected = expected
        self.found = found
        where = f"{self.path or '<in memory>'}: field '{field}'"
        if frame is not None:
            where += f", frame {frame}"
        super().__init__(f"{where}: expected {expected}, found {found}")


class UnsafePickleError(SequenceFormatError):
    """A pickle in a data file names a global that plain data never needs (``os.system``,
    ``builtins.exec``): unpickling it could run code, so it is refused unread.

    Attributes:
        global_name: The refused global, ``module.name``.
    """

    def __init__(self, path: str | Path | None, global_name: str, field: str = "<pickle>") -> None:
        self.global_name = global_name
        super().__init__(
            path,
            field,
            "plain data only (arrays, numbers, strings, lists, dicts; a data file runs no code)",
            f"the global '{global_name}', refused",
        )


class IncompleteStageError(RuntimeError):
    """Items of a stage failed for a reason other than their input (I/O, memory, a killed
    worker, an unexpected error). The stage must fail: its finished items are kept and a rerun
    retries the others.

    Attributes:
        stage: The stage's label.
        failed: Per item name its error.
    """

    def __init__(self, stage: str, failed: Mapping[str, str]) -> None:
        self.stage = stage
        self.failed = dict(failed)
        lines = "".join(f"\n  {name}: {error}" for name, error in sorted(self.failed.items()))
        super().__init__(
            f"{stage}: {len(self.failed)} item(s) failed for a reason other than their input; "
            f"the finished ones are kept: run `dvc repro` again to retry these (if one fails "
            f"the same way again, remove it from the data or report the error):{lines}"
        )
