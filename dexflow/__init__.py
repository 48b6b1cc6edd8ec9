"""dexflow: human hand-object interaction retargeted to robot hands (the DexFlow method)."""

from dexflow.errors import (
    ConfigError,
    DexflowError,
    HandConfigError,
    MeshError,
    SequenceFormatError,
)

__version__ = "0.1.0"

__all__ = [
    "ConfigError",
    "DexflowError",
    "HandConfigError",
    "MeshError",
    "SequenceFormatError",
    "__version__",
]
