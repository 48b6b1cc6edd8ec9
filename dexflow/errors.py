"""Typed exceptions raised at dexflow's boundaries (files, configs, hands)."""

from __future__ import annotations

from pathlib import Path

__all__ = [
    "ArtifactError",
    "ConfigError",
    "DexflowError",
    "HandConfigError",
    "MeshError",
    "SequenceFormatError",
]


class DexflowError(Exception):
    """Base class of every error dexflow raises on purpose."""


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
