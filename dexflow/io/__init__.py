"""Reading and writing dexflow files: the canonical sequence format and atomic writes."""

from dexflow.io.atomic import atomic_path, save_json, save_npz
from dexflow.io.sequence import Sequence, load_sequence, save_sequence, validate_sequence

__all__ = [
    "Sequence",
    "atomic_path",
    "load_sequence",
    "save_json",
    "save_npz",
    "save_sequence",
    "validate_sequence",
]
